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
def _columns(a, b):
    """Per-segment quantities the pair loop reads (each its own column): end points, length, unit direction, angle."""
    n = a.shape[0]
    length, ux, uy, phi = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    ax, ay, bx, by = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):
        ax[i], ay[i], bx[i], by[i] = a[i, 0], a[i, 1], b[i, 0], b[i, 1]
        dx = b[i, 0] - a[i, 0]
        dy = b[i, 1] - a[i, 1]
        length[i] = math.hypot(dx, dy)
        ux[i] = dx / length[i]
        uy[i] = dy / length[i]
        phi[i] = math.atan2(dy, dx)
    return ax, ay, bx, by, length, ux, uy, phi


@njit(cache=True, inline="always")
def _reference(row, i, j0, j1, cols, n_angle, directed, n_dist, d_max, point_span):
    """Reference segment i's un-normalised PGH (angle bins, n_dist), added into `row` (zeros), from segments
    j0:j1 (its group)."""
    ax, ay, bx, by, length, ux, uy, phi = cols
    w = d_max / n_dist
    step = math.pi / n_angle
    nx, ny = -uy[i], ux[i]
    base = nx * ax[i] + ny * ay[i]
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


@njit(cache=True)
def histograms(a, b, starts, n_angle, directed, n_dist, d_max, point_span):
    """Un-normalised PGHs (n, angle bins, n_dist) of segments a -> b (n, 2), grouped by CSR `starts`."""
    n = a.shape[0]
    na = 2 * n_angle if directed else n_angle + 1
    out = np.zeros((n, na, n_dist))
    cols = _columns(a, b)
    for g in range(len(starts) - 1):
        for i in range(starts[g], starts[g + 1]):
            _reference(out[i], i, starts[g], starts[g + 1], cols, n_angle, directed, n_dist, d_max, point_span)
    return out


