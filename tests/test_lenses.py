"""Lens models beyond k1, k2: OpenCV's rational model (k3..k6) and the equidistant fisheye, against OpenCV,
mpmath at wide angles, and the fisheye's near rule (points beside and behind the camera's plane)."""

from __future__ import annotations

import math

import cv2
import mpmath
import numpy as np
import pytest
from test_projection import _dist_to_polyline, random_rotation

from wiredsl.engine import geometry
from wiredsl.engine.simulate import project_view
from wiredsl.engine.world import World
from wiredsl.scene import Camera


def _K(cam: Camera) -> np.ndarray:
    return np.array([[cam.f * cam.ax, 0, cam.cx], [0, cam.f * cam.ay, cam.cy], [0, 0, 1.0]])


def rational_camera(rng: np.random.Generator) -> Camera:
    return Camera(name="c", f=rng.uniform(200, 2000), ax=rng.uniform(0.8, 1.2), ay=rng.uniform(0.8, 1.2),
                  cx=rng.uniform(200, 400), cy=rng.uniform(150, 300), width=640, height=480,
                  k1=rng.uniform(-0.3, 0.3), k2=rng.uniform(-0.1, 0.1), k3=rng.uniform(-0.05, 0.05),
                  k4=rng.uniform(-0.2, 0.2), k5=rng.uniform(-0.05, 0.05), k6=rng.uniform(-0.02, 0.02),
                  p1=rng.uniform(-0.01, 0.01), p2=rng.uniform(-0.01, 0.01))


def fisheye_camera(rng: np.random.Generator, **kw) -> Camera:
    return Camera(name="c", f=rng.uniform(150, 600), ax=rng.uniform(0.9, 1.1), ay=rng.uniform(0.9, 1.1),
                  cx=rng.uniform(500, 700), cy=rng.uniform(400, 600), width=1280, height=1024,
                  distortion="equidistant", k1=rng.uniform(-0.05, 0.05), k2=rng.uniform(-0.01, 0.01),
                  k3=rng.uniform(-0.002, 0.002), k4=rng.uniform(-0.0005, 0.0005), **kw)


def test_rational_model_agrees_with_opencv_8_coefficients_to_1e_6_px():
    rng = np.random.default_rng(1703)
    worst, n = 0.0, 0
    for _ in range(300):
        cam = rational_camera(rng)
        R, t = random_rotation(rng), rng.normal(size=3)
        xy = rng.uniform(-0.8, 0.8, size=(50, 2))
        xy = xy[np.hypot(*xy.T) < 0.9 * geometry.lens_limit(cam)]  # one-to-one there
        z = rng.uniform(0.5, 20, size=len(xy))
        P_world = (np.column_stack([xy * z[:, None], z]) - t) @ R
        ours = geometry.cam_to_pixels(geometry.world_to_cam(P_world, R, t), cam)
        dist = np.array([cam.k1, cam.k2, cam.p1, cam.p2, cam.k3, cam.k4, cam.k5, cam.k6])
        theirs, _ = cv2.projectPoints(P_world.reshape(-1, 1, 3), cv2.Rodrigues(R)[0], t, _K(cam), dist)
        worst = max(worst, float(np.abs(ours - theirs.reshape(-1, 2)).max()))
        n += len(xy)
    assert n > 10_000 and worst < 1e-6, (n, worst)


def test_fisheye_agrees_with_opencv_fisheye_to_1e_6_px():
    """cv2.fisheye.projectPoints, which takes Z > 0 (theta below 90 deg): up to 85 deg off the axis."""
    rng = np.random.default_rng(1704)
    worst, n = 0.0, 0
    for _ in range(300):
        cam = fisheye_camera(rng)
        R, t = random_rotation(rng), rng.normal(size=3)
        theta = rng.uniform(0, math.radians(85), 50)
        theta = theta[theta < geometry.lens_limit(cam)]
        phi = rng.uniform(-math.pi, math.pi, len(theta))
        d = rng.uniform(0.5, 20, len(theta))
        P_cam = d[:, None] * np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
        P_world = (P_cam - t) @ R
        ours = geometry.cam_to_pixels(geometry.world_to_cam(P_world, R, t), cam)
        D = np.array([cam.k1, cam.k2, cam.k3, cam.k4])
        theirs, _ = cv2.fisheye.projectPoints(P_world.reshape(-1, 1, 3), cv2.Rodrigues(R)[0], t, _K(cam), D)
        worst = max(worst, float(np.abs(ours - theirs.reshape(-1, 2)).max()))
        n += len(theta)
    assert n > 10_000 and worst < 1e-6, (n, worst)


