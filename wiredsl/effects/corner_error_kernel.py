"""The compiled kernel of corner_error (numba), its stage function `stage` (see wiredsl.engine.kernel for the
signature); imported only when a run uses the kernel. Its key is the rig's (KernelStage.rig): the draws are
corner_error.py's, by feature id."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from wiredsl.effects.variation_kernel import magnitude
from wiredsl.engine.kernel import _normal_pair


@njit(cache=True)
def stage(pts, start, meta, corners, cfid, key, params, epipole, right, st):
    sigma, rho = params[0], params[1]
    if params[2] > 0:
        sigma = magnitude(key, sigma, params[2], False)
    a, b = sigma * math.sqrt(rho), sigma * math.sqrt(1.0 - rho)
    out = np.empty_like(corners)
    count, sq = st[0], st[1]  # (summed in the same order as into st: the statistics are unchanged)
    for c in range(len(corners)):
        pair = 3 * np.uint64(cfid[c])
        sx, sy = _normal_pair(key, pair)
        ox, oy = _normal_pair(key, pair + np.uint64(2 if right else 1))
        nx, ny = a * sx + b * ox, a * sy + b * oy
        out[c, 0] = corners[c, 0] + nx
        out[c, 1] = corners[c, 1] + ny
        count += 2
        sq += nx * nx + ny * ny
    st[0], st[1] = count, sq
    return pts, start, meta, out, cfid
