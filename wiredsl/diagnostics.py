"""Source spans and compiler diagnostics (gcc/rustc form, or JSON)."""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

MAX_REPORTED = 20
MAX_TOKEN = 200  # a longer run of non-blank characters in a message is quoted as its start and end
MAX_TEXT = 2000  # a message, hint or note longer than this keeps its start and end
MAX_LINE = 160  # a longer source line is shown as a window around the span


@dataclass(frozen=True, slots=True)
class Span:
    """A range in a source file; lines and columns count from 1, end exclusive."""

    file: str
    line: int
    col: int
    end_line: int
    end_col: int

    def __str__(self) -> str:
        return f"{self.file}:{self.line}:{self.col}"


@dataclass(frozen=True, slots=True)
class Diagnostic:
    """One message about the input, pointing at a span."""

    severity: str  # "error" | "warning"
    code: str
    message: str
    span: Span | None
    hint: str | None = None
    notes: tuple[str, ...] = ()

    def __post_init__(self):
        # messages quote the input: a 5,000,000-digit token must not become 15 MB of diagnostics
        object.__setattr__(self, "message", bounded(self.message))
        if self.hint is not None:
            object.__setattr__(self, "hint", bounded(self.hint))
        if self.notes:
            object.__setattr__(self, "notes", tuple(bounded(n) for n in self.notes))

    def to_json(self) -> dict:
        out: dict = {"severity": self.severity, "code": self.code, "message": self.message}
        if self.span is not None:
            s = self.span
            out.update(file=s.file, line=s.line, column=s.col, end_line=s.end_line, end_column=s.end_col)
        if self.hint:
            out["hint"] = self.hint
        if self.notes:
            out["notes"] = list(self.notes)
        return out


class WiredslError(Exception):
    """Raised when input cannot be turned into a scene; carries every diagnostic found."""

    def __init__(self, diagnostics: Sequence[Diagnostic]):
        self.diagnostics = in_order(diagnostics)
        super().__init__("\n".join(f"{d.span}: {d.severity}[{d.code}]: {d.message}" if d.span is not None
                                   else f"{d.severity}[{d.code}]: {d.message}" for d in self.diagnostics))

    def __reduce__(self):  # whole across processes (a study's workers)
        return (self.__class__, (self.diagnostics,))


@dataclass
class Collector:
    """Collects diagnostics so that a check reports every error of a file, not just the first."""

    diagnostics: list[Diagnostic] = field(default_factory=list)
    n_errors: int = 0  # kept as they come: counting the list at every statement made checks quadratic
    # While part of a program did not load (a missing include, a syntax error), a reference to an unknown
    # name may well be to a name declared there: `unknown` then counts it instead of reporting it.
    hold_unknown: bool = False
    unknown_held: int = 0

    def error(self, code: str, message: str, span: Span | None, hint: str | None = None) -> None:
        self.diagnostics.append(Diagnostic("error", code, message, span, hint))
        self.n_errors += 1

    def unknown(self, message: str, span: Span | None, hint: str | None = None) -> None:
        """E104 for a reference to a name the program does not declare (held back, see `hold_unknown`)."""
        if self.hold_unknown:
            self.unknown_held += 1
        else:
            self.error("E104", message, span, hint)

    def warning(self, code: str, message: str, span: Span | None, hint: str | None = None) -> None:
        self.diagnostics.append(Diagnostic("warning", code, message, span, hint))

    def extend(self, diags: Iterable[Diagnostic]) -> None:
        for d in diags:
            self.diagnostics.append(d)
            self.n_errors += d.severity == "error"

    @property
    def errors(self) -> list[Diagnostic]:
        return [d for d in self.diagnostics if d.severity == "error"]

    def raise_if_errors(self) -> None:
        if self.n_errors:
            raise WiredslError(self.diagnostics)


def in_order(diags: Iterable[Diagnostic]) -> list[Diagnostic]:
    """Diagnostics by file (in the order the files first appear: as given on the command line, a file before
    what it includes if it is reported first), then line and column; those without a place last. A stable
    sort: two at one place keep the order they were found in."""
    diags = list(diags)
    files: dict[str, int] = {}
    for d in diags:
        if d.span is not None:
            files.setdefault(d.span.file, len(files))
    return sorted(diags, key=lambda d: (files[d.span.file], d.span.line, d.span.col) if d.span is not None
                  else (len(files), 0, 0))


