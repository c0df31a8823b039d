"""The language: every statement's signature, and binding of AST arguments to it.

One table (`CONTEXTS`) says which statements may appear where and what they
take. It drives argument binding and its diagnostics, `wiredsl fmt`, and the
reference in the README (`wiredsl reference`), so a statement is described once.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from wiredsl.diagnostics import NOT_INSTALLED, Collector, Span, did_you_mean
from wiredsl.effects import BUILTIN, REGISTRY
from wiredsl.language import ast
from wiredsl.language.units import KIND_NAMES, UNITS
from wiredsl.plugins import lookup

SCALARS = ("length", "angle", "image", "number", "fraction", "length|image", "number|length", "integer", "time")
MAX_MAGNITUDE = 1e9  # metres or pixels: squares and products of a few stay far from float overflow
BOARD_KINDS = ("chessboard", "charuco")
# OpenCV's predefined ArUco dictionaries (cv2.aruco.DICT_<NAME upper>)
ARUCO = tuple(f"DICT_{n}X{n}_{k}" for n in (4, 5, 6, 7) for k in (50, 100, 250, 1000)) + (
    "DICT_ARUCO_ORIGINAL", "DICT_APRILTAG_16h5", "DICT_APRILTAG_25h9", "DICT_APRILTAG_36h10", "DICT_APRILTAG_36h11")


@dataclass(frozen=True)
class Slot:
    """One value a statement takes. `kind` is a scalar kind, `vecN:kind`, or one of
    name, ref, refs, str, word, pts, matrix, names. `choices`: a word's words, or the words a scalar also takes."""

    kind: str
    label: str
    choices: tuple[str, ...] = ()


@dataclass(frozen=True)
class Clause:
    slots: tuple[Slot, ...]
    doc: str
    required: bool = False
    repeat: bool = False


@dataclass(frozen=True)
class Sig:
    keyword: str
    doc: str
    positional: tuple[Slot, ...] = ()
    clauses: dict[str, Clause] = field(default_factory=dict)
    block: str | None = None  # the context of the statements in its { block }
    block_required: bool = False
    example: str = ""


def S(kind: str, label: str, *choices: str) -> Slot:
    return Slot(kind, label, tuple(choices))


def C(doc: str, *slots: Slot, required: bool = False, repeat: bool = False) -> Clause:
    return Clause(tuple(slots), doc, required, repeat)


NAME = S("name", "name")
P3 = S("vec3:length", "point (x, y, z)")
P2 = S("vec2:length", "floor point (x, y)")
DIR = S("vec3:number", "direction (x, y, z)")

_ROTATE = {
    "rotate": C("rotation about a world axis, applied in order", S("word", "axis", "x", "y", "z"),
                S("angle", "angle"), repeat=True),
    "ypr": C("R = Rz(yaw) Ry(pitch) Rx(roll): yaw about z, then pitch about the turned y, then roll",
             S("vec3:angle", "(yaw, pitch, roll)")),
}

