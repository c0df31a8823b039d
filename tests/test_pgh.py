"""Pairwise geometric histograms: invariances, a case computed by hand, a brute-force sampling oracle,
the Bhattacharyya coefficient against OpenCV's distance, and recognition of the lab's ideal views."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from wiredsl.engine.simulate import Options
from wiredsl.engine.trials import to_imageset
from wiredsl.engine.world import build_world
from wiredsl.language.compile import compile_file
from wiredsl.measures.base import segments
from wiredsl.measures.pgh import (
    PGH,
    PGHParams,
    angle_bins,
    bhattacharyya,
    flat,
    histograms,
    raw_histograms,
    roots,
    transfer_angle,
    transfer_dist,
)
from wiredsl.montecarlo import Run

LAB, _, _ = compile_file("scenes/lab.wd")
WORLD = build_world(LAB)
MODES = [PGHParams(), PGHParams(directed=True), PGHParams(blur_angle=0.05, blur_dist=2.0),
         PGHParams(directed=True, blur_angle=0.1, blur_dist=4.0, n_angle=7, n_dist=9, d_max=60)]


def random_segments(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 300, (n, 2))
    return np.stack([a, a + rng.normal(0, 40, (n, 2))], axis=1)


def rotate(segs: np.ndarray, angle: float, shift) -> np.ndarray:
    R = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    return segs @ R.T + np.asarray(shift)


@pytest.mark.parametrize("engine", ["numpy", "numba"])
@pytest.mark.parametrize("p", MODES)
def test_rotation_and_translation_change_nothing(p, engine):
    segs = random_segments(40, 1)
    h = histograms(segs, p, engine=engine)
    rng = np.random.default_rng(2)
    for _ in range(5):
        g = histograms(rotate(segs, rng.uniform(-math.pi, math.pi), rng.uniform(-500, 500, 2)), p, engine=engine)
        assert np.abs(g - h).max() < 1e-9
        assert np.abs(np.diag(bhattacharyya(h, g)) - 1).max() < 1e-9


@pytest.mark.parametrize("engine", ["numpy", "numba"])
@pytest.mark.parametrize("p", MODES)
def test_fragmentation_changes_nothing(p, engine):
    """Every segment cut into 1-4 pieces: each piece has its whole segment's histogram."""
    segs = random_segments(30, 3)
    rng = np.random.default_rng(4)
    pieces, owner = [], []
    for k, (a, b) in enumerate(segs):
        cuts = np.sort(np.concatenate([[0.0, 1.0], rng.uniform(0, 1, rng.integers(0, 4))]))
        for t0, t1 in zip(cuts[:-1], cuts[1:], strict=True):
            pieces.append([a + t0 * (b - a), a + t1 * (b - a)])
            owner.append(k)
    h = histograms(segs, p, engine=engine)
    g = histograms(np.array(pieces), p, engine=engine)
    assert len(pieces) > len(segs)
    assert np.abs(g - h[owner]).max() < 1e-9
    assert np.abs(np.einsum("ij,ij->i", np.sqrt(g.reshape(len(g), -1)), np.sqrt(h[owner].reshape(len(g), -1)))
                  - 1).max() < 1e-9


def test_a_mirror_image_matches_only_in_the_mirror_symmetric_mode():
    segs = random_segments(25, 5)
    mirrored = segs * np.array([-1.0, 1.0])
    for p in (PGHParams(), PGHParams(blur_angle=0.1, blur_dist=3)):
        assert np.abs(np.diag(bhattacharyya(histograms(segs, p), histograms(mirrored, p))) - 1).max() < 1e-9
    p = PGHParams(directed=True)
    scores = np.diag(bhattacharyya(histograms(segs, p), histograms(mirrored, p)))
    assert scores.max() <= 1 + 1e-12 and scores.mean() < 0.9


