"""Stereo reconstruction error: what the disturbed features give in 3D, against the true world points.

Left and right features are matched by their source, as a perfect matcher
would, so only the simulated errors act. Image points are undistorted with the
nominal camera model and triangulated (linear DLT, as `cv2.triangulatePoints`)
with the nominal rig: the calibration the robot believes, not a trial's
perturbed one.

- Corners: the left and right corner of the same feature. The true point is
  the world corner.
- Lines (straight 3D lines and polyline segments; silhouettes are left out,
  since each camera sees a different contour generator, and so are ellipses):
  each end point of each left stroke is matched along its epipolar line to the
  right stroke of the same source (feature, segment): the point where the
  epipolar line meets the right stroke's line (through its end points, after
  undistortion). When edge loss left several right fragments, the one that
  holds the meeting point (or is nearest to it) is used. End points on lines
  within `band` of the epipolar direction are not reconstructed (a matcher
  cannot place them along the line). The true point is the point of the true
  3D line nearest to the left camera's ray through the end point, so an end
  point anywhere along a fragment is judged by its depth, not by where the
  fragment happens to end.

Per trial: the number of reconstructed points, the mean, median and RMS of
their 3D errors (metres), the fraction above `outlier`, and the mean error of
corners and of line points separately. The error statistics are averages over
points: where a trial reconstructs nothing they are 0 with weight 0 (`weights`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from wiredsl import install_hint
from wiredsl.engine import geometry
from wiredsl.engine import imageset as im
from wiredsl.measures.base import Measure, Params, param, source_key

NEWTON_STEPS = 20


class Stereo3DParams(Params):
    outlier: float = param(0.1, "length", "3D error above which a point is an outlier", gt=0, le=1e6)
    band: float = param(math.radians(5.0), "angle", "line end points within this angle of the epipolar line "
                        "are not reconstructed", ge=0, lt=math.pi / 2)


# ----------------------------------------------------------------------------- geometry

def pixels_to_distorted(uv: np.ndarray, cam) -> np.ndarray:
    """Distorted unit-plane coordinates (n, 2) of pixels (n, 2): the inverse of `plane_to_pixels`."""
    return np.column_stack([(uv[:, 0] - cam.cx) / (cam.f * cam.ax), (uv[:, 1] - cam.cy) / (cam.f * cam.ay)])


def undistort(uv: np.ndarray, cam, engine: str = "auto", limit: float | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted unit-plane coordinates (n, 2) of pixels (n, 2) under `cam`, and which converged (n,).

    Each lens model's own unprojection: radtan by Newton's method on `geometry.distort` from the distorted point
    (`engine`: "numpy", the reference `geometry.undistort_radtan`; "numba", the same operations compiled point by
    point, equal to the last bit, `wiredsl[fast]`; "auto", numba when installed), kept when the residual is below
    1e-12 and it lies inside the fold radius (`limit`: the camera's `geometry.lens_limit`, when the caller has it
    already); the other models by their closed forms (`geometry.pixels_to_rays`), kept inside the lens's valid
    region and less than 90 deg from the axis (a ray at or past 90 deg has no point on the unit plane, so it is
    not triangulated).
    """
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    if not geometry.is_distorted(cam):
        return pixels_to_distorted(uv, cam), np.ones(len(uv), dtype=bool)
    if cam.distortion == "radtan":
        return _undistort_radtan(pixels_to_distorted(uv, cam), cam, engine, limit)
    rays, ok = geometry.pixels_to_rays(uv, cam)
    ok &= rays[:, 2] > math.cos(math.pi / 2 - 1e-6)
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = rays[:, :2] / np.where(ok, rays[:, 2], 1.0)[:, None]
    return np.where(ok[:, None], xy, 0.0), ok


def _undistort_radtan(xd: np.ndarray, cam, engine: str, limit: float | None) -> tuple[np.ndarray, np.ndarray]:
    """`undistort` of a radtan camera's distorted unit-plane points xd (n, 2), on `engine`."""
    lens = tuple(float(getattr(cam, k)) for k in geometry.RADTAN_KEYS)
    limit = geometry.lens_limit(cam) if limit is None else limit
    compiled = kernel() if engine != "numpy" else None
    if engine == "numba" and compiled is None:
        raise ImportError(f"the numba engine needs numba: {install_hint('fast')}")
    if compiled is not None:
        return compiled.undistort_radtan(np.ascontiguousarray(xd), *lens, NEWTON_STEPS, float(limit))
    xy, res = geometry.undistort_radtan(xd, *lens, steps=NEWTON_STEPS)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(xy).all(axis=1) & (res < 1e-12) & (np.hypot(xy[:, 0], xy[:, 1]) < limit)
    return np.where(ok[:, None], xy, 0.0), ok


