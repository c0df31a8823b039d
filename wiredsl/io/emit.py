"""Stage 5a: simulation results -> the features dump (JSON), validated by its pydantic model."""

from __future__ import annotations

import hashlib
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from wiredsl import __version__
from wiredsl.engine import geometry
from wiredsl.engine.simulate import PoseResult, gc_paused
from wiredsl.engine.simulate import View as SimView
from wiredsl.engine.world import World
from wiredsl.files import json_text, printable_path, publish, require_finite
from wiredsl.io import layout
from wiredsl.io.manifest import SceneRef, StageRecord
from wiredsl.scene import SCHEMA_VERSION, Scene, checked, dumped

if TYPE_CHECKING:  # a build writes its dump from arrays: the dump's models are imported where they validate
    from wiredsl.io.features import Features

DECIMALS = 6  # pixels: 1e-6 px, far below any effect modelled, and stable across platforms


def scene_ref(scene: Scene) -> SceneRef:
    """The scene's name, file and sha256 of the file; a scene compiled from text (`wiredsl.compile(text)`, source
    "<string>") has no file, and its digest is of its compiled form (the canonical JSON of the Scene)."""
    if scene.source == "<string>":
        digest = hashlib.sha256(to_json(scene, indent=None).encode()).hexdigest()
    else:
        digest = hashlib.sha256(Path(scene.source).read_bytes()).hexdigest()
    return checked(SceneRef, name=scene.name, file=printable_path(scene.source), sha256=digest)


def _r(x: float, decimals: int | None = DECIMALS) -> float:
    """A finite number for a dump, rounded to `decimals` (None: full float64 precision)."""
    if not math.isfinite(x):
        require_finite(float(x), "a coordinate")  # refuses it, saying why
    v = float(x) if decimals is None else round(float(x), decimals)
    return 0.0 if v == 0 else v  # no "-0.0" in dumps


def rounded(a: np.ndarray, where: str, decimals: int = DECIMALS) -> np.ndarray:
    """Array `a` rounded to `decimals` exactly as Python's round(x, decimals) rounds each element (no -0.0),
    or UnwritableValue when an element is not finite.

    np.round scales, rounds to an integer and scales back: it gives round()'s double whenever the scaled value
    is not within its rounding error of a half-integer, so only those few (and values too large to scale) are
    rounded one by one."""
    a = require_finite(np.ascontiguousarray(a, dtype=np.float64), where)
    scale = 10.0 ** decimals
    with np.errstate(over="ignore", invalid="ignore"):  # a value too large to scale is rounded one by one below
        scaled = a * scale
        out = np.round(scaled) / scale
        near = (np.abs(scaled - np.floor(scaled) - 0.5) < 1e-3) | ~(np.abs(scaled) < 2.0 ** 52)
    for i in np.flatnonzero(near):
        out.flat[i] = round(float(a.flat[i]), decimals)
    return out + 0.0  # -0.0 + 0.0 is 0.0: no "-0.0" in dumps


def _full(a) -> np.ndarray:
    """A pose's matrix or vector at full precision, checked finite, without -0.0."""
    return require_finite(np.ascontiguousarray(a, dtype=np.float64), "a camera pose") + 0.0


_CORNER, _STROKE = ("corner",), ("line", "polyline")


def _rounded_points(views: list[SimView]) -> tuple[np.ndarray, dict]:
    """Every stroke's and corner's pixels of all the views, rounded at once, and where each feature's are:
    {id(feature): (first, end)}."""
    pointed = [f for v in views for f in v.features if f.kind in _STROKE or f.kind in _CORNER]
    ends = np.cumsum([0] + [len(f.points) for f in pointed])
    pts = rounded(np.concatenate([f.points for f in pointed]) if pointed else np.zeros((0, 2)), "a pixel")
    return pts, dict(zip(map(id, pointed), zip(ends[:-1].tolist(), ends[1:].tolist(), strict=True), strict=True))


