"""Corner localisation noise that grows away from the image centre (a numpy-only effect).

A corner detector's error grows towards the image border, where blur, vignetting and lens distortion are
largest. Each corner moves by an isotropic Gaussian whose standard deviation is
sigma * (1 + gain * (r / r_max)^2), with r its distance from the image centre and r_max the half diagonal.
There is no compiled kernel: a pipeline with this stage runs on wiredsl's numpy engine, and the manifest says so.
"""

from __future__ import annotations

import numpy as np

from wiredsl import Effect
from wiredsl.effects.base import Params, param
from wiredsl.engine import imageset as im


class RadialCornerNoiseParams(Params):
    sigma: float = param(0.3, "image", "standard deviation at the image centre", ge=0, le=1000)
    gain: float = param(2.0, "number", "extra standard deviation at the image corners, in units of sigma",
                        ge=0, le=1000)


class RadialCornerNoise(Effect):
    name = "radial_corner_noise"
    acts_on = "corner detection"
    Params = RadialCornerNoiseParams
    doc = __doc__

    @classmethod
    def is_identity(cls, p: RadialCornerNoiseParams) -> bool:
        return p.sigma == 0

    @classmethod
    def disturb(cls, p: RadialCornerNoiseParams, s: im.ImageSet, ctx) -> im.ImageSet:
        w, h = ctx.camera.width, ctx.camera.height
        centre = np.array([w / 2.0, h / 2.0])
        r2 = ((s.corners - centre) ** 2).sum(axis=1) / (w * w / 4.0 + h * h / 4.0)
        sd = p.sigma * (1.0 + p.gain * r2)
        move = ctx.draws(cls.name, s.corner_trial, 2, normal=True) * sd[:, None]
        ctx.stats.add(cls.name, count=len(sd), sum_sq=float((move**2).sum()))
        return im.replace(s, corners=s.corners + move)

    @classmethod
    def report(cls, p: RadialCornerNoiseParams, stats) -> dict:
        s = stats.sums[cls.name]
        rms = float(np.sqrt(s["sum_sq"] / (2 * s["count"]))) if s["count"] else None
        return {"rms_per_axis_px": {"declared_at_centre": p.sigma, "measured": rms}}
