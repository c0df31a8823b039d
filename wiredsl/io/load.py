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

from wiredsl.files import UnreadableFile, json_loads, read_regular, regular_size
from wiredsl.io import layout

KIND_ORDER = ("lines", "polylines", "conics", "corners")
MAX_JSON_BYTES = 1 << 30  # a JSON or JSON-lines dump read whole (as `validate` reads one)


class DumpError(ValueError):
    """The file is not a features dump, or the selection asks for what the dump does not hold."""


_NOT_A_DUMP = "pass features.json, features.jsonl or features.npz"
_DOCUMENTS = {"manifest": "a run manifest", "study": "a study table", "study-manifest": "a study manifest",
              "viewdep": "a view-dependency file", "scene": "a compiled scene"}


def load(path, *, trial=None, pose=None, camera=None, arrays: bool = False):
    """Records (list of dicts) of a dump, or its arrays (npz only), selected by trial, pose and camera.

    Each selector is None (everything), one value or a collection; camera is "left", "right", 0 or 1,
    or (JSON dumps, which name them) the scene's camera, e.g. "cam_l". A file that is not a dump, or a
    trial, pose or camera the dump does not hold, raises DumpError naming what it does hold.
    """
    path = Path(path)
    try:
        regular_size(path, MAX_JSON_BYTES if path.suffix != ".npz" else 2**63)  # FIFOs and devices stay unopened
    except UnreadableFile as exc:
        raise DumpError(f"{path} {exc}") from None
    with open(path, "rb") as fh:
        head = fh.read(4)
    if head == b"PK\x03\x04":
        try:
            pick = _pick(path, _npz_held(path), trial, pose, camera, names=None)
            return _npz_arrays(path, *pick) if arrays else _npz_records(path, *pick)
        except (KeyError, IndexError, TypeError, ValueError, EOFError, zipfile.BadZipFile, NotImplementedError,
                RuntimeError) as exc:  # RuntimeError: an encrypted member
            if isinstance(exc, DumpError) or str(exc).startswith(f"{path}: "):  # ours, naming the file already
                raise
            raise layout.NpzError(f"{path}: not a features.npz of layout {layout.NPZ_VERSION} ({type(exc).__name__}:"
                                  f" {exc}); `wiredsl validate {path}` says what is wrong") from None
    if arrays:
        raise DumpError(f"{path}: arrays=True reads npz dumps; this is JSON")
    docs = _json_docs(path)
    held = ({d.get("trial") or 0 for d in docs}, {p["index"] for d in docs for p in d["poses"]})
    first = docs[0]["poses"][0] if docs and docs[0]["poses"] else {}
    names = [str((first.get(side) or {}).get("camera", {}).get("name", "")).split(":")[0] or None
             for side in layout.CAMERAS]  # the scene's camera of each side, e.g. "cam_l:left" -> "cam_l"
    pick = _pick(path, (*held, None), trial, pose, camera, names)
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
                # a kind list left out is empty, as the features model (and so `validate`) takes it
                out += [{"trial": t, "pose": p["index"], "camera": side, **f} for k in KIND_ORDER
                        for f in view.get(k, [])]
    return out


def _json_docs(path: Path) -> list[dict]:
    """The features documents of a JSON or JSON-lines dump, or DumpError saying what the file is instead."""
    try:
        data = read_regular(path, MAX_JSON_BYTES)
    except UnreadableFile as exc:
        raise DumpError(f"{path} {exc}") from None
    start = data.lstrip()[:200]
    if start.startswith((b"<svg", b"<?xml")):
        raise DumpError(f"{path} is an SVG image, not a dump; {_NOT_A_DUMP}")
    try:
        text = data.decode("utf-8")
        lines = [(n, line) for n, line in enumerate(text.splitlines(), 1) if line.strip()]
        docs = [json_loads(line) for _, line in lines] if path.suffix == ".jsonl" else [json_loads(text)]
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        if b"," in start.split(b"\n", 1)[0] and not start.startswith((b"{", b"[")):
            raise DumpError(f"{path} is a CSV table, not a dump; {_NOT_A_DUMP}") from None
        raise DumpError(f"{path} is not JSON ({exc}); {_NOT_A_DUMP}") from None
    for doc in docs:
        kind = doc.get("document") if isinstance(doc, dict) else None
        if kind != "features" or not isinstance(doc.get("poses"), list):
            # (a damaged "document" may be a list or an object: no key of the table)
            what = _DOCUMENTS.get(kind, "not a wiredsl features document") if isinstance(kind, str) else \
                "not a wiredsl features document"
            raise DumpError(f"{path}: this is {what}, not a dump; {_NOT_A_DUMP}")
    _check_features(path, lines if path.suffix == ".jsonl" else [(None, text)])
    return docs


