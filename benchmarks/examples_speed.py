"""What the examples the closed-loop tutorial runs cost (docs/tutorials/closed-loop.md): the Gymnasium example
`examples/gym/evaluate.py --episodes 10` (its steps counted from its output: an observation at a pose, both
cameras, each) and the closed loop `examples/closed_loop/drive_to_bin.py` as CI runs it (100 trials per lateral
shift range, six ranges, with its plot).

    python benchmarks/examples_speed.py [--repeat 1] [--episodes 10] [--trials 100]

Each run is a new process (benchmarks/_cli.py): its CPU time (os.wait4: user + system) and wall time, imports
included, best of `--repeat` by CPU. The load average is printed before and after.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _cli import load, run  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--episodes", type=int, default=10)
    ap.add_argument("--trials", type=int, default=100)
    args = ap.parse_args()
    print(load())
    with tempfile.TemporaryDirectory() as tmp:
        gym = []
        for k in range(args.repeat):
            out = Path(tmp) / f"gym{k}.json"
            child = run([str(ROOT / "examples" / "gym" / "evaluate.py"), "--episodes", str(args.episodes), "-o",
                         str(out)], cwd=str(ROOT))
            steps = round(sum(r["mean_steps"] * r["episodes"] for r in json.loads(out.read_text())))
            gym.append((child, steps))
        child, steps = min(gym, key=lambda g: g[0].cpu)
        print(f"gym evaluate.py --episodes {args.episodes}\t{steps} steps\tCPU {child.cpu:.1f} s\t"
              f"wall {child.wall:.1f} s\t{child.cpu / steps * 1e3:.1f} ms of CPU a step, imports and resets included")
        loops = [run([str(ROOT / "examples" / "closed_loop" / "drive_to_bin.py"), "--trials", str(args.trials), "-o",
                      str(Path(tmp) / f"loop{k}")], cwd=str(ROOT)) for k in range(args.repeat)]
        child = min(loops, key=lambda c: c.cpu)
        print(f"closed_loop drive_to_bin.py --trials {args.trials}\tCPU {child.cpu:.1f} s\twall {child.wall:.1f} s")
    print(load())


if __name__ == "__main__":
    main()
