"""Spreads between images and correlation along their sequence, estimated by `verify --fit` (issue 34 item 2).

Each image i gives its own estimate x_i of a magnitude, with a measurement variance v_i from within the image;
if the magnitude varies between views with variance tau^2 (the effect's `spread` squared), the x_i scatter
with variance tau^2 + v_i, so

    tau^2 = var(x_i) - mean(v_i)

(a method-of-moments variance component: unbiased, and as often below 0 as above when nothing varies), and
spread = sqrt(max(tau^2, 0)). Its 95% interval is the bootstrap over images of tau^2 (fit._interval: the same
resamples and widening as every other estimate), square-rooted with its negative part at 0; an estimate below 0
moves the interval up by as much (it starts at 0 and keeps its width: never the zero-width [0, 0] of a clipped
one). Per magnitude:

- edge_loss: x_i the image's gap fraction (fit's edge-loss estimate on its sums alone, the end loss pooled),
  v_i from the scatter of its strokes' own (the ratio estimator's variance over strokes);
- lateral_shift: x_i = sqrt(3 m_i), m_i the mean square of the image's fragment offsets about the pooled mean
  less their measurement noise; v_i by the delta method from the scatter of the squared offsets;
- corner_loss: x_i the image's found fraction, v_i = x_i (1 - x_i) / (n_i - 1) (unbiased binomial).

Correlation along the sequence (images of one camera with consecutive frame numbers): the lag-1 covariance of
the x_i (frames k and k + 1; measurement errors are independent between images, so only the magnitude's own
correlation is left) over tau^2 is the correlation rho between neighbouring poses, and the effect's
`correlation` length is -d / ln(rho), d the mean distance between neighbouring frames' poses (metres). Its
interval is the bootstrap over the neighbouring pairs. Written into the fitted pipeline only where the
spread's interval excludes 0 (else the spread's interval is a comment).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

MIN_IMAGES = 6  # images with an estimate for a spread
MIN_PAIRS = 5  # neighbouring pairs for a correlation
MIN_FRAGMENTS = 8  # fragments an image needs for its lateral-shift range
KIND = {"edge_loss": "fraction", "lateral_shift": "image", "corner_loss": "fraction"}
VALUE = {"edge_loss": "fraction", "lateral_shift": "range", "corner_loss": "keep"}


@dataclass
class ImageExtras:
    """Per image, what the spreads need beyond fit.ImageSums: its side and per-stroke lost lengths."""

    side: str = ""
    lost_middle: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per tested stroke, px
    gap_ends: np.ndarray = field(default_factory=lambda: np.zeros(0))
    length: np.ndarray = field(default_factory=lambda: np.zeros(0))
    lost_ends: float = 0.0
    ends: float = 0.0
    tested: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per tested stroke: samples
    verified: np.ndarray = field(default_factory=lambda: np.zeros(0))
    offsets: np.ndarray = field(default_factory=lambda: np.zeros(0))  # fragments' mean offsets, px
    noise: float = 0.0  # their summed measurement variances
    corners: float = 0.0
    found: float = 0.0


def extras_of(results, side: str, edge_det: str | None, corner_det: str | None, min_samples: int) -> ImageExtras:
    """One image's extras from its results by detector (the first edge and corner detector, as fit's sums)."""
    x = ImageExtras(side=side)
    for r in results:
        if r.detector == edge_det and r.stats is not None:
            st = r.stats
            t = st.tested > 0
            x.lost_middle, x.gap_ends, x.length = (np.asarray(a[t], float) for a in
                                                   (st.lost_middle, st.gap_ends, st.tested_length))
            x.lost_ends, x.ends = float(st.lost_ends.sum()), float(st.ends.sum())
            x.tested, x.verified = np.asarray(st.tested[t], float), np.asarray(st.verified[t], float)
            ok = st.run_n >= min_samples
            x.offsets = np.asarray(st.run_mean[ok], float)
            x.noise = float(np.nansum(st.run_noise[ok]))
        if r.detector == corner_det and r.corners is not None:
            x.corners, x.found = float(len(r.corners.fid)), float(r.corners.found.sum())
    return x


def per_image(extras: list[ImageExtras], stage: str, raw: bool = False
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x_i, v_i, which images have one) of a stage's magnitude (`raw`: edge_loss as everything lost, 1 - the
    verified fraction, as `verify --edge-loss raw` fits it)."""
    n = len(extras)
    x, v, ok = np.full(n, np.nan), np.full(n, np.nan), np.zeros(n, bool)
    if stage == "edge_loss" and raw:
        for i, e in enumerate(extras):
            T = e.tested.sum()
            if len(e.tested) >= 3 and T > 0:
                a = e.tested - e.verified
                x[i] = a.sum() / T
                k = len(a)
                v[i] = k / (k - 1) * np.sum((a - x[i] * e.tested) ** 2) / (T * T)
                ok[i] = True
    elif stage == "edge_loss":
        ends = sum(e.ends for e in extras)
        end = sum(e.lost_ends for e in extras) / ends if ends > 0 else 0.0
        for i, e in enumerate(extras):
            L = e.length.sum()
            if len(e.length) >= 3 and L > 0:
                a = e.lost_middle - end * e.gap_ends
                x[i] = a.sum() / L
                k = len(a)
                v[i] = k / (k - 1) * np.sum((a - x[i] * e.length) ** 2) / (L * L)
                ok[i] = True
    elif stage == "lateral_shift":
        d_all = np.concatenate([e.offsets for e in extras]) if extras else np.zeros(0)
        m = float(d_all.mean()) if len(d_all) else 0.0
        for i, e in enumerate(extras):
            k = len(e.offsets)
            if k >= MIN_FRAGMENTS:
                q = (e.offsets - m) ** 2
                m2 = q.mean() - e.noise / k
                if m2 > 0:
                    x[i] = math.sqrt(3 * m2)
                    v[i] = (3 / (2 * x[i])) ** 2 * q.var(ddof=1) / k
                    ok[i] = True
    elif stage == "corner_loss":
        for i, e in enumerate(extras):
            if e.corners >= 5:
                x[i] = e.found / e.corners
                v[i] = x[i] * (1 - x[i]) / (e.corners - 1)
                ok[i] = True
    return x, v, ok


