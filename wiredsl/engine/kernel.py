"""The trial-major compiled Monte-Carlo kernel (numba): one pass per trial and view over packed strokes.

For each trial of a batch and each view it takes the cameras of the trial's calibration draw (or the
ideal view when there is none), re-projects the raw strokes, cuts them at invalid vertices and at the
image border, runs exactly the declared image stages in order, and appends the result to output arrays
that grow with the output only. It is a transcription of the numpy path (`wiredsl.effects.*`,
`wiredsl.engine.imageset`) with the same keyed draws and the same arithmetic, so that the two agree
in every discrete decision and to rounding in coordinates (tests hold them together).

numba is imported only here, and this module only when a run uses the kernel; compiled code is cached
on disk, and the one-time compile is announced on stderr.
"""

from __future__ import annotations

import math
import sys

import numpy as np
from numba import njit

# the per-stroke functions view_batch dispatches to, by the code each effect declares (its `kernel`,
# wiredsl.effects.base.KernelStage); a code with no function here is refused before the kernel runs
EDGE_LOSS, LATERAL_SHIFT, APPROX_ERROR, CORNER_LOSS, CORNER_MISMATCH, STEREO_MISMATCH = range(6)
KNOWN = frozenset(range(6))
FID, SEG, FRAG, KIND, CLIP, CLOSED, OCC = range(7)  # columns of a stroke's metadata row
NMETA = 7
ELLIPSE = 2
NSTAT = 6  # statistics a stage records, per stage (see `stage_stats`)

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(11)
_ONE = np.uint64(1)
_TWO = np.uint64(2)


# ----------------------------------------------------------------------------- keyed draws

@njit(cache=True)
def _bits(key, index):
    z = key + (np.uint64(index) + _ONE) * _GOLDEN
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@njit(cache=True)
def _uniform(key, index):
    return np.float64(_bits(key, index) >> _S11) * 2.0**-53


@njit(cache=True)
def _normal_pair(key, pair):
    """Normals 2 pair and 2 pair + 1 of a key (base.keyed_normal)."""
    u1 = _uniform(key, _TWO * np.uint64(pair))
    u2 = _uniform(key, _TWO * np.uint64(pair) + _ONE)
    r = math.sqrt(-2.0 * math.log1p(-u1))
    phi = 2.0 * math.pi * u2
    return r * math.cos(phi), r * math.sin(phi)


# ----------------------------------------------------------------------------- packed strokes

@njit(cache=True)
def _arcs(pts, start):
    """Arc length at each vertex from its stroke's start, and stroke lengths (as imageset.arc_lengths)."""
    S = len(start) - 1
    arc = np.empty(len(pts))
    L = np.zeros(S)
    for k in range(S):
        a, b = start[k], start[k + 1]
        if b > a:
            acc = 0.0
            arc[a] = 0.0
            for i in range(a + 1, b):
                dx = pts[i, 0] - pts[i - 1, 0]
                dy = pts[i, 1] - pts[i - 1, 1]
                acc = acc + math.sqrt(dx * dx + dy * dy)
                arc[i] = acc
            L[k] = arc[b - 1]
    return arc, L


@njit(cache=True)
def _total_length(pts, start):
    """The sum of the strokes' lengths, summed as _arcs does each stroke (for the statistics)."""
    total = 0.0
    for k in range(len(start) - 1):
        acc = 0.0
        for i in range(start[k] + 1, start[k + 1]):
            dx = pts[i, 0] - pts[i - 1, 0]
            dy = pts[i, 1] - pts[i - 1, 1]
            acc = acc + math.sqrt(dx * dx + dy * dy)
        total += acc
    return total


@njit(cache=True)
def _after(arc, lo, hi, x):
    """First index in [lo, hi) with arc > x (hi if none)."""
    while lo < hi:
        mid = (lo + hi) // 2
        if arc[mid] <= x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True)
def _at_or_after(arc, lo, hi, x):
    """First index in [lo, hi) with arc >= x (hi if none)."""
    while lo < hi:
        mid = (lo + hi) // 2
        if arc[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True)
