"""The compiled scene (pydantic): what `compile` produces, in SI units, fully checked."""

from __future__ import annotations

import math
import operator
from types import UnionType
from typing import Any, Literal, TypeVar, Union, get_args, get_origin

from pydantic import BaseModel, ConfigDict, Field, model_serializer

SCHEMA_VERSION = "1"

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]
Mat3 = tuple[Vec3, Vec3, Vec3]

# Parameters of one camera that a calibration matrix may name, as `left.<p>` or `right.<p>`.
CALIBRATION_PARAMETERS = {
    "f": "focal length in pixels (f / pixel)",
    "ax": "aspect scale x",
    "ay": "aspect scale y",
    "cx": "optical centre x (px)",
    "cy": "optical centre y (px)",
    "k": "TINA radial coefficient",
    "k2": "second radial coefficient",
    "p1": "first tangential coefficient",
    "p2": "second tangential coefficient",
    "k3": "third radial coefficient (radtan: OpenCV's k3; equidistant: k3 of theta^6)",
    "k4": "fourth coefficient (radtan: OpenCV's rational k4; equidistant: k4 of theta^8)",
    "k5": "OpenCV's rational k5",
    "k6": "OpenCV's rational k6",
    "xi": "unified and double-sphere models: xi",
    "alpha": "extended unified and double-sphere models: alpha",
    "beta": "extended unified model: beta",
    "w": "FOV (ATAN) model: w (rad)",
    "tx": "mount translation along camera x (m)",
    "ty": "mount translation along camera y (m)",
    "tz": "mount translation along camera z (m)",
    "rx": "mount rotation about camera x (rad)",
    "ry": "mount rotation about camera y (rad)",
    "rz": "mount rotation about camera z (rad)",
}


class Node(BaseModel):
    # allow_inf_nan=False: a non-finite number is refused at construction, so no dump or JSON can carry one
    # ser_json_inf_nan: a non-finite number that got in anyway stays one in a JSON-mode dump (not null, as it would
    # through a model serializer such as Camera's), so that the writers refuse it by name
    # defer_build: a model's validator and serializer are built when first used, not on import: the compiler makes
    # most of a scene's nodes from values it has checked (`trusted`), and a build never validates them
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False, ser_json_inf_nan="constants",
                              defer_build=True)


N = TypeVar("N", bound=BaseModel)
CHECK_TRUSTED = False  # the test suite sets it (tests/conftest.py): `trusted` then validates too, and compares


def trusted(cls: type[N], **values) -> N:
    """A model of values the compiler has checked, each of its field's type already (floats as float, vectors as
    tuples of floats, lists, nested models): made without validation (`model_construct`), so that compiling
    builds no validator for it. Under CHECK_TRUSTED the same values also go through validation, and the two
    models must be equal, type for type and bit for bit (`same_nodes`)."""
    made = cls.model_construct(**values)
    if CHECK_TRUSTED:
        checked = cls(**values)
        problem = same_nodes(made, checked)
        if problem is not None:
            raise AssertionError(f"trusted {cls.__name__}: {problem}")
    return made


_BOUNDS = {"Ge": ("ge", operator.ge), "Gt": ("gt", operator.gt), "Le": ("le", operator.le), "Lt": ("lt", operator.lt)}


def plainly_valid(model: type[BaseModel], values: dict) -> bool:
    """Whether validating `values` with `model` would pass and change nothing: every key one of its fields, every
    value of its field's type exactly (a finite float for `float`, not an int that validation would convert; an int
    for `int`, a bool for `bool`, a str for `str` or one of a Literal's strings; None where the field allows it; a
    list or a str-keyed dict of such values; an instance of a model field's own class; anything for `Any`),
    within the field's annotated_types bounds (Ge, Gt, Le, Lt), and no validator of the model's own. Anything else
    is left to validation and its messages."""
    decorators = model.__pydantic_decorators__
    after = getattr(model, "plain_after", None)  # a model validator's check of plain values, without a model
    if decorators.validators or decorators.field_validators or decorators.root_validators \
            or (decorators.model_validators and after is None):
        return False
    fields = model.model_fields
    for key, value in values.items():
        f = fields.get(key)
        if f is None or not _plain(f.annotation, value):
            return False
        if value is not None:
            for c in f.metadata:
                bound = _BOUNDS.get(type(c).__name__)
                if bound is None or type(c).__module__ != "annotated_types" \
                        or not bound[1](value, getattr(c, bound[0])):
                    return False
    if after is not None:
        try:
            after({**{k: f.default for k, f in fields.items()}, **values})
        except ValueError:
            return False  # left to validation and its message
    return True


