"""Stage 4: the ideal projection of a compiled scene, pose by pose, camera by camera.

For every pose of the path the rig is placed on the robot; each camera images
the features visible from there (the nearest view-point's list, or an exact
per-camera computation). Everything is clipped in 3D to the near plane and to
the radius where distortion folds before projection, and to the image
rectangle [0, width] x [0, height] after it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from wiredsl.diagnostics import Diagnostic, Span, WiredslError
from wiredsl.engine import conics, geometry, occlusion, visibility
from wiredsl.engine.world import World, build_world, ellipse_points
from wiredsl.scene import Camera, Scene

DEFAULT_TOLERANCE = 0.1  # px: largest deviation of an emitted polyline from the true image curve


@dataclass(frozen=True)
class Options:
    tolerance: float = DEFAULT_TOLERANCE
    visibility: str = "scene"  # "scene" (the mesh's lists), "exact" (per camera and pose), "all"
    poses: tuple[int, ...] | None = None  # None: every pose
    right: bool = True  # project the right camera too


@dataclass
class ImageFeature:
    fid: int
    kind: str  # line | polyline | conic | corner
    points: np.ndarray  # (k, 2) pixels; a corner has k = 1
    segment: int = -1
    clipped: bool = False
    closed: bool = False
    conic: tuple | None = None  # (centre (2,), axes (2,), angle, arc or None)
    fragment: int = -1  # piece number after a stage cut the feature, -1 when whole
    occluded: bool = False  # a visible part of a feature that occlusion cut (--visibility exact)


@dataclass
class Raw:
    """A stroke before image clipping: the world points its vertices image, for re-projection."""

    fid: int
    segment: int
    kind: str  # "line" (straight in the image), "polyline"
    closed: bool
    clipped: bool  # already cut in 3D (near plane, fold)
    world: np.ndarray  # (k, 3)
    fragment: int = -1  # part number when occlusion cut the feature
    occluded: bool = False


@dataclass
class View:
    camera: Camera
    R_cw: np.ndarray
    t_cw: np.ndarray
    features: list[ImageFeature] = field(default_factory=list)
    raw: list[Raw] = field(default_factory=list)  # the strokes before image clipping
    corner_world: np.ndarray | None = None  # (C, 3) the corners in front of the camera, before image clipping
    corner_fid: np.ndarray | None = None


@dataclass
class PoseResult:
    index: int
    pose: tuple[float, float, float]
    viewpoint: str | None
    left: View
    right: View | None


def simulate(scene: Scene, options: Options = Options(), world: World | None = None,
             visible: tuple | None = None) -> list[PoseResult]:
    """Project every selected pose of the scene's path; the ideal (undisturbed) feature sets.

    `visible` is `visibility_masks(...)` computed beforehand (e.g. once for many trials).
    """
    require_buildable(scene)
    world = world or build_world(scene)
    poses = np.array(scene.path.poses, dtype=float)
    chosen = range(len(poses)) if options.poses is None else options.poses
    vp_names, masks = visible if visible is not None else visibility_masks(scene, world, options)
    # --visibility exact: hidden lines removed, features cut at occlusion boundaries (occlusion.py)
    occluders = occlusion.Occluders.of_world(world) if options.visibility == "exact" else None
    out = []
    for i in chosen:
        pose = tuple(float(v) for v in poses[i])
        views = []
        for side, mount in (("left", scene.rig.left), ("right", scene.rig.right)):
            if side == "right" and not options.right:
                views.append(None)
                continue
            cam = scene.camera(mount.camera)
            R_cw, t_cw = geometry.camera_from_world(pose, mount.rotation, mount.position)
            mask = masks[(i, side)]
            views.append(project_view(world, cam, R_cw, t_cw, mask, options.tolerance, occluders))
        out.append(PoseResult(i, pose, vp_names.get(i), views[0], views[1]))
    return out


def require_buildable(scene: Scene) -> None:
    """A scene needs a rig and a path to be projected."""
    if scene.rig is None or scene.path is None:
        missing = "a rig" if scene.rig is None else "a path"
        start = Span(scene.source, 1, 1, 1, 1)  # the scene has no statement to point at: its file's start
        raise WiredslError([Diagnostic("error", "E102", f"scene '{scene.name}' needs {missing} to be built", start)])


def visibility_masks(scene: Scene, world: World, options: Options):
    """Per (pose, camera side) feature masks, and the view-point used for each pose."""
    poses = np.array(scene.path.poses, dtype=float)
    chosen = range(len(poses)) if options.poses is None else options.poses
    everything = world.mask(None)
    names: dict[int, str] = {}
    masks: dict[tuple[int, str], np.ndarray] = {}
    vp = scene.viewpoints
    if vp is None or vp.visibility == "all" or options.visibility in ("all", "exact"):  # exact: occlusion.py cuts
        for i in chosen:
            masks[(i, "left")] = masks[(i, "right")] = everything
        return names, masks
    points = np.array(vp.points, dtype=float)
    nearest = visibility.nearest_viewpoint(points, poses[list(chosen), :2]) if len(list(chosen)) else []
    lists = viewpoint_lists(scene, world, sorted(set(int(k) for k in nearest)))
    for i, k in zip(chosen, nearest, strict=True):
        names[i] = vp.names[k]
        masks[(i, "left")] = masks[(i, "right")] = lists[int(k)]
    return names, masks


def viewpoint_lists(scene: Scene, world: World, which: list[int]) -> dict[int, np.ndarray]:
    """Visibility masks of the given view-point indices, from wherever the scene says they come."""
    vp = scene.viewpoints
    if vp.visibility == "authored":
        return {k: world.mask(set(vp.visible.get(vp.names[k], []))) for k in which}
    if vp.visibility == "file":
        data = read_viewdep(Path(scene.source).parent / vp.file, scene)
        return {k: world.mask(set(data.get(vp.names[k], []))) for k in which}
    eyes = visibility.viewpoint_eyes(scene)[which]
    vis = visibility.visible_features(world, eyes)
    return {k: vis[j] for j, k in enumerate(which)}


def read_viewdep(path: Path, scene: Scene) -> dict[str, list[str]]:
    """View-point -> visible feature ids, from a view-dependency file (schema/viewdep.schema.json)."""
    from wiredsl.io.schema import problems
    from wiredsl.language.ast import decode, display_path, read_bytes

    where = Span(display_path(path), 1, 1, 1, 1)
    try:
        text = decode(read_bytes(path, "view-dependency file", Span(scene.source, 1, 1, 1, 1)), path,
                      "view-dependency file")
        doc = json.loads(text)
    except WiredslError as err:
        raise WiredslError([Diagnostic(d.severity, d.code, d.message, d.span,
                                       "run 'wiredsl viewdep' on the scene to write it") for d in err.diagnostics]
                           ) from None
    except json.JSONDecodeError as exc:  # at the line and column of the file where the JSON breaks
        at = Span(where.file, exc.lineno, exc.colno, exc.lineno, exc.colno + 1)
        raise WiredslError([Diagnostic("error", "E010", f"cannot read view-dependency file: {exc.msg}", at,
                                       "run 'wiredsl viewdep' on the scene to write it")]) from None
    bad = problems(doc)
    if bad:
        raise WiredslError([Diagnostic("error", "E142", f"view-dependency file {where.file}: {bad[0]}", where)])
    return doc["viewpoints"]


# --------------------------------------------------------------------------- projection

def project_view(world: World, cam: Camera, R_cw: np.ndarray, t_cw: np.ndarray, mask: np.ndarray,
                 tol: float = DEFAULT_TOLERANCE, occluders: occlusion.Occluders | None = None) -> View:
    """What one camera sees of the features in `mask` (only their unoccluded parts, given occluders)."""
    view = View(cam, R_cw, t_cw)
    eye = None if occluders is None else occluders.seen_from(R_cw, t_cw)
    r_fold = geometry.fold_radius(cam.k1, cam.k2)
    distorted = geometry.is_distorted(cam)

    # straight 3D segments: lines, polyline segments, then silhouette generators (camera frame)
    sel = mask[world.line_fid]
    A = geometry.world_to_cam(world.lines[sel, 0], R_cw, t_cw)
    B = geometry.world_to_cam(world.lines[sel, 1], R_cw, t_cw)
    fid = world.line_fid[sel]
    seg = world.line_segment[sel]
    sA, sB, sfid, sseg = silhouettes_cam(world, mask, R_cw, t_cw)
    A, B = np.concatenate([A, sA]), np.concatenate([B, sB])
    fid, seg = np.concatenate([fid, sfid]).astype(int), np.concatenate([seg, sseg]).astype(int)
    view.features += _segments(A, B, fid, seg, cam, r_fold, distorted, tol, view.raw, R_cw, t_cw, eye)

    sel = np.flatnonzero(mask[world.ell_fid])
    for e in sel:
        view.features += _ellipse(world, e, cam, R_cw, t_cw, r_fold, distorted, tol, view.raw, eye)

    sel = mask[world.corner_fid]
    if sel.any():
        P = geometry.world_to_cam(world.corners[sel], R_cw, t_cw)
        ok = P[:, 2] > geometry.NEAR
        xy = np.where(ok[:, None], P[:, :2] / np.where(ok, P[:, 2], 1.0)[:, None], 0.0)
        ok &= np.hypot(xy[:, 0], xy[:, 1]) < r_fold
        if eye is not None:  # --visibility exact (occlusion.py)
            ok &= ~eye.hidden(P)
        uv = geometry.plane_to_pixels(geometry.distort(xy, cam.k1, cam.k2, cam.p1, cam.p2),
                                      cam.f, cam.ax, cam.ay, cam.cx, cam.cy)
        view.corner_world, view.corner_fid = world.corners[sel][ok], world.corner_fid[sel][ok]
        ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height)
        for f, p in zip(world.corner_fid[sel][ok], uv[ok], strict=True):
            view.features.append(ImageFeature(int(f), "corner", p[None, :]))
    if eye is not None:  # parts also cut by the image border get their own numbers (occlusion.py)
        occlusion.number_parts(view.features)
    return view


def silhouettes_cam(world: World, mask: np.ndarray, R_cw, t_cw):
    """Camera-frame contour generators of the visible silhouettes, with feature ids and side index."""
    A, B, fids, sides = [], [], [], []
    for fid, (a, b) in zip(world.sil_fid, world.sil_pair, strict=True):
        if not mask[fid]:
            continue
        args = []
        for e in (a, b):
            args += [R_cw @ world.ell_c[e] + t_cw, R_cw @ world.ell_U[e], R_cw @ world.ell_V[e]]
        arcs = [None if world.ell_full[e] else tuple(world.ell_arc[e]) for e in (a, b)]
        segs = conics.silhouette_segments(*args, arc_a=arcs[0], arc_b=arcs[1])
        # order the two sides by where they appear (left to right in the image) for stable indices
        segs.sort(key=lambda s: (s[0][0] / s[0][2] if s[0][2] > 0 else math.inf))
        for side, (p, q) in enumerate(segs):
            A.append(p)
            B.append(q)
            fids.append(fid)
            sides.append(side)
    z = np.zeros((0, 3))
    return (np.array(A).reshape(-1, 3) if A else z, np.array(B).reshape(-1, 3) if B else z,
            np.array(fids, dtype=int), np.array(sides, dtype=int))


def _to_world(P_cam: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray) -> np.ndarray:
    return (P_cam - t_cw) @ R_cw


def _segments(A, B, fid, seg, cam: Camera, r_fold: float, distorted: bool, tol: float, raw: list[Raw],
              R_cw, t_cw, eye: occlusion.Eye | None = None) -> list[ImageFeature]:
    out: list[ImageFeature] = []
    if len(A) == 0:
        return out
    t0, t1, keep = geometry.clip_segments_cone(A, B, geometry.NEAR, r_fold * (1 - 1e-9))
    cut3d = (t0 > 0) | (t1 < 1)
    piece, hid = np.full(len(A), -1), np.zeros(len(A), dtype=bool)
    if eye is not None:  # --visibility exact: one row per unoccluded part (occlusion.py)
        rows, u0, u1, piece, hid = occlusion.split_segments(eye, A, B, t0, t1, keep)
        cut3d = ((u0 > 0) & (u0 == t0[rows])) | ((u1 < 1) & (u1 == t1[rows]))  # the near plane, not occlusion
        A, B, fid, seg, t0, t1, keep = A[rows], B[rows], fid[rows], seg[rows], u0, u1, np.ones(len(rows), bool)
    D = B - A
    idx = np.flatnonzero(keep)
    if not distorted:
        Pa, Pb = A[idx] + t0[idx, None] * D[idx], A[idx] + t1[idx, None] * D[idx]
        for j, i in enumerate(idx):
            raw.append(Raw(int(fid[i]), int(seg[i]), "line", False, bool(cut3d[i]),
                           _to_world(np.stack([Pa[j], Pb[j]]), R_cw, t_cw), int(piece[i]), bool(hid[i])))
        a = geometry.cam_to_pixels(Pa, cam)
        b = geometry.cam_to_pixels(Pb, cam)
        r0, r1, ok = geometry.clip_segments_rect(a, b, cam.width, cam.height)
        d = b - a
        long_enough = np.linalg.norm(d, axis=1) * (r1 - r0) > 1e-9  # a line seen end-on has no image
        for j in np.flatnonzero(ok & (r1 > r0) & long_enough):
            i = idx[j]
            pts = np.stack([a[j] + r0[j] * d[j], a[j] + r1[j] * d[j]])
            cut = bool(cut3d[i] or r0[j] > 0 or r1[j] < 1)
            out.append(ImageFeature(int(fid[i]), "line", pts, int(seg[i]), cut, fragment=int(piece[i]),
                                    occluded=bool(hid[i])))
        return out

    def point(c, t):
        return geometry.cam_to_pixels(A[idx][c] + t[:, None] * D[idx][c], cam)

    params = geometry.adaptive_samples(point, t0[idx], t1[idx], tol, start=2)
    for j, ts in enumerate(params):
        i = idx[j]
        pts = point(np.full(len(ts), j), ts)
        raw.append(Raw(int(fid[i]), int(seg[i]), "polyline", False, bool(cut3d[i]),
                       _to_world(A[i] + ts[:, None] * D[i], R_cw, t_cw), int(piece[i]), bool(hid[i])))
        for part, cut in geometry.clip_polyline_rect(pts, cam.width, cam.height):
            out.append(ImageFeature(int(fid[i]), "polyline", part, int(seg[i]), bool(cut or cut3d[i]),
                                    fragment=int(piece[i]), occluded=bool(hid[i])))
    return out


def _front_intervals(cz: float, Az: float, Bz: float, arc: tuple[float, float]) -> list[tuple[float, float]]:
    """Parts of [t0, t1] where cz + Az cos t + Bz sin t > NEAR."""
    t0, t1 = arc
    R = math.hypot(Az, Bz)
    level = geometry.NEAR - cz
    if R <= 1e-15 * max(abs(cz), 1.0) or level / R <= -1:
        return [(t0, t1)] if level < 0 or level / max(R, 1e-300) <= -1 else []
    if level / R >= 1:
        return []
    phi, alpha = math.atan2(Bz, Az), math.acos(level / R)
    out = []
    # visible where |t - phi| < alpha (mod 2 pi); intersect with [t0, t1]
    k0 = math.floor((t0 - phi - alpha) / (2 * math.pi))
    for k in range(k0, k0 + 3):
        lo, hi = phi - alpha + 2 * math.pi * k, phi + alpha + 2 * math.pi * k
        a, b = max(lo, t0), min(hi, t1)
        if b > a:
            out.append((a, b))
    return out


def _ellipse(world: World, e: int, cam: Camera, R_cw, t_cw, r_fold, distorted, tol, raw: list[Raw],
             eye: occlusion.Eye | None = None) -> list[ImageFeature]:
    fid = int(world.ell_fid[e])
    c = R_cw @ world.ell_c[e] + t_cw
    U = R_cw @ world.ell_U[e]
    V = R_cw @ world.ell_V[e]
    arc = tuple(world.ell_arc[e])
    full = bool(world.ell_full[e])
    intervals = _front_intervals(c[2], U[2], V[2], arc)
    whole = len(intervals) == 1 and intervals[0] == arc  # wholly in front of the camera
    hid = False
    if eye is not None and intervals:  # --visibility exact: the unoccluded arcs (occlusion.py)
        intervals, hid = occlusion.split_arcs(eye, c, U, V, intervals, full)
    out: list[ImageFeature] = []
    if not intervals:
        return out

    def point(cid, t):
        P = ellipse_points(np.broadcast_to(c, (len(t), 3)), np.broadcast_to(U, (len(t), 3)),
                           np.broadcast_to(V, (len(t), 3)), t)
        return geometry.cam_to_pixels(P, cam)

    lo = np.array([a for a, _ in intervals])
    hi = np.array([b for _, b in intervals])
    params = geometry.adaptive_samples(point, lo, hi, tol, start=16)
    any_cut = not whole
    pieces = []
    first_raw = len(raw)
    for ts in params:
        P = ellipse_points(np.broadcast_to(c, (len(ts), 3)), np.broadcast_to(U, (len(ts), 3)),
                           np.broadcast_to(V, (len(ts), 3)), ts)
        inside = np.hypot(P[:, 0] / P[:, 2], P[:, 1] / P[:, 2]) < r_fold
        any_cut |= not inside.all()
        runs = _runs(inside)
        for run in runs:
            raw.append(Raw(fid, -1, "polyline", full and whole and not hid and len(runs) == 1 and inside.all(),
                           not (whole and inside.all()), _to_world(P[run], R_cw, t_cw),
                           len(raw) - first_raw if hid else -1, hid))
            pts = geometry.cam_to_pixels(P[run], cam)
            for piece, cut in geometry.clip_polyline_rect(pts, cam.width, cam.height):
                pieces.append((piece, cut))
    closed = full and whole and not hid and len(pieces) == 1 and not pieces[0][1]
    for k, (piece, cut) in enumerate(pieces):
        out.append(ImageFeature(fid, "polyline", piece, -1, bool(cut or not whole or any_cut), closed,
                                fragment=k if hid else -1, occluded=hid))
    if not distorted and whole and not hid:  # an occluded ellipse is its visible arcs only
        K = np.array([[cam.f * cam.ax, 0, cam.cx], [0, cam.f * cam.ay, cam.cy], [0, 0, 1.0]])
        H = K @ conics.homography(c, U, V)
        params_ = conics.ellipse_params(conics.dual_conic(H))
        if params_ is not None:
            centre, axes, angle = params_
            arc_img = None if full else _image_arc(H, centre, axes, angle, arc)
            clipped = any(cut for _, cut in pieces) or not pieces
            out.append(ImageFeature(fid, "conic", centre[None, :], -1, clipped, full,
                                    (centre, axes, angle, arc_img)))
    return out


def _runs(mask: np.ndarray) -> list[slice]:
    """Slices of consecutive True values."""
    d = np.diff(np.concatenate([[0], mask.astype(int), [0]]))
    return [slice(a, b) for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True)]


def _image_arc(H, centre, axes, angle, arc) -> tuple[float, float]:
    """The section's range in the image ellipse's own parameter s (centre + A cos s e1 + B sin s e2)."""
    e1 = np.array([math.cos(angle), math.sin(angle)])
    e2 = np.array([-e1[1], e1[0]])

    def s_of(t):
        p = H @ np.array([math.cos(t), math.sin(t), 1.0])
        q = p[:2] / p[2] - centre
        return math.atan2(q @ e2 / axes[1], q @ e1 / axes[0])

    t0, t1 = arc
    s0, s1, sm = s_of(t0), s_of(t1), s_of((t0 + t1) / 2)
    forward = (sm - s0) % (2 * math.pi) <= (s1 - s0) % (2 * math.pi)
    if not forward:
        s0, s1 = s1, s0
    span = (s1 - s0) % (2 * math.pi)
    return s0, s0 + span
