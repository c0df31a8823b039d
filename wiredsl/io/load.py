"""`wiredsl.load`: read a build's dump (features.json, features.jsonl, features.npz) back into a program.

Records are the JSON dump's feature objects (`kind`, `source`, `segment`,
`fragment`, `clipped`, `occluded`, and `points`, `closed`, `at` or the conic's
fields), each with the `trial`, `pose` and `camera` ("left" or "right") it
belongs to; the ideal projection is trial 0. They come in the JSON dump's order:
per trial, pose and camera, lines, polylines, conics, then corners. An npz dump
gives the same records (its stroke and corner pixels are float32); with
`arrays=True` it gives its arrays instead (layout.py), including each view's
camera, rotation and translation.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

from wiredsl.io import layout
from wiredsl.io.files import json_loads

KIND_ORDER = ("lines", "polylines", "conics", "corners")


def load(path, *, trial=None, pose=None, camera=None, arrays: bool = False):
    """Records (list of dicts) of a dump, or its arrays (npz only), selected by trial, pose and camera.

    Each selector is None (everything), one value or a collection; camera is "left", "right", 0 or 1.
    """
    path = Path(path)
    pick = _selector(trial), _selector(pose), _selector(_camera_index(camera))
    with open(path, "rb") as fh:
        is_zip = fh.read(4) == b"PK\x03\x04"
    if is_zip:
        try:
            return _npz_arrays(path, *pick) if arrays else _npz_records(path, *pick)
        except (KeyError, IndexError, TypeError, ValueError, EOFError, zipfile.BadZipFile, NotImplementedError,
                RuntimeError) as exc:  # RuntimeError: an encrypted member
            if str(exc).startswith(f"{path}: "):  # ours, naming the file already
                raise
            raise layout.NpzError(f"{path}: not a features.npz of layout {layout.NPZ_VERSION} ({type(exc).__name__}:"
                                  f" {exc}); `wiredsl validate {path}` says what is wrong") from None
    if arrays:
        raise ValueError(f"{path}: arrays=True reads npz dumps; this is JSON")
    text = path.read_text(encoding="utf-8")
    docs = [json_loads(line) for line in text.splitlines() if line.strip()] if path.suffix == ".jsonl" \
        else [json_loads(text)]
    out = []
    for doc in docs:
        t = doc.get("trial") or 0
        if not pick[0](t):
            continue
        for p in doc["poses"]:
            if not pick[1](p["index"]):
                continue
            for cam, side in enumerate(layout.CAMERAS):
                view = p.get(side)
                if view is None or not pick[2](cam):
                    continue
                out += [{"trial": t, "pose": p["index"], "camera": side, **f} for k in KIND_ORDER for f in view[k]]
    return out


def _camera_index(camera):
    if camera is None:
        return None
    many = camera if isinstance(camera, (list, tuple, set)) else [camera]
    return [layout.CAMERAS.index(c) if isinstance(c, str) else int(c) for c in many]


def _selector(value):
    if value is None:
        return lambda x: True
    wanted = {int(v) for v in value} if isinstance(value, (list, tuple, set, range)) else {int(value)}
    return lambda x: int(x) in wanted


def _batches(data):
    return sorted({n.split("_", 1)[0] for n in data.files if n.startswith("b") and n[1:6].isdigit()})


def _npz_arrays(path: Path, want_trial, want_pose, want_cam) -> dict:
    """The selected members of every batch, concatenated (stroke offsets rebased), with feature_ids and the
    manifest."""
    import numpy as np

    def chosen(rows):
        return np.array([want_trial(r[0]) and want_pose(r[1]) and want_cam(r[2]) for r in rows[:, :3]], dtype=bool)

    # member -> the member whose rows select it
    selected_by = {"corners": "corner_rows", "corner_rows": "corner_rows", "views": "views",
                   "view_cameras": "views", "view_poses": "views", "conics": "conic_rows", "conic_rows": "conic_rows"}
    try:
        data = layout.open_npz(path)
    except layout.NpzError as exc:
        raise layout.NpzError(f"{path}: {exc}") from None
    return _read_npz(data, path, selected_by, chosen)


def _read_npz(data, path: Path, selected_by: dict, chosen) -> dict:
    import numpy as np

    with data:
        if data["layout"].shape != () or int(data["layout"]) != layout.NPZ_VERSION:
            raise layout.NpzError(f"{path}: layout {data['layout'].tolist()}, this wiredsl reads "
                                  f"{layout.NPZ_VERSION}")
        out = {k: [] for k in ("pts", "strokes", *selected_by)}
        start = [0]
        for b in _batches(data):
            s, st = data[f"{b}_strokes"], data[f"{b}_start"]
            keep = chosen(s)
            out["pts"].append(data[f"{b}_pts"][np.repeat(keep, np.diff(st))])
            start += (start[-1] + np.cumsum(np.diff(st)[keep])).tolist()
            out["strokes"].append(s[keep])
            for m, by in selected_by.items():
                out[m].append(data[f"{b}_{m}"][chosen(data[f"{b}_{by}"])])
        arrays = {k: np.concatenate(v) for k, v in out.items() if v}
        dtypes = {m[2:]: d for m, d, _, _ in layout.MEMBERS if m.startswith("b_")}
        wrong = [k for k, v in arrays.items() if v.dtype != np.dtype(dtypes[k])]
        if wrong:
            raise layout.NpzError(f"{path}: its {wrong[0]} are {arrays[wrong[0]].dtype}, the layout's are "
                                  f"{dtypes[wrong[0]]} (`wiredsl validate {path}` says more)")
        bad = [k for k, v in arrays.items() if v.dtype.kind == "f" and not np.isfinite(v).all()]
        if bad:
            raise ValueError(f"{path}: its {bad[0]} hold NaN or infinity: not a dump wiredsl wrote "
                             f"(wiredsl validate {path} says which member)")
        arrays["start"] = np.array(start, dtype=np.int64)
        arrays["feature_ids"] = data["feature_ids"].tolist()
        arrays["manifest"] = json.loads(str(data["manifest"]))
        return arrays


def _npz_records(path: Path, *pick) -> list[dict]:
    """The JSON dump's feature records, rebuilt from the npz arrays."""
    a = _npz_arrays(path, *pick)
    ids, col = a["feature_ids"], {n: i for i, (n, _) in enumerate(layout.STROKE_COLUMNS)}
    groups: dict[tuple[int, int, int], dict[str, list]] = {}

    def group(t, p, c):
        return groups.setdefault((int(t), int(p), int(c)), {k: [] for k in KIND_ORDER})

    for k, row in enumerate(a["strokes"]):
        xy = a["pts"][a["start"][k]:a["start"][k + 1]].tolist()
        straight = row[col["kind"]] == 0 and len(xy) == 2
        rec = {"source": ids[row[col["feature"]]], "segment": _none(row[col["segment"]]),
               "fragment": _none(row[col["fragment"]]), "clipped": bool(row[col["clipped"]]),
               "occluded": bool(row[col["occluded"]]), "kind": "line" if straight else "polyline",
               "points": [[float(u), float(v)] for u, v in xy]}
        if not straight:
            rec["closed"] = bool(row[col["closed"]])
        group(*row[:3])["lines" if straight else "polylines"].append(rec)
    for (u, v), row in zip(a["corners"].tolist(), a["corner_rows"], strict=True):
        group(*row[:3])["corners"].append({"source": ids[row[3]], "segment": None, "fragment": None,
                                           "clipped": False, "occluded": False, "kind": "corner",
                                           "at": [float(u), float(v)]})
    for row, (u, v, A, B, angle, s0, s1) in zip(a["conic_rows"], a["conics"].tolist(), strict=True):
        group(*row[:3])["conics"].append({"source": ids[row[3]], "segment": None, "fragment": None,
                                          "clipped": bool(row[4]), "occluded": False, "kind": "conic",
                                          "centre": [u, v], "axes": [A, B], "angle": angle,
                                          "arc": [s0, s1] if row[5] else None})
    out = []
    for (t, p, c) in sorted(groups):
        g = groups[(t, p, c)]
        out += [{"trial": t, "pose": p, "camera": layout.CAMERAS[c], **f} for k in KIND_ORDER for f in g[k]]
    return out


def _none(x) -> int | None:
    return None if x < 0 else int(x)
