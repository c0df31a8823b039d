"""Named hard cases: each gives finite, deterministic output or a clean diagnostic, and agrees with an
mpmath (50 digits) evaluation of the documented camera model where an answer exists."""

from __future__ import annotations

import math
import sys

import mpmath as mp
import numpy as np
import pytest
from helpers import circle, compile_text, errors_of, silhouette_segments

from wiredsl.effects import REGISTRY
from wiredsl.effects import calibration_error as calib
from wiredsl.effects.stereo_mismatch import angle_to_epipolar
from wiredsl.engine import geometry
from wiredsl.engine import imageset as im
from wiredsl.engine.simulate import Options, project_view, simulate
from wiredsl.engine.visibility import nearest_viewpoint
from wiredsl.engine.world import World, build_world
from wiredsl.montecarlo import Run
from wiredsl.scene import Camera, Pipeline

mp.mp.dps = 50
PX = 1e-6  # agreement required with the reference, in pixels
CAM = Camera(name="c", f=600, ax=1.0, ay=1.02, cx=320, cy=240, k1=-0.05, k2=0.004, p1=1e-4, p2=-2e-4,
             width=640, height=480)
PINHOLE = CAM.model_copy(update={"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0})


def ref_pixels(P, cam=CAM):
    """The camera model evaluated in 50-digit arithmetic (the README's formula, written plainly)."""
    X, Y, Z = (mp.mpf(float(v)) for v in P)
    x, y = X / Z, Y / Z
    r2 = x * x + y * y
    k1, k2, p1, p2 = (mp.mpf(v) for v in (cam.k1, cam.k2, cam.p1, cam.p2))
    radial = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return float(cam.f * cam.ax * xd + cam.cx), float(cam.f * cam.ay * yd + cam.cy)


def world_of_lines(*segments) -> World:
    w = World(feature_ids=[f"p.l{i}" for i in range(len(segments))], feature_kind=["line"] * len(segments))
    w.lines = np.array(segments, dtype=float).reshape(-1, 2, 3)
    w.line_fid = np.arange(len(segments))
    w.line_segment = -np.ones(len(segments), int)
    return w


def world_of_corners(*points) -> World:
    w = World(feature_ids=[f"p.c{i}" for i in range(len(points))], feature_kind=["corner"] * len(points))
    w.corners = np.array(points, dtype=float).reshape(-1, 3)
    w.corner_fid = np.arange(len(points))
    return w


def view(w: World, cam=CAM, tol=0.1):
    v = project_view(w, cam, np.eye(3), np.zeros(3), np.ones(w.n_features, bool), tol)
    for f in v.features:
        assert np.isfinite(f.points).all()
    return v


def ellipse_world(c, U, V, arc=(0.0, 2 * math.pi)) -> World:
    w = World(feature_ids=["p.e"], feature_kind=["ellipse"])
    w.ell_c, w.ell_U, w.ell_V = (np.array([x], float) for x in (c, U, V))
    w.ell_arc = np.array([arc], float)
    w.ell_full = np.array([arc[1] - arc[0] >= 2 * math.pi - 1e-12])
    w.ell_fid = np.array([0])
    return w


# ------------------------------------------------------------------ points and segments

def case_point_far_1e6_m():
    (f,) = view(world_of_corners([3e5, -2e5, 1e6])).features
    assert f.points[0] == pytest.approx(ref_pixels([3e5, -2e5, 1e6]), abs=PX)


def case_point_near_1e_6_m_is_not_projected():
    assert view(world_of_corners([0, 0, 1e-6])).features == []


def case_point_at_camera_centre_is_not_projected():
    assert view(world_of_corners([0, 0, 0])).features == []


def case_point_behind_camera_is_not_projected():
    assert view(world_of_corners([0.1, 0.1, -2])).features == []


def case_point_exactly_at_image_corner_is_kept():
    (f,) = view(world_of_corners([-320 / 600 * 2, -240 / 612 * 2, 2]), cam=PINHOLE).features  # f ay = 612
    assert f.points[0] == pytest.approx([0, 0], abs=PX)


def case_segment_crossing_camera_plane_is_clipped_at_near():
    (f,) = view(world_of_lines([[0.1, 0.05, -1.0], [0.1, 0.05, 3.0]]), cam=PINHOLE).features
    assert f.clipped
    near, far = sorted(f.points.tolist(), key=lambda p: -abs(p[0] - 320))
    # the part near the camera plane projects far outside: the visible part ends on the image border
    assert min(near[0], 640 - near[0], near[1], 480 - near[1]) == pytest.approx(0, abs=1e-9)
    assert far == pytest.approx(ref_pixels([0.1, 0.05, 3.0], PINHOLE), abs=PX)


def case_segment_through_camera_centre():
    for f in view(world_of_lines([[0, 0, -1.0], [0, 0.2, 1.0]]), cam=PINHOLE).features:
        assert f.clipped


def case_segment_from_1e_6_to_1e6_m():
    feats = view(world_of_lines([[1e-7, 1e-7, 1e-6], [2e5, 1e5, 1e6]]), cam=PINHOLE).features
    (f,) = feats
    assert f.points[-1] == pytest.approx(ref_pixels([2e5, 1e5, 1e6], PINHOLE), abs=PX)


def case_segment_entirely_behind():
    assert view(world_of_lines([[0, 0, -1.0], [1, 1, -5.0]])).features == []


def case_segment_in_the_camera_plane():
    assert view(world_of_lines([[-1, 0, 0.0], [1, 0, 0.0]])).features == []


def case_segment_pointing_at_the_camera_is_a_point_and_dropped():
    assert view(world_of_lines([[0.1, 0.1, 1.0], [0.2, 0.2, 2.0]]), cam=PINHOLE).features == []


def case_segment_along_the_image_border():
    y = -240 / 612 * 2
    (f,) = view(world_of_lines([[-0.5, y, 2.0], [0.5, y, 2.0]]), cam=PINHOLE).features
    assert f.points[:, 1] == pytest.approx([0, 0], abs=PX)


def case_distorted_far_segment_matches_reference():
    (f,) = view(world_of_lines([[-3e5, 1e5, 1e6], [2e5, -1.5e5, 1e6]]), tol=0.01).features
    assert f.points[0] == pytest.approx(ref_pixels([-3e5, 1e5, 1e6]), abs=PX)
    assert f.points[-1] == pytest.approx(ref_pixels([2e5, -1.5e5, 1e6]), abs=PX)


def case_distorted_segment_vertices_lie_on_the_reference_curve():
    A, B = np.array([-1.2, -0.7, 2.0]), np.array([1.1, 0.8, 2.5])
    (f,) = view(world_of_lines([A, B]), tol=0.01).features
    for p in f.points[1:-1]:
        # find the 3D point whose reference projection is p: along A->B by bisection on u
        lo, hi = 0.0, 1.0
        for _ in range(60):
            mid = (lo + hi) / 2
            if ref_pixels(A + mid * (B - A))[0] < p[0]:
                lo = mid
            else:
                hi = mid
        assert ref_pixels(A + lo * (B - A))[1] == pytest.approx(p[1], abs=1e-6)


# ------------------------------------------------------------------ distortion folding

def case_fold_radius_matches_mpmath_root():
    for k1, k2 in ((-0.5, 0.0), (-0.3, 0.02), (-0.2, -0.01)):
        r = geometry.fold_radius(k1, k2)
        ref = mp.findroot(lambda r, k1=k1, k2=k2: 1 + 3 * k1 * r**2 + 5 * k2 * r**4, 1.0 / math.sqrt(-3 * k1))
        assert r == pytest.approx(float(ref), rel=1e-12)


def case_folding_distortion_is_clipped_not_wrapped():
    cam = CAM.model_copy(update={"k1": -0.5, "k2": 0.0, "p1": 0.0, "p2": 0.0})  # folds at r = 0.816
    feats = view(world_of_lines([[-3.0, 0.01, 1.0], [3.0, 0.01, 1.0]]), cam=cam, tol=0.01).features
    assert feats
    for f in feats:
        assert f.clipped
        assert np.all(np.diff(f.points[:, 0]) > 0) or np.all(np.diff(f.points[:, 0]) < 0)  # one-to-one: no fold


def case_corner_beyond_the_fold_is_dropped():
    cam = CAM.model_copy(update={"k1": -0.5, "k2": 0.0})
    assert view(world_of_corners([0.9, 0.0, 1.0]), cam=cam).features == []


# ------------------------------------------------------------------ ellipses and conics

def _conic_points_ok(c, U, V, cam=PINHOLE):
    (conic,) = [f for f in view(ellipse_world(c, U, V), cam=cam).features if f.kind == "conic"]
    centre, axes, angle, _ = conic.conic
    e1 = np.array([math.cos(angle), math.sin(angle)])
    e2 = np.array([-e1[1], e1[0]])
    for t in np.linspace(0, 2 * np.pi, 37):
        p = np.array(ref_pixels(c + math.cos(t) * U + math.sin(t) * V, cam))
        q = p - centre
        value = (q @ e1 / axes[0]) ** 2 + (q @ e2 / axes[1]) ** 2
        assert value == pytest.approx(1.0, abs=2 * PX / min(axes))
    return axes


def case_circle_facing_the_camera_zero_eccentricity():
    axes = _conic_points_ok(*circle([0.1, 0.0, 2.0], [0, 0, 1], 0.3))
    assert axes[0] == pytest.approx(axes[1] / 1.02 * 1.02, rel=0.05)


def case_ellipse_of_huge_eccentricity():
    c = np.array([0.0, 0.1, 3.0])
    _conic_points_ok(c, np.array([0.5, 0, 0]), np.array([0, 0.5e-6, 0]))


def case_ellipse_nearly_edge_on():
    _conic_points_ok(*circle([0.0, 0.0, 3.0], [0, 1, 1e-6], 0.3))


def case_ellipse_exactly_edge_on_has_no_conic_but_a_finite_polyline():
    feats = view(ellipse_world(*circle([0.0, 0.0, 3.0], [0, 1, 0], 0.3)), cam=PINHOLE).features
    assert not [f for f in feats if f.kind == "conic"]
    assert all(f.kind == "polyline" and np.ptp(f.points[:, 1]) < 1e-9 for f in feats)


def case_ellipse_crossing_the_camera_plane():
    feats = view(ellipse_world(*circle([0.0, 0.3, 0.5], [0, 1, 0], 1.0)), cam=CAM).features
    assert feats and all(f.clipped for f in feats)


def case_ellipse_section_arc_is_reported_in_image_parameter():
    c, U, V = circle([0.0, 0.0, 3.0], [0.2, 0.1, 1], 0.4)
    feats = view(ellipse_world(c, U, V, arc=(0.3, 2.0)), cam=PINHOLE).features
    (conic,) = [f for f in feats if f.kind == "conic"]
    centre, axes, angle, (s0, s1) = conic.conic
    e1 = np.array([math.cos(angle), math.sin(angle)])
    e2 = np.array([-e1[1], e1[0]])
    for t in (0.3, 2.0):
        p = np.array(ref_pixels(c + math.cos(t) * U + math.sin(t) * V, PINHOLE))
        s = math.atan2((p - centre) @ e2 / axes[1], (p - centre) @ e1 / axes[0])
        assert min(abs((s - s0 + math.pi) % (2 * math.pi) - math.pi), abs((s - s1 + math.pi) % (2 * math.pi)
                                                                           - math.pi)) < 1e-6


# ------------------------------------------------------------------ silhouettes

def _sil(a, b):
    segs = silhouette_segments(*a, *b)
    for A, B in segs:
        assert np.isfinite(A).all() and np.isfinite(B).all()
    return segs


def case_silhouette_nearly_concentric():
    for eps in (0.0, 1e-12, 1e-8):
        _sil(circle([eps, 0, 3.0], [0, 0, 1], 0.3), circle([0, 0, 4.0], [0, 0, 1], 0.3))


def case_silhouette_camera_exactly_on_the_surface():
    _sil(circle([0.3, -0.5, 0.0], [0, 1, 0], 0.3), circle([0.3, 0.5, 0.0], [0, 1, 0], 0.3))


def case_silhouette_camera_inside_the_cylinder():
    assert _sil(circle([0.0, -0.5, 0.0], [0, 1, 0], 0.3), circle([0.0, 0.5, 0.0], [0, 1, 0], 0.3)) == []


def case_silhouette_cone_to_a_point_like_top():
    assert len(_sil(circle([0, -0.5, 3.0], [0, 1, 0], 0.3), circle([0, 0.5, 3.0], [0, 1, 0], 1e-6))) == 2


def case_silhouette_tangent_point_matches_mpmath_tangency():
    a, b = circle([0.2, -0.5, 3.0], [0, 1, 0], 0.3), circle([0.2, 0.5, 3.0], [0, 1, 0], 0.3)
    for A, _ in _sil(a, b):
        # the viewing ray to the tangent point is tangent to the circle: its direction is orthogonal to the
        # circle's radius there (in the circle's plane), checked in 50 digits
        c = [mp.mpf(float(v)) for v in a[0]]
        p = [mp.mpf(float(v)) for v in A]
        radial = [p[i] - c[i] for i in range(3)]
        assert abs(sum(p[i] * radial[i] for i in range(3))) < mp.mpf("1e-12")


# ------------------------------------------------------------------ the epipolar band

def _band_angles(deg):
    a = np.array([[100.0, 100.0]])
    rad = math.radians(deg)
    b = a + 50 * np.array([[math.cos(rad), math.sin(rad)]])
    return float(np.degrees(angle_to_epipolar(a, b, np.array([1.0, 0.0, 0.0])))[0])


def case_line_exactly_parallel_to_epipolar():
    assert _band_angles(0.0) == 0.0


def case_line_at_the_band_edge_exactly():
    assert _band_angles(5.0) == pytest.approx(5.0, abs=1e-12)


def case_line_a_hair_inside_and_outside_the_band():
    assert _band_angles(5.0 - 1e-9) < 5.0 < _band_angles(5.0 + 1e-9)


def case_epipole_inside_the_image():
    # a forward-moving baseline puts the epipole in the image: directions still well defined around it
    a = np.array([[320.0, 240.0], [330.0, 240.0]])
    b = a + np.array([[0.0, 0.0], [10.0, 0.0]])
    got = angle_to_epipolar(a, b, np.array([320.0, 240.0, 1.0]))
    assert np.isfinite(got).all() and got[1] == pytest.approx(0.0)


# ------------------------------------------------------------------ calibration matrices

def _draws(M, kind="information", cutoff=1e-9):
    p = REGISTRY["calibration_error"].Params(sigma=1.0, cutoff=cutoff)
    s = calib.sampler(p, kind, M, [f"left.{k}" for k in ("f", "cx", "cy", "k")][: len(M)])
    d = np.array([calib.draw(s, t, 0) for t in range(100)])
    assert np.isfinite(d).all()
    return s, d


def case_calibration_singular_zero_matrix():
    s, d = _draws(np.zeros((3, 3)).tolist())
    assert np.abs(d).max() == 0 and len(s.unconstrained) == 3


def case_calibration_rank_deficient():
    v = np.array([[1.0, 2.0, 3.0]])
    s, d = _draws((v.T @ v).tolist())
    assert len(s.unconstrained) == 2 and np.abs(d).max() < 10


def case_calibration_condition_1e12():
    s, d = _draws(np.diag([1.0, 1e-6, 1e-12]).tolist())  # below the default cutoff 1e-9: unconstrained
    assert s.unconstrained == ["left.cy"] and np.abs(d[:, 2]).max() == 0
    s, d = _draws(np.diag([1.0, 1e-6, 1e-12]).tolist(), cutoff=1e-14)  # admitted: large but finite
    assert s.unconstrained == [] and 1e5 < np.abs(d[:, 2]).max() < 1e7


def case_calibration_condition_1e16():
    s, d = _draws(np.diag([1.0, 1e-8, 1e-16]).tolist())
    assert s.unconstrained == ["left.cy"] and np.abs(d).max() < 1e5


def case_calibration_slightly_indefinite_from_rounding():
    M = np.diag([4.0, 1.0, 1e-17])
    M[2, 2] = -1e-17
    assert errors_of("wiredsl 1\ncamera c { focal 600px\n size (640px, 480px) }\nrig r { left c at (0, 0, 1) "
                     "looking (1, 0, 0)\n right c at (0, -0.1, 1) looking (1, 0, 0)\n calibration covariance order "
                     "[left.f, left.cx, left.cy] matrix [[4, 0, 0], [0, 1, 0], [0, 0, -1e-17]] }\n") == []
    s, d = _draws(M.tolist(), kind="covariance")
    assert np.abs(d[:, 2]).max() == 0


def case_calibration_perturbed_rig_projects_finitely():
    from wiredsl.language.compile import compile_file

    scene, _, _ = compile_file("scenes/lab.wd")
    order = scene.rig.calibration.order
    big = calib.perturb(scene, np.full(len(order), 0.5), order)
    for r in simulate(big, Options(poses=(0,))):
        for v in (r.left, r.right):
            assert all(np.isfinite(f.points).all() for f in v.features)


# ------------------------------------------------------------------ view-points, empty inputs, fractions

def case_robot_exactly_on_a_view_point():
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, 1.0]])
    assert nearest_viewpoint(pts, np.array([[1.0, 0.0]])).tolist() == [1]


