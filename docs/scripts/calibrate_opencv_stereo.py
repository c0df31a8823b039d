"""Regenerate the stereo camera and the board poses of scenes/chessboard.wd from OpenCV's sample images.

    python docs/scripts/calibrate_opencv_stereo.py
    python docs/scripts/calibrate_opencv_stereo.py --monte-carlo 800 [SEED]   # check the covariance; writes nothing

Reads tests/data/opencv_stereo/left*.jpg and right*.jpg (13 pairs, a 9 x 6 inner-corner chessboard), and
writes, with OpenCV alone (no wiredsl code, so that the scene is an independent description of the images):

- scenes/calib/opencv_stereo.yml: the stereo calibration in cv2.FileStorage's layout (M1, D1, M2, D2, R, T,
  image size), as `stereoCalibrate` gives it after each camera's own `calibrateCamera` (five coefficients,
  no tangential terms, k3 fixed at 0: what the images support);
- scenes/trajectories/opencv_stereo.tum: the left camera's pose in the scene's world for each pair (TUM
  layout: the image number as the time, the optical centre, the camera-to-world quaternion), from
  `solvePnP` of the left image's corners, the board placed as scenes/chessboard.wd places it.
- scenes/calib/opencv_stereo.cov: how well the calibration knows its numbers, the covariance of the 18 rig
  parameters over wiredsl's names (ORDER below: each camera's f, ay, cx, cy, k, k2 and the right mount's t, r),
  linearised at the solution through both stages that estimate it, with the corner noise the residuals show
  (see `covariance`). tests/test_calibration_covariance.py checks it against 200 re-calibrations of noisier
  corners and the names against what wiredsl's `calibration_error` does with them.

OpenCV's threads sum in varying order: a rerun may change the last digits (1e-9 of R and T).

The images do not give the board's square size (OpenCV's sample takes 1.0): it is taken as SQUARE below.
Every pixel statistic is independent of that choice; lengths (the baseline, 3D errors) scale with it.
Prints the reprojection errors.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data" / "opencv_stereo"
PATTERN = (9, 6)  # inner corners across and down
SQUARE = 0.030  # m: assumed (see the module's docstring)
# the board's placement in scenes/chessboard.wd: `place target as board at (0, 0, 1m) rotate x -90deg rotate y
# 90deg` (R = Ry Rx): its rows (model x) point down (world -z), its printed side towards world -y, as it was
# held in most of the images (on its side)
R_PLACE = np.array([[0.0, -1, 0], [0, 0, 1], [-1, 0, 0]])
T_PLACE = np.array([0.0, 0.0, 1.0])
CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 60, 1e-4)
SIZE = (640, 480)
FLAGS = cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3  # free: fx, fy, cx, cy, k1, k2 (what the images support)


def corners(path: Path) -> np.ndarray | None:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    ok, found = cv2.findChessboardCorners(img, PATTERN, flags=cv2.CALIB_CB_ADAPTIVE_THRESH
                                          | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not ok:
        return None
    return cv2.cornerSubPix(img, found, (5, 5), (-1, -1), CRITERIA)


def detected() -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(image number, left corners, right corners) of the pairs whose board is found in both images."""
    pairs = []
    for n in sorted(int(p.stem[4:]) for p in DATA.glob("left[0-9][0-9].jpg")):
        a, b = corners(DATA / f"left{n:02d}.jpg"), corners(DATA / f"right{n:02d}.jpg")
        print(f"pair {n:02d}: board {'found' if a is not None else 'NOT found'} left, "
              f"{'found' if b is not None else 'NOT found'} right")
        if a is not None and b is not None:
            pairs.append((n, a, b))
    return pairs


def board_points() -> np.ndarray:
    """The board's inner corners in its own frame (54, 3), m: OpenCV's order (across, then down)."""
    obj = np.zeros((PATTERN[0] * PATTERN[1], 3), np.float32)
    obj[:, :2] = np.mgrid[0:PATTERN[0], 0:PATTERN[1]].T.reshape(-1, 2) * SQUARE
    return obj