_TOP = [
    Sig("wiredsl", "format version of the file; must be 1", (S("integer", "version"),), example="wiredsl 1"),
    Sig("scene", "the scene's name (default: the file name; ignored in an included file)", (NAME,),
        example="scene lab"),
    Sig("units", "units of bare numbers in this file (default m, deg, px)",
        clauses={"length": C("length unit", S("word", "unit", "mm", "cm", "m", "in", "ft")),
                 "angle": C("angle unit", S("word", "unit", "deg", "rad"))},
        example="units length mm angle deg"),
    Sig("include", "read another file's statements (path relative to this file)", (S("str", "path"),),
        example='include "models/bin.wd"'),
    Sig("model", "a named wire-frame object", (NAME,), block="model", block_required=True,
        example="model bin { ... }"),
    Sig("place", "an instance of a model in the world",
        (S("ref", "model"),),
        {"as": C("the placement's name", NAME, required=True),
         "at": C("position of the model's origin", P3),
         **_ROTATE},
        example="place bin as bin1 at (2m, 1m, 0) rotate z 30deg"),
    Sig("board", "a calibration board as a model: its inner corners are corners, its squares' edges lines, its "
        "face a plane (model frame: x along a row, y down a column, z out of its back; the first inner corner at "
        "the origin, as OpenCV's object points)", (NAME, S("word", "kind", *BOARD_KINDS)),
        {"inner": C("chessboard: inner corners across and down (OpenCV's patternSize)",
                    S("vec2:integer", "(columns, rows)")),
         "squares": C("charuco: squares across and down (OpenCV's squaresX, squaresY)",
                      S("vec2:integer", "(columns, rows)")),
         "square": C("side of a square", S("length", "side"), required=True),
         "marker": C("charuco: side of a marker", S("length", "side")),
         "dictionary": C("charuco: OpenCV's ArUco dictionary (default DICT_4X4_50)", S("word", "dictionary", *ARUCO)),
         "margin": C("white border around the squares (default one square)", S("length", "margin"))},
        example="board target chessboard inner (9, 6) square 25mm"),
    Sig("camera", "a camera model C = F(f, ax, ay, ox, oy, k, R, T)", (NAME,),
        {"like": C("start from another camera's parameters", S("ref", "camera"))},
        block="camera", example="camera left { focal 6mm ... }  /  camera right like left { k 0.02 }"),
    Sig("rig", "the stereo rig on the robot and its calibration uncertainty", (NAME,), block="rig",
        block_required=True, example="rig head { ... }"),
    Sig("viewpoints", "the triangular mesh of view-points on the floor", (NAME,), block="viewpoints",
        block_required=True, example="viewpoints floor { grid from (0, 0) to (6m, 4m) spacing 1m }"),
    Sig("path", "the robot's poses: on the floor, or 6-DoF from a trajectory file", (NAME,), block="path",
        block_required=True,
        example="path run { straight from (1, 1) to (5, 1) step 0.5m }"),
    Sig("pipeline", "an ordered list of uncertainty stages", (NAME,),
        {"default": C("the pipeline a build runs without --pipeline")},
        block="pipeline", block_required=True, example="pipeline paper default { edge_loss ... }"),
    Sig("study", "a sensitivity study: a design over pipeline parameters, trials, measures", (NAME,),
        block="study", block_required=True, example="study shift { vary lateral_shift.range ... }"),
]

_MODEL = [
    Sig("line", "a 3D segment", (NAME,),
        {"from": C("start point", P3, required=True), "to": C("end point", P3, required=True)},
        example="line edge from (0, 0, 0) to (1m, 0, 0)"),
    Sig("polyline", "consecutive segments through points", (NAME,),
        {"through": C("the points, at least two", S("pts", "points"), required=True),
         "closed": C("join the last point to the first")},
        example="polyline top closed through (0, 0, 1) (1, 0, 1) (1, 1, 1)"),
    Sig("ellipse", "an ellipse or ellipse section (TINA's E record)", (NAME,),
        {"centre": C("centre", P3, required=True),
         "normal": C("normal of its plane", DIR, required=True),
         "axis": C("major-axis direction, perpendicular to the normal", DIR, required=True),
         "radii": C("semi-axes along `axis` and across it", S("vec2:length", "(a, b)"), required=True),
         "range": C("parameter range of a section (default full)", S("vec2:angle", "(t1, t2)"))},
        example="ellipse rim centre (0, 0, 0.6) normal (0, 0, 1) axis (1, 0, 0) radii (0.2, 0.2)"),
    Sig("silhouette", "occluding side lines of the surface between two ellipses", (NAME,),
        {"between": C("the two ellipses of this model", S("ref", "ellipse"), S("ref", "ellipse"), required=True)},
        example="silhouette side between rim base"),
    Sig("corner", "a 3D corner point", (NAME,),
        {"at": C("position", P3, required=True),
         "joins": C("the lines meeting there", S("refs", "lines"))},
        example="corner c1 at (0, 0, 1) joins top front"),
    Sig("face", "a planar polygon that occludes but is never emitted", (NAME,),
        {"through": C("the vertices, at least three, coplanar", S("pts", "vertices"), required=True)},
        example="face lid through (0, 0, 1) (1, 0, 1) (1, 1, 1) (0, 1, 1)"),
    Sig("mesh", "features read from a triangle mesh: crease edges as lines, rims as ellipses, cylinder and cone "
        "sides as silhouettes, corners, faces; its other triangles occlude",
        clauses={"read": C("the mesh file (OBJ, PLY, STL, glTF/GLB), relative to this file", S("str", "path"),
                           required=True),
                 "crease": C("edges whose triangles' normals differ by more than this are features (default 30deg)",
                             S("angle", "angle")),
                 "scale": C("the length of one unit of the file: 1in, 1mm, or a bare number of metres (default: "
                            "this file's length unit)", S("number|length", "scale")),
                 "units": C("the file's unit (mm, cm, m, in, ft): the same as scale 1<unit>",
                            S("word", "unit", "mm", "cm", "m", "in", "ft")),
                 "up": C("the file's up axis, turned to z (default z; OBJ and glTF are often y-up)",
                         S("word", "axis", "x", "y", "z")),
                 "origin": C("where the part's origin is: file (as the file has it, the default), centre (of its "
                             "bounding box) or base (the centre of the bottom of its bounding box)",
                             S("word", "origin", "file", "centre", "base")),
                 "shortest": C("lines, polylines and faces shorter than this are left out (default 0.2% of the "
                               "part's bounding-box diagonal; 0 keeps every one)", S("length", "length")),
                 "budget": C("at most this many lines and polylines, the longest and sharpest (ranked by length "
                             "x dihedral angle); auto (the default): 200 for a scan, every one for a CAD part "
                             "(told apart by the share of its edges between coplanar triangles)",
                             S("integer", "n", "auto"))},
        example='mesh read "crate.obj" crease 30deg units mm up y origin base'),
]

