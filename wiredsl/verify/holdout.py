"""Held-out prediction, image by image (`wiredsl verify --holdout`, issue 34 item 3).

The frames (a stereo pair, or one image) are split into folds: `odd` / `even` (a named split: fit on the
even-numbered frames in name order and predict the odd ones, or the other way), or `kfold:K` (frame i in fold
i mod K; each fold predicted by a pipeline fitted on the others). A fold's pipeline is fitted from the other
frames' verification sums alone (`fit.fit`, spreads and correlations included) and simulates each held-out frame
at its own pose `trials` times. For each held-out image and statistic, the real value's place among its own
trials is reported: its percentile (the share of trials below it, ties counted half), and whether it lies in the
trials' central 90% band (their 5th to 95th percentile). If the simulation predicts the detector image by image,
the percentiles are uniform and 90% of the images lie in their bands: the calibration summary gives, per
statistic, the share that do.

The statistics, the same way from the real detector and from a trial:
- per image: the verified fraction (overall, and per object when the scene has several), the RMS lateral offset
  of the verified samples (px), the fragments (verified runs per tested stroke), the corner keep (model corners
  with a detected corner within the radius) and the RMS corner error of those within the inlier distance (px);
- per stereo pair: the triangulated corners' 3D error and the 3D shape error after a rigid fit (mm,
  `predict.corner_errors_3d`).
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path

import numpy as np

from wiredsl.verify import verification as ver

BAND = (5.0, 95.0)  # the central 90% band, percentiles of a frame's trials
STATS = {"verified_fraction": ("verified fraction", ""), "offset_rms_px": ("RMS lateral offset", "px"),
         "fragments": ("verified runs a stroke", ""), "corner_keep": ("corner keep", ""),
         "corner_rms_px": ("RMS corner error", "px"), "corner_error_3d": ("triangulated corner error", "mm"),
         "corner_shape_3d": ("3D shape error", "mm")}
PAIR = ("corner_error_3d", "corner_shape_3d")


def parse_split(text: str, frames: int) -> list[list[int]]:
    """The held-out folds (frame indices) of a split's name; ValueError (a usage error) for a bad one."""
    m = re.fullmatch(r"kfold:(\d+)", text or "")
    if text in ("odd", "even"):
        folds = [[i for i in range(frames) if i % 2 == (1 if text == "odd" else 0)]]
    elif m:
        k = int(m.group(1))
        if not 2 <= k <= frames:
            raise ValueError(f"--holdout kfold:{k}: K must be from 2 to the number of frames ({frames})")
        folds = [list(range(j, frames, k)) for j in range(k)]
    else:
        raise ValueError(f"--holdout {text!r}: one of odd, even, kfold:K")
    if any(len(f) == 0 or len(f) == frames for f in folds):
        raise ValueError(f"--holdout {text}: {frames} frames leave a fold with nothing to fit or to predict")
    return folds


def side_values(stats: ver.StrokeStats | None, strokes: ver.Strokes | None, corners: ver.CornerMatch | None,
                cfg: ver.Settings, objects: list[str] | None = None) -> dict[str, float | None]:
    """One image's statistics (see the module's list) from its verification (real or simulated)."""
    from wiredsl.verify.predict import edge_values

    out = dict(edge_values(stats))
    out["fragments"] = None
    if stats is not None and (stats.tested > 0).any():
        tested = stats.tested > 0
        out["fragments"] = float(stats.runs[tested].sum() / tested.sum())
        if objects is not None and strokes is not None and len(set(objects)) > 1:
            names = np.array([objects[f] for f in strokes.fid])
            for o in sorted(set(objects)):
                m = names == o
                t = stats.tested[m].sum()
                out[f"verified_fraction:{o}"] = float(stats.verified[m].sum() / t) if t > 0 else None
    out["corner_keep"] = out["corner_rms_px"] = None
    if corners is not None and len(corners.fid):
        out["corner_keep"] = float(corners.found.mean())
        near = corners.found & (corners.error <= cfg.inlier)
        out["corner_rms_px"] = float(np.sqrt(np.mean(corners.error[near] ** 2))) if near.any() else None
    return out


def observe(frame, views, per_side, edge_det, corner_det, cfg, objects):
    """A verified frame's real statistics, a predict.Observed (command.run's per_side: side -> (grey, found,
    results, shape))."""
    from wiredsl.verify import predict

    o = predict.Observed(frame.label, tuple(frame.pose))
    for side, (_, _, results, shape) in per_side.items():
        o.shape[side] = shape
        e = next((r for r in results if r.detector == edge_det), None)
        c = next((r for r in results if r.detector == corner_det), None)
        o.values[side] = side_values(e.stats if e else None, e.strokes if e else None, c.corners if c else None,
                                     cfg, objects)
    if corner_det is not None and len(per_side) == 2:
        found = {s: per_side[s][1][corner_det].corners for s in ("left", "right")}
        o.pair = predict.corner_errors_3d(views["left"], views["right"], found["left"], found["right"], cfg.radius)
    return o


