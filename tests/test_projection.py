"""Projection against OpenCV (an independent implementation), clipping, and curve tolerances."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from wiredsl.diagnostics import WiredslError
from wiredsl.engine import geometry
from wiredsl.engine.simulate import project_view
from wiredsl.engine.world import World
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


def test_world_from_robot_via_camera_is_the_robot_whose_mounted_camera_is_there():
    """Against 4x4 homogeneous matrices and a general inverse: world_from_robot = world_from_camera .
    inverse(robot_from_camera); and camera_from_world of the pose found gives the camera back."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(7)
    for _ in range(20):
        T_rc, T_wc = np.eye(4), np.eye(4)
        T_rc[:3, :3], T_rc[:3, 3] = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)
        T_wc[:3, :3], T_wc[:3, 3] = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3) * 10
        pose = geometry.world_from_robot_via_camera(T_wc[:3, :3], T_wc[:3, 3], T_rc[:3, :3], T_rc[:3, 3])
        assert len(pose) == 12
        np.testing.assert_allclose(np.reshape(pose, (3, 4)), (T_wc @ np.linalg.inv(T_rc))[:3], atol=1e-12)
        R_cw, t_cw = geometry.camera_from_world(pose, T_rc[:3, :3], T_rc[:3, 3])
        np.testing.assert_allclose(np.column_stack([R_cw, t_cw]), np.linalg.inv(T_wc)[:3], atol=1e-12)


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


def test_sampler_hands_back_the_points_it_evaluated():
    """The pixels the packed sampler returns (clipping uses them instead of projecting again) are the curves'
    own points at the returned parameters, for several start counts at once and a curve that stays coarse."""
    cam = Camera(name="c", f=600, cx=320, cy=240, k1=-0.25, k2=0.05, width=640, height=480)
    A = np.array([[-1.5, -1.0, 2.0], [0.2, -0.3, 1.5], [-0.4, 0.1, 3.0], [1.0, 0.5, 2.0]])
    B = np.array([[1.5, 0.9, 2.5], [0.3, 0.4, 1.2], [0.5, -0.2, 4.0], [1.0, 0.5, 2.0]])  # the last: one point

    def point(c, t):
        return geometry.cam_to_pixels(A[c] + t[:, None] * (B[c] - A[c]), cam)

    cid, ts, bounds, pts = geometry.adaptive_samples_packed(point, np.zeros(4), np.ones(4), 0.05,
                                                            np.array([2, 5, 2, 3]), points=True)
    assert np.array_equal(pts, point(cid, ts))
    assert np.array_equal(geometry.adaptive_samples_packed(point, np.zeros(4), np.ones(4), 0.05,
                                                           np.array([2, 5, 2, 3]))[1], ts)
    assert np.diff(bounds).tolist()[3] == 4 and np.diff(bounds).min() >= 3


def test_raw_strokes_are_made_when_read():
    """A projection's raw strokes (what the Monte-Carlo engines re-project) are made the first time any view's
    are read, for all its views; they image the same pixels as the view's features, and pickle as a list."""
    import pickle

    from wiredsl.engine.simulate import project_views

    cam = Camera(name="c", f=600, cx=320, cy=240, k1=-0.2, width=640, height=480)
    w = World(feature_ids=["p.l0", "p.l1"], feature_kind=["line", "line"])
    w.lines = np.array([[[-0.5, -0.2, 2.0], [0.6, 0.3, 2.5]], [[-0.2, 0.4, 3.0], [0.2, -0.4, 3.0]]])
    w.line_fid, w.line_segment = np.arange(2), -np.ones(2, int)
    R, t = np.eye(3), np.zeros(3)
    views = project_views(w, [cam, cam], [R, R], [t, t + [0.1, 0, 0]], [np.ones(2, bool)] * 2)
    assert views[0].raw._strokes.lists is None  # nothing made by the projection itself
    assert [r.fid for r in views[1].raw] == [0, 1] and views[0].raw._strokes.lists is not None
    for v in views:
        for r, f in zip(v.raw, v.features, strict=True):  # both lines wholly in the image: a feature each
            assert np.allclose(geometry.cam_to_pixels(r.world @ v.R_cw.T + v.t_cw, cam), f.points, rtol=0, atol=1e-9)
    again = pickle.loads(pickle.dumps(views[0].raw))
    assert type(again) is list and [r.fid for r in again] == [0, 1]
    assert all(np.array_equal(a.world, b.world) for a, b in zip(again, views[0].raw, strict=True))


