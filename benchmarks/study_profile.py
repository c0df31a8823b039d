"""Where the lab's Sobol' `sources` study spends its time, in process under cProfile: the shares the issue's
table names (PGH's scoring and location, stereo3d and its undistortion, the Monte-Carlo batches, the calibration
draws, the shard writes and reads), and the ten costliest functions by own time.

    python benchmarks/study_profile.py [--points 64] [--top 10]

Run it on another commit with that tree on PYTHONPATH (the names it looks for are the same there); note that
BLAS's threads are whatever the environment gives (OPENBLAS_NUM_THREADS=1 for the figures of one core).
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import re
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# (label, file suffix, function name): cumulative time of each
PARTS = [
    ("measures/pgh.py measure", "measures/pgh.py", "measure"),
    ("  pgh _own_scores", "measures/pgh.py", "_own_scores"),
    ("  pgh _located", "measures/pgh.py", "_located"),
    ("  pgh prepare (ideal and view-point PGHs)", "measures/pgh.py", "prepare"),
    ("  pgh histograms", "measures/pgh.py", "histograms"),
    ("measures/stereo3d.py measure", "measures/stereo3d.py", "measure"),
    ("  stereo3d undistort", "measures/stereo3d.py", "undistort"),
    ("  stereo3d triangulate", "measures/stereo3d.py", "triangulate"),
    ("Monte-Carlo batches (montecarlo.py batches)", "wiredsl/montecarlo.py", "batches"),
    ("  calibration draws (calibration_draws/_rigs)", "wiredsl/montecarlo.py", "calibration_"),
    ("  rotation_vectors", "effects/calibration_error.py", "rotation_vectors"),
    ("shard writes (shards.write / journal append)", "study/", "write|append"),
    ("  fsync", "~", "<built-in method posix.fsync>"),
    ("shard reads (shards.read / journal replay)", "study/", "read$|replay"),
    ("  measures' read-only views (shards.read_only)", "study/shards.py", "read_only"),
    ("pooled measure calls (shards._measure_pool)", "study/shards.py", "_measure_pool"),
    ("  sets concatenated (shards._stack)", "study/shards.py", "_stack"),
    ("table (report.rows, to_json, to_csv)", "study/report.py", "rows|to_json|to_csv"),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=64)
    ap.add_argument("--top", type=int, default=10)
    args = ap.parse_args()
    from wiredsl.language.compile import compile_file
    from wiredsl.study import run_study

    text = (ROOT / "scenes/studies/lab_study.wd").read_text()
    text = text.replace('include "../lab.wd"', f'include "{(ROOT / "scenes/lab.wd").as_posix()}"')
    text = re.sub(r"design sobol points \d+", f"design sobol points {args.points}", text)
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "s.wd").write_text(text)
        scene = compile_file(Path(tmp) / "s.wd")[0]
        study = scene.study("sources")
        run_study(scene, study, Path(tmp) / "warm", executor="inprocess", limit=2)  # numba's caches, imports
        prof = cProfile.Profile()
        t = time.perf_counter()
        prof.enable()
        run_study(scene, study, Path(tmp) / "out", executor="inprocess")
        prof.disable()
        wall = time.perf_counter() - t
    stats = pstats.Stats(prof).stats  # (file, line, name) -> (cc, nc, tt, ct, callers)
    print(f"lab sources, {(len(study.factors) + 2) * args.points} points x {study.trials} trials x "
          f"{len(study.poses)} poses, in process: {wall:.1f} s under cProfile; OPENBLAS_NUM_THREADS="
          f"{os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}; load average {os.getloadavg()[0]:.1f}")
    total = sum(v[2] for v in stats.values())
    for label, where, name in PARTS:
        pattern = re.compile(rf"^(?:{name})")
        hits = [(k, v) for k, v in stats.items() if k[0].replace("\\", "/").endswith(where) or
                (where.endswith("/") and where in k[0].replace("\\", "/")) or (where == "~" and k[0] == "~")]
        hits = [(k, v) for k, v in hits if pattern.match(k[2])]
        # cumulative time of the outermost matches only (a recursive or nested match is not counted twice)
        names = {k for k, _ in hits}
        ct = sum(v[3] for k, v in hits if not any(c in names for c in v[4]))
        calls = sum(v[1] for k, v in hits if not any(c in names for c in v[4]))
        if calls:
            print(f"  {label:48s} {ct:7.2f} s  {100 * ct / total:5.1f}%  {calls:6d} calls  "
                  f"{1000 * ct / calls:7.2f} ms a call")
    print(f"\nthe {args.top} costliest functions by own time:")
    for k, v in sorted(stats.items(), key=lambda kv: -kv[1][2])[:args.top]:
        print(f"  {v[2]:7.2f} s  {v[1]:7d} calls  {Path(k[0]).name}:{k[1]} {k[2]}")


if __name__ == "__main__":
    sys.exit(main())
