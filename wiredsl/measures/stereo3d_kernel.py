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


@njit(cache=True)
def _distort(x, y, k1, k2, p1, p2, k3, k4, k5, k6):
    """`geometry.distort_xy` of one point, operation for operation."""
    r2 = x * x + y * y
    radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


@njit(cache=True)
def undistort_radtan(xd, k1, k2, p1, p2, k3, k4, k5, k6, steps, limit):
    """Undistorted unit-plane points (n, 2) of distorted ones xd (n, 2), and which converged (n,)."""
    n = xd.shape[0]
    out = np.zeros((n, 2))
    ok = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        x0, y0 = xd[i, 0], xd[i, 1]
        x, y = x0, y0
        for _ in range(steps):
            r2 = x * x + y * y
            num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
            rad = num / den
            g = 2.0 * ((k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)) * den - num * (k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2))) \
                / (den * den)
            j11 = rad + g * x * x + 2.0 * p1 * y + 6.0 * p2 * x
            j12 = g * x * y + 2.0 * p1 * x + 2.0 * p2 * y
            j22 = rad + g * y * y + 6.0 * p1 * y + 2.0 * p2 * x
            dx, dy = _distort(x, y, k1, k2, p1, p2, k3, k4, k5, k6)
            r0, r1 = dx - x0, dy - y0
            det = j11 * j22 - j12 * j12
            x, y = x - (j22 * r0 - j12 * r1) / det, y - (j11 * r1 - j12 * r0) / det
        dx, dy = _distort(x, y, k1, k2, p1, p2, k3, k4, k5, k6)
        # both residuals below 1e-12 (numpy's max of the two, a NaN failing either way)
        if math.isfinite(x) and math.isfinite(y) and abs(dx - x0) < 1e-12 and abs(dy - y0) < 1e-12 \
                and math.hypot(x, y) < limit:
            ok[i] = True
            out[i, 0], out[i, 1] = x, y
    return out, ok