def kernel():
    """The numba undistortion and triangulation, or None without numba (imported on first use: it is slow to import)."""
    global _KERNEL
    if _KERNEL is None:
        try:
            from wiredsl.measures import stereo3d_kernel
        except ImportError:
            stereo3d_kernel = False
        _KERNEL = stereo3d_kernel
    return _KERNEL or None


_KERNEL = None


def triangulate(P1: np.ndarray, P2: np.ndarray, x1: np.ndarray, x2: np.ndarray, engine: str = "auto"
                ) -> tuple[np.ndarray, np.ndarray]:
    """Linear (DLT) triangulation, as `cv2.triangulatePoints`: points (n, 3) from image points x1, x2 (n, 2)
    under projection matrices P1, P2 ((3, 4) or (n, 3, 4)); and which are finite (not at infinity) (n,).

    The homogeneous point is the right singular vector of the smallest singular value of the DLT's 4 x 4 rows.
    `engine`: "numpy" (the reference: LAPACK's batched SVD), "numba" (`stereo3d_kernel.triangulate`: inverse
    iteration point by point, one-sided Jacobi where it does not converge; the same points to rounding, within
    1e-10 relative, `wiredsl[fast]`), "auto" (numba when installed).
    """
    P1 = np.broadcast_to(P1, (len(x1), 3, 4))
    P2 = np.broadcast_to(P2, (len(x1), 3, 4))
    if len(x1) == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=bool)
    compiled = kernel() if engine != "numpy" else None
    if engine == "numba" and compiled is None:
        raise ImportError(f"the numba engine needs numba: {install_hint('fast')}")
    if compiled is not None:
        c = np.ascontiguousarray
        return compiled.triangulate(c(P1, dtype=float), c(P2, dtype=float), c(x1, dtype=float), c(x2, dtype=float))
    A = np.stack([x1[:, 0, None] * P1[:, 2] - P1[:, 0], x1[:, 1, None] * P1[:, 2] - P1[:, 1],
                  x2[:, 0, None] * P2[:, 2] - P2[:, 0], x2[:, 1, None] * P2[:, 2] - P2[:, 1]], axis=1)
    Xh = np.linalg.svd(A)[2][:, -1]
    w = Xh[:, 3]
    ok = np.abs(w) > 1e-12 * np.abs(Xh[:, :3]).max(axis=1)
    return np.where(ok[:, None], Xh[:, :3] / np.where(ok, w, 1.0)[:, None], 0.0), ok


