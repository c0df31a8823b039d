"""Spreads between images and correlation along their sequence, estimated by `verify --fit` (issue 34 item 2).

Each image i gives its own estimate x_i of a magnitude, with a measurement variance v_i from within the image.
Each camera's images, in frame order, are modelled as x = mu + tau z + e: z a stationary AR(1) over the frame
numbers (correlation rho^|k - l| between frames k and l), e the measurement noise, mu the camera's mean. tau (the
effect's `spread`) and rho are the maximum of the restricted (REML) Gaussian likelihood on a grid (`loglik`;
rho is 0 unless the images have neighbouring frames), with 95% profile-likelihood intervals: an interval that
reaches 0 keeps the width the data leave (never [0, 0]), and short correlated sequences, whose sample variance
is biased low, are handled by the likelihood rather than by moments. The effect's `correlation` length is
-d / ln(rho), d the mean distance between neighbouring frames' poses (metres). Per magnitude:

- edge_loss: x_i the image's gap fraction (fit's edge-loss estimate on its strokes alone, the end loss pooled;
  with --edge-loss raw, 1 - its verified fraction), v_i from the scatter of its strokes' own (the ratio
  estimator's variance over strokes); and the spread between an image's features (`feature_spread`) from that
  scatter itself (`feature_spread`);
- lateral_shift: x_i = sqrt(3 m_i), m_i the mean square of the image's fragment offsets about the pooled mean
  less their measurement noise; v_i by the delta method from the scatter of the squared offsets;
- corner_loss: x_i the image's found fraction, v_i = p (1 - p) / n_i at the pooled p (at least 1 / (4 n_i^2)).

A spread (and its correlation) is written into the fitted pipeline only where its interval excludes 0; else
its interval is a comment.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

MIN_IMAGES = 6  # images with an estimate for a spread
MIN_PAIRS = 5  # neighbouring pairs for a correlation
MIN_FRAGMENTS = 8  # fragments an image needs for its lateral-shift range
KIND = {"edge_loss": "fraction", "lateral_shift": "image", "corner_loss": "fraction", "corner_error": "image"}
VALUE = {"edge_loss": "fraction", "lateral_shift": "range", "corner_loss": "keep", "corner_error": "sigma"}
ALONG = ("edge_loss", "lateral_shift", "corner_loss")  # the stages that take a correlation along the path


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
    loc2: float = 0.0  # the located corners' squared residuals (verification.corner_residuals)
    loc_dof: float = 0.0  # their degrees of freedom an axis


MIN_STROKE_SAMPLES = 5  # verified samples a stroke needs for its mean offset to count in an image's shift

def extras_of(results, side: str, edge_det: str | None, corner_det: str | None, min_samples: int,
              inlier: float = 2.0) -> ImageExtras:
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
            from wiredsl.verify.verification import corner_residuals

            _, e, dof = corner_residuals(r.corners, inlier)
            x.loc2, x.loc_dof = float(np.sum(e * e)), float(dof)
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
    elif stage == "corner_error":  # a pair's sigma: the same in both cameras, so the left image's stands for it
        lefts = any(e.side == "left" for e in extras)
        for i, e in enumerate(extras):
            if e.loc_dof >= 5 and e.loc2 > 0 and not (lefts and e.side == "right"):
                x[i] = math.sqrt(e.loc2 / (2 * e.loc_dof))  # two axes
                v[i] = x[i] * x[i] / (4 * e.loc_dof)  # a normal's sd from 2 dof of squares: var sigma^2 / (2 * 2 dof)
                ok[i] = True
    elif stage == "corner_loss":
        # the binomial variance at the pooled keep (an image's own x (1 - x) is 0 where it found all or none)
        n_all = sum(e.corners for e in extras if e.corners >= 5)
        p = sum(e.found for e in extras if e.corners >= 5) / n_all if n_all else 0.0
        for i, e in enumerate(extras):
            if e.corners >= 5:
                x[i] = e.found / e.corners
                v[i] = max(p * (1 - p), 0.25 / e.corners) / e.corners
                ok[i] = True
    return x, v, ok


def stroke_losses(extras: list[ImageExtras], raw: bool) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per image, its strokes' lost amounts a_k and their sizes L_k (gaps: px less the pooled end loss at each
    gap end, over px tested; raw: samples lost over samples tested)."""
    if raw:
        return [(e.tested - e.verified, e.tested) for e in extras]
    ends = sum(e.ends for e in extras)
    end = sum(e.lost_ends for e in extras) / ends if ends > 0 else 0.0
    return [(e.lost_middle - end * e.gap_ends, e.length) for e in extras]