_CAMERA = [
    Sig("focal", "focal length: a length (with `pixel`) or directly in px", (S("length|image", "focal length"),),
        example="focal 6mm"),
    Sig("pixel", "pixel size on the sensor", (S("length", "pixel size"),), example="pixel 0.01mm"),
    Sig("aspect", "aspect scales (ax, ay)", (S("vec2:number", "(ax, ay)"),), example="aspect (1, 1.02)"),
    Sig("centre", "optical centre (ox, oy) in pixels (default: image centre)", (S("vec2:image", "(ox, oy)"),),
        example="centre (320px, 240px)"),
    Sig("size", "image width and height", (S("vec2:image", "(width, height)"),), example="size (640px, 480px)"),
    Sig("k", "TINA's radial coefficient: v = (1 - k r^2) w (so OpenCV's k1 = -k)", (S("number", "k"),),
        example="k 0.05"),
    Sig("k1", "OpenCV's first radial coefficient (= -k)", (S("number", "k1"),), example="k1 -0.05"),
    Sig("k2", "OpenCV's second radial coefficient", (S("number", "k2"),), example="k2 0.001"),
    Sig("p1", "OpenCV's first tangential coefficient", (S("number", "p1"),), example="p1 0"),
    Sig("p2", "OpenCV's second tangential coefficient", (S("number", "p2"),), example="p2 0"),
    Sig("k3", "third radial coefficient: OpenCV's k3 (r^6), or the fisheye's k3 (theta^6)", (S("number", "k3"),),
        example="k3 0.0001"),
    Sig("k4", "OpenCV's rational k4 (denominator's r^2), or the fisheye's k4 (theta^8)", (S("number", "k4"),),
        example="k4 0"),
    Sig("k5", "OpenCV's rational k5 (denominator's r^4)", (S("number", "k5"),), example="k5 0"),
    Sig("k6", "OpenCV's rational k6 (denominator's r^6)", (S("number", "k6"),), example="k6 0"),
    Sig("distortion", "the lens model: radtan (OpenCV's k1..k6, p1, p2; the default), equidistant "
        "(OpenCV's fisheye, Kannala-Brandt: theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8)), unified (Mei's "
        "unified model, Kalibr's omni: xi, then radtan k1, k2, p1, p2), eucm (extended unified: alpha, beta), "
        "ds (double sphere: xi, alpha) or fov (Devernay and Faugeras's FOV / ATAN model: w)",
        (S("word", "model", "radtan", "equidistant", "unified", "eucm", "ds", "fov"),),
        example="distortion equidistant"),
    Sig("xi", "unified: Mei's xi (>= 0); ds: the double sphere's xi (in (-1, 1])", (S("number", "xi"),),
        example="xi 0.9"),
    Sig("alpha", "eucm and ds: alpha, in [0, 1]", (S("number", "alpha"),), example="alpha 0.6"),
    Sig("beta", "eucm: beta (> 0)", (S("number", "beta"),), example="beta 1.1"),
    Sig("w", "fov: the FOV model's w, in (0, 180) deg", (S("angle", "w"),), example="w 53deg"),
    Sig("fov", "every lens model but radtan: the lens's full field of view; nothing farther than half of it from "
        "the optical axis is imaged (default: the model's own valid region; equidistant: where theta_d stops "
        "increasing, at most 360 deg)", (S("angle", "field of view"),), example="fov 190deg"),
    Sig("read", "take the camera's parameters from a calibration file (OpenCV, ROS, Kalibr, ORB-SLAM, camodocal / "
        "VINS or basalt); "
        "statements beside it override them", (S("str", "path"),),
        {"format": C("the file's format (default: recognised from its content)",
                     S("word", "format", "opencv", "ros", "kalibr", "camodocal", "basalt")),
         "entry": C("which camera of a file with several: first, second, third (OpenCV's M1/M2, Kalibr's and basalt's "
                    "cam0/cam1...) or Kalibr's camN", S("word", "entry", "first", "second", "third",
                                                          *(f"cam{i}" for i in range(10))))},
        example='read "calib/stereo.yaml" entry second'),
]

