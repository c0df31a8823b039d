"""A closed loop: a robot drives to the waste bin from what its stereo rig sees, with wiredsl in the loop.

Each step the robot observes the lab through `wiredsl.Simulator.observe` (every uncertainty source of the
chosen pipeline applied, draws keyed by trial and step), finds the bin in both images (its silhouette
lines, else its rim), takes the bearing and the range from its stereo disparity, filters the range with its odometry,
turns towards the bin and drives on. It stops when it believes it is within `--stop` of the bin's side.
A trial succeeds when the robot stopped and is truly within `--tolerance` of that distance, facing the bin.

    python examples/closed_loop/drive_to_bin.py --trials 100 --shifts 0,2,4,8,16,32 -o build/closed_loop

writes `closed_loop.json` (success rate and steps per lateral shift, with the arguments and the run's `digest`)
and `closed_loop.png`.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
from pathlib import Path

import numpy as np

import wiredsl
from wiredsl.files import write_atomic

HERE = Path(__file__).resolve().parent
LAB = HERE.parent.parent / "scenes" / "lab.wd"
BIN = np.array([4.6, 3.2])  # bin1's axis on the floor (scenes/lab.wd)
BIN_RADIUS = 0.2
START = (1.0, 1.2, 0.2)  # x, y (m), heading (rad)


def scene_with_shift(shift_px: float):
    """The lab with a pipeline 'drive': lateral shift at the given range, and the paper's fitting error."""
    return wiredsl.compile(f"""wiredsl 1
include {json.dumps(str(LAB))}
pipeline drive {{
  lateral_shift range {shift_px:g}px
  approx_error sigma 0.15px
}}
""")


def stroke_points(obs, camera: int, feature: int, segment: int | None = None) -> np.ndarray:
    """The vertices (n, 2) of one feature's strokes in one camera (0 left, 1 right), from the batch's arrays."""
    rows = obs["strokes"]  # columns: trial, pose, camera, feature, segment, ... (the npz layout)
    pick = (rows[:, 2] == camera) & (rows[:, 3] == feature)
    if segment is not None:
        pick &= rows[:, 4] == segment
    start = obs["start"]
    parts = [obs["pts"][start[k]:start[k + 1]] for k in np.flatnonzero(pick)]
    return np.concatenate(parts) if parts else np.zeros((0, 2))


def bin_centre(obs, camera: int, ids: dict[str, int]) -> np.ndarray | None:
    """Where the bin's axis is in one camera (u, v) (px), or None when it is not seen.

    The mid-point of its two silhouette lines when both are seen (lateral shift moves them sideways), else
    the centre of its rim's bounding box."""
    sides = [stroke_points(obs, camera, ids["bin1.side"], seg) for seg in (0, 1)]
    if all(len(p) for p in sides):
        return np.mean([p.mean(axis=0) for p in sides], axis=0)
    rim = stroke_points(obs, camera, ids["bin1.rim"])
    if not len(rim):
        return None
    return (rim.min(axis=0) + rim.max(axis=0)) / 2.0


def estimate(obs, scene) -> tuple[float, float] | None:
    """(bearing (rad, left positive), range (m)) of the bin's axis from the robot's centre, or None.

    The bin's centre is triangulated from its disparity (the rig is parallel: both cameras look the same way;
    each camera's own principal point is taken off) and taken to the robot's frame through the left mount.
    """
    ids = {name: i for i, name in enumerate(obs.feature_ids)}
    left, right = bin_centre(obs, 0, ids), bin_centre(obs, 1, ids)
    if left is None or right is None:
        return None
    rig = scene.rig
    cl, cr = scene.camera(rig.left.camera), scene.camera(rig.right.camera)
    fx, fy = cl.f * cl.ax, cl.f * cl.ay
    disparity = (left[0] - cl.cx) - (right[0] - cr.cx) * fx / (cr.f * cr.ax)
    if disparity <= 0.5:
        return None
    z = fx * float(np.linalg.norm(np.subtract(rig.left.position, rig.right.position))) / disparity
    in_robot = np.asarray(rig.left.rotation) @ [(left[0] - cl.cx) / fx * z, (left[1] - cl.cy) / fy * z, z] \
        + np.asarray(rig.left.position)
    return math.atan2(in_robot[1], in_robot[0]), float(np.hypot(in_robot[0], in_robot[1]))


def drive(sim, scene, trial: int, stop: float, max_steps: int, gain: float = 0.5) -> dict:
    """One trial: observe, filter the range (odometry predicts it, each observation corrects it), turn, drive."""
    x, y, h = START
    rng = None  # the filtered range to the bin's axis
    for step in range(max_steps):
        obs = sim.observe((x, y, h), trial=trial, step=step)
        est = estimate(obs, scene)
        if est is None:  # the bin is not seen by both cameras: turn on the spot and look again
            h += 0.25
            continue
        bearing, seen = est
        rng = seen if rng is None else (1 - gain) * rng + gain * seen
        if rng - BIN_RADIUS <= stop:
            truth = float(np.hypot(*(BIN - (x, y)))) - BIN_RADIUS
            return {"stopped": True, "steps": step + 1, "true_distance": truth}
        h += 0.8 * bearing
        advance = min(0.25, max(0.05, 0.5 * (rng - BIN_RADIUS - stop)))
        x, y = x + advance * math.cos(h), y + advance * math.sin(h)
        rng -= advance * math.cos(0.2 * bearing)
        if np.hypot(*(BIN - (x, y))) < BIN_RADIUS + 0.05:  # ran into it
            return {"stopped": False, "steps": step + 1, "true_distance": 0.0}
    return {"stopped": False, "steps": max_steps, "true_distance": float(np.hypot(*(BIN - (x, y)))) - BIN_RADIUS}


