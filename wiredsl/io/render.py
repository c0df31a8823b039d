"""Emit stage: what the cameras see of a scene, drawn as 8-bit greyscale images (`wiredsl render`).

A test and teaching device, not a renderer: flat-shaded faces, anti-aliased features, blur and sensor
noise, all in numpy, deterministic for a seed. What it draws:

- **Pixels.** OpenCV's convention: pixel (column c, row r) is centred on image point (c, r), so a feature
  projected to u = 12.0 lies on the centre of column 12 (as `cv2.projectPoints` and every detector say).
- **Faces** (the models' `face`s, mesh triangles, and the ruled sides between silhouette ellipses) by ray
  casting: every pixel's ray (`SUPERSAMPLE` x `SUPERSAMPLE` rays a pixel, averaged) meets the nearest
  triangle, whose grey is Lambert's |n . l| for a fixed light `LIGHT` (camera frame), kept `CONTRAST` grey
  levels off the background's and the ink's on its own side (`face_grey`: faces of both polarities, each with
  an outline). Any lens the engine
  knows, since rays come from undistorting the pixels. A calibration board's face carries its pattern
  (`board_albedo`).
- **Features** (after the pipeline's disturbances when one is given, hidden lines removed by the faces with
  the default `visibility exact`) as strokes whose pixel coverage is the exact box-filter integral across
  the stroke: `step` (the default) paints a band of `width` px on the left of the stroke's direction
  (image axes: the side of (dy, -dx); on a curve, its convex side: `_outside`), so the feature itself is a
  single step edge at sub-pixel accuracy, as an object's boundary is in a photograph; the band stops halfway
  to the next feature on its side (a thin ellipse's other half, a rim beside a silhouette: it never paints
  over another edge) and is mitred along a curve's chords (painted whole, not as a comb); `line` paints a line
  of `width` px centred on it;
  `none` draws no features (the faces alone: a calibration board's squares, say).
- **Corners** (`corners mark`): a small 2 x 2 checker (a saddle, what Harris and `cornerSubPix` find
  exactly) centred on each corner the pipeline kept, where it moved it.
- **Motion blur**: a camera that declares `exposure` on a path with times is drawn as the mean of sub-frames at
  times spread evenly over the exposure, centred on the pose's time (`exposure_times`), each the scene as the
  robot moved with its velocities at the pose sees it (effects/motion_blur.py `scene_at`), its pipeline's draws
  the same (keyed by trial, pose and camera) but for `motion_blur`'s, left out (it simulates what is drawn); as
  many sub-frames as make the image move at most `SUBFRAME_PX` from one to the next. `Look.smear` (dx, dy px)
  smears the drawn features along a known image vector instead, the same way (the blur benchmark's blur of known
  length and direction).
- **Blur** (Gaussian, sigma in px, scipy) then **noise** (Gaussian, in grey levels, drawn with the effects'
  keyed generator: stream `render_noise` of (seed, pose, camera)), then rounding to 0..255.

PNG files are written by a small zlib writer (no image library), atomically.
"""

from __future__ import annotations

import functools
import math
import struct
import warnings
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from wiredsl.engine import geometry
from wiredsl.scene import Camera

SUPERSAMPLE = 3  # rays a pixel side for the faces (their boundaries are anti-aliased by averaging)
LIGHT = (-0.4, -0.6, -1.0)  # towards the light, camera frame: above, left of and behind the camera
EDGES = ("step", "line", "none")
FACES = ("shaded", "none")
CORNERS = ("none", "mark")
TOLERANCE = 0.02  # px: largest deviation of a drawn polyline from the true image curve
NOISE_STREAM = "render_noise"
CONTRAST = 40.0  # grey levels: the least difference of a face's grey from the background's (face_grey)
PIECE = 3.0  # px: a step's band is clipped (render._clearance) piece by piece, segments cut to at most this long
MITRE_TURN = 0.5  # rad: a polyline's joins up to this turn are mitred (a curve's chords), sharper ones not (corners)
# px: motion blur's sub-frames are at most this far apart; their mean is within 0.7% of the contrast of the continuous
# smear's (a straight step edge smeared 2.5-9 px, against sub-frames 0.02 px apart)
SUBFRAME_PX = 0.5
MAX_SUBFRAMES = 512  # a longer smear is drawn with this many sub-frames (2 px apart at 1024 px of motion)
BACK = 0.8  # reflectance of a board's back (its pattern is printed on the side its z axis points away from)


@dataclass(frozen=True)
class Look:
    """How images are drawn: greys are 0..255."""

    blur: float = 0.0  # Gaussian sigma, px (0: none)
    noise: float = 0.0  # Gaussian sigma, grey levels (0: none)
    edges: str = "step"  # step | line
    width: float = 4.0  # px: the band beside a step edge, or a line's width
    ink: float = 30.0  # the grey of the features
    background: float = 128.0
    faces: str = "shaded"  # shaded | none
    corners: str = "none"  # none | mark
    mark: float = 4.0  # px: half the side of a corner mark
    supersample: int = SUPERSAMPLE  # rays a pixel side for the faces
    smear: tuple[float, float] = (0.0, 0.0)  # px: the features drawn smeared along this image vector (centred)
    boards: dict = field(default_factory=dict, compare=False)  # face source name -> board (see board_albedo)


@dataclass
class Image:
    """One rendered view: the path pose's index, the rig side, its camera and pose, and the pixels."""

    pose: int
    side: str
    camera: Camera
    R_cw: np.ndarray
    t_cw: np.ndarray
    pixels: np.ndarray  # (height, width) uint8
    subframes: int = 1  # drawn as the mean of this many sub-frames over its camera's exposure

    @property
    def name(self) -> str:
        return f"{self.side}_{self.pose:03d}.png"


# ----------------------------------------------------------------------------- the scene's views

