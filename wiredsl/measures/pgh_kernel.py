"""PGH compiled with numba: the pair loop (`pgh.raw_histograms` without its (pairs,) temporaries) and the scoring
(`pgh._own_scores`, `pgh._located`: a matrix product a trial, so a trial's scores do not depend on what else
shares the call).

Imported only when numba is installed (the `fast` extra); `pgh._padded` is the numpy reference it is
tested against. Sums run in a different order, so results agree with numpy's to rounding (1e-12).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def _add(row, abin, x0, x1, rho, w, nd, d_max):
    """Density rho of length over distances [x0, x1], clipped to d_max, into row[abin] (a reference's
    histogram)."""
    x0 = min(x0, d_max)
    x1 = min(x1, d_max)
    if x1 <= x0:
        return
    ka = min(int(x0 / w), nd - 1)
    kb = min(int(x1 / w), nd - 1)
    if ka == kb:
        row[abin, ka] += rho * (x1 - x0)
        return
    row[abin, ka] += rho * ((ka + 1) * w - x0)
    row[abin, kb] += rho * (x1 - kb * w)
    for k in range(ka + 1, kb):
        row[abin, k] += rho * w


@njit(cache=True)
def histograms(a, b, starts, n_angle, directed, n_dist, d_max, point_span):
    """Un-normalised PGHs (n, angle bins, n_dist) of segments a -> b (n, 2), grouped by CSR `starts`."""
    n = a.shape[0]
    na = 2 * n_angle if directed else n_angle + 1
    out = np.zeros((n, na, n_dist))
    w = d_max / n_dist
    step = math.pi / n_angle
    length, ux, uy, phi = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    ax, ay, bx, by = np.empty(n), np.empty(n), np.empty(n), np.empty(n)  # end points as separate columns
    for i in range(n):
        ax[i], ay[i], bx[i], by[i] = a[i, 0], a[i, 1], b[i, 0], b[i, 1]
        dx = b[i, 0] - a[i, 0]
        dy = b[i, 1] - a[i, 1]
        length[i] = math.hypot(dx, dy)
        ux[i] = dx / length[i]
        uy[i] = dy / length[i]
        phi[i] = math.atan2(dy, dx)
    for g in range(len(starts) - 1):
        j0, j1 = starts[g], starts[g + 1]
        for i in range(j0, j1):
            nx, ny = -uy[i], ux[i]
            base = nx * ax[i] + ny * ay[i]
            row = out[i]  # the reference's histogram
            pi_ = phi[i]
            for j in range(j0, j1):
                da = nx * ax[j] + ny * ay[j] - base
                db = nx * bx[j] + ny * by[j] - base
                if da < db:
                    lo, hi = da, db
                else:
                    lo, hi = db, da
                if lo > d_max or hi < -d_max:
                    continue
                theta = phi[j] - pi_
                if theta > math.pi:
                    theta -= 2 * math.pi
                elif theta <= -math.pi:
                    theta += 2 * math.pi
                if directed:
                    abin = (int(math.floor(theta / step + 0.5)) + 2 * n_angle) % (2 * n_angle)
                else:
                    abin = int(math.floor(abs(theta) / step + 0.5))
                span = hi - lo
                L = length[j]
                if span < point_span:
                    x = abs(0.5 * (lo + hi))
                    if x <= d_max:
                        row[abin, min(int(x / w), n_dist - 1)] += L
                    continue
                rho = L / span
                alo, ahi = abs(lo), abs(hi)
                near_end = min(alo, ahi)
                far_end = max(alo, ahi)
                if lo < 0 < hi:
                    _add(row, abin, 0.0, far_end, rho, w, n_dist, d_max)
                    _add(row, abin, 0.0, near_end, rho, w, n_dist, d_max)
                else:
                    _add(row, abin, near_end, far_end, rho, w, n_dist, d_max)
    return out


@njit(cache=True)
def _trial_best(root, idx, ideal_t, owner, k):
    """One trial's rows `idx`: best[i, j] = the largest score (one matrix product of the rows with the ideal rows
    `ideal_t`) of row idx[i] over the ideal rows r of owner j < k (-inf where j has none), in the product's dtype."""
    S = np.dot(root[idx], ideal_t)
    best = np.full((len(idx), k), -np.inf, dtype=S.dtype)
    for i in range(len(idx)):
        for r in range(S.shape[1]):
            if S[i, r] > best[i, owner[r]]:
                best[i, owner[r]] = S[i, r]
    return best


@njit(cache=True)
def own_scores(root, key, order, bounds, ideal_t, owner, sources, tie):
    """`pgh._own_scores` a trial at a time (rows `order[bounds[g]:bounds[g + 1]]` are trial g's): each disturbed
    row's best score among its own source's ideal rows (0 if none), and whether that is the best among every
    source (within `tie`). The scores of a trial are one matrix product of its rows alone with the ideal rows
    (`ideal_t`: (bins, n)), so they do not depend on which other trials share the call."""
    M = root.shape[0]
    K = len(sources)
    own = np.zeros(M)
    recog = np.zeros(M, dtype=np.bool_)
    for g in range(len(bounds) - 1):
        idx = order[bounds[g]:bounds[g + 1]]
        trial_best = _trial_best(root, idx, ideal_t, owner, K)
        for i in range(len(idx)):
            m = idx[i]
            best = trial_best[i]
            col = min(np.searchsorted(sources, key[m]), K - 1)
            if sources[col] != key[m]:
                continue
            other = -1.0
            for k in range(K):
                if k != col and best[k] > other:
                    other = best[k]
            own[m] = best[col]
            recog[m] = best[col] >= other - tie
    return own, recog


@njit(cache=True)
def located_scores(root, L, trial, order, bounds, n_trials, ideal_t, owner, n):
    """`pgh._located`'s scores (n_trials, n), a trial at a time as `own_scores`: per trial and candidate
    view-point, the length-weighted sum of each disturbed row's best match among the candidate's ideal rows
    (float32 products, as float64); and each trial's length (n_trials,)."""
    score = np.zeros((n_trials, n))
    w = np.zeros(n_trials)
    for g in range(len(bounds) - 1):
        idx = order[bounds[g]:bounds[g + 1]]
        trial_best = _trial_best(root, idx, ideal_t, owner, n)
        for i in range(len(idx)):
            m = idx[i]
            best = trial_best[i]
            t = trial[m]
            for c in range(n):
                if best[c] > -np.inf:
                    score[t, c] += L[m] * np.float64(best[c])
            w[t] += L[m]
    return score, w
