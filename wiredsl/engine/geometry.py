"""Geometry as small vectorised functions whose names say their frames.

Frames: world (x, y on the floor, z up); robot (x forward, y left, z up);
camera (OpenCV: x right, y down, z along the optical axis); the unit focal
plane (x/z, y/z, undistorted); pixels (u right, v down, origin at the top-left
corner of the image).

Camera models (TINA's, in OpenCV's terms), a camera point P = (X, Y, Z) to
distorted unit-plane coordinates (x_d, y_d), then u = f ax x_d + cx,
v = f ay y_d + cy:
- radtan, OpenCV's full rational model (cv2.projectPoints with the vector
  (k1, k2, p1, p2, k3, k4, k5, k6)):
    (x, y) = (X/Z, Y/Z),  r^2 = x^2 + y^2
    radial = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
    x_d = x radial + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y radial + p1 (r^2 + 2 y^2) + 2 p2 x y
  with k1 = -k for TINA's k (TINA: v = (1 - k r^2) w).
- equidistant, OpenCV's fisheye / Kannala-Brandt (cv2.fisheye.projectPoints
  with (k1, k2, k3, k4)): theta = atan2(sqrt(X^2 + Y^2), Z), the angle from
  the optical axis, theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6
  + k4 theta^8), (x_d, y_d) = theta_d (X, Y) / sqrt(X^2 + Y^2).

Which points are imaged (the near rule), with the lens limit of `lens_limit`:
- radtan: Z >= NEAR and the unit-plane radius below the radius where radial
  distortion folds back (d r_d / d r = 0, or the rational denominator's zero);
- equidistant: theta below the lens's largest angle (half its declared `fov`,
  else where theta_d stops increasing, at most 180 deg) and the point at least
  NEAR from the camera centre; so a fisheye sees points beside and behind its
  own plane (Z <= 0) when its field of view passes 180 deg.
- the wide-angle models (unified, eucm, ds, fov): theta below the model's own valid region (and half a declared
  `fov`), the point at least NEAR from the camera centre, as for a fisheye.
Callers clip in 3D first (`clip_segments_lens`).

The wide-angle models (Usenko, Demmel, Cremers, "The Double Sphere Camera Model", 3DV 2018, sec. 3, which
tabulates them with their valid regions), d = sqrt(X^2 + Y^2 + Z^2), pixels as above:
- unified (Mei and Rives, ICRA 2007; Kalibr `omni`, camodocal MEI, OpenCV omnidir): m = (X, Y) / (Z + xi d),
  then (Mei's form) OpenCV's radtan k1, k2, p1, p2 on m; valid where Z > -w d, w = min(xi, 1 / xi);
- eucm (Khomenko et al., RA-L 2016): m = (X, Y) / (alpha rho + (1 - alpha) Z), rho = sqrt(beta (X^2 + Y^2)
  + Z^2); valid where Z > -w rho, w = alpha / (1 - alpha) for alpha <= 1/2, else (1 - alpha) / alpha;
- ds (double sphere): d2 = sqrt(X^2 + Y^2 + (xi d + Z)^2), m = (X, Y) / (alpha d2 + (1 - alpha)(xi d + Z));
  valid where Z > -w2 d, w2 = (w1 + xi) / sqrt(2 w1 xi + xi^2 + 1), w1 as eucm's w;
- fov (Devernay and Faugeras, MVA 2001; Kalibr's `fov` distortion, basalt's fov): r_u = |(X, Y)| / Z,
  r_d = atan(2 r_u tan(w / 2)) / w, m = (X, Y) / Z * r_d / r_u; valid in front of the camera (Z > 0).
Each valid region is rotationally symmetric: an angle from the optical axis, as a fisheye's lens limit.
"""

from __future__ import annotations

import math

import numpy as np

NEAR = 1e-3  # metres: the near plane; nothing closer to the camera plane is projected


def distinct(a: np.ndarray) -> np.ndarray:
    """np.unique(a), sorted distinct values, without importing numpy.ma: numpy 2's plain `unique` imports it
    (some 15 ms of CPU, a build's cold start pays it), its counting form does not."""
    return np.unique(a, return_counts=True)[0]


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


def world_from_robot_via(R_wx, t_wx, R_rx, p_rx) -> tuple[np.ndarray, np.ndarray]:
    """(R_wr (..., 3, 3), t_wr (..., 3)): world_from_robot = world_from_x . x_from_robot, for a frame x on the robot
    (a camera, a trajectory file's body) at world_from_x (R_wx (..., 3, 3), t_wx (..., 3)) and mounted at
    robot_from_x (R_rx (3, 3), p_rx (3,): x's axes and origin in the robot frame)."""
    R_rx, p_rx = np.asarray(R_rx, dtype=float), np.asarray(p_rx, dtype=float)
    R_wr = np.asarray(R_wx, dtype=float) @ R_rx.T
    return R_wr, np.asarray(t_wx, dtype=float) - R_wr @ p_rx


def world_from_robot_via_camera(R_wc, t_wc, mount_rotation, mount_position) -> tuple[float, ...]:
    """The robot pose whose camera, mounted as `camera_from_world` takes it (mount_rotation robot_from_camera,
    mount_position in the robot frame), is at world_from_camera (R_wc, t_wc): camera_from_world's inverse, as the
    12 numbers of the row-major [R_wr | t_wr] that `world_from_robot` reads."""
    R_wr, t_wr = world_from_robot_via(R_wc, t_wc, mount_rotation, mount_position)
    return tuple(float(v) for v in np.column_stack([R_wr, t_wr]).ravel())


def world_to_cam(P_world: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray) -> np.ndarray:
    """P_cam, shape (..., 3), from P_world, shape (..., 3)."""
    return P_world @ R_cw.T + t_cw


def cam_to_plane(P_cam: np.ndarray) -> np.ndarray:
    """Unit focal plane (x/z, y/z), shape (..., 2); P_cam must be in front (z > 0)."""
    return P_cam[..., :2] / P_cam[..., 2:3]