def feature_spread(extras: list[ImageExtras], seed: int, raw: bool = False):
    """(spread, lo, hi, strokes) of edge_loss's fraction between the features of an image: the strokes' lost
    fractions y_k about their image's x_i, weighted as an image's fraction weighs them,
    sigma^2 = sum_i k_i / (k_i - 1) sum_k L_k^2 (y_k - x_i)^2 / sum_i sum_k L_k^2, so that a simulation drawing
    each feature's fraction with this sd scatters each image's fraction as the detector's did (the detector's own
    scatter between strokes is counted in); bootstrap over images. None with too few images."""
    from wiredsl.verify import fit as fitting

    num, den = [], []
    for a, L in stroke_losses(extras, raw):
        k = len(a)
        if k < 3 or L.sum() <= 0:
            continue
        x = a.sum() / L.sum()
        num.append(k / (k - 1) * np.sum((a - x * L) ** 2))
        den.append(np.sum(L * L))
    if len(num) < MIN_IMAGES:
        return None
    num, den = np.array(num), np.array(den)
    value = math.sqrt(num.sum() / den.sum())
    W = fitting._weights(len(num), seed, "edge_loss.feature_spread")
    lo, hi = fitting._interval(np.sqrt((W @ num) / (W @ den)), value, len(num))
    return value, lo, hi, len(num)


RHO_GRID = np.concatenate([np.linspace(0.0, 0.9, 46), np.linspace(0.91, 0.99, 9)])
TAU_STEPS = 81  # spreads on the likelihood's grid, from 0 to 3 times the estimates' standard deviation
CHI2_95 = 3.841458820694124  # chi-squared with one degree of freedom, its 95% point (scipy.stats.chi2.ppf)


def sequences(extras: list[ImageExtras], frames: list[int], ok: np.ndarray) -> list[np.ndarray]:
    """Each camera's images with an estimate, in frame order (index arrays): the sequences along the path."""
    sides = {}
    for i in np.flatnonzero(ok):
        sides.setdefault(extras[i].side, []).append(i)
    return [np.array(sorted(v, key=lambda i: frames[i])) for v in sides.values() if len(v) >= 2]


def loglik(x: np.ndarray, v: np.ndarray, seqs: list[np.ndarray], frames: list[int], tau: np.ndarray,
           rho: np.ndarray) -> np.ndarray:
    """The restricted (REML) Gaussian log-likelihood of the per-image estimates x, each sequence (one camera, in
    frame order) x = mu + tau z + e: z a stationary AR(1) over the frame numbers (correlation rho^|k - l|), e the
    measurement noise (variances v), mu its own mean; on the grid tau (T,) x rho (R,), (T, R)."""
    total = np.zeros((len(tau), len(rho)))
    for q in seqs:
        f = np.array([frames[i] for i in q], float)
        lag = np.abs(f[:, None] - f[None, :])
        R = rho[:, None, None] ** lag[None]  # (R, n, n)
        S = (tau[:, None, None, None] ** 2) * R[None] + np.diag(v[q])[None, None]  # (T, R, n, n)
        _, logdet = np.linalg.slogdet(S)
        rhs = np.broadcast_to(np.stack([np.ones(len(q)), x[q]], axis=-1), (*S.shape[:2], len(q), 2))
        sol = np.linalg.solve(S, rhs)  # Sigma^-1 [1, x]
        a = sol[..., 0].sum(axis=-1)  # 1' Sigma^-1 1
        b = sol[..., 1].sum(axis=-1)  # 1' Sigma^-1 x
        quad = sol[..., 1] @ x[q] - b * b / a  # (x - mu)' Sigma^-1 (x - mu) at the GLS mean mu = b / a
        total += -0.5 * (logdet + quad + np.log(a))
    return total


