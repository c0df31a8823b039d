"""Stage 1: text -> lark tree (LALR), with syntax errors as diagnostics."""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field
from pathlib import Path

import lark

from wiredsl.diagnostics import MAX_REPORTED, Diagnostic, Span, WiredslError, source_lines


def grammar_path() -> Path:
    """The grammar file: packaged copy when installed, the checkout's `grammar/` otherwise."""
    here = Path(__file__).resolve().parent.parent  # the package folder
    for candidate in (here / "grammar" / "wiredsl.lark", here.parent / "grammar" / "wiredsl.lark"):
        if candidate.is_file():
            return candidate
    raise FileNotFoundError("wiredsl.lark not found next to the package")


class _CommentSink:
    """Where the lexer puts comment tokens during one parse; `fmt` needs them."""

    tokens: list[lark.Token] = []


MAX_NESTING = 32  # brackets and blocks; real scenes nest 2 deep, and deeper input would exhaust recursion later
MAX_ECHOES = 200  # errors in a row on one line (one reported) before the parse gives up on the file


_CLOSER = {"LPAR": "RPAR", "LSQB": "RSQB", "LBRACE": "RBRACE"}
_OPENER = {v: k for k, v in _CLOSER.items()}
_CHAR = {"LPAR": "(", "RPAR": ")", "LSQB": "[", "RSQB": "]", "LBRACE": "{", "RBRACE": "}"}


class Brackets:
    """Postlexer: newlines inside ( ) and [ ] are spaces; runs of newlines are one; nesting is bounded.

    It keeps the stack of open brackets, so that a syntax error can be reported at the bracket that
    was never closed, and can close a block before a given line (`close_before`, line -> count) when a
    first parse found it unclosed. Its state lives on the instance, not in the generator, because
    lark starts a new generator when it resumes after a syntax error; `reset` starts a parse.
    """

    always_accept = ("_NL",)

    def __init__(self) -> None:
        self.reset()

    def reset(self, path: str = "<string>", close_before: dict[int, int] | None = None) -> None:
        self.last_nl = True  # drop newlines at the start of the file too
        self.path = path
        self.stack: list[lark.Token] = []  # open ( [ {
        self.before: list[lark.Token] = []  # the stack before the last closing bracket
        self.prev: lark.Token | None = None  # the token before the last one yielded
        self.last: lark.Token | None = None
        self.close_before = dict(close_before or {})

    @property
    def depth(self) -> int:
        return sum(t.type != "LBRACE" for t in self.stack)

    def process(self, stream):
        for tok in stream:
            kind = tok.type
            if kind == "_NL":
                if self.depth or self.last_nl:
                    continue
                self.last_nl = True
                yield tok
                continue
            if self.close_before and tok.line in self.close_before and self.last is not None:
                yield from self._close_blocks(self.close_before.pop(tok.line))
            self.last_nl = False
            if kind in _CLOSER:
                self.stack.append(tok)
                if len(self.stack) > MAX_NESTING:
                    span = Span(self.path, tok.line, tok.column, tok.line, tok.column + 1)
                    raise WiredslError([Diagnostic("error", "E151", f"brackets and blocks nested deeper than "
                                                   f"{MAX_NESTING}", span)])
            elif kind in _OPENER:
                self.before = list(self.stack)
                if self.stack and self.stack[-1].type == _OPENER[kind]:
                    self.stack.pop()
            self.prev, self.last = self.last, tok
            yield tok

    def _close_blocks(self, n: int):
        """Synthetic `}` (and newlines) at the end of the last token, closing n blocks opened before."""
        for _ in range(n):
            if not self.stack or self.stack[-1].type != "LBRACE":
                return
            self.stack.pop()
            if not self.last_nl:
                yield synthetic("_NL", "\n", self.last)
            yield synthetic("RBRACE", "}", self.last)
            yield synthetic("_NL", "\n", self.last)
            self.last_nl = True

    def open_at(self, tok: lark.Token) -> list[lark.Token]:
        """The brackets open when the parser met `tok` (the token last yielded, or an earlier one)."""
        return self.before if tok is self.last and tok.type in _OPENER else self.stack