def case_robot_exactly_between_two_view_points():
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, 1.0]])
    assert nearest_viewpoint(pts, np.array([[0.5, 0.0]])).tolist() == [0]


def case_robot_between_view_points_with_rounding():
    pts = np.array([[0.1, 0.2], [0.3, 0.2]])
    assert nearest_viewpoint(pts, np.array([[0.2, 0.2]])).tolist() == [0]  # 0.2 - 0.1 vs 0.3 - 0.2 in floats


EMPTY = ("wiredsl 1\ncamera c { focal 600px\n size (640px, 480px) }\nrig r { left c at (0, 0.05, 1) looking (1, 0, 0)"
         "\n right c at (0, -0.05, 1) looking (1, 0, 0) }\npath p { pose (0, 0) }\n")


def case_empty_scene_builds_empty_views():
    scene, _ = compile_text(EMPTY)
    (r,) = simulate(scene)
    assert r.left.features == [] and r.right.features == []


def case_empty_pipeline_is_the_ideal_projection():
    scene, _ = compile_text(EMPTY)
    run = Run.create(scene, build_world(scene), Pipeline(name="p"), 0, Options())
    assert run.stages == []


def _lab_strokes(trials=3):
    from test_effects import lab_view

    return lab_view(side="right", trials=trials)


