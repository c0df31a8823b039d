"""docs/tutorials/plugin.md runs as written: its code blocks (each opening with `# file: NAME`) make a package,
installed here as pip leaves one (its module on sys.path, a .dist-info with the entry points of its
pyproject.toml), and the page's scene is checked and its study run; its detector is the one `wiredsl init
--plugin` writes, and its commands print what the page shows."""

from __future__ import annotations

import json
import re
import shlex
import tomllib
from pathlib import Path

import pytest
from click.testing import CliRunner
from helpers import dist_info, entry_points_text, plugins_on_path

from wiredsl import init
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
    assert set(blocks()) == {"pyproject.toml", "wd_tutorial/effects.py", "wd_tutorial/measures.py",
                             "wd_tutorial/detect.py", "tutorial.wd"}


def test_the_tutorials_detector_is_the_one_wiredsl_init_writes():
    assert blocks()["wd_tutorial/detect.py"] == init.fill(init.PLUGIN_DETECTOR, {"detector": "sobel_edges"})


def section(title: str) -> str:
    return PAGE.read_text(encoding="utf-8").split(f"## {title}\n", 1)[1].split("\n## ", 1)[0]


def test_the_detector_sections_commands_print_what_the_page_shows(tutorial, tmp_path, monkeypatch):
    """`wiredsl render` then `wiredsl verify --detector sobel_edges`, as the page writes them (run in the scene's
    folder): the table printed is the page's, and both detectors find nearly every edge of the ideal drawing."""
    text = section("Your detector")
    commands = re.search(r"```sh\n(.*?)```", text, re.S).group(1).splitlines()
    shown = re.search(r"```text\n(.*?)```", text, re.S).group(1)
    monkeypatch.chdir(tutorial.parent)
    printed = ""
    for line in commands:
        args = shlex.split(line)
        assert args[0] == "wiredsl", line
        r = CliRunner().invoke(main, args[1:])
        assert r.exit_code == 0, (line, r.output)
        printed = r.stdout
    assert printed == shown
    doc = json.loads((tutorial.parent / "build" / "verify" / "verification.json").read_text())
    assert {o["detector"] for o in doc["objects"]} == {"sobel_edges", "canny"}
    assert all(o["verified_fraction"] > 0.9 for o in doc["objects"]), doc["objects"]


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


def test_the_tutorials_pyproject_builds_with_its_scene_and_a_scenes_folder_beside_it(tmp_path):
    """Issue 35, item 5: `pip install -e .` stopped with "Multiple top-level packages discovered in a flat-layout:
    ['scenes', 'wd_tutorial']". The page's pyproject.toml, with the page's files and a scenes/ folder beside the
    package, builds a wheel of wd_tutorial alone (pip, no network: the venv's hatchling, from the test extra)."""
    import subprocess
    import sys
    import zipfile

    for name, body in blocks().items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(body)
    (tmp_path / "wd_tutorial" / "__init__.py").write_text("")
    (tmp_path / "scenes").mkdir()
    (tmp_path / "scenes" / "mine.wd").write_text("wiredsl 1\n")
    (tmp_path / "scenes" / "helper.py").write_text("")  # a stray module there too
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-build-isolation", "--no-deps", "-q", "-w",
                        str(tmp_path / "dist"), str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    (wheel,) = (tmp_path / "dist").glob("wd_tutorial-0.1.0-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert {n.split("/")[0] for n in names} == {"wd_tutorial", "wd_tutorial-0.1.0.dist-info"}
    assert "wd_tutorial/effects.py" in names
