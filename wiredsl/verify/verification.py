"""The paper's verification of projected models against detected features (Coupe and Thacker, CRV 2008, as
Tian, Thacker and Stancu describe it; their Figure 7).

For each image the scene is projected by the engine with hidden lines removed (`--visibility exact`). Every
visible stroke is sampled along its length every `step` px; from each sample the detected edges are searched
along the stroke's normal within +-`band` px for the nearest edge pixel whose gradient lies within `angle`
of that normal (either polarity). A sample is verified when one is found; its signed lateral offset (along
the normal n = (-t_y, t_x) of the stroke's direction t) is refined to sub-pixel: along the gradient by a
parabola through the gradient magnitude (an edge map), or exactly to the segment's line (LSD).

Corners: a model corner is found when a detected corner lies within `radius` px (the paper's 10 px); its
localisation error is that distance. In a stereo pair, each found left corner is matched among the right
image's detected corners within `radius` of where the model puts it, by normalised cross-correlation of
patches (the standard matcher); the match is wrong when it is not the right corner nearest the model's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from wiredsl.verify.detectors import Detection, angle_ok, segment_gradients

STEP = 2.0  # px between samples along a stroke
BAND = 6.0  # px searched either side of a sample along its normal
ANGLE = math.radians(20.0)  # largest angle between the detected gradient and the model's normal
RADIUS = 10.0  # px: the paper's corner match search radius
BORDER = 2.0  # px: samples nearer the image's border are not tested (detectors see nothing there)
GOLDEN = 0.6180339887498949  # the sample grids' phases: (i + 1) * GOLDEN mod 1 for stroke i
RUN_TRIM = 2.0  # px at each end of a run left out of its offsets
END_TRIM = 6.0  # px at each end of a model stroke left out of its runs' offsets: there it meets other edges (a
# junction, a silhouette's tangent to its rim), and the detected edge bends off it
JUNCTION = 6.0  # px: samples this near another stroke's end are left out of the loss and offset statistics: there
# (a silhouette's tangent to its rim, a T-junction where an occluded edge meets its occluder, a corner of two
# lines) the detector's response bends off the model's strokes and loses a pixel or two that no effect removed (on
# the cylinders with nothing injected, every middle loss lay within 4 px of one); and only a free end (no other's
# within JUNCTION, not a closed stroke's seam) measures the detector's own loss at an end, what a gap's ends lose
CORR_PX = 8.0  # px: the longest lag of the residuals' correlation counted in a run mean's noise
PATCH = 5  # half size of the correlation patches of the stereo corner matcher (11 x 11)


@dataclass
class Settings:
    step: float = STEP
    band: float = BAND
    angle: float = ANGLE
    radius: float = RADIUS
    inlier: float = 2.0  # px: a found corner farther than this from the model's is displaced (a mismatch)
    margin: float = 3.0  # px at each end of a stroke where the detector's own end loss is measured


@dataclass
class Strokes:
    """A view's visible model strokes (lines and polylines; conics are duplicates of polylines)."""

    pts: np.ndarray  # (V, 2) pixels
    start: np.ndarray  # (S + 1,) vertex offsets
    fid: np.ndarray  # (S,) feature index into world.feature_ids
    segment: np.ndarray  # (S,)
    part: np.ndarray  # (S,) occlusion part (fragment), -1 whole
    ellipse: np.ndarray | None = None  # (S,) bool: the stroke is an ellipse's (whole, or a visible arc of it)

    @property
    def n(self) -> int:
        return len(self.fid)


def strokes_of(view, ellipses: set | None = None) -> Strokes:
    """`ellipses`: the world's ellipse feature ids (None: those with a conic in the view, whole ellipses)."""
    feats = [f for f in view.features if f.kind in ("line", "polyline") and len(f.points) >= 2]
    counts = np.array([len(f.points) for f in feats], dtype=int)
    start = np.concatenate([[0], np.cumsum(counts)])
    pts = np.concatenate([f.points for f in feats]).astype(float) if feats else np.zeros((0, 2))
    conics = ellipses if ellipses is not None else {f.fid for f in view.features if f.kind == "conic"}
    return Strokes(pts, start, np.array([f.fid for f in feats], int), np.array([f.segment for f in feats], int),
                   np.array([f.fragment for f in feats], int),
                   np.array([f.kind == "polyline" and f.fid in conics for f in feats], bool))


