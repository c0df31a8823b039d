"""Magnitudes that vary from view to view, and fates that persist along a path (issue 34, item 2).

An effect that declares `spread` draws its magnitude once a view (a trial, a pose and a camera) instead of using
the declared value:

- a **fraction** (edge_loss `fraction`, corner_loss `keep`) from a Beta with the declared mean and standard
  deviation `spread`: it stays in [0, 1], its mean is exactly the declared value, and its two shapes follow from
  the mean and spread (a = f nu, b = (1 - f) nu, nu = f (1 - f) / spread^2 - 1), so a spread must be below
  sqrt(f (1 - f)); a truncated normal would move the mean, a logit-normal's mean has no closed form;
- a **non-negative magnitude** (lateral_shift `range`) from a Gamma with the declared mean and standard
  deviation (shape m^2 / s^2, scale s^2 / m): it stays >= 0 with the declared mean, and it is drawn by the
  same sampler as the Beta's two Gammas (one piece of code for both; a log-normal would need its own).

Both are drawn by Marsaglia and Tsang's method (2000) from the stage's keyed stream at reserved draw indices,
so a trial's magnitude is a pure function of its keys, as every other draw is.

An effect that declares `correlation` (a length, metres along the path) makes each feature's draw (where its
gap lies, how far it shifts, whether its corner is kept) and the view's magnitude *persist* from pose to pose:
a stationary Markov chain over the path's poses that, between poses k - 1 and k, a distance d_k apart, keeps
its value with probability rho_k = exp(-d_k / correlation) and otherwise draws it afresh (a renewal). Its
marginal is exactly the independent draw's (a uniform stays uniform, a Beta stays that Beta), and two poses'
values are equal with probability prod rho = exp(-distance / correlation), so that the correlation of any
function of them is exactly exp(-distance / correlation): the AR(1) autocorrelation of a stationary process
sampled along the path. A feature's state therefore runs in stretches (of mean length correlation / step),
as a real detector's losses do from frame to frame.

The draws stay keyed: a persistent stage's stream is keyed without the pose (`stream_key(..., pose=-1, ...)`),
pose k's draws come from `keyed_bits(key, POSE + k)`, a renewal at pose k from that key's draw REN + item, and
the value from its draw VAL + item; the value at pose p is found by walking back from p to its last renewal
(pose 0 always is one), so a trial still replays alone and a subset of the path's poses draws what the whole
path draws at them. The compiled kernel (variation_kernel.py) does the same arithmetic in the same order.
"""

from __future__ import annotations

import math

import numpy as np

from wiredsl.effects.base import CAMERA_INDEX, keyed_bits, keyed_normal, keyed_uniform, stream_key

# reserved draw indices of a stage's stream (item draws use indices below 2**40)
MAG = 2**56  # the view's magnitude: its Gammas' normals (even indices MAG + 2 a), then the uniforms below
GAMMA_U = 2**44  # + base: a Gamma's acceptance uniforms (one an attempt)
GAMMA_BOOST = 2**45  # + base: the uniform that takes a Gamma of shape a + 1 to shape a < 1
SECOND = 2**48  # + MAG: the Beta's second Gamma
REN = 2**58  # + item: whether pose k renews the item's value
VAL = 2**59  # + item: the item's value drawn at pose k
POSE = 2**60  # + k: pose k's key from a persistent stage's key
FEATURE = 2**57  # + item slot * 2**21: a feature's own magnitude (its Gammas' draws, as MAG's)
VIEW_ITEM = 2**39  # the view's magnitude as a persistent item
ITEM_SLOTS = 16  # an item: feature id * 16 + fragment + 1 (the halves of a split ellipse are items of their own)


def unchanged_when_fixed(*more: str):
    """The Params serializer that leaves out `spread` and `correlation` (and `more`) while 0: a stage that
    declares none dumps (scene JSON, manifests) exactly as it did before they existed."""
    from wiredsl.scene import omitted_when_default

    return omitted_when_default(spread=0.0, correlation=0.0, **dict.fromkeys(more, 0.0))


def varies(p) -> bool:
    """Whether a stage's parameters declare a spread or a correlation (else it draws exactly as before)."""
    return getattr(p, "spread", 0.0) > 0 or getattr(p, "correlation", 0.0) > 0 or getattr(p, "feature_spread", 0) > 0


def along_path(p) -> bool:
    """Whether a stage's draws persist along the path (its stream is keyed without the pose)."""
    return getattr(p, "correlation", 0.0) > 0


def beta_shapes(mean: float, spread: float) -> tuple[float, float]:
    """The Beta's shapes (a, b) of a mean in (0, 1) and a standard deviation below sqrt(mean (1 - mean))."""
    nu = mean * (1 - mean) / (spread * spread) - 1
    return mean * nu, (1 - mean) * nu


