"""A triangle mesh as the paper's features: crease lines, rims (ellipses), silhouettes, corners, faces.

- Vertices closer than MERGE of the mesh's size are one vertex (STL repeats them); triangles of no area
  are dropped (and counted).
- An edge is sharp when its two triangles' normals differ by more than the crease angle (the normals
  compared with the edge's winding, so a mesh wound inconsistently still reads right), when it has one
  triangle (a boundary) or more than two (non-manifold). Sharp edges are features, nothing else: the
  diagonals of a triangulated planar face are never sharp.
- A closed loop of sharp edges with at least RIM_MIN vertices, planar and on an ellipse to RIM_TOL of its
  size, is a rim: an `ellipse`. A smooth region (triangles joined by edges that are not sharp) whose
  vertices all lie on two rims, or on one rim and one apex vertex, is the side of a cylinder or cone: a
  `silhouette` between them (an apex is an ellipse of radius APEX_RADIUS).
- Other sharp edges form chains between nodes (vertices where other than two meet, or where the chain
  turns by more than CORNER_TURN); a chain whose points are collinear to COLLINEAR of its length is a
  `line`, otherwise a `polyline` through its turning points.
- Corners: vertices where three or more sharp edges meet, or two at a turn sharper than CORNER_TURN,
  joined to the lines and polylines that end there.
- A planar region (normals within FLAT of each other) bounded by one convex loop is a `face`. Every other
  smooth or non-convex triangle is kept as an occluder; smooth regions that are not cylinder or cone
  sides are marked `contour`: their outline is view-dependent (edges between a triangle facing the eye
  and one facing away, `Contours`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

MERGE = 1e-6  # of the bounding box's diagonal: vertices this close are one (20 bits an axis: one int64 key)
AREA = 1e-12  # of the diagonal squared: a triangle with less area is degenerate
RIM_MIN = 12  # vertices a closed loop needs to be read as a rim (a square or an octagon is not a circle)
RIM_TOL = 0.01  # of the rim's mean radius: how far its vertices may be off the fitted ellipse or plane
COLLINEAR = 1e-6  # of a chain's length: points this far off its line are still on it
CORNER_TURN = math.radians(30)  # a chain turning more than this at a vertex has a corner there
FLAT = math.radians(0.01)  # normals of one planar region differ by at most this
APEX_RADIUS = 1e-6  # metres: the rim of a cone's apex


@dataclass
class MeshFeatures:
    """Features found in a mesh, in its (scaled, turned) frame; names are assigned by the caller."""

    lines: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    polylines: list[np.ndarray] = field(default_factory=list)  # (k, 3) points, open
    ellipses: list[dict] = field(default_factory=list)  # centre, normal, axis, a, b
    silhouettes: list[tuple[int, int]] = field(default_factory=list)  # indices into ellipses
    corners: list[tuple[np.ndarray, list[tuple[str, int]]]] = field(default_factory=list)  # at, [(kind, index)]
    faces: list[np.ndarray] = field(default_factory=list)  # (k, 3) convex planar polygons
    vertices: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    occluders: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), int))  # triangles kept as occluders
    contour: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # per occluder: a smooth surface's
    degenerate: int = 0  # triangles dropped for having no area
    nonmanifold: int = 0  # edges with more than two triangles


def merge_vertices(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices closer than MERGE of the size made one, and F re-indexed."""
    size = float(np.linalg.norm(np.ptp(V, axis=0))) or 1.0
    q = np.round((V - V.min(axis=0)) / (MERGE * size)).astype(np.int64)  # each < 2^20
    _, first, inverse = np.unique((q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2], return_index=True,
                                  return_inverse=True)
    return V[first], inverse.reshape(-1)[F]