# a camera's lens model; its code in camera tables is its index. Every model but radtan (code 0) bounds what it
# images by an angle from the optical axis (its lens limit)
MODELS = ("radtan", "equidistant", "unified", "eucm", "ds", "fov")
RADTAN, EQUIDISTANT, UNIFIED, EUCM, DS, FOV = range(len(MODELS))
# A camera's numbers in the engine's tables; the kernel's camera rows add the model code (CAMERA_ROW).
CAMERA_KEYS = ("f", "ax", "ay", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "xi", "alpha", "beta", "w")
CAMERA_ROW = (*CAMERA_KEYS, "model")
RADTAN_KEYS = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
# the model's own parameters beside the pixel scale and centre (a file or a statement giving another is refused)
MODEL_KEYS = {"radtan": RADTAN_KEYS, "equidistant": ("k1", "k2", "k3", "k4"), "unified": ("xi", "k1", "k2", "p1", "p2"),
              "eucm": ("alpha", "beta"), "ds": ("xi", "alpha"), "fov": ("w",)}


def distort(xy: np.ndarray, k1, k2=0.0, p1=0.0, p2=0.0, k3=0.0, k4=0.0, k5=0.0, k6=0.0) -> np.ndarray:
    """Distorted unit-plane coordinates under OpenCV's rational model (k1..k6, p1, p2), shape (..., 2)."""
    return np.stack(distort_xy(xy[..., 0], xy[..., 1], k1, k2, p1, p2, k3, k4, k5, k6), axis=-1)


def distort_xy(x: np.ndarray, y: np.ndarray, k1, k2=0.0, p1=0.0, p2=0.0, k3=0.0, k4=0.0, k5=0.0, k6=0.0):
    """`distort` of the coordinates apart: (x_d, y_d)."""
    r2 = x * x + y * y
    radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


def fisheye_plane(P_cam: np.ndarray, k1, k2=0.0, k3=0.0, k4=0.0) -> np.ndarray:
    """Distorted unit-plane coordinates of camera points (..., 3) under the equidistant model, (..., 2).

    theta is the angle from the optical axis, so points beside and behind the camera's plane have an
    image too; a point on the backward axis (theta = 180 deg) or at the centre has none (NaN).
    """
    return np.stack(fisheye_xy(P_cam[..., 0], P_cam[..., 1], P_cam[..., 2], k1, k2, k3, k4), axis=-1)


def fisheye_xy(X: np.ndarray, Y: np.ndarray, Z: np.ndarray, k1, k2=0.0, k3=0.0, k4=0.0):
    """`fisheye_plane` of the coordinates apart: (x_d, y_d)."""
    rho = np.hypot(X, Y)
    td = fisheye_theta_d(np.arctan2(rho, Z), k1, k2, k3, k4)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        scale = np.where(rho > 0, td / np.where(rho > 0, rho, 1.0), np.where(Z > 0, 0.0, np.nan))
    return scale * X, scale * Y


def fisheye_theta_d(theta, k1, k2=0.0, k3=0.0, k4=0.0):
    """The equidistant model's distorted angle theta_d of angles theta from the optical axis."""
    t2 = theta * theta
    return theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))


