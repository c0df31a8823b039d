"""Stage 3: AST -> pydantic `Scene`, with every semantic check, units in SI.

Each check reports through a Collector with its own code, so one run lists all
the errors of a scene. Codes are documented in the README.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path as FsPath

import numpy as np
import pydantic

from wiredsl.diagnostics import Collector, Diagnostic, Span, WiredslError, did_you_mean
from wiredsl.effects import REGISTRY
from wiredsl.language import ast
from wiredsl.language.statements import MAX_MAGNITUDE, Bound, bind
from wiredsl.language.units import DEFAULT_UNITS
from wiredsl.scene import (
    CALIBRATION_PARAMETERS,
    Calibration,
    Camera,
    Corner,
    Ellipse,
    Face,
    Line,
    Model,
    Mount,
    Path,
    Pipeline,
    Placement,
    Polyline,
    Rig,
    Scene,
    Silhouette,
    Stage,
    Viewpoints,
)

FORMAT_VERSION = 1
MAX_VIEWPOINTS = 100_000
MAX_POSES = 100_000
MAX_MATRIX = 1_000
COUNTABLE = 1e15  # a count of grid points or poses below this is exact in a float, so it may be computed
GEOM_EPS = 1e-9  # metres: shorter is degenerate
PERP_TOL = 1e-6  # |cos| between an ellipse's axis and normal
BARE_FOCAL_METRES = 0.1  # a bare focal length this long (in m) is more likely mm written without its unit
PLAUSIBLE_FOV = 1000  # f over the image's larger side beyond which a focal length is probably missing its unit
MAX_MATRIX_ENTRY = 1e100  # calibration entries: inverses, square roots and products of them stay finite


def compile_file(path: str | os.PathLike) -> tuple[Scene, list[Diagnostic], ast.Program]:
    """Load, check and compile a scene file; raise WiredslError listing every error."""
    program = ast.load(path)
    scene, diags = compile_program(program)
    return scene, diags, program


def compile_program(program: ast.Program) -> tuple[Scene, list[Diagnostic]]:
    """Compile a loaded program; returns the scene and its warnings."""
    out = Collector()
    scene = Compiler(program, out).run()
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


class Compiler:
    def __init__(self, program: ast.Program, out: Collector):
        self.program = program
        self.out = out
        self.units: dict[str, dict[str, str]] = {}
        self.models: dict[str, _Decl] = {}
        self.features: dict[str, dict[str, str]] = {}  # model -> feature -> kind
        self.placements: dict[str, _Decl] = {}
        self.camera_stmts: dict[str, Bound] = {}
        self.cameras: dict[str, Camera] = {}
        self.singles: dict[str, Bound] = {}  # rig, viewpoints, path
        self.pipelines: dict[str, _Decl] = {}
        self.study_stmts: list[Bound] = []
        self.calibration_stages: list[Span] = []  # where pipelines call calibration_error
        self.scene_name: str | None = None
        self.rig_without_calibration = False

    # ------------------------------------------------------------------ driver
    def run(self) -> Scene:
        self._header()
        handlers: dict[str, Callable[[Bound], None]] = {
            "model": self._model, "place": self._place, "camera": self._camera_decl,
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
        path = self._path(self.singles["path"]) if "path" in self.singles else None
        self._check_defaults()
        studies = self._studies(path)
        if self.rig_without_calibration:
            for span in self.calibration_stages:
                self.out.error("E162", f"calibration_error needs a calibration, and rig "
                                       f"'{self.singles['rig'].name}' has none", span,
                               "add 'calibration ...' to the rig, or remove the stage")
        root = self.program.root
        name = self.scene_name or FsPath(root.path).stem
        if self.out.n_errors:
            # Sentinel; never returned to a user, compile_program raises first.
            return Scene.model_construct(name=name, source=root.path)
        return Scene(
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
            if not versions and file is self.program.root:
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
        self.out.error("E104", f"unknown {what} '{name}'{context}", span, did_you_mean(name, table))
        return False

    # ------------------------------------------------------------------ models
    def _model(self, b: Bound) -> None:
        feats: dict[str, list] = {k: [] for k in ("lines", "polylines", "ellipses", "silhouettes", "corners", "faces")}
        names: dict[str, _Decl] = {}
        silhouettes, corners = [], []  # checked once every feature name is known
        for stmt in b.stmt.block:
            fb = bind(stmt, "model", self._units(stmt), self.out)
            if fb is None or not fb.ok:
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
        model = Model(name=b.name, **feats)
        if self._declare(self.models, "model", b.name, b.name_span, model):
            self.features[b.name] = kinds

    def _point(self, fb: Bound, key: str) -> np.ndarray:
        return np.array(fb.get(key), dtype=float)

    def _feature_line(self, fb: Bound) -> Line | None:
        p0, p1 = self._point(fb, "from"), self._point(fb, "to")
        if np.linalg.norm(p1 - p0) <= GEOM_EPS:
            self.out.error("E120", f"line '{fb.name}' has zero length", fb.stmt.span, "its two ends are the same point")
            return None
        return Line(name=fb.name, start=fb.get("from"), end=fb.get("to"))

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
        return Polyline(name=fb.name, points=pts, closed=closed)

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
        return Ellipse(name=fb.name, centre=fb.get("centre"), normal=tuple(n), axis=tuple(u), a=a, b=b, t0=t0, t1=t1)

    def _feature_silhouette(self, fb: Bound) -> Silhouette:
        refs = fb.clauses["between"][0]
        return Silhouette(name=fb.name, ellipses=(refs[0].value, refs[1].value))

    def _feature_corner(self, fb: Bound) -> Corner:
        joins = [r.value for r in fb.get("joins", [])]
        return Corner(name=fb.name, at=fb.get("at"), joins=joins)

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
        return Face(name=fb.name, vertices=pts)

    # ------------------------------------------------------------------ placements
    def _place(self, b: Bound) -> None:
        model = b.pos(0)
        name = b.get("as")
        if not self._ref(self.models, "model", model, b.positional[0].span):
            return
        if b.has("rotate") and b.has("ypr"):
            self.out.error("E103", "give either 'rotate' or 'ypr', not both", b.span("ypr"))
            return
        R = np.eye(3)
        for axis, angle in b.clauses.get("rotate", []):
            R = rotation(axis.value, angle.value) @ R
        if b.has("ypr"):
            yaw, pitch, roll = b.get("ypr")
            R = rotation("z", yaw) @ rotation("y", pitch) @ rotation("x", roll)
        placement = Placement(name=name, model=model, position=b.get("at", (0.0, 0.0, 0.0)), rotation=_mat(R))
        self._declare(self.placements, "placement", name, b.span("as"), placement)

    # ------------------------------------------------------------------ cameras
    def _camera_decl(self, b: Bound) -> None:
        if b.name in self.camera_stmts:
            self.out.error("E105", f"duplicate camera '{b.name}'", b.name_span,
                           f"first declared at {self.camera_stmts[b.name].name_span}")
            return
        self.camera_stmts[b.name] = b

    def _resolve_cameras(self) -> None:
        settings: dict[str, dict[str, tuple[object, Span]] | None] = {}
        failed: set[str] = set()

        def resolve(name: str, chain: tuple[str, ...]) -> dict | None:
            if name in settings:
                return settings[name]
            b = self.camera_stmts[name]
            base: dict = {}
            if b.has("like"):
                parent = b.get("like")
                if parent in chain:
                    self.out.error("E104", "cameras are declared like each other in a cycle: "
                                           + " -> ".join((*chain, parent)), b.span("like"))
                    settings[name] = None
                    return None
                if not self._ref(self.camera_stmts, "camera", parent, b.span("like")):
                    settings[name] = None
                    return None
                base = resolve(parent, (*chain, parent))
                if base is None:
                    settings[name] = None
                    return None
            own = dict(base)
            here: set[str] = set()
            for stmt in b.stmt.block or ():
                if stmt.keyword == "read":
                    sb = bind(stmt, "camera", self._units(stmt), self.out)
                    if sb is not None and sb.ok:
                        read = self._camera_file(sb)
                        if read is None:  # reported: no cascade of "needs focal"
                            settings[name] = None
                            return None
                        own.update(read)
            for stmt in b.stmt.block or ():
                if stmt.keyword == "read":
                    continue
                sb = bind(stmt, "camera", self._units(stmt), self.out)
                if sb is None or not sb.ok:
                    failed.add(name)  # what it would have set is unknown: no 'needs' errors on top
                    continue
                here.add(stmt.keyword)
                if stmt.keyword in ("k", "k1"):
                    if here >= {"k", "k1"}:
                        self.out.error("E103", "give either TINA's 'k' or OpenCV's 'k1', not both",
                                       stmt.keyword_span, "k1 = -k")
                    own.pop("k1" if stmt.keyword == "k" else "k", None)  # one parameter, two spellings
                own[stmt.keyword] = (sb.pos(0), sb.positional[0].span)
            settings[name] = own
            return own

        for name, b in self.camera_stmts.items():
            s = resolve(name, (name,))
            if s is not None and name not in failed:
                cam = self._camera(b, s)
                if cam is not None:
                    self.cameras[name] = cam

    def _calibration_file(self, sb: Bound, path_span: Span, path: str, fmt: str | None):
        """The cameras of a calibration file named in a statement, or None (reported)."""
        from wiredsl.io.calibration import CalibrationFileError, read

        try:
            target = FsPath(sb.stmt.span.file).parent / path
            ast.read_bytes(target, "calibration file", path_span)  # a regular file, not a FIFO (would block)
            return read(target, fmt)
        except WiredslError as err:
            self.out.extend(err.diagnostics)
        except CalibrationFileError as exc:
            self.out.error("E141", f"calibration file {path}: {exc}", path_span)
        except ValueError as exc:  # e.g. a NUL byte in the path
            self.out.error("E010", f"cannot read calibration file {path!r}: {exc}", path_span)
        return None

    def _camera_file(self, sb: Bound) -> dict[str, tuple[object, Span]] | None:
        """A camera's settings from a calibration file, as if written as statements at `read`."""
        cams = self._calibration_file(sb, sb.positional[0].span, sb.pos(0), sb.get("format"))
        if cams is None:
            return None
        i = 1 if sb.get("entry") == "second" else 0
        if i >= len(cams):
            self.out.error("E104", f"calibration file {sb.pos(0)} has one camera; there is no second",
                           sb.span("entry"))
            return None
        c, span = cams[i], sb.stmt.span
        if not all(math.isfinite(v) and abs(v) <= MAX_MAGNITUDE for v in (c.fx, c.fy, c.cx, c.cy)):
            self.out.error("E141", f"calibration file {sb.pos(0)}: the camera matrix has a value that is not "
                                   f"finite or beyond {MAX_MAGNITUDE:g} px", sb.positional[0].span)
            return None
        out = {"focal": ((c.fx, "image", "px"), span), "aspect": ((1.0, c.fy / c.fx), span),
               "centre": ((c.cx, c.cy), span), "k1": (c.dist[0], span), "k2": (c.dist[1], span),
               "p1": (c.dist[2], span), "p2": (c.dist[3], span)}
        if c.width is not None:
            out["size"] = ((c.width, c.height), span)
        return out

    def _camera(self, b: Bound, s: dict[str, tuple[object, Span]]) -> Camera | None:
        n0 = self.out.n_errors
        where = b.name_span

        def need(key: str, what: str) -> None:
            if key not in s:
                self.out.error("E102", f"camera '{b.name}' needs '{key}' ({what})", where)

        need("focal", "focal length")
        need("size", "image size")
        if n0 != self.out.n_errors:
            return None
        (f, kind, unit), fspan = s["focal"]
        written = f
        if kind == "length":
            if "pixel" not in s:
                self.out.error("E102", f"camera '{b.name}' gives its focal length in {kind} units and needs 'pixel'",
                               fspan, "add e.g. 'pixel 0.01mm', or give the focal length in px")
                return None
            pixel, pspan = s["pixel"]
            self._positive(pixel, "pixel size", pspan)
            f = f / pixel if pixel > 0 else f
        self._positive(f, "focal length", fspan)
        (w, h), sspan = s["size"]
        for v in (w, h):
            if not (v > 0 and float(v).is_integer()):
                self.out.error("E110", f"image size must be whole pixels > 0, got {v:g}", sspan)
        ax, ay = s.get("aspect", ((1.0, 1.0), None))[0]
        for v in (ax, ay):
            self._positive(v, "aspect scale", s.get("aspect", (None, where))[1])
        if self.out.n_errors == n0:
            fx = f * max(ax, ay)
            if not fx <= MAX_MAGNITUDE:  # also catches inf from a huge focal over a tiny pixel
                self.out.error("E110", f"camera '{b.name}': focal length of {fx:.3g} px (with aspect) is beyond "
                                       f"the limit of {MAX_MAGNITUDE:g} px", fspan)
            else:
                bare_metres = unit is None and kind == "length" and self.units[fspan.file]["length"] == "m"
                hint = f"did you mean {written:g}mm?" if bare_metres else None
                if f < 1 or f > PLAUSIBLE_FOV * max(w, h):
                    fov = math.degrees(2 * math.atan(max(w, h) / (2 * f)))
                    self.out.warning("W111", f"camera '{b.name}': a focal length of {f:.4g} px gives a field of "
                                             f"view of {fov:.3g} deg over its {max(w, h):g} px image", fspan, hint)
                elif bare_metres and written >= BARE_FOCAL_METRES:  # a bare number is metres: 6 is a 6 m lens
                    self.out.warning("W111", f"camera '{b.name}': a bare focal length is in metres, so "
                                             f"{written:g} is a {written:g} m lens", fspan, hint)
        k1 = -s["k"][0] if "k" in s else s.get("k1", (0.0, None))[0]
        cx, cy = s.get("centre", ((w / 2, h / 2), None))[0]
        if self.out.n_errors != n0:
            return None
        return Camera(name=b.name, f=f, ax=ax, ay=ay, cx=cx, cy=cy, k1=k1, k2=s.get("k2", (0.0,))[0],
                      p1=s.get("p1", (0.0,))[0], p2=s.get("p2", (0.0,))[0], width=int(w), height=int(h))

    def _positive(self, v: float, what: str, span: Span | None) -> None:
        if not v > 0:
            self.out.error("E110", f"{what} must be > 0, got {v:g}", span)

    # ------------------------------------------------------------------ rig, viewpoints, path
    def _single(self, b: Bound) -> None:
        kind = b.stmt.keyword
        if kind in self.singles:
            self.out.error("E105", f"a scene has one {kind}; '{b.name}' is a second",
                           b.name_span, f"the first is at {self.singles[kind].name_span}")
            return
        self.singles[kind] = b

    def _rig(self, b: Bound) -> Rig | None:
        mounts: dict[str, Mount] = {}
        calibration = None
        seen: dict[str, Span] = {}
        for stmt in b.stmt.block:
            sb = bind(stmt, "rig", self._units(stmt), self.out)
            if sb is None or not sb.ok:
                continue
            if stmt.keyword in seen:
                self.out.error("E105", f"'{stmt.keyword}' given twice in rig '{b.name}'", stmt.keyword_span)
                continue
            seen[stmt.keyword] = stmt.keyword_span
            if stmt.keyword == "calibration":
                calibration = self._calibration(sb)
            else:
                mount = self._mount(sb)
                if mount is not None:
                    mounts[stmt.keyword] = mount
        for side in ("left", "right"):
            if side not in seen:
                self.out.error("E102", f"rig '{b.name}' needs a '{side}' camera", b.name_span)
        self.rig_without_calibration = "calibration" not in seen and not any(
            s.keyword == "calibration" for s in b.stmt.block)  # a calibration with errors is reported already
        for side, other in (("left", "right"), ("right", "left")):
            if isinstance(mounts.get(side), Bound):
                mounts[side] = self._relative_mount(mounts[side], mounts.get(other), side)
        if len(mounts) != 2 or not all(isinstance(m, Mount) for m in mounts.values()):
            return None
        return Rig(name=b.name, left=mounts["left"], right=mounts["right"], calibration=calibration)

    def _mount(self, sb: Bound) -> Mount | Bound | None:
        """A mount, or its statement when it is `relative` to the other camera (resolved in `_rig`)."""
        cam = sb.pos(0)
        ok = self._ref(self.camera_stmts, "camera", cam, sb.positional[0].span)
        if sb.has("relative"):
            for key in ("at", "looking", "roll"):
                if sb.has(key):
                    self.out.error("E103", f"'{key}' and 'relative' both give the mount's pose: keep one",
                                   sb.span(key))
                    return None
            return sb if ok else None
        for key in ("at", "looking"):
            if not sb.has(key):
                self.out.error("E102", f"'{sb.stmt.keyword}' needs '{key}' ({sb.sig.clauses[key].doc}), or "
                                       "'relative' with a stereo calibration file", sb.stmt.span,
                               f"e.g. {sb.sig.example}")
                return None
        look = _unit(np.array(sb.get("looking"), dtype=float))
        if np.linalg.norm(look) == 0:
            self.out.error("E121", "viewing direction is zero", sb.span("looking"))
            return None
        R = camera_rotation(look, sb.get("roll", 0.0))
        if R is None:
            self.out.error("E122", "viewing direction is vertical: the camera's image axes are undefined",
                           sb.span("looking"), "tilt it slightly, e.g. (0.01, 0, -1)")
            return None
        return Mount(camera=cam, position=sb.get("at"), rotation=_mat(R)) if ok else None

    def _relative_mount(self, sb: Bound, other: Mount | Bound | None, side: str) -> Mount | None:
        """A camera's mount from a stereo file's extrinsics (X2 = R X1 + T, from the first camera to the
        second) and the other camera's mount: the file's second camera is the right one."""
        if not isinstance(other, Mount):
            if isinstance(other, Bound):
                self.out.error("E103", "only one camera of a rig can be 'relative' to the other", sb.span("relative"))
            return None
        cams = self._calibration_file(sb, sb.span("relative"), sb.get("relative"), None)
        if cams is None:
            return None
        posed = next((c for c in cams if c.R is not None), None)
        if posed is None:
            self.out.error("E141", f"calibration file {sb.get('relative')} has no extrinsics (R and T, or "
                                   "T_cn_cnm1)", sb.span("relative"))
            return None
        R_o, p_o = np.array(other.rotation), np.array(other.position)  # camera -> robot
        if side == "right":  # X_r = R X_l + T: the right camera in the robot frame
            R_s = R_o @ posed.R.T
            p_s = p_o - R_s @ posed.T
        else:  # X_r = R X_l + T, with the right camera known
            R_s = R_o @ posed.R
            p_s = p_o + R_o @ posed.T
        if not np.abs(p_s).max() <= MAX_MAGNITUDE:  # T near the float limit overflows here
            self.out.error("E141", f"calibration file {sb.get('relative')}: the translation T is beyond "
                                   f"{MAX_MAGNITUDE:g} m", sb.span("relative"))
            return None
        return Mount(camera=sb.pos(0), position=tuple(float(x) for x in p_s), rotation=_mat(R_s))

    def _calibration(self, sb: Bound) -> Calibration | None:
        kind = sb.pos(0)
        if sb.has("kalibr"):
            return self._kalibr_calibration(sb)
        if not sb.has("order"):
            self.out.error("E102", "'calibration' needs 'order' (the parameter of each row), or 'kalibr' with "
                                   "Kalibr's results-cam.txt", sb.stmt.span, f"e.g. {sb.sig.example}")
            return None
        order = sb.get("order")
        n0 = self.out.n_errors
        seen = set()
        for item in order:
            side, _, param = item.value.partition(".")
            if side not in ("left", "right") or param not in CALIBRATION_PARAMETERS:
                choices = [f"{s}.{p}" for s in ("left", "right") for p in CALIBRATION_PARAMETERS]
                self.out.error("E104", f"unknown calibration parameter '{item.value}'", item.span,
                               did_you_mean(item.value, choices) or "parameters are left.<p> or right.<p> with <p> "
                               "one of " + ", ".join(CALIBRATION_PARAMETERS))
            elif item.value in seen:
                self.out.error("E105", f"calibration parameter '{item.value}' listed twice", item.span)
            seen.add(item.value)
        if sb.has("matrix") == sb.has("file"):
            self.out.error("E102", "calibration needs exactly one of 'matrix' or 'file'", sb.stmt.span)
            return None
        if sb.has("matrix"):
            matrix, mspan = sb.get("matrix"), sb.span("matrix")
        else:
            mspan = sb.span("file")
            matrix = read_matrix_file(FsPath(sb.stmt.span.file).parent / sb.get("file"), len(order), mspan, self.out)
            if matrix is None:
                return None
        n = len(order)
        if n > MAX_MATRIX:
            self.out.error("E151", f"calibration of {n} parameters exceeds the limit of {MAX_MATRIX}", sb.span("order"))
            return None
        if len(matrix) != n or any(len(r) != n for r in matrix):
            shape = f"{len(matrix)} x {max((len(r) for r in matrix), default=0)}"
            self.out.error("E140", f"calibration matrix is {shape}, but 'order' names {n} parameters "
                                   f"(expected {n} x {n})", mspan)
            return None
        M = np.array(matrix, dtype=float)
        problem = matrix_problem(M)
        if problem:
            self.out.error("E140", f"calibration {kind} matrix {problem}", mspan)
        if self.out.n_errors != n0:
            return None
        return Calibration(kind=kind, order=[o.value for o in order], matrix=M.tolist())

    def _kalibr_calibration(self, sb: Bound) -> Calibration | None:
        """The rig's calibration uncertainty as Kalibr reports it: independent standard deviations
        (cam0 is the left camera, cam1 the right; the baseline's as the right mount's)."""
        for key in ("matrix", "file"):
            if sb.has(key):
                self.out.error("E103", f"'{key}' and 'kalibr' both give the matrix: keep one", sb.span(key))
                return None
        if sb.pos(0) != "covariance":
            self.out.error("E103", "Kalibr reports standard deviations: the calibration kind is 'covariance'",
                           sb.positional[0].span)
            return None
        cams = self._calibration_file(sb, sb.span("kalibr"), sb.get("kalibr"), "kalibr")
        if cams is None:
            return None
        sigma = {f"{side}.{k}": v for side, cam in zip(("left", "right"), cams, strict=False)
                 for k, v in cam.sigma.items() if v > 0}
        names = [(o.value, o.span) for o in sb.get("order")] if sb.has("order") else [(k, None) for k in sigma]
        for name, span in names:
            if name not in sigma:
                self.out.error("E104", f"Kalibr's file gives no standard deviation for '{name}'", span,
                               did_you_mean(name, sigma) or "it has: " + ", ".join(sigma))
                return None
        return Calibration(kind="covariance", order=[n for n, _ in names],
                           matrix=np.diag([sigma[n] ** 2 for n, _ in names]).tolist())

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
        return Viewpoints(name=b.name, names=names, points=points, triangles=triangles, visibility=mode, file=file,
                          visible={k: sorted(set(v)) for k, v in visible.items()})

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
        return {n: k for n, k in self.features.get(model, {}).items() if k != "face"}

    def _path(self, b: Bound) -> Path | None:
        poses: list[tuple[float, float, float]] = []
        n0 = self.out.n_errors
        for stmt in b.stmt.block:
            sb = bind(stmt, "path", self._units(stmt), self.out)
            if sb is None or not sb.ok:
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
        if not poses:
            if self.out.n_errors == n0:  # else the statements that failed are the reason, reported already
                self.out.error("E102", f"path '{b.name}' has no poses", b.name_span)
            return None
        return Path(name=b.name, poses=poses)

    # ------------------------------------------------------------------ pipelines
    def _pipeline(self, b: Bound) -> None:
        stages = []
        seen: dict[str, Span] = {}
        last: tuple[int, str] | None = None
        for stmt in b.stmt.block:
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
            if name == "calibration_error" and stages:
                self.out.error("E160", "calibration_error must be the first stage: it acts on the cameras, "
                                       "before anything is projected", stmt.keyword_span,
                               "move it to the top of the pipeline")
            elif last is not None and rank < last[0]:
                self.out.warning("W161", f"'{name}' ({effect.acts_on}) after '{last[1]}' "
                                         f"({REGISTRY[last[1]].acts_on}) departs from the data flow of a real "
                                         "system", stmt.keyword_span,
                                 "real order: cameras, edges, fitting, corner detection, corner matching, stereo")
            last = (rank, name) if last is None or rank >= last[0] else last
            params = {k: sb.get(k) for k in sb.clauses}
            try:
                stages.append(Stage(effect=name, params=effect.Params(**params).model_dump()))
            except pydantic.ValidationError as exc:
                for err in exc.errors():
                    key = str(err["loc"][0]) if err["loc"] else ""
                    self.out.error("E110", f"{name} {key}: {_range_message(err, params.get(key))}",
                                   sb.span(key) if key in sb.clauses else stmt.span, _percent_hint(sb, key))
        pipeline = Pipeline(name=b.name, default=b.has("default"), stages=stages)
        self._declare(self.pipelines, "pipeline", b.name, b.name_span, pipeline)

    def _studies(self, path: Path | None) -> list:
        from wiredsl.language.compile_study import compile_study

        pipelines = {name: d.value for name, d in self.pipelines.items()}
        n_poses = len(path.poses) if path is not None else None
        studies: dict[str, _Decl] = {}
        for b in self.study_stmts:
            for stmt in b.stmt.block or ():  # varying calibration_error needs a calibration too (E162)
                if (stmt.keyword == "vary" and stmt.args and isinstance(stmt.args[0], ast.Ref)
                        and stmt.args[0].parts[0] == "calibration_error"):
                    self.calibration_stages.append(stmt.args[0].span)
            study = compile_study(b, pipelines, n_poses, self._units, self.out, tuple(self.cameras))
            if study is not None:
                self._declare(studies, "study", b.name, b.name_span, study)
        return [d.value for d in studies.values()]

    def _check_defaults(self) -> None:
        marked = [d for d in self.pipelines.values() if d.value.default]
        for d in marked[1:]:
            self.out.error("E105", f"pipeline '{d.value.name}' is a second default", d.span,
                           f"'{marked[0].value.name}' is already the default")


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


