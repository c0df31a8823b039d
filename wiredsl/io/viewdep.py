"""View-dependency files (schema/viewdep.schema.json): which features each view-point sees."""

from __future__ import annotations

import json
from pathlib import Path

from wiredsl.diagnostics import Diagnostic, Span, WiredslError
from wiredsl.scene import Scene


def of_scene(scene: Scene) -> dict[str, list[str]] | None:
    """The lists of the file the scene's view-points name (`visibility file`), else None."""
    vp = scene.viewpoints
    if vp is None or vp.visibility != "file":
        return None
    return read(Path(scene.source).parent / vp.file, scene)


def read(path: Path, scene: Scene) -> dict[str, list[str]]:
    """View-point -> visible feature ids, from a view-dependency file (schema/viewdep.schema.json)."""
    from wiredsl.io.schema import problems
    from wiredsl.io.sources import decode, display_path, read_bytes

    where = Span(display_path(path), 1, 1, 1, 1)
    try:
        text = decode(read_bytes(path, "view-dependency file", Span(scene.source, 1, 1, 1, 1)), path,
                      "view-dependency file")
        doc = json.loads(text)
    except WiredslError as err:
        raise WiredslError([Diagnostic(d.severity, d.code, d.message, d.span,
                                       "run 'wiredsl viewdep' on the scene to write it") for d in err.diagnostics]
                           ) from None
    except json.JSONDecodeError as exc:  # at the line and column of the file where the JSON breaks
        at = Span(where.file, exc.lineno, exc.colno, exc.lineno, exc.colno + 1)
        raise WiredslError([Diagnostic("error", "E010", f"cannot read view-dependency file: {exc.msg}", at,
                                       "run 'wiredsl viewdep' on the scene to write it")]) from None
    bad = problems(doc)
    if bad:
        raise WiredslError([Diagnostic("error", "E142", f"view-dependency file {where.file}: {bad[0]}", where)])
    return doc["viewpoints"]