def fisheye_theta(theta_d: np.ndarray, k1, k2=0.0, k3=0.0, k4=0.0, steps: int = 20, tol: float | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The angles theta (n,) whose theta_d are given (Newton's method), and the residual |theta_d(theta) - given|
    (n,); the caller bounds theta by the lens limit, below which the map is one-to-one. With `tol`, an angle stops
    where its residual is within it."""
    theta = np.array(theta_d, dtype=float)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        for _ in range(steps):
            t2 = theta * theta
            slope = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
            res = fisheye_theta_d(theta, k1, k2, k3, k4) - theta_d
            if tol is not None:
                done = np.abs(res) <= tol
                if np.all(done):
                    break
                res = np.where(done, 0.0, res)
            theta = theta - res / slope
        return theta, np.abs(fisheye_theta_d(theta, k1, k2, k3, k4) - theta_d)


def plane_to_pixels(xy_d: np.ndarray, f, ax, ay, cx, cy) -> np.ndarray:
    """Pixels (u, v) from distorted unit-plane coordinates, shape (..., 2)."""
    return np.stack([f * ax * xy_d[..., 0] + cx, f * ay * xy_d[..., 1] + cy], axis=-1)


def camera_table(cam) -> dict:
    """A Camera's numbers by CAMERA_KEYS, with its model code ("model") and lens limit ("limit")."""
    table = _numbers(cam)
    table["limit"] = lens_limit(cam)
    return table


def project(P_cam: np.ndarray, g: dict) -> np.ndarray:
    """Pixels (m, 2) of camera points (m, 3) under cameras g: CAMERA_KEYS and "model", each a scalar or (m,).

    A radtan camera gives NaN for points with Z <= 0 (nothing there is imaged; callers clip first), as
    does a fisheye for the backward axis. A pixel beyond float range is inf.
    """
    return np.stack(project_xyz(P_cam[..., 0], P_cam[..., 1], P_cam[..., 2], g), axis=-1)


def project_xyz(X: np.ndarray, Y: np.ndarray, Z: np.ndarray, g: dict) -> tuple[np.ndarray, np.ndarray]:
    """`project` of the coordinates apart: camera points X, Y, Z (m,) each -> pixels (u, v), (m,) each.

    Contiguous coordinates cost less than the columns of an (m, 3) array; a camera's numbers given as
    scalars cost less than a column a number, and give the same doubles."""
    code = np.asarray(g["model"])
    present = distinct(code.ravel()).astype(int).tolist() if code.ndim else [int(code)]
    xd = yd = None
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        for m in present:
            mx, my = model_plane_xy(m, X, Y, Z, g)
            if xd is None or len(present) == 1:
                xd, yd = mx, my
            else:
                here = np.broadcast_to(code == m, np.shape(mx))
                xd, yd = np.where(here, mx, xd), np.where(here, my, yd)
        if xd is None:
            xd = yd = np.zeros(np.shape(X))
        return g["f"] * g["ax"] * xd + g["cx"], g["f"] * g["ay"] * yd + g["cy"]


def model_plane_xy(model: int, X, Y, Z, g: dict):
    """Distorted unit-plane coordinates (x_d, y_d) of camera points under lens model `model` (its code) with
    the numbers g (CAMERA_KEYS, scalars or arrays); NaN where the model has no image (callers clip first)."""
    if model == RADTAN:
        front = Z > 0
        return distort_xy(np.where(front, X / Z, np.nan), np.where(front, Y / Z, np.nan), g["k1"], g["k2"],
                          g["p1"], g["p2"], g["k3"], g["k4"], g["k5"], g["k6"])
    if model == EQUIDISTANT:
        return fisheye_xy(X, Y, Z, g["k1"], g["k2"], g["k3"], g["k4"])
    if model == FOV:
        rho = np.hypot(X, Y)
        w = g["w"]
        two_tan = 2.0 * np.tan(0.5 * w)
        # atan2 (rho 2 tan(w/2), Z) / (w rho); on the axis its limit 2 tan(w/2) / (w Z)
        scale = np.where(rho > 0, np.arctan2(rho * two_tan, Z) / (w * np.where(rho > 0, rho, 1.0)), two_tan / (w * Z))
        return scale * X, scale * Y
    r2 = X * X + Y * Y
    d = np.sqrt(r2 + Z * Z)
    xi = g["xi"]
    if model == UNIFIED:
        den = stable_sum(xi * d, Z, xi * xi * r2 - (1.0 - xi) * (1.0 + xi) * (Z * Z))
        return distort_xy(X / den, Y / den, g["k1"], g["k2"], g["p1"], g["p2"], g["k3"], g["k4"], g["k5"], g["k6"])
    a = g["alpha"]
    if model == EUCM:
        den = stable_sum(a * np.sqrt(g["beta"] * r2 + Z * Z), (1.0 - a) * Z,
                         a * a * g["beta"] * r2 + (2.0 * a - 1.0) * (Z * Z))
    else:  # DS
        zs = stable_sum(xi * d, Z, xi * xi * r2 - (1.0 - xi) * (1.0 + xi) * (Z * Z))
        den = stable_sum(a * np.sqrt(r2 + zs * zs), (1.0 - a) * zs, a * a * r2 + (2.0 * a - 1.0) * (zs * zs))
    return X / den, Y / den


def stable_sum(p, q, squares):
    """p + q, where p >= 0 (xi d, alpha rho: a distance's multiple) or of the sign opposite q's, and `squares` is
    p^2 - q^2 written out from the point's coordinates: where p and q have opposite signs their sum cancels near a
    lens's edge, and (p^2 - q^2) / (p - q) keeps the digits that the point's own coordinates hold (the rounding of p
    and q is not amplified; what cancels in `squares` is the point's true closeness to the edge). The kernel's
    _project evaluates the same expressions."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(p * q < 0, squares / (p - q), p + q)


def lens_radius(theta, cam) -> np.ndarray:
    """The undistorted-by-radtan unit-plane radius |m| (Mei's radtan not applied) of rays at angles theta from
    the optical axis, for an angle-bounded camera (`cam`: a Camera or a dict of CAMERA_KEYS and "model")."""
    g = _numbers(cam)
    theta = np.asarray(theta, dtype=float)
    s, c = np.sin(theta), np.cos(theta)
    if g["model"] == UNIFIED:  # before Mei's radtan
        with np.errstate(divide="ignore", invalid="ignore"):
            return s / (c + g["xi"])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        X, _ = model_plane_xy(g["model"], s, np.zeros_like(s), c, g)
    return X


def lens_theta(r, cam, tol: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of `lens_radius`: angles theta (n,) from the optical axis of rays whose radius is r (n,), by
    each model's closed-form unprojection (equidistant: Newton's method), and which have one (n,).

    A radius past the model's image (beyond the circle its valid region maps to) has none. `tol`: fisheye_theta's."""
    g = _numbers(cam)
    r = np.asarray(r, dtype=float)
    m = g["model"]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if m == EQUIDISTANT:
            theta, res = fisheye_theta(r, g["k1"], g["k2"], g["k3"], g["k4"], tol=tol)
            return theta, np.isfinite(theta) & (res < 1e-12) & (theta >= 0)
        r2 = r * r
        if m == UNIFIED:  # Mei and Rives 2007, eq. (the lifting): (x, y, z) = f (mx, my, 1) - (0, 0, xi)
            xi = g["xi"]
            f = (xi + np.sqrt(1.0 + (1.0 - xi * xi) * r2)) / (1.0 + r2)
            theta = np.arctan2(f * r, f - xi)
        elif m == EUCM:  # Khomenko et al. 2016: z = (1 - beta alpha^2 r^2) / (alpha sqrt(...) + 1 - alpha)
            a, b = g["alpha"], g["beta"]
            z = (1.0 - b * a * a * r2) / (a * np.sqrt(1.0 - (2.0 * a - 1.0) * b * r2) + 1.0 - a)
            theta = np.arctan2(r, z)
        elif m == DS:  # Usenko et al. 2018, eq. (44)-(46)
            a, xi = g["alpha"], g["xi"]
            mz = (1.0 - a * a * r2) / (a * np.sqrt(1.0 - (2.0 * a - 1.0) * r2) + 1.0 - a)
            k = (mz * xi + np.sqrt(mz * mz + (1.0 - xi * xi) * r2)) / (mz * mz + r2)
            theta = np.arctan2(k * r, k * mz - xi)
        elif m == FOV:  # Devernay and Faugeras 2001: r_u = tan(r_d w) / (2 tan(w / 2))
            w = g["w"]
            theta = np.where(r * w < 0.5 * math.pi, np.arctan(np.tan(r * w) / (2.0 * np.tan(0.5 * w))), np.nan)
        else:
            theta = np.arctan(r)
        return theta, np.isfinite(theta) & (theta >= 0)


def _numbers(cam) -> dict:
    """A camera's CAMERA_KEYS and model code as a dict (a Camera, or such a dict already)."""
    if isinstance(cam, dict):
        return cam
    return {**{k: float(getattr(cam, k)) for k in CAMERA_KEYS}, "model": MODELS.index(cam.distortion)}


def undistort_radtan(xd: np.ndarray, k1, k2=0.0, p1=0.0, p2=0.0, k3=0.0, k4=0.0, k5=0.0, k6=0.0, steps: int = 20,
                     start: np.ndarray | None = None, tol: float | None = None):
    """Unit-plane points xy (n, 2) whose `distort` is xd (n, 2), by Newton's method from xd (or `start`), and the
    residual max |distort(xy) - xd| (n,). With `tol`, a point stops where both its residuals are within it (what
    a loop over the points that breaks there gives)."""
    lens = (k1, k2, p1, p2, k3, k4, k5, k6)
    xy = np.array(xd if start is None else start, dtype=float)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        for _ in range(steps):
            x, y = xy[:, 0], xy[:, 1]
            r2 = x * x + y * y
            num, den = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)), 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
            rad = num / den
            # d rad / d x = g x, d rad / d y = g y
            g = 2.0 * ((k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)) * den - num * (k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2))) \
                / (den * den)
            j11 = rad + g * x * x + 2.0 * p1 * y + 6.0 * p2 * x
            j12 = g * x * y + 2.0 * p1 * x + 2.0 * p2 * y
            j22 = rad + g * y * y + 6.0 * p1 * y + 2.0 * p2 * x
            res = distort(xy, *lens) - xd
            det = j11 * j22 - j12 * j12
            step = np.column_stack([j22 * res[:, 0] - j12 * res[:, 1],
                                    j11 * res[:, 1] - j12 * res[:, 0]]) / det[:, None]
            if tol is not None:
                done = (np.abs(res) <= tol).all(axis=1)
                if done.all():
                    break
                step[done] = 0.0
            xy = xy - step
        return xy, np.abs(distort(xy, *lens) - xd).max(axis=1)


