from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(autouse=True)
def _at_root(monkeypatch):
    """Run every test from the checkout's root, so that reported paths are stable."""
    monkeypatch.chdir(ROOT)
