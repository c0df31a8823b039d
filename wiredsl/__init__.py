"""wiredsl: Monte-Carlo simulation of wire-frame worlds seen by a stereo robot, without rendering.

Stages, one module each: parse (lark tree) -> ast (spans) -> compile (Scene)
-> simulate (numpy) -> emit (JSON, SVG).
"""

__version__ = "0.2.0"


_API = ("compile", "simulate", "Simulator", "Batch", "CameraAt", "CompileError", "CompileWarning", "PluginError",
        "Measure", "Effect")
__all__ = ["load", *_API]


def __getattr__(name: str):
    """The public names are imported on first use, so importing wiredsl stays light (no numpy)."""
    if name == "load":
        from wiredsl.io.load import load

        return load
    if name in _API:
        from wiredsl import api

        return getattr(api, name)
    raise AttributeError(f"module 'wiredsl' has no attribute {name!r}")


def __dir__() -> list[str]:
    """The public API beside the module's own names, for tab completion (they are not imported until used)."""
    return sorted({*globals(), *__all__})
