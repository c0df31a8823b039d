"""Small helpers shared by the tests."""

from __future__ import annotations

from wiredsl.ast import Program, parse_text
from wiredsl.compile import compile_program
from wiredsl.diagnostics import WiredslError


def compile_text(text: str, path: str = "t.wd"):
    """Compile a one-file scene from text; returns (scene, warnings)."""
    file = parse_text(text, path)
    program = Program(file, files={path: file}, statements=list(file.statements))
    return compile_program(program)


def errors_of(text: str) -> list[str]:
    """'line:col: CODE message' of every error a text produces."""
    try:
        compile_text(text)
    except WiredslError as err:
        return [f"{d.span.line}:{d.span.col}: {d.code} {d.message}" for d in err.diagnostics if d.severity == "error"]
    return []
