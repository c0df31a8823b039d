"""The uncertainty sources, one module each, registered by their language name."""

from __future__ import annotations

from .approx_error import ApproxError
from .base import FLOW, Effect, Params
from .calibration_error import CalibrationError
from .corner_loss import CornerLoss
from .corner_mismatch import CornerMismatch
from .edge_loss import EdgeLoss
from .lateral_shift import LateralShift
from .stereo_mismatch import StereoMismatch

REGISTRY: dict[str, type[Effect]] = {
    e.name: e
    for e in (CalibrationError, EdgeLoss, LateralShift, ApproxError, CornerLoss, CornerMismatch, StereoMismatch)
}

__all__ = ["FLOW", "REGISTRY", "Effect", "Params"]