_MOUNT = {
    "at": C("position in the robot frame (x forward, y left, z up)", P3),
    "looking": C("viewing direction in the robot frame", DIR),
    "roll": C("rotation about the viewing direction", S("angle", "angle")),
    "relative": C("instead of at and looking: the pose relative to the other camera, read from a stereo "
                  "calibration file (OpenCV's R, T or Kalibr's T_cn_cnm1)", S("str", "path")),
}
_RIG = [
    Sig("left", "the left camera and its mount", (S("ref", "camera"),), _MOUNT,
        example="left cam_l at (0.1, 0.06, 1.2) looking (1, 0, -0.2)"),
    Sig("right", "the right camera and its mount", (S("ref", "camera"),), _MOUNT,
        example="right cam_r at (0.1, -0.06, 1.2) looking (1, 0, -0.2)"),
    Sig("calibration", "calibration uncertainty: information matrix (J^T J) or covariance",
        (S("word", "kind", "information", "covariance"),),
        {"order": C("the parameter of each row, e.g. [left.f, left.cx, right.tx]", S("names", "parameters")),
         "matrix": C("the matrix, inline", S("matrix", "rows")),
         "file": C("read the matrix from a file (plain rows, or TINA's covariance format)", S("str", "path")),
         "kalibr": C("a diagonal covariance from the standard deviations in Kalibr's results-cam.txt "
                     "(with order: only those parameters)", S("str", "path"))},
        example="calibration covariance order [left.f, right.f] matrix [[4, 0], [0, 4]]"),
]

_VIEWPOINTS = [
    Sig("grid", "view-points on a triangulated grid over a rectangle", (),
        {"from": C("one corner", P2, required=True), "to": C("the opposite corner", P2, required=True),
         "spacing": C("distance between neighbouring view-points", S("length", "spacing"), required=True)},
        example="grid from (0, 0) to (6m, 4m) spacing 1m"),
    Sig("vertex", "one view-point", (NAME,), {"at": C("position on the floor", P2, required=True)},
        example="vertex v1 at (1m, 2m)"),
    Sig("triangle", "a mesh triangle over three vertices", (S("ref", "vertex"), S("ref", "vertex"), S("ref", "vertex")),
        example="triangle v1 v2 v3"),
    Sig("visibility", "where visibility lists come from",
        clauses={"auto": C("computed by the engine"), "authored": C("from `visible` statements"),
                 "file": C("from a view-dependency file", S("str", "path"))},
        example="visibility auto"),
    Sig("visible", "the features visible from a view-point", (S("ref", "vertex"), S("refs", "features")),
        example="visible v1 bin1.* table1.top"),
]

_PATH = [
    Sig("pose", "one robot pose", (P2,), {"heading": C("heading from the x axis", S("angle", "heading"))},
        example="pose (1m, 2m) heading 90deg"),
    Sig("straight", "poses along a straight run, facing along it", (),
        {"from": C("start", P2, required=True), "to": C("end", P2, required=True),
         "step": C("distance between poses", S("length", "step"), required=True)},
        example="straight from (1, 1) to (5, 1) step 0.5m"),
    Sig("read", "6-DoF poses from a trajectory file (TUM, EuRoC ground truth, KITTI poses, CSV with a header), "
        "resampled by time", (S("str", "path"),),
        {"format": C("the file's format (default: recognised from its content)",
                     S("word", "format", "tum", "euroc", "kitti", "csv")),
         "every": C("one pose every this long: positions linear, rotations slerp (default: the file's poses)",
                    S("time", "period")),
         "from": C("start of the window, from the file's first pose", S("time", "start")),
         "to": C("end of the window, from the file's first pose", S("time", "end")),
         "limit": C("at most this many poses (the first)", S("integer", "n")),
         "rate": C("poses a second of a file without timestamps (KITTI)", S("number", "rate (Hz)")),
         "times": C("a file of timestamps, one a line, for a file without them (KITTI's times.txt)",
                    S("str", "path"))},
        example='read "run.tum" format tum every 0.1s from 2s to 10s'),
    Sig("body", "the frame the file's poses are of, on the robot (default: the robot frame)", (),
        {"at": C("its origin in the robot frame (x forward, y left, z up)", P3), **_ROTATE,
         "camera": C("the file's poses are this rig camera's, OpenCV axes (TUM RGB-D, KITTI)",
                     S("word", "side", "left", "right")),
         "kalibr": C("the file's poses are the IMU's (EuRoC): the left camera is cam0 at T_cam_imu of this "
                     "Kalibr camchain", S("str", "path"))},
        example="body camera left"),
    Sig("world", "the file's world frame in the scene (default: the scene's; the scene's z is up)", (),
        {"at": C("its origin in the scene", P3), **_ROTATE},
        example="world at (1m, 2m, 0) rotate x -90deg rotate z -90deg"),
]


