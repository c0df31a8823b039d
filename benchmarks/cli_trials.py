"""`paper` trials to npz through the command line against the bare numpy kernel, in million feature-trials per
second of one core's CPU time, measured in the same run (target: >= 0.5x the bare numpy kernel).

    python benchmarks/cli_trials.py [--trials 2000] [--repeat 3] [--baseline DIR]

`wiredsl build scenes/lab.wd --trials N --format npz` runs in a new process, as a user runs it: the figure
covers compiling the scene, loading the kernel, the trials, packing and writing the npz. Every build names
`--engine kernel`, what `auto` chooses for N (and not for fewer than 75 trials of the lab, KERNEL_PAYS over its
trial size, where numpy costs less: the N/8 build too runs the kernel, so that the marginal rate and the fixed
cost are the kernel's).
The marginal rate (the CPU of N trials less that of N/8, over the extra trials) leaves out the fixed cost of a
run. The bare numpy kernel is benchmarks/throughput.py's: projection of each feature's two end points plus three
perturbations on (trials, features) arrays, the least any implementation has to do; measured before and after
the builds, in this process (one thread).

Two splits follow. The fixed cost: one build of N/8 trials in a child process whose functions are timed
(CPU, each phase without the phases nested in it): interpreter start, imports, numba's import, compiling the
scene, the ideal projection, loading the cached kernel, the size estimate's trial, the batches (the compiled
kernel and the Python around it), the npz writer, the manifest, and the rest (click, the output folder). A
trial's CPU in-process: the compiled kernel, the Python around it (keys, cameras, packing), the npz writer.

--baseline DIR measures another checkout (e.g. main: `git archive main | tar -x -C DIR`) in the same run,
each of its builds beside this checkout's, through PYTHONPATH (its kernel is compiled into the cache once).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(__file__))
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from _cli import ENV, Child, load, run  # noqa: E402

FEATURES = 276  # the lab's strokes a trial (7 poses x 2 cameras), as throughput.py counts them
HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=2000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--baseline", default=None, help="another checkout's folder, measured beside this one")
    ap.add_argument("--phases", type=int, default=None, help=argparse.SUPPRESS)  # a child: one timed build
    ap.add_argument("--split", type=int, default=None, help=argparse.SUPPRESS)  # a child: the per-trial split
    args = ap.parse_args()
    if args.phases is not None:
        return print(json.dumps(phases(args.phases)))
    if args.split is not None:
        return print(json.dumps(split(args.split)))
    from throughput import numpy_rate

    checkouts = {"this": HERE, **({"baseline": os.path.abspath(args.baseline)} if args.baseline else {})}
    print(load())
    bare = numpy_rate(FEATURES, args.trials)
    small = max(args.trials // 8, 2)
    got: dict[str, dict] = {name: {"few": [], "many": [], "phases": [], "split": []} for name in checkouts}
    with tempfile.TemporaryDirectory() as out:
        def build(where: str, n: int) -> Child:
            return run(["-m", "wiredsl", "build", "scenes/lab.wd", "--trials", str(n), "--format", "npz", "--seed",
                        "1", "--no-svg", "--engine", "kernel", "-o", f"{out}/n{n}", "--force"],
                       env={"PYTHONPATH": where}, cwd=where)  # -m imports the current folder's wiredsl first

        for where in checkouts.values():
            build(where, 2)  # the kernel's cache on disk
        for _ in range(args.repeat):  # each figure of one checkout measured beside the other's
            for name, where in checkouts.items():
                got[name]["few"].append(build(where, small))
                got[name]["many"].append(build(where, args.trials))
                got[name]["phases"].append(child(["--phases", str(small)], where))
                got[name]["split"].append(child(["--split", str(args.trials)], where))
    bare = (bare + numpy_rate(FEATURES, args.trials)) / 2  # before and after: the machine is shared
    print(f"bare numpy kernel: {bare / 1e6:.3f} million feature-trials/s")
    table = {name: summary(g, bare, small, args.trials) for name, g in got.items()}
    rows = list(table["this"])
    heads = list(checkouts)
    print(f"{'':58s}" + "".join(f"{h:>12s}" for h in heads))
    for row in rows:
        print(f"{row:58s}" + "".join(f"{table[h].get(row, ''):>12s}" for h in heads))
    print(load())


def summary(g: dict, bare: float, small: int, trials: int) -> dict[str, str]:
    """One checkout's figures (best runs by CPU) as the table's column."""
    few, many = (min(g[k], key=lambda c: c.cpu) for k in ("few", "many"))
    rss = max(c.rss for c in g["many"])
    whole = FEATURES * trials / many.cpu
    marginal = FEATURES * (trials - small) / max(many.cpu - few.cpu, 1e-9)
    fixed = few.cpu - small * (many.cpu - few.cpu) / (trials - small)
    out = {f"whole run of {trials} trials, x bare numpy (target >= 0.5x)": f"{whole / bare:.3f}x",
           "  its CPU (s)": f"{many.cpu:.2f}", "  its peak RSS (MiB)": f"{rss:.0f}",
           f"marginal ({small} -> {trials} trials), x bare numpy": f"{marginal / bare:.3f}x",
           "fixed cost of a run (s CPU)": f"{fixed:.3f}",
           f"phases of one build of {small} trials (ms CPU):": ""}
    ph = min(g["phases"], key=lambda p: p["total"])
    for label in PHASE_ORDER:
        out[f"  {label}"] = f"{1e3 * ph.get(label, 0.0):.0f}"
    out["  total"] = f"{1e3 * ph['total']:.0f}"
    kernel, around, writer = min(g["split"], key=sum)
    out[f"a trial in-process, {trials} trials (us CPU):"] = ""
    for label, v in (("compiled kernel", kernel), ("Python around it (keys, cameras, packing)", around),
                     ("npz writer", writer), ("sum", kernel + around + writer)):
        out[f"  a trial's {label}"] = f"{v:.0f}"
    return out


def child(args: list[str], where: str):
    """This script run as a child on the checkout `where`: what it prints, as JSON."""
    proc = subprocess.run([sys.executable, os.path.abspath(__file__), *args], env={**ENV, "PYTHONPATH": where},
                          capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise SystemExit(f"{args} on {where} failed:\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _montecarlo() -> str:
    """The module of `Run`: wiredsl/montecarlo.py, engine/montecarlo.py in a checkout from before it moved (a
    --baseline); found without importing wiredsl, since a child times the imports from the first one on."""
    import importlib.util

    spec = importlib.util.find_spec("wiredsl")
    folder = os.path.dirname(spec.origin) if spec is not None and spec.origin else ""
    moved = os.path.exists(os.path.join(folder, "montecarlo.py"))
    return "wiredsl.montecarlo" if moved else "wiredsl.engine.montecarlo"


MONTECARLO = _montecarlo()
# the phases of a build: (label, module, function or Class.method), each timed without the phases nested in it
PHASES = (
    ("compile the scene", "wiredsl.language.compile", "compile_file"),
    ("world and run set-up", "wiredsl.engine.world", "build_world"),
    ("world and run set-up", "wiredsl.run", "start"),
    ("ideal projection", MONTECARLO, "Run.ideal"),
    ("numba's array functions (no BLAS)", "wiredsl.cli", "_numba_without_blas"),
    ("compiled kernel", "wiredsl.engine.kernel", "run_view"),  # its first call: loading the cached kernel
    ("the size estimate's trial (its own part)", "wiredsl.cli", "trial_bytes"),
    ("Python around the kernel (batches)", MONTECARLO, "Run._batch"),
    ("npz writer", "wiredsl.io.emit", "NpzStream.__init__"),
    ("npz writer", "wiredsl.io.emit", "NpzStream.write_batch"),
    ("npz writer", "wiredsl.io.emit", "NpzStream.close"),
    ("manifest", MONTECARLO, "Run.manifest"),
)
NUMBA_IMPORTS = "numba's imports (with those of the kernel's load)"
LOAD = "loading the cached kernel (its first call)"
PHASE_ORDER = ("interpreter start", "imports (numba's apart)", NUMBA_IMPORTS, LOAD,
               *dict.fromkeys(label for label, _, _ in PHASES), "the rest (click, output folder, ...)")


def phases(trials: int) -> dict[str, float]:
    """CPU seconds of each phase of one `wiredsl build scenes/lab.wd --trials N --format npz` in this process
    (the timers are installed as the modules load, so nothing is imported ahead of the command)."""
    import _frozen_importlib as bootstrap
    import collections

    start = time.process_time()
    acc: collections.Counter = collections.Counter()
    nested: list[float] = []

    def timed(label, f):
        def g(*a, **k):
            t0 = time.process_time()
            nested.append(0.0)
            try:
                return f(*a, **k)
            finally:
                dt = time.process_time() - t0
                acc[label] += dt - nested.pop()
                if nested:
                    nested[-1] += dt
        return g

    todo = {}
    for label, module, name in PHASES:
        todo.setdefault(module, []).append((label, name))
    find_and_load = bootstrap._find_and_load

    def loading(name, import_):
        top = name.split(".")[0]
        module = timed(NUMBA_IMPORTS if top in ("numba", "llvmlite") else "imports (numba's apart)",
                       find_and_load)(name, import_)
        for label, attr in todo.pop(name, ()):  # the module's phases timed from now on
            owner, _, attr = attr.rpartition(".")
            holder = getattr(module, owner) if owner else module
            f = timed(label, getattr(holder, attr))
            if attr == "run_view":  # its first call loads the kernel from numba's cache (and runs one view)
                f = first_call(timed(LOAD, getattr(holder, attr)), f)
            setattr(holder, attr, f)
        return module

    def first_call(first, then):
        calls = []

        def g(*a):
            calls.append(1)
            return (first if len(calls) == 1 else then)(*a)
        return g

    bootstrap._find_and_load = loading
    with tempfile.TemporaryDirectory() as out:
        from wiredsl.cli import main as cli

        try:
            cli(["build", "scenes/lab.wd", "--trials", str(trials), "--format", "npz", "--seed", "1", "--no-svg",
                 "--engine", "kernel", "-o", f"{out}/o"], standalone_mode=False)
        finally:
            bootstrap._find_and_load = find_and_load
    total = time.process_time()
    got = {"interpreter start": start, **acc}
    got["the rest (click, output folder, ...)"] = total - sum(got.values())
    return {**got, "total": total}


def split(trials: int) -> tuple[float, float, float]:
    """Microseconds of CPU a lab trial spends in the compiled kernel, in the Python around it and in the npz
    writer, measured in this process (the kernel's calls timed one by one)."""
    import importlib

    from wiredsl.engine import kernel as kn
    from wiredsl.engine.simulate import Options
    from wiredsl.engine.world import build_world
    from wiredsl.io import emit
    from wiredsl.language.compile import compile_file

    inside = [0.0]
    run_view = kn.run_view

    def timed(*a):
        t = time.process_time()
        out = run_view(*a)
        inside[0] += time.process_time() - t
        return out

    Run = importlib.import_module(MONTECARLO).Run
    scene, _, _ = compile_file("scenes/lab.wd")
    world = build_world(scene)
    run = Run.create(scene, world, scene.pipeline("paper"), 1, Options())
    run.engine = "kernel"
    run.ideal()
    list(run.batches(range(4)))  # load the kernel
    kn.run_view = timed
    batches = writing = 0.0
    with tempfile.TemporaryDirectory() as out:
        writer = emit.NpzStream(f"{out}/features.npz")
        it = iter(run.batches(range(trials)))
        while True:
            t0 = time.process_time()
            got = next(it, None)
            t1 = time.process_time()
            if got is None:
                break
            writer.write_batch(*got, run.world)
            batches, writing = batches + t1 - t0, writing + time.process_time() - t1
        writer.abort()
    kn.run_view = run_view
    return 1e6 * inside[0] / trials, 1e6 * (batches - inside[0]) / trials, 1e6 * writing / trials


if __name__ == "__main__":
    main()
