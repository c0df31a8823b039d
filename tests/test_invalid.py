"""Every tests/invalid/*.wd states in its first line the exact first diagnostic it must produce."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from wiredsl.cli import main

CASES = sorted(Path("tests/invalid").resolve().glob("*.wd"))


def expected(path: Path) -> str:
    first = path.read_text(encoding="utf-8").splitlines()[0]
    m = re.fullmatch(r"# expect: (.*)", first)
    assert m, f"{path.name} must start with '# expect: ...'"
    want = m.group(1)
    rel = path.relative_to(Path.cwd()).as_posix()
    return want if not want[0].isdigit() else f"{rel}:{want}"


@pytest.mark.parametrize("path", CASES, ids=[p.stem for p in CASES])
def test_invalid_file_gives_its_diagnostic(path: Path):
    rel = path.relative_to(Path.cwd()).as_posix()
    result = CliRunner().invoke(main, ["check", rel])
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output
    first = result.stderr.splitlines()[0]
    assert first == expected(path)


def test_every_error_code_is_exercised():
    codes = {re.search(r"error\[(E\d+)\]", expected(p)).group(1) for p in CASES}
    from wiredsl.diagnostics import CODES

    documented = {c for c in CODES if c.startswith("E")}  # the diagnostics page is generated from CODES
    assert documented, "CODES lists the error codes"
    # build-time only: tested in test_hostile.py and test_effect_defects.py
    build_time = {"E142", "E161"}
    plugins = {"E180", "E181"}  # need an installed package: tested in test_plugins.py
    images = {"E190", "E191", "E192", "E193", "E197", "E198", "E199"}  # images, not scenes: test_verify, test_board
    untested = documented - codes - build_time - plugins - images
    assert not untested, f"codes without a bad-input file: {untested}"