def synthetic(kind: str, value: str, after: lark.Token) -> lark.Token:
    """A zero-width token at the end of `after`, standing for one the user left out."""
    line, col = after.end_line or after.line, after.end_column or after.column
    return lark.Token(kind, value, after.end_pos, line, col, line, col, after.end_pos)


_BRACKETS = Brackets()


def _cache_ok() -> bool:
    """lark caches tables in the temporary directory; skip the cache where that is not writable."""
    import os
    import tempfile

    return os.access(tempfile.gettempdir(), os.W_OK)


def _sink(tok: lark.Token) -> None:
    _CommentSink.tokens.append(tok)


@functools.lru_cache(maxsize=4)
def parser(transformer: lark.Transformer | None = None) -> lark.Lark:
    """The one LALR parser; with a transformer, the tree is transformed while parsing.

    The AST transformer takes every span from tokens (the grammar keeps brackets), so
    position propagation, a third of the parse time, is on only for the plain tree.
    """
    return lark.Lark(
        grammar_path().read_text(encoding="utf-8"),
        parser="lalr",
        cache=transformer is None or _cache_ok(),  # LALR tables keyed by the grammar's hash: fast cold starts
        propagate_positions=transformer is None,
        maybe_placeholders=False,
        transformer=transformer,
        lexer_callbacks={"COMMENT": _sink},
        postlex=_BRACKETS,
    )


def parse_tree(text: str, path: str = "<string>") -> lark.Tree:
    """Parse text into a lark tree, raising WiredslError with a located diagnostic."""
    parsed = run(parser(), text, path)
    if parsed.errors:
        raise WiredslError(parsed.errors)
    return parsed.result


@dataclass
class Parsed:
    """What a parse gives: the result of what parsed, the comments met, and the syntax errors.

    `broken` holds the positions (line, col) of the tokens the parser skipped or stood in for, so that
    the statements around them can be set aside rather than compiled as if whole.
    """

    result: object
    comments: list[lark.Token]
    errors: list[Diagnostic] = field(default_factory=list)
    broken: list[tuple[int, int]] = field(default_factory=list)


def run(p: lark.Lark, text: str, path: str, close_before: dict[int, int] | None = None) -> Parsed:
    """Parse with `p`; every syntax error is collected (one a line) and the parse goes on after it.

    A bad token is skipped; a `(` or `[` left open at the end of a line is closed there; a `{` never
    closed is reported where it was opened, and the file is parsed again with the block closed before
    the first later line that starts a statement at its indentation (or at the end of the file).
    """
    _CommentSink.tokens = comments = []
    _BRACKETS.reset(path, close_before)
    errors: list[Diagnostic] = []
    broken: list[tuple[int, int]] = []
    unclosed: dict[int, int] = {}  # line -> blocks to close before it, for a second parse
    lines = source_lines(text)  # once: recovery may be called for every token of a long broken line

    echoes = [0]  # errors in a row on one line, not reported: past MAX_ECHOES the parse stops there (a line of
    # 4,000,000 `{` was 4,000,000 recoveries, 33 s, for one diagnostic)

    def add(d: Diagnostic) -> None:
        if not errors or errors[-1].span.line != d.span.line or d.code == "E003":  # the rest of a line is echo
            errors.append(d)
            echoes[0] = 0
        else:
            echoes[0] += 1

    def recover(exc: lark.exceptions.UnexpectedInput) -> bool:
        tok = getattr(exc, "token", None)
        if isinstance(exc, lark.exceptions.UnexpectedToken) and tok is not None:
            opened = _BRACKETS.open_at(tok)
            if tok.type == "$END" and opened:
                for b in opened:
                    add(unclosed_diagnostic(b, lines, path, None))
                    # a bracket's statement is set aside; for a block, only the last statement (cut short?)
                    broken.append((b.line, b.column) if b.type != "LBRACE" else (tok.line, tok.column))
                    if b.type == "LBRACE" and close_before is None:
                        line = _block_end_guess(b, lines)
                        if line is not None:
                            unclosed[line] = unclosed.get(line, 0) + 1
                return _close(exc, opened, None) and len(errors) <= MAX_REPORTED
            inner = _open_parens(opened)
            if inner and inner[0].line < tok.line and _starts_statement(tok, lines):
                add(unclosed_diagnostic(inner[0], lines, path, tok))
                broken.append((inner[0].line, inner[0].column))
                return _close(exc, inner, tok) and len(errors) <= MAX_REPORTED
        d = syntax_diagnostic(exc, text, path)
        add(d)
        broken.append((d.span.line, d.span.col))
        if echoes[0] >= MAX_ECHOES:
            errors[-1] = dataclasses.replace(errors[-1], notes=(*errors[-1].notes, f"over {MAX_ECHOES} more errors "
                                                                 "on this line: the rest of the file is not checked"))
            return False
        return d.code != "E003" and len(errors) <= MAX_REPORTED

    result = None
    try:
        result = p.parse(text, on_error=recover)
    except lark.exceptions.UnexpectedInput as exc:
        d = syntax_diagnostic(exc, text, path)
        if not any(e.span == d.span for e in errors):
            add(d)
        broken.append((d.span.line, d.span.col))
    except WiredslError as err:  # nesting too deep: stop there
        raise WiredslError(errors + err.diagnostics) from None
    finally:
        _CommentSink.tokens = []
    if unclosed:  # parse again with each block closed where its indentation says it ends
        again = run(p, text, path, unclosed)
        seen = {d.span for d in again.errors}
        opened_here = [d for d in errors if d.code == "E003" and d.message.startswith("'{'") and d.span not in seen]
        again.errors = sorted(opened_here + again.errors, key=lambda d: (d.span.line, d.span.col))
        return again
    return Parsed(result, comments, errors, broken)


