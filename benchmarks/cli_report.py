"""Every speed and memory script in one sitting, for docs/performance.md: the machine, its load before and after,
and each script's own output, for this checkout and (--against REF) for another commit run alternately beside it,
so that both see the same machine.

    python benchmarks/cli_report.py [--against main] [--quick | --smoke] [--write [docs/performance.md]]

The scripts: cold_start.py, cli_ideal_view.py, cli_trials.py, big_scene.py --memory-only and memory_npz.py
(100,000 trials; --quick runs 10,000) through the command line, then throughput.py and vs_opencv.py
in-process, then the study scripts: study_speed.py and study_scaling.py (--quick: fewer trials and points).
--smoke runs every script with tiny sizes (seconds each): it checks the runner and the scripts, not the figures.
--against REF checks REF out into a temporary git worktree and runs the same scripts there (its own benchmarks,
its own wiredsl on PYTHONPATH, the same Python).

--write also runs `wiredsl bench scenes/lab.wd --budget 200` (this checkout; --quick 20 s, --smoke 1 s) and
rewrites the marked regions of docs/performance.md (or the file given), keeping everything else byte for byte:

    <!-- cli_report: NAME -->
    ... replaced ...
    <!-- /cli_report: NAME -->

with NAME `bench` (the bench's tables as it prints them) and `scripts` (a table: each script's headline lines,
those its record below keeps, a column a tree, and the sitting's machine and load).
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "performance.md"


@dataclass(frozen=True)
class Script:
    name: str  # the file in benchmarks/
    full: tuple[str, ...]  # its arguments in a full sitting
    quick: tuple[str, ...]  # --quick
    smoke: tuple[str, ...]  # --smoke: tiny sizes
    headline: str  # a regex: the output lines that go into the docs' table
    target: str  # the target its docstring states


SCRIPTS = (
    Script("cold_start.py", (), (), ("--repeat", "1"), r"x the imports", "build <= 1.5x the imports"),
    Script("cli_ideal_view.py", (), (), ("--step", "0.5", "--repeat", "1"), r"per extra view|more a pose",
           "<= 0.5 ms a view"),
    Script("cli_trials.py", (), (), ("--trials", "16", "--repeat", "1"), r"^whole run|^marginal|^fixed cost",
           ">= 0.5x bare numpy"),
    Script("big_scene.py", ("--memory-only",), ("--memory-only",), ("--memory-only", "--trials", "10"),
           r"peak RSS", "< 250 MB"),
    Script("memory_npz.py", ("--trials", "100000"), ("--trials", "10000"), ("--trials", "40"),
           r"^\s*[\d,]+ trials\s*:", "linear in trials, < 250 MB"),
    Script("throughput.py", (), (), ("--trials", "64"), r"^wiredsl paper|^loading", ">= 0.5x bare numpy, aim 1.0x"),
    Script("vs_opencv.py", (), (), ("--trials", "8", "--rounds", "1"), r"^speed-up|ms a view",
           "batched >= 200x; ideal <= 0.5 ms a view and >= 5x"),
    Script("study_speed.py", (), ("--trials", "1024", "--repeat", "1"), ("--trials", "16", "--repeat", "1"),
           r"speed-up|overhead|the machine itself", ">= 1.7x on 2 processes; overhead < 20%"),
    Script("study_scaling.py", (), ("--points", "64"), ("--points", "4", "--workers", "1,2"),
           r"workers:.*speed-up", "efficiency >= 0.8"),
)


def arguments(script: Script, size: str) -> list[str]:
    return [script.name, *{"full": script.full, "quick": script.quick, "smoke": script.smoke}[size]]


def commit(tree: Path) -> str:
    return subprocess.run(["git", "-C", str(tree), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True, check=True).stdout.strip()


def run_script(tree: Path, args: list[str]) -> tuple[bool, str]:
    """(succeeded, what it printed and the wall time it took)."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, str(tree / "benchmarks" / args[0]), *args[1:]], cwd=tree, env=env,
                          capture_output=True, text=True)
    took = time.perf_counter() - t0
    if proc.returncode != 0:
        return False, f"FAILED ({proc.returncode}) after {took:.0f} s:\n{proc.stderr[-2000:]}"
    return True, proc.stdout.rstrip() + f"\n({took:.0f} s wall for the script)"


