"""Corner detection loss: each camera keeps each corner with the same probability, independently.

With `spread`, each view's keep probability is drawn from a Beta of that mean and standard deviation; with
`correlation` (metres along the path), whether a corner is kept, and the view's probability, persist from pose
to pose (wiredsl.effects.variation).
"""

from __future__ import annotations

import numpy as np
from pydantic import model_validator

from wiredsl.effects import variation as var
from wiredsl.effects.base import Context, Effect, KernelStage, Params, Stats, param
from wiredsl.engine import imageset as im


class CornerLossParams(Params):
    keep: float = param(0.85, "fraction", "probability that a corner is found again", ge=0, le=1)
    spread: float = param(0.0, "fraction", "standard deviation of keep between views (a Beta; 0: fixed)",
                          ge=0, le=0.5)
    correlation: float = param(0.0, "length", "distance along the path over which whether a corner is kept, and "
                               "the view's keep, persist (exp(-d / correlation); 0: independent poses)", ge=0, le=1e6)
    _dump = var.unchanged_when_fixed()  # a stage without them dumps as before they existed

    @model_validator(mode="after")
    def _spread_fits(self):
        var.check_fraction_spread("keep", self.keep, self.spread)
        return self

    @classmethod
    def plain_after(cls, values: dict) -> None:
        """_spread_fits on plain values (scene.plainly_valid: the compiler then builds no validator)."""
        var.check_fraction_spread("keep", values["keep"], values["spread"])


class CornerLoss(Effect):
    name = "corner_loss"
    acts_on = "corner detection"
    kernel = KernelStage("wiredsl.effects.corner_loss_kernel:stage", ("keep", "spread", "correlation"),
                         (("total", "add"), ("kept", "add")), path=True)
    Params = CornerLossParams
    doc = __doc__

    @classmethod
    def is_identity(cls, p: CornerLossParams) -> bool:
        return p.keep == 1

    @classmethod
    def disturb(cls, p: CornerLossParams, s: im.ImageSet, ctx: Context) -> im.ImageSet:
        if var.varies(p):
            u = var.item_uniforms(ctx, cls.name, p, s.corner_trial, var.stroke_items(s.corner_fid, -1)) \
                if var.along_path(p) else ctx.draws(cls.name, s.corner_trial)[:, 0]
            keep = u < var.view_magnitudes(ctx, cls.name, p, p.keep, "fraction")[s.corner_trial]
        else:
            keep = ctx.draws(cls.name, s.corner_trial)[:, 0] < p.keep
        ctx.add(cls.name, s.corner_trial, total=np.ones(len(keep), dtype=int), kept=keep)
        return s.take_corners(keep)

    @classmethod
    def report(cls, p: CornerLossParams, stats: Stats) -> dict:
        s = stats.sums[cls.name]
        return {"keep_rate": {"declared": p.keep, "measured": s["kept"] / s["total"] if s["total"] else None}}
