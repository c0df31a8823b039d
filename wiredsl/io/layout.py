"""The npz dump's layout: every member, column and code, as data (rendered into the README, checked by tests).

`features.npz` is an ordinary numpy zip (np.load reads it, no pickles). Its
strokes and corners come in batches of trials; batch b's members are named
`b{b:05d}_<member>`. Pixel coordinates follow the JSON dump's convention
(origin at the image's top-left corner).
"""

from __future__ import annotations

import json
import math

NPZ_VERSION = 5  # 1: seven stroke columns; 2: closed, fragment, occluded, views and conics added;
# 3: view cameras with k3..k6 and the lens model; 4: the stroke column `contour`; 5: view cameras with the
# wide-angle models' xi, alpha, beta, w

STROKE_COLUMNS = (
    ("trial", "Monte-Carlo trial (0 for the ideal projection)"),
    ("pose", "index of the pose in the scene's path"),
    ("camera", "0 left, 1 right"),
    ("feature", "feature id: index into `feature_ids` (`placement.feature`)"),
    ("segment", "segment of a polyline, side 0 or 1 of a silhouette; -1 when none"),
    ("kind", "0 straight (a segment in the image), 1 curve (a line's image under distortion), 2 ellipse (arc)"),
    ("clipped", "1 when cut by the image border or the near plane"),
    ("closed", "1 when the last vertex joins the first (a whole ellipse)"),
    ("fragment", "the JSON dump's `fragment`: piece number after a cut; -1 when whole (null in JSON)"),
    ("occluded", "1 for a visible part of a feature that occlusion cut (--visibility exact)"),
    ("contour", "1 for (part of) a smooth mesh surface's occluding contour in this view: view-dependent "
     "(the JSON dump's `contour`)"),
)
CORNER_COLUMNS = (
    ("trial", "Monte-Carlo trial"),
    ("pose", "index of the pose in the scene's path"),
    ("camera", "0 left, 1 right"),
    ("feature", "feature id: index into `feature_ids`"),
)
VIEW_COLUMNS = (
    ("trial", "Monte-Carlo trial"),
    ("pose", "index of the pose in the scene's path"),
    ("camera", "0 left, 1 right"),
)
# `model`: the lens model's code, 0 radtan, 1 equidistant, 2 unified, 3 eucm, 4 ds, 5 fov (geometry.MODELS); the
# wide-angle models' numbers after it
LENS_MODELS = ("radtan", "equidistant", "unified", "eucm", "ds", "fov")
CAMERA_COLUMNS = ("f", "ax", "ay", "cx", "cy", "k1", "k2", "p1", "p2", "width", "height", "k3", "k4", "k5", "k6",
                  "model", "xi", "alpha", "beta", "w")


def camera_value(camera, column: str) -> float:
    """A camera's number in CAMERA_COLUMNS (the lens model as its code)."""
    return LENS_MODELS.index(camera.distortion) if column == "model" else getattr(camera, column)


CONIC_COLUMNS = (
    ("trial", "Monte-Carlo trial"),
    ("pose", "index of the pose in the scene's path"),
    ("camera", "0 left, 1 right"),
    ("feature", "feature id: index into `feature_ids`"),
    ("clipped", "1 when the ellipse's image is cut by the image border"),
    ("section", "1 for an ellipse section (its arc is in `conics` columns 5 and 6), 0 for a whole ellipse"),
)
KINDS = {0: "straight", 1: "curve", 2: "ellipse"}
CAMERAS = ("left", "right")

