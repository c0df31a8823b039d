"""Geometry as small vectorised functions whose names say their frames.

Frames: world (x, y on the floor, z up); robot (x forward, y left, z up);
camera (OpenCV: x right, y down, z along the optical axis); the unit focal
plane (x/z, y/z, undistorted); pixels (u right, v down, origin at the top-left
corner of the image).

Camera model (TINA's, in OpenCV's terms):
    (x, y) = (X/Z, Y/Z),  r^2 = x^2 + y^2
    x_d = x (1 + k1 r^2 + k2 r^4) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y (1 + k1 r^2 + k2 r^4) + p1 (r^2 + 2 y^2) + 2 p2 x y
    u = f ax x_d + cx,  v = f ay y_d + cy
with k1 = -k for TINA's k (TINA: v = (1 - k r^2) w).

Points behind the camera, or nearer than `NEAR` to its plane, are never
projected: callers clip in 3D first. Points beyond the radius where radial
distortion folds back (d r_d / d r = 0) are not projected either.
"""

from __future__ import annotations

import math

import numpy as np

NEAR = 1e-3  # metres: the near plane; nothing closer to the camera plane is projected


def rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def camera_from_world(pose: tuple[float, float, float], mount_rotation, mount_position):
    """(R_cw, t_cw) with P_cam = R_cw @ P_world + t_cw, for a camera mounted on the robot at `pose`.

    pose = (x, y, heading); mount_rotation is robot_from_camera (3, 3); mount_position in the robot frame.
    """
    x, y, heading = pose
    R_wr = rot_z(heading)
    R_wc = R_wr @ np.asarray(mount_rotation, dtype=float)
    t_wc = R_wr @ np.asarray(mount_position, dtype=float) + np.array([x, y, 0.0])
    R_cw = R_wc.T
    return R_cw, -R_cw @ t_wc


def world_to_cam(P_world: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray) -> np.ndarray:
    """P_cam, shape (..., 3), from P_world, shape (..., 3)."""
    return P_world @ R_cw.T + t_cw


def cam_to_plane(P_cam: np.ndarray) -> np.ndarray:
    """Unit focal plane (x/z, y/z), shape (..., 2); P_cam must be in front (z > 0)."""
    return P_cam[..., :2] / P_cam[..., 2:3]


def distort(xy: np.ndarray, k1: float, k2: float = 0.0, p1: float = 0.0, p2: float = 0.0) -> np.ndarray:
    """Distorted unit-plane coordinates (OpenCV's k1, k2, p1, p2), shape (..., 2)."""
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + k2 * r2)
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def plane_to_pixels(xy_d: np.ndarray, f: float, ax: float, ay: float, cx: float, cy: float) -> np.ndarray:
    """Pixels (u, v) from distorted unit-plane coordinates, shape (..., 2)."""
    return np.stack([f * ax * xy_d[..., 0] + cx, f * ay * xy_d[..., 1] + cy], axis=-1)


def cam_to_pixels(P_cam: np.ndarray, cam) -> np.ndarray:
    """The whole chain for points in front of the camera: P_cam (..., 3) -> pixels (..., 2)."""
    xy = cam_to_plane(P_cam)
    return plane_to_pixels(distort(xy, cam.k1, cam.k2, cam.p1, cam.p2), cam.f, cam.ax, cam.ay, cam.cx, cam.cy)


def is_distorted(cam) -> bool:
    return any(c != 0.0 for c in (cam.k1, cam.k2, cam.p1, cam.p2))


def fold_radius(k1: float, k2: float = 0.0) -> float:
    """Smallest unit-plane radius where r (1 + k1 r^2 + k2 r^4) stops increasing (inf if never).

    Beyond it the radial mapping folds back and is no longer one-to-one, so nothing
    there is projected (tangential terms, small in practice, are not considered).
    """
    # d/dr = 1 + 3 k1 r^2 + 5 k2 r^4 = 0: a s^2 + b s + 1 = 0 in s = r^2, solved in the stable form
    # (q = -(b + sign(b) sqrt(disc)) / 2, roots q / a and 1 / q) so that a tiny a cannot overflow
    a, b = 5.0 * k2, 3.0 * k1
    disc = b * b - 4.0 * a
    if disc < 0:
        return math.inf
    q = -0.5 * (b + math.copysign(math.sqrt(disc), b))
    roots = [1.0 / q if q != 0 else math.inf]
    if a != 0:
        roots.append(q / a)
    positive = [s for s in roots if math.isfinite(s) and s > 0]
    return math.sqrt(min(positive)) if positive else math.inf