def _point_at(pts, arc, first, last, target, out, o):
    j = _after(arc, first, last + 1, target) - 1
    top = max(last - 1, first)
    j = min(max(j, first), top)
    j1 = min(j + 1, last)
    span = arc[j1] - arc[j]
    t = (target - arc[j]) / span if span > 0 else 0.0
    out[o, 0] = pts[j, 0] + t * (pts[j1, 0] - pts[j, 0])
    out[o, 1] = pts[j, 1] + t * (pts[j1, 1] - pts[j, 1])


@njit(cache=True)
def _keep(pts, start, meta, arc, L, ps, pa, pb, pfrag, pclosed, pcut, pwhole, n):
    """imageset.keep_intervals: parts [a, b] of strokes ps (n parts), whole parts verbatim; arc and L are
    the strokes' arc lengths (_arcs)."""
    okp = np.zeros(n, np.bool_)
    lo = np.zeros(n, np.int64)
    cnt = np.zeros(n, np.int64)
    aa = np.empty(n)
    bb = np.empty(n)
    total = 0
    S = 0
    for q in range(n):
        k = ps[q]
        first, last = start[k], start[k + 1] - 1
        if pwhole[q]:
            a, b = 0.0, L[k]
            okp[q] = True
            lo[q] = first
            cnt[q] = last + 1 - first
        else:
            a = min(max(pa[q], 0.0), L[k])
            b = min(max(pb[q], 0.0), L[k])
            if not b - a > 1e-9:
                continue
            okp[q] = True
            lq = _after(arc, first, last + 1, a)
            hq = _at_or_after(arc, first, last + 1, b)
            lo[q] = lq
            cnt[q] = max(hq - lq, 0) + 2
        aa[q], bb[q] = a, b
        total += cnt[q]
        S += 1
    out = np.empty((total, 2))
    ostart = np.zeros(S + 1, np.int64)
    ometa = np.empty((S, NMETA), np.int64)
    o = 0
    s = 0
    for q in range(n):
        if not okp[q]:
            continue
        k = ps[q]
        first, last = start[k], start[k + 1] - 1
        if pwhole[q]:
            for i in range(cnt[q]):
                out[o + i, 0] = pts[lo[q] + i, 0]
                out[o + i, 1] = pts[lo[q] + i, 1]
        else:
            _point_at(pts, arc, first, last, aa[q], out, o)
            inner = cnt[q] - 2
            for i in range(inner):
                out[o + 1 + i, 0] = pts[lo[q] + i, 0]
                out[o + 1 + i, 1] = pts[lo[q] + i, 1]
            _point_at(pts, arc, first, last, bb[q], out, o + cnt[q] - 1)
        o += cnt[q]
        ostart[s + 1] = o
        for c in range(NMETA):
            ometa[s, c] = meta[k, c]
        ometa[s, FRAG] = pfrag[q]
        ometa[s, CLOSED] = pclosed[q]
        ometa[s, CLIP] = 1 if (meta[k, CLIP] != 0 or pcut[q]) else 0
        s += 1
    return out, ostart, ometa


@njit(cache=True)
def _unroll(pts, start, meta, which):
    """imageset.unroll_closed for the closed strokes where which[k]: traversed twice, then vertex 0."""
    S = len(start) - 1
    ostart = np.zeros(S + 1, np.int64)
    for k in range(S):
        c = start[k + 1] - start[k]
        ostart[k + 1] = ostart[k] + (2 * c + 1 if (which[k] and meta[k, CLOSED] != 0) else c)
    out = np.empty((ostart[S], 2))
    ometa = meta.copy()
    for k in range(S):
        c = start[k + 1] - start[k]
        for i in range(ostart[k + 1] - ostart[k]):
            src = start[k] + (i % max(c, 1))
            out[ostart[k] + i, 0] = pts[src, 0]
            out[ostart[k] + i, 1] = pts[src, 1]
        if which[k] and meta[k, CLOSED] != 0:
            ometa[k, CLOSED] = 0
    return out, ostart, ometa


# ----------------------------------------------------------------------------- the image stages

