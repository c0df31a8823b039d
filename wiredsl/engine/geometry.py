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


def world_from_robot(pose) -> tuple[np.ndarray, np.ndarray]:
    """(R_wr (3, 3), t_wr (3,)) with P_world = R_wr @ P_robot + t_wr: the robot's rigid pose in the world.

    `pose` is one of: (x, y, heading), a robot on the floor turned by heading about z; the 12 numbers of
    the row-major [R | t] (3, 4) world_from_robot matrix (a path read from a trajectory file); or a (3, 4)
    or (4, 4) array of it. A floor pose gives exactly rot_z(heading) and (x, y, 0).
    """
    if len(pose) == 3 and np.ndim(pose) == 1:
        x, y, heading = pose
        return rot_z(heading), np.array([x, y, 0.0])
    M = np.asarray(pose, dtype=float)
    if M.shape not in ((12,), (3, 4), (4, 4)):
        raise ValueError(f"a pose is (x, y, heading), [R | t] (3, 4) or (4, 4), not of shape {M.shape}")
    M = M.reshape(-1, 4)
    return M[:3, :3], M[:3, 3].copy()


def floor_pose(pose) -> tuple[float, float, float]:
    """(x, y, heading) of a pose on the floor: its position's x and y, and the heading of its x axis
    projected onto the floor (0 when that axis is vertical). A floor pose is returned as it is."""
    if len(pose) == 3 and np.ndim(pose) == 1:
        return tuple(float(v) for v in pose)
    R, t = world_from_robot(pose)
    return float(t[0]), float(t[1]), math.atan2(R[1, 0], R[0, 0])


def camera_from_world(pose, mount_rotation, mount_position):
    """(R_cw, t_cw) with P_cam = R_cw @ P_world + t_cw, for a camera mounted on the robot at `pose`.

    pose: see `world_from_robot`; mount_rotation is robot_from_camera (3, 3); mount_position in the robot frame.
    """
    R_wr, t_wr = world_from_robot(pose)
    R_wc = R_wr @ np.asarray(mount_rotation, dtype=float)
    t_wc = R_wr @ np.asarray(mount_position, dtype=float) + t_wr
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


