"""The robot's motion along its path, and what a camera sees of it: velocities from a continuous-time
interpolation of the path's poses, the robot's pose at times near a pose's (a stereo pair's sync offset), and the
rolling-shutter projection (each point imaged from the camera's pose at its own row's time).

Within a frame (a readout, a sync offset: milliseconds) the robot moves with its velocity at the pose, a constant
twist in the world frame: world_from_robot(tau) = (exp([w] tau) R_wr, t_wr + v tau). The velocities (v, w) at a
pose are the tangents, at that pose, of the piecewise cubic Hermite interpolation through the poses at their times
whose tangents are the three-point derivatives (the derivative of the parabola through a pose and its two
neighbours; one-sided at the ends): exact for a straight run at a constant speed.

A path without times (no `speed`, a trajectory file without timestamps) stands still at every pose: nothing here
is used for it, and a scene that declares no readout and no sync never imports this module.
"""

from __future__ import annotations

import math

import numpy as np

from wiredsl.engine import geometry

ROW_TOL = 1e-9  # px: a point's row time is settled when its pixel's row is within this of the row it is read at
MAX_FIXED = 64  # fixed-point iterations: each kept one halves the step, so 64 reach ROW_TOL from any image's height
GRID = 8  # rows spread from the bracket's lower end to the image's last row, searched for a sign change of g
MAX_BRACKET = 192  # Illinois steps, every third a bisection: the bracket halves every three, 2^-64 of it in 192
CONTRACTION = 0.5  # the fixed point is kept while each step is at most half the one before


