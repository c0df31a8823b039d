"""The trial-major compiled Monte-Carlo kernel (numba): one pass per trial and view over packed strokes.

For each trial of a batch and each view it takes the cameras of the trial's calibration draw (or the
ideal view when there is none), re-projects the raw strokes, cuts them at invalid vertices and at the
image border, runs exactly the declared image stages in order, and appends the result to output arrays
that grow with the output only. It is a transcription of the numpy path (`wiredsl.effects.*`,
`wiredsl.engine.imageset`) with the same keyed draws and the same arithmetic, so that the two agree
in every discrete decision and to rounding in coordinates (tests hold them together).

Each image stage's numba function lives with its effect (its KernelStage names it, e.g.
`wiredsl.effects.edge_loss_kernel:stage`), with the one signature

    stage(pts, start, meta, corners, cfid, key, params, epipole, right, stats) -> (pts, start, meta, corners, cfid)

(a stage whose KernelStage says `camera=True` takes one more argument, `camera`: float64 (20,), the view's
nominal image width and height, then its CAMERA_ROW: f, ax, ay, cx, cy, k1, k2, p1, p2, k3..k6, xi,
alpha, beta, w, model code; a stage whose KernelStage names a `workspace` function takes one more, last: the
float64 array that function, `workspace(params, epipole, right, camera, trials) -> array`, made for the view
before the batch's trials, for what depends on the view and not on the trial), and may call the shared parts
here (keyed draws `_bits`/`_uniform`/`_normal_pair`, `_arcs`, `_total_length`, `_keep`, `_unroll`, the metadata
columns FID..OCC). `compose` builds the loop over a table of stage functions from those names, so this module
names no effect: the stage list is an array of codes into the table, so every pipeline of built-in stages (any
subset, order and parameters) runs the one loop of the built-in table (`builtin_table`), compiled once, and a
plug-in's pipeline the loop of its own table. numba is imported only here and by those functions' modules, and
they only when a run uses the kernel; compiled code is cached on disk, and a compile is announced on stderr.
"""

from __future__ import annotations

import math
import sys

import numpy as np
from numba import njit

from wiredsl.engine.geometry import CAMERA_ROW

FID, SEG, FRAG, KIND, CLIP, CLOSED, OCC = range(7)  # columns of a stroke's metadata row
NMETA = 7
ELLIPSE = 2
NSTAT = 6  # the least width of a stage's statistics row (montecarlo.stage_rows)

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11, _S32 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(11), np.uint64(32)
_ONE = np.uint64(1)
_TWO = np.uint64(2)


# ----------------------------------------------------------------------------- keyed draws

@njit(cache=True, error_model="numpy")
def _bits(key, index):
    z = key + (np.uint64(index) + _ONE) * _GOLDEN
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@njit(cache=True, error_model="numpy")
def _uniform(key, index):
    return np.float64(_bits(key, index) >> _S11) * 2.0**-53


@njit(cache=True, error_model="numpy")
def _normal_pair(key, pair):
    """Normals 2 pair and 2 pair + 1 of a key (base.keyed_normal: Marsaglia's polar method, attempt a at uniforms
    2 (pair + a 2**32) and the next)."""
    attempt = np.uint64(0)
    while True:
        i = _TWO * (np.uint64(pair) + (attempt << _S32))
        u = 2.0 * _uniform(key, i) - 1.0
        v = 2.0 * _uniform(key, i + _ONE) - 1.0
        s = u * u + v * v
        if s < 1.0 and s > 0.0:
            f = math.sqrt(-2.0 * math.log(s) / s)
            return u * f, v * f
        attempt += _ONE


# ----------------------------------------------------------------------------- packed strokes

@njit(cache=True, error_model="numpy")
def _stroke_arcs(pts, start, k, arc, L):
    """Arc length at each vertex of stroke k from its start, into arc, and its length into L[k]: alone for
    the strokes a cut needs, or for every stroke through _arcs."""
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


@njit(cache=True, error_model="numpy")
def _arcs(pts, start):
    """Arc length at each vertex from its stroke's start, and stroke lengths (as imageset.arc_lengths)."""
    S = len(start) - 1
    arc = np.zeros(len(pts))
    L = np.zeros(S)
    for k in range(S):
        _stroke_arcs(pts, start, k, arc, L)
    return arc, L


@njit(cache=True, error_model="numpy")
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


@njit(cache=True, error_model="numpy")
def _point_at(pts, arc, first, last, after, target, out, o):
    """The point at arc length target of the stroke [first, last] into out[o]; after is the first vertex of the
    stroke with arc > target (last + 1 if none), which the caller has at hand."""
    j = after - 1
    top = max(last - 1, first)
    j = min(max(j, first), top)
    j1 = min(j + 1, last)
    span = arc[j1] - arc[j]
    t = (target - arc[j]) / span if span > 0 else 0.0
    out[o, 0] = pts[j, 0] + t * (pts[j1, 0] - pts[j, 0])
    out[o, 1] = pts[j, 1] + t * (pts[j1, 1] - pts[j, 1])