def _plain(annotation, value) -> bool:
    """Whether `value` is exactly of a plain `annotation` (see plainly_valid)."""
    if annotation is float:
        return type(value) is float and math.isfinite(value)
    if annotation in (int, bool, str):
        return type(value) is annotation
    origin, args = get_origin(annotation), get_args(annotation)
    if origin is Literal:
        return type(value) is str and all(type(a) is str for a in args) and value in args
    if origin in (Union, UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        return value is None or (len(rest) == 1 and _plain(rest[0], value))
    if origin is list:
        return type(value) is list and all(_plain(args[0], v) for v in value)
    if origin is dict:
        return type(value) is dict and args[0] is str and all(type(k) is str and _plain(args[1], v)
                                                              for k, v in value.items())
    if annotation is Any:  # validation takes anything as it is
        return True
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):  # an instance is taken as it is
        return type(value) is annotation
    return False


def checked(cls: type[N], **values) -> N:
    """`cls(**values)`, made without validation (`trusted`) when the values are plainly valid (`plainly_valid`):
    a model's validator costs its first use 0.5-1 ms, and the first validator of a process pydantic's plug-in
    loader (some 9 ms: it imports importlib.metadata and scans the installed packages' entry points)."""
    return trusted(cls, **values) if plainly_valid(cls, values) else cls(**values)


_NOT_PLAIN = object()


def plain_dump(node: BaseModel) -> dict | None:
    """`node`'s dump made from its fields (the same in python and json mode: see `dumped`), or None where it is
    not plain."""
    out = _plain_dump(node)
    return None if out is _NOT_PLAIN else out


def dumped(node: BaseModel) -> dict:
    """`node.model_dump(mode="json")`, made from its fields where that gives the same (`_plain_dump`: every value
    None, a bool, int, str or finite float, a list, tuple or str-keyed dict of them, or a model of them, whose only
    serializers are `omitted_when_none` and `omitted_when_default`), so that dumping builds no serializer: pydantic
    builds a model's validator with it, and the first validator of a process costs pydantic's plug-in loader (some
    13 ms: it imports importlib.metadata and scans the installed packages' entry points). Under CHECK_TRUSTED the
    model's own dump is made too, and the two must be equal, type for type and bit for bit."""
    out = _plain_dump(node)
    if out is _NOT_PLAIN:
        return node.model_dump(mode="json")
    if CHECK_TRUSTED:
        problem = same_nodes(out, node.model_dump(mode="json"))
        if problem is not None:
            raise AssertionError(f"dumped {type(node).__name__}: {problem}")
    return out


def _plain_dump(v):
    t = type(v)
    if v is None or t in (bool, int, str) or (t is float and math.isfinite(v)):
        return v
    if t in (list, tuple):
        out = [_plain_dump(x) for x in v]
        return _NOT_PLAIN if any(x is _NOT_PLAIN for x in out) else out
    if t is dict:
        out = {k: _plain_dump(x) for k, x in v.items()}
        return _NOT_PLAIN if any(type(k) is not str or x is _NOT_PLAIN for k, x in out.items()) else out
    if not isinstance(v, BaseModel):
        return _NOT_PLAIN
    decorators = t.__pydantic_decorators__
    if decorators.field_serializers or t.model_computed_fields or v.__pydantic_extra__ \
            or t.model_config.get("serialize_by_alias"):
        return _NOT_PLAIN
    omitted = {}
    for s in decorators.model_serializers.values():
        if not hasattr(s.func, "omitted"):
            return _NOT_PLAIN
        omitted.update(s.func.omitted)
    out = {}
    for name, f in t.model_fields.items():
        if f.exclude or f.serialization_alias is not None or (f.alias is not None and f.alias != name):
            return _NOT_PLAIN
        out[name] = x = _plain_dump(getattr(v, name))
        if x is _NOT_PLAIN:
            return x
    for name, default in omitted.items():
        value = getattr(v, name)
        if value is None if default is None else value == default:
            out.pop(name, None)
    return out


