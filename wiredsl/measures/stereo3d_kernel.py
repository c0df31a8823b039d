"""stereo3d's undistortion compiled with numba: `stereo3d.undistort`'s Newton iterations point by point.

Imported only when numba is installed (the `fast` extra); `stereo3d.undistort_numpy` is the numpy reference
it is tested against. Each point runs the same floating-point operations in the same order as the numpy
path (no fast-math, so no fused multiply-adds), so the results are equal to the last bit; what it saves is
numpy's per-operation overhead on the few dozen points a pose and trial batch has (about 200 array
operations a call).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from wiredsl.engine.kernel import distort_radtan, radtan_jacobian


@njit(cache=True, error_model="numpy")
def undistort_radtan(xd, k1, k2, p1, p2, k3, k4, k5, k6, steps, limit):
    """Undistorted unit-plane points (n, 2) of distorted ones xd (n, 2), and which converged (n,)."""
    n = xd.shape[0]
    out = np.zeros((n, 2))
    ok = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        x0, y0 = xd[i, 0], xd[i, 1]
        x, y = x0, y0
        for _ in range(steps):
            j11, j12, j22 = radtan_jacobian(x, y, k1, k2, p1, p2, k3, k4, k5, k6)
            dx, dy = distort_radtan(x, y, k1, k2, p1, p2, k3, k4, k5, k6)
            r0, r1 = dx - x0, dy - y0
            det = j11 * j22 - j12 * j12
            x, y = x - (j22 * r0 - j12 * r1) / det, y - (j11 * r1 - j12 * r0) / det
        dx, dy = distort_radtan(x, y, k1, k2, p1, p2, k3, k4, k5, k6)
        # both residuals below 1e-12 (numpy's max of the two, a NaN failing either way)
        if math.isfinite(x) and math.isfinite(y) and abs(dx - x0) < 1e-12 and abs(dy - y0) < 1e-12 \
                and math.hypot(x, y) < limit:
            ok[i] = True
            out[i, 0], out[i, 1] = x, y
    return out, ok


@njit(cache=True, error_model="numpy")
def _inverse_iteration(A, v):
    """v (4,) := the unit right singular vector of the smallest singular value of A (4, 4) by inverse iteration,
    and True, when it converged in 3 solves; else False (v undefined). A = P L U once (partial pivoting; a pivot
    below 2e-16 |A| is set to that size, keeping its sign, so an exactly singular A works too), then solves
    A x = b from b = (1, 1, 1, 1), normalised between them: a solve multiplies the vector's part along the
    smallest singular direction by 1 / sigma_4, the others' by at most 1 / sigma_3. Converged: the third solve
    moved the vector by less than 1e-12, so sigma_4 / sigma_3 < 1e-6 and its error is rounding's (about
    1e-16 sigma_1 / sigma_3). A is overwritten with its LU factors."""
    scale = 0.0
    for r in range(4):
        for c in range(4):
            scale = max(scale, abs(A[r, c]))
    if not (scale > 0.0 and scale < np.inf):
        return False
    tiny = 2e-16 * scale
    perm = np.arange(4)
    for k in range(4):
        p = k
        for r in range(k + 1, 4):
            if abs(A[r, k]) > abs(A[p, k]):
                p = r
        if p != k:
            for c in range(4):
                A[k, c], A[p, c] = A[p, c], A[k, c]
            perm[k], perm[p] = perm[p], perm[k]
        if abs(A[k, k]) < tiny:
            A[k, k] = tiny if A[k, k] >= 0 else -tiny
        for r in range(k + 1, 4):
            f = A[r, k] / A[k, k]
            A[r, k] = f
            for c in range(k + 1, 4):
                A[r, c] -= f * A[k, c]
    for r in range(4):
        v[r] = 0.5
    y = np.empty(4)
    old = np.empty(4)
    moved = np.inf
    for _ in range(3):
        old[:] = v
        for r in range(4):  # L y = P b
            acc = v[perm[r]]
            for c in range(r):
                acc -= A[r, c] * y[c]
            y[r] = acc
        for r in range(3, -1, -1):  # U x = y
            acc = y[r]
            for c in range(r + 1, 4):
                acc -= A[r, c] * v[c]
            v[r] = acc / A[r, r]
        norm = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2] + v[3] * v[3])
        if not (norm > 0.0 and norm < np.inf):
            return False
        dot = 0.0
        for r in range(4):
            v[r] /= norm
            dot += v[r] * old[r]
        sign = 1.0 if dot >= 0 else -1.0
        moved = 0.0
        for r in range(4):
            moved = max(moved, abs(v[r] - sign * old[r]))
    return moved < 1e-12


@njit(cache=True, error_model="numpy")
def _jacobi(A, v):
    """v (4,) := the right singular vector of the smallest singular value of A (4, 4), by one-sided Jacobi
    (Hestenes): plane rotations of A's columns until every pair is orthogonal to rounding, accumulated in V; the
    column of smallest norm is then sigma_min u_min, and V's column the vector. A is overwritten."""
    V = np.eye(4)
    for _sweep in range(30):
        rotated = False
        for p in range(3):
            for q in range(p + 1, 4):
                alpha = beta = gamma = 0.0
                for r in range(4):
                    alpha += A[r, p] * A[r, p]
                    beta += A[r, q] * A[r, q]
                    gamma += A[r, p] * A[r, q]
                if gamma == 0.0 or abs(gamma) <= 1e-15 * math.sqrt(alpha * beta):
                    continue
                rotated = True
                zeta = (beta - alpha) / (2.0 * gamma)
                t = math.copysign(1.0, zeta) / (abs(zeta) + math.sqrt(1.0 + zeta * zeta))
                c = 1.0 / math.sqrt(1.0 + t * t)
                s = c * t
                for r in range(4):
                    x, y = A[r, p], A[r, q]
                    A[r, p], A[r, q] = c * x - s * y, s * x + c * y
                    x, y = V[r, p], V[r, q]
                    V[r, p], V[r, q] = c * x - s * y, s * x + c * y
        if not rotated:
            break
    best, k = np.inf, 0
    for col in range(4):
        norm = 0.0
        for r in range(4):
            norm += A[r, col] * A[r, col]
        if norm < best:
            best, k = norm, col
    for r in range(4):
        v[r] = V[r, k]