def test_gc_paused_restores_the_collector():
    """The projection pauses the cyclic collector and gives it back as it found it, also on an error."""
    import gc

    from wiredsl.engine.simulate import gc_paused

    assert gc.isenabled()
    with pytest.raises(RuntimeError), gc_paused():
        assert not gc.isenabled()
        with gc_paused():
            pass
        assert not gc.isenabled()  # an inner pause does not restart it early
        raise RuntimeError
    assert gc.isenabled()


# --------------------------------------------------------------------------- packed projection of whole views

def _opencv_pixels(P_cam: np.ndarray, cam: Camera) -> np.ndarray:
    """Camera-frame points (n, 3) to pixels by OpenCV: the independent reference for true curve points."""
    K, dist = opencv_mapping(cam)
    uv, _ = cv2.projectPoints(P_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    return uv.reshape(-1, 2)


def _random_view(rng: np.random.Generator):
    """A distorted camera looking at random lines and ellipses in front of it (some crossing the border)."""
    cam = random_camera(rng).model_copy(update={"k1": rng.uniform(-0.3, 0.1), "k2": rng.uniform(0.0, 0.05)})
    n_lines, n_ell = 6, 3
    A = np.column_stack([rng.uniform(-2, 2, (n_lines, 2)), rng.uniform(1, 5, n_lines)])
    B = np.column_stack([rng.uniform(-2, 2, (n_lines, 2)), rng.uniform(1, 5, n_lines)])
    w = World(feature_ids=[f"p.f{i}" for i in range(n_lines + n_ell)],
              feature_kind=["line"] * n_lines + ["ellipse"] * n_ell)
    w.lines, w.line_fid, w.line_segment = np.stack([A, B], axis=1), np.arange(n_lines), -np.ones(n_lines, int)
    c = np.column_stack([rng.uniform(-1.5, 1.5, (n_ell, 2)), rng.uniform(2, 5, n_ell)])
    U = rng.normal(size=(n_ell, 3))
    V = np.cross(U, rng.normal(size=(n_ell, 3)))
    U *= rng.uniform(0.2, 1.0, (n_ell, 1)) / np.linalg.norm(U, axis=1, keepdims=True)
    V *= rng.uniform(0.05, 1.0, (n_ell, 1)) / np.linalg.norm(V, axis=1, keepdims=True)
    w.ell_c, w.ell_U, w.ell_V = c, U, V
    w.ell_arc = np.tile([0.0, 2 * math.pi], (n_ell, 1))
    w.ell_full, w.ell_fid = np.ones(n_ell, bool), n_lines + np.arange(n_ell)
    return cam, w


def _true_points(w: World, fid: int, n: int = 20001) -> np.ndarray:
    """Dense camera-frame points of feature fid (all in front of these random views)."""
    t = np.linspace(0.0, 1.0, n)
    if fid < len(w.lines):
        a, b = w.lines[fid]
        return a + t[:, None] * (b - a)
    e = fid - len(w.lines)
    s = 2 * math.pi * t
    return w.ell_c[e] + np.cos(s)[:, None] * w.ell_U[e] + np.sin(s)[:, None] * w.ell_V[e]


@pytest.mark.parametrize("tol", [0.1, 0.02])
def test_polylines_stay_within_tolerance_of_a_dense_reference(tol):
    """Every true curve point (OpenCV, 5,001 a feature) inside the image lies within tol of its polylines."""
    rng = np.random.default_rng(8 if tol == 0.1 else 9)
    worst = 0.0
    for _ in range(25):
        cam, w = _random_view(rng)
        r_fold = geometry.fold_radius(cam.k1, cam.k2)
        view = project_view(w, cam, np.eye(3), np.zeros(3), np.ones(w.n_features, bool), tol)
        for fid in range(w.n_features):
            # 5,001 points a feature: under 0.3 px apart on these curves, where the deviation from a polyline
            # segment (a parabola peaking mid-segment, segments px long) varies by far less than tol between them
            P = _true_points(w, fid, 5001)
            P = P[np.hypot(P[:, 0] / P[:, 2], P[:, 1] / P[:, 2]) < r_fold * (1 - 1e-6)]
            truth = _opencv_pixels(P, cam)
            inside = (truth[:, 0] >= 0) & (truth[:, 0] <= 640) & (truth[:, 1] >= 0) & (truth[:, 1] <= 480)
            polys = [f.points for f in view.features if f.fid == fid and f.kind == "polyline"]
            if not inside.any():
                continue
            assert polys, f"feature {fid} is in the image but has no polyline"
            d = np.min([_dist_to_polyline(truth[inside], p) for p in polys], axis=0)
            worst = max(worst, float(d.max()))
    assert worst <= tol, worst
    assert worst > tol / 10  # the check has teeth: curves really are approximated near the tolerance


def test_ends_cut_at_the_image_border_lie_on_the_true_curve():
    """A polyline end on the border is where the true curve (bisected with OpenCV's projection) crosses it."""

    rng = np.random.default_rng(11)
    checked = 0
    for _ in range(15):
        cam, w = _random_view(rng)
        view = project_view(w, cam, np.eye(3), np.zeros(3), np.ones(w.n_features, bool), 0.5)
        for f in view.features:
            if f.kind != "polyline" or not f.clipped:
                continue
            P = _true_points(w, f.fid, 4001)
            uv = _opencv_pixels(P, cam)
            for end in (f.points[0], f.points[-1]):
                on = [abs(end[0]), abs(end[0] - 640), abs(end[1]), abs(end[1] - 480)]
                side = int(np.argmin(on))
                if on[side] > 1e-9:
                    continue  # not an end at the border (cut by the fold radius)
                axis, level = (0, 0.0) if side == 0 else (0, 640.0) if side == 1 else (1, 0.0) if side == 2 \
                    else (1, 480.0)
                g = uv[:, axis] - level
                # the bracket of the dense curve nearest the end, then bisection on the true curve
                cross = np.flatnonzero(np.sign(g[:-1]) != np.sign(g[1:]))
                k = cross[np.argmin(np.linalg.norm(uv[cross] - end, axis=1))]
                a, b = k / 4000, (k + 1) / 4000

                def point(s, fid=f.fid, w=w, cam=cam):
                    return _opencv_pixels(_at(w, fid, s), cam)[0]

                ga = point(a)[axis] - level
                for _ in range(60):
                    m = 0.5 * (a + b)
                    gm = point(m)[axis] - level
                    if np.sign(gm) == np.sign(ga):
                        a, ga = m, gm
                    else:
                        b = m
                assert np.abs(point(0.5 * (a + b)) - end).max() < 1e-6, (end, point(0.5 * (a + b)))
                checked += 1
    assert checked > 20


def _at(w: World, fid: int, s: float) -> np.ndarray:
    """The camera-frame point at curve fraction s of feature fid (as _true_points)."""
    if fid < len(w.lines):
        a, b = w.lines[fid]
        return (a + s * (b - a))[None]
    e = fid - len(w.lines)
    t = 2 * math.pi * s
    return (w.ell_c[e] + math.cos(t) * w.ell_U[e] + math.sin(t) * w.ell_V[e])[None]


def test_no_conic_for_an_ellipse_wholly_outside_the_image():
    """Like lines and polylines, an ellipse seen outside the image gives no feature at all."""

    cam = Camera(name="c", f=600, cx=320, cy=240, width=640, height=480)
    w = World(feature_ids=["p.out", "p.in"], feature_kind=["ellipse", "ellipse"])
    w.ell_c = np.array([[4.0, 0.0, 2.0], [0.0, 0.0, 2.0]])  # 1200 px right of the centre; at the centre
    w.ell_U = np.array([[0.2, 0.0, 0.0], [0.2, 0.0, 0.0]])
    w.ell_V = np.array([[0.0, 0.2, 0.0], [0.0, 0.2, 0.0]])
    w.ell_arc, w.ell_full, w.ell_fid = np.tile([0.0, 2 * math.pi], (2, 1)), np.ones(2, bool), np.arange(2)
    view = project_view(w, cam, np.eye(3), np.zeros(3), np.ones(2, bool))
    assert {(f.fid, f.kind) for f in view.features} == {(1, "polyline"), (1, "conic")}


def test_too_small_a_tolerance_is_a_diagnostic_not_a_memory_blow_up():

    cam, w = _random_view(np.random.default_rng(3))
    with pytest.raises(WiredslError) as err:
        project_view(w, cam, np.eye(3), np.zeros(3), np.ones(w.n_features, bool), 1e-300)
    assert err.value.diagnostics[0].code == "E151"


@pytest.mark.parametrize("focal", [1e12, 1e300])
def test_huge_focal_lengths_give_finite_features(focal):

    cam, w = _random_view(np.random.default_rng(5))
    cam = cam.model_copy(update={"f": focal, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0})
    w.lines[0] = [[0.0, 0.0, 2.0], [1e-10, 1e-10, 3.0]]  # through the optical axis: seen even at 1e12 px
    view = project_view(w, cam, np.eye(3), np.zeros(3), np.ones(w.n_features, bool))
    assert view.features or focal > 1e12
    for f in view.features:
        assert np.isfinite(f.points).all()
        if f.conic is not None:
            assert all(np.isfinite(np.asarray(x, float)).all() for x in f.conic[:3])


def test_extreme_scales_and_focal_lengths_stay_finite_and_quiet():
    """Lines, ellipses, a silhouette and a corner from 1e-6 m to 1e15 m under focal lengths up to 1e300 px:
    finite features and raw strokes, or E151; no RuntimeWarning (errors in this suite), no LAPACK message."""
    rng = np.random.default_rng(2015)
    for _ in range(150):
        s = 10.0 ** rng.uniform(-6, 15)
        cam = Camera(name="c", f=10.0 ** rng.uniform(0, 300), cx=320, cy=240, width=640, height=480,
                     k1=rng.choice([0, rng.uniform(-1, 1)]), k2=rng.choice([0, rng.uniform(-1, 1)]),
                     p1=rng.choice([0, rng.uniform(-0.1, 0.1)]))
        w = World(feature_ids=[f"p.{i}" for i in range(11)], feature_kind=["line"] * 3 + ["ellipse"] * 6
                  + ["silhouette", "corner"])
        w.lines, w.line_fid, w.line_segment = rng.normal(size=(3, 2, 3)) * s, np.arange(3), -np.ones(3, int)
        axis = rng.normal(size=3)
        w.ell_c = rng.normal(size=(6, 3)) * s
        w.ell_U = np.tile(axis, (6, 1)) * 10.0 ** rng.uniform(-8, 3)
        flat = rng.random() < 0.3  # seen edge-on whatever the view
        w.ell_V = np.tile(np.cross(axis, rng.normal(size=3)), (6, 1)) * 10.0 ** rng.uniform(-8, 3) * (not flat)
        w.ell_arc, w.ell_full, w.ell_fid = np.tile([0.0, 2 * math.pi], (6, 1)), np.ones(6, bool), 3 + np.arange(6)
        w.sil_pair, w.sil_fid = np.array([[0, 1]]), np.array([9])
        w.corners, w.corner_fid = rng.normal(size=(1, 3)) * s, np.array([10])
        R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        try:
            v = project_view(w, cam, R, rng.normal(size=3) * s, np.ones(11, bool))
        except WiredslError as err:
            assert err.diagnostics[0].code == "E151"
            continue
        for f in v.features:
            assert np.isfinite(f.points).all()
            if f.conic is not None:
                assert np.isfinite(np.concatenate([f.conic[0], f.conic[1], [f.conic[2]]])).all()
        assert all(np.isfinite(r.world).all() for r in v.raw)
