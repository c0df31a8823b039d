"""Each effect's parameters estimated from the verification, with 95% bootstrap intervals over images, written
as a pipeline block (`pipeline measured { ... }`) that a scene includes.

Per image the verification leaves a few sums (`ImageSums`); a statistic is a ratio of weighted sums, so a
bootstrap replicate is the image weights of a multinomial resample (B x images) times those sums: every
replicate costs one matrix product, whatever the number of images. The resamples are drawn from a generator
keyed by the seed and the statistic's name (the same seed gives the same intervals).

- edge_loss.fraction = the length lost in the strokes' middles less the detector's own loss at an edge's end
  (measured at the model strokes' free ends: verification.junctions) at each end of each gap, over the length
  tested; its interval is widened by END_DOUBT of that correction. The fragments (verified runs per stroke) are
  reported beside it: the effect removes one gap a stroke, so it leaves 2 runs.
- lateral_shift.range: the mean offsets d of the fragments the detector found (runs of verified samples;
  the effect shifts each fragment edge_loss leaves on its own) are taken as the effect's shifts, uniform on
  [-range, range]: range = sqrt(3 (var(d) - noise)), with noise the mean measurement variance of a fragment's
  mean (its samples' scatter about a line fitted to them, over their number); their mean is reported apart. Which law
  fits d better, uniform or normal (sigma^2 =
  mean(d^2)), is decided by the Kolmogorov-Smirnov statistic (smaller D; both laws' parameters estimated from
  the same d, so the p-values are optimistic), with the log-likelihoods beside it.
- approx_error.sigma: a line fitted to each stroke's verified offsets along it gives the offsets e0, e1 of
  its two ends; the effect moves each end by N(0, sigma^2) in each direction after one shift of the whole
  stroke, so e1 - e0 ~ N(0, 2 sigma^2): sigma = sqrt(mean((e1 - e0)^2) / 2). Without fragments of lines (curves
  only) it is not estimated and left at 0 (UNMEASURED), not the paper's value.
- corner_loss.keep = model corners with a detected corner within the radius / model corners (corner detector).
- corner_error.sigma: the found corners within `inlier` px of the model's are placed by the detector's
  localisation error, an isotropic 2D Gaussian: their offsets, less each image's affine map of them (what a pose
  or calibration error moves, to first order; `verification.corner_residuals`), have the mean square
  2 sigma^2 - t^2 q / (1 - q) a degree of freedom, q = exp(-t^2 / (2 sigma^2)), of sigma^2 chi^2_2 truncated at
  t = inlier, solved for sigma (bisection).
- corner_error.correlation: over the corners located in both images of a stereo pair, the sum of the products
  of their two residuals over the root of the product of their sums of squares.
- corner_mismatch: a found corner farther than `inlier` px from the model's is displaced, less the corners the
  localisation error alone puts there (its normal's tail beyond `inlier`). The effect moves a fraction of
  corners to a uniform point of the disc of `radius`; a move shorter than `inlier` is not seen, so radius R
  solves E[r | r > t] = (2/3)(R^3 - t^3)/(R^2 - t^2) at the displaced corners' mean distance (less sigma^2 /
  (R + t), what the localisation error adds) and fraction = displaced / found / (1 - (t/R)^2); the two corner
  estimates take each other's share off in turn (`corner_model`). In stereo pairs the matcher's wrong-pair rate
  is reported too.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field

import numpy as np

B = 1000  # bootstrap resamples
PAPER = {"edge_loss.fraction": 0.29, "lateral_shift.range": 3.0, "approx_error.sigma": 0.15,
         "corner_loss.keep": 0.85, "corner_mismatch.fraction": 0.01, "corner_mismatch.radius": 10.0}
# what a statistic the images cannot estimate is left at instead of the paper's value: the approximation error is
# measured from fragments of lines only, so on curves (a circle grid's dots) it is not measured, and the paper's
# 0.15 px on every vertex of a curve's dense chords loses edge no real dot loses (issue 34): it is not simulated
UNMEASURED = {"approx_error.sigma": 0.0}
# The edge-loss correction takes a gap's ends to lose what a model stroke's ends lose. In the round trip
# (tests/test_verify_roundtrip.py) the two differ by up to about a fifth of the correction, so its interval is
# widened by this share of the correction either way.
END_DOUBT = 0.25
EDGE_SOFT = 0.1  # the shift mixture's uniform law: its edges softened by this share of its range (shift_mixture)
MIN_RUN_PX = 10.0  # px of offsets a fragment needs for its mean offset to count (px, not samples: alike at every step)
# below these a statistic is not estimated
MIN = {"edges": 20, "strokes": 5, "corners": 10, "displaced": 3, "located": 10}


@dataclass
class ImageSums:
    """What one image contributes to the fit."""

    tested: float = 0.0  # samples
    verified: float = 0.0
    length: float = 0.0  # px of stroke tested
    lost_middle: float = 0.0  # px lost farther than the margin from the strokes' ends
    lost_ends: float = 0.0  # px lost within it
    ends: float = 0.0  # stroke ends tested
    gap_ends: float = 0.0  # ends of the gaps in the middles
    strokes: int = 0  # runs (fragments) with enough verified samples for a mean offset
    d1: float = 0.0  # sum of their mean offsets
    d2: float = 0.0  # sum of their squared mean offsets
    noise: float = 0.0  # sum of their means' measurement variances
    offsets: list = field(default_factory=list)  # their mean offsets
    offset_noise: list = field(default_factory=list)  # their measurement variances
    offset_length: list = field(default_factory=list)  # px their offsets cover
    offset_line: list = field(default_factory=list)  # whether each is a line's (approx_error moves its mean)
    runs: float = 0.0
    run_strokes: int = 0
    fitted: int = 0  # runs with a fitted line
    fitted2: float = 0.0  # sum of (e1 - e0)^2
    fitted_noise: float = 0.0  # sum of their measurement variances
    corners: float = 0.0  # model corners tested
    found: float = 0.0
    displaced: float = 0.0
    displaced_r: float = 0.0  # sum of their distances
    located: float = 0.0  # found corners within the inlier distance (not displaced)
    loc_dof: float = 0.0  # their residuals' degrees of freedom an axis (verification.corner_residuals)
    loc2: float = 0.0  # sum of their squared residuals (offsets less the image's affine map of them)
    pairs: float = 0.0  # (stereo pairs, on the left image's sums) corners located in both images
    pair_lr: float = 0.0  # sum of the products of their left and right residuals, both axes
    pair_ll: float = 0.0  # sum of their squared left residuals
    pair_rr: float = 0.0  # sum of their squared right residuals
    matched: float = 0.0  # stereo matcher
    wrong: float = 0.0


@dataclass
class Estimate:
    key: str  # stage.param
    value: float | None  # None: not estimated (the paper's value is kept, or UNMEASURED's)
    lo: float | None = None
    hi: float | None = None
    note: str = ""

    @property
    def used(self) -> float:
        return self.value if self.value is not None else UNMEASURED.get(self.key, PAPER[self.key])

    def to_json(self) -> dict:
        return {"parameter": self.key, "value": self.value, "low95": self.lo, "high95": self.hi,
                "paper": PAPER.get(self.key), "used": self.used if self.key in PAPER else self.value,
                "note": self.note}


def _weights(n: int, seed: int, name: str) -> np.ndarray:
    rng = np.random.default_rng([seed, zlib.crc32(name.encode())])
    return rng.multinomial(n, np.full(n, 1.0 / n), size=B).astype(float)


def _interval(reps: np.ndarray, value: float | None = None, n: int | None = None
              ) -> tuple[float | None, float | None]:
    """The 2.5% and 97.5% quantiles of the replicates; with the estimate and the number of images n, the
    replicates' spread about the estimate is first widened by sqrt(n / (n - 1)) t(n - 1) / z: the bootstrap's
    variance of a mean is (n - 1) / n of the usual estimate, and with an estimated spread Student's t, not the
    normal z, gives 95% (with few images the plain percentiles cover about 90%)."""
    reps = reps[np.isfinite(reps)]
    if len(reps) < B // 2:
        return None, None
    if value is not None and n is not None and n > 1 and math.isfinite(value):
        from scipy import stats

        widen = math.sqrt(n / (n - 1)) * float(stats.t.ppf(0.975, n - 1)) / float(stats.norm.ppf(0.975))
        reps = value + (reps - value) * widen
    lo, hi = np.quantile(reps, [0.025, 0.975])
    lo, hi = max(float(lo), 0.0), float(hi)  # every parameter is >= 0 (fractions are clipped to 1 by callers)
    if hi - lo <= 1e-12 * max(1.0, abs(hi)):
        return None, None  # no spread: a "95%" interval of zero width would claim a certainty the images lack
    return lo, hi


def exact_binomial(x: float, n: float) -> tuple[float, float]:
    """The Clopper-Pearson 95% interval of a proportion of x in n (counts rounded): it has width at 0 and at 1,
    where a bootstrap over images that all agree has none."""
    from scipy import stats

    x, n = int(round(x)), max(int(round(n)), 1)
    lo = 0.0 if x <= 0 else float(stats.beta.ppf(0.025, x, n - x + 1))
    hi = 1.0 if x >= n else float(stats.beta.ppf(0.975, x + 1, n - x))
    return lo, hi


def _at_bound(value: float | None, lo, hi, x: float, n: float):
    """(lo, hi, how) of a proportion: where it is 0 or 1, or its bootstrap has no spread, the hull of the bootstrap's
    interval and the exact binomial one of x in n; `how` says so (empty otherwise)."""
    if value is None or n <= 0:
        return lo, hi, ""
    if lo is not None and 1e-12 < value < 1 - 1e-12:
        return lo, hi, ""
    elo, ehi = exact_binomial(x, n)
    lo, hi = (elo, ehi) if lo is None else (min(lo, elo), max(hi, ehi))
    return lo, hi, f"; interval: exact binomial of {int(round(x)):,} in {int(round(n)):,} (at {value:.3g} the " \
                   "bootstrap over images has no spread)"


def _ratio(num: np.ndarray, den: np.ndarray, seed: int, name: str, fn=lambda r: r, fraction: bool = True):
    """(value, lo, hi) of fn(sum num / sum den) over images, and its bootstrap."""
    total = den.sum()
    if total <= 0:
        return None, None, None
    value = float(fn(num.sum() / total))
    W = _weights(len(num), seed, name)
    with np.errstate(invalid="ignore", divide="ignore"):
        reps = fn((W @ num) / (W @ den))
    lo, hi = _interval(np.asarray(reps, float), value, int((den > 0).sum()))
    if hi is not None and fraction:
        hi = min(hi, 1.0)
    return value, lo, hi


def _proportion(num: np.ndarray, den: np.ndarray, seed: int, name: str):
    """(value, lo, hi, how) of the proportion sum num / sum den of counts: the bootstrap over images, and at 0 or 1
    (or without spread) the exact binomial interval beside it (`_at_bound`)."""
    value, lo, hi = _ratio(num, den, seed, name)
    lo, hi, how = _at_bound(value, lo, hi, float(num.sum()), float(den.sum()))
    return value, lo, hi, how


def _edge_loss(col, seed: int):
    """(fraction, lo, hi, end loss px): the lost length in the strokes' middles less the detector's own end loss
    at each gap end, over the tested length."""

    def value(lost_mid, lost_ends, ends, gap_ends, length):
        with np.errstate(invalid="ignore", divide="ignore"):
            end = np.where(ends > 0, lost_ends / np.maximum(ends, 1), 0.0)
            return np.clip((lost_mid - end * gap_ends) / length, 0.0, 1.0), end

    keys = ("lost_middle", "lost_ends", "ends", "gap_ends", "length")
    f, end = value(*(col[k].sum() for k in keys))
    W = _weights(len(col["length"]), seed, "edge_loss.fraction")
    reps, _ = value(*(W @ col[k] for k in keys))
    lo, hi = _interval(np.asarray(reps, float), float(f), int((col["length"] > 0).sum()))
    n = col["tested"].sum()  # at 0 or 1: the exact binomial interval of the samples beside the bootstrap's
    lo, hi, how = _at_bound(float(f), lo, hi, float(f) * n, n)
    if lo is not None:  # the correction's own assumption, that a gap's end loses what a stroke's end does
        s = END_DOUBT * float(end) * col["gap_ends"].sum() / col["length"].sum()
        lo, hi = max(lo - s, 0.0), hi + s
    return float(f), lo, None if hi is None else min(hi, 1.0), float(end), how


def shift_mixture(d: np.ndarray, v: np.ndarray, wts: np.ndarray, band: float, shape: str = "uniform", start=None,
                  rounds: int = 200, tol: float = 1e-7):
    """(R, m, w, r, loglik) of the fragments' mean offsets d (F,) with measurement variances v (F,), under weights
    wts (K, F) (a bootstrap replicate a row): a mixture of the effect's shifts with weight 1 - w, centred on m, of
    spread R (the range of the uniform law of that variance, R^2 / 3), each fragment's measurement noise N(0, v)
    added, and a background with weight w, uniform over the search band (+-(band + 0.5) px): a fragment the
    detector found on an edge the model does not name (another object's, the paper's edge beside a board) is as
    likely at any offset the search reaches. The uniform's edges are softened by EDGE_SOFT R (a fragment just past
    the estimate's edge is not given to the background outright, which would shrink the estimate round after
    round). The shifts' law is `shape`: "uniform" (the effect's: uniform on
    [-R, R]) or "normal" (N(0, R^2 / 3): the same spread, with tails). Each round the fragments' shares r of the
    effect (K, F) are taken from the densities, then m and R from their r-weighted first and second moments (the
    variance less the noise) and w from the shares: a fixed point from the plain moments (or `start`), reached
    within a few tens of rounds."""
    from scipy.special import ndtr

    d, v = np.asarray(d, float), np.asarray(v, float)
    wts = np.atleast_2d(np.asarray(wts, float))
    tot = np.maximum(wts.sum(axis=1), 1e-300)
    f_bg = 1.0 / (2.0 * (band + 0.5))
    if start is None:
        m = wts @ d / tot
        R = np.sqrt(3 * np.maximum(wts @ (d * d) / tot - m * m - wts @ v / tot, 0.0))
        w = np.full(len(wts), 0.05)
    else:
        R, m, w = (np.full(len(wts), float(x)) for x in start)  # (R, m, w)

    def density(m, R):
        x = d[None, :] - m[:, None]
        if shape == "normal":
            s2 = (R * R / 3)[:, None] + v[None, :] + 1e-12
            return np.exp(-x * x / (2 * s2)) / np.sqrt(2 * np.pi * s2)
        Rr = np.maximum(R, 1e-3)[:, None]
        sd = np.sqrt(v[None, :] + (EDGE_SOFT * Rr) ** 2 + 1e-6)
        return (ndtr((x + Rr) / sd) - ndtr((x - Rr) / sd)) / (2 * Rr)

    for _ in range(rounds):
        a = (1 - w)[:, None] * density(m, R)
        r = a / np.maximum(a + w[:, None] * f_bg, 1e-300)
        wr = wts * r
        n = np.maximum(wr.sum(axis=1), 1e-300)
        m_new = wr @ d / n
        var = (wr * ((d[None, :] - m_new[:, None]) ** 2 - v[None, :])).sum(axis=1) / n
        R_new = np.sqrt(3 * np.maximum(var, 0.0))
        w_new = np.clip(1 - n / tot, 0.0, 1.0)
        done = np.all(np.abs(R_new - R) < tol) and np.all(np.abs(w_new - w) < tol)
        m, R, w = m_new, R_new, w_new
        if done:
            break
    a = (1 - w)[:, None] * density(m, R)
    r = a / np.maximum(a + w[:, None] * f_bg, 1e-300)
    loglik = (wts * np.log(np.maximum(a + w[:, None] * f_bg, 1e-300))).sum(axis=1)
    return R, m, w, r, loglik


def _shift_range(sums: list, seed: int, band: float, approx: float = 0.0):
    """(range, lo, hi, mean, background share, effect's offsets, law) of the lateral shift, from the fragments'
    mean offsets by `shift_mixture` with the law (uniform or normal) of the larger likelihood; the interval by the
    bootstrap over images (each replicate's fixed point from the estimate's, with the same law)."""
    d = np.concatenate([np.asarray(s.offsets, float) for s in sums])
    v = np.concatenate([np.asarray(s.offset_noise, float) if len(s.offset_noise) == len(s.offsets) else
                        np.zeros(len(s.offsets)) for s in sums])  # (no noise given: none)
    v = np.where(np.isfinite(v), v, 0.0)
    # approx_error moves a line fragment's two ends by N(0, approx^2) each across it: its mean by N(0, approx^2 / 2),
    # what the shift does not explain
    line = np.concatenate([np.asarray(s.offset_line, bool) if len(s.offset_line) == len(s.offsets) else
                           np.zeros(len(s.offsets), bool) for s in sums])
    v = v + np.where(line, approx * approx / 2, 0.0)
    img = np.repeat(np.arange(len(sums)), [len(s.offsets) for s in sums])
    one = np.ones((1, len(d)))
    fits = {shape: [x[0] for x in shift_mixture(d, v, one, band, shape)] for shape in ("uniform", "normal")}
    shape = max(fits, key=lambda k: fits[k][4])  # the law of the shifts with the larger likelihood
    R, m, w, r, _ = fits[shape]
    W = _weights(len(sums), seed, "lateral_shift.range")
    reps = []
    for k in range(0, B, 250):  # replicates in blocks: (250, fragments) arrays
        reps.append(shift_mixture(d, v, W[k:k + 250][:, img], band, shape, start=(R, m, w), rounds=8,
                                   tol=1e-4)[0])
    lo, hi = _interval(np.concatenate(reps), float(R), int(sum(len(s.offsets) > 0 for s in sums)))
    # the background's share by length (what a simulation gives the background, run by run: predict.py), the
    # fragments' share w by number where their lengths are not given
    length = np.concatenate([np.asarray(s.offset_length, float) if len(s.offset_length) == len(s.offsets) else
                             np.full(len(s.offsets), np.nan) for s in sums])
    w_len = float(((1 - r) * length).sum() / length.sum()) if len(d) and np.isfinite(length).all() and \
        length.sum() > 0 else float(w)
    if lo is None and R == 0 and len(d):
        # no spread beyond the noise in any resample: the interval reaches to the range whose variance is 1.96
        # standard errors of the noise's (sqrt(2 / n) of it over n fragments), the least it could tell from none
        hi = math.sqrt(3 * 1.96 * math.sqrt(2 / len(d)) * max(float(np.mean(v)), 1e-12))
        lo = 0.0
    return float(R), lo, hi, float(m), float(w), d[r > 0.5], shape, w_len


def disc_radius(mean_r: np.ndarray, t: float) -> np.ndarray:
    """R with E[r | r > t] = mean_r for r uniform over a disc of radius R (bisection, vectorised)."""
    mean_r = np.asarray(mean_r, float)
    lo = np.full(mean_r.shape, t)
    hi = np.maximum(3.0 * mean_r, t + 1e-9) + 1.0

    def m(R):
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(R - t > 1e-12, (2.0 / 3.0) * (R**3 - t**3) / (R**2 - t**2), t)

    for _ in range(60):
        mid = (lo + hi) / 2
        below = m(mid) < mean_r
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return (lo + hi) / 2


def law_test(d: np.ndarray) -> dict:
    """Uniform on [-R, R] against N(0, sigma^2) for the stroke shifts d, both fitted by their second moment."""
    from scipy import stats

    d = np.asarray(d, float)
    m2 = float(np.mean(d * d))
    R, sigma = math.sqrt(3 * m2), math.sqrt(m2)
    ks_u = stats.kstest(d, stats.uniform(loc=-R, scale=2 * R).cdf) if R > 0 else None
    ks_n = stats.kstest(d, stats.norm(0, sigma).cdf) if sigma > 0 else None
    r_mle = float(np.abs(d).max())
    ll_u = -len(d) * math.log(2 * r_mle) if r_mle > 0 else None
    ll_n = float(stats.norm(0, sigma).logpdf(d).sum()) if sigma > 0 else None
    better = None
    if ks_u is not None and ks_n is not None:
        better = "uniform" if ks_u.statistic <= ks_n.statistic else "normal"
    return {"n": len(d), "mean": float(d.mean()), "rms": sigma, "uniform_range": R,
            "ks_uniform": None if ks_u is None else {"D": float(ks_u.statistic), "p": float(ks_u.pvalue)},
            "ks_normal": None if ks_n is None else {"D": float(ks_n.statistic), "p": float(ks_n.pvalue)},
            "loglik_uniform_mle": ll_u, "loglik_normal": ll_n, "better": better}


@dataclass
class Fit:
    estimates: list[Estimate]
    shift_law: dict | None
    fragments: dict
    stereo: dict
    images: int
    background: float = 0.0  # the shift mixture's background share of the fragments' length (predict.py's)

    def get(self, key: str) -> Estimate:
        return next(e for e in self.estimates if e.key == key)

    def to_json(self) -> dict:
        return {"images": self.images, "estimates": [e.to_json() for e in self.estimates],
                "lateral_shift_law": self.shift_law, "fragments": self.fragments, "stereo_matcher": self.stereo,
                "lateral_shift_background": self.background}


def fit(sums: list[ImageSums], seed: int, inlier: float = 2.0, radius: float = 10.0, edge_loss: str = "gaps",
        band: float = 6.0) -> Fit:
    """Every estimate. `edge_loss`: "gaps" (the default) fits the gaps, the detector's own loss at each gap's
    ends taken off (what a simulation's edge_loss stage injected, as the round trip checks); "raw" everything
    the detector lost (1 - the verified fraction: a simulation with it loses as much as the detector did)."""
    n = len(sums)
    col = {k: np.array([getattr(s, k) for s in sums], float) for k in
           ("tested", "verified", "length", "lost_middle", "lost_ends", "ends", "gap_ends", "strokes", "d1", "d2",
            "noise", "runs", "run_strokes", "fitted", "fitted2", "fitted_noise", "corners", "found",
            "displaced", "displaced_r", "located", "loc_dof", "loc2", "pairs", "pair_lr", "pair_ll", "pair_rr",
            "matched", "wrong")}
    out = []
    # edge loss: the gaps themselves (the detector's end loss at each gap end taken off), or everything lost
    if col["tested"].sum() >= MIN["edges"]:
        raw, rlo, rhi, rhow = _proportion(col["tested"] - col["verified"], col["tested"], seed, "edge_loss.raw")
        raw_note = (f"1 - verified fraction of {int(col['tested'].sum()):,} samples over "
                    f"{int((col['tested'] > 0).sum())} images{rhow}")
        v, lo, hi, end, how = _edge_loss(col, seed)
        from wiredsl.verify import verification as ver

        gaps_note = (f"lost length over {col['length'].sum():,.0f} px of {int((col['tested'] > 0).sum())} images, "
                     + (f"less the detector's own loss at an edge's end ({end:.3g} px, measured at the model "
                        f"strokes' {int(col['ends'].sum())} free ends) at each of {int(col['gap_ends'].sum())} gap ends"
                        if col["ends"].sum() else f"the model strokes have no free end to measure the detector's own "
                        f"loss at an edge's end: none taken off at the {int(col['gap_ends'].sum())} gap ends")
                     + f"; samples within {ver.JUNCTION:g} px of another stroke's end inside their own left out{how}")
        if edge_loss == "raw":
            out.append(Estimate("edge_loss.fraction", raw, rlo, rhi, raw_note + f" (the gaps alone: {100 * v:.3g}%)"))
        else:
            span = f", [{100 * rlo:.3g}%, {100 * rhi:.3g}%]" if rlo is not None and rhi is not None else ""
            out.append(Estimate("edge_loss.fraction", v, lo, hi, gaps_note + f" (everything lost: {100 * raw:.3g}%"
                                                                             f"{span})"))
    else:
        out.append(Estimate("edge_loss.fraction", None, note="no edge detector, or too few edge samples"))
    # lateral shift and its law
    if col["fitted"].sum() >= MIN["strokes"]:
        # on sigma^2 first: the bootstrap's interval, widened by the noise taken off's own doubt (1.96 standard
        # errors of a mean of the fragments' noise, each estimated from its residuals: about sqrt(2 / fragments))
        v2, lo2, hi2 = _ratio(col["fitted2"] - col["fitted_noise"], 2 * col["fitted"], seed, "approx_error.sigma",
                              fraction=False)
        doubt = 1.96 * math.sqrt(2 / col["fitted"].sum()) * col["fitted_noise"].sum() / (2 * col["fitted"].sum())
        v = math.sqrt(max(v2, 0.0))
        if lo2 is not None:
            lo, hi = math.sqrt(max(lo2 - doubt, 0.0)), math.sqrt(max(hi2 + doubt, 0.0))
        else:
            lo = hi = None
        noise = math.sqrt(max(col["fitted_noise"].sum() / col["fitted"].sum(), 0.0))
        out.append(Estimate("approx_error.sigma", v, lo, hi, f"from the tilts of {int(col['fitted'].sum())} fragments "
                            "of lines, carried to the fragments' ends (e1 - e0 ~ N(0, 2 sigma^2)), less their "
                            f"measurement noise ({noise:.3g} px rms)"))
    else:
        out.append(Estimate("approx_error.sigma", None, note="too few strokes with a fitted line"))
    law, bg_len = None, 0.0
    if col["strokes"].sum() >= MIN["strokes"]:
        apx = out[-1].value or 0.0  # approx_error's share of the fragments' mean offsets is taken off
        v, lo, hi, mean, bg, own, shape, bg_len = _shift_range(sums, seed, band, apx)
        law = law_test(own)
        noise = math.sqrt(max(col['noise'].sum() / col['strokes'].sum(), 0))
        note = (f"sqrt(3 (var d - noise)) of the mean offsets d of {int(col['strokes'].sum())} fragments of at least "
                f"{MIN_RUN_PX:g} px (mean {mean:+.3g} px, not part of the effect; their measurement noise "
                f"{noise:.3g} px rms), {100 * bg:.3g}% of them taken as the background (offsets uniform over the "
                f"+-{band:g} px band: edges the model does not name; the shifts' law in that mixture: {shape})")
        if law["better"] == "normal":
            note += f"; a normal law fits better (KS D {law['ks_normal']['D']:.3g} against uniform's " \
                    f"{law['ks_uniform']['D']:.3g}): this is the uniform range of the same spread"
        out.append(Estimate("lateral_shift.range", v, lo, hi, note))
    else:
        out.append(Estimate("lateral_shift.range", None, note="too few strokes with verified samples"))
    # corners
    if col["corners"].sum() >= MIN["corners"]:
        v, lo, hi, how = _proportion(col["found"], col["corners"], seed, "corner_loss.keep")
        out.append(Estimate("corner_loss.keep", v, lo, hi, f"{int(col['found'].sum())} of "
                                                           f"{int(col['corners'].sum())} model corners found within "
                                                           f"{radius:g} px{how}"))
    else:
        out.append(Estimate("corner_loss.keep", None, note="no corner detector, or too few model corners"))
    out += _corner_estimates(col, seed, inlier)
    fragments = {}
    if col["run_strokes"].sum():
        fragments = {"runs_per_stroke": float(col["runs"].sum() / col["run_strokes"].sum()),
                     "strokes": int(col["run_strokes"].sum()), "effect_gives": 2}
    stereo = {"matched": int(col["matched"].sum()), "wrong": int(col["wrong"].sum()),
              "rate": float(col["wrong"].sum() / col["matched"].sum()) if col["matched"].sum() else None}
    for e in out:
        if e.value is not None and e.lo is None and "interval" not in e.note:
            e.note += " (no interval: the bootstrap over images has no spread, every resample gives the same)"
    return Fit(out, law, fragments, stereo, n, bg_len)


def truncated_sigma(mean_r2: np.ndarray, t: float) -> np.ndarray:
    """sigma with E[r^2 | r <= t] = mean_r2 for r the length of an isotropic 2D N(0, sigma^2) (bisection,
    vectorised); NaN where mean_r2 >= t^2 / 2, the limit as sigma grows (the spread is not bounded by the data)."""
    mean_r2 = np.asarray(mean_r2, float)

    def m(sig):
        with np.errstate(over="ignore"):  # (a narrow normal: q = 0, exactly)
            return 2 * sig * sig - t * t / np.expm1(t * t / (2 * sig * sig))  # q / (1 - q) = 1 / (exp(a) - 1)

    lo = np.full(mean_r2.shape, 1e-9 * t)
    hi = np.full(mean_r2.shape, 1e3 * t)
    for _ in range(80):
        mid = np.sqrt(lo * hi)  # geometric: sigma spans decades
        below = m(mid) < mean_r2
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    with np.errstate(invalid="ignore"):
        return np.where((mean_r2 > 0) & (mean_r2 < t * t / 2 * (1 - 1e-9)), np.sqrt(lo * hi),
                        np.where(mean_r2 <= 0, 0.0, np.nan))


def _tails(sig, located, t: float):
    """(count, summed distance) expected beyond t of the corners the localisation error alone places, given the
    `located` ones within t: located q / (1 - q), q = exp(-t^2 / (2 sigma^2)), each at E[r | r > t] = t + sigma
    sqrt(pi / 2) erfcx(t / (sigma sqrt 2)) (Rayleigh). Nothing where sigma is not a positive number."""
    from scipy.special import erfcx

    ok = np.isfinite(sig) & (sig > 0)
    sig = np.where(ok, sig, 1.0)
    with np.errstate(over="ignore"):
        n = np.where(ok, located / np.expm1(t * t / (2 * sig * sig)), 0.0)
    return n, n * (t + sig * math.sqrt(math.pi / 2) * erfcx(t / (sig * math.sqrt(2))))


def corner_model(found, displaced, displaced_r, located, loc_dof, loc2, t: float, mismatch: bool = True,
                 rounds: int = 5):
    """(sigma, fraction, radius, displaced) of the corner stages from a verification's sums (arrays: the same
    for every bootstrap replicate). The two laws overlap: the localisation normal's tail beyond t is counted
    among the displaced corners, and the mismatches that land within t among the located ones (r^2 about
    uniform over that disc, mean t^2 / 2), and the displaced corners' distances carry the localisation error
    too (their mean grows by sigma^2 / (R + t)). Each is estimated with the other's share taken off, a few rounds
    from none (a fixed point, reached in three or four). Without `mismatch` (too few displaced corners) no
    mismatch share is taken off the located ones."""
    found, displaced, displaced_r, located, loc_dof, loc2 = (np.asarray(a, float) for a in
                                                             (found, displaced, displaced_r, located, loc_dof, loc2))
    inside, blur = np.zeros_like(found), np.zeros_like(found)
    with np.errstate(invalid="ignore", divide="ignore"):
        for _ in range(rounds):
            n_loc = np.maximum(located - inside, 1e-12)
            sig = truncated_sigma(np.maximum(loc2 - inside * t * t / 2, 0.0) / np.maximum(loc_dof - inside, 1e-12), t)
            n_tail, r_tail = _tails(sig, n_loc, t)
            d = np.maximum(displaced - n_tail, 0.0)
            mean_r = np.where(d > 0, np.maximum(displaced_r - r_tail, 0.0) / np.maximum(d, 1e-12), t)
            R = disc_radius(np.maximum(mean_r - blur, t), t)
            # a mismatched corner is placed by the localisation error too: |p + n| is |p| + sigma^2 / (2 |p|)
            # on average, and 1 / |p| averages 2 / (R + t) over the disc beyond t
            blur = np.where(np.isfinite(sig), sig * sig, 0.0) / (R + t)
            share = np.clip((t / R) ** 2, 0.0, 1.0 - 1e-9)
            frac = d / found / (1 - share)
            if not mismatch:
                break
            inside = np.minimum(d * share / (1 - share), located)
    return sig, frac, R, d


def _correlation(col, seed: int) -> Estimate:
    """corner_error.correlation: sum(l r) / sqrt(sum(l^2) sum(r^2)) of the residuals of the corners located in
    both images of the stereo pairs, clipped to [0, 1] (the effect's range)."""
    key = "corner_error.correlation"
    if col["pairs"].sum() < MIN["located"]:
        return Estimate(key, None, note=f"fewer than {MIN['located']} corners located in both images of a stereo "
                                        "pair")

    def value(lr, ll, rr):
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.clip(lr / np.sqrt(ll * rr), 0.0, 1.0)

    keys = ("pair_lr", "pair_ll", "pair_rr")
    v = float(value(*(col[k].sum() for k in keys)))
    W = _weights(len(col["pairs"]), seed, key)
    lo, hi = _interval(np.asarray(value(*(W @ col[k] for k in keys)), float), v, int((col["pairs"] > 0).sum()))
    return Estimate(key, v, lo, None if hi is None else min(hi, 1.0),
                    f"of the two cameras' residuals at {int(col['pairs'].sum())} corners located in both images")


def _corner_estimates(col, seed: int, t: float) -> list[Estimate]:
    """corner_error.sigma, corner_mismatch.fraction and .radius, from the one model of both (corner_model), and
    corner_error.correlation."""
    found, disp = col["found"], col["displaced"]
    keys = ("corner_error.sigma", "corner_mismatch.fraction", "corner_mismatch.radius")
    if found.sum() < MIN["corners"]:
        return [Estimate(k, None, note="too few found corners") for k in (*keys, "corner_error.correlation")]
    mismatch = disp.sum() >= MIN["displaced"]
    args = ("found", "displaced", "displaced_r", "located", "loc_dof", "loc2")
    sig, f, R, d = (float(x) for x in corner_model(*(col[a].sum() for a in args), t, mismatch))
    W = _weights(len(found), seed, "corner_mismatch")
    sig_b, f_b, R_b, _ = corner_model(*(W @ col[a] for a in args), t, mismatch)
    k = int((found > 0).sum())
    rms = math.sqrt(col["loc2"].sum() / col["loc_dof"].sum()) if col["loc_dof"].sum() > 0 else float("nan")
    if col["located"].sum() < MIN["located"]:
        out = [Estimate(keys[0], None, note=f"fewer than {MIN['located']} found corners within {t:g} px")]
    elif not math.isfinite(sig):
        out = [Estimate(keys[0], None, note=f"the corners within {t:g} px are spread as if uniformly (RMS "
                                            f"{rms:.3g} px): widen --inlier")]
    else:
        out = [Estimate(keys[0], sig, *_interval(sig_b, sig, k),
                        f"from {int(col['located'].sum())} found corners within {t:g} px of the model's (RMS "
                        f"{rms:.3g} px; each image's affine map of them taken off where it has 20 or more), a normal "
                        "truncated there"
                        + (", less the mismatches landing there" if mismatch else ""))]
    out.append(_correlation(col, seed))
    tail = disp.sum() - d
    tail_note = f", {tail:.3g} of them the localisation error's tail" if tail > 0 else ""
    if not mismatch or d < 1:
        n = int(disp.sum())
        out += [Estimate(keys[1], float(d / found.sum()), *exact_binomial(d, found.sum()),
                         f"{n} of {int(found.sum())} found corners displaced beyond {t:g} px{tail_note} "
                         "(interval: exact binomial)"),
                Estimate(keys[2], None, note=f"fewer than {MIN['displaced']} displaced corners" if not mismatch
                         else "no displaced corners beyond the localisation error's")]
        return out
    flo, fhi = _interval(np.minimum(f_b, 1.0), min(f, 1.0), k)
    mean_r = float(col["displaced_r"].sum() / disp.sum())
    return out + [
        Estimate(keys[1], min(f, 1.0), flo, None if fhi is None else min(fhi, 1.0),
                 f"{int(disp.sum())} of {int(found.sum())} found corners displaced beyond {t:g} px{tail_note}, "
                 "corrected for the moves shorter than that"),
        Estimate(keys[2], R, *_interval(R_b, R, k), f"from the displaced corners' distances (mean {mean_r:.3g} "
                                                    "px; uniform over the disc)")]
