"""Does the simulation predict the detector? (`wiredsl verify --fit --predict`, issue 24 item 7.)

The imaged scene is simulated at every frame's pose with a pipeline (the fitted one), `trials` times with a
fixed seed, and four downstream measures are computed image by image, the same way from the real detector's
features and from the simulated ones:

- **verified fraction**: the ideal projection's strokes are sampled as the verification samples them
  (`verification.sample_strokes`, the same step and border), and a sample is verified when its normal meets
  a simulated stroke within the band at an angle within the tolerance, found exactly (`search_simulated`),
  so that a stroke the pipeline dropped, or shifted beyond the band, is unverified as a missing edge is.
  Exactly, not by rasterising the simulated strokes into an edge map: a rasterised stroke reaches half a
  pixel or more past its ends, which on the fence scene verified 2% more than the pipeline kept. (Rendering
  the simulated features and running the detector on them would measure the renderer and the detector
  again, not the pipeline.)
- **RMS lateral offset** of the verified samples (px): what the shift and approximation stages predict.
- **3D corner error** of the stereo pairs (mm, the scene's unit): each camera's model corners matched to the
  nearest detected (or simulated) corner within the radius, undistorted, triangulated (DLT) with the rig at
  the frame's pose and compared with the model's corner; the RMS (mm) over the corners found in both images.
- **3D shape error** of the same triangulated corners (mm): the RMS left after the rigid motion that best
  fits them to the model's corners (Kabsch, `scipy.spatial.transform.Rotation.align_vectors`). The real
  frames' poses are estimated (`--poses board` fits them to the left image's corners), and an estimated pose
  takes up part of the corners' error in the real images and none in the simulated ones, where the pose is
  the truth; this measure does not depend on the pose, so it compares the two alike.

Each measure's real values (one an image, or a pair) and simulated values (one an image and trial) are
compared with the two-sample Kolmogorov-Smirnov and Mann-Whitney tests (scipy.stats), and per image by where
the real value falls among its trials (its rank; uniform if the simulation is right).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from wiredsl.verify import verification as ver

TRIALS = 50
MEASURES = {"verified_fraction": ("verified fraction", ""), "offset_rms_px": ("RMS lateral offset", "px"),
            "corner_error_3d": ("triangulated corner error, RMS", "mm"),
            "corner_shape_3d": ("3D shape error after a rigid fit", "mm")}
PAIR = ("corner_error_3d", "corner_shape_3d")  # one value a stereo pair, not an image


@dataclass
class Observed:
    """One frame's real values: per side, the verified fraction and RMS offset; per stereo pair, the 3D ones."""

    frame: str
    pose: tuple
    shape: dict[str, tuple[int, int]] = field(default_factory=dict)
    values: dict[str, dict[str, float | None]] = field(default_factory=dict)  # side -> measure -> value
    pair: dict[str, float | None] = field(default_factory=dict)  # PAIR measure -> value


def edge_values(stats: ver.StrokeStats | None) -> dict[str, float | None]:
    """Verified fraction and RMS signed offset (px) of one image's verified samples."""
    if stats is None or stats.tested.sum() == 0:
        return {"verified_fraction": None, "offset_rms_px": None}
    n = stats.verified.astype(float)
    ok = n > 0
    sq = np.nansum(n[ok] * (np.nan_to_num(stats.offset_std[ok]) ** 2 + np.nan_to_num(stats.offset_mean[ok]) ** 2))
    return {"verified_fraction": float(n.sum() / stats.tested.sum()),
            "offset_rms_px": float(np.sqrt(sq / n.sum())) if n.sum() > 0 else None}