def same_nodes(a, b, where: str = "") -> str | None:
    """Where two values (models, containers, numbers) differ in type or value (floats bit for bit), or None."""
    import struct

    if type(a) is not type(b):
        return f"{where or 'value'}: {type(a).__name__} against {type(b).__name__} ({a!r}, {b!r})"
    if isinstance(a, BaseModel):
        if a.model_fields_set != b.model_fields_set:
            return f"{where}: fields set {sorted(a.model_fields_set)} against {sorted(b.model_fields_set)}"
        return next((p for name in type(a).model_fields
                     if (p := same_nodes(getattr(a, name), getattr(b, name), f"{where}.{name}")) is not None), None)
    if isinstance(a, (list, tuple)):
        if len(a) != len(b):
            return f"{where}: {len(a)} items against {len(b)}"
        return next((p for i, (x, y) in enumerate(zip(a, b, strict=True))
                     if (p := same_nodes(x, y, f"{where}[{i}]")) is not None), None)
    if isinstance(a, dict):
        if list(a) != list(b):
            return f"{where}: keys {list(a)} against {list(b)}"
        return next((p for k in a if (p := same_nodes(a[k], b[k], f"{where}[{k!r}]")) is not None), None)
    if isinstance(a, float):
        return None if struct.pack("<d", a) == struct.pack("<d", b) else f"{where}: {a!r} against {b!r}"
    return None if a == b else f"{where}: {a!r} against {b!r}"


def omitted_when_none(*names: str):
    """A model serializer leaving out these fields while they are None: documents without them stay as they
    were before the fields existed (use as `_dump = omitted_when_none("field")` in the class body)."""
    def dump(self, handler):
        out = handler(self)
        for name in names:
            if getattr(self, name) is None:
                out.pop(name, None)
        return out

    dump.omitted = dict.fromkeys(names)  # what `dumped` leaves out while None
    return model_serializer(mode="wrap")(dump)


def omitted_when_default(**defaults):
    """A model serializer leaving out these fields while they hold their defaults: documents of cameras without
    them stay as they were before the fields existed (use as `_dump = omitted_when_default(name=default)`)."""
    def dump(self, handler):
        out = handler(self)
        for name, default in defaults.items():
            if getattr(self, name) == default:
                out.pop(name, None)
        return out

    dump.omitted = dict(defaults)  # what `dumped` leaves out while it holds its default
    return model_serializer(mode="wrap")(dump)


class Line(Node):
    name: str
    start: Vec3
    end: Vec3


class Polyline(Node):
    name: str
    points: list[Vec3] = Field(min_length=2)
    closed: bool = False


class Ellipse(Node):
    """Points c + a cos(t) u + b sin(t) v for t in [t0, t1]; u = axis, v = normal x axis."""

    name: str
    centre: Vec3
    normal: Vec3 = Field(description="unit normal of the ellipse's plane")
    axis: Vec3 = Field(description="unit direction of semi-axis a, perpendicular to normal")
    a: float = Field(gt=0)
    b: float = Field(gt=0)
    t0: float = 0.0
    t1: float = Field(6.283185307179586, description="t1 - t0 in (0, 2 pi]")


class Silhouette(Node):
    name: str
    ellipses: tuple[str, str]


class Corner(Node):
    name: str
    at: Vec3
    joins: list[str] = []


class Face(Node):
    name: str
    vertices: list[Vec3] = Field(min_length=3)


class Surface(Node):
    """Triangles of a mesh kept as occluders, never emitted (`mesh read`): those of planar regions that are
    not one convex face, and those of smooth surfaces (`contour`: their outline is view-dependent)."""

    name: str
    file: str = Field(description="the mesh file, as the scene names it")
    vertices: list[Vec3]
    triangles: list[tuple[int, int, int]] = Field(description="indices into vertices")
    contour: list[int] = Field([], description="indices of the triangles of smooth surfaces")