def bounded(text: str) -> str:
    """`text` with each run of over MAX_TOKEN non-blank characters, and then the whole if over MAX_TEXT, cut to
    its start and end around a '...' that says how much was left out (short text is returned as it is)."""
    if len(text) <= MAX_TOKEN:
        return text
    import re

    def cut(m: re.Match) -> str:
        t = m.group()
        return f"{t[:60]}...({len(t) - 80:,} more characters)...{t[-20:]}"

    text = re.sub(rf"[^\s'\"]{{{MAX_TOKEN + 1},}}", cut, text)  # the quotes around a token kept whole
    if len(text) > MAX_TEXT:
        text = f"{text[:MAX_TEXT - 200]}...({len(text) - MAX_TEXT + 100:,} more characters)...{text[-100:]}"
    return text


def source_lines(text: str) -> list[str]:
    """The lines of a source as the lexer counts them: split at \\n only (str.splitlines also splits at
    \\u2028, \\x0c, \\x85 and others, which would put carets and comments on the wrong line)."""
    lines = [line.removesuffix("\r") for line in text.split("\n")]
    if len(lines) > 1 and lines[-1] == "":
        lines.pop()
    return lines


MAX_QUOTED_BYTES = 16 * 1024 * 1024  # the caret lines quote a source from at most this prefix of it


def read_sources(diags: Iterable[Diagnostic]) -> dict[str, str]:
    """Source text of the files diagnostics point into, for the caret lines (unreadable ones left out).

    Only regular files, and at most their first MAX_QUOTED_BYTES: a diagnostic may point into /dev/zero or a
    FIFO (E010 refused it), which must neither be read whole nor block the report.
    """
    out: dict[str, str] = {}
    for d in diags:
        if d.span is not None and d.span.file not in out:
            text = _quotable(d.span.file)
            if text is not None:
                out[d.span.file] = text
    return out


def _quotable(path: str) -> str | None:
    """A regular file's text from its first MAX_QUOTED_BYTES (cut at its last whole line), else None."""
    import os
    import stat

    try:
        # O_NONBLOCK: opening a FIFO (even one swapped in after a stat) must not wait for a writer
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0))
    except (OSError, ValueError):  # ValueError: a NUL byte in the path
        return None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return None
        with os.fdopen(fd, "rb", closefd=False) as fh:
            data = fh.read(MAX_QUOTED_BYTES + 1)
    except OSError:
        return None
    finally:
        os.close(fd)
    if len(data) > MAX_QUOTED_BYTES:
        data = data[:data.rfind(b"\n", 0, MAX_QUOTED_BYTES) + 1]
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


# the hint for a stage or measure name that is no near-miss of a known one
NOT_INSTALLED = "maybe a plug-in that provides it is not installed ('wiredsl plugins' lists the installed ones)"


class UnknownName(KeyError):
    """A name a registry (effects, measures) does not know, from Python: a KeyError whose text says so, with the
    close matches or the plug-in hint (a bare KeyError('edge_los') said neither)."""

    def __init__(self, kind: str, name: str, known: Iterable[str]):
        known = list(known)
        hint = did_you_mean(name, known) or f"{NOT_INSTALLED}; {kind}s: {', '.join(known)}"
        super().__init__(f"unknown {kind} {name!r}: {hint}")
        self.name = name

    def __str__(self) -> str:  # KeyError's own shows the repr of its text
        return str(self.args[0])


def did_you_mean(word: str, candidates: Iterable[str]) -> str | None:
    """A 'did you mean' hint for a misspelt name, or None."""
    import difflib

    match = difflib.get_close_matches(word, list(candidates), n=1, cutoff=0.6)
    return f"did you mean '{match[0]}'?" if match else None


def render(diags: Sequence[Diagnostic], sources: dict[str, str], colour: bool = False) -> str:
    """Diagnostics in compiler form in source order, at most MAX_REPORTED of them (errors chosen first)."""
    ordered = sorted(diags, key=lambda d: d.severity != "error")
    shown = in_order(ordered[:MAX_REPORTED])
    parts = [_render_one(d, sources, colour) for d in shown]
    if len(ordered) > len(shown):
        parts.append(f"... and {len(ordered) - len(shown)} more")
    return "\n".join(parts) + "\n"


def render_json(diags: Sequence[Diagnostic]) -> str:
    """Diagnostics as a JSON document for editors and CI."""
    return json.dumps({"diagnostics": [d.to_json() for d in in_order(diags)]}, indent=2) + "\n"


def _paint(text: str, code: str, colour: bool) -> str:
    return f"\x1b[{code}m{text}\x1b[0m" if colour else text