@pytest.mark.parametrize("engine", ["numpy", "numba"])
def test_a_small_case_computed_by_hand(engine):
    """Reference r (0,0)-(10,0); v (0,5)-(0,25) perpendicular, 5..25 px away; c (3,-4)-(3,6) crossing r.
    d_max 30 px in 6 bins of 5 px; angle steps of 10 deg (bin 9 is 90 deg)."""
    p = PGHParams(d_max=30, n_dist=6, n_angle=18)
    segs = np.array([[[0, 0], [10, 0]], [[0, 5], [0, 25]], [[3, -4], [3, 6]]], dtype=float)
    h = histograms(segs, p, engine=engine) * 40.0  # total length 10 + 20 + 10 = 40, all within 30 px of r's line
    expect = np.zeros((19, 6))
    expect[0, 0] = 10  # r itself
    expect[9, 1:5] = 5  # v: 5 px of it in each of [5,10) [10,15) [15,20) [20,25)
    expect[9, 0] = 4 + 5  # c folded at r's line: [0,4] from below, [0,6] from above -> 9 in [0,5), 1 in [5,10)
    expect[9, 1] += 1
    assert np.abs(h[0] - expect).max() < 1e-12
    # v as the reference (direction +y): r and c lie 0..10 and 3 px away, at -90 deg and 0 deg
    h = histograms(segs, p, engine=engine)[1] * 40.0
    expect = np.zeros((19, 6))
    expect[0, 0] = 20  # v itself
    expect[9, 0], expect[9, 1] = 5, 5  # r spans 0..10 px
    expect[0, 0] += 10  # c: parallel to v, 3 px away
    assert np.abs(h - expect).max() < 1e-12
    # directed: from r to v is +90 deg (bin 9 of 36), from v to r -90 deg (bin 27)
    hd = histograms(segs, PGHParams(d_max=30, n_dist=6, n_angle=18, directed=True), engine=engine) * 40.0
    assert hd[0, 9].sum() == pytest.approx(30) and hd[1, 27].sum() == pytest.approx(10)
    # 20 px of d_max: what lies beyond is left out, then the rest normalised
    h = histograms(segs, PGHParams(d_max=20, n_dist=4, n_angle=18), engine=engine)[0]
    assert h[9, 3] == pytest.approx(5 / 35) and h[0, 0] == pytest.approx(10 / 35)


def sampled(segs: np.ndarray, p: PGHParams, k: int = 4000) -> np.ndarray:
    """The histograms by brute force: every segment as k points carrying length / k each."""
    out = np.zeros((len(segs), angle_bins(p), p.n_dist))
    t = (np.arange(k) + 0.5) / k
    for i, (a, b) in enumerate(segs):
        u = (b - a) / np.linalg.norm(b - a)
        n = np.array([-u[1], u[0]])
        for c, d in segs:
            v = (d - c) / np.linalg.norm(d - c)
            theta = math.atan2(u[0] * v[1] - u[1] * v[0], u @ v)
            step = math.pi / p.n_angle
            row = round(theta / step) % (2 * p.n_angle) if p.directed else round(abs(theta) / step)
            dist = np.abs((c + t[:, None] * (d - c) - a) @ n)
            hist, _ = np.histogram(dist, bins=p.n_dist, range=(0, p.d_max))
            out[i, row] += hist * np.linalg.norm(d - c) / k
    return out / out.sum(axis=(1, 2), keepdims=True)


@pytest.mark.parametrize("engine", ["numpy", "numba"])
@pytest.mark.parametrize("p", [PGHParams(), PGHParams(directed=True, n_angle=18, n_dist=20, d_max=80)])
def test_histograms_agree_with_brute_force_sampling(p, engine):
    segs = random_segments(12, 7)
    assert np.abs(histograms(segs, p, engine=engine) - sampled(segs, p)).max() < 2e-3


@pytest.mark.parametrize("p", MODES)
def test_the_compiled_pair_loop_agrees_with_numpy(p):
    """Many groups of random segments, and the lab's views: the same sums to rounding."""
    rng = np.random.default_rng(11)
    segs = random_segments(600, 12)
    segs[::7, 1] = segs[::7, 0] + [5.0, 0.0]  # parallel pieces, which are point masses
    group = rng.integers(0, 9, 600)
    raw = {e: raw_histograms(segs[:, 0], segs[:, 1], group, p, e) for e in ("numpy", "numba")}
    assert np.abs(raw["numpy"] - raw["numba"]).max() < 1e-9 * raw["numpy"].max()
    run = lab_run()
    for result in run.ideal():
        s = segments(to_imageset(result.left, WORLD))
        ab = np.stack([s["a"], s["b"]], axis=1)
        assert np.abs(histograms(ab, p, engine="numpy") - histograms(ab, p, engine="numba")).max() < 1e-12


