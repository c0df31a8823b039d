"""Study speed: local processes on 2 cores against in-process, and the study's overhead against the
same trials run bare (the engine's batches as `build` runs them, and the same measure calls, without
shards, files, executors or progress).

    python benchmarks/study_speed.py [--trials 256] [--repeat 2]

Uses the installed `survival` measure when there is one, else the tests' `kept` measure.

    python benchmarks/study_speed.py --against 4959980 [--repeat 2] [--workers 2]

The lab's Sobol' `sources` study (576 points x 2 trials x 3 poses, measures pgh and stereo3d) on commit REF
(a temporary git worktree) and on this checkout, side by side in one run, alternately: points per second per
core in process (one core) and with local processes (--workers), REF both as it runs by default and with
OPENBLAS_NUM_THREADS=1 (its PGH products on one BLAS thread, as this checkout's workers run them), and
whether the tables are equal byte for byte.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))

STUDY = """wiredsl 1
include "{lab}"
study speed {{
  pipeline paper
  vary lateral_shift.range values [1px, 4px]
  vary calibration_error.sigma values [0.005, 0.02]
  trials {trials}
  poses [0, 3, 6]
  measure {measure}
}}
"""


def burn(n: int) -> int:
    """Pure-Python work, to measure what parallelism the machine offers right now."""
    s = 0
    for i in range(n):
        s += i * i
    return s


def machine_speedup(n: int = 4_000_000) -> float:
    """Two processes against one on the same embarrassingly parallel work, at this moment."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    t = time.perf_counter()
    burn(n)
    burn(n)
    one = time.perf_counter() - t
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        list(pool.map(burn, [1, 1]))  # started before timing
        t = time.perf_counter()
        list(pool.map(burn, [n, n]))
        two = time.perf_counter() - t
    return one / two


def _timed_study(tree: Path, out: Path, env: dict | None = None, cpu: bool = False, full: bool = False, **kw):
    """The wall time (with `cpu`: (wall, the study process's CPU time); with `full`: _study.py's whole record,
    the workers' CPU time included) of one `sources` study run by `tree`'s wiredsl in a new process
    (benchmarks/_study.py)."""
    import json
    import os
    import subprocess

    shutil.rmtree(out, ignore_errors=True)
    cmd = [sys.executable, str(ROOT / "benchmarks" / "_study.py"), str(out), "--scenes", str(tree / "scenes")]
    for k, v in kw.items():
        cmd += [f"--{k}", str(v)]
    proc = subprocess.run(cmd, env={**os.environ, "PYTHONPATH": str(tree), **(env or {})}, capture_output=True,
                          text=True, cwd=tree)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    return got if full else (got["wall"], got["cpu"]) if cpu else got["wall"]


def table_difference(a: bytes, b: bytes) -> str:
    """How two study tables (CSV) differ: rows that differ, by statistic, and the largest relative difference of
    the mean and quantiles and of the standard error (cells compared as numbers)."""
    import csv
    import io

    ra, rb = list(csv.reader(io.StringIO(a.decode()))), list(csv.reader(io.StringIO(b.decode())))
    if len(ra) != len(rb) or ra[0] != rb[0]:
        return f"different shapes ({len(ra)} and {len(rb)} lines)"
    head = ra[0]
    stat, which = head.index("statistic"), head.index("measure")
    worst = {"mean and quantiles": 0.0, "sem": 0.0}
    rows: dict[str, int] = {}
    for x, y in zip(ra[1:], rb[1:], strict=True):
        if x == y:
            continue
        rows[f"{x[which]}.{x[stat]}"] = rows.get(f"{x[which]}.{x[stat]}", 0) + 1
        for col, u, v in zip(head, x, y, strict=True):
            if u != v and col in ("mean", "sem", "q05", "q25", "q50", "q75", "q95") and u and v:
                rel = abs(float(u) - float(v)) / max(abs(float(u)), abs(float(v)))
                group = "sem" if col == "sem" else "mean and quantiles"
                worst[group] = max(worst[group], rel)
    if not rows:
        return "equal"
    return (f"{sum(rows.values())} of {len(ra) - 1} rows differ ({', '.join(f'{k} {v}' for k, v in rows.items())}); "
            f"largest relative difference {worst['mean and quantiles']:.1e} (mean, quantiles), "
            f"{worst['sem']:.1e} (sem)")