@njit(cache=True)
def _edge_loss(pts, start, meta, key, fraction, st):
    S = len(start) - 1
    closed = meta[:, CLOSED] != 0
    upts, ustart, umeta = _unroll(pts, start, meta, np.ones(S, np.bool_))
    arc, Lu = _arcs(upts, ustart)
    n = 0
    for k in range(S):
        n += 1 if closed[k] else 2
    ps = np.empty(n, np.int64)
    pa = np.empty(n)
    pb = np.empty(n)
    pf = np.zeros(n, np.int64)
    zeros = np.zeros(n, np.int64)
    q = 0
    for k in range(S):
        L = Lu[k] / 2 if closed[k] else Lu[k]
        u = _uniform(key, k)
        gap = fraction * L
        g0 = u * (L if closed[k] else L - gap)
        st[0] += L
        if closed[k]:
            ps[q], pa[q], pb[q] = k, g0 + gap, g0 + L
            q += 1
        else:
            ps[q], pa[q], pb[q] = k, 0.0, g0
            ps[q + 1], pa[q + 1], pb[q + 1], pf[q + 1] = k, g0 + gap, L, 1
            q += 2
    out = _keep(upts, ustart, umeta, arc, Lu, ps, pa, pb, pf, zeros, zeros, np.zeros(n, np.bool_), n)
    st[1] += _total_length(out[0], out[1])
    return out


@njit(cache=True)
def _split_ellipses(pts, start, meta):
    """lateral_shift.split_ellipses."""
    S = len(start) - 1
    ell = meta[:, KIND] == ELLIPSE
    if not ell.any():
        return pts, start, meta
    closed = (meta[:, CLOSED] != 0) & ell
    upts, ustart, umeta = _unroll(pts, start, meta, closed)
    arc, Lu = _arcs(upts, ustart)
    crossings = np.empty(len(upts))
    ccount = np.zeros(S, np.int64)
    coff = np.zeros(S + 1, np.int64)
    for k in range(S):
        a, b = ustart[k], ustart[k + 1]
        coff[k + 1] = coff[k]
        if not ell[k] or b - a < 2:
            continue
        # centre and second moments of segment midpoints weighted by length (bincount order: by segment)
        tot, cx, cy = 0.0, 0.0, 0.0
        for i in range(a, b - 1):
            dx = upts[i + 1, 0] - upts[i, 0]
            dy = upts[i + 1, 1] - upts[i, 1]
            w = math.sqrt(dx * dx + dy * dy)
            tot += w
            cx += w * ((upts[i, 0] + upts[i + 1, 0]) / 2)
            cy += w * ((upts[i, 1] + upts[i + 1, 1]) / 2)
        tot = max(tot, 1e-300)
        cx /= tot
        cy /= tot
        sxx, sxy, syy = 0.0, 0.0, 0.0
        for i in range(a, b - 1):
            dx = upts[i + 1, 0] - upts[i, 0]
            dy = upts[i + 1, 1] - upts[i, 1]
            w = math.sqrt(dx * dx + dy * dy)
            mx = (upts[i, 0] + upts[i + 1, 0]) / 2 - cx
            my = (upts[i, 1] + upts[i + 1, 1]) / 2 - cy
            sxx += w * (mx * mx)
            sxy += w * (mx * my)
            syy += w * (my * my)
        theta = 0.5 * math.atan2(2 * sxy, sxx - syy)
        nx, ny = -math.sin(theta), math.cos(theta)
        c = (b - a - 1) // 2 if closed[k] else b - a  # a loop's own segments: its first lap
        prev = (upts[a, 0] - cx) * nx + (upts[a, 1] - cy) * ny
        for i in range(a, b - 1):
            nxt = (upts[i + 1, 0] - cx) * nx + (upts[i + 1, 1] - cy) * ny
            if (prev < 0) != (nxt < 0) and i - a < c:
                t = prev / (prev - nxt)
                crossings[coff[k + 1]] = arc[i] + t * (arc[i + 1] - arc[i])
                coff[k + 1] += 1
            prev = nxt
        ccount[k] = coff[k + 1] - coff[k]
    halves = closed & (ccount >= 2)
    n = 0
    for k in range(S):
        n += 2 if halves[k] else (ccount[k] + 1 if (not closed[k] and ccount[k] > 0) else 1)
    ps = np.empty(n, np.int64)
    pa = np.zeros(n)
    pb = np.zeros(n)
    pf = np.zeros(n, np.int64)
    pc = np.zeros(n, np.int64)
    pw = np.zeros(n, np.bool_)
    q = 0
    for k in range(S):
        L = Lu[k] / 2 if closed[k] else Lu[k]
        o = coff[k]
        if halves[k]:
            ps[q], pa[q], pb[q] = k, crossings[o], crossings[o + 1]
            ps[q + 1], pa[q + 1], pb[q + 1] = k, crossings[o + 1], crossings[o] + L
            q += 2
        elif not closed[k] and ccount[k] > 0:
            for j in range(ccount[k] + 1):
                ps[q] = k
                pa[q] = 0.0 if j == 0 else crossings[o + j - 1]
                pb[q] = L if j == ccount[k] else crossings[o + j]
                q += 1
        else:
            ps[q], pf[q], pc[q], pw[q] = k, meta[k, FRAG], meta[k, CLOSED], True
            q += 1
    if (halves == closed).all():  # every loop is cut into halves: the unrolled strokes are the ones to cut
        return _keep(upts, ustart, umeta, arc, Lu, ps, pa, pb, pf, pc, np.zeros(n, np.int64), pw, n)
    vpts, vstart, vmeta = _unroll(pts, start, meta, halves)
    varc, vL = _arcs(vpts, vstart)
    return _keep(vpts, vstart, vmeta, varc, vL, ps, pa, pb, pf, pc, np.zeros(n, np.int64), pw, n)


