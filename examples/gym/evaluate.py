"""Evaluate two simple policies on wiredsl's Gymnasium environment: reach a pose 1.2 m in front of the lab's
waste bin (bin1), seeing the room through the rig's disturbed features.

- `goal`: a proportional controller that knows the goal pose (info["goal"]) and its own pose (obs["pose"]):
  turn towards the goal point, drive when facing it, then turn to face the bin;
- `random`: uniform random actions.

Prints each policy's success rate and mean return over the episodes; writes them as JSON with -o.

    python examples/gym/evaluate.py --episodes 20 [-o build/gym/evaluate.json]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

import wiredsl.gym as wg

ROOT = Path(__file__).resolve().parents[2]


def goal_policy(env: wg.WiredslEnv, obs: dict, info: dict) -> np.ndarray:
    x, y, h = (float(v) for v in obs["pose"])
    gx, gy, gh = info["goal"]
    d = math.hypot(gx - x, gy - y)
    want = math.atan2(gy - y, gx - x) if d > 0.5 * env.task.tolerance else gh
    err = math.atan2(math.sin(want - h), math.cos(want - h))
    forward = min(d / env.step_length, 1.0) if abs(err) < 0.3 and d > 0.5 * env.task.tolerance else 0.0
    return np.array([forward, np.clip(err / env.turn, -1.0, 1.0)], dtype=np.float32)


def evaluate(policy: str, episodes: int, seed: int) -> dict:
    env = wg.WiredslEnv(ROOT / "scenes" / "lab.wd", wg.Task("reach", "bin1"))
    env.action_space.seed(seed)
    successes, returns, steps = 0, [], []
    for episode in range(episodes):
        obs, info = env.reset(seed=seed + episode)
        total, done = 0.0, False
        while not done:
            action = goal_policy(env, obs, info) if policy == "goal" else env.action_space.sample()
            obs, reward, terminated, truncated, info = env.step(action)
            total += reward
            done = terminated or truncated
        successes += bool(terminated and reward > 5)
        returns.append(total)
        steps.append(info["step"])
    return {"policy": policy, "episodes": episodes, "success_rate": successes / episodes,
            "mean_return": float(np.mean(returns)), "mean_steps": float(np.mean(steps))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("-o", "--out", type=Path)
    args = ap.parse_args()
    results = [evaluate(p, args.episodes, args.seed) for p in ("goal", "random")]
    for r in results:
        print(f"{r['policy']:>6}: success {r['success_rate']:.2f}, mean return {r['mean_return']:.2f}, "
              f"mean steps {r['mean_steps']:.1f} over {r['episodes']} episodes")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
