"""One ideal build per view, end to end through the command line: the CPU time a long path's extra views add
to `wiredsl build --no-effects` (target: <= 0.5 ms a view).

    python benchmarks/cli_ideal_view.py [--step 0.02] [--repeat 3]

scenes/lab.wd's path (7 poses, 14 views) is rebuilt with a finer step (0.02 m: 121 poses, 242 views); both
scenes are built as a user builds them (`wiredsl build SCENE --no-effects`, JSON dump, no SVG), and the extra
views' cost is the difference of the two CPU times over the difference of their views, which leaves out the
fixed cost of a run (imports, compiling, the view-point lists). The SVGs are measured apart (`--svg`).
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, os.path.dirname(__file__))

from _cli import best, lab_folder, load  # noqa: E402


def views(folder: str) -> int:
    import json

    doc = json.loads(Path(folder, "features.json").read_text())
    return sum(1 + (p["right"] is not None) for p in doc["poses"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--step", type=float, default=0.02)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    print(load())
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        lab_folder(folder)
        text = Path("scenes/lab.wd").read_text(encoding="utf-8")
        (folder / "short.wd").write_text(text, encoding="utf-8")
        (folder / "long.wd").write_text(re.sub(r"step 0\.4m", f"step {args.step}m", text), encoding="utf-8")
        got = {}
        for name in ("short", "long"):
            out = str(folder / f"out_{name}")
            got[name] = best(["-m", "wiredsl", "build", str(folder / f"{name}.wd"), "--no-effects", "--no-svg",
                              "-o", out], args.repeat), views(out)
        svg = best(["-m", "wiredsl", "build", str(folder / "long.wd"), "--no-effects", "-o", str(folder / "svg")],
                   args.repeat)
    (short, n_short), (long, n_long) = got["short"], got["long"]
    per = 1e3 * (long.cpu - short.cpu) / (n_long - n_short)
    print(f"lab, {n_short} views             : {short.cpu:.3f} s CPU ({short.wall:.3f} s wall)")
    print(f"lab, step {args.step} m, {n_long} views: {long.cpu:.3f} s CPU ({long.wall:.3f} s wall)")
    print(f"ideal build per extra view     : {per:.2f} ms CPU (target <= 0.5 ms)")
    print(f"  with the SVGs (one a pose)   : {1e3 * (svg.cpu - long.cpu) / (n_long / 2):.2f} ms CPU more a pose")
    print(load())


if __name__ == "__main__":
    main()