def _render_one(d: Diagnostic, sources: dict[str, str], colour: bool) -> str:
    sev = _paint(f"{d.severity}[{d.code}]", "1;31" if d.severity == "error" else "1;33", colour)
    head = f"{d.span}: {sev}: {d.message}" if d.span else f"wiredsl: {sev}: {d.message}"
    lines = [head]
    text = sources.get(d.span.file) if d.span else None
    if text is not None:
        src_lines = source_lines(text)
        if 1 <= d.span.line <= len(src_lines):
            src = src_lines[d.span.line - 1].expandtabs(1)
            gutter = " " * len(str(d.span.line))
            end = d.span.end_col if d.span.end_line == d.span.line else len(src) + 1
            col = d.span.col
            if len(src) > MAX_LINE:  # a window of the line around the span's start, its cuts marked
                first = max(0, col - 1 - 40)
                last = min(len(src), first + MAX_LINE - 40)
                src = ("..." if first else "") + src[first:last] + ("..." if last < len(src) else "")
                shift = first - (3 if first else 0)
                col, end = col - shift, min(end - shift, len(src) + 1)
            width = max(1, end - col)
            caret = " " * (col - 1) + _paint("^" * width, "1;32", colour)
            if d.hint:
                caret += " " + d.hint
            lines += [f" {d.span.line} | {src}", f" {gutter} | {caret}"]
    elif d.hint:
        lines.append(f"  hint: {d.hint}")
    lines += [f"  note: {n}" for n in d.notes]
    return "\n".join(lines)

