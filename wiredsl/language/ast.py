"""Stage 2: lark tree -> AST of frozen dataclasses, each node with its source span.

Also loads a file with its includes (resolved relative to the including file,
each file read once, cycles and chains deeper than 64 refused) into a
`Program`: the flat list of statements to compile.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Union

import lark

from wiredsl.diagnostics import Diagnostic, Span, WiredslError
from wiredsl.io.sources import decode, display_path, read_bytes
from wiredsl.language import parse


@dataclass(frozen=True, slots=True)
class Number:
    """A number as written, e.g. `0.6m`, `30deg`, `29%`, `3`."""

    text: str
    value: float
    unit: str | None
    span: Span


@dataclass(frozen=True, slots=True)
class String:
    value: str
    span: Span


@dataclass(frozen=True, slots=True)
class Ref:
    """A name or dotted reference, possibly ending in a `*` wildcard."""

    parts: tuple[str, ...]
    span: Span

    @property
    def name(self) -> str:
        return ".".join(self.parts)


@dataclass(frozen=True, slots=True)
class Tuple:
    items: tuple[Arg, ...]
    span: Span


@dataclass(frozen=True, slots=True)
class List:
    items: tuple[Arg, ...]
    span: Span


Arg = Union[Number, String, Ref, Tuple, List]  # noqa: UP007 (a runtime alias)


@dataclass(frozen=True, slots=True)
class Statement:
    """`keyword arg* { statement* }?`; `block` is None when there are no braces."""

    keyword: str
    args: tuple[Arg, ...]
    block: tuple[Statement, ...] | None
    span: Span
    keyword_span: Span


@dataclass(frozen=True, slots=True)
class Comment:
    text: str
    line: int
    col: int


@dataclass(frozen=True, slots=True)
class File:
    path: str
    text: str
    statements: tuple[Statement, ...]
    comments: tuple[Comment, ...]


@dataclass
class Program:
    """A root file and everything it includes, in include order."""

    root: File
    files: dict[str, File] = field(default_factory=dict)
    included_from: dict[str, Span] = field(default_factory=dict)
    resolved: set[Path] = field(default_factory=set)  # every file read, for include-once
    statements: list[Statement] = field(default_factory=list)
    # What could not be loaded: syntax errors (the statements around them are set aside, the rest kept)
    # and includes that could not be read. The compiler reports these first and, while there are any,
    # no reference to an unknown name: that name may be declared in what did not load.
    errors: list[Diagnostic] = field(default_factory=list)
    partial: set[str] = field(default_factory=set)  # files with statements set aside
    mesh_reports: list = field(default_factory=list)  # (span, text): each `mesh read`'s size and bounds, compiled
    motion_reports: list = field(default_factory=list)  # (span, text): the path's times and speeds, compiled

    @property
    def sources(self) -> dict[str, str]:
        return {p: f.text for p, f in self.files.items()}

    def include_notes(self, path: str) -> tuple[str, ...]:
        """'included from' notes for a diagnostic in `path`, innermost first."""
        notes = []
        while path in self.included_from:
            span = self.included_from[path]
            notes.append(f"{path} included from {span}")
            path = span.file
        return tuple(notes)


def _span(path: str, tok: lark.Token) -> Span:
    return Span(path, tok.line, tok.column, tok.end_line, tok.end_column)


class ToAst(lark.Transformer):
    """Builds AST nodes while the LALR parser reduces (no intermediate tree)."""

    path = "<string>"

    def number(self, children):
        (tok,) = children
        text = str(tok)
        i = len(text)
        while i and (text[i - 1].isalpha() or text[i - 1] in "%/"):  # 30deg, 29%, 0.5m/s
            i -= 1
        unit = text[i:] or None
        return Number(text, float(text[:i]), unit, _span(self.path, tok))

    def string(self, children):
        (tok,) = children
        return String(str(tok)[1:-1], _span(self.path, tok))

    def ref(self, children):
        first, last = children[0], children[-1]
        span = Span(self.path, first.line, first.column, last.end_line, last.end_column)
        return Ref(tuple(str(t) for t in children), span)

    def tuple(self, children):
        return Tuple(_items(children), _outer(self.path, children))

    def list(self, children):
        return List(_items(children), _outer(self.path, children))

    def block(self, children):
        return Block(_items(children), _outer(self.path, children))

    def statement(self, children):
        kw, *args = children
        block = None
        if args and isinstance(args[-1], Block):
            block = args.pop().statements
        end = args[-1].span if args and block is None else None
        last = children[-1]
        if isinstance(last, Block):
            end = last.span
        kw_span = _span(self.path, kw)
        span = kw_span if end is None else Span(self.path, kw.line, kw.column, end.end_line, end.end_col)
        return Statement(str(kw), tuple(args), block, span, kw_span)

    def start(self, children):
        return tuple(children)


@dataclass(frozen=True, slots=True)
class Block:
    """Transient: a braced block while parsing; stored as Statement.block."""

    statements: tuple[Statement, ...]
    span: Span


def _items(children) -> tuple:
    return tuple(c for c in children if not isinstance(c, lark.Token))


def _outer(path: str, children) -> Span:
    first, last = children[0], children[-1]
    return Span(path, first.line, first.column, last.end_line, last.end_column)


_TO_AST = ToAst()


def parse_text(text: str, path: str = "<string>") -> File:
    """Parse one file's text into a File AST (includes are not followed); raise on a syntax error."""
    file, errors = parse_partial(text, path)
    if errors:
        raise WiredslError(errors)
    return file


