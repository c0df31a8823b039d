"""docs/tutorials/plugin.md runs as written: its code blocks (each opening with `# file: NAME`) make a package,
installed here as pip leaves one (its module on sys.path, a .dist-info with the entry points of its
pyproject.toml), and the page's scene is checked and its study run."""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path

import pytest
from click.testing import CliRunner
from helpers import dist_info, entry_points_text, plugins_on_path

from wiredsl.cli import main

ROOT = Path(__file__).resolve().parent.parent
PAGE = ROOT / "docs" / "tutorials" / "plugin.md"


def blocks() -> dict[str, str]:
    found = re.findall(r"```\w+\n# file: (\S+)\n(.*?)```", PAGE.read_text(encoding="utf-8"), re.S)
    return {name: body for name, body in found}


@pytest.fixture
def tutorial(tmp_path, monkeypatch):
    files = blocks()
    site = tmp_path / "site"
    for name, body in files.items():
        if name.endswith(".py"):
            (site / name).parent.mkdir(parents=True, exist_ok=True)
            (site / name).write_text(body)
    (site / "wd_tutorial" / "__init__.py").write_text("")
    project = tomllib.loads(files["pyproject.toml"])["project"]
    dist_info(site, project["name"], project["version"], entry_points_text(project["entry-points"]))
    scene = tmp_path / "tutorial.wd"
    scene.write_text(files["tutorial.wd"].replace('"scenes/lab.wd"', f'"{ROOT / "scenes" / "lab.wd"}"'))
    with plugins_on_path(monkeypatch, site, modules=("wd_tutorial",)):
        yield scene


def test_the_tutorial_has_a_package_an_effect_a_measure_and_a_scene():
    assert set(blocks()) == {"pyproject.toml", "wd_tutorial/effects.py", "wd_tutorial/measures.py", "tutorial.wd"}


def test_the_tutorial_package_loads_checks_and_runs_its_study(tutorial, tmp_path):
    r = CliRunner().invoke(main, ["plugins"])
    assert r.exit_code == 0 and "border_jitter" in r.output and "moved_corners" in r.output, r.output
    r = CliRunner().invoke(main, ["check", str(tutorial)])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["study", str(tutorial), "border", "-o", str(tmp_path / "st"), "--executor",
                                  "inprocess", "--no-plots"])
    assert r.exit_code == 0, r.output
    rows = json.loads((tmp_path / "st" / "table.json").read_text())["rows"]
    moved = {row["values"]["border_jitter.sigma"]: row["mean"] for row in rows if row["statistic"] == "moved"}
    assert moved[0.0] == 0.0 and 0.05 < moved[4.0] < 1.0, moved  # no noise moves nothing; 4 px at the border some
    manifest = json.loads((tmp_path / "st" / "manifest.json").read_text())
    assert {p["package"] for p in manifest["plugins"]} == {"wd-tutorial"}
    out = tmp_path / "plug.json"
    assert CliRunner().invoke(main, ["compile", str(tutorial), "-o", str(out)]).exit_code == 0
    r = CliRunner().invoke(main, ["validate", str(out)])
    assert r.exit_code == 0, r.output
