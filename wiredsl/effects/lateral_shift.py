"""Lateral edge shifting: every feature moves perpendicular to itself within a range.

Each stroke moves along its local normal by one offset drawn uniformly in
[-range, range]. Ellipses are first split along their major axis (in the image)
and each half moves independently (fragments 0 and 1 of an ellipse).
"""

from __future__ import annotations

import numpy as np

from .. import imageset as im
from .base import Context, Effect, Params, Stats, param


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
        d = ctx.per_trial(cls.name, s.trial, lambda rng, n: rng.uniform(-p.range, p.range, n))
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
    """Ellipse strokes cut where they cross their own major axis (principal axis of the vertices)."""
    ell = s.kind == im.ELLIPSE
    if not ell.any():
        return s
    closed = s.closed.copy()
    s = im.unroll_closed(s)
    arc, L = im.arc_lengths(s)
    L = np.where(closed, L / 2, L)
    strokes, a, b, frag = [], [], [], []
    for k in range(s.n_strokes):
        if not ell[k]:
            strokes.append(k)
            a.append(0.0)
            b.append(L[k])
            frag.append(-1 if s.fragment[k] < 0 else 0)
            continue
        lo, hi = s.start[k], s.start[k + 1]
        P = s.pts[lo:hi]
        n_one = (hi - lo - 1) // 2 + 1 if closed[k] else hi - lo
        centre = P[:n_one].mean(axis=0)
        _, _, Vt = np.linalg.svd(P[:n_one] - centre, full_matrices=False)
        side = (P - centre) @ Vt[1]  # signed distance across the major axis
        cross = np.flatnonzero(np.sign(side[:-1]) * np.sign(side[1:]) < 0)
        t = side[cross] / (side[cross] - side[cross + 1])
        s_cross = arc[lo + cross] + t * (arc[lo + cross + 1] - arc[lo + cross])
        if closed[k]:
            cuts = s_cross[s_cross < L[k]][:2]
            bounds = [(cuts[0], cuts[1]), (cuts[1], cuts[0] + L[k])] if len(cuts) == 2 else [(0.0, L[k])]
        else:
            edges = [0.0, *s_cross.tolist(), L[k]]
            bounds = list(zip(edges[:-1], edges[1:], strict=True))
        for x, y in bounds:
            strokes.append(k)
            a.append(x)
            b.append(y)
            frag.append(0)
    return im.keep_intervals(s, np.array(strokes, int), np.array(a), np.array(b), np.array(frag, int))
