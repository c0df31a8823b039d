"""Corner localisation error: every detected corner moves by an isotropic 2D Gaussian.

A corner detector places a corner it finds a fraction of a pixel from where the corner is (Harris's response
peak, a sub-pixel fit to it, the blur and the noise), independently in each camera. The paper's pipeline has no
such stage; without it a simulated stereo pair triangulates its corners exactly. `wiredsl verify --fit`
measures it, from the found corners within the inlier distance of the model's. The default, 0.17 px, is what
it measured for OpenCV's Harris with sub-pixel refinement on OpenCV's stereo chessboard images
(docs/scripts/verify_opencv_stereo.py).
"""

from __future__ import annotations

import numpy as np

from wiredsl.effects.base import Context, Effect, KernelStage, Params, Stats, param
from wiredsl.engine import imageset as im


class CornerErrorParams(Params):
    sigma: float = param(0.17, "image", "standard deviation of a corner's position, per axis", ge=0, le=100)


class CornerError(Effect):
    name = "corner_error"
    acts_on = "corner detection"
    kernel = KernelStage("wiredsl.effects.corner_error_kernel:stage", ("sigma",),
                         (("count", "add"), ("sum_sq", "add")))
    Params = CornerErrorParams
    doc = __doc__

    @classmethod
    def is_identity(cls, p: CornerErrorParams) -> bool:
        return p.sigma == 0

    @classmethod
    def disturb(cls, p: CornerErrorParams, s: im.ImageSet, ctx: Context) -> im.ImageSet:
        noise = p.sigma * ctx.draws(cls.name, s.corner_trial, 2, normal=True)
        ctx.add(cls.name, s.corner_trial, count=np.full(len(noise), 2), sum_sq=noise**2)
        return im.replace(s, corners=s.corners + noise)

    @classmethod
    def report(cls, p: CornerErrorParams, stats: Stats) -> dict:
        s = stats.sums[cls.name]
        return {"sigma_px": {"declared": p.sigma, "measured": float(np.sqrt(s["sum_sq"] / max(s["count"], 1)))}}
