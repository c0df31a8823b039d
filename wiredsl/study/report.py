"""A study's tidy table (one row per design point and measure statistic), its CSV forms, the manifest, and
Sobol' indices for space-filling designs; the documents' models are in io/study_documents.py.

Statistics of a row pool the study's poses and trials: `mean` and the quantiles are over every
(trial, pose) value; `sem` is the standard error of the mean over trials (each trial's values
averaged over the poses first), because a trial's poses share its calibration draw. A statistic
a measure weights (`weights`: statistic -> the statistic that counts its points) is averaged with
those weights, and its quantiles leave out the views of weight 0, where it has no value.
"""

from __future__ import annotations

import csv
import io
import math
import platform

import numpy as np

from wiredsl import __version__
from wiredsl.io.manifest import SceneRef
from wiredsl.io.study_documents import PluginUse, Row, SobolIndex, StudyManifest, StudyTable
from wiredsl.scene import Study
from wiredsl.study import design

QUANTILES = (0.05, 0.25, 0.5, 0.75, 0.95)


def _f(x: float) -> float:
    return float(np.float64(x))


def rows(study: Study, X: np.ndarray, per_point: list[dict[str, np.ndarray]],
         weights: dict[str, str] | None = None) -> list[Row]:
    """Rows from each point's values {"measure.statistic": (n_poses, trials)}.

    A statistic with a weight (a measure's `weights`: an average over a count, e.g. a 3D error over the
    points reconstructed) has the weighted mean sum(w v) / sum(w) over every (trial, pose), its standard
    error by the ratio estimator over trials, and quantiles over the views of weight > 0 (a view of weight
    0 holds only a placeholder); a point where no view has a weight gets no row.
    """
    found = []  # (fields, values pooled): the quantiles are computed together below
    labels = [f.label for f in study.factors]
    for p, arrays in enumerate(per_point):
        values = {k: _f(v) for k, v in zip(labels, X[p], strict=True)}
        for name, V in arrays.items():
            measure, stat = name.split(".", 1)
            w = (weights or {}).get(name)
            W = arrays[w] if w in arrays else np.ones(V.shape)
            valid = W > 0
            per_w, per_s = W.sum(axis=0), (W * V).sum(axis=0)  # per trial
            keep = per_w > 0
            n = int(keep.sum())
            if n == 0:
                continue
            mean = per_s.sum() / per_w.sum()
            sem = None
            if n > 1:
                resid = per_s[keep] - mean * per_w[keep]
                sem = _f(math.sqrt((resid ** 2).sum() / (n * (n - 1))) / per_w[keep].mean())
            pooled = V[valid]
            found.append(({"point": p, "values": values, "measure": measure, "statistic": stat, "n": n,
                           "n_values": len(pooled), "mean": _f(mean), "sem": sem}, pooled))
    # np.quantile of every row of a (rows, k) stack is what it gives each row alone: one call per count k
    q = [None] * len(found)
    by_size: dict[int, list[int]] = {}
    for i, (_, pooled) in enumerate(found):
        by_size.setdefault(len(pooled), []).append(i)
    for idx in by_size.values():
        Q = np.quantile(np.stack([found[i][1] for i in idx]), QUANTILES, axis=1).T
        for i, row in zip(idx, Q.tolist(), strict=True):
            q[i] = row
    names = [f"q{int(round(a * 100)):02d}" for a in QUANTILES]
    return [Row(**fields, **dict(zip(names, qs, strict=True))) for (fields, _), qs in zip(found, q, strict=True)]


CONSTANT = "the statistic has the same value at every point of A and B: no variance to apportion"


def sobol(study: Study, table: list[Row]) -> list[SobolIndex]:
    """First-order and total indices of every statistic's per-point mean (space-filling designs)."""
    if study.design == "grid" or not study.factors:
        return []
    n, d = study.points, len(study.factors)
    out = []
    for measure, stat in dict.fromkeys((r.measure, r.statistic) for r in table):
        y = np.array([r.mean for r in table if (r.measure, r.statistic) == (measure, stat)])
        if len(y) != n * (d + 2):  # some point had no value of it: no indices
            continue
        s = design.sobol_indices(y, n, d, seed=study.design_seed)
        if s is None:
            out += [SobolIndex(measure=measure, statistic=stat, factor=f.label, first_order=None, total_order=None,
                               undefined=CONSTANT) for f in study.factors]
            continue
        for i, f in enumerate(study.factors):
            ci = {k: (_f(s[k][0][i]), _f(s[k][1][i])) for k in ("first_order_ci", "total_order_ci") if k in s
                  and np.isfinite(s[k][:, i]).all()}
            out.append(SobolIndex(measure=measure, statistic=stat, factor=f.label,
                                  first_order=_f(s["first_order"][i]), total_order=_f(s["total_order"][i]), **ci))
    return out


COLUMNS = ("point", "measure", "statistic", "n", "n_values", "mean", "sem", "q05", "q25", "q50", "q75", "q95")


def to_csv(table: StudyTable) -> str:
    """The table as CSV: the varied parameters' columns first, then COLUMNS; floats in full precision."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([*table.factors, *COLUMNS])
    for r in table.rows:  # the fields read directly (what model_dump gives them, without a dict a row)
        d = [getattr(r, c) for c in COLUMNS]
        w.writerow([repr(r.values[f]) for f in table.factors]
                   + ["" if v is None else repr(v) if isinstance(v, float) else v for v in d])
    return buf.getvalue()


def sobol_csv(table: StudyTable) -> str:
    """The Sobol' indices as CSV: one row per statistic and factor, with the bootstrap intervals."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["measure", "statistic", "factor", "first_order", "first_order_lo", "first_order_hi", "total_order",
                "total_order_lo", "total_order_hi"])
    for s in table.sobol:
        ci1, cit = s.first_order_ci or ("", ""), s.total_order_ci or ("", "")
        w.writerow([s.measure, s.statistic, s.factor, _cell(s.first_order), *map(str, ci1), _cell(s.total_order),
                    *map(str, cit)])
    return buf.getvalue()


def _cell(x: float | None) -> str:
    return "" if x is None else repr(x)


def manifest(scene_ref: SceneRef, study: Study, digest: str, X: np.ndarray, shard_trials: int,
             plugins: list[dict] = (), engines: dict[str, str] | None = None,
             visibility: str = "scene") -> StudyManifest:
    """What the table was made from: the study, the seeds, the design, the scene, the versions, the plug-ins
    (package, version, hash of their files), the engine of each stage and the hidden lines' mode."""
    import scipy

    return StudyManifest(
        study=study, digest=digest, scene=scene_ref, seed=study.seed, design_seed=study.design_seed,
        draws="keyed by (seed, stage, trial, pose, camera, point): design point I is the run's point I",
        points=[[_f(v) for v in row] for row in X], shard_trials=shard_trials,
        versions={"wiredsl": __version__, "numpy": np.__version__, "scipy": scipy.__version__,
                  "python": platform.python_version()},
        plugins=[PluginUse(**p) for p in plugins], engines=engines or {}, visibility=visibility,
    )