def check_fraction_spread(name: str, mean: float, spread: float) -> None:
    """A located error's message (ValueError) where a fraction cannot have this spread."""
    if spread > 0 and not (0 < mean < 1 and spread * spread < mean * (1 - mean)):
        raise ValueError(f"spread {spread:g} of {name} {mean:g}: a fraction's spread must be below "
                         f"sqrt({name} (1 - {name})) = {np.sqrt(max(mean * (1 - mean), 0)):.4g}, with {name} "
                         "strictly between 0 and 1")


def path_coordinate(path) -> np.ndarray | None:
    """Distance along a path at each pose (metres): the cumulative length of the straight steps between the
    poses' positions (x, y of a floor path; the translation of a 6-DoF one). None without a path."""
    if path is None or not path.poses:
        return None
    if path.transforms is not None:
        xyz = np.array([[row[3] for row in T] for T in path.transforms], dtype=np.float64)
    else:
        xyz = np.array([[p[0], p[1]] for p in path.poses], dtype=np.float64)
    steps = np.sqrt(np.sum(np.diff(xyz, axis=0) ** 2, axis=1))
    return np.concatenate([[0.0], np.cumsum(steps)])


def persistence(path_s: np.ndarray | None, correlation: float) -> np.ndarray:
    """rho_k, the probability that pose k keeps pose k - 1's value (rho_0 = 0: pose 0 always draws afresh)."""
    if path_s is None or len(path_s) == 0 or correlation <= 0:
        return np.zeros(0)
    return np.concatenate([[0.0], np.exp(-np.diff(np.asarray(path_s, dtype=np.float64)) / correlation)])


# ----------------------------------------------------------------------------- the Gamma and Beta samplers

# libm's log and pow, as the compiled kernel calls them (numpy's own SIMD ones differ in the last bit now and
# then): a view's magnitude is the same double in both engines. Few calls (one a view and attempt).
_log = np.vectorize(lambda x: math.log(x) if x > 0 else -math.inf, otypes=[np.float64])
_pow = np.vectorize(math.pow, otypes=[np.float64])


def keyed_gamma(keys: np.ndarray, shape, base: int) -> np.ndarray:
    """Gamma(shape, 1) draws, one a key, by Marsaglia and Tsang (2000): attempt a takes the normal MAG-style
    index base + 2 a and the uniform base + GAMMA_U + a; a shape below 1 is drawn at shape + 1 and multiplied by
    u^(1 / shape), u the uniform base + GAMMA_BOOST."""
    keys = np.asarray(keys, dtype=np.uint64).ravel()
    return keyed_gamma_at(keys, shape, np.full(len(keys), base, dtype=np.uint64))


def keyed_gamma_at(keys: np.ndarray, shape, base: np.ndarray) -> np.ndarray:
    """keyed_gamma with a base index a key."""
    keys = np.asarray(keys, dtype=np.uint64).ravel()
    base = np.asarray(base, dtype=np.uint64).ravel()
    a = np.broadcast_to(np.asarray(shape, dtype=np.float64), keys.shape).copy()
    boost = a < 1
    aa = np.where(boost, a + 1, a)
    d = aa - 1.0 / 3.0
    c = 1.0 / np.sqrt(9.0 * d)
    out = np.empty(len(keys))
    todo = np.arange(len(keys))
    attempt = 0
    with np.errstate(divide="ignore", invalid="ignore"):
        while len(todo):
            kt, dt, bt = keys[todo], d[todo], base[todo]
            z = keyed_normal(kt, bt + np.uint64(2 * attempt))
            u = keyed_uniform(kt, bt + np.uint64(GAMMA_U + attempt))
            v = 1.0 + c[todo] * z
            v3 = v * v * v
            ok = (v > 0) & ((u <= 0) | (_log(u) < 0.5 * z * z + dt - dt * v3 + dt * _log(np.where(v > 0, v3, 1))))
            out[todo[ok]] = dt[ok] * v3[ok]
            todo, attempt = todo[~ok], attempt + 1
        if boost.any():
            u = keyed_uniform(keys[boost], base[boost] + np.uint64(GAMMA_BOOST))
            out[boost] = out[boost] * _pow(u, 1.0 / a[boost])
    return out


def magnitude(keys: np.ndarray, value: float, spread: float, kind: str) -> np.ndarray:
    """A view's magnitude from its key (one a view): the declared value itself without a spread; with one, a
    Beta (kind "fraction") or a Gamma (any other) of mean `value` and standard deviation `spread`."""
    keys = np.asarray(keys, dtype=np.uint64)
    if spread <= 0:
        return np.full(keys.shape, value)
    if kind == "fraction":
        a, b = beta_shapes(value, spread)
        ga, gb = keyed_gamma(keys, a, MAG), keyed_gamma(keys, b, MAG + SECOND)
        total = ga + gb
        return np.where(total > 0, ga / np.where(total > 0, total, 1.0), value)
    if value <= 0:
        return np.zeros(keys.shape)
    return keyed_gamma(keys, value * value / (spread * spread), MAG) * (spread * spread / value)


# ----------------------------------------------------------------------------- persistence along the path