def _open_parens(opened: list[lark.Token]) -> list[lark.Token]:
    """The ( and [ open inside the innermost block, outermost first."""
    i = len(opened)
    while i and opened[i - 1].type != "LBRACE":
        i -= 1
    return opened[i:]


def _starts_statement(tok: lark.Token, lines: list[str]) -> bool:
    """Is `tok` the first on its line and a `}` or a statement's keyword? Then a bracket left open on an
    earlier line, not this token, is the mistake."""
    if not 0 < tok.line <= len(lines) or lines[tok.line - 1][: tok.column - 1].strip():
        return False
    if tok.type == "RBRACE":
        return True
    if lines[tok.line - 1][tok.end_column - 1: tok.end_column] == ".":  # `right.f`: a reference, not `right`
        return False
    from wiredsl.language.statements import CONTEXTS

    return tok.type == "WORD" and any(str(tok) in sigs for sigs in CONTEXTS.values())


def _block_end_guess(brace: lark.Token, lines: list[str]) -> int | None:
    """The first line after an unclosed `{` that starts at or left of its statement's indentation with a
    statement keyword (the block was meant to end before it); None when there is none."""
    from wiredsl.language.statements import CONTEXTS

    opening = lines[brace.line - 1]
    indent = len(opening) - len(opening.lstrip())
    keywords = set(CONTEXTS["top"]) if indent == 0 else {k for sigs in CONTEXTS.values() for k in sigs}
    for n in range(brace.line + 1, len(lines) + 1):
        src = lines[n - 1]
        word = src.lstrip().split(" ", 1)[0].split("{", 1)[0]
        if src.strip() and len(src) - len(src.lstrip()) <= indent and word in keywords:
            return n
    return None


def _close(exc: lark.exceptions.UnexpectedToken, brackets: list[lark.Token], tok: lark.Token | None) -> bool:
    """Stand in for the closing brackets the user left out, then give the parser `tok` again."""
    ip = exc.interactive_parser
    after = _BRACKETS.prev if tok is not None else _BRACKETS.last
    after = after or exc.token
    try:
        for b in reversed(brackets):
            ip.feed_token(synthetic(_CLOSER[b.type], _CHAR[_CLOSER[b.type]], after))
            if b in _BRACKETS.stack:
                _BRACKETS.stack.remove(b)
        if tok is not None:
            if tok.type != "RBRACE":
                ip.feed_token(synthetic("_NL", "\n", after))
            ip.feed_token(tok)
            if tok.type == "RBRACE" and _BRACKETS.stack and _BRACKETS.stack[-1].type == "LBRACE":
                _BRACKETS.stack.pop()
    except lark.exceptions.UnexpectedInput:
        return False
    return True


