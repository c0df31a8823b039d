"""Effects and measures from installed packages: the entry-point groups `wiredsl.effects` and `wiredsl.measures`.

A package declares, in its pyproject.toml,

    [project.entry-points."wiredsl.effects"]
    centre_noise = "my_package.effects:CentreNoise"

and the language then knows `centre_noise` as a pipeline stage (its parameters from the class's Params model).
A scene file never names Python code: it names a stage or a measure, and only a name that is not built in is
looked up among the installed entry points (so a build with built-in names never scans them, and nothing
a file writes is ever imported unless an installed package registered it under that name).

A registry is a read-only mapping: the built-ins first, then the installed plug-ins, loaded on first use and
checked (a subclass of the right base, its name, its parameter model). A plug-in that cannot be used raises
PluginError (E180), whose message names its package.

Every call into a plug-in's code at run time (`is_identity`, `disturb`, its kernel's import, `report`, a measure's
`prepare`, `measure` and declarations) goes through `call`, the one guard: whatever it raises, `SystemExit` and a
`KeyboardInterrupt` that is not the user's included, becomes PluginError E181 naming the package and where in the
run it happened, chained to the plug-in's exception (whose traceback `wiredsl` prints under WIREDSL_DEBUG=1).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from wiredsl.diagnostics import Diagnostic, UnknownName, WiredslError

GROUPS = {"effect": "wiredsl.effects", "measure": "wiredsl.measures", "detector": "wiredsl.detectors"}


class PluginError(WiredslError):
    """A plug-in that cannot be used (E180) or that failed in a run (E181): its message names the package it comes
    from and, in a run, the stage or measure, pose, camera and trials. `detail` is the plug-in's own traceback
    (text, kept across a study's worker processes; in this process it is also the error's `__cause__`)."""

    def __init__(self, message: str | list[Diagnostic], code: str = "E180", detail: str | None = None):
        diags = [Diagnostic("error", code, message, None)] if isinstance(message, str) else list(message)
        super().__init__(diags)
        self.detail = detail

    @property
    def message(self) -> str:
        return self.diagnostics[0].message

    def __reduce__(self):
        return (self.__class__, (self.diagnostics, "E180", self.detail))


@dataclass(frozen=True)
class Plugin:
    """One installed entry point of a wiredsl group."""

    kind: str  # "effect" | "measure"
    name: str
    value: str  # module:attribute
    package: str  # distribution name
    version: str

    @property
    def origin(self) -> str:
        return f"package '{self.package}' {self.version} ({self.value})"


_SCANNED: dict[str, list[Plugin]] = {}


def installed(kind: str) -> list[Plugin]:
    """The installed entry points of a kind (read from package metadata once a process; nothing imported)."""
    if kind not in _SCANNED:
        from importlib.metadata import entry_points

        found = []
        for ep in entry_points(group=GROUPS[kind]):
            dist = ep.dist
            found.append(Plugin(kind, ep.name, ep.value, (dist.name if dist else None) or "?",
                                (dist.version if dist else None) or "?"))
        _SCANNED[kind] = sorted(set(found), key=lambda p: (p.name, p.package))
    return _SCANNED[kind]


def rescan() -> None:
    """Forget what was scanned and loaded (after installing a package in this process, e.g. in tests)."""
    _SCANNED.clear()
    for registry in _REGISTRIES:
        registry._loaded.clear()


def _load(plugin: Plugin, base: type, check) -> type:
    from importlib.metadata import EntryPoint

    ep = EntryPoint(plugin.name, plugin.value, GROUPS[plugin.kind])
    try:
        obj = ep.load()
    except BaseException as exc:  # noqa: BLE001 - whatever a plug-in raises on import is its package's fault
        if not _plugins_fault(exc):
            raise
        raise PluginError(f"{plugin.kind} '{plugin.name}' from {plugin.origin} failed to import: "
                          f"{_said(exc)}", detail=_traceback(exc)) from exc
    problem = _problem(obj, plugin, base) or check(obj)
    if problem:
        raise PluginError(f"{plugin.kind} '{plugin.name}' from {plugin.origin} {problem}")
    return obj


def _problem(obj: Any, plugin: Plugin, base: type) -> str | None:
    from pydantic import BaseModel

    if not (isinstance(obj, type) and issubclass(obj, base)):
        return f"is not a subclass of wiredsl.{base.__name__}"
    if getattr(obj, "name", None) != plugin.name:
        return f"declares name {getattr(obj, 'name', None)!r}, not its entry point's {plugin.name!r}"
    params = getattr(obj, "Params", None)
    if not (isinstance(params, type) and issubclass(params, BaseModel)):
        return "has no Params model (a pydantic model of its parameters)"
    try:
        params()
    except BaseException as exc:  # noqa: BLE001
        if not _plugins_fault(exc):
            raise
        return f"has parameters without defaults ({type(exc).__name__}): every parameter needs one"
    if not isinstance(getattr(obj, "doc", None), str):
        return "has no doc string (`doc`, shown by the reference and the editor)"
    return None


class Registry(Mapping):
    """The built-ins of a kind, then its installed plug-ins (looked up only for a name not built in)."""

    def __init__(self, kind: str, builtins: dict[str, type], base: type, check=lambda obj: None):
        self.kind, self.builtins, self.base, self.check = kind, builtins, base, check
        self._loaded: dict[str, type] = {}
        _REGISTRIES.append(self)

    def plugin(self, name: str) -> Plugin | None:
        """The installed entry point of this name (PluginError when two packages claim it)."""
        if name in self.builtins:
            return None
        same = [p for p in installed(self.kind) if p.name == name]
        if len(same) > 1:
            raise PluginError(f"{self.kind} '{name}' is claimed by " + " and by ".join(p.origin for p in same)
                              + ": uninstall one")
        return same[0] if same else None

    def __getitem__(self, name: str) -> type:
        if name in self.builtins:
            return self.builtins[name]
        if name not in self._loaded:
            plugin = self.plugin(name)
            if plugin is None:
                raise UnknownName(self.kind, name, self)
            self._loaded[name] = _load(plugin, self.base, self.check)
        return self._loaded[name]

    def __contains__(self, name: object) -> bool:
        return name in self.builtins or (isinstance(name, str) and any(p.name == name for p in installed(self.kind)))

    def __iter__(self) -> Iterator[str]:
        yield from self.builtins
        seen = set(self.builtins)
        for p in installed(self.kind):
            if p.name not in seen:
                seen.add(p.name)
                yield p.name

    def __len__(self) -> int:
        return sum(1 for _ in self)

    def origin(self, name: str) -> Plugin | None:
        """Where a name's class comes from: None for a built-in."""
        return None if name in self.builtins else self.plugin(name)

    def clashes(self) -> list[str]:
        """Installed plug-ins that can never be used: named like a built-in, or like another plug-in."""
        out = []
        names = [p.name for p in installed(self.kind)]
        for p in installed(self.kind):
            if p.name in self.builtins:
                out.append(f"{self.kind} '{p.name}' from {p.origin} is named like the built-in one, which wins: "
                           "rename it")
            elif names.count(p.name) > 1:
                out.append(f"{self.kind} '{p.name}' from {p.origin} is claimed by another package too")
        return out