def render(scene, *, pipeline=None, seed: int = 0, look: Look = Look(), poses=None, cameras: str = "both",
           visibility: str = "exact", world=None, force: bool = False) -> Iterator[Image]:
    """Every chosen view of the scene's path, drawn: trial 0 of `pipeline` (a Pipeline, None: the ideal
    projection) with `seed`, which also keys the noise. Images come pose by pose, left then right.

    Before the first image the work is estimated (`estimate`): beyond CPU_BUDGET or MEMORY_BUDGET the render is
    refused (RunSetupError naming --force) unless `force`. A camera with an exposure on a path with times is
    drawn as the mean of its sub-frames (`exposure_times`)."""
    from wiredsl.effects.motion_blur import scene_at
    from wiredsl.engine.world import build_world

    world = world if world is not None else build_world(scene)
    times = exposure_times(scene, world, poses, visibility)
    if times is not None and pipeline is not None:  # the blur is drawn: the stage that simulates it is left out
        pipeline = pipeline.model_copy(update={"stages": [s for s in pipeline.stages if s.effect != "motion_blur"]})
    if times is None:
        for r, side, view, img in _drawn(scene, world, pipeline, seed, look, poses, cameras, visibility, force):
            yield Image(r.index, side, view.camera, np.asarray(view.R_cw), np.asarray(view.t_cw),
                        finish(img, look, (seed, r.index, side)))
        return
    exposure = {side: scene.camera(getattr(scene.rig, side).camera).exposure for side in ("left", "right")}
    total: dict = {}
    for tau in times:  # sub-frames one at a time: the memory of one set of images
        within = [side for side in ("left", "right") if abs(tau) <= exposure[side] / 2]
        if not within or (cameras == "left" and "left" not in within):
            continue
        for r, side, _, img in _drawn(scene_at(scene, tau), world, pipeline, seed, look, poses, cameras, visibility,
                                      force):
            if side in within:
                n, acc = total.get((r.index, side), (0, 0.0))
                total[(r.index, side)] = (n + 1, acc + img)
    for r, side, view, img in _drawn(scene, world, pipeline, seed, look, poses, cameras, visibility, force):
        n, acc = total.get((r.index, side), (0, None))
        yield Image(r.index, side, view.camera, np.asarray(view.R_cw), np.asarray(view.t_cw),
                    finish(acc / n if n else img, look, (seed, r.index, side)), max(n, 1))


def exposure_times(scene, world, poses=None, visibility: str = "exact") -> np.ndarray | None:
    """The sub-frames' times (s, centred on the pose's) of a scene whose cameras expose over time, or None: the
    midpoints of n equal parts of the longest exposure, n the image motion over it (the largest distance a
    feature's vertex moves between the exposure's ends, in any view) over SUBFRAME_PX, rounded up (at least 2,
    at most MAX_SUBFRAMES). A shorter exposure of the other camera is drawn from the sub-frames within it."""
    if scene.path is None or scene.path.times is None or scene.rig is None:
        return None
    exposure = max(scene.camera(getattr(scene.rig, s).camera).exposure for s in ("left", "right"))
    if exposure <= 0:
        return None
    from wiredsl.effects.motion_blur import scene_at

    ends = [{(r.index, side, k): f.points for r, side, view in _views(scene_at(scene, tau), world, None, 0, poses,
                                                                       "both", visibility)
             for k, f in enumerate(view.features)} for tau in (-exposure / 2, exposure / 2)]
    motion = max((float(np.abs(ends[1][k] - p).max(initial=0.0)) for k, p in ends[0].items()
                  if k in ends[1] and ends[1][k].shape == p.shape), default=0.0)
    n = int(min(max(math.ceil(motion / SUBFRAME_PX), 2), MAX_SUBFRAMES))
    return exposure * ((np.arange(n) + 0.5) / n - 0.5)


def _views(scene, world, pipeline, seed, poses, cameras, visibility):
    """(pose result, side, view) of every chosen view, its features trial 0 of `pipeline` (None: ideal)."""
    from wiredsl.engine.simulate import Options
    from wiredsl.io import emit, viewdep
    from wiredsl.montecarlo import Run

    opts = Options(tolerance=TOLERANCE, visibility=visibility, poses=poses, right=cameras == "both",
                   viewdep=viewdep.of_scene(scene))
    run = Run.create(scene, world, pipeline, seed, opts)  # what wiredsl.run.start makes of these arguments
    run.engine = "numpy"  # one trial
    if run.stages:
        (_, batch_out), = list(run.batches([0]))
        results = emit.disturbed_results(batch_out, 0)
    else:
        results = run.ideal()
    return [(r, side, getattr(r, side)) for r in results for side in ("left", "right")
            if getattr(r, side) is not None]


def _drawn(scene, world, pipeline, seed, look, poses, cameras, visibility, force):
    """(pose result, side, view, float image before blur and noise) of every chosen view."""
    from wiredsl.engine.world import surface_triangles

    views = _views(scene, world, pipeline, seed, poses, cameras, visibility)
    tris, face_of = world.triangles, world.triangle_face
    sil, _ = surface_triangles(world)
    tris = np.concatenate([tris, sil]) if len(sil) else tris
    face_of = np.concatenate([face_of, np.full(len(sil), -1)])
    names = list(world.face_src)
    boards = {names.index(k): b for k, b in look.boards.items() if k in names}
    cost = estimate([v for _, _, v in views], tris, look)
    if not force and (cost.seconds > CPU_BUDGET or cost.bytes > MEMORY_BUDGET):
        from wiredsl.run import RunSetupError

        raise RunSetupError(f"{cost}, beyond the {CPU_BUDGET:g} s of CPU and {MEMORY_BUDGET / 1e9:g} GB a render may "
                            "take without --force: fewer poses (--pose), a smaller --supersample or --faces none",
                            "--force")
    rays: dict = {}
    for r, side, view in views:
        key = id(view.camera)
        if key not in rays:
            rays[key] = pixel_rays(view.camera, look.supersample)
        yield r, side, view, draw_view(view.camera, view.R_cw, view.t_cw, view.features, tris, face_of, look,
                                       rays=rays[key], boards=boards)


def render_view(cam: Camera, R_cw: np.ndarray, t_cw: np.ndarray, features, tris: np.ndarray, face_of: np.ndarray,
                look: Look, *, rays=None, boards: dict | None = None, noise_key=None) -> np.ndarray:
    """One camera's image (height, width) uint8: faces `tris` (T, 3, 3, world frame; `face_of` their face
    index, -1 none), then `features` (ImageFeature: strokes of pixels, corners), blur, noise."""
    return finish(draw_view(cam, R_cw, t_cw, features, tris, face_of, look, rays=rays, boards=boards), look,
                  noise_key)


