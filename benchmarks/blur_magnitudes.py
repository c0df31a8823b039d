"""What motion blur does to Canny's edges (issue 39 item 3): a wall of vertical straight edges drawn by
`wiredsl render` smeared along an image vector of known length and angle to the edges (Look.smear: the mean of
sub-frames at most render.SUBFRAME_PX apart, as an exposure is drawn), detected with Canny at its defaults,
verified and fitted (`verify --fit`); prints the fitted edge loss and lateral shift range (and the approximation
error) with their 95% intervals, per (blur length, angle to the edge).

    python benchmarks/blur_magnitudes.py [--lengths 0 4 8 10] [--angles 0 45 90] [--seed 39] [--json FILE]

The wall: tests/data/verify/fence.wd's ten vertical lines (no corners, no faces), 3 m away, seen by its rig from
its five poses (ten images a setting), as 12 px step edges of grey 70 on 190 (the verification round trip's
look), plus Gaussian noise of 2 grey levels keyed by the seed; the blur's component across an edge is
length * sin(angle). The motion_blur effect's table (wiredsl/effects/motion_blur.py) is this script's output.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
KEYS = ("edge_loss.fraction", "lateral_shift.range", "approx_error.sigma")
NOISE = 2.0  # grey levels


def wall() -> str:
    """The fence scene with its vertical lines alone."""
    lines = (ROOT / "tests/data/verify/fence.wd").read_text().splitlines()
    keep = [x for x in lines if not x.strip().startswith(("line h", "line s", "corner "))]
    text = "\n".join(keep).replace("scene fence", "scene blur_wall")
    return text[:text.index("pipeline injected")]


def setting(length: float, angle: float, seed: int, folder: Path, scene_file: Path) -> dict:
    """{parameter: (fitted, lo, hi)} of one (length px, angle deg) setting."""
    sys.path.insert(0, str(ROOT))
    import wiredsl
    from wiredsl.io import render
    from wiredsl.verify import command

    a = math.radians(angle)
    smear = (length * math.sin(a), length * math.cos(a))  # the edges run along the image's y axis
    look = render.Look(noise=NOISE, edges="step", width=12, faces="none", background=190, ink=70, smear=smear)
    img = folder / f"img_{length:g}_{angle:g}"
    render.write(img, wiredsl.compile(str(scene_file)), seed=seed, look=look)
    req = command.Request(str(scene_file), [(str(img / "*.png"), None)], ["canny"], fit=True, seed=seed,
                          predict=False, spreads=False)
    fit = command.run(req, folder / f"out_{length:g}_{angle:g}").fit
    return {key: (fit.get(key).value, fit.get(key).lo, fit.get(key).hi) for key in KEYS}


def measure(lengths, angles, seed: int, progress=None) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as d:
        scene_file = Path(d) / "blur_wall.wd"
        scene_file.write_text(wall())
        for length in lengths:
            for angle in angles:
                if length == 0 and angle != angles[0]:
                    continue  # no blur has no angle
                fitted = setting(length, angle, seed, Path(d), scene_file)
                rows.append({"length": length, "angle": angle,
                             "across": length * abs(math.sin(math.radians(angle))), **fitted})
                if progress is not None:
                    progress(rows[-1])
    return rows


def cell(v) -> str:
    value, lo, hi = v
    f = lambda x: "-" if x is None else f"{x:.3g}"  # noqa: E731
    return f"{f(value)} [{f(lo)}, {f(hi)}]"


def table(rows: list[dict]) -> str:
    out = ["| blur length (px) | angle to the edge (deg) | across the edge (px) | edge loss [95%] "
           "| lateral shift range px [95%] | approx. error sigma px [95%] |", "|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['length']:g} | {r['angle']:g} | {r['across']:.2f} | {cell(r['edge_loss.fraction'])} "
                   f"| {cell(r['lateral_shift.range'])} | {cell(r['approx_error.sigma'])} |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--lengths", type=float, nargs="+", default=[0, 4, 8, 10])
    ap.add_argument("--angles", type=float, nargs="+", default=[0, 45, 90])
    ap.add_argument("--seed", type=int, default=39)
    ap.add_argument("--json", default=None, help="also write the rows as JSON here")
    args = ap.parse_args()
    rows = measure(args.lengths, args.angles, args.seed,
                   progress=lambda r: print(f"length {r['length']:g} angle {r['angle']:g}: "
                                            f"loss {cell(r['edge_loss.fraction'])}", file=sys.stderr, flush=True))
    print(table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