_REGISTRIES: list[Registry] = []


def failure(kind: str, name: str, registry: Mapping, what: str, where: str | None = None,
            cause: BaseException | None = None) -> PluginError:
    """The error of a plug-in that misbehaved at run time (E181), naming its package and where in the run
    (`where`: "stage 2 of 3, pose 0, camera left, trials 0..255", say); `cause` the plug-in's exception."""
    origin = registry.origin(name) if isinstance(registry, Registry) else None
    source = f" from {origin.origin}" if origin is not None else ""
    at = f" (at {where})" if where else ""
    return PluginError(f"{kind} '{name}'{source}{at} {what}", "E181", _traceback(cause) if cause is not None else None)


def call(kind: str, name: str, registry: Mapping, doing: str, fn, *args, where=None, **kwargs):
    """fn(*args, **kwargs), a call into a plug-in's code: whatever it raises becomes E181 naming its package and
    `where` (a string, or a function giving one, called only on failure). Only the user's Ctrl-C (or wiredsl's
    SIGINT / SIGTERM unwinding) passes through: a plug-in's `SystemExit` or its own `KeyboardInterrupt` does not
    end the program."""
    try:
        return fn(*args, **kwargs)
    except BaseException as exc:  # noqa: BLE001 - a plug-in's failure is reported as its own, not as wiredsl's
        if not _plugins_fault(exc):
            raise
        if isinstance(exc, PluginError) and exc.diagnostics[0].code == "E181":
            raise  # already blamed (a nested call)
        at = where() if callable(where) else where
        raise failure(kind, name, registry, f"failed in {doing}: {_said(exc)}", at, exc) from exc


def _plugins_fault(exc: BaseException) -> bool:
    """Whether an exception out of a plug-in's code is the plug-in's: not if a signal's unwinding is in its chain
    (wiredsl's SIGINT / SIGTERM handlers raise their own; compiled code the signal landed in may have wrapped it in
    a SystemError), nor, where Python's own SIGINT handler is installed, a KeyboardInterrupt (which may be the
    user's Ctrl-C). Under the command line SIGINT is wiredsl's, so a KeyboardInterrupt raised there is the
    plug-in's."""
    from wiredsl import exception_chain

    return not any(_unwinding(e) for e in exception_chain(exc))


