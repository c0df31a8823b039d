"""Geometric approximation error: line end points move by a 2D Gaussian (poly_prox threshold)."""

from __future__ import annotations

from .base import Effect, Params, param


class ApproxErrorParams(Params):
    sigma: float = param(0.15, "image", "standard deviation of each end point, per axis", ge=0, le=100)


class ApproxError(Effect):
    name = "approx_error"
    acts_on = "fitting"
    Params = ApproxErrorParams
    doc = __doc__
