"""Corner match error: a fraction of corners jump to a random point in the match search disc."""

from __future__ import annotations

from .base import Effect, Params, param


class CornerMismatchParams(Params):
    fraction: float = param(0.01, "fraction", "fraction of corners mismatched", ge=0, le=1)
    radius: float = param(10.0, "image", "radius of the match search region", ge=0, le=10000)


class CornerMismatch(Effect):
    name = "corner_mismatch"
    acts_on = "corner matching"
    Params = CornerMismatchParams
    doc = __doc__
