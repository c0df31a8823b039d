"""Ellipse images and silhouettes, checked against sampled 3D points (not the same formulas)."""

from __future__ import annotations

import math

import mpmath as mp
import numpy as np
import pytest
from helpers import circle, silhouette_segments
from test_projection import _dist_to_polyline

from wiredsl.engine import conics, geometry
from wiredsl.engine.simulate import project_view
from wiredsl.engine.world import World
from wiredsl.scene import Camera

CAM = Camera(name="c", f=600, cx=320, cy=240, width=640, height=480)
K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])


def conic_matrix(centre, axes, angle):
    """Point conic of an image ellipse from its (centre, axes, angle)."""
    c, s = math.cos(angle), math.sin(angle)
    R = np.array([[c, -s], [s, c]])
    A = R @ np.diag(1 / np.asarray(axes) ** 2) @ R.T
    b = -A @ centre
    return np.block([[A, b[:, None]], [b[None, :], np.array([[centre @ A @ centre - 1]])]])


def pixels(P):
    return geometry.cam_to_pixels(np.atleast_2d(P), CAM)


def random_cylinders(n, seed=3, cone=False):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        base = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(3, 8)])
        height, r0 = rng.uniform(0.2, 1.5), rng.uniform(0.05, 0.5)
        r1 = r0 * rng.uniform(0.3, 1.5) if cone else r0
        yield circle(base, axis, r0), circle(base + height * axis, axis, r1)


def test_conic_parameters_fit_the_projected_ellipse_points():
    for (c, U, V), _ in random_cylinders(50):
        H = K @ conics.homography(c, U, V)
        ok, centre, axes, angle = (x[0] for x in conics.image_ellipses(H[None]))
        assert ok
        t = np.linspace(0, 2 * np.pi, 200)
        uv = pixels(c + np.cos(t)[:, None] * U + np.sin(t)[:, None] * V)
        C = conic_matrix(centre, axes, angle)
        h = np.column_stack([uv, np.ones(len(uv))])
        residual = np.einsum("ni,ij,nj->n", h, C, h)
        # residual of the normalised conic equation: a point 1e-6 px off gives ~2e-6 / axis
        assert np.abs(residual).max() < 1e-8


def _mp_ellipse(H):
    """(centre, axes, angle) of the unit circle's image under H, from its dual conic in 60-digit arithmetic."""
    mp.mp.dps = 60
    Hm = mp.matrix(H.tolist())
    C = Hm * mp.diag([1, 1, -1]) * Hm.T
    C = C / -C[2, 2]
    centre = [-C[0, 2], -C[1, 2]]
    A = mp.matrix(2, 2)
    for i in range(2):
        for j in range(2):
            A[i, j] = C[i, j] + centre[i] * centre[j]
    w, Q = mp.eigsy(A)
    big = 0 if w[0] > w[1] else 1
    angle = mp.atan(Q[1, big] / Q[0, big])  # a direction, in (-pi/2, pi/2)
    return [float(x) for x in centre], sorted((float(mp.sqrt(x)) for x in w), reverse=True), float(angle)