def _mp_fisheye(P, cam: Camera) -> tuple[float, float]:
    """The equidistant model at 40 digits: the wide-angle reference (OpenCV's fisheye stops at 90 deg)."""
    with mpmath.workdps(40):
        X, Y, Z = (mpmath.mpf(float(v)) for v in P)
        rho = mpmath.sqrt(X * X + Y * Y)
        th = mpmath.atan2(rho, Z)
        k = [mpmath.mpf(v) for v in (cam.k1, cam.k2, cam.k3, cam.k4)]
        td = th * (1 + k[0] * th**2 + k[1] * th**4 + k[2] * th**6 + k[3] * th**8)
        fx, fy = mpmath.mpf(cam.f) * cam.ax, mpmath.mpf(cam.f) * cam.ay
        return float(fx * td * X / rho + cam.cx), float(fy * td * Y / rho + cam.cy)


def test_fisheye_at_and_past_90_degrees_matches_mpmath():
    """Hard cases: theta near 90 deg (Z tiny, either sign), past it up to 100 deg, near the axis, far away."""
    rng = np.random.default_rng(1705)
    worst, n = 0.0, 0
    for _ in range(40):
        cam = fisheye_camera(rng)
        theta = np.concatenate([math.pi / 2 + rng.uniform(-1e-9, 1e-9, 5), [math.pi / 2],
                                rng.uniform(math.radians(85), math.radians(100), 10), rng.uniform(1e-12, 1e-6, 3)])
        phi = rng.uniform(-math.pi, math.pi, len(theta))
        d = 10.0 ** rng.uniform(-2, 4, len(theta))
        P = d[:, None] * np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
        ours = geometry.cam_to_pixels(P, cam)
        ref = np.array([_mp_fisheye(p, cam) for p in P])
        worst = max(worst, float(np.abs(ours - ref).max()))
        n += len(P)
    assert worst < 1e-6, worst


@pytest.mark.parametrize("k", [(0.0,) * 6, (-0.3, 0.1, 0.0, 0.0, 0.0, 0.0), (-0.2, 0.05, -0.01, 0.0, 0.0, 0.0),
                               (0.1, 0.0, 0.0, 0.5, 0.0, 0.0), (-0.1, 0.02, 0.001, -0.3, 0.05, 0.01),
                               (0.0, 0.0, 0.0, -0.5, 0.0, 0.0)])