def _ctx(trials=3):
    from test_effects import ctx

    return ctx(side="right", trials=trials)


def case_edge_loss_fraction_one_removes_everything():
    out = REGISTRY["edge_loss"].apply(REGISTRY["edge_loss"].Params(fraction=1.0), _lab_strokes(), _ctx())
    assert out.n_strokes == 0 or im.arc_lengths(out)[1].max() < 1e-9


def case_corner_loss_keep_zero_and_one():
    s = _lab_strokes()
    assert len(REGISTRY["corner_loss"].apply(REGISTRY["corner_loss"].Params(keep=0.0), s, _ctx()).corners) == 0
    assert REGISTRY["corner_loss"].apply(REGISTRY["corner_loss"].Params(keep=1.0), s, _ctx()) is s


def case_corner_mismatch_fraction_one_moves_all_within_radius():
    s = _lab_strokes()
    out = REGISTRY["corner_mismatch"].apply(REGISTRY["corner_mismatch"].Params(fraction=1.0, radius=4.0), s, _ctx())
    d = np.linalg.norm(out.corners - s.corners, axis=1)
    assert (d > 0).all() and d.max() <= 4.0


def case_stereo_mismatch_fraction_one_shifts_all_within_disparity():
    s = _lab_strokes()
    p = REGISTRY["stereo_mismatch"].Params(band=0.0, fraction=1.0, disparity=7.0)
    out = REGISTRY["stereo_mismatch"].apply(p, s, _ctx())
    d = np.linalg.norm(out.pts - s.pts, axis=1)
    assert d.max() <= 7.0 + 1e-9 and (d > 0).mean() > 0.99


