"""Hidden lines (`--visibility exact`): the unoccluded parts of every feature, seen from one eye.

Occluders are the scene's faces (convex planar polygons, as the fan triangles
`World.triangles` tile them exactly) and the ruled surfaces between the two
ellipses of every silhouette, S(th, s) = Ea(th) + s (Eb(th) - Ea(th)) with s in
[0, 1] (the cylinder or cone sides). Everything is computed in 3D, in the camera
frame, with the eye at the origin; a point P is hidden when the segment from the
eye to it meets an occluder at a ray parameter in (RAY_END, 1 - RAY_END).

- A segment P(u) = A + u (B - A) against a triangle: the rays through the
  triangle form a convex cone (three half-spaces through the eye), and the
  points beyond the triangle's plane are a half-space: four conditions, each
  linear in u, so the hidden set is one interval, found exactly.
- A ray against a ruled surface: the ray meets the ruling at th when the eye,
  Ea(th) and Eb(th) span a plane containing P, det(Ea(th), Eb(th), P) = 0, a
  trigonometric polynomial of degree 2 in th. Its roots are the eigenvalues of a
  4 x 4 companion matrix (batched over points), polished by Newton steps; each
  root gives the ruling's s and the ray's t in closed form.
- Curves (ellipse arcs) and segments against surfaces are sampled (SAMPLES
  points a feature) with that exact point test, and every change of visibility
  between two samples is refined by bisection to BISECT halvings of the sample
  step (about 1e-14 of the feature's parameter range), BISECT_BITS of them a round from one call.

Memory is bounded: every all-pairs array (queries x triangles, points x surfaces, samples of features) is
made in blocks of consecutive queries whose pairs, counted first from the grids' cells, fit in BUDGET bytes
at FACE_PAIR_BYTES / SURFACE_PAIR_BYTES a pair, and the pairs of a block are tested in slices of that many.
The peak of a view is then about

    BUDGET + 16 bytes x (the largest single query's candidate pairs, at most the triangles T)
           + what the scene holds anyway (the triangles, 72 bytes each, and their grid, ~100 bytes a chunk)

whatever the number of triangles, surfaces and features. A block is computed exactly as the whole was, so
the output does not depend on BUDGET (tests/test_occlusion_memory.py compares a tiny budget with the default
and runs a 43k-triangle gear under a 2 GB address-space limit).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wiredsl.engine import geometry
from wiredsl.engine.world import World, ellipse_points, side_ellipses

RAY_END = 1e-7  # fraction of the eye-to-point distance treated as touching the point: rounding, not geometry
SAMPLES = 128  # samples a segment or a full ellipse against the curved surfaces; a section gets its share
BISECT = 40  # halvings of a sample step that brackets a change of visibility
BISECT_BITS = 4  # of them a round: 2**BISECT_BITS - 1 points tested in one call (the calls' overhead dominates)
SLIVER = 1e-9  # parameter length below which a visible or hidden piece is dropped (rounding, not geometry)
# image distance (px) from a face's plane within which a point touches the face and is not hidden by it: an edge on
# the face it bounds, moved off it by rounding or by merging nearly collinear creases (0.05-0.15 um on a fandisk,
# some 1e-4 px); half MIN_PIECE_PX: a point moved onto the face by a displacement under a piece too short to keep
FACE_TOUCH_PX = 0.005
MIN_PIECE_PX = 0.01  # image length (px) below which a visible piece is dropped and a hidden gap closed (below)
GRID_NEAR = 1e-2  # metres from the eye's plane within which a triangle is tested against every query
GRID_REACH = 10.0  # the grid spans image-plane coordinates (x/z, y/z) within this; beyond, its border cells
GRID_MAX = 512  # cells a side of the grid of chunks
CHUNK = 8  # triangles a chunk: the grid bins chunks, so that a view's set-up costs T / CHUNK
BUDGET = 64 * 2**20  # bytes of working arrays the tests of one call hold at once (the memory bound, below)
FACE_PAIR_BYTES = 1024  # working bytes a (query, triangle) pair costs, temporaries included (measured: ~700)
SURFACE_PAIR_BYTES = 4096  # working bytes a (point, surface) pair costs in the root finder (measured: ~2,600)
FEW_SURFACES = 16  # up to this many ruled surfaces, a point is paired with each (no grid: its overhead, on the lab's
#   3, cost more than the pairs it saves; the answer is the same, every pair being tested exactly)
ARC_PAIR_BYTES = 4096  # working bytes an (arc piece, triangle) pair costs (its conditions, ends and pieces)
ARC_PIECE = np.pi / 8  # radians of an arc piece whose image box is asked of the grid
SAMPLE_BYTES = 256  # working bytes a sample point of a feature costs (its point, parameter, row, flags)


@dataclass(frozen=True)
class Occluders:
    """Occluding geometry, world or camera frame: triangles (T, 3, 3) and surfaces' two ellipses (S, 3) each.

    The triangles are kept in chunks of CHUNK neighbours (ordered along a Morton curve of their centroids),
    each with its bounding sphere (`chunk_c`, `chunk_r`), so that a view meets only the chunks over what
    it asks about and never transforms or tests the rest: the cost of a view grows more slowly than T.
    """

    tris: np.ndarray
    ca: np.ndarray
    Ua: np.ndarray
    Va: np.ndarray
    cb: np.ndarray
    Ub: np.ndarray
    Vb: np.ndarray
    chunk_c: np.ndarray | None = None
    chunk_r: np.ndarray | None = None
    index: np.ndarray | None = None  # each triangle's index in the triangles given (before the Morton order)

    def __post_init__(self):
        if self.chunk_c is None:
            tris, c, r, index = _chunks(np.asarray(self.tris, float).reshape(-1, 3, 3))
            object.__setattr__(self, "tris", tris)
            object.__setattr__(self, "chunk_c", c)
            object.__setattr__(self, "chunk_r", r)
            object.__setattr__(self, "index", index)

    @classmethod
    def of_world(cls, w: World) -> Occluders:
        return cls(w.triangles, *side_ellipses(w))  # b's parameter matched to a's: no hourglass sides

    def seen_from(self, R_cw: np.ndarray, t_cw: np.ndarray, px: float = 0.0) -> Eye:
        """The occluders in a camera's frame (P_cam = R P_world + t): the eye at the origin. `px`: the camera's
        pixels a radian (its focal length in pixels), which sets what is too small to keep (MIN_PIECE_PX); 0 keeps
        every piece."""
        return Eye(self, np.asarray(R_cw, float), np.asarray(t_cw, float), float(px))


def _chunks(tris: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Triangles reordered along a Morton curve, the bounding spheres (K, 3), (K,) of each CHUNK of them, and
    each reordered triangle's index among those given."""
    T = len(tris)
    if T == 0:
        return tris, np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64)
    cen = tris.mean(axis=1)
    lo, span = cen.min(axis=0), np.maximum(np.ptp(cen, axis=0), 1e-300)
    q = np.minimum((cen - lo) / span * 1024, 1023).astype(np.int64)
    code = np.zeros(T, np.int64)
    for bit in range(10):  # interleave the bits of x, y, z
        for axis in range(3):
            code |= ((q[:, axis] >> bit) & 1) << (3 * bit + axis)
    index = np.argsort(code, kind="stable")
    tris = tris[index]
    pad = (-T) % CHUNK
    V = np.concatenate([tris, np.repeat(tris[-1:], pad, axis=0)]).reshape(-1, CHUNK * 3, 3)
    c = (V.max(axis=1) + V.min(axis=1)) / 2
    r = np.linalg.norm(V - c[:, None], axis=2).max(axis=1) * (1 + 1e-9)
    return tris, c, r, index


