"""benchmarks/cli_report.py: which scripts a sitting runs, and `--write`'s rewriting of docs/performance.md's marked
regions (everything outside them kept byte for byte). The scripts themselves are not run here: they are
benchmarks, and their figures depend on the machine."""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
spec = importlib.util.spec_from_file_location("cli_report", ROOT / "benchmarks" / "cli_report.py")
report = importlib.util.module_from_spec(spec)
sys.modules.setdefault("cli_report", report)  # dataclasses look their module up there
spec.loader.exec_module(report)

DOC = """# Title

Prose before.
<!-- cli_report: bench -->
old bench
<!-- /cli_report: bench -->
Prose between, kept.

<!-- cli_report: scripts -->
| old | table |
<!-- /cli_report: scripts -->
Prose after.
"""


def test_write_replaces_only_the_marked_regions():
    new = report.rewrite(DOC, {"bench": "### new tables\n\n| a |\n", "scripts": "| new |"})
    assert new == DOC.replace("old bench\n", "### new tables\n\n| a |\n").replace("| old | table |", "| new |")
    assert report.rewrite(DOC, {"scripts": "x"}).split("Prose between")[0] == DOC.split("Prose between")[0]
    assert report.rewrite(DOC, {}) == DOC


@pytest.mark.parametrize("text", [DOC.replace("<!-- cli_report: bench -->\n", ""), DOC + DOC])
def test_write_refuses_a_document_without_one_region_of_each_name(text):
    with pytest.raises(SystemExit, match="regions marked 'bench'"):
        report.rewrite(text, {"bench": "x"})


def test_performance_md_has_both_regions_once_and_round_trips():
    text = (ROOT / "docs" / "performance.md").read_text(encoding="utf-8")
    regions = {m.group(1): m.group(2) for m in report.MARK.finditer(text)}
    assert sorted(regions) == ["bench", "scripts"]
    assert report.rewrite(text, regions) == text
    assert "### Polyline tolerance" in regions["bench"] and "| script" in regions["scripts"]


def test_a_sitting_runs_the_study_scripts_and_every_argument_is_one_the_script_takes():
    names = {s.name for s in report.SCRIPTS}
    assert {"study_speed.py", "study_scaling.py", "cold_start.py", "memory_npz.py"} <= names
    for s in report.SCRIPTS:
        source = (ROOT / "benchmarks" / s.name).read_text(encoding="utf-8")
        for size in ("full", "quick", "smoke"):
            for flag in (a for a in report.arguments(s, size)[1:] if a.startswith("--")):
                assert re.search(rf"add_argument\(\"{flag}\"", source), (s.name, size, flag)
    smoke = {s.name: report.arguments(s, "smoke") for s in report.SCRIPTS}
    assert smoke["study_scaling.py"][1:3] == ["--points", "4"]  # 36 design points, not the full study's 4,608


def test_the_table_keeps_each_scripts_headline_lines():
    s = next(s for s in report.SCRIPTS if s.name == "cli_ideal_view.py")
    out = ("load average 1 1 1\nlab, 14 views : 0.2 s CPU\nideal build per extra view     : 0.37 ms CPU (target "
           "<= 0.5 ms)\n  with the SVGs (one a pose)   : 0.99 ms CPU more a pose\n(9 s wall for the script)")
    results = {"cli_ideal_view.py": {"args": ["cli_ideal_view.py"], "this checkout": (True, out),
                                     "main": (False, "FAILED (1)")}}
    table = report.scripts_table(results, [("this checkout", "abc1234"), ("main", "def5678")], "machine: m")
    lines = table.splitlines()
    assert lines[0] == "machine: m" and lines[2] == "| script | this checkout (abc1234) | main (def5678) | target |"
    assert lines[4] == ("| `cli_ideal_view.py` | ideal build per extra view : 0.37 ms CPU (target <= 0.5 ms); with the "
                        f"SVGs (one a pose) : 0.99 ms CPU more a pose | failed | {s.target} |")
    assert len(lines) == 5  # a script not run has no row
