"""A batch of image features in packed arrays: what the uncertainty effects act on.

Edge features are *strokes*: polylines in a CSR layout (all vertices in `pts`,
stroke k's vertices are pts[start[k]:start[k+1]]), with per-stroke metadata.
A straight image segment is a 2-vertex stroke. Strokes of every trial of a
batch are packed together (`trial` says whose), so each effect is a handful of
vectorised operations over all strokes of all trials.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from wiredsl.engine import geometry

STRAIGHT, CURVE, ELLIPSE = 0, 1, 2  # stroke kinds: a segment; a curved image of a line; an ellipse (arc)


@dataclass(frozen=True)
class ImageSet:
    pts: np.ndarray  # (N, 2) float
    start: np.ndarray  # (S + 1,) int
    fid: np.ndarray  # (S,) feature id (World.feature_ids)
    segment: np.ndarray  # (S,) segment within a polyline / silhouette side, -1 if none
    fragment: np.ndarray  # (S,) fragment index after edge loss / splits, -1 if whole
    kind: np.ndarray  # (S,) STRAIGHT | CURVE | ELLIPSE
    clipped: np.ndarray  # (S,) bool
    closed: np.ndarray  # (S,) bool: last vertex joins the first
    trial: np.ndarray  # (S,) trial index within the batch
    corners: np.ndarray  # (C, 2)
    corner_fid: np.ndarray  # (C,)
    corner_trial: np.ndarray  # (C,)
    occluded: np.ndarray | None = None  # (S,) bool: a visible part of a feature occlusion cut; None: all False

    def __post_init__(self):
        if self.occluded is None:
            object.__setattr__(self, "occluded", np.zeros(len(self.start) - 1, dtype=bool))

    @property
    def n_strokes(self) -> int:
        return len(self.start) - 1

    @property
    def counts(self) -> np.ndarray:
        return np.diff(self.start)

    def vertex_stroke(self) -> np.ndarray:
        """Stroke index of every vertex, (N,)."""
        return np.repeat(np.arange(self.n_strokes), self.counts)

    def take(self, keep: np.ndarray) -> ImageSet:
        """Only the strokes where keep (S,) is True."""
        keep = np.asarray(keep, dtype=bool)
        counts = self.counts[keep]
        vkeep = np.repeat(keep, self.counts)
        start = np.concatenate([[0], np.cumsum(counts)]).astype(int)
        return replace(self, pts=self.pts[vkeep], start=start, **_meta(self, keep))

    def take_corners(self, keep: np.ndarray) -> ImageSet:
        return replace(self, corners=self.corners[keep], corner_fid=self.corner_fid[keep],
                       corner_trial=self.corner_trial[keep])

    def repeat_trials(self, n: int) -> ImageSet:
        """The same features for n trials (0..n-1), strokes ordered by trial."""
        S, N, C = self.n_strokes, len(self.pts), len(self.corners)
        start = (self.start[:-1][None, :] + N * np.arange(n)[:, None]).ravel()
        return ImageSet(
            pts=np.tile(self.pts, (n, 1)), start=np.concatenate([start, [N * n]]).astype(int),
            fid=np.tile(self.fid, n), segment=np.tile(self.segment, n), fragment=np.tile(self.fragment, n),
            kind=np.tile(self.kind, n), clipped=np.tile(self.clipped, n), closed=np.tile(self.closed, n),
            trial=np.repeat(np.arange(n), S), corners=np.tile(self.corners, (n, 1)),
            corner_fid=np.tile(self.corner_fid, n), corner_trial=np.repeat(np.arange(n), C),
            occluded=np.tile(self.occluded, n))


_META = ("fid", "segment", "fragment", "kind", "clipped", "closed", "trial", "occluded")


def _meta(s: ImageSet, index) -> dict:
    return {k: getattr(s, k)[index] for k in _META}


def empty() -> ImageSet:
    z = np.zeros(0, dtype=int)
    return ImageSet(np.zeros((0, 2)), np.zeros(1, dtype=int), z, z, z, z, z.astype(bool), z.astype(bool), z,
                    np.zeros((0, 2)), z, z)


def concat(sets: list[ImageSet], per_set: int) -> ImageSet:
    """One ImageSet from several of `per_set` trials each (several views' batches): trial k of set i gets batch
    index i * per_set + k, so that the strokes stay ordered by batch index."""
    offsets = np.cumsum([0] + [len(s.pts) for s in sets])
    cat = lambda name: np.concatenate([getattr(s, name) for s in sets])  # noqa: E731
    return ImageSet(
        pts=np.concatenate([s.pts for s in sets]).reshape(-1, 2),
        start=np.concatenate([s.start[:-1] + o for s, o in zip(sets, offsets, strict=False)] + [offsets[-1:]]),
        fid=cat("fid"), segment=cat("segment"), fragment=cat("fragment"), kind=cat("kind"), clipped=cat("clipped"),
        closed=cat("closed"), trial=np.concatenate([s.trial + i * per_set for i, s in enumerate(sets)]),
        corners=np.concatenate([s.corners for s in sets]).reshape(-1, 2), corner_fid=cat("corner_fid"),
        corner_trial=np.concatenate([s.corner_trial + i * per_set for i, s in enumerate(sets)]),
        occluded=cat("occluded"))


def split(s: ImageSet, n: int, per_set: int) -> list[ImageSet]:
    """The inverse of `concat`: the n sets of `per_set` trials each (batch indices i * per_set .. back to 0..),
    each a slice of `s`'s arrays."""
    bounds = np.arange(n + 1) * per_set
    cut = np.searchsorted(s.trial, bounds).tolist()
    corner_cut = np.searchsorted(s.corner_trial, bounds).tolist()
    out = []
    for i in range(n):
        a, b, c, d = cut[i], cut[i + 1], corner_cut[i], corner_cut[i + 1]
        start = s.start[a:b + 1]
        out.append(ImageSet(
            pts=s.pts[start[0]:start[-1]], start=start - start[0], fid=s.fid[a:b], segment=s.segment[a:b],
            fragment=s.fragment[a:b], kind=s.kind[a:b], clipped=s.clipped[a:b], closed=s.closed[a:b],
            trial=s.trial[a:b] - i * per_set, corners=s.corners[c:d], corner_fid=s.corner_fid[c:d],
            corner_trial=s.corner_trial[c:d] - i * per_set, occluded=s.occluded[a:b]))
    return out


def segmented_cumsum(values: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Running sums of `values` (N,) restarting at every stroke start (CSR `start`), each stroke summed on
    its own in order: a stroke's sums do not depend on the strokes packed before it (replay holds bit
    for bit whatever the batch). Strokes are padded by length class (at most 2x) and summed row-wise."""
    out = np.empty(len(values))
    counts = np.diff(start)
    if len(values) == 0:
        return out
    width = 1 << np.ceil(np.log2(np.maximum(counts, 1))).astype(int)
    for w in geometry.distinct(width[counts > 0]):
        rows = np.flatnonzero((width == w) & (counts > 0))
        c = counts[rows]
        col = np.arange(w)
        mask = col[None, :] < c[:, None]
        idx = start[rows][:, None] + col[None, :]
        block = np.zeros((len(rows), w))
        block[mask] = values[idx[mask]]
        out[idx[mask]] = np.cumsum(block, axis=1)[mask]
    return out


def arc_lengths(s: ImageSet) -> tuple[np.ndarray, np.ndarray]:
    """Cumulative arc length at each vertex from its stroke's start (N,), and stroke lengths (S,)."""
    if len(s.pts) == 0:
        return np.zeros(0), np.zeros(s.n_strokes)
    d = np.diff(s.pts, axis=0)
    seg = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])
    seg_len = np.concatenate([[0.0], seg])
    nonempty = s.counts > 0
    seg_len[s.start[:-1][nonempty]] = 0.0  # no length across a stroke boundary
    arc = segmented_cumsum(seg_len, s.start)
    lengths = np.zeros(s.n_strokes)
    lengths[nonempty] = arc[s.start[1:][nonempty] - 1]
    return arc, lengths