# (member, dtype, shape, meaning); a `b_` prefix stands for each batch's `b{b:05d}_`
MEMBERS = (
    ("b_pts", "float32", "(N, 2)", "stroke vertices (u, v) in pixels, all strokes of the batch end to end "
     "(float32: about 3e-5 px at 640 px)"),
    ("b_start", "int64", "(S + 1,)", "stroke k's vertices are pts[start[k]:start[k + 1]]"),
    ("b_strokes", "int32", f"(S, {len(STROKE_COLUMNS)})", "one row a stroke; columns below"),
    ("b_corners", "float32", "(C, 2)", "corner positions (u, v) in pixels"),
    ("b_corner_rows", "int32", f"(C, {len(CORNER_COLUMNS)})", "one row a corner; columns below"),
    ("b_views", "int32", f"(V, {len(VIEW_COLUMNS)})", "one row a camera view (trial, pose, camera)"),
    ("b_view_cameras", "float64", f"(V, {len(CAMERA_COLUMNS)})",
     "each view's camera as projected (perturbed under calibration error): " + ", ".join(CAMERA_COLUMNS)
     + " (model: " + ", ".join(f"{i} {m}" for i, m in enumerate(LENS_MODELS)) + ")"),
    ("b_view_poses", "float64", "(V, 12)", "each view's R (row-major, 9) and t (3) of P_cam = R P_world + t, "
     "full precision"),
    ("b_conics", "float64", "(K, 7)", "analytic ellipse images (undistorted cameras, ideal projection only): "
     "centre u, v; semi-axes; angle of the first axis (rad); arc start, end (0, 0 when whole)"),
    ("b_conic_rows", "int32", f"(K, {len(CONIC_COLUMNS)})", "one row a conic; columns below"),
    ("feature_ids", "unicode", "(F,)", "`placement.feature` of every feature id"),
    ("layout", "int64", "()", f"this layout's version ({NPZ_VERSION})"),
    ("manifest", "unicode", "()", "the run's manifest as JSON text (schema/manifest.schema.json)"),
)


def column(name: str) -> int:
    """Index of a column of `strokes` by name."""
    return [c for c, _ in STROKE_COLUMNS].index(name)


def markdown() -> str:
    """The layout as Markdown tables (the README's npz section)."""
    out = ["| member | dtype | shape | holds |", "|---|---|---|---|"]
    out += [f"| `{m.replace('b_', 'b00000_', 1) if m.startswith('b_') else m}` | {d} | {s} | {t} |"
            for m, d, s, t in MEMBERS]
    out += ["", "`strokes` columns (int32):", "", "| column | name | holds |", "|---|---|---|"]
    out += [f"| {i} | `{n}` | {t} |" for i, (n, t) in enumerate(STROKE_COLUMNS)]
    for name, cols in (("corner_rows", CORNER_COLUMNS), ("views", VIEW_COLUMNS), ("conic_rows", CONIC_COLUMNS)):
        out += ["", f"`{name}` columns (int32):", "", "| column | name | holds |", "|---|---|---|"]
        out += [f"| {i} | `{n}` | {t} |" for i, (n, t) in enumerate(cols)]
    return "\n".join(out) + "\n"


MAX_MEMBER_BYTES = 1 << 30  # an npz member larger than this (uncompressed, as its zip entry declares) is refused


class NpzError(ValueError):
    """An npz file refused before its arrays are read: not a zip of plain .npy arrays of a sane size."""


def open_npz(path):
    """np.load of an npz whose every member was first checked without reading its data.

    A member must be a .npy array of a plain dtype (no pickled Python objects; allow_pickle stays off), whose
    header's shape accounts for exactly the bytes its zip entry declares, at most MAX_MEMBER_BYTES: a zip
    bomb or a header claiming a huge shape is refused before anything is inflated. NpzError says why.
    """
    import tokenize
    import zipfile

    import numpy as np

    try:
        with zipfile.ZipFile(path) as z:
            for info in z.infolist():
                name = info.filename
                if not name.endswith(".npy"):
                    raise NpzError(f"member '{name}' is not a .npy array")
                if info.file_size > MAX_MEMBER_BYTES:
                    raise NpzError(f"member '{name}' is {info.file_size:,} bytes uncompressed, over the limit of "
                                   f"{MAX_MEMBER_BYTES:,}")
                with z.open(info) as fh:
                    try:
                        version = np.lib.format.read_magic(fh)
                        read = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
                            np.lib.format.read_array_header_2_0
                        shape, _, dtype = read(fh)
                    except (ValueError, SyntaxError, TypeError, KeyError, tokenize.TokenError, EOFError) as exc:
                        raise NpzError(f"member '{name}' has a damaged array header ({exc})") from None
                    if dtype.hasobject:
                        raise NpzError(f"member '{name}' holds Python objects (a pickle): refused, never unpickled")
                    need = math.prod(shape) * dtype.itemsize
                    if need != info.file_size - fh.tell():
                        raise NpzError(f"member '{name}': its header's shape {shape} ({dtype}) needs {need:,} bytes, "
                                       f"the member holds {info.file_size - fh.tell():,}")
        return np.load(path, allow_pickle=False)
    except (OSError, zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, NotImplementedError, RuntimeError) as exc:
        # NotImplementedError: a zip feature Python does not read (a method, a version); RuntimeError: encrypted
        raise NpzError(f"not an npz file this reader takes: {exc}") from None


