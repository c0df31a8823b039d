"""Trajectory files: robot paths as datasets and SLAM tools write them, read into 6-DoF poses.

Formats (each pose is the file's frame, the "body", in the file's world):
- `tum`: `timestamp tx ty tz qx qy qz qw` a line (seconds, metres, Hamilton quaternion, w last), `#` comments
  (TUM RGB-D's groundtruth.txt: the colour camera's optical centre in the motion-capture world);
- `euroc`: EuRoC MAV's ground truth CSV, `#timestamp, p_RS_R_x [m], ..., q_RS_w [], q_RS_x [], ...`
  (nanoseconds; w first; the IMU body frame S in the world R; further columns ignored);
- `kitti`: KITTI odometry poses, 12 numbers a line, the row-major [R | t] of camera 0 in camera 0's frame
  at the first pose (x right, y down, z forward); no timestamps: a `rate` or a times file gives them;
- `csv`: a header naming the columns (comma or white-space separated): t, x, y, z and qx, qy, qz, qw or
  roll, pitch, yaw (R = Rz(yaw) Ry(pitch) Rx(roll)); a unit in brackets, `t [ns]`, `yaw [deg]`, `x [mm]`;
  without a t column, a `rate` gives the timestamps.

Every problem is a `TrajectoryError` naming the line of the file it is on.

Files as they are (the rules, `judge`): a line whose timestamp repeats the one before it (TUM's fr2/desk has
one) is dropped, the first pose with that timestamp kept, and `Trajectory.repeated` names it for a warning. evo
reads such a file too: its reader keeps every row and its `check` reports "not ascending or duplicates"; its
association (evo/core/sync.py matching_time_indices) matches a repeated timestamp to the first row up to v1.36
(np.argmin) and to the last from v1.38 (np.searchsorted, side "right"). A timestamp that goes back is an error. Given
the window (`from`, `to`: seconds from the file's first pose), only the lines in
it and the one pose either side of it (what interpolation uses) are judged and kept; the others are not judged.
A line that is not numbers is an error wherever it is (its time is unknown).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from decimal import Decimal

import numpy as np

from wiredsl.engine import geometry

FORMATS = ("tum", "euroc", "kitti", "csv")
ROUNDING = 1e-3  # |length - 1| of a quaternion (or R^T R - I of a matrix) up to this: printed digits, silent
NOT_UNIT = 0.1  # beyond this it is not a rotation: an error; in between, normalised with a warning
MAX_COORDINATE = 1e9  # metres: as the language's lengths, so that sums and products of a few stay finite
MAX_SPAN = 1e12  # seconds (30,000 years) from the first pose: so that the poses of a period stay countable

_TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
_LENGTH_UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
_ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180.0}
_COLUMNS = {"t": "t", "time": "t", "timestamp": "t", "stamp": "t",
            **{f"{p}{a}": a for a in "xyz" for p in ("", "t", "p", "p_", "p_rs_r_", "pos_", "position_")},
            **{f"{p}{a}": f"q{a}" for a in "wxyz" for p in ("q", "q_", "q_rs_", "quat_", "orientation_")},
            "roll": "roll", "pitch": "pitch", "yaw": "yaw"}
_UNIT_KIND = {"t": _TIME_UNITS, "x": _LENGTH_UNITS, "y": _LENGTH_UNITS, "z": _LENGTH_UNITS,
              "roll": _ANGLE_UNITS, "pitch": _ANGLE_UNITS, "yaw": _ANGLE_UNITS}


class TrajectoryError(ValueError):
    """A trajectory file that cannot be used; `line` is the 1-based line of the file (None: the whole file)."""

    def __init__(self, message: str, line: int | None = None):
        super().__init__(message)
        self.line = line


@dataclass(frozen=True)
class Trajectory:
    """Poses of the file's frame in the file's world, in file order."""

    times: np.ndarray | None  # (n,) seconds from the first pose; None: the file has none (KITTI without them)
    positions: np.ndarray  # (n, 3) metres
    rotations: np.ndarray  # (n, 3, 3) world_from_body
    lines: np.ndarray  # (n,) the line of each pose in the file
    normalised: tuple[tuple[int, str], ...] = ()  # (line, what was off) of rotations normalised beyond ROUNDING
    repeated: tuple[tuple[int, int], ...] = ()  # (line dropped, the earlier line with its timestamp)
    origin: float | None = None  # the file's first timestamp (times[0] unless lines before the window were left)
    start_ns: int | None = None  # the file's first timestamp on its own clock, integer nanoseconds (None: no clock)
    span: float | None = None  # seconds from the file's first timestamp to its last (before any window)


def guess_format(text: str) -> str:
    """The format of a trajectory file: EuRoC's by its header, else by its first line of data (a CSV's header
    is words, or its rows have commas; KITTI's rows 12 numbers; TUM's 8)."""
    for line in text.splitlines():
        if "p_rs_r_x" in line.lower():
            return "euroc"
        words = line.replace(",", " ").split()
        if not words or line.lstrip().startswith("#"):
            continue
        try:
            float(words[0])
        except ValueError:
            return "csv"  # a header
        return "csv" if "," in line else "kitti" if len(words) == 12 else "tum"
    raise TrajectoryError("the file holds no poses")


def read(text: str, fmt: str | None = None, times: np.ndarray | None = None, rate: float | None = None,
         window: tuple[float | None, float | None] | None = None) -> Trajectory:
    """The poses of a trajectory file's text; KITTI's timestamps from `times` (`read_times`) or `rate`, a CSV's
    without a time column from `rate`; judged by the module's rules within `window` (from, to: seconds from the
    first pose; None: the whole file)."""
    fmt = fmt or guess_format(text)
    if fmt == "csv" and times is None:
        traj = _csv(text, fmt, rate)
    elif fmt == "kitti":
        traj = _kitti(text)
        if times is not None:
            stamps = times - times[0] if len(times) else times
            if len(stamps) != len(traj.lines):
                n, m = len(stamps), len(traj.lines)
                raise TrajectoryError(f"the times file has {n} timestamp{'s' * (n != 1)} for {m} pose{'s' * (m != 1)}")
            traj = Trajectory(stamps, traj.positions, traj.rotations, traj.lines, traj.normalised,
                              start_ns=round(float(times[0]) * 1e9) if len(times) else None)
        elif rate is not None:
            traj = Trajectory(np.arange(len(traj.lines)) / rate, traj.positions, traj.rotations, traj.lines,
                              traj.normalised)
    elif times is not None or rate is not None:
        raise TrajectoryError("the file has its own timestamps: 'rate' is for KITTI's poses and a CSV without a "
                              "time column, 'times' for KITTI's poses")
    elif fmt == "tum":
        traj = _tum(text)
    else:
        traj = _csv(text, fmt)
    far = np.flatnonzero(np.abs(traj.positions).max(axis=1) > MAX_COORDINATE)
    if len(far):
        raise TrajectoryError(f"a position beyond {MAX_COORDINATE:g} m", int(traj.lines[far[0]]))
    if traj.times is not None:
        traj = judge(traj, window)
    return traj


def judge(traj: Trajectory, window: tuple[float | None, float | None] | None = None) -> Trajectory:
    """The poses the module's rules keep: within the window and one pose either side of it, repeated timestamps
    dropped (named in `repeated`); an error at a timestamp that goes back among them."""
    t = traj.times
    origin = float(t[0])
    keep = np.ones(len(t), dtype=bool)
    if window is not None and len(t):
        rel = t - origin
        lo = -np.inf if window[0] is None else window[0]
        hi = np.inf if window[1] is None else window[1]
        inside = (rel >= lo) & (rel <= hi)
        keep = inside.copy()
        keep[1:] |= inside[:-1]  # the pose after the window's last, and the one before its first
        keep[:-1] |= inside[1:]
        keep[0] = True  # the first pose sets the clock
    idx = np.flatnonzero(keep)
    tk = t[idx]
    again = np.concatenate([[False], tk[1:] == tk[:-1]])
    first = idx[np.maximum.accumulate(np.where(~again, np.arange(len(idx)), 0))]  # the run's first line
    repeated = tuple((int(traj.lines[i]), int(traj.lines[j])) for i, j in zip(idx[again], first[again], strict=True))
    idx = idx[~again]
    _check_increasing(t[idx], traj.lines[idx])
    lines = set(traj.lines[idx].tolist())
    return Trajectory(t[idx], traj.positions[idx], traj.rotations[idx], traj.lines[idx],
                      tuple(n for n in traj.normalised if n[0] in lines), repeated, origin, traj.start_ns,
                      float(t.max() - origin) if len(t) else 0.0)


def _numbers(words: list[str], n: int, what: str, line: int) -> list[float]:
    if len(words) != n:
        raise TrajectoryError(f"expected {n} numbers ({what}), found {len(words)}", line)
    out = []
    for w in words:
        try:
            if "_" in w:  # Python reads 1_000; no trajectory writer does, nor Decimal
                raise ValueError
            v = float(w)
        except ValueError:
            raise TrajectoryError(f"'{w}' is not a number", line) from None
        if not math.isfinite(v):
            raise TrajectoryError(f"'{w}' is not a finite number", line)
        out.append(v)
    return out


def _rows(text: str):
    """(line number, words) of every line that is neither blank nor a `#` comment."""
    for i, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if s and not s.startswith("#"):
            yield i, s


def _table(text: str, n: int, what: str, sep: str | None = None, after: int = 0
           ) -> tuple[np.ndarray, np.ndarray, list[list[str]]]:
    """(lines (m,), numbers (m, n), words) of the data rows after line `after`: each row n finite numbers."""
    data = [(i, s) for i, s in _rows(text) if i > after]
    if not data:
        raise TrajectoryError("the file holds no poses")
    rows = [(i, _split(s, sep)) for i, s in data]
    words = [w for _, w in rows]
    a = None
    if all(len(w) == n for w in words) and not any("_" in s for _, s in data):  # numpy's fast reading
        try:
            a = np.array(words, dtype=float)
        except ValueError:
            a = None
    if a is None or not np.isfinite(a).all():  # find the first bad row, and say what is wrong with it
        a = np.array([_numbers(w, n, what, i) for i, w in rows])
    return np.array([i for i, _ in rows]), a, words


def _tum(text: str) -> Trajectory:
    lines, a, words = _table(text, 8, "timestamp tx ty tz qx qy qz qw")
    R, fixed = _from_quaternions(a[:, 4:8], lines)
    stamps = [w[0] for w in words]
    return Trajectory(_seconds(stamps), a[:, 1:4], R, lines, fixed, start_ns=_nanoseconds(stamps))


def _kitti(text: str) -> Trajectory:
    lines, a, _ = _table(text, 12, "a row-major 3 x 4 matrix [R | t]")
    M = a.reshape(-1, 3, 4)
    R, fixed = _nearest_rotations(M[:, :, :3], lines)
    return Trajectory(None, M[:, :, 3], R, lines, fixed)


def read_times(text: str) -> np.ndarray:
    """The timestamps of a times file (KITTI's times.txt): one number a line."""
    lines, a, _ = _table(text, 1, "a timestamp")
    _check_increasing(a[:, 0], lines)
    return a[:, 0]


def _header(text: str) -> tuple[int, list[str], str | None]:
    for i, line in enumerate(text.splitlines(), 1):
        s = line.strip().lstrip("#").strip()
        if s:
            sep = "," if "," in s else None
            return i, _split(s, sep), sep
    raise TrajectoryError("the file holds no header")


def _split(s: str, sep: str | None) -> list[str]:
    if sep is None:
        return s.split()
    words = [w.strip() for w in s.split(sep)]
    return words[:-1] if sep and words and words[-1] == "" else words  # a trailing comma ends some writers' rows


def _csv(text: str, fmt: str, rate: float | None = None) -> Trajectory:
    """A CSV with a header; without a `t` column the poses are `rate` per second apart."""
    line0, names, sep = _header(text)
    cols: dict[str, tuple[int, float]] = {}  # role -> (column, factor to SI)
    for k, name in enumerate(names):
        m = re.fullmatch(r"([^\[\]]*)(?:\[([^\]]*)\])?", name)  # (one way to split: linear in the name's length)
        key, unit = (m.group(1).strip().lower(), (m.group(2) or "").strip()) if m else (name.lower(), "")
        role = _COLUMNS.get(key)
        if role is None or role in cols:
            continue  # other columns (EuRoC's velocities and biases) are not poses' business
        if fmt == "euroc" and role == "t":
            unit = unit or "ns"  # EuRoC's ground truth writes '#timestamp' without its unit
        factors = _UNIT_KIND.get(role, {})
        if unit and factors and unit not in factors:
            raise TrajectoryError(f"column '{name}': unit '{unit}' is not one of {', '.join(factors)}", line0)
        cols[role] = (k, factors.get(unit, 1.0) if unit else 1.0)
    quaternion = all(f"q{a}" in cols for a in "wxyz")
    partial = [f"q{a}" for a in "wxyz" if f"q{a}" not in cols]
    euler = [names[cols[r][0]] for r in ("roll", "pitch", "yaw") if r in cols]
    if quaternion and euler:
        raise TrajectoryError(f"the header gives the orientation twice: a quaternion and {', '.join(euler)} "
                              "(keep one; wiredsl would not know which to believe)", line0)
    if 0 < len(partial) < 4:
        raise TrajectoryError(f"the header names part of a quaternion: no column {', '.join(partial)}", line0)
    if rate is not None and "t" in cols:
        raise TrajectoryError(f"the file has its own timestamps (column '{names[cols['t'][0]]}'): 'rate' is for a "
                              "CSV without a time column", line0)
    need = ([] if rate is not None else ["t"]) + ["x", "y"] + (
        [] if quaternion or "yaw" in cols else ["qw, qx, qy, qz (or yaw)"])
    missing = [n for n in need if n not in cols and n.split(",")[0] not in cols]
    if missing:
        hint = " (or declare 'rate' for poses at a fixed rate)" if missing[0] == "t" else ""
        raise TrajectoryError(f"the header names no column {' or '.join(missing)} (it names {', '.join(names)})"
                              + hint, line0)
    lines, a, words = _table(text, len(names), f"one a column of the header at line {line0}", sep, line0)

    def col(role: str, default: float = 0.0) -> np.ndarray:
        if role not in cols:
            return np.full(len(a), default)
        k, factor = cols[role]
        return a[:, k] * factor

    positions = np.column_stack([col("x"), col("y"), col("z")])
    if quaternion:
        R, fixed = _from_quaternions(np.column_stack([col("qx"), col("qy"), col("qz"), col("qw")]), lines)
    else:
        from scipy.spatial.transform import Rotation

        ypr = np.column_stack([col("yaw"), col("pitch"), col("roll")])
        R, fixed = Rotation.from_euler("ZYX", ypr).as_matrix(), ()
    if rate is not None:
        return Trajectory(np.arange(len(a)) / rate, positions, R, lines, fixed)
    k, factor = cols["t"]
    stamps = [w[k] for w in words]
    return Trajectory(_seconds(stamps, factor), positions, R, lines, fixed, start_ns=_nanoseconds(stamps, factor))


def _nanoseconds(stamps: list[str], factor: float = 1.0) -> int | None:
    """The first timestamp (its unit `factor` seconds) in integer nanoseconds, in exact decimal."""
    if not stamps:
        return None
    return int((Decimal(stamps[0]) * Decimal(repr(factor)) * 10**9).to_integral_value())


def _seconds(stamps: list[str], factor: float = 1.0) -> np.ndarray:
    """Times from the first, differences taken in exact decimal: a timestamp's digits (EuRoC's nanoseconds past
    2^53, TUM's microseconds of 1.3e9 s) are kept, as float64 of the whole stamp would not keep them."""
    first = Decimal(stamps[0])
    return np.array([float(Decimal(w) - first) for w in stamps]) * factor


def _from_quaternions(q: np.ndarray, lines: np.ndarray) -> tuple[np.ndarray, tuple]:
    """Rotation matrices of (n, 4) x, y, z, w quaternions, normalised; lengths far from 1 refused."""
    from scipy.spatial.transform import Rotation

    big = np.flatnonzero(np.abs(q).max(axis=1) > 1.0 + NOT_UNIT)  # before any square can overflow
    n = np.linalg.norm(np.clip(q, -2.0, 2.0), axis=1)
    off = np.abs(n - 1.0)
    bad = np.union1d(big, np.flatnonzero(off > NOT_UNIT))
    if len(bad):
        i = bad[0]
        length = f"{n[i]:.6g}" if i not in big else f"over {np.abs(q[i]).max():.6g}"
        raise TrajectoryError(f"quaternion of length {length} is not a rotation (a unit quaternion has length 1)",
                              int(lines[i]))
    fixed = tuple((int(lines[i]), f"quaternion of length {n[i]:.6g} normalised")
                  for i in np.flatnonzero(off > ROUNDING))
    return Rotation.from_quat(q / n[:, None]).as_matrix(), fixed


def _nearest_rotations(M: np.ndarray, lines: np.ndarray) -> tuple[np.ndarray, tuple]:
    """The rotations nearest to (n, 3, 3) matrices (SVD); matrices far from a rotation refused."""
    M = np.clip(M, -2.0, 2.0)  # a rotation's entries are within [-1, 1]: no square of these overflows
    off = np.abs(np.einsum("nji,njk->nik", M, M) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(M)
    bad = np.flatnonzero((off > NOT_UNIT) | (det <= 0))
    if len(bad):
        i = bad[0]
        why = "a reflection (determinant < 0)" if det[i] <= 0 else f"R^T R differs from I by {off[i]:.3g}"
        raise TrajectoryError(f"the matrix is not a rotation: {why}", int(lines[i]))
    U, _, Vt = np.linalg.svd(M)
    fixed = tuple((int(lines[i]), f"rotation matrix with R^T R off I by {off[i]:.3g}: the nearest rotation is used")
                  for i in np.flatnonzero(off > ROUNDING))
    return U @ Vt, fixed


def _check_increasing(t: np.ndarray, lines: np.ndarray) -> None:
    far = np.flatnonzero(~(np.abs(t - t[0]) <= MAX_SPAN)) if len(t) else []
    if len(far):
        raise TrajectoryError(f"the timestamp is over {MAX_SPAN:g} s from the first", int(lines[far[0]]))
    steps = np.flatnonzero(np.diff(t) <= 0)
    if len(steps):
        i = int(steps[0]) + 1
        raise TrajectoryError(f"the timestamp does not increase: {t[i]:.9g} s from the first pose, the previous "
                              f"(line {lines[i - 1]}) {t[i - 1]:.9g} s", int(lines[i]))


def resample(traj: Trajectory, every: float | None = None, start: float | None = None, end: float | None = None,
             limit: int | None = None, max_poses: int | None = None, with_times: bool = False) -> tuple:
    """(positions (n, 3), rotations (n, 3, 3)) of the poses in the window [start, end] (seconds from the file's
    first pose): every `every` seconds by linear and spherical (slerp) interpolation, else the file's own;
    at most `limit` (the first). `with_times`: and the poses' times (n,), seconds from the file's first pose (None
    for a file without timestamps)."""
    P, R, ts = _resample(traj, every, start, end, limit, max_poses)
    return (P, R, ts) if with_times else (P, R)


def _resample(traj: Trajectory, every, start, end, limit, max_poses) -> tuple:
    if traj.times is None:
        if every is not None or start is not None or end is not None:
            raise TrajectoryError("the file has no timestamps: give KITTI's times file or a rate")
        P, R = traj.positions, traj.rotations
        return P[:limit], R[:limit], None
    t = traj.times - (traj.times[0] if traj.origin is None else traj.origin)  # a times file need not start at 0
    lo = 0.0 if start is None else max(start, 0.0)  # the window starts at the first pose at the earliest
    hi = t[-1] if end is None else min(end, t[-1])
    if lo > hi:
        span = traj.span if traj.span is not None else float(t[-1])
        window = f"from {lo:g} s" + ("" if end is None else f" to {end:g} s")
        raise TrajectoryError(f"the window {window} holds no pose: the file spans 0 s to {span:g} s (from its "
                              "first pose)")
    if every is None:
        keep = (t >= lo) & (t <= hi)
        return traj.positions[keep][:limit], traj.rotations[keep][:limit], t[keep][:limit]
    if max_poses is not None and hi - lo >= every * max_poses:  # no division: a tiny period would give inf
        raise TrajectoryError(f"one pose every {every:g} s over {hi - lo:g} s exceeds the limit of {max_poses:,} "
                              "poses")
    n = math.floor((hi - lo) / every + 1e-9) + 1
    if limit is not None:
        n = min(n, limit)
    if max_poses is not None and n > max_poses:
        raise TrajectoryError(f"{n:,} poses exceed the limit of {max_poses:,}")
    ts = lo + every * np.arange(n)
    ts = np.minimum(ts, t[-1])  # the last sample may pass the end by rounding
    P = np.column_stack([np.interp(ts, t, traj.positions[:, k]) for k in range(3)])
    if len(t) == 1:
        return P, np.repeat(traj.rotations[:1], n, axis=0), ts
    from scipy.spatial.transform import Rotation, Slerp

    return P, Slerp(t, Rotation.from_matrix(traj.rotations))(ts).as_matrix(), ts


def world_from_robot(P: np.ndarray, R: np.ndarray, body: tuple, world: tuple) -> tuple[np.ndarray, np.ndarray]:
    """The robot's poses (R_wr (n, 3, 3), t_wr (n, 3)) from the file's (positions P (n, 3), rotations R (n, 3, 3)):
    world_from_robot = world_from_file . file_from_body . body_from_robot, with `body` = robot_from_body (R, p)
    and `world` = world_from_file (R, t)."""
    (R_rb, p_rb), (R_sf, t_sf) = body, world
    return geometry.world_from_robot_via(R_sf @ R, P @ R_sf.T + t_sf, R_rb, p_rb)


def implausible(R_wr: np.ndarray, t_wr: np.ndarray) -> list[tuple[str, str]]:
    """(message, hint) for a path that is most likely in the wrong frames: a robot on its side (a camera's
    or IMU's poses taken for the robot's), or one that climbs more than it drives (a world whose z is not up)."""
    out = []
    tilt = math.degrees(math.acos(float(np.clip(np.median(R_wr[:, 2, 2]), -1.0, 1.0))))
    if tilt > 60:
        out.append((f"the robot's up (z) axis is {tilt:.0f} deg from the scene's up at the median pose",
                    "the file's poses may be a camera's ('body camera left') or an IMU's ('body kalibr ...'), or "
                    "its world not z-up ('world rotate x -90deg ...')"))
    rise, run = float(np.ptp(t_wr[:, 2])), float(np.hypot(*np.ptp(t_wr[:, :2], axis=0)))
    if rise > 1.0 and rise > 2 * run:
        out.append((f"the path rises {rise:.3g} m and runs {run:.3g} m across the floor",
                    "the file's world may not be z-up: turn it with 'world rotate ...' (KITTI's: 'world rotate x "
                    "-90deg rotate z -90deg')"))
    return out
