"""Pose from corners: OpenCV's solvePnPRansac on the disturbed corners of one camera (the left, or the right
with `right 1`), against their known 3D positions, compared with the camera's true pose.

Per trial: `rotation_error` (degrees, the angle of R_est R_true^T), `position_error` (metres, between the
estimated and the true camera centres), `solved` (1 when RANSAC found a pose from at least `min_corners`
corners with `min_inliers` inliers, else 0), and `corners` (how many corners the camera kept). The errors
are averaged over solved trials only (their weight is `solved`); where a trial is not solved they are 0.
"""

from __future__ import annotations

import numpy as np

from wiredsl import Measure
from wiredsl.measures.base import Params, param


class PnPParams(Params):
    right: bool = param(False, "number", "estimate the right camera's pose instead of the left's")
    threshold: float = param(3.0, "image", "RANSAC's reprojection threshold", gt=0, le=1000)
    min_corners: int = param(6, "number", "fewest corners a trial needs to attempt a pose", ge=4, le=1000)
    min_inliers: int = param(5, "number", "fewest RANSAC inliers for a pose to count as solved", ge=4, le=1000)


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle of a rotation matrix, in degrees (robust near 0 and 180)."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    s = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return float(np.degrees(np.arctan2(s, c)))


class PnP(Measure):
    name = "pnp"
    Params = PnPParams
    statistics = ("rotation_error", "position_error", "solved", "corners")
    weights = {"rotation_error": "solved", "position_error": "solved"}
    units = {"rotation_error": "deg", "position_error": "m", "solved": "", "corners": ""}
    doc = __doc__

    @classmethod
    def prepare(cls, p: PnPParams, run) -> dict:
        """The world's corners by feature id (the 3D points PnP is given)."""
        world = run.world
        return {int(f): np.asarray(x, dtype=np.float64) for f, x in zip(world.corner_fid, world.corners, strict=True)}

    @classmethod
    def measure(cls, p: PnPParams, corners3d: dict, pose, disturbed: dict, n_trials: int) -> dict:
        import cv2

        out = {k: np.zeros(n_trials) for k in cls.statistics}
        side = "right" if p.right else "left"
        view = getattr(pose, side)
        s = disturbed.get(side)
        if view is None or s is None:
            return out
        cam = view.camera
        K = np.array([[cam.f * cam.ax, 0.0, cam.cx], [0.0, cam.f * cam.ay, cam.cy], [0.0, 0.0, 1.0]])
        dist = np.array([cam.k1, cam.k2, cam.p1, cam.p2], dtype=np.float64)
        centre_true = -view.R_cw.T @ view.t_cw
        order = np.argsort(s.corner_trial, kind="stable")
        trials, first = np.unique(s.corner_trial[order], return_index=True)
        bounds = np.append(first, len(order))
        for t, a, b in zip(trials, bounds[:-1], bounds[1:], strict=True):
            rows = order[a:b]
            fids = s.corner_fid[rows]
            known = np.array([int(f) in corners3d for f in fids], dtype=bool)
            rows, fids = rows[known], fids[known]
            out["corners"][t] = len(rows)
            if len(rows) < p.min_corners:
                continue
            obj = np.stack([corners3d[int(f)] for f in fids])
            img = np.ascontiguousarray(s.corners[rows], dtype=np.float64)
            ok, rvec, tvec, inliers = cv2.solvePnPRansac(
                obj, img, K, dist, reprojectionError=p.threshold, iterationsCount=200, confidence=0.999,
                flags=cv2.SOLVEPNP_EPNP)
            if not ok or inliers is None or len(inliers) < p.min_inliers:
                continue
            inl = inliers.ravel()
            ok, rvec, tvec = cv2.solvePnP(obj[inl], img[inl], K, dist, rvec, tvec, useExtrinsicGuess=True,
                                          flags=cv2.SOLVEPNP_ITERATIVE)
            if not ok or not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
                continue
            R_est = cv2.Rodrigues(rvec)[0]
            out["solved"][t] = 1.0
            out["rotation_error"][t] = rotation_angle_deg(R_est @ view.R_cw.T)
            out["position_error"][t] = float(np.linalg.norm(-R_est.T @ tvec.ravel() - centre_true))
        return out
