"""Recognition with pairwise geometric histograms (PGH), scored by the Bhattacharyya coefficient.

One histogram per reference segment (every straight piece of every stroke): for
every segment of the same view, the reference itself included, the relative
angle against the perpendicular distance of the segment's points from the
reference's infinite line, within `d_max` pixels. A segment adds its length,
spread over the distance bins it spans (the length of the part of it in each
bin), so cutting a segment into pieces leaves every histogram unchanged; the
reference adds itself at angle 0, distance 0, so a fragment of a line has the
histogram of the whole line. Distances are unsigned: a segment that crosses the
reference line counts on both sides at |d| (a signed variant would let rounding
move collinear pieces from one side to the other). Angles use the direction of
the stroke (the order its feature was declared in; a detector gets it from the
edge's contrast polarity): mirror-symmetric mode bins the unsigned angle between
the two directions, 0..pi; directed mode the signed one, -pi..pi. Angle bins are
centred on multiples of pi / n_angle, so parallel, anti-parallel and (n_angle
even) perpendicular pairs sit mid-bin, where rounding cannot move them.
Histograms are optionally blurred by Gaussian angle and distance errors, then
normalised to sum 1 and compared by the Bhattacharyya coefficient of the
paper's equation 1, sum_i sqrt(a_i b_i) (1.0 for identical histograms).
"""

from __future__ import annotations

import dataclasses
import math
import weakref
from dataclasses import dataclass

import numpy as np

from wiredsl import install_hint
from wiredsl.engine import geometry, visibility
from wiredsl.engine import imageset as im
from wiredsl.engine.simulate import simulate
from wiredsl.engine.trials import to_imageset
from wiredsl.measures.base import Measure, Params, param, segments, source_key

POINT_SPAN = 1e-6  # px: a segment spanning less distance than this (parallel to the reference) is a point mass
TIE = 1e-6  # scores this close to the best count as the best (float32 products, symmetric scenes)
PAIRS_PER_CHUNK = 1 << 20


class PGHParams(Params):
    d_max: float = param(100.0, "image", "distance limit from the reference line", gt=0, le=100000)
    n_dist: int = param(10, "number", "distance bins over 0..d_max", ge=1, le=1000)
    n_angle: int = param(12, "number", "angle steps over 0..pi (bins centred on multiples of pi / n_angle)",
                         ge=1, le=720)
    directed: bool = param(False, "number", "signed angles over -pi..pi instead of mirror-symmetric 0..pi")
    blur_angle: float = param(0.0, "angle", "standard deviation of the Gaussian angle blur", ge=0, le=math.pi)
    blur_dist: float = param(0.0, "image", "standard deviation of the Gaussian distance blur", ge=0, le=100000)
    viewpoints: int = param(4, "number", "rank the view-points nearest the robot, this many (0: every one)",
                            ge=0, le=100000)


def angle_bins(p: PGHParams) -> int:
    """Number of angle bins: n_angle + 1 (half-width end bins at 0 and pi) mirror-symmetric, 2 n_angle directed."""
    return 2 * p.n_angle if p.directed else p.n_angle + 1


def histograms(segs: np.ndarray, p: PGHParams, group: np.ndarray | None = None, engine: str = "auto") -> np.ndarray:
    """Normalised PGHs, shape (n, angle_bins, n_dist), of segments (n, 2, 2) (end points a, b).

    With `group` (n,) only segments of the same group see each other (e.g. the trials of a batch).
    `engine`: "numpy", "numba" (the compiled pair loop, `wiredsl[fast]`), or "auto" (numba when installed).
    """
    segs = np.asarray(segs, dtype=float).reshape(-1, 2, 2)
    if not (np.hypot(*(segs[:, 1] - segs[:, 0]).T) > 0).all():
        raise ValueError("every segment needs a positive, finite length (a direction)")
    group = np.zeros(len(segs), dtype=int) if group is None else np.asarray(group)
    h = raw_histograms(segs[:, 0], segs[:, 1], group, p, engine)
    h = blur(h, p)
    total = h.sum(axis=(1, 2), keepdims=True)
    return h / np.where(total > 0, total, 1.0)