def calibrate(left: list[np.ndarray], right: list[np.ndarray], quiet: bool = False) -> dict:
    """The stereo calibration of the corners: each camera's `calibrateCamera`, then `stereoCalibrate` of the
    pair with those intrinsics fixed. Returns M1, D1, M2, D2, R, T (x_r = R x_l + T), each camera's own board
    poses (rvecs1, tvecs1, rvecs2, tvecs2: board to camera), the stereo stage's left board poses (rvecs, tvecs) and
    its rms (px)."""
    objs = [board_points()] * len(left)
    rms1, M1, D1, rv1, tv1 = cv2.calibrateCamera(objs, left, SIZE, None, None, flags=FLAGS)
    rms2, M2, D2, rv2, tv2 = cv2.calibrateCamera(objs, right, SIZE, None, None, flags=FLAGS)
    rms, M1, D1, M2, D2, R, T, _, _, rv, tv, _ = cv2.stereoCalibrateExtended(
        objs, left, right, M1.copy(), D1.copy(), M2.copy(), D2.copy(), SIZE, None, None,
        flags=cv2.CALIB_FIX_INTRINSIC, criteria=CRITERIA)
    if not quiet:
        print(f"calibrateCamera rms: left {rms1:.3f} px, right {rms2:.3f} px; stereoCalibrate rms {rms:.3f} px; "
              f"baseline {np.linalg.norm(T) * 1000:.1f} mm (square {SQUARE * 1000:g} mm assumed)")
    return {"rms": float(rms), "M1": M1, "D1": D1, "M2": M2, "D2": D2, "R": R, "T": T.reshape(3), "rvecs1": rv1,
            "tvecs1": tv1, "rvecs2": rv2, "tvecs2": tv2, "rvecs": rv, "tvecs": tv}


# ---------------------------------------------------------------- the calibration's uncertainty, over wiredsl's names

# The rig's parameters the calibration estimates, as wiredsl's `calibration ... order` names them: each camera's
# focal length f (= fx; wiredsl keeps ax = 1), aspect ay (= fy / fx), centre, TINA's k (= -k1) and k2, and the
# right mount's translation and rotation vector in its own camera frame. `perturb` (wiredsl/effects/
# calibration_error.py) moves the right mount's camera-to-robot pose (R_s, p_s) to (R_s Exp(r), p_s + R_s t); with
# the left mount fixed that makes OpenCV's x_r = R x_l + T
#     R(r) = Exp(-r) R0,   T(r, t) = Exp(-r) (T0 - t).
INTRINSICS = ("f", "ay", "cx", "cy", "k", "k2")
ORDER = [f"{side}.{p}" for side in ("left", "right") for p in INTRINSICS] + [
    f"right.{p}" for p in ("tx", "ty", "tz", "rx", "ry", "rz")]
COVARIANCE = ROOT / "scenes" / "calib" / "opencv_stereo.cov"


def skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def intrinsics_map(M: np.ndarray) -> np.ndarray:
    """d(fx, fy, cx, cy, k1, k2) / d(f, ay, cx, cy, k, k2) at the camera matrix M: fx = f, fy = f ay, k1 = -k."""
    A = np.eye(6)
    A[1, 0], A[1, 1] = M[1, 1] / M[0, 0], M[0, 0]
    A[4, 4] = -1.0
    return A


def left_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """SO(3)'s inverse left Jacobian: Exp(d) Exp(phi) = Exp(phi + J^-1(phi) d + O(d^2))."""
    theta = float(np.linalg.norm(phi))
    P = skew(phi)
    if theta < 1e-8:
        return np.eye(3) - P / 2 + P @ P / 12
    return np.eye(3) - P / 2 + (1 / theta ** 2 - (1 + np.cos(theta)) / (2 * theta * np.sin(theta))) * (P @ P)


def rig_map(R0: np.ndarray, T0: np.ndarray) -> np.ndarray:
    """d(om, T) / d(t, r): OpenCV's rotation vector om (R = Rodrigues(om)) and T against the right mount's t and r,
    at r = t = 0. From R = Exp(-r) R0: d om / d r = -J^-1(om0); from T = Exp(-r) (T0 - t) = T0 - t - r x T0:
    d T / d t = -I, d T / d r = [T0]x."""
    om0 = cv2.Rodrigues(R0)[0].reshape(3)
    C = np.zeros((6, 6))
    C[:3, 3:] = -left_jacobian_inverse(om0)
    C[3:, :3] = -np.eye(3)
    C[3:, 3:] = skew(T0)
    return C


def rig_offsets(R: np.ndarray, T: np.ndarray, R0: np.ndarray, T0: np.ndarray) -> np.ndarray:
    """The right mount's (tx, ty, tz, rx, ry, rz) that move the rig (R0, T0) to (R, T), exactly: Exp(-r) = R R0^T,
    t = T0 - Exp(r) T."""
    r = -cv2.Rodrigues(R @ R0.T)[0].reshape(3)
    return np.concatenate([T0 - R0 @ R.T @ T, r])


