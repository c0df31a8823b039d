"""Stereo match error: features near-parallel to epipolar lines are lost, a few of the rest shift along them."""

from __future__ import annotations

import math

from .base import Effect, Params, param


class StereoMismatchParams(Params):
    band: float = param(math.radians(5.0), "angle", "features within this angle of the epipolar line are dropped",
                        ge=0, le=math.pi / 2)
    fraction: float = param(0.01, "fraction", "fraction of remaining features mismatched", ge=0, le=1)
    disparity: float = param(20.0, "image", "disparity search range either side", ge=0, le=10000)


class StereoMismatch(Effect):
    name = "stereo_mismatch"
    acts_on = "stereo"
    Params = StereoMismatchParams
    doc = __doc__
