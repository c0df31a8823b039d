"""Real ellipses: the two BoofCV circle-grid photograph sets verified, fitted and held out (issue 34 item 4), beside
the lines of OpenCV's stereo chessboard (the paper's Figure 7 by feature kind).

    python benchmarks/circle_grids.py [--figure docs/figures/verify_by_kind.png]

For each set (tests/data/circle_grids/<set>/, CC BY 4.0, (c) Peter Abeles, BoofCV-Data) it runs

    wiredsl verify scenes/circles_<kind>.wd --images '<set>/images/*.jpg' --camera left --poses board
        --detector canny --fit --holdout odd --trials 50 --seed 0

for the split odd (fit on the even-numbered images, predict the others image by image; the same run's --fit fits
on all of them first), and the chessboard's `wiredsl verify scenes/chessboard.wd --images
'tests/data/opencv_stereo/*.jpg' --poses board --detector canny` for its lines. It prints, per set, the verified
fraction and the strokes' mean offsets of the detected edges (along each model stroke's own normal, whose side
depends on the stroke's direction), the fitted pipeline's magnitudes with their 95% intervals, and per held-out
statistic the images inside their simulated central 90% band; with --figure, the Figure 7 by kind.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SETS = {"asymmetric": "boofcv_sony_acircles_4x5", "symmetric": "boofcv_sony_circles_10x8"}


def verify(out: Path, scene: str, images: str, *more: str) -> Path:
    cmd = [sys.executable, "-m", "wiredsl", "verify", scene, "--images", images, "--poses", "board",
           "--detector", "canny", "--seed", "0", *more, "-o", str(out)]
    said = out / "command.json"  # (with --keep: a folder that ran this command already is taken as it is)
    if said.is_file() and json.loads(said.read_text()) == cmd[1:]:
        return out
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
    if done.returncode:
        sys.stderr.write(done.stderr)
        raise SystemExit(done.returncode)
    said.write_text(json.dumps(cmd[1:]))
    return out


def edges(out: Path) -> dict:
    """Per image the verified fraction, and every stroke's mean offset, weighted by its verified samples."""
    rows = [r for r in json.loads((out / "verification.json").read_text())["rows"] if r["kind"] == "edge"]
    images = sorted({r["image"] for r in rows})
    frac = [sum(r["verified"] for r in rows if r["image"] == i) / max(1, sum(r["samples"] for r in rows
                                                                          if r["image"] == i)) for i in images]
    off = np.array([r["offset_mean_px"] for r in rows if r["offset_mean_px"] is not None], float)
    w = np.array([r["verified"] for r in rows if r["offset_mean_px"] is not None], float)
    return {"images": len(images), "fractions": frac, "offsets": off, "weights": w,
            "verified": sum(r["verified"] for r in rows) / max(1, sum(r["samples"] for r in rows))}


def estimate(fit: dict, key: str) -> str:
    e = next(e for e in fit["estimates"] if e["parameter"] == key)
    scale, unit = (100, "%") if key.startswith("edge_loss") else (1, " px")
    if e["value"] is None:
        return f"not estimated ({e['note']}): {scale * e['used']:.3g}{unit} used"
    v = f"{scale * e['value']:.3g}{unit}"
    if e.get("low95") is not None and e.get("high95") is not None:
        v += f" [{scale * e['low95']:.3g}, {scale * e['high95']:.3g}]"
    return v


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--figure", type=Path, default=None)
    ap.add_argument("--keep", type=Path, default=None, help="Keep the verify outputs in this folder.")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        d = args.keep or Path(d)
        kinds = {"lines (chessboard)": edges(verify(d / "chess", "scenes/chessboard.wd",
                                                    "tests/data/opencv_stereo/*.jpg"))}
        held, fits = {}, {}
        for kind, folder in SETS.items():
            images = f"tests/data/circle_grids/{folder}/images/*.jpg"
            for split in ("odd",):
                out = verify(d / f"{kind}-{split}", f"scenes/circles_{kind}.wd", images, "--camera", "left",
                             "--fit", "--holdout", split, "--trials", "50")
                held[(kind, split)] = json.loads((out / "holdout.json").read_text())["summary"]
                if split == "odd":
                    fits[kind] = json.loads((out / "fit.json").read_text())
                    kinds[f"ellipses ({kind} grid)"] = edges(out)
    print("| features | images | verified | offset mean (px) | offset sd between strokes (px) |")
    print("|---|---|---|---|---|")
    for name, k in kinds.items():
        w = k["weights"] / k["weights"].sum()
        mean = float(w @ k["offsets"])
        sd = float(np.sqrt(w @ (k["offsets"] - mean) ** 2))
        print(f"| {name} | {k['images']} | {100 * k['verified']:.1f}% | {mean:+.3f} | {sd:.3f} |")
    print()
    print("| fitted on all images | " + " | ".join(f"{k} grid" for k in SETS) + " |")
    print("|---|" + "---|" * len(SETS))
    for key in ("edge_loss.fraction", "lateral_shift.range", "approx_error.sigma"):
        print(f"| {key} | " + " | ".join(estimate(fits[k], key) for k in SETS) + " |")
    print()
    splits = [(k, s) for k in SETS for s in ("odd",)]
    print("| held out: inside the 90% band | " + " | ".join(f"{k}: {s}" for k, s in splits) + " |")
    print("|---|" + "---|" * len(splits))
    for stat in held[splits[0]]:
        cells = []
        for ks in splits:
            s = held[ks].get(stat)
            cells.append("-" if s is None else f"{s['inside']}/{s['images']} ({100 * s['inside_fraction']:.0f}%)")
        print(f"| {stat} | " + " | ".join(cells) + " |")
    if args.figure is not None:
        figure(kinds, args.figure)


def figure(kinds: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.6), constrained_layout=True)
    names = list(kinds)
    for i, name in enumerate(names):
        f = np.array(kinds[name]["fractions"])
        a.plot(np.full(len(f), i) + np.linspace(-0.15, 0.15, len(f)), 100 * f, "o", ms=4)
        b.hist(kinds[name]["offsets"], bins=np.linspace(-1.5, 1.5, 61), weights=kinds[name]["weights"],
               density=True, histtype="step", label=name)
    a.set_xticks(range(len(names)), [n.replace(" (", "\n(") for n in names], fontsize=8)
    a.set_ylabel("verified per image (%)")
    a.set_title("Verified edges by feature kind (Canny)", fontsize=9)
    b.set_xlabel("a stroke's mean offset (px)")
    b.set_ylabel("density (by verified samples)")
    b.set_title("Offsets of the detected edges", fontsize=9)
    b.legend(fontsize=7)
    fig.savefig(path, dpi=110, metadata={"Software": None})
    plt.close(fig)


if __name__ == "__main__":
    main()