_STUDY = [
    Sig("pipeline", "the pipeline the study starts from (default: the scene's default)", (S("ref", "pipeline"),),
        example="pipeline paper"),
    Sig("vary", "a parameter to vary, `stage.param` or `camera.<name>.<param>`: a list of values, or a range",
        (S("ref", "stage.param"),),
        {"values": C("the values, in the parameter's units", S("rawlist", "[values]")),
         "from": C("range start", S("raw", "value")),
         "to": C("range end", S("raw", "value")),
         "steps": C("grid: evenly spaced values from..to, ends included", S("integer", "n"))},
        example="vary lateral_shift.range from 0 to 6px steps 4"),
    Sig("design", "grid (every combination), or lhs / sobol: space-filling over the ranges",
        (S("word", "kind", "grid", "lhs", "sobol"),),
        {"points": C("lhs/sobol: base samples n; the design runs n (d + 2) points", S("integer", "n")),
         "seed": C("seed of the space-filling sampler (default 0)", S("integer", "seed"))},
        example="design sobol points 16 seed 7"),
    Sig("trials", "Monte-Carlo trials per design point", (S("integer", "n"),), example="trials 64"),
    Sig("poses", "the poses of the path to run (default: all)", (S("ints", "[pose indices]"),),
        example="poses [0, 3, 6]"),
    Sig("seed", "seed of every trial's random streams (with the point's index; default 0)",
        (S("integer", "seed"),), example="seed 1"),
    Sig("measure", "a measure to compute on every trial, with its parameters",
        (S("ref", "measure"), S("rest", "parameter value ...")), example="measure pgh limit 80px"),
]


def _effect_sig(name: str) -> Sig:
    effect = REGISTRY[name]
    clauses = {
        key: C(f.description or "", S(f.json_schema_extra["kind"], key))
        for key, f in effect.Params.model_fields.items()
    }
    return Sig(name, (effect.doc or "").strip(), clauses=clauses)


class _StageSigs(Mapping):
    """A pipeline block's statements: one a stage the effects registry knows (built-in, then installed plug-ins,
    looked up only for a name not built in), each signature made on first use from the effect's Params."""

    def __init__(self) -> None:
        self._sigs: dict[str, Sig] = {}

    def __getitem__(self, name: str) -> Sig:
        if name in self._sigs:
            return self._sigs[name]
        effect, _ = lookup(REGISTRY, name) if isinstance(name, str) else (None, None)
        if effect is None:
            raise KeyError(name)
        sig = _effect_sig(name)
        if name in BUILTIN:  # a plug-in's is made again: packages come and go (plugins.rescan)
            self._sigs[name] = sig
        return sig

    def __iter__(self):
        return (name for name in REGISTRY if lookup(REGISTRY, name)[0] is not None)

    def __len__(self) -> int:
        return sum(1 for _ in self)

    def problem(self, name: str) -> str | None:
        """Why an installed plug-in of this name cannot be used (naming its package), else None."""
        return lookup(REGISTRY, name)[1]


CONTEXTS: dict[str, Mapping[str, Sig]] = {
    "top": {s.keyword: s for s in _TOP},
    "model": {s.keyword: s for s in _MODEL},
    "camera": {s.keyword: s for s in _CAMERA},
    "rig": {s.keyword: s for s in _RIG},
    "viewpoints": {s.keyword: s for s in _VIEWPOINTS},
    "path": {s.keyword: s for s in _PATH},
    "pipeline": _StageSigs(),
    "study": {s.keyword: s for s in _STUDY},
}


def takes(sig: Sig) -> str:
    """What a statement takes, as the reference writes it: `<model> as <name> [at <point>]...`."""
    out = [f"<{s.label}>" for s in sig.positional]
    for key, clause in sig.clauses.items():
        piece = " ".join([key, *(f"<{s.label}>" for s in clause.slots)])
        out.append(piece if clause.required else f"[{piece}]" + ("..." if clause.repeat else ""))
    if sig.block:
        out.append("{ ... }" if sig.block_required else "[{ ... }]")
    return " ".join(out)


