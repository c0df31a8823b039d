"""The compiled kernel of stereo_mismatch (numba), its stage function `stage` (see wiredsl.engine.kernel for the
signature); imported only when a run uses the kernel."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from wiredsl.engine.kernel import CLOSED, FRAG, _arcs, _keep, _pieces, _total_length, _uniform, _unroll


@njit(cache=True)
def _epi_dir(x, y, e0, e1, e2):
    dx = x * e2 - e0
    dy = y * e2 - e1
    n = math.sqrt(dx * dx + dy * dy)
    if n > 0:
        return dx / n, dy / n
    return 1.0, 0.0


@njit(cache=True)
def _in_band(ax, ay, bx, by, e0, e1, e2, tanb, everything):
    """stereo_mismatch.in_band for one segment (the epipole as scalars: a call handed an array may pay its
    reference count each time)."""
    if everything:
        return True
    lx = (ax + bx) / 2 * e2 - e0
    ly = (ay + by) / 2 * e2 - e1
    if lx == 0 and ly == 0:
        lx, ly = 1.0, 0.0
    dx, dy = bx - ax, by - ay
    return abs(dx * ly - dy * lx) <= tanb * abs(dx * lx + dy * ly)


@njit(cache=True)
def _drop_band(pts, start, meta, e, band):
    """stereo_mismatch._drop_band, and the strokes' total length before it. Each segment's angle is computed once: slot start[k] + i holds segment
    i of stroke k, the last slot of a closed stroke its closing segment (an unrolled loop reuses them)."""
    S = len(start) - 1
    everything = band >= math.pi / 2
    e0, e1, e2 = e[0], e[1], e[2]
    tanb = math.tan(band) if not everything else 0.0
    inside = np.zeros(len(pts), np.bool_)
    cut_loop = np.zeros(S, np.bool_)
    intact = np.zeros(S, np.bool_)
    for k in range(S):
        a, b = start[k], start[k + 1]
        hit = False
        for i in range(a, b - 1):
            inside[i] = _in_band(pts[i, 0], pts[i, 1], pts[i + 1, 0], pts[i + 1, 1], e0, e1, e2, tanb, everything)
            hit = hit or inside[i]
        if meta[k, CLOSED] != 0:
            if b - a > 1:
                inside[b - 1] = _in_band(pts[b - 1, 0], pts[b - 1, 1], pts[a, 0], pts[a, 1], e0, e1, e2, tanb,
                                         everything)
                hit = hit or inside[b - 1]
            cut_loop[k] = hit
            intact[k] = not hit
    upts, ustart, umeta = _unroll(pts, start, meta, cut_loop)
    arc, uL = _arcs(upts, ustart)
    before = 0.0  # the strokes' length before the cut, as _total_length sums it (a loop's first lap: its own arcs)
    for k in range(S):
        before += arc[ustart[k] + start[k + 1] - start[k] - 1] if cut_loop[k] else uL[k]
    ps, pa, pb, pf, pc, pcut, pw = _pieces(len(upts) + S)
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
    out = _keep(upts, ustart, umeta, arc, uL, ps, pa, pb, pf, pc, pcut, pw, q)
    return out[0], out[1], out[2], before


@njit(cache=True)
def stage(pts, start, meta, corners, cfid, key, params, e, right, st):
    band, fraction, disparity = params[0], params[1], params[2]
    if band > 0 and len(start) > 1:
        pts, start, meta, before = _drop_band(pts, start, meta, e, band)
        st[0] += before
        st[1] += _total_length(pts, start)
    else:
        before = _total_length(pts, start)
        st[0] += before
        st[1] += before
    if not right or fraction == 0 or disparity == 0:
        return pts, start, meta, corners, cfid
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
        dx, dy = _epi_dir(mx, my, e[0], e[1], e[2])
        for i in range(a, b):
            out[i, 0] = pts[i, 0] + shift * dx
            out[i, 1] = pts[i, 1] + shift * dy
        st[2] += 1
        st[3] += 1 if hit else 0
        st[4] = max(st[4], abs(shift))
    return out, start, meta, corners, cfid