def _tau2(W: np.ndarray, x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """tau^2 = var(x) - mean(v) under image weights W (B, n) (rows summing to n)."""
    n = x.shape[0]
    mean = W @ x / n
    var = (W @ (x * x) / n - mean * mean) * n / (n - 1)
    return var - W @ v / n


def spread(extras: list[ImageExtras], stage: str, seed: int, raw: bool = False):
    """(spread, lo, hi, tau2, images) of a stage's magnitude between images, or None with too few images."""
    from wiredsl.verify import fit as fitting

    x, v, ok = per_image(extras, stage, raw)
    x, v = x[ok], v[ok]
    n = len(x)
    if n < MIN_IMAGES:
        return None
    tau2 = float(_tau2(np.ones((1, n)), x, v)[0])
    reps = _tau2(fitting._weights(n, seed, f"{stage}.spread"), x, v)
    lo, hi = fitting._interval(np.asarray(reps, float), tau2, n)
    if lo is None:
        return None
    if tau2 < 0:  # below the boundary: the interval starts at 0 and reaches as far above it as its own width
        hi = hi - tau2
    return math.sqrt(max(tau2, 0.0)), math.sqrt(max(lo, 0.0)), math.sqrt(max(hi, 0.0)), tau2, n


def neighbours(extras: list[ImageExtras], frames: list[int], ok: np.ndarray) -> list[tuple[int, int]]:
    """Index pairs (i, j) of images of one camera whose frames follow each other (k, k + 1), both estimated."""
    at = {(e.side, f): i for i, (e, f) in enumerate(zip(extras, frames, strict=True)) if ok[i]}
    return [(i, at[(s, f + 1)]) for (s, f), i in at.items() if (s, f + 1) in at]


def frame_distances(poses: list) -> np.ndarray:
    """Distance (m) from each frame's pose to the next's (the robot's position: x, y of a floor pose, the
    translation of a 3 x 4 one)."""
    xyz = np.array([[p[3], p[7], p[11]] if len(p) == 12 else [p[0], p[1], 0.0] for p in poses], float)
    return np.sqrt(np.sum(np.diff(xyz, axis=0) ** 2, axis=1)) if len(xyz) > 1 else np.zeros(0)


def correlation(extras, frames, steps: np.ndarray, stage: str, tau2: float, seed: int, raw: bool = False):
    """(length m, lo, hi, rho, pairs) along the sequence, or None (too few neighbours, or no spread)."""
    from wiredsl.verify import fit as fitting

    x, v, ok = per_image(extras, stage, raw)
    pairs = neighbours(extras, frames, ok)
    if len(pairs) < MIN_PAIRS or tau2 <= 0:
        return None
    i, j = np.array(pairs).T
    d = float(np.mean([steps[frames[a]] for a in i if frames[a] < len(steps)] or [0.0]))
    if d <= 0:
        return None
    xs = x[ok]
    mean = xs.mean()
    prod = (x[i] - mean) * (x[j] - mean)
    rho = float(np.clip(prod.mean() / tau2, 1e-6, 1 - 1e-9))
    W = fitting._weights(len(prod), seed, f"{stage}.correlation")
    tau_b = np.maximum(_tau2(fitting._weights(len(xs), seed, f"{stage}.spread"), xs, v[ok]), 1e-300)
    reps = np.clip((W @ prod / len(prod)) / tau_b, 1e-6, 1 - 1e-9)
    r_lo, r_hi = np.quantile(reps, [0.025, 0.975])
    length = lambda r: -d / math.log(r)  # noqa: E731
    return length(rho), length(float(r_lo)), length(float(r_hi)), rho, len(pairs)


def add(result, extras: list[ImageExtras], frames: list[int], poses: list, seed: int, edge_loss: str = "gaps"
        ) -> None:
    """Append the spreads (and correlations) of edge_loss, lateral_shift and corner_loss to a fit.Fit (edge_loss:
    "gaps" or "raw", as fit.fit's)."""
    from wiredsl.verify.fit import Estimate

    steps = frame_distances(poses)
    for stage in KIND:
        raw = stage == "edge_loss" and edge_loss == "raw"
        got = spread(extras, stage, seed, raw)
        if got is None:
            result.estimates.append(Estimate(f"{stage}.spread", None, note=f"fewer than {MIN_IMAGES} images "
                                                                           "with an estimate"))
            result.estimates.append(Estimate(f"{stage}.correlation", None, note="no spread"))
            continue
        s, lo, hi, tau2, n = got
        unit = "" if KIND[stage] == "fraction" else " px^2"
        result.estimates.append(Estimate(f"{stage}.spread", s, lo, hi, f"between {n} images: the variance of their "
                                         f"own estimates less their measurement variance, {tau2:.3g}{unit}"))
        c = correlation(extras, frames, steps, stage, tau2, seed, raw)
        if c is None:
            result.estimates.append(Estimate(f"{stage}.correlation", None,
                                             note="too few neighbouring frames, or no spread"))
        else:
            length, clo, chi, rho, pairs = c
            result.estimates.append(Estimate(f"{stage}.correlation", length, clo, chi,
                                             f"lag-1 correlation {rho:.3g} over {pairs} neighbouring frames"))


def clauses(result, stage: str) -> tuple[list[str], str]:
    """(comment lines, clauses after the stage's value) of a stage's spread and correlation in the fitted
    pipeline: written only where the spread's interval excludes 0."""
    try:
        s, c = result.get(f"{stage}.spread"), result.get(f"{stage}.correlation")
    except StopIteration:
        return [], ""
    if s.value is None:
        return [f"  # {stage} spread between images not estimated ({s.note})"], ""
    fmt = (lambda x: f"{100 * x:.4g}%") if KIND[stage] == "fraction" else (lambda x: f"{x:.4g}px")  # noqa: E731
    line = f"  # {stage} spread between images {fmt(s.value)}, 95% interval [{fmt(s.lo)}, {fmt(s.hi)}]: {s.note}"
    if not s.lo or s.lo <= 0:
        return [line + " (not written: 0 is inside)"], ""
    value = result.get(f"{stage}.{VALUE[stage]}").used
    top = 0.95 * math.sqrt(max(value * (1 - value), 0.0)) if KIND[stage] == "fraction" else math.inf
    if s.value >= top:  # a Beta of this mean cannot spread more
        line += f" (written as {fmt(top)}, the widest a Beta of mean {fmt(value)} takes here)"
    out = f" spread {fmt(min(s.value, top))}"
    lines = [line]
    if c.value is not None:
        lines.append(f"  # {stage} correlation along the frames {c.value:.4g}m, 95% interval [{c.lo:.4g}m, "
                     f"{c.hi:.4g}m]: {c.note}")
        out += f" correlation {c.value:.4g}m"
    else:
        lines.append(f"  # {stage} correlation along the frames not estimated ({c.note})")
    return lines, out
