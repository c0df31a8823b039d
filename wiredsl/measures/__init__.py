"""The downstream consumers of the disturbed features, one module each, registered by their language name."""

from __future__ import annotations

from wiredsl.measures.base import Measure, Params
from wiredsl.measures.pgh import PGH
from wiredsl.measures.stereo3d import Stereo3D
from wiredsl.measures.survival import Survival
from wiredsl.plugins import Registry

BUILTIN: dict[str, type[Measure]] = {m.name: m for m in (PGH, Stereo3D, Survival)}


def _check(measure: type[Measure]) -> str | None:
    """What an installed measure lacks for a study, or None."""
    stats = getattr(measure, "statistics", None)
    if not (isinstance(stats, tuple) and stats and all(isinstance(s, str) for s in stats)):
        return "declares no statistics (a tuple of names)"
    if measure.measure.__func__ is Measure.measure.__func__:
        return "does not define measure()"
    return None


REGISTRY = Registry("measure", BUILTIN, Measure, _check)  # the built-ins, then the installed plug-ins

__all__ = ["BUILTIN", "REGISTRY", "Measure", "Params"]
