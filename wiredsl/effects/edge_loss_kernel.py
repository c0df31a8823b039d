"""The compiled kernel of edge_loss (numba), its stage function `stage` (see wiredsl.engine.kernel for the
signature); imported only when a run uses the kernel."""

from __future__ import annotations

import numpy as np
from numba import njit

from wiredsl.effects.variation_kernel import feature_magnitude, item_uniform, stroke_item, view_magnitude
from wiredsl.engine.kernel import CLOSED, FID, FRAG, _arcs, _keep, _pieces, _total_length, _uniform, _unroll


@njit(cache=True)
def stage(pts, start, meta, corners, cfid, key, params, epipole, right, st):
    fraction, spread, correlation, fspread = params[0], params[1], params[2], params[3]
    persistent = correlation > 0
    pose = int(params[4]) if persistent else -1
    rho = params[5:] if persistent else params[:0]
    fraction = view_magnitude(key, fraction, spread, True, pose, rho, persistent)
    S = len(start) - 1
    closed = meta[:, CLOSED] != 0
    upts, ustart, umeta = _unroll(pts, start, meta, np.ones(S, np.bool_))
    arc, Lu = _arcs(upts, ustart)
    n = 0
    for k in range(S):
        n += 1 if closed[k] else 2
    ps, pa, pb, pf, pc, pcut, pw = _pieces(n)
    q = 0
    for k in range(S):
        L = Lu[k] / 2 if closed[k] else Lu[k]
        u = item_uniform(key, stroke_item(umeta[k, FID], umeta[k, FRAG]), pose, rho) if persistent else \
            _uniform(key, k)
        f = fraction
        if fspread > 0:
            f = feature_magnitude(key, stroke_item(umeta[k, FID], umeta[k, FRAG]), k, fraction, fspread, pose, rho,
                                  persistent)
        gap = f * L
        g0 = u * (L if closed[k] else L - gap)
        st[0] += L
        if closed[k]:
            ps[q], pa[q], pb[q] = k, g0 + gap, g0 + L
            q += 1
        else:
            ps[q], pa[q], pb[q] = k, 0.0, g0
            ps[q + 1], pa[q + 1], pb[q + 1], pf[q + 1] = k, g0 + gap, L, 1
            q += 2
    out = _keep(upts, ustart, umeta, arc, Lu, ps, pa, pb, pf, pc, pcut, pw, n)
    st[1] += _total_length(out[0], out[1])
    return out[0], out[1], out[2], corners, cfid
