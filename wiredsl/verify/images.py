"""Images in: file names grouped into frames (one pose, one image per camera), each frame's pose, and the
pixels of one image at a time (its header is read and checked before anything is decoded).

A frame's key is the number in its images' file names (`left_003.png` -> 3, `left01.jpg` -> 1,
`1305031102.175304.png` -> that timestamp), and the camera the leading word (`left`, `right`, or a rig
camera's name) unless `--camera` names it. Images of the two rig cameras with the same key form a stereo
pair. Nothing here holds more than one image's pixels.

Bad input is a WiredslError with diagnostics located at the file: E190 an image that cannot be used
(unreadable, empty, truncated or corrupt, a format not read, over MAX_PIXELS), E191 an image whose size
differs from its camera's, E192 an image without a pose, E193 a glob that matches nothing or an image
whose camera cannot be told; W190 a 16-bit or colour image converted to 8-bit grey.
"""

from __future__ import annotations

import glob as globbing
import math
import os
import re
import struct
from dataclasses import dataclass, field
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from wiredsl.diagnostics import Diagnostic, Span, WiredslError
from wiredsl.engine import geometry

MAX_BYTES = 256 << 20  # an image file larger than this is refused unread
MAX_PIXELS = 100_000_000  # width x height from the header: more is refused before decoding
SIDES = ("left", "right")
_NAME = re.compile(r"^(?P<word>[A-Za-z][A-Za-z0-9_\-]*?)?[_\-.]?(?P<num>\d+(?:\.\d+)?)$")


def at(path: str | os.PathLike, line: int = 1) -> Span:
    """The span of a whole file (an image) or of one of its lines (a pose file)."""
    return Span(str(path), line, 1, line, 2)


def error(code: str, message: str, path, line: int = 1, hint: str | None = None) -> WiredslError:
    return WiredslError([Diagnostic("error", code, message, at(path, line), hint)])


@dataclass
class Frame:
    """One pose: its key (number in the file names), its images by rig side, and the robot pose the engine
    takes (geometry.world_from_robot), set by `assign_poses`."""

    key: Decimal
    images: dict[str, str] = field(default_factory=dict)
    pose: tuple[float, ...] | None = None
    pose_from: str = ""  # where the pose came from: "path pose 3", "poses.txt:12"

    @property
    def label(self) -> str:
        return str(self.key)


def side_of(word: str | None, rig, cameras) -> str | None:
    """The rig side an image's leading word names: left/right, or the name of the camera mounted there."""
    if word is None:
        return None
    w = word.lower()
    if w in SIDES:
        return w
    for side in SIDES:
        if getattr(rig, side).camera.lower() == w:
            return side
    return None


def frames_of(patterns: list[tuple[str, str | None]], rig) -> list[Frame]:
    """Frames from (glob, camera or None) pairs, in key order. A glob matching nothing is E193."""
    by_key: dict[Decimal, Frame] = {}
    for pattern, camera in patterns:
        paths = sorted(p for p in globbing.glob(pattern) if not os.path.isdir(p))
        if not paths:
            raise WiredslError([Diagnostic("error", "E193", f"no image matches {pattern!r}", None)])
        forced = None
        if camera is not None:
            forced = side_of(camera, rig, None)
            if forced is None:
                names = ", ".join([*SIDES, rig.left.camera, rig.right.camera])
                raise WiredslError([Diagnostic("error", "E193", f"--camera {camera!r} is not a camera of rig "
                                               f"'{rig.name}' (one of {names})", None)])
        for order, path in enumerate(paths):
            stem = Path(path).name.split(".")[0] if not re.search(r"\d\.\d", Path(path).stem) else Path(path).stem
            m = _NAME.match(stem)
            word, num = (m.group("word"), m.group("num")) if m else (None, None)
            side = forced or side_of(word, rig, None) or (None if word else "left")
            if side is None:
                raise error("E193", f"cannot tell which camera took {Path(path).name} (its name starts with "
                                    f"{word!r})", path, hint="name images left_*/right_* or give --camera per --images")
            try:
                key = Decimal(num) if num is not None else Decimal(order)
            except InvalidOperation:
                key = Decimal(order)
            frame = by_key.setdefault(key, Frame(key))
            if side in frame.images:
                raise error("E193", f"two images of the {side} camera for frame {key}: {frame.images[side]} and "
                                    f"{path}", path)
            frame.images[side] = path
    return [by_key[k] for k in sorted(by_key)]


# --------------------------------------------------------------------------- poses

