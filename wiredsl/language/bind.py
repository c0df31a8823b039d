"""Binding a statement's AST arguments to its signature in `statements.CONTEXTS` (the compile stage's first step):
each value converted to its kind and unit, with diagnostics where it does not fit."""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from typing import Any

from wiredsl.diagnostics import NOT_INSTALLED, Collector, Span, did_you_mean
from wiredsl.language import ast
from wiredsl.language.statements import CONTEXTS, MAX_MAGNITUDE, SCALARS, Sig, Slot, StageSigs
from wiredsl.language.units import KIND_NAMES, UNITS


@dataclass(frozen=True, slots=True)
class Value:
    """A bound argument: its converted value and where it was written."""

    value: Any
    span: Span


@dataclass
class Bound:
    """A statement matched against its signature."""

    stmt: ast.Statement
    sig: Sig
    positional: list[Value]
    clauses: dict[str, list[list[Value]]]  # key -> occurrences -> slot values
    clause_spans: dict[str, list[Span]]
    ok: bool = True

    def has(self, key: str) -> bool:
        return key in self.clauses

    def get(self, key: str, default: Any = None) -> Any:
        """The value of a single-slot clause (first occurrence), or default."""
        occ = self.clauses.get(key)
        return occ[0][0].value if occ and occ[0] else default

    def span(self, key: str) -> Span:
        occ = self.clauses.get(key)
        if occ and occ[0]:
            return occ[0][0].span
        spans = self.clause_spans.get(key)
        return spans[0] if spans else self.stmt.span

    def pos(self, i: int) -> Any:
        return self.positional[i].value

    @property
    def name(self) -> str:
        return self.positional[0].value

    @property
    def name_span(self) -> Span:
        return self.positional[0].span


def bind(stmt: ast.Statement, context: str, units: dict[str, str], out: Collector) -> Bound | None:
    """Match a statement's arguments to its signature in `context`; None if unknown."""
    sigs = CONTEXTS[context]
    sig = sigs.get(stmt.keyword)
    problem = sigs.problem(stmt.keyword) if sig is None and isinstance(sigs, StageSigs) else None
    if problem is not None:  # an installed plug-in of that name that cannot be used
        out.error("E180", problem, stmt.keyword_span, "see 'wiredsl plugins'")
        return None
    if sig is None:
        where = "at the top level" if context == "top" else f"in a {context} block"
        hint = (did_you_mean(stmt.keyword, sigs) or _elsewhere(stmt.keyword, context)
                or (NOT_INSTALLED if isinstance(sigs, StageSigs) else None))
        out.error("E100", f"unknown statement '{stmt.keyword}' {where}", stmt.keyword_span, hint)
        return None
    b = Bound(stmt, sig, [], {}, {})
    n_before = out.n_errors
    args = list(stmt.args)
    i = 0
    for slot in sig.positional:
        if slot.kind == "rest":  # everything left, converted later by whoever knows its kinds
            b.positional.append(Value(args[i:], _join(args[i].span, args[-1].span) if i < len(args) else stmt.span))
            i = len(args)
            continue
        if i >= len(args):
            out.error("E102", f"'{sig.keyword}' needs {_a(slot.label)}", stmt.span, f"e.g. {sig.example}")
            b.ok = False
            return b
        val, i = _take(slot, args, i, sig, units, out)
        b.positional.append(val)
    while i < len(args):
        arg = args[i]
        key = arg.name if isinstance(arg, ast.Ref) and len(arg.parts) == 1 else None
        if key not in sig.clauses:
            if key in CONTEXTS[context] and context != "top":
                out.error("E101", f"'{key}' starts another statement: a block holds one statement a line",
                          arg.span, f"put '{key} ...' on a line of its own")
            elif sig.clauses:
                hint = did_you_mean(key, sig.clauses) if key else None
                hint = hint or "expected one of: " + ", ".join(sig.clauses)
                what = f"unknown word '{key}'" if key else "unexpected value"
                out.error("E101", f"{what} in '{sig.keyword}'", arg.span, hint)
            else:
                out.error("E101", f"'{sig.keyword}' takes no more arguments", arg.span)
            b.ok = False
            return b
        clause = sig.clauses[key]
        if key in b.clauses and not clause.repeat:
            out.error("E103", f"'{key}' given twice in '{sig.keyword}'", arg.span)
        i += 1
        values = []
        for slot in clause.slots:
            if i >= len(args) or _is_key(args[i], sig, slot):
                out.error("E102", f"'{key}' needs {_a(slot.label)}", arg.span, f"e.g. {sig.example}")
                b.ok = False
                return b
            val, i = _take(slot, args, i, sig, units, out)
            values.append(val)
        b.clauses.setdefault(key, []).append(values)
        b.clause_spans.setdefault(key, []).append(arg.span)
    for key, clause in sig.clauses.items():
        if clause.required and key not in b.clauses:
            out.error("E102", f"'{sig.keyword}' needs '{key}' ({clause.doc})", stmt.span, f"e.g. {sig.example}")
    if sig.block is None and stmt.block is not None:
        out.error("E101", f"'{sig.keyword}' takes no {{ block }}", stmt.span)
    if sig.block_required and stmt.block is None:
        out.error("E102", f"'{sig.keyword}' needs a {{ block }}", stmt.span, f"e.g. {sig.example}")
    b.ok = out.n_errors == n_before
    return b