@njit(cache=True)
def _block_sum(a, lo, n):
    """numpy's pairwise sum of a[lo:lo + n] for n <= 128: 8 partial sums, combined as a tree, then the rest."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - (n % 8):
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True)
def _pairwise_sum(a, lo, n):
    """numpy's pairwise summation of a[lo:lo + n] (`pairwise_sum` of its add reduction: blocks of up to 128 values
    as `_block_sum`, above that the sum of the two halves, the first a multiple of 8), so that a sum here is
    numpy's to the last bit. The halving is walked with an explicit stack (numba's cache and recursion do not
    mix)."""
    los = np.empty(64, dtype=np.int64)
    ns = np.empty(64, dtype=np.int64)
    right = np.zeros(64, dtype=np.bool_)  # the node's first half is summed (in left), its second is being summed
    left = np.empty(64)
    d = 0
    los[0], ns[0] = lo, n
    while True:
        while ns[d] > 128:  # down the first halves
            half = ns[d] // 2
            half -= half % 8
            right[d] = False
            los[d + 1], ns[d + 1] = los[d], half
            d += 1
        v = _block_sum(a, los[d], ns[d])
        while True:  # up, adding second halves to their first
            if d == 0:
                return v
            d -= 1
            if not right[d]:
                left[d] = v
                right[d] = True
                half = ns[d] // 2
                half -= half % 8
                los[d + 1], ns[d + 1] = los[d] + half, ns[d] - half
                d += 1
                break
            v = left[d] + v


@njit(cache=True)
def roots(a, b, starts, order, n_angle, directed, n_dist, d_max, point_span):
    """sqrt of the normalised PGHs as rows (n, bins), row order[i] that of sorted segment i: `histograms`, then
    numpy's `h / where(total > 0, total, 1)` and `sqrt` of `pgh.histograms` without blur, fused (the totals by
    numpy's pairwise sum, so the roots are the numpy path's to the last bit). Each reference's histogram is
    built in one small buffer that stays in cache and is normalised straight into its row: no (n, bins)
    temporary."""
    n = a.shape[0]
    na = 2 * n_angle if directed else n_angle + 1
    bins = na * n_dist
    out = np.empty((n, bins))
    cols = _columns(a, b)
    buf = np.empty((na, n_dist))
    flat = buf.reshape(bins)
    for g in range(len(starts) - 1):
        for i in range(starts[g], starts[g + 1]):
            flat[:] = 0.0
            _reference(buf, i, starts[g], starts[g + 1], cols, n_angle, directed, n_dist, d_max, point_span)
            total = 0.0 + _pairwise_sum(flat, 0, bins)
            if not total > 0:
                total = 1.0
            dst = out[order[i]]
            for k in range(bins):
                dst[k] = math.sqrt(flat[k] / total)
    return out


@njit(cache=True)
def _bounds(owner, k):
    """Where each of k owners' rows start in `owner` (sorted: an owner's rows are contiguous), and the end (k + 1,)."""
    out = np.zeros(k + 1, dtype=np.int64)
    for r in range(len(owner)):
        out[owner[r] + 1] += 1
    for c in range(k):
        out[c + 1] += out[c]
    return out


@njit(cache=True)
def _trial_best(root, idx, ideal_t, rows):
    """For one trial's disturbed rows `idx`: best[i, k] = the largest score of row idx[i] against owner k's ideal
    rows (rows[k]:rows[k + 1] of `ideal_t`'s columns; -inf where k has none). One matrix product of the trial's
    rows alone, so the scores do not depend on which other trials share the call; then a running maximum over
    each owner's contiguous columns (max is exact: the order does not matter)."""
    S = np.dot(root[idx], ideal_t)
    best = np.empty((len(idx), len(rows) - 1), dtype=S.dtype)
    for i in range(len(idx)):
        for k in range(len(rows) - 1):
            m = -np.inf
            for r in range(rows[k], rows[k + 1]):
                v = S[i, r]
                if v > m:
                    m = v
            best[i, k] = m
    return best


@njit(cache=True)
def own_scores(root, key, order, bounds, ideal_t, owner, sources, tie):
    """`pgh._own_scores` a trial at a time (rows `order[bounds[g]:bounds[g + 1]]` are trial g's, scored by
    `_trial_best`): each disturbed row's best score among its own source's ideal rows (0 if none), and whether
    that is the best among every source (within `tie`)."""
    M = root.shape[0]
    K = len(sources)
    rows = _bounds(owner, K)
    own = np.zeros(M)
    recog = np.zeros(M, dtype=np.bool_)
    for g in range(len(bounds) - 1):
        idx = order[bounds[g]:bounds[g + 1]]
        best = _trial_best(root, idx, ideal_t, rows)
        for i in range(len(idx)):
            m = idx[i]
            col = min(np.searchsorted(sources, key[m]), K - 1)
            if sources[col] != key[m]:
                continue
            other = -1.0
            for k in range(K):
                if k != col and best[i, k] > other:
                    other = best[i, k]
            own[m] = best[i, col]
            recog[m] = best[i, col] >= other - tie
    return own, recog


@njit(cache=True)
def located_scores(root, L, trial, order, bounds, n_trials, ideal_t, owner, n):
    """`pgh._located`'s scores (n_trials, n), a trial at a time as `own_scores`: per trial and candidate
    view-point, the length-weighted sum of each disturbed row's best match among the candidate's ideal rows
    (float32 products, as float64); and each trial's length (n_trials,)."""
    score = np.zeros((n_trials, n))
    w = np.zeros(n_trials)
    rows = _bounds(owner, n)
    for g in range(len(bounds) - 1):
        idx = order[bounds[g]:bounds[g + 1]]
        best = _trial_best(root, idx, ideal_t, rows)
        for i in range(len(idx)):
            m = idx[i]
            t = trial[m]
            for c in range(n):
                if best[i, c] > -np.inf:
                    score[t, c] += L[m] * np.float64(best[i, c])
            w[t] += L[m]
    return score, w