def case_stereo_band_ninety_degrees_removes_everything():
    p = REGISTRY["stereo_mismatch"].Params(band=math.pi / 2, fraction=0.0)
    assert REGISTRY["stereo_mismatch"].apply(p, _lab_strokes(), _ctx()).n_strokes == 0


def case_lateral_shift_range_zero_is_identity():
    s = _lab_strokes()
    assert REGISTRY["lateral_shift"].apply(REGISTRY["lateral_shift"].Params(range=0.0), s, _ctx()) is s


def case_all_stages_at_their_extremes_stay_finite():
    s = _lab_strokes()
    c = _ctx()
    for name, kw in (("edge_loss", {"fraction": 0.999}), ("lateral_shift", {"range": 1000}),
                     ("approx_error", {"sigma": 100}), ("corner_error", {"sigma": 100}),
                     ("corner_mismatch", {"fraction": 1, "radius": 10000}),
                     ("stereo_mismatch", {"fraction": 1, "disparity": 10000})):
        s = REGISTRY[name].apply(REGISTRY[name].Params(**kw), s, c)
        assert np.isfinite(s.pts).all() and np.isfinite(s.corners).all()


def case_vertical_viewing_direction_is_a_clean_diagnostic():
    errs = errors_of("wiredsl 1\ncamera c { focal 600px\n size (640px, 480px) }\nrig r { left c at (0, 0, 1) "
                     "looking (0, 0, -1)\n right c at (0, -0.1, 1) looking (1, 0, 0) }\n")
    assert errs and "E122" in errs[0]