@njit(cache=True, error_model="numpy")
def _keep(pts, start, meta, arc, L, ps, pa, pb, pfrag, pclosed, pcut, pwhole, n):
    """imageset.keep_intervals: parts [a, b] of strokes ps (n parts), whole parts verbatim; arc and L are
    the strokes' arc lengths (_arcs)."""
    span = np.empty((n, 3), np.int64)  # a part's first inner vertex, its vertex count (-1: empty), first past b
    ends = np.empty((n, 2))
    total = 0
    S = 0
    for q in range(n):
        k = ps[q]
        first, last = start[k], start[k + 1] - 1
        if pwhole[q]:
            a, b = 0.0, L[k]
            span[q, 0] = first
            span[q, 1] = last + 1 - first
        else:
            a = min(max(pa[q], 0.0), L[k])
            b = min(max(pb[q], 0.0), L[k])
            if not b - a > 1e-9:
                span[q, 1] = -1
                continue
            # the first vertices with arc > a, arc >= b and arc > b: scans along the stroke (arc does not
            # decrease), cheaper than bisection on strokes of a few vertices
            lq = first
            while lq <= last and arc[lq] <= a:
                lq += 1
            hq = lq
            while hq <= last and arc[hq] < b:
                hq += 1
            hb = hq
            while hb <= last and arc[hb] <= b:
                hb += 1
            span[q, 0] = lq
            span[q, 1] = hq - lq + 2
            span[q, 2] = hb
        ends[q, 0], ends[q, 1] = a, b
        total += span[q, 1]
        S += 1
    out = np.empty((total, 2))
    ostart = np.zeros(S + 1, np.int64)
    ometa = np.empty((S, NMETA), np.int64)
    o = 0
    s = 0
    for q in range(n):
        cnt = span[q, 1]
        if cnt < 0:
            continue
        k = ps[q]
        first, last = start[k], start[k + 1] - 1
        lo = span[q, 0]
        if pwhole[q]:
            for i in range(cnt):
                out[o + i, 0] = pts[lo + i, 0]
                out[o + i, 1] = pts[lo + i, 1]
        else:
            _point_at(pts, arc, first, last, lo, ends[q, 0], out, o)
            for i in range(cnt - 2):
                out[o + 1 + i, 0] = pts[lo + i, 0]
                out[o + 1 + i, 1] = pts[lo + i, 1]
            _point_at(pts, arc, first, last, span[q, 2], ends[q, 1], out, o + cnt - 1)
        o += cnt
        ostart[s + 1] = o
        for c in range(NMETA):
            ometa[s, c] = meta[k, c]
        ometa[s, FRAG] = pfrag[q]
        ometa[s, CLOSED] = pclosed[q]
        ometa[s, CLIP] = 1 if (meta[k, CLIP] != 0 or pcut[q]) else 0
        s += 1
    return out, ostart, ometa


@njit(cache=True, error_model="numpy")
def _unroll(pts, start, meta, which):
    """imageset.unroll_closed for the closed strokes where which[k]: traversed twice, then vertex 0. Where there
    is none, the strokes themselves (not a copy: callers only read them)."""
    S = len(start) - 1
    for k in range(S):
        if which[k] and meta[k, CLOSED] != 0:
            break
    else:
        return pts, start, meta
    ostart = np.zeros(S + 1, np.int64)
    for k in range(S):
        c = start[k + 1] - start[k]
        ostart[k + 1] = ostart[k] + (2 * c + 1 if (which[k] and meta[k, CLOSED] != 0) else c)
    out = np.empty((ostart[S], 2))
    ometa = meta.copy()
    for k in range(S):
        a, c, o = start[k], start[k + 1] - start[k], ostart[k]
        for i in range(c):
            out[o + i, 0] = pts[a + i, 0]
            out[o + i, 1] = pts[a + i, 1]
        if ostart[k + 1] - o > c:  # the second lap and vertex 0 again
            for i in range(c):
                out[o + c + i, 0] = pts[a + i, 0]
                out[o + c + i, 1] = pts[a + i, 1]
            out[o + 2 * c, 0] = pts[a, 0]
            out[o + 2 * c, 1] = pts[a, 1]
            ometa[k, CLOSED] = 0
    return out, ostart, ometa


# ----------------------------------------------------------------------------- cameras and the image

@njit(cache=True, error_model="numpy")
def _within(r2, x, y, limit):
    """hypot(x, y) < limit, with r2 = x * x + y * y: decided on the squares, and by hypot itself only within
    1e-12 of the limit (the squares' rounding is far below that), so the decision is hypot's exactly."""
    l2 = limit * limit
    if r2 < l2 * (1.0 - 1e-12):
        return True
    if r2 > l2 * (1.0 + 1e-12):
        return False
    return math.hypot(x, y) < limit


@njit(cache=True, error_model="numpy")
def _stable_sum(p, q, squares):
    """geometry.stable_sum of scalars."""
    return squares / (p - q) if p * q < 0 else p + q


