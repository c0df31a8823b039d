"""The uncertainty sources, one module each, registered by their language name."""

from __future__ import annotations

from typing import Literal

from wiredsl.effects.approx_error import ApproxError
from wiredsl.effects.base import FLOW, Effect, KernelStage, Params
from wiredsl.effects.calibration_error import CalibrationError
from wiredsl.effects.corner_error import CornerError
from wiredsl.effects.corner_loss import CornerLoss
from wiredsl.effects.corner_mismatch import CornerMismatch
from wiredsl.effects.edge_loss import EdgeLoss
from wiredsl.effects.lateral_shift import LateralShift
from wiredsl.effects.motion_blur import MotionBlur
from wiredsl.effects.stereo_mismatch import StereoMismatch
from wiredsl.plugins import Registry

BUILTIN: dict[str, type[Effect]] = {
    e.name: e
    for e in (CalibrationError, EdgeLoss, LateralShift, MotionBlur, ApproxError, CornerLoss, CornerError,
              CornerMismatch, StereoMismatch)
}
KINDS = ("length", "angle", "image", "number", "fraction")  # the unit kinds a stage parameter may have


def _check(effect: type[Effect]) -> str | None:
    """What an installed effect lacks for the language and the engine, or None."""
    if getattr(effect, "acts_on", None) not in FLOW or effect.acts_on == "cameras":
        return f"acts on {getattr(effect, 'acts_on', None)!r}: one of " + ", ".join(FLOW[1:])
    for key, f in effect.Params.model_fields.items():
        kind = (f.json_schema_extra or {}).get("kind") if isinstance(f.json_schema_extra, dict) else None
        if kind not in KINDS:
            return (f"parameter '{key}' has unit kind {kind!r}: declare it with wiredsl.effects.base.param(default, "
                    f"kind, doc), kind one of {', '.join(KINDS)}")
    k = getattr(effect, "kernel", None)
    if k is not None:
        if not isinstance(k, KernelStage) or not isinstance(k.function, str) or k.function.count(":") != 1:
            return "declares a kernel that is not a KernelStage('module:function', params, stats)"
        if unknown := [name for name in k.params if name not in effect.Params.model_fields]:
            return f"its kernel takes {', '.join(map(repr, unknown))}, not among its parameters"
        if any(len(c) != 2 or c[1] not in ("add", "peak") for c in k.stats):
            return "its kernel's stats columns are not (key, 'add' or 'peak') pairs"
        if not all(isinstance(flag, bool) for flag in (k.epipole, k.camera, k.rig)):
            return "its kernel's epipole, camera and rig are not True or False"
    for method in ("is_identity", "disturb"):
        if getattr(effect, method).__func__ is getattr(Effect, method).__func__:
            return f"does not define {method}()"
    return None


REGISTRY = Registry("effect", BUILTIN, Effect, _check)  # the built-ins, then the installed plug-ins

__all__ = ["BUILTIN", "FLOW", "REGISTRY", "Effect", "Params"]


def stage_models() -> dict[str, type]:
    """A model per effect the registry knows (built-in and installed), `{effect: <name>, params: <its Params>}`,
    for the JSON schema of a pipeline's stages (the compiled scene keeps a stage as name and parameters)."""
    from pydantic import create_model

    from wiredsl.plugins import lookup
    from wiredsl.scene import Node

    usable = {name: effect for name in REGISTRY if (effect := lookup(REGISTRY, name)[0]) is not None}
    return {name: create_model("".join(w.title() for w in name.split("_")) + "Stage", __base__=Node,
                               effect=(Literal[name], ...), params=(effect.Params, effect.Params()))
            for name, effect in usable.items()}
