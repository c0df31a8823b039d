"""The compiled kernel of stereo_mismatch (numba), its stage function `stage` (see wiredsl.engine.kernel for the
signature); imported only when a run uses the kernel."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from wiredsl.engine.kernel import (
    CLOSED,
    FRAG,
    _keep,
    _pieces,
    _stable_sum,
    _stroke_arcs,
    _total_length,
    _uniform,
    _unroll,
    distort_radtan,
    radtan_jacobian,
)


@njit(cache=True)
def _epi_dir(x, y, e0, e1, e2):
    dx = x * e2 - e0
    dy = y * e2 - e1
    n = math.sqrt(dx * dx + dy * dy)
    if n > 0:
        return dx / n, dy / n
    return 1.0, 0.0


NUDGE = 1e-4  # stereo_mismatch.NUDGE
NEWTON_TOL = 1e-14  # geometry.NEWTON_TOL


@njit(cache=True, error_model="numpy")
def _undistort(xd, yd, k1, k2, p1, p2, k3, k4, k5, k6):
    """geometry.undistort_radtan of one point from itself (20 Newton steps at most, tol NEWTON_TOL), NaN where its
    residual is not below 1e-12."""
    x, y = xd, yd
    for _ in range(20):
        j11, j12, j22 = radtan_jacobian(x, y, k1, k2, p1, p2, k3, k4, k5, k6)
        ex, ey = distort_radtan(x, y, k1, k2, p1, p2, k3, k4, k5, k6)
        r0, r1 = ex - xd, ey - yd
        if abs(r0) <= NEWTON_TOL and abs(r1) <= NEWTON_TOL:
            break
        det = j11 * j22 - j12 * j12
        x, y = x - (j22 * r0 - j12 * r1) / det, y - (j11 * r1 - j12 * r0) / det
    ex, ey = distort_radtan(x, y, k1, k2, p1, p2, k3, k4, k5, k6)
    if abs(ex - xd) < 1e-12 and abs(ey - yd) < 1e-12:
        return x, y
    return math.nan, math.nan


@njit(cache=True, error_model="numpy")
def _theta(r, cam):
    """geometry.lens_theta of one radius (NaN where there is none), the camera a kernel camera row."""
    model = int(cam[19])
    xi, a, b, w = cam[15], cam[16], cam[17], cam[18]
    r2 = r * r
    if model == 1:
        k1, k2, k3, k4 = cam[7], cam[8], cam[11], cam[12]
        theta = r
        for _ in range(20):
            t2 = theta * theta
            slope = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
            res = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - r
            if abs(res) <= NEWTON_TOL:
                break
            theta = theta - res / slope
        t2 = theta * theta
        if not abs(theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - r) < 1e-12:
            return math.nan
    elif model == 2:
        f = (xi + math.sqrt(1.0 + (1.0 - xi * xi) * r2)) / (1.0 + r2)
        theta = math.atan2(f * r, f - xi)
    elif model == 3:
        z = (1.0 - b * a * a * r2) / (a * math.sqrt(1.0 - (2.0 * a - 1.0) * b * r2) + 1.0 - a)
        theta = math.atan2(r, z)
    elif model == 4:
        mz = (1.0 - a * a * r2) / (a * math.sqrt(1.0 - (2.0 * a - 1.0) * r2) + 1.0 - a)
        k = (mz * xi + math.sqrt(mz * mz + (1.0 - xi * xi) * r2)) / (mz * mz + r2)
        theta = math.atan2(k * r, k * mz - xi)
    elif model == 5:
        theta = math.atan(math.tan(r * w) / (2.0 * math.tan(0.5 * w))) if r * w < 0.5 * math.pi else math.nan
    else:
        theta = math.atan(r)
    return theta if math.isfinite(theta) and theta >= 0 else math.nan


@njit(cache=True, error_model="numpy")
def _pixel_ray(u, v, cam):
    """geometry.pixels_to_rays_newton of one pixel, the camera a kernel camera row (KernelStage.camera)."""
    model = int(cam[19])
    k1, k2, p1, p2, k3, k4, k5, k6 = cam[7], cam[8], cam[9], cam[10], cam[11], cam[12], cam[13], cam[14]
    mx = (u - cam[5]) / (cam[2] * cam[3])
    my = (v - cam[6]) / (cam[2] * cam[4])
    if (model == 0 or model == 2) and (k1 != 0 or k2 != 0 or p1 != 0 or p2 != 0 or k3 != 0 or k4 != 0 or k5 != 0
                                       or k6 != 0):
        mx, my = _undistort(mx, my, k1, k2, p1, p2, k3, k4, k5, k6)
    if model == 0:
        n = math.sqrt(mx * mx + my * my + 1.0)
        return mx / n, my / n, 1.0 / n
    r = math.hypot(mx, my)
    theta = _theta(r, cam)
    s = math.sin(theta) / r if r > 0 else 0.0
    return mx * s, my * s, math.cos(theta)


@njit(cache=True, error_model="numpy")
def _pixel(X, Y, Z, cam):
    """geometry.project_xyz of one camera point, the camera a kernel camera row (no lens-limit test: NaN where the
    model has no image, as geometry.model_plane_xy)."""
    model = int(cam[19])
    k1, k2, p1, p2, k3, k4, k5, k6 = cam[7], cam[8], cam[9], cam[10], cam[11], cam[12], cam[13], cam[14]
    xi, a, beta, w = cam[15], cam[16], cam[17], cam[18]
    if model == 0:
        if Z > 0:
            xd, yd = distort_radtan(X / Z, Y / Z, k1, k2, p1, p2, k3, k4, k5, k6)
        else:
            xd, yd = math.nan, math.nan
    elif model == 1:
        rho = math.hypot(X, Y)
        theta = math.atan2(rho, Z)
        t2 = theta * theta
        td = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        scale = td / rho if rho > 0 else (0.0 if Z > 0 else math.nan)
        xd, yd = scale * X, scale * Y
    elif model == 5:
        rho = math.hypot(X, Y)
        two_tan = 2.0 * math.tan(0.5 * w)
        scale = math.atan2(rho * two_tan, Z) / (w * rho) if rho > 0 else two_tan / (w * Z)
        xd, yd = scale * X, scale * Y
    else:
        r2 = X * X + Y * Y
        d = math.sqrt(r2 + Z * Z)
        if model == 2:
            den = _stable_sum(xi * d, Z, xi * xi * r2 - (1.0 - xi) * (1.0 + xi) * (Z * Z))
            xd, yd = distort_radtan(X / den, Y / den, k1, k2, p1, p2, k3, k4, k5, k6)
        else:
            if model == 3:
                den = _stable_sum(a * math.sqrt(beta * r2 + Z * Z), (1.0 - a) * Z,
                                  a * a * beta * r2 + (2.0 * a - 1.0) * (Z * Z))
            else:
                zs = _stable_sum(xi * d, Z, xi * xi * r2 - (1.0 - xi) * (1.0 + xi) * (Z * Z))
                den = _stable_sum(a * math.sqrt(r2 + zs * zs), (1.0 - a) * zs, a * a * r2 + (2.0 * a - 1.0) * (zs * zs))
            xd, yd = X / den, Y / den
    return cam[2] * cam[3] * xd + cam[5], cam[2] * cam[4] * yd + cam[6]


@njit(cache=True, error_model="numpy")
def _tangent(x, y, e0, e1, e2, cam):
    """stereo_mismatch.epipolar_tangents of one point: the unit tangent of the epipolar curve through it (the
    pinhole direction, _epi_dir, where there is none)."""
    tx, ty, found = _curve_tangent(x, y, e0, e1, e2, cam)
    if found:
        return tx, ty
    return _epi_dir(x, y, e0, e1, e2)


@njit(cache=True, error_model="numpy")
def _curve_tangent(x, y, e0, e1, e2, cam):
    """The unit tangent of the epipolar curve through a point and whether there is one (_tangent without its
    fallback)."""
    dx, dy, dz = _pixel_ray(x, y, cam)
    Xx = (e0 - cam[5] * e2) / (cam[2] * cam[3])
    Xy = (e1 - cam[6] * e2) / (cam[2] * cam[4])
    Xz = e2
    step = NUDGE / math.sqrt(Xx * Xx + Xy * Xy + Xz * Xz)
    Xx, Xy, Xz = Xx * step, Xy * step, Xz * step
    ua, va = _pixel(dx - Xx, dy - Xy, dz - Xz, cam)
    ub, vb = _pixel(dx + Xx, dy + Xy, dz + Xz, cam)
    tx, ty = ua - ub, va - vb
    norm = math.sqrt(tx * tx + ty * ty)
    if math.isfinite(norm) and norm > 0:
        return tx / norm, ty / norm, True
    return 0.0, 0.0, False


@njit(cache=True)
def _curved(cam):
    """geometry.is_distorted of a kernel camera row: whether its epipolar lines are curves."""
    return cam[19] != 0 or (cam[7] != 0 or cam[8] != 0 or cam[9] != 0 or cam[10] != 0 or cam[11] != 0
                            or cam[12] != 0 or cam[13] != 0 or cam[14] != 0)


@njit(cache=True)
def _in_band(ax, ay, bx, by, e0, e1, e2, tanb, everything, curved, cam):
    """stereo_mismatch.in_band for one segment (the epipole as scalars: a call handed an array may pay its
    reference count each time); `curved`: the camera row's lens is distorted (the curve's tangent, _tangent)."""
    if everything:
        return True
    if curved:
        lx, ly = _tangent((ax + bx) / 2, (ay + by) / 2, e0, e1, e2, cam)
    else:
        lx = (ax + bx) / 2 * e2 - e0
        ly = (ay + by) / 2 * e2 - e1
        if lx == 0 and ly == 0:
            lx, ly = 1.0, 0.0
    dx, dy = bx - ax, by - ay
    return abs(dx * ly - dy * lx) <= tanb * abs(dx * lx + dy * ly)


# ----------------------------------------------------------------------------- the view's table of tangents
# Under a distorted lens the band's direction at a segment is the epipolar curve's tangent at its midpoint,
# `_tangent`: an undistortion by Newton's method and two projections, some 100 ns. The view's workspace holds a
# table of it over the image (`workspace`, once per view and batch), interpolated at each midpoint, with a
# bound on the interpolation's angular error per cell; a segment whose angle to the interpolated direction is
# farther than that bound from the band's edge is decided by the table, the rest by `_tangent` itself. The
# decisions are `_in_band`'s, so the outputs are the same bytes. Before the table, a gate: every tangent over
# the table lies within a cone about one direction, and a segment far enough outside that cone is outside the
# band wherever it is (most segments: the lab's epipolar curves are near horizontal).

GRID = 64.0  # pixels between the table's nodes
EDGE = 8.0  # pixels the table reaches beyond the image (the stages before the band move points a little)
SAFETY = 4.0  # a cell's bound: this many times the largest error sampled in it, plus TINY
TINY = 1e-9  # radians: far above the rounding of the band's test (some 1e-16 relative)
FEW = 4  # trials a batch below which no table is made (it costs some 400 tangents a view)
HEAD = 8  # the header: nodes across and down, the first node's x and y, 1 / spacing, the gate's direction, its tangent


@njit(cache=True)
def workspace(params, e, right, camera, trials):
    """The view's table of epipolar tangents (its workspace, see KernelStage.workspace): the header, the unit
    tangents at nodes GRID apart covering the image and EDGE beyond it (x components, then y, row by row), then
    per cell the tangents of band - d and of band + d, with d its bound (SAFETY times the largest angle between the
    interpolated and the exact tangent at the cell's edge midpoints and centre, plus TINY; where a sample has no
    curve, or a bound reaches 0 or pi/2, -1 and inf: nothing decided there). The gate: the nodes' mean direction
    c and the tangent of band + s + d, with s the largest angle of a node from c and d the largest bound (inf where
    a cell has none or the angle reaches pi/2): a bilinear mean of the nodes lies in their cone about c, and the
    true tangent within d of it. Empty where the band needs none: no band, every direction, a pinhole, fewer than
    FEW trials."""
    band = params[0]
    if not (band > 0 and band < math.pi / 2) or not _curved(camera) or trials < FEW:
        return np.zeros(0)
    e0, e1, e2 = e[0], e[1], e[2]
    nx = int(math.ceil((camera[0] + 2 * EDGE) / GRID)) + 1
    ny = int(math.ceil((camera[1] + 2 * EDGE) / GRID)) + 1
    fine_x, fine_y = 2 * nx - 1, 2 * ny - 1  # nodes and the points halfway between them
    tx, ty = np.empty((fine_y, fine_x)), np.empty((fine_y, fine_x))
    found = np.empty((fine_y, fine_x), np.bool_)
    for j in range(fine_y):
        for i in range(fine_x):
            tx[j, i], ty[j, i], found[j, i] = _curve_tangent(-EDGE + i * GRID / 2, -EDGE + j * GRID / 2, e0, e1, e2,
                                                             camera)
    m, c = nx * ny, (nx - 1) * (ny - 1)
    ws = np.empty(HEAD + 2 * m + 2 * c)
    ws[0], ws[1], ws[2], ws[3], ws[4] = nx, ny, -EDGE, -EDGE, 1.0 / GRID
    cx, cy = 0.0, 0.0
    for j in range(ny):
        for i in range(nx):
            ws[HEAD + j * nx + i] = tx[2 * j, 2 * i]
            ws[HEAD + m + j * nx + i] = ty[2 * j, 2 * i]
            cx, cy = cx + tx[2 * j, 2 * i], cy + ty[2 * j, 2 * i]
    gate = True
    spread, widest = 0.0, 0.0
    for j in range(ny):
        for i in range(nx):
            dot = cx * tx[2 * j, 2 * i] + cy * ty[2 * j, 2 * i]
            gate = gate and found[2 * j, 2 * i] and dot > 0
            spread = max(spread, math.atan2(abs(cx * ty[2 * j, 2 * i] - cy * tx[2 * j, 2 * i]), dot))
    for j in range(ny - 1):
        for i in range(nx - 1):
            good = True
            worst = 0.0
            for b in range(3):
                for a in range(3):
                    jj, ii = 2 * j + b, 2 * i + a
                    good = good and found[jj, ii]
                    if a % 2 == 0 and b % 2 == 0:
                        continue
                    u, v = a / 2, b / 2
                    lx = ((1 - u) * (1 - v) * tx[2 * j, 2 * i] + u * (1 - v) * tx[2 * j, 2 * i + 2]
                          + (1 - u) * v * tx[2 * j + 2, 2 * i] + u * v * tx[2 * j + 2, 2 * i + 2])
                    ly = ((1 - u) * (1 - v) * ty[2 * j, 2 * i] + u * (1 - v) * ty[2 * j, 2 * i + 2]
                          + (1 - u) * v * ty[2 * j + 2, 2 * i] + u * v * ty[2 * j + 2, 2 * i + 2])
                    dot = lx * tx[jj, ii] + ly * ty[jj, ii]
                    good = good and dot > 0
                    worst = max(worst, math.atan2(abs(lx * ty[jj, ii] - ly * tx[jj, ii]), dot))
            d = SAFETY * worst + TINY
            ok = good and band - d > 0 and band + d < math.pi / 2
            gate = gate and ok
            widest = max(widest, d)
            ws[HEAD + 2 * m + j * (nx - 1) + i] = math.tan(band - d) if ok else -1.0
            ws[HEAD + 2 * m + c + j * (nx - 1) + i] = math.tan(band + d) if ok else math.inf
    norm = math.sqrt(cx * cx + cy * cy)
    ws[5], ws[6] = (cx / norm, cy / norm) if norm > 0 else (1.0, 0.0)
    cone = band + spread + widest
    ws[7] = math.tan(cone) if gate and cone < math.pi / 2 else math.inf
    return ws


@njit(cache=True, inline="always")
def _table(ws, mx, my, dx, dy):
    """The band's decision for a segment (dx, dy) with midpoint (mx, my) from the view's table: 1 within the band,
    0 outside, -1 not decided (outside the table, or within its bound of the band's edge)."""
    u, v = (mx - ws[2]) * ws[4], (my - ws[3]) * ws[4]
    if not (u >= 0 and v >= 0 and u < ws[0] - 1 and v < ws[1] - 1):
        return -1
    if abs(dx * ws[6] - dy * ws[5]) > ws[7] * abs(dx * ws[5] + dy * ws[6]):  # outside the gate
        return 0
    nx, ny = int(ws[0]), int(ws[1])
    i, j = int(u), int(v)
    fu, fv = u - i, v - j
    m = nx * ny
    n = HEAD + j * nx + i
    w00, w10, w01, w11 = (1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv
    lx = w00 * ws[n] + w10 * ws[n + 1] + w01 * ws[n + nx] + w11 * ws[n + nx + 1]
    ly = w00 * ws[m + n] + w10 * ws[m + n + 1] + w01 * ws[m + n + nx] + w11 * ws[m + n + nx + 1]
    if lx == 0 and ly == 0:
        return -1
    cell = HEAD + 2 * m + j * (nx - 1) + i
    cross, dot = abs(dx * ly - dy * lx), abs(dx * lx + dy * ly)
    if cross <= ws[cell] * dot:
        return 1
    if cross > ws[cell + (nx - 1) * (ny - 1)] * dot:
        return 0
    return -1


@njit(cache=True)
def _drop_band(pts, start, meta, e, band, cam, ws):
    """stereo_mismatch._drop_band, and the strokes' total lengths before and after it (as _total_length sums them).
    Each segment's angle is computed once: slot start[k] + i holds segment i of stroke k, the last slot of a closed
    stroke its closing segment (an unrolled loop reuses them). `ws`: the view's table of tangents (`workspace`), or
    empty. Only the strokes with a segment in the band are measured and cut; with none, the input is returned."""
    S = len(start) - 1
    everything = band >= math.pi / 2
    e0, e1, e2 = e[0], e[1], e[2]
    tanb = math.tan(band) if not everything else 0.0
    curved = _curved(cam)
    table = len(ws) > 0 and not everything
    inside = np.zeros(len(pts), np.bool_)
    cut_loop = np.zeros(S, np.bool_)
    intact = np.zeros(S, np.bool_)
    hits = np.zeros(S, np.bool_)
    for k in range(S):
        a, b = start[k], start[k + 1]
        hit = False
        closed = meta[k, CLOSED] != 0
        for i in range(a, b if closed and b - a > 1 else b - 1):  # a closed stroke's last slot: its closing segment
            j = i + 1 if i < b - 1 else a
            ax, ay, bx, by = pts[i, 0], pts[i, 1], pts[j, 0], pts[j, 1]
            # the table where it decides (in the loop, not in a function handed the arrays: a call per segment
            # that takes an array costs its reference counts, and more than the table itself)
            got = _table(ws, (ax + bx) / 2, (ay + by) / 2, bx - ax, by - ay) if table else -1
            if got < 0:
                got = 1 if _in_band(ax, ay, bx, by, e0, e1, e2, tanb, everything, curved, cam) else 0
            inside[i] = got == 1
            hit = hit or inside[i]
        hits[k] = hit
        if closed:
            cut_loop[k] = hit
            intact[k] = not hit
    before = _total_length(pts, start)
    if not hits.any():  # nothing in the band: the strokes as they are (what the cut below would copy)
        return pts, start, meta, before, before
    upts, ustart, umeta = _unroll(pts, start, meta, cut_loop)
    arc, uL = np.zeros(len(upts)), np.zeros(S)
    ps, pa, pb, pf, pc, pcut, pw = _pieces(len(upts) + S)
    q = 0
    for k in range(S):
        a, b = ustart[k], ustart[k + 1]
        if not hits[k]:  # kept whole: a loop, or an open stroke of a segment or more
            if intact[k] or b - a > 1:
                ps[q], pf[q], pc[q], pw[q] = k, umeta[k, FRAG], umeta[k, CLOSED], True
                q += 1
            continue
        _stroke_arcs(upts, ustart, k, arc, uL)  # arc lengths along the strokes cut only
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
    return out[0], out[1], out[2], before, _total_length(out[0], out[1])


@njit(cache=True)
def stage(pts, start, meta, corners, cfid, key, params, e, right, st, camera, ws):
    band, fraction, disparity = params[0], params[1], params[2]
    if band > 0 and len(start) > 1:
        pts, start, meta, before, after = _drop_band(pts, start, meta, e, band, camera, ws)
        st[0] += before
        st[1] += after
    else:
        before = _total_length(pts, start)
        st[0] += before
        st[1] += before
    if not right or fraction == 0 or disparity == 0:
        return pts, start, meta, corners, cfid
    out = pts.copy()
    curved = _curved(camera)
    for k in range(len(start) - 1):
        u0, u1 = _uniform(key, 2 * k), _uniform(key, 2 * k + 1)
        hit = u0 < fraction
        shift = disparity * (2 * u1 - 1) if hit else 0.0
        a, b = start[k], start[k + 1]
        st[2] += 1
        st[3] += 1 if hit else 0
        st[4] = max(st[4], abs(shift))
        if not hit and not _has_zero(pts, a, b):  # a zero shift moves no point (only a -0.0 would become 0.0)
            continue
        mx, my = 0.0, 0.0
        for i in range(a, b):
            mx += pts[i, 0]
            my += pts[i, 1]
        mx /= b - a
        my /= b - a
        if curved:
            dx, dy = _tangent(mx, my, e[0], e[1], e[2], camera)
        else:
            dx, dy = _epi_dir(mx, my, e[0], e[1], e[2])
        for i in range(a, b):
            out[i, 0] = pts[i, 0] + shift * dx
            out[i, 1] = pts[i, 1] + shift * dy
    return out, start, meta, corners, cfid


@njit(cache=True)
def _has_zero(pts, a, b):
    """Whether a coordinate of vertices a..b-1 is zero (either sign)."""
    for i in range(a, b):
        if pts[i, 0] == 0 or pts[i, 1] == 0:
            return True
    return False
