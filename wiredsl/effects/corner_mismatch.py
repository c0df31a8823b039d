"""Corner match error: a fraction of corners jump to a uniform random point in the match search disc."""

from __future__ import annotations

import numpy as np

from wiredsl.effects.base import Context, Effect, KernelStage, Params, Stats, param
from wiredsl.engine import imageset as im


class CornerMismatchParams(Params):
    fraction: float = param(0.01, "fraction", "fraction of corners mismatched", ge=0, le=1)
    radius: float = param(10.0, "image", "radius of the match search region", ge=0, le=10000)


class CornerMismatch(Effect):
    name = "corner_mismatch"
    acts_on = "corner matching"
    kernel = KernelStage("wiredsl.effects.corner_mismatch_kernel:stage", ("fraction", "radius"),
                         (("total", "add"), ("shifted", "add"), ("max_distance", "peak")))
    Params = CornerMismatchParams
    doc = __doc__

    @classmethod
    def is_identity(cls, p: CornerMismatchParams) -> bool:
        return p.fraction == 0 or p.radius == 0

    @classmethod
    def disturb(cls, p: CornerMismatchParams, s: im.ImageSet, ctx: Context) -> im.ImageSet:
        draws = ctx.draws(cls.name, s.corner_trial, 3)
        hit = draws[:, 0] < p.fraction
        r = p.radius * np.sqrt(draws[:, 1])  # uniform over the disc
        theta = 2 * np.pi * draws[:, 2]
        move = np.where(hit[:, None], np.column_stack([r * np.cos(theta), r * np.sin(theta)]), 0.0)
        ctx.add(cls.name, s.corner_trial, total=np.ones(len(hit), dtype=int), shifted=hit)
        ctx.stats.peak(cls.name, max_distance=np.linalg.norm(move, axis=1).max(initial=0.0))
        return im.replace(s, corners=s.corners + move)

    @classmethod
    def report(cls, p: CornerMismatchParams, stats: Stats) -> dict:
        s = stats.sums[cls.name]
        rate = s["shifted"] / s["total"] if s["total"] else None
        return {"mismatch_rate": {"declared": p.fraction, "measured": rate},
                "max_distance_px": {"declared_bound": p.radius, "measured": stats.maxima[cls.name]["max_distance"]}}
