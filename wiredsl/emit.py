"""Stage 5a: simulation results -> the features dump (JSON), validated by its pydantic model."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np

from . import __version__
from .features import (
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
from .scene import Scene
from .simulate import PoseResult
from .simulate import View as SimView
from .world import World

DECIMALS = 6  # pixels: 1e-6 px, far below any effect modelled, and stable across platforms


def scene_ref(scene: Scene) -> SceneRef:
    digest = hashlib.sha256(Path(scene.source).read_bytes()).hexdigest()
    return SceneRef(name=scene.name, file=scene.source, sha256=digest)


def _r(x: float) -> float:
    if not math.isfinite(x):
        raise ValueError("a non-finite number reached the output")  # a bug upstream; never written
    v = round(float(x), DECIMALS)
    return 0.0 if v == 0 else v  # no "-0.0" in dumps


def _pts(a: np.ndarray) -> list[tuple[float, float]]:
    return [(_r(p[0]), _r(p[1])) for p in a]


def _view(v: SimView, world: World) -> View:
    lines, polylines, conics_, corners = [], [], [], []
    for f in v.features:
        common = {"source": world.feature_ids[f.fid], "segment": None if f.segment < 0 else f.segment,
                  "clipped": f.clipped}
        if f.kind == "line":
            lines.append(ImageLine(points=tuple(_pts(f.points)), **common))
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
    R = tuple(tuple(_r(x) for x in row) for row in v.R_cw)
    t = tuple(_r(x) for x in v.t_cw)
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
    return json.dumps(doc.model_dump(mode="json"), indent=indent, allow_nan=False) + "\n"