def _log_rotation(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (n, 3) of rotations R (n, 3, 3) (angles below pi)."""
    c = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(c)
    axis = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    s = np.sin(theta)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(s > 1e-12, theta / (2.0 * s), 0.5)  # small angles: the skew part is the vector itself
    return axis * scale[:, None]


def velocities(path) -> tuple[np.ndarray, np.ndarray]:
    """The robot's world-frame velocity v (n, 3) (of its origin, m/s) and angular velocity w (n, 3) (rad/s) at
    each pose of a path with times: the three-point derivatives (see the module's docstring)."""
    times = np.asarray(path.times, dtype=float)
    n = len(times)
    poses = [geometry.world_from_robot(path.pose(i)) for i in range(n)]
    if n < 2:
        return np.zeros((n, 3)), np.zeros((n, 3))
    R = np.stack([p[0] for p in poses])
    t = np.stack([p[1] for p in poses])
    h = np.diff(times)
    dp = np.diff(t, axis=0) / h[:, None]  # each interval's mean velocity
    dr = _log_rotation(np.einsum("nij,nkj->nik", R[1:], R[:-1])) / h[:, None]  # R_{i+1} R_i^T: world frame

    def tangents(d):
        out = np.empty((n, 3))
        out[0], out[-1] = d[0], d[-1]
        h0, h1 = h[:-1, None], h[1:, None]
        out[1:-1] = (h1 * d[:-1] + h0 * d[1:]) / (h0 + h1)
        return out

    return tangents(dp), tangents(dr)


def _rotate_back(d: np.ndarray, w: np.ndarray, tau) -> np.ndarray:
    """exp([w] tau)^T d for points d (..., 3), angular velocity w (3,) and times tau (...,) (Rodrigues)."""
    speed = math.sqrt(float(w @ w))
    if speed == 0.0:
        return d
    k = w / speed
    theta = -speed * np.asarray(tau, dtype=float)[..., None]
    c, s = np.cos(theta), np.sin(theta)
    return d * c + np.cross(k, d) * s + k * (d @ k)[..., None] * (1.0 - c)


def moved(X: np.ndarray, tau, robot: np.ndarray, v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """World points X (..., 3) as the robot at time tau (...,) sees them, put back in the world frame of the robot
    at time 0 (at `robot`, its origin in the world): exp([w] tau)^T (X - robot - v tau) + robot. A camera's
    pose at time 0 then images them as the camera at tau images X."""
    tau = np.asarray(tau, dtype=float)
    return _rotate_back(X - robot - v * tau[..., None], w, tau) + robot


def robots_at(pose, v: np.ndarray, w: np.ndarray, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`robot_at` for many times tau (T,): the robot's world_from_robot (R (T, 3, 3), t (T, 3)) at each."""
    tau = np.asarray(tau, dtype=float)
    R, t = geometry.world_from_robot(pose)
    E = np.transpose(_rotate_back(np.broadcast_to(np.eye(3), (len(tau), 3, 3)), w, -tau[:, None]), (0, 2, 1))
    return E @ R, t + v * tau[:, None]


def sync_offsets(rig, trials, index: int, seed: int, point: int | None = None) -> np.ndarray:
    """Each trial's offset of the right camera at path pose `index` under a sync jitter: sync + jitter n, n a
    standard normal keyed by ("rig.sync", trial, pose, the rig, seed, point): a trial's offset at a pose is its own,
    whichever trials share its batch."""
    from wiredsl.effects.base import keyed_normal, stream_key

    trials = np.asarray(trials, dtype=np.int64)
    keys = stream_key("rig.sync", trials, index, -1, seed, point)
    return rig.sync + rig.jitter * keyed_normal(keys, np.zeros(len(trials), dtype=np.uint64))


def jittered_robots(scene, index: int, trials, seed: int, point: int | None = None):
    """The right camera's robot pose at path pose `index` for each trial, at its drawn offset (`sync_offsets`):
    (R (T, 3, 3), t (T, 3))."""
    vs, ws = velocities_of(scene.path)
    return robots_at(scene.path.pose(index), vs[index], ws[index], sync_offsets(scene.rig, trials, index, seed, point))


def robot_at(pose, v: np.ndarray, w: np.ndarray, tau: float) -> tuple[float, ...]:
    """The robot's pose `tau` seconds after `pose` (moving with v, w): the 12 numbers of its [R | t]."""
    R, t = geometry.world_from_robot(pose)
    E = _rotate_back(np.eye(3), w, -tau).T  # exp([w] tau): columns of rotated unit vectors
    return tuple(float(x) for x in np.column_stack([E @ R, t + v * tau]).ravel())


def rolling_pixels(X: np.ndarray, pixels, readout: float, height: float, robot: np.ndarray, v: np.ndarray,
                   w: np.ndarray) -> np.ndarray:
    """Pixels (..., 2) of world points X (..., 3) under a rolling shutter: row r is exposed at readout r / height
    after the camera's time 0, and each point is imaged from the camera's pose at its own row's time.

    `pixels` maps world points (..., 3), as the camera's pose at time 0 sees them, to pixels (..., 2). With
    f(r) = row of X seen at time readout clip(r, 0, H) / H (H the height), the row time solves
    g(r) = f(r) - r = 0; a root beyond [0, H] is a row beyond the image, which takes the time of the image's
    nearest row (the map stays bounded where the lens folds or a point nears the camera). g has a root for every
    point: f(0) when f(0) < 0, f(H) when f(H) > H, and one in [0, H] when g(0) >= 0 >= g(H).

    The solver, each point on its own (`kernel._project_rolling` does the same, term by term):
    1. From r = f(0), the fixed-point iteration r <- f(clip(r, 0, H)) while it contracts (each step at most
       CONTRACTION times the one before; for q = readout |dr/dt| / H < 1/2 it always does, the error shrinking by
       q an iteration), until a step is at most ROW_TOL px. Each evaluated row is a lower (g >= 0) or upper
       (g < 0) end of a bracket of the earliest root found so far.
    2. Otherwise, without an upper end, g at GRID rows spread evenly from the lower end to H: the first where
       g < 0 closes the bracket; none (g(H) >= 0) gives the root f(H) (the point beyond the image's bottom).
    3. In the bracket, the Illinois method with every third step a bisection, until |g| <= ROW_TOL px.
    A point above the image when its readout starts (f(0) < 0) has the root f(0), the time 0, unless it comes
    into the image faster than the readout sweeps (g(H) > 0): then the bracket [0, H] (step 3).

    Convergence: a kept fixed-point step is at most half the one before and the first is at most H, so MAX_FIXED
    = 64 iterations reach ROW_TOL from any height below 2^33 px; the bracket halves at least every third step,
    so MAX_BRACKET = 192 steps take it below a double's resolution of any row (2^-64 of H), where |g| is at most
    (1 + q) times that. Each returned pixel is the exact projection at its row time, its row within ROW_TOL px
    of the row whose time that is (the bound reached, which the argument excludes, keeps the last estimate).

    Several roots (q > 1 somewhere, a point imaged at two rows): the earliest row is chosen, as a sensor reads
    top to bottom, the first at which the point is read. The fixed point from f(0) climbs to it where the image
    moves down (its iterates stay below the earliest root); the grid finds the first sign change at its
    spacing, (H - lower end) / GRID rows: two roots closer than that (a point whose image grazes the readout's
    sweep) count as none. A point above the image at both ends of the readout is taken as above it, not
    searched for a pair of rows in between. Points whose pixels are not finite (not imaged) at a row time stop
    there (invalid); not imaged at H, a point above the image keeps f(0)."""
    H = float(height)
    uv0 = pixels(X)
    y0 = uv0[..., 1]
    out = uv0.copy()
    finite = np.isfinite(y0)

    def at(x, live):  # every point's pixels as seen at row x's time (the live points' matter)
        return pixels(moved(X, readout * np.where(live, x, 0.0) / H, robot, v, w))

    zeros = np.zeros(y0.shape)
    with np.errstate(invalid="ignore"):
        above = finite & (y0 < 0)
    a, ga, b, gb = zeros.copy(), np.where(finite, y0, 0.0), np.full(y0.shape, H), np.full(y0.shape, np.nan)
    known = np.zeros(y0.shape, dtype=bool)  # an upper end b (g(b) < 0, or for `above` g(b) > 0) is known
    bracket = np.zeros(y0.shape, dtype=bool)
    if above.any():  # coming into the image faster than the readout sweeps: g(0) < 0 < g(H)
        uv = at(np.full(y0.shape, H), above)
        with np.errstate(invalid="ignore"):
            into = above & (uv[..., 1] - H > 0)
        gb = np.where(into, uv[..., 1] - H, gb)
        bracket |= into

    x = np.where(finite & ~above, np.minimum(y0, H), 0.0)  # 1. the fixed point
    prev = np.full(y0.shape, np.inf)
    live = finite & ~above
    stalled = np.zeros(y0.shape, dtype=bool)
    with np.errstate(invalid="ignore", divide="ignore"):
        for _ in range(MAX_FIXED):
            if not live.any():
                break
            uv = at(x, live)
            y = uv[..., 1]
            out = np.where(live[..., None], uv, out)
            seen = live & np.isfinite(y)
            g = y - x
            step = np.abs(np.clip(y, 0.0, H) - x)
            go = seen & ~(step <= ROW_TOL)
            below_b = ~known | (x < b)
            up = go & (g >= 0) & below_b & (x > a)
            a, ga = np.where(up, x, a), np.where(up, g, ga)
            down = go & (g < 0) & below_b
            b, gb = np.where(down, x, b), np.where(down, g, gb)
            known |= down
            reset = down & (a >= b)  # the lower end kept is beyond the new upper one: row 0's
            a, ga = np.where(reset, 0.0, a), np.where(reset, y0, ga)
            stall = go & (step > CONTRACTION * prev)
            stalled |= stall
            prev, x = np.where(go, step, prev), np.where(go, np.clip(y, 0.0, H), x)
            live = go & ~stall
        stalled |= live  # (the bound, not reached: see the docstring)

        live = stalled & ~known  # 2. the grid: a sign change of g beyond the lower end
        start = a.copy()
        for j in range(1, GRID + 1):
            if not live.any():
                break
            x = H if j == GRID else start + (H - start) * (j / GRID)
            x = np.where(live, x, 0.0)
            uv = at(x, live)
            y = uv[..., 1]
            out = np.where(live[..., None], uv, out)
            seen = live & np.isfinite(y)
            g = y - x
            hit = seen & (g < 0)
            b, gb = np.where(hit, x, b), np.where(hit, g, gb)
            known |= hit
            stay = seen & (g >= 0)
            a, ga = np.where(stay, x, a), np.where(stay, g, ga)
            live = stay
        bracket |= stalled & known

        live = bracket  # 3. Illinois in [a, b], g(a) and g(b) of opposite signs
        sa, sb = ga.copy(), gb.copy()  # their values, halved where an end is kept twice running
        side = np.zeros(y0.shape, dtype=np.int64)
        for k in range(MAX_BRACKET):
            if not live.any():
                break
            c = 0.5 * (a + b) if k % 3 == 2 else (a * sb - b * sa) / (sb - sa)
            c = np.where(live, c, 0.0)
            uv = at(c, live)
            y = uv[..., 1]
            out = np.where(live[..., None], uv, out)
            g = y - c
            go = live & np.isfinite(y) & ~(np.abs(g) <= ROW_TOL)
            new_a = go & ((g > 0) == (sa > 0))
            new_b = go & ~new_a
            sb = np.where(new_a & (side == -1), 0.5 * sb, sb)
            sa = np.where(new_b & (side == 1), 0.5 * sa, sa)
            a, sa = np.where(new_a, c, a), np.where(new_a, g, sa)
            b, sb = np.where(new_b, c, b), np.where(new_b, g, sb)
            side = np.where(new_a, -1, np.where(new_b, 1, side))
            live = go
    return out


def view_motions(scene, index: int) -> dict[str, tuple | None]:
    """Each side's motion at path pose `index`: (robot pose at the camera's own time, rolling shutter or None),
    the rolling shutter as (readout, height, robot origin, v, w); None for a side that neither moves (no sync)
    nor reads out rows over time."""
    out: dict[str, tuple | None] = {}
    path, rig = scene.path, scene.rig
    v = w = None
    for side in ("left", "right"):
        cam = scene.camera(getattr(rig, side).camera)
        tau = rig.sync if side == "right" else 0.0
        if path.times is None or (tau == 0.0 and cam.readout == 0.0):
            out[side] = None
            continue
        if v is None:
            vs, ws = velocities_of(path)
            v, w = vs[index], ws[index]
        pose = path.pose(index) if tau == 0.0 else robot_at(path.pose(index), v, w, tau)
        rolling = None
        if cam.readout > 0:
            rolling = (cam.readout, float(cam.height), geometry.world_from_robot(pose)[1], v, w)
        out[side] = (pose, rolling)
    return out


_VELOCITIES: dict[int, tuple] = {}


def velocities_of(path) -> tuple[np.ndarray, np.ndarray]:
    """`velocities(path)`, computed once per path object."""
    key = id(path)
    hit = _VELOCITIES.get(key)
    if hit is None or hit[0] is not path:
        hit = _VELOCITIES[key] = (path, *velocities(path))
        if len(_VELOCITIES) > 64:
            _VELOCITIES.pop(next(iter(_VELOCITIES)))
    return hit[1], hit[2]


def moving(scene) -> bool:
    """Whether the scene's cameras see the robot's motion (a readout or a sync, on a path with times)."""
    if scene.rig is None or scene.path is None or scene.path.times is None:
        return False
    return scene.rig.sync != 0.0 or any(scene.camera(getattr(scene.rig, s).camera).readout > 0
                                        for s in ("left", "right"))
