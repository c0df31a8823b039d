"""Edge detection loss: a fraction of every visible feature's length goes undetected.

Each feature loses exactly `fraction` of its length as one gap placed uniformly
at random along it, leaving up to two fragments (`fragment` 0 and 1). A closed
curve loses one arc and remains one fragment. Corners are untouched. With
`spread`, each view's fraction is drawn from a Beta of that mean and standard
deviation, and with `feature_spread` each feature's from a Beta about its view's;
with `correlation` (metres along the path), each feature's gap and
the view's fraction persist from pose to pose (wiredsl.effects.variation).
"""

from __future__ import annotations

import numpy as np
from pydantic import model_validator

from wiredsl.effects import variation as var
from wiredsl.effects.base import Context, Effect, KernelStage, Params, Stats, param
from wiredsl.engine import imageset as im


class EdgeLossParams(Params):
    fraction: float = param(0.29, "fraction", "fraction of each feature's length removed (Canny finds 71%)", ge=0, le=1)
    spread: float = param(0.0, "fraction", "standard deviation of the fraction between views (a Beta; 0: fixed)",
                          ge=0, le=0.5)
    correlation: float = param(0.0, "length", "distance along the path over which a feature's loss and the "
                               "view's fraction persist (exp(-d / correlation); 0: independent poses)", ge=0, le=1e6)
    feature_spread: float = param(0.0, "fraction", "standard deviation of the fraction between a view's features "
                                  "(a Beta about the view's; 0: every feature loses the same)", ge=0, le=0.5)
    _dump = var.unchanged_when_fixed("feature_spread")  # a stage without them dumps as before they existed

    @model_validator(mode="after")
    def _spread_fits(self):
        var.check_fraction_spread("fraction", self.fraction, self.spread)
        return self

    @classmethod
    def plain_after(cls, values: dict) -> None:
        """_spread_fits on plain values (scene.plainly_valid: the compiler then builds no validator)."""
        var.check_fraction_spread("fraction", values["fraction"], values["spread"])


class EdgeLoss(Effect):
    name = "edge_loss"
    acts_on = "edges"
    kernel = KernelStage("wiredsl.effects.edge_loss_kernel:stage",
                         ("fraction", "spread", "correlation", "feature_spread"),
                         (("total_length", "add"), ("kept_length", "add")), path=True)
    Params = EdgeLossParams
    doc = __doc__

    @classmethod
    def is_identity(cls, p: EdgeLossParams) -> bool:
        return p.fraction == 0

    @classmethod
    def disturb(cls, p: EdgeLossParams, s: im.ImageSet, ctx: Context) -> im.ImageSet:
        closed = s.closed.copy()
        s = im.unroll_closed(s)
        _, L = im.arc_lengths(s)
        L = np.where(closed, L / 2, L)  # an unrolled closed stroke is traversed twice
        if var.varies(p):
            u = var.item_uniforms(ctx, cls.name, p, s.trial, var.stroke_items(s.fid, s.fragment)) \
                if var.along_path(p) else ctx.draws(cls.name, s.trial)[:, 0]
            fraction = var.view_magnitudes(ctx, cls.name, p, p.fraction, "fraction")[s.trial]
            if p.feature_spread > 0:
                counts = np.bincount(s.trial, minlength=len(ctx.trials))
                slot = np.arange(s.n_strokes) - (np.cumsum(counts) - counts)[s.trial]
                fraction = var.feature_magnitudes(ctx, cls.name, p, s.trial, slot, var.stroke_items(s.fid, s.fragment),
                                                  fraction, p.feature_spread)
        else:
            u, fraction = ctx.draws(cls.name, s.trial)[:, 0], p.fraction
        gap = fraction * L
        g0 = u * np.where(closed, L, L - gap)  # where the gap starts
        k = np.arange(s.n_strokes)
        # open: [0, g0] and [g0 + gap, L]; closed: the single arc [g0 + gap, g0 + L]
        stroke = np.concatenate([k[~closed], k[~closed], k[closed]])
        a = np.concatenate([np.zeros((~closed).sum()), (g0 + gap)[~closed], (g0 + gap)[closed]])
        b = np.concatenate([g0[~closed], L[~closed], (g0 + L)[closed]])
        frag = np.concatenate([np.zeros((~closed).sum(), int), np.ones((~closed).sum(), int),
                               np.zeros(closed.sum(), int)])
        order = np.lexsort((frag, stroke))
        out = im.keep_intervals(s, stroke[order], a[order], b[order], frag[order])
        ctx.add(cls.name, s.trial, total_length=L)
        ctx.add(cls.name, out.trial, kept_length=im.arc_lengths(out)[1])
        return out

    @classmethod
    def report(cls, p: EdgeLossParams, stats: Stats) -> dict:
        s = stats.sums[cls.name]
        removed = 1 - s["kept_length"] / s["total_length"] if s["total_length"] else 0.0
        return {"removed_length_fraction": {"declared": p.fraction, "measured": removed}}