def draw_view(cam: Camera, R_cw: np.ndarray, t_cw: np.ndarray, features, tris: np.ndarray, face_of: np.ndarray,
              look: Look, *, rays=None, boards: dict | None = None) -> np.ndarray:
    """render_view's greys (float) before blur and noise."""
    R_cw, t_cw = np.asarray(R_cw, float), np.asarray(t_cw, float)
    img = np.full((cam.height, cam.width), float(look.background))
    if look.faces == "shaded" and len(tris):
        rays = rays if rays is not None else pixel_rays(cam, look.supersample)
        img = shade_faces(cam, tris @ R_cw.T + t_cw, face_of, rays, look.background, boards or {}, tris,
                          look.ink if look.edges != "none" else None)
    if look.edges != "none":
        drawn = [f for f in features if f.kind in ("line", "polyline") and len(f.points) >= 2]
        cover = smeared_coverage(cam.width, cam.height, [f.points for f in drawn], [f.closed for f in drawn],
                                 look.edges, look.width, look.smear)
        img = img * (1 - cover) + look.ink * cover
    if look.corners == "mark":
        pts = np.array([f.points[0] for f in features if f.kind == "corner"]).reshape(-1, 2)
        img = draw_marks(img, pts, look.mark, look.ink, 255.0 - look.ink)
    return img


def smeared_coverage(width: int, height: int, strokes: list, closed: list, style: str, w: float,
                     smear=(0.0, 0.0)) -> np.ndarray:
    """stroke_coverage averaged over the strokes moved along `smear` (dx, dy px), centred: the midpoints of n equal
    parts of it, n = its length over SUBFRAME_PX rounded up (at most MAX_SUBFRAMES); no smear: stroke_coverage."""
    d = np.asarray(smear, dtype=float)
    length = float(np.hypot(*d))
    if length == 0:
        return stroke_coverage(width, height, strokes, closed, style, w)
    n = int(min(max(math.ceil(length / SUBFRAME_PX), 2), MAX_SUBFRAMES))
    total = np.zeros((height, width))
    for s in (np.arange(n) + 0.5) / n - 0.5:
        total += stroke_coverage(width, height, [np.asarray(p, float) + s * d for p in strokes], closed, style, w)
    return total / n


def finish(img: np.ndarray, look: Look, noise_key=None) -> np.ndarray:
    """Greys (float) blurred, noised and rounded to uint8."""
    if look.blur > 0:
        from scipy.ndimage import gaussian_filter

        img = gaussian_filter(img, look.blur, mode="nearest", truncate=4.0)
    if look.noise > 0:
        img = img + look.noise * sensor_noise(img.shape, *(noise_key or (0, 0, "left")))
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def sensor_noise(shape: tuple[int, int], seed: int, pose: int, side: str) -> np.ndarray:
    """Standard normal noise of one image, keyed (seed, pose, camera) as the effects' draws are."""
    from wiredsl.effects.base import CAMERA_INDEX, keyed_normal, stream_key

    key = stream_key(NOISE_STREAM, 0, pose, CAMERA_INDEX[side], seed)
    return keyed_normal(key, np.arange(shape[0] * shape[1], dtype=np.uint64)).reshape(shape)


# ----------------------------------------------------------------------------- cost

# What a render may take without --force, and the rates its estimate is made with (measured by
# benchmarks/render_cost.py on a loaded 2-core machine; the estimate is for refusing the absurd, not a forecast)
CPU_BUDGET = 600.0  # s
MEMORY_BUDGET = 1.5e9  # bytes
RAY_TESTS_A_SECOND = 1.0e8  # ray-triangle tests (samples in a triangle's box) a second
PIXELS_A_SECOND = 2.0e6  # pixels a second drawn, blurred, noised and written, per image
FEATURE_PIXELS_A_SECOND = 2.0e7  # pixels of strokes' boxes (the band's coverage) a second
TRIANGLE_SECONDS = 3e-5  # the fixed cost of casting one triangle's box in one tile
BLUR_TAPS_A_SECOND = 3e8  # the Gaussian's taps (2 passes of 8 sigma + 1 each, a pixel) a second
IMAGE_ARRAYS = 10  # float64 arrays of one image alive at once (the image, ink coverage, blur, noise)
TILE = 1024  # samples a side of the tiles the faces are ray-cast in: the rays' memory is bounded whatever the size
TILE_BYTES = TILE * TILE * 200  # the rays and hit tests of one tile


@dataclass(frozen=True)
class Cost:
    """A render's estimated work: ray-triangle tests, pixels, CPU seconds and peak bytes."""

    views: int
    ray_tests: float
    pixels: float
    seconds: float
    bytes: float

    def __str__(self) -> str:
        return (f"{self.views} view{'s' * (self.views != 1)} would take about {self.seconds:,.0f} s of CPU "
                f"({self.ray_tests:.3g} ray-triangle tests, {self.pixels:.3g} pixels) and "
                f"{self.bytes / 1e9:.2g} GB of memory")