def clip_segments_cone(A: np.ndarray, B: np.ndarray, near: float, r_max: float):
    """Clip camera-frame segments A->B (n, 3) to the convex region z >= near and x^2 + y^2 <= r_max^2 z^2.

    Returns (t0, t1, keep): the kept part is A + t (B - A) for t in [t0, t1].
    """
    D = B - A
    t0 = np.zeros(len(A))
    t1 = np.ones(len(A))
    # z(t) = Az + t Dz >= near
    dz, az = D[:, 2], A[:, 2]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        tz = (near - az) / dz
    rising = dz > 0
    falling = dz < 0
    t0 = np.where(rising, np.maximum(t0, tz), t0)
    t1 = np.where(falling, np.minimum(t1, tz), t1)
    keep = ~((dz == 0) & (az < near))
    if r_max < 1e6:  # beyond that (89.99994 deg off-axis) nothing can be imaged anyway; avoids overflow
        # q(t) = a t^2 + b t + c <= 0 with q = x^2 + y^2 - r^2 z^2; a convex region meets a line in one interval
        r2 = r_max * r_max
        a = D[:, 0] ** 2 + D[:, 1] ** 2 - r2 * D[:, 2] ** 2
        b = 2.0 * (A[:, 0] * D[:, 0] + A[:, 1] * D[:, 1] - r2 * A[:, 2] * D[:, 2])
        c = A[:, 0] ** 2 + A[:, 1] ** 2 - r2 * A[:, 2] ** 2
        lo, hi, any_in = _quadratic_nonpositive(a, b, c, D[:, 2])
        t0 = np.maximum(t0, lo)
        t1 = np.minimum(t1, hi)
        keep &= any_in
    keep &= t1 > t0
    return t0, t1, keep


def _quadratic_nonpositive(a, b, c, dz):
    """Interval (lo, hi) of t where a t^2 + b t + c <= 0 and the line is on the z > 0 nappe.

    q(t) = x^2 + y^2 - r^2 z^2 along the line A + t D; the region is convex, so the set is
    one interval. With a > 0 it lies between the roots; with a < 0 the direction is inside
    the cone, the line crosses both nappes, and the front nappe's part is the ray on the
    side where z grows (the sign of dz).
    """
    n = len(a)
    lo = np.full(n, -np.inf)
    hi = np.full(n, np.inf)
    scale = np.maximum(np.maximum(np.abs(a), np.abs(b)), np.abs(c)) + 1e-300
    lin = np.abs(a) <= 1e-12 * scale
    disc = b * b - 4 * a * c
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        sq = np.sqrt(np.maximum(disc, 0.0))
        q = -0.5 * (b + np.where(b >= 0, sq, -sq))  # stable roots: q / a and c / q
        r1, r2 = q / a, c / q
        tl = -c / b
    rlo, rhi = np.fmin(r1, r2), np.fmax(r1, r2)
    quad_up = ~lin & (a > 0)
    quad_down = ~lin & (a < 0)
    lo = np.where(quad_up, rlo, lo)
    hi = np.where(quad_up, rhi, hi)
    lo = np.where(quad_down & (dz > 0), rhi, lo)
    hi = np.where(quad_down & (dz < 0), rlo, hi)
    lo = np.where(lin & (b < 0), tl, lo)
    hi = np.where(lin & (b > 0), tl, hi)
    any_in = ~(quad_up & (disc < 0)) & ~(lin & (b == 0) & (c > 0))
    return lo, hi, any_in