@njit(cache=True, error_model="numpy")
def triangulate(P1, P2, x1, x2):
    """`stereo3d.triangulate` (linear DLT of two views, as `cv2.triangulatePoints`) point by point: the homogeneous
    point is the right singular vector of the smallest singular value of A (4, 4), the DLT rows, found by inverse
    iteration (`_inverse_iteration`; one-sided Jacobi, `_jacobi`, where it has not converged in three solves)
    instead of LAPACK's batched SVD: the same point to rounding, not to the last bit.
    P1, P2: (n, 3, 4); x1, x2: (n, 2). Returns points (n, 3) (0 where not finite) and which are finite (n,)."""
    n = x1.shape[0]
    out = np.zeros((n, 3))
    ok = np.zeros(n, dtype=np.bool_)
    A = np.empty((4, 4))
    Xh = np.empty(4)
    for i in range(n):
        for copy in range(2):  # the rows again for the Jacobi fallback (inverse iteration overwrote them)
            for c in range(4):
                A[0, c] = x1[i, 0] * P1[i, 2, c] - P1[i, 0, c]
                A[1, c] = x1[i, 1] * P1[i, 2, c] - P1[i, 1, c]
                A[2, c] = x2[i, 0] * P2[i, 2, c] - P2[i, 0, c]
                A[3, c] = x2[i, 1] * P2[i, 2, c] - P2[i, 1, c]
            if copy == 0 and _inverse_iteration(A, Xh):
                break
            if copy == 1:
                _jacobi(A, Xh)
        w = Xh[3]
        big = max(abs(Xh[0]), abs(Xh[1]), abs(Xh[2]))
        if math.isfinite(w) and abs(w) > 1e-12 * big:
            ok[i] = True
            out[i, 0], out[i, 1], out[i, 2] = Xh[0] / w, Xh[1] / w, Xh[2] / w
    return out, ok
