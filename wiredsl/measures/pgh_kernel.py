"""The PGH pair loop compiled with numba: `pgh.raw_histograms` without its (pairs,) temporaries.

Imported only when numba is installed (the `fast` extra); `pgh._padded` is the numpy reference it is
tested against. Sums run in a different order, so results agree with numpy's to rounding (1e-12).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def _add(out, i, abin, x0, x1, rho, w, nd, d_max):
    """Density rho of length over distances [x0, x1], clipped to d_max, into row out[i, abin]."""
    x0 = min(x0, d_max)
    x1 = min(x1, d_max)
    if x1 <= x0:
        return
    ka = min(int(x0 / w), nd - 1)
    kb = min(int(x1 / w), nd - 1)
    if ka == kb:
        out[i, abin, ka] += rho * (x1 - x0)
        return
    out[i, abin, ka] += rho * ((ka + 1) * w - x0)
    out[i, abin, kb] += rho * (x1 - kb * w)
    for k in range(ka + 1, kb):
        out[i, abin, k] += rho * w


@njit(cache=True)
def histograms(a, b, starts, n_angle, directed, n_dist, d_max, point_span):
    """Un-normalised PGHs (n, angle bins, n_dist) of segments a -> b (n, 2), grouped by CSR `starts`."""
    n = a.shape[0]
    na = 2 * n_angle if directed else n_angle + 1
    out = np.zeros((n, na, n_dist))
    w = d_max / n_dist
    step = math.pi / n_angle
    length = np.empty(n)
    ux = np.empty(n)
    uy = np.empty(n)
    phi = np.empty(n)
    for i in range(n):
        dx = b[i, 0] - a[i, 0]
        dy = b[i, 1] - a[i, 1]
        length[i] = math.hypot(dx, dy)
        ux[i] = dx / length[i]
        uy[i] = dy / length[i]
        phi[i] = math.atan2(dy, dx)
    for g in range(len(starts) - 1):
        for i in range(starts[g], starts[g + 1]):
            nx, ny = -uy[i], ux[i]
            base = nx * a[i, 0] + ny * a[i, 1]
            for j in range(starts[g], starts[g + 1]):
                da = nx * a[j, 0] + ny * a[j, 1] - base
                db = nx * b[j, 0] + ny * b[j, 1] - base
                lo, hi = min(da, db), max(da, db)
                if lo > d_max or hi < -d_max:
                    continue
                theta = phi[j] - phi[i]
                if theta > math.pi:
                    theta -= 2 * math.pi
                elif theta <= -math.pi:
                    theta += 2 * math.pi
                if directed:
                    abin = (int(math.floor(theta / step + 0.5)) + 2 * n_angle) % (2 * n_angle)
                else:
                    abin = int(math.floor(abs(theta) / step + 0.5))
                span = hi - lo
                if span < point_span:
                    x = abs(0.5 * (lo + hi))
                    if x <= d_max:
                        out[i, abin, min(int(x / w), n_dist - 1)] += length[j]
                    continue
                rho = length[j] / span
                near_end = min(abs(lo), abs(hi))
                far_end = max(abs(lo), abs(hi))
                if lo < 0 < hi:
                    _add(out, i, abin, 0.0, far_end, rho, w, n_dist, d_max)
                    _add(out, i, abin, 0.0, near_end, rho, w, n_dist, d_max)
                else:
                    _add(out, i, abin, near_end, far_end, rho, w, n_dist, d_max)
    return out
