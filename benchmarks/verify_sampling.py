"""How the chessboard's fitted lateral shift (and the other edge estimates) depend on the verification's
sampling step and search band (issue 34: at most 0.1 px between `--step 0.25` and `--step 2`, and between
`--band 3` and `--band 6`).

    python benchmarks/verify_sampling.py [--detector canny]

Runs `wiredsl verify scenes/chessboard.wd --images 'tests/data/opencv_stereo/*.jpg' --poses board --detector
canny --fit` (OpenCV's 13 stereo pairs, Apache-2.0 / BSD-3-Clause: see that folder's README.md) at each
setting, seed 0, and prints the fitted values with their 95% intervals.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SETTINGS = [("2", "6"), ("1", "6"), ("0.5", "6"), ("0.25", "6"), ("2", "3"), ("2", "4.5"), ("0.5", "3")]
KEYS = ("lateral_shift.range", "approx_error.sigma", "edge_loss.fraction")


def fitted(step: str, band: str, detector: str, out: Path) -> dict:
    run = subprocess.run([sys.executable, "-m", "wiredsl", "verify", "scenes/chessboard.wd", "--images",
                          "tests/data/opencv_stereo/*.jpg", "--poses", "board", "--detector", detector, "--fit",
                          "--no-calibration-error", "--step", step, "--band", band, "--seed", "0", "-o", str(out)],
                         cwd=ROOT, capture_output=True, text=True, check=False)
    if run.returncode:
        sys.stderr.write(run.stderr)
        raise SystemExit(run.returncode)
    return {e["parameter"]: e for e in json.loads((out / "fit.json").read_text())["estimates"]}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--detector", default="canny")
    args = ap.parse_args()
    print(f"| step px | band px | {' | '.join(KEYS)} |")
    print("|---|---|" + "---|" * len(KEYS))
    with tempfile.TemporaryDirectory() as d:
        for k, (step, band) in enumerate(SETTINGS):
            est = fitted(step, band, args.detector, Path(d) / str(k))
            cells = []
            for key in KEYS:
                e = est[key]
                if e["value"] is None:
                    cells.append("-")
                    continue
                span = f" [{e['low95']:.3g}, {e['high95']:.3g}]" if e["low95"] is not None else ""
                cells.append(f"{e['value']:.3g}{span}")
            print(f"| {step} | {band} | {' | '.join(cells)} |", flush=True)


if __name__ == "__main__":
    main()