def ellipse_halves(st: Strokes, sm: Samples, m: EdgeMatch | None = None) -> np.ndarray:
    """(n,) int: which side of a principal axis each sample of an ellipse's stroke lies on (0 or 1; 0 for other
    strokes, -1 for an ellipse's samples in no fragment). The lateral shift moves an ellipse's stroke in pieces
    cut where it crosses its own major axis (the principal axis of its chords: effects.lateral_shift.
    split_ellipses), each piece by its own offset, so the fit's fragments are cut there too: a run across a tip
    averaged two shifts. The shift cuts what edge_loss left of the stroke, so with the match `m` each fragment
    (a stretch of verified samples, junction samples counted in, a closed stroke's last and first joined) is cut
    at its own axis, as the effect cut it; without, the whole stroke at its axis."""
    out = np.zeros(len(sm.stroke), int)
    if st.ellipse is None or not st.ellipse.any():
        return out
    alive = None if m is None else (m.verified & m.tested) | (sm.junction if sm.junction is not None else False)
    for k in np.flatnonzero(st.ellipse).tolist():
        at = np.flatnonzero(sm.stroke == k)
        if len(at) < 3:
            continue
        if alive is None:
            groups = [at]
        else:
            a = alive[at]
            label = np.cumsum(a & ~np.concatenate([[False], a[:-1]])) * a  # 1, 2, ... per stretch, 0 lost
            P0, P1 = st.pts[st.start[k]], st.pts[st.start[k + 1] - 1]
            if a[0] and a[-1] and label[-1] != 1 and np.hypot(*(P0 - P1)) < 1e-6:
                label[label == label[-1]] = 1  # a closed stroke's last stretch goes on into its first
            groups = [at[label == j] for j in range(1, int(label.max(initial=0)) + 1)]
        if alive is not None:
            out[at] = -1  # in no fragment (lost): no piece
        for g in groups:
            if len(g) < 3:
                continue
            X = sm.P[g] - sm.P[g].mean(axis=0)  # equally spaced samples: their mean is the chords' by length
            minor = np.linalg.eigh(X.T @ X)[1][:, 0]  # the eigenvector of the smaller eigenvalue: across the axis
            out[g] = (X @ minor > 0).astype(int)
    return out


def corners_of(view) -> tuple[np.ndarray, np.ndarray]:
    """(fid (C,), uv (C, 2)) of a view's visible model corners."""
    cs = [f for f in view.features if f.kind == "corner"]
    return (np.array([f.fid for f in cs], int),
            np.array([f.points[0] for f in cs], float).reshape(-1, 2))


@dataclass
class Samples:
    """Points along strokes: position P, unit normal N, their stroke, arc position s; per stroke its length L;
    `junction`: the samples at another stroke's end inside their own (`junctions`), left out of the statistics."""

    P: np.ndarray
    N: np.ndarray
    stroke: np.ndarray
    s: np.ndarray
    L: np.ndarray
    junction: np.ndarray | None = None
    free: np.ndarray | None = None  # (S, 2) bool: the stroke's start and end are free ends (`junctions`)


