"""Cold start: `wiredsl build scenes/lab.wd` from a new process against Python importing just the
dependencies a build needs (numpy, lark, click, pydantic). Best CPU time of several runs each, measured in the
same run (target: build within 1.5x of the imports).

    python benchmarks/cold_start.py [--repeat 7]

`python -X importtime -m wiredsl build ...` shows where the imports' time goes; `--phases` prints the CPU time
of each phase of the paper build in a new process (imports, compiling, projection, the trial, dump, SVGs).

wiredsl's modules are byte-compiled first, as `pip install` does for an installed package: without their
.pyc files (an editable install under PYTHONDONTWRITEBYTECODE=1) every run would compile about 50 modules
from source, some 50 ms CPU that no installed wiredsl pays.
"""

from __future__ import annotations

import argparse
import compileall
import importlib.util
import os
import sys
import tempfile

sys.path.insert(0, os.path.dirname(__file__))

from _cli import best, load, run  # noqa: E402

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
import wiredsl.engine.montecarlo, wiredsl.io.emit, wiredsl.io.svg; mark("import montecarlo, emit, svg")
from wiredsl.language.compile import compile_file
scene, _, _ = compile_file("scenes/lab.wd"); mark("compile scenes/lab.wd")
from wiredsl.engine.world import build_world
from wiredsl.engine.montecarlo import Run
from wiredsl.engine.simulate import Options
world = build_world(scene)
run = Run.create(scene, world, scene.pipeline(), 1, Options()); run.engine = "numpy"
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


def byte_compile() -> None:
    """Write the .pyc files of the wiredsl the children import (the checkout's, from the current folder)."""
    spec = importlib.util.find_spec("wiredsl")
    compileall.compile_dir(os.path.dirname(spec.origin), quiet=1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--phases", action="store_true", help="only the phases of a paper build, in a new process")
    args = ap.parse_args()
    byte_compile()
    if args.phases:
        run(["-c", PHASES], quiet=False)
        return
    print(load())
    bare = best(["-c", "pass"], args.repeat)
    imports = best(["-c", "import numpy, lark, click, pydantic"], args.repeat)
    with tempfile.TemporaryDirectory() as out:
        build = best(["-m", "wiredsl", "build", "scenes/lab.wd", "--seed", "1", "-o", out], args.repeat)
        ideal = best(["-m", "wiredsl", "build", "scenes/lab.wd", "--no-effects", "-o", out], args.repeat)
    check = best(["-m", "wiredsl", "check", "scenes/lab.wd"], args.repeat)
    imports2 = best(["-c", "import numpy, lark, click, pydantic"], args.repeat)
    dep = min(imports.cpu, imports2.cpu)  # before and after: the machine is shared
    print(f"python -c pass                 : {bare.cpu:6.3f} s CPU")
    print(f"import numpy, lark, click, pydantic: {dep:6.3f} s CPU, {imports.rss:.0f} MiB")
    for name, c in (("wiredsl check scenes/lab.wd", check), ("wiredsl build --no-effects", ideal),
                    ("wiredsl build (paper pipeline)", build)):
        print(f"{name:31s}: {c.cpu:6.3f} s CPU = {c.cpu / dep:4.2f}x the imports (target <= 1.5x), "
              f"{c.wall:.3f} s wall, {c.rss:.0f} MiB")
    print(load())


if __name__ == "__main__":
    main()
