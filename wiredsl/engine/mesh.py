"""A triangle mesh as the paper's features: crease lines, rims (ellipses), silhouettes, corners, faces.

- Vertices closer than MERGE of the mesh's size are one vertex (STL repeats them); triangles of no area
  are dropped (and counted).
- An edge is sharp when its two triangles' normals differ by more than the crease angle (the normals
  compared with the edge's winding, so a mesh wound inconsistently still reads right), when it has one
  triangle (a boundary) or more than two (non-manifold). Sharp edges are features, nothing else: the
  diagonals of a triangulated planar face are never sharp.
- A closed loop of sharp edges with at least RIM_MIN vertices, planar and on an ellipse to RIM_TOL of its
  size, whose edges' middles are also on it to RIM_EDGE of its radius and RIM_EDGE_ABS metres (so that a
  polygon with filleted corners, whose vertices may all be near one circle, keeps its straight sides), is
  a rim: an `ellipse`. The vertices are in metres (the caller scales them). A smooth region (triangles joined by edges
  that are not sharp) whose
  vertices all lie on two rims, or on one rim and one apex vertex, is the side of a cylinder or cone: a
  `silhouette` between them (an apex is an ellipse of radius APEX_RADIUS).
- Other sharp edges form chains between nodes (vertices where other than two meet, or where the chain
  turns by more than CORNER_TURN); a chain whose points are collinear to COLLINEAR of its length is a
  `line`, otherwise a `polyline` through its turning points.
- Lines and polylines shorter than `shortest` are left out; a scan keeps at most BUDGET of them (the largest
  length x dihedral angle), a CAD part every one (`budget auto`). A mesh is a CAD part when at least CAD_PLANAR
  of its interior edge length lies between triangles whose normals agree to PLANAR_EDGE (the diagonals of its
  tessellated flats and ruled surfaces), else a scan (`is_scan`).
- Corners: vertices where three or more kept lines and polylines meet, or two at a turn sharper than CORNER_TURN,
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
RIM_EDGE = 0.04  # of the rim's mean radius: how far the middle of an edge may be off the fitted ellipse (the
#   sagitta of a regular 12-gon, the coarsest rim, is 3.4%; a filleted hexagon's straight sides are 10% off)
RIM_EDGE_ABS = 0.002  # metres: and in absolute length (a 1 m wide rounded rectangle is not a 1 m circle)
COLLINEAR = 1e-6  # of a chain's length: points this far off its line are still on it
CORNER_TURN = math.radians(30)  # a chain turning more than this at a vertex has a corner there
FLAT = math.radians(0.01)  # normals of one planar region differ by at most this
APEX_RADIUS = 1e-6  # metres: the rim of a cone's apex
MERGE_LATERAL = 1e-3  # of the diagonal: consecutive crease edges merge into one line when every vertex dropped
MERGE_ANGLE = math.radians(5)  # is within this distance of it and within tan(MERGE_ANGLE) x its length
SHORTEST = 0.002  # of the diagonal: the default minimum length of a line or polyline (and extent of a face)
CONTOUR_SMOOTH = 2  # passes of normal smoothing before the facing test of a contour (Contours)
OWN_DEPTH = 4.0  # of the longest edge at a contour edge's ends: how far before it, along its ray, its own surface
#   must be to hide it (Contours.reach)
BUDGET = 200  # the most lines and polylines a scan gives by default (`budget auto`): the longest and sharpest
PLANAR_EDGE = math.radians(0.1)  # an interior edge whose triangles' normals agree to this is planar (a flat's
#   diagonal in a CAD tessellation; real parts rounded to float32 100 m from their origin still are)
CAD_PLANAR = 0.10  # a mesh at least this share of whose interior edge length is planar is a CAD part (no budget by
#   default); below, a scan. CAD parts measure 26-71%, scans 0.4-1.1% (docs/how-to/meshes-at-full-size.md)


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
    planar: float = 0.0  # share of the interior edges' length between triangles within PLANAR_EDGE of coplanar
    scan: bool = False  # read as a scan (planar < CAD_PLANAR), not a CAD part
    budget: int | None = None  # the budget applied (None: none, every line and polyline kept)
    cut: int = 0  # lines and polylines at least `shortest` long that the budget left out
    degenerate: int = 0  # triangles dropped for having no area
    nonmanifold: int = 0  # edges with more than two triangles
    triangles: int = 0  # triangles the mesh had


def merge_vertices(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices closer than MERGE of the size made one, and F re-indexed."""
    size = float(np.linalg.norm(np.ptp(V, axis=0))) or 1.0
    q = np.round((V - V.min(axis=0)) / (MERGE * size)).astype(np.int64)  # each < 2^20
    _, first, inverse = np.unique((q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2], return_index=True,
                                  return_inverse=True)
    return V[first], inverse.reshape(-1)[F]