@pytest.mark.parametrize("p", [*MODES, PGHParams(n_dist=30, n_angle=36), PGHParams(n_dist=3, n_angle=1)])
def test_the_fused_roots_are_the_numpy_normalisation_of_the_compiled_histograms_to_the_last_bit(p):
    """`roots` (histograms, totals by numpy's pairwise sum, division and sqrt in one compiled pass) against
    np.sqrt(flat(histograms(engine="numba"))), bit for bit: groups in any order, empty histograms (total 0) and
    bin counts below and above numpy's 8 and 128 summation blocks (13 x 10, 37 x 30, 2 x 3 bins)."""
    rng = np.random.default_rng(12)
    segs = random_segments(700, 13)
    segs[::5, 1] = segs[::5, 0] + [4.0, 0.0]
    segs[3] = [[1e6, 1e6], [1e6 + 1.0, 1e6]]  # alone, far beyond d_max of every other: only itself
    group = rng.integers(0, 11, 700)
    fused = roots(segs, p, group=group, engine="numba")
    assert np.array_equal(fused, np.sqrt(flat(histograms(segs, p, group=group, engine="numba"))))
    assert np.array_equal(roots(segs[:0], p), np.zeros((0, flat(histograms(segs[:1], p)).shape[1])))
    blurred = p.model_copy(update={"blur_angle": 0.05})  # with a blur: the unfused path
    assert np.array_equal(roots(segs, blurred, group=group), np.sqrt(flat(histograms(segs, blurred, group=group))))


def test_the_kernels_pairwise_sum_is_numpys_to_the_last_bit():
    """The fused roots' totals: numpy's own summation order (blocks of 8 partial sums, halves above 128)."""
    from wiredsl.measures import pgh_kernel

    rng = np.random.default_rng(3)
    for n in (0, 1, 7, 8, 9, 127, 128, 129, 130, 257, 1000, 4097, 100_000):
        for _ in range(5):
            a = rng.random(n) * 10 ** rng.uniform(-8, 8, n)
            assert 0.0 + pgh_kernel._pairwise_sum(a, 0, n) == a.sum()


def test_a_segment_without_length_is_refused():
    with pytest.raises(ValueError, match="positive"):
        histograms(np.array([[[0, 0], [10, 0]], [[3, 3], [3, 3]]], dtype=float), PGHParams())


@pytest.mark.parametrize("engine", ["numpy", "numba"])
def test_groups_see_only_their_own_segments(engine):
    segs = random_segments(30, 8)
    group = np.random.default_rng(9).integers(0, 4, 30)
    h = histograms(segs, PGHParams(), group=group, engine=engine)
    for g in range(4):
        assert np.abs(h[group == g] - histograms(segs[group == g], PGHParams(), engine=engine)).max() < 1e-15


def test_blur_keeps_mass_except_beyond_d_max():
    p = PGHParams(blur_angle=0.2, blur_dist=6.0)
    for directed in (False, True):
        assert np.allclose(transfer_angle(p.model_copy(update={"directed": directed})).sum(axis=1), 1.0)
    rows = transfer_dist(p).sum(axis=1)
    assert np.allclose(rows[:5], 1.0) and rows[-1] < 0.9  # the last bin's Gaussian crosses d_max


def test_bhattacharyya_is_the_coefficient_opencv_turns_into_a_distance():
    """OpenCV's HISTCMP_BHATTACHARYYA is sqrt(1 - BC) for histograms that sum to 1."""
    rng = np.random.default_rng(10)
    h = rng.dirichlet(np.full(60, 0.3), size=8)
    bc = bhattacharyya(h, h)
    assert np.allclose(np.diag(bc), 1.0) and np.allclose(bc, bc.T) and (bc <= 1 + 1e-12).all()
    for i in range(8):
        for j in range(8):
            d = cv2.compareHist(h[i].astype(np.float32), h[j].astype(np.float32), cv2.HISTCMP_BHATTACHARYYA)
            assert bc[i, j] == pytest.approx(1 - d * d, abs=1e-5)
    disjoint = np.zeros((2, 4))
    disjoint[0, :2] = disjoint[1, 2:] = 0.5
    assert bhattacharyya(disjoint, disjoint)[0, 1] == 0.0