@njit(cache=True, error_model="numpy")
def _project(X, R, t, cam, limit, out, ok):
    """Perturbed camera (R (3, 3), t (3,), cam = geometry.CAMERA_ROW, lens limit) applied to world points:
    geometry.project and geometry.visible, term by term."""
    f, ax, ay, cx, cy, k1, k2, p1, p2 = cam[0], cam[1], cam[2], cam[3], cam[4], cam[5], cam[6], cam[7], cam[8]
    k3, k4, k5, k6, xi, alpha, beta, w = cam[9], cam[10], cam[11], cam[12], cam[13], cam[14], cam[15], cam[16]
    model = int(cam[17])
    two_tan = 2.0 * math.tan(0.5 * w) if model == 5 else 0.0
    for i in range(len(X)):
        Px = R[0, 0] * X[i, 0] + R[0, 1] * X[i, 1] + R[0, 2] * X[i, 2] + t[0]
        Py = R[1, 0] * X[i, 0] + R[1, 1] * X[i, 1] + R[1, 2] * X[i, 2] + t[1]
        Pz = R[2, 0] * X[i, 0] + R[2, 1] * X[i, 1] + R[2, 2] * X[i, 2] + t[2]
        if model != 0:  # an angle-bounded lens (geometry.MODELS)
            rho = math.hypot(Px, Py)
            d = math.sqrt(Px * Px + Py * Py + Pz * Pz)
            good = math.atan2(rho, Pz) < limit and d > 1e-3
            xd, yd = 0.0, 0.0
            if good:
                if model == 1:
                    theta = math.atan2(rho, Pz)
                    t2 = theta * theta
                    td = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
                    scale = td / rho if rho > 0 else 0.0
                    xd, yd = scale * Px, scale * Py
                elif model == 5:
                    if rho > 0:
                        scale = math.atan2(rho * two_tan, Pz) / (w * rho)
                    else:
                        scale = two_tan / (w * Pz)
                    xd, yd = scale * Px, scale * Py
                else:
                    r2 = Px * Px + Py * Py  # geometry.model_plane_xy's stable sums, term by term
                    if model == 2:
                        den = _stable_sum(xi * d, Pz, xi * xi * r2 - (1.0 - xi) * (1.0 + xi) * (Pz * Pz))
                    elif model == 3:
                        den = _stable_sum(alpha * math.sqrt(beta * r2 + Pz * Pz), (1.0 - alpha) * Pz,
                                          alpha * alpha * beta * r2 + (2.0 * alpha - 1.0) * (Pz * Pz))
                    else:
                        zs = _stable_sum(xi * d, Pz, xi * xi * r2 - (1.0 - xi) * (1.0 + xi) * (Pz * Pz))
                        den = _stable_sum(alpha * math.sqrt(r2 + zs * zs), (1.0 - alpha) * zs,
                                          alpha * alpha * r2 + (2.0 * alpha - 1.0) * (zs * zs))
                    xd, yd = Px / den, Py / den
                    if model == 2:  # Mei's radtan on the unified model's m
                        x, y = xd, yd
                        r2 = x * x + y * y
                        radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
                        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
                        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        else:
            good = Pz > 1e-3
            z = Pz if good else 1.0
            x, y = Px / z, Py / z
            r2 = x * x + y * y
            good = good and _within(r2, x, y, limit)
            radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
            xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
            yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        ok[i] = good
        out[i, 0] = f * ax * xd + cx if good else 0.0
        out[i, 1] = f * ay * yd + cy if good else 0.0


ROW_TOL = 1e-9  # motion.ROW_TOL, MAX_FIXED, GRID, MAX_BRACKET and CONTRACTION: the row-time solver's rules
MAX_FIXED = 64
GRID = 8
MAX_BRACKET = 192
CONTRACTION = 0.5


@njit(cache=True, error_model="numpy")
def _row_at(X, i, x, R, t, cam, limit, rolling, k, one, uv, good):
    """Point i of X imaged from the camera's pose at row x's time (motion.moved, then _project): uv[0], good[0].
    k: the angular velocity's unit axis and speed."""
    tau = rolling[0] * x / rolling[1]
    d0 = X[i, 0] - rolling[2] - rolling[5] * tau  # motion.moved: exp([w] tau)^T (X - robot - v tau) + robot
    d1 = X[i, 1] - rolling[3] - rolling[6] * tau
    d2 = X[i, 2] - rolling[4] - rolling[7] * tau
    if k[3] > 0:
        theta = -k[3] * tau
        c, s = math.cos(theta), math.sin(theta)
        dk = (d0 * k[0] + d1 * k[1] + d2 * k[2]) * (1.0 - c)
        d0, d1, d2 = (d0 * c + (k[1] * d2 - k[2] * d1) * s + k[0] * dk,
                      d1 * c + (k[2] * d0 - k[0] * d2) * s + k[1] * dk,
                      d2 * c + (k[0] * d1 - k[1] * d0) * s + k[2] * dk)
    one[0, 0], one[0, 1], one[0, 2] = d0 + rolling[2], d1 + rolling[3], d2 + rolling[4]
    _project(one, R, t, cam, limit, uv, good)