# --------------------------------------------------------------------------- binding

@dataclass(frozen=True, slots=True)
class Value:
    """A bound argument: its converted value and where it was written."""

    value: Any
    span: Span


@dataclass
class Bound:
    """A statement matched against its signature."""

    stmt: ast.Statement
    sig: Sig
    positional: list[Value]
    clauses: dict[str, list[list[Value]]]  # key -> occurrences -> slot values
    clause_spans: dict[str, list[Span]]
    ok: bool = True

    def has(self, key: str) -> bool:
        return key in self.clauses

    def get(self, key: str, default: Any = None) -> Any:
        """The value of a single-slot clause (first occurrence), or default."""
        occ = self.clauses.get(key)
        return occ[0][0].value if occ and occ[0] else default

    def span(self, key: str) -> Span:
        occ = self.clauses.get(key)
        if occ and occ[0]:
            return occ[0][0].span
        spans = self.clause_spans.get(key)
        return spans[0] if spans else self.stmt.span

    def pos(self, i: int) -> Any:
        return self.positional[i].value

    @property
    def name(self) -> str:
        return self.positional[0].value

    @property
    def name_span(self) -> Span:
        return self.positional[0].span


def bind(stmt: ast.Statement, context: str, units: dict[str, str], out: Collector) -> Bound | None:
    """Match a statement's arguments to its signature in `context`; None if unknown."""
    sigs = CONTEXTS[context]
    sig = sigs.get(stmt.keyword)
    problem = sigs.problem(stmt.keyword) if sig is None and isinstance(sigs, _StageSigs) else None
    if problem is not None:  # an installed plug-in of that name that cannot be used
        out.error("E180", problem, stmt.keyword_span, "see 'wiredsl plugins'")
        return None
    if sig is None:
        where = "at the top level" if context == "top" else f"in a {context} block"
        hint = (did_you_mean(stmt.keyword, sigs) or _elsewhere(stmt.keyword, context)
                or (NOT_INSTALLED if isinstance(sigs, _StageSigs) else None))
        out.error("E100", f"unknown statement '{stmt.keyword}' {where}", stmt.keyword_span, hint)
        return None
    b = Bound(stmt, sig, [], {}, {})
    n_before = out.n_errors
    args = list(stmt.args)
    i = 0
    for slot in sig.positional:
        if slot.kind == "rest":  # everything left, converted later by whoever knows its kinds
            b.positional.append(Value(args[i:], _join(args[i].span, args[-1].span) if i < len(args) else stmt.span))
            i = len(args)
            continue
        if i >= len(args):
            out.error("E102", f"'{sig.keyword}' needs {_a(slot.label)}", stmt.span, f"e.g. {sig.example}")
            b.ok = False
            return b
        val, i = _take(slot, args, i, sig, units, out)
        b.positional.append(val)
    while i < len(args):
        arg = args[i]
        key = arg.name if isinstance(arg, ast.Ref) and len(arg.parts) == 1 else None
        if key not in sig.clauses:
            if key in CONTEXTS[context] and context != "top":
                out.error("E101", f"'{key}' starts another statement: a block holds one statement a line",
                          arg.span, f"put '{key} ...' on a line of its own")
            elif sig.clauses:
                hint = did_you_mean(key, sig.clauses) if key else None
                hint = hint or "expected one of: " + ", ".join(sig.clauses)
                what = f"unknown word '{key}'" if key else "unexpected value"
                out.error("E101", f"{what} in '{sig.keyword}'", arg.span, hint)
            else:
                out.error("E101", f"'{sig.keyword}' takes no more arguments", arg.span)
            b.ok = False
            return b
        clause = sig.clauses[key]
        if key in b.clauses and not clause.repeat:
            out.error("E103", f"'{key}' given twice in '{sig.keyword}'", arg.span)
        i += 1
        values = []
        for slot in clause.slots:
            if i >= len(args) or _is_key(args[i], sig, slot):
                out.error("E102", f"'{key}' needs {_a(slot.label)}", arg.span, f"e.g. {sig.example}")
                b.ok = False
                return b
            val, i = _take(slot, args, i, sig, units, out)
            values.append(val)
        b.clauses.setdefault(key, []).append(values)
        b.clause_spans.setdefault(key, []).append(arg.span)
    for key, clause in sig.clauses.items():
        if clause.required and key not in b.clauses:
            out.error("E102", f"'{sig.keyword}' needs '{key}' ({clause.doc})", stmt.span, f"e.g. {sig.example}")
    if sig.block is None and stmt.block is not None:
        out.error("E101", f"'{sig.keyword}' takes no {{ block }}", stmt.span)
    if sig.block_required and stmt.block is None:
        out.error("E102", f"'{sig.keyword}' needs a {{ block }}", stmt.span, f"e.g. {sig.example}")
    b.ok = out.n_errors == n_before
    return b


