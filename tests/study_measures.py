"""A tiny measure for the study tests, written against the agreed measure interface
(`wiredsl.measures.base.Measure`): strokes and stroke length that remain in the left image."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


class KeptParams(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")
    scale: float = Field(1.0, gt=0, json_schema_extra={"kind": "number"}, description="multiplies the length")


class Kept:
    """Strokes and their total length per trial in the left image, relative to the ideal view."""

    name: ClassVar[str] = "kept"
    Params: ClassVar[type[BaseModel]] = KeptParams
    statistics: ClassVar[tuple[str, ...]] = ("strokes", "length")
    units: ClassVar[dict[str, str]] = {"strokes": "fraction", "length": "px"}

    @classmethod
    def prepare(cls, params, run) -> object:
        return {r.index: max(1, len(r.left.features)) for r in run.ideal()}

    @classmethod
    def measure(cls, params, prepared, pose, disturbed, n_trials: int) -> dict[str, np.ndarray]:
        s = disturbed["left"]
        seg = np.diff(s.pts, axis=0)
        inner = np.ones(len(seg), dtype=bool)
        inner[s.start[1:-1] - 1] = False  # steps between strokes are not lengths
        owner = np.searchsorted(s.start, np.arange(len(seg)), side="right") - 1
        length = np.bincount(s.trial[owner[inner]], np.hypot(*seg[inner].T), minlength=n_trials)
        strokes = np.bincount(s.trial, minlength=n_trials) / prepared[pose.index]
        return {"strokes": strokes.astype(float), "length": params.scale * length}


REGISTRY = {"kept": Kept}


class SlowKept(Kept):
    """`kept`, 20 ms slower a call, and held once the study is far enough along: a study surely still running
    when a test stops it, however slow the machine (the test waits for shards, not for time).

    `hold(out, n)` gives the environment of a study run into `out` whose calls wait, from the moment its journal
    holds `n` shards, for as long as the file `release(out)` names is absent (`release` it to let them go)."""

    @staticmethod
    def hold(out, n: int) -> dict[str, str]:
        import json
        import os

        return {**os.environ, "WIREDSL_TEST_HOLD": json.dumps([str(out), n])}

    @staticmethod
    def release(out):
        from pathlib import Path

        return Path(f"{out}.released")

    @classmethod
    def measure(cls, params, prepared, pose, disturbed, n_trials: int) -> dict[str, np.ndarray]:
        import json
        import os
        import time

        if os.environ.get("WIREDSL_TEST_HOLD"):
            from wiredsl.study import journal

            out, n = json.loads(os.environ["WIREDSL_TEST_HOLD"])
            while len(journal.replay(out)) >= n and not cls.release(out).exists():
                time.sleep(0.01)
        time.sleep(0.02)
        return super().measure(params, prepared, pose, disturbed, n_trials)


class SignalledKept(Kept):
    """`kept` whose first call sends SIGTERM to its own process and then acts as compiled code may when the
    signal's exception lands in it: wraps it in a SystemError ("wrap") or drops it ("swallow")."""

    how: ClassVar[str] = "wrap"

    @classmethod
    def measure(cls, params, prepared, pose, disturbed, n_trials: int) -> dict[str, np.ndarray]:
        import os
        import signal
        import time

        if not getattr(cls, "sent", False):
            cls.sent = True
            try:
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(30)  # the handler raises in here
            except SystemExit as exc:
                if cls.how == "wrap":
                    raise SystemError("returned a result with an exception set") from exc
        return super().measure(params, prepared, pose, disturbed, n_trials)