def _view(v: SimView, world: World, cameras: dict, rounded_points: tuple) -> dict:
    """One view as the dump's `View` document (plain data: numpy arrays where the dump has lists of numbers).

    Every stroke's and corner's pixels are rounded at once (`rounded_points`: `_rounded_points` of the
    views being dumped); the fields come in the models' order."""
    feats = v.features
    pts, at = rounded_points
    lines, polylines, conics_, corners = [], [], [], []
    for f in feats:
        d = {"source": world.feature_ids[f.fid], "segment": None if f.segment < 0 else f.segment,
             "fragment": None if f.fragment < 0 else f.fragment, "clipped": f.clipped, "occluded": f.occluded,
             "kind": f.kind}
        if f.kind == "line":
            lo, hi = at[id(f)]
            d["points"] = pts[lo:hi]
            if world.feature_kind[f.fid] == "contour":  # written only when true: dumps without meshes unchanged
                d["contour"] = True
            lines.append(d)
        elif f.kind == "polyline":
            lo, hi = at[id(f)]
            d["points"], d["closed"] = pts[lo:hi], f.closed
            if world.feature_kind[f.fid] == "contour":
                d["contour"] = True
            polylines.append(d)
        elif f.kind == "conic":
            centre, axes, angle, arc = f.conic
            d.update(centre=(_r(centre[0]), _r(centre[1])), axes=(_r(axes[0]), _r(axes[1])), angle=_r(angle),
                     arc=None if arc is None else (_r(arc[0]), _r(arc[1])))
            conics_.append(d)
        elif f.kind == "corner":
            lo, _ = at[id(f)]
            d["at"] = pts[lo]
            corners.append(d)
        else:
            raise ValueError(f"unknown feature kind {f.kind!r}")
    if id(v.camera) not in cameras:
        cameras[id(v.camera)] = dumped(v.camera)
    # the camera's pose at full precision: re-projecting through it must give the dumped pixels
    return {"camera": cameras[id(v.camera)], "rotation": _full(v.R_cw).reshape(3, 3), "translation": _full(v.t_cw),
            "lines": lines, "polylines": polylines, "conics": conics_, "corners": corners}


def features_doc(scene: Scene, world: World, results: list[PoseResult], *, pipeline: str | None = None,
                 stages: list[StageRecord] = (), seed: int | None = None, trial: int | None = None) -> dict:
    """The features dump as plain data, what `Features(...).model_dump(mode="json")` gives, built from the
    engine's arrays without a model a feature (numpy arrays in place of lists of numbers: see `to_json`)."""
    cameras: dict = {}
    with gc_paused():
        pts = _rounded_points([v for r in results for v in (r.left, r.right) if v is not None])
        poses = [_pose_doc(r, world, cameras, pts) for r in results]
    return {"document": "features", "schema_version": SCHEMA_VERSION, "tool_version": __version__,
            "scene": dumped(scene_ref(scene)), "pipeline": pipeline, "stages": [dumped(s) for s in stages],
            "seed": seed, "trial": trial, "poses": poses}


def _pose_doc(r: PoseResult, world: World, cameras: dict, pts: tuple) -> dict:
    """One pose's `PoseViews` document (its `transform` only for a 6-DoF pose, as the model dumps it)."""
    d = {"index": r.index, "pose": [_r(x) for x in geometry.floor_pose(r.pose)]}
    transform = _transform(r.pose)
    if transform is not None:
        d["transform"] = transform
    d.update(viewpoint=r.viewpoint, left=_view(r.left, world, cameras, pts),
             right=None if r.right is None else _view(r.right, world, cameras, pts))
    return d


def _transform(pose: tuple) -> tuple | None:
    """A 6-DoF pose's [R | t] rows at full precision (None for a floor pose: dumps of floor paths unchanged)."""
    if len(pose) == 3:
        return None
    R, t = geometry.world_from_robot(pose)
    return tuple(tuple(_r(x, None) for x in (*R[i], t[i])) for i in range(3))


def features(scene: Scene, world: World, results: list[PoseResult], *, pipeline: str | None = None,
             stages: list[StageRecord] = (), seed: int | None = None, trial: int | None = None) -> Features:
    """The features dump as its pydantic model (validated): `features_doc` read back."""
    from wiredsl.io.features import Features

    doc = features_doc(scene, world, results, pipeline=pipeline, stages=stages, seed=seed, trial=trial)
    return Features.model_validate_json(_dumps(doc, None))


def _dumps(doc, indent: int | None, newline: bool = False) -> bytes:
    import orjson

    return orjson.dumps(doc, option=orjson.OPT_SERIALIZE_NUMPY | (orjson.OPT_INDENT_2 if indent else 0)
                        | (orjson.OPT_APPEND_NEWLINE if newline else 0))


def to_json(doc, indent: int | None = 1) -> str:
    """JSON text of a document: a pydantic model, or plain data from `features_doc` (numpy arrays serialised as
    lists; every number in it is checked finite where it was made). Indented by 2 unless `indent` is None.

    orjson writes each float as the shortest text that reads back as the same double, as Python's repr does
    (1e-6 where repr writes 1e-06)."""
    if not isinstance(doc, dict):
        doc = dumped(doc)  # a model refuses non-finite numbers when it is made
    return _dumps(doc, indent, newline=True).decode()  # no copy of a long text to add its newline


