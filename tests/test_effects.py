"""The uncertainty effects: a registry-wide battery, statistics over many trials, exact band edges,
independent streams, replay, and nothing simulated that a scene does not call for."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from helpers import compile_text, errors_of, out_of_range

from wiredsl.cli import main
from wiredsl.effects import REGISTRY
from wiredsl.effects import calibration_error as calib
from wiredsl.effects.base import Context, Stats
from wiredsl.effects.stereo_mismatch import angle_to_epipolar
from wiredsl.engine import imageset as im
from wiredsl.engine.simulate import Options
from wiredsl.engine.trials import to_imageset
from wiredsl.engine.world import build_world
from wiredsl.language.compile import compile_file
from wiredsl.montecarlo import Run
from wiredsl.scene import Pipeline

LAB, _, _ = compile_file("scenes/lab.wd")
WORLD = build_world(LAB)
ZERO = {"edge_loss": {"fraction": 0}, "lateral_shift": {"range": 0}, "approx_error": {"sigma": 0},
        "corner_loss": {"keep": 1}, "corner_mismatch": {"fraction": 0}, "stereo_mismatch": {"band": 0, "fraction": 0},
        "calibration_error": {"sigma": 0}, "corner_error": {"sigma": 0}, "motion_blur": {"scale": 0}}
IMAGE_EFFECTS = [n for n in REGISTRY if n != "calibration_error"]


def lab_view(pose: int = 3, side: str = "left", trials: int = 1) -> im.ImageSet:
    run = Run.create(LAB, WORLD, None, 0, Options())
    return to_imageset(getattr(run.ideal()[pose], side), WORLD).repeat_trials(trials)


def ctx(seed=1, side="left", trials=1, pose=3) -> Context:
    run = Run.create(LAB, WORLD, None, seed, Options())
    return Context(pose=pose, side=side, trials=np.arange(trials), seed=seed, stats=Stats(),
                   epipole=lambda: run.epipole(tuple(LAB.path.poses[pose]), side))


def same(a: im.ImageSet, b: im.ImageSet) -> bool:
    return (np.array_equal(a.pts, b.pts) and np.array_equal(a.start, b.start) and np.array_equal(a.fid, b.fid)
            and np.array_equal(a.corners, b.corners))


def run_pipeline(text_stages: str, trials: int = 1, seed: int = 5, engine: str = "auto", **opts) -> tuple[Run, list]:
    scene, _ = compile_text(f"wiredsl 1\npipeline p {{\n{text_stages}\n}}\n")
    pipe = Pipeline(name="p", stages=scene.pipelines[0].stages)
    run = Run.create(LAB, WORLD, pipe, seed, Options(**opts))
    run.engine = engine
    return run, list(run.batches(range(trials)))


ENGINES = ["numpy", "kernel"]  # the readable reference and the compiled kernel: both must keep these promises


# ----------------------------------------------------------------------------- registry battery

def test_every_effect_has_a_zero_setting_here():
    assert set(ZERO) == set(REGISTRY)


@pytest.mark.parametrize("name", IMAGE_EFFECTS)
def test_zero_magnitude_changes_nothing(name):
    effect = REGISTRY[name]
    params = effect.Params(**ZERO[name])
    assert effect.is_identity(params)
    s = lab_view(side="right", trials=2)
    assert same(effect.apply(params, s, ctx(side="right", trials=2)), s)


@pytest.mark.parametrize("name", IMAGE_EFFECTS)
def test_same_seed_same_output_other_seed_other_output(name):
    effect = REGISTRY[name]
    params = effect.Params()
    s = lab_view(side="right", trials=3)
    a = effect.apply(params, s, ctx(seed=11, side="right", trials=3))
    b = effect.apply(params, s, ctx(seed=11, side="right", trials=3))
    assert same(a, b)
    if name in ("edge_loss", "lateral_shift", "approx_error", "corner_loss", "corner_error"):
        assert not same(a, effect.apply(params, s, ctx(seed=12, side="right", trials=3)))


@pytest.mark.parametrize("name", list(REGISTRY))
def test_out_of_range_parameters_are_refused_at_their_line(name):
    effect = REGISTRY[name]
    for key, field in effect.Params.model_fields.items():
        unit = {"image": "px", "angle": "rad"}.get(field.json_schema_extra["kind"], "")
        for value in out_of_range(field):
            text = f"wiredsl 1\npipeline p {{\n  {name} {key} {value!r}{unit}\n}}\n"
            errs = errors_of(text)
            col = 4 + len(name) + len(key) + 1
            assert errs and errs[0].startswith(f"3:{col}: E110 {name} {key}: must be"), (text, errs)


# ----------------------------------------------------------------------------- statistics

def test_measured_statistics_match_the_declared_values_over_many_trials():
    run, batches = run_pipeline("edge_loss\nlateral_shift\napprox_error\ncorner_loss\ncorner_error sigma 0.4px\n"
                                "corner_mismatch fraction 5%\n"
                                "stereo_mismatch fraction 5%", trials=300)
    report = {st["effect"]: st["measured"] for st in run.manifest()["stages"]}
    assert report["edge_loss"]["removed_length_fraction"]["measured"] == pytest.approx(0.29, abs=0.01)
    assert report["corner_loss"]["keep_rate"]["measured"] == pytest.approx(0.85, abs=0.01)
    assert report["lateral_shift"]["max_abs_shift_px"]["measured"] <= 3.0
    assert report["lateral_shift"]["mean_abs_shift_px"]["measured"] == pytest.approx(1.5, abs=0.05)
    assert report["approx_error"]["sigma_px"]["measured"] == pytest.approx(0.15, rel=0.02)
    assert report["corner_error"]["sigma_px"]["measured"] == pytest.approx(0.4, rel=0.03)
    assert report["corner_mismatch"]["mismatch_rate"]["measured"] == pytest.approx(0.05, abs=0.01)
    assert report["corner_mismatch"]["max_distance_px"]["measured"] <= 10.0
    assert report["stereo_mismatch"]["mismatch_rate"]["measured"] == pytest.approx(0.05, abs=0.01)
    assert report["stereo_mismatch"]["max_shift_px"]["measured"] <= 20.0


@pytest.mark.parametrize("engine", ENGINES)
def test_corner_error_moves_each_corner_by_a_normal_of_its_sigma_per_axis(engine):
    """Every corner of every trial, both cameras: the moves are N(0, sigma^2) in x and in y (Kolmogorov-Smirnov
    against scipy's normal), uncorrelated, and a corner's move in one trial is not its move in the next."""
    from scipy import stats

    _, ideal = run_pipeline("corner_loss keep 1", trials=1, engine=engine)
    _, moved = run_pipeline("corner_error sigma 0.7px", trials=200, engine=engine)
    start = {(r.index, side): s.corners for _, out in ideal for r, d, _ in out for side, s in d.items()}
    moves = np.concatenate([s.corners - _by_trial(start[r.index, side], s)
                            for _, out in moved for r, d, _ in out for side, s in d.items()])
    assert len(moves) > 10_000
    for axis in (0, 1):
        assert stats.kstest(moves[:, axis], stats.norm(0, 0.7).cdf).pvalue > 1e-3
    assert abs(np.corrcoef(moves.T)[0, 1]) < 0.03
    assert not np.allclose(moves[: len(moves) // 2], moves[len(moves) // 2:])


@pytest.mark.parametrize("engine", ENGINES)
def test_corner_error_correlates_the_two_cameras_moves_of_a_corner_by_its_correlation(engine):
    """The same corner (feature id) in the left and right views of a trial: its moves correlate by
    `correlation` on each axis (0.6 measured within 0.05 over some 4,000 pairs), not at 0, equal at 1."""
    _, ideal = run_pipeline("corner_loss keep 1", trials=1, engine=engine)
    start = {(r.index, side): s.corners for _, out in ideal for r, d, _ in out for side, s in d.items()}

    def moves(rho):
        _, out = run_pipeline(f"corner_error sigma 0.7px correlation {rho}", trials=150, engine=engine)
        pairs = []
        for _, o in out:
            for r, d, _ in o:
                left, right = (d[side].corners - _by_trial(start[r.index, side], d[side]) for side in ("left", "right"))
                fl, fr = d["left"].corner_fid, d["right"].corner_fid
                tl, tr = d["left"].corner_trial, d["right"].corner_trial
                both, il, ir = np.intersect1d(tl * 10**6 + fl, tr * 10**6 + fr, return_indices=True)
                pairs.append(np.stack([left[il], right[ir]], axis=1))
        return np.concatenate(pairs)  # (n, 2 cameras, 2 axes)

    m = moves(0.6)
    assert len(m) > 4000  # (the correlation's standard error: about 0.01)
    for axis in (0, 1):
        assert np.corrcoef(m[:, 0, axis], m[:, 1, axis])[0, 1] == pytest.approx(0.6, abs=0.05)
    assert abs(np.corrcoef(moves(0)[:, 0, 0], moves(0)[:, 1, 0])[0, 1]) < 0.05
    one = moves(1)
    assert np.allclose(one[:, 0], one[:, 1], rtol=0, atol=1e-9) and one.std() > 0.5  # (pixels differ by rounding)


def _by_trial(corners: np.ndarray, s: im.ImageSet) -> np.ndarray:
    """The ideal corners repeated in the order of s's corners (trial by trial, each trial all of them)."""
    counts = np.bincount(s.corner_trial)
    assert (counts == len(corners)).all() and (s.corner_fid == np.tile(s.corner_fid[: len(corners)], len(counts))).all()
    return np.tile(corners, (len(counts), 1))


def segments(n: int, trials: int = 1, seed: int = 0) -> im.ImageSet:
    """n random straight strokes, repeated for `trials` trials."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(0, 600, size=(n, 2, 2)).reshape(-1, 2)
    z = np.zeros(n, int)
    one = im.ImageSet(pts=pts, start=np.arange(0, 2 * n + 1, 2), fid=np.arange(n), segment=z - 1, fragment=z - 1,
                      kind=z, clipped=z.astype(bool), closed=z.astype(bool), trial=z, corners=np.zeros((0, 2)),
                      corner_fid=np.zeros(0, int), corner_trial=np.zeros(0, int))
    return one.repeat_trials(trials)


def test_lateral_shift_moves_straight_lines_perpendicular_within_range():
    straight = segments(40, trials=50)
    out = REGISTRY["lateral_shift"].apply(REGISTRY["lateral_shift"].Params(range=2.0), straight, ctx(trials=50))
    d = out.pts - straight.pts
    direction = straight.pts[1::2] - straight.pts[::2]
    along = np.abs((d[::2] * direction).sum(1)) / np.linalg.norm(direction, axis=1)
    assert along.max() < 1e-9 and np.linalg.norm(d, axis=1).max() <= 2.0 + 1e-12
    assert np.allclose(d[::2], d[1::2])  # both ends move together


def test_edge_loss_removes_its_fraction_of_every_feature():
    s = lab_view(trials=4)
    out = REGISTRY["edge_loss"].apply(REGISTRY["edge_loss"].Params(fraction=0.4), s, ctx(trials=4))
    _, before = im.arc_lengths(s)
    _, after = im.arc_lengths(out)
    key_b = {}
    for L, f, g, t in zip(before, s.fid, s.segment, s.trial, strict=True):
        key_b[(f, g, t)] = key_b.get((f, g, t), 0) + L
    key_a = {}
    for L, f, g, t in zip(after, out.fid, out.segment, out.trial, strict=True):
        key_a[(f, g, t)] = key_a.get((f, g, t), 0) + L
    for k, L in key_b.items():
        assert key_a.get(k, 0.0) == pytest.approx(0.6 * L, rel=1e-6, abs=1e-9)


def test_calibration_draws_have_the_declared_covariance():
    C = np.array([[4.0, 1.2, 0], [1.2, 1.0, 0.1], [0, 0.1, 0.25]])
    for kind, M, sigma in (("covariance", C, 1.0), ("information", np.linalg.inv(C) * 0.01**2, 0.01)):
        p = REGISTRY["calibration_error"].Params(sigma=sigma)
        smp = calib.sampler(p, kind, M.tolist(), ["left.f", "left.cx", "left.cy"])
        draws = calib.draws(smp, np.arange(20000), 3)  # every trial at once: the same values as one by one
        assert np.array_equal(draws[[0, 7, 19999]], [calib.draw(smp, t, 3) for t in (0, 7, 19999)])
        S = np.cov(draws, rowvar=False)
        scale = np.sqrt(np.outer(np.diag(C), np.diag(C)))
        assert np.all(np.abs(S - C) <= 0.05 * scale), (kind, S, C)  # 20,000 draws: ~1% sampling error


@pytest.mark.parametrize("eigs", [[1.0, 1e-3, 0.0], [1.0, 1e-14, 1e-16], [1.0, 1e-12, -1e-15]])
def test_near_singular_information_gives_finite_bounded_draws_and_names_the_loose_direction(eigs):
    rng = np.random.default_rng(0)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    M = Q @ np.diag(eigs) @ Q.T
    p = REGISTRY["calibration_error"].Params(sigma=1.0, cutoff=1e-9)
    smp = calib.sampler(p, "information", M.tolist(), ["left.f", "left.cx", "right.tz"])
    draws = np.array([calib.draw(smp, t, 1) for t in range(200)])
    assert np.isfinite(draws).all() and np.abs(draws).max() < 1e4
    loose = sum(e <= 1e-9 for e in eigs)
    assert len(smp.unconstrained) == loose


# ----------------------------------------------------------------------------- the epipolar band

def test_the_band_edge_is_exact():
    horizontal = np.array([1.0, 0.0, 0.0])  # epipole at infinity along x: horizontal epipolar lines
    angles = np.radians([4.9, 5.0 - 1e-9, 5.1, 90.0, 0.0])
    a = np.tile([100.0, 100.0], (len(angles), 1))
    b = a + 50 * np.column_stack([np.cos(angles), np.sin(angles)])
    got = np.degrees(angle_to_epipolar(a, b, horizontal))
    assert got == pytest.approx(np.degrees(angles), abs=1e-9)
    s = im.ImageSet(pts=np.stack([a, b], 1).reshape(-1, 2), start=np.arange(0, 2 * len(a) + 1, 2),
                    fid=np.arange(len(a)), segment=-np.ones(len(a), int), fragment=-np.ones(len(a), int),
                    kind=np.zeros(len(a), int), clipped=np.zeros(len(a), bool), closed=np.zeros(len(a), bool),
                    trial=np.zeros(len(a), int), corners=np.zeros((0, 2)), corner_fid=np.zeros(0, int),
                    corner_trial=np.zeros(0, int))
    c = Context(pose=0, side="left", trials=np.array([0]), seed=0, stats=Stats(), epipole=lambda: horizontal)
    out = REGISTRY["stereo_mismatch"].apply(REGISTRY["stereo_mismatch"].Params(fraction=0), s, c)
    assert sorted(out.fid.tolist()) == [2, 3]  # 4.9, 5.0- and 0 deg dropped; 5.1 and 90 kept


# ----------------------------------------------------------------------------- streams, replay, seeds

def _corners(batches):
    return [(r.index, side, s.corners.tobytes(), s.corner_trial.tobytes())
            for _, out in batches for r, d, _ in out for side, s in sorted(d.items())]


@pytest.mark.parametrize("engine", ENGINES)
def test_a_stage_draws_the_same_whatever_other_stages_run(engine):
    _, alone = run_pipeline("corner_loss", trials=4, engine=engine)
    _, with_edges = run_pipeline("edge_loss\nlateral_shift\ncorner_loss\napprox_error", trials=4, engine=engine)
    _, reordered = run_pipeline("approx_error\ncorner_loss\nedge_loss", trials=4, engine=engine)
    assert _corners(alone) == _corners(with_edges) == _corners(reordered)


def test_replaying_a_trial_alone_gives_exactly_its_output(tmp_path):
    args = ["build", "scenes/lab.wd", "--pipeline", "edges", "--seed", "42", "--no-svg"]
    r = CliRunner().invoke(main, [*args, "--trials", "4", "--format", "jsonl", "-o", str(tmp_path / "all")])
    assert r.exit_code == 0, r.output
    lines = [json.loads(x) for x in (tmp_path / "all" / "features.jsonl").read_text().splitlines()]
    assert len(lines) == 4 * 7
    trial2 = [doc["poses"][0] for doc in lines if doc["trial"] == 2]
    r = CliRunner().invoke(main, [*args, "--trial", "2", "-o", "-"])
    replay = json.loads(r.stdout)
    assert replay["trial"] == 2 and replay["poses"] == trial2


def test_same_seed_gives_byte_identical_dumps_and_the_seed_is_recorded(tmp_path):
    outs = []
    for d in ("a", "b"):
        r = CliRunner().invoke(main, ["build", "scenes/lab.wd", "--seed", "9", "--pose", "1", "-o", str(tmp_path / d)])
        assert r.exit_code == 0, r.output
        outs.append({p.name: p.read_bytes() for p in (tmp_path / d).iterdir()})
    assert outs[0] == outs[1]
    doc = json.loads(outs[0]["features.json"])
    assert doc["seed"] == 9 and doc["pipeline"] == "paper"
    r = CliRunner().invoke(main, ["build", "scenes/lab.wd", "--pose", "1", "-o", "-"])
    assert isinstance(json.loads(r.stdout)["seed"], int)  # drawn and recorded when omitted


# ----------------------------------------------------------------------------- only what is called for

@pytest.mark.parametrize("engine", ENGINES)
def test_only_the_stages_called_for_run(engine):
    run, _ = run_pipeline("edge_loss\nlateral_shift", trials=3, engine=engine)
    assert run.uses_kernel() == (engine == "kernel")
    assert set(run.trace) == {"project", "project:right", "edge_loss", "lateral_shift"}
    assert run.trace["project"] == 1  # no calibration error: one projection shared by every trial
    assert [s["effect"] for s in run.manifest()["stages"]] == ["edge_loss", "lateral_shift"]


@pytest.mark.parametrize("engine", ENGINES)
def test_no_epipolar_geometry_without_stereo_and_no_decomposition_without_calibration(engine):
    run, _ = run_pipeline("corner_loss\napprox_error", trials=2, engine=engine)
    assert "epipole" not in run.trace and "decompose" not in run.trace
    run, _ = run_pipeline("stereo_mismatch", trials=2, engine=engine)
    assert run.trace["epipole"] > 0 and "decompose" not in run.trace
    run, _ = run_pipeline("calibration_error", trials=2, engine=engine)
    assert run.trace["decompose"] == 1 and run.trace["project"] == 1 and run.trace["reproject"] == 1
    assert "epipole" not in run.trace


@pytest.mark.parametrize("engine", ENGINES)
def test_no_right_camera_projection_when_only_the_left_is_asked_for(engine):
    run, batches = run_pipeline("edge_loss", trials=2, right=False, engine=engine)
    assert run.trace["project:right"] == 0
    assert all(set(d) == {"left"} for _, out in batches for _, d, _ in out)


@pytest.mark.parametrize("engine", ENGINES)
def test_stages_at_zero_are_not_run_and_not_listed(engine):
    run, _ = run_pipeline("edge_loss fraction 0\nlateral_shift", trials=1, engine=engine)
    assert "edge_loss" not in run.trace and [e.name for e, _ in run.stages] == ["lateral_shift"]


def test_dump_lists_exactly_the_stages_that_ran(tmp_path):
    r = CliRunner().invoke(main, ["build", "scenes/lab.wd", "--pipeline", "edges", "--seed", "1", "--pose", "0",
                                  "-o", "-"])
    doc = json.loads(r.stdout)
    assert [s["effect"] for s in doc["stages"]] == ["edge_loss", "lateral_shift"]
    assert doc["stages"][0]["params"] == {"fraction": 0.29}
    r = CliRunner().invoke(main, ["build", "scenes/lab.wd", "--no-effects", "--pose", "0", "-o", "-"])
    doc = json.loads(r.stdout)
    assert doc["stages"] == [] and doc["seed"] is None and doc["pipeline"] is None


def test_unknown_pipeline_is_a_usage_error():
    r = CliRunner().invoke(main, ["build", "scenes/lab.wd", "--pipeline", "papr", "-o", "-"])
    assert r.exit_code == 2 and "no pipeline 'papr'" in r.output and "paper, edges" in r.output


def test_npz_streams_batches_and_carries_the_manifest(tmp_path):
    r = CliRunner().invoke(main, ["build", "scenes/lab.wd", "--pipeline", "edges", "--trials", "300", "--format",
                                  "npz", "--seed", "3", "-o", str(tmp_path)])
    assert r.exit_code == 0, r.output
    z = np.load(tmp_path / "features.npz")
    batches = sorted({k.split("_")[0] for k in z.files if k.startswith("b")})
    assert len(batches) == math.ceil(300 / 128)  # the lab's batches: 128 trials (Run.batch_size)
    rows = np.concatenate([z[f"{b}_strokes"] for b in batches])
    assert sorted(set(rows[:, 0].tolist())) == list(range(300))
    manifest = json.loads(str(z["manifest"]))
    assert manifest["trials"] == 300 and manifest["seed"] == 3
    assert json.loads((tmp_path / "manifest.json").read_text())["stages"][0]["effect"] == "edge_loss"


def test_batched_calibration_reprojection_agrees_with_exact_projection():
    """Re-projecting the ideal strokes with every trial's perturbed cameras (the fast path) against
    projecting each trial's rig from scratch: corners agree exactly, strokes within the tolerance."""
    from wiredsl.bench import _distance_to_polylines

    outs = {}
    for exact in (False, True):
        run, _ = run_pipeline("calibration_error", trials=0)
        run.exact_calibration = exact
        outs[exact] = [o for _, o in run.batches(list(range(6)))][0]
        assert ("reproject" in run.trace) != exact
    worst_corner = worst_stroke = 0.0
    for (_, fast, _), (_, ref, _) in zip(outs[False], outs[True], strict=True):
        for side in ref:
            a, b = fast[side], ref[side]
            ka = {(f, t): p for p, f, t in zip(a.corners, a.corner_fid, a.corner_trial, strict=True)}
            for p, f, t in zip(b.corners, b.corner_fid, b.corner_trial, strict=True):
                worst_corner = max(worst_corner, float(np.abs(ka[(f, t)] - p).max()))
            for k in range(b.n_strokes):
                key = (b.fid[k], b.segment[k], b.trial[k])
                mine = [a.pts[a.start[i]:a.start[i + 1]] for i in range(a.n_strokes)
                        if (a.fid[i], a.segment[i], a.trial[i]) == key]
                pts = b.pts[b.start[k]:b.start[k + 1]]
                inside = (pts[:, 0] > 1) & (pts[:, 0] < 639) & (pts[:, 1] > 1) & (pts[:, 1] < 479)
                assert mine or not inside.any()
                if inside.any():
                    worst_stroke = max(worst_stroke, float(_distance_to_polylines(pts[inside], mine).max()))
    assert worst_corner < 1e-9
    assert worst_stroke < 0.1 + 0.05  # the polyline tolerance, plus the nominal view's sampling


def test_ellipses_split_into_two_halves_across_the_major_axis():
    """Checked against the analytic conic of an undistorted camera (the cylinder scene)."""
    from wiredsl.effects.lateral_shift import split_ellipses

    scene, _, _ = compile_file("scenes/cylinder.wd")
    w = build_world(scene)
    view = Run.create(scene, w, None, 0, Options()).ideal()[0].left
    s = to_imageset(view, w)
    ell = s.take((s.kind == im.ELLIPSE) & s.closed)
    conic = {f.fid: f.conic for f in view.features if f.kind == "conic"}
    assert ell.n_strokes == 2 and set(ell.fid) == set(conic)
    out = split_ellipses(ell)
    assert out.n_strokes == 4 and not out.closed.any()
    assert im.arc_lengths(out)[1].sum() == pytest.approx(im.arc_lengths(ell)[1].sum(), rel=1e-9)
    for h in range(4):
        centre, axes, angle, _ = conic[out.fid[h]]
        minor = np.array([-math.sin(angle), math.cos(angle)])
        side = (out.pts[out.start[h]:out.start[h + 1]] - centre) @ minor
        assert side.min() > -0.05 or side.max() < 0.05  # each half on one side of the major axis


def _epipolar_disagreement(path: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Angles (deg) between the true epipolar curve's tangent and, first, stereo_mismatch's band direction, then the
    pinhole epipolar line (the band's direction before it followed curves), at a 60 x 45 grid of pixels of the
    first pose's left camera, brute force: each pixel's own ray (the lens's unprojection) moved a little either
    way along the baseline, projected through the lens; and the pixels' distances from the principal point."""
    from wiredsl.effects.stereo_mismatch import curve_directions, epipolar_directions, lens_of
    from wiredsl.engine import geometry

    scene, _, _ = compile_file(path)
    run = Run.create(scene, build_world(scene), None, 1, Options())
    e = run.epipole(scene.path.pose(0), "left")
    cam = scene.camera(scene.rig.left.camera)
    K = np.array([[cam.f * cam.ax, 0, cam.cx], [0, cam.f * cam.ay, cam.cy], [0, 0, 1.0]])
    X = np.linalg.solve(K, e)  # the right camera's centre, in the left camera's frame (up to a positive scale)
    u, v = np.meshgrid(np.linspace(10, cam.width - 10, 60), np.linspace(10, cam.height - 10, 45))
    rays, ok = geometry.pixels_to_rays(np.column_stack([u.ravel(), v.ravel()]), cam)
    uv = np.column_stack([u.ravel(), v.ravel()])[ok]
    g = geometry.camera_table(cam)
    true = geometry.project(rays[ok] + 1e-6 * X, g) - geometry.project(rays[ok] - 1e-6 * X, g)
    c = Context(pose=0, side="left", trials=np.array([0]), seed=1, stats=Stats(), camera=cam)
    angles = []
    for d in (curve_directions(uv, e, lens_of(c, np.zeros(len(uv), int))), epipolar_directions(uv, e)):
        cross = np.abs(true[:, 0] * d[:, 1] - true[:, 1] * d[:, 0])
        angles.append(np.degrees(np.arctan2(cross, np.abs((true * d).sum(axis=1)))))
    return angles[0], angles[1], np.hypot(uv[:, 0] - cam.cx, uv[:, 1] - cam.cy)


def test_the_epipolar_band_follows_the_curve_and_the_documented_figures_hold(tmp_path):
    """The band's direction agrees with the brute-force tangent everywhere (an undistorted lab, the lab's mild
    barrel distortion, scenes/fisheye.wd); docs/explanation/uncertainty.md's figures of how far the pinhole line
    (what the band was before it followed curves) is from it on the fisheye hold."""
    import shutil

    shutil.copytree("scenes", tmp_path / "scenes")  # with its includes and calibration files
    pinhole = tmp_path / "scenes" / "lab.wd"
    pinhole.write_text(pinhole.read_text().replace("  k 0.02\n", "").replace("  k 0.018\n", ""))
    band, line, _ = _epipolar_disagreement(str(pinhole))
    assert band.max() < 1e-4 and line.max() < 1e-4
    band, line, _ = _epipolar_disagreement("scenes/lab.wd")  # its mild barrel distortion: half a degree at most
    assert band.max() < 1e-4 and 0.1 < line.max() < 0.6
    band, line, r = _epipolar_disagreement("scenes/fisheye.wd")
    assert band.max() < 1e-4
    text = Path("docs/explanation/uncertainty.md").read_text()
    assert f"within {line[r < 100].max():.1f} deg" in text and f"by {np.median(line):.1f} deg at the median" in text
    assert f"band at {np.mean(line > 5):.0%} of the pixels" in text


@pytest.mark.parametrize("pack", [True, False])
def test_exact_calibration_gives_the_stages_the_nominal_cameras_as_the_fast_path_does(monkeypatch, pack):
    """Under calibration error, the image stages see each view's nominal camera (Context.view_cameras: what the
    software believes), on the fast path and on the exact reference alike; the exact path gave them trial 0's
    perturbed camera."""
    from wiredsl.effects import stereo_mismatch

    seen = {}
    disturb = stereo_mismatch.StereoMismatch.disturb

    def spy(params, sets, ctx):
        cams, which = ctx.view_cameras(np.arange(len(ctx.trials)))
        seen.setdefault(exact, []).extend(cams[i] for i in np.unique(which))
        return disturb(params, sets, ctx)

    monkeypatch.setattr(stereo_mismatch.StereoMismatch, "disturb", staticmethod(spy))
    for exact in (False, True):
        run, _ = run_pipeline("calibration_error sigma 0.05\nstereo_mismatch fraction 10%", trials=0,
                              engine="numpy")
        run.exact_calibration, run.pack = exact, pack
        [_ for _ in run.batches(list(range(4)))]
    nominal = {LAB.camera(getattr(LAB.rig, side).camera) for side in ("left", "right")}
    assert seen[True] and all(c in nominal for c in seen[True] + seen[False])
