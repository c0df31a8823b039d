"""Where the camera was for each image, from the calibration board the scene declares (`--poses board`).

The board (a `board` statement, placed once) is found in every image by OpenCV: a chessboard by
`cv2.findChessboardCorners` refined by `cv2.cornerSubPix`, a ChArUco board by `cv2.aruco.CharucoDetector`, a
circle grid by `cv2.findCirclesGrid` (its dots' centroids).
A chessboard's corners come back in one of two orders (its two 180-degree turns look alike to the detector);
the one whose first outer square is dark, as the model's is (scene.Board), is kept. The pose is
`cv2.solvePnP` with the scene's camera (its intrinsics and lens: radtan directly, an equidistant lens on the
points undistorted by wiredsl), and is given as the camera's pose in the world (the board's placement) and as
the robot's pose the engine takes (`robot_pose`), through the rig's mount of that camera.

Needs the `images` extra (OpenCV), imported only here.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from wiredsl.diagnostics import Diagnostic, Span, WiredslError
from wiredsl.engine import geometry
from wiredsl.scene import Board, Camera, Scene

LEAST_FRACTION = 0.5  # a board found in fewer than this share of the images (or in none) is an error


@dataclass
class BoardPose:
    """One image: whether the board was found and, if so, the pose and how well it fits."""

    image: str
    found: bool
    R_cw: np.ndarray | None = None  # camera from world: X_cam = R_cw X_world + t_cw
    t_cw: np.ndarray | None = None
    corners: np.ndarray | None = None  # (n, 2) detected pixels (sub-pixel) of the model's corners `ids`
    ids: np.ndarray | None = None  # (n,) indices into the board model's corners (OpenCV's order)
    rms: float | None = None  # px: root-mean-square reprojection error of the corners under the pose
    robot_pose: tuple[float, ...] | None = None  # world_from_robot [R | t] row-major: the engine's 6-DoF pose


@dataclass
class BoardPoses:
    poses: list[BoardPose]  # one per image, in the order given
    diagnostics: list[Diagnostic]  # a warning per image without the board
    placement: str  # the board's placement in the scene

    @property
    def found(self) -> list[BoardPose]:
        return [p for p in self.poses if p.found]


def board_poses(scene: Scene, images: Sequence, camera: str = "left", *, placement: str | None = None,
                least: float = LEAST_FRACTION) -> BoardPoses:
    """Each image's pose from the scene's board, seen by `camera` (a rig side, "left" or "right", or a camera's
    name). `images` are paths or (name, greyscale uint8 array) pairs. A board not found in an image is a
    warning (W196) at the image; found in fewer than `least` of them, or in none, error E197."""
    import cv2

    place, board, model = _the_board(scene, placement)
    cam, side = _camera(scene, camera)
    # model frame, OpenCV's order: a chessboard's inner corners, a circle grid's dot centres
    obj_model = board.centres() if board.circles else np.array([c.at for c in model.corners], dtype=float)
    R_p, t_p = np.array(place.rotation), np.array(place.position)
    poses, diags = [], []
    for item in images:
        name, img = _image(item, cam)
        where = Span(name, 1, 1, 1, 1)
        if isinstance(img, Diagnostic):
            diags.append(img)
            poses.append(BoardPose(name, False))
            continue
        find = {"chessboard": _chessboard, "charuco": _charuco}.get(board.kind, _circles)
        ids, pts = find(cv2, img, board)
        if ids is None or len(ids) < 4:
            diags.append(Diagnostic("warning", "W196", f"the {board.kind} '{place.name}' ({_size(board)}) is not "
                                    "found in this image", where, "its pose is left out"))
            poses.append(BoardPose(name, False))
            continue
        R_cm, t_cm = _solve(cv2, obj_model[ids], pts, cam)
        uv = _project(obj_model[ids] @ R_cm.T + t_cm, cam)
        rms = float(np.sqrt(np.mean(np.sum((uv - pts) ** 2, axis=1))))
        R_cw = R_cm @ R_p.T  # camera from world: through the placement (world = R_p model + t_p)
        t_cw = t_cm - R_cw @ t_p
        poses.append(BoardPose(name, True, R_cw, t_cw, pts, ids, rms, _robot_pose(scene, side, R_cw, t_cw)))
    n_found = sum(p.found for p in poses)
    if n_found == 0 or n_found < least * len(poses):
        missed = [p.image for p in poses if not p.found]
        shown = ", ".join(os.path.basename(m) for m in missed[:5]) + (", ..." if len(missed) > 5 else "")
        raise WiredslError([*diags, Diagnostic(
            "error", "E197", f"the {board.kind} '{place.name}' ({_size(board)}) is found in {n_found} of "
            f"{len(poses)} images (at least {math.ceil(least * len(poses)) or 1} needed); not in: {shown}",
            None, "check the board's size in the scene (inner corners across and down), the lighting, and that "
            "the whole board is in view")])
    return BoardPoses(poses, diags, place.name)


def _size(board: Board) -> str:
    nx, ny = board.inner
    if board.circles:
        return f"{nx} x {ny} dots"
    return f"{nx} x {ny} inner corners" if board.kind == "chessboard" else f"{board.columns} x {board.rows} squares"


def _the_board(scene: Scene, name: str | None):
    """(placement, Board, model) of the scene's board: the named placement, else the only placed board."""
    placed = [(p, scene.model(p.model)) for p in scene.placements if scene.model(p.model).board is not None]
    if name is not None:
        placed = [(p, m) for p, m in placed if p.name == name]
    if len(placed) != 1:
        what = f"no placed board named '{name}'" if name is not None else (
            "no placed board (a `board` statement and a `place`)" if not placed else
            f"{len(placed)} placed boards ({', '.join(p.name for p, _ in placed)}): name one")
        raise WiredslError([Diagnostic("error", "E198", f"scene '{scene.name}' has {what}",
                                       Span(scene.source, 1, 1, 1, 1))])
    p, m = placed[0]
    return p, m.board, m


