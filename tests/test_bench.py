"""`wiredsl bench`: the four tables are measured and sane, the plot is valid SVG."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from click.testing import CliRunner

from wiredsl import bench
from wiredsl.cli import main
from wiredsl.engine.world import build_world
from wiredsl.language.compile import compile_file
from wiredsl.montecarlo import Run

TINY = Path("scenes/cylinder.wd").read_text().replace("""  silhouette side between top bottom
""", """  silhouette side between top bottom
  line post from (0.3, 0, 0) to (0.3, 0, 1)
  corner foot at (0.3, 0, 0) joins post
""") + """
pipeline shake {
  lateral_shift range 2px
  corner_mismatch fraction 50% radius 3px
}
"""


class TickClock:
    """A fake timer: each reading is `step` seconds after the last, so a timed row takes `step` seconds whatever
    the machine's speed or load, and which rows fit a budget is decided by the bench's arithmetic alone."""

    def __init__(self, step: float):
        self.now, self.step = 0.0, step

    def __call__(self) -> float:
        self.now += self.step
        return self.now


@pytest.fixture
def small_bench(monkeypatch):
    """The bench's knobs turned down: two tolerances, two trial counts, few points, short timing loops, and a
    fake clock (10 ms a timed row)."""
    monkeypatch.setattr(bench, "TOLERANCES", (0.03, 1.0))
    monkeypatch.setattr(bench, "SPACINGS", (0.5, 2.0))
    monkeypatch.setattr(bench, "TRIALS", (10, 100, 10**9))
    monkeypatch.setattr(bench, "PRECISION_POINTS", 5000)
    monkeypatch.setattr(bench, "MIN_SECONDS", 0.0)
    monkeypatch.setattr(bench, "clock", TickClock(0.01))


def _table(markdown: str, title: str) -> list[list[str]]:
    """The rows of the Markdown table under the heading that starts with `title`."""
    part = markdown.split(f"### {title}", 1)[1].split("###", 1)[0]
    return [[c.strip() for c in line.strip("|").split("|")] for line in part.splitlines()
            if line.startswith("|") and not line.startswith("|---")][1:]


@pytest.mark.parametrize("suffix", [".svg", ".pdf"])
def test_bench_command_measures_every_table_and_writes_the_plot(tmp_path, small_bench, suffix):
    scene = tmp_path / "tiny.wd"
    scene.write_text(TINY)
    out = tmp_path / f"bench{suffix}"
    r = CliRunner().invoke(main, ["bench", str(scene), "--budget", "1", "-o", str(out)])
    assert r.exit_code == 0, r.output
    md = r.stdout
    tol = _table(md, "Polyline tolerance")
    assert [row[0] for row in tol] == ["0.03", "1"] and 0 < float(tol[0][1]) <= 0.03 * 1.05
    assert int(tol[0][3]) > int(tol[1][3])  # finer, more vertices
    trials = _table(md, "Monte-Carlo trials")
    assert [row[0] for row in trials] == ["10", "100"]
    assert float(trials[1][2]) < float(trials[0][2])  # ten times the trials, a smaller standard error
    assert "1,000,000,000 trials not run" in md
    prec = _table(md, "float32 against float64")
    assert prec[0][:2] == ["float64", "0"] and 0 <= float(prec[1][1]) < 0.1
    assert len(_table(md, "View-dependency")) == 1 + 2  # exact, then the two grids (the scene has no mesh)
    if suffix == ".svg":
        root = ET.parse(out).getroot()
        assert root.tag.endswith("svg") and root.get("viewBox")
        labels = "".join(root.itertext())
        for unit in ("max deviation (px)", "wrong visibility (fraction)", "standard error (px)",
                     "max difference (px)"):
            assert unit in labels, unit
    else:
        assert out.read_bytes()[:5] == b"%PDF-"


def test_the_trials_rows_are_timed_after_a_warm_up(monkeypatch, small_bench, tmp_path):
    """The first row (10 trials) used to include compiling and first-call costs: a batch runs before any clock."""
    (tmp_path / "tiny.wd").write_text(TINY)
    scene, _, _ = compile_file(tmp_path / "tiny.wd")
    events = []
    real_batches, real_clock = Run.batches, bench.clock
    monkeypatch.setattr(Run, "batches", lambda self, trials, *a: (events.append(("batch", len(trials))),
                                                                   real_batches(self, trials, *a))[1])
    monkeypatch.setattr(bench, "clock", lambda: (events.append(("clock",)), real_clock())[1])
    bench.trials_table(scene, build_world(scene), budget=5.0)
    first_clock = events.index(("clock",))
    assert ("batch", 1) in events[:first_clock]


def test_tolerance_rows_keep_their_promise(monkeypatch):
    monkeypatch.setattr(bench, "MIN_SECONDS", 0.0)  # one timed call a row: the promise is about accuracy
    scene, _, _ = compile_file("scenes/cylinder.wd")
    table = bench.tolerance_table(scene, build_world(scene))
    assert [row[0] for row in table.rows] == list(bench.TOLERANCES)
    for tol, deviation, _, vertices in table.rows:
        assert 0 < deviation <= tol * 1.05 or tol >= 1  # coarse tolerances hit the minimum sampling first
        assert vertices > 0
    assert table.rows[0][3] > table.rows[-1][3]  # finer tolerance, more vertices


def test_trials_table_respects_its_budget_and_says_what_it_skipped(monkeypatch):
    """On a fake clock (0.3 s a row) the first row runs at 10 / 0.3 = 33 trials/s, so 100 trials (3 s) would
    overrun a 1 s budget: every later row is skipped, each with its predicted time."""
    monkeypatch.setattr(bench, "clock", TickClock(0.3))
    scene, _, _ = compile_file("scenes/lab.wd")
    table = bench.trials_table(scene, build_world(scene), budget=1.0)
    assert [row[0] for row in table.rows] == [10]
    assert table.rows[0][2] > 0 and table.rows[0][3] == pytest.approx(0.3)
    assert table.notes == [f"{n:,} trials not run: at the measured 33 trials/s they would take "
                           f"{bench._fmt(n * 0.03)} s, over the budget of 1 s (--budget)." for n in bench.TRIALS[1:]]


def test_trials_rows_run_while_their_predicted_time_fits_the_budget(monkeypatch, small_bench, tmp_path):
    """10 ms a row: 10 trials run first (1,000/s), 100 are predicted at 0.1 s and run (10,000/s), 10**9 would take
    100,000 s; with the budget cut to what the first row spent plus less than the second's prediction, the second
    is skipped too."""
    (tmp_path / "tiny.wd").write_text(TINY)
    scene, _, _ = compile_file(tmp_path / "tiny.wd")
    world = build_world(scene)
    table = bench.trials_table(scene, world, budget=1.0)
    assert [row[0] for row in table.rows] == [10, 100]
    assert table.notes == ["1,000,000,000 trials not run: at the measured 10,000 trials/s they would take "
                           "100,000 s, over the budget of 1 s (--budget)."]
    monkeypatch.setattr(bench, "clock", TickClock(0.01))
    table = bench.trials_table(scene, world, budget=0.1)  # 0.01 spent + 0.1 predicted > 0.1
    assert [row[0] for row in table.rows] == [10]
    assert table.notes[0].startswith("100 trials not run: at the measured 1,000 trials/s they would take 0.1 s, over")


def test_view_dependency_table_says_how_far_whole_feature_lists_are_from_hidden_lines():
    scene, _, _ = compile_file("scenes/box.wd")
    table = bench.viewdep_table(scene, build_world(scene))
    assert table.columns[-1] == "wrong image length vs hidden lines (fraction)"
    wrong = [row[-1] for row in table.rows]
    # the box hides parts of its own edges from the path: no whole-feature list can be right everywhere
    assert all(0 < w < 1 for w in wrong)


def test_a_scene_without_corners_has_no_trials_rows_and_says_why(tmp_path):
    """It used to take the mean of no displacement (a numpy RuntimeWarning, exit 3)."""
    pipeline = "pipeline p {\n lateral_shift range 1px\n}\n"
    (tmp_path / "c.wd").write_text(Path("scenes/cylinder.wd").read_text() + pipeline)
    scene, _, _ = compile_file(tmp_path / "c.wd")
    table = bench.trials_table(scene, build_world(scene), budget=1.0)
    assert table.rows == [] and "no corners" in table.notes[0]


def test_zero_error_labels_of_nearby_points_do_not_overlap():
    """Three rows of zero error close together on the x axis (a box's exact, 0.25 m grid and own mesh): their
    labels used to be drawn over each other at one height; each now sits above its point, one line up if need be."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table = bench.Table("t", ["from", "wrong", "time"], plot=(2, 1), short="t",
                        rows=[["exact", 0.0, 0.0013], ["grid 0.25 m", 0.0, 0.0005],
                              ["scene's mesh 'around'", 0.0, 0.0007], ["grid 2 m", 0.25, 0.00026],
                              ["grid 1 m", 0.25, 0.0045]])
    fig, ax = plt.subplots(figsize=(5, 3.6))
    bench._panel(ax, table)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    boxes = [t.get_window_extent(renderer) for t in ax.texts if t.get_text().endswith("zero error")]
    plt.close(fig)
    assert len(boxes) == 3
    assert not any(a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1:])
