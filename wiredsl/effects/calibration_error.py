"""Camera calibration error: the rig's parameters are drawn from the calibration covariance."""

from __future__ import annotations

from .base import Effect, Params, param


class CalibrationErrorParams(Params):
    sigma: float = param(0.01, "number", "standard deviation of the white noise on each singular direction",
                         ge=0, le=1e6)
    cutoff: float = param(1e-9, "number", "singular values below cutoff * largest are treated as unconstrained",
                          gt=0, lt=1)


class CalibrationError(Effect):
    name = "calibration_error"
    acts_on = "cameras"
    Params = CalibrationErrorParams
    doc = __doc__