@pytest.mark.parametrize("tilt", [1e-2, 1e-4, 1e-6, 1e-8])
def test_ellipses_seen_nearly_edge_on_match_a_60_digit_reference(tilt):
    """A circle whose plane passes `tilt` rad from the camera's centre: its image is a sliver a few 1e-5 px
    wide at 1e-6 and under the 1e-6 ratio of an edge-on one at 1e-8. Centre, axes and angle against mpmath's
    conic at 60 digits, to 1e-9 px and 1e-9 rad (the conic route in float64 was 1.3e-6 off at 1e-6)."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        base = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(3, 8)])
        along = rng.normal(size=3)
        u = np.cross(base, along)
        u /= np.linalg.norm(u)  # normal of a plane through the camera centre and base ...
        v = base / np.linalg.norm(base)
        normal = math.cos(tilt) * u + math.sin(tilt) * v  # ... tilted by `tilt` towards the line of sight
        c, U, V = circle(base, normal, rng.uniform(0.05, 0.5))
        H = K @ conics.homography(c, U, V)
        ok, centre, axes, angle = (x[0] for x in conics.image_ellipses(H[None]))
        want_c, want_ax, want_angle = _mp_ellipse(H)
        assert ok == (want_ax[1] > 1e-6 * want_ax[0])
        if not ok:
            continue
        assert np.abs(centre - want_c).max() < 1e-9 and np.abs(axes - want_ax).max() < 1e-9
        d = (angle - want_angle + math.pi / 2) % math.pi - math.pi / 2
        assert abs(d) < 1e-9 and -math.pi / 2 < angle <= math.pi / 2


def _signed_distances(line_pts, curve):
    (a, b) = line_pts
    d = b - a
    n = np.array([-d[1], d[0]]) / np.linalg.norm(d)
    return (curve - a) @ n


@pytest.mark.parametrize("cone", [False, True])
def test_silhouettes_are_tangent_to_both_ellipse_images(cone):
    t = np.linspace(0, 2 * np.pi, 20001)
    count = 0
    for (ca, Ua, Va), (cb, Ub, Vb) in random_cylinders(60, seed=11, cone=cone):
        segs = silhouette_segments(ca, Ua, Va, cb, Ub, Vb)
        if not cone:
            assert len(segs) == 2, "a cylinder seen from outside always has two sides"
        for A, B in segs:
            line = pixels(np.stack([A, B]))
            for c, U, V, touch in ((ca, Ua, Va, line[0]), (cb, Ub, Vb, line[1])):
                curve = pixels(c + np.cos(t)[:, None] * U + np.sin(t)[:, None] * V)
                assert _dist_to_polyline(touch[None], curve)[0] < 1e-5  # on it, to the dense curve's own sag
                s = _signed_distances(line, curve)
                assert min(s.max(), -s.min()) < 1e-6  # the whole ellipse on one side: tangent
            count += 1
    assert count >= 100


def test_camera_inside_a_cylinder_sees_no_sides():
    a, b = circle([0, -0.5, 0.0], [0, 1, 0], 0.3), circle([0, 0.5, 0.0], [0, 1, 0], 0.3)
    assert silhouette_segments(*a, *b) == []


def test_nearly_concentric_and_edge_on_views_stay_finite():
    # looking almost down the axis of a cylinder in front of the camera
    for tilt in (0.0, 1e-9, 1e-6, 1e-3):
        a = circle([0, 0, 3.0], [tilt, 0, 1], 0.3)
        b = circle([0, 0, 4.0], [tilt, 0, 1], 0.3)
        for A, B in silhouette_segments(*a, *b):
            assert np.isfinite(A).all() and np.isfinite(B).all()
    # the rim exactly edge-on (camera in its plane): the sides end at the rim's end points
    a, b = circle([0, 0, 3.0], [0, 1, 0], 0.3), circle([0, 1, 3.0], [0, 1, 0], 0.3)
    segs = silhouette_segments(*a, *b)
    assert len(segs) == 2
    ends = sorted(float(pixels(A)[0, 0]) for A, _ in segs)
    # the viewing rays from the camera touch the circle (radius r, distance d) at x = +-r sqrt(d^2 - r^2) / d
    r, d = 0.3, 3.0
    x, z = r * math.sqrt(d * d - r * r) / d, d - r * r / d
    assert ends == pytest.approx([320 - 600 * x / z, 320 + 600 * x / z], abs=1e-6)


def test_camera_exactly_on_the_surface_of_a_cylinder_is_finite():
    a, b = circle([0.3, -0.5, 0.0], [0, 1, 0], 0.3), circle([0.3, 0.5, 0.0], [0, 1, 0], 0.3)
    for A, B in silhouette_segments(*a, *b):
        assert np.isfinite(A).all() and np.isfinite(B).all()


def _world_with_ellipse(c, U, V, arc=(0, 2 * np.pi)):
    w = World(feature_ids=["p.e"], feature_kind=["ellipse"])
    w.ell_c, w.ell_U, w.ell_V = c[None], U[None], V[None]
    w.ell_arc, w.ell_full = np.array([arc], float), np.array([arc[1] - arc[0] >= 2 * np.pi - 1e-12])
    w.ell_fid = np.array([0])
    return w


@pytest.mark.parametrize("tol", [0.05, 0.5])
def test_ellipse_polyline_within_tolerance_of_the_distorted_curve(tol):
    cam = CAM.model_copy(update={"k1": -0.2, "k2": 0.03})
    c, U, V = circle([0.2, 0.1, 2.0], [0.3, -1, 0.4], 0.6)
    w = _world_with_ellipse(c, U, V)
    feats = project_view(w, cam, np.eye(3), np.zeros(3), np.array([True]), tol).features
    (poly,) = [f for f in feats if f.kind == "polyline"]
    t = np.linspace(0, 2 * np.pi, 20001)
    truth = geometry.cam_to_pixels(c + np.cos(t)[:, None] * U + np.sin(t)[:, None] * V, cam)
    inside = (truth[:, 0] >= 0) & (truth[:, 0] <= 640) & (truth[:, 1] >= 0) & (truth[:, 1] <= 480)
    assert _dist_to_polyline(truth[inside], poly.points).max() < tol
    assert not any(f.kind == "conic" for f in feats)  # distorted: no analytic conic


def test_ellipse_crossing_the_camera_plane_is_clipped_to_its_front_part():
    c, U, V = circle([0, 0.5, 0.2], [0, 1, 0], 1.0)  # half of it is behind the camera
    w = _world_with_ellipse(c, U, V)
    view = project_view(w, CAM, np.eye(3), np.zeros(3), np.array([True]), 0.1)
    assert all(f.kind == "polyline" and f.clipped for f in view.features)
    for f in view.features:
        assert np.isfinite(f.points).all()
