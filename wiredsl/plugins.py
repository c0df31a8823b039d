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
PluginError, whose message names its package.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

GROUPS = {"effect": "wiredsl.effects", "measure": "wiredsl.measures", "detector": "wiredsl.detectors"}


class PluginError(Exception):
    """A plug-in that cannot be used: its message names the package it comes from."""


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
    except Exception as exc:  # noqa: BLE001 - whatever a plug-in raises on import is its package's fault
        raise PluginError(f"{plugin.kind} '{plugin.name}' from {plugin.origin} failed to import: "
                          f"{type(exc).__name__}: {exc}") from None
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
    except Exception as exc:  # noqa: BLE001
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
                raise KeyError(name)
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


def failure(kind: str, name: str, registry: Mapping, what: str):
    """The error of a plug-in that misbehaved at run time (E181), naming its package."""
    from wiredsl.diagnostics import Diagnostic, WiredslError

    origin = registry.origin(name) if isinstance(registry, Registry) else None
    where = f" from {origin.origin}" if origin is not None else ""
    return WiredslError([Diagnostic("error", "E181", f"{kind} '{name}'{where} {what}", None)])


def lookup(registry: Mapping, name: str) -> tuple[type | None, str | None]:
    """(class, None) for a name a registry knows, (None, None) for an unknown one, (None, why) for an installed
    plug-in that cannot be used (why names its package)."""
    try:
        return registry.get(name), None
    except PluginError as err:
        return None, str(err)