def clip_segments_cone(A: np.ndarray, B: np.ndarray, near: float, r_max):
    """Clip camera-frame segments A->B (n, 3) to the convex region z >= near and x^2 + y^2 <= r_max^2 z^2.

    r_max is a scalar or one radius a segment, shape (n,). Returns (t0, t1, keep): the kept part is
    A + t (B - A) for t in [t0, t1].
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
    # beyond r = 1e6 (89.99994 deg off-axis) nothing can be imaged anyway; skipping it avoids overflow
    folds = np.broadcast_to(np.asarray(r_max, dtype=float) < 1e6, (len(A),))
    if folds.any():
        # q(t) = a t^2 + b t + c <= 0 with q = x^2 + y^2 - r^2 z^2; a convex region meets a line in one interval
        sel = np.flatnonzero(folds)
        A_, D_ = A[sel], D[sel]
        r2 = np.broadcast_to(np.asarray(r_max, dtype=float), (len(A),))[sel] ** 2
        a = D_[:, 0] ** 2 + D_[:, 1] ** 2 - r2 * D_[:, 2] ** 2
        b = 2.0 * (A_[:, 0] * D_[:, 0] + A_[:, 1] * D_[:, 1] - r2 * A_[:, 2] * D_[:, 2])
        c = A_[:, 0] ** 2 + A_[:, 1] ** 2 - r2 * A_[:, 2] ** 2
        lo, hi, any_in = _quadratic_nonpositive(a, b, c, D_[:, 2])
        t0[sel] = np.maximum(t0[sel], lo)
        t1[sel] = np.minimum(t1[sel], hi)
        keep[sel] &= any_in
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


MAX_CURVE_VERTICES = 100_000  # the most vertices one curve's polyline may get
MAX_VERTICES = 2_000_000  # the most vertices one packed sampling may create (memory: ~130 bytes each)
EVAL_CHUNK = 1 << 16  # points evaluated at once while sampling: bounds the temporaries


class TooManyVertices(ValueError):
    """The tolerance asks for more vertices than a curve (or a whole projection) may get."""

    def __init__(self, curve: int, limit: int):
        self.curve, self.limit = curve, limit  # curve: index of the curve over the limit, -1 for the total
        super().__init__(f"curve {curve} needs more than {limit} vertices")


def adaptive_samples(point_fn, t0: np.ndarray, t1: np.ndarray, tol: float, start=8, max_depth: int = 20):
    """Parameters at which to sample curves so that each polyline stays within `tol` of its curve.

    point_fn(curve_index (m,), t (m,)) -> points (m, 2). Returns one sorted parameter array per curve
    (see `adaptive_samples_packed`).
    """
    cid, ts, bounds = adaptive_samples_packed(point_fn, t0, t1, tol, start, max_depth)
    return [ts[bounds[i]:bounds[i + 1]] for i in range(len(t0))]


def adaptive_samples_packed(point_fn, t0: np.ndarray, t1: np.ndarray, tol: float, start=8, max_depth: int = 20,
                            max_vertices: int = MAX_CURVE_VERTICES, image=None):
    """Sample parameters of many curves at once so that each polyline stays within `tol` of its curve.

    Curves are sampled on `start` (scalar or one count a curve) equal intervals; an interval is halved
    while the estimated deviation of the curve from its chord exceeds tol, up to max_depth halvings.
    The estimate is sound for curves whose curvature varies slowly over an interval: the largest
    distance of the three quarter points from the chord segment, plus a quarter of the largest second
    difference of the five points across the curve (twice the bound 1/8 |p''| h^2 on the curve
    between those points).
    A midpoint test alone misses curves whose deviation peaks off-centre.
    With image = (width, height) (one each a curve), pieces whose five points all lie beyond one
    border of the image by more than a quarter of its size are not refined: nothing there is seen,
    even after perturbations of a hundred pixels, and curves through the near plane would otherwise
    get vertices by the million.
    Returns (cid, t, bounds): the parameters sorted by curve then t, curve i's are t[bounds[i]:bounds[i+1]].
    Raises TooManyVertices past max_vertices for one curve or MAX_VERTICES in all.
    """
    n = len(t0)
    starts = np.broadcast_to(np.asarray(start, dtype=int), (n,))
    done_c, done_t, live_c, live_a, live_b = [], [], [], [], []
    for k in np.unique(starts):
        rows = np.flatnonzero(starts == k)
        grid = np.linspace(0.0, 1.0, k + 1)
        ts = t0[rows, None] + (t1 - t0)[rows, None] * grid[None, :]
        done_c.append(np.repeat(rows, k + 1))
        done_t.append(ts.ravel())
        live_c.append(np.repeat(rows, k))
        live_a.append(ts[:, :-1].ravel())
        live_b.append(ts[:, 1:].ravel())
    cid = np.concatenate(live_c).astype(int) if live_c else np.zeros(0, dtype=int)
    ta, tb = (np.concatenate(x) if x else np.zeros(0) for x in (live_a, live_b))
    # each live interval keeps its five points (ends, quarters, middle): a halving reuses three of them
    tm = 0.5 * (ta + tb)
    T = np.stack([ta, 0.5 * (ta + tm), tm, 0.5 * (tm + tb), tb], axis=1)
    Pts = _evaluate(point_fn, np.repeat(cid, 5), T.ravel()).reshape(-1, 5, 2)
    counts = starts + 1
    total = int(counts.sum())
    for _ in range(max_depth):
        if len(cid) == 0:
            break
        split = _deviation(Pts, cid, image) > tol
        cid, T, Pts = cid[split], T[split], Pts[split]
        done_c.append(cid)
        done_t.append(T[:, 2])
        counts += np.bincount(cid, minlength=n)
        total += len(cid)
        if total > MAX_VERTICES:
            raise TooManyVertices(-1, MAX_VERTICES)
        if len(cid) and counts.max() > max_vertices:
            raise TooManyVertices(int(counts.argmax()), max_vertices)
        new_t = 0.5 * (T[:, :-1] + T[:, 1:])  # the eighths: the children's new quarter points
        new_p = _evaluate(point_fn, np.repeat(cid, 4), new_t.ravel()).reshape(-1, 4, 2)
        left_t = np.stack([T[:, 0], new_t[:, 0], T[:, 1], new_t[:, 1], T[:, 2]], axis=1)
        right_t = np.stack([T[:, 2], new_t[:, 2], T[:, 3], new_t[:, 3], T[:, 4]], axis=1)
        left_p = np.stack([Pts[:, 0], new_p[:, 0], Pts[:, 1], new_p[:, 1], Pts[:, 2]], axis=1)
        right_p = np.stack([Pts[:, 2], new_p[:, 2], Pts[:, 3], new_p[:, 3], Pts[:, 4]], axis=1)
        cid = np.concatenate([cid, cid])
        T, Pts = np.concatenate([left_t, right_t]), np.concatenate([left_p, right_p])
    all_c = np.concatenate(done_c).astype(int) if done_c else np.zeros(0, dtype=int)
    all_t = np.concatenate(done_t) if done_t else np.zeros(0)
    order = np.lexsort((all_t, all_c))
    all_c, all_t = all_c[order], all_t[order]
    return all_c, all_t, np.searchsorted(all_c, np.arange(n + 1))


def _evaluate(point_fn, c: np.ndarray, t: np.ndarray) -> np.ndarray:
    """point_fn over many points, a chunk at a time so that its temporaries stay bounded."""
    if len(t) <= EVAL_CHUNK:
        return point_fn(c, t)
    return np.concatenate([point_fn(c[lo:lo + EVAL_CHUNK], t[lo:lo + EVAL_CHUNK])
                           for lo in range(0, len(t), EVAL_CHUNK)])


def _deviation(p: np.ndarray, cid: np.ndarray, image=None) -> np.ndarray:
    """Estimated largest distance of curve pieces from their chords, from their five points p (m, 5, 2)."""
    dist = _distance_to_segment(p[:, 1:4], p[:, :1], p[:, 4:]).max(axis=1)
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite points give NaN: never split
        second = p[:, :-2] - 2 * p[:, 1:-1] + p[:, 2:]  # (m, 3, 2)
        across = _across(second, p[:, 2:] - p[:, :-2]).max(axis=1)
        out = dist + 0.25 * across
    if image is not None:
        w, h = image[0][cid], image[1][cid]
        m = 0.25 * np.maximum(w, h)[:, None]
        u, v = p[..., 0], p[..., 1]
        with np.errstate(invalid="ignore"):
            far = (u < -m).all(1) | (u > (w[:, None] + m)).all(1) | (v < -m).all(1) | (v > (h[:, None] + m)).all(1)
        out = np.where(far, 0.0, out)
    return out


def _across(v: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The part of vectors v (..., 2) across directions d (..., 2) (all of v where d is zero).

    A second difference along the curve only speeds up or slows down the parameter; across it,
    it bends the curve away from its chords.
    """
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        length = np.hypot(d[..., 0], d[..., 1])
        across = np.abs(v[..., 0] * d[..., 1] - v[..., 1] * d[..., 0]) / length
        return np.where(length > 0, across, np.hypot(v[..., 0], v[..., 1]))