def roots(segs: np.ndarray, p: PGHParams, group: np.ndarray | None = None, engine: str = "auto") -> np.ndarray:
    """Square roots of the normalised PGHs as rows (n, bins) (what the Bhattacharyya coefficient multiplies):
    `np.sqrt(flat(histograms(...)))`, fused in the compiled kernel when there is no blur (equal to the last bit)."""
    compiled = kernel() if engine != "numpy" else None
    if compiled is None or p.blur_angle > 0 or p.blur_dist > 0:
        return np.sqrt(flat(histograms(segs, p, group, engine)))
    segs = np.asarray(segs, dtype=float).reshape(-1, 2, 2)
    if not (np.hypot(*(segs[:, 1] - segs[:, 0]).T) > 0).all():
        raise ValueError("every segment needs a positive, finite length (a direction)")
    if len(segs) == 0:
        return np.zeros((0, angle_bins(p) * p.n_dist))
    group = np.zeros(len(segs), dtype=int) if group is None else np.asarray(group)
    order = np.argsort(group, kind="stable")
    g = group[order]
    bounds = np.flatnonzero(np.concatenate([[True], g[1:] != g[:-1], [True]]))
    return compiled.roots(np.ascontiguousarray(segs[order, 0]), np.ascontiguousarray(segs[order, 1]), bounds, order,
                          p.n_angle, p.directed, p.n_dist, p.d_max, POINT_SPAN)


def kernel():
    """The numba pair loop, or None without numba (imported on first use: it is slow to import)."""
    global _KERNEL
    if _KERNEL is None:
        try:
            from wiredsl.measures import pgh_kernel
        except ImportError:
            pgh_kernel = False
        _KERNEL = pgh_kernel
    return _KERNEL or None


_KERNEL = None


def raw_histograms(a: np.ndarray, b: np.ndarray, group: np.ndarray, p: PGHParams, engine: str = "auto"
                   ) -> np.ndarray:
    """Un-normalised, un-blurred PGHs (n, angle_bins, n_dist): the length of segment in each bin."""
    n = len(a)
    out = np.zeros((n, angle_bins(p), p.n_dist))
    if n == 0:
        return out
    order = np.argsort(group, kind="stable")
    g = np.asarray(group)[order]
    bounds = np.flatnonzero(np.concatenate([[True], g[1:] != g[:-1], [True]]))
    compiled = kernel() if engine != "numpy" else None
    if engine == "numba" and compiled is None:
        raise ImportError(f"the numba engine needs numba: {install_hint('fast')}")
    if compiled is not None:
        out[order] = compiled.histograms(np.ascontiguousarray(a[order]), np.ascontiguousarray(b[order]), bounds,
                                         p.n_angle, p.directed, p.n_dist, p.d_max, POINT_SPAN)
        return out
    sizes = np.diff(bounds)
    # chunks of whole groups, padded to the chunk's largest group, of at most PAIRS_PER_CHUNK pairs
    lo = 0
    while lo < len(sizes):
        hi, m = lo + 1, sizes[lo]
        while hi < len(sizes) and (hi + 1 - lo) * max(m, sizes[hi]) ** 2 <= PAIRS_PER_CHUNK:
            m = max(m, sizes[hi])
            hi += 1
        G = hi - lo
        local = np.arange(bounds[lo], bounds[hi]) - np.repeat(bounds[lo:hi], sizes[lo:hi])
        slot = np.repeat(np.arange(G), sizes[lo:hi]) * m + local  # row of each segment in the padded chunk
        pa, pb = np.zeros((G * m, 2)), np.zeros((G * m, 2))
        valid = np.zeros(G * m, dtype=bool)
        rows = order[bounds[lo]:bounds[hi]]
        pa[slot], pb[slot], valid[slot] = a[rows], b[rows], True
        out[rows] = _padded(pa.reshape(G, m, 2), pb.reshape(G, m, 2), valid.reshape(G, m), p)[slot]
        lo = hi
    return out


