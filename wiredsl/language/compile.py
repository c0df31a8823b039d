"""Stage 3: AST -> pydantic `Scene`, with every semantic check, units in SI.

Each check reports through a Collector with its own code, so one run lists all
the errors of a scene. Codes are documented in the README.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path as FsPath

import numpy as np
import pydantic

from wiredsl.diagnostics import Collector, Diagnostic, Span, WiredslError, did_you_mean
from wiredsl.effects import REGISTRY
from wiredsl.files import printable_path
from wiredsl.io import sources
from wiredsl.language import ast
from wiredsl.language.bind import Bound, bind
from wiredsl.language.compile_camera import CameraCompiler, _mat, _unit, rotation
from wiredsl.language.statements import ARUCO_MARKERS, CONTEXTS, MAX_MAGNITUDE
from wiredsl.language.units import DEFAULT_UNITS, UNITS
from wiredsl.plugins import params_dump, params_of
from wiredsl.scene import (
    PAPER,
    Board,
    Camera,
    Corner,
    Ellipse,
    Face,
    Line,
    Model,
    Path,
    Pipeline,
    Placement,
    Polyline,
    Rig,
    Scene,
    Silhouette,
    Stage,
    Viewpoints,
    paper_pipeline,
    trusted,
)

FORMAT_VERSION = 1
SIGMA_FAR_BELOW = 0.1  # W163: a calibration_error sigma below this scales a declared covariance far below 1
MAX_VIEWPOINTS = 100_000
MAX_POSES = 100_000
MAX_SPEED = 100.0  # m/s: faster than any ground robot (360 km/h); a larger speed is a unit written wrong
COUNTABLE = 1e15  # a count of grid points or poses below this is exact in a float, so it may be computed
GEOM_EPS = 1e-9  # metres: shorter is degenerate
PERP_TOL = 1e-6  # |cos| between an ellipse's axis and normal


def _speeds(path: Path) -> str:
    """What `check` says of a timed path: its duration and the robot's speeds (engine/motion.py's velocities)."""
    from wiredsl.engine import motion

    v, w = motion.velocities(path)
    speed, turn = np.linalg.norm(v, axis=1), np.abs(w).max(axis=1)
    fast = int(np.argmax(speed))
    return (f"path '{path.name}': {len(path.times)} poses over {path.times[-1] - path.times[0]:.4g} s; speed "
            f"{speed.min():.3g} to {speed.max():.3g} m/s (fastest at pose {fast}), turning at most "
            f"{math.degrees(turn.max()):.3g} deg/s")


def compile_file(path: str | os.PathLike) -> tuple[Scene, list[Diagnostic], ast.Program]:
    """Load, check and compile a scene file; raise WiredslError listing every error."""
    program = ast.load(path)
    scene, diags = compile_program(program)
    return scene, diags, program


def compile_program(program: ast.Program) -> tuple[Scene, list[Diagnostic]]:
    """Compile a loaded program; returns the scene and its warnings.

    What did not load (syntax errors, includes that cannot be read) is reported first, then the
    errors of everything that did, except references to unknown names: while part of the program is
    missing, such a name may well be declared there, so one note counts them instead.
    """
    out = Collector(hold_unknown=bool(program.errors))
    out.extend(program.errors)
    compiler = Compiler(program, out)
    scene = compiler.run()
    program.mesh_reports = compiler.mesh_reports
    program.motion_reports = compiler.motion_reports
    if out.unknown_held:  # noted at the first include that failed, else at the first syntax error
        i = next((i for i, d in enumerate(program.errors) if d.code in ("E010", "E011")), 0)
        n = out.unknown_held
        note = (f"{n} reference{'s' * (n != 1)} to unknown names not reported: they may be declared in what "
                f"did not load")
        out.diagnostics[i] = replace(out.diagnostics[i], notes=(*out.diagnostics[i].notes, note))
    out.diagnostics = [_noted(d, program) for d in out.diagnostics]
    out.raise_if_errors()
    return scene, out.diagnostics


def _noted(d: Diagnostic, program: ast.Program) -> Diagnostic:
    if d.span is None or d.notes:
        return d
    notes = program.include_notes(d.span.file)
    return Diagnostic(d.severity, d.code, d.message, d.span, d.hint, notes) if notes else d


@dataclass
class _Decl:
    """A named declaration and where it was written, for duplicate and reference checks."""

    value: object
    span: Span


class Compiler(CameraCompiler):
    def __init__(self, program: ast.Program, out: Collector):
        self.program = program
        self.out = out
        self.units: dict[str, dict[str, str]] = {}
        self.mesh_reports: list[tuple] = []  # (span, size and bounds) of each mesh read, for `check`
        self.motion_reports: list[tuple] = []  # (span, the path's times and speeds), for `check`
        self.models: dict[str, _Decl] = {}
        self.features: dict[str, dict[str, str]] = {}  # model -> feature -> kind
        self.placements: dict[str, _Decl] = {}
        self.camera_stmts: dict[str, Bound] = {}
        self.cameras: dict[str, Camera] = {}
        self.singles: dict[str, Bound] = {}  # rig, viewpoints, path
        self.pipelines: dict[str, _Decl] = {}
        self.study_stmts: list[Bound] = []
        self.calibration_stages: list[Span] = []  # where pipelines call calibration_error
        self.small_sigmas: list[tuple[float, Span]] = []  # calibration_error sigmas far below 1 (W163)
        self.paper_children: list[str] = []  # pipelines `like` the built-in paper
        self.scene_name: str | None = None
        self.rig_without_calibration = False
        self.motion_spans: list[tuple[str, Span]] = []  # (what, where) of readouts and syncs: they need times

    # ------------------------------------------------------------------ driver
    def run(self) -> Scene:
        self._header()
        handlers: dict[str, Callable[[Bound], None]] = {
            "model": self._model, "board": self._board, "place": self._place, "camera": self._camera_decl,
            "rig": self._single, "viewpoints": self._single, "path": self._single,
            "pipeline": self._pipeline, "scene": self._scene, "wiredsl": _ignore, "units": _ignore,
            "include": self._include, "study": self.study_stmts.append,
        }
        for stmt in self.program.statements:
            b = bind(stmt, "top", self._units(stmt), self.out)
            if b is not None and b.ok:
                handlers[stmt.keyword](b)
        self._resolve_cameras()
        rig = self._rig(self.singles["rig"]) if "rig" in self.singles else None
        viewpoints = self._viewpoints(self.singles["viewpoints"]) if "viewpoints" in self.singles else None
        path = self._path(self.singles["path"], rig) if "path" in self.singles else None
        self._check_defaults()
        if path is not None and path.times is not None and len(path.times) > 1:
            self.motion_reports.append((self.singles["path"].name_span, _speeds(path)))
        if path is not None and path.times is None:
            for what, span in self.motion_spans:
                self.out.error("E102", f"{what} needs the robot's motion, and path '{path.name}' has no times",
                               span, "give the path a 'speed' (e.g. speed 0.5m/s), or read a trajectory file with "
                                     "timestamps")
        studies = self._studies(path)
        if rig is not None and rig.calibration is not None and rig.calibration.kind == "covariance":
            for sigma, span in self.small_sigmas:
                self.out.warning("W163", f"calibration_error sigma {sigma:g} scales the calibration covariance of "
                                         f"rig '{rig.name}': the draws have {sigma:.2g} times its standard "
                                         "deviations", span,
                                 "sigma 1 simulates the calibration as measured (the paper's 0.01 scaled its own "
                                 "chi^2 matrix)")
        if self.rig_without_calibration or "rig" not in self.singles:  # as the built-in paper itself, for any rig
            for name in self.paper_children:
                d = self.pipelines[name]
                if isinstance(d.value, Pipeline):
                    d.value = d.value.model_copy(update={"stages": [st for st in d.value.stages
                                                                    if st.effect != "calibration_error"]})
        if self.rig_without_calibration:
            for span in self.calibration_stages:
                self.out.error("E162", f"calibration_error needs a calibration, and rig "
                                       f"'{self.singles['rig'].name}' has none", span,
                               "add 'calibration ...' to the rig, or remove the stage")
        root = self.program.root
        # a name from a file's name that is not UTF-8 shows its undecodable bytes as U+FFFD, as paths do
        name = self.scene_name or printable_path(FsPath(root.path).stem)
        if self.out.n_errors:
            # Sentinel; never returned to a user, compile_program raises first.
            return Scene.model_construct(name=name, source=root.path)
        return trusted(
            Scene,
            name=name,
            source=root.path.replace(os.sep, "/"),
            models=[d.value for d in self.models.values()],
            placements=[d.value for d in self.placements.values()],
            cameras=list(self.cameras.values()),
            rig=rig,
            viewpoints=viewpoints,
            path=path,
            pipelines=[d.value for d in self.pipelines.values()],
            studies=studies,
        )

    def _units(self, stmt: ast.Statement) -> dict[str, str]:
        return self.units.get(stmt.span.file, DEFAULT_UNITS)

    def _header(self) -> None:
        """Format versions and per-file units, read before anything else."""
        for path, file in self.program.files.items():
            units = dict(DEFAULT_UNITS)
            for stmt in file.statements:
                if stmt.keyword == "units":
                    b = bind(stmt, "top", units, Collector())  # errors reported in the main pass
                    if b is not None and b.ok:  # an unknown unit word is reported there, never used
                        units["length"] = b.get("length", units["length"])
                        units["angle"] = b.get("angle", units["angle"])
            self.units[path] = units
            versions = [s for s in file.statements if s.keyword == "wiredsl"]
            if not versions and file is self.program.root and path not in self.program.partial:
                first = file.statements[0].keyword_span if file.statements else Span(path, 1, 1, 1, 2)
                self.out.error("E012", "missing format version", first, "start the file with 'wiredsl 1'")
            for stmt in versions:
                arg = stmt.args[0] if len(stmt.args) == 1 else None
                if isinstance(arg, ast.Number) and arg.unit is None and arg.value != FORMAT_VERSION:
                    self.out.error("E012", f"unsupported format version {arg.text}", arg.span,
                                   f"this wiredsl reads version {FORMAT_VERSION}")

    def _include(self, b: Bound) -> None:
        pass  # followed by ast.load; a malformed include is reported by bind

    def _scene(self, b: Bound) -> None:
        if b.name_span.file != self.program.root.path:
            return  # an included file's name is its own builds' name: the scene is the including file's
        if self.scene_name is not None:
            self.out.error("E105", "the scene is named twice", b.name_span)
        self.scene_name = b.name

    def _declare(self, table: dict[str, _Decl], what: str, name: str, span: Span, value: object) -> bool:
        if name in table:
            self.out.error("E105", f"duplicate {what} '{name}'", span, f"first declared at {table[name].span}")
            return False
        table[name] = _Decl(value, span)
        return True

    def _ref(self, table, what: str, name: str, span: Span, context: str = "") -> bool:
        if name in table:
            return True
        self.out.unknown(f"unknown {what} '{name}'{context}", span, did_you_mean(name, table))
        return False

    # ------------------------------------------------------------------ models
    def _model(self, b: Bound) -> None:
        feats: dict[str, list] = {k: [] for k in ("lines", "polylines", "ellipses", "silhouettes", "corners", "faces",
                                                      "surfaces")}
        names: dict[str, _Decl] = {}
        silhouettes, corners = [], []  # checked once every feature name is known
        for stmt in b.stmt.block:
            fb = bind(stmt, "model", self._units(stmt), self.out)
            if fb is None or not fb.ok:
                continue
            if stmt.keyword == "mesh":
                self._mesh(fb, feats, names)
                continue
            if not self._declare(names, "feature", fb.name, fb.name_span, stmt.keyword):
                continue
            build = getattr(self, f"_feature_{stmt.keyword}")
            built = build(fb)
            if built is None:
                continue
            feats[stmt.keyword + "s"].append(built)
            if stmt.keyword == "silhouette":
                silhouettes.append((fb, built))
            elif stmt.keyword == "corner":
                corners.append(fb)
        kinds = {n: d.value for n, d in names.items()}
        in_model = f" in model '{b.name}'"
        for fb, sil in silhouettes:
            for ref, value in zip(fb.clauses["between"][0], sil.ellipses, strict=True):
                if "." in value:
                    self.out.error("E130", f"a silhouette joins two ellipses of its own model, not '{value}'",
                                   ref.span, "name an ellipse of this model")
                elif self._ref(kinds, "ellipse", value, ref.span, in_model) and kinds[value] != "ellipse":
                    self.out.error("E130", f"'{value}' is a {kinds[value]}, not an ellipse", ref.span)
            if sil.ellipses[0] == sil.ellipses[1]:
                self.out.error("E130", "a silhouette needs two different ellipses", fb.span("between"))
        for fb in corners:
            for ref in fb.get("joins", []):
                if self._ref(kinds, "line", ref.value, ref.span, in_model) and kinds[ref.value] not in (
                        "line", "polyline"):
                    self.out.error("E104", f"'{ref.value}' is a {kinds[ref.value]}, not a line", ref.span)
        model = trusted(Model, name=b.name, **feats)
        if self._declare(self.models, "model", b.name, b.name_span, model):
            self.features[b.name] = kinds

    def _mesh(self, fb: Bound, feats: dict[str, list], names: dict[str, _Decl]) -> None:
        """`mesh read`: the mesh's features added to the model's (engine/mesh.py says what becomes what), from
        the features' cache when this file was read with these options before (io/mesh.py)."""
        from wiredsl.engine import mesh as mesh_features

        path = fb.get("read")
        if any(d.value == "mesh" for d in names.values()):
            self.out.error("E103", "a model reads one mesh", fb.stmt.keyword_span, "put each mesh in its own model")
            return
        names[f"mesh {path}"] = _Decl("mesh", fb.stmt.span)  # a key no feature name can be
        found = read_mesh_features(fb, self._units(fb.stmt), self.out)
        if found is None:
            return
        self.mesh_reports.append((fb.stmt.span, f"mesh {path}: {mesh_size(found)}"))
        built = mesh_features.as_nodes(found, path)
        for kind, items in built.items():
            for item in items:
                what = "contour" if kind == "surfaces" and item.contour else kind[:-1]  # its outline is emitted
                if self._declare(names, "feature", item.name, fb.stmt.span, what):
                    feats[kind].append(item)

    def _point(self, fb: Bound, key: str) -> np.ndarray:
        return np.array(fb.get(key), dtype=float)

    def _feature_line(self, fb: Bound) -> Line | None:
        p0, p1 = self._point(fb, "from"), self._point(fb, "to")
        if np.linalg.norm(p1 - p0) <= GEOM_EPS:
            self.out.error("E120", f"line '{fb.name}' has zero length", fb.stmt.span, "its two ends are the same point")
            return None
        return trusted(Line, name=fb.name, start=fb.get("from"), end=fb.get("to"))

    def _points(self, fb: Bound, key: str, least: int, what: str) -> list | None:
        pts = fb.get(key)
        if len(pts) < least:
            self.out.error("E120", f"{fb.stmt.keyword} '{fb.name}' needs at least {least} {what}, got {len(pts)}",
                           fb.span(key))
            return None
        return [p.value for p in pts]

    def _feature_polyline(self, fb: Bound) -> Polyline | None:
        pts = self._points(fb, "through", 2, "points")
        if pts is None:
            return None
        arr = np.array(pts)
        closed = fb.has("closed")
        steps = np.diff(np.vstack([arr, arr[:1]]) if closed else arr, axis=0)
        bad = np.flatnonzero(np.linalg.norm(steps, axis=1) <= GEOM_EPS)
        if bad.size:
            i = int(bad[0])
            self.out.error("E120", f"polyline '{fb.name}' has a zero-length segment (points {i + 1} and "
                                   f"{(i + 1) % len(pts) + 1} coincide)", fb.get("through")[i].span)
            return None
        return trusted(Polyline, name=fb.name, points=pts, closed=closed)

    def _feature_ellipse(self, fb: Bound) -> Ellipse | None:
        n, u = _unit(self._point(fb, "normal")), _unit(self._point(fb, "axis"))
        a, b = fb.get("radii")
        ok = True
        for key, vec in (("normal", n), ("axis", u)):
            if np.linalg.norm(vec) == 0:
                self.out.error("E121", f"ellipse '{fb.name}' has a zero {key}", fb.span(key))
                ok = False
        if min(a, b) <= GEOM_EPS:
            self.out.error("E124", f"ellipse '{fb.name}' has a zero radius", fb.span("radii"), "radii must be > 0")
            ok = False
        if not ok:
            return None
        n = n / np.linalg.norm(n)
        u = u / np.linalg.norm(u)
        cos = abs(float(n @ u))
        if cos > PERP_TOL:
            self.out.error("E122", f"ellipse '{fb.name}': axis is not perpendicular to the normal "
                                   f"({math.degrees(math.acos(min(cos, 1.0))):.3g} deg apart)", fb.span("axis"),
                           "the major axis must lie in the ellipse's plane")
            return None
        t0, t1 = fb.get("range", (0.0, 2 * math.pi))
        if not (t1 > t0 and t1 - t0 <= 2 * math.pi + 1e-12):
            self.out.error("E110", f"ellipse '{fb.name}': range must satisfy t1 > t0 and t1 - t0 <= 360deg",
                           fb.span("range"))
            return None
        u = u - (u @ n) * n  # remove the tolerated rounding so the frame is exactly orthonormal
        u /= np.linalg.norm(u)
        return trusted(Ellipse, name=fb.name, centre=fb.get("centre"), normal=tuple(float(v) for v in n),
                       axis=tuple(float(v) for v in u), a=a, b=b, t0=t0, t1=t1)

    def _feature_silhouette(self, fb: Bound) -> Silhouette:
        refs = fb.clauses["between"][0]
        return trusted(Silhouette, name=fb.name, ellipses=(refs[0].value, refs[1].value))

    def _feature_corner(self, fb: Bound) -> Corner:
        joins = [r.value for r in fb.get("joins", [])]
        return trusted(Corner, name=fb.name, at=fb.get("at"), joins=joins)

    def _feature_face(self, fb: Bound) -> Face | None:
        pts = self._points(fb, "through", 3, "vertices")
        if pts is None:
            return None
        arr = np.array(pts)
        centred = arr - arr.mean(axis=0)
        s = np.linalg.svd(centred, compute_uv=False)
        size = float(np.ptp(arr, axis=0).max())
        if s[1] <= GEOM_EPS:
            self.out.error("E120", f"face '{fb.name}' has no area (its vertices are collinear)", fb.span("through"))
            return None
        normal = np.linalg.svd(centred)[2][2]
        off = float(np.abs(centred @ normal).max())
        if off > 1e-6 * max(size, 1.0):
            self.out.error("E123", f"face '{fb.name}' is not planar (a vertex is {off:.3g} m off its plane)",
                           fb.span("through"))
            return None
        return trusted(Face, name=fb.name, vertices=pts)

    def _board(self, b: Bound) -> None:
        """`board`: a model whose corners, lines (or ellipses) and face are a calibration board's (scene.Board's
        frame)."""
        kind = b.pos(1)
        label = {"chessboard": "chessboard", "charuco": "charuco board", "circles": "circle grid",
                 "acircles": "asymmetric circle grid"}[kind]
        own = {"chessboard": "inner", "charuco": "squares"}.get(kind, "dots")
        side_key = "spacing" if own == "dots" else "square"
        for other in ("inner", "squares", "dots"):
            if other != own and b.has(other):
                self.out.error("E103", f"a {label} takes '{own}', not '{other}'", b.clause_spans[other][0],
                               f"write {own} (columns, rows)")
                return
        for need in (own, side_key, *(("diameter",) if own == "dots" else ())):
            if not b.has(need):
                what = f"{need} (columns, rows)" if need == own else need
                self.out.error("E102", f"a {label} needs '{what}'", b.stmt.keyword_span)
                return
        theirs = {"marker": ("charuco",), "dictionary": ("charuco",), "square": ("chessboard", "charuco"),
                  "spacing": ("circles", "acircles"), "diameter": ("circles", "acircles")}
        for key, kinds in theirs.items():
            if kind not in kinds and b.has(key):
                self.out.error("E103", f"'{key}' is a {' or '.join(kinds)} board's, not a {label}'s", b.span(key))
                return
        across, down = (int(v) for v in b.get(own))
        if not (3 <= across <= MAX_BOARD and 3 <= down <= MAX_BOARD):  # OpenCV's detectors need 3 at least
            what = {"inner": "inner corners", "squares": "squares", "dots": "dots"}[own]
            self.out.error("E110", f"a board's {what} must be 3..{MAX_BOARD} each way, got ({across}, {down})",
                           b.span(own))
            return
        columns, rows = (across + 1, down + 1) if own == "inner" else (across, down)
        side = b.get(side_key)
        margin = b.get("margin", side)
        if not MIN_SQUARE <= side:  # (a marker of 1e-300 m is 0 to OpenCV's 32-bit floats)
            what = "a square's side" if side_key == "square" else "the spacing"
            self.out.error("E110", f"{what} must be at least {MIN_SQUARE:g} m, got {side:g} m", b.span(side_key))
            return
        if not 0 <= margin:
            self.out.error("E110", f"the margin must not be negative, got {margin:g} m", b.span("margin"))
            return
        marker = dictionary = diameter = None
        if kind == "charuco":
            marker = b.get("marker", 0.75 * side)
            if not MARKER_SHARE * side <= marker < side:  # a smaller one OpenCV neither draws nor finds
                self.out.error("E110", f"a marker must be at least {MARKER_SHARE:g} of a square and smaller than it "
                                       f"({MARKER_SHARE * side:g} to {side:g} m), got {marker:g} m", b.span("marker"))
                return
            dictionary = b.get("dictionary", "DICT_4X4_50")
            size = ARUCO_MARKERS[dictionary]
            wanted = (columns * rows) // 2
            if wanted > size:
                self.out.error("E110", f"a {columns} x {rows} charuco board needs {wanted} markers; dictionary "
                                       f"{dictionary} has {size}", b.span("dictionary"))
                return
        if own == "dots":
            diameter = b.get("diameter")
            gap = side * (math.sqrt(2) if kind == "acircles" else 1.0)  # nearest centres: diagonal on acircles
            if not DOT_SHARE * gap <= diameter < gap:  # touching dots are one blob to a detector
                self.out.error("E110", f"a dot's diameter must be at least {DOT_SHARE:g} of the nearest centres' "
                                       f"distance ({gap:g} m) and smaller than it, got {diameter:g} m",
                               b.span("diameter"))
                return
        board = trusted(Board, kind=kind, columns=columns, rows=rows, square=side, margin=margin, marker=marker,
                        dictionary=dictionary, diameter=diameter)
        model = board_model(b.name, board)
        if self._declare(self.models, "model", b.name, b.name_span, model):
            kinds = ({f.name: "line" for f in model.lines} | {c.name: "corner" for c in model.corners}
                     | {e.name: "ellipse" for e in model.ellipses})
            self.features[b.name] = kinds | {board.face: "face"}

    # ------------------------------------------------------------------ placements
    def _place(self, b: Bound) -> None:
        model = b.pos(0)
        name = b.get("as")
        if not self._ref(self.models, "model", model, b.positional[0].span):
            return
        R = self._rotation(b)
        if R is None:
            return
        placement = trusted(Placement, name=name, model=model, position=b.get("at", (0.0, 0.0, 0.0)), rotation=_mat(R))
        self._declare(self.placements, "placement", name, b.span("as"), placement)

    def _rotation(self, b: Bound) -> np.ndarray | None:
        """The rotation of a statement's `rotate` clauses (in order) or `ypr`, identity without them; None when
        both are given (reported)."""
        if b.has("rotate") and b.has("ypr"):
            self.out.error("E103", "give either 'rotate' or 'ypr', not both", b.span("ypr"))
            return None
        R = np.eye(3)
        for axis, angle in b.clauses.get("rotate", []):
            R = rotation(axis.value, angle.value) @ R
        if b.has("ypr"):
            yaw, pitch, roll = b.get("ypr")
            R = rotation("z", yaw) @ rotation("y", pitch) @ rotation("x", roll)
        return R

    # ------------------------------------------------------------------ rig, viewpoints, path
    def _single(self, b: Bound) -> None:
        kind = b.stmt.keyword
        if kind in self.singles:
            self.out.error("E105", f"a scene has one {kind}; '{b.name}' is a second",
                           b.name_span, f"the first is at {self.singles[kind].name_span}")
            return
        self.singles[kind] = b

    def _viewpoints(self, b: Bound) -> Viewpoints | None:
        names: list[str] = []
        points: list[tuple[float, float]] = []
        index: dict[str, int] = {}
        triangles: list[tuple[int, int, int]] = []
        visible: dict[str, list[str]] = {}
        mode, file = None, None
        grid = vertex = None
        stmts = []
        n0 = self.out.n_errors
        for stmt in b.stmt.block:
            sb = bind(stmt, "viewpoints", self._units(stmt), self.out)
            if sb is not None and sb.ok:
                stmts.append(sb)
        for sb in stmts:
            kw = sb.stmt.keyword
            if kw == "grid":
                if grid is not None:
                    self.out.error("E105", "a mesh has one grid", sb.stmt.keyword_span)
                    continue
                grid = sb
                made = self._grid(sb)
                if made:
                    n, p, t = made
                    names += n
                    points += p
                    triangles += t
            elif kw == "vertex":
                vertex = sb
                if self._declare_index(index, names, sb):
                    points.append(sb.get("at"))
        if grid is not None and vertex is not None:
            self.out.error("E103", "a mesh is either a generated grid or explicit vertices, not both",
                           vertex.stmt.keyword_span)
        index = {n: i for i, n in enumerate(names)}
        if len(names) > MAX_VIEWPOINTS:
            self.out.error("E151", f"{len(names):,} view-points exceed the limit of {MAX_VIEWPOINTS:,}", b.name_span)
            return None
        for sb in stmts:
            kw = sb.stmt.keyword
            if kw == "triangle":
                idx = []
                for v in sb.positional:
                    if self._ref(index, "view-point", v.value, v.span, f" in mesh '{b.name}'"):
                        idx.append(index[v.value])
                if len(idx) == 3:
                    p = np.array([points[i] for i in idx])
                    (ux, uy), (vx, vy) = p[1] - p[0], p[2] - p[0]
                    area = 0.5 * abs(ux * vy - uy * vx)
                    if area <= GEOM_EPS**2:
                        self.out.error("E120", "triangle has no area", sb.stmt.span)
                    else:
                        triangles.append(tuple(idx))
            elif kw == "visibility":
                given = [k for k in ("auto", "authored", "file") if sb.has(k)]
                if len(given) != 1:
                    self.out.error("E102", "visibility is one of: auto, authored, file \"path\"", sb.stmt.span)
                elif mode is not None:
                    self.out.error("E105", "visibility given twice", sb.stmt.keyword_span)
                else:
                    mode = given[0]
                    file = sb.get("file")
            elif kw == "visible":
                vname = sb.pos(0)
                if self._ref(index, "view-point", vname, sb.positional[0].span, f" in mesh '{b.name}'"):
                    ids = visible.setdefault(vname, [])
                    for ref in sb.pos(1):
                        ids += self._expand(ref.value, ref.span)
        if not names:
            if self.out.n_errors == n0:  # else the grid or vertices that failed are the reason, reported already
                self.out.error("E102", f"mesh '{b.name}' has no view-points", b.name_span, "add a grid or vertices")
            return None
        mode = mode or ("authored" if visible else "all")
        if visible and mode != "authored":
            self.out.error("E103", f"'visible' lists need 'visibility authored', not {mode}", b.name_span)
        return trusted(Viewpoints, name=b.name, names=names, points=points, triangles=triangles, visibility=mode,
                       file=file, visible={k: sorted(set(v)) for k, v in visible.items()})

    def _declare_index(self, index: dict, names: list, sb: Bound) -> bool:
        if sb.name in index:
            self.out.error("E105", f"duplicate view-point '{sb.name}'", sb.name_span)
            return False
        index[sb.name] = len(names)
        names.append(sb.name)
        return True

    def _grid(self, sb: Bound):
        (x0, y0), (x1, y1), step = sb.get("from"), sb.get("to"), sb.get("spacing")
        if not step > 0:
            self.out.error("E110", f"spacing must be > 0, got {step:g}", sb.span("spacing"))
            return None
        fx, fy = abs(x1 - x0) / step, abs(y1 - y0) / step  # floats first: a tiny spacing may give inf
        if not fx * fy <= COUNTABLE:  # (also inf) too many to count exactly
            self.out.error("E151", f"spacing {step:.3g} m over a {abs(x1 - x0):.3g} x {abs(y1 - y0):.3g} m "
                                   f"rectangle gives more view-points than the limit of {MAX_VIEWPOINTS:,}",
                           sb.span("spacing"), "use a larger spacing")
            return None
        nx = math.floor(fx + 1e-9) + 1
        ny = math.floor(fy + 1e-9) + 1
        if nx * ny > MAX_VIEWPOINTS:
            self.out.error("E151", f"grid of {nx:,} x {ny:,} = {nx * ny:,} view-points exceeds the limit of "
                                   f"{MAX_VIEWPOINTS:,}", sb.span("spacing"), "use a larger spacing")
            return None
        if nx < 2 or ny < 2:
            self.out.error("E120", "grid needs at least two view-points along x and along y", sb.stmt.span)
            return None
        sx = math.copysign(step, x1 - x0)
        sy = math.copysign(step, y1 - y0)
        names = [f"g{i}_{j}" for j in range(ny) for i in range(nx)]
        points = [(x0 + i * sx, y0 + j * sy) for j in range(ny) for i in range(nx)]
        tris = []
        for j in range(ny - 1):
            for i in range(nx - 1):
                a, b_, c, d = j * nx + i, j * nx + i + 1, (j + 1) * nx + i, (j + 1) * nx + i + 1
                tris += [(a, b_, d), (a, d, c)]
        return names, points, tris

    def _expand(self, ref: str, span: Span) -> list[str]:
        """Feature ids named by a reference: `*`, `p.*` or `p.feature`."""
        if ref == "*":
            return [f"{p}.{f}" for p, d in self.placements.items() for f in self._emitted(d.value.model)]
        head, _, rest = ref.partition(".")
        if not self._ref(self.placements, "placement", head, span):
            return []
        model = self.placements[head].value.model
        feats = self._emitted(model)
        if rest == "*":
            return [f"{head}.{f}" for f in feats]
        if not rest or "." in rest:
            self.out.error("E104", f"'{ref}' is not a feature reference", span,
                           "write placement.feature or placement.*")
            return []
        if self._ref(feats, "feature", rest, span, f" in model '{model}' (placement '{head}')"):
            return [ref]
        return []

    def _emitted(self, model: str) -> dict[str, str]:
        return {n: k for n, k in self.features.get(model, {}).items() if k not in ("face", "surface", "mesh")}

    def _path(self, b: Bound, rig: Rig | None) -> Path | None:
        poses: list[tuple[float, float, float]] = []
        n0 = self.out.n_errors
        reads: dict[str, Bound] = {}  # read, body, world
        speed: Bound | None = None
        for stmt in b.stmt.block:
            sb = bind(stmt, "path", self._units(stmt), self.out)
            if sb is None or not sb.ok:
                continue
            if stmt.keyword == "speed":
                if speed is not None:
                    self.out.error("E103", "a path takes one 'speed'", stmt.keyword_span)
                elif not 0 < sb.pos(0) <= MAX_SPEED:  # also NaN
                    self.out.error("E110", f"a speed must be in (0, {MAX_SPEED:g}] m/s, got {sb.pos(0):g} m/s",
                                   sb.positional[0].span)
                speed = sb
                continue
            if stmt.keyword in ("read", "body", "world"):
                if stmt.keyword in reads:
                    self.out.error("E103", f"a path takes one '{stmt.keyword}'", stmt.keyword_span)
                reads.setdefault(stmt.keyword, sb)
                continue
            if stmt.keyword == "pose":
                if len(poses) == MAX_POSES:
                    self.out.error("E151", f"more than {MAX_POSES:,} poses", stmt.keyword_span)
                    break
                x, y = sb.pos(0)
                poses.append((x, y, sb.get("heading", 0.0)))
                continue
            (x0, y0), (x1, y1), step = sb.get("from"), sb.get("to"), sb.get("step")
            length = math.hypot(x1 - x0, y1 - y0)
            if not step > 0:
                self.out.error("E110", f"step must be > 0, got {step:g}", sb.span("step"))
                continue
            if length <= GEOM_EPS:
                self.out.error("E120", "a straight run needs two different end points", sb.stmt.span)
                continue
            count = length / step  # a float first: a tiny step may give inf
            if not count <= COUNTABLE:
                self.out.error("E151", f"about {count:.3g} poses exceed the limit of {MAX_POSES:,}", sb.span("step"),
                               "use a larger step")
                continue
            n = math.floor(count + 1e-9) + 1
            if n + len(poses) > MAX_POSES:
                self.out.error("E151", f"{n:,} poses exceed the limit of {MAX_POSES:,}", sb.span("step"),
                               "use a larger step")
                continue
            heading = math.atan2(y1 - y0, x1 - x0)
            for i in range(n):
                t = i * step / length
                poses.append((x0 + t * (x1 - x0), y0 + t * (y1 - y0), heading))
        if reads:
            if "read" not in reads:
                sb = reads.get("body") or reads["world"]
                self.out.error("E102", f"'{sb.stmt.keyword}' places the poses of a trajectory file: the path has "
                                       "no 'read'", sb.stmt.keyword_span, f"e.g. {CONTEXTS['path']['read'].example}")
                return None
            if poses or speed is not None:
                self.out.error("E103", "a path read from a trajectory file takes no 'pose', 'straight' or 'speed' "
                                       "(its times are the file's)", reads["read"].stmt.keyword_span)
                return None
            return self._trajectory(b, reads, rig) if self.out.n_errors == n0 else None
        if not poses:
            if self.out.n_errors == n0:  # else the statements that failed are the reason, reported already
                self.out.error("E102", f"path '{b.name}' has no poses", b.name_span)
            return None
        if speed is not None:
            if self.out.n_errors != n0:
                return None
            return self._timed(b, poses, speed)
        return trusted(Path, name=b.name, poses=poses)

    def _timed(self, b: Bound, poses: list, speed: Bound) -> Path | None:
        """Written poses timed by a speed: each pose's time is its distance along the path over the speed."""
        v = float(speed.pos(0))
        xy = np.array([p[:2] for p in poses], dtype=float)
        steps = np.hypot(*np.diff(xy, axis=0).T) if len(xy) > 1 else np.zeros(0)
        still = np.flatnonzero(steps <= GEOM_EPS)
        if len(still):
            self.out.error("E120", f"path '{b.name}': poses {still[0]} and {still[0] + 1} are at one place, so a "
                                   "speed cannot time them", speed.stmt.keyword_span,
                           "a robot that turns on the spot needs times per pose")
            return None
        return trusted(Path, name=b.name, poses=poses).timed(v)

    def _trajectory(self, b: Bound, reads: dict[str, Bound], rig: Rig | None) -> Path | None:
        """A 6-DoF path from a trajectory file: world_from_robot = world_from_file . file_from_body .
        body_from_robot, each pose."""
        from wiredsl.io import trajectory

        sb = reads["read"]
        body = self._body(reads.get("body"), rig)
        world = reads.get("world")
        R_sf = self._rotation(world) if world is not None else np.eye(3)
        if body is None or R_sf is None:
            return None
        t_sf = np.array(world.get("at", (0.0, 0.0, 0.0)) if world is not None else (0.0, 0.0, 0.0))
        file_arg = sb.positional[0]
        target = FsPath(sb.stmt.span.file).parent / sb.pos(0)
        where = f"read by path '{b.name}' at {sb.stmt.span}"
        try:
            text = sources.decode(sources.read_bytes(target, "trajectory file", file_arg.span), target,
                                  "trajectory file", file_arg.span)
            times = None
            if sb.has("times"):
                t_target = FsPath(sb.stmt.span.file).parent / sb.get("times")
                t_text = sources.decode(sources.read_bytes(t_target, "times file", sb.span("times")), t_target,
                                        "times file", sb.span("times"))
                try:
                    times = trajectory.read_times(t_text)
                except trajectory.TrajectoryError as exc:
                    return self._trajectory_error(exc, t_target, t_text, where, sb.span("times"))
        except WiredslError as err:
            self.out.extend(err.diagnostics)
            return None
        for key in ("every", "limit", "rate"):
            if sb.has(key) and not sb.get(key) > 0:
                self.out.error("E110", f"{key} must be > 0, got {sb.get(key):g}", sb.span(key))
                return None
        try:
            traj = trajectory.read(text, sb.get("format"), times, sb.get("rate"), (sb.get("from"), sb.get("to")))
        except trajectory.TrajectoryError as exc:
            return self._trajectory_error(exc, target, text, where, file_arg.span)
        if traj.repeated:  # one warning, at the first, naming every dropped line
            (line, earlier), rest = traj.repeated[0], traj.repeated[1:]
            more = f"; also lines {', '.join(str(r[0]) for r in rest[:10])}" + (" ..." if len(rest) > 10 else "") \
                if rest else ""
            self.out.extend([Diagnostic(
                "warning", "W148", f"line {line} repeats the timestamp of line {earlier}: its pose is dropped, the "
                f"first kept{more}", _line_span(target, text, line),
                notes=(where, "a trajectory's timestamps should increase; evo reads both rows and reports them in "
                       "its --check"))])
        if traj.normalised:
            line, message = traj.normalised[0]
            more = f" (and {len(traj.normalised) - 1} more)" if len(traj.normalised) > 1 else ""
            self.out.extend([Diagnostic("warning", "W145", message + more, _line_span(target, text, line),
                                        notes=(where,))])
        try:
            P, R, times = trajectory.resample(traj, sb.get("every"), sb.get("from"), sb.get("to"),
                                              int(sb.get("limit")) if sb.has("limit") else None, MAX_POSES,
                                              with_times=True)
        except trajectory.TrajectoryError as exc:
            return self._trajectory_error(exc, target, text, where, sb.span("every") if sb.has("every")
                                          else file_arg.span)
        if len(P) == 0:
            self.out.error("E145", f"trajectory file {sources.display_path(target)}: no pose in the window",
                           sb.span("from") if sb.has("from") else file_arg.span)
            return None
        if len(P) > MAX_POSES:
            self.out.error("E151", f"{len(P):,} poses exceed the limit of {MAX_POSES:,}", file_arg.span,
                           "resample with 'every', or give a 'limit'")
            return None
        R_wr, t_wr = trajectory.world_from_robot(P, R, body, (R_sf, t_sf))
        if not np.all(np.abs(t_wr) <= MAX_MAGNITUDE):
            self.out.error("E110", f"trajectory file {sources.display_path(target)} places the robot beyond "
                                   f"{MAX_MAGNITUDE:g} m", file_arg.span)
            return None
        for message, hint in trajectory.implausible(R_wr, t_wr):
            self.out.warning("W146", message, sb.stmt.keyword_span, hint)
        floor = [(float(t[0]), float(t[1]), math.atan2(r[1, 0], r[0, 0])) for r, t in zip(R_wr, t_wr, strict=True)]
        transforms = [tuple(tuple(float(v) for v in row) for row in np.column_stack([r, t])) for r, t
                      in zip(R_wr, t_wr, strict=True)]
        stamps = [float(x) for x in times] if times is not None else None
        return trusted(Path, name=b.name, poses=floor, transforms=transforms, times=stamps,
                       start_ns=traj.start_ns if stamps is not None else None)

    def _trajectory_error(self, exc, target: FsPath, text: str, where: str, span: Span) -> None:
        """Report a TrajectoryError at its line of the file, else at `span` of the statement."""
        if exc.line is None:
            self.out.error("E145", f"trajectory file {sources.display_path(target)}: {exc}", span)
        else:
            self.out.extend([Diagnostic("error", "E145", str(exc), _line_span(target, text, exc.line),
                                        notes=(where,))])

    def _body(self, sb: Bound | None, rig: Rig | None) -> tuple[np.ndarray, np.ndarray] | None:
        """robot_from_body (R, p) of a path's `body` statement (identity without one); None when reported."""
        if sb is None:
            return np.eye(3), np.zeros(3)
        given = [k for k in ("at", "rotate", "ypr", "camera", "kalibr") if sb.has(k)]
        if sum(k in given for k in ("camera", "kalibr")) + any(k in given for k in ("at", "rotate", "ypr")) > 1:
            self.out.error("E103", f"'{given[-1]}' and '{given[0]}' both place the body: keep one", sb.span(given[-1]))
            return None
        if "camera" not in given and "kalibr" not in given:
            R = self._rotation(sb)
            return None if R is None else (R, np.array(sb.get("at", (0.0, 0.0, 0.0)), dtype=float))
        if rig is None:
            if "rig" not in self.singles:  # else the rig's own errors, reported already, are the reason
                self.out.error("E102", f"'{given[0]}' places the body by the rig's cameras: the scene has no rig",
                               sb.span(given[0]))
            return None
        mount = rig.left if sb.get("camera", "left") == "left" else rig.right
        R_m, p_m = np.array(mount.rotation), np.array(mount.position)
        if "camera" in given:
            return R_m, p_m
        T = self._kalibr_imu(sb)
        return None if T is None else (R_m @ T[:3, :3], R_m @ T[:3, 3] + p_m)

    def _kalibr_imu(self, sb: Bound) -> np.ndarray | None:
        """cam0's T_cam_imu (4, 4) of a Kalibr camchain, its rotation made exact; None when reported."""
        from wiredsl.io.calibration import CalibrationFileError, _yaml

        span = sb.span("kalibr")
        target = FsPath(sb.stmt.span.file).parent / sb.get("kalibr")
        try:
            doc = _yaml(sources.decode(sources.read_bytes(target, "Kalibr camchain", span), target, "Kalibr camchain",
                                       span))
        except WiredslError as err:
            self.out.extend(err.diagnostics)
            return None
        except CalibrationFileError as exc:
            self.out.error("E141", f"Kalibr camchain {sb.get('kalibr')}: {exc}", span)
            return None
        cam0 = doc.get("cam0") if isinstance(doc, dict) else None
        T = cam0.get("T_cam_imu") if isinstance(cam0, dict) else None
        try:
            T = np.array(T, dtype=float)
        except (TypeError, ValueError):
            T = np.zeros(0)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            self.out.error("E141", f"Kalibr camchain {sb.get('kalibr')}: cam0 has no 4 x 4 T_cam_imu of finite "
                                   "numbers (a camchain-imucam.yaml has one)", span)
            return None
        R = T[:3, :3]
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or np.linalg.det(R) <= 0:
            self.out.error("E141", f"Kalibr camchain {sb.get('kalibr')}: cam0's T_cam_imu has no rotation in its "
                                   "upper-left 3 x 3", span)
            return None
        U, _, Vt = np.linalg.svd(R)
        T[:3, :3] = U @ Vt
        return T

    # ------------------------------------------------------------------ pipelines
    def _pipeline(self, b: Bound) -> None:
        stages = []
        given: dict[str, dict] = {}  # the parameters each stage of the block gives, for `like`
        seen: dict[str, Span] = {}
        last: tuple[int, str] | None = None
        base = self._base_pipeline(b)
        if base is False:
            return
        inherited = {st.effect: st.params for st in base.stages} if base is not None else {}
        for stmt in b.stmt.block or ():
            sb = bind(stmt, "pipeline", self._units(stmt), self.out)
            if sb is None or not sb.ok:
                continue
            name = stmt.keyword
            effect = REGISTRY[name]
            if name in seen:
                self.out.error("E103", f"stage '{name}' appears twice in pipeline '{b.name}'", stmt.keyword_span,
                               f"first at {seen[name]}")
                continue
            seen[name] = stmt.keyword_span
            if name == "calibration_error":
                self.calibration_stages.append(stmt.keyword_span)
            rank = effect.flow_rank()
            if name == "calibration_error" and stages and base is None:
                self.out.error("E160", "calibration_error must be the first stage: it acts on the cameras, "
                                       "before anything is projected", stmt.keyword_span,
                               "move it to the top of the pipeline")
            elif last is not None and rank < last[0] and base is None:
                self.out.warning("W161", f"'{name}' ({effect.acts_on}) after '{last[1]}' "
                                         f"({REGISTRY[last[1]].acts_on}) departs from the data flow of a real "
                                         "system", stmt.keyword_span,
                                 "real order: cameras, edges, fitting, corner detection, corner matching, stereo")
            last = (rank, name) if last is None or rank >= last[0] else last
            params = {k: sb.get(k) for k in sb.clauses}
            try:
                checked = params_dump(params_of("effect", effect, REGISTRY, {**inherited.get(name, {}), **params}))
                stages.append(trusted(Stage, effect=name, params=checked))
                given[name] = params
                if name == "calibration_error":
                    self._check_sigma(checked, stmt, sb)
            except pydantic.ValidationError as exc:
                for err in exc.errors():
                    key = str(err["loc"][0]) if err["loc"] else ""
                    self.out.error("E110", f"{name} {key}: {_range_message(err, params.get(key))}",
                                   sb.span(key) if key in sb.clauses else stmt.span, _percent_hint(sb, key))
        if base is not None:
            stages = self._extended(b, base, stages)
        elif not b.stmt.block:
            self.out.error("E102", f"pipeline '{b.name}' needs a block of stages, or 'like' another pipeline",
                           b.stmt.span, "e.g. pipeline mine like paper { lateral_shift range 2px }")
            return
        pipeline = trusted(Pipeline, name=b.name, default=b.has("default"), stages=stages)
        self._declare(self.pipelines, "pipeline", b.name, b.name_span, pipeline)

    def _base_pipeline(self, b: Bound):
        """The pipeline `like` names (declared before, or the built-in paper); None without `like`; False after
        an error."""
        if not b.has("like"):
            if b.has("without"):
                self.out.error("E103", "'without' leaves stages out of the pipeline 'like' names: it needs 'like'",
                               b.span("without"))
                return False
            return None
        name = b.get("like")
        if name in self.pipelines:
            if name in self.paper_children:
                self.paper_children.append(b.name)
            return self.pipelines[name].value
        if name == PAPER:
            self.paper_children.append(b.name)  # its calibration_error is dropped for a rig without calibration
            return paper_pipeline(True)
        self.out.unknown(f"unknown pipeline '{name}' (like names a pipeline declared above, or paper)", b.span("like"),
                         did_you_mean(name, {**{k: None for k in self.pipelines}, PAPER: None}))
        return False

    def _extended(self, b: Bound, base: Pipeline, stages: list) -> list:
        """`like`: the base's stages, less `without`'s, each overridden by the block's, and the block's new
        stages placed in data-flow order."""
        without = _names(b.get("without"))
        for name in without:
            if name not in {st.effect for st in base.stages}:
                self.out.error("E104", f"'{name}' is not a stage of pipeline '{base.name}'", b.span("without"),
                               "its stages: " + ", ".join(st.effect for st in base.stages))
        own = {st.effect: st for st in stages}
        merged = [own.pop(st.effect, st) for st in base.stages if st.effect not in without]
        for st in own.values():  # after every stage that comes before it in a real system's data flow
            rank = REGISTRY[st.effect].flow_rank()
            at = next((i for i, m in enumerate(merged) if REGISTRY[m.effect].flow_rank() > rank), len(merged))
            merged.insert(at, st)
        return merged

    def _check_sigma(self, params: dict, stmt, sb: Bound) -> None:
        """W163: calibration_error's sigma scales the standard deviations of a declared covariance; far below 1
        it simulates a fraction of the calibration's uncertainty (checked once the rig is compiled)."""
        if params.get("sigma", 1.0) < SIGMA_FAR_BELOW:
            self.small_sigmas.append((params["sigma"], sb.span("sigma") if sb.has("sigma") else stmt.keyword_span))

    def _studies(self, path: Path | None) -> list:
        if not self.study_stmts:
            return []
        from wiredsl.language.compile_study import compile_study

        pipelines = {name: d.value for name, d in self.pipelines.items()}
        n_poses = len(path.poses) if path is not None else None
        studies: dict[str, _Decl] = {}
        for b in self.study_stmts:
            for stmt in b.stmt.block or ():  # varying calibration_error needs a calibration too (E162)
                if (stmt.keyword == "vary" and stmt.args and isinstance(stmt.args[0], ast.Ref)
                        and stmt.args[0].parts[0] == "calibration_error"):
                    self.calibration_stages.append(stmt.args[0].span)
            study = compile_study(b, pipelines, n_poses, self._units, self.out, dict(self.cameras), path)
            if study is not None:
                self._declare(studies, "study", b.name, b.name_span, study)
        return [d.value for d in studies.values()]

    def _check_defaults(self) -> None:
        marked = [d for d in self.pipelines.values() if d.value.default]
        for d in marked[1:]:
            self.out.error("E105", f"pipeline '{d.value.name}' is a second default", d.span,
                           f"'{marked[0].value.name}' is already the default")


