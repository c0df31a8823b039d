"""Common random numbers against independent draws: the precision of the lab `sources` study's Sobol' indices
per CPU-second.

    python benchmarks/study_crn.py [--trials 8] [--resamples 200]

Runs scenes/studies/lab_study.wd's Sobol' study `sources` (7 factors, 64 base samples: 576 points x 3 poses,
measures pgh and stereo3d) twice in process, once with `draws independent` and once with `draws common`, at
--trials trials a point, and times each run's CPU. Then, for every statistic, it bootstraps over trials (the
same resampled trial indices at every point, which keeps the common draws common) and recomputes the first-order
indices of the per-point means from each resample: their standard deviation over the resamples is the
Monte-Carlo standard error of each index. Printed per statistic: the median over the factors of each mode's
standard error, and the efficiency ratio (SE_ind^2 x CPU_ind) / (SE_common^2 x CPU_common), how many times
fewer CPU-seconds common draws need for the same standard error. A statistic that only some factors touch
(corners: corner_loss and corner_mismatch) gets exactly 0 from the others under common draws, whatever the
resample: its median standard error is 0 ("exact").

What each mode estimates: with independent draws the indices are those of the per-point mean plus its
Monte-Carlo noise, which inflates the first-order indices' denominator and scatters them; with common draws
every point sees the same disturbances, so the per-point means are one smooth function of the factors (the
expected statistic given this finite set of draws) and the indices are that function's.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def run(scene, study, trials: int, draws: str, folder: Path) -> tuple[dict, float]:
    """The study's per-trial values {statistic: (points, poses, trials)} and the run's CPU seconds."""
    from wiredsl.study import jobs, journal, run_study, shards

    s = study.model_copy(update={"draws": draws, "trials": trials})
    cpu = time.process_time()
    run_study(scene, s, folder, executor="inprocess")
    cpu = time.process_time() - cpu
    X, all_jobs = jobs(scene, s, folder)
    stored = journal.replay(folder, {shards.key(j) for j in all_jobs})
    per_point: list[dict[str, list]] = [{} for _ in range(len(X))]
    for j in all_jobs:
        for name, V in stored[shards.key(j)].items():
            per_point[j.shard.point].setdefault(name, []).append(V)
    names = sorted(set.intersection(*(set(p) for p in per_point)))
    return {k: np.stack([np.concatenate(p[k], axis=1) for p in per_point]) for k in names}, cpu


def index_se(values: np.ndarray, n: int, d: int, resamples: int, seed: int) -> np.ndarray | None:
    """Bootstrap standard error over trials of each factor's first-order index, (d,); None if undefined."""
    from wiredsl.study.design import sobol_indices

    rng = np.random.default_rng(seed)
    T = values.shape[2]
    got = []
    for _ in range(resamples):
        pick = rng.integers(0, T, T)
        v = values[:, :, pick]
        with np.errstate(invalid="ignore"):
            y = np.nanmean(v.reshape(len(v), -1), axis=1)
        if not np.isfinite(y).all():
            continue
        s = sobol_indices(y, n, d, resamples=0)
        if s is not None:
            got.append(s["first_order"])
    if len(got) < resamples // 2:
        return None
    return np.std(np.array(got), axis=0, ddof=1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=8)
    ap.add_argument("--resamples", type=int, default=200)
    args = ap.parse_args()

    from wiredsl.language.compile import compile_file

    scene, _, _ = compile_file(str(ROOT / "scenes/studies/lab_study.wd"))
    study = scene.study("sources")
    n, d = study.points, len(study.factors)
    out, cpu = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        run(scene, study, 1, "independent", Path(tmp) / "warm")  # compiles the kernel, loads the measures: untimed
        for mode in ("independent", "common"):
            out[mode], cpu[mode] = run(scene, study, args.trials, mode, Path(tmp) / mode)
    print(f"lab `sources` study: {n * (d + 2)} points x {args.trials} trials x {len(study.poses)} poses, "
          f"in process; CPU independent {cpu['independent']:.1f} s, common {cpu['common']:.1f} s")
    print(f"first-order indices' standard error (bootstrap over trials, {args.resamples} resamples), median over "
          f"the {d} factors")
    print(f"{'statistic':32s} {'SE independent':>15s} {'SE common':>10s} {'SE ratio':>9s} {'efficiency':>11s}")
    ratios = []
    for name in sorted(out["common"]):
        se = {m: index_se(out[m][name], n, d, args.resamples, seed=11) for m in out}
        if se["common"] is None or se["independent"] is None:
            print(f"{name:32s} {'undefined (constant)':>38s}")
            continue
        a, b = float(np.median(se["independent"])), float(np.median(se["common"]))
        if b < 1e-12:  # the same indices from every resample: the factors that do not touch the statistic
            print(f"{name:32s} {a:15.4f} {b:10.4f} {'exact':>9s} {'exact':>11s}")  # (most) give exactly 0
            continue
        eff = (a * a * cpu["independent"]) / (b * b * cpu["common"])
        ratios.append(eff)
        print(f"{name:32s} {a:15.4f} {b:10.4f} {a / b:9.2f} {eff:10.1f}x")
    if ratios:
        print(f"median efficiency ratio over statistics: {np.median(ratios):.1f}x (target: at least 3x)")


if __name__ == "__main__":
    sys.exit(main())