# Every code the compiler and the commands give, with its meaning: the diagnostics reference is generated from
# this table (docs/reference/diagnostics.md), and a test holds it to the codes the source gives.
CODES: dict[str, str] = {
    'E001': 'syntax error (unexpected token)',
    'E002': 'unexpected character',
    'E003': 'a bracket or block never closed (reported where it was opened), or an unexpected end of file',
    'E010': ('file cannot be read (missing, not UTF-8, a directory, FIFO or device, over 16 MiB, a NUL byte in its '
            'path), trajectory and times files included'),
    'E011': 'include cycle, or includes nested deeper than 64 files',
    'E012': 'missing or unsupported format version',
    'E100': 'unknown statement in this context',
    'E101': 'unknown word or extra argument in a statement (a block holds one statement a line)',
    'E102': 'missing clause, argument or block',
    'E103': 'clause given twice, or conflicting clauses',
    'E104': 'unknown name (with "did you mean")',
    'E105': 'duplicate name',
    'E106': 'wrong kind of value',
    'E107': 'unit of the wrong kind',
    'E108': 'unknown unit',
    'E109': 'number too large to represent (not finite, e.g. `1e999`)',
    'E110': 'value out of range (including lengths and image distances over 1e9, focal lengths over 1e9 px)',
    'W111': 'a bare number probably missing its unit (an angle below 1 degree, an implausible focal length)',
    'E120': 'degenerate geometry (zero length, collinear face, zero-area triangle)',
    'E121': 'zero normal or direction',
    'E122': 'axis not perpendicular to normal; vertical viewing direction',
    'E123': 'face not planar',
    'E124': 'zero radius',
    'E125': ('mesh file not usable: unknown format, not a mesh, empty, a vertex not finite, no triangle with an '
            'area (`mesh read`)'),
    'W125': 'mesh triangles of no area, dropped',
    'W126': 'mesh edges shared by more than two triangles (non-manifold), kept as lines',
    'W127': "a mesh's file origin lies far outside the part (place it by its centre or base: `origin centre|base`)",
    'W128': "the mesh reader (trimesh) warned about the file (a damaged or partly read mesh); its words are quoted",
    'W129': ('`--visibility auto` (the default of build, study, export, the API and the Gymnasium environment) '
             'keeps hidden lines of a scene with faces: exact visibility would cost more CPU than the default spends '
             '(its estimate is given); `--visibility exact` changes the answer'),
    'E130': 'silhouette not between two ellipses of its own model',
    'E140': 'matrix of the wrong shape, not symmetric, not positive semi-definite, or an entry over 1e100',
    'E141': ('calibration file malformed or not usable: a matrix file, or an OpenCV, ROS, Kalibr, ORB-SLAM, '
            'camodocal (VINS) or basalt file (a value of the wrong type, nesting over 64 deep, thin-prism or tilt '
            'terms, a camera model wiredsl does not implement (named, with those it does), skew, no extrinsics, '
            'a garbage results-cam.txt, PyYAML missing)'),
    'W143': ('a calibration file read with a doubt: a fisheye labelled plumb_bob, a `size` beside `read` that '
            "rescales the file's camera matrix or does not hold its centre, a rotation written with few digits"),
    'W144': ("a rig's extrinsics that are probably wrong: cameras over 5 m apart (a T in millimetres), the right "
            'camera to the left of the left one'),
    'E146': ("a stereo calibration file's cameras over 5 m apart, read without the unit of its T (OpenCV's is the "
             "board's, often millimetres): give `relative \"file\" units mm` (or cm, or m)"),
    'W147': ('a lens that does not image its own image: its distortion folds back inside the image, so the part '
            'beyond the fold is never reached (a fisheye bounded by its `fov` or imaging to 180 deg is not '
            "warned), or a radtan lens scales the image corner's radius by over 4x or under 1/4x (a `k1` of 1e6 "
            'from a file: the image spans a sliver of what the focal length gives)'),
    'W148': ("a trajectory's timestamp repeats the one before it: that line's pose is dropped, the first kept "
             '(one warning naming every such line; lines outside `from`/`to` are not judged)'),
    'E142': 'view-dependency file does not fit its schema (at build time)',
    'E145': ('trajectory file malformed or not usable (at its line: timestamps not increasing, a quaternion or '
            'matrix far from a rotation, non-finite values, wrong column count, missing columns; at the '
            'statement: no timestamps for `every`, an empty window, too many poses)'),
    'W145': "a trajectory's quaternion or rotation matrix off unit by more than printed digits explain: normalised",
    'W146': ("a path read from a trajectory file puts the robot's up axis more than 60 deg from the scene's up "
            '(median pose), or climbs more than it runs: `body` or `world` probably missing'),
    'E151': ('size over a limit (view-points, poses, matrix order, polyline vertices at a tolerance, brackets and '
            'blocks nested over 32 deep, a mesh over 2,000,000 triangles)'),
    'E160': 'a pipeline order that cannot be honoured',
    'W163': ("calibration_error's sigma far below 1 (under 0.1) on a rig with a declared calibration covariance: "
             'sigma scales its standard deviations, so the draws simulate that fraction of the calibration\'s '
             'uncertainty (sigma 1: as measured)'),
    'E170': 'a study design with no points (no values, no steps, no trials, no poses)',
    'E171': ("a factor or option that does not fit the study's design (a list in a space-filling design, a range "
            'without steps in a grid, base samples not a power of 2)'),
    'W161': 'pipeline stage out of the data-flow order of a real system',
    'E161': ('64 calibration draws in a row give a camera a pixel scale that is not positive or implausibly large '
            '(at build time)'),
    'E162': '`calibration_error` in a pipeline, or varied in a study, of a scene whose rig has no calibration',
    'E180': ('an installed plug-in of that name cannot be used: it fails to import, is not an `Effect` / '
            '`Measure`, lacks a parameter model, or two packages claim the name (the message names the package)'),
    'E181': ('a plug-in failed at run time: it raised, or returned a malformed ImageSet, another shape or a '
            'non-finite value (the message names the package)'),
    'E190': ('an image that cannot be used: unreadable, empty, not PNG/JPEG/BMP/PNM, a header without a size, over '
             '100,000,000 pixels by its header (refused before decoding), a truncated JPEG, data that does not '
             'decode, pixels neither 8- nor 16-bit'),
    'E191': "an image whose size differs from its camera's (checked on the header, before decoding)",
    'E192': ('an image without a pose: the pose file (at its last line) has fewer poses than frames, a timestamp '
             "outside the pose file's span, or (--poses path) the number in an image's name is not a pose index of "
             "the scene's path"),
    'E193': ("a glob that matches no file, an image whose camera cannot be told from its name, two images of one "
             "camera in a frame, a `--camera` that is not the rig's"),
    'W190': 'a 16-bit image scaled to 8 bits for the detectors',
    'W192': ('most of the model is unverified in some images (under half of its edge samples, or model corners '
             'without an edge detector): likely an image paired with the wrong pose; the warning names them'),
    'W196': 'a calibration board is not found in one image (that image has no pose from the board)',
    'E197': 'a calibration board is found in too few of the images to give their poses',
    'E198': "images are named for a camera the scene does not have, or a scene without a board or rig for them",
    'E199': 'an image cannot be used: unreadable, not 8-bit, or a size other than its camera\'s',
}
