"""`wiredsl verify`: detectors and verification against drawn edges at known offsets, bad input, a plug-in
detector, the fit on samples of known laws, and the command's outputs (table, Figure 7, a pipeline that
compiles and builds)."""

from __future__ import annotations

import json
import math
import re
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from helpers import make_dist, plugins_on_path
from verify_drawing import draw, render_records

import wiredsl
from wiredsl.cli import main
from wiredsl.scene import Pipeline
from wiredsl.verify import detectors as D
from wiredsl.verify import fit as F
from wiredsl.verify import images as I
from wiredsl.verify import verification as V
from wiredsl.verify.measured import pipeline_text

FENCE = Path("tests/data/verify/fence.wd")
H, W = 480, 640


class _View:
    """The part of an engine View the verification reads: its features."""

    def __init__(self, features):
        self.features = features


class _Feat:
    def __init__(self, fid, points, kind="line"):
        self.fid, self.kind, self.points, self.segment, self.fragment = fid, kind, np.asarray(points, float), -1, -1


def _square(offset: float, blur: float = 1.0, noise: float = 1.0):
    """A dark square drawn with its four sides moved outwards by `offset` px, and the model's unmoved sides."""
    x0, y0, x1, y1 = 150.0, 120.0, 450.0, 360.0
    model = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    img = draw([], [], blur=blur, noise=noise)
    from verify_drawing import _ccw, _polygon

    cover = np.zeros((H, W))
    _polygon(cover, _ccw(np.array([(x0 - offset, y0 - offset), (x1 + offset, y0 - offset),
                                   (x1 + offset, y1 + offset), (x0 - offset, y1 + offset)])))
    img = np.clip(np.rint(cv2.GaussianBlur((190 - 120 * cover).astype(np.float32), (0, 0), blur)
                          + np.random.default_rng(3).normal(0, noise, (H, W))), 0, 255).astype(np.uint8)
    feats = [_Feat(i, [model[i], model[(i + 1) % 4]]) for i in range(4)]
    return img, _View(feats)


@pytest.mark.parametrize("offset", [0.0, 0.25, 0.5, 0.8, 1.7])
@pytest.mark.parametrize("name,tol", [("canny", 0.06), ("lsd", 0.25)])
def test_edges_drawn_at_a_known_offset_are_verified_with_that_offset(offset, name, tol):
    img, view = _square(offset)
    det = D.BUILTIN[name]
    found = D.checked(det.detect(img, det.Params()), img.shape, name)
    r = V.verify_image(view, found, img.shape, V.Settings(),
                       V.ImageResult("x", "left", "0", name, ["a", "b", "c", "d"]))
    s = r.stats
    assert (s.verified / s.tested > 0.95).all()
    # the sides run clockwise in the image (y down), so the outward normal is -n: the offset is -offset
    assert np.allclose(s.offset_mean, -offset, atol=tol), s.offset_mean
    assert (s.runs == 1).all()


def test_a_missing_edge_and_a_wrong_direction_are_not_verified():
    img, view = _square(0.0)
    found = D.Canny.detect(img, D.CannyParams())
    cross = _View([_Feat(0, [(300, 100), (300, 140)])])  # crosses the top side at right angles
    r = V.verify_image(cross, found, img.shape, V.Settings(), V.ImageResult("x", "left", "0", "canny", ["a"]))
    assert r.stats.verified[0] <= 2  # only where it meets the side's own bend, at most
    far = _View([_Feat(0, [(200, 240), (400, 240)])])  # nothing drawn there
    r = V.verify_image(far, found, img.shape, V.Settings(), V.ImageResult("x", "left", "0", "canny", ["a"]))
    assert r.stats.verified[0] == 0 and r.stats.tested[0] > 90


def test_corners_are_found_within_the_radius_with_their_error():
    img = draw([], [np.array([100.0, 100.0]), np.array([300.2, 200.7])], blur=1.0, noise=1.0)
    found = D.Harris.detect(img, D.CornerParams())
    fid = np.array([0, 1, 2])
    uv = np.array([[100.0, 100.0], [303.2, 200.7], [500.0, 400.0]])
    m = V.match_corners(fid, uv, found.corners, 10.0)
    assert m.found.tolist() == [True, True, False]
    assert m.error[0] < 0.3 and abs(m.error[1] - 3.0) < 0.3


def test_sampling_covers_each_stroke_evenly():
    st = V.Strokes(np.array([[0, 0], [10, 0], [10, 10], [5, 5], [5, 5.5]], float), np.array([0, 3, 5]),
                   np.array([0, 1]), np.array([-1, -1]), np.array([-1, -1]))
    sm = V.sample_strokes(st, 2.0)
    assert np.bincount(sm.stroke).tolist() == [10, 1]
    assert np.allclose(sm.L, [20.0, 0.5])
    assert ((sm.s >= 0) & (sm.s <= sm.L[sm.stroke])).all()
    first = sm.stroke == 0
    assert np.allclose(np.diff(sm.s[first]), 2.0)
    assert np.allclose(sm.N[first][:5], [0, 1]) and np.allclose(sm.N[first][5:], [-1, 0])


# --------------------------------------------------------------------------- the fit on known laws

def _sums_with_shifts(d: np.ndarray, per_image: int = 20) -> list[F.ImageSums]:
    out = []
    for k in range(0, len(d), per_image):
        x = d[k:k + per_image]
        out.append(F.ImageSums(strokes=len(x), d1=float(x.sum()), d2=float((x * x).sum()), offsets=x.tolist()))
    return out


