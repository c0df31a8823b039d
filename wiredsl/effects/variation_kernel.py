"""The compiled (numba) transcription of wiredsl.effects.variation: the same draws, arithmetic and order.

A stage that varies takes its parameters row as KernelStage.params in order, then (when it declares `path`)
the view's pose index and the path's rho table (montecarlo.stage_rows; zero-padded: a pose beyond the table
renews at itself, as the numpy code's does)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from wiredsl.effects.variation import (
    FEATURE,
    GAMMA_BOOST,
    GAMMA_U,
    ITEM_SLOTS,
    MAG,
    POSE,
    REN,
    SECOND,
    VAL,
    VIEW_ITEM,
)
from wiredsl.engine.kernel import _bits, _normal_pair, _uniform

_MAG, _SECOND = np.uint64(MAG), np.uint64(SECOND)
_GU, _GB = np.uint64(GAMMA_U), np.uint64(GAMMA_BOOST)
_FEATURE = np.uint64(FEATURE)
_REN, _VAL, _POSE, _VIEW = np.uint64(REN), np.uint64(VAL), np.uint64(POSE), np.int64(VIEW_ITEM)


@njit(cache=True)
def gamma(key, a, base):
    """variation.keyed_gamma for one key."""
    boost = a < 1
    aa = a + 1 if boost else a
    d = aa - 1.0 / 3.0
    c = 1.0 / math.sqrt(9.0 * d)
    attempt = np.uint64(0)
    while True:
        z = _normal_pair(key, (base + np.uint64(2) * attempt) >> np.uint64(1))[0]
        u = _uniform(key, base + _GU + attempt)
        v = 1.0 + c * z
        v3 = v * v * v
        if v > 0 and (u <= 0 or math.log(u) < 0.5 * z * z + d - d * v3 + d * math.log(v3)):
            g = d * v3
            break
        attempt += np.uint64(1)
    if boost:
        g = g * _uniform(key, base + _GB) ** (1.0 / a)
    return g


@njit(cache=True)
def magnitude(key, value, spread, fraction):
    """variation.magnitude for one key (fraction: the Beta, else the Gamma)."""
    if spread <= 0:
        return value
    if fraction:
        nu = value * (1 - value) / (spread * spread) - 1
        ga = gamma(key, value * nu, _MAG)
        gb = gamma(key, (1 - value) * nu, _MAG + _SECOND)
        total = ga + gb
        return ga / total if total > 0 else value
    if value <= 0:
        return 0.0
    return gamma(key, value * value / (spread * spread), _MAG) * (spread * spread / value)


@njit(cache=True)
def pose_key(key, pose):
    return _bits(key, np.uint64(pose) + _POSE)


@njit(cache=True)
def value_key(key, item, pose, rho):
    """variation.value_keys for one item: its last renewal's pose key (rho: the path's table, zero-padded)."""
    k = pose
    if k > 0 and k < len(rho):
        while k > 0:
            r = _uniform(pose_key(key, k), np.uint64(item) + _REN)
            if r < rho[k]:
                k -= 1
            else:
                break
    return pose_key(key, k)


@njit(cache=True)
def view_magnitude(key, value, spread, fraction, pose, rho, persistent):
    """variation.view_magnitudes for one view of one trial."""
    if spread <= 0:
        return value
    if persistent:
        key = value_key(key, _VIEW, pose, rho)
    return magnitude(key, value, spread, fraction)


@njit(cache=True)
def item_uniform(key, item, pose, rho):
    """variation.item_uniforms for one item."""
    return _uniform(value_key(key, item, pose, rho), np.uint64(item) + _VAL)


@njit(cache=True)
def feature_magnitude(key, item, slot, mean, spread, pose, rho, persistent):
    """variation.feature_magnitudes for one stroke (slot: its index in the trial)."""
    sd = min(spread, 0.95 * math.sqrt(max(mean * (1 - mean), 0.0)))
    if not (sd > 0 and mean > 0 and mean < 1):
        return mean
    if persistent:
        key = value_key(key, item, pose, rho)
        base = _FEATURE
    else:
        base = _FEATURE + np.uint64(slot) * np.uint64(2**21)
    nu = mean * (1 - mean) / (sd * sd) - 1
    ga = gamma(key, mean * nu, base)
    gb = gamma(key, (1 - mean) * nu, base + _SECOND)
    total = ga + gb
    return ga / total if total > 0 else mean


@njit(cache=True)
def stroke_item(fid, fragment):
    f = fragment + 1
    return fid * ITEM_SLOTS + min(max(f, 0), ITEM_SLOTS - 1)