def corner_errors_3d(left, right, det_left: np.ndarray, det_right: np.ndarray, radius: float
                     ) -> dict[str, float | None]:
    """The PAIR measures (mm) of the model corners whose nearest detected corner within `radius` is found in both
    views (left, right: the ideal engine views; det_*: (m, 2) detected corner pixels), triangulated by DLT:
    the RMS 3D error, and the RMS left after the best rigid fit to the model's corners (None with fewer than 3
    corners, or all on a line)."""
    none = dict.fromkeys(PAIR)
    from wiredsl.measures.stereo3d import triangulate, undistort

    fl, uvl = ver.corners_of(left)
    fr, uvr = ver.corners_of(right)
    ml = ver.match_corners(fl, uvl, det_left, radius)
    mr = ver.match_corners(fr, uvr, det_right, radius)
    common, il, ir = np.intersect1d(fl[ml.found], fr[mr.found], return_indices=True)
    if len(common) == 0 or left.corner_world is None:
        return none
    xl, okl = undistort(det_left[ml.nearest[ml.found][il]], left.camera)
    xr, okr = undistort(det_right[mr.nearest[mr.found][ir]], right.camera)
    P = [np.hstack([np.asarray(v.R_cw, float), np.asarray(v.t_cw, float).reshape(3, 1)]) for v in (left, right)]
    X, ok = triangulate(P[0], P[1], xl, xr)
    truth = dict(zip(np.asarray(left.corner_fid).tolist(), np.asarray(left.corner_world, float), strict=True))
    keep = ok & okl & okr & np.array([int(f) in truth for f in common], bool)
    if not keep.any():
        return none
    T = np.array([truth[int(f)] for f in common[keep]])
    return {"corner_error_3d": _rms_mm(X[keep] - T), "corner_shape_3d": shape_error_mm(X[keep], T)}


def _rms_mm(d: np.ndarray) -> float:
    return 1000.0 * float(np.sqrt(np.mean(np.sum(d**2, axis=1))))  # m (the engine's) to mm


def shape_error_mm(X: np.ndarray, T: np.ndarray) -> float | None:
    """RMS (mm) of X (n, 3; m) after the rotation and translation that best fit it to T; None when T has fewer
    than 3 points or lies on a line (the fit is not unique)."""
    from scipy.spatial.transform import Rotation

    if len(T) < 3:
        return None
    x, t = X - X.mean(axis=0), T - T.mean(axis=0)
    sv = np.linalg.svd(t, compute_uv=False)
    if sv[1] <= 1e-9 * max(sv[0], 1e-300):
        return None
    rot, _ = Rotation.align_vectors(t, x)  # rot @ x_i ~ t_i, least squares
    return _rms_mm(rot.apply(x) - t)


