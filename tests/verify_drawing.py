"""A tiny synthetic drawing for the verification tests (independent of the engine's projection: OpenCV draws).

Each stroke is drawn as a step edge: a dark band on one side of it (BAND px wide) over a light background, so
the stroke itself is the band's edge; each corner is the corner of its own dark square (SQUARE px) extending
down and right. Anti-aliased by each pixel's covered area (`_half`), then blurred and given noise. Pixel (i, j)'s
centre is at (i, j), OpenCV's (and cv2.projectPoints') convention.
"""

from __future__ import annotations

import cv2
import numpy as np

BAND = 12.0
SQUARE = 24.0
LIGHT, DARK = 190, 70


def _half(d: np.ndarray, n: np.ndarray) -> np.ndarray:
    """The fraction of a pixel (a unit square about its centre) on the positive side of a line at signed
    distance d (px) from its centre, for the line's unit normal n: linear across the square's width along n
    (exact for axis-aligned lines, and half at d = 0 whatever the direction: no bias either way)."""
    return np.clip(d / (abs(n[0]) + abs(n[1])) + 0.5, 0.0, 1.0)


def _polygon(cover: np.ndarray, quad: np.ndarray) -> None:
    """Add the coverage of a convex quadrilateral (counter-clockwise in image axes) to `cover` (max)."""
    h, w = cover.shape
    lo = np.maximum(np.floor(quad.min(axis=0)) - 2, 0).astype(int)
    hi = np.minimum(np.ceil(quad.max(axis=0)) + 3, [w, h]).astype(int)
    if (hi <= lo).any():
        return
    ys, xs = np.mgrid[lo[1]:hi[1], lo[0]:hi[0]].astype(float)
    c = np.ones_like(xs)
    for a, b in zip(quad, np.roll(quad, -1, axis=0), strict=True):
        t = (b - a) / max(np.hypot(*(b - a)), 1e-12)
        n = np.array([-t[1], t[0]])  # inward for this winding
        c = np.minimum(c, _half((xs - a[0]) * n[0] + (ys - a[1]) * n[1], n))
    view = cover[lo[1]:hi[1], lo[0]:hi[0]]
    np.maximum(view, c, out=view)


def _ccw(quad: np.ndarray) -> np.ndarray:
    (ax, ay), (bx, by) = quad[1] - quad[0], quad[2] - quad[0]
    area = ax * by - ay * bx
    return quad if area > 0 else quad[::-1]


def draw(strokes: list[np.ndarray], corners: list[np.ndarray], size=(640, 480), blur: float = 1.0,
         noise: float = 2.0, seed: int = 0) -> np.ndarray:
    w, h = size
    cover = np.zeros((h, w))
    for pts in strokes:
        pts = np.asarray(pts, float)
        for a, b in zip(pts[:-1], pts[1:], strict=True):
            t = b - a
            if np.hypot(*t) < 1e-9:
                continue
            n = np.array([-t[1], t[0]]) / np.hypot(*t)
            _polygon(cover, _ccw(np.array([a, b, b + BAND * n, a + BAND * n])))
    for c in corners:
        c = np.asarray(c, float).reshape(2)
        _polygon(cover, _ccw(np.array([c, c + (SQUARE, 0), c + (SQUARE, SQUARE), c + (0, SQUARE)])))
    img = (LIGHT + (DARK - LIGHT) * cover).astype(np.float32)
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