def spread_and_correlation(extras, frames, stage: str, seed: int, raw: bool = False):
    """(tau2, (lo, hi), rho, (lo, hi), images, pairs) of a stage's magnitude, or None with too few images: the
    maximum of `loglik` on its grid (tau from 0; rho 0 unless the images have neighbouring frames), with 95%
    profile-likelihood intervals (where twice the log-likelihood, maximised over the other, is within 3.84 of its
    maximum). An interval reaching 0 has the width the data leave, never [0, 0]."""
    x, v, ok = per_image(extras, stage, raw)
    if ok.sum() < MIN_IMAGES:
        return None
    seqs = sequences(extras, frames, ok)
    pairs = sum(int(np.sum(np.diff(np.array([frames[i] for i in q])) == 1)) for q in seqs)
    near = pairs >= MIN_PAIRS
    x0, v0 = np.where(ok, x, 0.0), np.where(ok, np.maximum(v, 1e-12), 1.0)
    sd = float(np.std(x[ok]))
    tau = np.linspace(0.0, 3.0 * max(sd, 1e-9), TAU_STEPS)
    rho = RHO_GRID if near else np.zeros(1)
    ll = loglik(x0, v0, seqs, frames, tau, rho)
    t, r = np.unravel_index(np.argmax(ll), ll.shape)
    keep_t = np.flatnonzero(2 * (ll.max() - ll.max(axis=1)) <= CHI2_95)
    keep_r = np.flatnonzero(2 * (ll.max() - ll.max(axis=0)) <= CHI2_95)
    step = tau[1] - tau[0]
    t_lo, t_hi = tau[keep_t.min()], tau[min(keep_t.max() + 1, len(tau) - 1)] if keep_t.max() + 1 < len(tau) else \
        tau[-1] + step
    r_lo, r_hi = rho[keep_r.min()], rho[keep_r.max()]
    return (float(tau[t] ** 2), (float(t_lo**2), float(t_hi**2)), float(rho[r]), (float(r_lo), float(r_hi)),
            int(ok.sum()), pairs if near else 0)


def frame_distances(poses: list) -> np.ndarray:
    """Distance (m) from each frame's pose to the next's (the robot's position: x, y of a floor pose, the
    translation of a 3 x 4 one)."""
    xyz = np.array([[p[3], p[7], p[11]] if len(p) == 12 else [p[0], p[1], 0.0] for p in poses], float)
    return np.sqrt(np.sum(np.diff(xyz, axis=0) ** 2, axis=1)) if len(xyz) > 1 else np.zeros(0)


def add(result, extras: list[ImageExtras], frames: list[int], poses: list, seed: int, edge_loss: str = "gaps"
        ) -> None:
    """Append the spreads (and correlations) of edge_loss, lateral_shift and corner_loss to a fit.Fit (edge_loss:
    "gaps" or "raw", as fit.fit's)."""
    from wiredsl.verify.fit import Estimate

    steps = frame_distances(poses)
    fs = feature_spread(extras, seed, edge_loss == "raw")
    result.estimates.append(Estimate("edge_loss.feature_spread", None, note=f"fewer than {MIN_IMAGES} images")
                            if fs is None else
                            Estimate("edge_loss.feature_spread", fs[0], fs[1], fs[2],
                                     f"the strokes' lost fractions about their image's, over {fs[3]} images"))
    for stage in KIND:
        raw = stage == "edge_loss" and edge_loss == "raw"
        got = spread_and_correlation(extras, frames, stage, seed, raw)
        if got is None:
            result.estimates.append(Estimate(f"{stage}.spread", None, note=f"fewer than {MIN_IMAGES} images "
                                                                           "with an estimate"))
            if stage in ALONG:
                result.estimates.append(Estimate(f"{stage}.correlation", None, note="no spread"))
            continue
        tau2, (lo, hi), rho, (r_lo, r_hi), n, pairs = got

        unit = "" if KIND[stage] == "fraction" else " px^2"
        root = lambda q: math.sqrt(max(q, 0.0))  # noqa: E731
        result.estimates.append(Estimate(
            f"{stage}.spread", root(tau2), root(lo), root(hi),
            f"between {n} images (REML, their measurement noise apart: tau^2 {tau2:.3g}{unit}"
            + (f"; an AR(1) along {pairs} neighbouring frames" if pairs else "") + ")"))
        if stage not in ALONG:  # (corner_error's correlation is its two cameras', fitted by fit.py)
            continue
        idx = [i for i in range(len(frames)) if frames[i] + 1 < len(poses)]
        d = float(np.mean([steps[frames[i]] for i in idx])) if idx else 0.0
        if not pairs or d <= 0 or tau2 <= 0 or r_lo <= 0:
            result.estimates.append(Estimate(f"{stage}.correlation", None,
                                             note="too few neighbouring frames, or no spread"))
            continue
        result.estimates.append(Estimate(f"{stage}.correlation", _length(rho, d), _length(r_lo, d), _length(r_hi, d),
                                         f"lag-1 correlation {rho:.3g} [{r_lo:.3g}, {r_hi:.3g}] over {pairs} "
                                         f"neighbouring frames {d:.3g} m apart"))