# --------------------------------------------------------------------------- disturbed output

def manifest_doc(**fields) -> dict:
    """`Manifest(**fields).model_dump(mode="json")`, without validating or dumping through pydantic where the
    values are plain (`scene.checked`, `scene.dumped`)."""
    from wiredsl.io.manifest import Manifest, ManifestStage

    stages = [checked(ManifestStage, **s) if type(s) is dict else s for s in fields.pop("stages", [])]
    return dumped(checked(Manifest, stages=stages, **fields))


def stage_records(run) -> list[StageRecord]:
    from wiredsl.plugins import params_dump

    return [checked(StageRecord, effect=e.name, params=params_dump(p)) for e, p in run.stages]


def disturbed_results(batch_out, k: int) -> list[PoseResult]:
    """Batch trial k's disturbed PoseResults (cameras as perturbed for that trial)."""
    from wiredsl.engine.trials import features_of

    out = []
    for result, disturbed, views in batch_out:
        sides = {}
        for side in ("left", "right"):
            if side not in disturbed:
                sides[side] = None
                continue
            v = views[side]
            base = getattr(result, side) if v is None else v(k) if callable(v) else v[k]
            sides[side] = SimView(base.camera, base.R_cw, base.t_cw, features_of(disturbed[side], k))
        out.append(PoseResult(result.index, result.pose, result.viewpoint, sides["left"], sides["right"]))
    return out


class JsonLines:
    """One features document per (trial, pose) a line, streamed to a temporary file, renamed at the end."""

    def __init__(self, path: Path):
        import tempfile

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, self.tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent)
        self.fh = open(fd, "w", encoding="utf-8")  # noqa: SIM115 - closed in close()/abort()

    def write(self, doc: dict | Features) -> None:
        self.fh.write(to_json(doc, indent=None))

    def close(self) -> None:
        self.fh.close()
        publish(self.tmp, self.path)

    def abort(self) -> None:
        _discard(self.tmp, self.fh.close)


class NpzStream:
    """Bulk arrays, one group of members a batch, written into a zip as they come (an .npz numpy reads).

    The members, columns and codes are listed in `wiredsl/io/layout.py` (and the README): b{b}_pts,
    b{b}_start, b{b}_strokes, b{b}_corners, b{b}_corner_rows a batch; `feature_ids`, `layout` and
    `manifest` (the run manifest as JSON text) once.
    """

    def __init__(self, path: Path):
        import tempfile
        import zipfile

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, self.tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent)
        self.zf = zipfile.ZipFile(open(fd, "wb"), "w", zipfile.ZIP_STORED)  # noqa: SIM115
        self.n = 0

    def member(self, name: str, a: np.ndarray, dtype: type | None = None) -> None:
        """One array member, checked (and cast to `dtype`) by require_finite before a byte is written."""
        a = require_finite(np.asarray(a), f"{self.path.name} member {name}", dtype)
        # (ascontiguousarray would turn the 0-d manifest into shape (1,))
        a = a if a.flags.c_contiguous else a.copy(order="C")
        fmt = np.lib.format
        with self.zf.open(f"{name}.npy", "w", force_zip64=True) as fh:
            if a.dtype.kind in "iuf" and a.ndim >= 1:  # a batch's arrays: what write_array writes, without a copy
                fmt.write_array_header_1_0(fh, fmt.header_data_from_array_1_0(a))
                fh.write(a.reshape(-1).view(np.uint8))
            else:
                fmt.write_array(fh, a, allow_pickle=False)

    def write_ideal(self, results: list[PoseResult], world: World) -> None:
        """The ideal projection (--no-effects) as trial 0, in the same layout as disturbed trials."""
        from wiredsl.engine.trials import to_imageset

        out = [(r, {side: to_imageset(getattr(r, side), world) for side in ("left", "right")
                    if getattr(r, side) is not None}, None) for r in results]
        self.write_batch([0], out, world, renumber=False)

    def write_batch(self, batch: list[int], batch_out, world: World, renumber: bool = True) -> None:
        """One batch's members (`batch_arrays`), as b{n}_<name>, each in its file type."""
        b = f"b{self.n:05d}"
        for name, a in batch_arrays(batch, batch_out, contours(world), renumber, NPZ_TYPES["pts"]).items():
            self.member(f"{b}_{name}", a, NPZ_TYPES.get(name))
        self.n += 1

    def close(self, feature_ids: list[str], manifest: dict) -> None:

        self.member("feature_ids", np.array(feature_ids))
        self.member("layout", np.array(layout.NPZ_VERSION, dtype=np.int64))
        self.member("manifest", np.array(json_text(manifest, indent=None, sort_keys=True, where="manifest")))
        fh = self.zf.fp
        self.zf.close()
        fh.close()
        publish(self.tmp, self.path)

    def abort(self) -> None:
        fh = self.zf.fp
        _discard(self.tmp, self.zf.close, fh.close)


