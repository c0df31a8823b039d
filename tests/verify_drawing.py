"""A tiny synthetic drawing for the verification tests (independent of the engine's projection: OpenCV draws).

Each stroke is drawn as a step edge: a dark band on one side of it (BAND px wide) over a light background, so
the stroke itself is the band's edge; each corner is the corner of its own dark square (SQUARE px) extending
down and right. Supersampled SS times and averaged down (anti-aliased), then blurred and given noise. Pixel
(i, j)'s centre is at (i, j), OpenCV's (and cv2.projectPoints') convention.
"""

from __future__ import annotations

import cv2
import numpy as np

BAND = 12.0
SQUARE = 24.0
SS = 4
LIGHT, DARK = 190, 70


def _sub(p: np.ndarray) -> np.ndarray:
    """Pixel coordinates as fixed-point (shift 4) coordinates of the supersampled image."""
    return np.round(((np.asarray(p, float) + 0.5) * SS - 0.5) * 16).astype(np.int32)


def draw(strokes: list[np.ndarray], corners: list[np.ndarray], size=(640, 480), blur: float = 1.0,
         noise: float = 2.0, seed: int = 0) -> np.ndarray:
    w, h = size
    big = np.full((h * SS, w * SS), LIGHT, np.uint8)
    for pts in strokes:
        pts = np.asarray(pts, float)
        for a, b in zip(pts[:-1], pts[1:], strict=True):
            t = b - a
            n = np.array([-t[1], t[0]]) / max(np.hypot(*t), 1e-12)
            quad = np.array([a, b, b + BAND * n, a + BAND * n])
            cv2.fillConvexPoly(big, _sub(quad), DARK, cv2.LINE_8, 4)
    for c in corners:
        c = np.asarray(c, float).reshape(2)
        sq = np.array([c, c + (SQUARE, 0), c + (SQUARE, SQUARE), c + (0, SQUARE)])
        cv2.fillConvexPoly(big, _sub(sq), DARK, cv2.LINE_8, 4)
    img = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    if noise > 0:
        img += np.random.default_rng(seed).normal(0, noise, img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def render_records(records: list[dict], folder, size=(640, 480), blur=1.0, noise=2.0, seed=0) -> list[str]:
    """One PNG per camera and pose, `<camera>_<pose>.png`, from feature records (wiredsl.load / Batch.records)."""
    from pathlib import Path

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    views: dict[tuple[str, int], tuple[list, list]] = {}
    for r in records:
        v = views.setdefault((r["camera"], r["pose"]), ([], []))
        if r["kind"] == "corner":
            v[1].append(np.asarray(r["at"], float).reshape(2))
        elif r["kind"] in ("line", "polyline"):
            v[0].append(np.asarray(r["points"], float))
    out = []
    for k, ((cam, pose), (strokes, corners)) in enumerate(sorted(views.items())):
        path = folder / f"{cam}_{pose:03d}.png"
        cv2.imwrite(str(path), draw(strokes, corners, size, blur, noise, seed * 1000 + k))
        out.append(str(path))
    return out
