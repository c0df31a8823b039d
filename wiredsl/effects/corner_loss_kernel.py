"""The compiled kernel of corner_loss (numba), its stage function `stage` (see wiredsl.engine.kernel for the
signature); imported only when a run uses the kernel."""

from __future__ import annotations

import numpy as np
from numba import njit

from wiredsl.effects.variation_kernel import item_uniform, stroke_item, view_magnitude
from wiredsl.engine.kernel import _uniform


@njit(cache=True)
def stage(pts, start, meta, corners, cfid, key, params, epipole, right, st):
    keep, spread, correlation = params[0], params[1], params[2]
    persistent = correlation > 0
    pose = int(params[3]) if persistent else -1
    rho = params[4:] if persistent else params[:0]
    keep = view_magnitude(key, keep, spread, True, pose, rho, persistent)
    n = len(corners)
    mask = np.zeros(n, np.bool_)
    for c in range(n):
        u = item_uniform(key, stroke_item(cfid[c], -1), pose, rho) if persistent else _uniform(key, c)
        mask[c] = u < keep
    st[0] += n
    st[1] += mask.sum()
    return pts, start, meta, corners[mask], cfid[mask]