def test_the_fit_recovers_a_uniform_range_and_tells_uniform_from_normal():
    rng = np.random.default_rng(5)
    hits = 0
    for k in range(40):
        R = rng.uniform(0.5, 4)
        f = F.fit(_sums_with_shifts(rng.uniform(-R, R, 400)), seed=k)
        e = f.get("lateral_shift.range")
        hits += e.lo <= R <= e.hi
        assert f.shift_law["better"] == "uniform" or k % 10  # most often: checked on a count below
    assert hits >= 34  # 95% intervals: 38 expected of 40
    laws = [F.law_test(rng.normal(0, 1.5, 800))["better"] for _ in range(20)]
    assert laws.count("normal") >= 18
    laws = [F.law_test(rng.uniform(-2, 2, 800))["better"] for _ in range(20)]
    assert laws.count("uniform") >= 18


def test_the_fit_recovers_corner_keep_and_mismatch_from_known_draws():
    rng = np.random.default_rng(9)
    keep, frac, R, t = 0.8, 0.2, 8.0, 2.0
    sums = []
    for _ in range(40):
        n = 30
        found = rng.random(n) < keep
        moved = found & (rng.random(n) < frac)
        r = R * np.sqrt(rng.random(n))
        far = moved & (r > t)
        sums.append(F.ImageSums(corners=n, found=float(found.sum()), displaced=float(far.sum()),
                                displaced_r=float(r[far].sum())))
    f = F.fit(sums, seed=1, inlier=t)
    for key, true in (("corner_loss.keep", keep), ("corner_mismatch.fraction", frac), ("corner_mismatch.radius", R)):
        e = f.get(key)
        assert e.lo <= true <= e.hi, (key, e)


def test_the_fit_recovers_corner_localisation_and_mismatch_together_from_known_draws():
    """Every found corner placed by N(0, sigma^2) per axis, a fifth also mismatched over a disc of 8 px: sigma
    from the ones within the inlier distance less the mismatches landing there, the mismatch fraction and radius
    from the ones beyond it less the normal's tail. Over 40 settings the estimates are unbiased (means within
    2% or 0.01) and their 95% intervals cover the truth in 80% or more (measured over 120: sigma 96%, fraction
    92%, radius 89%, the radius's percentile interval running short as it did before sigma was fitted). Without
    the located corners, as before corner_error was fitted, the normal's tail counts as mismatches."""
    keep, frac, R, t = 0.8, 0.2, 8.0, 2.0
    keys = ("corner_error.sigma", "corner_mismatch.fraction", "corner_mismatch.radius")
    hits, values, truths, naive = dict.fromkeys(keys, 0), {k: [] for k in keys}, [], []
    for seed in range(40):
        rng = np.random.default_rng([11, seed])
        sigma = rng.uniform(0.3, 1.0)
        sums = []
        for _ in range(40):
            n = 30
            found = rng.random(n) < keep
            pos = rng.normal(0, sigma, (n, 2))
            moved = rng.random(n) < frac
            r = R * np.sqrt(rng.random(n))
            phi = 2 * np.pi * rng.random(n)
            pos[moved] += np.column_stack([r * np.cos(phi), r * np.sin(phi)])[moved]
            d = np.hypot(*pos.T)
            far, near = found & (d > t), found & (d <= t)
            sums.append(F.ImageSums(corners=n, found=float(found.sum()), displaced=float(far.sum()),
                                    displaced_r=float(d[far].sum()), located=float(near.sum()),
                                    loc_dof=float(near.sum()), loc2=float((d[near] ** 2).sum())))
        f = F.fit(sums, seed=seed, inlier=t)
        truths.append(sigma)
        for key, true in zip(keys, (sigma, frac, R), strict=True):
            e = f.get(key)
            hits[key] += e.lo <= true <= e.hi
            values[key].append(e.value)
        for s in sums:  # the same corners, the localisation error not fitted: its tail counts as mismatches
            s.located = s.loc_dof = s.loc2 = 0.0
        naive.append(F.fit(sums, seed=seed, inlier=t).get("corner_mismatch.fraction").value)
    assert all(h >= 32 for h in hits.values()), hits
    assert np.mean(np.array(values[keys[0]]) / truths) == pytest.approx(1, abs=0.02)
    assert np.mean(values[keys[1]]) == pytest.approx(frac, abs=0.01)
    assert np.mean(values[keys[2]]) == pytest.approx(R, rel=0.02)
    assert np.mean(naive) > frac + 0.015  # (measured: 0.227 against 0.200)


def test_the_fit_recovers_the_cameras_correlation_from_known_pairs():
    """Pairs of residuals correlated by rho (40 frames of 40 corners): the estimate's 95% interval holds rho in
    at least 34 of 40 settings, and without stereo pairs no correlation is claimed (the stage gets 0)."""
    hits = 0
    for seed in range(40):
        rng = np.random.default_rng([12, seed])
        rho = rng.uniform(0, 0.9)
        sums = []
        for _ in range(40):
            shared, own = rng.normal(0, 0.2, (40, 2)), rng.normal(0, 0.2, (2, 40, 2))
            a, b = (np.sqrt(rho) * shared + np.sqrt(1 - rho) * own[k] for k in (0, 1))
            sums.append(F.ImageSums(corners=40, found=40, located=40, loc_dof=40, loc2=float((a * a).sum()),
                                    pairs=40, pair_lr=float((a * b).sum()), pair_ll=float((a * a).sum()),
                                    pair_rr=float((b * b).sum())))
        e = F.fit(sums, seed=seed).get("corner_error.correlation")
        hits += e.lo <= rho <= e.hi
    assert hits >= 34, hits
    alone = F.fit([F.ImageSums(corners=40, found=40, located=40, loc_dof=40, loc2=1.6)] * 5, seed=0)
    assert alone.get("corner_error.correlation").value is None
    assert "corner_error sigma 0.1414px correlation 0" in pipeline_text(alone, "m", ["t"])


