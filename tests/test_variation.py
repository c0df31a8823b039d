"""Magnitudes that vary between views and fates that persist along a path (issue 34, item 2): the declared
distributions against scipy.stats, the persistence against the AR(1) autocorrelation exp(-d / correlation),
replay (a trial alone, a pose alone), both engines bit for bit, and the language's clauses and errors."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import compile_text, errors_of
from scipy import stats

from wiredsl.effects import variation as var
from wiredsl.effects.base import stream_key
from wiredsl.engine.simulate import Options
from wiredsl.engine.world import build_world
from wiredsl.language.compile import compile_file
from wiredsl.montecarlo import Run
from wiredsl.scene import Path, Pipeline, Stage

FENCE = "tests/data/verify/fence.wd"
STEP = 0.05  # m between the test path's poses


def _scene(poses: int = 12):
    scene = compile_file(FENCE)[0]
    return scene.model_copy(update={"path": Path(name="p", poses=[[STEP * i, 0.0, 0.0] for i in range(poses)])})


def _keys(n: int, stage: str = "edge_loss") -> np.ndarray:
    return stream_key(stage, np.arange(n), 3, 0, 11)


@pytest.mark.parametrize(("value", "spread", "kind"), [(0.29, 0.06, "fraction"), (0.85, 0.1, "fraction"),
                                                       (0.05, 0.1, "fraction"), (2.0, 0.5, "image"),
                                                       (1.0, 2.0, "image")])
def test_view_magnitudes_follow_the_declared_beta_or_gamma(value, spread, kind):
    """KS against scipy.stats (an independent sampler's law): a Beta of that mean and sd for a fraction, a Gamma for
    a magnitude (shape 0.25 in the last case: the boosted branch)."""
    x = var.magnitude(_keys(4000), value, spread, kind)
    if kind == "fraction":
        a, b = var.beta_shapes(value, spread)
        law = stats.beta(a, b)
        assert ((x >= 0) & (x <= 1)).all()
    else:
        law = stats.gamma(value**2 / spread**2, scale=spread**2 / value)
        assert (x >= 0).all()
    assert stats.kstest(x, law.cdf).pvalue > 1e-3
    assert x.mean() == pytest.approx(value, abs=4 * spread / np.sqrt(4000))
    assert x.std() == pytest.approx(spread, rel=0.1)


def test_the_kernel_draws_the_same_magnitudes_and_persistent_uniforms_bit_for_bit():
    from wiredsl.effects import variation_kernel as vk

    keys = _keys(500)
    for value, spread, kind in ((0.29, 0.06, "fraction"), (1.0, 2.0, "image"), (3.0, 0.4, "image")):
        got = np.array([vk.magnitude(k, value, spread, kind == "fraction") for k in keys])
        assert np.array_equal(got, var.magnitude(keys, value, spread, kind))
    rho = var.persistence(np.arange(20) * STEP, 0.2)
    items = np.arange(500) * 16 + 3
    poses = np.arange(500) % 25  # some beyond the path's 20 poses: they renew at themselves
    want = var.keyed_uniform(var.value_keys(keys, items, poses, rho), items.astype(np.uint64) + np.uint64(var.VAL))
    padded = np.concatenate([rho, np.zeros(7)])  # as the kernel's zero-padded rows hold it
    got = np.array([vk.item_uniform(k, i, p, padded) for k, i, p in zip(keys, items, poses, strict=True)])
    assert np.array_equal(got, want)


def _run(pipe, scene, engine="numpy", seed=5, trials=range(0, 48), size=16):
    run = Run.create(scene, build_world(scene), pipe, seed, Options())
    run.engine = engine
    return run, [out for _, out in run.batches(trials, size)]


def test_edge_loss_removes_each_views_drawn_fraction_from_the_declared_beta():
    scene = _scene(3)
    pipe = Pipeline(name="v", stages=[Stage(effect="edge_loss", params={"fraction": 0.3, "spread": 0.08})])
    run = Run.create(scene, build_world(scene), pipe, 5, Options())
    ideal = {r.index: r for r in run.ideal()}
    removed = []
    for _, out in run.batches(range(400), 100):
        for r, disturbed, _ in out:
            L0 = _length(run.template(ideal[r.index], "left", raw=False)[0])
            s = disturbed["left"]
            for t in np.unique(s.trial):
                removed.append(1 - _length(s.take(s.trial == t)) / L0)
    a, b = var.beta_shapes(0.3, 0.08)
    assert stats.kstest(np.array(removed), stats.beta(a, b).cdf).pvalue > 1e-3
    assert np.std(removed) > 0.06  # not the fixed fraction's zero spread


def test_edge_loss_draws_each_features_fraction_from_a_beta_about_its_views():
    scene = _scene(2)
    pipe = Pipeline(name="v", stages=[Stage(effect="edge_loss", params={"fraction": 0.3, "feature_spread": 0.1})])
    run = Run.create(scene, build_world(scene), pipe, 5, Options())
    ideal = {r.index: r for r in run.ideal()}
    removed = []
    for _, out in run.batches(range(100), 100):
        for r, disturbed, _ in out:
            t0 = run.template(ideal[r.index], "left", raw=False)[0]
            L0 = dict(zip(t0.fid.tolist(), _lengths(t0), strict=True))
            s = disturbed["left"]
            for t in np.unique(s.trial):
                one = s.take(s.trial == t)
                kept = np.bincount(one.fid, weights=_lengths(one), minlength=max(L0) + 1)
                removed += [1 - kept[f] / L for f, L in L0.items()]
    a, b = var.beta_shapes(0.3, 0.1)
    assert stats.kstest(np.array(removed), stats.beta(a, b).cdf).pvalue > 1e-3


def _lengths(s) -> np.ndarray:
    from wiredsl.engine import imageset as im

    return im.arc_lengths(s)[1]


def _length(s) -> float:
    from wiredsl.engine import imageset as im

    return float(im.arc_lengths(s)[1].sum())


def test_a_corners_fate_persists_along_the_path_with_the_ar1_autocorrelation():
    """Kept or not, per corner and trial along 12 poses 5 cm apart, correlation 20 cm: the indicator's
    correlation at lag j is exp(-j 5 / 20) (the AR(1) formula), and without a correlation it is 0."""
    scene = _scene(12)
    for corr in (0.2, 0.0):
        pipe = Pipeline(name="v", stages=[Stage(effect="corner_loss", params={"keep": 0.6, "correlation": corr})])
        _, got = _run(pipe, scene, trials=range(200), size=200)  # one batch: batch index = trial
        kept = {}  # (trial, fid) -> [kept at pose 0..11]
        for out in got:
            for r, disturbed, _ in out:
                s = disturbed["left"]
                view = r.left
                for t in range(int(s.corner_trial.max(initial=-1)) + 1):
                    found = set(s.corner_fid[s.corner_trial == t].tolist())
                    for f in np.asarray(view.corner_fid).tolist():
                        kept.setdefault((t, f), {})[r.index] = f in found
        series = np.array([[v[p] for p in range(12)] for v in kept.values() if len(v) == 12], dtype=float)
        assert len(series) > 1000
        for lag in (1, 2, 4):
            r_ = np.corrcoef(series[:, :-lag].ravel(), series[:, lag:].ravel())[0, 1]
            want = np.exp(-lag * STEP / corr) if corr else 0.0
            assert r_ == pytest.approx(want, abs=0.05), (corr, lag, r_)
        assert series.mean() == pytest.approx(0.6, abs=0.02)


VARIED = Pipeline(name="v", stages=[
    Stage(effect="edge_loss", params={"fraction": 0.3, "spread": 0.1, "correlation": 0.2, "feature_spread": 0.1}),
    Stage(effect="lateral_shift", params={"range": 2.0, "spread": 0.5, "correlation": 0.15}),
    Stage(effect="corner_loss", params={"keep": 0.8, "spread": 0.1})])


@pytest.mark.parametrize("pipe", [VARIED, Pipeline(name="w", stages=[
    Stage(effect="edge_loss", params={"fraction": 0.3, "feature_spread": 0.15}),
    Stage(effect="lateral_shift", params={"range": 1.0, "spread": 1.5}),
    Stage(effect="corner_error", params={"sigma": 0.5, "spread": 0.3})])], ids=["along the path", "per view"])
def test_both_engines_agree_with_spreads_and_correlations(pipe):
    scene = _scene(6)
    outs = {e: _run(pipe, scene, e, trials=range(30, 62))[1] for e in ("numpy", "kernel")}
    n = 0
    for bn, bk in zip(outs["numpy"], outs["kernel"], strict=True):
        for (_, dn, _), (_, dk, _) in zip(bn, bk, strict=True):
            for side, a in dn.items():
                b = dk[side]
                for name in ("start", "fid", "fragment", "trial", "corner_fid", "corner_trial"):
                    assert np.array_equal(getattr(a, name), getattr(b, name)), (side, name)
                for name in ("pts", "corners"):  # to rounding, as tests/test_kernel.py holds the engines
                    assert np.abs(getattr(a, name) - getattr(b, name)).max(initial=0) < 1e-9, (side, name)
                n += a.n_strokes
    assert n > 0


@pytest.mark.parametrize("engine", ["numpy", "kernel"])
def test_a_trial_and_a_pose_replay_alone(engine):
    scene = _scene(6)
    run, full = _run(VARIED, scene, engine, trials=range(40, 56))
    at = {(r.index, int(t)): (d, k) for out in full for r, d, _ in out for k, t in enumerate(range(40, 56))}
    alone = Run.create(scene, build_world(scene), VARIED, 5, Options())
    alone.engine = engine
    ideal = alone.ideal()
    for pose, trial in ((4, 47), (0, 40), (5, 55)):
        _, disturbed, _ = alone.observe(ideal[pose], [trial])
        d, k = at[(pose, trial)]
        a, b = disturbed["left"], d["left"]
        b = b.take(b.trial == k).take_corners(b.corner_trial == k)
        assert np.array_equal(a.pts, b.pts) and np.array_equal(a.corner_fid, b.corner_fid)


def test_a_stage_without_spread_or_correlation_draws_as_before():
    scene = _scene(4)
    plain = Pipeline(name="a", stages=[Stage(effect="edge_loss", params={"fraction": 0.3}),
                                       Stage(effect="corner_loss", params={"keep": 0.8})])
    zero = Pipeline(name="b", stages=[Stage(effect="edge_loss", params={"fraction": 0.3, "spread": 0.0}),
                                      Stage(effect="corner_loss", params={"keep": 0.8, "correlation": 0.0})])
    (_, a), (_, b) = _run(plain, scene), _run(zero, scene)
    for x, y in zip(a, b, strict=True):
        for (_, dx, _), (_, dy, _) in zip(x, y, strict=True):
            assert np.array_equal(dx["left"].pts, dy["left"].pts)
    scene, _ = compile_text(open(FENCE).read())  # the compiled scene lists neither while 0
    assert scene.pipeline("injected").stages[0].params == {"fraction": 0.25}


def test_the_language_takes_spread_and_correlation_and_refuses_a_spread_too_wide():
    text = open(FENCE).read().replace("edge_loss fraction 25%", "edge_loss fraction 29% spread 6% correlation 0.5m")
    scene, _ = compile_text(text)
    st = scene.pipeline("injected").stages[0]
    assert st.params == {"fraction": 0.29, "spread": 0.06, "correlation": 0.5}
    errs = errors_of(open(FENCE).read().replace("edge_loss fraction 25%", "edge_loss fraction 25% spread 45%"))
    assert any("E110" in e and "spread 0.45 of fraction 0.25" in e and e.startswith("60:") for e in errs), errs
