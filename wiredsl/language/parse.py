"""Stage 1: text -> lark tree (LALR), with syntax errors as diagnostics."""

from __future__ import annotations

import functools
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


class Brackets:
    """Postlexer: newlines inside ( ) and [ ] are spaces; runs of newlines are one; nesting is bounded.

    Its state lives on the instance, not in the generator, because lark starts a
    new generator when it resumes after a syntax error; `reset` starts a parse.
    """

    always_accept = ("_NL",)

    def __init__(self) -> None:
        self.reset()

    def reset(self, path: str = "<string>") -> None:
        self.depth = 0
        self.nesting = 0  # ( [ and {
        self.last_nl = True  # drop newlines at the start of the file too
        self.path = path

    def process(self, stream):
        for tok in stream:
            kind = tok.type
            if kind == "_NL":
                if self.depth or self.last_nl:
                    continue
                self.last_nl = True
            else:
                self.last_nl = False
                if kind == "LPAR" or kind == "LSQB":
                    self.depth += 1
                elif kind == "RPAR" or kind == "RSQB":
                    self.depth = max(self.depth - 1, 0)
                if kind in ("LPAR", "LSQB", "LBRACE"):
                    self.nesting += 1
                    if self.nesting > MAX_NESTING:
                        span = Span(self.path, tok.line, tok.column, tok.line, tok.column + 1)
                        raise WiredslError([Diagnostic("error", "E151", f"brackets and blocks nested deeper than "
                                                       f"{MAX_NESTING}", span)])
                elif kind in ("RPAR", "RSQB", "RBRACE"):
                    self.nesting = max(self.nesting - 1, 0)
            yield tok


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
    return run(parser(), text, path)[0]


def run(p: lark.Lark, text: str, path: str) -> tuple[object, list[lark.Token]]:
    """Parse with `p`; return the result and the comment tokens met on the way.

    A syntax error does not stop the parse: the rest of its line is skipped and
    parsing goes on, so every syntax error of a file is reported (one a line).
    """
    _CommentSink.tokens = comments = []
    _BRACKETS.reset(path)
    errors: list[Diagnostic] = []

    def recover(exc: lark.exceptions.UnexpectedInput) -> bool:
        d = syntax_diagnostic(exc, text, path)
        if not errors or errors[-1].span.line != d.span.line:  # one error a line: the rest is its echo
            errors.append(d)
        return d.code != "E003" and len(errors) <= MAX_REPORTED

    try:
        result = p.parse(text, on_error=recover)
    except lark.exceptions.UnexpectedInput as exc:
        if not errors or errors[-1].span.line != (exc.line if exc.line > 0 else 1):
            errors.append(syntax_diagnostic(exc, text, path))
    except WiredslError as err:  # nesting too deep: stop there
        raise WiredslError(errors + err.diagnostics) from None
    finally:
        _CommentSink.tokens = []
    if errors:
        raise WiredslError(errors) from None
    return result, comments


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
