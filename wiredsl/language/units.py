"""The fixed unit table: every quantity is normalised to SI (metres, radians, pixels)."""

from __future__ import annotations

import math

# unit -> (kind, factor to the SI value of that kind)
UNITS: dict[str, tuple[str, float]] = {
    "mm": ("length", 1e-3),
    "cm": ("length", 1e-2),
    "m": ("length", 1.0),
    "in": ("length", 0.0254),
    "ft": ("length", 0.3048),
    "deg": ("angle", math.pi / 180.0),
    "rad": ("angle", 1.0),
    "px": ("image", 1.0),
    "%": ("fraction", 0.01),
    "s": ("time", 1.0),
    "ms": ("time", 1e-3),
    "m/s": ("speed", 1.0),
    "cm/s": ("speed", 1e-2),
    "mm/s": ("speed", 1e-3),
    "km/h": ("speed", 1 / 3.6),
}

# What a bare number means for each kind when the file sets no `units`.
DEFAULT_UNITS: dict[str, str] = {"length": "m", "angle": "deg", "image": "px", "time": "s", "speed": "m/s"}

KIND_NAMES = {
    "length": "a length",
    "angle": "an angle",
    "image": "an image distance",
    "number": "a plain number",
    "fraction": "a fraction",
    "time": "a time",
    "speed": "a speed",
    "integer": "a whole number",
}
