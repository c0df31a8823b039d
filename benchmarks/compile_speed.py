"""Compile speed: statements per second on a generated 50,000-statement scene.

Prints wiredsl's full compile (parse + AST + checks + pydantic Scene) next to
lark's bare LALR tree-building on the same text, measured in the same run so
the ratio is meaningful on a shared machine. Target: >= 10,000 statements/s.

    python benchmarks/compile_speed.py [--statements 50000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import time

import lark

from wiredsl.language import parse
from wiredsl.language.ast import Program, parse_text
from wiredsl.language.compile import compile_program


def generate(n_statements: int, light: bool = False) -> tuple[str, int]:
    """A scene of models holding lines, ellipses, silhouettes and corners, plus placements.

    The default mix is geometry-heavy (a line is ~19 tokens); `light` replaces lines by
    corners and pipeline-like statements (~9 tokens) to show how the rate depends on it."""
    out = ["wiredsl 1", "scene generated"]
    count = 2
    m = 0
    while count < n_statements:
        out.append(f"model m{m} {{")
        count += 1
        for i in range(24):
            x = i * 0.1
            out.append(f"  corner k{i} at ({x:.1f}, 0, 0)" if light else
                       f"  line l{i} from ({x:.1f}, 0, 0) to ({x:.1f}, 1m, 50cm)")
        out.append("  ellipse top centre (0, 0, 1) normal (0, 0, 1) axis (1, 0, 0) radii (0.3, 0.3)")
        out.append("  ellipse bottom centre (0, 0, 0) normal (0, 0, 1) axis (1, 0, 0) radii (0.3, 0.3)")
        out.append("  silhouette side between top bottom")
        out.append("  corner c at (0, 0, 0)" if light else "  corner c at (0, 0, 0) joins l0 l1")
        out.append("}")
        out.append(f"place m{m} as p{m} at ({m % 100}, {m // 100}, 0) rotate z {m % 360}deg")
        count += 29
        m += 1
    return "\n".join(out) + "\n", count


def best_of(repeat: int, fn) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--statements", type=int, default=50_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    for light in (False, True):
        text, n = generate(args.statements, light)
        measure(text, n, args.repeat, "light (~9 tokens a statement)" if light else "geometry (~19 tokens a statement)")


def measure(text: str, n: int, repeat: int, label: str) -> None:
    bare = lark.Lark(parse.grammar_path().read_text(), parser="lalr", postlex=parse.Brackets())

    def full():
        file = parse_text(text, "generated.wd")
        compile_program(Program(file, files={file.path: file}, statements=list(file.statements)))

    t_lark = best_of(repeat, lambda: bare.parse(text))
    t_full = best_of(repeat, full)
    print(f"{label}: {n:,} statements, {len(text) / 1e6:.1f} MB, best of {repeat}")
    print(f"  lark LALR tree only : {n / t_lark:8,.0f} statements/s  ({t_lark:.2f} s)")
    print(f"  wiredsl full compile: {n / t_full:8,.0f} statements/s  ({t_full:.2f} s) = {t_lark / t_full:.2f} x lark's "
          "tree-building rate (target >= 10,000/s)")

if __name__ == "__main__":
    main()