def simulate(scene, world, pipeline, frames: list, cfg: ver.Settings, trials: int, seed: int, objects,
             corners: bool, background: float = 0.0) -> list[dict]:
    """Per frame and trial the simulated statistics, [{frame, trial, side -> {statistic}, PAIR -> value}], with the
    fit's `background` share of the verified runs given the background term, as `--predict` draws it."""
    from wiredsl.verify import predict

    ellipses = set(world.ell_fid.tolist())

    def values(model, sim, shape, where=()):
        rng = predict.background_rng(seed, where) if background > 0 else None
        st, stats = predict.simulated_stats(model, sim, shape, cfg, background, rng, ellipses)
        cm = ver.match_corners(*ver.corners_of(model), ver.corners_of(sim)[1], cfg.radius) if corners else None
        return side_values(stats, st, cm, cfg, objects)

    return predict.simulate(scene, world, pipeline, frames, cfg, trials, seed, side_values=values,
                            background=background)


def place(real: float, sims: list[float]) -> dict:
    """The real value among its trials: percentile (ties half), the central band, and whether it lies in it."""
    s = np.asarray(sims, float)
    lo, hi = np.percentile(s, BAND)
    pct = float((np.sum(s < real) + 0.5 * np.sum(s == real)) / len(s))
    return {"real": float(real), "percentile": pct, "band": [float(lo), float(hi)],
            "median": float(np.median(s)), "inside": bool(lo <= real <= hi)}


def compare(frames: list, simulated: list[dict], fold: int) -> list[dict]:
    """Each held-out image's (and pair's) place among its trials, per statistic."""
    rows = []
    for o in frames:
        mine = [row for row in simulated if row["frame"] == o.frame]
        for side in [*o.values, "pair"]:
            real = o.pair if side == "pair" else o.values[side]
            for key, r in real.items():
                if r is None:
                    continue
                s = [row.get(key) if side == "pair" else row[side].get(key) for row in mine]
                s = [v for v in s if v is not None]
                if len(s) >= 5:
                    rows.append({"frame": o.frame, "side": side, "statistic": key, "fold": fold, "trials": len(s),
                                 **place(r, s)})
    return rows


def summary(rows: list[dict]) -> dict:
    """Per statistic: held-out images, the share inside their central 90% band, and the mean percentile."""
    out = {}
    for key in dict.fromkeys(r["statistic"] for r in rows):
        mine = [r for r in rows if r["statistic"] == key]
        p = np.array([r["percentile"] for r in mine])
        out[key] = {"images": len(mine), "inside": int(sum(r["inside"] for r in mine)),
                    "inside_fraction": float(np.mean([r["inside"] for r in mine])),
                    "below_band": int(sum(r["real"] < r["band"][0] for r in mine)),
                    "above_band": int(sum(r["real"] > r["band"][1] for r in mine)),
                    "mean_percentile": float(p.mean())}
    return out


def pipeline_of(scene_path: str, text: str, name: str, folder: Path):
    """The Pipeline a fitted pipeline's text declares, compiled with the scene (its includes resolved)."""
    from wiredsl.files import write_atomic
    from wiredsl.language.compile import compile_file

    fd, fitted = tempfile.mkstemp(suffix=".wd", dir=folder)
    os.close(fd)
    fd, both = tempfile.mkstemp(suffix=".wd", dir=folder)
    os.close(fd)
    try:
        write_atomic(Path(fitted), text)
        write_atomic(Path(both), f'wiredsl 1\ninclude "{Path(scene_path).resolve()}"\n'
                                 f'include "{Path(fitted).resolve()}"\n')
        return compile_file(both)[0].pipeline(name)
    finally:
        os.unlink(fitted)
        os.unlink(both)