class Board(Node):
    """The pattern of a calibration board (`board` statement), in its model's frame.

    A chessboard or ChArUco board: squares of side `square`, `columns` x `rows` of them, the outer corner of the
    first (dark) square at (-square, -square, 0), the inner corners at (i square, j square, 0); a ChArUco
    board's markers sit in its light squares. A circle grid (`circles`, `acircles`): `columns` x `rows` dark
    dots of diameter `diameter` (OpenCV's patternSize: dots in a row, rows), centre (i, j) at (i square, j square,
    0) on a symmetric grid and at ((2 i + j % 2) square, j square, 0) on an asymmetric one (OpenCV's object
    points), the margin measured from the outermost dots' edges."""

    kind: Literal["chessboard", "charuco", "circles", "acircles"]
    columns: int = Field(ge=3, description="squares across (a circle grid: dots in a row)")
    rows: int = Field(ge=3, description="squares down (a circle grid: rows of dots)")
    square: float = Field(gt=0, description="a square's side (a circle grid: the spacing of its rows)")
    margin: float = Field(ge=0, description="white border around the squares")
    marker: float | None = Field(None, gt=0, description="charuco: side of a marker")
    dictionary: str | None = Field(None, description="charuco: OpenCV's ArUco dictionary, e.g. DICT_4X4_50")
    diameter: float | None = Field(None, gt=0, description="circle grids: a dot's diameter")
    face: str = Field("plane", description="the model's face that carries the pattern")
    _dump = omitted_when_none("marker", "dictionary", "diameter")

    @property
    def circles(self) -> bool:
        return self.kind in ("circles", "acircles")

    @property
    def origin(self) -> Vec3:
        return (0.0, 0.0, 0.0) if self.circles else (-self.square, -self.square, 0.0)

    @property
    def inner(self) -> tuple[int, int]:
        """OpenCV's patternSize: inner corners across and down, or a circle grid's dots in a row and rows."""
        return (self.columns, self.rows) if self.circles else (self.columns - 1, self.rows - 1)

    def centres(self):
        """A circle grid's dot centres (n, 3) in the model's frame, in OpenCV's order (row by row)."""
        import numpy as np

        j, i = np.divmod(np.arange(self.columns * self.rows), self.columns)
        x = (2 * i + j % 2) if self.kind == "acircles" else i
        return np.stack([x * self.square, j * self.square, np.zeros(len(i))], axis=1).astype(float)


class Model(Node):
    name: str
    lines: list[Line] = []
    polylines: list[Polyline] = []
    ellipses: list[Ellipse] = []
    silhouettes: list[Silhouette] = []
    corners: list[Corner] = []
    faces: list[Face] = []
    surfaces: list[Surface] = []
    board: Board | None = Field(None, description="a calibration board's pattern (`board` statement)")
    _dump = omitted_when_none("board")


class Placement(Node):
    """world point = rotation @ model point + position."""

    name: str
    model: str
    position: Vec3
    rotation: Mat3


class Camera(Node):
    """TINA's camera: u = ax*f*x_d + cx, v = ay*f*y_d + cy, f in pixels (f / pixel size).

    The lens model maps a camera-frame point to (x_d, y_d) (engine/geometry.py): `radtan` is OpenCV's
    full rational model (k1..k6, p1, p2), `equidistant` OpenCV's fisheye / Kannala-Brandt (k1..k4 on the
    angle theta from the optical axis; p1 = p2 = k5 = k6 = 0); `unified` Mei's unified model (xi, then radtan
    k1, k2, p1, p2), `eucm` the extended unified model (alpha, beta), `ds` the double-sphere model (xi, alpha)
    and `fov` Devernay and Faugeras's FOV (ATAN) model (w). A model's unused numbers keep their defaults.
    """

    name: str
    f: float = Field(gt=0, description="focal length in pixels")
    ax: float = Field(1.0, gt=0)
    ay: float = Field(1.0, gt=0)
    cx: float
    cy: float
    k1: float = Field(0.0, description="OpenCV's k1 (= -k of TINA)")
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    distortion: Literal["radtan", "equidistant", "unified", "eucm", "ds", "fov"] = "radtan"
    k3: float = 0.0
    k4: float = 0.0
    k5: float = 0.0
    k6: float = 0.0
    fov: float | None = Field(None, gt=0, le=6.283185307179586,
                              description="every model but radtan: the lens's full field of view (rad); nothing "
                                          "farther than fov / 2 from the optical axis is imaged (default: where the "
                                          "lens's theta_d stops increasing, at most 360 deg)")
    xi: float = Field(0.0, description="unified: Mei's xi (>= 0); ds: the double sphere's xi (in (-1, 1])")
    alpha: float = Field(0.0, description="eucm and ds: alpha, in [0, 1]")
    beta: float = Field(1.0, description="eucm: beta (> 0)")
    w: float = Field(0.0, description="fov: Devernay and Faugeras's w (rad), in (0, pi)")
    readout: float = Field(0.0, ge=0, le=1, description="rolling shutter: seconds from the first row's exposure "
                           "to the last's, rows top to bottom (0: a global shutter)")
    exposure: float = Field(0.0, ge=0, le=1, description="motion blur: seconds the shutter is open, centred on the "
                            "row's (or the pose's) time (0: an instant)")

    _dump = omitted_when_default(xi=0.0, alpha=0.0, beta=1.0, w=0.0, readout=0.0, exposure=0.0)