def test_rational_fold_radius_is_where_the_radial_map_stops_increasing(k):
    k1, k2, k3, k4, k5, k6 = k
    r = geometry.fold_radius(*k)

    def g(r):
        s = r * r
        return r * (1 + k1 * s + k2 * s**2 + k3 * s**3) / (1 + k4 * s + k5 * s**2 + k6 * s**3)

    top = r if math.isfinite(r) else 20.0
    rs = np.linspace(0, top, 20001)[:-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        assert np.all(np.diff(g(rs)) > 0)
        if math.isfinite(r):  # past it the map turns back, or its denominator crosses zero
            assert g(r * 1.01) < g(r * 0.999) or (1 + k4 * r**2 + k5 * r**4 + k6 * r**6) * (
                1 + k4 * (1.01 * r)**2 + k5 * (1.01 * r)**4 + k6 * (1.01 * r)**6) <= 0


@pytest.mark.parametrize("k", [(0.0, 0.0, 0.0, 0.0), (-0.1, 0.0, 0.0, 0.0), (0.02, -0.01, 0.001, -0.0002),
                               (-0.05, 0.004, 0.0, 0.0)])
def test_fisheye_limit_is_where_theta_d_stops_increasing_or_180_deg(k):
    lim = geometry.fisheye_max_angle(*k)
    theta = np.linspace(0, lim, 20001)
    td = theta * (1 + k[0] * theta**2 + k[1] * theta**4 + k[2] * theta**6 + k[3] * theta**8)
    assert np.all(np.diff(td) > 0)
    if lim < math.pi:
        x = lim * 1.001
        assert x * (1 + k[0] * x**2 + k[1] * x**4 + k[2] * x**6 + k[3] * x**8) < td[-1]
    assert geometry.fisheye_max_angle(*k, fov=math.radians(190)) == min(lim, math.radians(95))


@pytest.mark.parametrize("deg", [60.0, 90.0, 95.0, 120.0, 179.0])
def test_fisheye_segment_clip_matches_dense_sampling(deg):
    """The parts a fisheye images (up to three a segment) are where dense samples are visible."""
    rng = np.random.default_rng(int(deg))
    A, B = rng.normal(size=(1000, 3)), rng.normal(size=(1000, 3))
    A[:100] *= 0.002  # some through the NEAR ball about the centre
    lim = math.radians(deg)
    rows, t0, t1 = geometry.clip_segments_lens(A, B, np.ones(len(A), int), np.full(len(A), lim))
    ts = np.linspace(0, 1, 2001)
    P = A[:, None] + ts[None, :, None] * (B - A)[:, None]
    seen = geometry.visible(P, 1, lim)
    pred = np.zeros_like(seen)
    np.logical_or.at(pred, rows, (ts[None] >= t0[:, None] - 1e-9) & (ts[None] <= t1[:, None] + 1e-9))
    assert ((pred != seen).sum(axis=1) <= 2).all()  # at most the boundary samples differ
    assert np.bincount(rows, minlength=len(A)).max() >= 2 if deg > 90 else True


def test_a_fisheye_sees_beside_and_behind_its_plane_and_not_past_its_fov():
    cam = Camera(name="c", f=300, cx=640, cy=512, width=1280, height=1024, distortion="equidistant",
                 fov=math.radians(190))
    lim = geometry.lens_limit(cam)
    P = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, -0.05], [1.0, 0.0, -0.1], [0.0, 0.0, -1.0], [0.0, 0.0, 1e-4]])
    assert geometry.visible(P, 1, lim).tolist() == [True, True, False, False, False]  # 90, 92.9, 95.7 deg; NEAR
    u = geometry.cam_to_pixels(P[:2], cam)[:, 0]
    assert u == pytest.approx(640 + 300 * np.array([math.pi / 2, math.atan2(1, -0.05)]), abs=1e-9)


# --------------------------------------------------------------------------- whole views under a fisheye

def _fisheye_view(rng: np.random.Generator):
    """A 190 deg fisheye amid lines and ellipses all around it, some behind its plane."""
    cam = fisheye_camera(rng, fov=math.radians(190)).model_copy(update={"f": 250.0, "cx": 640.0, "cy": 512.0})
    n_lines, n_ell = 8, 4
    A = np.column_stack([rng.uniform(-3, 3, (n_lines, 2)), rng.uniform(-1.5, 4, n_lines)])
    B = np.column_stack([rng.uniform(-3, 3, (n_lines, 2)), rng.uniform(-1.5, 4, n_lines)])
    w = World(feature_ids=[f"p.f{i}" for i in range(n_lines + n_ell)],
              feature_kind=["line"] * n_lines + ["ellipse"] * n_ell)
    w.lines, w.line_fid, w.line_segment = np.stack([A, B], axis=1), np.arange(n_lines), -np.ones(n_lines, int)
    c = np.column_stack([rng.uniform(-2, 2, (n_ell, 2)), rng.uniform(-1, 3, n_ell)])
    U = rng.normal(size=(n_ell, 3))
    V = np.cross(U, rng.normal(size=(n_ell, 3)))
    U *= rng.uniform(0.3, 1.0, (n_ell, 1)) / np.linalg.norm(U, axis=1, keepdims=True)
    V *= rng.uniform(0.1, 1.0, (n_ell, 1)) / np.linalg.norm(V, axis=1, keepdims=True)
    w.ell_c, w.ell_U, w.ell_V = c, U, V
    w.ell_arc = np.tile([0.0, 2 * math.pi], (n_ell, 1))
    w.ell_full, w.ell_fid = np.ones(n_ell, bool), n_lines + np.arange(n_ell)
    return cam, w


