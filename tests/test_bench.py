"""`wiredsl bench`: the four tables are measured and sane, the plot is valid SVG."""

from __future__ import annotations

import xml.etree.ElementTree as ET

from click.testing import CliRunner

from wiredsl import bench
from wiredsl.cli import main
from wiredsl.engine.world import build_world
from wiredsl.language.compile import compile_file


def test_bench_command_prints_four_tables_and_writes_the_plot(tmp_path):
    out = tmp_path / "bench.svg"
    r = CliRunner().invoke(main, ["bench", "scenes/cylinder.wd", "--budget", "1", "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert r.stdout.count("### ") == 4
    root = ET.parse(out).getroot()
    assert root.tag.endswith("svg") and root.get("viewBox")


def test_tolerance_rows_keep_their_promise():
    scene, _, _ = compile_file("scenes/cylinder.wd")
    table = bench.tolerance_table(scene, build_world(scene))
    assert [row[0] for row in table.rows] == list(bench.TOLERANCES)
    for tol, deviation, _, vertices in table.rows:
        assert 0 < deviation <= tol * 1.05 or tol >= 1  # coarse tolerances hit the minimum sampling first
        assert vertices > 0
    assert table.rows[0][3] > table.rows[-1][3]  # finer tolerance, more vertices


def test_trials_table_respects_its_budget_and_says_what_it_skipped():
    scene, _, _ = compile_file("scenes/lab.wd")
    table = bench.trials_table(scene, build_world(scene), budget=1.0)
    assert table.rows and table.rows[0][0] == 10
    assert all(row[2] > 0 for row in table.rows)
    assert any("not run" in note for note in table.notes)


def test_view_dependency_table_says_how_far_whole_feature_lists_are_from_hidden_lines():
    scene, _, _ = compile_file("scenes/box.wd")
    table = bench.viewdep_table(scene, build_world(scene))
    assert table.columns[-1] == "wrong image length vs hidden lines"
    wrong = [row[-1] for row in table.rows]
    # the box hides parts of its own edges from the path: no whole-feature list can be right everywhere
    assert all(0 < w < 1 for w in wrong)
