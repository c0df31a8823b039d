"""`wiredsl init`: the starter project and the plug-in template pass their own checks as generated.

(CI also installs the plug-in template with pip into a fresh virtual environment and runs its tests: .ci/run.)
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from click.testing import CliRunner
from helpers import dist_info, entry_points_text

from wiredsl import init
from wiredsl.cli import main

BIN = Path(sys.executable).parent


def env_with_wiredsl(**extra: str) -> dict[str, str]:
    return {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}", "MPLBACKEND": "Agg", **extra}


def test_the_starter_project_passes_its_own_ci_script(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(main, ["init", "my-lab"])
    assert result.exit_code == 0, result.output
    root = tmp_path / "my-lab"
    assert {p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()} == {
        "scenes/my_lab.wd", ".gitignore", "ci.sh", ".github/workflows/wiredsl.yml", "README.md"}
    assert "build/" in (root / ".gitignore").read_text().splitlines()
    script = (root / "ci.sh").read_text()
    assert "wiredsl check" in script and "wiredsl validate" in script
    assert "bash ci.sh" in (root / ".github/workflows/wiredsl.yml").read_text()
    proc = subprocess.run(["bash", str(root / "ci.sh")], env=env_with_wiredsl(), capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "ci.sh: all checks passed" in proc.stdout
    assert (root / "build/ci/study/table.json").is_file()


def test_the_starter_readme_names_the_folders_its_commands_write(tmp_path, monkeypatch):
    """Each `wiredsl` command of the project's README, run as written (the study without plots, in-process),
    writes the folder its comment names (it once said build/my_lab_shift/ for build/my_lab-shift/)."""
    monkeypatch.chdir(tmp_path)
    assert CliRunner().invoke(main, ["init", "my-lab"]).exit_code == 0
    monkeypatch.chdir(tmp_path / "my-lab")
    readme = Path("README.md").read_text()
    ran = []
    for line in readme.split("```sh\n", 1)[1].split("```", 1)[0].splitlines():
        command, _, comment = line.partition("#")
        args = command.split()
        folder = re.search(r"build/\S+/", comment)
        if args[0] != "wiredsl" or folder is None:
            continue
        extra = ["--no-plots", "--executor", "inprocess"] if args[1] == "study" else []
        r = CliRunner().invoke(main, [*args[1:], *extra])
        assert r.exit_code == 0, (line, r.output)
        assert Path(folder.group(0)).is_dir(), (line, sorted(p.name for p in Path("build").iterdir()))
        ran.append(args[1])
    assert ran == ["build", "study"]


def test_the_starter_scene_holds_a_model_a_camera_a_path_and_a_study():
    import wiredsl

    text = init.files("first")["scenes/first.wd"]
    scene = wiredsl.compile(text)
    assert len(scene.models) == 1 and len(scene.path.poses) == 5
    assert [s.name for s in scene.studies] == ["shift"]


def test_the_plugin_template_passes_its_own_tests(tmp_path, monkeypatch):
    """The generated package, put on a path as an installed distribution (its entry points from its own
    pyproject.toml), passes its generated tests in a new interpreter."""
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(main, ["init", "--plugin", "my-detector"])
    assert result.exit_code == 0, result.output
    root = tmp_path / "my-detector"
    project = tomllib.loads((root / "pyproject.toml").read_text())
    groups = project["project"]["entry-points"]
    assert set(groups) == {"wiredsl.effects", "wiredsl.measures", "wiredsl.detectors"}
    site = tmp_path / "site"
    site.mkdir()
    (site / "my_detector").symlink_to(root / "src" / "my_detector")
    dist_info(site, project["project"]["name"], project["project"]["version"], entry_points_text(groups))
    path = os.pathsep.join([str(site), *(p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p)])
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "0",
                           str(root / "tests")], cwd=root, env=env_with_wiredsl(PYTHONPATH=path),
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert " passed" in proc.stdout and "failed" not in proc.stdout


def test_the_plugin_names_follow_the_project_name():
    out = init.files("cam-noise", plugin=True)
    assert "src/cam_noise/effect.py" in out and "tests/test_cam_noise.py" in out
    assert 'name = "cam_noise_noise"' in out["src/cam_noise/effect.py"]
    assert "cam_noise_noise = \"cam_noise.effect:CornerNoise\"" in out["pyproject.toml"]
    assert not any("{{" in text for text in out.values())
    for rel, text in out.items():
        if rel.endswith(".py"):
            compile(text, rel, "exec")


@pytest.mark.parametrize("name", ["Bad", "1abc", "a b", "", "x" * 41, "../escape", "a/b"])
def test_a_bad_name_is_refused_and_writes_nothing(tmp_path, monkeypatch, name):
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(main, ["init", name])
    assert result.exit_code == 1, result.output
    assert "not a usable name" in result.stderr and "Traceback" not in result.output
    assert list(tmp_path.iterdir()) == []


def test_an_existing_folder_is_left_alone(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "proj").mkdir()
    (tmp_path / "proj" / "mine.txt").write_text("keep")
    result = CliRunner().invoke(main, ["init", "proj"])
    assert result.exit_code == 1 and "already exists" in result.stderr
    assert [p.name for p in tmp_path.iterdir()] == ["proj"]
    assert [p.name for p in (tmp_path / "proj").iterdir()] == ["mine.txt"]
    (tmp_path / "empty").mkdir()
    assert CliRunner().invoke(main, ["init", "empty"]).exit_code == 0  # an empty folder is filled
    assert (tmp_path / "empty" / "scenes" / "empty.wd").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "proj"]  # no temporary folder left