MAX_BOARD = 200  # squares or inner corners a board has each way at most
MARKER_SHARE = 0.25  # a ChArUco marker's side at least this share of its square's: OpenCV draws a square in 64 px
MIN_SQUARE = 1e-6  # m: a board's square at least this
DOT_SHARE = 0.05  # a circle grid's dot at least this share of the nearest centres' distance (a few pixels at least)


def board_model(name: str, board: Board) -> Model:
    """The model of a calibration board: inner corners `c<row>_<column>` (OpenCV's order: row by row) joining
    the grid lines `v<column>` (x = column squares) and `h<row>` (y = row squares), which span the squares;
    the outer edges of the dark border squares (`top<k>`, `bottom<k>`, `left<k>`, `right<k>`: a dark square
    against the white margin); the face `plane` over squares and margin. A circle grid: its dots `o<row>_<column>`
    (ellipses, OpenCV's order), the face over the dots and margin."""
    if board.circles:
        return _circle_grid_model(name, board)
    s, m = board.square, board.margin
    nx, ny = board.inner
    x0, x1, y0, y1 = -s, nx * s, -s, ny * s
    lines = [trusted(Line, name=f"v{i}", start=(i * s, y0, 0.0), end=(i * s, y1, 0.0)) for i in range(nx)]
    lines += [trusted(Line, name=f"h{j}", start=(x0, j * s, 0.0), end=(x1, j * s, 0.0)) for j in range(ny)]
    for a in range(nx + 1):  # square columns: square (a, b) spans x in [(a - 1) s, a s]
        if a % 2 == 0:
            lines.append(trusted(Line, name=f"top{a}", start=((a - 1) * s, y0, 0.0), end=(a * s, y0, 0.0)))
        if (a + ny) % 2 == 0:
            lines.append(trusted(Line, name=f"bottom{a}", start=((a - 1) * s, y1, 0.0), end=(a * s, y1, 0.0)))
    for c in range(ny + 1):
        if c % 2 == 0:
            lines.append(trusted(Line, name=f"left{c}", start=(x0, (c - 1) * s, 0.0), end=(x0, c * s, 0.0)))
        if (nx + c) % 2 == 0:
            lines.append(trusted(Line, name=f"right{c}", start=(x1, (c - 1) * s, 0.0), end=(x1, c * s, 0.0)))
    corners = [trusted(Corner, name=f"c{j}_{i}", at=(i * s, j * s, 0.0), joins=[f"v{i}", f"h{j}"])
               for j in range(ny) for i in range(nx)]
    face = trusted(Face, name=board.face, vertices=[(x0 - m, y0 - m, 0.0), (x1 + m, y0 - m, 0.0),
                                                    (x1 + m, y1 + m, 0.0), (x0 - m, y1 + m, 0.0)])
    return trusted(Model, name=name, lines=lines, corners=corners, faces=[face], board=board)