class Mount(Node):
    """A camera on the robot: robot point = rotation @ camera point + position (OpenCV camera frame)."""

    camera: str
    position: Vec3
    rotation: Mat3


class Calibration(Node):
    kind: Literal["information", "covariance"]
    order: list[str]
    matrix: list[list[float]]


class Rig(Node):
    name: str
    left: Mount
    right: Mount
    calibration: Calibration | None = None
    sync: float = Field(0.0, ge=-1, le=1, description="the right camera's exposure time minus the left's (s)")
    jitter: float = Field(0.0, ge=0, le=1, description="the standard deviation of sync drawn per trial and pose (s)")

    _dump = omitted_when_default(sync=0.0, jitter=0.0)

    def stereo_extrinsics(self):
        """(R, T) numpy arrays from the left camera's frame to the right's, X_r = R X_l + T, from the mounts."""
        import numpy as np

        R_l, p_l = np.array(self.left.rotation), np.array(self.left.position)  # camera -> robot
        R_r, p_r = np.array(self.right.rotation), np.array(self.right.position)
        return R_r.T @ R_l, R_r.T @ (p_l - p_r)


class Viewpoints(Node):
    name: str
    names: list[str]
    points: list[Vec2]
    triangles: list[tuple[int, int, int]]
    visibility: Literal["auto", "authored", "file", "all"]
    file: str | None = Field(None, description="view-dependency file, relative to the scene file")
    visible: dict[str, list[str]] = Field({}, description="authored: view-point name -> visible feature ids")


Vec4 = tuple[float, float, float, float]
Mat34 = tuple[Vec4, Vec4, Vec4]


class Path(Node):
    name: str
    poses: list[Vec3] = Field(description="(x, y, heading) in metres and radians; of a path read from a "
                                          "trajectory file, its poses' projections onto the floor")
    transforms: list[Mat34] | None = Field(None, description="of a path read from a trajectory file: every "
                                           "pose's world_from_robot [R | t] (rows), in full 6-DoF")
    times: list[float] | None = Field(None, description="of a path read from a trajectory file with timestamps: "
                                      "each pose's time, seconds from the file's first timestamp; of written "
                                      "poses with a speed: each pose's distance along the path over the speed")
    speed: float | None = Field(None, gt=0, description="written poses: the declared speed (m/s)")
    start_ns: int | None = Field(None, description="with times: the file's first timestamp on its own clock, "
                                 "integer nanoseconds (None: the file has no clock, as KITTI poses with a rate)")
    _dump = omitted_when_none("transforms", "times", "start_ns", "speed")

    def timed(self, speed: float) -> Path:
        """These written poses driven at `speed` (m/s): each pose's time is its distance along the path over the
        speed (the compiler refuses neighbours at one place: no speed times a turn on the spot)."""
        import numpy as np

        xy = np.array([p[:2] for p in self.poses], dtype=float)
        steps = np.hypot(*np.diff(xy, axis=0).T) if len(xy) > 1 else np.zeros(0)
        return self.model_copy(update={"speed": float(speed),
                                       "times": [0.0, *(float(t) for t in np.cumsum(steps) / speed)]})

    def pose(self, i: int) -> tuple[float, ...]:
        """Pose i as the engine takes it (geometry.world_from_robot): (x, y, heading), or [R | t] row-major."""
        if self.transforms is not None:
            return tuple(float(v) for row in self.transforms[i] for v in row)
        return tuple(float(v) for v in self.poses[i])


class Stage(Node):
    """One pipeline stage: an effect's language name and all its parameters (SI units).

    The compiler validates them against the effect's Params model (`wiredsl.effects.REGISTRY`), so the
    compiled scene needs no effect to exist; the JSON schema lists each effect's parameters
    (`wiredsl.effects.stage_models`).
    """

    effect: str
    params: dict[str, float | int | bool | str] = {}


class Pipeline(Node):
    name: str
    default: bool = False
    stages: list[Stage] = []


