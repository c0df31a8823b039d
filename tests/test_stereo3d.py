"""Stereo reconstruction: triangulation and undistortion against OpenCV, and the lab's ideal features
reconstructed to within what the projection tolerance allows."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from wiredsl.engine import geometry
from wiredsl.engine.simulate import Options
from wiredsl.engine.world import build_world
from wiredsl.language.compile import compile_file
from wiredsl.measures.stereo3d import Stereo3D, Stereo3DParams, triangulate, undistort
from wiredsl.montecarlo import Run
from wiredsl.scene import Camera

LAB, _, _ = compile_file("scenes/lab.wd")
WORLD = build_world(LAB)


def random_rig(rng):
    """Two random cameras [R | t] looking at the unit cube around (0, 0, 5)."""
    out = []
    for _ in range(2):
        R, _ = cv2.Rodrigues(rng.normal(0, 0.2, 3))
        centre = rng.normal(0, 0.5, 3)
        out.append(np.column_stack([R, -R @ centre]))
    return out


def noisy_views(rng, n: int, noise: float):
    """A random rig and intrinsics, n points in the cube around (0, 0, 5), and their pixels with Gaussian noise of
    `noise` px: K, P1, P2, X, x1, x2."""
    P1, P2 = random_rig(rng)
    K = np.array([[rng.uniform(300, 900), 0, 320], [0, rng.uniform(300, 900), 240], [0, 0, 1.0]])
    X = rng.uniform(-1, 1, (n, 3)) + [0, 0, 5]
    x1 = (K @ P1 @ np.column_stack([X, np.ones(n)]).T).T
    x2 = (K @ P2 @ np.column_stack([X, np.ones(n)]).T).T
    x1 = x1[:, :2] / x1[:, 2:] + rng.normal(0, noise, (n, 2))
    x2 = x2[:, :2] / x2[:, 2:] + rng.normal(0, noise, (n, 2))
    return K, P1, P2, X, x1, x2


def test_triangulation_agrees_with_opencv_on_random_rigs_and_noisy_points():
    rng = np.random.default_rng(0)
    for _ in range(20):
        K, P1, P2, X, x1, x2 = noisy_views(rng, 50, 2)  # noise: the least-squares solutions must agree
        ours, ok = triangulate(K @ P1, K @ P2, x1, x2)
        h = cv2.triangulatePoints(K @ P1, K @ P2, x1.T.copy(), x2.T.copy())
        theirs = (h[:3] / h[3]).T
        assert ok.all() and np.abs(ours - theirs).max() < 1e-9 * np.abs(theirs).max()
        assert np.abs(ours - X).max() > 1e-3  # the noise did act


def test_exact_points_triangulate_exactly():
    rng = np.random.default_rng(1)
    P1, P2 = random_rig(rng)
    X = rng.uniform(-1, 1, (100, 3)) + [0, 0, 5]
    x1 = X @ P1[:, :3].T + P1[:, 3]
    x2 = X @ P2[:, :3].T + P2[:, 3]
    ours, ok = triangulate(P1, P2, x1[:, :2] / x1[:, 2:], x2[:, :2] / x2[:, 2:])
    assert ok.all() and np.abs(ours - X).max() < 1e-12


@pytest.mark.parametrize("noise", [0.0, 1.0, 30.0, 300.0])
def test_compiled_triangulation_is_the_svds_point_to_rounding_against_opencv_and_mpmath(noise):
    """The numba engine (inverse iteration, Jacobi where it does not converge: large noise makes sigma_4 close to
    sigma_3) against LAPACK's SVD (the numpy engine), OpenCV, and mpmath's 50-digit SVD for the worst points."""
    mpmath = pytest.importorskip("mpmath")
    rng = np.random.default_rng(7)
    for _ in range(10):
        K, P1, P2, X, x1, x2 = noisy_views(rng, 200, noise)
        fast, ok_fast = triangulate(K @ P1, K @ P2, x1, x2, engine="numba")
        ref, ok_ref = triangulate(K @ P1, K @ P2, x1, x2, engine="numpy")
        h = cv2.triangulatePoints(K @ P1, K @ P2, x1.T.copy(), x2.T.copy())
        cv = (h[:3] / h[3]).T
        assert (ok_fast == ok_ref).all()
        rel = np.abs(fast - ref).max(axis=1) / np.abs(ref).max(axis=1)
        assert rel[ok_ref].max() < 1e-10, rel.max()
        assert (np.abs(fast - cv).max(axis=1) / np.abs(cv).max(axis=1))[ok_ref].max() < 1e-9
        i = int(np.argmax(np.where(ok_ref, rel, 0)))  # the worst point, against 50 digits
        A = np.stack([x1[i, 0] * (K @ P1)[2] - (K @ P1)[0], x1[i, 1] * (K @ P1)[2] - (K @ P1)[1],
                      x2[i, 0] * (K @ P2)[2] - (K @ P2)[0], x2[i, 1] * (K @ P2)[2] - (K @ P2)[1]])
        with mpmath.workdps(50):
            V = mpmath.svd_r(mpmath.matrix(A.tolist()))[2]
            exact = np.array([float(V[3, c] / V[3, 3]) for c in range(3)])
        assert np.abs(fast[i] - exact).max() <= max(1e-10 * np.abs(exact).max(), 2 * np.abs(ref[i] - exact).max())


def test_compiled_triangulation_of_degenerate_rows_gives_no_nan():
    """Exactly singular rows (a point on the baseline, both rays the same line) and zero rows: a finite point or
    none, never a NaN."""
    P1 = np.column_stack([np.eye(3), np.zeros(3)])
    P2 = np.column_stack([np.eye(3), [-1.0, 0, 0]])
    x = np.array([[0.0, 0.0], [1e-300, 0.0], [np.inf, 0.0]])
    for engine in ("numba", "numpy"):
        X, ok = triangulate(P1, P2, x[:2], x[:2], engine=engine)
        assert np.isfinite(X).all() and X.shape == (2, 3)
    X, ok = triangulate(P1, P2, x[2:], x[2:], engine="numba")
    assert np.isfinite(X).all() and not ok.any()


def test_undistortion_agrees_with_opencv():
    rng = np.random.default_rng(2)
    for _ in range(20):
        cam = Camera(name="c", f=rng.uniform(400, 900), ax=rng.uniform(0.9, 1.1), ay=rng.uniform(0.9, 1.1),
                     cx=320, cy=240, k1=rng.uniform(-0.3, 0.3), k2=rng.uniform(-0.05, 0.05),
                     p1=rng.uniform(-0.01, 0.01), p2=rng.uniform(-0.01, 0.01), width=640, height=480)
        xy = rng.uniform(-0.4, 0.4, (200, 2))
        xy = xy[np.hypot(*xy.T) < 0.7 * geometry.fold_radius(cam.k1, cam.k2)]
        uv = geometry.plane_to_pixels(geometry.distort(xy, cam.k1, cam.k2, cam.p1, cam.p2),
                                      cam.f, cam.ax, cam.ay, cam.cx, cam.cy)
        ours, ok = undistort(uv, cam)
        K = np.array([[cam.f * cam.ax, 0, cam.cx], [0, cam.f * cam.ay, cam.cy], [0, 0, 1.0]])
        dist = np.array([cam.k1, cam.k2, cam.p1, cam.p2])
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-16)
        theirs = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, dist, None, None, None, criteria).reshape(-1, 2)
        assert ok.all()
        assert np.abs(ours - xy).max() < 1e-11  # the exact inverse
        assert np.abs(ours - theirs).max() < 1e-8  # OpenCV's fixed-point iteration, to its convergence


def measure_all(run: Run, trials: list[int]) -> list[dict]:
    p = Stereo3DParams()
    prep = Stereo3D.prepare(p, run)
    out = []
    for batch, results in run.batches(trials):
        for result, disturbed, _ in results:
            out.append(Stereo3D.measure(p, prep, result, disturbed, len(batch)))
    return out


def test_compiled_undistortion_equals_the_numpy_reference_to_the_last_bit():
    """The numba engine runs numpy's operations in numpy's order, point by point: the same bits, the same points
    kept, on random rational lenses (tangential and denominator terms too) and on pixels far outside the image,
    where Newton's method diverges or lands past the fold radius."""
    pytest.importorskip("numba")
    rng = np.random.default_rng(3)
    refused = 0
    for t in range(60):
        lens = dict(k1=rng.uniform(-0.5, 0.5), k2=rng.uniform(-0.2, 0.2), p1=rng.uniform(-0.01, 0.01),
                    p2=rng.uniform(-0.01, 0.01))
        if t % 2:
            lens.update(k3=rng.uniform(-0.1, 0.1), k4=rng.uniform(-0.1, 0.1), k5=rng.uniform(-0.05, 0.05),
                        k6=rng.uniform(-0.05, 0.05))
        cam = Camera(name="c", f=600, cx=320, cy=240, width=640, height=480, **lens)
        uv = rng.uniform(-600, 1300, (400, 2))
        ref, ok_ref = undistort(uv, cam, engine="numpy")
        got, ok = undistort(uv, cam, engine="numba")
        assert np.array_equal(ok, ok_ref) and np.array_equal(got.view(np.int64), ref.view(np.int64))
        refused += int((~ok).sum())
    assert refused > 0  # the refusals were exercised too