@njit(cache=True, error_model="numpy")
def _project_rolling(X, R, t, cam, limit, rolling, out, ok):
    """_project under a rolling shutter, `rolling` = (readout, height, robot origin (3), v (3), w (3)): each point
    imaged from the camera's pose at its row's time, motion.rolling_pixels term by term (its fixed point, grid and
    Illinois bracket; a point the moved camera does not image is invalid)."""
    _project(X, R, t, cam, limit, out, ok)  # the camera at time 0: which points are valid, and the first rows
    H = rolling[1]
    speed = math.sqrt(rolling[8] * rolling[8] + rolling[9] * rolling[9] + rolling[10] * rolling[10])
    k = np.zeros(4)
    if speed > 0:
        k[0], k[1], k[2], k[3] = rolling[8] / speed, rolling[9] / speed, rolling[10] / speed, speed
    one = np.empty((1, 3))
    uv = np.empty((1, 2))
    good = np.empty(1, np.bool_)
    for i in range(len(X)):
        if not ok[i]:
            continue
        y0 = out[i, 1]
        a, ga, b, gb = 0.0, y0, H, 0.0
        bracket = False
        if y0 < 0:  # above the image at time 0: its root f(0), unless it comes in faster than the readout sweeps
            _row_at(X, i, H, R, t, cam, limit, rolling, k, one, uv, good)
            if not (good[0] and uv[0, 1] - H > 0):
                continue
            gb = uv[0, 1] - H
            bracket = True
        else:
            known = False
            x = min(y0, H)
            prev = np.inf
            settled = False
            for _ in range(MAX_FIXED):  # 1. the fixed point while it contracts
                _row_at(X, i, x, R, t, cam, limit, rolling, k, one, uv, good)
                if not good[0]:
                    ok[i] = False
                    break
                y = uv[0, 1]
                out[i, 0], out[i, 1] = uv[0, 0], y
                g = y - x
                step = abs(min(max(y, 0.0), H) - x)
                if step <= ROW_TOL:
                    settled = True
                    break
                below_b = not known or x < b
                if g >= 0 and below_b and x > a:
                    a, ga = x, g
                if g < 0 and below_b:
                    b, gb, known = x, g, True
                    if a >= b:
                        a, ga = 0.0, y0
                if step > CONTRACTION * prev:
                    break
                prev, x = step, min(max(y, 0.0), H)
            if not ok[i]:
                out[i, 0], out[i, 1] = 0.0, 0.0
                continue
            if settled:
                continue
            if not known:  # 2. the grid beyond the lower end
                start = a
                for j in range(1, GRID + 1):
                    x = H if j == GRID else start + (H - start) * (j / GRID)
                    _row_at(X, i, x, R, t, cam, limit, rolling, k, one, uv, good)
                    if not good[0]:
                        ok[i] = False
                        break
                    out[i, 0], out[i, 1] = uv[0, 0], uv[0, 1]
                    g = uv[0, 1] - x
                    if g < 0:
                        b, gb, known = x, g, True
                        break
                    a, ga = x, g
                if not ok[i]:
                    out[i, 0], out[i, 1] = 0.0, 0.0
                    continue
            bracket = known
        if not bracket:
            continue
        sa, sb = ga, gb  # 3. Illinois in [a, b]
        side = 0
        for it in range(MAX_BRACKET):
            c = 0.5 * (a + b) if it % 3 == 2 else (a * sb - b * sa) / (sb - sa)
            _row_at(X, i, c, R, t, cam, limit, rolling, k, one, uv, good)
            if not good[0]:
                ok[i] = False
                break
            out[i, 0], out[i, 1] = uv[0, 0], uv[0, 1]
            g = uv[0, 1] - c
            if abs(g) <= ROW_TOL:
                break
            if (g > 0) == (sa > 0):
                if side == -1:
                    sb = 0.5 * sb
                a, sa, side = c, g, -1
            else:
                if side == 1:
                    sa = 0.5 * sa
                b, sb, side = c, g, 1
        if not ok[i]:
            out[i, 0], out[i, 1] = 0.0, 0.0


@njit(cache=True, error_model="numpy")
def _pieces(n):
    """Room for n kept pieces (_keep's arguments): stroke, start and end arc length, fragment, closed, cut, whole
    (0 or 1); the last four zero. Rows of two arrays: two allocations, not seven."""
    whole = np.zeros((5, n), np.int64)
    ends = np.empty((2, n))
    return whole[0], ends[0], ends[1], whole[1], whole[2], whole[3], whole[4]


@njit(cache=True, error_model="numpy")
def _keep_vertex_runs(pts, start, meta, ok):
    """imageset.keep_vertex_runs (arc lengths measured only along the strokes that are cut: a whole one is copied)."""
    S = len(start) - 1
    arc = np.zeros(len(pts))
    L = np.zeros(S)
    n_max = len(pts)
    ps, pa, pb, pf, pc, pcut, pw = _pieces(n_max)
    q = 0
    for k in range(S):
        a, b = start[k], start[k + 1]
        for i in range(a, b):
            if not ok[i]:
                _stroke_arcs(pts, start, k, arc, L)
                break
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


@njit(cache=True, error_model="numpy")
def _inside(pts, a, b, width, height):
    """Whether vertices a..b-1 are all inside the image."""
    for i in range(a, b):
        if not (pts[i, 0] >= 0 and pts[i, 1] >= 0 and pts[i, 0] <= width and pts[i, 1] <= height):
            return False
    return True


@njit(cache=True, error_model="numpy")
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


