"""Where the compiled kernel starts to pay for itself: `wiredsl build scenes/lab.wd --trials N --format npz` on
`--engine numpy` and on `--engine kernel` (numba's cache warm), for a few N, and the trial count at which `auto`
switches (montecarlo.KERNEL_PAYS vertex-trials over the lab's vertices a trial). The figures
docs/explanation/uncertainty.md quotes.

    python benchmarks/engine_crossover.py [--trials 50,75,200] [--repeat 3] [--cold]

Each build is a new process (benchmarks/_cli.py; one thread for BLAS and numba): its CPU time (os.wait4) and wall,
best of `--repeat` by CPU, the two engines alternating so that load hits both alike. A first kernel build (not
timed) fills numba's cache. The load average is printed before and after.

--cold also prints what compiling costs, as a kernel build of 8 trials with fresh caches less the same build
warm: with an empty kernel cache (XDG_CACHE_HOME: the loop generated for the pipeline's stage list is new, so
it is compiled, and the functions it calls too, whose numba caches a new loop flushes: what a new stage list
costs), and with numba's cache empty too (NUMBA_CACHE_DIR: a new machine's first run).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _cli import load, run  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
LAB = str(ROOT / "scenes" / "lab.wd")


def build(out: str, trials: int, engine: str, env: dict | None = None):
    return run(["-m", "wiredsl", "build", LAB, "--trials", str(trials), "--format", "npz", "--seed", "1", "--no-svg",
                "--engine", engine, "-o", out, "--force"], env=env)


def cold(tmp: str, repeat: int) -> None:
    warm = min((build(f"{tmp}/w{k}", 8, "kernel") for k in range(repeat)), key=lambda c: c.cpu)
    for label, names in (("a new stage list (its loop and the functions it calls)", ("XDG_CACHE_HOME",)),
                         ("empty caches (everything compiled)", ("XDG_CACHE_HOME", "NUMBA_CACHE_DIR"))):
        runs = []
        for k in range(repeat):
            env = {name: f"{tmp}/cache-{label[:5]}-{k}-{name}" for name in names}
            runs.append(build(f"{tmp}/c{k}", 8, "kernel", env))
        c = min(runs, key=lambda c: c.cpu)
        print(f"compile, {label}: {c.cpu - warm.cpu:.1f} s of CPU ({c.cpu:.1f} against {warm.cpu:.1f} warm; "
              f"wall {c.wall:.1f} against {warm.wall:.1f})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", default="50,75,200")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--cold", action="store_true")
    args = ap.parse_args()
    from wiredsl import run as runs
    from wiredsl.language.compile import compile_file
    from wiredsl.montecarlo import KERNEL_PAYS

    scene = compile_file(Path(LAB))[0]
    size = runs.start(scene, scene.pipeline(None), seed=1).trial_size()[0]
    print(load())
    print(f"lab: {size:,} vertices a trial; auto runs the kernel from {KERNEL_PAYS:,} vertex-trials: "
          f"{-(-KERNEL_PAYS // size)} trials")
    with tempfile.TemporaryDirectory() as tmp:
        build(f"{tmp}/warm", 8, "kernel")
        if args.cold:
            cold(tmp, args.repeat)
        print("trials\tnumpy CPU s\tkernel CPU s\tnumpy wall s\tkernel wall s")
        for n in (int(x) for x in args.trials.split(",")):
            runs = {"numpy": [], "kernel": []}
            for k in range(args.repeat):
                for engine in runs:
                    runs[engine].append(build(f"{tmp}/{engine}{n}-{k}", n, engine))
            a, b = (min(runs[e], key=lambda c: c.cpu) for e in ("numpy", "kernel"))
            print(f"{n}\t{a.cpu:.2f}\t{b.cpu:.2f}\t{a.wall:.2f}\t{b.wall:.2f}")
    print(load())


if __name__ == "__main__":
    main()
