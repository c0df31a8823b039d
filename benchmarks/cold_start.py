"""Cold start: `wiredsl build scenes/lab.wd` from a new process against Python importing just the
dependencies a build needs (numpy, lark, click, pydantic). Best CPU time of several runs each, measured in the
same run (target: build within 1.5x of the imports).

    python benchmarks/cold_start.py [--repeat 7]

`python -X importtime -m wiredsl build ...` shows where the imports' time goes.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile

sys.path.insert(0, os.path.dirname(__file__))

from _cli import best, load  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
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