def _curve(w: World, fid: int, t: np.ndarray) -> np.ndarray:
    if fid < len(w.lines):
        a, b = w.lines[fid]
        return a + t[:, None] * (b - a)
    e = fid - len(w.lines)
    s = 2 * math.pi * t
    return w.ell_c[e] + np.cos(s)[:, None] * w.ell_U[e] + np.sin(s)[:, None] * w.ell_V[e]


def test_fisheye_polylines_stay_within_tolerance():
    """Every visible curve point inside the image (4,001 a feature, projected by the model checked against
    OpenCV and mpmath above) lies within tol of the feature's polylines, past 90 deg too."""
    rng, tol = np.random.default_rng(31), 0.05
    worst, behind = 0.0, 0
    for _ in range(4):
        cam, w = _fisheye_view(rng)
        lim = geometry.lens_limit(cam)
        view = project_view(w, cam, np.eye(3), np.zeros(3), np.ones(w.n_features, bool), tol)
        for fid in range(w.n_features):
            P = _curve(w, fid, np.linspace(0.0, 1.0, 4001))
            P = P[geometry.visible(P, 1, lim * (1 - 1e-6))]
            truth = geometry.cam_to_pixels(P, cam)
            inside = (truth[:, 0] >= 0) & (truth[:, 0] <= 1280) & (truth[:, 1] >= 0) & (truth[:, 1] <= 1024)
            if not inside.any():
                continue
            behind += int((P[inside, 2] < 0).sum())
            polys = [f.points for f in view.features if f.fid == fid and f.kind == "polyline"]
            assert polys, f"feature {fid} is in the image but has no polyline"
            d = np.min([_dist_to_polyline(truth[inside], p) for p in polys], axis=0)
            worst = max(worst, float(d.max()))
    assert worst <= tol and worst > tol / 10, worst
    assert behind > 100  # the views really image points behind the camera's plane


def test_fisheye_ends_at_the_image_border_and_at_the_lens_limit_lie_on_the_true_curve():
    rng = np.random.default_rng(33)
    on_border = on_limit = 0
    for _ in range(5):
        cam, w = _fisheye_view(rng)
        cam = cam.model_copy(update={"width": 900, "height": 700, "cx": 450.0, "cy": 350.0})  # cuts the circle
        lim = geometry.lens_limit(cam)
        view = project_view(w, cam, np.eye(3), np.zeros(3), np.ones(w.n_features, bool), 0.5)
        for f in view.features:
            if f.kind != "polyline" or not f.clipped:
                continue
            t = np.linspace(0, 1, 50001)
            uv = geometry.cam_to_pixels(_curve(w, f.fid, t), cam)
            for end in (f.points[0], f.points[-1]):
                d = np.hypot(*(uv - end).T)
                k = int(np.nanargmin(d))
                assert d[k] < 0.2, (f.fid, end)  # on the curve to the dense sampling's resolution
                on = [abs(end[0]), abs(end[0] - 900), abs(end[1]), abs(end[1] - 700)]
                side = int(np.argmin(on))
                if on[side] < 1e-9:  # where the true curve crosses that border: bisected on the curve
                    axis, level = (0, 0.0) if side == 0 else (0, 900.0) if side == 1 else (1, 0.0) if side == 2 \
                        else (1, 700.0)
                    g = uv[:, axis] - level
                    cross = np.flatnonzero(np.sign(g[:-1]) * np.sign(g[1:]) < 0)
                    j = cross[np.argmin(np.abs(cross - k))]
                    a, b = t[j], t[j + 1]
                    ga = g[j]
                    for _ in range(60):
                        m = 0.5 * (a + b)
                        gm = geometry.cam_to_pixels(_curve(w, f.fid, np.array([m])), cam)[0, axis] - level
                        a, b, ga = (m, b, gm) if np.sign(gm) == np.sign(ga) else (a, m, ga)
                    truth = geometry.cam_to_pixels(_curve(w, f.fid, np.array([0.5 * (a + b)])), cam)[0]
                    assert np.abs(truth - end).max() < 1e-6, (end, truth)
                    on_border += 1
                else:  # cut by the lens limit: the point there is at theta = limit
                    P = _curve(w, f.fid, t[k:k + 1])[0]
                    theta = math.atan2(math.hypot(P[0], P[1]), P[2])
                    if abs(theta - lim) < 1e-3:
                        on_limit += 1
    assert on_border > 10 and on_limit > 5, (on_border, on_limit)