def _circle_grid_model(name: str, board: Board) -> Model:
    r, m = board.diameter / 2, board.margin
    centres = board.centres()
    ellipses = [trusted(Ellipse, name=f"o{k // board.columns}_{k % board.columns}", centre=tuple(c.tolist()),
                        normal=(0.0, 0.0, 1.0), axis=(1.0, 0.0, 0.0), a=r, b=r) for k, c in enumerate(centres)]
    (x0, y0, _), (x1, y1, _) = (centres.min(axis=0) - r - m).tolist(), (centres.max(axis=0) + r + m).tolist()
    face = trusted(Face, name=board.face, vertices=[(x0, y0, 0.0), (x1, y0, 0.0), (x1, y1, 0.0), (x0, y1, 0.0)])
    return trusted(Model, name=name, ellipses=ellipses, faces=[face], board=board)


def _line_span(path: FsPath, text: str, line: int) -> Span:
    """The whole of one line of a file read by a statement."""
    lines = text.splitlines()
    return Span(sources.display_path(path), line, 1, line, len(lines[line - 1]) + 1 if line <= len(lines) else 2)


def _names(values) -> list[str]:
    """The words of a `names` slot ([a, b]), or [] when absent."""
    return [getattr(v, "value", v) for v in values or ()]


def _ignore(b: Bound) -> None:
    pass