def nearest_on_line(A: np.ndarray, D: np.ndarray, C: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (n, 3) of lines A + s D nearest to rays C + t r (all (n, 3)); and which are defined
    (the line is not parallel to the ray)."""
    w0 = A - C
    a, b, c = (D * D).sum(1), (D * r).sum(1), (r * r).sum(1)
    d, e = (D * w0).sum(1), (r * w0).sum(1)
    den = a * c - b * b
    ok = den > 1e-12 * a * c
    s = (b * e - c * d) / np.where(ok, den, 1.0)
    return A + s[:, None] * D, ok


# ----------------------------------------------------------------------------- the measure

@dataclass
class Camera:
    """A nominal camera at one pose: the model, P = [R | t] (world -> camera), its centre."""

    model: object
    P: np.ndarray
    centre: np.ndarray
    limit: float  # geometry.lens_limit of the model (its fold radius or largest angle), computed once


@dataclass
class Prepared:
    cameras: dict  # (pose index, side) -> Camera
    n_features: int
    corner_of: np.ndarray  # feature id -> row of world.corners, -1 if not a corner
    line_key: np.ndarray  # sorted keys (fid, segment) of the straight world segments
    line_rows: np.ndarray  # world.lines row of each key
    straight: np.ndarray  # feature id -> line or polyline
    lines: np.ndarray  # world.lines (n, 2, 3)
    corners: np.ndarray


class Stereo3D(Measure):
    name = "stereo3d"
    Params = Stereo3DParams
    statistics = ("points", "error_mean", "error_median", "error_rms", "outliers",
                  "corners", "corner_error", "line_points", "line_error")
    pooled = True  # each trial's values from its own features only
    weights = {"error_mean": "points", "error_median": "points", "error_rms": "points", "outliers": "points",
               "corner_error": "corners", "line_error": "line_points"}
    units = {"points": "count", "error_mean": "m", "error_median": "m", "error_rms": "m", "outliers": "fraction",
             "corners": "count", "corner_error": "m", "line_points": "count", "line_error": "m"}
    doc = __doc__

    @classmethod
    def prepare(cls, p: Stereo3DParams, run) -> Prepared:
        scene, w = run.scene, run.world
        cameras = {}
        for result in run.ideal():
            for side, mount in (("left", scene.rig.left), ("right", scene.rig.right)):
                R, t = geometry.camera_from_world(result.pose, mount.rotation, mount.position)
                model = scene.camera(mount.camera)
                cameras[(result.index, side)] = Camera(model, np.column_stack([R, t]), -R.T @ t,
                                                       geometry.lens_limit(model))
        corner_of = np.full(w.n_features, -1)
        corner_of[w.corner_fid] = np.arange(len(w.corner_fid))
        keys = source_key(w.line_fid, w.line_segment)
        order = np.argsort(keys, kind="stable")
        straight = np.array([k in ("line", "polyline") for k in w.feature_kind], dtype=bool)
        return Prepared(cameras, w.n_features, corner_of, keys[order], order, straight, w.lines, w.corners)

    @classmethod
    def measure(cls, p: Stereo3DParams, prep: Prepared, pose, disturbed: dict[str, im.ImageSet],
                n_trials: int) -> dict[str, np.ndarray]:
        err_c = trial_c = err_l = trial_l = np.zeros(0)
        if "left" in disturbed and "right" in disturbed:
            left, right = prep.cameras[(pose.index, "left")], prep.cameras[(pose.index, "right")]
            err_c, trial_c = _corners(prep, left, right, disturbed["left"], disturbed["right"])
            err_l, trial_l = _lines(p, prep, left, right, disturbed["left"], disturbed["right"])
        return summarise(np.concatenate([err_c, err_l]), np.concatenate([trial_c, trial_l]).astype(int),
                         err_c, trial_c.astype(int), err_l, trial_l.astype(int), n_trials, p.outlier)


def _corners(prep: Prepared, left: Camera, right: Camera, sl: im.ImageSet, sr: im.ImageSet):
    """3D errors and trials of the corners seen in both images."""
    F = prep.n_features
    kl = sl.corner_trial.astype(np.int64) * F + sl.corner_fid
    kr = sr.corner_trial.astype(np.int64) * F + sr.corner_fid
    _, il, ir = np.intersect1d(kl, kr, return_indices=True)
    xl, okl = undistort(sl.corners[il], left.model, limit=left.limit)
    xr, okr = undistort(sr.corners[ir], right.model, limit=right.limit)
    X, ok = triangulate(left.P, right.P, xl, xr)
    ok &= okl & okr
    truth = prep.corners[prep.corner_of[sl.corner_fid[il]]]
    return np.linalg.norm(X - truth, axis=1)[ok], sl.corner_trial[il][ok]


def _ends(s: im.ImageSet, straight: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Strokes of straight 3D features (indices), and their first and last vertices."""
    k = np.flatnonzero(straight[s.fid] & (s.counts >= 2))
    return k, s.pts[s.start[k]], s.pts[s.start[k + 1] - 1]


def _lines(p: Stereo3DParams, prep: Prepared, left: Camera, right: Camera, sl: im.ImageSet, sr: im.ImageSet):
    """3D errors and trials of the left strokes' end points matched along epipolar lines in the right image."""
    kl, a, b = _ends(sl, prep.straight)
    kr, ra, rb = _ends(sr, prep.straight)
    if len(kl) == 0 or len(kr) == 0:
        return np.zeros(0), np.zeros(0)
    # every left end point against every right stroke of the same trial and source
    stroke = np.concatenate([kl, kl])
    xl, okl = undistort(np.concatenate([a, b]), left.model, limit=left.limit)
    pa, oka = undistort(ra, right.model, limit=right.limit)
    pb, okb = undistort(rb, right.model, limit=right.limit)
    good = oka & okb & (np.linalg.norm(pb - pa, axis=1) > 0)
    kr, pa, pb = kr[good], pa[good], pb[good]
    T = max(int(sl.trial.max(initial=0)), int(sr.trial.max(initial=0))) + 1
    key_l = source_key(sl.fid[stroke], sl.segment[stroke]) * T + sl.trial[stroke]
    key_r = source_key(sr.fid[kr], sr.segment[kr]) * T + sr.trial[kr]
    order = np.argsort(key_r, kind="stable")
    key_r, kr, pa, pb = key_r[order], kr[order], pa[order], pb[order]
    lo, hi = np.searchsorted(key_r, key_l, "left"), np.searchsorted(key_r, key_l, "right")
    n = np.where(okl, hi - lo, 0)
    e = np.repeat(np.arange(len(key_l)), n)  # end point of each candidate pair
    c = np.repeat(lo, n) + (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n))  # right stroke of each pair
    # the epipolar line of each left end point in the right camera's unit plane: E x, E = [t]x R
    R_l, t_l, R_r, t_r = left.P[:, :3], left.P[:, 3], right.P[:, :3], right.P[:, 3]
    R = R_r @ R_l.T
    t = t_r - R @ t_l
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
    x1 = np.column_stack([xl, np.ones(len(xl))])
    epi = (x1 @ E.T)[e]
    d = pb[c] - pa[c]
    # meeting point pa + s d with epi . (pa + s d, 1) = 0
    num = -(epi[:, 0] * pa[c, 0] + epi[:, 1] * pa[c, 1] + epi[:, 2])
    den = epi[:, 0] * d[:, 0] + epi[:, 1] * d[:, 1]
    # sine of the angle between the right stroke and the epipolar line (direction (-epi_y, epi_x))
    scale = np.hypot(epi[:, 0], epi[:, 1]) * np.linalg.norm(d, axis=1)
    usable = np.abs(den) > (math.sin(p.band) + 1e-15) * scale  # (the left point is not the epipole: scale > 0)
    s = num / np.where(usable, den, 1.0)
    outside = np.maximum(np.maximum(-s, s - 1.0), 0.0) * np.linalg.norm(d, axis=1)
    outside = np.where(usable, outside, np.inf)
    # per end point, the candidate nearest to holding the meeting point
    if len(e) == 0:
        return np.zeros(0), np.zeros(0)
    order = np.lexsort((outside, e))
    first = order[np.flatnonzero(np.concatenate([[True], e[order][1:] != e[order][:-1]]))]
    first = first[np.isfinite(outside[first])]
    end = e[first]
    xr = pa[c[first]] + s[first, None] * d[first]
    X, ok = triangulate(left.P, right.P, xl[end], xr)
    # the true point: where the true 3D line passes nearest the left ray through the end point
    rows = prep.line_rows[np.searchsorted(prep.line_key, source_key(sl.fid[stroke[end]], sl.segment[stroke[end]]))]
    A, B = prep.lines[rows, 0], prep.lines[rows, 1]
    ray = x1[end] @ R_l  # R_l^T (x, y, 1): the ray's direction in the world
    truth, defined = nearest_on_line(A, B - A, np.broadcast_to(left.centre, A.shape), ray)
    ok &= defined
    return np.linalg.norm(X - truth, axis=1)[ok], sl.trial[stroke[end]][ok]


