"""The uncertainty sources, one module each, registered by their language name."""

from __future__ import annotations

from wiredsl.effects.approx_error import ApproxError
from wiredsl.effects.base import FLOW, Effect, Params
from wiredsl.effects.calibration_error import CalibrationError
from wiredsl.effects.corner_loss import CornerLoss
from wiredsl.effects.corner_mismatch import CornerMismatch
from wiredsl.effects.edge_loss import EdgeLoss
from wiredsl.effects.lateral_shift import LateralShift
from wiredsl.effects.stereo_mismatch import StereoMismatch

REGISTRY: dict[str, type[Effect]] = {
    e.name: e
    for e in (CalibrationError, EdgeLoss, LateralShift, ApproxError, CornerLoss, CornerMismatch, StereoMismatch)
}

__all__ = ["FLOW", "REGISTRY", "Effect", "Params"]
