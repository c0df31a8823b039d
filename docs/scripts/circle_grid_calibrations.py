"""The circle-grid scenes' camera files (scenes/calib/<set>.yml, OpenCV FileStorage YAML) from each photograph
set's own calibration (tests/data/circle_grids/<set>/calibration.json: OpenCV's calibrateCamera on that set's
detected dot centres, k1 k2 p1 p2 k3; see the set's README.md for how it was made and checked).

    python docs/scripts/circle_grid_calibrations.py [--check]

--check fails when a written file differs from what the calibration gives.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parents[2]
SETS = ("boofcv_sony_acircles_4x5", "boofcv_sony_circles_10x8")


def camera_file(calibration: Path) -> str:
    from wiredsl.io.calibration import opencv_yaml

    doc = json.loads(calibration.read_text())
    width, height = doc["image_size"]
    cam = {"K": np.array(doc["K"], float), "D": np.array(doc["dist_k1k2p1p2k3"], float), "width": width,
           "height": height}
    head, rest = opencv_yaml([cam]).split("---\n", 1)  # OpenCV wants its %YAML line first
    return (f"{head}---\n# written by docs/scripts/circle_grid_calibrations.py from tests/data/circle_grids/"
            f"{calibration.parent.name}/calibration.json (RMS {doc['rms_px']:.3f} px)\n{rest}")


def main(argv: list[str]) -> int:
    drift = 0
    for name in SETS:
        text = camera_file(HERE / "tests" / "data" / "circle_grids" / name / "calibration.json")
        out = HERE / "scenes" / "calib" / f"{name}.yml"
        if "--check" in argv:
            if not out.exists() or out.read_text() != text:
                print(f"{out.relative_to(HERE)} differs from its calibration.json", file=sys.stderr)
                drift += 1
        else:
            out.write_text(text)
            print(f"wrote {out.relative_to(HERE)}")
    return 1 if drift else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