@njit(cache=True)
def _lateral_shift(pts, start, meta, key, rng, st):
    pts, start, meta = _split_ellipses(pts, start, meta)
    S = len(start) - 1
    out = pts.copy()
    for k in range(S):
        u = _uniform(key, k)
        d = rng * (2 * u - 1)
        st[0] += 1
        st[1] += abs(d)
        st[2] = max(st[2], abs(d))
        a, b = start[k], start[k + 1]
        for i in range(a, b):
            tx, ty = 0.0, 0.0
            if i + 1 < b:  # the step to the next vertex
                dx = pts[i + 1, 0] - pts[i, 0]
                dy = pts[i + 1, 1] - pts[i, 1]
                ln = math.sqrt(dx * dx + dy * dy)
                if ln > 0:
                    tx, ty = 0.0 + dx / ln, 0.0 + dy / ln
            if i > a:  # the step from the previous one
                dx = pts[i, 0] - pts[i - 1, 0]
                dy = pts[i, 1] - pts[i - 1, 1]
                ln = math.sqrt(dx * dx + dy * dy)
                if ln > 0:
                    tx, ty = tx + dx / ln, ty + dy / ln
            nrm = math.sqrt(tx * tx + ty * ty)
            if nrm > 0:
                tx, ty = tx / nrm, ty / nrm
            else:
                tx, ty = 0.0, 0.0
            out[i, 0] = pts[i, 0] + d * -ty
            out[i, 1] = pts[i, 1] + d * tx
    return out, start, meta


@njit(cache=True)
def _approx_error(pts, start, meta, key, sigma, st):
    out = np.empty_like(pts)
    for v in range(len(pts)):
        gx, gy = _normal_pair(key, v)
        nx, ny = sigma * gx, sigma * gy
        out[v, 0] = pts[v, 0] + nx
        out[v, 1] = pts[v, 1] + ny
        st[0] += 2
        st[1] += nx * nx + ny * ny
    return out, start, meta


@njit(cache=True)
def _epi_dir(x, y, e):
    dx = x * e[2] - e[0]
    dy = y * e[2] - e[1]
    n = math.sqrt(dx * dx + dy * dy)
    if n > 0:
        return dx / n, dy / n
    return 1.0, 0.0


@njit(cache=True)
def _in_band(ax, ay, bx, by, e, tanb, everything):
    """stereo_mismatch.in_band for one segment."""
    if everything:
        return True
    lx = (ax + bx) / 2 * e[2] - e[0]
    ly = (ay + by) / 2 * e[2] - e[1]
    if lx == 0 and ly == 0:
        lx, ly = 1.0, 0.0
    dx, dy = bx - ax, by - ay
    return abs(dx * ly - dy * lx) <= tanb * abs(dx * lx + dy * ly)


