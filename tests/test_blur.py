"""Motion blur (issue 39 item 3): a camera's exposure, `wiredsl render`'s smear over it, and the motion_blur effect,
which reproduces the magnitudes benchmarks/blur_magnitudes.py measured (render, Canny, verify, fit) within their
intervals. Its table is the benchmark's output, as the path tutorial prints it."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from helpers import compile_text, errors_of

from wiredsl.effects import motion_blur as mb
from wiredsl.engine.simulate import Options
from wiredsl.engine.world import build_world
from wiredsl.montecarlo import Run

F, Z = 500.0, 3.0  # the wall's focal length (px) and distance (m): image motion = F v exposure / Z


def wall(angle: float, speed: float = 2.0, exposure: float = 0.024, pipeline: str = "motion_blur",
         lines: int = 8) -> str:
    """Lines on a wall 3 m ahead at `angle` deg from the image's horizontal, the robot sliding sideways (along its
    y axis) at `speed`: the image moves horizontally, at `angle` to the lines, F speed exposure / Z px."""
    a = math.radians(angle)
    d = 0.2 * np.array([math.cos(a), math.sin(a)])  # (world -y, world z) half extent
    rows = "\n".join(f"  line l{k} from (0, {y - d[0]:.6f}, {1.2 - d[1]:.6f}) to (0, {y + d[0]:.6f}, "
                     f"{1.2 + d[1]:.6f})" for k, y in enumerate(np.linspace(-0.9, 0.9, lines)))
    expose = f"  exposure {exposure * 1e3:g}ms\n" if exposure else ""
    return (f"wiredsl 1\nmodel m {{\n{rows}\n}}\nplace m as w at (3, 0, 0)\n"
            f"camera eye {{\n  focal {F:g}px\n  size (640px, 480px)\n{expose}}}\n"
            "rig pair {\n  left eye at (0, 0.06, 1.2) looking (1, 0, 0)\n"
            "  right eye at (0, -0.06, 1.2) looking (1, 0, 0)\n}\n"
            f"path walk {{\n  speed {speed:g}m/s\n  pose (0, 0) heading 0\n  pose (0, 0.1) heading 0\n"
            "  pose (0, 0.2) heading 0\n}\n"
            f"pipeline p {{\n  {pipeline}\n}}\n")


def run_of(text: str, seed: int = 5, engine: str = "numpy") -> Run:
    scene, _ = compile_text(text)
    run = Run.create(scene, build_world(scene), scene.pipelines[0], seed, Options())
    run.engine = engine
    return run


def sets(run: Run, trials) -> list:
    return [(r.index, side, s) for _, out in run.batches(trials, 64) for r, d, _ in out for side, s in d.items()]


def measured_rows() -> list[dict]:
    """The benchmark's rows, parsed from its table in docs/tutorials/path.md (docs/reproduce.py's blur-table)."""
    text = Path("docs/tutorials/path.md").read_text()
    block = text[text.index("<!-- numbers: blur-table -->"):]
    num = r"([-\d.e]+|-)"
    rows = []
    for m in re.finditer(rf"^\| {num} \| {num} \| {num} \| {num} \[{num}, {num}\] \| {num} \[{num}, {num}\] \|",
                         block, re.M):
        v = [None if x == "-" else float(x) for x in m.groups()]
        rows.append({"length": v[0], "angle": v[1], "edge_loss.fraction": v[3:6], "lateral_shift.range": v[6:9]})
    return rows


def test_the_effects_table_is_the_benchmarks_output():
    rows = measured_rows()
    assert len(rows) == 1 + 3 * 3
    for r in rows:
        i, j = mb.TABLE_LENGTHS.index(r["length"]), mb.TABLE_ANGLES.index(r["angle"])
        assert mb.LOSS[i][j] == pytest.approx(r["edge_loss.fraction"][0], abs=5e-4)
        assert mb.SHIFT[i][j] == pytest.approx(r["lateral_shift.range"][0], abs=5e-4)
    for j in range(1, 3):  # no blur has no angle: its row holds for all
        assert mb.LOSS[0][j] == mb.LOSS[0][0] and mb.SHIFT[0][j] == mb.SHIFT[0][0]


def test_image_motion_is_the_closed_form_along_the_motion():
    """F v exposure / Z px, horizontal, whatever the lines' angle (the report's mean and largest motion)."""
    for angle in (0.0, 45.0, 90.0):
        run = run_of(wall(angle, speed=1.5, exposure=0.02))
        sets(run, range(2))
        got = run.manifest()["stages"][0]["measured"]
        want = F * 1.5 * 0.02 / Z
        assert got["mean_image_motion_px"]["measured"] == pytest.approx(want, rel=1e-6)
        assert got["max_image_motion_px"]["measured"] == pytest.approx(want, rel=1e-6)


@pytest.mark.parametrize("angle", [0.0, 45.0, 90.0])
def test_the_effect_reproduces_the_measured_magnitudes(angle):
    """At each measured (length, angle), 200 trials of the wall: the removed length fraction and the range of the
    shifts (the largest |shift|, and twice the mean) lie in the benchmark's 95% intervals."""
    rows = {(r["length"], r["angle"]): r for r in measured_rows()}
    for length in mb.TABLE_LENGTHS[1:]:
        row = rows[(length, angle)]
        speed = length * Z / (F * 0.024)
        run = run_of(wall(angle, speed=speed))  # lines at `angle` to the horizontal motion
        out = sets(run, range(200))
        st = run.stats
        removed = 1 - st.sums["motion_blur"]["kept_length"] / st.sums["motion_blur"]["total_length"]
        value, lo, hi = row["edge_loss.fraction"]
        assert lo - 1e-9 <= removed <= hi + 1e-9, (length, angle, removed, row)
        value, lo, hi = row["lateral_shift.range"]
        if removed < 1:  # shifts uniform on [-range, range]: twice their mean |shift| estimates the range
            shift = 2 * st.sums["motion_blur"]["sum_abs"] / st.sums["motion_blur"]["vertices"]
            assert lo - 1e-9 <= shift <= hi + 1e-9, (length, angle, shift, row)
        assert any(s.n_strokes for _, _, s in out) or removed == 1


