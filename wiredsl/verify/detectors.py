"""Feature detectors: OpenCV's Canny, LSD, Harris and Shi-Tomasi, and a researcher's own as a plug-in.

A detector takes an 8-bit grey image (height, width) and gives a `Detection`: an edge map with the
gradient at each edge pixel (Canny; a plug-in may give the same), line segments (LSD), or corners
(Harris, Shi-Tomasi), in pixels with OpenCV's convention (pixel (i, j)'s centre at x = i, y = j, as
cv2.projectPoints and the engine's projection give them).

A plug-in is a subclass of `Detector` registered in the entry-point group `wiredsl.detectors`:

    [project.entry-points."wiredsl.detectors"]
    my_edges = "my_package.detect:MyEdges"

with `name` (its entry point's), `doc`, a pydantic `Params` whose fields all have defaults, and
`detect(cls, image, params) -> Detection`. It is loaded only when `--detector` names it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field


@dataclass
class Detection:
    """What a detector found in one image. Any part may be None.

    edges: (H, W) bool, the edge pixels; gx, gy: (H, W) float32, the grey-level gradient there (its
    direction is the edge's normal; its length the edge strength); segments: (n, 4) float (x0, y0, x1, y1);
    corners: (m, 2) float (x, y).
    """

    edges: np.ndarray | None = None
    gx: np.ndarray | None = None
    gy: np.ndarray | None = None
    segments: np.ndarray | None = None
    corners: np.ndarray | None = None
    note: str = ""  # what the detector did that the user should know (a fallback)

    @property
    def has_edges(self) -> bool:
        return self.edges is not None or self.segments is not None

    @property
    def has_corners(self) -> bool:
        return self.corners is not None


class DetectorParams(BaseModel):
    # allow_inf_nan: a NaN or infinite parameter means nothing to a detector (min_distance=inf crashed OpenCV)
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Detector:
    """A detector: `name`, `doc`, `Params` (every field with a default) and `detect`."""

    name: str = ""
    doc: str = ""
    Params: type[BaseModel] = DetectorParams
    finds = "edges"  # "edges" | "corners": what the verification tests

    @classmethod
    def detect(cls, image: np.ndarray, params) -> Detection:
        raise NotImplementedError


class CannyParams(DetectorParams):
    low: float = Field(50.0, ge=0, description="hysteresis low threshold (gradient magnitude)")
    high: float = Field(150.0, ge=0, description="hysteresis high threshold")
    aperture: int = Field(3, description="Sobel aperture: 3, 5 or 7")
    l2: bool = Field(False, description="L2 gradient magnitude (else L1)")
    blur: float = Field(0.0, ge=0, le=20, description="Gaussian pre-smoothing sigma in px (0: none)")


class Canny(Detector):
    name = "canny"
    doc = "cv2.Canny edges; the gradient at each edge pixel from cv2.Sobel with the same aperture."
    Params = CannyParams

    @classmethod
    def detect(cls, image, p: CannyParams) -> Detection:
        import cv2

        if p.aperture not in (3, 5, 7):
            raise ValueError("aperture must be 3, 5 or 7")
        img = cv2.GaussianBlur(image, (0, 0), p.blur) if p.blur > 0 else image
        edges = cv2.Canny(img, p.low, p.high, apertureSize=p.aperture, L2gradient=p.l2) > 0
        gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=p.aperture)
        gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=p.aperture)
        return Detection(edges=edges, gx=gx, gy=gy)


class LSDParams(DetectorParams):
    # at least 0.05: OpenCV's LSD smooths with sigma 0.6 / scale, and a scale of 1e-8 ran for ever
    scale: float = Field(0.8, ge=0.05, le=1, description="image scale the segments are found at")
    min_length: float = Field(5.0, ge=0, description="shorter segments are dropped (px)")


class LSD(Detector):
    name = "lsd"
    doc = ("cv2.createLineSegmentDetector (LSD, von Gioi et al.); where the installed OpenCV lacks it, "
           "cv2.ximgproc's FastLineDetector, else Canny + cv2.HoughLinesP (the note says which ran).")
    Params = LSDParams

    @classmethod
    def detect(cls, image, p: LSDParams) -> Detection:
        import cv2

        note = ""
        try:
            lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD, p.scale)
            lines = lsd.detect(image)[0]
        except (AttributeError, cv2.error):
            if hasattr(cv2, "ximgproc"):
                lines, note = cv2.ximgproc.createFastLineDetector().detect(image), "LSD unavailable: FastLineDetector"
            else:
                edges = cv2.Canny(image, 50, 150)
                lines = cv2.HoughLinesP(edges, 1, np.pi / 360, 30, minLineLength=max(p.min_length, 10), maxLineGap=2)
                note = "LSD unavailable in this OpenCV: Canny + HoughLinesP"
        seg = np.zeros((0, 4)) if lines is None else np.asarray(lines, float).reshape(-1, 4)
        keep = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]) >= p.min_length
        return Detection(segments=seg[keep], note=note)


class CornerParams(DetectorParams):
    max_corners: int = Field(2000, ge=1, le=100000, description="at most this many, strongest first")
    quality: float = Field(0.01, gt=0, le=1, description="weakest response kept, relative to the strongest")
    min_distance: float = Field(5.0, ge=0, description="closest two corners may be (px)")
    block: int = Field(3, ge=2, le=31, description="neighbourhood of the structure tensor (px)")
    k: float = Field(0.04, gt=0, lt=0.25, description="Harris' k")
    subpix_window: int = Field(5, ge=1, le=30, description="cv2.cornerSubPix half window (px)")


class Harris(Detector):
    name = "harris"
    doc = "Harris-Stephens corners (cv2.goodFeaturesToTrack with useHarrisDetector), refined by cv2.cornerSubPix."
    Params = CornerParams
    finds = "corners"
    harris = True

    @classmethod
    def detect(cls, image, p: CornerParams) -> Detection:
        import cv2

        h, w = image.shape[:2]
        # a min_distance beyond the image's diagonal keeps one corner, as the diagonal does; OpenCV's grid of
        # min_distance cells overflows an int (and segfaults) near 2**31 px
        min_distance = min(p.min_distance, math.hypot(h, w) + 1.0)
        pts = cv2.goodFeaturesToTrack(image, p.max_corners, p.quality, min_distance, blockSize=p.block,
                                      useHarrisDetector=cls.harris, k=p.k)
        if pts is None:
            return Detection(corners=np.zeros((0, 2)))
        pts = pts.astype(np.float32)
        # cv2.cornerSubPix asserts an image of at least 2 x window + 5 px each way: a smaller image gets the
        # largest window that fits, or no refinement at all
        window = min(p.subpix_window, (min(h, w) - 5) // 2)
        note = ""
        if window < p.subpix_window:
            note = (f"image {w} x {h} px too small for the sub-pixel window {p.subpix_window}: "
                    + (f"refined with window {window}" if window >= 1 else "corners not refined"))
        if window >= 1:
            crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
            cv2.cornerSubPix(image, pts, (window, window), (-1, -1), crit)
        return Detection(corners=pts.reshape(-1, 2).astype(float), note=note)


class ShiTomasi(Harris):
    name = "shi-tomasi"
    doc = "Shi-Tomasi corners (cv2.goodFeaturesToTrack, minimum eigenvalue), refined by cv2.cornerSubPix."
    harris = False


BUILTIN: dict[str, type[Detector]] = {d.name: d for d in (Canny, LSD, Harris, ShiTomasi)}


def _check(obj) -> str | None:
    if getattr(obj, "finds", None) not in ("edges", "corners"):
        return "declares `finds` neither 'edges' nor 'corners'"
    if obj.detect.__func__ is Detector.detect.__func__:
        return "does not define detect()"
    return None


def registry():
    from wiredsl.plugins import Registry

    global _REGISTRY
    if _REGISTRY is None:
        _REGISTRY = Registry("detector", BUILTIN, Detector, _check)
    return _REGISTRY


_REGISTRY = None


def params_of(detector: type[Detector], pairs: list[str]):
    """The detector's Params from `key=value` strings (ValueError naming what is wrong)."""
    values: dict[str, object] = {}
    fields = detector.Params.model_fields
    for pair in pairs:
        key, eq, value = pair.partition("=")
        key = key.strip().replace("-", "_")
        if not eq or key not in fields:
            known = ", ".join(fields) or "none"
            raise ValueError(f"detector '{detector.name}' has no parameter {key!r} (its parameters: {known})")
        values[key] = value.strip()
    from pydantic import ValidationError

    try:
        return detector.Params(**values)
    except ValidationError as exc:
        first = exc.errors()[0]
        raise ValueError(f"detector '{detector.name}' parameter {'.'.join(map(str, first['loc']))}: "
                         f"{first['msg']}") from None


def checked(detection, shape: tuple[int, int], name: str) -> Detection:
    """A detector's output checked for shape and finiteness (ValueError saying what is wrong)."""
    if not isinstance(detection, Detection):
        raise ValueError(f"returned {type(detection).__name__}, not a wiredsl.verify.detectors.Detection")
    d = detection
    if d.edges is not None:
        d.edges = np.asarray(d.edges).astype(bool, copy=False)
        if d.edges.shape != shape:
            raise ValueError(f"returned an edge map of shape {d.edges.shape}, not the image's {shape}")
        for g in ("gx", "gy"):
            a = getattr(d, g)
            if a is None or np.shape(a) != shape:
                raise ValueError(f"returned an edge map without its gradient {g} of the image's shape")
            a = np.asarray(a, np.float32)
            if not np.isfinite(a[d.edges]).all():
                raise ValueError(f"returned a gradient {g} that is not finite at an edge pixel")
            setattr(d, g, a)
    for part, width in (("segments", 4), ("corners", 2)):
        a = getattr(d, part)
        if a is not None:
            a = np.asarray(a, float).reshape(-1, width)
            if not np.isfinite(a).all():
                raise ValueError(f"returned {part} that are not finite")
            setattr(d, part, a)
    if not (d.has_edges or d.has_corners):
        raise ValueError("returned neither edges, segments nor corners")
    return d


def segment_gradients(segments: np.ndarray, shape: tuple[int, int]):
    """Segments rasterised as an edge map: (edges, gx, gy, label), the gradient of each pixel the segment's unit
    normal and label its segment's index (-1 elsewhere), for the same search as an edge detector's."""
    import cv2

    h, w = shape
    label = np.full((h, w), -1, np.int32)
    if len(segments):
        # cv2.line on int32 images draws value i + 1; shift 4 gives sub-pixel end points
        canvas = np.zeros((h, w), np.int32)
        fixed = np.round(segments * 16).astype(np.int64)
        for i, (x0, y0, x1, y1) in enumerate(fixed):
            cv2.line(canvas, (int(x0), int(y0)), (int(x1), int(y1)), i + 1, 1, cv2.LINE_8, 4)
        label = canvas - 1
    edges = label >= 0
    d = segments[:, 2:] - segments[:, :2]
    n = np.column_stack([-d[:, 1], d[:, 0]]) / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)[:, None]
    gx = np.zeros((h, w), np.float32)
    gy = np.zeros((h, w), np.float32)
    gx[edges] = n[label[edges], 0]
    gy[edges] = n[label[edges], 1]
    return edges, gx, gy, label


def angle_ok(gx, gy, nx, ny, tolerance: float) -> np.ndarray:
    """Does the gradient (gx, gy) lie within `tolerance` (rad) of the normal (nx, ny), either way round?"""
    return np.abs(gx * nx + gy * ny) >= math.cos(tolerance) * np.hypot(gx, gy) * np.hypot(nx, ny) - 1e-12