def pose_key(keys: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Pose k's key of a persistent stage's (pose-free) key."""
    return keyed_bits(keys, np.asarray(pose, dtype=np.int64).astype(np.uint64) + np.uint64(POSE))


def value_keys(keys: np.ndarray, items: np.ndarray, poses: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """The key each item's value at its pose is drawn from: its last renewal's pose key (keys, items and poses
    aligned, (n,)). A pose outside the path (or a path of one pose) renews at itself."""
    keys = np.asarray(keys, dtype=np.uint64)
    items = np.asarray(items, dtype=np.int64).astype(np.uint64)
    k = np.asarray(poses, dtype=np.int64).copy()
    todo = np.flatnonzero((k > 0) & (k < len(rho)))
    while len(todo):
        kk = k[todo]
        r = keyed_uniform(pose_key(keys[todo], kk), items[todo] + np.uint64(REN))
        stay = r < rho[kk]  # not renewed at kk: the value is pose kk - 1's
        k[todo[stay]] -= 1
        todo = todo[stay & (kk - 1 > 0)]
    return pose_key(keys, k)


def stage_keys(ctx, stage: str, p) -> np.ndarray:
    """The stage's keys by batch index: pose-free when its draws persist along the path."""
    if not along_path(p):
        return ctx.keys(stage)
    cameras = ctx.cameras if getattr(ctx, "cameras", None) is not None else CAMERA_INDEX[ctx.side]
    return stream_key(stage, ctx.trials, -1, cameras, ctx.seed, ctx.point)


def batch_poses(ctx) -> np.ndarray:
    """The pose of each batch index."""
    poses = getattr(ctx, "poses", None)
    return np.asarray(poses if poses is not None else np.full(len(ctx.trials), ctx.pose), dtype=np.int64)


def view_magnitudes(ctx, stage: str, p, value: float, kind: str) -> np.ndarray:
    """The magnitude of each batch index's view (see `magnitude`), persistent along the path with a correlation."""
    spread = getattr(p, "spread", 0.0)
    if spread <= 0:
        return np.full(len(ctx.trials), value)
    keys = stage_keys(ctx, stage, p)
    if along_path(p):
        rho = persistence(getattr(ctx, "path_s", None), p.correlation)
        keys = value_keys(keys, np.full(len(keys), VIEW_ITEM), batch_poses(ctx), rho)
    return magnitude(keys, value, spread, kind)


def item_uniforms(ctx, stage: str, p, batch_index: np.ndarray, items: np.ndarray) -> np.ndarray:
    """Uniforms in [0, 1) for items (ids `items`, by batch index `batch_index`), persistent along the path."""
    keys = stage_keys(ctx, stage, p)
    rho = persistence(getattr(ctx, "path_s", None), p.correlation)
    batch_index = np.asarray(batch_index, dtype=np.int64)
    vk = value_keys(keys[batch_index], items, batch_poses(ctx)[batch_index], rho)
    return keyed_uniform(vk, np.asarray(items, dtype=np.int64).astype(np.uint64) + np.uint64(VAL))


def feature_magnitudes(ctx, stage: str, p, batch_index: np.ndarray, slots: np.ndarray, items: np.ndarray,
                       mean: np.ndarray, spread: float) -> np.ndarray:
    """Each feature's own fraction: a Beta about its view's (`mean`, per item) of sd `spread` (at most 0.95 of
    the widest a Beta of that mean takes), drawn from the stage's key at FEATURE + slot * 2**21 (slot: the
    stroke's index in its trial), or, persistent along the path, from the item's value key at FEATURE."""
    mean = np.asarray(mean, dtype=np.float64)
    sd = np.minimum(spread, 0.95 * np.sqrt(np.maximum(mean * (1 - mean), 0.0)))
    out = mean.copy()
    ok = (sd > 0) & (mean > 0) & (mean < 1)
    if not ok.any():
        return out
    keys = stage_keys(ctx, stage, p)[np.asarray(batch_index, dtype=np.int64)]
    if along_path(p):
        rho = persistence(getattr(ctx, "path_s", None), p.correlation)
        keys = value_keys(keys, items, batch_poses(ctx)[np.asarray(batch_index, dtype=np.int64)], rho)
        base = np.full(len(keys), FEATURE, dtype=np.uint64)
    else:
        base = np.uint64(FEATURE) + np.asarray(slots, dtype=np.uint64) * np.uint64(2**21)
    m, s = mean[ok], sd[ok]
    nu = m * (1 - m) / (s * s) - 1
    ga = keyed_gamma_at(keys[ok], m * nu, base[ok])
    gb = keyed_gamma_at(keys[ok], (1 - m) * nu, base[ok] + np.uint64(SECOND))
    total = ga + gb
    out[ok] = np.where(total > 0, ga / np.where(total > 0, total, 1.0), m)
    return out


def stroke_items(fid: np.ndarray, fragment: np.ndarray) -> np.ndarray:
    """A stroke's item id: its feature and its fragment (-1 whole, 0, 1, ... pieces)."""
    return np.asarray(fid, dtype=np.int64) * ITEM_SLOTS + np.clip(np.asarray(fragment, dtype=np.int64) + 1, 0,
                                                                  ITEM_SLOTS - 1)
