"""`wiredsl lsp`: the language in the editor, a language server over stdio (pygls).

Two halves. The analysis (`analyse`, `completions`, `hover`, `definition`,
`references`, `symbols`) is plain functions over the compiler's own stages:
the same parse, statement table and diagnostics as `wiredsl check`. The server
(`serve`) only maps LSP requests onto them; pygls is imported there alone, so
the rest of wiredsl never pays for it. Positions here are 1-based (line, col)
like every `Span`; the server converts to LSP's 0-based ones.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from wiredsl.diagnostics import Collector, Diagnostic, Span, WiredslError, source_lines
from wiredsl.io import sources
from wiredsl.language import ast
from wiredsl.language.bind import bind
from wiredsl.language.statements import CONTEXTS, Sig, takes
from wiredsl.language.units import DEFAULT_UNITS, UNITS

# The kind of symbol a reference slot names, by the slot's label in the statement table.
_SLOT_TARGET = {"model": "model", "camera": "camera", "ellipse": "feature", "lines": "feature",
                "vertex": "vertex", "features": "place"}


@dataclass(frozen=True)
class Symbol:
    """A declared name: `kind` is the declaring statement's family, `name` qualified
    (`model.feature`, `mesh.vertex`) so that equal names in two models differ."""

    kind: str  # model | camera | rig | viewpoints | path | pipeline | scene | place | feature | vertex
    name: str
    span: Span  # the name as written
    stmt: ast.Statement
    what: str  # the declaring keyword (line, ellipse, place, ...)


@dataclass(frozen=True)
class Reference:
    kind: str  # the kind of symbol it names, or "file" for an include
    name: str  # qualified as in Symbol, or the included file's absolute path
    span: Span


@dataclass
class Index:
    """What the editor needs of one document: diagnostics, declarations, references."""

    path: str  # the document as spans name it
    text: str
    diagnostics: list[Diagnostic] = field(default_factory=list)
    files: dict[str, ast.File] = field(default_factory=dict)
    symbols: list[Symbol] = field(default_factory=list)
    refs: list[Reference] = field(default_factory=list)

    def symbol(self, kind: str, name: str) -> Symbol | None:
        return next((s for s in self.symbols if s.kind == kind and s.name == name), None)

    def at(self, path: str, line: int, col: int) -> Symbol | Reference | None:
        """The declaration or reference under a 1-based position."""
        for item in (*self.refs, *self.symbols):
            if _inside(item.span, path, line, col):
                return item
        return None


def _inside(span: Span, path: str, line: int, col: int) -> bool:
    return (span.file == path and (span.line, span.col) <= (line, col)
            and (line, col) <= (span.end_line, span.end_col))


# --------------------------------------------------------------------------- analysis

def analyse(path: str, text: str) -> Index:
    """Diagnostics and symbols of a document's current text (its includes read from disk)."""
    from wiredsl.language.compile import compile_program

    shown = sources.display_path(Path(path))
    index = Index(shown, text)
    try:
        program = ast.load(path, text=text)
    except WiredslError as err:
        index.diagnostics = err.diagnostics
        return index
    index.files = dict(program.files)
    try:
        _, warnings = compile_program(program)
        index.diagnostics = list(warnings)
    except WiredslError as err:
        index.diagnostics = err.diagnostics
    for file in program.files.values():
        _walk(index, file.statements, "top", file, None)
    return index


