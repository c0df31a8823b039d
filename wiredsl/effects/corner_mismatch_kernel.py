"""The compiled kernel of corner_mismatch (numba), its stage function `stage` (see wiredsl.engine.kernel for the
signature); imported only when a run uses the kernel."""

from __future__ import annotations

import math

from numba import njit

from wiredsl.engine.kernel import _uniform


@njit(cache=True)
def stage(pts, start, meta, corners, cfid, key, params, epipole, right, st):
    fraction, radius = params[0], params[1]
    out = corners.copy()
    for c in range(len(corners)):
        u0, u1, u2 = _uniform(key, 3 * c), _uniform(key, 3 * c + 1), _uniform(key, 3 * c + 2)
        hit = u0 < fraction
        r = radius * math.sqrt(u1)
        theta = 2 * math.pi * u2
        mx = r * math.cos(theta) if hit else 0.0
        my = r * math.sin(theta) if hit else 0.0
        out[c, 0] = corners[c, 0] + mx
        out[c, 1] = corners[c, 1] + my
        st[0] += 1
        st[1] += 1 if hit else 0
        st[2] = max(st[2], math.sqrt(mx * mx + my * my))
    return pts, start, meta, out, cfid