def _distance_to_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance of points p from segments a-b, (..., 2) each (broadcast)."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        d = b - a
        dd = (d * d).sum(axis=-1)
        s = np.clip(((p - a) * d).sum(axis=-1) / dd, 0.0, 1.0)
        q = a + np.where(dd > 0, s, 0.0)[..., None] * d
    return np.hypot(p[..., 0] - q[..., 0], p[..., 1] - q[..., 1])


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


def clip_polylines_rect(pts: np.ndarray, start: np.ndarray, width, height):
    """Cut packed 2D polylines (CSR: polyline k is pts[start[k]:start[k+1]]) to [0, width] x [0, height].

    width and height are scalars or one a polyline. The pieces are those of `clip_polyline_rect`, for all
    polylines at once. Returns a dict of arrays: `src` (P,) the polyline of each piece, `start` (P + 1,)
    CSR offsets into `pts` (Q, 2), `cut` (P,), and per piece vertex `seg` (Q,) the index into `pts` of the
    segment it lies on (its first vertex) and `end` (Q,): 0 an original vertex, 1 where the piece enters
    the image, 2 where it leaves, with `side` (Q,) the border crossed (0 u = 0, 1 u = width, 2 v = 0,
    3 v = height) and `at` (Q,) the chord parameter of the crossing.
    """
    n = len(start) - 1
    counts = np.diff(start)
    W = np.broadcast_to(np.asarray(width, dtype=float), (n,))
    H = np.broadcast_to(np.asarray(height, dtype=float), (n,))
    owner = np.repeat(np.arange(n), counts)
    x, y = pts[:, 0], pts[:, 1]
    finite = np.isfinite(pts).all(axis=1)
    with np.errstate(invalid="ignore"):
        outside = ~finite | (x < 0) | (y < 0) | (x > W[owner]) | (y > H[owner])
    any_out = np.bincount(owner, weights=outside, minlength=n) > 0
    # segments: vertex j to j + 1 within one polyline
    seg = np.flatnonzero(np.repeat(counts >= 2, counts) & (np.arange(len(pts)) + 1 < start[owner + 1]))
    poly = owner[seg]
    sw = seg[any_out[poly]]  # only polylines that leave the image are cut
    a, b = pts[sw], pts[sw + 1]
    both = finite[sw] & finite[sw + 1]  # a vertex beyond float range cuts the polyline there
    a, b = np.where(both[:, None], a, 0.0), np.where(both[:, None], b, 0.0)
    d = b - a
    t0, t1, keep, s0, s1 = _liang_barsky(a, b, W[owner[sw]], H[owner[sw]])
    keep &= both
    first = sw == start[owner[sw]]
    prev_open = np.zeros(len(sw), dtype=bool)  # the previous segment's piece carries on into this one
    prev_open[1:] = keep[:-1] & (t1[:-1] >= 1) & ~first[1:]
    begins = keep & ((t0 > 0) | ~prev_open)
    leaves = keep & (t1 < 1)
    # vertices: the entry point of a beginning segment, then every kept segment's end point
    nv = keep.astype(int) + begins
    vseg = np.repeat(sw, nv)
    is_first = np.zeros(len(vseg), dtype=bool)
    offs = np.cumsum(nv) - nv
    is_first[offs[begins]] = True
    j = np.repeat(np.arange(len(sw)), nv)
    at = np.where(is_first, t0[j], t1[j])
    cpts = a[j] + at[:, None] * d[j]
    end = np.where(is_first, np.where(t0[j] > 0, 1, 0), np.where(leaves[j], 2, 0))
    side = np.where(is_first, s0[j], s1[j])
    piece_of_v = np.cumsum(is_first) - 1
    # whole polylines inside the image: one uncut piece each
    inside = np.flatnonzero(~any_out & (counts >= 2))
    in_v = np.flatnonzero(np.repeat(~any_out & (counts >= 2), counts))
    # merge both kinds, ordered by polyline (then by position along it)
    src = np.concatenate([inside, owner[sw[begins]]])
    n_in = counts[inside]
    n_cut = np.bincount(piece_of_v, minlength=int(begins.sum())) if len(piece_of_v) else np.zeros(0, int)
    sizes = np.concatenate([n_in, n_cut])
    cut = np.concatenate([np.zeros(len(inside), bool), np.ones(len(n_cut), bool)])
    vpts = np.concatenate([pts[in_v], cpts])
    vmeta = [np.concatenate([in_v, vseg]), np.concatenate([np.zeros(len(in_v), int), end]),
             np.concatenate([np.full(len(in_v), -1), side]), np.concatenate([np.zeros(len(in_v)), at])]
    order = np.argsort(src, kind="stable")
    vstart = np.concatenate([[0], np.cumsum(sizes)])
    sizes, src, cut = sizes[order], src[order], cut[order]
    vidx = _ranges(vstart[:-1][order], sizes)
    vpts = vpts[vidx]
    vmeta = [m[vidx] for m in vmeta]
    # a piece must have extent
    pstart = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    if len(sizes):
        lo = np.minimum.reduceat(vpts, pstart[:-1], axis=0) if len(vpts) else np.zeros((0, 2))
        hi = np.maximum.reduceat(vpts, pstart[:-1], axis=0) if len(vpts) else np.zeros((0, 2))
        ok = (sizes >= 2) & ((hi - lo).max(axis=1) > 0)
    else:
        ok = np.zeros(0, dtype=bool)
    vkeep = np.repeat(ok, sizes)
    sizes = sizes[ok]
    return {"src": src[ok], "start": np.concatenate([[0], np.cumsum(sizes)]).astype(int), "cut": cut[ok],
            "pts": vpts[vkeep], "seg": vmeta[0][vkeep], "end": vmeta[1][vkeep], "side": vmeta[2][vkeep],
            "at": vmeta[3][vkeep]}