def _walk(index: Index, stmts, context: str, file: ast.File, owner: str | None) -> None:
    for stmt in stmts:
        b = bind(stmt, context, DEFAULT_UNITS, Collector())
        if b is None:
            continue
        sig = b.sig
        name = b.positional[0].value if sig.positional and sig.positional[0].kind == "name" and b.positional else None
        name_span = b.positional[0].span if name else None
        if context == "top" and name is not None:  # a board declares a model
            kind = "model" if sig.keyword == "board" else sig.keyword
            index.symbols.append(Symbol(kind, name, name_span, stmt, sig.keyword))
        elif context == "model" and name is not None:
            index.symbols.append(Symbol("feature", f"{owner}.{name}", name_span, stmt, sig.keyword))
        elif context == "viewpoints" and name is not None:
            index.symbols.append(Symbol("vertex", f"{owner}.{name}", name_span, stmt, sig.keyword))
        if stmt.keyword == "place" and b.has("as") and b.get("as") is not None:
            index.symbols.append(Symbol("place", b.get("as"), b.span("as"), stmt, "place"))
        if stmt.keyword == "include" and b.positional and b.positional[0].value is not None:
            target = (Path(file.path).resolve().parent / b.positional[0].value).resolve()
            index.refs.append(Reference("file", str(target), b.positional[0].span))
        slots = list(zip(sig.positional, b.positional, strict=False))
        for key, occurrences in b.clauses.items():
            for values in occurrences:
                slots += list(zip(sig.clauses[key].slots, values, strict=False))
        for slot, value in slots:
            target = _SLOT_TARGET.get(slot.label)
            if target is None or slot.kind not in ("ref", "refs") or value.value is None:
                continue
            for v in (value.value if slot.kind == "refs" else [value]):
                _reference(index, target, v.value, v.span, owner)
        if stmt.block is not None and sig.block is not None:
            _walk(index, stmt.block, sig.block, file, name)


def _reference(index: Index, target: str, name: str | None, span: Span, owner: str | None) -> None:
    if name is None:
        return
    if target in ("feature", "vertex"):
        index.refs.append(Reference(target, f"{owner}.{name}", span))
    elif target == "place":  # `placement.feature` or `placement.*` in a `visible` list
        placement, _, feature = name.partition(".")
        head = Span(span.file, span.line, span.col, span.line, span.col + len(placement))
        index.refs.append(Reference("place", placement, head))
        place = index.symbol("place", placement)
        if feature and feature != "*" and place is not None and place.stmt.args:
            tail = Span(span.file, span.line, head.end_col + 1, span.end_line, span.end_col)
            index.refs.append(Reference("feature", f"{place.stmt.args[0].name}.{feature}", tail))
    else:
        index.refs.append(Reference(target, name, span))


def definition(index: Index, path: str, line: int, col: int) -> tuple[str, Span | None] | None:
    """Where the name under the cursor is declared: (file path, span), span None for a whole file."""
    item = index.at(path, line, col)
    if isinstance(item, Symbol):
        return item.span.file, item.span
    if isinstance(item, Reference):
        if item.kind == "file":
            return item.name, None
        sym = _resolve(index, item)
        return (sym.span.file, sym.span) if sym else None
    return None


def _resolve(index: Index, ref: Reference) -> Symbol | None:
    sym = index.symbol(ref.kind, ref.name)
    if sym is None and ref.kind == "feature":  # a silhouette's ellipse or a corner's line: same model
        return None
    return sym


def references(index: Index, path: str, line: int, col: int, declaration: bool = True) -> list[Span]:
    """Every use of the name under the cursor (and its declaration)."""
    item = index.at(path, line, col)
    if item is None or (isinstance(item, Reference) and item.kind == "file"):
        return []
    kind, name = item.kind, item.name
    out = [r.span for r in index.refs if r.kind == kind and r.name == name]
    sym = index.symbol(kind, name)
    if declaration and sym is not None:
        out.insert(0, sym.span)
    return out


# --------------------------------------------------------------------------- completion and hover

_WORD = re.compile(r"[A-Za-z_][A-Za-z0-9_.*]*")


def context_at(text: str, line: int) -> tuple[str, str | None]:
    """(context, owner name) of a 1-based line, read from the braces before it.

    Works on text that does not parse, as text being typed usually does.
    """
    stack: list[tuple[str, str | None]] = [("top", None)]
    for raw in source_lines(text)[: line - 1]:
        src = re.sub(r'"[^"]*"', '""', raw).split("#", 1)[0]
        for m in re.finditer(r"[{}]", src):
            if m.group() == "}":
                if len(stack) > 1:
                    stack.pop()
                continue
            words = _WORD.findall(src[: m.start()])
            sig = CONTEXTS[stack[-1][0]].get(words[0]) if words else None
            inner = sig.block if sig is not None and sig.block else stack[-1][0]
            stack.append((inner, words[1] if len(words) > 1 else None))
    return stack[-1]


@dataclass(frozen=True)
class Completion:
    label: str
    kind: str  # keyword | clause | name
    detail: str
    doc: str = ""


