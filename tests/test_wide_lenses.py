"""The wide-angle lens models (unified / Mei, extended unified, double sphere, FOV) against independent references:
each model's published formulas evaluated in mpmath (written here from the papers, not from wiredsl's code), and
OpenCV's own Mei model (cv2.omnidir, stored by tests/data/lenses/make_omnidir_reference.py); on both engines (numpy's
geometry.project and the numba kernel's _project); their valid regions, unprojections, and whole views and builds."""

from __future__ import annotations

import json
import math
from pathlib import Path

import mpmath
import numpy as np
import pytest
from test_lenses import _curve, _dist_to_polyline, _fisheye_view

from wiredsl.engine import geometry, kernel
from wiredsl.engine.simulate import project_view
from wiredsl.scene import Camera

mpmath.mp.dps = 40
N_CAMERAS = 320
MODELS = ("unified", "eucm", "ds", "fov")


def random_camera(rng: np.random.Generator, model: str) -> Camera:
    lens = {"unified": lambda: {"xi": float(rng.choice([rng.uniform(0, 1), rng.uniform(1, 3)])),
                                "k1": rng.uniform(-0.3, 0.3), "k2": rng.uniform(-0.05, 0.05),
                                "p1": rng.uniform(-0.01, 0.01), "p2": rng.uniform(-0.01, 0.01)},
            "eucm": lambda: {"alpha": rng.uniform(0, 1), "beta": rng.uniform(0.3, 3.0)},
            "ds": lambda: {"xi": rng.uniform(-0.6, 1.0), "alpha": rng.uniform(0, 1)},
            "fov": lambda: {"w": rng.uniform(0.05, 3.0)}}[model]()
    return Camera(name="c", f=rng.uniform(150, 900), ax=rng.uniform(0.9, 1.1), ay=rng.uniform(0.9, 1.1),
                  cx=rng.uniform(400, 900), cy=rng.uniform(300, 700), width=1280, height=1024, distortion=model,
                  **lens)


# ------------------------------------------------------------------ the papers' formulas, in mpmath

def mp_pixel(P, cam: Camera) -> tuple[mpmath.mpf, mpmath.mpf]:
    x, y, z = (mpmath.mpf(v) for v in P)
    if cam.distortion == "unified":  # Mei and Rives 2007: onto the unit sphere, then from (0, 0, -xi), then radtan
        n = mpmath.sqrt(x * x + y * y + z * z)
        xs, ys, zs = x / n, y / n, z / n
        mx, my = xs / (zs + cam.xi), ys / (zs + cam.xi)
        r2 = mx * mx + my * my
        radial = 1 + cam.k1 * r2 + cam.k2 * r2 * r2
        xd = mx * radial + 2 * cam.p1 * mx * my + cam.p2 * (r2 + 2 * mx * mx)
        yd = my * radial + cam.p1 * (r2 + 2 * my * my) + 2 * cam.p2 * mx * my
    elif cam.distortion == "eucm":  # Khomenko et al. 2016, eq. (2)-(3)
        a, b = mpmath.mpf(cam.alpha), mpmath.mpf(cam.beta)
        d = mpmath.sqrt(b * (x * x + y * y) + z * z)
        xd, yd = x / (a * d + (1 - a) * z), y / (a * d + (1 - a) * z)
    elif cam.distortion == "ds":  # Usenko et al. 2018, eq. (40)-(42)
        a, xi = mpmath.mpf(cam.alpha), mpmath.mpf(cam.xi)
        d1 = mpmath.sqrt(x * x + y * y + z * z)
        d2 = mpmath.sqrt(x * x + y * y + (xi * d1 + z) ** 2)
        den = a * d2 + (1 - a) * (xi * d1 + z)
        xd, yd = x / den, y / den
    else:  # Devernay and Faugeras 2001, eq. (13): r_d = atan(2 r_u tan(w / 2)) / w on the pinhole point
        w = mpmath.mpf(cam.w)
        xu, yu = x / z, y / z
        ru = mpmath.sqrt(xu * xu + yu * yu)
        if ru == 0:
            xd, yd = xu * 2 * mpmath.tan(w / 2) / w, yu * 2 * mpmath.tan(w / 2) / w
        else:
            rd = mpmath.atan(2 * ru * mpmath.tan(w / 2)) / w
            xd, yd = xu * rd / ru, yu * rd / ru
    return cam.f * cam.ax * xd + cam.cx, cam.f * cam.ay * yd + cam.cy


