"""What reading a long trajectory file costs: a 100,000-pose TUM file (100 Hz for 1,000 s of a smooth walk),
read and judged by `wiredsl.io.trajectory.read` (what `path read` does), then resampled every 0.1 s (slerp), and
the whole `wiredsl check` of a scene whose path reads it, from a new process. Figures quoted by
docs/tutorials/path.md.

    python benchmarks/read_trajectory.py [--poses 100000] [--repeat 3]

In-process figures are the best of `--repeat` by CPU time (process time), with that run's wall time; the check's
are the child's own CPU (os.wait4) and wall, best of `--repeat`. The load average is printed before and after.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from _cli import best, load  # noqa: E402


def tum_text(n: int, seed: int = 1) -> str:
    """n poses at 100 Hz: a smooth random walk in the plane at 1.5 m height, heading along the motion, with a
    little roll and pitch; quaternions (x, y, z, w) as TUM writes them, 4 decimals in position, 6 in rotation."""
    rng = np.random.default_rng(seed)
    t = 1305031102.0 + np.arange(n) / 100.0
    heading = np.cumsum(rng.normal(0, 0.01, n))
    step = 0.01 * np.column_stack([np.cos(heading), np.sin(heading)])
    xy = np.cumsum(step, axis=0)
    z = 1.5 + 0.02 * np.sin(np.arange(n) / 50)
    roll, pitch = 0.02 * np.sin(np.arange(n) / 37), 0.02 * np.cos(np.arange(n) / 41)
    cr, sr, cp, sp = np.cos(roll / 2), np.sin(roll / 2), np.cos(pitch / 2), np.sin(pitch / 2)
    cy, sy = np.cos(heading / 2), np.sin(heading / 2)
    q = np.column_stack([sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
                         cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy])
    rows = [f"{a:.4f} {x:.4f} {y:.4f} {c:.4f} {q0:.6f} {q1:.6f} {q2:.6f} {q3:.6f}"
            for a, x, y, c, (q0, q1, q2, q3) in zip(t, xy[:, 0], xy[:, 1], z, q, strict=True)]
    return "# timestamp tx ty tz qx qy qz qw\n" + "\n".join(rows) + "\n"


def timed(fn, repeat: int) -> tuple[float, float, object]:
    """(CPU s, wall s, result) of the run with the least CPU time."""
    runs = []
    for _ in range(repeat):
        c0, w0 = time.process_time(), time.perf_counter()
        out = fn()
        runs.append((time.process_time() - c0, time.perf_counter() - w0, out))
    return min(runs, key=lambda r: r[0])


def scene_text(file: Path) -> str:
    """`wiredsl init`'s starter scene (a crate, a camera, a rig) with its path read from `file`."""
    from wiredsl import init

    text = init.files("long")["scenes/long.wd"]
    start = text.index("path approach {")
    end = text.index("}", start) + 1
    return text[:start] + f'path long {{\n  read "{file}" format tum every 0.1s\n  body camera left\n}}' + text[end:]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--poses", type=int, default=100_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    from wiredsl.io import trajectory

    print(load())
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "long.tum"
        path.write_text(tum_text(args.poses))
        size = path.stat().st_size / 1e6
        cpu, wall, traj = timed(lambda: trajectory.read(path.read_text()), args.repeat)
        print(f"read\t{args.poses:,} poses\t{size:.1f} MB\tCPU {cpu:.2f} s\twall {wall:.2f} s")
        cpu, wall, (P, _) = timed(lambda: trajectory.resample(traj, every=0.1), args.repeat)
        print(f"resample every 0.1 s\t{len(P):,} poses\tCPU {cpu:.2f} s\twall {wall:.2f} s")
        scene = Path(tmp) / "long.wd"
        scene.write_text(scene_text(path))
        child = best(["-m", "wiredsl", "check", str(scene)], args.repeat)
        print(f"wiredsl check (a new process, reading it every 0.1 s)\tCPU {child.cpu:.2f} s\twall {child.wall:.2f} s"
              f"\tpeak RSS {child.rss:.0f} MiB")
    print(load())


if __name__ == "__main__":
    main()