def test_truncated_sigma_inverts_the_truncated_mean_square_of_an_isotropic_normal():
    """Against the mean square of a million draws kept within t, and against quadrature of the Rayleigh
    density (scipy.integrate.quad, not the closed form)."""
    from scipy import integrate

    rng = np.random.default_rng(4)
    for sigma, t in ((0.2, 2.0), (1.0, 2.0), (1.5, 2.0), (0.05, 0.5)):
        r2 = (rng.normal(0, sigma, (1_000_000, 2)) ** 2).sum(1)
        m2 = r2[r2 <= t * t].mean()
        assert F.truncated_sigma(np.array([m2]), t)[0] == pytest.approx(sigma, rel=0.01)
        dens = lambda r, s=sigma: r / s**2 * np.exp(-r * r / (2 * s * s))  # noqa: E731
        quad = integrate.quad(lambda r, d=dens: r * r * d(r), 0, t)[0] / integrate.quad(dens, 0, t)[0]
        assert F.truncated_sigma(np.array([quad]), t)[0] == pytest.approx(sigma, rel=1e-6)
    assert np.isnan(F.truncated_sigma(np.array([2.0]), 2.0)[0])  # t^2 / 2: spread as if uniform, not bounded
    assert F.truncated_sigma(np.array([0.0]), 2.0)[0] == 0.0


def test_disc_radius_inverts_the_mean_distance_beyond_the_inlier_radius():
    rng = np.random.default_rng(2)
    for R, t in ((10.0, 2.0), (5.0, 1.0), (20.0, 3.0)):
        r = R * np.sqrt(rng.random(400_000))
        assert abs(F.disc_radius(np.array([r[r > t].mean()]), t)[0] - R) < 0.02 * R


def test_a_statistic_without_data_keeps_the_papers_value_and_says_so():
    f = F.fit([F.ImageSums(tested=100, verified=80, length=200, lost_middle=40)] * 5, seed=0)
    text = pipeline_text(f, "measured", ["test"])
    assert "corner_loss keep 85%" in text and "not estimated" in text
    assert "stereo matcher: no stereo pairs" in text
    assert f.get("edge_loss.fraction").value == pytest.approx(0.2)
    raw = F.fit([F.ImageSums(tested=100, verified=70, length=200, lost_middle=40)] * 5, seed=0, edge_loss="raw")
    assert raw.get("edge_loss.fraction").value == pytest.approx(0.3) and "the gaps alone: 20%" in \
        raw.get("edge_loss.fraction").note


def test_a_rig_with_a_declared_calibration_uncertainty_gets_it_simulated_first(tmp_path):
    """The fit measures the detector; the camera's uncertainty is the rig's own (lab.wd declares an information
    matrix): the pipeline starts with `calibration_error sigma 1`, which draws exactly it, and compiles with the
    scene without E160 (calibration first) or W161 (out of data-flow order)."""
    f = F.fit([F.ImageSums(tested=100, verified=80, length=200, lost_middle=40)] * 5, seed=0)
    assert "calibration_error" not in pipeline_text(f, "measured", ["test"])
    (tmp_path / "measured.wd").write_text(pipeline_text(f, "measured", ["test"], "information over 14 parameters"))
    (tmp_path / "s.wd").write_text(f'wiredsl 1\ninclude "{Path("scenes/lab.wd").resolve().as_posix()}"\n'
                                   'include "measured.wd"\n')
    from wiredsl.language.compile import compile_file

    scene, warnings, _ = compile_file(tmp_path / "s.wd")
    stages = scene.pipeline("measured").stages
    assert (stages[0].effect, stages[0].params["sigma"]) == ("calibration_error", 1.0)
    assert not [w for w in warnings if "W161" in str(w)]
    left_out = pipeline_text(f, "measured", ["test"], "information over 14 parameters", with_calibration=False)
    assert "calibration_error" not in left_out.replace("--no-calibration-error", "")


# --------------------------------------------------------------------------- the command

@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """The fence scene drawn undisturbed and through its `injected` pipeline (one trial, seed 3)."""
    scene = wiredsl.compile(FENCE)
    base = tmp_path_factory.mktemp("verify")
    for name, pipe in (("ideal", Pipeline(name="none")), ("injected", "injected")):
        batch = next(wiredsl.simulate(scene, trials=1, seed=3, pipeline=pipe, engine="numpy"))
        render_records(batch.records(), base / name, blur=1.0, noise=2.0, seed=3)
    return base


def _verify(*args) -> object:
    return CliRunner().invoke(main, ["verify", str(FENCE), *map(str, args)])