def pixels_to_rays(uv: np.ndarray, cam) -> tuple[np.ndarray, np.ndarray]:
    """Unit rays (n, 3) in the camera frame of pixels (n, 2) under `cam` by its model's own unprojection, and
    which have one inside the lens's valid region (n,) (others are (0, 0, 1))."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    xd = np.column_stack([(uv[:, 0] - cam.cx) / (cam.f * cam.ax), (uv[:, 1] - cam.cy) / (cam.f * cam.ay)])
    limit = lens_limit(cam)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        if cam.distortion in ("radtan", "unified") and is_distorted(cam):
            keys = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
            lens = [getattr(cam, k) for k in keys]
            # Newton from the radial root inside the fold (bisected): from xd itself it may find the one beyond
            r_fold = fold_radius(cam.k1, cam.k2, cam.k3, cam.k4, cam.k5, cam.k6)
            rd = np.hypot(xd[:, 0], xd[:, 1])
            lo, hi = np.zeros(len(rd)), np.full(len(rd), min(r_fold, 1e8))
            for _ in range(80):
                mid = 0.5 * (lo + hi)
                below = distort_xy(mid, 0.0, *lens[:2], 0.0, 0.0, *lens[4:])[0] < rd
                lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
            start = xd * np.where(rd > 0, lo / np.where(rd > 0, rd, 1.0), 0.0)[:, None]
            m, res = undistort_radtan(xd, *lens, start=start)
            ok = np.isfinite(m).all(axis=1) & (res < 1e-12)
            if cam.distortion == "unified":  # Mei's radtan on m must not fold before m is reached
                ok &= np.hypot(m[:, 0], m[:, 1]) < fold_radius(cam.k1, cam.k2)
        else:
            m, ok = xd, np.ones(len(xd), dtype=bool)
        r = np.hypot(m[:, 0], m[:, 1])
        if cam.distortion == "radtan":
            ok &= r < limit
            rays = np.column_stack([m, np.ones(len(m))])
        else:
            theta, good = lens_theta(r, cam)
            ok &= good & (theta < limit)
            s = np.where(r > 0, np.sin(theta) / np.where(r > 0, r, 1.0), 0.0)
            rays = np.column_stack([m * s[:, None], np.cos(theta)])
        rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
        ok &= np.isfinite(rays).all(axis=1)
    return np.where(ok[:, None], rays, np.array([0.0, 0.0, 1.0])), ok


NEWTON_TOL = 1e-14  # pixels_to_rays_newton: a point's Newton's method stops where its residuals are within this


def pixels_to_rays_newton(u: np.ndarray, v: np.ndarray, g: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit rays (x, y, z), (n,) each, in the camera frame of pixels u, v (n,) each under the camera numbers g
    (CAMERA_KEYS and "model"; a camera table or a kernel's camera row as a dict), NaN where none is found.

    `pixels_to_rays` without the fold radius, so that a compiled stage, handed only a camera row, computes the same
    (wiredsl.effects.stereo_mismatch_kernel._pixel_ray, term by term): a radtan's (and Mei's on a unified
    model's) distortion undone by `undistort_radtan`'s Newton's method from the distorted point itself (right
    wherever it converges inside the fold: every pixel of a mildly distorted lens), then the model's own lifting
    (`lens_theta`). No lens-limit test: a pixel past the lens's image gets whatever ray the formulas give."""
    model = int(g["model"])
    xd = (u - g["cx"]) / (g["f"] * g["ax"])
    yd = (v - g["cy"]) / (g["f"] * g["ay"])
    lens = [float(g[k]) for k in RADTAN_KEYS]
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        if model in (RADTAN, UNIFIED) and any(lens):
            m, res = undistort_radtan(np.column_stack([xd, yd]), *lens, tol=NEWTON_TOL)
            fail = ~(res < 1e-12)
            mx, my = np.where(fail, np.nan, m[:, 0]), np.where(fail, np.nan, m[:, 1])
        else:
            mx, my = xd, yd
        if model == RADTAN:
            n = np.sqrt(mx * mx + my * my + 1.0)
            return mx / n, my / n, 1.0 / n
        r = np.hypot(mx, my)
        theta, ok = lens_theta(r, g, tol=NEWTON_TOL)
        theta = np.where(ok, theta, np.nan)
        s = np.where(r > 0, np.sin(theta) / np.where(r > 0, r, 1.0), 0.0)
        return mx * s, my * s, np.cos(theta)


def cam_to_pixels(P_cam: np.ndarray, cam) -> np.ndarray:
    """The whole chain for points the camera images: P_cam (..., 3) -> pixels (..., 2)."""
    return project(P_cam, camera_table(cam))


def is_distorted(cam) -> bool:
    """Whether lines are curves in the camera's image (any fisheye; a radtan with a coefficient)."""
    return cam.distortion != "radtan" or any(getattr(cam, k) != 0.0 for k in RADTAN_KEYS)