def _padded(a: np.ndarray, b: np.ndarray, valid: np.ndarray, p: PGHParams) -> np.ndarray:
    """PGHs (G m, angle_bins, n_dist) of G groups of m segments (a, b: (G, m, 2); `valid` marks real ones):
    every ordered pair (reference i, other j) within a group, as batched (G, m, m) arrays."""
    G, m = valid.shape
    na, nd = angle_bins(p), p.n_dist
    d = b - a
    length = np.where(valid, np.hypot(d[..., 0], d[..., 1]), 1.0)
    u = d / length[..., None]
    nrm = np.stack([-u[..., 1], u[..., 0]], axis=-1)
    D, w = p.d_max, p.d_max / nd
    # [g, i, j]: distances of j's ends from i's line
    base = (nrm * a).sum(-1)[..., None]
    da = nrm @ np.swapaxes(a, 1, 2) - base
    db = nrm @ np.swapaxes(b, 1, 2) - base
    lo, hi = np.minimum(da, db), np.maximum(da, db)
    # pairs wholly beyond d_max on one side contribute nothing: dropped before the rest of the work
    near = (lo <= D) & (hi >= -D) & valid[:, :, None] & valid[:, None, :]
    lo, hi = lo[near], hi[near]
    gi, i, j = np.nonzero(near)
    # the angle from i's direction to j's, from each segment's own direction angle, wrapped to (-pi, pi]
    phi = np.arctan2(u[..., 1], u[..., 0])
    theta = phi[gi, j] - phi[gi, i]
    theta = np.where(theta > math.pi, theta - 2 * math.pi, np.where(theta <= -math.pi, theta + 2 * math.pi, theta))
    step = math.pi / p.n_angle
    if p.directed:
        abin = np.floor(theta / step + 0.5).astype(int) % (2 * p.n_angle)
    else:
        abin = np.floor(np.abs(theta) / step + 0.5).astype(int)
    span = hi - lo
    L = length[gi, j]
    row = ((gi * m + i) * na + abin) * nd  # flat index of distance bin 0 of the pair's (reference, angle) row
    idx, wts = [], []
    # a segment parallel to the reference: its whole length at one distance
    point = span < POINT_SPAN
    x = np.abs(0.5 * (lo + hi))[point]
    inside = x <= D
    idx.append(row[point][inside] + np.minimum((x[inside] / w).astype(int), nd - 1))
    wts.append(L[point][inside])
    # otherwise a uniform density of length over [lo, hi], folded at 0: a segment crossing the line covers
    # [0, max |d|] once and [0, min |d|] a second time; one that does not, [min |d|, max |d|]
    sp = ~point
    rho, lo, hi, row = L[sp] / span[sp], lo[sp], hi[sp], row[sp]
    near_end, far_end = np.minimum(np.abs(lo), np.abs(hi)), np.maximum(np.abs(lo), np.abs(hi))
    crossing = (lo < 0) & (hi > 0)
    parts = ((np.where(crossing, 0.0, near_end), far_end, rho, row),
             (np.zeros(crossing.sum()), near_end[crossing], rho[crossing], row[crossing]))
    for x0, x1, r, rw in parts:
        x0, x1 = np.minimum(x0, D), np.minimum(x1, D)
        ok = x1 > x0
        x0, x1, r, rw = x0[ok], x1[ok], r[ok], rw[ok]
        ka = np.minimum((x0 / w).astype(int), nd - 1)
        kb = np.minimum((x1 / w).astype(int), nd - 1)
        one = ka == kb
        k = ~one
        idx += [rw[one] + ka[one], rw[k] + ka[k], rw[k] + kb[k]]
        wts += [r[one] * (x1[one] - x0[one]), r[k] * ((ka[k] + 1) * w - x0[k]), r[k] * (x1[k] - kb[k] * w)]
        between = np.where(k, kb - ka - 1, 0)  # bins strictly between get the density times the bin width
        if between.any():
            first = np.repeat(rw + ka + 1, between)
            idx.append(first + (np.arange(len(first)) - np.repeat(np.cumsum(between) - between, between)))
            wts.append(np.repeat(r * w, between))
    return np.bincount(np.concatenate(idx), weights=np.concatenate(wts), minlength=G * m * na * nd
                       ).reshape(G * m, na, nd)


def _normal_cdf(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.vectorize(math.erf, otypes=[float])(x / math.sqrt(2.0)))