def _elsewhere(keyword: str, context: str) -> str | None:
    for ctx, sigs in CONTEXTS.items():
        if ctx != context and keyword in sigs:
            return f"'{keyword}' belongs " + ("at the top level" if ctx == "top" else f"in a {ctx} block")
    return None


def _a(label: str) -> str:
    """'a unit', 'an entry', '(x, y)': the label with its article, as English says it."""
    if label.startswith(("(", "[")):
        return label
    return ("an " if label[0] in "aeiou" and not label.startswith(("uni", "use", "one")) else "a ") + label


def _is_key(arg: ast.Arg, sig: Sig, slot: Slot) -> bool:
    """A bare word naming a clause ends a run of values (refs cannot use clause words)."""
    return isinstance(arg, ast.Ref) and len(arg.parts) == 1 and arg.name in sig.clauses and slot.kind not in (
        "ref", "name", "word")


def _take(slot: Slot, args: list, i: int, sig: Sig, units: dict[str, str], out: Collector) -> tuple[Value, int]:
    """Convert args[i] (or a run from i, for pts/refs) to `slot`; report what does not fit."""
    kind = slot.kind
    if kind in ("pts", "refs"):
        items = []
        while i < len(args) and not _is_key(args[i], sig, slot):
            items.append(_convert(Slot("vec3:length" if kind == "pts" else "ref", slot.label), args[i], units, out))
            i += 1
        span = _join(items[0].span, items[-1].span) if items else args[i - 1].span
        return Value(items, span), i
    return _convert(slot, args[i], units, out), i + 1


def _join(a: Span, b: Span) -> Span:
    return Span(a.file, a.line, a.col, b.end_line, b.end_col)


def _convert(slot: Slot, arg: ast.Arg, units: dict[str, str], out: Collector) -> Value:
    kind = slot.kind
    bad = Value(None, arg.span)
    if kind in SCALARS:
        if slot.choices and isinstance(arg, ast.Ref) and arg.name in slot.choices:  # a word it also takes (auto)
            return Value(arg.name, arg.span)
        if not isinstance(arg, ast.Number):
            out.error("E106", f"expected {_a(slot.label)} ({KIND_NAMES.get(kind, kind)}), got {_show(arg)}", arg.span)
            return bad
        value = quantity(arg, kind, units, out)
        if "|" in kind:  # say which alternative was written, e.g. focal 6mm or 800px, and whether bare
            value = (value, UNITS[arg.unit][0] if arg.unit in UNITS else kind.split("|")[0], arg.unit)
        return Value(value, arg.span)
    if kind.startswith("vec"):
        n, elem = int(kind[3]), kind.split(":")[1]
        if not isinstance(arg, ast.Tuple) or len(arg.items) != n:
            got = f"{len(arg.items)} values" if isinstance(arg, ast.Tuple) else _show(arg)
            out.error("E106", f"expected {slot.label}: {n} values in ( ), got {got}", arg.span)
            return bad
        vals = []
        for item in arg.items:
            if not isinstance(item, ast.Number):
                out.error("E106", f"expected {KIND_NAMES[elem]}, got {_show(item)}", item.span)
                return bad
            vals.append(quantity(item, elem, units, out))
        return Value(tuple(vals), arg.span)
    if kind in ("name", "ref", "word"):
        if not isinstance(arg, ast.Ref) or (kind != "ref" and len(arg.parts) != 1) or (
                kind == "name" and arg.parts == ("*",)):
            out.error("E106", f"expected {_a(slot.label)}, got {_show(arg)}", arg.span)
            return bad
        if kind == "word" and arg.name not in slot.choices:
            hint = did_you_mean(arg.name, slot.choices) or "one of: " + ", ".join(slot.choices)
            out.error("E106", f"'{arg.name}' is not {_a(slot.label)}", arg.span, hint)
            return bad
        return Value(arg.name, arg.span)
    if kind == "str":
        if not isinstance(arg, ast.String):
            out.error("E106", f"expected {_a(slot.label)} in double quotes, got {_show(arg)}", arg.span)
            return bad
        if "\0" in arg.value:  # the operating system would refuse it later, without a location
            out.error("E010", "a file path cannot contain a NUL byte", arg.span)
            return bad
        return Value(arg.value, arg.span)
    if kind == "raw":  # converted by the compiler, which knows the kind (e.g. a stage parameter's)
        return Value(arg, arg.span)
    if kind == "rawlist":
        if not isinstance(arg, ast.List):
            out.error("E106", f"expected a list in [ ], got {_show(arg)}", arg.span)
            return bad
        return Value(list(arg.items), arg.span)
    if kind == "ints":
        if not isinstance(arg, ast.List):
            out.error("E106", f"expected a list of whole numbers in [ ], got {_show(arg)}", arg.span)
            return bad
        vals = []
        for x in arg.items:
            if not isinstance(x, ast.Number) or x.unit is not None or not x.value.is_integer():
                out.error("E106", f"expected a whole number, got {_show(x)}", x.span)
                return bad
            vals.append(Value(int(x.value), x.span))
        return Value(vals, arg.span)
    if kind == "names":
        if not isinstance(arg, ast.List) or not all(isinstance(x, ast.Ref) for x in arg.items):
            out.error("E106", f"expected a list of names in [ ], got {_show(arg)}", arg.span)
            return bad
        return Value([Value(x.name, x.span) for x in arg.items], arg.span)
    if kind == "matrix":
        rows = arg.items if isinstance(arg, ast.List) else None
        if rows is None or not all(isinstance(r, ast.List) for r in rows):
            out.error("E106", f"expected a matrix as [[...], [...]], got {_show(arg)}", arg.span)
            return bad
        matrix = []
        for row in rows:
            vals = []
            for x in row.items:
                if not isinstance(x, ast.Number):
                    out.error("E106", f"expected a number, got {_show(x)}", x.span)
                    return bad
                vals.append(quantity(x, "number", units, out))
            matrix.append(vals)
        return Value(matrix, arg.span)
    raise AssertionError(f"signature slot kind {kind!r} has no converter")


