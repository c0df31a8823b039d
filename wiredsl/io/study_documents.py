"""The models of a study's documents (wiredsl/study/report.py makes them): the tidy table (`table.json`: a row
per design point and measure statistic, and the Sobol' indices) and the study's manifest (`manifest.json`).
Here, below the study, for `wiredsl schema` (io/schema.py) as io/manifest.py is for a build's."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from wiredsl.io.manifest import SceneRef
from wiredsl.scene import Study


class _Node(BaseModel):
    # allow_inf_nan=False: a non-finite number is refused when a row is made, so that no table carries one
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class Row(_Node):
    point: int = Field(ge=0)
    values: dict[str, float] = Field(description="the varied parameters at this point, `stage.param` -> SI value")
    measure: str
    statistic: str
    n: int = Field(ge=1, description="trials with a value")
    n_values: int = Field(ge=1, description="(trial, pose) values pooled")
    mean: float
    sem: float | None = Field(description="standard error of the mean over trials (None with one trial)")
    q05: float
    q25: float
    q50: float
    q75: float
    q95: float


class SobolIndex(_Node):
    measure: str
    statistic: str
    factor: str
    first_order: float | None = Field(description="None when undefined (see `undefined`)")
    total_order: float | None = Field(description="None when undefined (see `undefined`)")
    first_order_ci: tuple[float, float] | None = None
    total_order_ci: tuple[float, float] | None = None
    undefined: str | None = Field(None, description="why the indices are undefined (None when they are not)")


class StudyTable(_Node):
    """The result of `wiredsl study`: one row per design point and measure statistic."""

    document: Literal["study"] = "study"
    schema_version: Literal["1"] = "1"
    tool_version: str
    scene: SceneRef
    study: str
    design: Literal["grid", "lhs", "sobol"]
    factors: list[str]
    seed: int
    trials: int
    rows: list[Row]
    sobol: list[SobolIndex] = []


class PluginUse(_Node):
    """An installed plug-in a study used, as its shards are keyed on it."""

    kind: Literal["effect", "measure"]
    name: str
    package: str = Field(description="its distribution's name")
    version: str
    sha256: str = Field(description="of its installed files and its packages' source files (an editable install's "
                                    "too): a change in its code changes it, whatever the version says")


class StudyManifest(_Node):
    """What a study's table was made from: the study, its seeds and design points, the scene, the versions."""

    document: Literal["study-manifest"] = "study-manifest"
    schema_version: Literal["1"] = "1"
    study: Study
    digest: str = Field(description="sha256 of what every shard's key is made from (the scene and the study)")
    scene: SceneRef
    seed: int
    design_seed: int
    draws: str
    points: list[list[float]] = Field(description="each design point's factor values (SI units), by index")
    shard_trials: int = Field(ge=1)
    versions: dict[str, str]
    plugins: list[PluginUse] = Field([], description="the installed plug-ins the study ran, each keying its shards")
    engines: dict[str, str] = Field({}, description="the engine each stage ran on: kernel (compiled) or numpy")
    visibility: Literal["scene", "exact"] = Field(
        "scene", description="the hidden lines of every point: scene (the nearest view-point's list) or exact "
                             "(decided once for the study from what it projects, as `--visibility auto`)")
