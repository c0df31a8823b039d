"""Edge detection loss: a fraction of every visible feature's length goes undetected."""

from __future__ import annotations

from .base import Effect, Params, param


class EdgeLossParams(Params):
    fraction: float = param(0.29, "fraction", "fraction of each feature's length removed (Canny finds 71%)", ge=0, le=1)


class EdgeLoss(Effect):
    name = "edge_loss"
    acts_on = "edges"
    Params = EdgeLossParams
    doc = __doc__