def quantity(num: ast.Number, kind: str, units: dict[str, str], out: Collector) -> float:
    """A number in SI for the expected kind; a unit of the wrong kind, or a value no float holds, is reported."""
    if not math.isfinite(num.value):
        out.error("E109", f"number '{num.text}' is too large to represent", num.span,
                  f"numbers must be finite, below {sys.float_info.max:.3g} in size")
        return 0.0
    if kind == "integer":
        if num.unit is not None or not num.value.is_integer():
            out.error("E106", f"expected a whole number, got '{num.text}'", num.span)
        return num.value
    if num.unit is None:
        if kind.split("|")[0] in ("number", "fraction"):
            return num.value
        unit = units[kind.split("|")[0]]
        if kind == "angle" and unit == "deg" and 0 < abs(num.value) < 1:
            out.warning("W111", f"'{num.text}' is {num.text} degrees (a bare angle is in degrees)", num.span,
                        f"{num.text} is degrees; did you mean {num.text}rad?")
    else:
        unit = num.unit
        if unit not in UNITS:
            hint = did_you_mean(unit, UNITS) or "units are " + ", ".join(UNITS)
            out.error("E108", f"unknown unit '{unit}' in '{num.text}'", num.span, hint)
            return num.value
    unit_kind, factor = UNITS[unit]
    allowed = kind.split("|")
    if unit_kind not in allowed and not (unit_kind == "fraction" and "number" in allowed):
        expected = " or ".join(KIND_NAMES[k] for k in allowed)
        out.error("E107", f"expected {expected}, got {KIND_NAMES[unit_kind]} '{num.text}'", num.span)
        return num.value
    value = num.value * factor
    if unit_kind in ("length", "image") and abs(value) > MAX_MAGNITUDE:
        what = "m" if unit_kind == "length" else "px"
        out.error("E110", f"'{num.text}' is beyond the limit of {MAX_MAGNITUDE:g} {what}", num.span,
                  "lengths and image distances are bounded so that products of them stay finite")
        return 0.0
    return value


def _show(arg: ast.Arg) -> str:
    if isinstance(arg, ast.Number):
        return f"'{arg.text}'"
    if isinstance(arg, ast.String):
        return f'"{arg.value}"'
    if isinstance(arg, ast.Ref):
        return f"'{arg.name}'"
    if isinstance(arg, ast.Tuple):
        return f"a tuple of {len(arg.items)}"
    return f"a list of {len(arg.items)}"