@pytest.mark.parametrize("tolerance", [1e-2, 1e-4])
def test_ideal_features_are_reconstructed_within_the_projection_tolerance(tolerance):
    """Line end points sit on the emitted polylines, which stay within `tolerance` px of the true curves:
    the 3D error shrinks with it; corners are exact."""
    for out in measure_all(Run.create(LAB, WORLD, None, 0, Options(tolerance=tolerance, poses=(0, 3, 6))), [0]):
        assert out["corners"][0] > 0 and out["corner_error"][0] < 1e-12
        assert out["line_points"][0] >= 4 and out["error_rms"][0] < 3.0 * tolerance
        assert out["outliers"][0] == 0


def test_edge_loss_fragments_still_lie_on_their_lines():
    """Fragments end anywhere along a line; matched along epipolar lines they still reconstruct onto it."""
    from helpers import compile_text

    scene, _ = compile_text("wiredsl 1\npipeline p {\n  edge_loss fraction 40%\n}\n")
    run = Run.create(LAB, WORLD, scene.pipelines[0], 3, Options(tolerance=1e-4, poses=(1, 4)))
    outs = measure_all(run, list(range(4)))
    assert sum(o["line_points"].sum() for o in outs) > 100
    assert max(o["line_error"].max() for o in outs) < 1e-3