def _camera(scene: Scene, which: str) -> tuple[Camera, str | None]:
    """The camera of a rig side, or the camera of that name (its side, if the rig mounts it)."""
    rig = scene.rig
    if rig is not None and which in ("left", "right"):
        return scene.camera(getattr(rig, which).camera), which
    names = [c.name for c in scene.cameras]
    if which not in names:
        raise WiredslError([Diagnostic("error", "E198", f"no camera '{which}' in scene '{scene.name}' (a rig side, "
                                       f"left or right, or one of: {', '.join(names) or 'none'})",
                                       Span(scene.source, 1, 1, 1, 1))])
    side = next((s for s in ("left", "right") if rig is not None and getattr(rig, s).camera == which), None)
    return scene.camera(which), side


def _image(item, cam: Camera):
    """(name, greyscale uint8 array), or (name, a Diagnostic saying why the image cannot be used)."""
    import cv2

    if isinstance(item, tuple):
        name, img = str(item[0]), np.asarray(item[1])
    else:
        name = os.fspath(item)
        size = header_size(name)  # a header's claim is checked before anything is decoded (a 30000 x 30000 bomb)
        if size is not None and size != (cam.width, cam.height):
            return name, Diagnostic("error", "E199", f"the image is {size[0]} x {size[1]} px, camera '{cam.name}' "
                                    f"{cam.width} x {cam.height}", Span(name, 1, 1, 1, 1))
        img = cv2.imread(name, cv2.IMREAD_GRAYSCALE)
        if img is None:
            return name, Diagnostic("error", "E199", "cannot read this image", Span(name, 1, 1, 1, 1))
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        return name, Diagnostic("error", "E199", f"the image's pixels are {img.dtype}, not 8-bit",
                                Span(name, 1, 1, 1, 1))
    if img.shape != (cam.height, cam.width):
        return name, Diagnostic("error", "E199", f"the image is {img.shape[1]} x {img.shape[0]} px, camera "
                                f"'{cam.name}' {cam.width} x {cam.height}", Span(name, 1, 1, 1, 1))
    return name, img


