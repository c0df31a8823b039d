"""Corner detection loss: each camera keeps each corner with the same probability, independently."""

from __future__ import annotations

import numpy as np

from wiredsl.effects.base import Context, Effect, KernelStage, Params, Stats, param
from wiredsl.engine import imageset as im


class CornerLossParams(Params):
    keep: float = param(0.85, "fraction", "probability that a corner is found again", ge=0, le=1)


class CornerLoss(Effect):
    name = "corner_loss"
    acts_on = "corner detection"
    kernel = KernelStage("wiredsl.effects.corner_loss_kernel:stage", ("keep",),
                         (("total", "add"), ("kept", "add")))
    Params = CornerLossParams
    doc = __doc__

    @classmethod
    def is_identity(cls, p: CornerLossParams) -> bool:
        return p.keep == 1

    @classmethod
    def disturb(cls, p: CornerLossParams, s: im.ImageSet, ctx: Context) -> im.ImageSet:
        keep = ctx.draws(cls.name, s.corner_trial)[:, 0] < p.keep
        ctx.add(cls.name, s.corner_trial, total=np.ones(len(keep), dtype=int), kept=keep)
        return s.take_corners(keep)

    @classmethod
    def report(cls, p: CornerLossParams, stats: Stats) -> dict:
        s = stats.sums[cls.name]
        return {"keep_rate": {"declared": p.keep, "measured": s["kept"] / s["total"] if s["total"] else None}}