def mp_limit(cam: Camera) -> float:
    """The valid region's angle from the axis, from the DS paper's table (sec. 3): UCM z > -w d, EUCM z > -w rho,
    DS z > -w2 d1, FOV z > 0; solved on the unit sphere in mpmath by bisection on the angle."""
    if cam.distortion == "fov":
        return math.pi / 2

    def inside(t):
        x, z = mpmath.sin(t), mpmath.cos(t)
        if cam.distortion == "unified":
            w = min(cam.xi, 1 / cam.xi) if cam.xi > 0 else 0
            return z > -w
        a = mpmath.mpf(cam.alpha)
        w1 = a / (1 - a) if a <= 0.5 else (1 - a) / a
        if cam.distortion == "eucm":
            return z > -w1 * mpmath.sqrt(cam.beta * x * x + z * z)
        xi = mpmath.mpf(cam.xi)
        zs = xi + z  # and (a negative xi) where the projection's denominator is positive
        return z > -(w1 + xi) / mpmath.sqrt(2 * w1 * xi + xi * xi + 1) and a * mpmath.sqrt(x * x + zs * zs) \
            + (1 - a) * zs > 0

    if inside(mpmath.pi):
        return math.pi
    lo, hi = mpmath.mpf(0), mpmath.pi
    for _ in range(120):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if inside(mid) else (lo, mid)
    if cam.distortion == "ds":  # and where the radius stops increasing, if first (a negative xi): mpmath.diff
        def slope(t):
            return mpmath.diff(lambda a: mp_pixel((mpmath.sin(a), 0, mpmath.cos(a)), cam)[0], t)

        grid = [lo * k / 64 for k in range(1, 65)]
        stop = next((k for k, t in enumerate(grid) if not slope(t) > 0), None)
        if stop is not None:
            a, b = (grid[stop - 1] if stop else mpmath.mpf(0)), grid[stop]
            for _ in range(60):
                mid = (a + b) / 2
                a, b = (mid, b) if slope(mid) > 0 else (a, mid)
            return float(a)
    return float(lo)


