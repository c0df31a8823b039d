"""Regenerate the stereo camera and the board poses of scenes/chessboard.wd from OpenCV's sample images.

    python docs/scripts/calibrate_opencv_stereo.py

Reads tests/data/opencv_stereo/left*.jpg and right*.jpg (13 pairs, a 9 x 6 inner-corner chessboard), and
writes, with OpenCV alone (no wiredsl code, so that the scene is an independent description of the images):

- scenes/calib/opencv_stereo.yml: the stereo calibration in cv2.FileStorage's layout (M1, D1, M2, D2, R, T,
  image size), as `stereoCalibrate` gives it after each camera's own `calibrateCamera` (five coefficients,
  no tangential terms, k3 fixed at 0: what the images support);
- scenes/trajectories/opencv_stereo.tum: the left camera's pose in the scene's world for each pair (TUM
  layout: the image number as the time, the optical centre, the camera-to-world quaternion), from
  `solvePnP` of the left image's corners, the board placed as scenes/chessboard.wd places it.

The images do not give the board's square size (OpenCV's sample takes 1.0): it is taken as SQUARE below.
Every pixel statistic is independent of that choice; lengths (the baseline, 3D errors) scale with it.
Prints the reprojection errors.
"""

from __future__ import annotations

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


def corners(path: Path) -> np.ndarray | None:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    ok, found = cv2.findChessboardCorners(img, PATTERN, flags=cv2.CALIB_CB_ADAPTIVE_THRESH
                                          | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not ok:
        return None
    return cv2.cornerSubPix(img, found, (5, 5), (-1, -1), CRITERIA)


def main() -> int:
    numbers = sorted(int(p.stem[4:]) for p in DATA.glob("left[0-9][0-9].jpg"))
    obj = np.zeros((PATTERN[0] * PATTERN[1], 3), np.float32)
    obj[:, :2] = np.mgrid[0:PATTERN[0], 0:PATTERN[1]].T.reshape(-1, 2) * SQUARE
    pairs = []
    for n in numbers:
        a, b = corners(DATA / f"left{n:02d}.jpg"), corners(DATA / f"right{n:02d}.jpg")
        print(f"pair {n:02d}: board {'found' if a is not None else 'NOT found'} left, "
              f"{'found' if b is not None else 'NOT found'} right")
        if a is not None and b is not None:
            pairs.append((n, a, b))
    size = (640, 480)
    flags = cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
    objs = [obj] * len(pairs)
    rms1, M1, D1, _, _ = cv2.calibrateCamera(objs, [a for _, a, _ in pairs], size, None, None, flags=flags)
    rms2, M2, D2, _, _ = cv2.calibrateCamera(objs, [b for _, _, b in pairs], size, None, None, flags=flags)
    rms, M1, D1, M2, D2, R, T, E, F = cv2.stereoCalibrate(
        objs, [a for _, a, _ in pairs], [b for _, _, b in pairs], M1, D1, M2, D2, size,
        flags=cv2.CALIB_FIX_INTRINSIC, criteria=CRITERIA)
    print(f"calibrateCamera rms: left {rms1:.3f} px, right {rms2:.3f} px; stereoCalibrate rms {rms:.3f} px; "
          f"baseline {np.linalg.norm(T) * 1000:.1f} mm (square {SQUARE * 1000:g} mm assumed)")
    out = ROOT / "scenes" / "calib" / "opencv_stereo.yml"
    out.parent.mkdir(parents=True, exist_ok=True)
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", size[0])
    fs.write("image_height", size[1])
    for name, m in (("M1", M1), ("D1", D1), ("M2", M2), ("D2", D2), ("R", R), ("T", T)):
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