def test_stereo3d_undistorts_the_rational_model_and_the_fisheye_as_opencv_does():
    from wiredsl.measures.stereo3d import undistort

    rng = np.random.default_rng(1706)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-16)
    for _ in range(20):
        cam = rational_camera(rng)
        xy = rng.uniform(-0.4, 0.4, (200, 2))
        xy = xy[np.hypot(*xy.T) < 0.7 * geometry.lens_limit(cam)]
        uv = geometry.cam_to_pixels(np.column_stack([xy, np.ones(len(xy))]), cam)
        ours, ok = undistort(uv, cam)
        dist = np.array([cam.k1, cam.k2, cam.p1, cam.p2, cam.k3, cam.k4, cam.k5, cam.k6])
        theirs = cv2.undistortPoints(uv.reshape(-1, 1, 2), _K(cam), dist, None, None, None, criteria).reshape(-1, 2)
        assert ok.all() and np.abs(ours - xy).max() < 1e-11 and np.abs(ours - theirs).max() < 1e-8
        fish = fisheye_camera(rng)
        theta = rng.uniform(0, math.radians(80), 200)
        phi = rng.uniform(-math.pi, math.pi, 200)
        P = np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
        uv = geometry.cam_to_pixels(P, fish)
        ours, ok = undistort(uv, fish)
        D = np.array([fish.k1, fish.k2, fish.k3, fish.k4])
        theirs = cv2.fisheye.undistortPoints(uv.reshape(-1, 1, 2), _K(fish), D).reshape(-1, 2)
        assert ok.all() and np.abs(ours - P[:, :2] / P[:, 2:]).max() < 1e-9
        assert np.abs(ours - theirs).max() < 1e-6  # OpenCV's fisheye iteration stops earlier
    behind = geometry.cam_to_pixels(np.array([[1.0, 0.0, -0.05]]), fish.model_copy(update={"fov": 3.3}))
    assert undistort(behind, fish.model_copy(update={"fov": 3.3}))[1].tolist() == [False]  # no unit-plane point


@pytest.mark.parametrize("z", [(2.0, 3.0), (-0.5, 1.5), (-2.0, -1.0)])
def test_silhouette_generators_are_tangent_planes_through_the_eye_wherever_the_surface_is(z):
    """A vertical cylinder in front of, across and behind the camera's plane: each side is a generator in a
    plane through the eye with both rims wholly on one side of it (dense samples), the same side for both."""
    from wiredsl.engine import conics

    rng = np.random.default_rng(40)
    checked = 0
    for _ in range(20):
        axis = rng.normal(size=3) * [0.2, 1.0, 0.2]
        axis /= np.linalg.norm(axis)
        U = np.cross(axis, rng.normal(size=3))
        U /= np.linalg.norm(U)
        V = np.cross(axis, U)
        foot = np.array([rng.uniform(1.0, 2.0) * rng.choice([-1, 1]), 0.0, 0.0])
        ca, cb = foot + [0.0, 0.0, z[0]], foot + [0.0, 0.0, z[1]]
        r = rng.uniform(0.1, 0.4)
        arc = np.array([[0.0, 2 * math.pi]])
        one = np.ones(1, bool)
        o, A, B = conics.silhouette_segments_batch(ca[None], r * U[None], r * V[None], cb[None], r * U[None],
                                                   r * V[None], arc, one, arc, one)
        assert len(o) == 2
        s = np.linspace(0, 2 * math.pi, 3601)
        rims = [c + r * (np.cos(s)[:, None] * U + np.sin(s)[:, None] * V) for c in (ca, cb)]
        for a, b in zip(A, B, strict=True):
            n = np.cross(a, b)
            n /= np.linalg.norm(n)
            sides = [np.sign(np.round(rim @ n, 9)) for rim in rims]
            signs = {int(v) for side in sides for v in side if v != 0}
            assert len(signs) == 1, z  # both rims on one side of the plane through the eye
            checked += 1
    assert checked == 40