def _liang_barsky(a: np.ndarray, b: np.ndarray, width, height):
    """`clip_segments_rect` with per-segment bounds, also returning the border that sets t0 and t1."""
    d = b - a
    t0 = np.zeros(len(a))
    t1 = np.ones(len(a))
    s0 = np.full(len(a), -1)
    s1 = np.full(len(a), -1)
    keep = np.ones(len(a), dtype=bool)
    for k, (p, q) in enumerate(((-d[:, 0], a[:, 0]), (d[:, 0], width - a[:, 0]), (-d[:, 1], a[:, 1]),
                                (d[:, 1], height - a[:, 1]))):
        parallel = p == 0
        keep &= ~(parallel & (q < 0))
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            r = q / p
        enter = ~parallel & (p < 0) & (r > t0)
        leave = ~parallel & (p > 0) & (r < t1)
        t0, s0 = np.where(enter, r, t0), np.where(enter, k, s0)
        t1, s1 = np.where(leave, r, t1), np.where(leave, k, s1)
    keep &= t0 <= t1
    return t0, t1, keep, s0, s1


def _ranges(first: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Concatenated aranges first[k] .. first[k] + sizes[k] - 1, without a loop."""
    total = int(sizes.sum())
    offs = np.cumsum(sizes) - sizes
    return np.repeat(first - offs, sizes) + np.arange(total)