def _elsewhere(keyword: str, context: str) -> str | None:
    for ctx, sigs in CONTEXTS.items():
        if ctx != context and keyword in sigs:
            return f"'{keyword}' belongs " + ("at the top level" if ctx == "top" else f"in a {ctx} block")
    return None


def _a(label: str) -> str:
    """'a unit', 'an entry', '(x, y)': the label with its article, as English says it."""
    if label.startswith(("(", "[")):
        return label
    return ("an " if label[0] in "aeiou" and not label.startswith(("uni", "use", "one")) else "a ") + label


def _is_key(arg: ast.Arg, sig: Sig, slot: Slot) -> bool:
    """A bare word naming a clause ends a run of values (refs cannot use clause words)."""
    return isinstance(arg, ast.Ref) and len(arg.parts) == 1 and arg.name in sig.clauses and slot.kind not in (
        "ref", "name", "word")


def _take(slot: Slot, args: list, i: int, sig: Sig, units: dict[str, str], out: Collector) -> tuple[Value, int]:
    """Convert args[i] (or a run from i, for pts/refs) to `slot`; report what does not fit."""
    kind = slot.kind
    if kind in ("pts", "refs"):
        items = []
        while i < len(args) and not _is_key(args[i], sig, slot):
            items.append(_convert(Slot("vec3:length" if kind == "pts" else "ref", slot.label), args[i], units, out))
            i += 1
        span = _join(items[0].span, items[-1].span) if items else args[i - 1].span
        return Value(items, span), i
    return _convert(slot, args[i], units, out), i + 1


def _join(a: Span, b: Span) -> Span:
    return Span(a.file, a.line, a.col, b.end_line, b.end_col)


def _convert(slot: Slot, arg: ast.Arg, units: dict[str, str], out: Collector) -> Value:
    kind = slot.kind
    bad = Value(None, arg.span)
    if kind in SCALARS:
        if slot.choices and isinstance(arg, ast.Ref) and arg.name in slot.choices:  # a word it also takes (auto)
            return Value(arg.name, arg.span)
        if not isinstance(arg, ast.Number):
            out.error("E106", f"expected {_a(slot.label)} ({KIND_NAMES.get(kind, kind)}), got {_show(arg)}", arg.span)
            return bad
        value = quantity(arg, kind, units, out)
        if "|" in kind:  # say which alternative was written, e.g. focal 6mm or 800px, and whether bare
            value = (value, UNITS[arg.unit][0] if arg.unit in UNITS else kind.split("|")[0], arg.unit)
        return Value(value, arg.span)
    if kind.startswith("vec"):
        n, elem = int(kind[3]), kind.split(":")[1]
        if not isinstance(arg, ast.Tuple) or len(arg.items) != n:
            got = f"{len(arg.items)} values" if isinstance(arg, ast.Tuple) else _show(arg)
            out.error("E106", f"expected {slot.label}: {n} values in ( ), got {got}", arg.span)
            return bad
        vals = []
        for item in arg.items:
            if not isinstance(item, ast.Number):
                out.error("E106", f"expected {KIND_NAMES[elem]}, got {_show(item)}", item.span)
                return bad
            vals.append(quantity(item, elem, units, out))
        return Value(tuple(vals), arg.span)
    if kind in ("name", "ref", "word"):
        if not isinstance(arg, ast.Ref) or (kind != "ref" and len(arg.parts) != 1) or (
                kind == "name" and arg.parts == ("*",)):
            out.error("E106", f"expected {_a(slot.label)}, got {_show(arg)}", arg.span)
            return bad
        if kind == "word" and arg.name not in slot.choices:
            hint = did_you_mean(arg.name, slot.choices) or "one of: " + ", ".join(slot.choices)
            out.error("E106", f"'{arg.name}' is not {_a(slot.label)}", arg.span, hint)
            return bad
        return Value(arg.name, arg.span)
    if kind == "str":
        if not isinstance(arg, ast.String):
            out.error("E106", f"expected {_a(slot.label)} in double quotes, got {_show(arg)}", arg.span)
            return bad
        if "\0" in arg.value:  # the operating system would refuse it later, without a location
            out.error("E010", "a file path cannot contain a NUL byte", arg.span)
            return bad
        return Value(arg.value, arg.span)
    if kind == "raw":  # converted by the compiler, which knows the kind (e.g. a stage parameter's)
        return Value(arg, arg.span)
    if kind == "rawlist":
        if not isinstance(arg, ast.List):
            out.error("E106", f"expected a list in [ ], got {_show(arg)}", arg.span)
            return bad
        return Value(list(arg.items), arg.span)
    if kind == "ints":
        if not isinstance(arg, ast.List):
            out.error("E106", f"expected a list of whole numbers in [ ], got {_show(arg)}", arg.span)
            return bad
        vals = []
        for x in arg.items:
            if not isinstance(x, ast.Number) or x.unit is not None or not x.value.is_integer():
                out.error("E106", f"expected a whole number, got {_show(x)}", x.span)
                return bad
            vals.append(Value(int(x.value), x.span))
        return Value(vals, arg.span)
    if kind == "names":
        if not isinstance(arg, ast.List) or not all(isinstance(x, ast.Ref) for x in arg.items):
            out.error("E106", f"expected a list of names in [ ], got {_show(arg)}", arg.span)
            return bad
        return Value([Value(x.name, x.span) for x in arg.items], arg.span)
    if kind == "matrix":
        rows = arg.items if isinstance(arg, ast.List) else None
        if rows is None or not all(isinstance(r, ast.List) for r in rows):
            out.error("E106", f"expected a matrix as [[...], [...]], got {_show(arg)}", arg.span)
            return bad
        matrix = []
        for row in rows:
            vals = []
            for x in row.items:
                if not isinstance(x, ast.Number):
                    out.error("E106", f"expected a number, got {_show(x)}", x.span)
                    return bad
                vals.append(quantity(x, "number", units, out))
            matrix.append(vals)
        return Value(matrix, arg.span)
    raise AssertionError(f"signature slot kind {kind!r} has no converter")


