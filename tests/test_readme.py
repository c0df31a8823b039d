"""The site's Layout page (docs/explanation/layout.md) names every module of the package (but each effect and
measure) and every top-level folder of the repository; the README stays short and its Quick start runs in CI."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def layout() -> str:
    text = (ROOT / "docs/explanation/layout.md").read_text(encoding="utf-8")
    return re.search(r"```\n(.*?)```", text, re.S).group(1)


def test_layout_names_every_module_and_folder():
    shown = layout()
    named = set(re.findall(r"[\w]+\.py", shown))
    modules = {p.name for p in (ROOT / "wiredsl").rglob("*.py") if p.name not in ("__init__.py", "__main__.py")
               and p.parent.name not in ("effects", "measures")}  # "one module per source / measure"
    assert modules <= named, f"modules missing from docs/explanation/layout.md: {sorted(modules - named)}"
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout (an sdist): its folders are not the repository's")
    tracked = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    folders = {line.split("/")[0] for line in tracked.splitlines() if "/" in line and not line.startswith(".")}
    listed = set(re.findall(r"^([\w.-]+)/", shown, re.M))
    assert folders <= listed, f"folders missing from docs/explanation/layout.md: {sorted(folders - listed)}"


def test_the_readme_stays_short_and_points_at_the_site():
    """What wiredsl is, a figure, the Quick start and links: the rest lives in docs/ (the site)."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 250
    assert "## Quick start" in text and "![" in text
    for link in re.findall(r"\]\(((?:docs/)[^)#]+)", text):
        assert (ROOT / link).is_file(), link
    assert "## Layout" not in text  # the layout is docs/explanation/layout.md