NPZ_TYPES = {"pts": np.float32, "start": np.int64, "strokes": np.int32, "corners": np.float32,
             "corner_rows": np.int32, "views": np.int32, "conic_rows": np.int32}  # the rest: float64


def contours(world: World) -> np.ndarray:
    """True for each feature id that is a smooth mesh surface's occluding contour (the dump's `contour`)."""
    return np.array([k == "contour" for k in world.feature_kind], dtype=bool)


def batch_arrays(batch: list[int], batch_out, contour: np.ndarray, renumber: bool = True,
                 points: type = np.float64) -> dict[str, np.ndarray]:
    """One batch's strokes, corners, views (and conics) as the npz members of a batch (layout.py), without
    the b{n}_ prefix and at full precision; `fragment` numbered as the JSON dump numbers it; `contour` is
    `contours(world)`. `points`: the type of pts and corners (the npz writer's float32: each view's cast and
    checked by require_finite).

    Whole arrays a batch: trials' cameras and poses come from the batch's arrays (engine/trials.TrialViews), not
    from a camera model a trial; each view's strokes are written into the batch's arrays while they are in the
    cache, without a copy a view."""
    sets, views, vcams, vposes, conics_, krows = ([] for _ in range(6))
    trials_of = np.asarray(batch, dtype=np.int64)
    T = len(trials_of)
    for result, disturbed, per_trial in batch_out:
        for cam, side in enumerate(("left", "right")):
            s = disturbed.get(side)
            if s is None:
                continue
            v = per_trial and per_trial[side]
            views.append(_int32_rows(trials_of, result.index, cam))
            if v and not callable(v):  # each trial projected from scratch (--exact-calibration)
                vcams.append([[float(layout.camera_value(b.camera, c)) for c in layout.CAMERA_COLUMNS] for b in v[:T]])
                vposes.append([np.concatenate([np.ravel(b.R_cw), b.t_cw]) for b in v[:T]])
            elif v:  # each trial's perturbed camera, from the batch's arrays
                vcams.append(v.cameras(layout.CAMERA_COLUMNS, layout.camera_value))
                vposes.append(v.poses())
            else:  # every trial sees through the view's own camera
                base = getattr(result, side)
                vcams.append(np.tile([float(layout.camera_value(base.camera, c)) for c in layout.CAMERA_COLUMNS],
                                     (T, 1)))
                vposes.append(np.tile(np.concatenate([np.ravel(base.R_cw), base.t_cw]), (T, 1)))
            if not renumber:  # the ideal projection (one trial): its analytic conics too
                for t in batch:
                    for f in getattr(result, side).features:
                        if f.kind == "conic":
                            centre, axes, angle, arc = f.conic
                            conics_.append([*centre, *axes, angle, *(arc if arc is not None else (0.0, 0.0))])
                            krows.append([t, result.index, cam, f.fid, f.clipped, arc is not None])
            sets.append((s, result.index, cam))
    n_pts, n_strokes, n_corners = (sum(f(s) for s, _, _ in sets) for f in (lambda s: len(s.pts),
                                                                         lambda s: s.n_strokes,
                                                                         lambda s: len(s.corners)))
    pts, corners = np.empty((n_pts, 2), dtype=points), np.empty((n_corners, 2), dtype=points)
    start = np.empty(n_strokes + 1, dtype=np.int64)
    cast = (lambda a, what: a) if points == np.float64 else lambda a, what: require_finite(a, what, points)  # noqa: E731
    strokes = np.empty((n_strokes, len(layout.STROKE_COLUMNS)), dtype=np.int32)
    corner_rows = np.empty((n_corners, len(layout.CORNER_COLUMNS)), dtype=np.int32)
    p = k = c = 0
    for s, pose, cam in sets:
        n, m, nc = len(s.pts), s.n_strokes, len(s.corners)
        pts[p:p + n] = cast(s.pts, f"pose {pose}'s {layout.CAMERAS[cam]} vertex")
        start[k:k + m] = s.start[:-1] + p
        frag = _json_fragments(s) if renumber else s.fragment
        _int32_rows(trials_of[s.trial], pose, cam, s.fid, s.segment, s.kind, s.clipped, s.closed, frag, s.occluded,
                    contour[s.fid], out=strokes[k:k + m])
        corners[c:c + nc] = cast(s.corners, f"pose {pose}'s {layout.CAMERAS[cam]} corner")
        _int32_rows(trials_of[s.corner_trial], pose, cam, s.corner_fid, out=corner_rows[c:c + nc])
        p, k, c = p + n, k + m, c + nc
    start[k] = p
    return {
        "pts": pts,
        "start": start,
        "strokes": strokes,
        "corners": corners,
        "corner_rows": corner_rows,
        "views": _rows(views, len(layout.VIEW_COLUMNS), np.int32),
        "view_cameras": _rows(vcams, len(layout.CAMERA_COLUMNS), np.float64),
        "view_poses": _rows(vposes, 12, np.float64),
        "conics": np.array(conics_, dtype=np.float64).reshape(-1, 7),
        "conic_rows": np.array(krows).reshape(-1, len(layout.CONIC_COLUMNS)),
    }