def search_simulated(sm: ver.Samples, segs: np.ndarray, shape: tuple[int, int], cfg: ver.Settings
                     ) -> ver.EdgeMatch:
    """The verification's edge search against simulated strokes (n, 4), exactly: for each sample, the nearest
    segment its normal line crosses within the band, whose own normal lies within the angle tolerance."""
    from wiredsl.verify.detectors import angle_ok

    h, w = shape
    P, N = sm.P, sm.N
    b = ver.BORDER
    tested = (P[:, 0] >= b) & (P[:, 0] <= w - 1 - b) & (P[:, 1] >= b) & (P[:, 1] <= h - 1 - b)
    n = len(P)
    offset = np.full(n, np.nan)
    if n == 0 or len(segs) == 0:
        return ver.EdgeMatch(tested, np.zeros(n, bool), offset)
    A, D = segs[:, :2], segs[:, 2:] - segs[:, :2]  # (m, 2)
    # P + s N = A + u D: solve for (s, u) per sample and segment (Cramer)
    den = N[:, None, 0] * (-D[None, :, 1]) - N[:, None, 1] * (-D[None, :, 0])
    R = A[None, :, :] - P[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        sv = (R[..., 0] * (-D[None, :, 1]) - R[..., 1] * (-D[None, :, 0])) / den
        uv = (N[:, None, 0] * R[..., 1] - N[:, None, 1] * R[..., 0]) / den
    agree = angle_ok(-D[None, :, 1], D[None, :, 0], N[:, None, 0], N[:, None, 1], cfg.angle)
    ok = (np.abs(den) > 1e-12) & (uv >= 0) & (uv <= 1) & (np.abs(sv) <= cfg.band) & agree & tested[:, None]
    dist = np.where(ok, np.abs(sv), np.inf)
    best = np.argmin(dist, axis=1)
    verified = np.isfinite(dist[np.arange(n), best])
    offset[verified] = sv[np.flatnonzero(verified), best[verified]]
    return ver.EdgeMatch(tested, verified, offset)


def simulated_stats(model_view, sim_view, shape, cfg: ver.Settings, background: float = 0.0,
                    rng: np.random.Generator | None = None, ellipses: set | None = None
                    ) -> tuple[ver.Strokes, ver.StrokeStats]:
    """The model's strokes and the verification's statistics of them against a simulated view's strokes, as a
    real image's are taken (`verification.verify_image`: `ellipses`, the world's ellipse feature ids, have their
    runs cut at their major axes); with `background` (and `rng`), that share of the verified runs given the
    background term (`with_background`)."""
    st = ver.strokes_of(model_view, ellipses)
    sm = ver.sample_strokes(st, cfg.step)
    m = search_simulated(sm, segments_of(sim_view), shape, cfg)
    if background > 0 and rng is not None:
        m = with_background(sm, m, background, cfg.band, rng)
    return st, ver.stroke_stats(sm, m, st.n, cfg.margin, ver.ellipse_halves(st, sm, m))


def background_rng(seed: int, where) -> np.random.Generator:
    """The background term's draws of one simulated image: keyed by the seed and `where` (frame, trial, right)."""
    import zlib

    return np.random.default_rng([seed, zlib.crc32(b"background"), *where])


def with_background(sm: ver.Samples, m: ver.EdgeMatch, share: float, band: float, rng: np.random.Generator
                    ) -> ver.EdgeMatch:
    """The fit's background term of the lateral shift (fit.shift_mixture) simulated: each verified run (consecutive
    verified samples of a stroke) is, with probability `share`, a fragment of an edge the model does not name,
    found instead of the model's: its offsets one value uniform over the search band, +-(band + 0.5) px, as the
    mixture models it. One uniform a run and one for its offset, drawn in run order from `rng`."""
    v = m.verified & m.tested
    if not v.any():
        return m
    same = np.concatenate([[False], sm.stroke[1:] == sm.stroke[:-1]])
    start = v & ~(np.concatenate([[False], v[:-1]]) & same)
    run = np.cumsum(start) - 1
    R = int(start.sum())
    u = rng.random((R, 2))
    bg = u[:, 0] < share
    value = (2 * u[:, 1] - 1) * (band + 0.5)
    hit = v & bg[np.clip(run, 0, R - 1)]
    offset = m.offset.copy()
    offset[hit] = value[run[hit]]
    return ver.EdgeMatch(m.tested, m.verified, offset)


def segments_of(view) -> np.ndarray:
    """(n, 4) segments (x0, y0, x1, y1) of a simulated view's strokes."""
    segs = [np.hstack([f.points[:-1], f.points[1:]]) for f in view.features
            if f.kind in ("line", "polyline") and len(f.points) >= 2]
    return np.concatenate(segs).astype(float) if segs else np.zeros((0, 4))


def simulate(scene, world, pipeline, observed: list[Observed], cfg: ver.Settings, trials: int, seed: int,
             side_values=None, background: float = 0.0) -> list[dict]:
    """Per frame and trial, the simulated measures: [{frame, trial, side -> {measure}, PAIR measure -> value}].
    `side_values(model_view, simulated_view, shape) -> dict` gives an image's measures (default: `edge_values`
    of `simulated_stats`, with the fit's `background` share of the runs given the background term, each image's
    draws keyed by the seed, frame, trial and side; holdout.py's adds fragments and corners)."""
    if side_values is None:
        ellipses = set(world.ell_fid.tolist())

        def side_values(model, sim, shape, where=()):
            rng = background_rng(seed, where) if background > 0 else None
            return edge_values(simulated_stats(model, sim, shape, cfg, background, rng, ellipses)[1])
    from wiredsl import run as runs
    from wiredsl.engine.geometry import floor_pose
    from wiredsl.engine.simulate import Options
    from wiredsl.io import emit
    from wiredsl.scene import Path

    poses = [o.pose for o in observed]
    six = any(len(p) != 3 for p in poses)
    path = Path(name="frames", poses=[floor_pose(p) for p in poses],
                transforms=[np.reshape(p, (3, 4)).tolist() for p in poses] if six else None)
    if six and any(len(p) == 3 for p in poses):
        raise ValueError("mixed floor and 6-DoF poses")
    sim_scene = scene.model_copy(update={"path": path})
    run = runs.start(sim_scene, pipeline, seed=seed, options=Options(visibility="exact"), world=world,
                     engine="numpy")
    ideal = {r.index: r for r in run.ideal()}
    out = []
    for batch, batch_out in run.batches(range(trials)):
        for k, trial in enumerate(batch):
            for r in (emit.disturbed_results(batch_out, k) if run.stages else run.ideal()):
                o = observed[r.index]
                row = {"frame": o.frame, "trial": int(trial)}
                views = {"left": r.left, "right": r.right}
                for side in o.values:
                    where = (r.index, int(trial), side == "right")
                    row[side] = side_values(getattr(ideal[r.index], side), views[side], o.shape[side],
                                            **({"where": where} if background > 0 else {}))
                if o.pair or len(o.values) == 2:
                    row.update(corner_errors_3d(ideal[r.index].left, ideal[r.index].right,
                                                ver.corners_of(r.left)[1], ver.corners_of(r.right)[1], cfg.radius))
                out.append(row)
    return out


def compare(observed: list[Observed], simulated: list[dict]) -> dict:
    """Each measure: real and simulated values side by side, the two-sample tests, and per image the real
    value's rank among its trials."""
    from scipy import stats

    result = {}
    for key in MEASURES:
        real, sim, ranks = [], [], []
        for o in observed:
            sides = ["pair"] if key in PAIR else list(o.values)
            for side in sides:
                r = o.pair.get(key) if side == "pair" else o.values[side][key]
                s = [row.get(key) if side == "pair" else row[side][key]
                     for row in simulated if row["frame"] == o.frame]
                s = [v for v in s if v is not None]
                if r is None or not s:
                    continue
                real.append({"frame": o.frame, "side": side, "value": r})
                sim.extend(s)
                ranks.append((np.sum(np.array(s) < r) + 0.5 * np.sum(np.array(s) == r)) / len(s))
        entry = {"label": MEASURES[key][0], "unit": MEASURES[key][1], "real": real, "simulated": sim,
                 "real_mean": None, "simulated_mean": None, "ks": None, "mann_whitney": None,
                 "rank_mean": None}
        if real and sim:
            rv = np.array([r["value"] for r in real])
            sv = np.array(sim)
            entry.update(real_mean=float(rv.mean()), simulated_mean=float(sv.mean()),
                         real_median=float(np.median(rv)), simulated_median=float(np.median(sv)),
                         rank_mean=float(np.mean(ranks)), ranks=[float(x) for x in ranks])
            if np.ptp(np.concatenate([rv, sv])) > 0:
                ks = stats.ks_2samp(rv, sv)
                mw = stats.mannwhitneyu(rv, sv, alternative="two-sided")
                entry["ks"] = {"statistic": float(ks.statistic), "p": float(ks.pvalue)}
                entry["mann_whitney"] = {"statistic": float(mw.statistic), "p": float(mw.pvalue)}
            else:  # identical constants: nothing to tell apart
                entry["ks"] = {"statistic": 0.0, "p": 1.0}
                entry["mann_whitney"] = {"statistic": float(len(rv) * len(sv) / 2), "p": 1.0}
        result[key] = entry
    return result


def plot(comparison: dict, path, caption: str, fmt: str = "png") -> None:
    """Per measure: real values per image (dots) against the simulated spread per image (5-95% bars, median),
    and the two distributions' empirical CDFs with the KS p-value."""
    from wiredsl.study.plots import _pyplot, _save

    plt = _pyplot()
    from matplotlib.ticker import MaxNLocator

    keys = [k for k, e in comparison.items() if e["real"] and e["ks"] is not None]
    if not keys:  # no edge detector and no stereo pair with a corner detector: nothing to compare
        fig = plt.figure(figsize=(6, 2))
        fig.text(0.5, 0.5, "nothing to compare: no edge detector, and no stereo pair with a corner detector",
                 ha="center", fontsize=9)
        _save(fig, path, fmt, 110)
        plt.close(fig)
        return
    fig, axes = plt.subplots(len(keys), 2, figsize=(11, 3.2 * len(keys)), squeeze=False,
                             gridspec_kw={"width_ratios": [2, 1]})
    for row, key in zip(axes, keys, strict=True):
        e = comparison[key]
        unit = f" ({e['unit']})" if e["unit"] else ""
        ax = row[0]
        sims = e.get("_per_image", [])
        xs = np.arange(len(e["real"]))
        if sims:
            lo = [np.percentile(s, 5) if s else np.nan for s in sims]
            hi = [np.percentile(s, 95) if s else np.nan for s in sims]
            med = [np.median(s) if s else np.nan for s in sims]
            ax.vlines(xs, lo, hi, color="tab:orange", lw=4, alpha=0.5, label="simulated 5-95%")
            ax.plot(xs, med, "_", color="tab:orange", ms=12, mew=2, label="simulated median")
        ax.plot(xs, [r["value"] for r in e["real"]], "o", color="tab:blue", ms=5, label="real detector")
        ax.set_xticks(xs)
        ax.set_xticklabels([f"{r['frame']}{r['side'][0] if r['side'] != 'pair' else ''}" for r in e["real"]],
                           rotation=90, fontsize=7)
        ax.set_ylabel(e["label"] + unit)
        ax.set_xlabel("image (frame, l/r camera)" if key not in PAIR else "stereo pair (frame)")
        ax.legend(fontsize=7, loc="best")
        ax = row[1]
        for vals, colour, name in ((np.array([r["value"] for r in e["real"]]), "tab:blue", "real"),
                                   (np.array(e["simulated"]), "tab:orange", "simulated")):
            v = np.sort(vals)
            ax.step(v, np.arange(1, len(v) + 1) / len(v), where="post", color=colour, label=f"{name} (n={len(v)})")
        ks, mw = e["ks"], e["mann_whitney"]
        ax.set_title(f"KS D={ks['statistic']:.2f} p={ks['p']:.2g}; Mann-Whitney p={mw['p']:.2g}", fontsize=8)
        ax.set_xlabel(e["label"] + unit)
        ax.xaxis.set_major_locator(MaxNLocator(nbins=4))  # a narrow range's many long ticks ran together
        ax.set_ylabel("cumulative fraction")
        ax.legend(fontsize=7, loc="lower right")
    fig.suptitle("Does the simulation predict the detector? Real against simulated, image by image", fontsize=10)
    fig.text(0.5, 0.005, caption, ha="center", fontsize=7, wrap=True)
    fig.tight_layout(rect=(0, 0.03, 1, 0.97))
    _save(fig, path, fmt, 110)
    plt.close(fig)


def per_image(comparison: dict, observed: list[Observed], simulated: list[dict]) -> None:
    """Attach each real value's simulated values (for the plot), in the order of `real`."""
    for key, e in comparison.items():
        lists = []
        for r in e["real"]:
            vals = [row.get(key) if r["side"] == "pair" else row[r["side"]][key]
                    for row in simulated if row["frame"] == r["frame"]]
            lists.append([v for v in vals if v is not None])
        e["_per_image"] = lists