@njit(cache=True, error_model="numpy")
def _clip_rect(pts, start, meta, width, height):
    """imageset.clip_rect (arc lengths measured only along the strokes that cross the border: a stroke inside is
    copied whole)."""
    S = len(start) - 1
    arc = np.zeros(len(pts))
    L = np.zeros(S)
    n_max = len(pts)
    ps, pa, pb, pf, pc, pcut, pw = _pieces(n_max)
    q = 0
    for k in range(S):
        a, b = start[k], start[k + 1]
        if b - a >= 2 and _inside(pts, a, b, width, height):  # the loop below would keep it whole: say so
            ps[q], pa[q], pb[q], pw[q], pf[q], pc[q], pcut[q] = k, 0.0, 0.0, True, meta[k, FRAG], meta[k, CLOSED], 0
            q += 1
            continue
        _stroke_arcs(pts, start, k, arc, L)
        open_run = False
        ja, t0a = 0, 0.0
        prev_keep, prev_t1 = False, 0.0
        for i in range(a, b - 1):
            t0, t1, keep = _liang_barsky(pts[i, 0], pts[i, 1], pts[i + 1, 0], pts[i + 1, 1], width, height)
            keep = keep and t1 > t0
            joins = open_run and keep and prev_keep and prev_t1 >= 1 and t0 <= 0 and i > a
            if open_run and not joins:  # close the run that ended at pair i - 1
                pa[q], pb[q], whole = _clip_part(pts, arc, a, b, ja, t0a, i - 1, prev_t1)
                ps[q], pw[q] = k, whole
                pf[q], pc[q], pcut[q] = _part_meta(meta[k, FRAG], meta[k, CLOSED], whole)
                q += 1
                open_run = False
            if keep and not open_run:
                open_run, ja, t0a = True, i, t0
            prev_keep, prev_t1 = keep, t1
        if open_run:
            pa[q], pb[q], whole = _clip_part(pts, arc, a, b, ja, t0a, b - 2, prev_t1)
            ps[q], pw[q] = k, whole
            pf[q], pc[q], pcut[q] = _part_meta(meta[k, FRAG], meta[k, CLOSED], whole)
            q += 1
    return _keep(pts, start, meta, arc, L, ps, pa, pb, pf, pc, pcut, pw, q)


@njit(cache=True, error_model="numpy")
def _dist(pts, i, j):
    dx = pts[j, 0] - pts[i, 0]
    dy = pts[j, 1] - pts[i, 1]
    return math.sqrt(dx * dx + dy * dy)


@njit(cache=True, error_model="numpy")
def _clip_part(pts, arc, a, b, j, t0, e, t1):
    """The run of kept pairs j..e of stroke [a, b) (entering pair j at t0, leaving pair e at t1): its start and end
    arc lengths, and whether it is the whole stroke. (Scalars out, not writes into the pieces: a call that is
    handed arrays to write pays their reference counts, each time.)"""
    whole = j == a and t0 <= 0 and e == b - 2 and t1 >= 1
    return arc[j] + t0 * _dist(pts, j, j + 1), arc[e] + t1 * _dist(pts, e, e + 1), whole


@njit(cache=True, error_model="numpy")
def _part_meta(frag, closed, whole):
    """A clipped run's fragment, closed and cut columns."""
    return (frag, closed, 0) if whole else (max(frag, 0), 0, 1)


# ----------------------------------------------------------------------------- one view of a batch

@njit(cache=True, error_model="numpy")
def _trial_input(tpts, tstart, tmeta, tcorners, cfid, W, CW, R, tv, cams, folds, width, height, calibrated, t,
                 rolling):
    """Trial t's view before the image stages: the strokes and corners through its cameras (when calibrated; under
    the view's rolling shutter when rolling[t, 0], its readout, is > 0: rolling has a row a trial), cut at invalid
    vertices and at the image border, or the template's as they are."""
    if calibrated:
        pts = np.empty((len(W), 2))
        ok = np.empty(len(W), np.bool_)
        if rolling[t, 0] > 0:
            _project_rolling(W, R[t], tv[t], cams[t], folds[t], rolling[t], pts, ok)
        else:
            _project(W, R[t], tv[t], cams[t], folds[t], pts, ok)
        start, meta = tstart, tmeta
        if not ok.all():  # (when all are valid, the cut keeps every stroke verbatim: skip it)
            pts, start, meta = _keep_vertex_runs(pts, tstart, tmeta, ok)
        if not _inside(pts, 0, len(pts), width, height):
            pts, start, meta = _clip_rect(pts, start, meta, width, height)
        cp = np.empty((len(CW), 2))
        cok = np.empty(len(CW), np.bool_)
        if rolling[t, 0] > 0:
            _project_rolling(CW, R[t], tv[t], cams[t], folds[t], rolling[t], cp, cok)
        else:
            _project(CW, R[t], tv[t], cams[t], folds[t], cp, cok)
        for c in range(len(CW)):
            cok[c] = cok[c] and cp[c, 0] >= 0 and cp[c, 0] <= width and cp[c, 1] >= 0 and cp[c, 1] <= height
        return pts, start, meta, cp[cok], cfid[cok]
    return tpts, tstart, tmeta, tcorners, cfid


@njit(cache=True, error_model="numpy")
def _pack(res, cres):
    """The trials' packed strokes res [(pts, start, meta)] and corners cres [(corners, fid)] as one batch:
    (pts, start, meta, trial, corners, fid, trial)."""
    T = len(res)
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