def test_a_fisheye_rig_calibrated_over_k3_k4_builds_with_trials_on_both_engines(tmp_path):
    """calibration_error over the fisheye's own coefficients: every trial's cameras carry drawn k3, k4, and the
    compiled kernel and the numpy engine write the same dumps."""
    import json
    import os

    from click.testing import CliRunner

    from wiredsl.cli import main

    text = open("scenes/fisheye.wd").read()
    text = text.replace('include "models/', f'include "{os.path.abspath("scenes/models")}/')
    a = text.index("  calibration information")
    b = text.index("]", a) + 1
    text = text[:a] + ("  calibration covariance order [left.k3, left.k4, right.k3] "
                       "matrix [[1e-6, 0, 0], [0, 1e-8, 0], [0, 0, 1e-6]]") + text[b:]
    (tmp_path / "fish.wd").write_text(text)
    dumps = {}
    for engine in ("kernel", "numpy"):
        r = CliRunner().invoke(main, ["build", str(tmp_path / "fish.wd"), "-o", str(tmp_path / engine), "--seed", "5",
                                      "--trials", "4", "--engine", engine, "--format", "jsonl", "--no-svg"])
        assert r.exit_code == 0, r.output
        dumps[engine] = [json.loads(line) for line in (tmp_path / engine / "features.jsonl").read_text().splitlines()]
    k = [(d["poses"][0]["left"]["camera"]["k3"], d["poses"][0]["left"]["camera"]["k4"]) for d in dumps["numpy"]
         if d.get("poses")]
    assert len(set(k)) == 4 and all(k3 != -0.0372 and k4 != 0.0067 for k3, k4 in k)
    strip = [[{key: v for key, v in d.items() if key not in ("tool_version", "engine")} for d in dumps[e]]
             for e in ("kernel", "numpy")]
    assert strip[0] == strip[1]


def test_a_study_varies_a_fisheye_coefficient(tmp_path):
    from pathlib import Path

    from wiredsl.engine.world import build_world
    from wiredsl.language.compile import compile_file
    from wiredsl.study import design, shards

    path = tmp_path / "fish.wd"
    path.write_text(f'wiredsl 1\ninclude "{Path("scenes/fisheye.wd").resolve().as_posix()}"\n'
                    "study lens {\n  pipeline edges\n  vary camera.cam_l.k3 values [-0.0372, 0.01]\n"
                    "  trials 2\n  poses [1]\n  measure kept\n}\n")
    scene = compile_file(path)[0]
    study = scene.study("lens")
    X = design.matrix(study)
    world = build_world(scene)
    runs = [shards.point_run(scene, world, study, p, X[p]) for p in range(len(X))]
    assert [r.scene.camera("cam_l").k3 for r in runs] == [-0.0372, 0.01]
    a, b = (max((f.points for f in r.ideal()[0].left.features), key=len) for r in runs)
    assert a.shape != b.shape or not np.allclose(a, b)


