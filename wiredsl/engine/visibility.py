"""View-dependency: which features are visible from where.

The paper's rule: the view-point of the mesh nearest to the robot selects the
visibility list. Ties (the robot exactly between view-points) go to the
view-point declared first.

Computed visibility: from an eye point, a feature is visible when at least
`threshold` of its sample points (9 along a line or polyline segment, 24 around
an ellipse, the point itself for a corner) can be seen. A sample is seen when
the segment from the eye to it meets no occluder except within RAY_END of its
end. Occluders are the scene's faces and the sides of every silhouette's
cylinder or cone (48 quads around). A silhouette is visible when either of its
ellipses is. View-points are evaluated with the eye at the rig's mean camera
height above the view-point.
"""

from __future__ import annotations

import numpy as np

from wiredsl.engine.world import World, ellipse_points, surface_triangles

THRESHOLD = 0.3
RAY_END = 1e-4  # fraction of the eye-to-sample distance treated as touching the sample
LINE_SAMPLES = 9
ELLIPSE_SAMPLES = 24


def nearest_viewpoint(points: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Index of the nearest view-point (V, 2) to each robot position (P, 2); ties to the lowest index."""
    d2 = ((xy[:, None, :] - points[None, :, :]) ** 2).sum(-1)
    best = d2.min(axis=1, keepdims=True)
    tie = d2 <= best * (1 + 1e-12) + 1e-24  # exactly equal distances, up to rounding
    return tie.argmax(axis=1)


def samples(w: World) -> tuple[np.ndarray, np.ndarray]:
    """Sample points (S, 3) of every feature and the feature id of each."""
    pts, fid = [], []
    if len(w.lines):
        s = (np.arange(LINE_SAMPLES) + 0.5) / LINE_SAMPLES
        P = w.lines[:, 0, None, :] + s[None, :, None] * (w.lines[:, 1] - w.lines[:, 0])[:, None, :]
        pts.append(P.reshape(-1, 3))
        fid.append(np.repeat(w.line_fid, LINE_SAMPLES))
    if len(w.ell_c):
        s = (np.arange(ELLIPSE_SAMPLES) + 0.5) / ELLIPSE_SAMPLES
        t = (w.ell_arc[:, 0, None] + s[None, :] * (w.ell_arc[:, 1] - w.ell_arc[:, 0])[:, None]).ravel()
        rows = np.repeat(np.arange(len(w.ell_c)), ELLIPSE_SAMPLES)
        pts.append(ellipse_points(w.ell_c[rows], w.ell_U[rows], w.ell_V[rows], t))
        fid.append(w.ell_fid[rows])
    if len(w.corners):
        pts.append(w.corners)
        fid.append(w.corner_fid)
    if not pts:
        return np.zeros((0, 3)), np.zeros(0, dtype=int)
    return np.concatenate(pts), np.concatenate(fid)


def occluders(w: World) -> np.ndarray:
    """All occluding triangles (T, 3, 3): faces and silhouette surfaces."""
    surf, _ = surface_triangles(w)
    return np.concatenate([w.triangles, surf]) if len(surf) else w.triangles


def seen(eye: np.ndarray, targets: np.ndarray, tris: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """Whether each target (S, 3) is unoccluded from `eye` (3,) by triangles (T, 3, 3) (Moller-Trumbore)."""
    out = np.ones(len(targets), dtype=bool)
    if len(tris) == 0 or len(targets) == 0:
        return out
    v0 = tris[:, 0]
    e1 = tris[:, 1] - v0
    e2 = tris[:, 2] - v0
    s = eye - v0  # (T, 3)
    for lo in range(0, len(targets), chunk):
        d = targets[lo:lo + chunk] - eye  # (S, 3), the ray is eye + t d with t in (0, 1)
        p = np.cross(d[:, None, :], e2[None, :, :])  # (S, T, 3)
        det = (p * e1[None]).sum(-1)
        ok = np.abs(det) > 1e-14
        with np.errstate(divide="ignore", invalid="ignore"):  # det == 0 rows are masked by `ok`
            inv = 1.0 / det
            u = (p * s[None]).sum(-1) * inv
            q = np.cross(s, e1)  # (T, 3)
            v = (d[:, None, :] * q[None]).sum(-1) * inv
            t = (q[None] * e2[None]).sum(-1) * inv
            hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > RAY_END) & (t < 1 - RAY_END)
        out[lo:lo + chunk] = ~hit.any(axis=1)
    return out


def visible_features(w: World, eyes: np.ndarray, threshold: float = THRESHOLD) -> np.ndarray:
    """Boolean (E, n_features): visibility of every feature from each eye point (E, 3)."""
    pts, fid = samples(w)
    tris = occluders(w)
    out = np.zeros((len(eyes), w.n_features), dtype=bool)
    counts = np.bincount(fid, minlength=w.n_features)
    for i, eye in enumerate(eyes):
        ok = seen(eye, pts, tris)
        frac = np.bincount(fid, weights=ok, minlength=w.n_features) / np.maximum(counts, 1)
        out[i] = frac >= threshold - 1e-12
    # silhouettes follow their ellipses
    for fid_s, (a, b) in zip(w.sil_fid, w.sil_pair, strict=True):
        out[:, fid_s] = out[:, w.ell_fid[a]] | out[:, w.ell_fid[b]]
    return out


def eye_height(scene) -> float:
    """The height from which view-points see: the rig's mean camera height."""
    if scene.rig is None:
        return 1.0
    return (scene.rig.left.position[2] + scene.rig.right.position[2]) / 2


def viewpoint_eyes(scene) -> np.ndarray:
    pts = np.array(scene.viewpoints.points, dtype=float).reshape(-1, 2)
    return np.column_stack([pts, np.full(len(pts), eye_height(scene))])


def as_lists(w: World, names: list[str], vis: np.ndarray) -> dict[str, list[str]]:
    ids = np.array(w.feature_ids, dtype=object)
    return {name: sorted(ids[row].tolist()) for name, row in zip(names, vis, strict=True)}