def features(V: np.ndarray, F: np.ndarray, crease: float) -> MeshFeatures:
    """The features of the mesh (V (n, 3), F (m, 3)) with crease angle `crease` (radians)."""
    V, F = merge_vertices(np.asarray(V, float), np.asarray(F, np.int64))
    size = float(np.linalg.norm(np.ptp(V, axis=0))) or 1.0
    N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    area2 = np.linalg.norm(N, axis=1)
    ok = (area2 > 2 * AREA * size * size) & (F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])
    out = MeshFeatures(degenerate=int((~ok).sum()))
    F, N = F[ok], N[ok] / area2[ok, None]
    out.vertices = V
    if len(F) == 0:
        return out
    # edges: (m * 3) directed, their undirected id, and the triangles of each edge
    d = np.stack([F, np.roll(F, -1, axis=1)], axis=2).reshape(-1, 2)
    edges, eid, count = _edges(d, len(V))
    tri = np.repeat(np.arange(len(F)), 3)
    order = np.argsort(eid, kind="stable")
    start = np.concatenate([[0], np.cumsum(count)])
    sharp = count != 2
    out.nonmanifold = int((count > 2).sum())
    two = np.flatnonzero(count == 2)
    i0, i1 = order[start[two]], order[start[two] + 1]
    same_way = (d[i0] == d[i1]).all(axis=1)  # wound inconsistently: one normal is flipped
    cos = (N[tri[i0]] * N[tri[i1]]).sum(1) * np.where(same_way, -1.0, 1.0)
    sharp[two] = cos < math.cos(crease)
    # smooth regions: triangles joined through edges that are not sharp
    region = _components(len(F), tri[i0][~sharp[two]], tri[i1][~sharp[two]])
    chains = _chains(edges[sharp], len(V))
    rims, rest = [], []
    for loop, closed in chains:
        fit = _rim(V[loop[:-1]], size) if closed and len(loop) - 1 >= RIM_MIN else None
        if fit is not None:
            fit["verts"] = set(loop[:-1].tolist())
            rims.append(fit)
        else:
            rest.append((loop, closed))
    out.ellipses = [{k: r[k] for k in ("centre", "normal", "axis", "a", "b")} for r in rims]
    # sides of cylinders and cones: smooth regions all of whose vertices are on two rims (or a rim and an apex)
    n_region = int(region.max()) + 1
    ruled = np.zeros(n_region, bool)
    # each region's triangles, ascending, as slices of one sort (a scan of all triangles a region was quadratic:
    # a soup of 200,000 triangles is 200,000 regions); flat: every normal within FLAT of its first triangle's
    by_region = np.argsort(region, kind="stable")
    first = np.concatenate([[0], np.cumsum(np.bincount(region, minlength=n_region))])
    tilted = np.abs((N * N[by_region[first[:-1]]][region]).sum(1)) < math.cos(FLAT)
    flat = np.bincount(region, weights=tilted, minlength=n_region) == 0
    for g in np.flatnonzero(~flat):
        tris = by_region[first[g]:first[g + 1]]
        verts = set(np.unique(F[tris]).tolist())
        on = [k for k, r in enumerate(rims) if verts & r["verts"]]
        left = verts.difference(*(rims[k]["verts"] for k in on)) if on else verts
        if len(on) == 2 and not left:
            out.silhouettes.append((on[0], on[1]))
            ruled[g] = True
        elif len(on) == 1 and len(left) == 1:
            apex = V[next(iter(left))]
            r = rims[on[0]]
            out.ellipses.append({"centre": apex, "normal": r["normal"], "axis": r["axis"],
                                 "a": APEX_RADIUS, "b": APEX_RADIUS})
            out.silhouettes.append((on[0], len(out.ellipses) - 1))
            ruled[g] = True
    # faces: planar regions bounded by one convex loop (a region of one triangle: the triangle, unless a sliver)
    face = np.zeros(n_region, bool)
    single = flat & (np.diff(first) == 1)
    lone = _triangle_faces(V, F[by_region[first[:-1][single]]])
    for g, tri in zip(np.flatnonzero(single), lone, strict=True):
        face[g] = tri is not None
    lone_of = dict(zip(np.flatnonzero(single).tolist(), lone, strict=True))
    for g in np.flatnonzero(flat).tolist():
        tris = by_region[first[g]:first[g + 1]]
        poly = lone_of[g] if g in lone_of else _convex_boundary(V, F[tris], N[tris[0]])
        if poly is not None:
            out.faces.append(poly)
            face[g] = True
    keep = ~ruled[region] & ~face[region]
    out.occluders = F[keep]
    out.contour = ~flat[region[keep]]
    _lines_and_corners(V, rest, out)
    return out


