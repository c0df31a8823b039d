"""What every effect declares (name, data-flow position, parameters) and the machinery they share.

Randomness is keyed, not streamed: every draw is a pure function of (seed, stage, trial, pose, camera,
design point, draw index), so adding, removing or reordering a stage never changes another stage's
draws, and a trial's draws do not depend on which other trials share its batch (see `keyed_bits`).
"""

from __future__ import annotations

import zlib
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

# Where each kind of stage acts in a real system, in data-flow order.
FLOW = ("cameras", "edges", "fitting", "corner detection", "corner matching", "stereo")
CAMERA_INDEX = {"left": 0, "right": 1}

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)  # SplitMix64's Weyl increment
_M1, _M2 = np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)


def mix64(z: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser (Steele, Lea, Flood 2014), elementwise on uint64 arrays (wrapping)."""
    z = np.asarray(z, dtype=np.uint64)
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


def stream_key(stage: str, trial, pose: int, camera: int, seed: int, point: int | None = None) -> np.ndarray:
    """The 64-bit key of the draws of one stage for trials `trial`, a pose and a camera (-1: the rig); `trial`,
    `pose` and `camera` may be arrays, broadcast together (the keys of many views in one call).

    key = h(h(h(h(h(seed) + crc32(stage)) + trial) + pose + 1) + camera + 1), then h(key + point + 1) when a
    design point is given, with h = SplitMix64's mix of (x + golden); sums wrap modulo 2**64.
    """
    h = lambda x: mix64(np.asarray(x, dtype=np.uint64) + _GOLDEN)  # noqa: E731
    u = lambda x: (np.asarray(x, dtype=np.int64) + 1).astype(np.uint64)  # noqa: E731 - x + 1, -1 (none) to 0
    with np.errstate(over="ignore"):
        k = h(np.uint64(seed))
        k = h(k + np.uint64(zlib.crc32(stage.encode())))
        k = h(k + np.asarray(trial, dtype=np.int64).astype(np.uint64))
        k = h(k + u(pose))
        k = h(k + u(camera))
        if point is not None:
            k = h(k + np.uint64(point + 1))
    return k


def keyed_bits(key: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Draw `index` of the stream with key `key` (arrays, broadcast): SplitMix64's output number index + 1
    from state `key`, i.e. mix64(key + (index + 1) * golden). A counter-based generator: no state."""
    with np.errstate(over="ignore"):
        return mix64(np.asarray(key, dtype=np.uint64) + (np.asarray(index, dtype=np.uint64) + np.uint64(1)) * _GOLDEN)


def keyed_uniform(key: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Uniform doubles in [0, 1) from the top 53 bits of draw `index`: (bits >> 11) * 2**-53."""
    return (keyed_bits(key, index) >> np.uint64(11)).astype(np.float64) * 2.0**-53


def keyed_normal(key: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Standard normals by Marsaglia's polar method: normals 2j and 2j + 1 are u f and v f, with
    f = sqrt(-2 ln(s) / s), from the first attempt a = 0, 1, ... whose s = u^2 + v^2 is in (0, 1), where
    u = 2 uniform(2i) - 1 and v = 2 uniform(2i + 1) - 1 of the key at i = j + a 2**32 (attempt 0 uses uniforms 2j
    and 2j + 1; about one pair in five takes a second attempt). No trigonometry: a third of Box-Muller's cost."""
    key, index = np.broadcast_arrays(np.asarray(key, dtype=np.uint64), np.asarray(index, dtype=np.uint64))
    keys, pair = key.ravel(), index.ravel() >> np.uint64(1)
    u, v, s = np.empty(len(pair)), np.empty(len(pair)), np.empty(len(pair))
    todo = np.arange(len(pair))
    attempt = 0
    while len(todo):
        i = np.uint64(2) * (pair[todo] + np.uint64(attempt << 32))
        ut = 2.0 * keyed_uniform(keys[todo], i) - 1.0
        vt = 2.0 * keyed_uniform(keys[todo], i + np.uint64(1)) - 1.0
        st = ut * ut + vt * vt
        ok = (st < 1.0) & (st > 0.0)
        u[todo[ok]], v[todo[ok]], s[todo[ok]] = ut[ok], vt[ok], st[ok]
        todo, attempt = todo[~ok], attempt + 1
    f = np.sqrt(-2.0 * np.log(s) / s)
    return np.where(index.ravel() & np.uint64(1), v * f, u * f).reshape(index.shape)


def param(default: float, kind: str, doc: str, **limits: Any) -> Any:
    """A parameter field: default (the paper's), unit kind, bounds and a one-line doc."""
    return Field(default, description=doc, json_schema_extra={"kind": kind}, **limits)


class Params(BaseModel):
    """Base of every effect's parameter model: frozen, no unknown fields."""

    model_config = ConfigDict(frozen=True, extra="forbid", defer_build=True)


@dataclass
class Stats:
    """Running sums an effect records, reported in the run manifest."""

    sums: dict[str, dict[str, float]] = field(default_factory=lambda: defaultdict(lambda: defaultdict(float)))
    maxima: dict[str, dict[str, float]] = field(default_factory=lambda: defaultdict(lambda: defaultdict(float)))
    samples: dict[str, list] = field(default_factory=lambda: defaultdict(list))

    def add(self, stage: str, **values: float) -> None:
        for k, v in values.items():
            self.sums[stage][k] += float(v)

    def peak(self, stage: str, **values: float) -> None:
        for k, v in values.items():
            self.maxima[stage][k] = max(self.maxima[stage][k], float(v))


@dataclass
class Context:
    """What a stage needs to know about the view it acts on."""

    pose: int
    side: str  # "left" | "right"
    trials: np.ndarray  # absolute trial numbers of the batch, by batch index
    seed: int
    stats: Stats
    epipole: Callable[[], np.ndarray] | None = None  # homogeneous epipole in this camera's pixels
    point: int | None = None  # a study's design point: one more key component
    camera: Any = None  # the view's nominal camera (wiredsl.scene.Camera: image size, intrinsics, lens)
    path_s: np.ndarray | None = None  # distance along the run's path at each pose (m; effects.variation)
    # the ideal views as the robot sees them tau seconds after each pose's time, {path pose index: PoseResult}, of
    # a run whose robot moves (effects.motion_blur); None: it does not
    moved: Callable[[float], dict] | None = None

    def draws(self, stage: str, batch_index: np.ndarray, per_item: int = 1, normal: bool = False) -> np.ndarray:
        """Draws (n, per_item) for items of trials `batch_index` (n,), sorted: item j of a trial gets the
        draws j * per_item .. j * per_item + per_item - 1 of its trial's key, uniform in [0, 1) or normal."""
        batch_index = np.asarray(batch_index, dtype=np.int64)
        keys = self.keys(stage)
        counts = np.bincount(batch_index, minlength=len(self.trials))
        first = np.cumsum(counts) - counts
        j = np.arange(len(batch_index)) - first[batch_index]
        index = j[:, None] * per_item + np.arange(per_item)[None, :]
        fn = keyed_normal if normal else keyed_uniform
        return fn(keys[batch_index][:, None], index).reshape(len(batch_index), per_item)

    def keys(self, stage: str, rig: bool = False) -> np.ndarray:
        """The stage's keys, by batch index (`stream_key`); with `rig`, the rig's (camera -1), the same in both
        views: draws the two cameras share (KernelStage.rig)."""
        return stream_key(stage, self.trials, self.pose, -1 if rig else CAMERA_INDEX[self.side], self.seed,
                          self.point)

    def add(self, stage: str, batch_index: np.ndarray, **values: np.ndarray) -> None:
        """Add the sums of per-item values (arrays aligned with `batch_index`, sorted) to the stage's statistics:
        what `stats.add(stage, name=values.sum())` does for one view (views packed: each view's sum in turn, so
        that the sums are those of a view at a time, to the last bit)."""
        self.stats.add(stage, **{k: np.sum(v) for k, v in values.items()})

    def epipoles(self, batch_index: np.ndarray) -> np.ndarray:
        """The epipole (homogeneous pixels) of each item's view, (n, 3)."""
        return np.broadcast_to(self.epipole(), (len(batch_index), 3))

    def right(self, batch_index: np.ndarray) -> np.ndarray:
        """Whether each item's view is the right camera's, (n,) bool."""
        return np.full(len(batch_index), self.side == "right")

    def view_cameras(self, batch_index: np.ndarray) -> tuple[list, np.ndarray]:
        """The nominal cameras of the items' views (wiredsl.scene.Camera, or None where not known): the distinct
        ones, and each item's index into them, (n,)."""
        return [self.camera], np.zeros(len(batch_index), dtype=np.int64)


@dataclass
class PackedContext(Context):
    """Several views' trials in one ImageSet, for the built-in effects (the one-trial build's path): batch index b is
    trial b % per_view of view b // per_view, of pose `poses[b]` and camera `cameras[b]` (CAMERA_INDEX); `trials`
    are the absolute trial numbers by batch index. The draws are keyed as one view at a time would key them (the
    same stream_key of the same (trial, pose, camera)), and statistics are summed view by view."""

    per_view: int = 1
    poses: np.ndarray | None = None  # (B,) pose index by batch index
    cameras: np.ndarray | None = None  # (B,) camera index by batch index
    view_epipoles: Callable[[], np.ndarray] | None = None  # (views, 3): each view's epipole
    cameras_of_views: list | None = None  # (views,): each view's nominal camera

    def keys(self, stage: str, rig: bool = False) -> np.ndarray:
        return stream_key(stage, self.trials, self.poses, -1 if rig else self.cameras, self.seed, self.point)

    def add(self, stage: str, batch_index: np.ndarray, **values: np.ndarray) -> None:
        views = len(self.trials) // self.per_view
        bounds = np.searchsorted(batch_index, np.arange(views + 1) * self.per_view)
        for v in range(views):
            lo, hi = bounds[v], bounds[v + 1]
            self.stats.add(stage, **{k: np.sum(a[lo:hi]) for k, a in values.items()})

    def epipoles(self, batch_index: np.ndarray) -> np.ndarray:
        return self.view_epipoles()[np.asarray(batch_index) // self.per_view]

    def right(self, batch_index: np.ndarray) -> np.ndarray:
        return self.cameras[batch_index] == CAMERA_INDEX["right"]

    def view_cameras(self, batch_index: np.ndarray) -> tuple[list, np.ndarray]:
        views = self.cameras_of_views or [None]
        first = {}
        index = np.array([first.setdefault(id(c), len(first)) for c in views], dtype=np.int64)
        distinct = list({id(c): c for c in views}.values())
        view = np.asarray(batch_index) // self.per_view if self.cameras_of_views else np.zeros(len(batch_index), int)
        return distinct, index[view]


@dataclass(frozen=True)
class KernelStage:
    """How the compiled kernel (engine/kernel.py) runs an effect, declared by the effect beside its numpy code.

    `function` names the stage's numba function as "module:attribute", imported only when a run uses the kernel
    (so that importing the effect does not import numba). It is an `@njit(cache=True)` function of one trial's
    view, `(pts, start, meta, corners, cfid, key, params, epipole, right, stats) -> (pts, start, meta, corners,
    cfid)`: packed strokes (float64 (n, 2) points, int64 stroke starts, int64 (strokes, 7) metadata rows, see
    `wiredsl.engine.kernel`), corners (float64 (c, 2)) and their feature ids, the stage's uint64 key for this
    trial (draw with `wiredsl.engine.kernel._uniform(key, i)` / `_normal_pair`, as `ctx.draws` does), its
    parameters (float64, `params` below in order), the view's epipole (homogeneous, when `epipole`), whether the
    view is the right camera, and its statistics row (float64, one slot per `stats` column, added to in place).
    `params` are the Params fields it takes, `stats` the columns of its statistics row: (Stats key, "add" or
    "peak"), recorded as the numpy path records them. With `camera=True` the function takes one argument more,
    after `stats`: the view's camera, float64 (20,): its nominal image width and height, then f, ax, ay, cx, cy,
    k1, k2, p1, p2, k3, k4, k5, k6, xi, alpha, beta, w and the distortion model's code
    (`wiredsl.engine.geometry.CAMERA_ROW`): what
    `ctx.camera` gives the numpy code (a rolling shutter needs the image height, say). `workspace`, optionally,
    names ("module:attribute") an `@njit(cache=True)` function `(params, epipole, right, camera, trials) -> float64
    1-D array` that the kernel calls once per view and batch, before its trials (`trials`: how many), with the
    arguments the stage gets (`camera` as above, whether or not the stage takes it); the stage then takes the
    array it returned as its last argument: what depends on the view only (a table over the image, say) is
    computed once for the batch rather than once a trial. Every trial gets the same array: a stage reads it and
    must not depend on what an earlier trial wrote into it. With `rig=True` the stage's key is the rig's
    (`stream_key` with camera -1, the numpy code's `ctx.keys(name, rig=True)`), the same in the left and the
    right view of a trial: draws the two cameras share (correlated errors), told apart by `right`. With
    `path=True` and parameters whose `correlation` is above 0 (wiredsl.effects.variation), the stage's key is
    keyed without the pose, and its parameters row ends with the view's pose index and the path's rho table
    (`variation.persistence`), so that its draws persist along the path. An effect
    without a kernel
    (kernel None) runs on the numpy path, and so do the stages after it (`--engine auto` says so on stderr).
    """

    function: str
    params: tuple[str, ...]
    stats: tuple[tuple[str, str], ...]
    epipole: bool = False  # the stage needs the view's epipole
    camera: bool = False  # the stage takes the view's camera row (see above)
    rig: bool = False  # the stage's key is the rig's (camera -1) in both views (see above)
    workspace: str | None = None  # "module:attribute" of the view's workspace function (see above)
    path: bool = False  # with a `correlation` > 0: key without the pose, and the row ends pose, rho (variation)


class Effect:
    """An uncertainty source: one pipeline stage, named in scene files by `name`. Subclass it for a plug-in
    (entry point group `wiredsl.effects`; the tutorial docs/tutorials/plugin.md has a complete package).

    Declare, as class attributes:

    - `name`: the stage's language name (a plug-in's must equal its entry point's name);
    - `acts_on`: where it acts in a real system, one of FLOW after "cameras" (sets the data-flow check);
    - `Params`: a frozen pydantic model (subclass `wiredsl.effects.base.Params`) whose fields, each made with
      `param(default, kind, doc, ge=..., le=...)`, are the stage's clauses: the language converts units by
      `kind` ("length" to metres, "angle" to radians, "image" to pixels, "number", "fraction") and checks the
      bounds; every field needs a default;
    - `doc`: one paragraph for the reference and the editor;
    - `kernel`: optionally, a KernelStage for the compiled engine (None: the numpy path; the stages before it
      still run compiled, it and those after it on numpy, at some 1.4x the CPU time of a wholly compiled run of
      the lab: `--engine auto` says so on stderr).

    Define, as class methods (`@classmethod`, no instance is ever made):

    - `is_identity(params) -> bool`: True when the parameters change nothing (the stage is then skipped);
    - `disturb(params, features, ctx) -> ImageSet`. `features` is a `wiredsl.engine.imageset.ImageSet` holding
      every trial of a batch for one view (a pose and a camera): strokes packed in `pts` (float64 (N, 2) pixels)
      and `start` (int64 (S + 1,) offsets: stroke k is pts[start[k]:start[k + 1]], two points at least), and per
      stroke `fid` (feature id, an index of the world's features), `segment`, `fragment` (-1: whole), `kind`
      (0 a straight segment of 2 points; 1 a curve: a straight edge that lens distortion bends arrives as a
      polyline of kind 1; 2 an ellipse's arc), `clipped`, `closed`, `occluded` (bool) and `trial` (the batch
      index 0..T-1 of its trial); corners in `corners` (float64 (C, 2)) with `corner_fid` and `corner_trial`.
      Return a new set (never change the input's arrays in place: other stages hold them), made with
      `wiredsl.engine.imageset.replace(features, corners=..., pts=...)` (dataclasses.replace) or the set's
      `take(keep)` / `take_corners(keep)`. `ctx` is a Context: `pose` (index), `side` ("left" / "right"),
      `trials` (the absolute trial numbers, by batch index), `camera` (the view's nominal wiredsl.scene.Camera:
      `width`, `height`, `f`, `ax`, `ay`, `cx`, `cy`, distortion), `epipole()` (homogeneous, in this camera's
      pixels), `stats` (a Stats to add measured sums to; `add(name, batch_index, **per_item_values)` adds their
      sums) and `draws(name, batch_index, per_item, normal)`. (The built-in effects are also handed a
      `PackedContext`: several views in one set, `epipoles(batch_index)` and `right(batch_index)` per item.)
      Draw randomness only with `ctx.draws(cls.name, ...)`: keyed by (seed, stage, trial, pose, camera, design
      point), so a trial's values do not depend on its batch or on other stages, and a seed reproduces them;
    - `report(params, stats) -> dict` (optional): measured statistics for the run manifest (JSON values).

    What a plug-in returns is checked before anything reads it (an ImageSet with these dtypes, feature ids in
    range, finite coordinates within 1e9 px, two points a stroke, trials in range; `is_identity` a bool;
    `report` a dict of finite JSON values), and whatever it raises (SystemExit included) is reported as its
    package's error E181, naming the stage, pose, camera and trials, with its traceback under WIREDSL_DEBUG=1.
    """

    name: ClassVar[str]
    acts_on: ClassVar[str]  # one of FLOW
    Params: ClassVar[type[Params]]
    doc: ClassVar[str]
    kernel: ClassVar[KernelStage | None] = None

    @classmethod
    def flow_rank(cls) -> int:
        return FLOW.index(cls.acts_on)

    @classmethod
    def is_identity(cls, params: Params) -> bool:
        """True when these parameters change nothing (the stage is then skipped)."""
        raise NotImplementedError

    @classmethod
    def apply(cls, params: Params, features, ctx: Context):
        """The disturbed features; exactly the input when the parameters change nothing."""
        return features if cls.is_identity(params) else cls.disturb(params, features, ctx)

    @classmethod
    def disturb(cls, params: Params, features, ctx: Context):
        """Draw this stage's randomness from ctx and apply it."""
        raise NotImplementedError

    @classmethod
    def report(cls, params: Params, stats: Stats) -> dict:
        """Measured statistics next to the declared ones, for the run manifest."""
        return {}
