"""Corner detection loss: each camera keeps each corner with the same probability."""

from __future__ import annotations

from .base import Effect, Params, param


class CornerLossParams(Params):
    keep: float = param(0.85, "fraction", "probability that a corner is found again", ge=0, le=1)


class CornerLoss(Effect):
    name = "corner_loss"
    acts_on = "corner detection"
    Params = CornerLossParams
    doc = __doc__