def assign_path(frames: list[Frame], scene) -> None:
    """`--poses path`: each frame takes the scene path's pose of the number in its images' names (`left_003.png`
    -> pose 3, as `wiredsl render` names them), never its position among the images given, so that a subset
    of the images (`left_00[37].png`) is verified each at its own pose. A number that is not a pose of the path
    (a timestamp, a fraction, beyond the path's last pose) is E192."""
    n = len(scene.path.poses) if scene.path is not None else 0
    for frame in frames:
        first = next(iter(frame.images.values()))
        k = frame.key
        if k != k.to_integral_value() or k < 0 or k >= n:
            why = (f"its number {k} is not a pose index of the scene's path (0 to {n - 1})" if n else
                   "the scene's path has no poses")
            raise error("E192", f"{Path(first).name}: {why}", first,
                        hint="--poses path pairs each image with the path pose of the number in its name (as "
                             "`wiredsl render` names them); give images taken elsewhere their poses with "
                             "--poses FILE")
        frame.pose = scene.path.pose(int(k))
        frame.pose_from = f"path pose {int(k)}"


def assign_file(frames: list[Frame], scene, path: str, fmt: str | None, match: str, side: str) -> str:
    """`--poses FILE`: the file's poses are world_from_camera of the `side` camera (OpenCV axes) in the scene's
    world; matched to frames by order, or by the frames' keys as timestamps. Returns the match used."""
    from wiredsl.files import read_regular
    from wiredsl.io import trajectory

    try:
        text = read_regular(path, 64 << 20).decode("utf-8")
    except (OSError, ValueError) as exc:
        raise error("E010", f"cannot read pose file {path}: {getattr(exc, 'strerror', None) or exc}", path) from None
    try:
        traj = trajectory.read(text, fmt)
    except trajectory.TrajectoryError as exc:
        raise error("E145", f"pose file {path}: {exc}", path, exc.line or 1) from None
    mount = getattr(scene.rig, side)
    n = len(traj.lines)
    if match == "auto":
        match = "time" if _stamped(frames, traj, text, fmt) else "order"
    if match == "order":
        for k, frame in enumerate(frames):
            if k >= n:
                first = next(iter(frame.images.values()))
                raise error("E192", f"the pose file has {n} pose{'s' * (n != 1)} for {len(frames)} frames of "
                                    f"images: {Path(first).name} has none", path, int(traj.lines[-1]) if n else 1)
            frame.pose = geometry.world_from_robot_via_camera(traj.rotations[k], traj.positions[k], mount.rotation,
                                                              mount.position)
            frame.pose_from = f"{path}:{int(traj.lines[k])}"
        return match
    start, scale = _first_stamp(text, fmt or trajectory.guess_format(text))
    t = traj.times
    from scipy.spatial.transform import Rotation, Slerp

    slerp = Slerp(t, Rotation.from_matrix(traj.rotations)) if n > 1 else None
    for frame in frames:
        s = float((frame.key * scale) - start)
        if not (t[0] - 1e-6 <= s <= t[-1] + 1e-6):
            first = next(iter(frame.images.values()))
            raise error("E192", f"{Path(first).name} is at {frame.key} but the pose file spans "
                                f"{start / scale} .. {(start + Decimal(repr(float(t[-1])))) / scale}", first)
        s = min(max(s, t[0]), t[-1])
        P = np.array([np.interp(s, t, traj.positions[:, k]) for k in range(3)])
        R = slerp([s]).as_matrix()[0] if slerp is not None else traj.rotations[0]
        frame.pose = geometry.world_from_robot_via_camera(R, P, mount.rotation, mount.position)
        frame.pose_from = f"{path} at t={frame.key}"
    return match


def _first_stamp(text: str, fmt: str) -> tuple[Decimal, Decimal]:
    """(the file's first timestamp in seconds, the factor from an image key to seconds)."""
    for line in text.splitlines():
        words = line.replace(",", " ").split()
        if not words or line.lstrip().startswith("#") or "timestamp" in line.lower():
            continue
        try:
            first = Decimal(words[0])
        except InvalidOperation:
            continue
        scale = Decimal("1e-9") if fmt == "euroc" else Decimal(1)
        return first * scale, scale
    return Decimal(0), Decimal(1)


def _stamped(frames: list[Frame], traj, text: str, fmt: str | None) -> bool:
    """Are the frames' keys timestamps within the pose file's span (TUM and EuRoC carry absolute times)?"""
    from wiredsl.io import trajectory

    fmt = fmt or trajectory.guess_format(text)
    if traj.times is None or fmt not in ("tum", "euroc"):
        return False
    start, scale = _first_stamp(text, fmt)
    span = float(traj.times[-1])
    return all(-1e-6 <= float(f.key * scale - start) <= span + 1e-6 for f in frames) and start > 0