def unclosed_diagnostic(bracket: lark.Token, lines: list[str], path: str, noticed: lark.Token | None) -> Diagnostic:
    """E003 at a bracket never closed, with a note of where the parser found out (None: the end of the file)."""
    char = _CHAR[bracket.type]
    span = Span(path, bracket.line, bracket.column, bracket.line, bracket.column + 1)
    if noticed is None:
        last = lines[-1] if lines else ""
        where = f"{path}:{max(len(lines), 1)}:{len(last) + 1}"
        note = f"the parser noticed at the end of the file ({where})"
    else:
        what = "starts the next statement" if noticed.type == "WORD" else "ends the block"
        note = f"the parser noticed at {path}:{noticed.line}:{noticed.column}, where {str(noticed)!r} {what}"
    hint = f"close it with '{_CHAR[_CLOSER[bracket.type]]}'"
    if bracket.type == "LBRACE":
        line = _block_end_guess(bracket, lines)
        if line is not None:
            hint = f"perhaps a '}}' is missing before line {line}"
    return Diagnostic("error", "E003", f"'{char}' opened here is never closed", span, hint, (note,))


_TOKEN_WORDS = {
    "_NL": "end of line",
    "$END": "end of file",
    "LBRACE": "'{'",
    "RBRACE": "'}'",
    "LPAR": "'('",
    "RPAR": "')'",
    "LSQB": "'['",
    "RSQB": "']'",
    "COMMA": "','",
    "DOT": "'.'",
    "STAR": "'*'",
    "QUANTITY": "a number",
    "WORD": "a name",
    "STRING": "a string",
}


def _describe(names: set[str]) -> str:
    words = sorted({_TOKEN_WORDS.get(n, n) for n in names})
    return words[0] if len(words) == 1 else ", ".join(words[:-1]) + " or " + words[-1]


def syntax_diagnostic(exc: lark.exceptions.UnexpectedInput, text: str, path: str) -> Diagnostic:
    """Map a lark error to a friendly, located diagnostic."""
    line, col = exc.line if exc.line > 0 else 1, exc.column if exc.column > 0 else 1
    if isinstance(exc, lark.exceptions.UnexpectedCharacters):
        char = text[exc.pos_in_stream] if exc.pos_in_stream < len(text) else "?"
        hint = "strings use double quotes" if char == "'" else None
        return Diagnostic("error", "E002", f"unexpected character {char!r}", Span(path, line, col, line, col + 1), hint)
    token = getattr(exc, "token", None)
    if isinstance(exc, lark.exceptions.UnexpectedEOF) or (token is not None and token.type == "$END"):
        lines = source_lines(text) or [""]
        line = len(lines)
        col = len(lines[-1]) + 1
        return Diagnostic(
            "error", "E003", "unexpected end of file", Span(path, line, col, line, col + 1),
            "a '{', '(' or '[' is not closed",
        )
    tok = exc.token
    expected = set(getattr(exc, "expected", ()) or ())
    span = Span(path, tok.line, tok.column, tok.end_line or tok.line, tok.end_column or tok.column + 1)
    if tok.type == "RBRACE" and "RBRACE" not in expected:
        return Diagnostic("error", "E001", "unmatched '}'", span, "no block is open here")
    if tok.type == "LBRACE" and tok.type not in expected:
        return Diagnostic("error", "E001", "a '{' block must follow a statement's keyword and arguments", span)
    if expected & {"COMMA", "RPAR", "RSQB"} and tok.type not in expected:
        hint = f"expected {_describe(expected)}"
        return Diagnostic("error", "E001", f"unexpected {tok.value!r} in a list", span, hint)
    return Diagnostic("error", "E001", f"unexpected {tok.value!r}", span, f"expected {_describe(expected)}")