def plot(rows: list[dict], summ: dict, path, caption: str, fmt: str = "png") -> None:
    """Per statistic: each held-out image's simulated central 90% band (bar) and median, and its real value
    (a dot: blue inside, red outside), with the share inside in the title."""
    from wiredsl.study.plots import _pyplot, _save

    plt = _pyplot()
    keys = list(summ)
    if not keys:
        fig = plt.figure(figsize=(6, 2))
        fig.text(0.5, 0.5, "nothing held out to compare", ha="center", fontsize=9)
        _save(fig, path, fmt, 110)
        plt.close(fig)
        return
    fig, axes = plt.subplots(len(keys), 1, figsize=(10, 2.4 * len(keys)), squeeze=False)
    for ax, key in zip(axes[:, 0], keys, strict=True):
        mine = [r for r in rows if r["statistic"] == key]
        xs = np.arange(len(mine))
        ax.vlines(xs, [r["band"][0] for r in mine], [r["band"][1] for r in mine], color="tab:orange", lw=5,
                  alpha=0.5, label="simulated 5-95%")
        ax.plot(xs, [r["median"] for r in mine], "_", color="tab:orange", ms=10, mew=2)
        inside = np.array([r["inside"] for r in mine])
        real = np.array([r["real"] for r in mine])
        ax.plot(xs[inside], real[inside], "o", color="tab:blue", ms=4, label="real, inside")
        ax.plot(xs[~inside], real[~inside], "o", color="tab:red", ms=4, label="real, outside")
        ax.set_xticks(xs)
        ax.set_xticklabels([f"{r['frame']}{'' if r['side'] == 'pair' else r['side'][0]}" for r in mine],
                           rotation=90, fontsize=6)
        base = key.split(":")[0]
        label, unit = STATS.get(base, (base, ""))
        ax.set_ylabel((label + (f" {key.split(':')[1]}" if ":" in key else "")) + (f" ({unit})" if unit else ""),
                      fontsize=8)
        s = summ[key]
        ax.set_title(f"{key}: {s['inside']} of {s['images']} held-out images inside their band "
                     f"({100 * s['inside_fraction']:.0f}%; 90% expected), mean percentile {s['mean_percentile']:.2f}",
                     fontsize=8)
        ax.legend(fontsize=6, loc="best")
    fig.suptitle("Held out, image by image: each real value against its own simulated 5-95% band", fontsize=10)
    fig.text(0.5, 0.003, caption, ha="center", fontsize=7, wrap=True)
    fig.tight_layout(rect=(0, 0.02, 1, 0.98))
    _save(fig, path, fmt, 110)
    plt.close(fig)


def run(req, staging: Path, scene, world, observed: list, sums: list, sums_frame: list[int], cfg: ver.Settings,
        calibration: str | None, corners: bool, objects: list[str], extras: list | None = None
        ) -> tuple[dict, list[str]]:
    """--holdout: each fold fitted on the other frames' sums (and, with `extras`, their spreads between images,
    variation_fit) and predicted; holdout.json and the plot in `staging`. Returns the document and the names
    written."""
    from wiredsl.files import json_text, write_atomic
    from wiredsl.verify import fit as fitting
    from wiredsl.verify import variation_fit
    from wiredsl.verify.measured import pipeline_text

    folds = parse_split(req.holdout, len(observed))
    rows, fits = [], []
    for k, held in enumerate(folds):
        held_set = set(held)
        train = [s for s, f in zip(sums, sums_frame, strict=True) if f not in held_set]
        result = fitting.fit(train, req.seed, cfg.inlier, cfg.radius, req.edge_loss)
        if extras is not None:
            keep = [i for i, f in enumerate(sums_frame) if f not in held_set]
            variation_fit.add(result, [extras[i] for i in keep], [sums_frame[i] for i in keep],
                              [o.pose for o in observed], req.seed, req.edge_loss)
        text = pipeline_text(result, req.pipeline_name, [f"Fold {k + 1} of {len(folds)} of --holdout "
                                                         f"{req.holdout}: fitted on {len(train)} images."],
                             calibration, req.calibration_error)
        pipeline = pipeline_of(req.scene, text, req.pipeline_name, staging)
        frames = [observed[i] for i in held]
        sim = simulate(scene, world, pipeline, frames, cfg, req.trials, req.seed + k, objects, corners,
                       result.background)
        rows += compare(frames, sim, k)
        fits.append({"fold": k, "held_out": [observed[i].frame for i in held], "images_fitted": len(train),
                     "pipeline": [s.model_dump() for s in pipeline.stages]})
    summ = summary(rows)
    doc = {"split": req.holdout, "folds": fits, "trials": req.trials, "seed": req.seed,
           "band_percentiles": list(BAND), "summary": summ, "images": rows}
    write_atomic(staging / "holdout.json", json_text(doc, indent=1))
    name = f"holdout.{req.plot_format}"
    plot(rows, summ, staging / name, f"{Path(req.scene).name}; --holdout {req.holdout} ({len(folds)} folds); "
                                     f"{req.trials} trials a frame, seed {req.seed}", req.plot_format)
    return doc, ["holdout.json", name]

