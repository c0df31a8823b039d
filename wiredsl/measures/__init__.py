"""The downstream consumers of the disturbed features, one module each, registered by their language name."""

from __future__ import annotations

from collections.abc import Mapping

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
    for attr in ("weights", "units"):
        declared = getattr(measure, attr, None)
        if not (isinstance(declared, Mapping) and all(isinstance(k, str) and isinstance(v, str)
                                                      for k, v in declared.items())):
            return f"declares {attr} that are not a mapping of statistic names to strings (a dict)"
    weights = measure.weights
    if unknown := [f"{k} -> {v}" for k, v in weights.items() if k not in stats or v not in stats or k == v]:
        return ("weights " + ", ".join(unknown) + ": each weights one of its statistics by another of them "
                f"(its statistics: {', '.join(stats)})")
    return None


REGISTRY = Registry("measure", BUILTIN, Measure, _check)  # the built-ins, then the installed plug-ins

__all__ = ["BUILTIN", "REGISTRY", "Measure", "Params"]