class Eye:
    """What hides what from an eye at the origin of a camera's frame (P_cam = R P_world + t)."""

    def __init__(self, world: Occluders, R: np.ndarray, t: np.ndarray, px: float = 0.0):
        self.R, self.t, self.px = R, t, px
        self.tris_w, self.index = world.tris, world.index
        occ = Occluders(world.tris[:0], world.ca @ R.T + t, world.Ua @ R.T, world.Va @ R.T,
                        world.cb @ R.T + t, world.Ub @ R.T, world.Vb @ R.T, np.zeros((0, 3)), np.zeros(0))
        self.occ = occ
        self.grid = _Grid(world.chunk_c @ R.T + t, world.chunk_r, len(world.tris), CHUNK)
        centre = (occ.ca + occ.cb) / 2
        reach = lambda c, U, V: (np.linalg.norm(c - centre, axis=1)  # noqa: E731
                                 + np.maximum(np.linalg.norm(U, axis=1), np.linalg.norm(V, axis=1)))
        self.sphere_c = centre
        al, be = (occ.ca, occ.Ua, occ.Va), (occ.cb, occ.Ub, occ.Vb)
        self.X = np.stack([np.cross(al[i], be[j]) for i in range(3) for j in range(3)], axis=1)  # (S, 9, 3)
        self.sphere_r = np.maximum(reach(occ.ca, occ.Ua, occ.Va), reach(occ.cb, occ.Ub, occ.Vb)) * (1 + 1e-9)
        self.sgrid = _Grid(self.sphere_c, self.sphere_r, len(self.sphere_c), 1)  # surfaces by their spheres
        self.hull_n, self.hull_c, self.hull_z = _surface_hulls(occ)

    # ----------------------------------------------------------------------- points

    def hidden(self, P: np.ndarray) -> np.ndarray:
        """Whether each point (n, 3) is hidden by a face or a surface (surfaces tested only where no face hides)."""
        out = self.hidden_by_faces(P)
        rest = np.flatnonzero(~out)
        out[rest] = self.hidden_by_surfaces(P[rest])
        return out

    def hidden_by_faces(self, P: np.ndarray) -> np.ndarray:
        out = np.zeros(len(P), dtype=bool)
        if len(self.tris_w) == 0 or len(P) == 0:
            return out
        for rows in self._row_blocks(self.grid, P, P, len(self.tris_w), FACE_PAIR_BYTES):
            for r, G, h in self._pairs(P[rows], P[rows]):
                r = r + rows.start
                lo, hi = _pair_intervals(G, h, P[r], np.zeros((len(r), 3)))
                out[r[hi > lo]] = True
        return out

    def _pairs(self, A: np.ndarray, B: np.ndarray, pair_bytes: int = FACE_PAIR_BYTES, own=None):
        """(row, G, h) in slices of at most BUDGET / pair_bytes pairs: the conditions of every triangle whose
        image-plane box meets that of segment A B (rows, camera frame), from the chunks the grid gives (the
        rest cannot hide any of it). `own` (first, end, reach) a row (`segment_pieces`): the triangles
        [first, end) (indices of those given) hide the row only where the ray meets them more than reach
        (metres) before the point (as RAY_END does, by moving their plane's condition away from the eye)."""
        r_all, t_all = self.grid.pairs(A, B)
        step = max(1, BUDGET // pair_bytes)
        ahead = (A[:, 2] > 0) & (B[:, 2] > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            qa = A[:, :2] / np.where(ahead, A[:, 2], 1.0)[:, None]
            qb = B[:, :2] / np.where(ahead, B[:, 2], 1.0)[:, None]
        qlo = np.where(ahead[:, None], np.minimum(qa, qb), -np.inf)
        qhi = np.where(ahead[:, None], np.maximum(qa, qb), np.inf)
        for at in range(0, max(len(r_all), 1), step):
            r, t = r_all[at:at + step], t_all[at:at + step]
            u, inv = np.unique(t, return_inverse=True)
            inv = inv.reshape(-1)
            W = self.tris_w[u] @ self.R.T + self.t
            z = W[:, :, 2]
            boxed = z.min(axis=1) > GRID_NEAR
            with np.errstate(divide="ignore", invalid="ignore"):
                q = W[:, :, :2] / np.where(boxed[:, None], z, 1.0)[:, :, None]
            tlo = np.where(boxed[:, None], q.min(axis=1), -np.inf)
            thi = np.where(boxed[:, None], q.max(axis=1), np.inf)
            keep = ((tlo[inv] <= qhi[r]) & (thi[inv] >= qlo[r])).all(axis=1) & (z.max(axis=1) > 0)[inv]
            G, h = _triangle_conditions(W, FACE_TOUCH_PX / self.px if self.px > 0 else 0.0)
            r, tk = r[keep], inv[keep]
            G, h = G[tk], h[tk]
            if own is not None:
                first, end, reach = own
                tri = self.index[u[tk]]
                mine = np.flatnonzero((tri >= first[r]) & (tri < end[r]))
                if len(mine):
                    rm = r[mine]
                    near = np.minimum(np.linalg.norm(A[rm], axis=1), np.linalg.norm(B[rm], axis=1))
                    rest = np.minimum(1 - reach[rm] / np.maximum(near, 1e-300), 1 - RAY_END)  # the ray before reach
                    h[mine, 3] = np.where(rest > RAY_END, h[mine, 3] * (1 - RAY_END) / np.maximum(rest, RAY_END),
                                          -np.inf)
            yield r, G, h

    @staticmethod
    def _row_blocks(grid, A: np.ndarray, B: np.ndarray, items: int, unit_bytes: int) -> list[slice]:
        """_blocks of the rows A B by their pairs in `grid`, counted only when every row with every one of its
        `items` could exceed BUDGET (counting costs as much as a small query: the bisection's many)."""
        if len(A) * items * unit_bytes <= BUDGET:
            return [slice(0, len(A))] if len(A) else []
        return _blocks(grid.load(A, B), unit_bytes)

    def hidden_by_surfaces(self, P: np.ndarray) -> np.ndarray:
        out = np.zeros(len(P), dtype=bool)
        if len(self.sphere_c) == 0 or len(P) == 0:
            return out
        step, S = max(1, BUDGET // SURFACE_PAIR_BYTES), len(self.sphere_c)
        for rows in self._row_blocks(self.sgrid, P, P, S, SURFACE_PAIR_BYTES):
            if S <= FEW_SURFACES:  # every pair: the sphere test below culls them as the grid would, at less cost
                n = rows.stop - rows.start
                i_all, k_all = np.repeat(np.arange(n), S), np.tile(np.arange(S), n)
            else:
                i_all, k_all = self.sgrid.pairs(P[rows], P[rows])
            for at in range(0, len(i_all), step):
                i, k = i_all[at:at + step] + rows.start, k_all[at:at + step]
                # only rays that pass through a surface's bounding sphere are solved for
                c = self.sphere_c[k]
                dd = np.maximum((P[i] * P[i]).sum(1), 1e-300)
                u = np.clip((P[i] * c).sum(1) / dd, 0.0, 1.0)
                near = np.linalg.norm(c - u[:, None] * P[i], axis=1) < self.sphere_r[k]
                i, k = i[near], k[near]
                # and whose image is inside the image of the surface's hull, beyond its nearest depth
                with np.errstate(divide="ignore", invalid="ignore"):
                    q = P[i, :2] / P[i, 2:]
                side = np.einsum("mhj,mj->mh", self.hull_n[k], np.where(P[i, 2:] > 0, q, 0.0)) - self.hull_c[k]
                inside = (P[i, 2] > self.hull_z[k]) & (side <= 0).all(axis=1)
                inside |= ~np.isfinite(self.hull_z[k]) | (P[i, 2] <= 0)  # near the eye's plane: not culled
                i, k = i[inside], k[inside]
                if len(i):
                    o = self.occ
                    hit = _ray_hits_ruled(P[i], self.X[k], o.ca[k], o.Ua[k], o.Va[k], o.cb[k], o.Ub[k], o.Vb[k])
                    out[i[hit]] = True
        return out

    # ----------------------------------------------------------------------- features

    def segment_pieces(self, A: np.ndarray, B: np.ndarray, t0: np.ndarray, t1: np.ndarray, own=None):
        """Visible parts of segments A + u (B - A), u in [t0, t1] (rows (n,)): (row, u0, u1) of each piece.
        `own` (first, end, reach) (n,) each: the triangles [first, end) (indices of those the Occluders were
        given) hide a row only where the ray meets them more than reach before the point (a contour and its
        own surface, `mesh.Contours`); None: every triangle hides."""
        n = len(A)
        hid_r, hid_a, hid_b = [], [], []
        if own is not None and not (own[1] > own[0]).any():
            own = None
        if len(self.tris_w) and n:
            D = B - A
            A0, A1 = A + t0[:, None] * D, A + t1[:, None] * D
            for rows in self._row_blocks(self.grid, A0, A1, len(self.tris_w), FACE_PAIR_BYTES):
                block = None if own is None else tuple(x[rows] for x in own)
                for r, G, h in self._pairs(A0[rows], A1[rows], own=block):
                    r = r + rows.start
                    lo, hi = _pair_intervals(G, h, A[r], D[r])
                    hid_r.append(r[hi > lo])
                    hid_a.append(lo[hi > lo])
                    hid_b.append(hi[hi > lo])
        if len(self.sphere_c) and n:
            D = B - A
            faces = tuple(np.concatenate(x) if x else np.zeros(0) for x in (hid_r, hid_a, hid_b))
            r, a, b = _hidden_runs(lambda rows, u: A[rows] + u[:, None] * D[rows], self.hidden_by_surfaces,
                                   t0, t1, np.full(n, SAMPLES), faces)
            hid_r.append(r)
            hid_a.append(a)
            hid_b.append(b)
        return self._tidy(t0, t1, _complement(n, t0, t1, hid_r, hid_a, hid_b),
                          lambda rows, u: A[rows] + u[:, None] * (B - A)[rows], 1)

    def arc_pieces(self, c: np.ndarray, U: np.ndarray, V: np.ndarray, lo: np.ndarray, hi: np.ndarray):
        """Visible parts of arcs [lo, hi] (rows) of the ellipses c + cos(t) U + sin(t) V (one ellipse (3,), or
        one a row (n, 3)): (row, t0, t1, cut) of each piece."""
        n = len(lo)
        c, U, V = (np.broadcast_to(np.asarray(x, float), (n, 3)) for x in (c, U, V))
        hid_r, hid_a, hid_b = [], [], []
        if len(self.tris_w) and n:
            hid_r, hid_a, hid_b = ([x] for x in self._arc_face_intervals(c, U, V, lo, hi))
        if len(self.sphere_c) and n:
            count = np.maximum(16, np.ceil(SAMPLES * (hi - lo) / (2 * np.pi))).astype(int)
            faces = tuple(np.concatenate(x) if x else np.zeros(0) for x in (hid_r, hid_a, hid_b))
            r, a, b = _hidden_runs(lambda rows, t: ellipse_points(c[rows], U[rows], V[rows], t),
                                   self.hidden_by_surfaces, lo, hi, count, faces)
            hid_r.append(r)
            hid_a.append(a)
            hid_b.append(b)
        return self._tidy(lo, hi, _complement(n, lo, hi, hid_r, hid_a, hid_b),
                          lambda rows, t: ellipse_points(c[rows], U[rows], V[rows], t), 8)

    def _tidy(self, lo, hi, pieces, point, chords: int):
        """Pieces (row, u0, u1, cut) without what no image shows: a hidden gap (between two pieces, or between a
        piece and its row's end) whose image is shorter than MIN_PIECE_PX is closed, then a visible piece that
        short is dropped; a row left whole is not cut. Image lengths are the angle seen from the eye (the sum
        over `chords` chords) times self.px: at the image's centre; a pinhole image is up to 1 / cos^2 of the
        field angle longer at its edges."""
        r, a, b, cut = pieces
        if self.px <= 0 or len(r) == 0:
            return pieces

        def short(rows, u0, u1):
            s = np.linspace(0.0, 1.0, chords + 1)
            u = u0[:, None] + (u1 - u0)[:, None] * s  # (m, chords + 1)
            P = point(np.repeat(rows, chords + 1), u.ravel()).reshape(len(rows), chords + 1, 3)
            p, q = P[:, :-1], P[:, 1:]
            angle = np.arctan2(np.linalg.norm(np.cross(p, q), axis=2), (p * q).sum(axis=2)).sum(axis=1)
            return angle * self.px < MIN_PIECE_PX

        first = np.concatenate([[True], r[1:] != r[:-1]])
        last = np.concatenate([r[1:] != r[:-1], [True]])
        start = np.where(first, lo[r], np.concatenate([[0.0], b[:-1]]))  # the hidden gap before each piece
        close = a <= start
        close[~close] = short(r[~close], start[~close], a[~close])
        end = np.zeros(len(r), dtype=bool)  # the gap after a row's last piece is closed
        e = np.flatnonzero(last)
        end[e] = (b[e] >= hi[r[e]]) | short(r[e], b[e], hi[r[e]])
        head = np.flatnonzero(first | ~close)  # the first piece of each run of pieces joined across closed gaps
        tail = np.concatenate([head[1:], [len(r)]]) - 1
        gr = r[head]
        ga = np.where(first[head] & close[head], lo[gr], a[head])
        gb = np.where(end[tail], hi[gr], b[tail])
        whole = (ga == lo[gr]) & (gb == hi[gr])
        keep = whole | ~short(gr, ga, gb)
        return gr[keep], ga[keep], gb[keep], (cut[head] & ~whole)[keep]

    def _arc_face_intervals(self, c, U, V, lo, hi):
        """The parts (row, a, b) of arcs [lo, hi] of c + cos(t) U + sin(t) V that each triangle hides, exactly.

        Each arc is cut into pieces of at most ARC_PIECE radians, each inside the triangle of its ends and the
        meeting point of its end tangents (so its image inside that triangle's image box, which the grid is asked
        about). On an arc a triangle's condition g P + h >= 0 is al + be cos t + ga sin t >= 0, true on one
        circular interval around atan2(ga, be): between the at most 8 ends of the four conditions' intervals,
        the triangle hides the pieces whose middles meet all four.
        """
        k = np.maximum(1, np.ceil((hi - lo) / ARC_PIECE)).astype(int)
        own = np.repeat(np.arange(len(lo)), k)
        j = np.arange(k.sum()) - np.repeat(np.cumsum(k) - k, k)
        sa = lo[own] + (hi - lo)[own] * j / k[own]
        sb = np.where(j == k[own] - 1, hi[own], lo[own] + (hi - lo)[own] * (j + 1) / k[own])
        mid, half = (sa + sb) / 2, (sb - sa) / 2
        C, Uo, Vo = c[own], U[own], V[own]
        hull = np.stack([ellipse_points(C, Uo, Vo, sa), ellipse_points(C, Uo, Vo, sb),
                         C + (np.cos(mid)[:, None] * Uo + np.sin(mid)[:, None] * Vo) / np.cos(half)[:, None]], axis=1)
        z = hull[:, :, 2]
        ahead = z.min(axis=1) > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            q = hull[:, :, :2] / np.where(ahead[:, None], z, 1.0)[:, :, None]
        margin = 1e-12 * (1 + np.abs(q).max(axis=(1, 2)))[:, None]
        A = np.column_stack([q.min(axis=1) - margin, np.where(ahead, 1.0, -1.0)])  # a segment with that box
        B = np.column_stack([q.max(axis=1) + margin, np.where(ahead, 1.0, -1.0)])
        out_r, out_a, out_b = [np.zeros(0, int)], [np.zeros(0)], [np.zeros(0)]
        for rows in self._row_blocks(self.grid, A, B, len(self.tris_w), ARC_PAIR_BYTES):
            for r, G, h in self._pairs(A[rows], B[rows], ARC_PAIR_BYTES):
                r = r + rows.start
                i, a, b = _arc_pair_intervals(G, h, C[r], Uo[r], Vo[r], sa[r], sb[r])
                out_r.append(own[r[i]])
                out_a.append(a)
                out_b.append(b)
        return np.concatenate(out_r), np.concatenate(out_a), np.concatenate(out_b)


def _surface_hulls(o: Occluders) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half-planes (S, 28, 2) n and offsets (S, 28) c bounding the image (x/z, y/z) of each ruled surface, which
    lies in the convex hull of the 8 corners c +- U +- V of its two ellipses' parallelograms: an image point q
    off n q <= c (with a margin of 1e-9 of the hull's reach) cannot see the surface; and the least depth z of
    the corners (no point of the surface is nearer). A surface reaching within GRID_NEAR of the eye's plane
    gets no half-planes and depth -inf (nothing culled)."""
    S = len(o.ca)
    corners = np.stack([c + a * U + b * V for c, U, V in ((o.ca, o.Ua, o.Va), (o.cb, o.Ub, o.Vb))
                        for a in (-1, 1) for b in (-1, 1)], axis=1)  # (S, 8, 3)
    z = corners[:, :, 2]
    ok = z.min(axis=1) > GRID_NEAR
    q = corners[:, :, :2] / np.where(ok[:, None], z, 1.0)[:, :, None]
    i, j = np.triu_indices(8, 1)
    d = q[:, j] - q[:, i]  # (S, 28, 2)
    n = np.stack([-d[..., 1], d[..., 0]], axis=-1)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    side = np.einsum("spj,skj->spk", n, q) - np.einsum("spj,spj->sp", n, q[:, i])[..., None]  # (S, 28, 8)
    reach = np.abs(q).max(axis=(1, 2))[:, None]
    eps = 1e-9 * (1 + reach)
    outward = np.where((side <= eps[..., None]).all(-1), 1.0, np.where((side >= -eps[..., None]).all(-1), -1.0, 0.0))
    n = n * (outward * ok[:, None])[..., None]
    c = np.einsum("spj,spj->sp", n, q[:, i]) + eps * (outward != 0)
    return n, np.where(ok[:, None], c, 0.0), np.where(ok, z.min(axis=1) if S else np.zeros(0), -np.inf)


def _triangle_conditions(W: np.ndarray, touch: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """For triangles (T, 3, 3) seen from the origin: G (T, 4, 3), h (T, 4) with P hidden iff G P + h >= 0.

    Rows 0-2: P inside the cone of rays through the triangle; row 3: P beyond the triangle's plane by
    more than RAY_END of the way, and by more than `touch` times its depth z (FACE_TOUCH_PX over the camera's
    pixels a radian: nearer the plane than that, P touches the face in image terms, and the face does not hide
    it). A triangle whose plane holds the eye hides nothing.
    """
    T = len(W)
    if T == 0:
        return np.zeros((0, 4, 3)), np.zeros((0, 4))
    G = np.empty((T, 4, 3))
    h = np.zeros((T, 4))
    for i in range(3):
        G[:, i] = np.cross(W[:, i], W[:, (i + 1) % 3])
    orient = np.sign((G[:, 0] * W[:, 2]).sum(1))  # the opposite vertex lies on the inner side
    G[:, :3] *= orient[:, None, None]
    N = np.cross(W[:, 1] - W[:, 0], W[:, 2] - W[:, 0])
    sE = -(N * W[:, 0]).sum(1)  # the eye's signed distance (times |N|) from the plane
    flip = np.where(sE < 0, -1.0, 1.0)
    N, sE = N * flip[:, None], sE * flip
    scale = np.linalg.norm(N, axis=1) * np.abs(W).max(axis=(1, 2))
    G[:, 3] = -N
    G[:, 3, 2] -= np.linalg.norm(N, axis=1) * touch
    h[:, 3] = np.where((sE > 1e-12 * scale) & (orient != 0), -sE / (1 - RAY_END), -np.inf)
    return G, h


def _pair_intervals(G: np.ndarray, h: np.ndarray, A: np.ndarray, D: np.ndarray):
    """The u-interval [lo, hi] (p,) of A + u D (u in [0, 1]) that the triangle of each pair hides (empty when
    lo >= hi); pairs: G (p, 4, 3), h (p, 4), A and D (p, 3)."""
    a = np.einsum("pkj,pj->pk", G, A) + h  # (p, 4): a + b u >= 0
    b = np.einsum("pkj,pj->pk", G, D)
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = -a / b
    lower = np.where(b > 0, bound, -np.inf)
    upper = np.where(b < 0, bound, np.inf)
    never = (b == 0) & ~(a >= 0)  # also a = -inf (a triangle that hides nothing)
    lo = np.maximum(lower.max(axis=1, initial=-np.inf), 0.0)
    hi = np.minimum(upper.min(axis=1, initial=np.inf), 1.0)
    # a point (D = 0) hidden by every condition: the whole [0, 1]
    return lo, np.where(never.any(axis=1), -np.inf, hi)


def _arc_pair_intervals(G: np.ndarray, h: np.ndarray, c, U, V, lo, hi):
    """The parts (pair, a, b) of the arcs [lo, hi] (p,) of c + cos(t) U + sin(t) V that the triangle of each pair
    hides (G (p, 4, 3), h (p, 4) as in _triangle_conditions), as at most 9 pieces a pair."""
    al = np.einsum("pkj,pj->pk", G, c) + h  # (p, 4): al + be cos t + ga sin t >= 0
    be = np.einsum("pkj,pj->pk", G, U)
    ga = np.einsum("pkj,pj->pk", G, V)
    rho = np.hypot(be, ga)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(rho > 0, -al / np.where(rho > 0, rho, 1.0), np.inf)
    turn = np.abs(x) < 1  # the condition changes at atan2(ga, be) +- arccos(x)
    phi, delta = np.arctan2(ga, be), np.arccos(np.where(turn, x, 1.0))
    ends = np.concatenate([phi - delta, phi + delta], axis=1)  # (p, 8)
    ends = lo[:, None] + np.mod(ends - lo[:, None], 2 * np.pi)
    ends = np.where(np.concatenate([turn, turn], axis=1), np.minimum(ends, hi[:, None]), lo[:, None])
    cuts = np.sort(np.concatenate([lo[:, None], ends, hi[:, None]], axis=1), axis=1)  # (p, 10)
    a, b = cuts[:, :-1], cuts[:, 1:]
    m = (a + b) / 2
    cm, sm = np.cos(m), np.sin(m)
    hides = (b > a) & (al[:, :, None] + be[:, :, None] * cm[:, None] + ga[:, :, None] * sm[:, None] >= 0).all(axis=1)
    i, k = np.nonzero(hides)
    return i, a[i, k], b[i, k]


class _Grid:
    """Chunks of triangles (or single surfaces, per = 1) binned by the image-plane box (x/z, y/z) of their
    bounding spheres, so that a query meets only the triangles of the chunks over its own box: a uniform grid
    of about one cell a chunk (at most GRID_MAX a side).

    A point can be hidden only by a triangle that its ray crosses, at a point with the same projection and
    z > 0: so chunks wholly behind the eye's plane are dropped, and those reaching within GRID_NEAR of it
    (whose projections are unbounded) are paired with every query, as is a query reaching behind the plane.
    Boxes beyond the grid's range are clamped to its border cells, which keeps every true pair.
    """

    def __init__(self, c: np.ndarray, r: np.ndarray, n_tris: int, per: int):
        self.n_tris, self.per = n_tris, per  # items, and items a chunk (the last may be short)
        live = c[:, 2] + r > 0
        self.live = np.flatnonzero(live)
        # a query reaching behind the eye's plane meets every live chunk; single surfaces (per = 1), every one
        self.behind = self.live if per > 1 else np.arange(len(c))
        self.always = np.flatnonzero(live & (c[:, 2] - r <= GRID_NEAR))
        binned = np.flatnonzero(live & (c[:, 2] - r > GRID_NEAR))
        self.n = len(binned)
        if self.n == 0:
            return
        c, r = c[binned], r[binned, None]
        near, far = c[:, 2:] - r, c[:, 2:] + r  # a conservative box of x/z, y/z over the sphere's box
        lo = np.where(c[:, :2] - r < 0, (c[:, :2] - r) / near, (c[:, :2] - r) / far)
        hi = np.where(c[:, :2] + r > 0, (c[:, :2] + r) / near, (c[:, :2] + r) / far)
        self.origin = np.maximum(lo.min(axis=0), -GRID_REACH)
        extent = np.maximum(np.minimum(hi.max(axis=0), GRID_REACH) - self.origin, 1e-12)
        self.side = int(np.clip(np.sqrt(self.n), 1, GRID_MAX))
        self.cell = extent / self.side
        self.box_lo = np.full((len(live), 2), -np.inf)
        self.box_hi = np.full((len(live), 2), np.inf)
        self.box_lo[binned], self.box_hi[binned] = lo, hi
        owner, cells = self._cells(lo, hi)
        order = np.argsort(cells, kind="stable")
        self.chunk = binned[owner[order]]
        self.start = np.searchsorted(cells[order], np.arange(self.side * self.side + 1))

    def _cells(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every (box, cell) pair of the boxes [lo, hi] (b, 2) in projected coordinates."""
        i0 = np.clip(np.floor((lo - self.origin) / self.cell), 0, self.side - 1).astype(int)
        i1 = np.clip(np.floor((hi - self.origin) / self.cell), 0, self.side - 1).astype(int)
        nx, ny = i1[:, 0] - i0[:, 0] + 1, i1[:, 1] - i0[:, 1] + 1
        owner = np.repeat(np.arange(len(lo)), nx * ny)
        k = np.arange(len(owner)) - np.repeat(np.cumsum(nx * ny) - nx * ny, nx * ny)
        return owner, (i0[owner, 0] + k % nx[owner]) * self.side + i0[owner, 1] + k // nx[owner]

    def load(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        """An upper bound (n,) of the pairs `pairs` gives each segment A B (rows (n, 3)), counted cell by cell in
        blocks, so that counting holds at most BUDGET bytes whatever the segments span."""
        n = len(A)
        ahead = (A[:, 2] > 0) & (B[:, 2] > 0)
        out = np.where(ahead, len(self.always), len(self.behind)).astype(np.int64)
        front = np.flatnonzero(ahead)
        if self.n and len(front):
            qa, qb = A[front, :2] / A[front, 2:], B[front, :2] / B[front, 2:]
            qlo, qhi = np.minimum(qa, qb), np.maximum(qa, qb)
            i0 = np.clip(np.floor((qlo - self.origin) / self.cell), 0, self.side - 1).astype(np.int64)
            i1 = np.clip(np.floor((qhi - self.origin) / self.cell), 0, self.side - 1).astype(np.int64)
            cells = (i1[:, 0] - i0[:, 0] + 1) * (i1[:, 1] - i0[:, 1] + 1)
            for rows in _blocks(cells, 64):
                owner, cell = self._cells(qlo[rows], qhi[rows])
                count = self.start[cell + 1] - self.start[cell]
                out[front[rows]] += np.bincount(owner, weights=count, minlength=rows.stop - rows.start).astype(np.int64)
        return out * self.per if n else out

    def pairs(self, A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, triangle) of every triangle that may hide part of the segment A B (rows (n, 3)), each once."""
        rows, chunks = [], []
        ahead = (A[:, 2] > 0) & (B[:, 2] > 0)
        behind = np.flatnonzero(~ahead)  # reaches the eye's plane: every chunk in front of it
        rows.append(np.repeat(behind, len(self.behind)))
        chunks.append(np.tile(self.behind, len(behind)))
        front = np.flatnonzero(ahead)
        rows.append(np.repeat(front, len(self.always)))
        chunks.append(np.tile(self.always, len(front)))
        if self.n and len(front):
            qa, qb = A[front, :2] / A[front, 2:], B[front, :2] / B[front, 2:]
            qlo, qhi = np.minimum(qa, qb), np.maximum(qa, qb)
            owner, cells = self._cells(qlo, qhi)
            count = self.start[cells + 1] - self.start[cells]
            row = np.repeat(owner, count)
            at = np.repeat(self.start[cells] - np.cumsum(count) + count, count) + np.arange(count.sum())
            chunk = self.chunk[at]
            near = ((self.box_lo[chunk] <= qhi[row]) & (self.box_hi[chunk] >= qlo[row])).all(axis=1)
            width = int(self.live.max()) + 1
            key = geometry.distinct(front[row[near]] * width + chunk[near])
            rows.append(key // width)
            chunks.append(key % width)
        row, chunk = np.concatenate(rows).astype(int), np.concatenate(chunks).astype(int)
        # each chunk's triangles; the last chunk may be short
        row, tri = np.repeat(row, self.per), (chunk[:, None] * self.per + np.arange(self.per)).ravel()
        keep = tri < self.n_tris
        return row[keep], tri[keep]


def _blocks(load: np.ndarray, unit_bytes: int) -> list[slice]:
    """Consecutive slices of rows whose summed `load` (items of unit_bytes each) fits in BUDGET; a row over it
    alone is a slice of its own."""
    cap = max(1, BUDGET // unit_bytes)
    n = len(load)
    if n == 0:
        return []
    total = np.cumsum(load)
    if total[-1] <= cap:
        return [slice(0, n)]
    out, i = [], 0
    while i < n:
        base = total[i - 1] if i else 0
        j = max(int(np.searchsorted(total, base + cap, side="right")), i + 1)
        out.append(slice(i, j))
        i = j
    return out


def _ray_hits_ruled(P, X, ca, Ua, Va, cb, Ub, Vb) -> np.ndarray:
    """Whether the segment from the origin to each P (m, 3) meets its row's ruled surface strictly before P.

    X (m, 9, 3) holds the row's cross products (ca, Ua, Va)_i x (cb, Ub, Vb)_j.
    """
    mm = np.einsum("mkj,mj->mk", X, P)
    # g(th) = det(Ea(th), Eb(th), P) = a0 + a1 cos + b1 sin + a2 cos 2th + b2 sin 2th
    a0 = mm[:, 0] + (mm[:, 4] + mm[:, 8]) / 2
    a1, b1 = mm[:, 3] + mm[:, 1], mm[:, 6] + mm[:, 2]
    a2, b2 = (mm[:, 4] - mm[:, 8]) / 2, (mm[:, 5] + mm[:, 7]) / 2
    scale = np.maximum.reduce([np.abs(a0), np.abs(a1), np.abs(b1), np.abs(a2), np.abs(b2)])
    scale = np.where(scale > 0, scale, 1.0)
    a0, a1, b1, a2, b2 = (x / scale for x in (a0, a1, b1, a2, b2))
    # cones and cylinders (parallel ellipses) have a2 = b2 = 0: then g is of degree 1, solved directly
    quartic = np.hypot(a2, b2) > 1e-9
    th = np.zeros((len(P), 4))
    on_circle = np.zeros((len(P), 4), dtype=bool)
    R = np.hypot(a1, b1)
    with np.errstate(invalid="ignore", divide="ignore"):
        half = np.arccos(np.clip(-a0 / R, -1.0, 1.0))
    phi = np.arctan2(b1, a1)
    th[:, 0], th[:, 1] = phi - half, phi + half
    on_circle[:, :2] = (~quartic & (np.abs(a0) <= R) & (R > 0))[:, None]
    if quartic.any():
        q_ = quartic
        A0, A1, B1, A2, B2 = (x[q_, None] for x in (a0, a1, b1, a2, b2))
        tq, on_circle[q_] = _trig_quadratic_roots(A0, A1, B1, A2, B2)
        for _ in range(2):  # Newton on the trigonometric polynomial: the roots to the last bits
            c, s = np.cos(tq), np.sin(tq)
            c2, s2 = c * c - s * s, 2 * s * c
            g = A0 + A1 * c + B1 * s + A2 * c2 + B2 * s2
            dg = B1 * c - A1 * s + 2 * (B2 * c2 - A2 * s2)
            step = np.divide(g, dg, out=np.zeros_like(g), where=np.abs(dg) > 1e-12)
            tq = tq - np.clip(step, -0.1, 0.1)
        th[q_] = tq
    # each real root th: the ruling Ea(th) + s w meets the ray t P where q + s w = t P
    row, k = np.nonzero(on_circle)
    cos, sin = np.cos(th[row, k])[:, None], np.sin(th[row, k])[:, None]
    q = ca[row] + cos * Ua[row] + sin * Va[row]
    w = cb[row] + cos * Ub[row] + sin * Vb[row] - q
    d = P[row]
    dw = _cross(d, w)
    n2 = (dw * dw).sum(1)
    ok = n2 > 1e-24 * (d * d).sum(1) * np.maximum((w * w).sum(1), 1e-300)
    n2 = np.where(ok, n2, 1.0)
    t = (_cross(q, w) * dw).sum(1) / n2
    s = (_cross(q, d) * dw).sum(1) / n2
    hit = ok & (s >= 0) & (s <= 1) & (t > RAY_END) & (t < 1 - RAY_END)
    out = np.zeros(len(P), dtype=bool)
    out[row[hit]] = True
    return out


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of (n, 3) arrays (np.cross's axis handling costs more than this)."""
    return np.column_stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]])


_EIGHTH = np.arange(8) * (np.pi / 4)


def _trig_quadratic_roots(a0, a1, b1, a2, b2) -> tuple[np.ndarray, np.ndarray]:
    """The four roots th (m, 4) of g = a0 + a1 cos + b1 sin + a2 cos 2th + b2 sin 2th (columns (m, 1), the
    largest coefficient of a row about 1), and whether each is real (a root of the complex quartic within 1e-6
    of the unit circle, as the companion matrices' eigenvalues were tested before).

    With x = tan((th - phi) / 2), (1 + x^2)^2 g is a real quartic in x whose leading coefficient is g(phi + pi):
    phi is the eighth of a turn where |g(phi + pi)| is largest (at least half the largest coefficient, since
    eight samples determine g), so no real root is near infinity. Ferrari's method in closed form: the
    depressed quartic y^4 + p y^2 + q y + r is split into two real quadratics by a positive root of its
    resolvent cubic (Cardano's or Viete's formula, Newton steps kept where they lower the residual), and a
    complex pair counts as real when its imaginary part is within the same 1e-6 of the circle.
    """
    a0, a1, b1, a2, b2 = (x[:, 0] for x in (a0, a1, b1, a2, b2))
    ck, sk, c2k, s2k = np.cos(_EIGHTH), np.sin(_EIGHTH), np.cos(2 * _EIGHTH), np.sin(2 * _EIGHTH)
    g8 = a0[:, None] - a1[:, None] * ck - b1[:, None] * sk + a2[:, None] * c2k + b2[:, None] * s2k
    j = np.abs(g8).argmax(axis=1)
    cp, sp, c2p, s2p = ck[j], sk[j], c2k[j], s2k[j]
    A1, B1 = a1 * cp + b1 * sp, b1 * cp - a1 * sp  # g in th - phi
    A2, B2 = a2 * c2p + b2 * s2p, b2 * c2p - a2 * s2p
    c4 = a0 - A1 + A2
    B, C = (2 * B1 - 4 * B2) / c4, (2 * a0 - 6 * A2) / c4
    D, E = (2 * B1 + 4 * B2) / c4, (a0 + A1 + A2) / c4
    BB = B * B
    p = C - 3 * BB / 8  # x = y - B / 4
    q = D - B * C / 2 + BB * B / 8
    r = E - B * D / 4 + BB * C / 16 - 3 * BB * BB / 256
    # the resolvent m^3 + p m^2 + (p^2 / 4 - r) m - q^2 / 8 = 0, its largest real root (>= 0)
    P3, Q3 = -p * p / 12 - r, -p ** 3 / 108 + p * r / 3 - q * q / 8  # in m = w - p / 3: w^3 + P3 w + Q3
    disc = (Q3 / 2) ** 2 + (P3 / 3) ** 3
    root = np.sqrt(np.maximum(disc, 0.0))
    cardano = np.cbrt(-Q3 / 2 + root) + np.cbrt(-Q3 / 2 - root)
    rho = np.sqrt(np.maximum(-P3 / 3, 0.0))
    cosine = np.clip(np.divide(-Q3, 2 * rho ** 3, out=np.zeros_like(Q3), where=rho > 0), -1.0, 1.0)
    m = np.where(disc > 0, cardano, 2 * rho * np.cos(np.arccos(cosine) / 3)) - p / 3
    lin, q8 = p * p / 4 - r, q * q / 8
    for _ in range(2):
        f = ((m + p) * m + lin) * m - q8
        df = (3 * m + 2 * p) * m + lin
        m2 = m - np.divide(f, df, out=np.zeros_like(f), where=np.abs(df) > 1e-300)
        m = np.where(np.abs(((m2 + p) * m2 + lin) * m2 - q8) < np.abs(f), m2, m)
    m = np.maximum(m, 0.0)
    s = np.sqrt(2 * m)
    # (y^2 + s y + p/2 + m - q/(2s)) (y^2 - s y + p/2 + m + q/(2s)); q/(2s) = sqrt((p/2 + m)^2 - r) near s = 0
    wide = s > 1e-3
    qs = np.where(wide, np.divide(q, 2 * s, out=np.zeros_like(q), where=wide),
                  np.copysign(np.sqrt(np.maximum((p / 2 + m) ** 2 - r, 0.0)), q))
    d1, d2 = s * s - 4 * (p / 2 + m - qs), s * s - 4 * (p / 2 + m + qs)
    r1, r2 = np.sqrt(np.maximum(d1, 0.0)), np.sqrt(np.maximum(d2, 0.0))
    x = np.column_stack([-s + r1, -s - r1, s + r2, s - r2]) / 2 - (B / 4)[:, None]
    imag = np.sqrt(np.maximum(-np.column_stack([d1, d1, d2, d2]), 0.0)) / 2
    return _EIGHTH[j][:, None] + 2 * np.arctan(x), imag < 0.5e-6 * (1 + x * x)


def _hidden_runs(point, hidden, lo: np.ndarray, hi: np.ndarray, count: np.ndarray, known=None):
    """Hidden sub-intervals (row, a, b) of [lo, hi] per row: `count` samples, changes bisected; rows in blocks
    of at most BUDGET / SAMPLE_BYTES samples. `known` (row, a, b): intervals hidden by something else (the faces,
    exactly); a sample whose steps to both neighbours lie in them is not tested (its runs change only there)."""
    parts = []
    if known is not None:
        kr, ka, kb = known
        kr = kr.astype(int)
        ka, kb = np.maximum(ka, lo[kr]), np.minimum(kb, hi[kr])
        order = np.argsort(kr, kind="stable")
        kr, ka, kb = kr[order], ka[order], kb[order]
    for rows in _blocks(count, SAMPLE_BYTES):
        block_known = None
        if known is not None:
            i0, i1 = np.searchsorted(kr, [rows.start, rows.stop])
            block_known = (kr[i0:i1] - rows.start, ka[i0:i1], kb[i0:i1])
        r, a, b = _hidden_runs_block(lambda rr, u, s=rows.start: point(rr + s, u), hidden, lo[rows], hi[rows],
                                     count[rows], block_known)
        parts.append((r + rows.start, a, b))
    if len(parts) == 1:
        return parts[0]
    if not parts:
        return np.zeros(0, int), np.zeros(0), np.zeros(0)
    return tuple(np.concatenate(x) for x in zip(*parts, strict=True))


def _known_steps(lo: np.ndarray, hi: np.ndarray, count: np.ndarray, known) -> np.ndarray:
    """Whether each sample's step to the next one (of its row: samples lo + (hi - lo) j / (count - 1)) lies
    inside one of the `known` intervals (row, a, b), with a margin of 1e-6 of a step: (sum(count),)."""
    first = np.cumsum(count) - count
    out = np.zeros(int(count.sum()) + 1, dtype=np.int64)
    kr, ka, kb = known
    span = (hi - lo)[kr]
    n1 = (count - 1)[kr]
    ok = (kb > ka) & (span > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        x0 = np.where(ok, (ka - lo[kr]) / np.where(ok, span, 1.0) * n1, 0.0)
        x1 = np.where(ok, (kb - lo[kr]) / np.where(ok, span, 1.0) * n1, 0.0)
    j0 = np.clip(np.ceil(x0 + 1e-6), 0, n1).astype(np.int64)  # the first sample at or after a
    j1 = np.clip(np.floor(x1 - 1e-6), 0, n1).astype(np.int64)  # the last sample at or before b
    ok &= j1 > j0  # steps j0 .. j1 - 1 are inside
    np.add.at(out, first[kr[ok]] + j0[ok], 1)
    np.add.at(out, first[kr[ok]] + j1[ok], -1)
    return np.cumsum(out)[:-1] > 0


def _hidden_runs_block(point, hidden, lo: np.ndarray, hi: np.ndarray, count: np.ndarray, known=None):
    """_hidden_runs of one block of rows."""
    n = len(lo)
    if n == 0:
        return np.zeros(0, int), np.zeros(0), np.zeros(0)
    row = np.repeat(np.arange(n), count)
    j = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    u = lo[row] + (hi - lo)[row] * j / (count[row] - 1)
    if known is None or len(known[0]) == 0:
        H = hidden(point(row, u))
    else:  # a sample both of whose steps are known hidden is counted hidden: runs then differ only inside them
        step_in = _known_steps(lo, hi, count, known)
        H = step_in & np.concatenate([[False], step_in[:-1]])
        test = np.flatnonzero(~H)
        H[test] = hidden(point(row[test], u[test]))
    change = np.flatnonzero((row[:-1] == row[1:]) & (H[:-1] != H[1:]))
    a, b, ha = u[change], u[change + 1], H[change]
    cr = row[change]
    ways = 2**BISECT_BITS
    at = np.arange(1, ways) / ways
    for _ in range(BISECT // BISECT_BITS):  # BISECT_BITS halvings a round, every point of a round in one call
        if not len(cr):
            break
        w = b - a
        hm = hidden(point(np.repeat(cr, ways - 1), (a[:, None] + w[:, None] * at).ravel())).reshape(-1, ways - 1)
        lo_i, hi_i = np.zeros(len(cr), dtype=np.int64), np.full(len(cr), ways)
        for _ in range(BISECT_BITS):  # the halvings bisection would make, read off the round's points
            mid = (lo_i + hi_i) // 2
            same = hm[np.arange(len(cr)), mid - 1] == ha
            lo_i, hi_i = np.where(same, mid, lo_i), np.where(same, hi_i, mid)
        a, b = a + w * (lo_i / ways), a + w * (hi_i / ways)
    edge = (a + b) / 2
    first = np.concatenate([[True], row[1:] != row[:-1]])
    last = np.concatenate([row[1:] != row[:-1], [True]])
    # a hidden run starts at the row's start or at a change into hidden, and ends likewise
    s_row = np.concatenate([row[first & H], cr[~ha]])
    s_val = np.concatenate([u[first & H], edge[~ha]])
    e_row = np.concatenate([row[last & H], cr[ha]])
    e_val = np.concatenate([u[last & H], edge[ha]])
    so, eo = np.lexsort((s_val, s_row)), np.lexsort((e_val, e_row))
    return s_row[so], s_val[so], e_val[eo]


def _complement(n: int, lo: np.ndarray, hi: np.ndarray, rows: list, a: list, b: list):
    """The parts of [lo, hi] (per row) outside the union of hidden intervals: (row, u0, u1, cut) of each piece.

    `cut` says the row lost something to occlusion.
    """
    r = np.concatenate(rows) if rows else np.zeros(0, int)
    a = np.concatenate(a) if a else np.zeros(0)
    b = np.concatenate(b) if b else np.zeros(0)
    span = hi - lo
    a, b = np.maximum(a, lo[r]), np.minimum(b, hi[r])  # hidden parts outside the range do not count
    keep = b - a > SLIVER * np.maximum(span[r], 1e-300)
    r, a, b = r[keep], a[keep], b[keep]
    order = np.lexsort((a, r))
    r, a, b = r[order], a[order], b[order]
    out_r, out_a, out_b, out_cut = [], [], [], []
    k = 0
    for i in range(n):
        cur, end, cut = lo[i], hi[i], False
        while k < len(r) and r[k] == i:
            if a[k] > cur + SLIVER * span[i]:
                out_r.append(i)
                out_a.append(cur)
                out_b.append(min(a[k], end))
            if b[k] > cur and a[k] < end:
                cut = True
            cur = max(cur, b[k])
            k += 1
        if end > cur + SLIVER * span[i]:
            out_r.append(i)
            out_a.append(cur)
            out_b.append(end)
        out_cut += [cut] * (len(out_r) - len(out_cut))
    return (np.array(out_r, dtype=int), np.array(out_a, dtype=float), np.array(out_b, dtype=float),
            np.array(out_cut, dtype=bool))


# --------------------------------------------------------------------------- the projection's hooks

def split_segments(eye: Eye, A, B, t0, t1, keep, own=None):
    """The unoccluded parts [u0, u1] of the kept segments A + u (B - A), u in [t0, t1]: (row, u0, u1, part
    index or -1 when the segment lost nothing, whether occlusion cut it), one entry a part. `own` (first, end,
    reach) a row: `Eye.segment_pieces`."""
    idx = np.flatnonzero(keep)
    r, u0, u1, cut = eye.segment_pieces(A[idx], B[idx], t0[idx], t1[idx],
                                        None if own is None else tuple(x[idx] for x in own))
    return idx[r], u0, u1, np.where(cut, _rank(r), -1), cut


def split_arcs(eye: Eye, c, U, V, owner, lo, hi, full):
    """The unoccluded parts of the arcs [lo, hi] of ellipses c + cos(t) U + sin(t) V (rows (E, 3), arcs of ellipse
    owner, sorted): (owner, t0, t1) of each part, and whether occlusion cut any of each ellipse's arcs (E,). A
    full ellipse given as one arc and seen in parts keeps one part across its seam."""
    n = len(c)
    r, a, b, cut = eye.arc_pieces(c[owner], U[owner], V[owner], lo, hi)
    e = owner[r]
    hid = np.zeros(n, dtype=bool)
    hid[e[cut]] = True
    arcs = np.bincount(owner, minlength=n)
    parts = np.bincount(e, minlength=n)
    keep = np.ones(len(e), dtype=bool)
    a, b = a.copy(), b.copy()
    for k in np.flatnonzero(full & (arcs == 1) & (parts > 1)).tolist():
        i0, i1 = np.searchsorted(e, [k, k + 1])
        j = np.searchsorted(owner, k)
        if a[i0] == lo[j] and b[i1 - 1] == hi[j]:  # one arc across the seam, first
            a[i0], b[i0] = a[i1 - 1], b[i0] + (hi[j] - lo[j])
            keep[i1 - 1] = False
    return e[keep], a[keep], b[keep], hid


def number_parts(features: list) -> None:
    """Number the image parts of each occluded (feature, segment) 0, 1, ... in order, in place, so that
    (source, segment, fragment) names one part even where the image border cut a part again."""
    seen: dict[tuple[int, int], int] = {}
    for f in features:
        if f.occluded and f.kind in ("line", "polyline"):
            key = (f.fid, f.segment)
            f.fragment = seen.get(key, 0)
            seen[key] = f.fragment + 1


def _rank(r: np.ndarray) -> np.ndarray:
    """Position of each element among the equal values of sorted r (0, 1, ... within each run)."""
    if len(r) == 0:
        return np.zeros(0, dtype=int)
    first = np.concatenate([[True], r[1:] != r[:-1]])
    start = np.maximum.accumulate(np.where(first, np.arange(len(r)), 0))
    return np.arange(len(r)) - start