@njit(cache=True)
def _drop_band(pts, start, meta, e, band):
    """stereo_mismatch._drop_band. Each segment's angle is computed once: slot start[k] + i holds segment
    i of stroke k, the last slot of a closed stroke its closing segment (an unrolled loop reuses them)."""
    S = len(start) - 1
    everything = band >= math.pi / 2
    tanb = math.tan(band) if not everything else 0.0
    inside = np.zeros(len(pts), np.bool_)
    cut_loop = np.zeros(S, np.bool_)
    intact = np.zeros(S, np.bool_)
    for k in range(S):
        a, b = start[k], start[k + 1]
        hit = False
        for i in range(a, b - 1):
            inside[i] = _in_band(pts[i, 0], pts[i, 1], pts[i + 1, 0], pts[i + 1, 1], e, tanb, everything)
            hit = hit or inside[i]
        if meta[k, CLOSED] != 0:
            if b - a > 1:
                inside[b - 1] = _in_band(pts[b - 1, 0], pts[b - 1, 1], pts[a, 0], pts[a, 1], e, tanb, everything)
                hit = hit or inside[b - 1]
            cut_loop[k] = hit
            intact[k] = not hit
    upts, ustart, umeta = _unroll(pts, start, meta, cut_loop)
    arc, uL = _arcs(upts, ustart)
    n_max = len(upts) + S
    ps = np.empty(n_max, np.int64)
    pa = np.empty(n_max)
    pb = np.empty(n_max)
    pf = np.zeros(n_max, np.int64)
    pc = np.zeros(n_max, np.int64)
    pw = np.zeros(n_max, np.bool_)
    q = 0
    for k in range(S):
        a, b = ustart[k], ustart[k + 1]
        if intact[k]:
            ps[q], pf[q], pc[q], pw[q] = k, umeta[k, FRAG], 1, True
            q += 1
            continue
        c = start[k + 1] - start[k]
        p0 = -1
        if cut_loop[k]:
            for i in range(c):
                if inside[start[k] + i]:
                    p0 = i
                    break
        run = -1
        for i in range(a, b):  # pairs i -> i + 1, and a sentinel at i = b - 1
            keep = False
            if i < b - 1:
                local = i - a
                keep = not inside[start[k] + (local % c if cut_loop[k] else local)]
                if cut_loop[k]:
                    keep = keep and local > p0 and local < p0 + c
            if keep and run < 0:
                run = i
            elif not keep and run >= 0:
                ps[q], pa[q], pb[q] = k, arc[run], arc[i]
                if run == a and i == b - 1 and not cut_loop[k]:
                    pw[q], pf[q] = True, umeta[k, FRAG]
                q += 1
                run = -1
    return _keep(upts, ustart, umeta, arc, uL, ps, pa, pb, pf, pc, np.zeros(q, np.int64), pw, q)


@njit(cache=True)
def _stereo(pts, start, meta, key, e, band, fraction, disparity, right, st):
    st[0] += _total_length(pts, start)
    if band > 0 and len(start) > 1:
        pts, start, meta = _drop_band(pts, start, meta, e, band)
        st[1] += _total_length(pts, start)
    else:
        st[1] += _total_length(pts, start)
    if not right or fraction == 0 or disparity == 0:
        return pts, start, meta
    out = pts.copy()
    for k in range(len(start) - 1):
        u0, u1 = _uniform(key, 2 * k), _uniform(key, 2 * k + 1)
        hit = u0 < fraction
        shift = disparity * (2 * u1 - 1) if hit else 0.0
        a, b = start[k], start[k + 1]
        mx, my = 0.0, 0.0
        for i in range(a, b):
            mx += pts[i, 0]
            my += pts[i, 1]
        mx /= b - a
        my /= b - a
        dx, dy = _epi_dir(mx, my, e)
        for i in range(a, b):
            out[i, 0] = pts[i, 0] + shift * dx
            out[i, 1] = pts[i, 1] + shift * dy
        st[2] += 1
        st[3] += 1 if hit else 0
        st[4] = max(st[4], abs(shift))
    return out, start, meta


@njit(cache=True)
def _corner_loss(corners, cfid, key, keep, st):
    n = len(corners)
    mask = np.zeros(n, np.bool_)
    for c in range(n):
        mask[c] = _uniform(key, c) < keep
    st[0] += n
    st[1] += mask.sum()
    return corners[mask], cfid[mask]


@njit(cache=True)
def _corner_mismatch(corners, key, fraction, radius, st):
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
    return out


# ----------------------------------------------------------------------------- cameras and the image

