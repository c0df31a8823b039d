"""Stage 5a: simulation results -> the features dump (JSON), validated by its pydantic model."""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np

from wiredsl import __version__
from wiredsl.engine.simulate import PoseResult
from wiredsl.engine.simulate import View as SimView
from wiredsl.engine.world import World
from wiredsl.io import layout
from wiredsl.io.features import (
    Features,
    ImageConic,
    ImageCorner,
    ImageLine,
    ImagePolyline,
    PoseViews,
    SceneRef,
    StageRecord,
    View,
)
from wiredsl.io.files import json_text, publish, require_finite
from wiredsl.scene import Scene

DECIMALS = 6  # pixels: 1e-6 px, far below any effect modelled, and stable across platforms


def scene_ref(scene: Scene) -> SceneRef:
    digest = hashlib.sha256(Path(scene.source).read_bytes()).hexdigest()
    return SceneRef(name=scene.name, file=scene.source, sha256=digest)


def _r(x: float, decimals: int | None = DECIMALS) -> float:
    """A finite number for a dump, rounded to `decimals` (None: full float64 precision)."""
    if not math.isfinite(x):
        require_finite(float(x), "a coordinate")  # refuses it, saying why
    v = float(x) if decimals is None else round(float(x), decimals)
    return 0.0 if v == 0 else v  # no "-0.0" in dumps


def _pts(a: np.ndarray) -> list[tuple[float, float]]:
    return [(_r(p[0]), _r(p[1])) for p in a]


def _view(v: SimView, world: World) -> View:
    lines, polylines, conics_, corners = [], [], [], []
    for f in v.features:
        common = {"source": world.feature_ids[f.fid], "segment": None if f.segment < 0 else f.segment,
                  "fragment": None if f.fragment < 0 else f.fragment, "clipped": f.clipped, "occluded": f.occluded}
        if f.kind == "line":
            lines.append(ImageLine(points=tuple(_pts(f.points)), contour=world.feature_kind[f.fid] == "contour",
                                   **common))
        elif f.kind == "polyline":
            polylines.append(ImagePolyline(points=_pts(f.points), closed=f.closed, **common))
        elif f.kind == "conic":
            centre, axes, angle, arc = f.conic
            conics_.append(ImageConic(centre=(_r(centre[0]), _r(centre[1])), axes=(_r(axes[0]), _r(axes[1])),
                                      angle=_r(angle), arc=None if arc is None else (_r(arc[0]), _r(arc[1])),
                                      **common))
        elif f.kind == "corner":
            corners.append(ImageCorner(at=(_r(f.points[0, 0]), _r(f.points[0, 1])), **common))
        else:
            raise ValueError(f"unknown feature kind {f.kind!r}")
    # the camera's pose at full precision: re-projecting through it must give the dumped pixels
    R = tuple(tuple(_r(x, None) for x in row) for row in v.R_cw)
    t = tuple(_r(x, None) for x in v.t_cw)
    return View(camera=v.camera, rotation=R, translation=t, lines=lines, polylines=polylines, conics=conics_,
                corners=corners)


def features(scene: Scene, world: World, results: list[PoseResult], *, pipeline: str | None = None,
             stages: list[StageRecord] = (), seed: int | None = None, trial: int | None = None) -> Features:
    poses = [PoseViews(index=r.index, pose=tuple(_r(x) for x in r.pose), viewpoint=r.viewpoint,
                       left=_view(r.left, world), right=None if r.right is None else _view(r.right, world))
             for r in results]
    return Features(tool_version=__version__, scene=scene_ref(scene), pipeline=pipeline, stages=list(stages),
                    seed=seed, trial=trial, poses=poses)


def to_json(doc, indent: int | None = 1) -> str:
    return json_text(doc.model_dump(mode="json"), indent=indent, where=doc.document)


# --------------------------------------------------------------------------- disturbed output

def stage_records(run) -> list[StageRecord]:
    return [StageRecord(effect=e.name, params=p.model_dump()) for e, p in run.stages]


