"""Lateral edge shifting: every feature moves perpendicular to itself within a range.

Each stroke moves along its local normal by one offset drawn uniformly in
[-range, range]. Ellipses are first split along their major axis (in the image)
and each half moves independently (fragments 0 and 1 of an ellipse). With
`spread`, each view's range is drawn from a Gamma of that mean and standard
deviation; with `correlation` (metres along the path), each feature's offset
and the view's range persist from pose to pose (wiredsl.effects.variation).
"""

from __future__ import annotations

import numpy as np

from wiredsl.effects import variation as var
from wiredsl.effects.base import Context, Effect, KernelStage, Params, Stats, param
from wiredsl.engine import imageset as im


class LateralShiftParams(Params):
    range: float = param(3.0, "image", "largest lateral shift either side", ge=0, le=1000)
    spread: float = param(0.0, "image", "standard deviation of the range between views (a Gamma; 0: fixed)",
                          ge=0, le=1000)
    correlation: float = param(0.0, "length", "distance along the path over which a feature's offset and the "
                               "view's range persist (exp(-d / correlation); 0: independent poses)", ge=0, le=1e6)
    _dump = var.unchanged_when_fixed()  # a stage without them dumps as before they existed


class LateralShift(Effect):
    name = "lateral_shift"
    acts_on = "edges"
    kernel = KernelStage("wiredsl.effects.lateral_shift_kernel:stage", ("range", "spread", "correlation"),
                         (("count", "add"), ("sum_abs", "add"), ("max_abs", "peak")), path=True)
    Params = LateralShiftParams
    doc = __doc__

    @classmethod
    def is_identity(cls, p: LateralShiftParams) -> bool:
        return p.range == 0

    @classmethod
    def disturb(cls, p: LateralShiftParams, s: im.ImageSet, ctx: Context) -> im.ImageSet:
        s = split_ellipses(s)
        if var.varies(p):
            u = var.item_uniforms(ctx, cls.name, p, s.trial, var.stroke_items(s.fid, s.fragment)) \
                if var.along_path(p) else ctx.draws(cls.name, s.trial)[:, 0]
            d = var.view_magnitudes(ctx, cls.name, p, p.range, "image")[s.trial] * (2 * u - 1)
        else:
            d = p.range * (2 * ctx.draws(cls.name, s.trial)[:, 0] - 1)
        normals = im.vertex_normals(s)
        pts = s.pts + np.repeat(d, s.counts)[:, None] * normals
        ctx.add(cls.name, s.trial, count=np.ones(len(d), dtype=int), sum_abs=np.abs(d))
        ctx.stats.peak(cls.name, max_abs=np.abs(d).max(initial=0.0))
        return im.replace(s, pts=pts)

    @classmethod
    def report(cls, p: LateralShiftParams, stats: Stats) -> dict:
        s = stats.sums[cls.name]
        return {"mean_abs_shift_px": {"declared": p.range / 2, "measured": s["sum_abs"] / max(s["count"], 1)},
                "max_abs_shift_px": {"declared_bound": p.range, "measured": stats.maxima[cls.name]["max_abs"]}}