def search(arc: np.ndarray, lo: np.ndarray, hi: np.ndarray, target: np.ndarray, side: str) -> np.ndarray:
    """np.searchsorted of each target within its own stroke's arc[lo:hi] (vectorised bisection): unlike a
    search over one global key, exact whatever else is packed in the batch."""
    lo, hi = lo.copy(), hi.copy()
    while True:
        active = lo < hi
        if not active.any():
            return lo
        mid = (lo + hi) // 2
        v = arc[np.minimum(mid, len(arc) - 1)]
        right = (v < target) if side == "left" else (v <= target)
        go = active & right
        stay = active & ~right
        lo = np.where(go, mid + 1, lo)
        hi = np.where(stay, mid, hi)


def unroll_closed(s: ImageSet, which: np.ndarray | None = None) -> ImageSet:
    """Closed strokes (those of `which`, default all) as open ones traversed twice (vertex 0 .. last,
    0 .. last, 0), so that any arc of length <= L starting in [0, L) is a single interval."""
    which = s.closed if which is None else s.closed & which
    if not which.any():
        return s
    counts = s.counts
    new_counts = np.where(which, 2 * counts + 1, counts)
    start = np.concatenate([[0], np.cumsum(new_counts)]).astype(int)
    k = np.repeat(np.arange(s.n_strokes), new_counts)  # the stroke of every output vertex
    i = np.arange(start[-1]) - start[:-1][k]  # its position within the output stroke
    src = s.start[:-1][k] + i % np.maximum(counts[k], 1)
    return replace(s, pts=s.pts[src], start=start, closed=s.closed & ~which)


