"""The compiled scene as world-frame arrays: what the engine projects.

Every emitted feature (`placement.feature`) gets an integer id; each array row
carries the id of the feature it belongs to, so a visibility list becomes a
boolean mask in one indexing step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from wiredsl.scene import Scene

if TYPE_CHECKING:  # engine.mesh is imported only for a scene with smooth mesh surfaces
    from wiredsl.engine.mesh import Contours


def _empty(shape, dtype=float) -> np.ndarray:
    return np.zeros(shape, dtype=dtype)


@dataclass
class World:
    """World-frame geometry. Shapes: lines (n, 2, 3); ellipses centre/U/V (m, 3), arc (m, 2)."""

    feature_ids: list[str] = field(default_factory=list)  # id -> "placement.feature"
    feature_kind: list[str] = field(default_factory=list)
    line_fid: np.ndarray = field(default_factory=lambda: _empty(0, int))
    line_segment: np.ndarray = field(default_factory=lambda: _empty(0, int))  # in a polyline; -1 for a line
    lines: np.ndarray = field(default_factory=lambda: _empty((0, 2, 3)))
    ell_fid: np.ndarray = field(default_factory=lambda: _empty(0, int))
    ell_c: np.ndarray = field(default_factory=lambda: _empty((0, 3)))
    ell_U: np.ndarray = field(default_factory=lambda: _empty((0, 3)))
    ell_V: np.ndarray = field(default_factory=lambda: _empty((0, 3)))
    ell_arc: np.ndarray = field(default_factory=lambda: _empty((0, 2)))
    ell_full: np.ndarray = field(default_factory=lambda: _empty(0, bool))  # the whole ellipse, not a section
    sil_fid: np.ndarray = field(default_factory=lambda: _empty(0, int))
    sil_pair: np.ndarray = field(default_factory=lambda: _empty((0, 2), int))  # indices into the ellipses
    corner_fid: np.ndarray = field(default_factory=lambda: _empty(0, int))
    corners: np.ndarray = field(default_factory=lambda: _empty((0, 3)))
    face_src: list[str] = field(default_factory=list)
    triangles: np.ndarray = field(default_factory=lambda: _empty((0, 3, 3)))  # occluders (faces, fanned)
    triangle_face: np.ndarray = field(default_factory=lambda: _empty(0, int))  # index into face_src
    contours: list[tuple[int, Contours]] = field(default_factory=list)  # (fid, edges) of smooth mesh surfaces

    @property
    def n_features(self) -> int:
        return len(self.feature_ids)

    def mask(self, visible: set[str] | None) -> np.ndarray:
        """Boolean over feature ids; None means everything is visible."""
        if visible is None:
            return np.ones(self.n_features, dtype=bool)
        return np.array([f in visible for f in self.feature_ids], dtype=bool)


def build_world(scene: Scene) -> World:
    """World-frame arrays of every placement's features."""
    w = World()
    lines, line_fid, line_seg = [], [], []
    ec, eU, eV, earc, efull, efid = [], [], [], [], [], []
    sil_fid, sil_pair = [], []
    corners, corner_fid = [], []
    tris, tri_face = [], []
    for p in scene.placements:
        model = scene.model(p.model)
        R = np.array(p.rotation)
        t = np.array(p.position)

        def to_world(points, R=R, t=t):
            return np.asarray(points, dtype=float) @ R.T + t

        def new_id(name: str, kind: str, placement=p.name) -> int:
            w.feature_ids.append(f"{placement}.{name}")
            w.feature_kind.append(kind)
            return len(w.feature_ids) - 1

        for ln in model.lines:
            lines.append(to_world([ln.start, ln.end]))
            line_fid.append(new_id(ln.name, "line"))
            line_seg.append(-1)
        for pl in model.polylines:
            fid = new_id(pl.name, "polyline")
            pts = to_world(pl.points)
            if pl.closed:
                pts = np.vstack([pts, pts[:1]])
            for i in range(len(pts) - 1):
                lines.append(pts[i:i + 2])
                line_fid.append(fid)
                line_seg.append(i)
        index_of = {}
        for el in model.ellipses:
            index_of[el.name] = len(ec)
            ec.append(to_world([el.centre])[0])
            eU.append(R @ (np.array(el.axis) * el.a))
            eV.append(R @ (np.cross(el.normal, el.axis) * el.b))
            earc.append((el.t0, el.t1))
            efull.append(el.t1 - el.t0 >= 2 * math.pi - 1e-12)
            efid.append(new_id(el.name, "ellipse"))
        for sl in model.silhouettes:
            sil_pair.append((index_of[sl.ellipses[0]], index_of[sl.ellipses[1]]))
            sil_fid.append(new_id(sl.name, "silhouette"))
        for cn in model.corners:
            corners.append(to_world([cn.at])[0])
            corner_fid.append(new_id(cn.name, "corner"))
        for fc in model.faces:
            w.face_src.append(f"{p.name}.{fc.name}")
            v = to_world(fc.vertices)
            for i in range(1, len(v) - 1):  # a fan: faces are convex polygons
                tris.append(np.stack([v[0], v[i], v[i + 1]])[None])
                tri_face.append(len(w.face_src) - 1)
        for sf in model.surfaces:
            w.face_src.append(f"{p.name}.{sf.name}")
            v = to_world(sf.vertices)
            F = np.array(sf.triangles, dtype=int).reshape(-1, 3)
            first = len(tri_face)  # its first triangle's index in w.triangles
            tris.append(v[F])
            tri_face.extend([len(w.face_src) - 1] * len(sf.triangles))
            if sf.contour:  # the outline of its smooth part: a feature of each view (engine/mesh.py)
                from wiredsl.engine.mesh import Contours

                w.contours.append((new_id(sf.name, "contour"), Contours.of(v, F[np.array(sf.contour)], F, first)))
    w.lines = np.array(lines, dtype=float).reshape(-1, 2, 3)
    w.line_fid = np.array(line_fid, dtype=int)
    w.line_segment = np.array(line_seg, dtype=int)
    w.ell_c = np.array(ec, dtype=float).reshape(-1, 3)
    w.ell_U = np.array(eU, dtype=float).reshape(-1, 3)
    w.ell_V = np.array(eV, dtype=float).reshape(-1, 3)
    w.ell_arc = np.array(earc, dtype=float).reshape(-1, 2)
    w.ell_full = np.array(efull, dtype=bool)
    w.ell_fid = np.array(efid, dtype=int)
    w.sil_fid = np.array(sil_fid, dtype=int)
    w.sil_pair = np.array(sil_pair, dtype=int).reshape(-1, 2)
    w.corners = np.array(corners, dtype=float).reshape(-1, 3)
    w.corner_fid = np.array(corner_fid, dtype=int)
    w.triangles = np.concatenate(tris).astype(float) if tris else _empty((0, 3, 3))  # blocks (k, 3, 3)
    w.triangle_face = np.array(tri_face, dtype=int)
    return w