def offsets(cal: dict, ref: dict) -> np.ndarray:
    """A calibration's parameters over ORDER less the reference calibration's (exactly, not linearised)."""
    out = []
    for M, D, M0, D0 in ((cal["M1"], cal["D1"], ref["M1"], ref["D1"]), (cal["M2"], cal["D2"], ref["M2"], ref["D2"])):
        out += [M[0, 0] - M0[0, 0], M[1, 1] / M[0, 0] - M0[1, 1] / M0[0, 0], M[0, 2] - M0[0, 2],
                M[1, 2] - M0[1, 2], -(D.ravel()[0] - D0.ravel()[0]), D.ravel()[1] - D0.ravel()[1]]
    return np.concatenate([out, rig_offsets(cal["R"], cal["T"], ref["R"], ref["T"])])


def _projection(obj, rvec, tvec, M, D):
    """Pixels (2N,) of the board points, u0 v0 u1 ..., and their Jacobian: d / d(rvec, tvec) (2N, 6) and
    d / d(f, ay, cx, cy, k, k2) (2N, 6)."""
    uv, J = cv2.projectPoints(obj, rvec, tvec, M, D)  # J: rvec, tvec, fx, fy, cx, cy, then D's coefficients
    return uv.reshape(-1), J[:, :6], J[:, [6, 7, 8, 9, 10, 11]] @ intrinsics_map(M)


def jacobians(cal: dict, left: list[np.ndarray], right: list[np.ndarray]) -> dict:
    """The reprojection residuals (projected - detected) and their Jacobians at the calibration, for the two
    stages that estimated it. Stereo stage, residuals [all left; all right] (n,): `J_intr` (n, 12) over both
    cameras' intrinsics, `J_rig` (n, 6) over the right mount's (t, r), `J_board` (n, 6 V) over the left board
    poses. Each camera's own stage: `own` = [(residuals, J over its intrinsics, J over its own board poses)]."""
    obj = board_points().astype(np.float64)
    V, n2 = len(left), 2 * len(obj)
    C = rig_map(cal["R"], cal["T"])
    om0 = cv2.Rodrigues(cal["R"])[0]
    res, J_intr, J_rig, J_board = np.zeros(2 * V * n2), np.zeros((2 * V * n2, 12)), np.zeros((2 * V * n2, 6)), \
        np.zeros((2 * V * n2, 6 * V))
    for i in range(V):
        rv, tv = cal["rvecs"][i], cal["tvecs"][i]
        uv, Jp, Ji = _projection(obj, rv, tv, cal["M1"], cal["D1"])
        rows = slice(i * n2, (i + 1) * n2)
        res[rows], J_intr[rows, :6], J_board[rows, 6 * i:6 * i + 6] = uv - left[i].reshape(-1), Ji, Jp
        # the right camera sees the board through the rig: (rvec3, tvec3) = (om, T) after (rv, tv)
        rv3, tv3, dr3dr1, dr3dt1, dr3dr2, dr3dt2, dt3dr1, dt3dt1, dt3dr2, dt3dt2 = cv2.composeRT(
            rv, tv, om0, cal["T"].reshape(3, 1))
        uv, Jp, Ji = _projection(obj, rv3, tv3, cal["M2"], cal["D2"])
        rows = slice((V + i) * n2, (V + i + 1) * n2)
        res[rows], J_intr[rows, 6:] = uv - right[i].reshape(-1), Ji
        J_board[rows, 6 * i:6 * i + 6] = (Jp[:, :3] @ np.hstack([dr3dr1, dr3dt1])
                                          + Jp[:, 3:] @ np.hstack([dt3dr1, dt3dt1]))
        J_rig[rows] = (Jp[:, :3] @ np.hstack([dr3dr2, dr3dt2]) + Jp[:, 3:] @ np.hstack([dt3dr2, dt3dt2])) @ C
    own = []
    for k, corners_ in ((1, left), (2, right)):
        r, Ji, Jb = np.zeros(V * n2), np.zeros((V * n2, 6)), np.zeros((V * n2, 6 * V))
        for i in range(V):
            uv, Jp, Jk = _projection(obj, cal[f"rvecs{k}"][i], cal[f"tvecs{k}"][i], cal[f"M{k}"], cal[f"D{k}"])
            rows = slice(i * n2, (i + 1) * n2)
            r[rows], Ji[rows], Jb[rows, 6 * i:6 * i + 6] = uv - corners_[i].reshape(-1), Jk, Jp
        own.append((r, Ji, Jb))
    return {"residuals": res, "J_intr": J_intr, "J_rig": J_rig, "J_board": J_board, "own": own}