def transfer_angle(p: PGHParams) -> np.ndarray:
    """(angle_bins, angle_bins): share of bin k's content (at its centre) that the angle blur moves to bin m."""
    na, step, s = angle_bins(p), math.pi / p.n_angle, p.blur_angle
    c = np.arange(na) * step
    lo, hi = c - step / 2, c + step / 2
    if not p.directed:  # the fold theta -> |theta|: bin m collects [lo, hi] and [-hi, -lo], clipped to 0..pi
        lo, hi = np.maximum(lo, 0.0), np.minimum(hi, math.pi)
        spans = [(lo, hi), (-hi, -lo)]
    else:
        spans = [(lo, hi)]
    T = np.zeros((na, na))
    for r in range(-3, 4):  # angles wrap around the circle
        for x0, x1 in spans:
            shift = 2 * math.pi * r
            T += (_normal_cdf((x1[None, :] + shift - c[:, None]) / s)
                  - _normal_cdf((x0[None, :] + shift - c[:, None]) / s))
    return T


def transfer_dist(p: PGHParams) -> np.ndarray:
    """(n_dist, n_dist): share of bin k's content (at its centre) that the distance blur moves to bin m;
    distances fold at 0 and what goes beyond d_max is lost."""
    nd, w, s = p.n_dist, p.d_max / p.n_dist, p.blur_dist
    c = (np.arange(nd) + 0.5) * w
    lo, hi = np.arange(nd) * w, (np.arange(nd) + 1) * w
    return sum(_normal_cdf((x1[None, :] - c[:, None]) / s) - _normal_cdf((x0[None, :] - c[:, None]) / s)
               for x0, x1 in ((lo, hi), (-hi, -lo)))


def blur(h: np.ndarray, p: PGHParams) -> np.ndarray:
    """Histograms (n, angle_bins, n_dist) blurred by the declared angle and distance errors."""
    if p.blur_angle > 0:
        h = np.einsum("nad,ab->nbd", h, transfer_angle(p))
    if p.blur_dist > 0:
        h = np.einsum("nad,de->nae", h, transfer_dist(p))
    return h


def flat(h: np.ndarray) -> np.ndarray:
    """Histograms (n, ...) as rows (n, bins), also when n is 0."""
    return h.reshape(len(h), int(np.prod(h.shape[1:])))


def bhattacharyya(h1: np.ndarray, h2: np.ndarray) -> np.ndarray:
    """Match scores (n1, n2) between normalised histograms h1 (n1, ...) and h2 (n2, ...): sum sqrt(a_i b_i)."""
    return np.sqrt(flat(h1)) @ np.sqrt(flat(h2)).T


# ----------------------------------------------------------------------------- the measure

@dataclass
class Reference:
    """The ideal PGHs of one view, ordered by source: square roots of the histograms (n, bins), the
    sources present (sorted) and where each one's rows start."""

    root: np.ndarray
    sources: np.ndarray
    starts: np.ndarray
    owner: np.ndarray | None = None  # (n,) index into `sources` of each row, for the compiled scoring

    @classmethod
    def of(cls, s: im.ImageSet, p: PGHParams) -> Reference:
        seg = segments(s)
        key = source_key(seg["fid"], seg["segment"])
        order = np.argsort(key, kind="stable")
        sources, starts = np.unique(key[order], return_index=True)
        root = roots(np.stack([seg["a"], seg["b"]], axis=1), p)[order]
        return cls(root, sources, starts, np.repeat(np.arange(len(sources)), np.diff([*starts, len(root)])))