def estimate(views, tris: np.ndarray, look: Look) -> Cost:
    """The work of drawing `views` (engine Views: camera, pose, features) with faces `tris` (T, 3, 3, world
    frame): the samples of every triangle's box, and of every stroke segment's, counted as the drawing meets
    them; the memory of the largest image."""
    tests = pixels = stroke = boxes = 0.0
    peak = 0.0
    for view in views:
        cam = view.camera
        n_pix = float(cam.width) * float(cam.height)
        pixels += n_pix
        peak = max(peak, IMAGE_ARRAYS * 8 * n_pix + TILE_BYTES)
        if look.faces == "shaded" and len(tris):
            R_cw, t_cw = np.asarray(view.R_cw, float), np.asarray(view.t_cw, float)
            b = _pixel_boxes(cam, tris @ R_cw.T + t_cw, look.supersample).astype(float)
            area = np.maximum(b[:, 1] - b[:, 0], 0) * np.maximum(b[:, 3] - b[:, 2], 0)
            tests += float(area.sum())
            boxes += float(np.ceil(area / TILE**2).sum())  # (at least one tile a triangle that shows)
        if look.edges != "none":
            reach = look.width + 2.0
            for f in view.features:
                if f.kind in ("line", "polyline") and len(f.points) >= 2:
                    P = np.asarray(f.points, float)
                    P = P[np.isfinite(P).all(axis=1)]
                    lo = np.clip(np.minimum(P[:-1], P[1:]) - reach, 0, [cam.width, cam.height])
                    hi = np.clip(np.maximum(P[:-1], P[1:]) + reach, 0, [cam.width, cam.height])
                    stroke += float(np.prod(np.maximum(hi - lo, 0), axis=1).sum())
    blur = pixels * 2 * (8 * look.blur + 1) if look.blur > 0 else 0.0
    seconds = (tests / RAY_TESTS_A_SECOND + boxes * TRIANGLE_SECONDS + pixels / PIXELS_A_SECOND
               + stroke / FEATURE_PIXELS_A_SECOND + blur / BLUR_TAPS_A_SECOND)
    return Cost(len(views), tests, pixels, seconds, peak)


# ----------------------------------------------------------------------------- faces

