"""View-dependency: which features are visible from where.

The paper's rule: the view-point of the mesh nearest to the robot selects the
visibility list. Ties (the robot exactly between view-points) go to the
view-point declared first.

Computed visibility: from an eye point, a feature is visible when at least
`threshold` of its sample points (9 along a line or polyline segment, 24 around
an ellipse, the point itself for a corner) can be seen. A sample is seen when
the segment from the eye to it meets no occluder except within RAY_END of its
end. Occluders are the scene's faces and the sides of every silhouette's
cylinder or cone: the exact surface (a quadric, hit in closed form) when its two
ellipses are similar and parallel, else 48 quads around. A silhouette is visible
when either of its ellipses is. View-points are evaluated with the eye at the
rig's mean camera height above the view-point.

Ray casting works on chunks of (sample, occluder) pairs of at most PAIRS_CAP, so
its temporaries have a fixed size whatever the scene.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wiredsl.engine.world import World, ellipse_points, side_ellipses, surface_triangles

THRESHOLD = 0.3
RAY_END = 1e-4  # fraction of the eye-to-sample distance treated as touching the sample
LINE_SAMPLES = 9
ELLIPSE_SAMPLES = 24
PAIRS_CAP = 1 << 18  # (sample, occluder) pairs tested at once: about 2 MB a temporary


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


@dataclass
class Occluders:
    """Triangles (T, 3, 3), and ruled surfaces between similar parallel ellipses as quadrics.

    A quadric k is the set c + a U + b V + s W with a^2 + b^2 = (1 + g s)^2, 0 <= s <= 1: `to_local`
    (Q, 3, 3) maps X - c to (a, b, s), `origin` (Q, 3) is c and `growth` (Q,) is g (the ellipse b
    is 1 + g times ellipse a; g = 0 a cylinder).
    """

    triangles: np.ndarray
    origin: np.ndarray
    to_local: np.ndarray
    growth: np.ndarray

    def __len__(self) -> int:
        return len(self.triangles) + len(self.origin)

    def spheres(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounding spheres (centres (T + Q, 3), radii): the triangles', then the quadrics'."""
        tc = self.triangles.mean(axis=1) if len(self.triangles) else np.zeros((0, 3))
        tr = np.linalg.norm(self.triangles - tc[:, None], axis=2).max(axis=1) if len(tc) else np.zeros(0)
        M = np.linalg.inv(self.to_local) if len(self.origin) else np.zeros((0, 3, 3))  # columns U, V, W
        W = M[:, :, 2]
        qc = self.origin + W / 2
        reach = np.linalg.norm(M[:, :, 0], axis=1) + np.linalg.norm(M[:, :, 1], axis=1)
        qr = np.linalg.norm(W, axis=1) / 2 + reach * np.maximum(1.0, np.abs(1.0 + self.growth))
        return np.concatenate([tc, qc]), np.concatenate([tr, qr]) * (1 + 1e-9) + 1e-12


def occluders(w: World) -> Occluders:
    """All occluders: faces, the exact sides of cylinders and cones, other silhouette surfaces as triangles."""
    a, b = w.sil_pair[:, 0], w.sil_pair[:, 1]
    ca, Ua, Va, cb, Ub, Vb = side_ellipses(w)  # b's parameter matched to a's: a cylinder's rims are similar
    nu = (Ua * Ua).sum(axis=1)
    ratio = np.where(nu > 0, (Ub * Ua).sum(axis=1) / np.where(nu > 0, nu, 1.0), 0.0)  # Ub = ratio Ua ?
    W = cb - ca
    M = np.stack([Ua, Va, W], axis=-1)
    scale = np.maximum(np.abs(M).max(axis=(1, 2), initial=0.0), 1e-300) if len(M) else np.zeros(0)
    similar = ((np.abs(Ub - ratio[:, None] * Ua).max(axis=1) <= 1e-9 * scale)
               & (np.abs(Vb - ratio[:, None] * Va).max(axis=1) <= 1e-9 * scale)
               & (ratio > 0) & w.ell_full[a] & w.ell_full[b])
    if similar.any():
        det = np.abs(np.linalg.det(M[similar]))
        similar[np.flatnonzero(similar)[det <= 1e-12 * scale[similar] ** 3]] = False  # flat: no side
    q = np.flatnonzero(similar)
    to_local = np.linalg.inv(M[q]) if len(q) else np.zeros((0, 3, 3))
    surf, owner = surface_triangles(w)
    surf = surf[~similar[owner]] if len(surf) else surf
    tris = np.concatenate([w.triangles, surf]) if len(surf) else w.triangles
    return Occluders(tris, ca[q], to_local, ratio[q] - 1.0)