def npz_problems(path) -> list[str]:
    """Why a file is not a features.npz of this layout (empty when it is): members, dtypes, shapes, manifest."""

    import zipfile

    try:
        with open_npz(path) as data:
            return _layout_problems(data)
    except NpzError as exc:
        return [str(exc)]
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, NotImplementedError, RuntimeError) as exc:  # damaged
        return [f"a damaged member: {exc}"]


def _shape_problems(key: str, a, dtype: str, shape: str) -> list[str]:
    """A member's dtype and shape against its row of MEMBERS ("(N, 2)": two dimensions, the second 2)."""
    import numpy as np

    dims = [d.strip() for d in shape.strip("()").split(",") if d.strip()]
    kind_ok = a.dtype.kind == "U" if dtype == "unicode" else a.dtype == np.dtype(dtype)
    if not kind_ok:
        return [f"{key}: dtype {a.dtype}, expected {dtype}"]
    if a.ndim != len(dims) or any(d.isdigit() and a.shape[i] != int(d) for i, d in enumerate(dims)):
        return [f"{key}: shape {a.shape}, expected {shape}"]
    return []


def _rows_problems(data, b: str, n_ids: int) -> list[str]:
    """Each batch's row members: one row per value, cameras 0 or 1, feature ids within feature_ids."""
    out = []
    for values, rows in (("corners", "corner_rows"), ("view_cameras", "views"), ("view_poses", "views"),
                         ("conics", "conic_rows")):
        if len(data[f"{b}_{values}"]) != len(data[f"{b}_{rows}"]):
            out.append(f"{b}: {values} and {rows} differ in length")
    for rows, has_feature in (("strokes", True), ("corner_rows", True), ("views", False), ("conic_rows", True)):
        r = data[f"{b}_{rows}"]
        if len(r) and not ((r[:, 2] == 0) | (r[:, 2] == 1)).all():
            out.append(f"{b}_{rows}: a camera other than 0 (left) or 1 (right)")
        if len(r) and ((r[:, :2] < 0).any() or (has_feature and not (0 <= r[:, 3].min() <= r[:, 3].max() < n_ids))):
            out.append(f"{b}_{rows}: a negative trial or pose, or a feature id outside feature_ids")
    return out


def _layout_problems(data) -> list[str]:
    """npz_problems of an opened npz."""
    import numpy as np

    names = set(data.files)
    out = [f"missing member '{m}'" for m in ("feature_ids", "layout", "manifest") if m not in names]
    if out:
        return out
    for m, dtype, shape, _ in MEMBERS[-3:]:
        out += _shape_problems(m, data[m], dtype, shape)
    if out:
        return out
    if int(data["layout"]) != NPZ_VERSION:
        return [f"layout {int(data['layout'])}, this wiredsl reads {NPZ_VERSION}"]
    batches = sorted({n.split("_", 1)[0] for n in names if n.startswith("b") and n[1:6].isdigit()})
    n_ids = len(data["feature_ids"])
    for b in batches:
        for m, dtype, shape, _ in MEMBERS[:-3]:
            key = f"{b}_{m[2:]}"
            if key not in names:
                out.append(f"missing member '{key}'")
            else:
                out += _shape_problems(key, data[key], dtype, shape)
        if out:
            continue
        start, strokes, pts = data[f"{b}_start"], data[f"{b}_strokes"], data[f"{b}_pts"]
        if strokes.shape[1:] != (len(STROKE_COLUMNS),) or len(start) != len(strokes) + 1 \
                or start[-1] != len(pts) or (np.diff(start) < 2).any():
            out.append(f"{b}: strokes, start and pts do not agree")
        elif len(strokes) and not (0 <= strokes[:, column("feature")].min() <= strokes[:, column("feature")].max()
                                   < n_ids):
            out.append(f"{b}: a feature id outside feature_ids")
        elif not all(np.isfinite(data[f"{b}_{m}"]).all() for m in ("pts", "corners", "view_cameras", "view_poses",
                                                                    "conics")):
            out.append(f"{b}: non-finite coordinates")
        else:
            out += _rows_problems(data, b, n_ids)
    from wiredsl.io.schema import problems

    try:
        manifest = json.loads(str(data["manifest"]))
    except json.JSONDecodeError as exc:
        return [*out, f"manifest: not JSON: {exc.msg}"]
    return out + [f"manifest: {m}" for m in problems(manifest)]
