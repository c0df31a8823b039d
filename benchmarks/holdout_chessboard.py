"""Held out, image by image, on OpenCV's stereo chessboard (tests/data/opencv_stereo, 13 pairs; issue 34 item 3).

    python benchmarks/holdout_chessboard.py

Runs `wiredsl verify scenes/chessboard.wd --poses board --detector canny --detector harris --edge-loss raw
--no-calibration-error --holdout SPLIT --trials 50 --seed 0` for the splits odd and even (fit on about half the
pairs, predict the rest), with and without the spreads (`--no-spreads`: constant magnitudes, as before issue 34),
and prints per statistic the held-out images inside their simulated central 90% band.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run(out: Path, split: str, *more: str) -> dict:
    cmd = [sys.executable, "-m", "wiredsl", "verify", "scenes/chessboard.wd", "--images",
           "tests/data/opencv_stereo/*.jpg", "--poses", "board", "--detector", "canny", "--detector", "harris",
           "--edge-loss", "raw", "--no-calibration-error", "--holdout", split, "--trials", "50", "--seed", "0",
           *more, "-o", str(out)]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
    if done.returncode:
        sys.stderr.write(done.stderr)
        raise SystemExit(done.returncode)
    return json.loads((out / "holdout.json").read_text())["summary"]


def main() -> None:
    with tempfile.TemporaryDirectory() as d:
        got = {(split, mode): run(Path(d) / f"{split}-{mode}", split, *([] if mode == "spreads" else ["--no-spreads"]))
               for split in ("odd", "even") for mode in ("constants", "spreads")}
    keys = list(got[("odd", "spreads")])
    print("| statistic | constants: odd | constants: even | spreads fitted: odd | spreads fitted: even |")
    print("|---|---|---|---|---|")
    for k in keys:
        cells = []
        for mode in ("constants", "spreads"):
            for split in ("odd", "even"):
                s = got[(split, mode)].get(k)
                cells.append("-" if s is None else f"{s['inside']}/{s['images']} ({100 * s['inside_fraction']:.0f}%)")
        print(f"| {k} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
