"""Corner localisation error: every detected corner moves by an isotropic 2D Gaussian, correlated between the
two cameras.

A corner detector places a corner it finds a fraction of a pixel from where the corner is (Harris's response
peak, a sub-pixel fit to it, the blur and the noise). The paper's pipeline has no such stage; without it a
simulated stereo pair triangulates its corners exactly. The two cameras see a corner alike, so their errors
are alike too: each axis's error is sqrt(rho) s + sqrt(1 - rho) e, s shared by the pair's views of the corner
and e the camera's own (standard normals, times sigma), so the two cameras' errors correlate by rho. What a
triangulation suffers is mostly their difference, sigma sqrt(2 (1 - rho)) an axis. `wiredsl verify --fit`
measures both. The defaults, 0.15 px and 0.43, are what it measured for OpenCV's Harris with sub-pixel
refinement on OpenCV's stereo chessboard images (docs/scripts/verify_opencv_stereo.py). With `spread`, each
stereo pair's sigma is drawn from a Gamma of that mean and standard deviation (wiredsl.effects.variation).
"""

from __future__ import annotations

import numpy as np

from wiredsl.effects import variation as var
from wiredsl.effects.base import Context, Effect, KernelStage, Params, Stats, keyed_normal, param
from wiredsl.engine import imageset as im
from wiredsl.scene import omitted_when_default


class CornerErrorParams(Params):
    sigma: float = param(0.15, "image", "standard deviation of a corner's position, per axis", ge=0, le=100)
    correlation: float = param(0.43, "fraction", "correlation of the two cameras' errors of a corner", ge=0, le=1)
    spread: float = param(0.0, "image", "standard deviation of sigma between stereo pairs (a Gamma, the same in "
                          "both cameras of a pair; 0: fixed)", ge=0, le=100)
    _dump = omitted_when_default(spread=0.0)  # a stage without it dumps as before it existed


class CornerError(Effect):
    name = "corner_error"
    acts_on = "corner detection"
    kernel = KernelStage("wiredsl.effects.corner_error_kernel:stage", ("sigma", "correlation", "spread"),
                         (("count", "add"), ("sum_sq", "add")), rig=True)
    Params = CornerErrorParams
    doc = __doc__

    @classmethod
    def is_identity(cls, p: CornerErrorParams) -> bool:
        return p.sigma == 0

    @classmethod
    def disturb(cls, p: CornerErrorParams, s: im.ImageSet, ctx: Context) -> im.ImageSet:
        # the rig's key, the same in both views; a corner's normals by its feature id: pair 3 f shared,
        # 3 f + 1 the left camera's own, 3 f + 2 the right's
        keys = ctx.keys(cls.name, rig=True)[s.corner_trial][:, None]
        pair = 3 * np.asarray(s.corner_fid, dtype=np.uint64)
        own = pair + 1 + ctx.right(s.corner_trial).astype(np.uint64)
        shared = keyed_normal(keys, 2 * pair[:, None] + np.arange(2, dtype=np.uint64))
        mine = keyed_normal(keys, 2 * own[:, None] + np.arange(2, dtype=np.uint64))
        if p.spread > 0:  # each pair's sigma, from the rig's key: the same in its two views
            sigma = var.magnitude(ctx.keys(cls.name, rig=True), p.sigma, p.spread, "image")[s.corner_trial][:, None]
            a, b = sigma * np.sqrt(p.correlation), sigma * np.sqrt(1.0 - p.correlation)
        else:
            a, b = p.sigma * np.sqrt(p.correlation), p.sigma * np.sqrt(1.0 - p.correlation)  # (as the kernel rounds)
        noise = a * shared + b * mine
        ctx.add(cls.name, s.corner_trial, count=np.full(len(noise), 2), sum_sq=noise**2)
        return im.replace(s, corners=s.corners + noise)

    @classmethod
    def report(cls, p: CornerErrorParams, stats: Stats) -> dict:
        s = stats.sums[cls.name]
        return {"sigma_px": {"declared": p.sigma, "measured": float(np.sqrt(s["sum_sq"] / max(s["count"], 1)))}}