def disturbed_results(batch_out, k: int) -> list[PoseResult]:
    """Batch trial k's disturbed PoseResults (cameras as perturbed for that trial)."""
    from wiredsl.engine.montecarlo import features_of

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

    def write(self, doc: Features) -> None:
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
        with self.zf.open(f"{name}.npy", "w", force_zip64=True) as fh:
            # (ascontiguousarray would turn the 0-d manifest into shape (1,))
            np.lib.format.write_array(fh, a if a.flags.c_contiguous else a.copy(order="C"), allow_pickle=False)

    def write_ideal(self, results: list[PoseResult], world: World) -> None:
        """The ideal projection (--no-effects) as trial 0, in the same layout as disturbed trials."""
        from wiredsl.engine.montecarlo import to_imageset

        out = [(r, {side: to_imageset(getattr(r, side), world) for side in ("left", "right")
                    if getattr(r, side) is not None}, None) for r in results]
        self.write_batch([0], out, renumber=False)

    def write_batch(self, batch: list[int], batch_out, renumber: bool = True) -> None:
        """One batch's members (`batch_arrays`), as b{n}_<name>, each in its file type."""
        b = f"b{self.n:05d}"
        for name, a in batch_arrays(batch, batch_out, renumber).items():
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


def batch_arrays(batch: list[int], batch_out, renumber: bool = True) -> dict[str, np.ndarray]:
    """One batch's strokes, corners, views (and conics) as the npz members of a batch (layout.py), without
    the b{n}_ prefix and at full precision; `fragment` numbered as the JSON dump numbers it."""
    pts, starts, rows, corners, crows, views, vcams, vposes, conics_, krows = ([] for _ in range(10))
    offset = 0
    for result, disturbed, per_trial in batch_out:
        for cam, side in enumerate(("left", "right")):
            s = disturbed.get(side)
            if s is None:
                continue
            for k, t in enumerate(batch):  # each trial's camera as projected
                v = per_trial and per_trial[side]
                base = getattr(result, side) if not v else v(k) if callable(v) else v[k]
                views.append((t, result.index, cam))
                vcams.append([float(layout.camera_value(base.camera, c)) for c in layout.CAMERA_COLUMNS])
                vposes.append(np.concatenate([np.ravel(base.R_cw), base.t_cw]))
                if not renumber:  # the ideal projection: its analytic conics too
                    for f in base.features:
                        if f.kind == "conic":
                            centre, axes, angle, arc = f.conic
                            conics_.append([*centre, *axes, angle, *(arc if arc is not None else (0.0, 0.0))])
                            krows.append([t, result.index, cam, f.fid, f.clipped, arc is not None])
            trials = np.asarray(batch)[s.trial]
            pts.append(s.pts)
            starts.append(s.start[:-1] + offset)
            offset += len(s.pts)
            frag = _json_fragments(s) if renumber else s.fragment
            rows.append(np.column_stack([trials, np.full(s.n_strokes, result.index), np.full(s.n_strokes, cam),
                                         s.fid, s.segment, s.kind, s.clipped, s.closed, frag, s.occluded]))
            ctrials = np.asarray(batch)[s.corner_trial]
            corners.append(s.corners)
            crows.append(np.column_stack([ctrials, np.full(len(ctrials), result.index),
                                          np.full(len(ctrials), cam), s.corner_fid]))
    width = len(layout.STROKE_COLUMNS)
    return {
        "pts": np.concatenate(pts) if pts else np.zeros((0, 2)),
        "start": np.concatenate([*starts, [offset]]).astype(np.int64),
        "strokes": np.concatenate(rows) if rows else np.zeros((0, width), int),
        "corners": np.concatenate(corners).reshape(-1, 2),
        "corner_rows": np.concatenate(crows).reshape(-1, len(layout.CORNER_COLUMNS)),
        "views": np.array(views).reshape(-1, len(layout.VIEW_COLUMNS)),
        "view_cameras": np.array(vcams, dtype=np.float64).reshape(-1, len(layout.CAMERA_COLUMNS)),
        "view_poses": np.array(vposes, dtype=np.float64).reshape(-1, 12),
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


def _json_fragments(s) -> np.ndarray:
    """The fragment numbers the JSON dump gives (montecarlo.features_of): within a trial, the strokes of one
    (feature, segment) are numbered 0, 1, ... in order when the feature was cut, else -1."""
    if s.n_strokes == 0:
        return np.zeros(0, dtype=int)
    key = np.column_stack([s.trial, s.fid, s.segment])
    _, group, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    group = group.ravel()
    order = np.argsort(group, kind="stable")
    rank = np.empty(len(group), dtype=int)
    sorted_group = group[order]
    first = np.concatenate([[True], sorted_group[1:] != sorted_group[:-1]])
    starts = np.maximum.accumulate(np.where(first, np.arange(len(group)), 0))
    rank[order] = np.arange(len(group)) - starts
    cut = (s.fragment >= 0) | (count[group] > 1)
    return np.where(cut, rank, -1)
