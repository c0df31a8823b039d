"""One run of the lab's Sobol' `sources` study (scenes/studies/lab_study.wd), timed; the driver of
study_speed.py --against and study_scaling.py, run in a new process with the tree under test on PYTHONPATH
(it uses only what commit 4959980 already had: compile_file and run_study).

    python benchmarks/_study.py OUT [--executor inprocess] [--workers N] [--points 64] [--limit K]

Prints one JSON line: the study's wall time (run_study alone: the workers' start included, the interpreter's
and the scene's compilation not), this process's CPU time over the same span (all its threads, BLAS's too;
not the workers'), the workers' CPU time (`cpu_workers`: the processes executor's workers and their fork
server, reaped at the end), and its points. --points N makes the design N (d + 2)
points (64: the file's 576; 512: 4,608); --limit K runs K shards only (a warm-up: numba's caches filled).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--executor", default="inprocess")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--points", type=int, default=64)
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--scenes", default="scenes", help="the scenes folder (of the tree under test)")
    args = ap.parse_args()
    from wiredsl.language.compile import compile_file
    from wiredsl.study import run_study

    scenes = Path(args.scenes).resolve()
    text = (scenes / "studies" / "lab_study.wd").read_text()
    text = text.replace('include "../lab.wd"', f'include "{(scenes / "lab.wd").as_posix()}"')
    text = re.sub(r"design sobol points \d+", f"design sobol points {args.points}", text)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "study.wd"
        path.write_text(text)
        scene = compile_file(path)[0]
        study = scene.study("sources")
        t, cpu, children = time.perf_counter(), time.process_time(), _children()
        run_study(scene, study, args.out, executor=args.executor, workers=args.workers, limit=args.limit)
        wall, cpu = time.perf_counter() - t, time.process_time() - cpu
        children = _children(stop_forkserver=True) - children
    points = (len(study.factors) + 2) * args.points
    print(json.dumps({"wall": wall, "cpu": cpu, "cpu_workers": children, "points": points, "trials": study.trials,
                      "poses": len(study.poses or []), "executor": args.executor, "workers": args.workers,
                      "pid": os.getpid(), "python": sys.executable}))


def _children(stop_forkserver: bool = False) -> float:
    """CPU seconds of this process's finished children. With `stop_forkserver`, multiprocessing's fork server
    (the parent of the processes executor's workers, which it reaps) is stopped first, so that its workers count."""
    import resource

    if stop_forkserver:
        try:
            from multiprocessing import forkserver

            forkserver._forkserver._stop()
        except Exception:  # noqa: BLE001 (no fork server, or a Python without _stop: the workers are not counted)
            pass
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


if __name__ == "__main__":
    main()