def keep_intervals(s: ImageSet, stroke: np.ndarray, a: np.ndarray, b: np.ndarray, fragment: np.ndarray,
                   closed: np.ndarray | None = None, cut: np.ndarray | None = None,
                   whole: np.ndarray | None = None) -> ImageSet:
    """New strokes: the parts of strokes `stroke` (K,) between arc lengths a and b (K,).

    Each part starts and ends at interpolated points and keeps the stroke's metadata, with `fragment`
    and `closed` set and `clipped` or-ed with `cut`; parts shorter than 1e-9 px are dropped. A part
    marked `whole` is its stroke's vertices verbatim (a and b unused): a stroke left uncut is exactly
    itself, whatever else is cut in the batch.
    """
    arc, lengths = arc_lengths(s)
    K = len(stroke)
    whole = np.zeros(K, dtype=bool) if whole is None else np.asarray(whole, dtype=bool)
    a = np.where(whole, 0.0, np.clip(a, 0.0, lengths[stroke]))
    b = np.where(whole, lengths[stroke], np.clip(b, 0.0, lengths[stroke]))
    ok = whole | (b - a > 1e-9)  # a whole stroke is kept as it is, even if degenerate
    stroke, a, b, fragment, whole = stroke[ok], a[ok], b[ok], np.asarray(fragment)[ok], whole[ok]
    closed = np.zeros(len(stroke), dtype=bool) if closed is None else np.asarray(closed, dtype=bool)[ok]
    cut = np.zeros(len(stroke), dtype=bool) if cut is None else np.asarray(cut, dtype=bool)[ok]
    if len(stroke) == 0:
        out = empty()
        return replace(out, corners=s.corners, corner_fid=s.corner_fid, corner_trial=s.corner_trial)
    first, last = s.start[stroke], s.start[stroke + 1] - 1
    lo = search(arc, first, last + 1, a, "right")  # first vertex strictly after a
    hi = search(arc, first, last + 1, b, "left")  # first vertex at or after b

    def point_at(target):
        j = np.clip(search(arc, first, last + 1, target, "right") - 1, first, np.maximum(last - 1, first))
        j1 = np.minimum(j + 1, last)
        span = arc[j1] - arc[j]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(span > 0, (target - arc[j]) / span, 0.0)
        return s.pts[j] + t[:, None] * (s.pts[j1] - s.pts[j])

    ends = ~whole  # parts with interpolated end points
    run_lo = np.where(whole, first, lo)  # then a run of the stroke's own vertices
    run_n = np.where(whole, last + 1 - first, np.maximum(hi - lo, 0))
    counts = run_n + 2 * ends
    start = np.concatenate([[0], np.cumsum(counts)]).astype(int)
    out = np.empty((start[-1], 2))
    out[start[:-1][ends]] = point_at(a)[ends]
    out[start[1:][ends] - 1] = point_at(b)[ends]
    n = int(run_n.sum())
    if n:
        within = np.arange(n) - np.repeat(np.cumsum(run_n) - run_n, run_n)
        out[np.repeat(start[:-1] + ends, run_n) + within] = s.pts[np.repeat(run_lo, run_n) + within]
    meta = _meta(s, stroke)
    meta["fragment"] = fragment
    meta["closed"] = closed
    meta["clipped"] = meta["clipped"] | cut
    return replace(s, pts=out, start=start, **meta)


def keep_vertex_runs(s: ImageSet, ok: np.ndarray) -> ImageSet:
    """Strokes cut to their runs of vertices where ok (N,) holds; cut strokes are flagged `clipped`."""
    if ok.all():
        return s
    n = len(ok)
    stroke_of = s.vertex_stroke()
    first = np.zeros(n, dtype=bool)
    first[s.start[:-1][s.counts > 0]] = True
    last = np.zeros(n, dtype=bool)
    last[s.start[1:][s.counts > 0] - 1] = True
    begins = ok & (first | ~np.concatenate([[False], ok[:-1]]))
    ends = ok & (last | ~np.concatenate([ok[1:], [False]]))
    b_idx, e_idx = np.flatnonzero(begins), np.flatnonzero(ends)
    arc, _ = arc_lengths(s)  # the same measure keep_intervals uses (invalid vertices only need be finite)
    stroke = stroke_of[b_idx]
    whole = first[b_idx] & last[e_idx]
    return keep_intervals(s, stroke, arc[b_idx], arc[e_idx], np.where(whole, s.fragment[stroke], 0),
                          closed=whole & s.closed[stroke], cut=~whole, whole=whole)