def test_a_study_may_not_vary_a_coefficient_a_fisheye_has_not(tmp_path):
    from pathlib import Path

    from click.testing import CliRunner

    from wiredsl.cli import main

    path = tmp_path / "bad.wd"
    path.write_text(f'wiredsl 1\ninclude "{Path("scenes/fisheye.wd").resolve().as_posix()}"\n'
                    "study s {\n  vary camera.cam_l.p1 values [0, 0.001]\n  measure kept\n}\n")
    r = CliRunner().invoke(main, ["check", str(path)])
    assert r.exit_code == 1
    first = r.stderr.splitlines()[0]
    assert "4:8: error[E104]: camera 'cam_l' has the equidistant lens model, which has no 'p1'" in first


def _w147(lens: str) -> list[str]:
    from helpers import compile_text

    _, warnings = compile_text(f"wiredsl 1\ncamera c {{\n  focal 500px\n  size (640px, 480px)\n{lens}}}\n", "t.wd")
    return [w.message for w in warnings if w.code == "W147"]


def _w147_where(lens: str) -> list[tuple[int, int, str]]:
    """(line, column, the text under the span) of each W147 of a camera with these lens lines."""
    from helpers import compile_text

    text = f"wiredsl 1\ncamera c {{\n  focal 500px\n  size (640px, 480px)\n{lens}}}\n"
    _, warnings = compile_text(text, "t.wd")
    lines = text.splitlines()
    return [(w.span.line, w.span.col, lines[w.span.line - 1][w.span.col - 1:w.span.end_col - 1])
            for w in warnings if w.code == "W147"]


def test_w147_points_at_the_number_that_folds_the_lens():
    """A fisheye whose positive k1 cannot fold it and whose k2 does: the warning is on k2, not on the first
    coefficient written (or the model's name); a radtan k1 that folds is blamed over a harmless k2; of a k1 and a
    huge k3 that squeeze the image, the k3 (its term at the corner dwarfs k1's)."""
    assert _w147_where("  distortion equidistant\n  k1 0.01\n  focal 150px\n  k2 -0.01\n") == [(8, 6, "-0.01")]
    assert _w147_where("  k2 0.001\n  k1 -0.5\n") == [(6, 6, "-0.5")]
    assert _w147_where("  k1 0.1\n  k3 1e6\n") == [(6, 6, "1e6")]
    assert _w147_where("  k1 1e6\n  k2 0.1\n") == [(5, 6, "1e6")]


def test_a_lens_that_does_not_image_its_own_image_is_w147():
    """k1 = -0.5 folds 39.2 deg off axis (d/dr r (1 + k1 r^2) = 0 at r^2 = 2/3, radius r (1 - 1/3)); k1 = 1e6
    squeezes the image into a sliver (the corner's unit-plane radius from cv2.undistortPoints); a fisheye whose
    polynomial stops rising at 100 deg warns unless its fov bounds it; ordinary lenses say nothing."""
    (fold,) = _w147("  k1 -0.5\n")
    r = math.sqrt(2 / 3)
    assert f"folds back {math.degrees(math.atan(r)):.3g} deg" in fold and f"{500 * r * 2 / 3:.4g} px" in fold
    (sliver,) = _w147("  k1 1e6\n")
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    xy = cv2.undistortPoints(np.array([[[640.0, 480.0]]]), K, np.array([1e6, 0, 0, 0]),
                             criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 500, 1e-15)).reshape(2)
    assert f"spans {math.degrees(2 * math.atan(np.hypot(*xy))):.3g} deg" in sliver
    assert f"gives {math.degrees(2 * math.atan(0.8)):.3g} deg" in sliver
    k1 = -1 / (3 * math.radians(100) ** 2)  # d theta_d / d theta = 1 + 3 k1 theta^2 = 0 at 100 deg
    (fisheye,) = _w147(f"  distortion equidistant\n  k1 {k1!r}\n  focal 150px\n")
    assert "folds back 100 deg" in fisheye
    assert _w147(f"  distortion equidistant\n  k1 {k1!r}\n  focal 150px\n  fov 190deg\n") == []
    assert _w147("  k1 -0.2\n  k2 0.05\n") == [] and _w147("  distortion equidistant\n  k1 0.01\n") == []