def test_verify_writes_the_table_figure7_and_a_pipeline_that_builds(rendered, tmp_path):
    out = tmp_path / "out"
    r = _verify("--images", rendered / "injected" / "*.png", "--detector", "canny", "--detector", "harris",
                "--fit", "-o", out)
    assert r.exit_code == 0, r.output
    assert {"verification.csv", "verification.json", "figure7.png", "measured.wd", "fit.json"} <= \
        {p.name for p in out.iterdir()}
    doc = json.loads((out / "verification.json").read_text())
    assert doc["images"] == 10 and doc["rows"]
    edge = [row for row in doc["rows"] if row["kind"] == "edge"]
    assert {row["image"].rsplit("/", 1)[1][:5] for row in edge} == {"left_", "right"}
    assert 0.6 < doc["objects"][0]["verified_fraction"] < 0.85  # 25% injected
    csv_lines = (out / "verification.csv").read_text().splitlines()
    assert len(csv_lines) == len(doc["rows"]) + 1 and "nan" not in (out / "verification.csv").read_text().lower()
    assert CliRunner().invoke(main, ["check", str(out / "measured.wd")]).exit_code == 0
    assert CliRunner().invoke(main, ["fmt", "--check", str(out / "measured.wd")]).exit_code == 0
    fit = json.loads((out / "fit.json").read_text())
    est = {e["parameter"]: e for e in fit["estimates"]}
    assert est["edge_loss.fraction"]["low95"] <= 0.25 <= est["edge_loss.fraction"]["high95"]
    scene = tmp_path / "with_measured.wd"
    scene.write_text(f'wiredsl 1\ninclude "{FENCE.resolve()}"\ninclude "{(out / "measured.wd").resolve()}"\n')
    b = CliRunner().invoke(main, ["build", str(scene), "--pipeline", "measured", "--seed", "1", "--no-svg", "-o",
                                  str(tmp_path / "build")])
    assert b.exit_code == 0, b.output
    # the same seed gives the same table and fit
    again = tmp_path / "again"
    _verify("--images", rendered / "injected" / "*.png", "--detector", "canny", "--detector", "harris", "--fit",
            "-o", again)
    assert (again / "measured.wd").read_bytes() == (out / "measured.wd").read_bytes()
    assert (again / "verification.csv").read_bytes() == (out / "verification.csv").read_bytes()


def test_undisturbed_images_verify_almost_whole_and_unshifted(rendered, tmp_path):
    r = _verify("--images", rendered / "ideal" / "left_*.png", "--detector", "canny", "--detector", "lsd", "--fit",
                "-o", tmp_path)
    assert r.exit_code == 0, r.output
    fit = json.loads((tmp_path / "fit.json").read_text())
    est = {e["parameter"]: e for e in fit["estimates"]}
    assert est["edge_loss.fraction"]["value"] < 0.01
    assert est["lateral_shift.range"]["value"] < 0.1
    assert abs(fit["lateral_shift_law"]["mean"]) < 0.05  # the verification is unbiased to 0.05 px
    objects = json.loads((tmp_path / "verification.json").read_text())["objects"]
    assert {o["detector"] for o in objects} == {"canny", "lsd"}
    assert all(o["verified_fraction"] > 0.95 for o in objects)


def test_poses_from_a_trajectory_file_by_order_and_by_time(rendered, tmp_path):
    scene = wiredsl.compile(FENCE)
    mount = scene.rig.left
    rows_t = []
    for k in range(5):
        from wiredsl.engine.geometry import camera_from_world

        R_cw, t_cw = camera_from_world(scene.path.pose(k), mount.rotation, mount.position)
        R_wc, p = R_cw.T, -R_cw.T @ t_cw
        from scipy.spatial.transform import Rotation

        q = Rotation.from_matrix(R_wc).as_quat()
        rows_t.append(f"{1000 + k * 0.5:.6f} " + " ".join(f"{v:.12f}" for v in (*p, *q)))
    (tmp_path / "poses.tum").write_text("\n".join(rows_t) + "\n")
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    for k in range(5):
        (imgs / f"{1000 + k * 0.5:.6f}.png").write_bytes((rendered / "ideal" / f"left_{k:03d}.png").read_bytes())
    by_time = _verify("--images", imgs / "*.png", "--poses", tmp_path / "poses.tum", "--detector", "canny", "-o",
                      tmp_path / "t")
    assert by_time.exit_code == 0, by_time.output
    doc = json.loads((tmp_path / "t" / "verification.json").read_text())
    assert "matched by time" in doc["poses"] and doc["objects"][0]["verified_fraction"] > 0.95
    by_order = _verify("--images", rendered / "ideal" / "left_*.png", "--poses", tmp_path / "poses.tum",
                       "--match", "order", "--detector", "canny", "-o", tmp_path / "o")
    assert by_order.exit_code == 0, by_order.output
    assert json.loads((tmp_path / "o" / "verification.json").read_text())["objects"][0]["verified_fraction"] > 0.95
    short = tmp_path / "short.tum"
    short.write_text("\n".join(rows_t[:3]) + "\n")
    r = _verify("--images", rendered / "ideal" / "left_*.png", "--poses", short, "--match", "order", "--detector",
                "canny", "-o", tmp_path / "s")
    assert r.exit_code == 1 and f"{short}:3:1: error[E192]" in r.stderr and "3 poses for 5 frames" in r.stderr


# --------------------------------------------------------------------------- bad input