def as_nodes(found: MeshFeatures, file: str) -> dict[str, list]:
    """The scene's nodes of the features, keyed as a Model's fields; names are kind and number (edge1,
    curve1, rim1, side1, corner1, face1) and `surface` for the triangles kept as occluders."""
    from wiredsl.scene import Corner, Ellipse, Face, Line, Polyline, Silhouette, Surface

    def vec(p) -> tuple[float, float, float]:
        return (float(p[0]), float(p[1]), float(p[2]))

    lines = [Line(name=f"edge{i + 1}", start=vec(a), end=vec(b)) for i, (a, b) in enumerate(found.lines)]
    polylines = [Polyline(name=f"curve{i + 1}", points=[vec(p) for p in P]) for i, P in enumerate(found.polylines)]
    ellipses = [Ellipse(name=f"rim{i + 1}", centre=vec(e["centre"]), normal=vec(e["normal"]), axis=vec(e["axis"]),
                        a=e["a"], b=e["b"]) for i, e in enumerate(found.ellipses)]
    silhouettes = [Silhouette(name=f"side{i + 1}", ellipses=(f"rim{a + 1}", f"rim{b + 1}"))
                   for i, (a, b) in enumerate(found.silhouettes)]
    ref = {"line": "edge", "polyline": "curve"}
    corners = [Corner(name=f"corner{i + 1}", at=vec(p), joins=[f"{ref[k]}{j + 1}" for k, j in refs])
               for i, (p, refs) in enumerate(found.corners)]
    faces = [Face(name=f"face{i + 1}", vertices=[vec(p) for p in P]) for i, P in enumerate(found.faces)]
    surfaces = []
    if len(found.occluders):
        used, F = np.unique(found.occluders, return_inverse=True)
        surfaces.append(Surface.model_construct(  # checked already: built from lists, not validated point by point
            name="surface", file=file, vertices=list(map(tuple, found.vertices[used].tolist())),
            triangles=list(map(tuple, F.reshape(-1, 3).tolist())), contour=np.flatnonzero(found.contour).tolist()))
    return {"lines": lines, "polylines": polylines, "ellipses": ellipses, "silhouettes": silhouettes,
            "corners": corners, "faces": faces, "surfaces": surfaces}


