"""The compiled kernel of corner_error (numba), its stage function `stage` (see wiredsl.engine.kernel for the
signature); imported only when a run uses the kernel."""

from __future__ import annotations

import numpy as np
from numba import njit

from wiredsl.engine.kernel import _normal_pair


@njit(cache=True)
def stage(pts, start, meta, corners, cfid, key, params, epipole, right, st):
    sigma = params[0]
    out = np.empty_like(corners)
    count, sq = st[0], st[1]  # (summed in the same order as into st: the statistics are unchanged)
    for c in range(len(corners)):
        gx, gy = _normal_pair(key, c)
        nx, ny = sigma * gx, sigma * gy
        out[c, 0] = corners[c, 0] + nx
        out[c, 1] = corners[c, 1] + ny
        count += 2
        sq += nx * nx + ny * ny
    st[0], st[1] = count, sq
    return pts, start, meta, out, cfid