def positive(text: str) -> int:
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"not a positive integer: {text!r}")
    return int(text)


def seed(text: str) -> int:
    if not text.isdigit() or int(text) >= 2**63:
        raise argparse.ArgumentTypeError(f"not a seed (an integer in 0..2**63-1): {text!r}")
    return int(text)


def shift_ranges(text: str) -> list[float]:
    try:
        values = [float(s) for s in text.split(",")]
    except ValueError:
        values = []
    if not values or not all(math.isfinite(v) and v >= 0 for v in values):
        raise argparse.ArgumentTypeError(f"not a comma-separated list of ranges >= 0 (px): {text!r}")
    return values


RESULT_ARGS = ("trials", "shifts", "stop", "tolerance", "max_steps", "seed")  # what the results depend on


def digest(a: argparse.Namespace, scenes: list) -> str:
    """Identity of a run's results: its arguments, each shift's compiled scene, this script's code and wiredsl's
    version (docs/reproduce.py reuses CI's run when it is the run the page shows)."""
    body = {"arguments": {k: getattr(a, k) for k in RESULT_ARGS}, "script": Path(__file__).read_text(),
            "scenes": [s.model_dump(mode="json", exclude={"source"}) for _, s in scenes],
            "wiredsl": wiredsl.__version__}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def parse(argv=None) -> tuple[argparse.Namespace, list]:
    """The arguments and each shift's scene, or a usage error (exit 2) before any trial runs."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=positive, default=100)
    ap.add_argument("--shifts", type=shift_ranges, default="0,2,4,8,16,32",
                    help="lateral shift ranges (px), comma-separated")
    ap.add_argument("--stop", type=float, default=1.2, help="stop this far from the bin's side (m)")
    ap.add_argument("--tolerance", type=float, default=0.1, help="success: within this of --stop (m)")
    ap.add_argument("--max-steps", type=positive, default=60)
    ap.add_argument("--seed", type=seed, default=1)
    ap.add_argument("-o", "--out", default="build/closed_loop")
    ap.add_argument("--no-plot", action="store_true")
    a = ap.parse_args(argv)
    if not a.no_plot:
        try:
            import matplotlib  # noqa: F401  (checked before the trials run, not after)
        except ImportError:
            ap.error("the plot needs matplotlib: pip install '.[plot]' in wiredsl's checkout, or give --no-plot")
    try:  # every scene before the first trial: a shift the effect refuses is a usage error, not a traceback
        scenes = [(shift, scene_with_shift(shift)) for shift in a.shifts]
    except wiredsl.CompileError as err:
        ap.error(f"--shifts: {err}")
    return a, scenes


def main(argv=None) -> int:
    a, scenes = parse(argv)
    rows = []
    for shift, scene in scenes:
        sim = wiredsl.Simulator(scene, seed=a.seed, pipeline="drive")
        runs = [drive(sim, scene, k, a.stop, a.max_steps) for k in range(a.trials)]
        stopped = [abs(r["true_distance"] - a.stop) for r in runs if r["stopped"]]
        ok = [r["stopped"] and abs(r["true_distance"] - a.stop) <= a.tolerance for r in runs]
        steps = [r["steps"] for r, good in zip(runs, ok, strict=True) if good]
        rows.append({"lateral_shift_px": shift, "trials": a.trials, "success_rate": float(np.mean(ok)),
                     "mean_steps": float(np.mean(steps)) if steps else None,
                     "stopped_rate": len(stopped) / a.trials,
                     "mean_stop_error_m": float(np.mean(stopped)) if stopped else None})
        print(f"lateral shift {shift:5.1f} px: success {rows[-1]['success_rate']:.2f}, "
              f"steps {rows[-1]['mean_steps'] or float('nan'):.1f}", file=sys.stderr)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "closed_loop.json", json.dumps({
        "seed": a.seed, "rows": rows, "arguments": {k: getattr(a, k) for k in RESULT_ARGS},
        "digest": digest(a, scenes)}, indent=2, allow_nan=False) + "\n")
    if not a.no_plot:
        plot(rows, out / "closed_loop.png")
    return 0


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shift = [r["lateral_shift_px"] for r in rows]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.4), dpi=110)
    a1.plot(shift, [r["success_rate"] for r in rows], "o-")
    a1.set(xlabel="lateral shift range (px)", ylabel="success rate", ylim=(-0.02, 1.02),
           title="reaching the bin")
    a2.plot(shift, [r["mean_steps"] if r["mean_steps"] is not None else np.nan for r in rows], "o-")
    a2.set(xlabel="lateral shift range (px)", ylabel="steps (successful trials)", title="steps to the bin")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