def _check_features(path: Path, texts: list[tuple[int | None, str]]) -> None:
    """Each document against the features model (the schema's source), strictly: a value of the wrong type or
    shape (`"points": true`, a corner at three numbers) is a DumpError naming where, not a record passed on."""
    from pydantic import ValidationError

    from wiredsl.io.features import Features

    for line, text in texts:
        try:
            Features.model_validate_json(text, strict=True)
        except ValidationError as exc:
            err = exc.errors()[0]
            where = "the document" if line is None else f"line {line}"
            at = "/".join(map(str, err["loc"])) or "(root)"
            more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
            raise DumpError(f"{path}: {where} is not a features document wiredsl wrote: {at}: {err['msg']}{more}; "
                            f"`wiredsl validate {path}` says what is wrong") from None


def _npz_held(path: Path) -> tuple[set[int], set[int], None]:
    """The trials and poses an npz dump holds (from its views), or DumpError when it is not a dump."""
    import numpy as np

    try:
        with _open_npz(path) as data:
            batches = _batches(data)
            if "manifest" not in data.files or "feature_ids" not in data.files or not batches:
                raise DumpError(f"{path} is an npz file but not a wiredsl dump (no manifest, feature_ids or "
                                f"batches); {_NOT_A_DUMP}")
            views = np.concatenate([data[f"{b}_views"] for b in batches])
    except (OSError, ValueError, KeyError) as exc:
        if isinstance(exc, (DumpError, layout.NpzError)):
            raise
        raise DumpError(f"{path} is not a readable npz dump ({exc}); {_NOT_A_DUMP}") from None
    return set(views[:, 0].tolist()), set(views[:, 1].tolist()), None


def _open_npz(path: Path):
    """The npz, its members checked before any is read (layout.open_npz), or NpzError naming the file."""
    try:
        return layout.open_npz(path)
    except layout.NpzError as exc:
        raise layout.NpzError(f"{path}: {exc}") from None


def _pick(path: Path, held, trial, pose, camera, names: list[str] | None):
    """Selectors for trial, pose and camera index; DumpError for a value the dump does not hold."""
    trials, poses, _ = held
    out = []
    for what, value, have in (("trial", trial, trials), ("pose", pose, poses)):
        wanted = _values(what, value)
        missing = sorted(wanted - have) if wanted is not None else []
        if missing:
            raise DumpError(f"{path} holds no {what} {', '.join(map(str, missing))}: it holds {what}"
                            f"{'s' * (len(have) != 1)} {_ranges(sorted(have))}")
        out.append(_selector(wanted))
    out.append(_selector(_camera_index(path, camera, names)))
    return out


def _values(what: str, value) -> set[int] | None:
    if value is None:
        return None
    many = value if isinstance(value, (list, tuple, set, frozenset, range)) else [value]
    try:
        return {int(v) for v in many}
    except (TypeError, ValueError):
        raise DumpError(f"{what} must be an integer or a collection of integers, not {value!r}") from None


def _ranges(xs: list[int]) -> str:
    """1, 3-5, 8: a sorted list of integers, runs written as ranges."""
    if not xs:
        return "none"
    runs, start = [], xs[0]
    for a, b in zip(xs, [*xs[1:], None], strict=True):
        if b != a + 1:
            runs.append(f"{start}" if start == a else f"{start}-{a}")
            start = b
    return ", ".join(runs)


def _camera_index(path: Path, camera, names: list[str] | None) -> set[int] | None:
    if camera is None:
        return None
    many = camera if isinstance(camera, (list, tuple, set, frozenset)) else [camera]
    out = set()
    for c in many:
        if c in layout.CAMERAS:
            out.add(layout.CAMERAS.index(c))
        elif names and c in names:
            out.add(names.index(c))
        elif not isinstance(c, str) and c in (0, 1):
            out.add(int(c))
        else:
            named = [n for n in names or () if n]
            choices = "'left', 'right', 0 or 1" + (f", or the scene's {' and '.join(map(repr, named))}"
                                                   if named else "")
            extra = "" if names is not None else " (an npz dump knows its cameras by side only)"
            raise DumpError(f"{path}: no camera {c!r}: choose {choices}{extra}")
    return out


def _selector(wanted: set[int] | None):
    if wanted is None:
        return lambda x: True
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
    return _read_npz(_open_npz(path), path, selected_by, chosen)


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
    return records(_npz_arrays(path, *pick))


def records(a: dict) -> list[dict]:
    """The JSON dump's feature records from one run's arrays (the npz members of its batches, without the
    b{n}_ prefix, with `feature_ids`): what `load` gives, in its order."""
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
        if row[col["contour"]]:  # written only when true, as in the JSON dump
            rec["contour"] = True
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