def quantity(num: ast.Number, kind: str, units: dict[str, str], out: Collector) -> float:
    """A number in SI for the expected kind; a unit of the wrong kind, or a value no float holds, is reported."""
    if not math.isfinite(num.value):
        out.error("E109", f"number '{num.text}' is too large to represent", num.span,
                  f"numbers must be finite, below {sys.float_info.max:.3g} in size")
        return 0.0
    if kind == "integer":
        if num.unit is not None or not num.value.is_integer():
            out.error("E106", f"expected a whole number, got '{num.text}'", num.span)
        return num.value
    if num.unit is None:
        if kind.split("|")[0] in ("number", "fraction"):
            return num.value
        unit = units[kind.split("|")[0]]
        if kind == "angle" and unit == "deg" and 0 < abs(num.value) < 1:
            out.warning("W111", f"'{num.text}' is {num.text} degrees (a bare angle is in degrees)", num.span,
                        f"{num.text} is degrees; did you mean {num.text}rad?")
    else:
        unit = num.unit
        if unit not in UNITS:
            hint = did_you_mean(unit, UNITS) or "units are " + ", ".join(UNITS)
            out.error("E108", f"unknown unit '{unit}' in '{num.text}'", num.span, hint)
            return num.value
    unit_kind, factor = UNITS[unit]
    allowed = kind.split("|")
    if unit_kind not in allowed and not (unit_kind == "fraction" and "number" in allowed):
        expected = " or ".join(KIND_NAMES[k] for k in allowed)
        out.error("E107", f"expected {expected}, got {KIND_NAMES[unit_kind]} '{num.text}'", num.span)
        return num.value
    value = num.value * factor
    if unit_kind in ("length", "image") and abs(value) > MAX_MAGNITUDE:
        what = "m" if unit_kind == "length" else "px"
        out.error("E110", f"'{num.text}' is beyond the limit of {MAX_MAGNITUDE:g} {what}", num.span,
                  "lengths and image distances are bounded so that products of them stay finite")
        return 0.0
    return value


def _show(arg: ast.Arg) -> str:
    if isinstance(arg, ast.Number):
        return f"'{arg.text}'"
    if isinstance(arg, ast.String):
        return f'"{arg.value}"'
    if isinstance(arg, ast.Ref):
        return f"'{arg.name}'"
    if isinstance(arg, ast.Tuple):
        return f"a tuple of {len(arg.items)}"
    return f"a list of {len(arg.items)}"

