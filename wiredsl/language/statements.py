"""The language: every statement's signature.

One table (`CONTEXTS`) says which statements may appear where and what they
take. It drives argument binding and its diagnostics (`bind`), the parser's
recovery from unclosed brackets, `wiredsl fmt`, and the reference
(`wiredsl reference`), so a statement is described once.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from wiredsl.effects import BUILTIN, REGISTRY
from wiredsl.plugins import lookup

SCALARS = ("length", "angle", "image", "number", "fraction", "length|image", "number|length", "integer", "time",
           "speed")
MAX_MAGNITUDE = 1e9  # metres or pixels: squares and products of a few stay far from float overflow
BOARD_KINDS = ("chessboard", "charuco", "circles", "acircles")
# OpenCV's predefined ArUco dictionaries (cv2.aruco.DICT_<NAME upper>)
ARUCO = tuple(f"DICT_{n}X{n}_{k}" for n in (4, 5, 6, 7) for k in (50, 100, 250, 1000)) + (
    "DICT_ARUCO_ORIGINAL", "DICT_APRILTAG_16h5", "DICT_APRILTAG_25h9", "DICT_APRILTAG_36h10", "DICT_APRILTAG_36h11")
# how many markers each holds (cv2.aruco.getPredefinedDictionary(...).bytesList.shape[0]; a name need not end in it)
ARUCO_MARKERS = {**{f"DICT_{n}X{n}_{k}": k for n in (4, 5, 6, 7) for k in (50, 100, 250, 1000)},
                 "DICT_ARUCO_ORIGINAL": 1024, "DICT_APRILTAG_16h5": 30, "DICT_APRILTAG_25h9": 35,
                 "DICT_APRILTAG_36h10": 2320, "DICT_APRILTAG_36h11": 587}


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
    Sig("board", "a calibration board as a model: a chessboard's or ChArUco board's inner corners are corners, "
        "its squares' edges lines; a circle grid's dots (circles: symmetric, acircles: asymmetric) are ellipses; "
        "its face a plane (model frame: x along a row, y down a column, z out of its back; the first inner corner "
        "or dot centre at the origin, as OpenCV's object points)", (NAME, S("word", "kind", *BOARD_KINDS)),
        {"inner": C("chessboard: inner corners across and down (OpenCV's patternSize)",
                    S("vec2:integer", "(columns, rows)")),
         "squares": C("charuco: squares across and down (OpenCV's squaresX, squaresY)",
                      S("vec2:integer", "(columns, rows)")),
         "dots": C("circles, acircles: dots in a row and rows (OpenCV's patternSize)",
                   S("vec2:integer", "(columns, rows)")),
         "square": C("chessboard, charuco: side of a square", S("length", "side")),
         "spacing": C("circles: the dots' pitch; acircles: the rows' spacing (OpenCV's squareSize: dots in a row "
                      "are 2 spacings apart)", S("length", "spacing")),
         "diameter": C("circles, acircles: a dot's diameter", S("length", "diameter")),
         "marker": C("charuco: side of a marker", S("length", "side")),
         "dictionary": C("charuco: OpenCV's ArUco dictionary (default DICT_4X4_50)", S("word", "dictionary", *ARUCO)),
         "margin": C("white border around the squares, or beyond the outermost dots' edges (default one square "
                     "or spacing)", S("length", "margin"))},
        example="board target chessboard inner (9, 6) square 25mm  /  board grid acircles dots (4, 5) spacing 30mm "
                "diameter 20mm"),
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
        {"default": C("the pipeline a build runs without --pipeline"),
         "like": C("start from another pipeline's stages (one declared before, or the built-in paper): a stage "
                   "in the block overrides the parameters it gives, a new one joins in data-flow order",
                   S("ref", "pipeline")),
         "without": C("with like: leave these stages out", S("names", "stages"))},
        block="pipeline", block_required=False, example="pipeline paper default { edge_loss ... }  /  "
        "pipeline mine like paper without [corner_mismatch] { lateral_shift range 2px }"),
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
    Sig("readout", "rolling shutter: the time from the first image row's exposure to the last's, rows top to "
        "bottom; each feature point is imaged from the camera's pose at its row's time (default 0: a global "
        "shutter, every row at the pose's time)", (S("time", "readout time"),), example="readout 30ms"),
    Sig("exposure", "motion blur: the time the shutter is open, centred on the row's (or the pose's) time; "
        "`wiredsl render` averages the image over it, and the motion_blur stage disturbs the features by the image "
        "motion over it (default 0: an instant)", (S("time", "exposure time"),), example="exposure 8ms"),
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
    "units": C("with relative: the unit of the file's translation T (OpenCV's is the board's square size's; a "
               "baseline over 5 m read without it is an error)", S("word", "unit", "m", "cm", "mm")),
}
_RIG = [
    Sig("left", "the left camera and its mount", (S("ref", "camera"),), _MOUNT,
        example="left cam_l at (0.1, 0.06, 1.2) looking (1, 0, -0.2)"),
    Sig("right", "the right camera and its mount", (S("ref", "camera"),), _MOUNT,
        example="right cam_r at (0.1, -0.06, 1.2) looking (1, 0, -0.2)"),
    Sig("sync", "stereo synchronisation: the right camera's exposure time minus the left's; each camera images "
        "the world from the robot's pose at its own time (default 0: both at the pose's time)",
        (S("time", "offset"),),
        {"jitter": C("the standard deviation of the offset: each trial and pose draws the right camera's offset "
                     "from a normal about the declared one (the ideal view keeps the declared offset)",
                     S("time", "sigma"))},
        example="sync 10ms jitter 2ms"),
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
    Sig("speed", "the robot's speed along the written poses: each pose's time is its distance along the path "
        "over the speed (default: the robot stands at each pose)", (S("speed", "speed"),), example="speed 0.5m/s"),
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
    Sig("seed", "seed of every trial's random streams (and the point's index under `draws independent`; "
        "default 0)", (S("integer", "seed"),), example="seed 1"),
    Sig("draws", "common: every design point draws the same disturbances (keyed by trial, not by point), so "
        "differences between points and Sobol' indices lose the noise of independent draws; independent: each "
        "point draws its own (default: common)", (S("word", "mode", "common", "independent"),),
        example="draws common"),
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


class StageSigs(Mapping):
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
    "pipeline": StageSigs(),
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


def reference() -> str:
    """The language reference as a Markdown table: every statement of every context, what it takes, what it means
    (`wiredsl reference`, and the site's language page)."""
    out = ["| where | statement | takes | meaning |", "|---|---|---|---|"]
    for ctx, sigs in CONTEXTS.items():
        for sig in sigs.values():
            where = "top level" if ctx == "top" else f"`{ctx}` block"
            text = takes(sig).replace("|", "\\|")
            out.append(f"| {where} | `{sig.keyword}` | `{text}` | {sig.doc.splitlines()[0]} |")
    return "\n".join(out)