def test_a_trial_replays_alone_and_a_seed_gives_the_same_bytes():
    text = wall(90.0, speed=(8 * Z / (F * 0.024)), pipeline="edge_loss fraction 10%\n  motion_blur\n"
                "  lateral_shift range 1px")
    batch = {(i, side): s for i, side, s in sets(run_of(text), range(40))}
    for trial in (3, 17, 39):
        for i, side, s in sets(run_of(text), [trial]):
            mine = batch[(i, side)]
            keep = mine.trial == trial
            assert np.array_equal(s.fid, mine.fid[keep]) and s.pts.tobytes() == _pts_of(mine, keep).tobytes()
    a = [s.pts.tobytes() for *_, s in sets(run_of(text, seed=11), range(8))]
    b = [s.pts.tobytes() for *_, s in sets(run_of(text, seed=11), range(8))]
    c = [s.pts.tobytes() for *_, s in sets(run_of(text, seed=12), range(8))]
    assert a == b and a != c


def _pts_of(s, keep):
    counts = np.diff(s.start)
    return s.pts[np.repeat(keep, counts)]


def test_a_scene_without_exposure_draws_nothing_and_costs_nothing():
    still = run_of(wall(90.0, exposure=0.0, pipeline="motion_blur\n  lateral_shift range 1px"))
    assert still.moved_views() is None
    ideal = run_of(wall(90.0, exposure=0.0, pipeline="lateral_shift range 1px"))
    a, b = sets(still, range(6)), sets(ideal, range(6))
    assert [s.pts.tobytes() for *_, s in a] == [s.pts.tobytes() for *_, s in b]
    assert still.trace["project"] == 1  # no projection at the exposure's ends


def test_both_engines_agree():
    text = wall(90.0, speed=(9 * Z / (F * 0.024)), pipeline="edge_loss fraction 10%\n  motion_blur\n"
                "  lateral_shift range 1px")
    n, k = sets(run_of(text, engine="numpy"), range(30)), sets(run_of(text, engine="kernel"), range(30))
    assert len(n) == len(k) > 0
    for (_, _, a), (_, _, b) in zip(n, k, strict=True):
        assert np.array_equal(a.start, b.start) and np.array_equal(a.fragment, b.fragment)
        assert np.abs(a.pts - b.pts).max(initial=0) < 1e-9


def test_bad_input_is_located():
    def line_of(text, word):
        return text.splitlines().index(next(x for x in text.splitlines() if x.strip().startswith(word))) + 1

    bad = wall(90.0, exposure=0.0).replace("focal 500px", "focal 500px\n  exposure -3ms")
    assert errors_of(bad) == [f"{line_of(bad, 'exposure')}:12: E110 an exposure time must be in [0, 1000] ms, "
                              "got -3 ms"]
    no_times = wall(90.0).replace("  speed 2m/s\n", "")
    assert errors_of(no_times)[0].startswith(f"{line_of(no_times, 'exposure')}:12: E102 the exposure of camera "
                                             "'eye' needs the robot's motion")
    scaled = wall(90.0, pipeline="motion_blur scale -1")
    assert errors_of(scaled)[0].startswith(f"{line_of(scaled, 'motion_blur')}:")
    assert errors_of(scaled)[0].split(" ")[1] == "E110"


def test_render_smears_an_exposed_camera_as_the_closed_form_motion():
    """The exposed render of pose 0 is the still render smeared along the image's x by F v exposure / Z (8 px)."""
    from wiredsl.io import render

    def image(text, smear=(0.0, 0.0)):
        scene, _ = compile_text(text)
        look = render.Look(edges="step", width=6, faces="none", smear=smear)
        (img,) = list(render.render(scene, look=look, poses=(0,), cameras="left"))
        counts.append(img.subframes)
        return img.pixels.astype(float)

    counts = []

    moving = image(wall(90.0, lines=3))
    still = [image(wall(90.0, lines=3, exposure=0.0), (sign * 8.0, 0.0)) for sign in (1, -1)]
    sharp = image(wall(90.0, lines=3, exposure=0.0))
    best = min(np.abs(moving - s).max() for s in still)
    assert best <= 2.0 and np.abs(moving - sharp).max() > 20
    assert counts[0] == math.ceil(8.0 / render.SUBFRAME_PX) and counts[1:] == [1, 1, 1]  # 0.5 px apart