def by_trial(trial: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows grouped by trial: (order, bounds), trial g's rows order[bounds[g]:bounds[g + 1]] (in row order)."""
    order = np.argsort(trial, kind="stable")
    t = trial[order]
    return order, np.flatnonzero(np.concatenate([[True], t[1:] != t[:-1], [True]])) if len(t) else np.zeros(1, int)


@dataclass
class Database:
    """The ideal PGH sets of candidate view-points for one pose and camera (float32 roots, by view-point)."""

    root: np.ndarray  # (N, bins)
    owner: np.ndarray  # (N,) candidate index of each row, sorted
    n: int  # candidates
    truth: int  # candidate index of the nearest view-point


@dataclass
class Prepared:
    views: dict  # (pose index, side) -> Reference
    databases: dict  # (pose index, side) -> Database


class PGH(Measure):
    name = "pgh"
    Params = PGHParams
    statistics = ("match", "recognition", "viewpoint", "viewpoint_cameras")
    pooled = True  # each trial's values from its own features only
    # viewpoint is defined only where a camera has a view-point mesh to rank: weighted by those cameras, a scene
    # without a mesh gets no viewpoint row (not a 0 that reads as "never located")
    weights = {"viewpoint": "viewpoint_cameras"}
    units = {"match": "fraction", "recognition": "fraction", "viewpoint": "fraction", "viewpoint_cameras": "count"}
    doc = __doc__

    @classmethod
    def prepare(cls, p: PGHParams, run) -> Prepared:
        views, databases = {}, {}
        ideal = run.ideal()
        for result in ideal:
            for side in ("left", "right"):
                view = getattr(result, side)
                if view is not None:
                    views[(result.index, side)] = Reference.of(to_imageset(view, run.world), p)
        vp = run.scene.viewpoints
        if vp is None or not vp.points:
            return Prepared(views, databases)
        points = np.array(vp.points, dtype=float).reshape(-1, 2)
        sets: dict[float, dict] = {}
        for result in ideal:
            x, y, heading = geometry.floor_pose(result.pose)
            if heading not in sets:  # the ideal view from every view-point, with this heading
                sets[heading] = _viewpoint_views(run, points, heading, p)
            xy = np.array([x, y])[None]
            truth = int(visibility.nearest_viewpoint(points, xy)[0])
            order = np.argsort(((points - xy) ** 2).sum(1), kind="stable")
            chosen = order[:p.viewpoints] if p.viewpoints else np.arange(len(points))
            if truth not in chosen:  # equidistant ties: the nearest view-point always competes
                chosen = np.concatenate([[truth], chosen[:-1]])
            chosen = np.sort(chosen)
            for side, refs in sets[heading].items():
                rows = [refs[v] for v in chosen]
                root = np.concatenate([r.root for r in rows]).astype(np.float32)
                databases[(result.index, side)] = Database(
                    root, np.repeat(np.arange(len(chosen)), [len(r.root) for r in rows]),
                    len(chosen), int(np.flatnonzero(chosen == truth)[0]))
        return Prepared(views, databases)

    @classmethod
    def measure(cls, p: PGHParams, prepared: Prepared, pose, disturbed: dict[str, im.ImageSet],
                n_trials: int) -> dict[str, np.ndarray]:
        total = np.zeros(n_trials)
        matched = np.zeros(n_trials)
        recognised = np.zeros(n_trials)
        located = np.zeros(n_trials)
        cameras = 0
        for side, s in disturbed.items():
            ref = prepared.views.get((pose.index, side))
            if ref is None:
                continue
            seg = segments(s)
            db = prepared.databases.get((pose.index, side))
            cameras += db is not None
            if len(seg["a"]) == 0:
                continue
            root = roots(np.stack([seg["a"], seg["b"]], axis=1), p, group=seg["trial"])
            L, trial = seg["length"], seg["trial"]
            groups = by_trial(trial)
            own, recog = _own_scores(root, source_key(seg["fid"], seg["segment"]), ref, groups)
            total += np.bincount(trial, weights=L, minlength=n_trials)
            matched += np.bincount(trial, weights=L * own, minlength=n_trials)
            recognised += np.bincount(trial, weights=L * recog, minlength=n_trials)
            if db is not None:
                located += _located(root, L, trial, n_trials, db, groups)
        some = total > 0
        return {"match": np.where(some, matched / np.where(some, total, 1.0), 0.0),
                "recognition": np.where(some, recognised / np.where(some, total, 1.0), 0.0),
                "viewpoint": located / max(cameras, 1), "viewpoint_cameras": np.full(n_trials, float(cameras))}


def _own_scores(root: np.ndarray, key: np.ndarray, ref: Reference, groups: tuple | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Each disturbed segment's best score among its own source's ideal segments (0 if none), and
    whether that is the best score among all ideal segments of the view (within TIE)."""
    K = len(ref.sources)
    if K == 0:
        return np.zeros(len(root)), np.zeros(len(root), dtype=bool)
    compiled = kernel()
    if compiled is not None and groups is not None:  # a product a trial: the same whatever shares the call
        return compiled.own_scores(np.ascontiguousarray(root), np.ascontiguousarray(key, dtype=np.int64), *groups,
                                   _transposed(ref), ref.owner, ref.sources, TIE)
    best = np.maximum.reduceat(root @ ref.root.T, ref.starts, axis=1)  # (M, K): best score per source
    col = np.minimum(np.searchsorted(ref.sources, key), K - 1)
    has = ref.sources[col] == key
    rows = np.arange(len(root))
    own = best[rows, col]
    best[rows, col] = -1.0
    other = best.max(axis=1)  # the best of every other source
    return np.where(has, own, 0.0), has & (own >= other - TIE)


def _located(root: np.ndarray, L: np.ndarray, trial: np.ndarray, n_trials: int, db: Database,
             groups: tuple | None = None) -> np.ndarray:
    """Per trial, 1.0 when the nearest view-point's ideal PGH set scores highest (within TIE), else 0.

    A set's score is the length-weighted mean over the disturbed segments of each one's best match in the set.
    """
    compiled = kernel()
    if compiled is not None and groups is not None:  # a product a trial: the same whatever shares the call
        score, w = compiled.located_scores(np.ascontiguousarray(root, dtype=np.float32), np.ascontiguousarray(L),
                                           np.ascontiguousarray(trial, dtype=np.int64), *groups, n_trials,
                                           _transposed(db), db.owner.astype(np.int64), db.n)
        score /= np.where(w > 0, w, 1.0)[:, None]
        return ((w > 0) & (score[:, db.truth] >= score.max(axis=1) - TIE)).astype(float)
    score = np.zeros((n_trials, db.n))
    if len(db.root):
        S = root.astype(np.float32) @ db.root.T
        starts = np.flatnonzero(np.concatenate([[True], db.owner[1:] != db.owner[:-1]]))
        best = np.maximum.reduceat(S, starts, axis=1).astype(float)  # (M, view-points with segments)
        cols = db.owner[starts]
        for c, column in zip(cols, best.T, strict=True):
            score[:, c] = np.bincount(trial, weights=L * column, minlength=n_trials)
    w = np.bincount(trial, weights=L, minlength=n_trials)
    score /= np.where(w > 0, w, 1.0)[:, None]
    return ((w > 0) & (score[:, db.truth] >= score.max(axis=1) - TIE)).astype(float)


def _transposed(ref) -> np.ndarray:
    """A Reference's or Database's roots as a C-contiguous (bins, rows) array, made once and kept on it."""
    t = getattr(ref, "_t", None)
    if t is None:
        t = np.ascontiguousarray(ref.root.T)
        object.__setattr__(ref, "_t", t)
    return t


# the view-points' ideal views depend only on the nominal scene and the projection options, not on a run's
# effects: kept per World (by identity, while it lives) for the design points of a study
_VIEWS: dict[int, tuple[weakref.ref, dict]] = {}


def _viewpoint_views(run, points: np.ndarray, heading: float, p: PGHParams) -> dict[str, list[Reference]]:
    """The left camera's ideal PGH set with the robot on each view-point, facing `heading`."""
    scene = run.scene
    key = (heading, run.options.tolerance, run.options.visibility, scene.source,
           *(m.model_dump_json() for m in (scene.rig, scene.viewpoints, *scene.cameras)))
    ref, cache = _VIEWS.get(id(run.world), (None, None))
    if ref is None or ref() is not run.world:
        for k in [k for k, (r, _) in _VIEWS.items() if r() is None]:
            del _VIEWS[k]
        cache = {}
        _VIEWS[id(run.world)] = (weakref.ref(run.world), cache)
    if key not in cache:
        # a view-point's ideal view is of a robot standing on it: the path's times (its motion) are not its
        path = scene.path.model_copy(update={"poses": [(float(x), float(y), heading) for x, y in points],
                                            "transforms": None, "times": None, "speed": None})
        options = dataclasses.replace(run.options, poses=None, right=False)
        results = simulate(scene.model_copy(update={"path": path}), options, run.world)
        cache[key] = [to_imageset(r.left, run.world) for r in results]
    return {"left": [Reference.of(s, p) for s in cache[key]]}