@njit(cache=True)
def _project(X, R, t, cam, fold, out, ok):
    """Perturbed camera (R (3, 3), t (3,), cam = f, ax, ay, cx, cy, k1, k2, p1, p2) applied to world points."""
    f, ax, ay, cx, cy, k1, k2, p1, p2 = cam[0], cam[1], cam[2], cam[3], cam[4], cam[5], cam[6], cam[7], cam[8]
    for i in range(len(X)):
        Px = R[0, 0] * X[i, 0] + R[0, 1] * X[i, 1] + R[0, 2] * X[i, 2] + t[0]
        Py = R[1, 0] * X[i, 0] + R[1, 1] * X[i, 1] + R[1, 2] * X[i, 2] + t[1]
        Pz = R[2, 0] * X[i, 0] + R[2, 1] * X[i, 1] + R[2, 2] * X[i, 2] + t[2]
        good = Pz > 1e-3
        z = Pz if good else 1.0
        x, y = Px / z, Py / z
        good = good and math.hypot(x, y) < fold
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + k2 * r2)
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        ok[i] = good
        out[i, 0] = f * ax * xd + cx if good else 0.0
        out[i, 1] = f * ay * yd + cy if good else 0.0


@njit(cache=True)
def _pieces(n):
    """Room for n kept pieces: stroke, start and end arc length, fragment, closed, cut count, whole."""
    return (np.empty(n, np.int64), np.empty(n), np.empty(n), np.zeros(n, np.int64), np.zeros(n, np.int64),
            np.zeros(n, np.int64), np.zeros(n, np.bool_))


@njit(cache=True)
def _keep_vertex_runs(pts, start, meta, ok):
    """imageset.keep_vertex_runs."""
    arc, L = _arcs(pts, start)
    S = len(start) - 1
    n_max = len(pts)
    ps, pa, pb, pf, pc, pcut, pw = _pieces(n_max)
    q = 0
    for k in range(S):
        a, b = start[k], start[k + 1]
        i = a
        while i < b:
            if not ok[i]:
                i += 1
                continue
            j = i
            while j + 1 < b and ok[j + 1]:
                j += 1
            whole = i == a and j == b - 1
            ps[q], pa[q], pb[q], pw[q] = k, arc[i], arc[j], whole
            pf[q] = meta[k, FRAG] if whole else 0
            pc[q] = meta[k, CLOSED] if whole else 0
            pcut[q] = 0 if whole else 1
            q += 1
            i = j + 1
    return _keep(pts, start, meta, arc, L, ps, pa, pb, pf, pc, pcut, pw, q)


@njit(cache=True)
def _inside(pts, width, height):
    for i in range(len(pts)):
        if not (pts[i, 0] >= 0 and pts[i, 1] >= 0 and pts[i, 0] <= width and pts[i, 1] <= height):
            return False
    return True


@njit(cache=True)
def _liang_barsky(ax, ay, bx, by, width, height):
    dx, dy = bx - ax, by - ay
    t0, t1, keep = 0.0, 1.0, True
    for side in range(4):
        if side == 0:
            p, q = -dx, ax
        elif side == 1:
            p, q = dx, width - ax
        elif side == 2:
            p, q = -dy, ay
        else:
            p, q = dy, height - ay
        if p == 0:
            if q < 0:
                keep = False
        else:
            r = q / p
            if p < 0:
                t0 = max(t0, r)
            else:
                t1 = min(t1, r)
    return t0, t1, keep and t0 <= t1


@njit(cache=True)
def _clip_rect(pts, start, meta, width, height):
    """imageset.clip_rect."""
    arc, L = _arcs(pts, start)
    S = len(start) - 1
    n_max = len(pts)
    ps, pa, pb, pf, pc, pcut, pw = _pieces(n_max)
    q = 0
    for k in range(S):
        a, b = start[k], start[k + 1]
        if b - a >= 2 and _inside(pts[a:b], width, height):  # the loop below would keep it whole: say so
            ps[q], pa[q], pb[q], pw[q], pf[q], pc[q], pcut[q] = k, 0.0, L[k], True, meta[k, FRAG], meta[k, CLOSED], 0
            q += 1
            continue
        open_run = False
        ja, t0a = 0, 0.0
        prev_keep, prev_t1 = False, 0.0
        for i in range(a, b - 1):
            t0, t1, keep = _liang_barsky(pts[i, 0], pts[i, 1], pts[i + 1, 0], pts[i + 1, 1], width, height)
            keep = keep and t1 > t0
            joins = open_run and keep and prev_keep and prev_t1 >= 1 and t0 <= 0 and i > a
            if open_run and not joins:  # close the run that ended at pair i - 1
                seg = _dist(pts, i - 1, i)
                _clip_part(k, a, b, ja, t0a, i - 1, prev_t1, arc, pts, seg, meta, ps, pa, pb, pf, pc, pcut, pw, q)
                q += 1
                open_run = False
            if keep and not open_run:
                open_run, ja, t0a = True, i, t0
            prev_keep, prev_t1 = keep, t1
        if open_run:
            i = b - 1
            seg = _dist(pts, i - 1, i)
            _clip_part(k, a, b, ja, t0a, i - 1, prev_t1, arc, pts, seg, meta, ps, pa, pb, pf, pc, pcut, pw, q)
            q += 1
    return _keep(pts, start, meta, arc, L, ps, pa, pb, pf, pc, pcut, pw, q)


