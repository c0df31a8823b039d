"""The fuzz campaign on the surfaces of issue 36 (not part of the default suite): the Gymnasium environment's
actions and arguments, the detectors' parameters on small images, the lenses' extreme parameters through check,
render and build, verify's pose files, and export of hostile scenes read back by pycolmap and rosbags.

    nice -n 10 python tests/fuzz_surfaces.py --budget 30000 --minutes 40 --out /tmp/fuzz-surfaces

Counts exit 3, hangs, crashes (a detector's segfault, in a child process), non-finite outputs and an
observation outside its space; keeps every finding's input in --out with summary.json, and prints the counts.
Inputs are drawn from random.Random(--seed) (same seed, same inputs); the exit status is 1 when anything was found.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import random
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

import numpy as np  # noqa: E402
from fuzz_campaign import Campaign  # noqa: E402

EXTREME = [0.0, -0.0, 1.0, -1.0, 0.5, 1e-300, -1e-300, 5e-324, 1e-12, 1e6, -1e6, 1e100, -1e100, 1e300, 1e308,
           2147483647.0, 2.0**31, 2.0**63, math.pi, 1 - 1e-16, 1 + 1e-16]
NONFINITE = [math.nan, math.inf, -math.inf]


def number(rng: random.Random, bad: bool = True) -> float:
    r = rng.random()
    if bad and r < 0.1:
        return rng.choice(NONFINITE)
    if r < 0.5:
        return rng.choice(EXTREME) * rng.choice([1, -1])
    return rng.uniform(-1, 1) * 10 ** rng.uniform(-8, 8)


# --------------------------------------------------------------------------- the Gymnasium environment

def gym(c: Campaign, n: int, rng: random.Random) -> None:
    import wiredsl
    import wiredsl.gym as wg

    lab = wiredsl.compile(ROOT / "scenes" / "lab.wd")
    envs = {m: wg.WiredslEnv(lab, wg.Task("reach", "bin1"), motion=m) for m in ("planar", "6dof")}
    for env in envs.values():
        env.reset(seed=0)

    def action(size: int):
        kind = rng.random()
        if kind < 0.5:  # the right shape, any numbers
            with np.errstate(over="ignore"):  # 1e300 as a float32 is inf: one more non-finite action
                return np.array([number(rng) for _ in range(size)], dtype=rng.choice([np.float32, np.float64]))
        if kind < 0.7:
            return np.zeros(rng.choice([0, 1, size - 1, size + 1, size * 2]))
        return rng.choice([None, "x", b"ab", 0.5, np.float32(0.1), np.array(0.2), [[0.1] * size], [None] * size,
                           {"a": 1}, object(), [0.1] * size, (0.1,) * size, np.array([1 + 2j] * size),
                           np.array([True] * size), ["0.1"] * size])

    for i in range(n):
        if c.expired():
            return
        if i % 50 == 49:  # arguments
            c.counts["gym:inputs"] += 1
            kwargs = {rng.choice(["start_noise", "step_length", "turn", "margin"]): number(rng),
                      **({"start": (number(rng, False), number(rng, False), number(rng, False))}
                         if rng.random() < 0.3 else {})}
            task = {rng.choice(["distance", "tolerance", "heading_tolerance"]): number(rng)}
            try:
                env = wg.WiredslEnv(lab, wg.Task("reach", "bin1", **task), **kwargs)
                for seed in range(3):
                    obs, _ = env.reset(seed=seed)
                    if not env.observation_space.contains(obs):
                        c.found("gym", "space", repr((kwargs, task, seed)), f"reset obs {obs['pose']}")
            except ValueError:
                pass
            except Exception as exc:  # noqa: BLE001
                c.found("gym", "exception", repr((kwargs, task)), f"{type(exc).__name__}: {exc}")
            continue
        motion = rng.choice(["planar", "6dof"])
        env = envs[motion]
        a = action(env.action_space.shape[0])
        c.counts["gym:inputs"] += 1
        before = (np.array(env._pose, copy=True), env._step)
        try:
            obs, reward, terminated, truncated, _ = env.step(a)
        except ValueError:
            if not (np.array_equal(before[0], env._pose) and before[1] == env._step):
                c.found("gym", "state", repr(a), "a refused action changed the state")
            continue
        except Exception as exc:  # noqa: BLE001
            c.found("gym", "exception", repr(a), f"{type(exc).__name__}: {exc}")
            env.reset(seed=i)
            continue
        if not env.observation_space.contains(obs) or not math.isfinite(reward):
            c.found("gym", "space", repr(a), f"obs pose {obs['pose']}, reward {reward}")
        if terminated or truncated:
            env.reset(seed=i)


# --------------------------------------------------------------------------- detectors (in a child: a segfault)

def _detector_worker(inputs: list, last: str) -> None:
    from wiredsl.verify import detectors as D

    for k, (name, shape, seed, pairs) in enumerate(inputs):
        Path(last).write_text(str(k))
        img = (np.random.default_rng(seed).random(shape) * 255).astype(np.uint8)
        det = D.BUILTIN[name]
        try:
            p = D.params_of(det, pairs)
        except ValueError:
            continue
        try:
            D.checked(det.detect(img, p), img.shape, name)
        except ValueError:
            pass


def _param_value(rng: random.Random) -> str:
    return rng.choice([repr(number(rng)), str(rng.randint(-5, 40)), str(2**31 - 1), "1e308", "inf", "nan", "-0",
                       "abc", "", "1e999", str(rng.randint(0, 10**6))])


def detectors(c: Campaign, n: int, rng: random.Random) -> None:
    from wiredsl.verify import detectors as D

    inputs = []
    for _ in range(n):
        name = rng.choice(list(D.BUILTIN))
        fields = list(D.BUILTIN[name].Params.model_fields)
        pairs = [f"{rng.choice(fields)}={_param_value(rng)}" for _ in range(rng.randint(0, 3))]
        shape = (rng.choice([1, 2, 3, 5, 7, 9, 14, 15, 16, 31, 64, 120]), rng.choice([1, 2, 3, 6, 11, 15, 16, 40, 160]))
        inputs.append((name, shape, rng.randrange(2**32), pairs))
    ctx = multiprocessing.get_context("fork")
    with tempfile.TemporaryDirectory() as tmp:
        last = os.path.join(tmp, "last")
        start = 0
        while start < len(inputs) and not c.expired():
            batch = inputs[start:start + 2000]
            proc = ctx.Process(target=_detector_worker, args=(batch, last))
            proc.start()
            proc.join(600)
            if proc.is_alive():
                proc.kill()
                proc.join()
            if proc.exitcode != 0:
                k = int(Path(last).read_text() or 0)
                c.found("detectors", "crash", repr(batch[k]), f"child exited {proc.exitcode} at {batch[k]}")
                c.counts["detectors:inputs"] += k + 1
                start += k + 1
                continue
            c.counts["detectors:inputs"] += len(batch)
            start += len(batch)


# --------------------------------------------------------------------------- lenses through check, render, build

LENS = """wiredsl 1
scene lens
model panel {
  face plate through (0, -0.3, 0.6) (0, 0.05, 0.6) (0, 0.05, 1.4) (0, -0.3, 1.4)
  line edge from (0, -0.3, 0.6) to (0, 0.05, 1.4)
  corner c at (0, 0.05, 1.0)
}
place panel as p at (1.5m, 0, 0)
camera eye {
  focal {focal}px
  size ({w}px, {h}px)
  centre ({cx}px, {cy}px)
{lens}
}
rig pair {
  left eye at (0, 0.05m, 1m) looking (1, 0.1, 0.02)
  right eye at (0, -0.05m, 1m) looking (1, 0.1, 0.02)
}
path here { pose (0, 0) heading 0deg }
"""
MODELS = {"radtan": ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"], "equidistant": ["k1", "k2", "k3", "k4"],
          "unified": ["xi", "k1", "k2", "p1", "p2"], "eucm": ["alpha", "beta"], "ds": ["xi", "alpha"], "fov": ["w"]}


def lens_text(rng: random.Random) -> str:
    model = rng.choice(list(MODELS))
    lines = [] if model == "radtan" else [f"  distortion {model}"]
    for key in rng.sample(MODELS[model], rng.randint(1, len(MODELS[model]))):
        v = number(rng, bad=False) if rng.random() < 0.5 else rng.uniform(-2, 2)
        lines.append(f"  {key} {v:.17g}")
    if model != "radtan" and rng.random() < 0.3:
        lines.append(f"  fov {rng.uniform(10, 360):.6g}deg")
    w, h = rng.choice([(1, 1), (7, 5), (15, 12), (40, 30), (64, 48)])
    focal = rng.choice([0.001, 1.0, 0.65 * w, 30 * w, 1e6])
    return (LENS.replace("{lens}", "\n".join(lines)).replace("{w}", str(w)).replace("{h}", str(h))
            .replace("{cx}", f"{w / 2:g}").replace("{cy}", f"{h / 2:g}").replace("{focal}", f"{focal:g}"))


def lenses(c: Campaign, n: int, rng: random.Random, work: Path) -> None:
    f = work / "_lens.wd"
    for _ in range(n):
        if c.expired():
            return
        text = lens_text(rng)
        f.write_text(text)
        r = c.invoke("lenses", ["check", "--diagnostics", "json", str(f)], text)
        if r is None or r.exit_code != 0:
            continue
        out = Path(tempfile.mkdtemp(dir=work))
        c.invoke("lenses", ["render", str(f), "-o", str(out / "r"), "--supersample", "1", "--seed", "1"], text, 60)
        r = c.invoke("lenses", ["build", str(f), "-o", str(out / "b"), "--no-svg", "--no-effects"], text, 60)
        if r is not None and r.exit_code == 0:
            _finite_json(c, "lenses", out / "b" / "features.json", text)


def _finite_json(c: Campaign, part: str, path: Path, data: str) -> None:
    try:
        json.loads(path.read_text(), parse_constant=lambda k: (_ for _ in ()).throw(ValueError(k)))
    except ValueError as exc:
        c.found(part, "nonfinite", data, f"{path.name}: {exc}")


# --------------------------------------------------------------------------- verify's pose files

def verify(c: Campaign, n: int, rng: random.Random, work: Path) -> None:
    import cv2
    from fuzz_campaign import _mutate_text

    img = work / "left_0.png"
    cv2.imwrite(str(img), (np.random.default_rng(0).random((120, 160)) * 255).astype(np.uint8))
    good = "".join(f"{1.0 + i:.1f} {0.1 * i} 0.0 1.0 0 0 0 1\n" for i in range(3))
    poses = work / "poses.txt"
    scene = ROOT / "tests" / "data" / "verify" / "fence.wd"
    for _ in range(n):
        if c.expired():
            return
        text = _mutate_text(rng, good)
        poses.write_text(text, encoding="utf-8", errors="surrogatepass")
        det = rng.choice(["canny", "lsd", "harris", "shi-tomasi"])
        extra = rng.choice([[], ["--refine"], ["--format", "tum"],
                            ["--param", f"min_distance={_param_value(rng)}"]])
        if det in ("canny", "lsd") and extra and extra[0] == "--param":
            extra = []
        c.invoke("verify", ["verify", str(scene), "--detector", det, "--images", str(img), "--poses", str(poses),
                            "-o", str(work / "vout"), *extra], text, 60)


# --------------------------------------------------------------------------- export read back

def export(c: Campaign, n: int, rng: random.Random, work: Path) -> None:
    f = work / "_export.wd"
    for _ in range(n):
        if c.expired():
            return
        text = lens_text(rng)
        f.write_text(text)
        fmt = rng.choice(["colmap", "rosbag2"])
        out = Path(tempfile.mkdtemp(dir=work)) / "x"
        args = ["export", str(f), "--format", fmt, "--no-effects", "-o", str(out)]
        if fmt == "colmap" and rng.random() < 0.5:
            args.append("--undistort")
        r = c.invoke("export", args, text, 60)
        if r is None or r.exit_code != 0:
            continue
        try:
            if fmt == "colmap":
                import pycolmap

                rec = pycolmap.Reconstruction(str(out / "ideal"))
                bad = [p for im in rec.images.values() for p in im.points2D if not np.isfinite(p.xy).all()]
                if bad:
                    c.found("export", "nonfinite", text, f"{len(bad)} 2D points not finite")
            else:
                from rosbags.highlevel import AnyReader

                with AnyReader([out / "ideal"]) as reader:
                    for conn, _, raw in reader.messages():
                        reader.deserialize(raw, conn.msgtype)
        except Exception as exc:  # noqa: BLE001
            c.found("export", "readback", text, f"{fmt}: {type(exc).__name__}: {exc}")


# --------------------------------------------------------------------------- the campaign

SHARE = {"gym": 0.2, "detectors": 0.7, "lenses": 0.06, "verify": 0.02, "export": 0.02}


def main_(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budget", type=int, default=30000, help="inputs in all (split over the parts)")
    ap.add_argument("--minutes", type=float, default=40.0, help="stop drawing new inputs after this long")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "wiredsl-fuzz-surfaces")
    ap.add_argument("--parts", default=",".join(SHARE))
    args = ap.parse_args(argv)
    os.chdir(ROOT)
    c = Campaign(args.out, time.monotonic() + 60 * args.minutes)
    parts = args.parts.split(",")
    total = sum(SHARE[p] for p in parts)
    started = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for p in parts:
            n = max(1, int(args.budget * SHARE[p] / total))
            rng = random.Random(f"{args.seed}:{p}")
            t0 = time.monotonic()
            if p == "gym":
                gym(c, n, rng)
            elif p == "detectors":
                detectors(c, n, rng)
            elif p == "lenses":
                lenses(c, n // 3 + 1, rng, work)  # check, render and build an input
            else:
                {"verify": verify, "export": export}[p](c, n, rng, work)
            print(f"{p}: {time.monotonic() - t0:.0f} s, {dict((k, v) for k, v in c.counts.items() if k.startswith(p))}",
                  file=sys.stderr, flush=True)
    inputs = sum(v for k, v in c.counts.items() if k.endswith(":inputs"))
    summary = {"inputs": inputs, "seconds": round(time.monotonic() - started), "counts": dict(c.counts),
               "findings": c.findings}
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps({k: v for k, v in summary.items() if k != "findings"}, indent=1))
    return 1 if c.findings else 0


if __name__ == "__main__":
    sys.exit(main_())