@dataclass
class Rays:
    """Camera-frame ray directions through a camera's sub-pixel sample points, made a tile at a time.

    Sample (i, j) of pixel (r, c) is at (c + (j + 0.5) / ss - 0.5, r + (i + 0.5) / ss - 0.5): the sample grid
    is (height ss, width ss). Under distortion the rays are solved on a grid of nodes every `step` px and
    interpolated by bicubic splines (the lens is smooth: within 1e-6 of the unit plane of each ray, far below a
    pixel, in the tests' lenses); `splines` is None for a pinhole."""

    cam: Camera
    ss: int
    u: np.ndarray  # (width ss,) sample columns, px
    v: np.ndarray  # (height ss,) sample rows, px
    splines: tuple | None = None  # x, y, z and the nodes' existence

    @property
    def shape(self) -> tuple[int, int]:
        return len(self.v), len(self.u)

    def tile(self, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        """Directions (r1 - r0, c1 - c0, 3) of sample rows [r0, r1) and columns [c0, c1), and which exist."""
        cam, u, v = self.cam, self.u[c0:c1], self.v[r0:r1]
        if self.splines is None:
            X = (u - cam.cx) / (cam.f * cam.ax)
            Y = (v - cam.cy) / (cam.f * cam.ay)
            D = np.stack(np.broadcast_arrays(X[None, :], Y[:, None], 1.0), axis=-1).astype(float)
            return D, np.ones((len(v), len(u)), dtype=bool)
        *xyz, exists = self.splines
        D = np.stack([sp(v, u) for sp in xyz], axis=-1)
        near = exists(v, u) > 0.999  # rays all of whose grid neighbours exist
        return np.where(near[..., None], D, 0.0), near


def _nodes(n: int, step: int) -> np.ndarray:
    """Spline nodes across [-1, n] every `step` px, and n itself; at least 4 (a bicubic spline's minimum)."""
    nodes = np.unique(np.concatenate([np.arange(-1.0, n + 1, step), [float(n)]]))
    return nodes if len(nodes) >= 4 else np.linspace(-1.0, float(n), 4)


def pixel_rays(cam: Camera, ss: int, step: int = 8) -> Rays:
    """The rays of `cam` at `ss` x `ss` samples a pixel (see Rays); under distortion the spline nodes solved."""
    from scipy.interpolate import RectBivariateSpline

    off = (np.arange(ss) + 0.5) / ss - 0.5
    u = (np.arange(cam.width)[:, None] + off[None, :]).ravel()
    v = (np.arange(cam.height)[:, None] + off[None, :]).ravel()
    if not geometry.is_distorted(cam):
        return Rays(cam, ss, u, v)
    gu, gv = _nodes(cam.width, step), _nodes(cam.height, step)
    G, ok = _rays_at(cam, np.stack(np.meshgrid(gu, gv), axis=-1).reshape(-1, 2))
    G, ok = G.reshape(len(gv), len(gu), 3), ok.reshape(len(gv), len(gu))
    splines = tuple(RectBivariateSpline(gv, gu, G[..., k], kx=3, ky=3) for k in range(3))
    return Rays(cam, ss, u, v, (*splines, RectBivariateSpline(gv, gu, ok.astype(float), kx=1, ky=1)))


def _rays_at(cam: Camera, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray directions (n, 3) of pixels (n, 2): (x, y, 1) on the unit plane, or unit vectors for a fisheye."""
    from wiredsl.measures.stereo3d import pixels_to_distorted, undistort

    if cam.distortion == "equidistant":  # rays at any angle: the unit sphere
        xd = pixels_to_distorted(uv, cam)
        rd = np.hypot(xd[:, 0], xd[:, 1])
        theta, res = geometry.fisheye_theta(rd, cam.k1, cam.k2, cam.k3, cam.k4)
        ok = np.isfinite(theta) & (res < 1e-9) & (theta >= 0) & (theta < geometry.lens_limit(cam))
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.where(rd > 0, np.sin(theta) / np.where(rd > 0, rd, 1), 1.0)
        D = np.column_stack([xd * s[:, None], np.cos(theta)])
    else:
        xy, ok = undistort(uv, cam)
        D = np.column_stack([xy, np.ones(len(xy))])
    return np.where(ok[:, None], D, 0.0), ok


def shade_faces(cam: Camera, T: np.ndarray, face_of: np.ndarray, rays: Rays, background: float, boards: dict,
                T_world: np.ndarray, ink: float | None = None) -> np.ndarray:
    """The faces' image (H, W) float: nearest triangle of T (camera frame) along every ray, Lambert-shaded.

    Cast in tiles of at most TILE x TILE samples (whole pixels), each with the triangles whose box meets it."""
    Hs, Ws = rays.shape
    ss = rays.ss
    boxes = _pixel_boxes(cam, T, ss)
    live = np.flatnonzero((boxes[:, 0] < boxes[:, 1]) & (boxes[:, 2] < boxes[:, 3]))
    out = np.empty((cam.height, cam.width))
    side = max(1, TILE // ss) * ss
    for r0 in range(0, Hs, side):
        r1 = min(r0 + side, Hs)
        for c0 in range(0, Ws, side):
            c1 = min(c0 + side, Ws)
            b = boxes[live]
            meets = live[(b[:, 0] < c1) & (b[:, 1] > c0) & (b[:, 2] < r1) & (b[:, 3] > r0)]
            grey = np.full((r1 - r0, c1 - c0), float(background))
            if len(meets):
                D, ok = rays.tile(r0, r1, c0, c1)
                box = np.clip(boxes[meets] - [c0, c0, r0, r0], 0, [c1 - c0, c1 - c0, r1 - r0, r1 - r0])
                _shade_tile(D, ok, grey, T, meets, box, face_of, boards, T_world, background, ink)
            out[r0 // ss:r1 // ss, c0 // ss:c1 // ss] = grey.reshape(
                (r1 - r0) // ss, ss, (c1 - c0) // ss, ss).mean(axis=(1, 3))
    return out


def _shade_tile(D, ok, grey, T, which, boxes, face_of, boards, T_world, background, ink) -> None:
    """Shade one tile's samples `grey` (h, w) in place: triangles `which` of T, `boxes` their [c0, c1, r0, r1)
    in the tile, along the tile's rays D (h, w, 3) where `ok`."""
    depth = np.full(grey.shape, np.inf)
    light = np.asarray(LIGHT, float) / np.linalg.norm(LIGHT)
    for k, (c0, c1, r0, r1) in zip(which.tolist(), boxes.tolist(), strict=True):
        if c0 >= c1 or r0 >= r1:
            continue
        d = D[r0:r1, c0:c1].reshape(-1, 3)
        V0, e1, e2 = T[k, 0], T[k, 1] - T[k, 0], T[k, 2] - T[k, 0]
        # Moller-Trumbore with the ray's direction d factored out: det = d . (e2 x e1), u = d . (e2 x s) / det,
        # v = d . (s x e1) / det, t = e2 . (s x e1) / det, with s = -V0: one product of d with three vectors
        s_ = -V0
        q = np.cross(s_, e1)
        M = np.stack([np.cross(e2, e1), np.cross(e2, s_), q], axis=1)
        det, un, vn = (d @ M).T
        tn = float(e2 @ q)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            a, b, t = un * inv, vn * inv, tn * inv
        hit = (np.abs(det) > 1e-300) & (a >= 0) & (b >= 0) & (a + b <= 1) & (t > 0)
        hit &= ok[r0:r1, c0:c1].ravel()
        zone = depth[r0:r1, c0:c1].reshape(-1)
        hit &= t < zone
        if hit.any():  # beyond the near plane: the ray's length to the hit
            hit[hit] = t[hit] * np.sqrt(np.einsum("ij,ij->i", d[hit], d[hit])) > geometry.NEAR
        if not hit.any():
            continue
        n = np.cross(e1, e2)
        n = n / max(np.linalg.norm(n), 1e-300)
        lit = face_grey(abs(float(n @ light)), background, ink)
        value = np.full(int(hit.sum()), lit)
        f = int(face_of[k])
        if f in boards:  # the pattern, at the hit's point on the board (world frame), on its printed side
            W0, W1, W2 = T_world[k]
            ez_cam = n * np.sign(np.cross(W1 - W0, W2 - W0) @ boards[f][3])  # the board's z, camera frame
            if V0 @ ez_cam > 0:  # the printed side faces -z: the camera is on that side
                X = W0 + a[hit, None] * (W1 - W0) + b[hit, None] * (W2 - W0)
                value = lit * board_albedo(boards[f], X)
            else:
                value = value * BACK
        zone[hit] = t[hit]
        depth[r0:r1, c0:c1] = zone.reshape(r1 - r0, c1 - c0)
        g = grey[r0:r1, c0:c1].reshape(-1)
        g[hit] = value
        grey[r0:r1, c0:c1] = g.reshape(r1 - r0, c1 - c0)


def face_grey(lambert: float, background: float, ink: float | None = None) -> float:
    """A face's grey, 60 + 170 |n . l|, moved to the nearest grey at least CONTRAST levels from the background's
    and the features' ink: faces stay darker or lighter than the background as their shading makes them (both
    polarities), and every face's outline against the background, and every feature's step against a face, is an
    edge (a face lit to the background's grey had none there, and a silhouette or a rim beside it went
    undetected)."""
    lit = 60.0 + 170.0 * lambert
    avoid = [g for g in (background, ink) if g is not None]

    def ok(g):
        return 0.0 <= g <= 255.0 and all(abs(g - a) >= CONTRAST - 1e-9 for a in avoid)

    if ok(lit):
        return lit
    edges = sorted({a + sgn * CONTRAST for a in avoid for sgn in (-1.0, 1.0)} | {0.0, 255.0},
                   key=lambda g: abs(g - lit))
    return next((g for g in edges if ok(g)), lit)


def _pixel_boxes(cam: Camera, T: np.ndarray, ss: int, samples: int = 8) -> np.ndarray:
    """Per triangle (T, 4): the sample-grid columns [c0, c1) and rows [r0, r1) its image may cover.

    Its edges are sampled (distortion bends them) and projected; a triangle reaching behind the camera or out
    of the lens's reach gets the whole image, one wholly behind the near plane none."""
    n = len(T)
    s = np.linspace(0, 1, samples, endpoint=False)
    P = np.concatenate([T[:, i, None] + s[None, :, None] * (T[:, (i + 1) % 3, None] - T[:, i, None])
                        for i in range(3)], axis=1)  # (n, 3 samples, 3)
    g = geometry.camera_table(cam)
    inside = geometry.visible(P.reshape(-1, 3), g["model"], g["limit"]).reshape(n, -1)
    uv = geometry.project(P.reshape(-1, 3), g).reshape(n, -1, 2)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a triangle with no sample in view: its box is whole
        lo = np.nanmin(np.where(inside[..., None], uv, np.nan), axis=1) if n else np.zeros((0, 2))
        hi = np.nanmax(np.where(inside[..., None], uv, np.nan), axis=1) if n else np.zeros((0, 2))
    whole = ~inside.all(axis=1)
    # no edge sample imaged: the triangle either misses the lens's cone (nothing to draw) or spans it, and
    # then the optical axis, inside the cone, passes through it
    behind = ~inside.any(axis=1) & ~_axis_hits(T)
    W, H = cam.width * ss, cam.height * ss
    margin = 2.0  # px: the chords of a bent edge, and the supersampling's half-pixel
    with np.errstate(invalid="ignore"):
        c0 = np.floor((lo[:, 0] - margin + 0.5) * ss)
        c1 = np.ceil((hi[:, 0] + margin + 0.5) * ss)
        r0 = np.floor((lo[:, 1] - margin + 0.5) * ss)
        r1 = np.ceil((hi[:, 1] + margin + 0.5) * ss)
    box = np.column_stack([c0, c1, r0, r1])
    box = np.where(whole[:, None], [0, W, 0, H], box)
    box = np.where(behind[:, None], [0, 0, 0, 0], box)
    box = np.nan_to_num(box, nan=0.0, posinf=0.0, neginf=0.0)
    box[:, :2] = np.clip(box[:, :2], 0, W)
    box[:, 2:] = np.clip(box[:, 2:], 0, H)
    return box.astype(int)


def _axis_hits(T: np.ndarray) -> np.ndarray:
    """Whether the optical axis (the camera frame's +z ray) passes through each triangle (n, 3, 3)."""
    A, B, C = T[:, 0, :2], T[:, 1, :2], T[:, 2, :2]  # where the axis meets the triangle's plane is (0, 0, z)

    def side(P, Q):
        return P[:, 0] * Q[:, 1] - P[:, 1] * Q[:, 0]  # the sign of the origin against edge P -> Q

    s1, s2, s3 = side(A, B), side(B, C), side(C, A)
    inside = ((s1 >= 0) & (s2 >= 0) & (s3 >= 0)) | ((s1 <= 0) & (s2 <= 0) & (s3 <= 0))
    # the point on the axis: z from the plane through the vertices, in front of the camera
    n = np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.einsum("ij,ij->i", n, T[:, 0]) / n[:, 2]
    return inside & (z > geometry.NEAR)


def board_albedo(board, X: np.ndarray) -> np.ndarray:
    """Reflectance (n,) in [0.1, 1] of board points X (n, 3, world frame). `board` is (origin (3,), its x, y and
    z axes (3,) each, scene.Board): the outer corner of square (0, 0), which is dark, and the pattern; the
    margin is white. A circle grid's origin is its first dot's centre; its dots are dark. A ChArUco board's
    pattern is OpenCV's own drawing of it (cv2.aruco, 64 px a square)."""
    origin, ex, ey, _, b = board
    rel = X - np.asarray(origin)
    x, y = rel @ np.asarray(ex) / b.square, rel @ np.asarray(ey) / b.square  # in squares (a circle grid: spacings)
    if b.circles:  # dark dots: a point within a dot's radius of the nearest centre in the row above or below
        r2 = (b.diameter / 2 / b.square) ** 2  # (a dot may reach past the middle between rows: acircles)
        dot = np.zeros(len(x), bool)
        for j in (np.floor(y), np.floor(y) + 1):
            i = np.round((x - j % 2) / 2) if b.kind == "acircles" else np.round(x)
            cx = 2 * i + j % 2 if b.kind == "acircles" else i
            on = (i >= 0) & (i < b.columns) & (j >= 0) & (j < b.rows)
            dot |= on & ((x - cx) ** 2 + (y - j) ** 2 <= r2)
        return np.where(dot, 0.1, 1.0)
    inside = (x >= 0) & (x < b.columns) & (y >= 0) & (y < b.rows)
    if b.kind == "charuco":
        img = _charuco_image(b.columns, b.rows, b.square, b.marker, b.dictionary)
        px = img.shape[0] // b.rows
        c = np.clip((x * px).astype(int), 0, img.shape[1] - 1)
        r = np.clip((y * px).astype(int), 0, img.shape[0] - 1)
        return np.where(inside, 0.1 + 0.9 * img[r, c] / 255.0, 1.0)
    dark = inside & ((np.floor(x) + np.floor(y)) % 2 == 0)
    return np.where(dark, 0.1, 1.0)


@functools.lru_cache(maxsize=4)
def _charuco_image(columns: int, rows: int, square: float, marker: float, dictionary: str) -> np.ndarray:
    import cv2

    aruco = cv2.aruco
    words = aruco.getPredefinedDictionary(getattr(aruco, dictionary))
    board = aruco.CharucoBoard((columns, rows), square, marker, words)
    return board.generateImage((64 * columns, 64 * rows), marginSize=0, borderBits=1)


# ----------------------------------------------------------------------------- strokes and marks

def stroke_coverage(width: int, height: int, strokes: list, closed: list, style: str = "step",
                    w: float = 4.0) -> np.ndarray:
    """Ink coverage (height, width) in [0, 1] of polylines (k, 2) in pixels: the largest over their segments
    of the box-filtered band across each segment (`step`: [0, w] on the side of (dy, -dx); `line`: [-w/2, w/2])
    times its extent along it (butt ends for `step`, square caps for `line`)."""
    cover = np.zeros((height, width))
    a_n, b_n = (0.0, w) if style == "step" else (-w / 2, w / 2)
    cap = 0.0 if style == "step" else w / 2
    segs = []
    for pts, c in zip(strokes, closed, strict=True):
        P = np.asarray(pts, float)
        if c and len(P) > 2:
            P = np.vstack([P, P[:1]])
        if style == "step" and len(P) >= 2:  # long segments cut into pieces, so that a band is clipped locally
            P = _pieces(_outside(P), PIECE)
        segs.append(np.concatenate([P[:-1], P[1:]], axis=1))
    if not segs:
        return cover
    # each segment's band reaches past its ends where it joins the next segment (`_join_reach`): butt-ended bands
    # of a curve's short chords covered each pixel in part and left a wedge unpainted at every join on the curve's
    # outer side, and a curve's band came out hatched, a comb of edges beside its own
    ext = [_join_reach(np.asarray(seg, float), bool(c) and len(seg) > 1, max(abs(a_n), abs(b_n)))
           for seg, c in zip(segs, closed, strict=True)]
    S = np.concatenate(segs)
    E = np.concatenate(ext)
    fin = np.isfinite(S).all(axis=1)
    S, E = S[fin], E[fin]
    d = S[:, 2:] - S[:, :2]
    L = np.hypot(d[:, 0], d[:, 1])
    S, d, L, E = S[L > 1e-12], d[L > 1e-12], L[L > 1e-12], E[L > 1e-12]
    tang = d / L[:, None]
    norm = np.column_stack([tang[:, 1], -tang[:, 0]])  # (dy, -dx): the band's side
    # a step's band stops halfway to the next stroke on its side: a band wider than the gap to another feature
    # (the two halves of a thin ellipse near its tips, a rim beside a silhouette) painted over that feature's
    # edge and hid it
    gap = _clearance(S, norm, L) if style == "step" else np.full(len(S), np.inf)
    B = np.minimum(b_n, np.minimum(gap / 2 + 0.5, gap))  # (half a pixel past halfway: two bands meet whole)
    reach = max(abs(a_n), abs(b_n)) + cap + float(E.max(initial=0.0)) + 1.0
    lo = np.floor(np.minimum(S[:, :2], S[:, 2:]) - reach).astype(int)
    hi = np.ceil(np.maximum(S[:, :2], S[:, 2:]) + reach).astype(int)
    lo = np.clip(lo, 0, [width, height])
    hi = np.clip(hi + 1, 0, [width, height])
    for k in np.flatnonzero((hi[:, 0] > lo[:, 0]) & (hi[:, 1] > lo[:, 1])).tolist():
        x0, y0 = lo[k]
        x1, y1 = hi[k]
        X, Y = np.meshgrid(np.arange(x0, x1, dtype=float) - S[k, 0], np.arange(y0, y1, dtype=float) - S[k, 1])
        t = X * tang[k, 0] + Y * tang[k, 1]
        s = X * norm[k, 0] + Y * norm[k, 1]
        c = _box(s, a_n, B[k]) * _box(t, -cap - E[k, 0], L[k] + cap + E[k, 1])
        np.maximum(cover[y0:y1, x0:x1], c, out=cover[y0:y1, x0:x1])
    return cover


CURVE_TURN = math.radians(60.0)  # a stroke that turns more than this in all is a curve (_outside)


def _outside(P: np.ndarray) -> np.ndarray:
    """The polyline P (k, 2), reversed where needed so that a step's band (on the side of (dy, -dx)) lies on a
    curve's convex side: a stroke of 8 or more vertices that turns one way by more than CURVE_TURN in all (an
    ellipse, whole or an arc; approx_error's kinks on a straight line turn both ways and leave it as it is).
    Painted inside, the band of a thin ellipse's near half put its inner edge a pixel or two from where the far
    half is: where edge_loss took the far half away, the verification found that edge in its place (on the
    cylinders of the round trip, the gaps of the far rims went unseen: edge loss 0.17 read 0.11)."""
    if len(P) < 8 or not np.isfinite(P).all():
        return P
    t = np.diff(P, axis=0)
    t = t / np.maximum(np.hypot(t[:, 0], t[:, 1]), 1e-12)[:, None]
    turn = np.arctan2(t[:-1, 0] * t[1:, 1] - t[:-1, 1] * t[1:, 0], (t[:-1] * t[1:]).sum(axis=1)).sum()
    if abs(turn) <= CURVE_TURN:
        return P
    inward = (t[:-1, 1] * (t[1:, 0] - t[:-1, 0]) - t[:-1, 0] * (t[1:, 1] - t[:-1, 1])).sum()  # (dy, -dx) . dt
    return P[::-1].copy() if inward > 0 else P


def _pieces(P: np.ndarray, most: float) -> np.ndarray:
    """The polyline P (k, 2) with points added along each segment longer than `most` px, evenly."""
    d = np.diff(P, axis=0)
    L = np.hypot(d[:, 0], d[:, 1])
    if not np.isfinite(L).all() or (L <= most).all():
        return P
    n = np.maximum(1, np.ceil(L / most)).astype(int)
    f = np.concatenate([np.arange(k) / k for k in n])
    i = np.repeat(np.arange(len(d)), n)
    return np.vstack([P[i] + f[:, None] * d[i], P[-1:]])


def _clearance(S: np.ndarray, norm: np.ndarray, L: np.ndarray, chunk: int = 256) -> np.ndarray:
    """(n,) px from each segment (rows x0, y0, x1, y1) along its normal `norm` to the nearest other segment, the
    least over rays from its two ends and its middle (inf where none is met); a segment it shares an end with is
    not counted."""
    n = len(S)
    out = np.full(n, np.inf)
    if n < 2:
        return out
    A, D = S[:, :2], S[:, 2:] - S[:, :2]

    def cross(u, v):
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

    for k0 in range(0, n, chunk):
        k = np.arange(k0, min(k0 + chunk, n))
        nk = norm[k][:, None, :]
        best = np.full(len(k), np.inf)
        for frac in (0.0, 0.5, 1.0):
            M = (A[k] + frac * D[k])[:, None, :]
            den = cross(nk, D[None, :, :])
            rel = A[None, :, :] - M
            with np.errstate(divide="ignore", invalid="ignore"):
                lam = cross(rel, D[None, :, :]) / den
                mu = cross(rel, nk) / den
            hit = (np.abs(den) > 1e-12) & (lam > 1e-6) & (mu >= 0) & (mu <= 1)
            touch = (np.hypot(*(S[None, :, :2] - S[k][:, None, 2:]).transpose(2, 0, 1)) < 1e-6) | \
                    (np.hypot(*(S[None, :, 2:] - S[k][:, None, :2]).transpose(2, 0, 1)) < 1e-6)
            hit &= ~touch
            hit[np.arange(len(k)), k] = False
            best = np.minimum(best, np.where(hit, lam, np.inf).min(axis=1))
        out[k] = best
    return out


def _join_reach(seg: np.ndarray, closed: bool, w: float) -> np.ndarray:
    """(n, 2) px each of a polyline's n segments (rows x0, y0, x1, y1) reaches past its start and its end: at a
    join with the next segment, half a pixel (a pixel's coverage along the stroke is its overlap with one segment:
    a curve's chords shorter than a pixel each covered every pixel in part, never whole) and w tan(theta / 2)
    for the turn theta there, up to MITRE_TURN (a sharper turn is a
    corner, not a curve: there a mitre on the band's inner side would paint across the next segment's edge);
    nothing at an open polyline's two ends."""
    n = len(seg)
    out = np.zeros((n, 2))
    if n < 2:
        return out
    d = seg[:, 2:] - seg[:, :2]
    a = np.arctan2(d[:, 1], d[:, 0])
    turn = np.abs(np.angle(np.exp(1j * (np.roll(a, -1) - a))))  # at the end of segment k, to segment k + 1
    reach = np.where(turn <= MITRE_TURN, 0.5 + w * np.tan(turn / 2), 0.0)
    if not closed:
        reach[-1] = 0.0  # (the last segment's end is the polyline's)
    out[:, 1] = reach
    out[:, 0] = np.roll(reach, 1)
    return out


def _box(s: np.ndarray, a: float, b: float) -> np.ndarray:
    """The length of [s - 1/2, s + 1/2] inside [a, b]: a unit pixel's share of a band, across it."""
    return np.clip(np.minimum(s + 0.5, b) - np.maximum(s - 0.5, a), 0.0, 1.0)


def draw_marks(img: np.ndarray, pts: np.ndarray, half: float, dark: float, light: float) -> np.ndarray:
    """A 2 x 2 checker of side 2 half at each point (n, 2): dark where (x - u)(y - v) > 0, box-filtered."""
    H, W = img.shape
    for u, v in pts[np.isfinite(pts).all(axis=1)].tolist():
        x0, x1 = max(int(math.floor(u - half - 1)), 0), min(int(math.ceil(u + half + 1)) + 1, W)
        y0, y1 = max(int(math.floor(v - half - 1)), 0), min(int(math.ceil(v + half + 1)) + 1, H)
        if x1 <= x0 or y1 <= y0:
            continue
        X, Y = np.meshgrid(np.arange(x0, x1) - u, np.arange(y0, y1) - v)
        gx, hx = _box(X, 0, half), _box(X, -half, 0)
        gy, hy = _box(Y, 0, half), _box(Y, -half, 0)
        pos, neg = gx * gy + hx * hy, gx * hy + hx * gy
        img[y0:y1, x0:x1] = img[y0:y1, x0:x1] * (1 - pos - neg) + dark * pos + light * neg
    return img


# ----------------------------------------------------------------------------- files

def png_bytes(img: np.ndarray) -> bytes:
    """An 8-bit greyscale PNG of img (H, W) uint8: filter 0 on every row, zlib level 6 (deterministic)."""
    img = np.ascontiguousarray(img, dtype=np.uint8)
    h, w = img.shape
    raw = np.concatenate([np.zeros((h, 1), np.uint8), img], axis=1).tobytes()

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


def manifest(scene, images: list[Image], *, seed: int, pipeline: str | None, look: Look, visibility: str) -> dict:
    """render.json: what was drawn and how, with every image's camera and pose (camera from world)."""
    from wiredsl import __version__
    from wiredsl.io import emit

    cams = {}
    for im_ in images:
        c = im_.camera
        cams.setdefault(im_.side, {"camera": c.name, "width": c.width, "height": c.height,
                                   "K": [[c.f * c.ax, 0.0, c.cx], [0.0, c.f * c.ay, c.cy], [0.0, 0.0, 1.0]],
                                   "distortion": c.distortion,
                                   "coefficients": {k: getattr(c, k) for k in geometry.CAMERA_KEYS[5:]}})
    poses: dict[int, dict] = {}
    for im_ in images:
        entry = poses.setdefault(im_.pose, {"index": im_.pose, "pose": list(scene.path.pose(im_.pose)), "images": {}})
        entry["images"][im_.side] = {"file": im_.name, "R_cw": im_.R_cw.tolist(), "t_cw": im_.t_cw.tolist(),
                                     **({"subframes": im_.subframes} if im_.subframes > 1 else {})}
    return {"document": "render", "tool_version": __version__, "scene": emit.scene_ref(scene).model_dump(mode="json"),
            "seed": seed, "pipeline": pipeline, "blur": look.blur, "noise": look.noise, "edges": look.edges,
            "width": look.width, "ink": look.ink, "background": look.background, "faces": look.faces,
            "corners": look.corners, "supersample": look.supersample, "visibility": visibility,
            **({"smear": list(look.smear)} if any(look.smear) else {}),
            "pixel_centres": "integer (OpenCV)",
            "cameras": cams, "poses": [poses[k] for k in sorted(poses)]}


def write(folder, scene, *, pipeline=None, seed: int = 0, look: Look = Look(), poses=None, cameras: str = "both",
          visibility: str = "exact", force: bool = False, progress=None) -> list[Image]:
    """Render into `folder` (replaced as a whole: staged, then swapped in): one PNG a view, and render.json."""
    from wiredsl.files import json_text, output_folder, write_atomic

    written = []
    with output_folder(folder, force) as stage:
        for image in render(scene, pipeline=pipeline, seed=seed, look=look, poses=poses, cameras=cameras,
                            visibility=visibility, force=force):
            write_atomic(stage / image.name, png_bytes(image.pixels), tidy=False)
            image.pixels = None  # bounded memory: only the manifest's numbers are kept
            written.append(image)
            if progress is not None:
                progress(image)
        doc = manifest(scene, written, seed=seed, pipeline=pipeline.name if pipeline is not None else None,
                       look=look, visibility=visibility)
        write_atomic(stage / "render.json", json_text(doc, sort_keys=True, where="render.json"), tidy=False)
    return written


def scene_boards(scene) -> dict:
    """Face source name ("placement.face") -> board tuple (see board_albedo) of every placed calibration board."""
    out = {}
    for p in scene.placements:
        b = getattr(scene.model(p.model), "board", None)
        if b is None:
            continue
        R, t = np.array(p.rotation), np.array(p.position)
        origin = R @ np.array(b.origin) + t
        out[f"{p.name}.{b.face}"] = (origin, R[:, 0], R[:, 1], R[:, 2], b)
    return out