def header_size(path: str) -> tuple[int, int] | None:
    """(width, height) a PNG's or a JPEG's header claims, read without decoding; None for other files (or a
    header too damaged to say: the decoder then refuses the file)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(65536)
    except OSError:
        return None
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR" and len(head) >= 24:
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if head[:2] == b"\xff\xd8":  # JPEG: walk the segments to the first start of frame
        i = 2
        while i + 9 <= len(head) and head[i] == 0xFF:
            marker, length = head[i + 1], int.from_bytes(head[i + 2:i + 4], "big")
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                return int.from_bytes(head[i + 7:i + 9], "big"), int.from_bytes(head[i + 5:i + 7], "big")
            i += 2 + length
    return None


def _chessboard(cv2, img: np.ndarray, board: Board):
    """(model corner indices, sub-pixel corners (n, 2)) of a chessboard, or (None, None)."""
    nx, ny = board.inner
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, found = cv2.findChessboardCorners(img, (nx, ny), flags=flags)
    if not ok:
        return None, None
    pts = found.reshape(-1, 2).astype(np.float64)
    # a window well inside a square: half the smallest corner spacing, less a pixel, at most 11 px across
    step = np.linalg.norm(np.diff(pts.reshape(ny, nx, 2), axis=1), axis=2).min()
    half = int(max(2, min(5, step / 2 - 1)))
    refined = cv2.cornerSubPix(img, pts.astype(np.float32).reshape(-1, 1, 2), (half, half), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 1e-3))
    pts = refined.reshape(-1, 2).astype(np.float64)
    if not _first_square_dark(img, pts, nx):
        pts = pts[::-1].copy()  # the other of the two orders: the board turned half a turn
    return np.arange(nx * ny), pts


def _first_square_dark(img: np.ndarray, pts: np.ndarray, nx: int) -> bool:
    """Whether the outer square diagonally beyond the first corner is dark and the one beyond the last light,
    rather than the other way round: each compared with the squares beside it (the other colour: the two that
    share a side with it and touch the corner), over a 5 x 5 grid of points in each square's middle half
    (glare and blur move single pixels)."""
    from scipy.ndimage import map_coordinates

    grid = (np.stack(np.meshgrid(np.linspace(-0.25, 0.25, 5), np.linspace(-0.25, 0.25, 5)), -1)).reshape(-1, 2)

    def grey(p0, p_row, p_col, outward):  # mean grey of the square centred p0 + outward (in corner steps)
        du, dv = p_row - p0, p_col - p0
        at = p0 + (outward[0] + grid[:, :1]) * du + (outward[1] + grid[:, 1:]) * dv
        return float(np.mean(map_coordinates(img.astype(float), [at[:, 1], at[:, 0]], order=1, mode="nearest")))

    ends = []
    for p0, p_row, p_col in ((pts[0], pts[1], pts[nx]), (pts[-1], pts[-2], pts[-1 - nx])):
        beside = (grey(p0, p_row, p_col, (0.5, -0.5)) + grey(p0, p_row, p_col, (-0.5, 0.5))) / 2
        ends.append(beside - grey(p0, p_row, p_col, (-0.5, -0.5)))  # the other colour's grey less the corner's
    return ends[0] >= ends[1]


def _circles(cv2, img: np.ndarray, board: Board):
    """(model dot indices, dot centres (n, 2)) of a circle grid by `cv2.findCirclesGrid` (dark dots; its default
    search first, then with CALIB_CB_CLUSTERING, which finds grids the default misses in tilted views), or
    (None, None). The centres are the blobs' centroids (a few tenths of a pixel off the projected centre at
    strong tilts): the pose they give is what an OpenCV calibration from the same images would use."""
    grid = cv2.CALIB_CB_ASYMMETRIC_GRID if board.kind == "acircles" else cv2.CALIB_CB_SYMMETRIC_GRID
    for extra in (0, cv2.CALIB_CB_CLUSTERING):
        try:
            ok, found = cv2.findCirclesGrid(img, board.inner, flags=grid | extra)
        except cv2.error:  # (OpenCV refuses some degenerate blob layouts outright)
            ok = False
        if ok:
            pts = found.reshape(-1, 2).astype(np.float64)
            if _half_turn_symmetric(board) and (pts[-1, 0], pts[-1, 1]) < (pts[0, 0], pts[0, 1]):
                pts = pts[::-1].copy()  # the grid looks the same turned half a turn: the first dot leftmost
            return np.arange(board.columns * board.rows), pts
    return None, None


def _half_turn_symmetric(board: Board) -> bool:
    """Whether a circle grid maps onto itself turned half a turn in its plane (dot k onto dot n - 1 - k): every
    symmetric grid, and an asymmetric one with an even number of rows. Its images then give two poses a half
    turn apart, the dots alike in both; `_circles` keeps the order whose first dot is left of its last in the
    image (then above it), so that the same view always gives the same pose."""
    return board.kind == "circles" or board.rows % 2 == 0


def _charuco(cv2, img: np.ndarray, board: Board):
    """(model corner indices, corners (n, 2)) of a ChArUco board, or (None, None)."""
    aruco = cv2.aruco
    dictionary = aruco.getPredefinedDictionary(getattr(aruco, board.dictionary))
    cv_board = aruco.CharucoBoard((board.columns, board.rows), board.square, board.marker, dictionary)
    corners, ids, _, _ = aruco.CharucoDetector(cv_board).detectBoard(img)
    if ids is None or len(ids) == 0:
        return None, None
    return ids.reshape(-1).astype(int), corners.reshape(-1, 2).astype(np.float64)


def _solve(cv2, obj: np.ndarray, pts: np.ndarray, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Camera from model (R, t) by solvePnP: a radtan camera with its K and coefficients; an equidistant one on
    the points undistorted by wiredsl (K = I, no distortion)."""
    if cam.distortion == "radtan":
        K = np.array([[cam.f * cam.ax, 0, cam.cx], [0, cam.f * cam.ay, cam.cy], [0, 0, 1.0]])
        dist = np.array([cam.k1, cam.k2, cam.p1, cam.p2, cam.k3, cam.k4, cam.k5, cam.k6])
        use = pts
    else:
        from wiredsl.measures.stereo3d import undistort

        use, ok = undistort(pts, cam)
        obj, use = obj[ok], use[ok]
        K, dist = np.eye(3), np.zeros(5)
    ok, rvec, tvec = cv2.solvePnP(obj.astype(np.float64), use.astype(np.float64), K, dist,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    return cv2.Rodrigues(rvec)[0], tvec.reshape(3)


def _project(P_cam: np.ndarray, cam: Camera) -> np.ndarray:
    return geometry.cam_to_pixels(P_cam, cam)


def _robot_pose(scene: Scene, side: str | None, R_cw: np.ndarray, t_cw: np.ndarray) -> tuple[float, ...] | None:
    """world_from_robot [R | t] row-major (12 numbers, the engine's 6-DoF pose) of a camera pose, through the
    rig's mount of that side (robot point = mount.rotation @ camera point + mount.position)."""
    if side is None or scene.rig is None:
        return None
    mount = getattr(scene.rig, side)
    return geometry.world_from_robot_via_camera(R_cw.T, -R_cw.T @ t_cw, mount.rotation, mount.position)