def features(V: np.ndarray, F: np.ndarray, crease: float, shortest: float | None = None,
             budget: int | None | str = "auto") -> MeshFeatures:
    """The features of the mesh (V (n, 3), F (m, 3)) with crease angle `crease` (radians): lines and polylines
    at least `shortest` long (default SHORTEST of the diagonal), at most `budget` of them (ranked by length
    times dihedral angle; "auto": BUDGET for a scan, none for a CAD part, see `is_scan`; None: none), corners
    where kept ones meet, faces at least `shortest` across."""
    V, F = merge_vertices(np.asarray(V, float), np.asarray(F, np.int64))
    size = float(np.linalg.norm(np.ptp(V, axis=0))) or 1.0
    N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    area2 = np.linalg.norm(N, axis=1)
    ok = (area2 > 2 * AREA * size * size) & (F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])
    out = MeshFeatures(degenerate=int((~ok).sum()), triangles=len(F))
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
    # each edge's sharpness for ranking: its dihedral angle; a boundary counts as 90 deg, a non-manifold as 180
    dihedral = np.where(count == 1, math.pi / 2, math.pi)
    dihedral[two] = np.arccos(np.clip(cos, -1.0, 1.0))
    out.planar, out.scan = is_scan(np.linalg.norm(V[edges[two, 0]] - V[edges[two, 1]], axis=1), cos)
    out.budget = (BUDGET if out.scan else None) if budget == "auto" else budget
    shortest = SHORTEST * size if shortest is None else shortest
    # smooth regions: triangles joined through edges that are not sharp
    region = _components(len(F), tri[i0][~sharp[two]], tri[i1][~sharp[two]])
    chains = _chains(edges[sharp], len(V))
    rims, rest = [], []
    for loop, closed in chains:
        fit = _rim(V[loop[:-1]], size) if closed and len(loop) - 1 >= RIM_MIN else None
        if fit is not None:
            fit["verts"] = loop[:-1]
            rims.append(fit)
        else:
            rest.append((loop, closed))
    out.ellipses = [{k: r[k] for k in ("centre", "normal", "axis", "a", "b")} for r in rims]
    # sides of cylinders and cones: smooth regions all of whose vertices are on two rims (or a rim and an apex)
    n_region = int(region.max()) + 1
    by_region = np.argsort(region, kind="stable")
    bounds = np.searchsorted(region[by_region], np.arange(n_region + 1))
    first = by_region[bounds[:-1]]  # each region's first triangle
    flat = np.bincount(region, weights=np.abs((N * N[first[region]]).sum(1)) < math.cos(FLAT),
                       minlength=n_region) == 0
    gv = np.unique(region[np.repeat(np.arange(len(F)), 3)] * len(V) + F.ravel())  # (region, vertex) pairs
    g, v = gv // len(V), gv % len(V)
    rim_v = np.concatenate([r["verts"] for r in rims]) if rims else np.zeros(0, int)
    rim_k = np.repeat(np.arange(len(rims)), [len(r["verts"]) for r in rims])
    o = np.argsort(rim_v, kind="stable")
    rim_v, rim_k = rim_v[o], rim_k[o]
    lo, hi = np.searchsorted(rim_v, v, "left"), np.searchsorted(rim_v, v, "right")
    n_on = hi - lo
    at = np.repeat(lo - np.cumsum(n_on) + n_on, n_on) + np.arange(n_on.sum())
    gk = np.unique(np.repeat(g, n_on) * max(len(rims), 1) + rim_k[at])  # (region, rim) pairs, sorted
    rims_of = np.bincount(gk // max(len(rims), 1), minlength=n_region)
    bare = n_on == 0
    left = np.bincount(g[bare], minlength=n_region)  # vertices of the region on no rim
    apex = np.zeros(n_region, int)
    apex[g[bare]] = v[bare]
    ruled = np.zeros(n_region, bool)
    pair_at = np.searchsorted(gk // max(len(rims), 1), np.arange(n_region))
    for g_ in np.flatnonzero(~flat & (((rims_of == 2) & (left == 0)) | ((rims_of == 1) & (left == 1)))).tolist():
        on = (gk[pair_at[g_]:pair_at[g_] + rims_of[g_]] % max(len(rims), 1)).tolist()
        if len(on) == 2:
            out.silhouettes.append((on[0], on[1]))
        else:
            r = rims[on[0]]
            out.ellipses.append({"centre": V[apex[g_]], "normal": r["normal"], "axis": r["axis"],
                                 "a": APEX_RADIUS, "b": APEX_RADIUS})
            out.silhouettes.append((on[0], len(out.ellipses) - 1))
        ruled[g_] = True
    key = edges[:, 0] * len(V) + edges[:, 1]  # sorted (np.unique): an edge by its ends
    edge_of = lambda a, b: np.searchsorted(key, np.minimum(a, b) * len(V) + np.maximum(a, b))  # noqa: E731
    kept_edge = np.zeros(len(edges), bool)
    _lines_and_corners(V, rest, out, lambda a, b: dihedral[edge_of(a, b)], kept_edge, edge_of,
                       MERGE_LATERAL * size, shortest, out.budget)
    # faces: planar regions bounded by one convex loop, at least `shortest` across; a region of one triangle
    # (unless a sliver) only when its three edges are on kept features (a scan's lone noisy triangles are
    # not faces); lone triangles all at once: a soup of 200,000 triangles is 200,000 regions
    is_face = np.zeros(n_region, bool)
    single = flat & (np.diff(bounds) == 1)
    T1 = F[first[single]]
    bounded = kept_edge[edge_of(T1, np.roll(T1, -1, axis=1))].all(axis=1)
    lone = dict(zip(np.flatnonzero(single).tolist(), zip(_triangle_faces(V, T1), bounded.tolist(), strict=True),
                    strict=True))
    for g_ in np.flatnonzero(flat).tolist():
        poly = (lone[g_][0] if lone[g_][1] else None) if g_ in lone else \
            _convex_boundary(V, F[np.sort(by_region[bounds[g_]:bounds[g_ + 1]])], N[first[g_]])
        if poly is not None and np.ptp(poly, axis=0).max() >= shortest:  # a smaller one only occludes
            out.faces.append(poly)
            is_face[g_] = True
    keep = ~ruled[region] & ~is_face[region]
    out.occluders = F[keep]
    out.contour = ~flat[region[keep]] | single[region[keep]]  # a lone triangle that is no face: surface too
    return out


def is_scan(length: np.ndarray, cos: np.ndarray) -> tuple[float, bool]:
    """Whether interior edges of these lengths, between triangles whose normals' dot products are `cos`, are a
    scan's rather than a CAD part's: (the share of their length within PLANAR_EDGE of planar, share < CAD_PLANAR).

    A CAD tessellation splits its flats, and the ruled quads of its cylinders, cones and fillets, along edges
    between exactly coplanar triangles: a third to two thirds of its edge length. A scan's noise tilts every
    pair of neighbours (a bunny has 1.1% of its edge length under 0.1 deg): a sharp edge of a CAD part is the
    part's, a scan's are mostly noise, and the budget is for those."""
    total = float(length.sum())
    planar = float(length[cos >= math.cos(PLANAR_EDGE)].sum()) / total if total > 0 else 0.0
    return planar, planar < CAD_PLANAR


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
    deg = np.bincount(E.ravel(), minlength=n)
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
    return out


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
    # the edges between the vertices too: their middles (where a chord is farthest from its arc), measured
    # along the ray from the centre, within RIM_EDGE of the radius and RIM_EDGE_ABS
    mid = (rel + np.roll(rel, -1, axis=0)) / 2
    rho_mid = np.sqrt(np.maximum(np.einsum("ki,ij,kj->k", mid, Q, mid) / k, 1e-300))
    off = np.linalg.norm(mid, axis=1) * np.abs(1 - 1 / rho_mid) * scale  # length units of P
    if off.max() > min(RIM_EDGE * float(radii.mean()) * scale, RIM_EDGE_ABS):
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


def _drop_collinear(P: np.ndarray, closed: bool) -> np.ndarray:
    """P without the points that lie on the line through their neighbours (to COLLINEAR of the length).

    Rounds of removal, vectorised: each round drops every other point of each run of points that lie within
    COLLINEAR of the chord through their present neighbours (never two neighbours at once), until none does.
    """
    length = float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum()) or 1.0
    keep = np.arange(len(P))
    while len(keep) > 2:
        Q = P[keep]
        a, b = np.roll(Q, 1, axis=0), np.roll(Q, -1, axis=0)
        ab = b - a
        off = np.linalg.norm(np.cross(Q - a, ab), axis=1) / np.maximum(np.linalg.norm(ab, axis=1), 1e-300)
        on = (off <= COLLINEAR * length) & (((Q - a) * ab).sum(1) >= 0) & (((b - Q) * ab).sum(1) >= 0)
        if not closed:
            on[[0, -1]] = False
        if not on.any():
            break
        # in each run of candidates keep its 1st, 3rd, ... for removal (a closed loop's run may wrap round)
        start = on & ~(np.roll(on, 1) if closed else np.concatenate([[False], on[:-1]]))
        if not start.any():  # a closed loop all of whose points are candidates
            start[0] = True
        idx = np.arange(len(on))
        first = np.maximum.accumulate(np.where(start, idx, -1))
        first = np.where(first < 0, np.flatnonzero(start)[-1] - len(on), first)  # the run through the seam
        drop = on & ((idx - first) % 2 == 0)
        if closed and drop[0] and drop[-1]:
            drop[-1] = False
        keep = keep[~drop]
    return P[keep]


def _simplify(P: np.ndarray, lateral: float) -> np.ndarray:
    """Indices of the points of the open chain P (k, 3) kept when nearly collinear runs merge (Ramer-Douglas-
    Peucker): every dropped point is within min(lateral, tan(MERGE_ANGLE) x L) of the kept segment of length L
    that replaces it (and between its ends); the ends are kept."""
    keep = np.zeros(len(P), bool)
    keep[[0, -1]] = True
    stack = [(0, len(P) - 1)]
    tan = math.tan(MERGE_ANGLE)
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        a, ab = P[i], P[j] - P[i]
        L = float(np.linalg.norm(ab))
        Q = P[i + 1:j] - a
        if L > 0:
            u = ab / L
            t = Q @ u
            off = np.linalg.norm(Q - t[:, None] * u, axis=1)
            off = np.where((t < 0) | (t > L), np.inf, off)  # folding back past an end is not on the segment
        else:
            off = np.linalg.norm(Q, axis=1) + np.inf
        k = int(np.argmax(off))
        if off[k] > min(lateral, tan * L):
            keep[i + 1 + k] = True
            stack += [(i, i + 1 + k), (i + 1 + k, j)]
    return np.flatnonzero(keep)


def _lines_and_corners(V: np.ndarray, chains: list[tuple[np.ndarray, bool]], out: MeshFeatures, angle_of,
                       kept_edge: np.ndarray, edge_of, lateral: float, shortest: float, budget: int | None) -> None:
    """Lines and polylines of the sharp chains (nearly collinear edges merged, split at sharp turns of what
    is left), those at least `shortest` long, the `budget` (None: all) with the largest length x dihedral angle;
    and the corners where kept ones meet. `kept_edge` is set for the mesh edges (`edge_of(a, b)`) they cover;
    `out.cut` counts those the budget left out."""
    pieces = []  # (points, first vertex, last vertex, length, score)
    for path, closed in chains:
        P = V[path]
        seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
        weight = np.concatenate([[0.0], np.cumsum(seg * angle_of(path[:-1], path[1:]))])
        along = np.concatenate([[0.0], np.cumsum(seg)])
        kept = _simplify(P, lateral)
        Q = P[kept]
        # cut where the chain turns sharply at a point the merge keeps (a scan's zig-zag merges away)
        u, w = P[1:-1] - P[:-2], P[2:] - P[1:-1]
        cosang = (u * w).sum(1) / np.maximum(np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1), 1e-300)
        turned = np.zeros(len(P), bool)
        turned[1:-1] = cosang < math.cos(CORNER_TURN)
        turns = np.flatnonzero(turned[kept]).tolist()
        cut = [0, *turns, len(kept) - 1]
        if closed and len(cut) == 2:  # a loop with no corner: one closed polyline, cut where it starts
            cut = [0, (len(kept) - 1) // 2, len(kept) - 1] if len(kept) > 2 else cut
        for s, e in zip(cut[:-1], cut[1:], strict=True):
            a, b = int(kept[s]), int(kept[e])
            pieces.append((Q[s:e + 1], int(path[a]), int(path[b]), along[b] - along[a], weight[b] - weight[a],
                           path[a:b + 1]))
    long_enough = [p for p in pieces if p[3] >= shortest]
    order = sorted(range(len(long_enough)), key=lambda k: -long_enough[k][4])
    order = order if budget is None else order[:max(budget, 0)]
    out.cut = len(long_enough) - len(order)
    ends: dict[int, list[tuple[str, int]]] = {}
    for k in sorted(order):  # in the chains' order
        piece, v0, v1 = long_enough[k][:3]
        on = long_enough[k][5]
        kept_edge[edge_of(on[:-1], on[1:])] = True
        if len(piece) == 2:
            out.lines.append((piece[0], piece[1]))
            ref = ("line", len(out.lines) - 1)
        else:
            out.polylines.append(piece)
            ref = ("polyline", len(out.polylines) - 1)
        for v in (v0, v1):
            ends.setdefault(v, []).append(ref)
    for v, refs in ends.items():  # three or more kept ends, or two that turn (not a loop's own cut)
        refs = list(dict.fromkeys(refs))
        if len(ends[v]) >= 3 or (len(ends[v]) == 2 and len(refs) == 2 and _turn(V[v], *refs, out)):
            out.corners.append((V[v], refs))


def _turn(at: np.ndarray, r0: tuple[str, int], r1: tuple[str, int], out: MeshFeatures) -> bool:
    """Two features ending at `at` turn there by more than CORNER_TURN."""
    def away(ref):  # the direction from `at` into the feature
        P = np.stack(out.lines[ref[1]]) if ref[0] == "line" else out.polylines[ref[1]]
        d = P[1] - P[0] if np.array_equal(P[0], at) else P[-2] - P[-1]
        return d / (np.linalg.norm(d) or 1.0)
    return float(away(r0) @ away(r1)) > -math.cos(CORNER_TURN)


@dataclass(frozen=True)
class Contours:
    """The edges of a smooth surface that can be on its occluding contour: edges between two triangles.

    `seen_from(eye)` gives those between a triangle facing the eye and one facing away (each pair's
    facing compared with the edge's winding, so an inconsistently wound mesh still reads right). A
    consistently wound surface's facing is taken with its normals smoothed CONTOUR_SMOOTH times (each
    triangle's normal the sum of its vertices' area-weighted normals), at its centroid: a scan's noise then
    does not flip facings all over it, and its contour is a few long chains rather than thousands of bits.

    The smoothed contour is the outline of the smoothed surface, not of the facets: an edge where the smoothed
    facing flips may lie a facet or two behind the faceted horizon, where the facets just in front of it hide
    it (and a scan's noise pokes bumps through it). So, under exact visibility, the contour's own surface hides
    a point of it only where the ray meets the surface more than `reach` before the point: OWN_DEPTH times the
    longest edge of the triangles at the contour edge's ends (measured: the ray re-enters the facets within
    0.9 of such an edge before a smoothed contour point of an icosphere or a uv sphere, within 4 on a sphere
    with noise of 0.1 of an edge along its normals, tests/test_contour_occlusion.py).
    Other models, and parts of the same surface farther along the ray (an ear in front of a head), still
    hide it (`occlusion.Eye.segment_pieces`'s `own`).
    """

    ends: np.ndarray  # (E, 2, 3) the edges' end points
    normal: np.ndarray  # (E, 2, 3) normals of the edge's two triangles
    origin: np.ndarray  # (E, 2, 3) a vertex of each
    flipped: np.ndarray  # (E,) the two triangles are wound inconsistently
    verts: np.ndarray  # (E, 2) the edges' end vertices (indices)
    reach: np.ndarray  # (E,) how far before an edge, along the ray, its own surface must be to hide it
    own: tuple[int, int] = (0, 0)  # the surface's triangles among the occluders (World.triangles): [first, end)

    @classmethod
    def of(cls, V: np.ndarray, F: np.ndarray, surface: np.ndarray | None = None, first: int = 0) -> Contours:
        """Contour candidates of the triangles F (m, 3) over vertices V (n, 3); `surface` (T, 3): every
        triangle of the surface F is part of (default F), the `first` of the occluders onwards."""
        S = np.asarray(F if surface is None else surface, np.int64).reshape(-1, 3)
        longest = np.zeros(len(V))  # each vertex's longest edge
        for j in range(3):
            L = np.linalg.norm(V[S[:, j]] - V[S[:, (j + 1) % 3]], axis=1)
            np.maximum.at(longest, S[:, j], L)
            np.maximum.at(longest, S[:, (j + 1) % 3], L)
        own = (int(first), int(first) + len(S))
        d = np.stack([F, np.roll(F, -1, axis=1)], axis=2).reshape(-1, 2)
        _, eid, count = _edges(d, len(V))
        order = np.argsort(eid, kind="stable")
        start = np.concatenate([[0], np.cumsum(count)])
        two = np.flatnonzero(count == 2)
        i0, i1 = order[start[two]], order[start[two] + 1]
        N = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        t = np.stack([i0 // 3, i1 // 3], axis=1)
        flipped = (d[i0] == d[i1]).all(axis=1)
        reach = OWN_DEPTH * longest[d[i0]].max(axis=1)
        if flipped.any():  # wound inconsistently: the triangles' own normals, compared edge by edge
            return cls(V[d[i0]], N[t], V[F[t, 0]], flipped, d[i0], reach, own)
        for _ in range(CONTOUR_SMOOTH):  # triangle -> vertex (area-weighted) -> triangle normals
            at_vertex = np.zeros_like(V)
            for j in range(3):
                np.add.at(at_vertex, F[:, j], N)
            N = at_vertex[F].sum(axis=1)
        return cls(V[d[i0]], N[t], V[F].mean(axis=1)[t], flipped, d[i0], reach, own)

    def seen_from(self, eye: np.ndarray) -> np.ndarray:
        """Boolean (E,): the edges on the occluding contour seen from `eye` (3,)."""
        front = ((eye - self.origin) * self.normal).sum(-1) > 0  # (E, 2)
        return (front[:, 0] != front[:, 1]) ^ self.flipped

    def chains(self, e: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The edges e (k,) (those `seen_from` an eye) chained end to end: (the edges in chain order, each
        one's chain number, whether it runs backwards). A chain ends where other than two of them meet."""
        if len(e) == 0:
            return e, np.zeros(0, int), np.zeros(0, bool)
        E = self.verts[e]
        n = int(E.max()) + 1
        pair = np.minimum(E[:, 0], E[:, 1]) * n + np.maximum(E[:, 0], E[:, 1])
        sort = np.argsort(pair, kind="stable")
        idx, chain, back = [], [], []
        for c, (path, _) in enumerate(_chains(E, n)):  # vertex paths; each step is one of the edges
            a, b = path[:-1], path[1:]
            j = sort[np.searchsorted(pair[sort], np.minimum(a, b) * n + np.maximum(a, b))]
            idx.append(j)
            chain.append(np.full(len(j), c))
            back.append(E[j, 0] != a)
        return e[np.concatenate(idx)], np.concatenate(chain), np.concatenate(back)