def visible(P_cam: np.ndarray, model, limit) -> np.ndarray:
    """Which camera points (..., 3) a camera images by the near rule (see the module's docstring).

    model and limit (`lens_limit`) are scalars or one per point.
    """
    X, Y, Z = P_cam[..., 0], P_cam[..., 1], P_cam[..., 2]
    fisheye = np.asarray(model) != RADTAN  # every other model bounds an angle
    radtan = fish = None
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if not fisheye.all():
            zs = np.where(Z > 0, Z, 1.0)
            radtan = (Z > NEAR) & (np.hypot(X / zs, Y / zs) < limit)
        if fisheye.any():
            fish = (np.arctan2(np.hypot(X, Y), Z) < limit) & (np.sqrt(X * X + Y * Y + Z * Z) > NEAR)
    if fish is None or radtan is None:
        out = fish if radtan is None else radtan
        shape = np.broadcast_shapes(X.shape, fisheye.shape)
        return out if out.shape == shape else np.array(np.broadcast_to(out, shape))
    return np.where(fisheye, fish, radtan)


def lens_limit(cam, *, bounded: bool = True, **values) -> float:
    """radtan: the fold radius on the unit plane; the other models: the largest angle from the axis imaged (rad),
    the model's own valid region and (with `bounded`) half a declared fov, whichever is smaller.

    values (e.g. k1=...) replace the camera's own numbers (a perturbed camera).
    """
    g = {n: float(values.get(n, getattr(cam, n))) for n in CAMERA_KEYS[5:]}
    if cam.distortion == "radtan":
        return fold_radius(*(g[n] for n in ("k1", "k2", "k3", "k4", "k5", "k6")))
    fov = cam.fov if bounded else None
    if cam.distortion == "equidistant":
        return fisheye_max_angle(g["k1"], g["k2"], g["k3"], g["k4"], fov)
    limit = model_max_angle(cam.distortion, g)
    return min(limit, fov / 2) if fov is not None else limit


# Beyond these the unified and EUCM formulas image every direction within a sliver of the centre (xi 1e100: a
# point 90 deg off the axis lands at the image centre; beta 1e300 overflows): no calibrated lens is near them
# (Kalibr's and basalt's fisheyes have xi about 1 to 3 and beta about 1)
MAX_XI = 100.0
MAX_BETA = 100.0


def model_max_angle(model: str, g: dict) -> float:
    """The valid region of a wide-angle model as an angle from the optical axis (the DS paper's regions: Z > -w d
    and its kin); NaN for numbers that define no model (the caller refuses them). The unified model's radtan also
    stops where it folds (`fold_radius` of k1, k2), as radtan's does."""
    def acos_(w):
        return math.acos(-w) if -1.0 <= w <= 1.0 else (math.pi if w > 1 else math.nan)

    def w_of(alpha):  # the EUCM and DS papers' w (w1): alpha / (1 - alpha) up to 1/2, then (1 - alpha) / alpha
        if not 0.0 <= alpha <= 1.0:
            return math.nan
        return alpha / (1.0 - alpha) if alpha <= 0.5 else (1.0 - alpha) / alpha

    if model == "fov":
        return math.pi / 2 if 0.0 < g["w"] < math.pi else math.nan
    if model == "unified":
        xi = g["xi"]
        if not 0.0 <= xi <= MAX_XI:
            return math.nan
        limit = acos_(min(xi, 1.0 / xi) if xi > 0 else 0.0)
        r_fold = fold_radius(g["k1"], g["k2"])
        if math.isfinite(r_fold):  # the angle whose |m| reaches the fold
            theta, ok = lens_theta(np.array([r_fold]), {"model": UNIFIED, "xi": xi})
            if ok[0]:
                limit = min(limit, float(theta[0]))
        return limit
    if model == "eucm":
        w, beta = w_of(g["alpha"]), g["beta"]
        if not 0.0 < beta <= MAX_BETA or math.isnan(w):
            return math.nan
        return math.pi if w >= 1.0 else math.pi / 2 + math.atan(w * math.sqrt(beta / (1.0 - w * w)))
    if model == "ds":
        w1, xi = w_of(g["alpha"]), g["xi"]
        if math.isnan(w1) or not -1.0 < xi <= 1.0:
            return math.nan
        return _ds_fold(g["alpha"], xi, acos_((w1 + xi) / math.sqrt(2.0 * w1 * xi + xi * xi + 1.0)))
    raise ValueError(f"unknown lens model {model!r}")


def _ds_fold(alpha: float, xi: float, limit: float, n: int = 2048) -> float:
    """The double sphere's valid region (the paper's, `limit`) cut where its radius stops increasing, which for a
    negative xi can come first: the first zero of d r / d theta (up to a positive factor, cos D + sin^2 (alpha xi
    / d2 + 1 - alpha), D the projection's denominator) or of D, sampled on n steps then bisected."""
    def g(t):
        s, c = np.sin(t), np.cos(t)
        zs = xi + c
        d2 = np.sqrt(s * s + zs * zs)
        D = alpha * d2 + (1.0 - alpha) * zs
        return np.minimum(c * D + s * s * (alpha * xi / d2 + 1.0 - alpha), D)

    t = np.linspace(0.0, limit, n + 1)[1:]
    bad = np.flatnonzero(~(g(t) > 0))
    if len(bad) == 0:
        return limit
    lo, hi = (float(t[bad[0] - 1]) if bad[0] > 0 else 0.0), float(t[bad[0]])
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if g(mid) > 0 else (lo, mid)
    return lo


def fisheye_max_angle(k1: float, k2: float = 0.0, k3: float = 0.0, k4: float = 0.0, fov: float | None = None) -> float:
    """The largest angle from the optical axis an equidistant lens images: half its fov, the first angle where
    theta_d (theta) stops increasing, and 180 deg, whichever is smallest."""
    # d theta_d / d theta = 1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3 + 9 k4 s^4 in s = theta^2
    sigma, (a1, a2, a3, a4) = _balance((k1, k2, k3, k4), (1, 2, 3, 4))
    t = _first_positive_root([1.0, 3.0 * a1, 5.0 * a2, 7.0 * a3, 9.0 * a4])
    with np.errstate(over="ignore"):
        limit = min(math.sqrt(sigma * t), math.pi)
    return min(limit, fov / 2) if fov is not None else limit


