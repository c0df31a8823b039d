"""What every measure declares (name, parameters, statistics) and the helpers they share.

A measure is a downstream consumer of the disturbed features (the recognition
and stereo systems the paper names). The study runner calls `prepare` once per
run (design point) and `measure` once per pose and batch of trials; each
statistic comes back as one finite value per trial. A statistic listed in
`weights` is an average over a count that may be zero in a trial (3D error
over reconstructed points, say): its value there is 0 and its weight is the
named count statistic, so a runner aggregates it as sum(weight * value) /
sum(weight) over trials; where the weight is 0 the value is a placeholder each
measure documents (0 for an error, 1 for a survival fraction).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from wiredsl.effects.base import Params as _EffectParams
from wiredsl.effects.base import param
from wiredsl.engine import imageset as im

__all__ = ["Measure", "Params", "param", "segments", "source_key"]


class Params(_EffectParams):
    """Base of every measure's parameter model: frozen, no unknown fields (as the effects')."""


class Measure:
    """A downstream consumer of the features: per pose and trial, named finite statistics. Subclass it for a
    plug-in (entry point group `wiredsl.measures`, named by `name`; docs/tutorials/plugin.md has a complete one).

    Declare, as class attributes: `name` (a study's `measure NAME`), `Params` (a frozen pydantic model, subclass
    `Params`, its fields made with `param(default, kind, doc, ...)`: the statement's parameters, each with a
    default), `statistics` (a tuple of names), optionally `weights` (a dict: statistic -> the count statistic that
    weights it across trials, see the module's doc) and `units` (a dict: statistic -> its unit, for plots), and
    `doc`.

    Define, as class methods (`@classmethod`):

    - `prepare(params, run) -> object` (optional): the ideal references the measure compares with, from a
      `wiredsl.montecarlo.Run` of the nominal scene (`run.ideal()`: a PoseResult a pose). Called once per
      worker (and per design point when the study varies a camera); it must depend on the scene only.
    - `measure(params, prepared, pose, disturbed, n_trials) -> {statistic: (n_trials,) values}`, called once per
      pose and batch of trials. `pose` is that pose's ideal `wiredsl.engine.simulate.PoseResult`: `index`,
      `pose` (the robot's (x, y, heading)), `left` and `right` Views (`camera`, `R_cw`, `t_cw` world-to-camera,
      `features`: ImageFeatures with `fid`, `kind` ("line", "polyline", "conic", "corner"), `points` (k, 2)
      pixels). `disturbed[side]` is the batch's disturbed ImageSet of that camera (see `Effect`: strokes `pts` /
      `start` with `fid`, `kind` (1: a distorted straight edge arrives as a curve), ... and `trial` 0..n_trials-1,
      corners with `corner_trial`). Both are read-only (numpy arrays with `flags.writeable` False): copy before
      changing anything, so that no measure changes what another reads.

    Each statistic must come back as one finite real value a trial (magnitude up to 1e150; a count that weights
    another statistic never negative). A measure that raises (SystemExit included) or returns anything else is
    reported as its package's error (E181), naming the pose, trials and design point. Outside a study, call it
    yourself on the batches of `wiredsl.simulate` or `wiredsl.Simulator.observe` (`batch.disturbed` holds, per
    pose, the ideal PoseResult and {side: ImageSet}).
    """

    name: ClassVar[str]
    Params: ClassVar[type[Params]]
    statistics: ClassVar[tuple[str, ...]]
    weights: ClassVar[dict[str, str]] = {}  # statistic -> count statistic that weights it across trials
    units: ClassVar[dict[str, str]] = {}  # statistic -> its unit (m, px, count, fraction), shown on plots' axes
    # True: a trial's values depend only on that trial's disturbed features (and the pose and prepared data), so a
    # study may measure the trials of several design points in one call, their trial indices renumbered 0..n-1
    pooled: ClassVar[bool] = False
    doc: ClassVar[str]

    @classmethod
    def prepare(cls, params: Params, run) -> object:
        """The ideal references the measure compares with, from a `wiredsl.montecarlo.Run`.

        A study calls it once per worker with a run of the nominal scene (its design points change only stage
        magnitudes, not the scene), and once per design point when it varies a camera; so it must depend on
        the run's scene and options only, never on its stages.
        """
        return None

    @classmethod
    def measure(cls, params: Params, prepared: object, pose, disturbed: dict[str, im.ImageSet],
                n_trials: int) -> dict[str, np.ndarray]:
        """One pose of one batch: {statistic: (n_trials,) finite values}.

        `pose` is the ideal `PoseResult`; `disturbed[side]` the batch's disturbed ImageSet
        (trial column 0..n_trials-1).
        """
        raise NotImplementedError


def segments(s: im.ImageSet) -> dict[str, np.ndarray]:
    """Every straight piece of every stroke (the closing piece of a closed stroke included).

    Returns arrays over pieces: `a`, `b` (n, 2) end points in stroke order, `length` (n,),
    `stroke`, `trial`, `fid`, `segment` (n,). Pieces shorter than 1e-9 px (no direction) are left out.
    """
    n = len(s.pts)
    stroke_of = s.vertex_stroke()
    head = np.arange(max(n - 1, 0))
    same = stroke_of[:-1] == stroke_of[1:] if n else np.zeros(0, dtype=bool)
    a_idx, b_idx = head[same], head[same] + 1
    closing = np.flatnonzero(s.closed & (s.counts > 2))
    a_idx = np.concatenate([a_idx, s.start[1:][closing] - 1]).astype(int)
    b_idx = np.concatenate([b_idx, s.start[:-1][closing]]).astype(int)
    a, b = s.pts[a_idx], s.pts[b_idx]
    length = np.hypot(*(b - a).T) if len(a_idx) else np.zeros(0)
    keep = length > 1e-9
    k = stroke_of[a_idx][keep]
    return {"a": a[keep], "b": b[keep], "length": length[keep], "stroke": k, "trial": s.trial[k],
            "fid": s.fid[k], "segment": s.segment[k]}


def source_key(fid: np.ndarray, segment: np.ndarray) -> np.ndarray:
    """One integer per (feature, segment): the source a stroke or piece comes from."""
    return np.asarray(fid, dtype=np.int64) * (1 << 20) + np.asarray(segment, dtype=np.int64) + 1
