"""Results that do not depend on which CPU (and so which BLAS kernels) computed them: the two places where a
last-bit difference between OpenBLAS's kernels became a visible one (found with OPENBLAS_CORETYPE=SkylakeX and
Sandybridge against Haswell on the lab's npz golden)."""

from __future__ import annotations

import numpy as np
import pytest

from wiredsl.effects import calibration_error as calib
from wiredsl.engine import imageset as im


def _spd_with_a_repeated_eigenvalue(rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    w = np.array([1e-6, 2e-4, 2e-4, 3e-2, 1.0, 4.0])  # a repeated eigenvalue: its vectors are any rotation
    return (Q * w) @ Q.T, w, Q


@pytest.mark.parametrize("kind", ["covariance", "information"])
def test_calibration_draws_do_not_depend_on_the_eigenvectors_lapack_returns(monkeypatch, kind):
    """eigh's vectors are defined up to sign, and up to a rotation within a repeated eigenvalue's space;
    LAPACK's kernels for different CPUs choose differently. The sampler's basis must be the same matrix for
    every such choice (before: V diag(s) changed sign with V, so a seed drew other perturbations on another CPU),
    and still have the declared covariance (sigma^2 M, or sigma^2 M^-1 for an information matrix)."""
    rng = np.random.default_rng(3)
    M, w, Q = _spd_with_a_repeated_eigenvalue(rng)
    p = calib.CalibrationErrorParams(sigma=0.5)
    order = [f"left.p{i}" for i in range(6)]
    c, s = np.cos(0.7), np.sin(0.7)
    other = Q.copy()
    other[:, [1, 2]] = Q[:, [1, 2]] @ np.array([[c, -s], [s, c]])  # another basis of the repeated eigenvalue
    other *= np.array([-1, 1, -1, 1, -1, -1])  # and other signs
    bases = []
    for vectors in (Q, other):
        calib._EIGH.clear()
        monkeypatch.setattr(np.linalg, "eigh", lambda _M, V=vectors: (w.copy(), V.copy()))
        bases.append(calib.sampler(p, kind, M, order).basis)
    calib._EIGH.clear()
    assert np.abs(bases[0] - bases[1]).max() <= 1e-12 * np.abs(bases[0]).max()
    want = 0.25 * (M if kind == "covariance" else np.linalg.inv(M))
    assert np.allclose(bases[0] @ bases[0].T, want, rtol=1e-9, atol=1e-12 * np.abs(want).max())


def _stroke_with_a_copied_end(eps: float) -> im.ImageSet:
    # a vertical stroke whose first vertex has a copy eps px to its right (what a cut leaves at a stroke's end)
    pts = np.array([[10.0, 10.0], [10.0 + eps, 10.0], [10.0, 20.0], [10.0, 30.0]])
    z = np.zeros(1, dtype=int)
    return im.ImageSet(pts=pts, start=np.array([0, 4]), fid=z, segment=z - 1, fragment=z - 1, kind=z,
                       clipped=z.astype(bool), closed=z.astype(bool), trial=z, corners=np.zeros((0, 2)),
                       corner_fid=np.zeros(0, dtype=int), corner_trial=np.zeros(0, dtype=int))


@pytest.mark.parametrize("eps", [0.0, 1e-13, -3e-12, 5e-10])
def test_a_stroke_ends_copy_of_a_vertex_takes_its_strokes_normal(eps):
    """A step shorter than imageset.STEP_PX has no direction: before, its direction was the rounding's (1e-13 px
    to the right gave the first vertex the normal (0, 1) of a horizontal step, on one CPU and not another), and
    lateral_shift moved the stroke's end 0.7 px away from where the rest of the stroke went."""
    n = im.vertex_normals(_stroke_with_a_copied_end(eps))
    assert np.allclose(n, [[-1.0, 0.0]] * 4, atol=1e-9)


def test_the_kernels_lateral_shift_moves_a_copied_end_as_numpy_does():
    pytest.importorskip("numba")
    from wiredsl.effects.lateral_shift_kernel import stage
    from wiredsl.engine.kernel import NMETA, NSTAT

    s = _stroke_with_a_copied_end(1e-13)
    meta = np.zeros((1, NMETA), dtype=np.int64)
    meta[0, 1] = -1  # segment
    meta[0, 2] = -1  # fragment
    key = np.uint64(12345)
    st = np.zeros(NSTAT)
    out = stage(s.pts.copy(), s.start.astype(np.int64), meta, np.zeros((0, 2)), np.zeros(0, dtype=np.int64), key,
                np.array([3.0, 0.0, 0.0]), np.zeros(3), False, st)[0]
    move = out - s.pts
    assert np.abs(move[:, 1]).max() < 1e-12  # every vertex along x only, by the one draw
    assert np.allclose(move[:, 0], move[2, 0], atol=1e-12) and abs(move[2, 0]) > 0
