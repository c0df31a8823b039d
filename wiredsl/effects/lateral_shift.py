"""Lateral edge shifting: every feature moves perpendicular to itself within a range.

Each stroke moves along its local normal by one offset drawn uniformly in
[-range, range]. Ellipses are first split along their major axis (in the image)
and each half moves independently (fragments 0 and 1 of an ellipse).
"""

from __future__ import annotations

import numpy as np

from wiredsl.effects.base import Context, Effect, Params, Stats, param
from wiredsl.engine import imageset as im


class LateralShiftParams(Params):
    range: float = param(3.0, "image", "largest lateral shift either side", ge=0, le=1000)


class LateralShift(Effect):
    name = "lateral_shift"
    acts_on = "edges"
    Params = LateralShiftParams
    doc = __doc__

    @classmethod
    def is_identity(cls, p: LateralShiftParams) -> bool:
        return p.range == 0

    @classmethod
    def disturb(cls, p: LateralShiftParams, s: im.ImageSet, ctx: Context) -> im.ImageSet:
        s = split_ellipses(s)
        d = p.range * (2 * ctx.draws(cls.name, s.trial)[:, 0] - 1)
        normals = im.vertex_normals(s)
        pts = s.pts + np.repeat(d, s.counts)[:, None] * normals
        ctx.stats.add(cls.name, count=len(d), sum_abs=np.abs(d).sum())
        ctx.stats.peak(cls.name, max_abs=np.abs(d).max(initial=0.0))
        return im.replace(s, pts=pts)

    @classmethod
    def report(cls, p: LateralShiftParams, stats: Stats) -> dict:
        s = stats.sums[cls.name]
        return {"mean_abs_shift_px": {"declared": p.range / 2, "measured": s["sum_abs"] / max(s["count"], 1)},
                "max_abs_shift_px": {"declared_bound": p.range, "measured": stats.maxima[cls.name]["max_abs"]}}


def split_ellipses(s: im.ImageSet) -> im.ImageSet:
    """Ellipse strokes cut where they cross their own major axis (principal axis of their vertices);
    a closed ellipse becomes its two halves, an open arc its pieces between crossings."""
    ell = s.kind == im.ELLIPSE
    if not ell.any():
        return s
    closed = s.closed.copy()
    s = im.unroll_closed(s)
    arc, L = im.arc_lengths(s)
    L = np.where(closed, L / 2, L)
    S = s.n_strokes
    # principal axes of each stroke as a curve: segment midpoints weighted by length, which does not
    # depend on how densely the sampler placed vertices (an unrolled loop counts each segment twice)
    stroke_of = s.vertex_stroke()
    same = stroke_of[:-1] == stroke_of[1:]
    mid = (s.pts[:-1] + s.pts[1:]) / 2
    w = np.where(same, np.linalg.norm(s.pts[1:] - s.pts[:-1], axis=1), 0.0)
    seg_stroke = stroke_of[:-1]
    total = np.maximum(np.bincount(seg_stroke, weights=w, minlength=S), 1e-300)
    centre = np.column_stack([np.bincount(seg_stroke, weights=w * mid[:, i], minlength=S) for i in (0, 1)])
    centre /= total[:, None]
    dm = mid - centre[seg_stroke]
    sxx, sxy, syy = (np.bincount(seg_stroke, weights=w * v, minlength=S)
                     for v in (dm[:, 0] ** 2, dm[:, 0] * dm[:, 1], dm[:, 1] ** 2))
    theta = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # the major axis
    minor = np.column_stack([-np.sin(theta), np.cos(theta)])
    side = ((s.pts - centre[stroke_of]) * minor[stroke_of]).sum(axis=1)
    pair = np.flatnonzero((stroke_of[:-1] == stroke_of[1:]) & (side[:-1] * side[1:] < 0) & ell[stroke_of[:-1]])
    t = side[pair] / (side[pair] - side[pair + 1])
    sc = arc[pair] + t * (arc[pair + 1] - arc[pair])
    kc = stroke_of[pair]
    first_lap = ~closed[kc] | (sc < L[kc])
    sc, kc = sc[first_lap], kc[first_lap]
    cnt = np.bincount(kc, minlength=S)
    off = np.cumsum(cnt) - cnt
    # open strokes: [0, c1], [c1, c2], ..., [ck, L]; a closed ellipse with two crossings: [c1, c2], [c2, c1 + L]
    halves = closed & (cnt >= 2)
    m = np.where(halves, 2, np.where(closed, 1, cnt + 1))
    k = np.repeat(np.arange(S), m)
    j = np.arange(m.sum()) - np.repeat(np.cumsum(m) - m, m)
    c = lambda i: sc[np.clip(off[k] + i, 0, max(len(sc) - 1, 0))] if len(sc) else np.zeros(len(k))  # noqa: E731
    a = np.where(halves[k], np.where(j == 0, c(0), c(1)), np.where(j == 0, 0.0, c(j - 1)))
    b = np.where(halves[k], np.where(j == 0, c(1), c(0) + L[k]),
                 np.where(closed[k] | (j == cnt[k]), L[k], c(j)))
    split = m[k] > 1
    frag = np.where(split, 0, np.where(s.fragment[k] < 0, -1, 0))
    return im.keep_intervals(s, k, a, b, frag, closed=~split & closed[k])
