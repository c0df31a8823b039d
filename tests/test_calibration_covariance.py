"""The chessboard rig's calibration covariance (docs/scripts/calibrate_opencv_stereo.py writes it with OpenCV alone,
scenes/calib/opencv_stereo.cov; scenes/chessboard.wd declares it): its change of parameters against what
`calibration_error` does with each name, its linearisation against a Monte-Carlo of OpenCV's own calibration, and a
build that draws from it."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

import wiredsl
from wiredsl.cli import main
from wiredsl.effects import REGISTRY
from wiredsl.effects import calibration_error as calib

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "scenes" / "chessboard.wd"
FILE = ROOT / "scenes" / "calib" / "opencv_stereo.cov"


def _script():
    spec = importlib.util.spec_from_file_location("calibrate_opencv_stereo",
                                                  ROOT / "docs" / "scripts" / "calibrate_opencv_stereo.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


cal = _script()


def _file_matrix() -> np.ndarray:
    rows = [line.split() for line in FILE.read_text().splitlines() if line.strip() and not line.startswith("#")]
    return np.array(rows, dtype=float)


@pytest.fixture(scope="module")
def calibrated():
    """The detected corners, the script's calibration of them and its covariance."""
    pairs = cal.detected()
    left, right = [a for _, a, _ in pairs], [b for _, _, b in pairs]
    ref = cal.calibrate(left, right, quiet=True)
    return left, right, ref, cal.covariance(ref, left, right)


# ----------------------------------------------------------------------------- OpenCV's parameters as wiredsl's

def _extrinsics(scene, phi: np.ndarray, order: list[str]):
    return calib.perturb(scene, phi, order).rig.stereo_extrinsics()


def test_the_rig_map_is_what_perturb_does_with_each_name():
    """d(om, T) / d(t, r) of the script against central differences of wiredsl's own perturb (wiredsl to
    OpenCV), and the script's exact inverse recovering a finite perturb (OpenCV to wiredsl)."""
    scene = wiredsl.compile(SCENE)
    R0, T0 = scene.rig.stereo_extrinsics()
    om0 = cv2.Rodrigues(R0)[0].reshape(3)
    C = cal.rig_map(R0, T0)
    order = [f"right.{p}" for p in ("tx", "ty", "tz", "rx", "ry", "rz")]
    h = 1e-6
    for j in range(6):
        ends = []
        for sign in (1, -1):
            R, T = _extrinsics(scene, sign * h * np.eye(6)[j], order)
            ends.append(np.concatenate([cv2.Rodrigues(R)[0].reshape(3) - om0, T - T0]))
        numeric = (ends[0] - ends[1]) / (2 * h)
        assert numeric == pytest.approx(C[:, j], abs=1e-8), order[j]
    assert np.abs(C[3:, 3:]).max() > 1e-3 and np.abs(C[:3, 3:] + np.eye(3)).max() > 1e-5  # not the identity
    rng = np.random.default_rng(5)
    for _ in range(5):
        phi = rng.normal(size=6) * [0.002, 0.002, 0.002, 0.02, 0.02, 0.02]  # far beyond linear
        R, T = _extrinsics(scene, phi, order)
        assert cal.rig_offsets(R, T, R0, T0) == pytest.approx(phi, abs=1e-12)


def test_the_intrinsics_map_is_what_perturb_does_with_each_name():
    scene = wiredsl.compile(SCENE)
    order = [f"{side}.{p}" for side in ("left", "right") for p in cal.INTRINSICS]

    def opencv(s):
        out = {}
        for k, side in ((1, "left"), (2, "right")):
            c = s.camera(getattr(s.rig, side).camera)
            out[f"M{k}"] = np.array([[c.f * c.ax, 0, c.cx], [0, c.f * c.ay, c.cy], [0, 0, 1]])
            out[f"D{k}"] = np.array([c.k1, c.k2, c.p1, c.p2, c.k3])
        R, T = s.rig.stereo_extrinsics()
        return {**out, "R": R, "T": T}

    ref = opencv(scene)
    rng = np.random.default_rng(6)
    phi = rng.normal(size=12) * np.tile([1.0, 1e-3, 1.0, 1.0, 0.01, 0.01], 2)
    moved = opencv(calib.perturb(scene, phi, order))
    assert cal.offsets(moved, ref)[:12] == pytest.approx(phi, abs=1e-12)
    for k in (1, 2):  # and the linear map of one camera's, by differences
        A = cal.intrinsics_map(ref[f"M{k}"])
        M, D = moved[f"M{k}"], moved[f"D{k}"]
        M0, D0 = ref[f"M{k}"], ref[f"D{k}"]
        d = np.array([M[0, 0] - M0[0, 0], M[1, 1] - M0[1, 1], M[0, 2] - M0[0, 2], M[1, 2] - M0[1, 2],
                      D[0] - D0[0], D[1] - D0[1]])
        lin = A @ phi[6 * (k - 1):6 * k]
        assert d == pytest.approx(lin, rel=1e-3, abs=1e-9)  # bilinear fy = f ay: second order only


