"""Draw docs/figures/chessboard_real_and_rendered.png: OpenCV's left01.jpg beside the scene rendered from its pose.

    python docs/scripts/chessboard_figure.py [-o PNG]

Runs RENDERS below (`wiredsl render` of scenes/chessboard.wd at its first pose, the left camera: the ideal
projection with the board's faces and pattern, then the paper pipeline's disturbed edges alone) and puts the real
image and the two renders side by side at half size (2 x 2 pixel means), 4 px of white between them.
"""

from __future__ import annotations

import argparse
import io
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

from wiredsl.files import write_atomic

ROOT = Path(__file__).resolve().parents[2]
REAL = "tests/data/opencv_stereo/left01.jpg"
RENDERS = ["wiredsl render scenes/chessboard.wd --no-effects --edges none --pose 0 --cameras left",
           "wiredsl render scenes/chessboard.wd --pipeline paper --seed 1 --edges step --faces none --pose 0 "
           "--cameras left"]
GAP = 4  # px of white between the panels


def half(path: Path) -> np.ndarray:
    a = np.asarray(Image.open(path).convert("L"), dtype=np.float64)
    h, w = a.shape[0] // 2 * 2, a.shape[1] // 2 * 2
    return a[:h, :w].reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", type=Path, default=ROOT / "docs/figures/chessboard_real_and_rendered.png")
    a = ap.parse_args(argv)
    panels = [half(ROOT / REAL)]
    with tempfile.TemporaryDirectory() as tmp:
        for i, command in enumerate(RENDERS):
            out = Path(tmp) / str(i)
            subprocess.run([sys.executable, "-m", "wiredsl", *command.split()[1:], "-o", str(out)], cwd=ROOT,
                           check=True, capture_output=True)
            panels.append(half(out / "left_000.png"))
    gap = np.full((panels[0].shape[0], GAP), 255.0)
    row = np.hstack([x for p in panels for x in (p, gap)][:-1])
    buf = io.BytesIO()
    Image.fromarray(np.round(row).astype(np.uint8)).save(buf, format="PNG")
    write_atomic(a.output, buf.getvalue())
    print(f"wrote {a.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
