"""Defects found by independent checks (issue 8), each against a reference that does not share the
effect's code: the epipolar band on closed curves, ellipse halves when the axis meets a vertex, a
one-parameter calibration, and calibration draws that would make a camera nonsensical."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from wiredsl.cli import main
from wiredsl.effects import REGISTRY
from wiredsl.effects.base import Context, Stats
from wiredsl.effects.lateral_shift import split_ellipses
from wiredsl.engine import imageset as im

pytestmark = pytest.mark.usefixtures("engine")  # every reference on both engines


def one_stroke(pts: np.ndarray, closed: bool, kind: int = im.CURVE) -> im.ImageSet:
    z = np.zeros(1, int)
    return im.ImageSet(pts=np.asarray(pts, float), start=np.array([0, len(pts)]), fid=z, segment=z - 1,
                       fragment=z - 1, kind=z + kind, clipped=z.astype(bool), closed=np.array([closed]), trial=z,
                       corners=np.zeros((0, 2)), corner_fid=np.zeros(0, int), corner_trial=np.zeros(0, int))


def wobbly_loop(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0, 2 * np.pi, n))
    r = 100 + 20 * np.sin(3 * t + rng.uniform(0, 6))
    return np.column_stack([320 + r * np.cos(t), 240 + r * np.sin(t)])


def band_reference(pts: np.ndarray, epipole: np.ndarray, band: float) -> list[bool]:
    """Which segments of the loop (i -> i + 1, the last closing) survive: the angle between each segment
    and the line from the epipole through its midpoint, in plain Python."""
    ex, ey, ew = epipole
    keep = []
    for i in range(len(pts)):
        (ax, ay), (bx, by) = pts[i], pts[(i + 1) % len(pts)]
        mx, my = (ax + bx) / 2, (ay + by) / 2
        lx, ly = mx * ew - ex, my * ew - ey
        dx, dy = bx - ax, by - ay
        cos = abs(dx * lx + dy * ly) / (math.hypot(dx, dy) * math.hypot(lx, ly))
        keep.append(math.degrees(math.acos(min(cos, 1.0))) > math.degrees(band))
    return keep


@pytest.mark.parametrize("seed", range(12))
def test_band_on_a_closed_curve_keeps_each_surviving_part_once_and_rejoins_at_the_start(seed):
    pts = wobbly_loop(40, seed)
    epipole = np.array([1.0, 0.05 * (seed - 6), 0.0])  # epipolar lines nearly horizontal
    band = math.radians(20)
    p = REGISTRY["stereo_mismatch"].Params(band=band, fraction=0)
    ctx = Context(pose=0, side="left", trials=np.array([0]), seed=0, stats=Stats(), epipole=lambda: epipole)
    out = REGISTRY["stereo_mismatch"].apply(p, one_stroke(pts, True), ctx)
    keep = band_reference(pts, epipole, band)
    n = len(pts)
    if all(keep):
        assert out.n_strokes == 1 and out.closed[0] and np.array_equal(out.pts, pts)
        return
    # the reference pieces: maximal runs of kept segments, cyclically
    runs = sum(1 for i in range(n) if keep[i] and not keep[i - 1])
    assert out.n_strokes == runs and not out.closed.any()
    # densely sampled points of the kept segments are each on exactly one output piece; dropped ones on none
    pieces = [out.pts[out.start[k]:out.start[k + 1]] for k in range(out.n_strokes)]
    for i in range(n):
        a, b = pts[i], pts[(i + 1) % n]
        for t in (0.25, 0.5, 0.75):
            q = a + t * (b - a)
            on = sum(_on_polyline(q, piece) for piece in pieces)
            assert on == (1 if keep[i] else 0), (i, t, keep[i], on)


def _on_polyline(q: np.ndarray, piece: np.ndarray) -> bool:
    a, b = piece[:-1], piece[1:]
    d = b - a
    t = np.clip(((q - a) * d).sum(1) / np.maximum((d * d).sum(1), 1e-300), 0, 1)
    return bool((np.linalg.norm(a + t[:, None] * d - q, axis=1) < 1e-7).any())


def ellipse(n: int, phase: float = 0.0, a: float = 100.0, b: float = 40.0) -> np.ndarray:
    t = 2 * np.pi * np.arange(n) / n + phase
    return np.column_stack([320 + a * np.cos(t), 240 + b * np.sin(t)])


@pytest.mark.parametrize("n", [16, 32, 64, 100, 128, 256, 512])
def test_an_ellipse_splits_at_its_major_axis_even_through_a_vertex(n):
    """Face-on sampling puts vertices on the major axis (y = 240); each half must lie on one side."""
    out = split_ellipses(one_stroke(ellipse(n), True, im.ELLIPSE))
    assert out.n_strokes == 2 and not out.closed.any()
    for k in range(2):
        y = out.pts[out.start[k]:out.start[k + 1], 1] - 240
        assert y.min() > -1e-6 or y.max() < 1e-6
    total = sum(np.linalg.norm(np.diff(out.pts[out.start[k]:out.start[k + 1]], axis=0), axis=1).sum() for k in (0, 1))
    loop = ellipse(n)
    assert total == pytest.approx(np.linalg.norm(np.roll(loop, -1, 0) - loop, axis=1).sum(), rel=1e-12)


def test_strokes_that_are_not_ellipses_are_untouched_by_the_split():
    s = one_stroke(wobbly_loop(30, 1), True)
    out = split_ellipses(im.replace(s, kind=np.array([im.CURVE])))
    assert out is s or (np.array_equal(out.pts, s.pts) and out.closed[0])


ONE_PARAMETER = """wiredsl 1
scene one
camera c {
  focal 600px
  centre (320px, 240px)
  size (640px, 480px)
}
model m {
  line a from (0, 0, 0) to (0, 0, 1m)
}
place m as m1 at (3m, 0, 0)
rig r {
  left c at (0, 0.1m, 0.5m) looking (1, 0, 0)
  right c at (0, -0.1m, 0.5m) looking (1, 0, 0)
  calibration covariance order [left.f] matrix [[SIGMA2]]
}
path p {
  straight from (0, 0) to (0.4m, 0) step 0.2m
}
pipeline cal default {
  calibration_error sigma 1
}
"""


def _build(tmp_path, text, *args):
    (tmp_path / "s.wd").write_text(text)
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["build", str(tmp_path / "s.wd"), "--seed", "4", "--format", "jsonl", "-o", str(out),
                                  *args])
    return r, out


def test_a_calibration_over_one_parameter_writes_its_manifest(tmp_path):
    r, out = _build(tmp_path, ONE_PARAMETER.replace("SIGMA2", "4"), "--trials", "50")
    assert r.exit_code == 0, r.output
    manifest = json.loads((out / "manifest.json").read_text())
    measured = manifest["stages"][0]["measured"]
    assert measured["std_relative_error"]["trials"] == 50 and measured["std_relative_error"]["measured"] < 0.5
    assert measured["refused_draws"]["measured"] == 0
    names = {p.name for p in out.iterdir()}
    assert {"features.jsonl", "manifest.json"} <= names
    assert not [n for n in names if n.startswith(".") or n.endswith(".tmp")]  # no temporary left


def test_draws_giving_a_non_positive_focal_are_refused_redrawn_and_counted(tmp_path):
    # sigma of f = 500 px on a 600 px focal length: about 12% of draws would be negative
    r, out = _build(tmp_path, ONE_PARAMETER.replace("SIGMA2", "250000"), "--trials", "200")
    assert r.exit_code == 0, r.output
    assert "calibration draws refused" in r.output
    refused = json.loads((out / "manifest.json").read_text())["stages"][0]["measured"]["refused_draws"]["measured"]
    expected = 200 * 0.5 * math.erfc(600 / 500 / math.sqrt(2)) / (1 - 0.5 * math.erfc(600 / 500 / math.sqrt(2)))
    assert abs(refused - expected) < 4 * math.sqrt(expected) + 2
    focals = [v["camera"]["f"] for line in (out / "features.jsonl").read_text().splitlines()
              for v in _views(json.loads(line))]
    assert focals and min(focals) > 0


def test_a_batchs_rigs_with_redrawn_trials_are_those_of_its_final_draws(tmp_path):
    """The rigs that checked a batch's draws are the rigs it projects with: the redrawn trials' rows spliced in
    equal, bit for bit, the rigs built from scratch from the accepted draws."""
    from wiredsl.effects import calibration_error as calib
    from wiredsl.language.compile import compile_file
    from wiredsl.run import start

    (tmp_path / "s.wd").write_text(ONE_PARAMETER.replace("SIGMA2", "250000"))
    scene = compile_file(tmp_path / "s.wd")[0]
    run = start(scene, "cal", seed=4)
    phis, rigs = run.calibration_rigs(list(range(300)))
    assert run.stats.sums["calibration_error"]["refused"] > 10  # the redraw path ran
    fresh = calib.perturbed_rigs(scene, phis, scene.rig.calibration.order)
    for side in ("left", "right"):
        for key, value in fresh[side]["params"].items():
            assert np.array_equal(np.broadcast_to(value, (300,)), rigs[side]["params"][key]), key
        for key in ("rotation", "position"):
            assert np.array_equal(fresh[side][key], rigs[side][key])


def _views(doc):
    for pose in doc["poses"]:
        for side in ("left", "right"):
            if pose.get(side):
                yield pose[side]


def test_a_calibration_too_uncertain_for_its_cameras_is_a_diagnostic(tmp_path):
    r, out = _build(tmp_path, ONE_PARAMETER.replace("SIGMA2", "1e20"), "--trials", "3")
    assert r.exit_code == 1, r.output
    assert "E161" in r.output and "Traceback" not in r.output


def axis_ellipse(n: int, j: int, angle: float) -> np.ndarray:
    """n vertices of an ellipse (semi-axes 100 and 40, centre (320.3, 240.7), major axis at `angle`), vertex j
    on the major axis (parameter 0) and, for even n, vertex j + n / 2 too."""
    t = 2 * np.pi * (np.arange(n) - j) / n
    x, y = 100 * np.cos(t), 40 * np.sin(t)
    c, s = math.cos(angle), math.sin(angle)
    return np.column_stack([320.3 + c * x - s * y, 240.7 + s * x + c * y])


def halves_reference(pts: np.ndarray, angle: float) -> list[list[tuple[float, float]]]:
    """The two halves of a closed polyline cut by the line through (320.3, 240.7) at `angle`, in plain
    Python: walk the loop from vertex 0, a vertex within 1e-9 px of the line being a cut there."""
    nx, ny = -math.sin(angle), math.cos(angle)
    side = [(x - 320.3) * nx + (y - 240.7) * ny for x, y in pts.tolist()]
    side = [0.0 if abs(v) < 1e-9 else v for v in side]
    n = len(pts)
    walk: list[tuple[tuple[float, float], bool]] = []  # (point, is a cut) in loop order, vertex 0 first
    for i in range(n):
        p, q = pts[i].tolist(), pts[(i + 1) % n].tolist()
        walk.append(((p[0], p[1]), side[i] == 0))
        if side[i] * side[(i + 1) % n] < 0:
            u = side[i] / (side[i] - side[(i + 1) % n])
            walk.append(((p[0] + u * (q[0] - p[0]), p[1] + u * (q[1] - p[1])), True))
    cuts = [i for i, (_, c) in enumerate(walk) if c]
    assert len(cuts) == 2
    c1, c2 = cuts
    first = [p for p, _ in walk[c1:c2 + 1]]
    second = [p for p, _ in walk[c2:] + walk[:c1 + 1]]
    return [first, second]


def kernel_split(s: im.ImageSet) -> list[np.ndarray]:
    from wiredsl.effects.lateral_shift_kernel import _split_ellipses
    from wiredsl.engine import kernel as K

    meta = np.zeros((1, K.NMETA), np.int64)
    meta[0, K.KIND], meta[0, K.CLOSED], meta[0, K.FRAG] = K.ELLIPSE, 1, -1
    pts, start, _ = _split_ellipses(s.pts.copy(), s.start.astype(np.int64), meta)
    return [pts[start[k]:start[k + 1]] for k in range(len(start) - 1)]


@pytest.mark.parametrize("angle", [0.0, 0.3, 1.1])
@pytest.mark.parametrize("n", [9, 16, 33, 64, 101])
def test_ellipse_halves_through_a_vertex_match_an_independent_split_vertex_by_vertex(n, angle):
    """Issue 15: a half began with an extra copy of the axis vertex (a sliver segment, so that copy was not
    shifted) and ended with a duplicate; both engines against a separately written split."""
    pts = axis_ellipse(n, j=3, angle=angle)
    s = one_stroke(pts, True, im.ELLIPSE)
    ref = halves_reference(pts, angle)
    out = split_ellipses(s)
    numpy_halves = [out.pts[out.start[k]:out.start[k + 1]] for k in range(out.n_strokes)]
    for halves in (numpy_halves, kernel_split(s)):
        assert len(halves) == 2
        for got, want in zip(halves, ref, strict=True):
            assert got.shape == (len(want), 2)
            np.testing.assert_allclose(got, np.array(want), atol=1e-6, rtol=0)
