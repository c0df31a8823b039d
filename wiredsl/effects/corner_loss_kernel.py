"""The compiled kernel of corner_loss (numba), its stage function `stage` (see wiredsl.engine.kernel for the
signature); imported only when a run uses the kernel."""

from __future__ import annotations

import numpy as np
from numba import njit

from wiredsl.engine.kernel import _uniform


@njit(cache=True)
def stage(pts, start, meta, corners, cfid, key, params, epipole, right, st):
    keep = params[0]
    n = len(corners)
    mask = np.zeros(n, np.bool_)
    for c in range(n):
        mask[c] = _uniform(key, c) < keep
    st[0] += n
    st[1] += mask.sum()
    return pts, start, meta, corners[mask], cfid[mask]