def rotation(axis: str, angle: float) -> np.ndarray:
    """Right-handed rotation matrix about a coordinate axis."""
    c, s = math.cos(angle), math.sin(angle)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def camera_rotation(look: np.ndarray, roll: float) -> np.ndarray | None:
    """robot_from_camera for an OpenCV camera frame (x right, y down, z along `look`); z is up."""
    z = look / np.linalg.norm(look)
    x = np.cross(z, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-9:
        return None
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = math.cos(roll), math.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    return np.column_stack([x, y, z])


def _unit(v: np.ndarray) -> np.ndarray:
    """v scaled so its largest component is 1 (zero stays zero): norms of huge or tiny vectors stay finite."""
    big = float(np.abs(v).max())
    return v / big if big > 0 else v


def _mat(R: np.ndarray):
    return tuple(tuple(float(v) for v in row) for row in R)


def matrix_problem(M: np.ndarray) -> str | None:
    """Why a matrix is not a usable covariance or information matrix, or None."""
    if not np.all(np.isfinite(M)):
        return "has a value that is not finite"
    scale = float(np.abs(M).max()) if M.size else 0.0
    if scale > MAX_MATRIX_ENTRY:
        return f"has an entry of {scale:.3g}, beyond the limit of {MAX_MATRIX_ENTRY:g}"
    unit = scale if scale > 0 else 1.0
    M = M / unit  # judged at unit scale (differences and eigenvalues of huge entries overflow), reported unscaled
    asym = float(np.abs(M - M.T).max()) if M.size else 0.0
    if asym > 1e-9:
        i, j = np.unravel_index(np.argmax(np.abs(M - M.T)), M.shape)
        return f"is not symmetric (entry [{i + 1}, {j + 1}] differs from [{j + 1}, {i + 1}] by {asym * unit:.3g})"
    if M.size:
        low = float(np.linalg.eigvalsh((M + M.T) / 2).min())
        if low < -1e-9:
            return f"is not positive semi-definite (smallest eigenvalue {low * unit:.3g})"
    return None


def read_matrix_file(path: FsPath, n: int, span: Span, out: Collector) -> list[list[float]] | None:
    """A matrix from a file: plain rows of numbers, or TINA's covariance format
    (n, a label, the n x n matrix, then the n mean parameters)."""
    try:
        text = ast.read_bytes(path, "calibration file", span).decode("utf-8")
    except WiredslError as err:
        out.extend(err.diagnostics)
        return None
    except UnicodeDecodeError as exc:
        out.error("E010", f"calibration file {ast.display_path(path)} is not UTF-8 text ({exc.reason} at byte "
                          f"{exc.start})", span)
        return None
    words = [w for line in text.splitlines() for w in line.partition("#")[0].split()]
    try:
        if len(words) >= 2 and words[0].isdigit() and not _is_number(words[1]):
            size = int(words[0])
            nums = [float(w) for w in words[2:]]
            if len(nums) != size * size + size:
                raise ValueError(f"TINA covariance file of size {size} needs {size * size + size} numbers, "
                                 f"has {len(nums)}")
        else:
            nums = [float(w) for w in words]
            size = n
            if len(nums) != n * n:
                raise ValueError(f"expected {n} x {n} = {n * n} numbers for the {n} parameters of 'order', "
                                 f"found {len(nums)}")
    except ValueError as exc:
        out.error("E141", f"{ast.display_path(path)}: {exc}", span)
        return None
    return [nums[i * size:(i + 1) * size] for i in range(size)]


def _is_number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True