def view_batch(tpts, tstart, tmeta, tcorners, cfid, W, CW, R, tv, cams, folds, width, height, calibrated,
               params, keys, epipole, right, stats, camera, rolling, codes):
    """Every trial of a batch for one view, the image stages `codes` (indices into the loop's table of stage
    functions, in order), the view's rolling shutter `rolling` (run_view's rows, one a trial; readout 0: none).
    Returns packed strokes (pts, start, meta, trial) and corners (corners, fid, trial), strokes and corners ordered
    by trial.

    The template of the compiled loop: `compose` compiles it once per table of stage functions, in a module of its
    own, with the line that calls `_stages` replaced by a dispatch on each stage's code to its function, and the
    line that calls `_workspaces` by a call of each workspace function of the table where a stage's code names it,
    once for the batch (so that the kernel names no effect, and a plug-in's function is composed as a built-in's
    is). The stage list is data: every pipeline of the table's stages (any subset, order and parameters) runs the
    one compiled loop."""
    res = []
    cres = []
    spaces = _workspaces(params, epipole, right, camera, keys.shape[1], codes)  # noqa: F821
    for t in range(keys.shape[1]):
        pts, start, meta, corners, cf = _trial_input(tpts, tstart, tmeta, tcorners, cfid, W, CW, R, tv, cams, folds,
                                                     width, height, calibrated, t, rolling)
        for g in range(len(codes)):
            pts, start, meta, corners, cf = _stages(pts, start, meta, corners, cf, keys, t, params, epipole,  # noqa: F821
                                                    right, stats, camera, spaces, codes, g)
        res.append((pts, start, meta))
        cres.append((corners, cf))
    return _pack(res, cres)


def run_view(tpts, tstart, meta, tcorners, cfid, W, CW, R_cw, t_cw, cams, folds, width, height, calibrated,
             functions, params, keys, epipole, right, stats, cameras=(), camera=None, workspaces=(), rolling=None):
    """The compiled view_batch of the stage functions `functions` (KernelStage.function, in order), with every
    argument in the one layout it is compiled for (no second compile). `cameras`: per function, whether it takes
    the view's `camera` row (KernelStage.camera), float64 (20,): width, height, then the nominal CAMERA_ROW.
    `workspaces`: per function, its workspace function (KernelStage.workspace) or None. `rolling`: the view's
    rolling shutter (View.rolling: readout, height, robot origin, v, w; the origin a trial's each under a
    jittered sync) or None."""
    f2 = lambda a, n: np.ascontiguousarray(a, dtype=np.float64).reshape(-1, n)  # noqa: E731
    i1 = lambda a: np.ascontiguousarray(a, dtype=np.int64).reshape(-1)  # noqa: E731
    stages = tuple(zip(functions, tuple(bool(c) for c in cameras) or (False,) * len(functions),
                       tuple(workspaces) or (None,) * len(functions), strict=True))
    table = stage_table(stages)
    batch = _compose(table)
    n_camera = 2 + len(CAMERA_ROW)  # the image's width and height, then the camera row
    camera = np.zeros(n_camera) if camera is None else np.ascontiguousarray(camera, dtype=np.float64).reshape(n_camera)
    announce_compile(batch)
    return batch(f2(tpts, 2), i1(tstart), np.ascontiguousarray(meta, dtype=np.int64).reshape(-1, NMETA),
                      f2(tcorners, 2), i1(cfid), f2(W, 3), f2(CW, 3),
                      np.ascontiguousarray(R_cw, dtype=np.float64).reshape(-1, 3, 3), f2(t_cw, 3),
                      f2(cams, len(CAMERA_ROW)),
                      np.ascontiguousarray(folds, dtype=np.float64).reshape(-1), float(width), float(height),
                      bool(calibrated), f2(params, params.shape[-1]),
                      np.ascontiguousarray(keys, dtype=np.uint64).reshape(len(functions), len(folds)),
                      np.ascontiguousarray(epipole, dtype=np.float64).reshape(3), bool(right), stats, camera,
                      _rolling_rows(rolling, len(folds)),
                      np.array([table.index(s) for s in stages], dtype=np.int64))


def _rolling_rows(rolling, T: int) -> np.ndarray:
    """The view's rolling shutter (View.rolling, its robot origin (3,) or a trial's each (T, 1, 3)) as a row a
    trial: readout, height, robot origin (3), v (3), w (3); readout 0: none."""
    rows = np.zeros((T, 11))
    if rolling is not None:
        rows[:, 0], rows[:, 1] = rolling[0], rolling[1]
        rows[:, 2:5] = np.asarray(rolling[2], dtype=np.float64).reshape(-1, 3)
        rows[:, 5:8], rows[:, 8:11] = rolling[3], rolling[4]
    return rows


Stage = tuple[str, bool, "str | None"]  # a stage function ("module:attribute"), whether it takes the camera row,
# its workspace function (KernelStage.function, .camera, .workspace)


def builtin_table() -> tuple[Stage, ...]:
    """Every built-in effect's stage function, in the registry's order: the table of the one loop that runs every
    pipeline of built-in stages."""
    from wiredsl.effects import BUILTIN

    return tuple((e.kernel.function, e.kernel.camera, e.kernel.workspace) for e in BUILTIN.values()
                 if e.kernel is not None)


def stage_table(stages: tuple[Stage, ...]) -> tuple[Stage, ...]:
    """The table of stage functions the loop that runs `stages` is compiled for: the built-ins' (`builtin_table`)
    when every stage is a built-in's, so that no pipeline of built-in stages compiles a loop of its own; else these
    stages' functions, each once (a plug-in's pipeline compiles its loop once)."""
    table = _tables.get(stages)
    if table is None:
        builtin = builtin_table()
        table = _tables[stages] = builtin if set(stages) <= set(builtin) else tuple(dict.fromkeys(stages))
    return table