def _percent_hint(sb: Bound, key: str) -> str | None:
    """'did you mean 29%?' for a bare fraction above 1, which was surely meant as a percentage."""
    if key not in sb.clauses or sb.sig.clauses[key].slots[0].kind != "fraction":
        return None
    span = sb.span(key)
    num = next((a for a in sb.stmt.args if isinstance(a, ast.Number) and a.span == span), None)
    if num is not None and num.unit is None and 1 < num.value <= 100:
        return f"did you mean {num.text}%?"
    return None


def _range_message(err: dict, value: object) -> str:
    ctx = err.get("ctx", {})
    for key, word in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<")):
        if key in ctx:
            return f"must be {word} {ctx[key]:g}, got {value:g}"
    return err["msg"]


def read_mesh_features(fb: Bound, units: dict[str, str], out: Collector):
    """The features of a `mesh read` statement's mesh, scaled, turned and placed (MeshFeatures), from the
    features' cache when this file was read with these options before (io/mesh.py); None when reported."""
    from wiredsl.engine import mesh as mesh_features
    from wiredsl.io import mesh as mesh_io

    path, where = fb.get("read"), fb.span("read")
    scale = mesh_scale(fb, units, out)
    crease = fb.get("crease", math.radians(30))
    if not 0 <= crease <= math.pi:  # below 0 every edge would be a feature, above 180 deg none
        out.error("E110", f"crease angle must be in 0..180 deg, got {math.degrees(crease):g} deg",
                       fb.span("crease"))
        return None
    if scale is None:
        return None
    up, origin = fb.get("up", "z"), fb.get("origin", "file")
    shortest, budget = fb.get("shortest"), fb.get("budget", "auto")  # auto: BUDGET for a scan, none for CAD
    if shortest is not None and not 0 <= shortest <= MAX_MAGNITUDE:
        out.error("E110", f"shortest must be in 0..{MAX_MAGNITUDE:g} m, got {shortest:g}", fb.span("shortest"))
        return None
    if budget != "auto" and budget < 0:
        out.error("E110", f"budget must be >= 0, got {budget:g}", fb.span("budget"))
        return None
    budget = budget if budget == "auto" else int(budget)
    try:
        target = FsPath(fb.stmt.span.file).parent / path
        data = sources.read_bytes(target, "mesh file", where, limit=mesh_io.MAX_MESH_BYTES)
        kind = mesh_io.FORMATS.get(target.suffix.lower(), "")
        key = mesh_io.features_key(data, kind, (scale, up, crease, origin, shortest, budget))
        found = mesh_io.load_features(key)
        if found is None:
            raw = mesh_io.read_mesh(target, data)
    except WiredslError as err:
        out.extend(err.diagnostics)
        return None
    except mesh_io.MeshTooLarge as exc:
        out.error("E151", f"mesh file {path} {exc}", where, "simplify the mesh (decimate it) first")
        return None
    except mesh_io.MeshFileError as exc:
        out.error("E125", f"mesh file {path}: {exc}", where)
        return None
    if found is None:
        V = raw.vertices * scale
        if np.abs(V).max() > MAX_MAGNITUDE:
            out.error("E110", f"mesh file {path} has a vertex beyond {MAX_MAGNITUDE:g} m", where)
            return None
        if up != "z":  # the file's up axis becomes z: y-up turns about x, x-up about y
            V = V @ (rotation("x", math.pi / 2) if up == "y" else rotation("y", -math.pi / 2)).T
        lo, hi = V.min(axis=0), V.max(axis=0)
        if origin != "file":  # the part's centre, or the centre of its base, at the model's origin
            V = V - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2] if origin == "base" else
                              (lo[2] + hi[2]) / 2])
        found = mesh_features.features(V, raw.triangles, crease, shortest, budget)
        if not (len(found.lines) + len(found.polylines) + len(found.ellipses) + len(found.faces)
                + len(found.occluders)):
            out.error("E125", f"mesh file {path}: no triangle has an area", where)
            return None
        for text in raw.warnings:  # a file the reader warns about is read (and warned about) every time
            out.warning("W128", f"mesh file {path}: the reader warns: {text}", where,
                        "the file may be damaged: check what was read ('wiredsl compile' lists it)")
        if not raw.warnings:
            mesh_io.save_features(key, found)
    if found.degenerate:
        out.warning("W125", f"mesh file {path}: {found.degenerate} triangle(s) of no area dropped", where)
    if found.nonmanifold:
        out.warning("W126", f"mesh file {path}: {found.nonmanifold} edge(s) shared by more than two "
                            "triangles (non-manifold), kept as lines", where)
    lo, hi = found.vertices.min(axis=0), found.vertices.max(axis=0)
    away = float(np.linalg.norm(np.maximum(np.maximum(lo, -hi), 0.0)))  # from the origin to the part's box
    if origin == "file" and away > 0.5 * float((hi - lo).max()):
        size = mesh_size(found).split(", from")[0]
        out.warning("W127", f"mesh file {path}: its origin is {_length(away)} outside the part (which spans {size}), "
                            "so `place` puts the part that far from where it says",
                    where, "place it by its centre or its base: origin centre, origin base")
    return found