def split_ellipses(s: im.ImageSet) -> im.ImageSet:
    """Ellipse strokes cut where they cross their own major axis (principal axis of their vertices);
    a closed ellipse becomes its two halves, an open arc its pieces between crossings. A crossing
    exactly at a vertex counts once; every other stroke is kept verbatim."""
    ell = s.kind == im.ELLIPSE
    if not ell.any():
        return s
    closed = s.closed & ell
    original = s
    s = im.unroll_closed(s, closed)
    arc, L = im.arc_lengths(s)
    L = np.where(closed, L / 2, L)
    S = s.n_strokes
    # principal axes of each stroke as a curve: segment midpoints weighted by length, which does not
    # depend on how densely the sampler placed vertices (an unrolled loop counts each segment twice)
    stroke_of = s.vertex_stroke()
    same = stroke_of[:-1] == stroke_of[1:]
    mid = (s.pts[:-1] + s.pts[1:]) / 2
    d = s.pts[1:] - s.pts[:-1]
    w = np.where(same, np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]), 0.0)
    seg_stroke = stroke_of[:-1]
    total = np.maximum(np.bincount(seg_stroke, weights=w, minlength=S), 1e-300)
    centre = np.column_stack([np.bincount(seg_stroke, weights=w * mid[:, i], minlength=S) for i in (0, 1)])
    centre /= total[:, None]
    dm = mid - centre[seg_stroke]
    sxx, sxy, syy = (np.bincount(seg_stroke, weights=w * v, minlength=S)
                     for v in (dm[:, 0] * dm[:, 0], dm[:, 0] * dm[:, 1], dm[:, 1] * dm[:, 1]))
    theta = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # the major axis
    minor = np.column_stack([-np.sin(theta), np.cos(theta)])
    rel = s.pts - centre[stroke_of]
    side = rel[:, 0] * minor[stroke_of, 0] + rel[:, 1] * minor[stroke_of, 1]
    # a crossing: the pair's ends on different sides, a vertex on the axis (side 0) counting as the + side,
    # so that an axis through a vertex is one crossing there (t = 0 or 1), not none
    neg = side < 0
    pair = np.flatnonzero(same & (neg[:-1] != neg[1:]) & ell[seg_stroke])
    kc = stroke_of[pair]
    # a closed loop's crossings are those of its first lap: its own segments, including the closing one
    lap = (s.counts[kc] - 1) // 2
    first_lap = ~closed[kc] | (pair - s.start[kc] < lap)
    pair, kc, lap = pair[first_lap], kc[first_lap], lap[first_lap]
    t = side[pair] / (side[pair] - side[pair + 1])
    sc = _crossing(arc, pair, t)
    sc2 = _crossing(arc, np.where(closed[kc], pair + lap, pair), t)  # the same point on the second lap
    cnt = np.bincount(kc, minlength=S)
    off = np.cumsum(cnt) - cnt
    # open arcs: [0, c1], [c1, c2], ..., [ck, L]; a closed ellipse with two crossings: [c1, c2], [c2, c1 + L];
    # anything else (no crossing, or a closed loop crossed fewer than twice) is kept whole
    halves = closed & (cnt >= 2)
    split = halves | (~closed & (cnt > 0))
    m = np.where(halves, 2, np.where(split, cnt + 1, 1))
    k = np.repeat(np.arange(S), m)
    j = np.arange(m.sum()) - np.repeat(np.cumsum(m) - m, m)
    c = lambda i, x=sc: x[np.clip(off[k] + i, 0, max(len(x) - 1, 0))] if len(x) else np.zeros(len(k))  # noqa: E731
    a = np.where(halves[k], np.where(j == 0, c(0), c(1)), np.where(j == 0, 0.0, c(j - 1)))
    b = np.where(halves[k], np.where(j == 0, c(1), c(0, sc2)), np.where(j == cnt[k], L[k], c(j)))
    # only the loops cut into halves stay unrolled (the same first lap, so the same arc lengths); a loop
    # kept whole is copied verbatim from its own vertices
    s = im.unroll_closed(original, halves)
    return im.keep_intervals(s, k, a, b, np.where(split[k], 0, s.fragment[k]), closed=~split[k] & s.closed[k],
                             whole=~split[k])


SNAP_PX = 1e-9  # a crossing closer than this to a vertex is at the vertex: no sliver segment, no copy of it


def _crossing(arc: np.ndarray, pair: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Arc length of the point at fraction t of segment pair -> pair + 1, exactly a vertex's when it is one."""
    seg = arc[pair + 1] - arc[pair]
    return np.where(t * seg < SNAP_PX, arc[pair], np.where((1 - t) * seg < SNAP_PX, arc[pair + 1],
                                                           arc[pair] + t * seg))