def completions(index: Index | None, text: str, line: int, col: int) -> list[Completion]:
    """What may be typed at a 1-based position: keywords, clauses or declared names."""
    lines = source_lines(text)
    before = (lines[line - 1] if line - 1 < len(lines) else "")[: col - 1]
    context, owner = context_at(text, line)
    words = _WORD.findall(before.split("#", 1)[0])
    typing = bool(before) and not before[-1].isspace()
    if typing:
        words = words[:-1]
    sigs = CONTEXTS[context]
    if not words:  # the start of a statement
        return [Completion(k, "keyword", signature(s), s.doc) for k, s in sigs.items()]
    sig = sigs.get(words[0])
    if sig is None:
        return []
    slot = _slot_after(sig, words[1:])
    out: list[Completion] = []
    if slot is not None and slot.kind in ("ref", "refs") and index is not None:
        out += _names(index, _SLOT_TARGET.get(slot.label), owner, context)
    if slot is None or slot.kind == "refs" or slot.kind not in ("ref", "refs"):
        used = set(words[1:])
        for key, clause in sig.clauses.items():
            if key not in used or clause.repeat:
                out.append(Completion(key, "clause", _clause_detail(sig, key), clause.doc))
    if slot is not None and slot.kind == "word":
        out = [Completion(c, "keyword", slot.label) for c in slot.choices] + out
    return out


def _slot_after(sig: Sig, words: list[str]):
    """The slot the next value fills, judged from the words already on the line."""
    for i in range(len(words) - 1, -1, -1):
        clause = sig.clauses.get(words[i])
        if clause is not None:
            taken = len(words) - 1 - i
            if clause.slots and (taken < len(clause.slots) or clause.slots[-1].kind in ("refs", "pts")):
                return clause.slots[min(taken, len(clause.slots) - 1)]
            return None
    return sig.positional[len(words)] if len(words) < len(sig.positional) else None


def _names(index: Index, target: str | None, owner: str | None, context: str) -> list[Completion]:
    out = []
    for s in index.symbols:
        if s.kind != target:
            continue
        if target in ("feature", "vertex"):
            head, _, tail = s.name.partition(".")
            if head == owner:
                out.append(Completion(tail, "name", f"{s.what} in {head}"))
        elif target == "place":
            out.append(Completion(f"{s.name}.*", "name", f"every feature of {s.name}"))
            model = s.stmt.args[0].name if s.stmt.args else ""
            out += [Completion(f"{s.name}.{f.name.partition('.')[2]}", "name", f"{f.what} of {model}")
                    for f in index.symbols if f.kind == "feature" and f.name.startswith(model + ".")]
        else:
            out.append(Completion(s.name, "name", s.what))
    return out


def signature(sig: Sig) -> str:
    """`keyword <takes>`, as the README's reference table writes it."""
    return f"{sig.keyword} {takes(sig)}".strip()


def _clause_detail(sig: Sig, key: str) -> str:
    if sig.keyword in CONTEXTS["pipeline"]:
        from wiredsl.effects import BUILTIN, REGISTRY

        f = REGISTRY[sig.keyword].Params.model_fields[key]
        extra = f.json_schema_extra if isinstance(f.json_schema_extra, dict) else {}
        unit = {"image": " px", "angle": " rad", "length": " m"}.get(extra.get("kind"), "")
        shown = f"{f.default:g}" if isinstance(f.default, (int, float)) and not isinstance(f.default, bool) \
            else f"{f.default!r}"
        whose = ", the paper's" if sig.keyword in BUILTIN else ""  # a plug-in's default is its author's
        return f"{key} (default {shown}{unit}{whose})"
    return key + "".join(f" <{s.label}>" for s in sig.clauses[key].slots)


