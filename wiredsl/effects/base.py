"""What every effect declares (name, data-flow position, parameters) and the machinery they share.

Randomness: every stage draws from its own streams, one per (stage, trial, pose,
camera), seeded by `np.random.default_rng([crc32(stage), trial, pose, camera, seed])`.
Adding, removing or reordering another stage never changes a stage's draws, and
trial K of a run can be replayed alone.
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


def param(default: float, kind: str, doc: str, **limits: Any) -> Any:
    """A parameter field: default (the paper's), unit kind, bounds and a one-line doc."""
    return Field(default, description=doc, json_schema_extra={"kind": kind}, **limits)


class Params(BaseModel):
    """Base of every effect's parameter model: frozen, no unknown fields."""

    model_config = ConfigDict(frozen=True, extra="forbid")


def stream(stage: str, trial: int, pose: int, camera: int, seed: int) -> np.random.Generator:
    """The generator of one stage for one trial, pose and camera (-1 for the whole rig)."""
    return np.random.default_rng([zlib.crc32(stage.encode()), trial, pose + 1, camera + 1, seed])


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

    def per_trial(self, stage: str, batch_index: np.ndarray, fn: Callable[[np.random.Generator, int], np.ndarray]):
        """Draws for items that belong to trials `batch_index` (sorted), each trial from its own stream."""
        counts = np.bincount(batch_index, minlength=len(self.trials))
        parts = [fn(stream(stage, int(t), self.pose, CAMERA_INDEX[self.side], self.seed), int(n))
                 for t, n in zip(self.trials, counts, strict=True)]
        return np.concatenate(parts) if parts else fn(np.random.default_rng(0), 0)


class Effect:
    """An uncertainty source of the paper, applied as one pipeline stage."""

    name: ClassVar[str]
    acts_on: ClassVar[str]  # one of FLOW
    Params: ClassVar[type[Params]]
    doc: ClassVar[str]

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