def _png(width: int, height: int) -> bytes:
    """A PNG header (signature and IHDR) of any size, with no image data."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))


@pytest.mark.parametrize("case,code,words", [
    ("empty", "E190", "empty"),
    ("text", "E190", "not a PNG"),
    ("huge_header", "E190", "30000 x 30000"),
    ("truncated_jpeg", "E190", "truncated"),
    ("corrupt_png", "E190", "cannot be decoded"),
    ("wrong_size", "E191", "320 x 240 but its camera's image is 640 x 480"),
])
def test_hostile_images_give_a_located_diagnostic_never_exit_3(rendered, tmp_path, case, code, words):
    good = (rendered / "ideal" / "left_000.png").read_bytes()
    ok, jpeg = cv2.imencode(".jpg", cv2.imread(str(rendered / "ideal" / "left_000.png")))
    data = {"empty": b"", "text": b"hello, not an image\n", "huge_header": _png(30000, 30000),
            "truncated_jpeg": jpeg.tobytes()[: len(jpeg) // 2], "corrupt_png": good[:40] + b"\x00" * 200,
            "wrong_size": cv2.imencode(".png", np.zeros((240, 320), np.uint8))[1].tobytes()}[case]
    path = tmp_path / ("left_000.jpg" if "jpeg" in case else "left_000.png")
    path.write_bytes(data)
    r = _verify("--images", path, "--detector", "canny", "-o", tmp_path / "out")
    assert r.exit_code == 1, r.output
    assert f"{path}:1:1: error[{code}]" in r.stderr and words in r.stderr, r.stderr
    assert "Traceback" not in r.output and not (tmp_path / "out" / "verification.csv").exists()


def test_a_16_bit_image_is_scaled_with_a_warning(rendered, tmp_path):
    img = cv2.imread(str(rendered / "ideal" / "left_000.png"), cv2.IMREAD_UNCHANGED).astype(np.uint16) * 257
    path = tmp_path / "left_000.png"
    cv2.imwrite(str(path), img)
    r = _verify("--images", path, "--detector", "canny", "-o", tmp_path / "out")
    assert r.exit_code == 0, r.output
    assert "warning[W190]" in r.stderr and "16-bit" in r.stderr


def test_no_image_an_unknown_camera_and_an_unknown_detector_are_refused(tmp_path, rendered):
    r = _verify("--images", tmp_path / "none*.png", "--detector", "canny", "-o", tmp_path / "out")
    assert r.exit_code == 1 and "error[E193]" in r.stderr and "no image matches" in r.stderr
    odd = tmp_path / "middle_001.png"
    odd.write_bytes((rendered / "ideal" / "left_000.png").read_bytes())
    r = _verify("--images", odd, "--detector", "canny", "-o", tmp_path / "out")
    assert r.exit_code == 1 and "cannot tell which camera took middle_001.png" in r.stderr
    r = _verify("--images", odd, "--camera", "left", "--detector", "sobel", "-o", tmp_path / "out")
    assert r.exit_code == 2 and "unknown detector 'sobel'" in r.output
    r = _verify("--images", odd, "--camera", "left", "--detector", "canny", "--param", "canny.lowest=3", "-o",
                tmp_path / "out")
    assert r.exit_code == 2 and "no parameter 'lowest'" in r.output


def test_image_headers_give_format_and_size_without_decoding():
    assert I.header(_png(30000, 20000)) == I.Header("png", 30000, 20000)
    ok, jpeg = cv2.imencode(".jpg", np.zeros((48, 64), np.uint8))
    assert I.header(jpeg.tobytes()) == I.Header("jpeg", 64, 48)
    ok, bmp = cv2.imencode(".bmp", np.zeros((5, 7), np.uint8))
    assert I.header(bmp.tobytes()) == I.Header("bmp", 7, 5)
    assert I.header(b"P5\n# c\n12 9\n255\n" + bytes(108)) == I.Header("pnm", 12, 9)
    assert I.header(b"GIF89a") is None


# --------------------------------------------------------------------------- a plug-in detector

PLUGIN = '''
import numpy as np
from wiredsl.verify.detectors import Detection, Detector, DetectorParams


class Params(DetectorParams):
    threshold: float = 20.0


class Gradient(Detector):
    name = "gradient_edges"
    doc = "edges where a central-difference gradient is strong (a test plug-in)"
    Params = Params

    @classmethod
    def detect(cls, image, p):
        img = image.astype(np.float32)
        gx = np.zeros_like(img); gy = np.zeros_like(img)
        gx[:, 1:-1] = (img[:, 2:] - img[:, :-2]) / 2
        gy[1:-1, :] = (img[2:, :] - img[:-2, :]) / 2
        m = np.hypot(gx, gy)
        # thin: a pixel whose magnitude is a maximum along x or y
        peak = np.zeros_like(m, bool)
        c, ax, ay = m[1:-1, 1:-1], np.abs(gx[1:-1, 1:-1]), np.abs(gy[1:-1, 1:-1])
        peak[1:-1, 1:-1] = (((c >= m[1:-1, :-2]) & (c >= m[1:-1, 2:]) & (ax >= ay))
                            | ((c >= m[:-2, 1:-1]) & (c >= m[2:, 1:-1]) & (ay > ax)))
        return Detection(edges=peak & (m > p.threshold), gx=gx, gy=gy)


class Broken(Detector):
    name = "broken_edges"
    doc = "returns the wrong shape"

    @classmethod
    def detect(cls, image, p):
        return Detection(edges=np.zeros((3, 3), bool), gx=np.zeros((3, 3)), gy=np.zeros((3, 3)))
'''


def test_a_plugin_detector_is_loaded_by_name_and_verified_like_canny(tmp_path, monkeypatch, rendered):
    entry = "[wiredsl.detectors]\ngradient_edges = wdetect:Gradient\nbroken_edges = wdetect:Broken\n"
    with plugins_on_path(monkeypatch, make_dist(tmp_path / "site", "wdetect", PLUGIN, entry), modules=("wdetect",)):
        r = _verify("--images", rendered / "ideal" / "left_00[01].png", "--detector", "gradient_edges", "--param",
                    "threshold=15", "-o", tmp_path / "out")
        assert r.exit_code == 0, r.output
        doc = json.loads((tmp_path / "out" / "verification.json").read_text())
        assert doc["detectors"] == [{"name": "gradient_edges", "params": {"threshold": 15.0}}]
        assert doc["objects"][0]["verified_fraction"] > 0.9
        r = _verify("--images", rendered / "ideal" / "left_000.png", "--detector", "broken_edges", "-o",
                    tmp_path / "bad")
        assert r.exit_code == 1 and "error[E181]" in r.stderr and "wdetect" in r.stderr, r.output
        listed = CliRunner().invoke(main, ["plugins"])
        assert "detector\tgradient_edges\twdetect 0.3\twdetect:Gradient\tok" in listed.output, listed.output


def test_verifying_one_image_costs_little(rendered):
    """Not a timing test (benchmarks/verify_speed.py measures): the work is vectorised, a few array passes."""
    img = cv2.imread(str(rendered / "ideal" / "left_000.png"), cv2.IMREAD_GRAYSCALE)
    scene = wiredsl.compile(FENCE)
    from wiredsl.engine.simulate import Options, project_pose
    from wiredsl.engine.world import build_world

    world = build_world(scene)
    view = project_pose(scene, world, scene.path.pose(0), 0, Options(visibility="exact")).left
    found = D.Canny.detect(img, D.CannyParams())
    r = V.verify_image(view, found, img.shape, V.Settings(), V.ImageResult("x", "left", "0", "canny",
                                                                             world.feature_ids))
    assert r.samples == r.stats.tested.sum() > 500
    assert math.isfinite(float(np.nanmean(r.stats.offset_mean)))


def test_refine_moves_wrong_poses_onto_the_edges_and_says_how_far(rendered, tmp_path):
    from scipy.spatial.transform import Rotation

    from wiredsl.engine.geometry import camera_from_world

    scene = wiredsl.compile(FENCE)
    rng = np.random.default_rng(0)
    rows = []
    for k in range(3):
        R_cw, t_cw = camera_from_world(scene.path.pose(k), scene.rig.left.rotation, scene.rig.left.position)
        R_wc = R_cw.T @ Rotation.from_rotvec(rng.normal(0, 0.002, 3)).as_matrix()
        p = -R_cw.T @ t_cw + rng.normal(0, 0.01, 3)
        rows.append(f"{k} " + " ".join(f"{v:.12f}" for v in (*p, *Rotation.from_matrix(R_wc).as_quat())))
    (tmp_path / "off.tum").write_text("\n".join(rows) + "\n")
    args = ["--images", rendered / "ideal" / "left_00[012].png", "--poses", tmp_path / "off.tum", "--match", "order",
            "--detector", "canny", "--fit"]
    plain = _verify(*args, "-o", tmp_path / "plain")
    refined = _verify(*args, "--refine", "-o", tmp_path / "refined")
    assert plain.exit_code == 0 and refined.exit_code == 0, refined.output
    moved = json.loads((tmp_path / "refined" / "verification.json").read_text())["refined"]
    assert len(moved) == 3
    for m in moved:
        assert m["rms_offset_after_px"] < 0.2 < 0.3 < m["rms_offset_before_px"]
        assert 0.005 < m["rotation_deg"] < 1 and m["translation"] < 0.05
    shift = {p: json.loads((tmp_path / p / "fit.json").read_text())["lateral_shift_law"]["rms"]
             for p in ("plain", "refined")}
    assert shift["refined"] < 0.1 < shift["plain"]
    assert "refined 3 poses" in refined.stderr
    assert re.search(r"median move [0-9.e-]+ deg, [0-9.e-]+ m; median RMS", refined.stderr)  # metres, named


def test_board_poses_verify_a_rendered_chessboard_and_a_missing_board_is_an_error(tmp_path):
    from test_board import BOARD, CHESS

    scene = tmp_path / "boards.wd"
    scene.write_text(BOARD.format(board=CHESS))
    r = CliRunner().invoke(main, ["render", str(scene), "-o", str(tmp_path / "r"), "--edges", "none", "--blur", "0.7",
                                  "--noise", "1", "--seed", "1"])
    assert r.exit_code == 0, r.output
    v = CliRunner().invoke(main, ["verify", str(scene), "--images", str(tmp_path / "r" / "*.png"), "--poses", "board",
                                  "--detector", "canny", "--detector", "harris", "--fit", "-o", str(tmp_path / "v")])
    assert v.exit_code == 0, v.output
    doc = json.loads((tmp_path / "v" / "verification.json").read_text())
    assert doc["poses"].startswith("the scene's board") and doc["objects"][0]["verified_fraction"] > 0.8
    fit = {e["parameter"]: e for e in json.loads((tmp_path / "v" / "fit.json").read_text())["estimates"]}
    assert fit["corner_loss.keep"]["value"] > 0.97 and fit["lateral_shift.range"]["value"] < 0.3
    assert json.loads((tmp_path / "v" / "fit.json").read_text())["stereo_matcher"]["matched"] > 100
    blank = tmp_path / "blank"
    blank.mkdir()
    for k in range(2):
        cv2.imwrite(str(blank / f"left_{k:03d}.png"), np.full((480, 640), 128, np.uint8))
    e = CliRunner().invoke(main, ["verify", str(scene), "--images", str(blank / "*.png"), "--poses", "board",
                                  "--detector", "canny", "-o", str(tmp_path / "e")])
    assert e.exit_code == 1 and "error[E197]" in e.stderr and "found in 0 of 2 frames" in e.stderr, e.output


def test_opencvs_stereo_chessboard_images_verify_with_canny_lsd_and_harris(tmp_path):
    """Real images (tests/data/opencv_stereo/, 13 pairs) with poses from the board: most edges and corners found."""
    r = CliRunner().invoke(main, ["verify", "scenes/chessboard.wd", "--images", "tests/data/opencv_stereo/*.jpg",
                                  "--poses", "board", "--detector", "canny", "--detector", "lsd", "--detector",
                                  "harris", "--fit", "-o", str(tmp_path)])
    assert r.exit_code == 0, r.output
    objects = {o["detector"]: o for o in json.loads((tmp_path / "verification.json").read_text())["objects"]}
    assert objects["canny"]["images"] == 26 and 0.8 < objects["canny"]["verified_fraction"] < 0.95
    assert 0.85 < objects["lsd"]["verified_fraction"] < 0.97
    fit = json.loads((tmp_path / "fit.json").read_text())
    est = {e["parameter"]: e for e in fit["estimates"]}
    assert est["corner_loss.keep"]["value"] > 0.98
    assert 0 < est["lateral_shift.range"]["value"] < 2 and fit["stereo_matcher"]["matched"] > 500
    assert CliRunner().invoke(main, ["check", str(tmp_path / "measured.wd")]).exit_code == 0


def test_frames_pair_the_cameras_images_by_the_number_in_their_names(tmp_path):
    rig = wiredsl.compile(FENCE).rig
    for name in ("left_003.png", "right_003.png", "left_010.png", "right01.png"):
        (tmp_path / name).write_bytes(b"")
    frames = I.frames_of([(str(tmp_path / "*.png"), None)], rig)
    assert [(str(f.key), sorted(f.images)) for f in frames] == [("1", ["right"]), ("3", ["left", "right"]),
                                                                ("10", ["left"])]
    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "1305031102.175304.png").write_bytes(b"")
    (frame,) = I.frames_of([(str(tmp_path / "t" / "*.png"), "right")], rig)
    assert str(frame.key) == "1305031102.175304" and list(frame.images) == ["right"]


def test_poses_path_pairs_a_subset_of_images_by_their_numbers_and_warns_of_a_wrong_pairing(rendered, tmp_path):
    """Issue 34 item 6: `--poses path` on `left_00[34].png` verifies each at its own pose (3 and 4), not at the
    path's first two; an image numbered for another pose (a copy of pose 3's named 4) is W192 naming it; a
    number beyond the path is E192 at that image."""
    r = _verify("--images", rendered / "ideal" / "left_00[34].png", "--detector", "canny", "-o", tmp_path / "a")
    assert r.exit_code == 0, r.output
    assert "W192" not in r.output
    doc = json.loads((tmp_path / "a" / "verification.json").read_text())
    assert doc["images"] == 2 and all(o["verified_fraction"] > 0.95 for o in doc["objects"])
    wrong = tmp_path / "wrong"
    wrong.mkdir()
    (wrong / "left_004.png").write_bytes((rendered / "ideal" / "left_003.png").read_bytes())
    (wrong / "left_002.png").write_bytes((rendered / "ideal" / "left_002.png").read_bytes())
    r = _verify("--images", wrong / "*.png", "--detector", "canny", "-o", tmp_path / "b")
    assert r.exit_code == 0, r.output
    assert "W192" in r.output and "left_004.png" in r.output and "left_002.png" not in r.output
    (wrong / "left_009.png").write_bytes((rendered / "ideal" / "left_002.png").read_bytes())
    r = _verify("--images", wrong / "left_009.png", "--detector", "canny", "-o", tmp_path / "c")
    assert r.exit_code == 1 and "E192" in r.output and "left_009.png" in r.output and "0 to 4" in r.output


def test_the_shift_mixture_takes_fragments_on_unnamed_edges_off_and_keeps_the_range():
    """Issue 34: uniform shifts of range R with 4% of the fragments on another edge 4-6 px away (the paper's edge
    beside a board): the mixture's interval holds R in most settings, where the plain moments (sqrt(3 var d))
    are far off; with no background the share taken off is about none."""
    rng = np.random.default_rng(11)
    hits, naive = 0, []
    for k in range(12):
        R = rng.uniform(0.3, 2.5)
        d = rng.uniform(-R, R, 480) + rng.normal(0, 0.05, 480)
        bg = rng.random(480) < 0.04
        d[bg] = rng.choice([-1, 1], bg.sum()) * rng.uniform(4, 6, bg.sum())
        sums = _sums_with_shifts(d, per_image=40)
        for s in sums:
            s.offset_noise = [0.05 ** 2] * len(s.offsets)
        e = F.fit(sums, seed=k, band=6.0).get("lateral_shift.range")
        hits += e.lo <= R <= e.hi
        naive.append(abs(math.sqrt(3 * d.var()) - R))
    assert hits >= 10 and min(naive) > 0.3
    clean = _sums_with_shifts(rng.uniform(-1.5, 1.5, 800))
    f = F.fit(clean, seed=0)
    assert "taken as the background" in f.get("lateral_shift.range").note
    R, m, w, r, _ = (x[0] for x in F.shift_mixture(np.concatenate([s.offsets for s in clean]), np.zeros(800),
                                                    np.ones((1, 800)), 6.0))
    assert w < 0.005 and abs(R - 1.5) < 0.1


def test_the_chessboards_fitted_shift_does_not_depend_on_the_step_or_the_band(tmp_path):
    """Issue 34: OpenCV's 13 left chessboard images, Canny, poses from the board: the fitted lateral shift moves by
    at most 0.1 px between --step 0.25 and 2, and between --band 3 and 6 (it was 0.94 / 1.54 px at steps 2 /
    0.25, and 0.72 at band 3: border fragments on the paper's edge 4-6 px beside the board)."""
    from wiredsl.verify import command

    got = {}
    for step, band in ((2.0, 6.0), (0.25, 6.0), (2.0, 3.0)):
        req = command.Request("scenes/chessboard.wd", [("tests/data/opencv_stereo/left*.jpg", None)], ["canny"],
                              poses="board", settings=V.Settings(step=step, band=band), fit=True,
                              calibration_error=False)
        got[step, band] = command.run(req, tmp_path / f"{step}_{band}").fit.get("lateral_shift.range").value
    assert abs(got[0.25, 6.0] - got[2.0, 6.0]) <= 0.1, got
    assert abs(got[2.0, 3.0] - got[2.0, 6.0]) <= 0.1, got
    assert 0.2 < got[2.0, 6.0] < 0.8, got


def test_intervals_of_proportions_at_0_or_1_and_of_a_sigma_at_0_keep_width():
    """Issue 34: every image finds every corner and verifies every sample: corner keep 1 and edge loss 0, each with
    an interval of width (exact binomial: at 1 of 400 corners the lower bound is 1 - 0.025^(1/400)); a corner
    sigma of 0 from residuals of 0 gets no "95%" interval of zero width."""
    sums = [F.ImageSums(tested=500, verified=500, length=1000, corners=40, found=40, located=40, loc_dof=40,
                        loc2=0.0) for _ in range(10)]
    f = F.fit(sums, seed=0, edge_loss="raw")
    keep = f.get("corner_loss.keep")
    assert keep.value == 1 and keep.hi == 1 and keep.lo == pytest.approx(0.025 ** (1 / 400), abs=1e-9)
    assert "exact binomial" in keep.note
    loss = f.get("edge_loss.fraction")
    assert loss.value == 0 and loss.lo == 0 and loss.hi == pytest.approx(1 - 0.025 ** (1 / 5000), rel=1e-6)
    gaps = F.fit(sums, seed=0).get("edge_loss.fraction")
    assert gaps.value == 0 and gaps.hi > 0
    sigma = f.get("corner_error.sigma")
    assert sigma.lo is None or sigma.hi - sigma.lo > 0
    assert F.exact_binomial(0, 10) == (0.0, pytest.approx(1 - 0.025 ** 0.1))
    assert all(e.lo is None or e.hi > e.lo for e in f.estimates)


def test_an_ellipses_runs_are_cut_at_its_major_axis_as_the_shift_cuts_it():
    """Issue 34: lateral_shift moves an ellipse's two halves (cut at its major axis) each by its own offset; a run
    verified all round must give two fragments, +1 px and -1 px, not one averaging them to 0."""
    a = np.linspace(0, 2 * np.pi, 121)
    pts = np.column_stack([320 + 80 * np.cos(a), 240 + 30 * np.sin(a)])
    st = V.Strokes(pts, np.array([0, len(pts)]), np.array([0]), np.array([-1]), np.array([-1]), np.array([True]))
    sm = V.sample_strokes(st, 2.0)
    half = V.ellipse_halves(st, sm)
    assert set(half.tolist()) == {0, 1}
    off = np.where(half == 1, 1.0, -1.0)
    m = V.EdgeMatch(np.ones(len(off), bool), np.ones(len(off), bool), off)
    cut = V.stroke_stats(sm, m, 1, 3.0, half)
    whole = V.stroke_stats(sm, m, 1, 3.0)
    big = cut.run_length > 50
    assert sorted(np.round(cut.run_mean[big], 6).tolist()) == [-1.0, 1.0]
    assert len(whole.run_mean) == 1 and abs(whole.run_mean[0]) < 0.2


def test_a_junction_is_no_loss_and_only_free_ends_measure_the_end_loss():
    """Issue 34: at a T-junction (a stroke ending on another's middle: a silhouette at its rim's tangent, an
    occluded edge at its occluder) the detector loses a pixel or two of both that no effect removed. Those
    samples of the crossed stroke are left out (they were lost middles, read as edge loss with none injected),
    and the stem's end there is no free end: it does not measure the loss at an edge's end that the fit takes
    off each gap's ends."""
    st = V.Strokes(np.array([[100, 200], [300, 200], [200, 100], [200, 199]], float), np.array([0, 2, 4]),
                   np.array([0, 1]), np.array([-1, -1]), np.array([-1, -1]))
    sm = V.sample_strokes(st, 1.0)
    # the detector's response: lost within 2.5 px of the junction (200, 200) on both strokes, nothing else
    lost = np.hypot(sm.P[:, 0] - 200, sm.P[:, 1] - 200) < 2.5
    # and the stem's free end loses its first px, as a detector does at an edge's end
    lost |= (sm.stroke == 1) & (sm.s < 1.0)
    m = V.EdgeMatch(np.ones(len(lost), bool), ~lost, np.where(lost, np.nan, 0.0))
    assert sm.free.tolist() == [[True, True], [True, False]]
    got = V.stroke_stats(sm, m, 2)
    assert got.lost_middle.tolist() == [0.0, 0.0]
    assert got.ends.tolist() == [2, 1] and got.lost_ends[1] == pytest.approx(1.0, abs=0.51)
    assert got.runs.tolist() == [1, 1]  # the crossed stroke's run goes on across the junction
    plain = V.stroke_stats(V.Samples(sm.P, sm.N, sm.stroke, sm.s, sm.L), m, 2)  # (no junctions known)
    assert plain.lost_middle[0] > 3.0 and plain.runs[0] == 2
