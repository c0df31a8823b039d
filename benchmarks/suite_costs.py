"""What the test suite's tests cost: each test's CPU time (setup, call and teardown; its own process's and the
processes it ran and waited for) and wall time, the slowest listed, and the totals of chosen test files. The
figures docs/explanation/testing.md quotes.

    python benchmarks/suite_costs.py [--top 15] [--file tests/test_fuzz.py] [-- PYTEST ARGS]

Runs `python -m pytest -n 2` (or the given arguments) with this module as a plug-in (`-p suite_costs`): in each
worker it measures every test with getrusage (self and waited-for children) and the clock, and the controller
writes the figures to a file this script reads. The whole run's CPU (os.wait4) and wall, and the load average
before and after, are printed beside them: on a shared machine, CPU is the figure to compare.
"""

from __future__ import annotations

import json
import os
import resource
import time

import pytest

OUT = "SUITE_COSTS_OUT"


def _now() -> tuple[float, float]:
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime, time.perf_counter()


def _timed(item):
    cpu, wall = _now()
    yield
    cpu2, wall2 = _now()
    item.user_properties += [("suite_costs_cpu", cpu2 - cpu), ("suite_costs_wall", wall2 - wall)]


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_setup(item):
    yield from _timed(item)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item):
    yield from _timed(item)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item):
    yield from _timed(item)


_FOUND: dict[str, dict] = {}


def pytest_runtest_logreport(report):
    if report.when != "teardown":  # the teardown report holds all three phases' properties
        return
    props = report.user_properties
    _FOUND[report.nodeid] = {"cpu": sum(v for k, v in props if k == "suite_costs_cpu"),
                             "wall": sum(v for k, v in props if k == "suite_costs_wall")}


def pytest_sessionfinish(session):
    if os.environ.get(OUT) and not hasattr(session.config, "workerinput"):
        with open(os.environ[OUT], "w") as f:
            json.dump(_FOUND, f)


def main() -> None:
    import argparse
    import sys
    import tempfile
    from pathlib import Path

    here = Path(__file__).resolve().parent
    sys.path.insert(0, str(here))
    from _cli import load, run

    argv = sys.argv[1:]
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--top", type=int, default=15)
    ap.add_argument("--file", action="append", default=[], help="print this test file's total too (repeatable)")
    args = ap.parse_args(argv)
    print(load(), f"cores {os.cpu_count()}")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "costs.json"
        env = {OUT: str(out), "PYTHONPATH": os.pathsep.join([str(here), os.environ.get("PYTHONPATH", "")])}
        child = run(["-m", "pytest", "-p", "suite_costs", "-p", "no:cacheprovider", *(extra or ["-n", "2"])],
                    env=env, cwd=str(here.parent))
        found = json.loads(out.read_text())
    print(f"pytest {' '.join(extra or ['-n', '2'])}: {len(found)} tests, wall {child.wall:.0f} s, "
          f"CPU {child.cpu:.0f} s (all workers)")
    print(f"slowest {args.top} by CPU (s): cpu\twall\ttest")
    for nodeid, t in sorted(found.items(), key=lambda kv: -kv[1]["cpu"])[:args.top]:
        print(f"{t['cpu']:.1f}\t{t['wall']:.1f}\t{nodeid}")
    for name in args.file:
        mine = [t for nodeid, t in found.items() if nodeid.split("::")[0] == name]
        print(f"{name}: {len(mine)} tests, CPU {sum(t['cpu'] for t in mine):.1f} s, "
              f"wall {sum(t['wall'] for t in mine):.1f} s (summed over its tests)")
    print(load())


if __name__ == "__main__":
    main()
