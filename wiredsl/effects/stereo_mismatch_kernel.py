"""The compiled kernel of stereo_mismatch (numba), its stage function `stage` (see wiredsl.engine.kernel for the
signature); imported only when a run uses the kernel."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from wiredsl.engine.kernel import (CLOSED, FRAG, _arcs, _keep, _pieces, _stable_sum, _total_length, _uniform, _unroll,
                                   distort_radtan, radtan_jacobian)


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
        return tx / norm, ty / norm
    return _epi_dir(x, y, e0, e1, e2)


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


@njit(cache=True)
def _drop_band(pts, start, meta, e, band, cam):
    """stereo_mismatch._drop_band, and the strokes' total length before it. Each segment's angle is computed once: slot start[k] + i holds segment
    i of stroke k, the last slot of a closed stroke its closing segment (an unrolled loop reuses them)."""
    S = len(start) - 1
    everything = band >= math.pi / 2
    e0, e1, e2 = e[0], e[1], e[2]
    tanb = math.tan(band) if not everything else 0.0
    curved = _curved(cam)
    inside = np.zeros(len(pts), np.bool_)
    cut_loop = np.zeros(S, np.bool_)
    intact = np.zeros(S, np.bool_)
    for k in range(S):
        a, b = start[k], start[k + 1]
        hit = False
        for i in range(a, b - 1):
            inside[i] = _in_band(pts[i, 0], pts[i, 1], pts[i + 1, 0], pts[i + 1, 1], e0, e1, e2, tanb, everything,
                                 curved, cam)
            hit = hit or inside[i]
        if meta[k, CLOSED] != 0:
            if b - a > 1:
                inside[b - 1] = _in_band(pts[b - 1, 0], pts[b - 1, 1], pts[a, 0], pts[a, 1], e0, e1, e2, tanb,
                                         everything, curved, cam)
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
def stage(pts, start, meta, corners, cfid, key, params, e, right, st, camera):
    band, fraction, disparity = params[0], params[1], params[2]
    if band > 0 and len(start) > 1:
        pts, start, meta, before = _drop_band(pts, start, meta, e, band, camera)
        st[0] += before
        st[1] += _total_length(pts, start)
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
        st[2] += 1
        st[3] += 1 if hit else 0
        st[4] = max(st[4], abs(shift))
    return out, start, meta, corners, cfid
