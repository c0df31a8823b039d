"""Cold start: `wiredsl build scenes/lab.wd` from a new process against Python importing just
wiredsl's own dependencies (lark, pydantic, numpy, click, jsonschema). Best of several runs each,
measured in the same run (target: build within 1.5x of the imports).

    python benchmarks/cold_start.py [--repeat 7]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time


def best(cmd: list[str], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True)
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    py = sys.executable
    imports = best([py, "-c", "import lark, pydantic, numpy, click, jsonschema"], args.repeat)
    bare = best([py, "-c", "pass"], args.repeat)
    with tempfile.TemporaryDirectory() as out:
        build = best([py, "-m", "wiredsl", "build", "scenes/lab.wd", "--seed", "1", "-o", out], args.repeat)
        ideal = best([py, "-m", "wiredsl", "build", "scenes/lab.wd", "--no-effects", "-o", out], args.repeat)
    check = best([py, "-m", "wiredsl", "check", "scenes/lab.wd"], args.repeat)
    print(f"python -c pass                 : {bare:6.3f} s")
    print(f"import the dependencies        : {imports:6.3f} s")
    print(f"wiredsl check scenes/lab.wd    : {check:6.3f} s = {check / imports:4.2f} x the imports")
    print(f"wiredsl build --no-effects     : {ideal:6.3f} s = {ideal / imports:4.2f} x the imports")
    print(f"wiredsl build (paper pipeline) : {build:6.3f} s = {build / imports:4.2f} x the imports (target <= 1.5)")


if __name__ == "__main__":
    main()
