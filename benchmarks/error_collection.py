"""Collecting errors scales linearly: checks of 10k, 20k and 40k erroneous lines.

Each line `scene 1` is one error (E106). Before the error count was kept by the
collector, every statement counted the list of errors so far, so a check of n
bad lines took O(n^2) (measured 2.4, 7.6 and 34.5 s from the command line).
Prints seconds per size and the ratio of each to the previous: ~2 is linear,
~4 quadratic.

    python benchmarks/error_collection.py [--sizes 10000 20000 40000]
"""

from __future__ import annotations

import argparse
import time

from wiredsl.diagnostics import WiredslError, render
from wiredsl.language.ast import Program, parse_text
from wiredsl.language.compile import compile_program


def check_seconds(n: int) -> float:
    """Seconds to parse, compile and render the diagnostics of n lines of `scene 1`."""
    text = "wiredsl 1\n" + "scene 1\n" * n
    t0 = time.perf_counter()
    file = parse_text(text, "bad.wd")
    try:
        compile_program(Program(file, files={"bad.wd": file}, statements=list(file.statements)))
    except WiredslError as err:
        assert len(err.diagnostics) == n
        render(err.diagnostics, {"bad.wd": text})
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 20_000, 40_000])
    args = ap.parse_args()
    check_seconds(1000)  # warm up: the parser's tables
    print("| lines | seconds | ratio to the previous size |")
    print("|---|---|---|")
    prev = None
    for n in args.sizes:
        s = check_seconds(n)
        ratio = f"{s / prev:.2f}" if prev else "-"
        print(f"| {n:,} | {s:.3f} | {ratio} |")
        prev = s


if __name__ == "__main__":
    main()