def _discard(tmp: str, *closers) -> None:
    """Remove a temporary first, then close what wrote it: a close that fails again (a full disk) leaves nothing."""
    import contextlib
    import os

    with contextlib.suppress(FileNotFoundError):
        os.unlink(tmp)
    for close in closers:
        with contextlib.suppress(OSError, ValueError):
            close()


def _int32_rows(first: np.ndarray, *columns, out: np.ndarray | None = None) -> np.ndarray:
    """Rows (len(first), 1 + len(columns)) of int32, one column each (a scalar fills its column), into `out` if
    given. Every value fits: trials are below 2**31 (cli.MAX_TRIAL), poses, cameras, features and codes far below."""
    out = np.empty((len(first), 1 + len(columns)), dtype=np.int32) if out is None else out
    out[:, 0] = first
    for j, c in enumerate(columns, 1):
        out[:, j] = c
    return out


def _rows(parts: list, width: int, dtype: type = np.int64) -> np.ndarray:
    """Blocks of rows stacked into one (n, width) array (an empty one when there are none)."""
    return np.concatenate([np.asarray(p, dtype=dtype).reshape(-1, width) for p in parts]) if parts else \
        np.zeros((0, width), dtype=dtype)


def _json_fragments(s) -> np.ndarray:
    """The fragment numbers the JSON dump gives (engine/trials.features_of): within a trial, the strokes of one
    (feature, segment) are numbered 0, 1, ... in order when the feature was cut, else -1."""
    n = s.n_strokes
    if n == 0:
        return np.zeros(0, dtype=int)
    # one int64 key a stroke, (trial, feature, segment) in lexicographic order; a stable sort keeps each
    # group's strokes in their order, so a stroke's rank in its group is its fragment number
    trial, fid, seg = (np.asarray(a, dtype=np.int64) for a in (s.trial, s.fid, s.segment))
    nf, ns = int(fid.max()) + 1, int(seg.max()) + 2  # segment -1 (none) is shifted to 0
    key = (trial * nf + fid) * ns + seg + 1
    first = np.empty(n, dtype=bool)
    first[0] = True
    np.not_equal(key[1:], key[:-1], out=first[1:])
    group_start = np.flatnonzero(first)
    runs = np.sort(key[group_start])
    if not (runs[1:] == runs[:-1]).any():  # each group's strokes are adjacent, as the engines give them: a
        group = np.cumsum(first) - 1  # stroke's rank is its place in its run (no stable sort of every stroke)
        count = np.diff(np.append(group_start, n))[group]
        return np.where((s.fragment >= 0) | (count > 1), np.arange(n) - group_start[group], -1)
    order = np.argsort(key, kind="stable")
    key = key[order]
    first = np.empty(n, dtype=bool)
    first[0] = True
    np.not_equal(key[1:], key[:-1], out=first[1:])
    group_start = np.flatnonzero(first)
    group = np.cumsum(first) - 1
    count = np.diff(np.append(group_start, n))[group]
    rank_sorted = np.arange(n) - group_start[group]
    rank, counts = np.empty(n, dtype=int), np.empty(n, dtype=int)
    rank[order], counts[order] = rank_sorted, count
    return np.where((s.fragment >= 0) | (counts > 1), rank, -1)