def test_corner_mismatch_and_calibration_error_are_seen_in_3d():
    from helpers import compile_text

    scene, _ = compile_text("wiredsl 1\npipeline p {\n  calibration_error sigma 1\n  corner_mismatch fraction 50%\n}\n")
    outs = measure_all(Run.create(LAB, WORLD, scene.pipelines[0], 3, Options()), list(range(6)))
    errs = np.concatenate([o["corner_error"][o["corners"] > 0] for o in outs])
    assert errs.mean() > 0.01
    for o in outs:
        assert all(np.isfinite(v).all() for v in o.values())
        assert ((o["outliers"] >= 0) & (o["outliers"] <= 1)).all()


def test_line_end_points_near_the_epipolar_direction_are_not_reconstructed():
    run = Run.create(LAB, WORLD, None, 0, Options(poses=(2,)))
    prep_wide = Stereo3D.prepare(Stereo3DParams(band=math.radians(89.9)), run)
    prep = Stereo3D.prepare(Stereo3DParams(band=0.0), run)
    (batch, [(result, disturbed, _)]), = list(run.batches([0]))
    wide = Stereo3D.measure(Stereo3DParams(band=math.radians(89.9)), prep_wide, result, disturbed, 1)
    none = Stereo3D.measure(Stereo3DParams(band=0.0), prep, result, disturbed, 1)
    assert wide["line_points"][0] == 0 and wide["corners"][0] == none["corners"][0] > 0
    assert none["line_points"][0] >= Stereo3D.measure(Stereo3DParams(), prep, result, disturbed, 1)["line_points"][0]