def mesh_scale(fb: Bound, units: dict[str, str], out: Collector) -> float | None:
    """Metres per unit of a `mesh read`'s file: `scale 1in` (a length), `scale 0.0254` (bare: metres), `units in`,
    or the scene file's length unit; None (reported) when out of range or given twice."""
    if "scale" in fb.clauses and "units" in fb.clauses:
        out.error("E103", "give the file's unit once: scale or units", fb.span("units"))
        return None
    if "units" in fb.clauses:
        return UNITS[fb.get("units")][1]
    scale = fb.get("scale", UNITS[units["length"]][1])
    if isinstance(scale, tuple):  # (value, kind, unit) of `number|length`
        scale = scale[0]
    if not (0 < scale <= MAX_MAGNITUDE):
        out.error("E110", f"mesh scale must be in (0, {MAX_MAGNITUDE:g}], got {scale:g}", fb.span("scale"))
        return None
    return scale


def _length(x: float) -> str:
    return f"{x * 1e3:.3g} mm" if x < 1 else f"{x:.3g} m"


def mesh_size(found) -> str:
    """A mesh's size and bounds, in metres after scaling and placing, and its features, for `check` and hover."""
    lo, hi = found.vertices.min(axis=0), found.vertices.max(axis=0)
    size = " x ".join(_length(float(x)) for x in hi - lo)
    tiny = 1e-9 * max(float(np.abs(found.vertices).max(initial=0.0)), 1.0)  # rounding's -1.2e-17 is 0
    box = lambda p: "(" + ", ".join(f"{0.0 if abs(x) < tiny else float(x):.4g}" for x in p) + ")"  # noqa: E731
    counts = ", ".join(_count(len(getattr(found, what)), word) for what, word in (
        ("lines", "line"), ("polylines", "polyline"), ("ellipses", "ellipse"), ("silhouettes", "silhouette"),
        ("corners", "corner"), ("faces", "face"), ("occluders", "occluding triangle")))
    return f"{size}, from {box(lo)} to {box(hi)} m; {counts}; {read_as(found)}"


def _count(n: int, word: str) -> str:
    """'1 silhouette', '2 silhouettes' (ellipse: 'ellipses')."""
    return f"{n} {word}" + ("" if n == 1 else "s")


def read_as(found) -> str:
    """Whether a mesh was read as a CAD part or a scan, and what its budget left out, for `check` and hover."""
    kind = "a scan" if found.scan else "a CAD part"
    kept = (f"budget {found.budget} left out {found.cut:,} lines and polylines" if found.cut else
            "every line and polyline kept" if found.budget is None else f"budget {found.budget} cut nothing")
    return f"read as {kind} ({100 * found.planar:.3g}% of its edge length between coplanar triangles): {kept}"