def lab_run(pipeline=None, **options) -> Run:
    return Run.create(LAB, WORLD, pipeline, 0, Options(**options))


def test_ideal_views_are_recognised_perfectly():
    run = lab_run()
    p = PGHParams()
    prep = PGH.prepare(p, run)
    for batch, results in run.batches([0, 1]):
        for result, disturbed, _ in results:
            out = PGH.measure(p, prep, result, disturbed, len(batch))
            assert np.allclose(out["match"], 1.0, atol=1e-9) and np.allclose(out["recognition"], 1.0)


def test_the_robot_on_a_view_point_recognises_it():
    """Poses exactly on view-points: the ideal view is that view-point's database entry, ranked first."""
    points = LAB.viewpoints.points[::7]
    path = LAB.path.model_copy(update={"poses": [(x, y, -0.4) for x, y in points]})
    run = Run.create(LAB.model_copy(update={"path": path}), WORLD, None, 0, Options())
    for p in (PGHParams(), PGHParams(viewpoints=0)):
        prep = PGH.prepare(p, run)
        for _batch, results in run.batches([0]):
            for result, disturbed, _ in results:
                assert PGH.measure(p, prep, result, disturbed, 1)["viewpoint"][0] == 1.0


def test_disturbances_lower_the_scores():
    run = lab_run(LAB.pipeline("edges"), poses=(2,))
    p = PGHParams()
    prep = PGH.prepare(p, run)
    (batch, [(result, disturbed, _)]), = list(run.batches(list(range(8))))
    out = PGH.measure(p, prep, result, disturbed, 8)
    assert 0.3 < out["match"].mean() < 0.99 and out["recognition"].mean() < 1.0


def test_the_compiled_scores_agree_with_the_matrix_products_and_do_not_depend_on_other_trials():
    """pgh_kernel.own_scores and located_scores (a product a trial) against the numpy reference (one BLAS product
    for the whole batch): scores to rounding, the same decisions; and a trial's values are the same measured
    alone as with the others of its batch."""
    from wiredsl.measures import pgh

    run = lab_run(LAB.pipeline("paper"), poses=(2,))
    p = PGHParams()
    prep = PGH.prepare(p, run)
    (batch, [(result, disturbed, _)]), = list(run.batches(list(range(12))))
    seg = segments(disturbed["left"])
    root = np.sqrt(pgh.flat(histograms(np.stack([seg["a"], seg["b"]], axis=1), p, group=seg["trial"])))
    ref, db = prep.views[(result.index, "left")], prep.databases[(result.index, "left")]
    key = pgh.source_key(seg["fid"], seg["segment"])
    groups = pgh.by_trial(seg["trial"])
    own, recog = pgh._own_scores(root, key, ref, groups)
    own_np, recog_np = pgh._own_scores(root, key, ref)
    assert 0.3 < own.mean() < 1 and np.allclose(own, own_np, rtol=0, atol=1e-13)
    assert np.array_equal(recog, recog_np)
    located = pgh._located(root, seg["length"], seg["trial"], 12, db, groups)
    assert np.array_equal(located, pgh._located(root, seg["length"], seg["trial"], 12, db))
    assert 0 < located.sum() <= 12
    for t in (0, 5, 11):  # trial t alone, renumbered 0
        rows = seg["trial"] == t
        alone = pgh._own_scores(root[rows], key[rows], ref, pgh.by_trial(np.zeros(rows.sum(), dtype=int)))
        assert np.array_equal(alone[0], own[rows]) and np.array_equal(alone[1], recog[rows])
        one = pgh._located(root[rows], seg["length"][rows], np.zeros(rows.sum(), dtype=int), 1, db,
                           pgh.by_trial(np.zeros(rows.sum(), dtype=int)))
        assert one[0] == located[t]