def fold_radius(k1: float, k2: float = 0.0, k3: float = 0.0, k4: float = 0.0, k5: float = 0.0,
                k6: float = 0.0) -> float:
    """Smallest unit-plane radius where r radial(r) stops increasing or the rational denominator
    vanishes (inf if never). k1 and k2 may be arrays when the others are 0 (elementwise).

    Beyond it the radial mapping folds back and is no longer one-to-one, so nothing
    there is projected (tangential terms, small in practice, are not considered).
    """
    if k3 == k4 == k5 == k6 == 0.0:
        return _fold_radius_quadratic(k1, k2)
    npoly = np.polynomial.polynomial
    # in t = s / sigma every coefficient is at most 1 in size, so nothing below overflows (a k3 of 1e308) or
    # divides by a subnormal (a k6 of 5e-324); the roots are found in t and scaled back
    sigma, (a1, a2, a3, a4, a5, a6) = _balance((k1, k2, k3, k4, k5, k6), (1, 2, 3, 1, 2, 3))
    N, D = np.array([1.0, a1, a2, a3]), np.array([1.0, a4, a5, a6])
    t_ = np.array([0.0, 1.0])
    # d/dr (r N(s) / D(s)) = ((N + 2 s N') D - 2 s N D') / D^2 with s = r^2 (and s N'(s) = t N'(t))
    num = npoly.polysub(npoly.polymul(npoly.polyadd(N, 2 * npoly.polymul(t_, npoly.polyder(N))), D),
                        2 * npoly.polymul(npoly.polymul(t_, N), npoly.polyder(D)))
    t = min(_first_positive_root(num), _first_positive_root(D))
    with np.errstate(over="ignore"):
        return math.sqrt(sigma * t)


def _balance(k, powers) -> tuple[float, list[float]]:
    """sigma and the coefficients k_i sigma^p_i of a polynomial 1 + sum k_i s^p_i rewritten in t = s / sigma,
    sigma chosen so that the largest of them is 1 in size (and none overflows on the way: logarithms)."""
    logs = [-math.log(abs(x)) / p for x, p in zip(k, powers, strict=False) if x != 0.0]
    if not logs:
        return 1.0, [0.0] * len(k)
    log_sigma = min(logs)
    scaled = [0.0 if x == 0.0 else math.copysign(math.exp(math.log(abs(x)) + p * log_sigma), x)
              for x, p in zip(k, powers, strict=False)]
    return math.exp(min(log_sigma, 709.0)), scaled


def _first_positive_root(coef) -> float:
    """The smallest positive real root of a polynomial (coefficients lowest order first, constant 1, none far
    above 1 in size: see `_balance`), or inf."""
    c = np.trim_zeros(np.asarray(coef, dtype=float), "b")
    if len(c) < 2:
        return math.inf
    if len(c) == 3:  # the stable quadratic formula: a tiny leading coefficient cannot overflow
        return _fold_radius_quadratic(c[1] / 3.0, c[2] / 5.0) ** 2
    # the roots u = 1/s of the reversed polynomial: its leading coefficient is the constant 1, so the companion
    # matrix never divides by a tiny (subnormal) leading coefficient; a huge root s is a u near 0
    with np.errstate(all="ignore"):
        u = np.polynomial.polynomial.polyroots(c[::-1])
        real = u.real[(np.abs(u.imag) <= 1e-9 * np.maximum(np.abs(u.real), 1e-300)) & (u.real > 0)]
        if len(real) == 0:
            return math.inf
        s = float(1.0 / real.max())
        if not math.isfinite(s):
            return math.inf
        d = np.polynomial.polynomial.polyder(c)
        for _ in range(3):  # Newton polish of the eigenvalue root
            ds = np.polynomial.polynomial.polyval(s, d)
            step = np.polynomial.polynomial.polyval(s, c) / ds if ds != 0 else 0.0
            if not math.isfinite(step) or step == 0:
                break
            s = s - step
    return s if s > 0 else math.inf


def _fold_radius_quadratic(k1, k2=0.0):
    """fold_radius for k1, k2 only: floats, or arrays (elementwise, the same doubles as one by one)."""
    # d/dr = 1 + 3 k1 r^2 + 5 k2 r^4 = 0: a s^2 + b s + 1 = 0 in s = r^2, solved in the stable form
    # (q = -(b + sign(b) sqrt(disc)) / 2, roots c / q and q / a) so that a tiny a cannot overflow; the whole
    # equation is first divided by its largest coefficient, so that a huge k1 or k2 cannot overflow b^2 either
    k1, k2 = np.asarray(k1, dtype=float), np.asarray(k2, dtype=float)
    m = np.maximum(np.maximum(np.abs(k1), np.abs(k2)), 1.0)
    a, b, c = 5.0 * (k2 / m), 3.0 * (k1 / m), 1.0 / m
    with np.errstate(all="ignore"):  # what divides by zero or roots a negative is masked out below
        linear = np.where(b < 0, np.sqrt(-c / b), np.inf)  # no k2: b s + c = 0 directly, as b * b could underflow
        disc = b * b - 4.0 * a * c
        q = -0.5 * (b + np.copysign(np.sqrt(disc), b))
        roots = np.stack([np.where(q != 0, c / q, np.inf), q / a])
    s = np.where(np.isfinite(roots) & (roots > 0), roots, np.inf).min(axis=0)
    out = np.where(a == 0, linear, np.where(disc < 0, np.inf, np.sqrt(s)))
    return float(out) if out.ndim == 0 else out


