"""The documentation site's generated reference: Markdown made from the code's own tables, so it cannot drift.

A page writes `<!-- generated: NAME -->` on a line of its own; `expand` (called by the site's MkDocs hook,
docs/hooks.py, at build time) puts the Markdown of GENERATORS[NAME] there. The language reference comes from the
statement table (wiredsl/language/statements.py), the diagnostics from `wiredsl.diagnostics.CODES`, the effects
and measures from their registries (parameters with unit kinds, defaults and bounds), the command line from click,
the npz layout from wiredsl/io/layout.py.
"""

from __future__ import annotations

import re
from collections.abc import Callable

MARKER = re.compile(r"^<!-- generated: ([\w-]+) -->$", re.M)

# The unit a parameter of each kind is given in when a number is bare (the file's default units) and where it is
# stored after conversion.
UNITS = {"length": "m", "angle": "deg (stored in rad)", "image": "px", "fraction": "0..1, or %",
         "number": "", "integer": "", "time": "s"}


def _cell(text: object) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def statements() -> str:
    """The language reference: every statement of every context, as `wiredsl reference` prints it."""
    from wiredsl.language.statements import reference

    return reference()


def diagnostics() -> str:
    """Every diagnostic code with its meaning, errors and warnings in code order."""
    from wiredsl.diagnostics import CODES

    rows = sorted(CODES.items(), key=lambda kv: (int(kv[0][1:]), kv[0][0]))
    return "\n".join(["| code | meaning |", "|---|---|", *(f"| {c} | {_cell(m)} |" for c, m in rows)])


def _params(model) -> list[str]:
    out = ["| parameter | default | unit | bounds | meaning |", "|---|---|---|---|---|"]
    for key, f in model.model_fields.items():
        extra = f.json_schema_extra if isinstance(f.json_schema_extra, dict) else {}
        kind = extra.get("kind", "")
        bounds = []
        for m in f.metadata:
            for op, attr in ((">=", "ge"), (">", "gt"), ("<=", "le"), ("<", "lt")):
                if getattr(m, attr, None) is not None:
                    bounds.append(f"{op} {getattr(m, attr)}")
        unit = UNITS.get(kind, kind)
        out.append(f"| `{key}` | {f.default} | {kind}{f' ({unit})' if unit else ''} | {', '.join(bounds)} | "
                   f"{_cell(f.description or '')} |")
    return out


def _doc(cls) -> str:
    return (cls.doc or cls.__doc__ or "").strip()


def effects() -> str:
    """The built-in uncertainty sources in data-flow order: what each does, where it acts, its parameters."""
    from wiredsl.effects import BUILTIN

    out: list[str] = []
    for name, effect in sorted(BUILTIN.items(), key=lambda kv: kv[1].flow_rank()):
        engine = ("it perturbs the cameras before projection, on either engine" if effect.acts_on == "cameras"
                  else "compiled kernel and numpy" if effect.kernel is not None else "numpy only")
        out += [f"### `{name}`", "", f"Acts on: {effect.acts_on}. Engines: {engine}.", "", _doc(effect), "",
                *_params(effect.Params), ""]
    return "\n".join(out).rstrip()


def measures() -> str:
    """The built-in measures: what each computes, its parameters and its statistics with their units."""
    from wiredsl.measures import BUILTIN

    out: list[str] = []
    for name, measure in BUILTIN.items():
        stats = ["| statistic | unit | weighted by |", "|---|---|---|"]
        stats += [f"| `{s}` | {measure.units.get(s, '')} | {measure.weights.get(s, '')} |"
                  for s in measure.statistics]
        out += [f"### `{name}`", "", _doc(measure), "", *_params(measure.Params), "", *stats, ""]
    return "\n".join(out).rstrip()


def cli() -> str:
    """Every command of `wiredsl`: its usage line, help and options, from click."""
    import click

    from wiredsl.cli import main

    ctx = click.Context(main, info_name="wiredsl")
    out: list[str] = []
    for name in main.list_commands(ctx):
        cmd = main.get_command(ctx, name)
        sub = click.Context(cmd, info_name=name, parent=ctx)
        usage = " ".join(cmd.collect_usage_pieces(sub))
        out += [f"### `wiredsl {name}`", "", "```", f"wiredsl {name} {usage}".rstrip(), "```", "",
                (cmd.help or "").strip(), ""]
        rows = []
        for p in cmd.get_params(sub):
            rec = None if isinstance(p, click.Argument) else p.get_help_record(sub)
            if rec is not None:
                rows.append(f"| `{_cell(rec[0])}` | {_cell(rec[1])} |")
        if rows:
            out += ["| option | does |", "|---|---|", *rows, ""]
    return "\n".join(out).rstrip()


def npz_layout() -> str:
    """The npz dump's members, columns and codes."""
    from wiredsl.io import layout

    return layout.markdown().strip()


GENERATORS: dict[str, Callable[[], str]] = {
    "statements": statements, "diagnostics": diagnostics, "effects": effects, "measures": measures,
    "cli": cli, "npz-layout": npz_layout,
}


def expand(markdown: str) -> str:
    """The page with every generated block in place; an unknown name is an error (the strict build fails)."""

    def one(m: re.Match) -> str:
        if m.group(1) not in GENERATORS:
            raise KeyError(f"unknown generated block {m.group(1)!r}: one of {', '.join(GENERATORS)}")
        return GENERATORS[m.group(1)]()

    return MARKER.sub(one, markdown)
