"""`wiredsl fmt`: a file's AST printed back in canonical form, comments kept.

Canonical form: two-space indents, one space between arguments, `(a, b)` and
`[a, b]` with a space after each comma, numbers as written, at most one blank
line between statements, long lists wrapped and long statements continued
with `\\` between arguments (a point is never split). Comments stay with the statement
they precede or end; the output parses to the same AST (so compiles to the
same scene) and formatting it again changes nothing.
"""

from __future__ import annotations

import bisect

from wiredsl.diagnostics import source_lines
from wiredsl.language import ast

WIDTH = 100
INDENT = "  "


def format_text(text: str, path: str = "<string>") -> str:
    """Canonical form of a file's text (raises WiredslError on a syntax error)."""
    file = ast.parse_text(text, path)
    printer = _Printer(file)
    out = printer.block(file.statements, 0, 0, len(source_lines(text)) + 1)
    while out and out[-1] == "":
        out.pop()
    return "\n".join(out) + "\n" if out else ""


class _Printer:
    def __init__(self, file: ast.File):
        self.lines = source_lines(file.text)
        self.comments = sorted(file.comments, key=lambda c: (c.line, c.col))
        self.comment_lines = [c.line for c in self.comments]
        self.used: set[int] = set()

    def _take(self, lo: int, hi: int) -> list[ast.Comment]:
        """Unused comments on lines lo..hi inclusive (bisected: scanning them all per statement was quadratic)."""
        a, b = bisect.bisect_left(self.comment_lines, lo), bisect.bisect_right(self.comment_lines, hi)
        got = [c for c in self.comments[a:b] if id(c) not in self.used]
        self.used.update(id(c) for c in got)
        return got

    def _blank_between(self, a: int, b: int) -> bool:
        return any(not self.lines[k - 1].strip() for k in range(a + 1, b) if 0 < k <= len(self.lines))

    def block(self, stmts, depth: int, lo: int, hi: int) -> list[str]:
        """Lines for `stmts`, which sit between source lines lo and hi (exclusive)."""
        pad = INDENT * depth
        out: list[str] = []
        prev_end = lo
        for i, s in enumerate(stmts):
            leading = self._take(prev_end + 1, s.span.line - 1)
            first = leading[0].line if leading else s.span.line
            if i and self._blank_between(prev_end, first):
                out.append("")
            out += [pad + c.text for c in leading]
            out += self.statement(s, depth)
            prev_end = s.span.end_line
        tail = self._take(prev_end + 1, hi - 1)
        if tail:
            if out and self._blank_between(prev_end, tail[0].line):
                out.append("")
            out += [pad + c.text for c in tail]
        return out

    def statement(self, s: ast.Statement, depth: int) -> list[str]:
        pad = INDENT * depth
        if s.block is None:
            inner = self._take(s.span.line, s.span.end_line - 1)  # comments inside a multi-line statement
            trailing = self._take(s.span.end_line, s.span.end_line)
            body = self.head(s, depth)
            out = [pad + c.text for c in inner] + body
            return _trail(out, trailing)
        header = self.head(s, depth)
        header_comments = self._take(s.span.line, s.span.line)
        inner = self.block(s.block, depth + 1, s.span.line, s.span.end_line)
        closing = self._take(s.span.end_line, s.span.end_line)
        if not inner and not header_comments:
            header[-1] += " {}"
            return _trail(header, closing)
        header[-1] += " {"
        return _trail(header, header_comments) + inner + _trail([pad + "}"], closing)

    def head(self, s: ast.Statement, depth: int) -> list[str]:
        pad = INDENT * depth
        flat = " ".join([s.keyword, *(_flat(a) for a in s.args)])
        if len(pad) + len(flat) <= WIDTH:
            return [pad + flat]
        # Too long: wrap inside a list or tuple of compound items (the grammar allows newlines there), and
        # between arguments with a `\` continuation; a point's tuple is never split.
        parts = [s.keyword]
        lines: list[str] = []
        cont = pad + INDENT * 2
        for arg in s.args:
            flat_arg = _flat(arg)
            here = " ".join(parts) if lines else pad + " ".join(parts)
            if len(here) + 1 + len(flat_arg) <= WIDTH:
                parts.append(flat_arg)
                continue
            if isinstance(arg, ast.List) or (isinstance(arg, ast.Tuple) and not all(map(_scalar, arg.items))):
                opener, closer = ("[", "]") if isinstance(arg, ast.List) else ("(", ")")
                lines.append(here + " " + opener)
                lines += _wrap([_flat(x) for x in arg.items], pad + INDENT * 2,
                               one_per_line=all(isinstance(x, ast.List) for x in arg.items))
                parts = [pad + INDENT + closer]
                continue
            lines.append(here + " \\")
            parts = [cont + flat_arg]
        lines.append(" ".join(parts) if lines else pad + " ".join(parts))
        return lines


def _scalar(arg: ast.Arg) -> bool:
    """A number, string or name; a tuple of them (a point) is kept on one line."""
    return isinstance(arg, (ast.Number, ast.String, ast.Ref))


def _trail(lines: list[str], comments: list[ast.Comment]) -> list[str]:
    if comments:
        lines[-1] += "  " + " ".join(c.text for c in comments)
    return lines


def _wrap(items: list[str], pad: str, one_per_line: bool) -> list[str]:
    out: list[str] = []
    line = ""
    for item in items:
        piece = item + ","
        if one_per_line or (line and len(pad) + len(line) + 1 + len(piece) > WIDTH):
            if line:
                out.append(pad + line)
            line = piece
        else:
            line = f"{line} {piece}" if line else piece
    if line:
        out.append(pad + line)
    return out


def _flat(arg: ast.Arg) -> str:
    if isinstance(arg, ast.Number):
        return arg.text
    if isinstance(arg, ast.String):
        return f'"{arg.value}"'
    if isinstance(arg, ast.Ref):
        return arg.name
    inner = ", ".join(_flat(x) for x in arg.items)
    return f"({inner})" if isinstance(arg, ast.Tuple) else f"[{inner}]"