# The built-in `paper` pipeline (Tian, Thacker & Stancu 2015, section 2): the paper's seven sources at its
# magnitudes, in the data-flow order of a real system; any scene can name it (`--pipeline paper`, a study's
# `pipeline paper`) or extend it (`pipeline mine like paper { ... }`), and a scene's own `pipeline paper`
# replaces it. calibration_error runs at sigma 1 -- the draws then have the rig's calibration covariance as
# measured (the paper's 0.01 scaled its own chi^2 matrix) -- and only when the rig has a calibration.
PAPER = "paper"
PAPER_STAGES: tuple[tuple[str, dict], ...] = (
    ("calibration_error", {"sigma": 1.0}),
    ("edge_loss", {"fraction": 0.29}),
    ("lateral_shift", {"range": 3.0}),
    ("approx_error", {"sigma": 0.15}),
    ("corner_loss", {"keep": 0.85}),
    ("corner_mismatch", {"fraction": 0.01, "radius": 10.0}),
    ("stereo_mismatch", {"band": 0.08726646259971647, "fraction": 0.01, "disparity": 20.0}),  # 5 deg
)


def paper_pipeline(calibrated: bool) -> Pipeline:
    """The built-in `paper` pipeline (PAPER_STAGES), without calibration_error for a rig without a calibration;
    every parameter given, as the compiler gives a declared stage's."""
    from wiredsl.effects import REGISTRY
    from wiredsl.plugins import params_dump, params_of

    stages = [Stage(effect=name, params=params_dump(params_of("effect", REGISTRY[name], REGISTRY, dict(given))))
              for name, given in PAPER_STAGES if calibrated or name != "calibration_error"]
    return Pipeline(name=PAPER, stages=stages)


class Factor(Node):
    """One varied parameter of a study: `stage.param` (or `camera.<name>.param`) over a list of values or a
    range."""

    stage: str = Field(description="a pipeline stage, or camera.<name>")
    param: str
    values: list[float] | None = Field(None, description="explicit values (a grid axis)")
    low: float | None = Field(None, description="range start (SI units)")
    high: float | None = Field(None, description="range end (SI units)")
    steps: int | None = Field(None, ge=1, description="grid: evenly spaced values over [low, high]")

    @property
    def label(self) -> str:
        return f"{self.stage}.{self.param}"


class MeasureUse(Node):
    """A measure a study computes, with its parameters (validated against the measure's model)."""

    name: str
    params: dict[str, float | str] = {}


class Study(Node):
    """A declared sensitivity study: a design over pipeline parameters, trials per point, measures."""

    name: str
    pipeline: str | None = Field(None, description="the pipeline it starts from (None: no stages)")
    factors: list[Factor] = []
    design: Literal["grid", "lhs", "sobol"] = "grid"
    points: int | None = Field(None, ge=1, description="lhs/sobol: base samples n (the design has n (d + 2))")
    design_seed: int = 0
    seed: int = 0
    draws: Literal["common", "independent"] = Field(
        "common", description="common: every design point draws the same disturbances (keyed by trial, not "
        "by point); independent: each point its own (its index is one more key component)")
    trials: int = Field(16, ge=1)
    poses: list[int] | None = Field(None, description="pose indices (None: every pose)")
    measures: list[MeasureUse] = []


class Scene(Node):
    """A compiled wiredsl scene."""

    document: Literal["scene"] = "scene"
    schema_version: Literal["1"] = SCHEMA_VERSION
    name: str
    source: str
    models: list[Model] = []
    placements: list[Placement] = []
    cameras: list[Camera] = []
    rig: Rig | None = None
    viewpoints: Viewpoints | None = None
    path: Path | None = None
    pipelines: list[Pipeline] = []
    studies: list[Study] = []

    def study(self, name: str | None = None) -> Study | None:
        """The named study, else the only one."""
        if name is not None:
            return next((s for s in self.studies if s.name == name), None)
        return self.studies[0] if len(self.studies) == 1 else None

    def model(self, name: str) -> Model:
        return next(m for m in self.models if m.name == name)

    def camera(self, name: str) -> Camera:
        return next(c for c in self.cameras if c.name == name)

    def pipeline(self, name: str | None = None) -> Pipeline | None:
        """The named pipeline (`paper`, undeclared: the built-in one), else the default one, else the only one."""
        if name is not None:
            found = next((p for p in self.pipelines if p.name == name), None)
            if found is None and name == PAPER:
                return paper_pipeline(self.rig is not None and self.rig.calibration is not None)
            return found
        marked = [p for p in self.pipelines if p.default]
        if marked:
            return marked[0]
        return self.pipelines[0] if len(self.pipelines) == 1 else None
