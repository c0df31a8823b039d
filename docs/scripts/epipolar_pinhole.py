"""How far the pinhole epipolar line (stereo_mismatch's band direction before it followed curves) is from the true
epipolar curve's tangent, brute force as tests/test_effects.py measures it (a 60 x 45 grid of pixels of the first
pose's left camera): on scenes/fisheye.wd (the largest angle within 100 px of the centre, the median, the share of
pixels over the default 5 deg band) and on scenes/lab.wd's mild barrel distortion (the largest). A JSON line.

    python docs/scripts/epipolar_pinhole.py
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

from test_effects import _epipolar_disagreement  # noqa: E402


def main() -> None:
    _, line, r = _epipolar_disagreement(str(ROOT / "scenes/fisheye.wd"))
    _, lab, _ = _epipolar_disagreement(str(ROOT / "scenes/lab.wd"))
    print(json.dumps({"within_100px": float(line[r < 100].max()), "median": float(np.median(line)),
                      "over_5deg": float(np.mean(line > 5)), "lab_max": float(lab.max())}))


if __name__ == "__main__":
    main()
