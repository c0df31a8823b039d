"""Regenerate the docs' Figure 7 and fitted pipeline of OpenCV's stereo chessboard images.

    python docs/scripts/verify_opencv_stereo.py

Runs `wiredsl verify scenes/chessboard.wd` on tests/data/opencv_stereo/*.jpg (13 pairs, Apache-2.0 /
BSD-3-Clause, see that folder's README.md) with the poses from the board (`--poses board`), Canny, LSD and
Harris, and `--fit`, seed 0; copies the plot to docs/figures/verify_opencv_stereo_figure7.png and the
fitted pipeline to docs/figures/verify_opencv_stereo_measured.wd, and prints the summary.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def main() -> None:
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "verify"
        run = subprocess.run([sys.executable, "-m", "wiredsl", "verify", "scenes/chessboard.wd", "--images",
                              "tests/data/opencv_stereo/*.jpg", "--poses", "board", "--detector", "canny",
                              "--detector", "lsd", "--detector", "harris", "--fit", "--seed", "0", "-o", str(out)],
                             cwd=ROOT, capture_output=True, text=True, check=False)
        sys.stdout.write(run.stdout)
        sys.stderr.write(run.stderr)
        if run.returncode:
            raise SystemExit(run.returncode)
        shutil.copy(out / "figure7.png", ROOT / "docs" / "figures" / "verify_opencv_stereo_figure7.png")
        shutil.copy(out / "measured.wd", ROOT / "docs" / "figures" / "verify_opencv_stereo_measured.wd")
        print((out / "measured.wd").read_text())


if __name__ == "__main__":
    main()