def _unwinding(exc: BaseException) -> bool:
    import signal

    if getattr(exc, "signal_unwinding", False):  # a study's SIGTERM handler (study/executors.py)
        return True
    if isinstance(exc, (Exception, SystemExit)):
        return False
    if isinstance(exc, KeyboardInterrupt):
        try:
            return signal.getsignal(signal.SIGINT) is signal.default_int_handler
        except ValueError:  # (not the main interpreter)
            return True
    return True  # the command line's Stopped


def _said(exc: BaseException) -> str:
    """An exception as one short line: its type and the start of its message."""
    text = str(exc).replace("\n", " ")
    if len(text) > 300:
        text = text[:300] + " ..."
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _traceback(exc: BaseException) -> str:
    import traceback

    return "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))


def lookup(registry: Mapping, name: str) -> tuple[type | None, str | None]:
    """(class, None) for a name a registry knows, (None, None) for an unknown one, (None, why) for an installed
    plug-in that cannot be used (why names its package)."""
    try:
        return registry.get(name), None
    except PluginError as err:
        return None, err.message


def fingerprint(kind: str, name: str, registry: Mapping) -> dict:
    """What identifies an installed plug-in's code: its distribution's name and version and a sha256 of its files
    (the distribution's installed files and the source files of the packages its entry point and its kernel live
    in, so an editable install's edited source counts, and so does a code change without a new version).

    A study keys its shards on these (wiredsl.study.digest): a plug-in changed in any way recomputes them."""
    plugin = registry.plugin(name) if isinstance(registry, Registry) else None
    if plugin is None:
        return {"kind": kind, "name": name, "package": "?", "version": "?", "sha256": "?"}
    modules = [plugin.value.split(":")[0]]
    kernel = getattr(registry.get(name), "kernel", None) if kind == "effect" else None
    if kernel is not None and isinstance(getattr(kernel, "function", None), str):
        modules.append(kernel.function.split(":")[0])
    return {"kind": kind, "name": name, "package": plugin.package, "version": plugin.version,
            "sha256": _files_hash(plugin, modules)}


def _files_hash(plugin: Plugin, modules: list[str]) -> str:
    import hashlib
    import importlib.util
    from importlib.metadata import distribution
    from pathlib import Path

    files: dict[str, Path] = {}  # by a name relative to where it is installed: the same code hashes the same anywhere
    for module in modules:
        try:
            spec = importlib.util.find_spec(module.split(".")[0])  # a top-level name: found, not imported
        except (ImportError, ValueError):
            spec = None
        if spec is None:
            continue
        if spec.submodule_search_locations:  # a package: every file under its folders
            for folder in map(Path, spec.submodule_search_locations):
                files.update((p.relative_to(folder.parent).as_posix(), p) for p in folder.rglob("*")
                             if p.is_file() and "__pycache__" not in p.parts)
        elif spec.origin and Path(spec.origin).is_file():
            files[Path(spec.origin).name] = Path(spec.origin)
    try:
        record = distribution(plugin.package).files or []
    except Exception:  # noqa: BLE001 - no metadata: the package's files above still count
        record = []
    for f in record:
        p = Path(f.locate())
        metadata = any(part.endswith(".dist-info") for part in f.parts) and f.name != "entry_points.txt"
        if p.suffix != ".pyc" and not metadata and p.is_file():  # (metadata holds paths and install times)
            files.setdefault(f.as_posix(), p)
    h = hashlib.sha256()
    for name in sorted(files):
        h.update(name.encode("utf-8", "surrogateescape") + b"\0")
        try:
            h.update(hashlib.sha256(files[name].read_bytes()).digest())
        except OSError:
            h.update(b"unreadable")
    return h.hexdigest()


def params_dump(params) -> dict:
    """`params.model_dump()`, made from the fields where that gives the same (`scene.plain_dump`), so that no
    serializer is built (nor, with it, the validator)."""
    from wiredsl.scene import plain_dump

    out = plain_dump(params)
    return params.model_dump() if out is None else out


def params_of(kind: str, cls: type, registry: Mapping, values: dict):
    """`cls.Params(**values)`: a plug-in's model guarded (its validators are its code; a pydantic ValidationError
    passes, as a built-in's does, for the caller's range message). A built-in's are made without validation when
    the values are plainly valid (`scene.checked`), as the compiler's are."""
    if not isinstance(registry, Registry) or cls.name in registry.builtins:
        from wiredsl.scene import checked

        return checked(cls.Params, **values)
    from pydantic import ValidationError

    try:
        return cls.Params(**values)
    except ValidationError:
        raise
    except BaseException as exc:  # noqa: BLE001
        if not _plugins_fault(exc):
            raise
        raise failure(kind, cls.name, registry, f"failed in its Params model: {_said(exc)}", cause=exc) from exc
