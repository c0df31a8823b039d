"""Projection against OpenCV (an independent implementation), clipping, and curve tolerances."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from wiredsl.engine import geometry
from wiredsl.scene import Camera


def random_camera(rng: np.random.Generator, distorted: bool = True) -> Camera:
    k = dict(k1=rng.uniform(-0.3, 0.3), k2=rng.uniform(-0.1, 0.1), p1=rng.uniform(-0.01, 0.01),
             p2=rng.uniform(-0.01, 0.01)) if distorted else {}
    return Camera(name="c", f=rng.uniform(200, 2000), ax=rng.uniform(0.8, 1.2), ay=rng.uniform(0.8, 1.2),
                  cx=rng.uniform(200, 400), cy=rng.uniform(150, 300), width=640, height=480, **k)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q @ np.diag(np.sign(np.diag(r)))
    return q if np.linalg.det(q) > 0 else -q


def opencv_mapping(cam: Camera):
    """The documented mapping: K = [[f ax, 0, cx], [0, f ay, cy], [0, 0, 1]], distCoeffs = (k1, k2, p1, p2)."""
    K = np.array([[cam.f * cam.ax, 0, cam.cx], [0, cam.f * cam.ay, cam.cy], [0, 0, 1.0]])
    return K, np.array([cam.k1, cam.k2, cam.p1, cam.p2])


def test_projection_agrees_with_opencv_to_1e_6_px():
    rng = np.random.default_rng(20151)
    worst = 0.0
    for _ in range(300):
        cam = random_camera(rng)
        R = random_rotation(rng)
        t = rng.normal(size=3)
        # points in front, within |x/z|, |y/z| < 0.8 (inside the fold radius of these distortions)
        xy = rng.uniform(-0.8, 0.8, size=(50, 2))
        z = rng.uniform(0.5, 20, size=50)
        P_cam = np.column_stack([xy * z[:, None], z])
        P_world = (P_cam - t) @ R  # invert P_cam = R P_world + t
        ours = geometry.cam_to_pixels(geometry.world_to_cam(P_world, R, t), cam)
        K, dist = opencv_mapping(cam)
        rvec, _ = cv2.Rodrigues(R)
        theirs, _ = cv2.projectPoints(P_world.reshape(-1, 1, 3), rvec, t, K, dist)
        worst = max(worst, float(np.abs(ours - theirs.reshape(-1, 2)).max()))
    assert worst < 1e-6, worst


def test_tina_k_sign_is_barrel_for_positive_k():
    """TINA: v = (1 - k r^2) w; a positive k pulls points towards the centre."""
    cam = Camera(name="c", f=500, cx=320, cy=240, k1=-0.1, width=640, height=480)  # TINA k = 0.1
    u = geometry.cam_to_pixels(np.array([[0.5, 0.0, 1.0]]), cam)[0, 0]
    assert u == pytest.approx(320 + 500 * 0.5 * (1 - 0.1 * 0.25))


def test_camera_from_world_puts_a_point_ahead_at_the_centre():
    R_rc = np.column_stack([[0, -1, 0], [0, 0, -1], [1, 0, 0]])  # looking along robot x
    R_cw, t_cw = geometry.camera_from_world((1.0, 2.0, math.pi / 2), R_rc, (0.0, 0.0, 1.2))
    P = geometry.world_to_cam(np.array([[1.0, 5.0, 1.2], [0.0, 5.0, 1.2]]), R_cw, t_cw)
    assert P[0] == pytest.approx([0, 0, 3])  # 3 m ahead along the heading (world +y)
    assert P[1][0] < 0  # world -x is to the robot's left: image left


@pytest.mark.parametrize("k1,k2", [(-0.02, 0.0), (-0.3, 0.0), (-0.3, 0.05), (0.1, -0.02)])
def test_fold_radius_is_where_the_radial_map_stops_increasing(k1, k2):
    r = geometry.fold_radius(k1, k2)
    g = lambda r: r * (1 + k1 * r**2 + k2 * r**4)  # noqa: E731
    if math.isinf(r):
        rs = np.linspace(0, 20, 20001)
        assert np.all(np.diff(g(rs)) > 0)
    else:
        rs = np.linspace(0, r, 1001)
        assert np.all(np.diff(g(rs)) > 0)
        assert g(r * 1.01) < g(r)


def test_cone_clip_matches_dense_sampling():
    rng = np.random.default_rng(7)
    A, B = rng.normal(size=(5000, 3)) * 3, rng.normal(size=(5000, 3)) * 3
    t0, t1, keep = geometry.clip_segments_cone(A, B, 0.01, 0.8)
    ts = np.linspace(0, 1, 1001)
    P = A[:, None] + ts[None, :, None] * (B - A)[:, None]
    inside = (P[..., 2] >= 0.01) & (P[..., 0] ** 2 + P[..., 1] ** 2 <= 0.64 * P[..., 2] ** 2)
    pred = keep[:, None] & (ts >= t0[:, None] - 1e-9) & (ts <= t1[:, None] + 1e-9)
    assert ((pred != inside).sum(axis=1) <= 1).all()  # at most the boundary sample differs


def test_segments_through_the_camera_plane_are_clipped_not_nan():
    A = np.array([[0.0, 0.0, -1.0], [0.1, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 1.0, -2.0]])
    B = np.array([[0.0, 0.1, 3.0], [0.2, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 1.0, -1.0]])
    t0, t1, keep = geometry.clip_segments_cone(A, B, geometry.NEAR, math.inf)
    assert keep.tolist() == [True, False, False, False]
    z = A[0, 2] + t0[0] * (B[0, 2] - A[0, 2])
    assert z == pytest.approx(geometry.NEAR)


def _dist_to_polyline(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    a, b = poly[:-1], poly[1:]
    d = b - a
    t = np.clip(((points[:, None] - a[None]) * d[None]).sum(-1) / np.maximum((d * d).sum(-1), 1e-300), 0, 1)
    closest = a[None] + t[..., None] * d[None]
    return np.linalg.norm(points[:, None] - closest, axis=-1).min(axis=1)


@pytest.mark.parametrize("tol", [0.01, 0.1, 1.0])
def test_distorted_line_polyline_stays_within_tolerance(tol):
    cam = Camera(name="c", f=600, cx=320, cy=240, k1=-0.25, k2=0.05, width=640, height=480)
    A, B = np.array([-1.5, -1.0, 2.0]), np.array([1.5, 0.9, 2.5])

    def point(c, t):
        return geometry.cam_to_pixels(A + t[:, None] * (B - A), cam)

    (ts,) = geometry.adaptive_samples(point, np.array([0.0]), np.array([1.0]), tol, start=2)
    poly = point(None, ts)
    truth = point(None, np.linspace(0, 1, 20001))
    assert _dist_to_polyline(truth, poly).max() < tol
    assert len(ts) < 4 / math.sqrt(tol) + 10  # and not absurdly dense