def parse_partial(text: str, path: str = "<string>") -> tuple[File, list[Diagnostic]]:
    """Parse one file's text, keeping every statement a syntax error did not touch; and the errors."""
    _TO_AST.path = path
    parsed = parse.run(parse.parser(_TO_AST), text, path)
    stmts = parsed.result or ()
    if parsed.errors:
        stmts = _whole(stmts, parsed.broken)
    return File(path, text, stmts, tuple(Comment(str(c), c.line, c.column) for c in parsed.comments)), parsed.errors


def _whole(stmts: tuple[Statement, ...], broken: list[tuple[int, int]]) -> tuple[Statement, ...]:
    """The statements without those the parser had to skip a token in or stand in for a bracket of.

    A block keeps its whole statements when the trouble is on a line of its own, not on the header's.
    """
    kept = []
    for s in stmts:
        inside = [p for p in broken if (s.span.line, s.span.col) <= p <= (s.span.end_line, s.span.end_col)]
        if not inside:
            kept.append(s)
            continue
        head = s.args[-1].span if s.args else s.keyword_span
        if s.block is not None and all(p[0] > head.end_line for p in inside):  # on a line of its block
            kept.append(dataclasses.replace(s, block=_whole(s.block, inside)))
    return tuple(kept)


MAX_INCLUDE_DEPTH = 64


def read_source(path: Path, where: Span | None = None) -> str:
    """Read a source file, or raise a located diagnostic."""
    return decode(read_bytes(path, "file", where), path, "file", where)


def load(path: str | os.PathLike, text: str | None = None) -> Program:
    """Parse a file (or `text` standing for it, as an editor has it) and, recursively, its includes.

    Only an unreadable root file raises; syntax errors and includes that cannot be read are kept in
    `Program.errors` with everything else that loaded, for the compiler to report with its own.
    """
    root_path = Path(path)
    text = read_source(root_path) if text is None else text
    root, errors = parse_partial(text, display_path(root_path))
    program = Program(root)
    _loaded(program, root, errors)
    _add(program, root, root_path.resolve(), (root_path.resolve(),))
    order = {f: i for i, f in enumerate(program.files)}
    program.errors.sort(key=lambda d: (order.get(d.span.file, 0), d.span.line, d.span.col) if d.span else (0, 0, 0))
    return program


def _loaded(program: Program, file: File, errors: list[Diagnostic]) -> None:
    program.errors += errors
    if errors:
        program.partial.add(file.path)


def _add(program: Program, file: File, resolved: Path, stack: tuple[Path, ...]) -> None:
    """Follow includes depth first; a file already read is not read again (include once)."""
    program.files[file.path] = file
    program.resolved.add(resolved)
    for stmt in file.statements:
        if stmt.keyword != "include":
            program.statements.append(stmt)
            continue
        if len(stmt.args) != 1 or not isinstance(stmt.args[0], String):
            program.statements.append(stmt)  # the compiler reports the malformed include
            continue
        where = stmt.args[0].span
        notes = program.include_notes(file.path)
        try:
            target = _include_target(resolved.parent, stmt.args[0].value, where, notes)
            if target in stack:
                chain = " -> ".join(display_path(p) for p in (*stack[stack.index(target):], target))
                raise WiredslError([Diagnostic("error", "E011", f"include cycle: {chain}", where, notes=notes)])
            if target in program.resolved:
                continue  # include once: a second include of a file adds nothing
            if len(stack) >= MAX_INCLUDE_DEPTH:
                raise WiredslError([Diagnostic("error", "E011", f"includes nested deeper than "
                                               f"{MAX_INCLUDE_DEPTH} files", where,
                                               "a chain this deep is almost certainly generated by mistake", notes)])
            child, errors = parse_partial(read_source(target, where), display_path(target))
        except WiredslError as err:  # this include is left out; the rest of the program still loads
            program.errors += [_with_notes(d, program, file.path, where) for d in err.diagnostics]
            continue
        program.included_from[child.path] = where
        _loaded(program, child, [_with_notes(d, program, file.path, where) for d in errors])
        _add(program, child, target, (*stack, target))


def _include_target(folder: Path, name: str, where: Span, notes: tuple[str, ...]) -> Path:
    """The resolved path of an include, or E010 at its string (NUL byte, symlink loop)."""
    try:
        if "\0" in name:
            raise ValueError("a path cannot contain a NUL byte")
        return (folder / name).resolve()
    except (ValueError, OSError, RuntimeError) as exc:
        raise WiredslError([Diagnostic("error", "E010", f"cannot include {name!r}: "
                                       f"{getattr(exc, 'strerror', None) or exc}", where, notes=notes)]) from None


def _with_notes(d: Diagnostic, program: Program, including: str, where: Span) -> Diagnostic:
    if d.span is not None and d.span.file != including and not d.notes:
        notes = (f"{d.span.file} included from {where}", *program.include_notes(including))
        return Diagnostic(d.severity, d.code, d.message, d.span, d.hint, notes)
    return d
