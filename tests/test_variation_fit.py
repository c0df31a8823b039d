"""verify --fit's spreads between images and correlation along the sequence (variation_fit), on synthetic
per-image sums with a known spread and lag-1 correlation (the oracle), and the holdout split's names."""

from __future__ import annotations

import math

import numpy as np
import pytest

from wiredsl.verify import holdout
from wiredsl.verify import variation_fit as vf
from wiredsl.verify.fit import Fit


def _corner_images(rng, n, keep, spread, rho, corners=400):
    """Images of one camera along a sequence whose keep follows an AR(1) of lag-1 correlation rho about `keep`
    with sd `spread`; each image's found count binomial."""
    z = np.empty(n)
    z[0] = rng.normal()
    for i in range(1, n):
        z[i] = rho * z[i - 1] + math.sqrt(1 - rho * rho) * rng.normal()
    p = np.clip(keep + spread * z, 0, 1)
    return [vf.ImageExtras(side="left", corners=corners, found=float(rng.binomial(corners, q))) for q in p]


def test_the_spread_interval_holds_the_injected_spread_and_reaches_zero_when_none_is():
    rng = np.random.default_rng(4)
    held = clean = 0
    for k in range(40):
        spread = 0.05 if k % 2 == 0 else 0.0
        ex = _corner_images(rng, 30, 0.8, spread, 0.0)
        tau2, (lo, hi), _, _, n, _ = vf.spread_and_correlation(ex, list(range(0, 60, 2)), "corner_loss", seed=k)
        s, lo, hi = (math.sqrt(max(q, 0)) for q in (tau2, lo, hi))
        assert n == 30 and lo <= s <= hi and hi > lo  # never a zero-width interval
        if spread:
            held += lo <= spread <= hi
        else:
            clean += lo == 0
    assert held >= 17 and clean >= 17, (held, clean)  # 95% intervals: 19 of 20 expected


def test_the_spread_and_lag1_correlation_of_a_correlated_sequence_are_recovered():
    frames = 16
    """An AR(1) sequence of keep (sd 0.08, lag-1 correlation 0.8): the interval holds both in at least 17 of 20
    sequences, short and long."""
    rng = np.random.default_rng(9)
    held_t = held_r = 0
    for k in range(20):
        ex = _corner_images(rng, frames, 0.7, 0.08, 0.8, corners=2000)
        tau2, (lo, hi), r, (rlo, rhi), n, pairs = vf.spread_and_correlation(ex, list(range(frames)), "corner_loss",
                                                                            k)
        assert pairs == frames - 1
        held_t += lo <= 0.08**2 <= hi
        held_r += rlo <= 0.8 <= rhi
    assert held_t >= 17 and held_r >= 17, (held_t, held_r)


def test_the_fitted_pipeline_writes_a_spread_only_where_its_interval_excludes_zero():
    from wiredsl.verify.fit import Estimate

    rng = np.random.default_rng(1)
    for spread, written in ((0.08, True), (0.0, False)):
        ex = _corner_images(rng, 40, 0.8, spread, 0.0, corners=1000)
        f = Fit([Estimate("corner_loss.keep", 0.8, 0.79, 0.81)], None, {}, {}, 40)
        vf.add(f, ex, list(range(0, 80, 2)), [(0.05 * i, 0.0, 0.0) for i in range(80)], 0)  # not a sequence
        notes, more = vf.clauses(f, "corner_loss")
        assert ("spread" in more) == written, (spread, notes, more)
        if written:
            assert f.get("corner_loss.spread").lo > 0


@pytest.mark.parametrize(("text", "frames", "want"), [("odd", 5, [[1, 3]]), ("even", 4, [[0, 2]]),
                                                      ("kfold:3", 7, [[0, 3, 6], [1, 4], [2, 5]])])
def test_holdout_splits_by_frame(text, frames, want):
    assert holdout.parse_split(text, frames) == want


@pytest.mark.parametrize(("text", "message"), [("kfold:1", "K must be from 2"), ("half", "one of odd, even"),
                                               ("odd", "nothing to fit or to predict")])
def test_a_bad_holdout_split_is_a_usage_error(text, message):
    with pytest.raises(ValueError, match=message):
        holdout.parse_split(text, 1)


def test_a_held_out_image_is_placed_among_its_trials():
    sims = list(np.linspace(0, 1, 101))
    assert holdout.place(0.5, sims)["inside"] and holdout.place(0.5, sims)["percentile"] == pytest.approx(0.5)
    out = holdout.place(0.99, sims)
    assert not out["inside"] and out["band"] == pytest.approx([0.05, 0.95])