@njit(cache=True)
def _dist(pts, i, j):
    dx = pts[j, 0] - pts[i, 0]
    dy = pts[j, 1] - pts[i, 1]
    return math.sqrt(dx * dx + dy * dy)


@njit(cache=True)
def _clip_part(k, a, b, j, t0, e, t1, arc, pts, seg_e, meta, ps, pa, pb, pf, pc, pcut, pw, q):
    dxj = pts[j + 1, 0] - pts[j, 0]
    dyj = pts[j + 1, 1] - pts[j, 1]
    seg_j = math.sqrt(dxj * dxj + dyj * dyj)
    whole = j == a and t0 <= 0 and e == b - 2 and t1 >= 1
    ps[q] = k
    pa[q] = arc[j] + t0 * seg_j
    pb[q] = arc[e] + t1 * seg_e
    pw[q] = whole
    pf[q] = meta[k, FRAG] if whole else max(meta[k, FRAG], 0)
    pc[q] = meta[k, CLOSED] if whole else 0
    pcut[q] = 0 if whole else 1


# ----------------------------------------------------------------------------- one view of a batch

@njit(cache=True)
def view_batch(tpts, tstart, tmeta, tcorners, cfid, W, CW, R, tv, cams, folds, width, height, calibrated,
               codes, params, keys, epipole, right, stats):
    """Every trial of a batch for one view. Returns packed strokes (pts, start, meta, trial) and corners
    (corners, fid, trial), strokes and corners ordered by trial."""
    T = keys.shape[1]
    res = []
    cres = []
    for t in range(T):
        if calibrated:
            pts = np.empty((len(W), 2))
            ok = np.empty(len(W), np.bool_)
            _project(W, R[t], tv[t], cams[t], folds[t], pts, ok)
            start, meta = tstart, tmeta
            if not ok.all():  # (when all are valid, the cut keeps every stroke verbatim: skip it)
                pts, start, meta = _keep_vertex_runs(pts, tstart, tmeta, ok)
            if not _inside(pts, width, height):
                pts, start, meta = _clip_rect(pts, start, meta, width, height)
            cp = np.empty((len(CW), 2))
            cok = np.empty(len(CW), np.bool_)
            _project(CW, R[t], tv[t], cams[t], folds[t], cp, cok)
            for c in range(len(CW)):
                cok[c] = cok[c] and cp[c, 0] >= 0 and cp[c, 0] <= width and cp[c, 1] >= 0 and cp[c, 1] <= height
            corners, cf = cp[cok], cfid[cok]
        else:
            pts, start, meta = tpts, tstart, tmeta
            corners, cf = tcorners, cfid
        for g in range(len(codes)):
            code, key, st = codes[g], keys[g, t], stats[g]
            if code == EDGE_LOSS:
                pts, start, meta = _edge_loss(pts, start, meta, key, params[g, 0], st)
            elif code == LATERAL_SHIFT:
                pts, start, meta = _lateral_shift(pts, start, meta, key, params[g, 0], st)
            elif code == APPROX_ERROR:
                pts, start, meta = _approx_error(pts, start, meta, key, params[g, 0], st)
            elif code == CORNER_LOSS:
                corners, cf = _corner_loss(corners, cf, key, params[g, 0], st)
            elif code == CORNER_MISMATCH:
                corners = _corner_mismatch(corners, key, params[g, 0], params[g, 1], st)
            elif code == STEREO_MISMATCH:
                pts, start, meta = _stereo(pts, start, meta, key, epipole, params[g, 0], params[g, 1], params[g, 2],
                                           right, st)
            else:
                raise ValueError("kernel: unknown stage code")
        res.append((pts, start, meta))
        cres.append((corners, cf))
    N = 0
    S = 0
    C = 0
    for t in range(T):
        N += len(res[t][0])
        S += len(res[t][1]) - 1
        C += len(cres[t][0])
    opts = np.empty((N, 2))
    ostart = np.zeros(S + 1, np.int64)
    ometa = np.empty((S, NMETA), np.int64)
    otrial = np.empty(S, np.int64)
    ocorners = np.empty((C, 2))
    ocfid = np.empty(C, np.int64)
    octrial = np.empty(C, np.int64)
    n = s = c = 0
    for t in range(T):
        pts, start, meta = res[t]
        k = len(start) - 1
        opts[n:n + len(pts)] = pts
        for i in range(k):
            ostart[s + i + 1] = n + start[i + 1]
            otrial[s + i] = t
        ometa[s:s + k] = meta
        n += len(pts)
        s += k
        corners, cf = cres[t]
        ocorners[c:c + len(corners)] = corners
        ocfid[c:c + len(corners)] = cf
        octrial[c:c + len(corners)] = t
        c += len(corners)
    return opts, ostart, ometa, otrial, ocorners, ocfid, octrial


