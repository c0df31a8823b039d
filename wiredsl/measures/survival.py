"""Survival: how much of the ideal view remains after the disturbances.

Per trial, over both cameras of the pose: `features`, the fraction of the ideal
strokes' sources (feature, segment) of which some part remains; `length`, the
disturbed strokes' total image length over the ideal one (shifts can make it
slightly exceed 1 when nothing is lost); `corners`, the disturbed corners over
the ideal ones. Fractions are 1.0 when the ideal view has nothing of the kind
(nothing could be lost), and `ideal_features`, `ideal_corners` give their
weights.
"""

from __future__ import annotations

import numpy as np

from wiredsl.engine import imageset as im
from wiredsl.engine.trials import to_imageset
from wiredsl.measures.base import Measure, Params, source_key


class SurvivalParams(Params):
    """Survival has no parameters."""


class Survival(Measure):
    name = "survival"
    Params = SurvivalParams
    statistics = ("features", "length", "corners", "ideal_features", "ideal_corners")
    pooled = True  # each trial's values from its own features only
    weights = {"features": "ideal_features", "length": "ideal_features", "corners": "ideal_corners"}
    units = {"features": "fraction", "length": "fraction", "corners": "fraction", "ideal_features": "count",
             "ideal_corners": "count"}
    doc = __doc__

    @classmethod
    def prepare(cls, p: SurvivalParams, run) -> dict:
        """Per (pose index, side): the ideal sources (sorted keys), total length and corner count."""
        out = {}
        for result in run.ideal():
            for side in ("left", "right"):
                view = getattr(result, side)
                if view is not None:
                    s = to_imageset(view, run.world)
                    _, length = im.arc_lengths(s)
                    out[(result.index, side)] = (np.unique(source_key(s.fid, s.segment)), float(length.sum()),
                                                 len(s.corners))
        return out

    @classmethod
    def measure(cls, p: SurvivalParams, prepared: dict, pose, disturbed: dict[str, im.ImageSet],
                n_trials: int) -> dict[str, np.ndarray]:
        kept = np.zeros(n_trials)
        length = np.zeros(n_trials)
        corners = np.zeros(n_trials)
        n_feat = n_len = n_corn = 0.0
        for side, s in disturbed.items():
            if (pose.index, side) not in prepared:
                continue
            keys, total, n = prepared[(pose.index, side)]
            n_feat, n_len, n_corn = n_feat + len(keys), n_len + total, n_corn + n
            # sources that appear in a trial, each counted once, and only if the ideal view has them
            pair = np.unique(np.column_stack([s.trial, source_key(s.fid, s.segment)]), axis=0).reshape(-1, 2)
            pair = pair[np.isin(pair[:, 1], keys)]
            kept += np.bincount(pair[:, 0], minlength=n_trials)
            _, L = im.arc_lengths(s)
            length += np.bincount(s.trial, weights=L, minlength=n_trials)
            corners += np.bincount(s.corner_trial, minlength=n_trials)
        return {"features": kept / n_feat if n_feat else np.ones(n_trials),
                "length": length / n_len if n_len else np.ones(n_trials),
                "corners": corners / n_corn if n_corn else np.ones(n_trials),
                "ideal_features": np.full(n_trials, n_feat),
                "ideal_corners": np.full(n_trials, float(n_corn))}