def _solve_map(J: np.ndarray) -> np.ndarray:
    """(J^T J)^-1 J^T with the columns scaled to unit norm first (pixels, radians and metres differ by 10^6)."""
    s = np.linalg.norm(J, axis=0)
    Js = J / s
    return np.linalg.solve(Js.T @ Js, Js.T) / s[:, None]


def covariance(cal: dict, left: list[np.ndarray], right: list[np.ndarray]) -> dict:
    """The covariance over ORDER of the calibration's estimate, by linearisation at it, for corners with independent
    N(0, sigma^2) errors in each coordinate. sigma^2 = RSS / (n - p) of the stereo stage's residuals, p the
    parameters of the whole problem (both cameras' intrinsics, the rig, the board poses). The estimate is made in two
    stages, so its linearisation is too: each camera's intrinsics move by G_c e_c (its own least squares, its own
    board poses marginalised), then the rig and the left board poses by (J_b^T J_b)^-1 J_b^T (e - J_intr G e); the
    covariance is sigma^2 M M^T of that map M from the corner errors e to the parameters. `joint` is what one
    estimate of everything at once would have: sigma^2 [(J^T J)^-1] over the rig's block (the board poses
    marginalised)."""
    J = jacobians(cal, left, right)
    res, J_intr, J_rig, J_board = J["residuals"], J["J_intr"], J["J_rig"], J["J_board"]
    n, p = len(res), J_intr.shape[1] + J_rig.shape[1] + J_board.shape[1]
    sigma2 = float(res @ res) / (n - p)
    half = n // 2
    G = np.zeros((12, n))  # each camera's own stage: its intrinsics from its own corners
    for k, (_, Ji, Jb) in enumerate(J["own"]):
        G[6 * k:6 * k + 6, half * k:half * (k + 1)] = _solve_map(np.hstack([Ji, Jb]))[:6]
    stereo = _solve_map(np.hstack([J_rig, J_board]))[:6]  # the rig's rows
    M = np.vstack([G, stereo @ (np.eye(n) - J_intr @ G)])
    full = np.hstack([J_intr, J_rig, J_board])
    s = np.linalg.norm(full, axis=0)
    joint = np.linalg.inv((full / s).T @ (full / s))[:18, :18] / np.outer(s[:18], s[:18])
    return {"covariance": sigma2 * (M @ M.T), "joint": sigma2 * joint, "sigma": np.sqrt(sigma2), "n": n, "p": p}


def write_covariance(path: Path, cov: dict) -> None:
    C = (cov["covariance"] + cov["covariance"].T) / 2
    sd = np.sqrt(np.diag(C))
    rows = ["# covariance of the stereo calibration in opencv_stereo.yml, by docs/scripts/calibrate_opencv_stereo.py:",
            "# linearised at the solution (both cameras' calibrateCamera, then stereoCalibrate with those intrinsics),",
            f"# corner noise sigma = {cov['sigma']:.4f} px from the residuals (RSS / (n - p), n = {cov['n']}, "
            f"p = {cov['p']}); the board poses marginalised.",
            "# rows and columns, with their standard deviations (px; TINA's k = -k1; m; rad):",
            *(f"#   {name:9s} {v:.4g}" for name, v in zip(ORDER, sd, strict=True)),
            *(" ".join(f"{v:.12e}" for v in row) for row in C)]
    tmp = path.with_suffix(".tmp")
    tmp.write_text("\n".join(rows) + "\n")
    tmp.replace(path)


def monte_carlo(left: list[np.ndarray], right: list[np.ndarray], ref: dict, sigma: float, runs: int,
                rng: np.random.Generator) -> np.ndarray:
    """`runs` calibrations (as `calibrate`) of the detected corners plus fresh N(0, sigma^2) noise: their parameters
    over ORDER less the reference's (runs, 18), converted exactly (`offsets`), not linearised."""
    out = []
    for _ in range(runs):
        noisy = [[c + rng.normal(0.0, sigma, c.shape).astype(np.float32) for c in side] for side in (left, right)]
        out.append(offsets(calibrate(*noisy, quiet=True), ref))
    return np.array(out)