def table_agreement(ref: bytes, this: bytes) -> list[str]:
    """Whether two study tables tell the same story where their draws differ: for each measure's statistic, the
    design's points paired (the same factors in both), the mean over points of this table's mean less the
    reference's, its standard error from the spread of the paired differences, and t = difference / error
    (|t| > 3: a shift beyond what the two tables' own noise explains); the difference also relative to the
    reference's mean level. A table whose draws changed on purpose (0.2.0's normals, the epipolar curve) differs
    row by row; this says whether the change moved the results as a whole."""
    import csv
    import io
    import math

    def means(data: bytes) -> dict[tuple[str, str, str], float]:
        rows = list(csv.DictReader(io.StringIO(data.decode())))
        return {(r["measure"], r["statistic"], r["point"]): float(r["mean"]) for r in rows if r["mean"]}

    a, b = means(ref), means(this)
    stats = sorted({k[:2] for k in a} & {k[:2] for k in b})
    lines = []
    for m, s in stats:
        d = [b[k] - a[k] for k in a if k[:2] == (m, s) and k in b and math.isfinite(a[k]) and math.isfinite(b[k])]
        level = [abs(a[k]) for k in a if k[:2] == (m, s) and math.isfinite(a[k])]
        if len(d) < 2:
            continue
        mean = sum(d) / len(d)
        se = math.sqrt(sum((x - mean) ** 2 for x in d) / (len(d) - 1) / len(d))
        t = mean / se if se > 0 else (0.0 if mean == 0 else math.inf)
        rel = mean / (sum(level) / len(level)) if sum(level) > 0 else 0.0
        lines.append(f"  {m + '.' + s:28s} {len(d):4d} points  this - reference {mean:+.3e} ({rel:+.1%} of its level)"
                     f" +- {se:.1e}  t {t:+6.1f}{'  <- beyond the noise' if abs(t) > 3 else ''}")
    return lines


