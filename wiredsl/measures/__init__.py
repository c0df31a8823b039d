"""The downstream consumers of the disturbed features, one module each, registered by their language name."""

from __future__ import annotations

from wiredsl.measures.base import Measure, Params
from wiredsl.measures.pgh import PGH
from wiredsl.measures.stereo3d import Stereo3D
from wiredsl.measures.survival import Survival

REGISTRY: dict[str, type[Measure]] = {m.name: m for m in (PGH, Stereo3D, Survival)}

__all__ = ["REGISTRY", "Measure", "Params"]