def seen(eye: np.ndarray, targets: np.ndarray, occ, cap: int = PAIRS_CAP, chunk: int = 256) -> np.ndarray:
    """Whether each target (S, 3) is unoccluded from `eye` (3,) by the occluders (or triangles (T, 3, 3)).

    Targets are taken in chunks ordered by direction from the eye; a chunk is tested only against the
    occluders whose bounding spheres lie, seen from the eye, within the chunk's range of directions and
    nearer than its farthest target. That keeps the exact tests to pairs that can hit: about linear in
    the scene's size where the brute force is samples x occluders.
    """
    if not isinstance(occ, Occluders):
        occ = Occluders(occ, np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0))
    out = np.ones(len(targets), dtype=bool)
    if len(occ) == 0 or len(targets) == 0:
        return out
    v = targets - eye
    dist = np.linalg.norm(v, axis=1)
    az, el = _direction(v, dist)
    order = np.lexsort((az, np.floor(el / 0.05)))  # bands of elevation, by azimuth within a band
    centre, radius = occ.spheres()
    w = centre - eye
    D = np.linalg.norm(w, axis=1)
    inside = D <= radius * (1 + 1e-9) + 1e-12  # the eye is in the sphere: every direction
    caz, cel = _direction(w, np.where(D > 0, D, 1.0))
    alpha = np.arcsin(np.clip(radius / np.where(D > 0, D, 1.0), 0.0, 1.0)) + 1e-6
    polar = inside | (np.abs(cel) + alpha >= np.pi / 2 - 1e-6)
    with np.errstate(divide="ignore", invalid="ignore"):
        beta = np.where(polar, np.pi, np.arcsin(np.clip(np.sin(alpha) / np.cos(np.abs(cel)), 0.0, 1.0)) + 1e-6)
    n_tri = len(occ.triangles)
    per = max(1, min(chunk, cap // max(len(occ), 1)))  # targets a chunk
    for lo in range(0, len(targets), per):
        rows = order[lo:lo + per]
        a0, a1, e0, e1 = az[rows].min(), az[rows].max(), el[rows].min(), el[rows].max()
        off = np.abs(np.angle(np.exp(1j * (caz - (a0 + a1) / 2)))) - (a1 - a0) / 2
        near = inside | ((D - radius < dist[rows].max()) & (cel + alpha >= e0) & (cel - alpha <= e1) & (off <= beta))
        pick = np.flatnonzero(near)
        if len(pick) == 0:
            continue
        d = v[rows]  # the ray is eye + t d with t in (0, 1)
        hit = np.zeros(len(rows), dtype=bool)
        tri, quad = pick[pick < n_tri], pick[pick >= n_tri] - n_tri
        for t0 in range(0, len(tri), cap):
            hit |= _hits_triangles(eye, d, occ.triangles[tri[t0:t0 + cap]])
        for q0 in range(0, len(quad), cap):
            q = quad[q0:q0 + cap]
            hit |= _hits_quadrics(eye, d, occ.origin[q], occ.to_local[q], occ.growth[q])
        out[rows] = ~hit
    return out


def _direction(v: np.ndarray, length: np.ndarray):
    """Azimuth and elevation of vectors v (n, 3) of the given lengths."""
    with np.errstate(divide="ignore", invalid="ignore"):
        el = np.arcsin(np.clip(v[:, 2] / np.where(length > 0, length, 1.0), -1.0, 1.0))
    return np.arctan2(v[:, 1], v[:, 0]), el


def _hits_triangles(eye: np.ndarray, d: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Whether rays eye + t d (S, 3), t in (RAY_END, 1 - RAY_END), meet any triangle (Moller-Trumbore)."""
    if len(tris) == 0:
        return np.zeros(len(d), dtype=bool)
    v0 = tris[:, 0]
    e1 = tris[:, 1] - v0
    e2 = tris[:, 2] - v0
    s = eye - v0  # (T, 3)
    q = np.cross(s, e1)  # (T, 3)
    p = np.cross(d[:, None, :], e2[None, :, :])  # (S, T, 3)
    det = (p * e1[None]).sum(-1)
    ok = np.abs(det) > 1e-14
    with np.errstate(divide="ignore", invalid="ignore"):  # det == 0 rows are masked by `ok`
        inv = 1.0 / det
        u = (p * s[None]).sum(-1) * inv
        v = (d @ q.T) * inv
        t = (q * e2).sum(-1)[None] * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > RAY_END) & (t < 1 - RAY_END)
    return hit.any(axis=1)


def _hits_quadrics(eye, d, origin, to_local, growth) -> np.ndarray:
    """Whether rays eye + t d (S, 3), t in (RAY_END, 1 - RAY_END), meet the finite cones or cylinders.

    In the surface's own coordinates (a, b, s) the ray is q0 + t q1 and the surface a^2 + b^2 = (1 + g s)^2,
    0 <= s <= 1: a quadratic in t, solved in closed form.
    """
    q0 = np.einsum("qij,qj->qi", to_local, eye - origin)  # (Q, 3)
    q1 = np.einsum("qij,sj->sqi", to_local, d)  # (S, Q, 3)
    g = growth[None, :]
    r0 = 1.0 + g * q0[None, :, 2]
    r1 = g * q1[..., 2]
    A = q1[..., 0] ** 2 + q1[..., 1] ** 2 - r1 * r1
    B = 2.0 * (q0[None, :, 0] * q1[..., 0] + q0[None, :, 1] * q1[..., 1] - r0 * r1)
    C = (q0[None, :, 0] ** 2 + q0[None, :, 1] ** 2 - r0 * r0) * np.ones_like(A)
    hit = np.zeros(A.shape, dtype=bool)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        disc = B * B - 4.0 * A * C
        sq = np.sqrt(np.maximum(disc, 0.0))
        Q = -0.5 * (B + np.where(B >= 0, sq, -sq))  # stable roots Q / A and C / Q
        lin = np.abs(A) <= 1e-12 * np.maximum(np.abs(B), np.abs(C))
        real = lin | (disc >= 0)
        for t in (np.where(lin, -C / B, Q / A), np.where(lin, np.nan, C / Q)):
            s = q0[None, :, 2] + t * q1[..., 2]
            hit |= real & (t > RAY_END) & (t < 1 - RAY_END) & (s >= 0) & (s <= 1) & (1.0 + g * s >= 0)
    return hit.any(axis=1)


def visible_features(w: World, eyes: np.ndarray, threshold: float = THRESHOLD) -> np.ndarray:
    """Boolean (E, n_features): visibility of every feature from each eye point (E, 3)."""
    pts, fid = samples(w)
    occ = occluders(w)
    out = np.zeros((len(eyes), w.n_features), dtype=bool)
    counts = np.bincount(fid, minlength=w.n_features)
    for i, eye in enumerate(eyes):
        ok = seen(eye, pts, occ)
        frac = np.bincount(fid, weights=ok, minlength=w.n_features) / np.maximum(counts, 1)
        out[i] = frac >= threshold - 1e-12
    # silhouettes follow their ellipses
    for fid_s, (a, b) in zip(w.sil_fid, w.sil_pair, strict=True):
        out[:, fid_s] = out[:, w.ell_fid[a]] | out[:, w.ell_fid[b]]
    # a smooth surface's outline is made for each view (engine/mesh.py), so it is always listed
    for fid_c, _ in w.contours:
        out[:, fid_c] = True
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
