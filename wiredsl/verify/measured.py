"""The fitted pipeline as a `.wd` file (`verify --fit`'s measured.wd): each fitted stage with its interval and
what it was measured from in comments, the spread and correlation clauses of variation_fit, in canonical form."""

from __future__ import annotations

from wiredsl.language.fmt import format_text
from wiredsl.verify.fit import UNMEASURED, Estimate, Fit
from wiredsl.verify.variation_fit import clauses


def _num(x: float) -> str:
    return f"{x:.4g}"


def _pct(x: float) -> str:
    return f"{100 * x:.4g}%"


def pipeline_text(f: Fit, name: str, provenance: list[str], calibration: str | None = None,
                  with_calibration: bool = True) -> str:
    """The fitted pipeline as a `.wd` file (canonical form), intervals and provenance in comments.
    `calibration`: how the scene's rig declares its calibration's uncertainty (None: it does not); then the
    pipeline starts with `calibration_error sigma 1`, which draws the rigs with exactly that uncertainty, unless
    not `with_calibration` (the images calibrated the rig: their corners already fit it)."""
    def iv(e: Estimate, fmt) -> str:
        if e.value is None:
            return f"not estimated ({e.note}): " + ("not simulated" if e.key in UNMEASURED else "the paper's value")
        span = f", 95% interval [{fmt(e.lo)}, {fmt(e.hi)}]" if e.lo is not None else ""
        return f"{fmt(e.value)}{span}: {e.note}"

    lines = ["wiredsl 1", *[f"# {p}" for p in provenance], f"pipeline {name} {{"]
    if calibration is None:
        lines.append("  # calibration: the rig declares no uncertainty, so none is simulated")
    elif not with_calibration:
        lines.append(f"  # calibration: the rig declares its uncertainty ({calibration}), left out "
                     "(--no-calibration-error: these images calibrated the rig)")
    else:
        lines.append(f"  # calibration: the uncertainty the rig declares ({calibration}), not fitted here")
        lines.append("  calibration_error sigma 1")
    e = f.get("edge_loss.fraction")
    lines.append(f"  # edge loss {iv(e, _pct)}")
    if f.fragments:
        lines.append(f"  # fragments: {f.fragments['runs_per_stroke']:.3g} verified runs a stroke over "
                     f"{f.fragments['strokes']} strokes (the effect's one gap leaves 2)")
    notes, more = clauses(f, "edge_loss")  # spread between images, correlation along them (variation_fit)
    lines += notes
    lines.append(f"  edge_loss fraction {_pct(e.used)}{more}")
    e = f.get("lateral_shift.range")
    lines.append(f"  # lateral shift range {iv(e, lambda x: _num(x) + ' px')}")
    if f.shift_law and f.shift_law.get("better"):
        law = f.shift_law
        lines.append(f"  # law of the shifts: {law['better']} fits better (Kolmogorov-Smirnov D uniform "
                     f"{law['ks_uniform']['D']:.3g} p {law['ks_uniform']['p']:.3g}, normal {law['ks_normal']['D']:.3g} "
                     f"p {law['ks_normal']['p']:.3g}; parameters fitted from the same {law['n']} strokes)")
    notes, more = clauses(f, "lateral_shift")
    lines += notes
    lines.append(f"  lateral_shift range {_num(e.used)}px{more}")
    e = f.get("approx_error.sigma")
    lines.append(f"  # approximation error sigma {iv(e, lambda x: _num(x) + ' px')}")
    lines.append(f"  approx_error sigma {_num(e.used)}px")
    e = f.get("corner_loss.keep")
    lines.append(f"  # corner keep {iv(e, _pct)}")
    notes, more = clauses(f, "corner_loss")
    lines += notes
    lines.append(f"  corner_loss keep {_pct(e.used)}{more}")
    e, r = f.get("corner_error.sigma"), f.get("corner_error.correlation")
    if e.value is None:
        lines.append(f"  # corner localisation error not estimated ({e.note}): no corner_error stage")
    else:
        lines.append(f"  # corner localisation error sigma {iv(e, lambda x: _num(x) + ' px')}")
        if r.value is None:
            lines.append(f"  # its correlation between the cameras not estimated ({r.note}): taken as 0, "
                         "independent")
        else:
            lines.append(f"  # its correlation between the cameras {iv(r, _num)}")
        notes, more = clauses(f, "corner_error")
        lines += notes
        lines.append(f"  corner_error sigma {_num(e.value)}px correlation {_num(r.value or 0.0)}{more}")
    ef, er = f.get("corner_mismatch.fraction"), f.get("corner_mismatch.radius")
    lines.append(f"  # corner mismatch fraction {iv(ef, _pct)}")
    lines.append(f"  # corner mismatch radius {iv(er, lambda x: _num(x) + ' px')}")
    if f.stereo.get("matched"):
        lines.append(f"  # stereo matcher (NCC within the radius): {f.stereo['wrong']} wrong of {f.stereo['matched']} "
                     "matched corners")
    else:
        lines.append("  # stereo matcher: no stereo pairs with corners, not measured")
    lines.append(f"  corner_mismatch fraction {_pct(ef.used)} radius {_num(er.used)}px")
    lines.append("}")
    text = "\n".join(line.replace("\n", " ") for line in lines) + "\n"
    return format_text(text)