def run_view(tpts, tstart, meta, tcorners, cfid, W, CW, R_cw, t_cw, cams, folds, width, height, calibrated,
             codes, params, keys, epipole, right, stats):
    """view_batch with every argument in the one layout it is compiled for (no second compile)."""
    f2 = lambda a, n: np.ascontiguousarray(a, dtype=np.float64).reshape(-1, n)  # noqa: E731
    i1 = lambda a: np.ascontiguousarray(a, dtype=np.int64).reshape(-1)  # noqa: E731
    announce_compile()
    return view_batch(f2(tpts, 2), i1(tstart), np.ascontiguousarray(meta, dtype=np.int64).reshape(-1, NMETA),
                      f2(tcorners, 2), i1(cfid), f2(W, 3), f2(CW, 3),
                      np.ascontiguousarray(R_cw, dtype=np.float64).reshape(-1, 3, 3), f2(t_cw, 3), f2(cams, 9),
                      np.ascontiguousarray(folds, dtype=np.float64).reshape(-1), float(width), float(height),
                      bool(calibrated), i1(codes), f2(params, 3),
                      np.ascontiguousarray(keys, dtype=np.uint64).reshape(len(codes), len(folds)),
                      np.ascontiguousarray(epipole, dtype=np.float64).reshape(3), bool(right), stats)


_announced = False


def announce_compile() -> None:
    """Say on stderr, once, when the kernel is about to be compiled (not when it is loaded from the cache)."""
    import os

    global _announced
    if _announced or view_batch.signatures:
        return
    _announced = True
    try:
        index = view_batch._cache._cache_file._index_path
    except AttributeError:  # numba's internals moved: say it anyway rather than stay silent for a minute
        index = None
    if index is None or not os.path.exists(index):
        print("wiredsl: compiling the Monte-Carlo kernel (once; numba caches it for later runs)...",
              file=sys.stderr, flush=True)


def warm() -> None:
    """Compile (or load from the cache) the kernel on a tiny view, e.g. once before parallel test workers."""
    z2, zi = np.zeros((0, 2)), np.zeros(0, np.int64)
    run_view(np.array([[0.0, 0.0], [1.0, 1.0]]), np.array([0, 2]), np.zeros((1, NMETA), np.int64), z2, zi,
             np.zeros((2, 3)), np.zeros((0, 3)), np.eye(3)[None], np.zeros((1, 3)), np.ones((1, 9)), np.ones(1),
             10.0, 10.0, True, np.arange(6), np.zeros((6, 3)), np.ones((6, 1), np.uint64), np.ones(3), True,
             np.zeros((6, NSTAT)))


def record(name: str, columns, row: np.ndarray, stats) -> None:
    """Add one view's statistics row of stage `name` (its KernelStage's `stats` columns) to the run's Stats."""
    for (key, how), value in zip(columns, row, strict=False):
        (stats.add if how == "add" else stats.peak)(name, **{key: value})