def ellipse_points(c: np.ndarray, U: np.ndarray, V: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Points c + cos(t) U + sin(t) V for per-point ellipse rows: shapes (n, 3) and t (n,)."""
    return c + np.cos(t)[:, None] * U + np.sin(t)[:, None] * V


PHASE_TOL = 1e-9  # radians: a side's rims this close to matched are used as they are (their bytes kept)


def side_ellipses(w: World) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The two ellipses (c, U, V) of every silhouette's side, (S, 3) each, the second one's parameter matched to
    the first's by geometry, so that the ruled surface Ea(th) + s (Eb(th) - Ea(th)) is the cylinder or cone it
    is, not a twisted hyperboloid or an hourglass through the axis.

    Each ellipse is c + U cos th + V sin th; its orientation (U x V) and its start (U) are the declaration's or,
    for a mesh's rims, the fit's, and a side's two rims often come out with opposite normals or other starts
    (issue 37: 21 of the counter's 59 sides). The same curve travelled the first's way round (V -> -V when the
    normals are opposite) and started at the point in the first's start direction about its axis (U projected
    into the second's plane, as x U + y V: the phase atan2(y, x)) is the same ellipse. Only full ellipses are
    re-parameterised (an arc's range is in its own parameter)."""
    a, b = w.sil_pair[:, 0], w.sil_pair[:, 1]
    ca, Ua, Va, cb = w.ell_c[a], w.ell_U[a], w.ell_V[a], w.ell_c[b]
    Ub, Vb = w.ell_U[b].copy(), w.ell_V[b].copy()
    full = w.ell_full[a] & w.ell_full[b]
    flip = full & ((np.cross(Ua, Va) * np.cross(Ub, Vb)).sum(axis=1) < 0)
    Vb[flip] = -Vb[flip]
    nb = np.cross(Ub, Vb)
    nn = (nb * nb).sum(axis=1)
    d = Ua - ((Ua * nb).sum(axis=1) / np.where(nn > 0, nn, 1.0))[:, None] * nb  # a's start in b's plane
    g11, g12, g22 = (Ub * Ub).sum(axis=1), (Ub * Vb).sum(axis=1), (Vb * Vb).sum(axis=1)
    r1, r2 = (d * Ub).sum(axis=1), (d * Vb).sum(axis=1)
    det = g11 * g22 - g12 * g12
    ok = full & (det > 1e-24 * np.maximum(g11 * g22, 1e-300)) & ((d * d).sum(axis=1) > 0)
    x = np.where(ok, g22 * r1 - g12 * r2, 1.0)
    y = np.where(ok, g11 * r2 - g12 * r1, 0.0)
    phi = np.arctan2(y, x)  # (det > 0 scales x and y alike)
    turn = ok & (np.abs(phi) > PHASE_TOL)
    cp, sp = np.cos(phi[turn])[:, None], np.sin(phi[turn])[:, None]
    Ub[turn], Vb[turn] = Ub[turn] * cp + Vb[turn] * sp, Vb[turn] * cp - Ub[turn] * sp
    return ca, Ua, Va, cb, Ub, Vb


def surface_triangles(w: World, segments: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of the ruled surfaces between silhouette ellipse pairs (cylinder and cone sides)."""
    tris, owner = [], []
    t = np.linspace(0.0, 2 * math.pi, segments + 1)
    ca, Ua, Va, cb, Ub, Vb = side_ellipses(w)
    for k in range(len(w.sil_pair)):
        ring_a = ca[k] + np.cos(t)[:, None] * Ua[k] + np.sin(t)[:, None] * Va[k]
        ring_b = cb[k] + np.cos(t)[:, None] * Ub[k] + np.sin(t)[:, None] * Vb[k]
        for i in range(segments):
            tris.append((ring_a[i], ring_a[i + 1], ring_b[i + 1]))
            tris.append((ring_a[i], ring_b[i + 1], ring_b[i]))
            owner += [k, k]
    return np.array(tris, dtype=float).reshape(-1, 3, 3), np.array(owner, dtype=int)
