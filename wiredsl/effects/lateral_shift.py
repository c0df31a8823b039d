"""Lateral edge shifting: every feature moves perpendicular to itself within a range."""

from __future__ import annotations

from .base import Effect, Params, param


class LateralShiftParams(Params):
    range: float = param(3.0, "image", "largest lateral shift either side", ge=0, le=1000)


class LateralShift(Effect):
    name = "lateral_shift"
    acts_on = "edges"
    Params = LateralShiftParams
    doc = __doc__