CASES = {name[5:]: fn for name, fn in sorted(globals().items()) if name.startswith("case_")}


def fingerprint(value) -> bytes:
    """Bytes that change with any number in `value`: arrays by dtype, shape and bytes, models by their JSON,
    containers and dataclasses member by member; anything else by its type alone (no addresses)."""
    import dataclasses

    if isinstance(value, np.ndarray | np.generic):
        a = np.ascontiguousarray(value)
        return b"A" + str((a.dtype.str, a.shape)).encode() + (a.tobytes() if a.dtype.kind != "O" else
                                                               b"".join(fingerprint(x) for x in a.ravel()))
    if isinstance(value, bool | int | float | complex | str | bytes | type(None)):
        return repr(value).encode()
    if isinstance(value, dict):
        return b"{" + b",".join(fingerprint(k) + b":" + fingerprint(v) for k, v in value.items()) + b"}"
    if isinstance(value, list | tuple | set | frozenset):
        items = sorted(value, key=repr) if isinstance(value, set | frozenset) else value
        return b"[" + b",".join(fingerprint(v) for v in items) + b"]"
    if hasattr(value, "model_dump_json"):
        return value.model_dump_json().encode()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return type(value).__name__.encode() + fingerprint({f.name: getattr(value, f.name)
                                                            for f in dataclasses.fields(value)})
    return type(value).__name__.encode()