def sample_points(rng: np.random.Generator, limit: float, n: int) -> np.ndarray:
    """Camera points at every angle up to the limit: a third of them within 1e-2 .. 1e-9 (relative) of it."""
    frac = np.concatenate([rng.uniform(0, 1, n - n // 3) ** 0.5, 1 - 10.0 ** -rng.uniform(2, 9, n // 3)])
    theta = limit * frac
    phi = rng.uniform(-math.pi, math.pi, n)
    d = rng.uniform(0.01, 50.0, n)
    return d[:, None] * np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])


def kernel_pixels(P: np.ndarray, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    table = geometry.camera_table(cam)
    row = np.array([table[k] for k in geometry.CAMERA_ROW], dtype=float)
    out, ok = np.empty((len(P), 2)), np.empty(len(P), dtype=bool)
    kernel._project(np.ascontiguousarray(P), np.eye(3), np.zeros(3), row, table["limit"], out, ok)
    return out, ok


@pytest.mark.parametrize("model", MODELS)
def test_each_model_matches_its_papers_formulas_on_both_engines_to_1e_9_px(model):
    """320 random cameras, 30 points each up to the valid region's edge. The error allowed is 1e-9 px where the
    pixel is within 20 image widths of the centre (the unified model with xi < 1 and EUCM with alpha < 1/2 send their
    edge to infinity, where a double's own rounding of the point exceeds 1e-9 px; there the relative error is below
    2e-7: what one ulp of the point's coordinates moves the pixel by, amplified by Mei's radtan near its fold; see
    the next test)."""
    rng = np.random.default_rng(2600 + MODELS.index(model))
    worst, near_edge, n = 0.0, 0, 0
    for _ in range(N_CAMERAS):
        cam = random_camera(rng, model)
        limit = geometry.lens_limit(cam)
        assert limit == pytest.approx(mp_limit(cam), rel=1e-12, abs=1e-12) or model == "unified"
        P = sample_points(rng, limit, 30)
        ours = geometry.cam_to_pixels(P, cam)
        kern, ok = kernel_pixels(P, cam)
        assert ok.all() and geometry.visible(P, geometry.MODELS.index(model), limit).all()
        ref = np.array([[float(v) for v in mp_pixel(p, cam)] for p in P])
        far = np.hypot(ref[:, 0] - cam.cx, ref[:, 1] - cam.cy) > 20 * cam.width
        for got in (ours, kern):
            err = np.abs(got - ref).max(axis=1)
            assert (err[~far] < 1e-9).all(), (model, cam, err[~far].max())
            # out there (1e10 px and more near such an edge) the cancellation in z + xi d costs relative digits
            assert (err[far] < 2e-7 * np.abs(ref[far]).max(axis=1)).all()
            worst = max(worst, float(err[~far].max(initial=0)))
        theta = np.arctan2(np.hypot(P[:, 0], P[:, 1]), P[:, 2])
        near_edge += int(((theta > limit * (1 - 1e-6)) & ~far).sum())
        n += int((~far).sum())
    assert n > 7000 and near_edge > 300, (n, near_edge, worst)


@pytest.mark.parametrize("model", ["unified", "eucm", "ds"])
def test_near_the_edge_the_error_is_what_one_ulp_of_the_point_makes(model):
    """Where a model sends its edge to infinity its denominator (xi d + z, alpha rho + (1 - alpha) z) cancels. Summed
    as (p^2 - q^2) / (p - q) (geometry.stable_sum) the rounding is not amplified: the error stays within a few times
    how far the reference pixel moves when one coordinate of the point moves by one ulp (the point's own precision).
    (Summed plainly, over 120 cameras a model, it was 20x (eucm), 50x (ds) and 2000x (unified with radtan) that.)
    Mei's radtan is left out of the unified cameras here: its polynomial near the fold amplifies rounding by itself
    (up to 205x, measured)."""
    rng = np.random.default_rng(2700 + MODELS.index(model))
    ratios = []
    for _ in range(40):
        cam = random_camera(rng, model)
        if model == "unified":
            cam = cam.model_copy(update={"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0})
        P = sample_points(rng, geometry.lens_limit(cam), 30)
        ref = np.array([[float(v) for v in mp_pixel(p, cam)] for p in P])
        far = np.flatnonzero(np.hypot(ref[:, 0] - cam.cx, ref[:, 1] - cam.cy) > 20 * cam.width)
        for got in (geometry.cam_to_pixels(P[far], cam), kernel_pixels(P[far], cam)[0]):
            for g, i in zip(got, far, strict=True):
                ulp_moves = (P[i] + np.eye(3)[j] * (np.nextafter(P[i][j], np.inf) - P[i][j]) for j in range(3))
                moved = max(np.hypot(*(np.array([float(v) for v in mp_pixel(q, cam)]) - ref[i])) for q in ulp_moves)
                ratios.append(np.hypot(*(g - ref[i])) / moved)
    bound = {"unified": 4, "eucm": 2.5, "ds": 8}[model]  # measured 1.7, 1.1, 6.4 (summed plainly: 54, 4.5, 7.0)
    assert len(ratios) > 100 and max(ratios) < bound, (len(ratios), max(ratios))


def test_the_unified_model_matches_opencv_omnidir_to_1e_9_px():
    """OpenCV's Mei model (opencv-contrib's cv2.omnidir.projectPoints), stored for 320 random cameras: the points
    wiredsl images (inside the valid region and the radtan fold) with pixels within 20 image widths."""
    ref = np.load(Path(__file__).parent / "data" / "lenses" / "omnidir_reference.npz")
    assert len(ref["cameras"]) >= 300
    worst, n = 0.0, 0
    for (xi, fx, fy, cx, cy, k1, k2, p1, p2), P, uv in zip(ref["cameras"], ref["points"], ref["pixels"], strict=True):
        cam = Camera(name="c", f=fx, ay=fy / fx, cx=cx, cy=cy, width=1000, height=800, distortion="unified", xi=xi,
                     k1=k1, k2=k2, p1=p1, p2=p2)
        keep = geometry.visible(P, geometry.UNIFIED, geometry.lens_limit(cam)) \
            & (np.hypot(uv[:, 0] - cx, uv[:, 1] - cy) < 20 * 1000)
        P, uv = P[keep], uv[keep]
        for got in (geometry.cam_to_pixels(P, cam), kernel_pixels(P, cam)[0]):
            worst = max(worst, float(np.abs(got - uv).max(initial=0)))
        n += len(P)
    assert worst < 1e-9 and n > 2000, (worst, n)


@pytest.mark.parametrize("model", MODELS)
def test_unprojection_inverts_the_reference_projection(model):
    """geometry.pixels_to_rays of the mpmath pixels gives the points' own directions (to 1e-9 rad) wherever the
    model's image is one-to-one, up to 1e-6 of the valid region's edge. (Mei's tangential terms bend the radtan fold
    off the circle `fold_radius` gives, as for a radtan camera, so there they are tested to 0.9 of the limit.)"""
    rng = np.random.default_rng(7 + len(model))
    worst = 0.0
    for i in range(200):
        cam = random_camera(rng, model)
        if model == "unified" and i % 2:
            cam = cam.model_copy(update={"p1": 0.0, "p2": 0.0})
        limit = geometry.lens_limit(cam)
        P = sample_points(rng, limit * (1 - 1e-6 if cam.p1 == cam.p2 == 0 else 0.9), 20)
        uv = np.array([[float(v) for v in mp_pixel(p, cam)] for p in P])
        keep = np.hypot(uv[:, 0] - cam.cx, uv[:, 1] - cam.cy) < 20 * cam.width
        rays, ok = geometry.pixels_to_rays(uv[keep], cam)
        assert ok.all(), (cam, uv[keep][~ok])
        truth = P[keep] / np.linalg.norm(P[keep], axis=1, keepdims=True)
        angle = np.arccos(np.clip((rays * truth).sum(axis=1), -1, 1))
        worst = max(worst, float(angle.max(initial=0)))
    assert worst < 1e-7, worst  # arccos of a dot product: 1e-8 rad is its own floor near 0


@pytest.mark.parametrize("model", MODELS)
def test_the_image_is_one_to_one_up_to_the_limit_and_refused_past_it(model):
    """The radius on the unit plane increases with the angle all the way to the limit (dense samples); a pixel
    beyond the image of the limit has no ray; a point past the limit is not visible."""
    rng = np.random.default_rng(11)
    for _ in range(200):
        cam = random_camera(rng, model).model_copy(update={"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0})
        limit = geometry.lens_limit(cam)
        t = np.linspace(0, limit, 20001)[:-1]
        r = geometry.lens_radius(t, cam)
        assert (np.diff(r) > 0).all(), cam
        P = np.array([[math.sin(limit * (1 + 1e-6)), 0, math.cos(limit * (1 + 1e-6))]])
        assert not geometry.visible(P, geometry.MODELS.index(model), limit).any() or limit >= math.pi
        edge = float(geometry.lens_radius(limit, cam))
        if 0 < edge < 1e6:  # the models whose edge is at infinity have no pixel beyond it
            beyond = np.array([[cam.cx + cam.f * cam.ax * edge * 1.001, cam.cy]])
            assert not geometry.pixels_to_rays(beyond, cam)[1].any(), cam


def test_mei_radtan_folds_the_limit_where_its_radius_stops_increasing():
    cam = Camera(name="c", f=300, cx=640, cy=512, width=1280, height=1024, distortion="unified", xi=0.9, k1=-0.4)
    limit = geometry.lens_limit(cam)
    r_fold = geometry.fold_radius(-0.4)
    assert geometry.lens_radius(limit, cam) == pytest.approx(r_fold, rel=1e-12)
    assert limit < math.acos(-0.9)


# ------------------------------------------------------------------ whole views, the language and builds

@pytest.mark.parametrize("lens", [{"distortion": "unified", "xi": 1.6, "k1": -0.1, "k2": 0.01},
                                  {"distortion": "unified", "xi": 0.8},
                                  {"distortion": "eucm", "alpha": 0.6, "beta": 1.2},
                                  {"distortion": "ds", "xi": -0.2, "alpha": 0.6},
                                  {"distortion": "fov", "w": 0.9}])
def test_lines_become_curves_and_ellipses_stay_on_the_true_curve(lens):
    """Every visible point (4,001 a feature) of lines and ellipses around the camera, past 90 deg where the model
    sees there, lies within tol of the feature's polylines; some are behind the camera's plane."""
    rng, tol = np.random.default_rng(41), 0.05
    worst, behind, seen = 0.0, 0, 0
    for _ in range(3):
        _, w = _fisheye_view(rng)
        cam = Camera(name="c", f=250, cx=640, cy=512, width=1280, height=1024, **lens)
        lim = geometry.lens_limit(cam)
        view = project_view(w, cam, np.eye(3), np.zeros(3), np.ones(w.n_features, bool), tol)
        for fid in range(w.n_features):
            P = _curve(w, fid, np.linspace(0.0, 1.0, 4001))
            P = P[geometry.visible(P, 2, lim * (1 - 1e-6))]
            truth = geometry.cam_to_pixels(P, cam)
            inside = (truth[:, 0] >= 0) & (truth[:, 0] <= 1280) & (truth[:, 1] >= 0) & (truth[:, 1] <= 1024)
            if not inside.any():
                continue
            polys = [f.points for f in view.features if f.fid == fid and f.kind == "polyline"]
            assert polys, f"feature {fid} is in the image but has no polyline"
            worst = max(worst, float(np.min([_dist_to_polyline(truth[inside], p) for p in polys], axis=0).max()))
            behind += int((P[inside, 2] < 0).sum())
            seen += int(inside.sum())
    assert tol / 10 < worst <= tol and seen > 20_000, (worst, seen)
    assert behind > 100 or lim <= math.pi / 2


def _scene(tmp_path: Path, lens: str, calibration: str | None = None) -> Path:
    text = Path("scenes/fisheye.wd").read_text()
    text = text.replace('include "models/', f'include "{Path("scenes/models").resolve()}/')
    a = text.index("  distortion equidistant")
    b = text.index("  fov 190deg")
    text = text[:a] + lens + text[b:]
    text = text.replace("  k1 -0.0052\n", "")
    if calibration is not None:
        a = text.index("  calibration information")
        text = text[:a] + calibration + text[text.index("]", a) + 1:]
    (tmp_path / "s.wd").write_text(text)
    return tmp_path / "s.wd"


@pytest.mark.parametrize("lens,order", [
    ("  distortion ds\n  xi -0.2\n  alpha 0.57\n", "[left.xi, left.alpha, right.alpha]"),
    ("  distortion unified\n  xi 1.1\n  k1 -0.05\n", "[left.xi, left.k, right.xi]"),
    ("  distortion eucm\n  alpha 0.6\n  beta 1.1\n", "[left.alpha, left.beta, right.beta]"),
    ("  distortion fov\n  w 52deg\n", "[left.w, left.f, right.w]")])
def test_a_wide_angle_rig_calibrated_over_its_own_numbers_builds_alike_on_both_engines(tmp_path, lens, order):
    """calibration_error draws the model's own numbers; the kernel and numpy engines write the same dumps."""
    from click.testing import CliRunner

    from wiredsl.cli import main

    path = _scene(tmp_path, lens, f"  calibration covariance order {order} "
                                  "matrix [[1e-6, 0, 0], [0, 1e-6, 0], [0, 0, 1e-6]]")
    dumps = {}
    for engine in ("kernel", "numpy"):
        r = CliRunner().invoke(main, ["build", str(path), "-o", str(tmp_path / engine), "--seed", "5", "--trials",
                                      "3", "--engine", engine, "--format", "jsonl", "--no-svg"])
        assert r.exit_code == 0, r.output
        dumps[engine] = [json.loads(line) for line in (tmp_path / engine / "features.jsonl").read_text().splitlines()]
    strip = [[{k: v for k, v in d.items() if k not in ("tool_version", "engine")} for d in dumps[e]]
             for e in ("kernel", "numpy")]
    assert strip[0] == strip[1]
    key = order[1:-1].split(", ")[0].split(".")[1]
    drawn = {d["poses"][0]["left"]["camera"][key] for d in dumps["numpy"] if d.get("poses")}
    assert len(drawn) == 3
    strokes = sum(len(p[s]["polylines"]) + len(p[s]["corners"]) for d in dumps["numpy"] for p in d.get("poses", [])
                  for s in ("left", "right"))
    assert strokes > 500, strokes


@pytest.mark.parametrize("model", MODELS)
def test_the_stereo_measures_undistort_by_the_models_own_unprojection(model):
    """stereo3d.undistort of the mpmath pixels of points in front gives their x / z, y / z."""
    from wiredsl.measures.stereo3d import undistort

    rng = np.random.default_rng(60 + MODELS.index(model))
    for _ in range(50):
        cam = random_camera(rng, model).model_copy(update={"p1": 0.0, "p2": 0.0})
        P = sample_points(rng, min(geometry.lens_limit(cam), math.radians(85)) * 0.999, 20)
        uv = np.array([[float(v) for v in mp_pixel(p, cam)] for p in P])
        xy, ok = undistort(uv, cam)
        assert ok.all() and np.abs(xy - P[:, :2] / P[:, 2:]).max() < 1e-6, cam


@pytest.mark.parametrize("lens,message", [
    ("  distortion ds\n  xi 1.5\n  alpha 0.5\n", "define no ds lens"),
    ("  distortion eucm\n  alpha 1.2\n", "define no eucm lens"),
    ("  distortion fov\n  w 200deg\n", "define no fov lens"),
    ("  distortion ds\n  xi 0.1\n  k2 0.1\n", "'k2' does not belong to the ds lens model"),
    ("  distortion radtan\n  xi 0.1\n", "'xi' does not belong to the radtan lens model")])
def test_numbers_that_define_no_lens_are_refused_with_their_span(tmp_path, lens, message):
    from click.testing import CliRunner

    from wiredsl.cli import main

    r = CliRunner().invoke(main, ["check", str(_scene(tmp_path, lens))])
    assert r.exit_code == 1 and message in r.output and "s.wd:" in r.output, r.output


# ------------------------------------------------------------------ every model's region, enforced alike

def scan_radius(theta: np.ndarray, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """The image radius on the unit plane of the point (sin theta, 0, cos theta) by each paper's formula (written
    here, not wiredsl's), and its denominator (a point whose denominator is not positive is not imaged)."""
    s, c = np.sin(theta), np.cos(theta)
    one = np.ones_like(theta)
    with np.errstate(all="ignore"):
        if cam.distortion == "radtan":  # OpenCV's rational model on the pinhole radius
            r = s / c
            q = r * r
            den = (1 + cam.k4 * q + cam.k5 * q * q + cam.k6 * q**3) * np.sign(c)
            return r * (1 + cam.k1 * q + cam.k2 * q * q + cam.k3 * q**3) / den, den
        if cam.distortion == "equidistant":  # Kannala-Brandt's theta_d
            q = theta * theta
            return theta * (1 + q * (cam.k1 + q * (cam.k2 + q * (cam.k3 + q * cam.k4)))), one
        if cam.distortion == "unified":  # Mei: (X, Y) / (Z + xi d), then radtan k1, k2 on m
            den = c + cam.xi
            m = s / den
            return m * (1 + cam.k1 * m * m + cam.k2 * m**4), den
        if cam.distortion == "eucm":
            den = cam.alpha * np.sqrt(cam.beta * s * s + c * c) + (1 - cam.alpha) * c
            return s / den, den
        if cam.distortion == "ds":
            zs = cam.xi + c
            den = cam.alpha * np.sqrt(s * s + zs * zs) + (1 - cam.alpha) * zs
            return s / den, den
        return np.arctan(2 * (s / c) * math.tan(cam.w / 2)) / cam.w, c  # fov (ATAN): in front only


REGION_CAMERAS = [
    {"distortion": "radtan", "k1": -0.3}, {"distortion": "radtan", "k1": -0.1, "k2": 0.02, "k3": 0.001, "k4": -0.3,
                                           "k5": 0.05, "k6": 0.01},
    {"distortion": "radtan", "k6": -1000.0}, {"distortion": "radtan", "k4": -2.0}, {"distortion": "radtan"},
    {"distortion": "equidistant", "k1": -0.05, "k2": 0.004}, {"distortion": "equidistant", "k1": 0.02, "k2": -0.01},
    {"distortion": "equidistant"}, {"distortion": "unified", "xi": 0.8}, {"distortion": "unified", "xi": 1.6},
    {"distortion": "unified", "xi": 0.9, "k1": -0.4}, {"distortion": "unified", "xi": 2.5, "k1": 0.1, "k2": -0.05},
    {"distortion": "eucm", "alpha": 0.3, "beta": 1.2}, {"distortion": "eucm", "alpha": 0.7, "beta": 2.0},
    {"distortion": "eucm", "alpha": 0.6, "beta": 100.0}, {"distortion": "eucm", "alpha": 0.5, "beta": 1.0},
    {"distortion": "ds", "xi": -0.2, "alpha": 0.6}, {"distortion": "ds", "xi": 0.5, "alpha": 0.3},
    {"distortion": "ds", "xi": -0.6, "alpha": 0.9}, {"distortion": "ds", "xi": 0.9, "alpha": 0.55},
    {"distortion": "fov", "w": 0.9}, {"distortion": "fov", "w": 3.0}]


@pytest.mark.parametrize("lens", REGION_CAMERAS, ids=lambda d: "-".join(f"{v}" for v in d.values()))
def test_each_models_region_is_where_its_radius_increases_and_both_engines_stop_there(lens):
    """The region a model images is where its own radius function (the paper's formula, `scan_radius`) still
    increases with the angle and its denominator is positive, found by a dense scan (2e6 steps over 180 deg, not
    wiredsl's root finders), and for the double sphere within the paper's published region, which ends first for
    these three (122.1 deg against the scan's 123.2, 135.8 against 142.2, 161.5 against 176.1); geometry.lens_limit
    is that angle to the scan's step. Points 1e-6 inside it are
    projected, and 1e-6 outside not, by numpy (`visible`, `project`) and the kernel (`_project`) alike."""
    cam = Camera(name="c", f=300.0, cx=640.0, cy=512.0, width=1280, height=1024, **lens)
    theta = np.linspace(0.0, math.pi, 2_000_001)
    r, den = scan_radius(theta, cam)
    good = np.isfinite(r) & (den > 0)
    good[1:] &= np.diff(r) > 0
    good[0] = True
    stop = int(np.argmin(good)) if not good.all() else len(theta)
    oracle = theta[stop - 1] if stop < len(theta) else math.pi
    if cam.distortion == "ds":  # the paper's region z > -w2 d (its eq. 43-45) is narrower than the scan's here
        w1 = cam.alpha / (1 - cam.alpha) if cam.alpha <= 0.5 else (1 - cam.alpha) / cam.alpha
        oracle = min(oracle, math.acos(-(w1 + cam.xi) / math.sqrt(2 * w1 * cam.xi + cam.xi**2 + 1)))
    limit = geometry.lens_limit(cam)
    angle = math.atan(limit) if cam.distortion == "radtan" else limit
    assert abs(angle - oracle) <= 2 * (theta[1] - theta[0]), (angle, oracle)
    model = geometry.MODELS.index(cam.distortion)
    rng = np.random.default_rng(3)
    phi = rng.uniform(-math.pi, math.pi, 16)
    for side, scale in (("inside", 1 - 1e-6), ("outside", 1 + 1e-6)):
        if cam.distortion == "radtan":  # the region bounds the unit-plane radius
            if not math.isfinite(limit):
                continue
            rad = limit * scale
            P = np.column_stack([rad * np.cos(phi), rad * np.sin(phi), np.ones(16)]) * rng.uniform(0.5, 20, (16, 1))
        else:
            t = min(limit * scale, math.pi)
            if side == "outside" and t >= math.pi:
                continue
            P = np.column_stack([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), np.full(16, math.cos(t))])
            P *= rng.uniform(0.5, 20, (16, 1))
        seen = geometry.visible(P, model, limit)
        uv, ok = kernel_pixels(P, cam)
        assert (seen == ok).all() and (seen == (side == "inside")).all(), (side, seen, ok)
        if side == "inside":
            ref = geometry.project(P, geometry.camera_table(cam))
            assert np.isfinite(ref).all()
            assert np.allclose(uv, ref, rtol=1e-9, atol=1e-6)