def summarise(err, trial, err_c, trial_c, err_l, trial_l, n_trials: int, outlier: float) -> dict[str, np.ndarray]:
    """Per-trial statistics of 3D errors; 0 where a trial has no point (their weight, the count, is 0)."""
    count = np.bincount(trial, minlength=n_trials).astype(float)
    some = count > 0
    per = np.where(some, count, 1.0)
    order = np.lexsort((err, trial))
    start = np.concatenate([[0], np.cumsum(count)]).astype(int)[:-1]
    c = count.astype(int)
    sorted_err = err[order]
    mid_lo = np.clip(start + (c - 1) // 2, 0, max(len(err) - 1, 0))
    mid_hi = np.clip(start + c // 2, 0, max(len(err) - 1, 0))
    median = 0.5 * (sorted_err[mid_lo] + sorted_err[mid_hi]) if len(err) else np.zeros(n_trials)
    nc = np.bincount(trial_c, minlength=n_trials).astype(float)
    nl = np.bincount(trial_l, minlength=n_trials).astype(float)
    return {
        "points": count,
        "error_mean": np.bincount(trial, weights=err, minlength=n_trials) / per,
        "error_median": np.where(some, median, 0.0),
        "error_rms": np.sqrt(np.bincount(trial, weights=err * err, minlength=n_trials) / per),
        "outliers": np.bincount(trial, weights=(err > outlier).astype(float), minlength=n_trials) / per,
        "corners": nc,
        "corner_error": np.bincount(trial_c, weights=err_c, minlength=n_trials) / np.maximum(nc, 1.0),
        "line_points": nl,
        "line_error": np.bincount(trial_l, weights=err_l, minlength=n_trials) / np.maximum(nl, 1.0),
    }
