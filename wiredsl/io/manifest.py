"""The models a build makes (io/emit.py): the manifest (`manifest.json`, and the `manifest` member of
features.npz), its stages, and the scene reference the dumps share. Apart from the feature dump's models
(io/features.py), so that a build does not define the classes it never makes (the cold start)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field

from wiredsl.scene import SCHEMA_VERSION
from wiredsl.scene import Node as SceneNode


class Node(SceneNode):
    """The output documents' base (validators built when first used, as the scene's nodes': a build writes its dump
    from arrays, io/emit.py, and only makes a manifest)."""


class SceneRef(Node):
    name: str
    file: str
    sha256: str


class StageRecord(Node):
    effect: str
    params: dict[str, float]


class ManifestStage(Node):
    effect: str
    params: dict[str, float]
    measured: dict[str, Any] = Field(description="each effect's measured statistic beside the declared value")


class Manifest(Node):
    """What a build ran (`manifest.json`, and the `manifest` member of features.npz)."""

    document: Literal["manifest"] = "manifest"
    schema_version: Literal["1"] = SCHEMA_VERSION
    tool_version: str
    scene: SceneRef
    pipeline: str | None = None
    seed: int | None = Field(None, description="the seed of every random stream; null for the ideal projection")
    trials: int = Field(ge=1)
    first_trial: int = Field(ge=0)
    visibility: str = Field("scene", description="scene (the nearest view-point's list), exact or all")
    stages: list[ManifestStage] = []
    ran: dict[str, int] = Field({}, description="how often each piece of work ran (the run's trace)")
    engine: Literal["kernel", "numpy"] = Field("numpy", description="the Monte-Carlo engine that ran the trials "
                                                "(the same draws; a replay is byte-identical with the same one)")
    engines: dict[str, Literal["kernel", "numpy"]] = Field(
        {}, description="the engine that ran each stage: a stage that has no compiled kernel (an installed "
                        "plug-in's, say) and the stages after it run on numpy, those before it compiled")
    warnings: list[str] = []