def junctions(st: Strokes, P: np.ndarray, stroke: np.ndarray, s: np.ndarray, L: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """((n,) bool, (S, 2) bool): the samples at junctions (within JUNCTION px of another stroke's end, END_TRIM px
    or more from their own stroke's ends), and which
    strokes' ends are free: meeting no other stroke (no other's end or sample within JUNCTION px), and not the seam
    of a closed stroke (its first vertex its last)."""
    from scipy.spatial import cKDTree

    S = st.n
    ends = np.concatenate([st.pts[st.start[:-1]], st.pts[st.start[1:] - 1]]) if S else np.zeros((0, 2))
    owner = np.concatenate([np.arange(S), np.arange(S)])
    closed = np.hypot(*(ends[:S] - ends[S:]).T) < 1e-6 if S else np.zeros(0, bool)
    free = np.tile(~closed[:, None], (1, 2))
    out = np.zeros(len(P), bool)
    if S < 2:
        return out, free
    tree = cKDTree(ends)
    k = min(3, len(ends))  # a stroke has two ends: among the three nearest, one is another's where any is near

    def near_other(X, own):
        dist, idx = tree.query(X, k=k, distance_upper_bound=JUNCTION)
        dist, idx = dist.reshape(len(X), k), idx.reshape(len(X), k)
        return (np.isfinite(dist) & (owner[np.minimum(idx, len(ends) - 1)] != own[:, None])).any(axis=1)

    meets = near_other(ends, owner)
    if len(P):
        # at their own stroke's ends the end margins take a junction (there the effect's gaps reach less often:
        # leaving those samples out would bias the loss up)
        inside = np.minimum(s, L[stroke] - s) >= END_TRIM - 1e-9
        out = inside & near_other(P, stroke)
        # an end meeting another stroke anywhere along it (a silhouette's end at a whole rim's tangent) is not free
        hits = cKDTree(P).query_ball_point(ends, JUNCTION)
        meets |= np.array([bool(len(h)) and bool((stroke[h] != o).any()) for h, o in zip(hits, owner, strict=True)])
    free &= ~meets.reshape(2, S).T
    return out, free


def sample_strokes(st: Strokes, step: float) -> Samples:
    """Samples every ~`step` px along each stroke: floor(L / step) of them (at least one), L / n apart, the first
    at a phase in (0, 1) of that spacing from the stroke's start."""
    S = st.n
    if S == 0 or len(st.pts) < 2:
        z = np.zeros((0, 2))
        return Samples(z, z, np.zeros(0, int), np.zeros(0), np.zeros(S))
    d = np.diff(st.pts, axis=0)
    seg_len = np.hypot(d[:, 0], d[:, 1])
    junction = np.zeros(len(seg_len), bool)
    junction[st.start[1:-1] - 1] = True  # last vertex of a stroke to the first of the next
    seg_len[junction] = 0.0
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    base = cum[st.start[:-1]]
    L = cum[st.start[1:] - 1] - base
    n = np.where(L > 0, np.maximum(1, np.floor(L / step)), 0).astype(int)
    stroke = np.repeat(np.arange(S), n)
    k = np.arange(len(stroke)) - np.repeat(np.cumsum(n) - n, n)
    # each stroke's grid starts at its own phase (a Weyl sequence over the strokes), so that where an edge's
    # end falls between two samples is uniform over strokes, at the strokes' ends as at the gaps inside them
    phase = np.modf((np.arange(S) + 1) * GOLDEN)[0]
    s = (k + phase[stroke]) * (L / np.maximum(n, 1))[stroke]
    g = base[stroke] + s
    seg = np.clip(np.searchsorted(cum[1:], g, side="left"), 0, len(seg_len) - 1)
    t = d[seg] / np.maximum(seg_len[seg], 1e-300)[:, None]
    P = st.pts[seg] + t * (g - cum[seg])[:, None]
    N = np.column_stack([-t[:, 1], t[:, 0]])
    return Samples(P, N, stroke, s, L, *junctions(st, P, stroke, s, L))


@dataclass
class EdgeMatch:
    tested: np.ndarray  # (n,) bool: the sample is far enough inside the image to be tested
    verified: np.ndarray  # (n,) bool
    offset: np.ndarray  # (n,) px, signed along the normal (NaN where not verified)


def search_edges(sm: Samples, det: Detection, shape: tuple[int, int], cfg: Settings) -> EdgeMatch:
    """For each sample, the nearest detected edge along its normal within the band whose gradient agrees."""
    h, w = shape
    n = len(sm.P)
    P, N = sm.P, sm.N
    tested = (P[:, 0] >= BORDER) & (P[:, 0] <= w - 1 - BORDER) & (P[:, 1] >= BORDER) & (P[:, 1] <= h - 1 - BORDER)
    offset = np.full(n, np.nan)
    verified = np.zeros(n, bool)
    if n == 0:
        return EdgeMatch(tested, verified, offset)
    if det.edges is not None:
        edges, gx, gy, label = det.edges, det.gx, det.gy, None
    else:
        edges, gx, gy, label = segment_gradients(det.segments, shape)
    # positions every half pixel along the normal, each also half a pixel either way along the stroke: a ray
    # alone can slip through the diagonal step of an 8-connected edge; nearest first, the ray's own first
    kn = np.arange(-cfg.band, cfg.band + 1e-9, 0.5)
    ks = np.repeat(kn, 3)
    ts = np.tile([0.0, -0.5, 0.5], len(kn))
    order = np.lexsort((np.abs(ts), np.abs(ks)))
    ks, ts = ks[order], ts[order]
    T = np.column_stack([N[:, 1], -N[:, 0]])
    X = np.rint(P[:, None, 0] + ks[None, :] * N[:, None, 0] + ts[None, :] * T[:, None, 0]).astype(np.int64)
    Y = np.rint(P[:, None, 1] + ks[None, :] * N[:, None, 1] + ts[None, :] * T[:, None, 1]).astype(np.int64)
    inside = (X >= 0) & (X < w) & (Y >= 0) & (Y < h) & tested[:, None]
    Xc, Yc = np.where(inside, X, 0), np.where(inside, Y, 0)
    hit = inside & edges[Yc, Xc]
    rows, cols = np.nonzero(hit)
    if len(rows):
        ok = angle_ok(gx[Yc[rows, cols], Xc[rows, cols]], gy[Yc[rows, cols], Xc[rows, cols]],
                      N[rows, 0], N[rows, 1], cfg.angle)
        hit[rows[~ok], cols[~ok]] = False
    found = hit.any(axis=1)
    first = np.argmax(hit, axis=1)
    idx = np.flatnonzero(found)
    cx, cy = Xc[idx, first[idx]], Yc[idx, first[idx]]
    if label is not None:  # exact distance along the normal to the segment's line
        seg = det.segments[label[cy, cx]]
        a, dvec = seg[:, :2], seg[:, 2:] - seg[:, :2]
        m = np.column_stack([-dvec[:, 1], dvec[:, 0]]) / np.maximum(np.hypot(dvec[:, 0], dvec[:, 1]), 1e-12)[:, None]
        dn = np.einsum("ij,ij->i", N[idx], m)
        o = np.einsum("ij,ij->i", a - P[idx], m) / np.where(np.abs(dn) > 1e-9, dn, 1e-9)
    else:
        o = _subpixel(P[idx], N[idx], cx, cy, gx, gy, shape)
    good = np.abs(o) <= cfg.band + 0.5
    verified[idx[good]] = True
    offset[idx[good]] = o[good]
    return EdgeMatch(tested, verified, offset)


def _subpixel(P, N, cx, cy, gx, gy, shape) -> np.ndarray:
    """Offsets along N of edge pixels (cx, cy) moved to the gradient magnitude's peak along their gradient."""
    h, w = shape
    g0x, g0y = gx[cy, cx].astype(float), gy[cy, cx].astype(float)
    norm = np.maximum(np.hypot(g0x, g0y), 1e-12)
    dx, dy = np.rint(g0x / norm).astype(np.int64), np.rint(g0y / norm).astype(np.int64)

    def mag(x, y):
        x, y = np.clip(x, 0, w - 1), np.clip(y, 0, h - 1)
        return np.hypot(gx[y, x].astype(float), gy[y, x].astype(float))

    m_minus, m0, m_plus = mag(cx - dx, cy - dy), norm, mag(cx + dx, cy + dy)
    den = m_minus - 2 * m0 + m_plus
    frac = np.where(den < -1e-12, 0.5 * (m_minus - m_plus) / np.where(den < -1e-12, den, -1.0), 0.0)
    frac = np.clip(frac, -0.5, 0.5)
    qx, qy = cx + frac * dx, cy + frac * dy
    return (qx - P[:, 0]) * N[:, 0] + (qy - P[:, 1]) * N[:, 1]


@dataclass
class StrokeStats:
    """Per stroke: length, samples tested and verified, runs of verified samples, the offsets' mean and scatter;
    the lost length within `margin` of its ends and in its middle, and the ends of its gaps there. Per run (a
    fragment the detector found: consecutive verified samples): its stroke, samples, mean offset, and the
    difference at its two ends of a line fitted to its offsets along it (NaN under 4 samples), with
    that difference's measurement variance."""

    length: np.ndarray
    tested: np.ndarray
    verified: np.ndarray
    runs: np.ndarray
    offset_mean: np.ndarray
    offset_std: np.ndarray
    tested_length: np.ndarray  # px: tested samples times their spacing
    lost_middle: np.ndarray  # px lost farther than `margin` from the stroke's ends
    lost_ends: np.ndarray  # px lost within `margin` of its ends
    ends: np.ndarray  # tested ends (0, 1 or 2)
    gap_ends: np.ndarray  # changes between verified and lost among the middle samples
    run_stroke: np.ndarray
    run_n: np.ndarray
    run_mean: np.ndarray
    run_end_diff: np.ndarray  # px: the run's fitted line's offsets at the run's two ends, the second less the first
    run_noise: np.ndarray  # variance of the run's mean offset from its samples' scatter about its fitted line
    run_length: np.ndarray  # px its offsets cover (its samples less RUN_TRIM at each end, times their spacing)
    run_end_noise: np.ndarray  # px^2: the measurement variance of run_end_diff


def _bins(idx, w, n):
    return np.bincount(idx, weights=w, minlength=n)


def stroke_stats(sm: Samples, m: EdgeMatch, n_strokes: int, margin: float = 3.0,
                 piece: np.ndarray | None = None) -> StrokeStats:
    """`piece` (n,): a run also ends where it changes (an ellipse's halves, `ellipse_halves`). The samples at
    junctions (`sm.junction`) are dropped first, as if not sampled, so that a run or a gap goes on across them;
    the stroke's spacing stays that of all its samples."""
    spacing = sm.L / np.maximum(np.bincount(sm.stroke, minlength=n_strokes), 1)
    drop = np.zeros(len(sm.stroke), bool) if sm.junction is None else sm.junction.copy()
    if drop.any():
        k = ~drop
        sm = Samples(sm.P[k], sm.N[k], sm.stroke[k], sm.s[k], sm.L, None, sm.free)
        m = EdgeMatch(m.tested[k], m.verified[k], m.offset[k])
        piece = None if piece is None else piece[k]
    S, st = n_strokes, sm.stroke
    t, v = m.tested, m.verified & m.tested
    cnt = _bins(st, t, S)
    nv = _bins(st, v, S)
    same = np.concatenate([[False], st[1:] == st[:-1]]) if len(st) else np.zeros(0, bool)
    if piece is not None and len(st):
        same_piece = same & np.concatenate([[False], piece[1:] == piece[:-1]])
    else:
        same_piece = same
    prev = np.concatenate([[False], v[:-1]]) & same_piece if len(v) else v
    start = v & ~prev
    runs = _bins(st, start, S)
    o = np.where(v, m.offset, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(nv > 0, _bins(st, o, S) / np.maximum(nv, 1), np.nan)
        var = np.where(nv > 1, (_bins(st, o * o, S) - nv * mean * mean) / np.maximum(nv - 1, 1), np.nan)
    per = np.bincount(st, minlength=S)
    # an end that meets another stroke (not free) takes JUNCTION px as its margin: there the detected edge bends off
    wide = max(margin, JUNCTION)
    mh, mt = ((np.full(S, margin), np.full(S, margin)) if sm.free is None else
              (np.where(sm.free[:, 0], margin, wide), np.where(sm.free[:, 1], margin, wide)))
    head = sm.s < mh[st]
    tail = (sm.s > sm.L[st] - mt[st]) & ~head
    near = head | tail
    lost = t & ~v
    # an end's own loss counts only where the sample just past its margin was verified; where it was lost too,
    # a gap reaches the end, and the margin's loss belongs to that gap
    first = np.cumsum(per) - per
    n_head, n_tail = np.bincount(st, weights=head, minlength=S).astype(int), np.bincount(
        st, weights=tail, minlength=S).astype(int)
    g0 = first + n_head  # the first sample past the head margin
    g1 = first + per - 1 - n_tail  # the last before the tail margin
    okh = (n_head > 0) & (g0 <= g1) & v[np.minimum(g0, len(v) - 1)] if len(v) else np.zeros(S, bool)
    okt = (n_tail > 0) & (g1 >= g0) & v[np.clip(g1, 0, max(len(v) - 1, 0))] if len(v) else np.zeros(S, bool)
    end_ok = np.where(head, okh[st], okt[st]) & near
    # only a free end measures the detector's own loss at an end (what a gap's ends lose): at one that meets
    # another stroke (a junction, a silhouette's end at its rim) the detected edge bends off, and loses more
    fh, ft = (np.ones(S, bool), np.ones(S, bool)) if sm.free is None else (sm.free[:, 0], sm.free[:, 1])
    free_end = np.where(head, fh[st], ft[st])
    lost_ends = _bins(st, lost & end_ok & free_end, S) * spacing
    lost_mid = _bins(st, lost & ~end_ok, S) * spacing
    first_end = (_bins(st, t & head, S) > 0) & okh & fh
    last_end = (_bins(st, t & tail, S) > 0) & okt & ft
    mid = t & ~near
    # changes of state between consecutive middle samples of a stroke (each interior gap has two)
    change = np.concatenate([[False], (v[1:] != v[:-1]) & mid[1:] & mid[:-1] & same[1:]]) if len(v) else v
    gap_ends = _bins(st, change, S)
    # runs: the fragments the detector found
    run_id = np.cumsum(start) - 1
    R = int(start.sum())
    # a run's samples within RUN_TRIM px of its ends are left out of its offsets (there the edge bends round its
    # end): px, not samples, so that the offsets a run gives do not depend on the sampling step
    allv = np.flatnonzero(v)
    arid, a_s = run_id[allv], sm.s[allv]
    first_s, last_s = np.full(R, np.inf), np.full(R, -np.inf)
    np.minimum.at(first_s, arid, a_s)
    np.maximum.at(last_s, arid, a_s)
    inner = (a_s >= END_TRIM - 1e-9) & (a_s <= sm.L[st[allv]] - END_TRIM + 1e-9) if len(allv) else np.zeros(0, bool)
    rv = allv[(a_s - first_s[arid] >= RUN_TRIM - 1e-9) & (last_s[arid] - a_s >= RUN_TRIM - 1e-9) & inner]
    rid, ro, rs = run_id[rv], m.offset[rv], sm.s[rv]
    rn = np.bincount(rid, minlength=R).astype(float)
    run_spacing = spacing[st[np.flatnonzero(start)]] if R else np.zeros(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        rmean = _bins(rid, ro, R) / np.maximum(rn, 1)
        ms = _bins(rid, rs, R) / np.maximum(rn, 1)
        vs = _bins(rid, rs * rs, R) / np.maximum(rn, 1) - ms * ms
        cov = _bins(rid, rs * ro, R) / np.maximum(rn, 1) - ms * rmean
        slope = np.where((rn >= 4) & (vs > 1e-9), cov / np.where(vs > 1e-9, vs, 1.0), np.nan)
        vo = _bins(rid, ro * ro, R) / np.maximum(rn, 1) - rmean * rmean
        rss = rn * np.maximum(vo - np.where(np.isfinite(slope), slope * cov, 0.0), 0.0)
        noise = np.where(rn >= 4, rss / np.maximum(rn - 2, 1) / np.maximum(rn, 1), np.nan)
        # neighbouring samples' noise is correlated (blur, the detector's own smoothing, and samples closer than a
        # pixel read the same pixels): the variance of a mean of n grows by 1 + 2 sum_k (1 - k / n) rho_k, rho_k
        # the correlation of the residuals k samples apart, pooled over the view's runs, summed over lags up to
        # CORR_PX px while positive (the initial positive sequence)
        res = ro - rmean[rid] - np.where(np.isfinite(slope), slope, 0.0)[rid] * (rs - ms[rid])
        usable = rn[rid] >= 4 if len(rid) else np.zeros(0, bool)
        den = float((res[usable] ** 2).sum())
        gap = float(np.median(run_spacing)) if R else 1.0
        grow = np.ones(R)
        for k in range(1, max(1, int(round(CORR_PX / max(gap, 1e-9)))) + 1):
            if den <= 0 or len(rid) <= k:
                break
            pair = (rid[k:] == rid[:-k]) & usable[k:]
            rho = float((res[:-k][pair] * res[k:][pair]).sum()) / den
            if rho <= 0:
                break
            grow += 2 * min(rho, 1.0) * np.maximum(1 - k / np.maximum(rn, 1), 0.0)
        noise = noise * grow
        run_stroke = st[np.flatnonzero(start)]
        # the line fitted to a run's offsets, carried to the run's own ends (its first and last samples, and half
        # a spacing beyond each: the fragment it found): the effect moves each fragment's two ends, so the
        # difference of the fitted offsets there is slope x that length, with the measurement variance of that,
        # var(slope) length^2 (var(slope) the residuals' variance over n var(s), grown by the residuals'
        # correlation as the mean's is)
        Ls = (last_s - first_s + run_spacing) if R else np.zeros(0)
        sig2 = np.where(rn >= 4, rss / np.maximum(rn - 2, 1), np.nan)
        end_noise = np.where(np.isfinite(slope), sig2 * grow / np.maximum(rn * vs, 1e-12) * Ls * Ls, np.nan)
    return StrokeStats(sm.L, cnt.astype(int), nv.astype(int), runs.astype(int), mean, np.sqrt(np.maximum(var, 0)),
                       cnt * spacing, lost_mid, lost_ends, first_end.astype(int) + last_end.astype(int),
                       gap_ends.astype(int), run_stroke, rn.astype(int), rmean, slope * Ls, noise,
                       rn * run_spacing, end_noise)


@dataclass
class CornerMatch:
    fid: np.ndarray  # (C,) model corners
    uv: np.ndarray  # (C, 2)
    found: np.ndarray  # (C,) bool: a detected corner within the radius
    error: np.ndarray  # (C,) px to the nearest detected corner (NaN when none within the radius)
    nearest: np.ndarray  # (C,) index of that detected corner (-1)
    offset: np.ndarray  # (C, 2) px from the model's corner to that detected corner (NaN when none)


def match_corners(fid, uv, det_corners: np.ndarray, radius: float) -> CornerMatch:
    C = len(uv)
    if C == 0 or det_corners is None or len(det_corners) == 0:
        return CornerMatch(fid, uv, np.zeros(C, bool), np.full(C, np.nan), np.full(C, -1), np.full((C, 2), np.nan))
    d2 = ((uv[:, None, :] - det_corners[None, :, :]) ** 2).sum(-1)
    j = d2.argmin(axis=1)
    d = np.sqrt(d2[np.arange(C), j])
    found = d <= radius
    return CornerMatch(fid, uv, found, np.where(found, d, np.nan), np.where(found, j, -1),
                       np.where(found[:, None], det_corners[j] - uv, np.nan))


# Located corners an image needs for its affine map to be taken off. The map takes 3 parameters an axis, and a
# corner mismatched by less than the inlier distance pulls it: with fewer corners (the round trip's fence, 8 an
# image) the fit took much of the injected error with it (the sigma's interval held it in 26 of 30 settings,
# against 30 without the fit).
AFFINE_MIN = 20


def corner_residuals(c: CornerMatch, inlier: float) -> tuple[np.ndarray, np.ndarray, float]:
    """The found corners within `inlier` px of the model's (mask (C,)), their offsets less the image's least-squares
    affine map of the model's corners (n, 2), and the residuals' degrees of freedom an axis (n - 3). A pose (or
    calibration) error moves an image's corners together, smoothly: to first order an affine map takes it off,
    and what is left is the detector's. With fewer than AFFINE_MIN corners, or all on a line, the offsets as
    they are (n degrees of freedom)."""
    near = c.found & (c.error <= inlier)
    d = c.offset[near]
    n = len(d)
    if n < AFFINE_MIN:
        return near, d, float(n)
    uv = c.uv[near] - c.uv[near].mean(axis=0)
    A = np.column_stack([uv, np.ones(n)])
    coef, _, rank, _ = np.linalg.lstsq(A, d, rcond=None)
    if rank < 3:
        return near, d, float(n)
    return near, d - A @ coef, float(n - 3)


def stereo_mismatches(left_img, right_img, lm: CornerMatch, rm: CornerMatch, left_det, right_det,
                      radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The standard matcher on one pair: for each model corner found in the left image and seen in the right,
    the right detected corner within `radius` of the model's right corner with the best normalised
    cross-correlation of 11 x 11 patches. Returns (fid, wrong (bool), distance of the pick from the right
    corner nearest the model's, px) for each corner matched."""
    import cv2

    out_f, out_w, out_d = [], [], []
    if len(left_det) == 0 or len(right_det) == 0:
        return np.zeros(0, int), np.zeros(0, bool), np.zeros(0)
    right_at = {int(f): k for k, f in enumerate(rm.fid)}
    size = (2 * PATCH + 1, 2 * PATCH + 1)
    lf, rf = left_img.astype(np.float32), right_img.astype(np.float32)
    for k in np.flatnonzero(lm.found):
        r = right_at.get(int(lm.fid[k]))
        if r is None or not rm.found[r]:
            continue
        near = np.flatnonzero(((right_det - rm.uv[r]) ** 2).sum(1) <= radius * radius)
        if len(near) == 0:
            continue
        a = cv2.getRectSubPix(lf, size, tuple(map(float, left_det[lm.nearest[k]])))
        a = (a - a.mean()) / (a.std() + 1e-9)
        scores = []
        for j in near:
            b = cv2.getRectSubPix(rf, size, tuple(map(float, right_det[j])))
            scores.append(float(((b - b.mean()) / (b.std() + 1e-9) * a).mean()))
        pick = int(near[int(np.argmax(scores))])
        out_f.append(int(lm.fid[k]))
        out_w.append(pick != rm.nearest[r])
        out_d.append(float(np.hypot(*(right_det[pick] - right_det[rm.nearest[r]]))))
    return np.array(out_f, int), np.array(out_w, bool), np.array(out_d, float)


@dataclass
class ImageResult:
    """One image verified with one detector."""

    image: str
    side: str
    frame: str
    detector: str
    sources: list[str]  # feature ids by fid (the world's)
    strokes: Strokes | None = None
    stats: StrokeStats | None = None
    corners: CornerMatch | None = None
    stereo: tuple | None = None  # (fid, wrong, distance) of the stereo matcher (left images of pairs)
    samples: int = 0
    note: str = ""
    refined: dict = field(default_factory=dict)


def verify_image(view, det: Detection, shape, cfg: Settings, result: ImageResult,
                 ellipses: set | None = None) -> ImageResult:
    """Edge and corner verification of one image's detection against the engine's view of the model
    (`ellipses`: the world's ellipse feature ids, whose strokes' runs are cut at their major axes)."""
    if det.has_edges:
        st = strokes_of(view, ellipses)
        sm = sample_strokes(st, cfg.step)
        m = search_edges(sm, det, shape, cfg)
        result.strokes, result.stats = st, stroke_stats(sm, m, st.n, cfg.margin, ellipse_halves(st, sm, m))
        result.samples = int(m.tested.sum())
    if det.has_corners:
        fid, uv = corners_of(view)
        result.corners = match_corners(fid, uv, det.corners, cfg.radius)
    return result
