"""wiredsl: Monte-Carlo simulation of wire-frame worlds seen by a stereo robot, without rendering.

Stages, one module each: parse (lark tree) -> ast (spans) -> compile (Scene)
-> simulate (numpy) -> emit (JSON, SVG).
"""

__version__ = "0.2.0"

# The visibility `wiredsl build`, the Python API (`simulate`, `Simulator`) and studies use unless told: "auto"
# is exact hidden lines where a scene's faces would hide what the view-points' lists cannot say and the estimate
# is affordable, else the lists (run.choose_visibility). Kept here, where importing costs nothing.
DEFAULT_VISIBILITY = "auto"
VISIBILITIES = ("auto", "scene", "exact", "all")


def install_hint(extra: str) -> str:
    """How to install an optional extra, for the messages of the code that needs it: wiredsl installs from its
    checkout (it is not on PyPI, where `pip install 'wiredsl[plot]'` would look)."""
    return f"pip install '.[{extra}]' in wiredsl's checkout"


def exception_chain(exc: BaseException | None):
    """exc and the exceptions it was raised from or during, outermost first: where a signal's exception ended
    up when compiled code it landed in wrapped it (in a SystemError)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        yield exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__


# The exception a SIGINT or SIGTERM handler raised (the command line's, a study's), kept until the run ends: code
# it lands in may drop it (a C callback that prints "Exception ignored" and returns), and the run must not then
# finish as if no signal came. Commit points (files.publish, an output folder's swap) and the loops between
# batches and shards raise it again.
_STOPS: list[BaseException] = []


def signal_stop(exc: BaseException) -> BaseException:
    """Note the exception a signal handler is about to raise (and return it)."""
    _STOPS.append(exc)
    return exc


def check_stop() -> None:
    """Raise again a signal's exception that the code it landed in dropped; nothing when no signal came."""
    if _STOPS:
        raise _STOPS[0]


def pending_stop() -> BaseException | None:
    return _STOPS[0] if _STOPS else None


def clear_stops() -> None:
    _STOPS.clear()


_HOLD: list[int] = [0]  # > 0: a signal's handler notes its exception and returns, for check_stop to raise


def hold_stops(on: bool) -> None:
    """Hold signals off Python code (on) or no longer (off), nested: pthread_sigmask blocks a signal in the calling
    thread only, and another thread's taking it still runs the handler in this one, between any two lines."""
    _HOLD[0] += 1 if on else -1


def holding_stops() -> bool:
    return _HOLD[0] > 0


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
