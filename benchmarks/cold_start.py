"""Cold start: `wiredsl build scenes/lab.wd` from a new process against Python importing just the
dependencies a build needs (numpy, lark, click, pydantic). Best CPU time of several runs each, measured in the
same run (target: build within 1.5x of the imports).

    python benchmarks/cold_start.py [--repeat 7] [--baseline DIR]

`python -X importtime -m wiredsl build ...` shows where the imports' time goes; `--phases` prints the CPU time
of each phase of the paper build in a new process (imports, compiling, projection, the trial, dump, SVGs).

wiredsl's modules are byte-compiled first, as `pip install` does for an installed package: without their
.pyc files (an editable install under PYTHONDONTWRITEBYTECODE=1) every run would compile about 50 modules
from source, some 50 ms CPU that no installed wiredsl pays.

--baseline DIR measures another checkout (e.g. main: `git archive main | tar -x -C DIR`) in the same run, through
its folder (the children run there, and `-m` imports the wiredsl of the current folder first), each of its runs
beside this checkout's (the same imports are the yardstick of both).
"""

from __future__ import annotations

import argparse
import compileall
import os
import sys
import tempfile

sys.path.insert(0, os.path.dirname(__file__))

from _cli import Child, best, load, run  # noqa: E402

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

PHASES = """
import gc, time
marks = [("start", time.process_time())]
def mark(name):
    marks.append((name, time.process_time()))
collecting = [0.0, 0.0]  # when the running collection started; CPU seconds spent collecting
def collected(phase, info):
    if phase == "start":
        collecting[0] = time.process_time()
    else:
        collecting[1] += time.process_time() - collecting[0]
gc.callbacks.append(collected)
import numpy, lark, click, pydantic; mark("import numpy, lark, click, pydantic")
import pydantic.main; mark("import pydantic.main (pydantic's models; `import pydantic` is lazy)")
import wiredsl.cli; mark("import wiredsl.cli")
wiredsl.cli._tune_gc()  # as every command does (a full collection alone would land in some phase: ~25 ms)
import wiredsl.language.compile; mark("import the compiler, the scene's and the effects' models")
import wiredsl.engine.simulate; mark("import the engine (simulate, visibility, occlusion, conics)")
try:
    import wiredsl.montecarlo as montecarlo
except ImportError:  # a --baseline from before it moved out of engine/
    import wiredsl.engine.montecarlo as montecarlo
import wiredsl.io.emit, wiredsl.io.svg; mark("import montecarlo, emit, svg")
from wiredsl.language.compile import compile_file
scene, _, _ = compile_file("scenes/lab.wd"); mark("compile scenes/lab.wd")
from wiredsl.engine.world import build_world
from wiredsl.engine.simulate import Options
world = build_world(scene)
run = montecarlo.Run.create(scene, world, scene.pipeline(), 1, Options()); run.engine = "numpy"
run.ideal(); mark("world, view-point lists, ideal projection")
(b, out), = list(run.batches([0])); mark("the paper trial (numpy path)")
from wiredsl.io import emit, svg
res = emit.disturbed_results(out, 0)
emit.to_json(emit.features_doc(scene, world, res, pipeline="paper", stages=emit.stage_records(run), seed=1, trial=0))
mark("the dump (JSON text)")
svg.pose_figures(run, res, "overlay", svg.Info("paper", 1, 0, "scene", "overlay")); mark("the SVGs")
for (_, a), (name, b) in zip(marks, marks[1:]):
    print(f"  {name:70s} {1e3 * (b - a):6.1f} ms CPU")
print(f"  {'total':70s} {1e3 * (marks[-1][1] - marks[0][1]):6.1f} ms CPU")
print(f"  {'of which collecting garbage cycles':70s} {1e3 * collecting[1]:6.1f} ms CPU")
"""


def byte_compile(baseline: str | None = None) -> None:
    """Write the .pyc files of the wiredsl the children import (this checkout's, their current folder; and the
    baseline's)."""
    compileall.compile_dir(os.path.join(HERE, "wiredsl"), quiet=1)
    if baseline is not None:
        compileall.compile_dir(os.path.join(baseline, "wiredsl"), quiet=1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--phases", action="store_true", help="only the phases of a paper build, in a new process")
    ap.add_argument("--baseline", default=None, help="another checkout's folder, measured beside this one")
    args = ap.parse_args()
    baseline = os.path.abspath(args.baseline) if args.baseline else None
    byte_compile(baseline)
    if args.phases:
        run(["-c", PHASES], quiet=False)
        if baseline is not None:
            print(f"baseline {args.baseline}:")
            run(["-c", PHASES], quiet=False, cwd=baseline)
        return
    checkouts = {"this": HERE, **({"baseline": baseline} if baseline else {})}
    print(load())
    bare = best(["-c", "pass"], args.repeat)
    imports = best(["-c", "import numpy, lark, click, pydantic"], args.repeat)
    commands = {"wiredsl check scenes/lab.wd": ["check", "scenes/lab.wd"],
                "wiredsl build --no-effects": ["build", "scenes/lab.wd", "--no-effects", "-o", "{out}"],
                "wiredsl build (paper pipeline)": ["build", "scenes/lab.wd", "--seed", "1", "-o", "{out}"]}
    got: dict[tuple[str, str], list[Child]] = {(c, n): [] for c in checkouts for n in commands}
    with tempfile.TemporaryDirectory() as out:
        for _ in range(args.repeat):  # each run of one checkout beside the other's: the machine is shared
            for name, argv in commands.items():
                for c, where in checkouts.items():
                    got[c, name].append(run(["-m", "wiredsl", *(a.format(out=out) for a in argv)],
                                            cwd=where))
    imports2 = best(["-c", "import numpy, lark, click, pydantic"], args.repeat)
    dep = min(imports.cpu, imports2.cpu)  # before and after: the machine is shared
    print(f"python -c pass                 : {bare.cpu:6.3f} s CPU")
    print(f"import numpy, lark, click, pydantic: {dep:6.3f} s CPU, {imports.rss:.0f} MiB "
          f"(before {imports.cpu:.3f}, after {imports2.cpu:.3f})")
    for c in checkouts:
        if len(checkouts) > 1:
            print(f"{c} ({checkouts[c]}):")
        for name in commands:
            runs = got[c, name]
            fastest = min(runs, key=lambda r: r.cpu)
            print(f"{name:31s}: {fastest.cpu:6.3f} s CPU = {fastest.cpu / dep:4.2f}x the imports (target <= 1.5x), "
                  f"{min(r.wall for r in runs):.3f} s wall, {max(r.rss for r in runs):.0f} MiB")
    print(load())


if __name__ == "__main__":
    main()
