"""What every effect declares: its language name, data-flow position and parameters."""

from __future__ import annotations

from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict, Field

# Where each kind of stage acts in a real system, in data-flow order.
FLOW = ("cameras", "edges", "fitting", "corner detection", "corner matching", "stereo")


def param(default: float, kind: str, doc: str, **limits: Any) -> Any:
    """A parameter field: default (the paper's), unit kind, bounds and a one-line doc."""
    return Field(default, description=doc, json_schema_extra={"kind": kind}, **limits)


class Params(BaseModel):
    """Base of every effect's parameter model: frozen, no unknown fields."""

    model_config = ConfigDict(frozen=True, extra="forbid")


class Effect:
    """An uncertainty source of the paper, applied as one pipeline stage."""

    name: ClassVar[str]
    acts_on: ClassVar[str]  # one of FLOW
    Params: ClassVar[type[Params]]
    doc: ClassVar[str]

    @classmethod
    def flow_rank(cls) -> int:
        return FLOW.index(cls.acts_on)