def hover(index: Index | None, text: str, path: str, line: int, col: int) -> str | None:
    """Markdown for the word under a 1-based position: a statement's signature and
    meaning, a pipeline parameter's default, or a name's declaration."""
    lines = source_lines(text)
    src = lines[line - 1] if line - 1 < len(lines) else ""
    word = next((m for m in _WORD.finditer(src) if m.start() < col <= m.end() + 1 and m.start() + 1 <= col), None)
    if word is None:
        return None
    context, _ = context_at(text, line)
    first = _WORD.match(src.lstrip())
    sig = CONTEXTS[context].get(first.group()) if first else None
    if sig is not None and word.start() == len(src) - len(src.lstrip()):
        found = mesh_summary(path, src) if sig.keyword == "mesh" and context == "model" else ""
        return f"```wiredsl\n{signature(sig)}\n```\n{sig.doc}" + (f"\n\ne.g. `{sig.example}`" if sig.example else "") \
            + found
    if sig is not None and word.group() in sig.clauses:
        clause = sig.clauses[word.group()]
        return f"`{_clause_detail(sig, word.group())}`: {clause.doc}"
    if index is not None:
        item = index.at(path, line, col)
        sym = item if isinstance(item, Symbol) else _resolve(index, item) if isinstance(item, Reference) else None
        if sym is not None:
            declaring = index.files.get(sym.span.file)
            decl = source_lines(declaring.text)[sym.stmt.span.line - 1].strip() if declaring else sym.name
            return f"{sym.what} `{sym.name}`, declared at {sym.span}:\n```wiredsl\n{decl}\n```"
    return None


def mesh_summary(path: str, src: str) -> str:
    """What a `mesh read` line finds in its mesh: its size and bounds as scaled and placed, and the count of each
    kind of feature (compiled as `check` compiles it, from the same cache)."""
    from wiredsl.language.compile import mesh_size, read_mesh_features

    try:
        stmt = ast.parse_text(src.strip() + "\n", path).statements[0]
        out = Collector()
        b = bind(stmt, "model", DEFAULT_UNITS, out)
        if b is None or not b.ok:
            return ""
        found = read_mesh_features(b, DEFAULT_UNITS, out)
    except (WiredslError, IndexError) as exc:
        return f"\n\n**cannot read the mesh**: {exc.diagnostics[0].message if isinstance(exc, WiredslError) else exc}"
    if found is None:
        errors = [d.message for d in out.diagnostics if d.severity == "error"]
        return f"\n\n**cannot read the mesh**: {errors[0] if errors else 'see the diagnostics'}"
    smooth = int(found.contour.sum())
    return (f"\n\n`{b.get('read')}`: {found.triangles:,} triangles, {mesh_size(found)}, "
            f"of them {smooth} smooth (contours)")


@dataclass(frozen=True)
class Outline:
    name: str
    kind: str
    span: Span  # the whole statement
    name_span: Span
    children: tuple[Outline, ...] = ()


def symbols(index: Index) -> list[Outline]:
    """The document's outline: top-level declarations with their features and vertices."""
    out = []
    file = index.files.get(index.path)
    if file is None:
        return out
    for s in index.symbols:
        if s.span.file != index.path or s.kind in ("feature", "vertex"):
            continue
        children = tuple(Outline(c.name.partition(".")[2], c.what, c.stmt.span, c.span) for c in index.symbols
                         if c.kind in ("feature", "vertex") and c.name.partition(".")[0] == s.name
                         and c.span.file == index.path and s.kind in ("model", "viewpoints"))
        out.append(Outline(s.name, s.what, s.stmt.span, s.span, children))
    return out


# --------------------------------------------------------------------------- TextMate grammar