# ----------------------------------------------------------------------------- the linearisation against OpenCV

def test_the_covariance_file_is_the_scripts_linearisation_of_the_scenes_calibration(calibrated):
    _, _, ref, cov = calibrated
    scene = wiredsl.compile(SCENE)
    R0, T0 = scene.rig.stereo_extrinsics()
    # (OpenCV's threads make the last digits vary from run to run: 1e-9)
    assert ref["R"] == pytest.approx(R0, abs=1e-7) and ref["T"] == pytest.approx(T0, abs=1e-7)
    assert scene.rig.calibration.order == cal.ORDER and scene.rig.calibration.kind == "covariance"
    C = _file_matrix()
    assert np.array_equal(C, np.array(scene.rig.calibration.matrix))
    assert np.sqrt(np.diag(C)) == pytest.approx(np.sqrt(np.diag(cov["covariance"])), rel=1e-6)
    assert 0.12 < cov["sigma"] < 0.25  # px: the corners' own scatter (stereoCalibrate's rms is 0.22 px)


def test_the_covariance_is_the_spread_of_opencvs_calibration_of_noisier_corners(calibrated):
    """200 calibrations (each camera's calibrateCamera, then stereoCalibrate, as the script calibrates) of the
    detected corners plus fresh N(0, sigma^2) noise: the spread of their parameters, converted exactly (not
    linearised), against the file's covariance."""
    left, right, ref, cov = calibrated
    C = _file_matrix()
    # 200 draws estimate a standard deviation to ~5%: seeds 7, 8, 9 put the worst of the 18 at 0.90, 0.91, 0.95
    # and 1.11, 1.05, 1.05 of the file's; seed 2026 right.cx at 0.81; their 800 together all within 4%
    rng = np.random.default_rng(8)
    runs = []
    for _ in range(200):
        noisy = [[c + rng.normal(0.0, cov["sigma"], c.shape).astype(np.float32) for c in side]
                 for side in (left, right)]
        runs.append(cal.offsets(cal.calibrate(*noisy, quiet=True), ref))
    X = np.array(runs)
    sd, mc = np.sqrt(np.diag(C)), X.std(axis=0, ddof=1)
    ratio = mc / sd
    assert np.all(np.abs(ratio - 1) < 0.2), dict(zip(cal.ORDER, ratio.round(3), strict=True))
    rho, rho_mc = C / np.outer(sd, sd), np.corrcoef(X.T)
    big = np.abs(rho) > 0.5
    np.fill_diagonal(big, False)
    assert big.sum() >= 10 and np.abs(rho - rho_mc)[big].max() < 0.15
    # the estimate of everything at once would claim less than the script's two stages deliver: the baseline's
    # depth tz by a factor of 2.5, which this oracle would catch
    tz = cal.ORDER.index("right.tz")
    assert mc[tz] / np.sqrt(cov["joint"][tz, tz]) > 1.8


# ----------------------------------------------------------------------------- the scene draws from it

def test_a_covariance_draws_its_small_directions_too():
    """A rig's covariance spans px^2 to m^2: an eigenvalue 1e-12 of the largest is a variance, not a direction
    the calibration left unconstrained (that cutoff is an information matrix's)."""
    C = np.diag([1.0, 1e-12, 4e-14])
    p = REGISTRY["calibration_error"].Params(sigma=1.0)
    s = calib.sampler(p, "covariance", C.tolist(), ["left.f", "right.tx", "right.rz"])
    d = calib.draws(s, np.arange(4000), 0)
    assert s.unconstrained == [] and d.std(axis=0) == pytest.approx(np.sqrt(np.diag(C)), rel=0.05)


def test_building_the_chessboard_with_its_calibration_records_the_files_covariance(tmp_path):
    r = CliRunner().invoke(main, ["build", str(SCENE), "--pipeline", "calibration", "--trials", "300", "--seed", "4",
                                  "--pose", "0", "--format", "npz", "--no-svg", "-o", str(tmp_path)])
    assert r.exit_code == 0, r.output
    (stage,) = json.loads((tmp_path / "manifest.json").read_text())["stages"]
    assert stage["effect"] == "calibration_error" and stage["params"]["sigma"] == 1
    recorded = stage["measured"]["covariance"]
    C = _file_matrix()
    assert recorded["order"] == cal.ORDER
    S, sd = np.asarray(recorded["measured"]), np.sqrt(np.diag(C))
    declared = np.asarray(recorded["declared"])  # the file's, to the decomposition's rounding (correlation units)
    assert np.abs((declared - C) / np.outer(sd, sd)).max() < 1e-7
    assert np.sqrt(np.diag(S)) / sd == pytest.approx(np.ones(len(C)), abs=0.2)  # 300 draws: ~4% each
    assert stage["measured"]["refused_draws"]["measured"] == 0