def outcome(case) -> bytes:
    """The fingerprint of every value a case and the helpers of this file computed: each returning frame's
    locals and return value, in order (the case's assertions see only some of them)."""
    here = case.__code__.co_filename
    trace: list[bytes] = []

    def hook(frame, event, arg):
        if event == "return" and frame.f_code.co_filename == here:
            trace.append(frame.f_code.co_name.encode() + fingerprint(dict(frame.f_locals)) + fingerprint(arg))

    sys.setprofile(hook)
    try:
        case()
    finally:
        sys.setprofile(None)
    return b"\n".join(trace)


def test_the_outcome_tells_a_case_with_hidden_state():
    """What test_hard_case relies on: a case drawing from a global stream gives two different outcomes."""
    def leaky():
        x = np.random.default_rng().random(3)  # noqa: NPY002 (the hidden state this test must see)
        assert x.shape == (3,)

    def clean():
        x = np.random.default_rng(7).random(3)
        assert x.shape == (3,)

    assert outcome(leaky) != outcome(leaky)
    assert outcome(clean) == outcome(clean) and len(outcome(clean)) > 24


@pytest.mark.parametrize("name", sorted(CASES))
def test_hard_case(name, engine):
    """Every case on both engines (a stage applied by hand runs in the kernel under engine "kernel")."""
    first = outcome(CASES[name])
    # deterministic: the same case twice computes the same values, byte for byte (no hidden state)
    assert outcome(CASES[name]) == first