_tables: dict[tuple[Stage, ...], tuple[Stage, ...]] = {}
_composed: dict[tuple[Stage, ...], object] = {}


def compose(functions: tuple[str, ...], cameras: tuple[bool, ...] = (), workspaces: tuple[str | None, ...] = ()):
    """view_batch compiled for a table of stage functions that holds `functions` ("module:attribute" each; with
    their view's camera row where `cameras` says so, and the workspace their workspace function, `workspaces`,
    makes for the view's batch): `stage_table`'s."""
    return _compose(stage_table(tuple(zip(functions, cameras or (False,) * len(functions),
                                          workspaces or (None,) * len(functions), strict=True))))


def _compose(table: tuple[Stage, ...]):
    """view_batch compiled for the table of stage functions `table`: a module written once per table (and per text
    of the source files involved, `_called`, since numba's cache does not follow a change in a called function's
    file) into the user's cache folder, whose `_stages` dispatches on a stage's code to its function with its own
    row of keys, parameters and statistics. Compiled code is cached on disk by numba."""
    batch = _composed.get(table)
    if batch is None:
        batch = _composed[table] = _load(table)
    return batch


def _load(table: tuple[Stage, ...]):
    import hashlib
    import importlib
    import importlib.util
    import inspect
    import os
    import re
    import tempfile
    import time
    from pathlib import Path

    from wiredsl.files import cache_folder, write_atomic

    functions = [f for f, _, _ in table]
    parts = [f.split(":") for f in functions]
    spaces = {c: w.split(":") for c, (_, _, w) in enumerate(table) if w}
    template = inspect.getsource(view_batch)
    stages = re.search(r"^( *)pts, start, meta, corners, cf = _stages\(.*?codes, g\)\n", template, re.M | re.S)
    pad = stages.group(1)
    calls = "".join(f"{pad}{'if' if c == 0 else 'elif'} codes[g] == {c}:\n"
                    f"{pad}    pts, start, meta, corners, cf = _s{c}(pts, start, meta, corners, cf, keys[g, t], "
                    f"params[g], epipole, right, stats[g]{', camera' if cam else ''}"
                    f"{', spaces[g]' if c in spaces else ''})\n"
                    for c, (_, cam, _) in enumerate(table))
    before = re.search(r"^( *)spaces = _workspaces\(.*\n", template, re.M)
    pad = before.group(1)
    made = (f"{pad}spaces = [np.zeros(0) for _ in range(len(codes))]  # the workspace of each stage that has one\n"
            + (f"{pad}for g in range(len(codes)):\n" if spaces else "")
            + "".join(f"{pad}    {'if' if i == 0 else 'elif'} codes[g] == {c}:\n"
                      f"{pad}        spaces[g] = _ws{c}(params[g], epipole, right, camera, keys.shape[1])\n"
                      for i, c in enumerate(spaces)))
    source = ("import numpy as np\nfrom numba import njit\n\n"
              "from wiredsl.engine.kernel import _pack, _trial_input\n"
              + "".join(f"from {module} import {name} as _s{c}\n" for c, (module, name) in enumerate(parts))
              + "".join(f"from {module} import {name} as _ws{c}\n" for c, (module, name) in spaces.items())
              + "\n\n@njit(cache=True, error_model=\"numpy\")\n"
              + template.replace(stages.group(), calls).replace(before.group(), made))
    stamp = hashlib.sha256(source.encode())
    called = _called([getattr(importlib.import_module(module), name)
                      for module, name in [*parts, *spaces.values()]])
    for origin in sorted({__file__} | {f.py_func.__code__.co_filename for f in called}):
        stamp.update(f"{origin}\0{len(data := Path(origin).read_bytes())}\0".encode() + data)
    name = "wiredsl_stages_" + stamp.hexdigest()[:20]
    text = "# generated by wiredsl.engine.kernel.compose for " + ", ".join(functions) + "\n" + source
    folder = cache_folder("kernels") or Path(tempfile.mkdtemp(prefix="wiredsl-kernels-"))  # no cache: this run's
    path = folder / f"{name}.py"
    if not path.exists():  # never rewritten: numba's cache of it is keyed by the file's time stamp
        for f in called:  # compiled anew from the text hashed above: not from a cache keyed by a time stamp
            getattr(getattr(f, "_cache", None), "flush", lambda: None)()
        write_atomic(path, text)
        _prune(folder)
    else:
        try:
            os.utime(path, ns=(time.time_ns(), path.stat().st_mtime_ns))  # used: its access time, not its stamp
        except OSError:
            pass
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module.view_batch