def _edges(d: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Undirected edges (E, 2) of directed ones d (k, 2) over n vertices, the edge of each, and their counts."""
    key = np.minimum(d[:, 0], d[:, 1]) * n + np.maximum(d[:, 0], d[:, 1])
    u, inv, count = np.unique(key, return_inverse=True, return_counts=True)
    return np.column_stack([u // n, u % n]), inv.reshape(-1), count


def _components(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Connected-component label (0, 1, ...) of each of n nodes joined by the pairs (a, b)."""
    label = np.arange(n)
    while True:
        m = np.minimum(label[a], label[b])
        new = label.copy()
        for idx in (a, b, label[a], label[b]):  # the nodes and their roots take the smaller label
            np.minimum.at(new, idx, m)
        while not np.array_equal(new, new[new]):  # pointer jumping: every node straight to its root
            new = new[new]
        if np.array_equal(new, label):
            break
        label = new
    return np.unique(label, return_inverse=True)[1].reshape(-1)


def _chains(E: np.ndarray, n: int) -> list[tuple[np.ndarray, bool]]:
    """Maximal chains of the edges E (k, 2) through vertices of degree 2: (vertex path, closed)."""
    if len(E) == 0:
        return []
    # vertices numbered within E (a count over all n vertices for each small region's loop was quadratic)
    verts, E = np.unique(E, return_inverse=True)
    E = E.reshape(-1, 2)
    deg = np.bincount(E.ravel())
    adj: dict[int, list[int]] = {}
    for k, (a, b) in enumerate(E.tolist()):
        adj.setdefault(a, []).append(k)
        adj.setdefault(b, []).append(k)
    used = np.zeros(len(E), bool)
    out = []

    def walk(v: int, k: int) -> list[int]:
        path = [v]
        while True:
            used[k] = True
            a, b = E[k]
            v = int(b if a == v else a)
            path.append(v)
            if deg[v] != 2:
                return path
            nxt = [j for j in adj[v] if not used[j]]
            if not nxt:
                return path
            k = nxt[0]

    for v in np.flatnonzero((deg != 2) & (deg > 0)).tolist():
        for k in adj[v]:
            if not used[k]:
                out.append((np.array(walk(v, k)), False))
    for k in np.flatnonzero(~used).tolist():  # the rest are closed loops
        if not used[k]:
            path = walk(int(E[k, 0]), k)
            out.append((np.array(path), path[0] == path[-1]))
    return [(verts[path], closed) for path, closed in out]


def _plane(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid, unit normal and an orthonormal in-plane basis (2, 3) of points P (k, 3)."""
    c = P.mean(axis=0)
    _, _, vt = np.linalg.svd(P - c)
    return c, vt[2], vt[:2]


def _rim(P: np.ndarray, size: float) -> dict | None:
    """The ellipse through the loop P (k, 3), or None when the loop is not planar and elliptic to RIM_TOL."""
    c, n, B = _plane(P)
    xy = (P - c) @ B.T
    scale = float(np.sqrt((xy * xy).sum(1).mean()))
    if scale <= 1e-9 * size or np.abs((P - c) @ n).max() > RIM_TOL * scale:
        return None
    x, y = xy[:, 0] / scale, xy[:, 1] / scale
    # conic A x^2 + B xy + C y^2 + D x + E y = 1
    M = np.column_stack([x * x, x * y, y * y, x, y])
    coef, *_ = np.linalg.lstsq(M, np.ones(len(x)), rcond=None)
    A, Bc, C, D, E = coef
    Q = np.array([[A, Bc / 2], [Bc / 2, C]])
    w, vec = np.linalg.eigh(Q)
    if w.min() <= 0:
        return None
    centre2 = np.linalg.solve(2 * Q, -np.array([D, E]))
    k = 1 + centre2 @ Q @ centre2
    if k <= 0:
        return None
    radii = np.sqrt(k / w)  # along vec[:, 0] (larger radius: smaller eigenvalue) and vec[:, 1]
    rel = np.column_stack([x, y]) - centre2
    rho = np.sqrt(np.einsum("ki,ij,kj->k", rel, Q, rel) / k)  # 1 on the ellipse
    if np.abs(rho - 1).max() > RIM_TOL:
        return None
    # the loop must go once round the centre, not fold back
    ang = np.unwrap(np.arctan2(rel[:, 1], rel[:, 0]))
    turn = abs(ang[-1] - ang[0] + (np.angle(np.exp(1j * (ang[0] - ang[-1])))))
    if abs(turn - 2 * math.pi) > 0.5:
        return None
    axis = vec[:, 0] @ B
    centre = c + (centre2 * scale) @ B
    a, b = radii * scale
    if abs(a - b) <= RIM_TOL * a:  # a circle: the axis is the plane's first direction, cleanly
        a = b = float((a + b) / 2)
    axis = axis - (axis @ n) * n
    return {"centre": centre, "normal": n, "axis": axis / np.linalg.norm(axis), "a": float(a), "b": float(b)}


def _triangle_faces(V: np.ndarray, F: np.ndarray) -> list[np.ndarray | None]:
    """`_convex_boundary` of each triangle F (k, 3) alone, at once: its corners (3, 3), or None for a sliver
    (a corner within COLLINEAR of the length from its neighbours' line, which `_drop_collinear` drops)."""
    P = V[F]  # (k, 3, 3): a, b, c
    length = np.linalg.norm(P[:, 1] - P[:, 0], axis=1) + np.linalg.norm(P[:, 2] - P[:, 1], axis=1)
    tol = COLLINEAR * np.where(length > 0, length, 1.0)
    sliver = np.zeros(len(F), bool)
    for j in range(3):  # corner j against the line through the other two
        A, X, B = P[:, (j - 1) % 3], P[:, j], P[:, (j + 1) % 3]
        ab = B - A
        off = np.linalg.norm(np.cross(X - A, ab), axis=1) / np.maximum(np.linalg.norm(ab, axis=1), 1e-300)
        sliver |= (off <= tol) & (((X - A) * ab).sum(1) >= 0) & (((B - X) * ab).sum(1) >= 0)
    return [None if bad else tri for tri, bad in zip(P, sliver, strict=True)]


def _convex_boundary(V: np.ndarray, F: np.ndarray, normal: np.ndarray) -> np.ndarray | None:
    """The polygon bounding the planar triangles F, when it is one convex loop; else None."""
    d = np.stack([F, np.roll(F, -1, axis=1)], axis=2).reshape(-1, 2)
    _, inv, cnt = _edges(d, len(V))
    bnd = d[cnt[inv] == 1]
    chains = _chains(bnd, len(V))
    if len(chains) != 1 or not chains[0][1]:
        return None
    loop = chains[0][0][:-1]
    P = _drop_collinear(V[loop], closed=True)
    if P is None or len(P) < 3:
        return None
    e = np.roll(P, -1, axis=0) - P
    turn = np.cross(e, np.roll(e, -1, axis=0)) @ normal
    if not ((turn > 0).all() or (turn < 0).all()):
        return None
    return P


def _drop_collinear(P: np.ndarray, closed: bool) -> np.ndarray | None:
    """P without the points that lie on the line through their neighbours (to COLLINEAR of the length).

    One pass with a stack (linear: the old restart after each drop was quadratic, 15 s for a 3,000-point
    boundary): a kept point is dropped when it lies between the one before it and the next, which is then
    checked again against the one before; a closed chain's ends are checked across the seam last."""
    if len(P) < 3:  # nothing between two ends
        return P
    length = float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum()) or 1.0
    tol = COLLINEAR * length

    def between(a: int, p: int, b: int) -> bool:
        A, X, B = P[a], P[p], P[b]
        ab = B - A
        off = np.linalg.norm(np.cross(X - A, ab)) / max(np.linalg.norm(ab), 1e-300)
        return bool(off <= tol and (X - A) @ ab >= 0 and (B - X) @ ab >= 0)

    keep: list[int] = []
    for i in range(len(P)):
        while len(keep) >= 2 and between(keep[-2], keep[-1], i):
            keep.pop()
        keep.append(i)
    if closed:  # across the seam: the last kept points, then the first ones, against their wrapped neighbours
        start = 0
        while len(keep) - start > 2:
            if between(keep[-2], keep[-1], keep[start]):
                keep.pop()
            elif between(keep[-1], keep[start], keep[start + 1]):
                start += 1
            else:
                break
        keep = keep[start:]
    return P[keep]


def _lines_and_corners(V: np.ndarray, chains: list[tuple[np.ndarray, bool]], out: MeshFeatures) -> None:
    """Lines and polylines of the sharp chains (split at sharp turns) and the corners where they meet."""
    ends: dict[int, list[tuple[str, int]]] = {}
    sharp_turns: set[int] = set()
    for path, closed in chains:
        P = V[path]
        u = np.diff(P, axis=0)  # the turn at every inner vertex at once (a soup has 200,000 chains)
        norm = np.sqrt((u * u).sum(1))
        cosang = (u[:-1] * u[1:]).sum(1) / np.maximum(norm[:-1] * norm[1:], 1e-300)
        turns = (np.flatnonzero(cosang < math.cos(CORNER_TURN)) + 1).tolist()
        sharp_turns.update(path[turns].tolist())
        cut = [0, *turns, len(path) - 1]
        if closed and len(cut) == 2:  # a loop with no corner: one closed polyline, cut where it starts
            cut = [0, (len(path) - 1) // 2, len(path) - 1]
        for s, e in zip(cut[:-1], cut[1:], strict=True):
            piece = _drop_collinear(P[s:e + 1], closed=False)
            if len(piece) == 2:
                out.lines.append((piece[0], piece[1]))
                ref = ("line", len(out.lines) - 1)
            else:
                out.polylines.append(piece)
                ref = ("polyline", len(out.polylines) - 1)
            for v in (int(path[s]), int(path[e])):
                ends.setdefault(v, []).append(ref)
    deg: dict[int, int] = {}
    for path, _ in chains:
        for v in (int(path[0]), int(path[-1])):
            deg[v] = deg.get(v, 0) + 1
    for v, refs in ends.items():
        if deg.get(v, 0) >= 3 or v in sharp_turns:
            out.corners.append((V[v], list(dict.fromkeys(refs))))


@dataclass(frozen=True)
class Contours:
    """The edges of a smooth surface that can be on its occluding contour: edges between two triangles.

    `seen_from(eye)` gives those between a triangle facing the eye and one facing away (each pair's
    facing compared with the edge's winding, so an inconsistently wound mesh still reads right).
    """

    ends: np.ndarray  # (E, 2, 3) the edges' end points
    normal: np.ndarray  # (E, 2, 3) normals of the edge's two triangles
    origin: np.ndarray  # (E, 2, 3) a vertex of each
    flipped: np.ndarray  # (E,) the two triangles are wound inconsistently

    @classmethod
    def of(cls, V: np.ndarray, F: np.ndarray) -> Contours:
        """Contour candidates of the triangles F (m, 3) over vertices V (n, 3)."""
        d = np.stack([F, np.roll(F, -1, axis=1)], axis=2).reshape(-1, 2)
        _, eid, count = _edges(d, len(V))
        order = np.argsort(eid, kind="stable")
        start = np.concatenate([[0], np.cumsum(count)])
        two = np.flatnonzero(count == 2)
        i0, i1 = order[start[two]], order[start[two] + 1]
        N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        t = np.stack([i0 // 3, i1 // 3], axis=1)
        return cls(V[d[i0]], N[t], V[F[t, 0]], (d[i0] == d[i1]).all(axis=1))

    def seen_from(self, eye: np.ndarray) -> np.ndarray:
        """Boolean (E,): the edges on the occluding contour seen from `eye` (3,)."""
        front = ((eye - self.origin) * self.normal).sum(-1) > 0  # (E, 2)
        return (front[:, 0] != front[:, 1]) ^ self.flipped