def clip_segments_lens(A: np.ndarray, B: np.ndarray, model: np.ndarray, limit: np.ndarray):
    """The parts of camera-frame segments A->B (n, 3) that their cameras image (the near rule).

    model and limit (n,) as from `lens_limit`. A radtan part is one interval (a convex region); a fisheye
    may cut a segment in up to three (its region, past 90 deg, is the outside of a backward cone, and the
    ball of radius NEAR about the centre is cut out). Returns (rows, t0, t1): segment rows[j]'s part j is
    A + t (B - A) for t in [t0[j], t1[j]], rows sorted.
    """
    n = len(A)
    model = np.broadcast_to(np.asarray(model), (n,))
    limit = np.broadcast_to(np.asarray(limit, dtype=float), (n,))
    rad = np.flatnonzero(model == RADTAN)
    t0, t1, keep = clip_segments_cone(A[rad], B[rad], NEAR, limit[rad] * (1 - 1e-9))
    rows, lo, hi = [rad[keep]], [t0[keep]], [t1[keep]]
    fish = np.flatnonzero(model != RADTAN)  # every angle-bounded lens
    if len(fish):
        Af, Bf, lim = A[fish], B[fish], limit[fish] * (1 - 1e-9)  # strictly inside, as `visible` asks
        narrow = lim <= math.pi / 2
        # in front of a narrow lens: the convex cone theta <= limit (z >= 0)
        f0, f1, fk = clip_segments_cone(Af, Bf, 0.0, np.where(narrow, np.tan(np.minimum(lim, math.pi / 2)), 1e7))
        f0, f1 = np.where(fk & narrow, f0, np.where(narrow, 1.0, 0.0)), np.where(fk & narrow, f1, 1.0)
        # a wide lens: all but the convex backward cone theta > limit (mirrored: in front of -z)
        flip = np.array([1.0, 1.0, -1.0])
        b0, b1, bk = clip_segments_cone(Af * flip, Bf * flip, 0.0, np.tan(math.pi - np.maximum(lim, math.pi / 2)))
        back = bk & ~narrow
        e0, e1 = np.where(back, b0, np.inf), np.where(back, b1, np.inf)
        pieces = [(np.arange(len(fish)), f0, np.minimum(f1, e0)), (np.arange(len(fish)), np.maximum(f0, e1), f1)]
        # the ball |A + t D| < NEAR
        D = Bf - Af
        a, b, c = (D * D).sum(1), 2 * (Af * D).sum(1), (Af * Af).sum(1) - NEAR * NEAR
        disc = b * b - 4 * a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            sq = np.sqrt(np.maximum(disc, 0.0))
            n0, n1 = (-b - sq) / (2 * a), (-b + sq) / (2 * a)
        inball = (disc > 0) & (a > 0)
        n0, n1 = np.where(inball, n0, np.inf), np.where(inball, n1, np.inf)
        for k, p0, p1 in pieces:
            for q0, q1 in ((p0, np.minimum(p1, n0)), (np.maximum(p0, n1), p1)):
                ok = (q1 > q0) & ~((a[k] == 0) & (c[k] < 0))
                rows.append(fish[k[ok]])
                lo.append(q0[ok])
                hi.append(q1[ok])
    rows_, lo_, hi_ = np.concatenate(rows), np.concatenate(lo), np.concatenate(hi)
    order = np.lexsort((lo_, rows_))
    return rows_[order].astype(int), lo_[order], hi_[order]


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
EVAL_CHUNK = 15_000  # points evaluated at once while sampling: each temporary (m,) stays below the 128 KiB at
# which malloc maps fresh pages (a new process pays a page fault a 4 KiB page each time), and in cache


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
                            max_vertices: int = MAX_CURVE_VERTICES, image=None, points: bool = False):
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
    Returns (cid, t, bounds): the parameters sorted by curve then t, curve i's are t[bounds[i]:bounds[i+1]];
    with `points`, also point_fn's points there (m, 2), as evaluated while sampling.
    Raises TooManyVertices past max_vertices for one curve or MAX_VERTICES in all.
    """
    n = len(t0)
    starts = np.broadcast_to(np.asarray(start, dtype=int), (n,))
    done_c, done_t, done_i, live_c, live_a, live_b = [], [], [], [], [], []
    first = 0  # the first interval of this start count's curves
    for k in distinct(starts).tolist():
        rows = np.flatnonzero(starts == k)
        grid = np.linspace(0.0, 1.0, k + 1)
        ts = t0[rows, None] + (t1 - t0)[rows, None] * grid[None, :]
        done_c.append(np.repeat(rows, k + 1))
        done_t.append(ts.ravel())
        # where each grid point was evaluated: an interval's start, the last one's end; (point, interval)
        j = np.minimum(np.arange(k + 1), k - 1)
        done_i.append(np.stack(np.broadcast_arrays(np.where(j < np.arange(k + 1), 4, 0),
                                                   first + k * np.arange(len(rows))[:, None] + j)).reshape(2, -1))
        first += k * len(rows)
        live_c.append(np.repeat(rows, k))
        live_a.append(ts[:, :-1].ravel())
        live_b.append(ts[:, 1:].ravel())
    cid = np.concatenate(live_c).astype(int) if live_c else np.zeros(0, dtype=int)
    ta, tb = (np.concatenate(x) if x else np.zeros(0) for x in (live_a, live_b))
    # each live interval keeps its five points (ends, quarters, middle), their u and v apart, a row each
    # (5, intervals): a halving reuses three of them
    tm = 0.5 * (ta + tb)
    T = np.stack([ta, 0.5 * (ta + tm), tm, 0.5 * (tm + tb), tb])
    U, V = _evaluate_uv(point_fn, cid, T)
    at = tuple(np.concatenate(done_i, axis=1)) if done_i else (np.zeros(0, dtype=int),) * 2
    done_u, done_v = [U[at]], [V[at]]
    counts = starts + 1
    total = int(counts.sum())
    for _ in range(max_depth):
        if len(cid) == 0:
            break
        split = _deviation_uv(U, V, cid, image) > tol
        cid = cid[split]
        T, U, V = (x.compress(split, axis=1) for x in (T, U, V))
        done_c.append(cid)
        done_t.append(T[2])
        done_u.append(U[2])
        done_v.append(V[2])
        counts += np.bincount(cid, minlength=n)
        total += len(cid)
        if total > MAX_VERTICES:
            raise TooManyVertices(-1, MAX_VERTICES)
        if len(cid) and counts.max() > max_vertices:
            raise TooManyVertices(int(counts.argmax()), max_vertices)
        new_t = 0.5 * (T[:-1] + T[1:])  # the eighths: the children's new quarter points
        new_u, new_v = _evaluate_uv(point_fn, cid, new_t)
        # the nine points of the interval, then its halves: points 0-4 and 4-8
        cid = np.concatenate([cid, cid])
        T, U, V = (_halves(old, new) for old, new in ((T, new_t), (U, new_u), (V, new_v)))
    all_c = np.concatenate(done_c).astype(int) if done_c else np.zeros(0, dtype=int)
    all_t = np.concatenate(done_t) if done_t else np.zeros(0)
    order = np.lexsort((all_t, all_c))
    all_c, all_t = all_c[order], all_t[order]
    bounds = np.searchsorted(all_c, np.arange(n + 1))
    if not points:
        return all_c, all_t, bounds
    return all_c, all_t, bounds, np.stack([np.concatenate(done_u)[order], np.concatenate(done_v)[order]], axis=1)


def _evaluate_uv(point_fn, c: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points of curves c (m,) at parameters t (k, m) (row i: every curve's i-th point) as their u and v,
    each (k, m): about EVAL_CHUNK points a call, written in place (no (k m, 2) array in between)."""
    k, m = t.shape
    u, v = np.empty((k, m)), np.empty((k, m))
    if m <= EVAL_CHUNK:
        rows = max(EVAL_CHUNK // max(m, 1), 1)
        for i in range(0, k, rows):
            block = t[i:i + rows]
            p = point_fn(np.tile(c, len(block)), block.ravel())
            u[i:i + rows], v[i:i + rows] = p[:, 0].reshape(block.shape), p[:, 1].reshape(block.shape)
        return u, v
    for i in range(k):
        for lo in range(0, m, EVAL_CHUNK):
            p = point_fn(c[lo:lo + EVAL_CHUNK], t[i, lo:lo + EVAL_CHUNK])
            u[i, lo:lo + EVAL_CHUNK], v[i, lo:lo + EVAL_CHUNK] = p[:, 0], p[:, 1]
    return u, v


def _halves(old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """Five values a piece (5, m) and the four between them (4, m) -> the two halves' five values (5, 2m)."""
    nine = np.empty((9, old.shape[1]))
    nine[0::2], nine[1::2] = old, new
    return np.concatenate([nine[:5], nine[4:]], axis=1)


def _deviation_uv(u: np.ndarray, v: np.ndarray, cid: np.ndarray, image=None) -> np.ndarray:
    """Estimated largest distance of curve pieces from their chords, from their five points' u and v (5, m)
    each: the largest distance of the quarter points from the chord segment, plus a quarter of the largest
    second difference across the curve. Written a coordinate at a time: numpy's reductions over an axis of
    two cost more than the arithmetic."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # non-finite points give NaN: never split
        u0, v0, u4, v4 = u[0], v[0], u[4], v[4]
        du, dv = u4 - u0, v4 - v0  # the chord
        dd = du * du + dv * dv
        out = None
        for j in (1, 2, 3):  # the quarter points' distances from the chord segment
            s = np.clip(((u[j] - u0) * du + (v[j] - v0) * dv) / dd, 0.0, 1.0)
            s = np.where(dd > 0, s, 0.0)
            d = np.hypot(u[j] - (u0 + s * du), v[j] - (v0 + s * dv))
            out = d if out is None else np.maximum(out, d)  # NaN wins, as in max()
        across = None
        for j in (0, 1, 2):  # second differences, their part across the curve
            a = _across_uv(u[j] - 2 * u[j + 1] + u[j + 2], v[j] - 2 * v[j + 1] + v[j + 2],
                           u[j + 2] - u[j], v[j + 2] - v[j])
            across = a if across is None else np.maximum(across, a)
        out = out + 0.25 * across
    if image is not None:
        w, h = image[0][cid], image[1][cid]
        m = 0.25 * np.maximum(w, h)
        lo_u, hi_u, lo_v, hi_v = -m, w + m, -m, h + m
        with np.errstate(invalid="ignore"):
            below_u, above_u, below_v, above_v = u[0] < lo_u, u[0] > hi_u, v[0] < lo_v, v[0] > hi_v
            for j in (1, 2, 3, 4):
                below_u &= u[j] < lo_u
                above_u &= u[j] > hi_u
                below_v &= v[j] < lo_v
                above_v &= v[j] > hi_v
        out = np.where(below_u | above_u | below_v | above_v, 0.0, out)
    return out


def _across_uv(vu, vv, du, dv):
    """The part of vectors (vu, vv) across directions (du, dv) (all of it where a direction is zero).

    A second difference along the curve only speeds up or slows down the parameter; across it,
    it bends the curve away from its chords.
    """
    length = np.hypot(du, dv)
    return np.where(length > 0, np.abs(vu * dv - vv * du) / length, np.hypot(vu, vv))


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
    finite = np.isfinite(x) & np.isfinite(y)
    with np.errstate(invalid="ignore"):
        outside = ~finite | (x < 0) | (y < 0) | (x > W[owner]) | (y > H[owner])
    any_out = np.bincount(owner, weights=outside, minlength=n) > 0
    # segments: vertex j to j + 1 within one polyline
    seg = np.flatnonzero(np.repeat(counts >= 2, counts) & (np.arange(len(pts)) + 1 < start[owner + 1]))
    poly = owner[seg]
    sw = seg[any_out[poly]]  # only polylines that leave the image are cut
    a, b = pts.take(sw, axis=0), pts.take(sw + 1, axis=0)  # np.take: faster than pts[sw] on (n, 2)
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
    cpts = a.take(j, axis=0) + at[:, None] * d.take(j, axis=0)
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
    vpts = np.concatenate([pts.take(in_v, axis=0), cpts])
    vmeta = [np.concatenate([in_v, vseg]), np.concatenate([np.zeros(len(in_v), int), end]),
             np.concatenate([np.full(len(in_v), -1), side]), np.concatenate([np.zeros(len(in_v)), at])]
    order = np.argsort(src, kind="stable")
    vstart = np.concatenate([[0], np.cumsum(sizes)])
    sizes, src, cut = sizes[order], src[order], cut[order]
    vidx = _ranges(vstart[:-1][order], sizes)
    vpts = vpts.take(vidx, axis=0)
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
            "pts": vpts.compress(vkeep, axis=0), "seg": vmeta[0][vkeep], "end": vmeta[1][vkeep],
            "side": vmeta[2][vkeep], "at": vmeta[3][vkeep]}


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
