"""Regenerate the docs' Figure 7 and fitted pipeline of OpenCV's stereo chessboard images.

    python docs/scripts/verify_opencv_stereo.py

Runs `wiredsl verify scenes/chessboard.wd` on tests/data/opencv_stereo/*.jpg (13 pairs, Apache-2.0 /
BSD-3-Clause, see that folder's README.md) with the poses from the board (`--poses board`), Canny, LSD and
Harris, `--fit` and `--predict` (50 trials a frame), seed 0, `--no-calibration-error` (these images calibrated the
rig: its declared calibration uncertainty is not theirs to show); copies the plot to
docs/figures/verify_opencv_stereo_figure7.png, the fitted pipeline to docs/figures/verify_opencv_stereo_measured.wd
and the prediction plot to docs/figures/verify_opencv_stereo_prediction.png, and prints the summary. A second run
(Canny and Harris, `--edge-loss raw`) predicts with the other reading of the edge loss and prints its comparison
(docs/figures/verify_opencv_stereo_prediction_raw.png).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _verify(out: Path, *args: str) -> None:
    run = subprocess.run([sys.executable, "-m", "wiredsl", "verify", "scenes/chessboard.wd", "--images",
                          "tests/data/opencv_stereo/*.jpg", "--poses", "board", *args, "--fit", "--predict",
                          "--no-calibration-error",
                          "--trials", "50", "--seed", "0", "-o", str(out)],
                         cwd=ROOT, capture_output=True, text=True, check=False)
    sys.stdout.write(run.stdout)
    sys.stderr.write(run.stderr)
    if run.returncode:
        raise SystemExit(run.returncode)


def main() -> None:
    figures = ROOT / "docs" / "figures"
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "verify"
        _verify(out, "--detector", "canny", "--detector", "lsd", "--detector", "harris")
        shutil.copy(out / "figure7.png", figures / "verify_opencv_stereo_figure7.png")
        shutil.copy(out / "measured.wd", figures / "verify_opencv_stereo_measured.wd")
        shutil.copy(out / "prediction.png", figures / "verify_opencv_stereo_prediction.png")
        print((out / "measured.wd").read_text())
        raw = Path(d) / "raw"
        print("--edge-loss raw:")
        _verify(raw, "--detector", "canny", "--detector", "harris", "--edge-loss", "raw")
        shutil.copy(raw / "prediction.png", figures / "verify_opencv_stereo_prediction_raw.png")


if __name__ == "__main__":
    main()