def clip_segments_rect(a: np.ndarray, b: np.ndarray, width: float, height: float):
    """Liang-Barsky: clip 2D segments a->b (n, 2) to [0, width] x [0, height].

    Returns (t0, t1, keep) with the kept part a + t (b - a), t in [t0, t1].
    """
    d = b - a
    t0 = np.zeros(len(a))
    t1 = np.ones(len(a))
    keep = np.ones(len(a), dtype=bool)
    for p, q in ((-d[:, 0], a[:, 0]), (d[:, 0], width - a[:, 0]), (-d[:, 1], a[:, 1]), (d[:, 1], height - a[:, 1])):
        parallel = p == 0
        keep &= ~(parallel & (q < 0))
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            r = q / p
        t0 = np.where(~parallel & (p < 0), np.maximum(t0, r), t0)
        t1 = np.where(~parallel & (p > 0), np.minimum(t1, r), t1)
    keep &= t0 <= t1
    return t0, t1, keep


def adaptive_samples(point_fn, t0: np.ndarray, t1: np.ndarray, tol: float, start: int = 8, max_depth: int = 20):
    """Parameters at which to sample curves so that the polyline stays within `tol` of each curve.

    point_fn(curve_index (m,), t (m,)) -> points (m, 2). Curves are sampled on `start`
    equal intervals, then any interval whose midpoint lies further than tol from its
    chord is halved, until none does (or max_depth halvings). Returns a list of sorted
    parameter arrays, one per curve.
    """
    n = len(t0)
    grid = np.linspace(0.0, 1.0, start + 1)
    ts = t0[:, None] + (t1 - t0)[:, None] * grid[None, :]
    cid = np.repeat(np.arange(n), start)
    ta = ts[:, :-1].ravel()
    tb = ts[:, 1:].ravel()
    done_c, done_t = [np.repeat(np.arange(n), start + 1)], [ts.ravel()]
    for _ in range(max_depth):
        if len(ta) == 0:
            break
        tm = 0.5 * (ta + tb)
        pa, pb, pm = point_fn(cid, ta), point_fn(cid, tb), point_fn(cid, tm)
        dev = _distance_to_chord(pm, pa, pb)
        split = dev > tol
        done_c.append(cid[split])
        done_t.append(tm[split])
        cid, ta, tb, tm = cid[split], ta[split], tb[split], tm[split]
        cid = np.concatenate([cid, cid])
        ta, tb = np.concatenate([ta, tm]), np.concatenate([tm, tb])
    all_c = np.concatenate(done_c)
    all_t = np.concatenate(done_t)
    order = np.lexsort((all_t, all_c))
    all_c, all_t = all_c[order], all_t[order]
    bounds = np.searchsorted(all_c, np.arange(n + 1))
    return [all_t[bounds[i]:bounds[i + 1]] for i in range(n)]


def _distance_to_chord(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = b - a
    length = np.hypot(d[:, 0], d[:, 1])
    cross = np.abs(d[:, 0] * (p[:, 1] - a[:, 1]) - d[:, 1] * (p[:, 0] - a[:, 0]))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        perp = cross / length
    return np.where(length > 0, perp, np.hypot(p[:, 0] - a[:, 0], p[:, 1] - a[:, 1]))


def clip_polyline_rect(points: np.ndarray, width: float, height: float) -> list[tuple[np.ndarray, bool]]:
    """Cut a 2D polyline (k, 2) to the image rectangle: the visible pieces, each flagged if cut."""
    if len(points) < 2:
        return []
    x, y = points[:, 0], points[:, 1]
    if x.min() >= 0 and y.min() >= 0 and x.max() <= width and y.max() <= height:
        return [(points, False)] if np.ptp(points, axis=0).max() > 0 else []
    a, b = points[:-1], points[1:]
    t0, t1, keep = clip_segments_rect(a, b, width, height)
    d = b - a
    starts = a + t0[:, None] * d
    ends = a + t1[:, None] * d
    pieces: list[tuple[np.ndarray, bool]] = []
    current: list[np.ndarray] = []
    cut = False
    for i in range(len(a)):
        if not keep[i]:
            if current:
                pieces.append((np.array(current), True))
                current = []
            cut = True
            continue
        if t0[i] > 0 or not current:
            if current:
                pieces.append((np.array(current), True))
            current = [starts[i]]
            if t0[i] > 0:
                cut = True
        current.append(ends[i])
        if t1[i] < 1:
            pieces.append((np.array(current), True))
            current = []
            cut = True
    if current:
        pieces.append((np.array(current), cut))
    return [(p, c) for p, c in pieces if len(p) >= 2 and np.ptp(p, axis=0).max() > 0]