def textmate_grammar() -> dict:
    """Syntax highlighting for editors, generated from the statement table (it cannot drift)."""
    statements = sorted({k for sigs in CONTEXTS.values() for k in sigs})
    clauses = sorted({c for sigs in CONTEXTS.values() for s in sigs.values() for c in s.clauses} - set(statements))
    units = sorted(UNITS, key=lambda u: (-len(u), u))

    def words(ws):
        return r"\b(?:" + "|".join(re.escape(w) for w in ws) + r")\b"

    return {
        "$schema": "https://raw.githubusercontent.com/martinring/tmlanguage/master/tmlanguage.json",
        "name": "wiredsl",
        "scopeName": "source.wiredsl",
        "fileTypes": ["wd"],
        "patterns": [
            {"name": "comment.line.number-sign.wiredsl", "match": "#.*$"},
            {"name": "string.quoted.double.wiredsl", "match": r'"[^"\n]*"'},
            {"name": "keyword.control.statement.wiredsl", "match": r"^\s*" + words(statements)},
            {"name": "keyword.other.clause.wiredsl", "match": words(clauses)},
            {"match": r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?(" + "|".join(re.escape(u) for u in units)
                      + r")?(?![A-Za-z])",
             "name": "constant.numeric.wiredsl", "captures": {"1": {"name": "keyword.other.unit.wiredsl"}}},
            {"name": "variable.other.reference.wiredsl", "match": r"[A-Za-z_][A-Za-z0-9_]*(?:\.(?:[A-Za-z_]\w*|\*))+"},
            {"name": "punctuation.section.block.wiredsl", "match": r"[{}]"},
        ],
    }


# --------------------------------------------------------------------------- the server

MAX_MESSAGE_BYTES = 16 * 1024 * 1024  # a document as large as the compiler reads, plus its JSON framing
MAX_HEADER_BYTES = 64 * 1024
_SKIPPED = b'{"jsonrpc": "2.0", "method": "$/wiredsl/skipped", "params": {}}'  # an unknown notification: ignored


class BoundedInput:
    """The server's stdin: a header line or message body over the limit is skipped, never held in memory.

    pygls reads a message's `Content-Length` bytes in one call, so a header claiming 100 GB was a
    MemoryError. A body over the limit is read and dropped in small pieces (the next message is still
    framed right); the end of input ends the server as usual.
    """

    def __init__(self, raw) -> None:
        self.raw = raw

    def readline(self) -> bytes:
        return self.raw.readline(MAX_HEADER_BYTES)

    def read(self, n: int) -> bytes:
        if n <= MAX_MESSAGE_BYTES:
            return self.raw.read(n)
        import sys

        sys.stderr.write(f"wiredsl lsp: skipping a message of {n:,} bytes, over the limit of "
                         f"{MAX_MESSAGE_BYTES:,}\n")
        sys.stderr.flush()
        left = n
        while left:
            chunk = self.raw.read(min(left, 1 << 16))
            if not chunk:
                return b""  # the input ended inside the message: stop serving
            left -= len(chunk)
        return _SKIPPED


def serve() -> None:
    """Run the language server on stdin/stdout until the client exits."""
    from lsprotocol import types as T
    from pygls.lsp.server import LanguageServer

    from wiredsl import __version__

    server = LanguageServer("wiredsl", __version__)
    indexes: dict[str, Index] = {}  # by document URI: the latest analysis
    published: dict[str, set[str]] = {}  # root URI -> URIs it published diagnostics to

    def doc_path(uri: str) -> str:
        return server.workspace.get_text_document(uri).path

    def opened(uri: str):
        """The document if the client opened it, else None: pygls would read any other URI from disk, without
        bound (file:///dev/zero) or failing (a file that does not exist)."""
        doc = server.workspace.get_text_document(uri)
        return doc if doc.version is not None else None

    def to_range(span: Span | None) -> T.Range:
        if span is None:
            return T.Range(T.Position(0, 0), T.Position(0, 0))
        return T.Range(T.Position(span.line - 1, span.col - 1), T.Position(span.end_line - 1, span.end_col - 1))

    def uri_of(file: str) -> str:
        return Path(file).resolve().as_uri()

    def refresh(uri: str) -> None:
        doc = opened(uri)
        if doc is None:
            return
        index = analyse(doc.path, doc.source)
        indexes[uri] = index
        by_uri: dict[str, list] = {uri: []}
        for d in index.diagnostics:
            target = uri if d.span is None or d.span.file == index.path else uri_of(d.span.file)
            message = d.message + (f"\nhint: {d.hint}" if d.hint else "") + "".join(f"\nnote: {n}" for n in d.notes)
            severity = T.DiagnosticSeverity.Error if d.severity == "error" else T.DiagnosticSeverity.Warning
            by_uri.setdefault(target, []).append(
                T.Diagnostic(to_range(d.span), message, severity=severity, code=d.code, source="wiredsl"))
        for stale in published.get(uri, set()) - set(by_uri):
            by_uri[stale] = []
        published[uri] = set(by_uri)
        for target, diags in by_uri.items():
            server.text_document_publish_diagnostics(T.PublishDiagnosticsParams(uri=target, diagnostics=diags))

    @server.feature(T.TEXT_DOCUMENT_DID_OPEN)
    def did_open(ls, params: T.DidOpenTextDocumentParams):
        refresh(params.text_document.uri)

    @server.feature(T.TEXT_DOCUMENT_DID_CHANGE)
    def did_change(ls, params: T.DidChangeTextDocumentParams):
        refresh(params.text_document.uri)

    @server.feature(T.TEXT_DOCUMENT_DID_SAVE)
    def did_save(ls, params: T.DidSaveTextDocumentParams):
        refresh(params.text_document.uri)

    def where(uri: str, pos: T.Position) -> tuple[Index | None, str, int, int]:
        index = indexes.get(uri)
        path = index.path if index else sources.display_path(Path(doc_path(uri)))
        return index, path, pos.line + 1, pos.character + 1

    @server.feature(T.TEXT_DOCUMENT_COMPLETION, T.CompletionOptions(trigger_characters=[" ", "."]))
    def completion(ls, params: T.CompletionParams):
        doc = opened(params.text_document.uri)
        if doc is None:
            return None
        index, _, line, col = where(params.text_document.uri, params.position)
        text = doc.source
        kinds = {"keyword": T.CompletionItemKind.Keyword, "clause": T.CompletionItemKind.Property,
                 "name": T.CompletionItemKind.Reference}
        return T.CompletionList(is_incomplete=False, items=[
            T.CompletionItem(c.label, kind=kinds[c.kind], detail=c.detail, documentation=c.doc or None)
            for c in completions(index, text, line, col)])

    @server.feature(T.TEXT_DOCUMENT_HOVER)
    def on_hover(ls, params: T.HoverParams):
        doc = opened(params.text_document.uri)
        if doc is None:
            return None
        index, path, line, col = where(params.text_document.uri, params.position)
        text = doc.source
        md = hover(index, text, path, line, col)
        return T.Hover(T.MarkupContent(T.MarkupKind.Markdown, md)) if md else None

    @server.feature(T.TEXT_DOCUMENT_DEFINITION)
    def on_definition(ls, params: T.DefinitionParams):
        index, path, line, col = where(params.text_document.uri, params.position)
        found = definition(index, path, line, col) if index else None
        if found is None:
            return None
        file, span = found
        return T.Location(uri_of(file), to_range(span))

    @server.feature(T.TEXT_DOCUMENT_REFERENCES)
    def on_references(ls, params: T.ReferenceParams):
        index, path, line, col = where(params.text_document.uri, params.position)
        spans = references(index, path, line, col, params.context.include_declaration) if index else []
        return [T.Location(uri_of(s.file), to_range(s)) for s in spans]

    @server.feature(T.TEXT_DOCUMENT_FORMATTING)
    def on_format(ls, params: T.DocumentFormattingParams):
        from wiredsl.language.fmt import format_text

        doc = opened(params.text_document.uri)
        if doc is None:
            return None
        try:
            new = format_text(doc.source, doc.path)
        except WiredslError:
            return None  # the diagnostics already say why
        if new == doc.source:
            return []
        end = T.Position(len(doc.lines), 0)
        return [T.TextEdit(T.Range(T.Position(0, 0), end), new)]

    @server.feature(T.TEXT_DOCUMENT_DOCUMENT_SYMBOL)
    def on_symbols(ls, params: T.DocumentSymbolParams):
        index = indexes.get(params.text_document.uri)
        kinds = {"model": T.SymbolKind.Class, "camera": T.SymbolKind.Object, "rig": T.SymbolKind.Object,
                 "viewpoints": T.SymbolKind.Array, "path": T.SymbolKind.Array, "pipeline": T.SymbolKind.Function,
                 "place": T.SymbolKind.Variable, "scene": T.SymbolKind.Module}

        def convert(o: Outline) -> T.DocumentSymbol:
            return T.DocumentSymbol(name=o.name, kind=kinds.get(o.kind, T.SymbolKind.Field), detail=o.kind,
                                    range=to_range(o.span), selection_range=to_range(o.name_span),
                                    children=[convert(c) for c in o.children])

        return [convert(o) for o in symbols(index)] if index else []

    import sys

    server.start_io(stdin=BoundedInput(sys.stdin.buffer))