def _length(rho: float, d: float) -> float:
    """The correlation length (m) of a lag-1 correlation rho between frames d apart: exp(-d / length) = rho."""
    return 0.0 if rho <= 0 else -d / math.log(min(rho, 0.999))


def _feature_clause(result, stage: str, value, lines: list[str], out: str) -> tuple[list[str], str]:
    """edge_loss's feature_spread, where estimated with an interval above 0, after its other clauses."""
    try:
        e = result.get(f"{stage}.feature_spread")
    except StopIteration:
        return lines, out
    if e.value is None:
        return [*lines, f"  # {stage} spread between an image's features not estimated ({e.note})"], out
    span = f"95% interval [{100 * e.lo:.4g}%, {100 * e.hi:.4g}%]" if e.lo is not None and e.hi is not None \
        else "no interval"
    line = f"  # {stage} spread between an image's features {100 * e.value:.4g}%, {span}: {e.note}"
    if not e.lo or e.lo <= 0:
        return [*lines, line + " (not written: 0 is inside)"], out
    return [*lines, line], out + f" feature_spread {100 * e.value:.4g}%"


def clauses(result, stage: str) -> tuple[list[str], str]:
    """(comment lines, clauses after the stage's value) of a stage's spread and correlation in the fitted
    pipeline: written only where the spread's interval excludes 0."""
    try:
        s = result.get(f"{stage}.spread")
        c = result.get(f"{stage}.correlation") if stage in ALONG else None
    except StopIteration:
        return [], ""
    if s.value is None:
        return _feature_clause(result, stage, None, [f"  # {stage} spread between images not estimated "
                                                     f"({s.note})"], "")
    fmt = (lambda x: f"{100 * x:.4g}%") if KIND[stage] == "fraction" else (lambda x: f"{x:.4g}px")  # noqa: E731
    span = f"95% interval [{fmt(s.lo)}, {fmt(s.hi)}]" if s.lo is not None and s.hi is not None else "no interval"
    line = f"  # {stage} spread between images {fmt(s.value)}, {span}: {s.note}"
    if not s.lo or s.lo <= 0:
        return _feature_clause(result, stage, None, [line + " (not written: 0 is inside)"], "")
    value = result.get(f"{stage}.{VALUE[stage]}").used
    top = 0.95 * math.sqrt(max(value * (1 - value), 0.0)) if KIND[stage] == "fraction" else math.inf
    if s.value >= top:  # a Beta of this mean cannot spread more
        line += f" (written as {fmt(top)}, the widest a Beta of mean {fmt(value)} takes here)"
    out = f" spread {fmt(min(s.value, top))}"
    lines = [line]
    lines, out = _feature_clause(result, stage, value, lines, out)
    if c is None:
        pass
    elif c.value is not None and c.lo and c.lo > 0:
        lines.append(f"  # {stage} correlation along the frames {c.value:.4g}m, 95% interval [{c.lo:.4g}m, "
                     f"{c.hi:.4g}m]: {c.note}")
        out += f" correlation {c.value:.4g}m"
    else:
        lines.append(f"  # {stage} correlation along the frames not estimated ({c.note})")
    return lines, out