# --------------------------------------------------------------------------- pixels

@dataclass
class Header:
    format: str
    width: int
    height: int


def header(data: bytes) -> Header | None:
    """Format and size from the first bytes of PNG, JPEG, BMP and PNM files; None for anything else."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24 and data[12:16] == b"IHDR":
        w, h = struct.unpack(">II", data[16:24])
        return Header("png", w, h)
    if data[:2] == b"\xff\xd8":
        i = 2
        while i + 9 < len(data):
            if data[i] != 0xFF:
                return Header("jpeg", 0, 0)  # no marker where one must be: corrupt
            marker = data[i + 1]
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7 or marker == 0xFF:
                i += 1 if marker == 0xFF else 2
                continue
            length = struct.unpack(">H", data[i + 2:i + 4])[0]
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                h, w = struct.unpack(">HH", data[i + 5:i + 9])
                return Header("jpeg", w, h)
            i += 2 + length
        return Header("jpeg", 0, 0)
    if data[:2] == b"BM" and len(data) >= 26:
        w, h = struct.unpack("<ii", data[18:26])
        return Header("bmp", abs(w), abs(h))
    if data[:1] == b"P" and data[1:2] in (b"2", b"3", b"5", b"6"):
        words = re.sub(rb"#[^\n]*", b" ", data[2:200]).split()
        if len(words) >= 2 and words[0].isdigit() and words[1].isdigit():
            return Header("pnm", int(words[0]), int(words[1]))
    return None


def read_grey(path: str, width: int, height: int, warnings: list[Diagnostic] | None = None) -> np.ndarray:
    """An image as (height, width) uint8 grey, checked against the camera's size before it is decoded."""
    import cv2

    try:
        size = os.stat(path).st_size
        if not os.path.isfile(path):
            raise error("E190", f"image {path} is not a regular file", path)
        if size > MAX_BYTES:
            raise error("E190", f"image {path} is {size:,} bytes, over the limit of {MAX_BYTES:,}", path)
        with open(path, "rb") as fh:
            data = fh.read(MAX_BYTES + 1)
    except OSError as exc:
        raise error("E190", f"cannot read image {path}: {exc.strerror or exc}", path) from None
    if not data:
        raise error("E190", f"image {path} is empty (0 bytes)", path)
    h = header(data)
    if h is None:
        raise error("E190", f"image {path} is not a PNG, JPEG, BMP or PNM file (or its header is damaged)", path)
    if h.width <= 0 or h.height <= 0:
        raise error("E190", f"image {path}: its {h.format.upper()} header gives no size (corrupt or truncated)",
                    path)
    if h.width * h.height > MAX_PIXELS:
        raise error("E190", f"image {path} is {h.width} x {h.height} pixels by its header, over the limit of "
                            f"{MAX_PIXELS:,}: not decoded", path)
    if (h.width, h.height) != (width, height):
        raise error("E191", f"image {path} is {h.width} x {h.height} but its camera's image is {width} x {height}",
                    path, hint="give the camera's `size` the images' size, or the images of that camera")
    if h.format == "jpeg" and not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
        raise error("E190", f"image {path}: the JPEG data is truncated (no end-of-image marker)", path)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise error("E190", f"image {path}: its {h.format.upper()} data cannot be decoded (corrupt)", path)
    if img.shape[:2] != (height, width):
        raise error("E191", f"image {path} decodes to {img.shape[1]} x {img.shape[0]}, not its header's and "
                            f"camera's {width} x {height}", path)
    converted = []
    if img.ndim == 3:
        code = {3: cv2.COLOR_BGR2GRAY, 4: cv2.COLOR_BGRA2GRAY}.get(img.shape[2])
        if code is None:
            raise error("E190", f"image {path} has {img.shape[2]} channels (grey, BGR or BGRA are read)", path)
        img = cv2.cvtColor(img, code)
    if img.dtype == np.uint16:
        img = (img.astype(np.float32) / 257.0 + 0.5).astype(np.uint8)
        converted.append("16-bit")
    elif img.dtype != np.uint8:
        raise error("E190", f"image {path} has {img.dtype} pixels (8- or 16-bit are read)", path)
    if converted and warnings is not None:
        warnings.append(Diagnostic("warning", "W190", f"image {path}: {', '.join(converted)} pixels scaled to "
                                   "8-bit for the detectors", at(path)))
    return np.ascontiguousarray(img)


def check_finite_pose(frame: Frame) -> None:
    if frame.pose is None or not all(math.isfinite(v) for v in frame.pose):
        first = next(iter(frame.images.values()))
        raise error("E192", f"frame {frame.label} has no usable pose", first)
