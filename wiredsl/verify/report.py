"""The verification's outputs: the table (CSV and JSON, one row per image, feature and detector) and the
paper's Figure 7 (verified fraction per object, with its spread over images) as a matplotlib plot."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

import numpy as np

from wiredsl.files import json_text, write_atomic

COLUMNS = ("image", "camera", "frame", "detector", "kind", "feature", "object", "segment", "part", "length_px",
           "samples", "verified", "verified_fraction", "runs", "offset_mean_px", "offset_std_px", "lost_middle_px",
           "lost_ends_px", "corner_found", "corner_error_px", "stereo_wrong")
UNITS = {"length_px": "px", "offset_mean_px": "px", "offset_std_px": "px", "lost_middle_px": "px",
         "lost_ends_px": "px",
         "corner_error_px": "px"}


def _clean(v):
    """A cell: None for NaN (never written as NaN), plain Python numbers."""
    if isinstance(v, (float, np.floating)):
        v = float(v)
        return None if not math.isfinite(v) else round(v, 6)
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    return v


def rows_of(r) -> list[tuple]:
    """The table's rows of one ImageResult."""
    out = []
    base = (r.image, r.side, r.frame, r.detector)
    if r.stats is not None:
        st, s = r.strokes, r.stats
        for k in range(st.n):
            src = r.sources[st.fid[k]]
            frac = s.verified[k] / s.tested[k] if s.tested[k] else float("nan")
            out.append(tuple(_clean(v) for v in (*base, "edge", src, src.split(".")[0], st.segment[k], st.part[k],
                                                 s.length[k], s.tested[k], s.verified[k], frac, s.runs[k],
                                                 s.offset_mean[k], s.offset_std[k], s.lost_middle[k], s.lost_ends[k],
                                                 None, None, None)))
    if r.corners is not None:
        c = r.corners
        wrong = {}
        if r.stereo is not None:
            wrong = {int(f): bool(w) for f, w in zip(r.stereo[0], r.stereo[1], strict=True)}
        for k in range(len(c.fid)):
            src = r.sources[c.fid[k]]
            out.append(tuple(_clean(v) for v in (*base, "corner", src, src.split(".")[0], -1, -1, None, None, None,
                                                 None, None, None, None, None, None, bool(c.found[k]), c.error[k],
                                                 wrong.get(int(c.fid[k])))))
    return out


def write_table(folder: Path, rows: list[tuple], meta: dict) -> list[str]:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    for row in rows:
        w.writerow(["" if v is None else v for v in row])
    write_atomic(folder / "verification.csv", buf.getvalue())
    doc = {**meta, "columns": list(COLUMNS), "units": UNITS, "rows": [dict(zip(COLUMNS, r, strict=True))
                                                                      for r in rows]}
    write_atomic(folder / "verification.json", json_text(doc, indent=1))
    return ["verification.csv", "verification.json"]


class ObjectFractions:
    """Per detector, object and image: samples tested and verified (what Figure 7 plots)."""

    def __init__(self):
        self.data: dict[tuple[str, str], dict[str, list[float]]] = {}

    def add(self, r) -> None:
        if r.stats is None:
            return
        objs = np.array([r.sources[f].split(".")[0] for f in r.strokes.fid])
        for o in np.unique(objs):
            m = objs == o
            t, v = r.stats.tested[m].sum(), r.stats.verified[m].sum()
            if t > 0:
                self.data.setdefault((r.detector, str(o)), {"t": [], "v": []})
                self.data[(r.detector, str(o))]["t"].append(float(t))
                self.data[(r.detector, str(o))]["v"].append(float(v))

    def summary(self) -> list[dict]:
        out = []
        for (det, obj), d in sorted(self.data.items()):
            f = np.array(d["v"]) / np.array(d["t"])
            out.append({"detector": det, "object": obj, "images": len(f),
                        "verified_fraction": float(np.sum(d["v"]) / np.sum(d["t"])),
                        "image_mean": float(f.mean()), "image_sd": float(f.std(ddof=1)) if len(f) > 1 else 0.0,
                        "image_min": float(f.min()), "image_max": float(f.max())})
        return out


def figure7(fr: ObjectFractions, path: Path, caption: str, fmt: str = "png", dpi: int = 110) -> None:
    """Bars: each object's verified fraction (samples pooled over images), per detector; whiskers: the images'
    spread (mean +- one standard deviation), dots: each image."""
    from wiredsl.study.plots import _pyplot, _save

    plt = _pyplot()
    summary = fr.summary()
    dets = sorted({s["detector"] for s in summary})
    objs = sorted({s["object"] for s in summary})
    import textwrap

    fig_w = max(6.4, 0.9 * len(objs) * max(1, len(dets)) + 2)
    fig, ax = plt.subplots(figsize=(fig_w, 4.4))
    width = min(0.8 / max(1, len(dets)), 0.45)
    for j, det in enumerate(dets):
        xs, ys, lo = [], [], []
        for i, obj in enumerate(objs):
            s = next((s for s in summary if s["detector"] == det and s["object"] == obj), None)
            if s is None:
                continue
            x = i + (j - (len(dets) - 1) / 2) * width
            xs.append(x)
            ys.append(100 * s["verified_fraction"])
            lo.append(100 * s["image_sd"])
            d = fr.data[(det, obj)]
            f = 100 * np.array(d["v"]) / np.array(d["t"])
            jitter = np.linspace(-width / 4, width / 4, len(f)) if len(f) > 1 else np.zeros(1)
            ax.plot(x + jitter, f, ".", color="0.25", ms=3, zorder=3)
        ax.bar(xs, ys, width * 0.9, yerr=lo, capsize=3, label=det, alpha=0.8)
    mean_all = [100 * s["verified_fraction"] for s in summary]
    if mean_all:
        ax.axhline(71, color="0.5", ls="--", lw=1, label="paper's Canny mean (71%)")
    ax.set_xticks(range(len(objs)))
    ax.set_xticklabels(objs, rotation=30 if len(objs) > 5 else 0, ha="right" if len(objs) > 5 else "center")
    ax.set_ylabel("verified edges (% of model edge length)")
    ax.set_xlabel("object")
    ax.set_ylim(0, 105)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title("Verified image edges versus edges re-projected from the model\n"
                 "bars: samples pooled over images; whiskers: +-1 sd over images; dots: single images", fontsize=9)
    ax.set_xlim(-0.75, len(objs) - 0.25)
    wrapped = textwrap.fill(caption, width=int(fig_w * 17))
    fig.text(0.01, 0.01, wrapped, fontsize=7, color="0.3", va="bottom")
    fig.tight_layout(rect=(0, 0.04 + 0.03 * wrapped.count("\n"), 1, 1))
    _save(fig, path, fmt, dpi)
    plt.close(fig)
