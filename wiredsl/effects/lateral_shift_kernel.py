"""The compiled kernel of lateral_shift (numba), its stage function `stage` (see wiredsl.engine.kernel for the
signature); imported only when a run uses the kernel."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from wiredsl.effects.variation_kernel import item_uniform, stroke_item, view_magnitude
from wiredsl.engine.imageset import STEP_PX
from wiredsl.engine.kernel import CLOSED, ELLIPSE, FID, FRAG, KIND, _arcs, _keep, _pieces, _uniform, _unroll


@njit(cache=True)
def _crossing(arc, i, t):
    """lateral_shift._crossing: the arc length at fraction t of segment i, snapped to a vertex within 1e-9 px."""
    seg = arc[i + 1] - arc[i]
    if t * seg < 1e-9:
        return arc[i]
    if (1 - t) * seg < 1e-9:
        return arc[i + 1]
    return arc[i] + t * seg


@njit(cache=True)
def _split_ellipses(pts, start, meta):
    """lateral_shift.split_ellipses."""
    S = len(start) - 1
    ell = meta[:, KIND] == ELLIPSE
    if not ell.any():
        return pts, start, meta
    closed = (meta[:, CLOSED] != 0) & ell
    upts, ustart, umeta = _unroll(pts, start, meta, closed)
    # arc lengths along the ellipses only (the other strokes are kept whole), summed with the moments' weights
    arc, Lu = np.zeros(len(upts)), np.zeros(S)
    crossings = np.empty(len(upts))
    second = np.empty(len(upts))  # each crossing's point on a loop's second lap
    seg = np.empty(len(upts))  # segment lengths (the moments' weights)
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
            seg[i] = w
            arc[i + 1] = arc[i] + w  # as _arcs sums them
            tot += w
            cx += w * ((upts[i, 0] + upts[i + 1, 0]) / 2)
            cy += w * ((upts[i, 1] + upts[i + 1, 1]) / 2)
        Lu[k] = arc[b - 1]
        tot = max(tot, 1e-300)
        cx /= tot
        cy /= tot
        sxx, sxy, syy = 0.0, 0.0, 0.0
        for i in range(a, b - 1):
            w = seg[i]
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
                crossings[coff[k + 1]] = _crossing(arc, i, t)
                second[coff[k + 1]] = _crossing(arc, i + c, t) if closed[k] else 0.0
                coff[k + 1] += 1
            prev = nxt
        ccount[k] = coff[k + 1] - coff[k]
    halves = closed & (ccount >= 2)
    n = 0
    for k in range(S):
        n += 2 if halves[k] else (ccount[k] + 1 if (not closed[k] and ccount[k] > 0) else 1)
    ps, pa, pb, pf, pc, pcut, pw = _pieces(n)
    q = 0
    for k in range(S):
        L = Lu[k] / 2 if closed[k] else Lu[k]
        o = coff[k]
        if halves[k]:
            ps[q], pa[q], pb[q] = k, crossings[o], crossings[o + 1]
            ps[q + 1], pa[q + 1], pb[q + 1] = k, crossings[o + 1], second[o]
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
        return _keep(upts, ustart, umeta, arc, Lu, ps, pa, pb, pf, pc, pcut, pw, n)
    vpts, vstart, vmeta = _unroll(pts, start, meta, halves)
    varc, vL = _arcs(vpts, vstart)
    return _keep(vpts, vstart, vmeta, varc, vL, ps, pa, pb, pf, pc, pcut, pw, n)


@njit(cache=True)
def stage(pts, start, meta, corners, cfid, key, params, epipole, right, st):
    rng, spread, correlation = params[0], params[1], params[2]
    persistent = correlation > 0
    pose = int(params[3]) if persistent else -1
    rho = params[4:] if persistent else params[:0]
    rng = view_magnitude(key, rng, spread, False, pose, rho, persistent)
    pts, start, meta = _split_ellipses(pts, start, meta)
    S = len(start) - 1
    out = pts.copy()
    tan = np.zeros((len(pts), 2))
    stepped = np.zeros(len(pts), dtype=np.bool_)
    for k in range(S):
        u = item_uniform(key, stroke_item(meta[k, FID], meta[k, FRAG]), pose, rho) if persistent else \
            _uniform(key, k)
        d = rng * (2 * u - 1)
        st[0] += 1
        st[1] += abs(d)
        st[2] = max(st[2], abs(d))
        a, b = start[k], start[k + 1]
        # imageset.vertex_normals: a step of STEP_PX or less has no direction, and a vertex with no real step
        # (a stroke end's copy of a vertex) takes the tangent of the nearest one that has (next, else previous)
        for i in range(a, b):
            tx, ty, has = 0.0, 0.0, False
            if i + 1 < b:  # the step to the next vertex
                dx = pts[i + 1, 0] - pts[i, 0]
                dy = pts[i + 1, 1] - pts[i, 1]
                ln = math.sqrt(dx * dx + dy * dy)
                if ln > STEP_PX:
                    tx, ty, has = 0.0 + dx / ln, 0.0 + dy / ln, True
            if i > a:  # the step from the previous one
                dx = pts[i, 0] - pts[i - 1, 0]
                dy = pts[i, 1] - pts[i - 1, 1]
                ln = math.sqrt(dx * dx + dy * dy)
                if ln > STEP_PX:
                    tx, ty, has = tx + dx / ln, ty + dy / ln, True
            tan[i, 0], tan[i, 1], stepped[i] = tx, ty, has
        for i in range(a, b):
            j = i
            if not stepped[i]:
                j = -1
                for m in range(i + 1, b):
                    if stepped[m]:
                        j = m
                        break
                if j < 0:
                    for m in range(i - 1, a - 1, -1):
                        if stepped[m]:
                            j = m
                            break
                if j < 0:
                    j = i
            tx, ty = tan[j, 0], tan[j, 1]
            nrm = math.sqrt(tx * tx + ty * ty)
            if nrm > 0:
                tx, ty = tx / nrm, ty / nrm
            else:
                tx, ty = 0.0, 0.0
            out[i, 0] = pts[i, 0] + d * -ty
            out[i, 1] = pts[i, 1] + d * tx
    return out, start, meta, corners, cfid