def clip_rect(s: ImageSet, width, height) -> ImageSet:
    """Strokes cut to the image rectangle [0, width] x [0, height] (numbers, or arrays of one a vertex: views of
    several cameras); cut strokes are flagged `clipped`."""
    x, y = s.pts[:, 0], s.pts[:, 1]
    if len(x) == 0 or (x.min() >= 0 and y.min() >= 0 and np.all(x <= width) and np.all(y <= height)):
        return s
    from wiredsl.engine.geometry import clip_segments_rect

    n = len(s.pts)
    if np.ndim(width):  # a pair of vertices is cut to its first vertex's image (pairs across strokes are not used)
        width, height = width[:-1], height[:-1]
    t0, t1, keep = clip_segments_rect(s.pts[:-1], s.pts[1:], width, height)
    last = s.start[1:] - 1
    real = np.ones(n - 1, dtype=bool)
    real[last[last < n - 1]] = False  # pairs that straddle two strokes
    keep &= real & (t1 > t0)
    first_pair = np.zeros(n - 1, dtype=bool)
    first_pair[s.start[:-1][s.start[:-1] < n - 1]] = True
    last_pair = np.zeros(n - 1, dtype=bool)
    lp = last - 1
    last_pair[lp[(lp >= 0) & (lp < n - 1)]] = True
    prev_joins = np.zeros(n - 1, dtype=bool)  # pair j continues pair j - 1 without a cut
    prev_joins[1:] = keep[:-1] & keep[1:] & (t1[:-1] >= 1) & (t0[1:] <= 0) & ~first_pair[1:]
    begins = keep & ~prev_joins
    ends = keep & ~np.concatenate([prev_joins[1:], [False]])
    j, k = np.flatnonzero(begins), np.flatnonzero(ends)
    arc, lengths = arc_lengths(s)
    seg_len = np.linalg.norm(s.pts[1:] - s.pts[:-1], axis=1)
    stroke = s.vertex_stroke()[j]
    a = arc[j] + t0[j] * seg_len[j]
    b = arc[k] + t1[k] * seg_len[k]
    whole = first_pair[j] & (t0[j] <= 0) & last_pair[k] & (t1[k] >= 1)
    return keep_intervals(s, stroke, a, b, np.where(whole, s.fragment[stroke], np.maximum(s.fragment[stroke], 0)),
                          closed=whole & s.closed[stroke], cut=~whole, whole=whole)


STEP_PX = 1e-9  # a step shorter than this has no direction (a cut's copy of a vertex, rounding apart)


def vertex_normals(s: ImageSet) -> np.ndarray:
    """Unit normal at each vertex (N, 2): the direction of travel turned +90 deg, averaged at joins.

    A step shorter than STEP_PX has no direction: its direction would be that of the rounding between a
    vertex and its copy (different on different CPUs), so a stroke end's copy of a vertex takes the normal
    of the nearest vertex of its stroke that has a real step (the next, else the previous)."""
    n = len(s.pts)
    if n == 0:
        return np.zeros((0, 2))
    d = np.diff(s.pts, axis=0)
    length = np.linalg.norm(d, axis=1, keepdims=True)
    last = s.start[1:] - 1
    valid = length[:, 0] > STEP_PX
    valid[last[last < n - 1]] = False  # the step from one stroke's end to the next stroke's start
    u = np.divide(d, length, out=np.zeros_like(d), where=valid[:, None])
    tangent = np.zeros((n, 2))
    tangent[:-1] += u
    tangent[1:] += u
    stepped = np.zeros(n, dtype=bool)
    stepped[:-1] |= valid
    stepped[1:] |= valid
    if not stepped.all():
        idx = np.arange(n)
        stroke = s.vertex_stroke()
        nxt = np.minimum.accumulate(np.where(stepped, idx, n)[::-1])[::-1]
        prv = np.maximum.accumulate(np.where(stepped, idx, -1))
        nxt_ok = nxt < n
        nxt_ok[nxt_ok] = stroke[nxt[nxt_ok]] == stroke[nxt_ok]
        prv_ok = prv >= 0
        prv_ok[prv_ok] = stroke[prv[prv_ok]] == stroke[prv_ok]
        src = np.where(nxt_ok, nxt, np.where(prv_ok, prv, idx))
        tangent = np.where(stepped[:, None], tangent, tangent[src])
    norm = np.linalg.norm(tangent, axis=1, keepdims=True)
    tangent = np.divide(tangent, norm, out=np.zeros_like(tangent), where=norm > 0)
    return np.column_stack([-tangent[:, 1], tangent[:, 0]])