def check(runs: int, seed: int) -> dict:
    """The calibration, its linearised covariance and `runs` re-calibrations of noisier corners against it: each
    standard deviation's ratio (Monte-Carlo / linearised), the large correlations' largest difference, and how much
    less one joint estimate of everything would claim. Writes nothing."""
    pairs = detected()
    left, right = [a for _, a, _ in pairs], [b for _, _, b in pairs]
    ref = calibrate(left, right, quiet=True)
    cov = covariance(ref, left, right)
    X = monte_carlo(left, right, ref, cov["sigma"], runs, np.random.default_rng(seed))
    sd, mc = np.sqrt(np.diag(cov["covariance"])), X.std(axis=0, ddof=1)
    rho, rho_mc = cov["covariance"] / np.outer(sd, sd), np.corrcoef(X.T)
    big = np.abs(rho) > 0.5
    np.fill_diagonal(big, False)
    joint = mc / np.sqrt(np.diag(cov["joint"]))
    return {"pairs": len(pairs), "rms": ref["rms"], "baseline_mm": float(np.linalg.norm(ref["T"]) * 1000),
            "sigma": cov["sigma"], "n": cov["n"], "p": cov["p"], "runs": runs, "seed": seed,
            "ratio": dict(zip(ORDER, (mc / sd).tolist(), strict=True)), "big_correlations": int(big.sum() // 2),
            "correlation_difference": float(np.abs(rho - rho_mc)[big].max()),
            "joint_ratio": dict(zip(ORDER, joint.tolist(), strict=True))}


def main() -> int:
    if sys.argv[1:2] == ["--monte-carlo"]:  # --monte-carlo RUNS [SEED]: check the covariance, write nothing
        got = check(int(sys.argv[2]), int(sys.argv[3]) if len(sys.argv) > 3 else 0)
        print(f"stereoCalibrate rms {got['rms']:.3f} px, baseline {got['baseline_mm']:.1f} mm, corner noise sigma "
              f"{got['sigma']:.4f} px (n {got['n']}, p {got['p']}); {got['runs']} re-calibrations, seed {got['seed']}:")
        for name in ORDER:
            print(f"  {name:9s} Monte-Carlo / linearised {got['ratio'][name]:.3f}, / one joint estimate "
                  f"{got['joint_ratio'][name]:.2f}")
        print(f"the {got['big_correlations']} correlations beyond 0.5: largest difference "
              f"{got['correlation_difference']:.3f}")
        print(json.dumps(got))
        return 0
    pairs = detected()
    obj = board_points()
    cal = calibrate([a for _, a, _ in pairs], [b for _, _, b in pairs])
    M1, D1, M2, D2, R, T = (cal[k] for k in ("M1", "D1", "M2", "D2", "R", "T"))
    out = ROOT / "scenes" / "calib" / "opencv_stereo.yml"
    out.parent.mkdir(parents=True, exist_ok=True)
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", SIZE[0])
    fs.write("image_height", SIZE[1])
    for name, m in (("M1", M1), ("D1", D1), ("M2", M2), ("D2", D2), ("R", R), ("T", T.reshape(3, 1))):
        fs.write(name, m)
    fs.release()
    rows = ["# the left camera of OpenCV's stereo_calib sample images, by docs/scripts/calibrate_opencv_stereo.py",
            "# timestamp (the image number) tx ty tz qx qy qz qw: camera to world, OpenCV camera axes"]
    for n, a, _ in pairs:
        ok, rvec, tvec = cv2.solvePnP(obj.astype(np.float64), a.reshape(-1, 2).astype(np.float64), M1, D1)
        R_cm = cv2.Rodrigues(rvec)[0]  # camera from board model
        R_cw = R_cm @ R_PLACE.T  # camera from world (world = R_PLACE model + T_PLACE)
        t_cw = tvec.reshape(3) - R_cw @ T_PLACE
        R_wc, c = R_cw.T, -R_cw.T @ t_cw
        q = Rotation.from_matrix(R_wc).as_quat()  # x, y, z, w
        uv, _ = cv2.projectPoints(obj, rvec, tvec, M1, D1)
        err = np.sqrt(np.mean(np.sum((uv.reshape(-1, 2) - a.reshape(-1, 2)) ** 2, axis=1)))
        print(f"left{n:02d}: solvePnP rms {err:.3f} px, camera at {np.round(c, 3)} m")
        rows.append(f"{n} " + " ".join(f"{v:.9f}" for v in (*c, *q)))
    (ROOT / "scenes" / "trajectories" / "opencv_stereo.tum").write_text("\n".join(rows) + "\n")
    cov = covariance(cal, [a for _, a, _ in pairs], [b for _, _, b in pairs])
    write_covariance(COVARIANCE, cov)
    print(f"corner noise sigma {cov['sigma']:.4f} px; standard deviations (two stages | one joint estimate):")
    for name, a, b in zip(ORDER, np.sqrt(np.diag(cov["covariance"])), np.sqrt(np.diag(cov["joint"])), strict=True):
        print(f"  {name:9s} {a:.4g} | {b:.4g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
