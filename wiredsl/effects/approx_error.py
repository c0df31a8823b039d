"""Geometric approximation error: fitted end points and vertices move by a 2D Gaussian.

Every vertex of every stroke (the two end points of a line, each vertex of a
polyline, including fragment ends made by earlier stages) moves by an
isotropic 2D Gaussian with the poly_prox threshold as its standard deviation.
"""

from __future__ import annotations

import numpy as np

from wiredsl.effects.base import Context, Effect, KernelStage, Params, Stats, param
from wiredsl.engine import imageset as im


class ApproxErrorParams(Params):
    sigma: float = param(0.15, "image", "standard deviation of each end point, per axis", ge=0, le=100)


class ApproxError(Effect):
    name = "approx_error"
    acts_on = "fitting"
    kernel = KernelStage("wiredsl.effects.approx_error_kernel:stage", ("sigma",),
                         (("count", "add"), ("sum_sq", "add")))
    Params = ApproxErrorParams
    doc = __doc__

    @classmethod
    def is_identity(cls, p: ApproxErrorParams) -> bool:
        return p.sigma == 0

    @classmethod
    def disturb(cls, p: ApproxErrorParams, s: im.ImageSet, ctx: Context) -> im.ImageSet:
        vtrial = np.repeat(s.trial, s.counts)
        noise = p.sigma * ctx.draws(cls.name, vtrial, 2, normal=True)
        ctx.add(cls.name, vtrial, count=np.full(len(noise), 2), sum_sq=noise**2)
        return im.replace(s, pts=s.pts + noise)

    @classmethod
    def report(cls, p: ApproxErrorParams, stats: Stats) -> dict:
        s = stats.sums[cls.name]
        return {"sigma_px": {"declared": p.sigma, "measured": float(np.sqrt(s["sum_sq"] / max(s["count"], 1)))}}
