"""What the source and wheel distributions hold: third-party test data whose licence is not MIT-compatible
stays in the repository (each file keeps its own licence), never in the sdist; the wheel holds no tests."""

from __future__ import annotations

import re
import tarfile
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TABLES = [ROOT / "tests/data/calibration/README.md", ROOT / "tests/data/trajectories/SOURCES.md"]
PERMISSIVE = re.compile(r"Apache|BSD|\bMIT\b|CC BY 4\.0")
RESTRICTED = re.compile(r"GPL|NC|SA|terms|as the ")


def _licences() -> dict[str, str]:
    """Each third-party file under tests/data with the licence its table states (the last column)."""
    out = {}
    for table in TABLES:
        for line in table.read_text().splitlines():
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if len(cells) >= 3 and cells[0].startswith("`"):
                for name in re.findall(r"`([^`]+)`", cells[0]):
                    out[str((table.parent / name).relative_to(ROOT))] = cells[-1]
    return out


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    hatchling = pytest.importorskip("hatchling")
    from hatchling.builders.sdist import SdistBuilder
    from hatchling.builders.wheel import WheelBuilder

    assert hatchling
    out = tmp_path_factory.mktemp("dist")
    sdist = next(SdistBuilder(str(ROOT)).build(directory=str(out), versions=["standard"]))
    wheel = next(WheelBuilder(str(ROOT)).build(directory=str(out), versions=["standard"]))
    with tarfile.open(sdist) as t:
        names = {n.split("/", 1)[1] for n in t.getnames() if "/" in n}
    with zipfile.ZipFile(wheel) as z:
        return names, z.namelist()


def test_sdist_leaves_out_test_data_under_licences_that_are_not_mit_compatible(built):
    names, _ = built
    licences = _licences()
    restricted = {f for f, lic in licences.items() if RESTRICTED.search(lic) or not PERMISSIVE.search(lic)}
    assert len(licences) >= 20 and len(restricted) >= 15  # the tables were read
    assert not restricted & names, sorted(restricted & names)
    assert "tests/meshes/lbracket.stl" not in names  # CC-BY-SA 3.0 (tests/meshes/README.md)
    assert set(licences) - restricted <= names  # the permissive ones (OpenCV's samples, TUM's ground truth) stay
    assert {"tests/data/calibration/README.md", "tests/data/trajectories/SOURCES.md", "tests/test_study.py",
            "wiredsl/cli.py", "scenes/lab.wd"} <= names


def test_wheel_holds_no_tests(built):
    _, wheel = built
    assert any(n.startswith("wiredsl/") for n in wheel)
    assert not [n for n in wheel if n.startswith("tests/") or "/tests/" in n or "conftest" in n]