def headline(script: Script, ok: bool, output: str) -> str:
    """The table cell of one script's run: its headline lines, spaces squeezed, joined by '; '."""
    if not ok:
        return "failed"
    lines = [" ".join(line.split()) for line in output.splitlines() if re.search(script.headline, line)]
    return "; ".join(lines).replace("|", "\\|") or "(no headline line: see the script's output)"


def scripts_table(results: dict[str, dict[str, tuple[bool, str]]], trees: list[tuple[str, str]],
                  machine: str) -> str:
    """The `scripts` region: the sitting's machine, then a row a script, a column a tree."""
    heads = [f"{name} ({sha})" for name, sha in trees]
    out = [machine, "", "| script | " + " | ".join(heads) + " | target |", "|---" * (len(heads) + 2) + "|"]
    for script in SCRIPTS:
        if script.name not in results:
            continue
        cells = [headline(script, *results[script.name][name]) for name, _ in trees]
        args = " ".join(results[script.name]["args"])
        out.append(f"| `{args}` | " + " | ".join(cells) + f" | {script.target} |")
    return "\n".join(out)


MARK = re.compile(r"<!-- cli_report: (\w+) -->\n(.*?)<!-- /cli_report: \1 -->", re.S)


def rewrite(text: str, regions: dict[str, str]) -> str:
    """`text` with each marked region's content replaced by regions[NAME] (a region not in `regions` is kept);
    every region named must be in the text, once."""
    found = [m.group(1) for m in MARK.finditer(text)]
    for name in regions:
        if found.count(name) != 1:
            raise SystemExit(f"the document has {found.count(name)} regions marked '{name}' (it needs one: "
                             f"<!-- cli_report: {name} --> ... <!-- /cli_report: {name} -->)")

    def fill(m: re.Match) -> str:
        name = m.group(1)
        body = regions[name].strip("\n") + "\n" if name in regions else m.group(2)
        return f"<!-- cli_report: {name} -->\n{body}<!-- /cli_report: {name} -->"

    return MARK.sub(fill, text)


def bench_tables(size: str) -> str:
    """`wiredsl bench scenes/lab.wd`'s tables as it prints them, less its own heading."""
    budget = {"full": "200", "quick": "20", "smoke": "1"}[size]
    with tempfile.TemporaryDirectory() as tmp:
        proc = subprocess.run([sys.executable, "-m", "wiredsl", "bench", "scenes/lab.wd", "--budget", budget, "-o",
                               f"{tmp}/bench.svg"], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
                              capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"wiredsl bench failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    text = proc.stdout.strip()
    return re.sub(r"\A## wiredsl bench .*\n+", "", text) + f"\n\n(`--budget {budget}`)"


def load() -> str:
    return "load average " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", default=None, help="another commit to measure beside this checkout")
    size = ap.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="10,000 trials in memory_npz.py, smaller studies")
    size.add_argument("--smoke", action="store_true", help="every script with tiny sizes: the runner, not figures")
    ap.add_argument("--write", nargs="?", const=str(DOC), default=None, metavar="FILE",
                    help="rewrite the marked tables of FILE (default docs/performance.md)")
    args = ap.parse_args()
    how = "smoke" if args.smoke else "quick" if args.quick else "full"
    import numpy

    started = time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())
    machine = (f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
               f"numpy {numpy.__version__}; {started}")
    print(machine)
    before = load()
    print(f"uptime before: {before}")
    trees = [("this checkout", ROOT)]
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        if args.against:
            other = Path(tmp) / "against"
            subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(other), args.against],
                           check=True)
            trees.append((args.against, other))
        try:
            shas = [(name, commit(tree)) for name, tree in trees]
            print("trees: " + "; ".join(f"{name} at {sha}" for name, sha in shas))
            for script in SCRIPTS:
                argv = arguments(script, how)
                results[script.name] = {"args": argv}
                for name, tree in trees:
                    print(f"\n## {' '.join(argv)} ({name}, {commit(tree)})", flush=True)
                    ok, output = run_script(tree, argv)
                    results[script.name][name] = (ok, output)
                    print(output, flush=True)
        finally:
            if args.against:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(other)], check=False)
    after = load()
    print(f"\nuptime after: {after}")
    if args.write:
        regions = {"bench": bench_tables(how),
                   "scripts": scripts_table(results, shas, f"{machine}; {before} before, {after} after"
                                            + ("; smoke sizes, not figures" if how == "smoke" else ""))}
        path = Path(args.write)
        text = rewrite(path.read_text(encoding="utf-8"), regions)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
        print(f"wrote the regions {', '.join(regions)} of {path}")


if __name__ == "__main__":
    main()
