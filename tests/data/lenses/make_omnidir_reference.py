"""Writes omnidir_reference.npz: OpenCV's own Mei projection (cv2.omnidir.projectPoints, opencv-contrib) of random
points under random unified cameras, the second reference of tests/test_wide_lenses.py.

opencv-contrib's cv2 replaces opencv's, so it is not a test dependency: this script was run once with
`pip install --target DIR opencv-contrib-python-headless==5.0.0.93` and `PYTHONPATH=DIR python
tests/data/lenses/make_omnidir_reference.py`; the test reads the stored values.
"""

import math
from pathlib import Path

import cv2
import numpy as np

rng = np.random.default_rng(2607)
N_CAMERAS, N_POINTS = 320, 12
cams, points, pixels = [], [], []
for _ in range(N_CAMERAS):
    xi = rng.choice([rng.uniform(0.0, 1.0), rng.uniform(1.0, 3.0)])
    fx, fy = rng.uniform(200, 1200), rng.uniform(200, 1200)
    cx, cy = rng.uniform(300, 700), rng.uniform(200, 600)
    D = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.1, 0.1), rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01)])
    limit = math.acos(-min(xi, 1.0 / xi)) if xi > 0 else math.pi / 2
    limit = min(limit, math.radians(100))  # radtan on m stays far from its fold at these coefficients
    theta = limit * rng.uniform(0.0, 1.0, N_POINTS) ** 0.5
    phi = rng.uniform(-math.pi, math.pi, N_POINTS)
    d = rng.uniform(0.2, 30.0, N_POINTS)
    P = d[:, None] * np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    uv, _ = cv2.omnidir.projectPoints(P.reshape(1, -1, 3), np.zeros(3), np.zeros(3), K, float(xi), D.reshape(1, 4))
    cams.append([xi, fx, fy, cx, cy, *D])
    points.append(P)
    pixels.append(uv.reshape(-1, 2))
np.savez_compressed(Path(__file__).with_name("omnidir_reference.npz"), cameras=np.array(cams),
                    points=np.array(points), pixels=np.array(pixels), opencv=cv2.__version__)
print("wrote", len(cams), "cameras with opencv", cv2.__version__)