def _called(functions) -> list:
    """The numba functions the compiled loop of these stage functions runs: the stages and every numba function
    they call, followed through the global names each one's code uses (a helper imported from another module of
    a plug-in included, or called as `module.helper`). The generated loop's cache key hashes the text of their
    files and of this module (the loop's template, the projection and the cut): numba's own cache follows only
    the time stamp of the file that defines a function, not the text of the functions it calls, and a time stamp
    moves when a file is checked out again unchanged and can stay put when its text changes."""
    import types

    from numba.core.dispatcher import Dispatcher

    found: dict[int, object] = {}
    todo = list(functions)
    while todo:
        f = todo.pop()
        if id(f) in found or not isinstance(f, Dispatcher):
            continue
        found[id(f)] = f
        code = f.py_func.__code__
        glob, names = f.py_func.__globals__, _names(code)
        used = [glob[n] for n in names if n in glob]
        todo.extend(used)
        todo.extend(getattr(m, n) for m in used if isinstance(m, types.ModuleType) for n in names if hasattr(m, n))
    return list(found.values())


def _names(code) -> set[str]:
    """The global names a function's code (and the code nested in it) uses."""
    names = set(code.co_names)
    for c in code.co_consts:
        if hasattr(c, "co_names"):
            names |= _names(c)
    return names


KEPT_LOOPS = 64  # generated loop modules kept in the cache, the least recently used removed first


def _prune(folder) -> None:
    """Remove the generated loops beyond the KEPT_LOOPS most recently used (by access time, which `_load` sets
    on each use; the modification time is numba's cache key and is left alone), with numba's cache of each."""
    from wiredsl.files import prune_cache

    prune_cache(folder, "wiredsl_stages_*.py", KEPT_LOOPS, lambda p: (folder / "__pycache__").glob(f"{p.stem}.*"))


_announced = False


def announce_compile(batch) -> None:
    """Say on stderr, once, when a kernel is about to be compiled (not when it is loaded from the cache); a study's
    worker processes say nothing (each would say it: the study's own process speaks for them)."""
    import multiprocessing
    import os

    global _announced
    if _announced or batch.signatures or multiprocessing.parent_process() is not None:
        return
    _announced = True
    try:
        index = batch._cache._cache_file._index_path
    except AttributeError:  # numba's internals moved: say it anyway rather than stay silent for a minute
        index = None
    if index is None or not os.path.exists(index):
        print("wiredsl: compiling the Monte-Carlo kernel for these stages (once; numba caches it for later runs)...",
              file=sys.stderr, flush=True)


def loop_cached(stages: tuple[Stage, ...]) -> bool:
    """Whether the compiled loop that runs `stages` is in numba's on-disk cache for this CPU and numba version, so
    that running it loads it instead of compiling it: an entry of the loop's index (numba's own file, read as
    numba reads it: its numba version and the generated file's stamp checked) whose key numba would compute here
    (the same signature, `magic_tuple` of this CPU and the same bytecode), its data file present. Nothing is
    compiled; numba's internals moved: True (the kernel as before this check)."""
    import os

    batch = _compose(stage_table(stages))
    if batch.signatures:
        return True
    try:
        cache = batch._cache
        codegen = batch.targetctx.codegen()
        entries = cache._cache_file._load_index()
        return any(key == cache._index_key(key[0], codegen) and os.path.exists(cache._cache_file._data_path(name))
                   for key, name in entries.items())
    except (AttributeError, TypeError, IndexError):
        return True


def warm(functions: tuple[str, ...] = (), cameras: tuple[bool, ...] = (), workspaces: tuple[str | None, ...] = ()
         ) -> None:
    """Compile (or load from the cache) the kernel of a stage list on a tiny view, e.g. once before parallel test
    workers."""
    z2, zi, G = np.zeros((0, 2)), np.zeros(0, np.int64), len(functions)
    run_view(np.array([[0.0, 0.0], [1.0, 1.0]]), np.array([0, 2]), np.zeros((1, NMETA), np.int64), z2, zi,
             np.zeros((2, 3)), np.zeros((0, 3)), np.eye(3)[None], np.zeros((1, 3)), np.ones((1, len(CAMERA_ROW))),
             np.ones(1), 10.0, 10.0, True, functions, np.zeros((G, 3)), np.ones((G, 1), np.uint64), np.ones(3), True,
             np.zeros((G, NSTAT)), cameras, None, workspaces)


def record(name: str, columns, row: np.ndarray, stats) -> None:
    """Add one view's statistics row of stage `name` (its KernelStage's `stats` columns) to the run's Stats."""
    for (key, how), value in zip(columns, row, strict=False):
        (stats.add if how == "add" else stats.peak)(name, **{key: value})


@njit(cache=True, error_model="numpy")
def distort_radtan(x, y, k1, k2, p1, p2, k3, k4, k5, k6):
    """`geometry.distort_xy` of one unit-plane point, operation for operation (a zero denominator gives inf or NaN,
    never an exception)."""
    r2 = x * x + y * y
    radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


@njit(cache=True, error_model="numpy")
def radtan_jacobian(x, y, k1, k2, p1, p2, k3, k4, k5, k6):
    """The Jacobian (j11, j12, j22; j21 = j12) of `distort_radtan` at one point, as `geometry.undistort_radtan`'s
    Newton step computes it."""
    r2 = x * x + y * y
    num, den = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)), 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    rad = num / den
    g = 2.0 * ((k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)) * den - num * (k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2))) \
        / (den * den)
    return (rad + g * x * x + 2.0 * p1 * y + 6.0 * p2 * x, g * x * y + 2.0 * p1 * x + 2.0 * p2 * y,
            rad + g * y * y + 6.0 * p1 * y + 2.0 * p2 * x)