def side_by_side(ref: str, repeat: int, workers: int) -> None:
    """`sources` on commit `ref` and on this checkout, alternately; points/s per core and their ratio."""
    import os
    import subprocess

    from _cli import load

    points = 9 * 64
    print(f"machine: {os.cpu_count()} cores; {load()} before")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        other = tmp / "against"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(other), ref], check=True)
        try:
            commits = {name: subprocess.run(["git", "-C", str(t), "rev-parse", "--short", "HEAD"], capture_output=True,
                                            text=True, check=True).stdout.strip() for name, t in
                       (("this", ROOT), ("ref", other))}
            one = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
            cases = {  # name: (tree, environment)
                f"{ref} ({commits['ref']}), default BLAS threads": (other, None),
                f"{ref} ({commits['ref']}), OPENBLAS_NUM_THREADS=1": (other, one),
                f"this checkout ({commits['this']})": (ROOT, None),
            }
            for tree in (other, ROOT):  # numba's caches filled for both trees before timing
                _timed_study(tree, tmp / "warm", limit=4)
            runs = {"inprocess": {"executor": "inprocess", "workers": 1},
                    f"processes x{workers}": {"executor": "processes", "workers": workers}}
            best: dict[tuple[str, str], float] = {}
            for _ in range(repeat):  # interleaved, so that the machine's other load hits each alike
                for run, kw in runs.items():
                    for name, (tree, env) in cases.items():
                        out = tmp / f"out-{len(best)}-{_}"
                        wall, cpu = _timed_study(tree, out, env, cpu=True, **kw)
                        print(f"  {run}, {name}: {wall:.1f} s wall, {cpu:.1f} s CPU ({load()})", flush=True)
                        best[(run, name)] = min(wall, best.get((run, name), float("inf")))
                        if run == "inprocess":  # one core: its CPU time is the study's whole cost
                            best[("cpu", name)] = min(cpu, best.get(("cpu", name), float("inf")))
                            (tmp / f"table-{name}.csv").write_bytes((out / "table.csv").read_bytes())
            names = list(cases)
            print(f"\nstudy: lab sources, {points} points x 2 trials x 3 poses, measures pgh + stereo3d; "
                  f"best of {repeat} interleaved runs (run_study's time, workers' start included)")
            rows = [("in process, per CPU-second of the study's process (BLAS threads included)", "cpu", 1),
                    ("in process, per wall second", "inprocess", 1),
                    (f"processes x{workers}, per wall second / {workers}", f"processes x{workers}", workers)]
            for title, run, n in rows:
                print(f"\n{title}:")
                mine = points / best[(run, names[2])] / n
                for name in names:
                    rate = points / best[(run, name)] / n
                    print(f"  {name:48s} {best[(run, name)]:7.1f} s  {rate:6.1f} points/s per core"
                          + ("" if name == names[2] else f"   this checkout: {mine / rate:.2f}x"))
            table = {n: (tmp / f"table-{n}.csv").read_bytes() for n in names}
            print(f"\ntable.csv equal to {names[1]}'s: {table[names[2]] == table[names[1]]}; "
                  f"to {names[0]}'s: {table[names[2]] == table[names[0]]}; "
                  f"{ref}'s two equal each other: {table[names[0]] == table[names[1]]}")
            for name in names[:2]:
                print(f"this checkout's table against {name}'s: {table_difference(table[name], table[names[2]])}")
            print(f"\nthis checkout's table against {names[1]}'s, point by point (paired over the design):")
            print("\n".join(table_agreement(table[names[1]], table[names[2]])))
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(other)], check=False)
    print(f"machine: {load()} after (target: this checkout >= 5x {ref}'s points/s per core)")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=4096)
    ap.add_argument("--repeat", type=int, default=2, help="interleaved repetitions; the best of each is reported")
    ap.add_argument("--against", default=None, help="a commit: the lab's sources study there and here, side by side")
    ap.add_argument("--workers", type=int, default=2, help="--against: workers of the processes runs")
    args = ap.parse_args()
    if args.against:
        side_by_side(args.against, args.repeat, args.workers)
        return
    from wiredsl.engine.world import build_world
    from wiredsl.language import compile_study
    from wiredsl.language.compile import compile_file
    from wiredsl.study import design, run_study, shards

    installed = compile_study.measure_registry()
    if "survival" in installed:
        registry, measure = installed, "survival"
    else:
        import study_measures

        registry, measure = study_measures.REGISTRY, "kept"
        compile_study.measure_registry = lambda: registry
    tmp = Path(tempfile.mkdtemp())
    try:
        path = tmp / "speed.wd"
        path.write_text(STUDY.format(lab=(ROOT / "scenes/lab.wd").as_posix(), trials=args.trials, measure=measure))
        scene = compile_file(path)[0]
        study = scene.study("speed")
        n_trials = len(design.matrix(study)) * study.trials

        def timed(executor: str, **kw) -> float:
            out = tmp / executor
            shutil.rmtree(out, ignore_errors=True)
            t = time.perf_counter()
            run_study(scene, study, out, executor=executor, registry=registry, **kw)
            return time.perf_counter() - t

        def bare() -> float:
            """The same trials and measure calls, without shards, files, executors or progress."""
            t = time.perf_counter()
            world = build_world(scene)
            X = design.matrix(study)
            m = registry[measure]
            params = m.Params()
            for p in range(len(X)):
                run = shards.point_run(scene, world, study, p, X[p])
                shards.measure_batches(run, [(m, params, m.prepare(params, run))], list(range(study.trials)))
            return time.perf_counter() - t

        times: dict[str, list[float]] = {"inprocess": [], "processes": [], "bare": [], "machine": []}
        for _ in range(args.repeat):  # interleaved, so that the machine's other load hits each alike
            times["inprocess"].append(timed("inprocess"))
            times["processes"].append(timed("processes", workers=2))
            times["bare"].append(bare())
            times["machine"].append(machine_speedup())
        inproc, procs, engine = (min(times[k]) for k in ("inprocess", "processes", "bare"))
        machine = max(times["machine"])
        import os

        print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at the end; best of "
              f"{args.repeat} interleaved runs")
        print(f"study: lab, pipeline paper, {len(design.matrix(study))} points x {study.trials} trials x 3 poses "
              f"({n_trials} trials), measure {measure}")
        print(f"in-process:            {inproc:6.2f} s  ({n_trials / inproc:,.0f} trials/s)")
        print(f"processes, 2 workers:  {procs:6.2f} s  ({n_trials / procs:,.0f} trials/s)  "
              f"speed-up {inproc / procs:.2f}x (target >= 1.7x)")
        print(f"the machine itself, 2 processes of pure-Python work against 1: {machine:.2f}x "
              "(2x on two idle cores); the study reaches "
              f"{(inproc / procs) / machine:.0%} of what the machine offered")
        print(f"bare batches + measure: {engine:5.2f} s  ({n_trials / engine:,.0f} trials/s)")
        print(f"study overhead (in-process against the bare batches and measure calls): "
              f"{100 * (inproc / engine - 1):.1f}% (target < 20%)")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
