from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(autouse=True)
def _at_root(monkeypatch):
    """Run every test from the checkout's root, so that reported paths are stable."""
    monkeypatch.chdir(ROOT)


def pytest_configure(config):
    """Compile the Monte-Carlo kernel once, before any test worker starts, so that the workers share the
    compiled code through numba's cache instead of each compiling it."""
    import importlib.util

    if hasattr(config, "workerinput") or importlib.util.find_spec("numba") is None:
        return
    from wiredsl.engine import kernel

    kernel.warm()
