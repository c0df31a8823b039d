"""A study's plots (matplotlib, imported only here): each statistic against each varied parameter
with 95% confidence bands, and for space-filling designs the Sobol' indices as bars."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np

from wiredsl import install_hint
from wiredsl.files import write_atomic
from wiredsl.scene import Study
from wiredsl.study.report import StudyTable

Z95 = 1.959963984540054
MAX_LINES = 6  # a grid's other factors beyond this many combinations are averaged over


def _pyplot():
    try:
        import matplotlib
    except ImportError as exc:
        raise RuntimeError(f"plots need matplotlib: {install_hint('plot')}, or run with --no-plots") from exc
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


FORMATS = ("png", "svg", "pdf")
DPI = 150  # the default raster resolution; SVG and PDF are vector (dpi sizes only embedded rasters)
SOBOL_LIMITS = (-0.5, 1.5)  # indices are shares of variance: a heavy-tailed statistic's wild estimate is cut here


def _save(fig, path: Path, fmt: str, dpi: int) -> None:
    """The figure as `fmt` bytes, written atomically; no date or software stamp, so reruns give equal files."""
    import io

    import matplotlib

    meta = {"png": {"Software": None}, "svg": {"Date": None}, "pdf": {"CreationDate": None, "Producer": None}}[fmt]
    buf = io.BytesIO()
    with matplotlib.rc_context({"svg.hashsalt": "wiredsl", "svg.fonttype": "none"}):
        fig.savefig(buf, format=fmt, dpi=dpi, metadata=meta)
    write_atomic(path, buf.getvalue())


def units_of(study: Study) -> dict[str, str]:
    """{"measure.statistic": unit} from the measures' declarations (`Measure.units`)."""
    from wiredsl.language.compile_study import measure_registry

    registry = measure_registry()
    return {f"{m.name}.{stat}": unit for m in study.measures
            for stat, unit in (getattr(registry.get(m.name), "units", None) or {}).items()}


def write_all(table: StudyTable, study: Study, folder: Path, fmt: str = "png", dpi: int = DPI,
              units: dict[str, str] | None = None) -> list[str]:
    """Every plot of the study into `folder` as `fmt` (png, svg or pdf); returns the written names."""
    plt = _pyplot()
    units = units_of(study) if units is None else units
    written = []
    stats = list(dict.fromkeys((r.measure, r.statistic) for r in table.rows))
    # a grid's factor of one value (a setting the study holds, as its speed study's 30 ms readouts) has no panel
    # and no legend entry: the title states it
    held = [f for f in table.factors if study.design == "grid" and len({r.values[f] for r in table.rows}) == 1]
    factors = [f for f in table.factors if f not in held]
    at = ("\nheld at " if held else "") + ", ".join(
        f"{f}={table.rows[0].values[f]:g}{(' ' + _unit(f)) if _unit(f) else ''}" for f in held)
    for measure, stat in stats:
        if not factors:
            break
        rows = [r for r in table.rows if (r.measure, r.statistic) == (measure, stat)]
        d = len(factors)
        cols = min(d, 4)
        fig, axes = plt.subplots(-(-d // cols), cols, figsize=(4.2 * cols, 3.3 * -(-d // cols)), squeeze=False,
                                 layout="constrained")  # room for every label and the title, none cut or overlapping
        unit = units.get(f"{measure}.{stat}")
        span = statistic_range(unit, [r.mean for r in rows])
        for ax, f in itertools.zip_longest(axes.ravel(), factors):
            if f is None:
                ax.axis("off")
                continue
            (_grid if study.design == "grid" else _scatter)(ax, rows, f, factors, span)
            ax.set_xlabel(_label(f), fontsize=8)
            ax.set_ylabel(_words(stat) + (f" ({unit})" if unit else ""))
            ax.grid(alpha=0.3)
        fig.suptitle(f"{_measure_words(measure)}: {_words(stat)}" + (f" ({unit})" if unit else "")
                     + f"\nmean and 95% band, study {table.study} ({measure}.{stat}){at}", fontsize=10)
        name = f"{measure}.{stat}.{fmt}"
        _save(fig, folder / name, fmt, dpi)
        plt.close(fig)
        written.append(f"plots/{name}")
    if table.sobol:
        written.append(_sobol(plt, table, stats, folder, fmt, dpi))
    return written


def _unit(factor: str) -> str:
    """The SI unit of the factor's kind (the unit the table's values are in), or "" for a plain number."""
    from wiredsl.effects import REGISTRY
    from wiredsl.language.compile_study import CAMERA_FACTORS, MOTION_FACTORS

    stage, param = factor.rsplit(".", 1)
    if stage.startswith("camera."):
        kind = CAMERA_FACTORS[param][0]
    elif factor in MOTION_FACTORS:
        kind = MOTION_FACTORS[factor][0]
    else:
        kind = (REGISTRY[stage].Params.model_fields[param].json_schema_extra or {}).get("kind")
    return {"image": "px", "angle": "rad", "length": "m", "time": "s", "speed": "m/s"}.get(kind, "")


def _words(name: str) -> str:
    """A code name in words: error_mean -> error mean."""
    return name.replace("_", " ")


def _measure_words(measure: str) -> str:
    """A measure in words: the lead of its doc's first line (up to a colon or comma), else its name."""
    from wiredsl.language.compile_study import measure_registry

    cls = measure_registry().get(measure)
    first = ((getattr(cls, "doc", None) or "").strip().splitlines() or [""])[0]
    lead = first.split(":")[0].split(",")[0].strip().rstrip(".")
    return lead if 0 < len(lead) <= 60 else _words(measure)


def _description(factor: str) -> str | None:
    """A factor's parameter as its declaration describes it (an effect's Params field, a camera factor)."""
    from wiredsl.effects import REGISTRY
    from wiredsl.language.compile_study import CAMERA_FACTORS, MOTION_FACTORS

    stage, param = factor.rsplit(".", 1)
    if stage.startswith("camera."):
        return CAMERA_FACTORS[param][2] if param in CAMERA_FACTORS else None
    if factor in MOTION_FACTORS:
        return MOTION_FACTORS[factor][1]
    field = REGISTRY[stage].Params.model_fields.get(param)
    return field.description if field is not None else None


LABEL_WIDTH = 56  # characters of an x label's line at fontsize 8 on a 4.2-inch axis


def _label(factor: str) -> str:
    """The factor in words (its stage, its parameter's description) with its unit, and its code name below, for
    an axis."""
    unit = _unit(factor)
    stage = factor.rsplit(".", 1)[0]
    what = _description(factor)
    if not what:
        return f"{factor} ({unit})" if unit else factor
    import textwrap

    text = f"{_words(stage.replace('camera.', 'camera '))}: {what}" + (f" ({unit})" if unit else "")
    return textwrap.fill(text, LABEL_WIDTH) + f"\n{factor}"  # wrapped to the 4.2-inch axis


def statistic_range(unit: str | None, means) -> tuple[float, float]:
    """Where a statistic's values can lie, for clipping its bands: a fraction in [0, 1], a count at or above 0,
    and a length, pixel or angle statistic at or above 0 when every mean of it is (an error's size, never a
    signed bias that happens to be positive: a negative mean shows it is signed)."""
    if unit == "fraction":
        return 0.0, 1.0
    if unit == "count" or (unit in ("m", "px", "rad") and all(m >= 0 for m in means)):
        return 0.0, math.inf
    return -math.inf, math.inf


def _grid(ax, rows, f: str, factors: list[str], span=(-math.inf, math.inf)) -> None:
    """One line per combination of the other factors (averaged over them when there are too many)."""
    others = [g for g in factors if g != f]
    combos = sorted({tuple(r.values[g] for g in others) for r in rows})
    if len(combos) > MAX_LINES:
        combos, others = [()], []
    for combo in combos:
        sel = [r for r in rows if tuple(r.values[g] for g in others) == combo]
        xs = sorted({r.values[f] for r in sel})
        mean = np.array([np.mean([r.mean for r in sel if r.values[f] == x]) for x in xs])
        sem = np.array([np.sqrt(np.mean([(r.sem or 0.0) ** 2 for r in sel if r.values[f] == x])) for x in xs])
        label = ", ".join(f"{g}={v:g}{(' ' + _unit(g)) if _unit(g) else ''}"
                          for g, v in zip(others, combo, strict=True)) or None
        line, = ax.plot(xs, mean, marker="o", ms=3, label=label)
        ax.fill_between(xs, np.clip(mean - Z95 * sem, *span), np.clip(mean + Z95 * sem, *span),
                        color=line.get_color(), alpha=0.2, lw=0)
    if others:
        ax.legend(fontsize=7)


def _scatter(ax, rows, f: str, factors: list[str], span=(-math.inf, math.inf)) -> None:
    """Each point's mean against this factor, and the mean over 8 bins of it with its 95% band."""
    x = np.array([r.values[f] for r in rows])
    y = np.array([r.mean for r in rows])
    ax.scatter(x, y, s=6, alpha=0.35, color="0.4", lw=0)
    edges = np.quantile(x, np.linspace(0, 1, 9))
    which = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, 7)
    mids, means, half = [], [], []
    for b in range(8):
        yb = y[which == b]
        if len(yb) >= 2:
            mids.append(x[which == b].mean())
            means.append(yb.mean())
            half.append(Z95 * yb.std(ddof=1) / np.sqrt(len(yb)))
    mids, means, half = map(np.array, (mids, means, half))
    line, = ax.plot(mids, means, marker="o", ms=3, color="C0")
    ax.fill_between(mids, np.clip(means - half, *span), np.clip(means + half, *span), color=line.get_color(),
                    alpha=0.25, lw=0)


def _sobol(plt, table: StudyTable, stats, folder: Path, fmt: str, dpi: int) -> str:
    fig = sobol_figure(plt, table, stats)
    _save(fig, folder / f"sobol.{fmt}", fmt, dpi)
    plt.close(fig)
    return f"plots/sobol.{fmt}"


def sobol_figure(plt, table: StudyTable, stats):
    """First-order and total indices of every statistic, one panel each, with bootstrap 95% intervals.

    Bars and intervals beyond SOBOL_LIMITS are cut there and marked with a triangle and their value; a
    negative first-order index (an estimate of a share near 0) is drawn downwards with its interval; an
    undefined index (a statistic constant over the design) is written as such in place of its bars.
    """
    lo_lim, hi_lim = SOBOL_LIMITS
    n = len(stats)
    cols = min(n, 3)
    nrows = -(-n // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(4.6 * cols, 3.4 * nrows), squeeze=False, layout="constrained")
    d = len(table.factors)
    for ax, shown_stat in itertools.zip_longest(axes.ravel(), stats):
        if shown_stat is None:  # a grid cell past the last statistic
            ax.axis("off")
            continue
        measure, stat = shown_stat
        idx = {s.factor: s for s in table.sobol if (s.measure, s.statistic) == (measure, stat)}
        pos = np.arange(d)
        shown = [0.0, 1.0]  # what the axis must hold: 0, 1, every value and interval (within the limits)
        for shift, key, colour in ((-0.2, "first_order", "C0"), (0.2, "total_order", "C1")):
            for i, f in enumerate(table.factors):
                s = idx.get(f)
                v = None if s is None else getattr(s, key)
                x = pos[i] + shift
                if v is None:
                    continue
                ci = getattr(s, key + "_ci")
                ax.bar(x, min(max(v, lo_lim), hi_lim), 0.4, color=colour,
                       label=("first order" if key == "first_order" else "total") if i == 0 else None)
                shown += [v] + (list(ci) if ci else [])
                if ci is not None:
                    a, b = max(ci[0], lo_lim), min(ci[1], hi_lim)
                    ax.plot([x, x], [a, b], color="0.15", lw=1)
                    for end, inside in ((a, ci[0] >= lo_lim), (b, ci[1] <= hi_lim)):
                        if inside:  # a cap; a cut end gets the triangle below instead
                            ax.plot([x - 0.07, x + 0.07], [end, end], color="0.15", lw=1)
                for beyond, edge, marker, va in ((v > hi_lim or (ci and ci[1] > hi_lim), hi_lim, "^", "bottom"),
                                                 (v < lo_lim or (ci and ci[0] < lo_lim), lo_lim, "v", "top")):
                    if beyond:  # cut at the axis limit: say so, with the value that does not fit
                        ax.plot(x, edge, marker=marker, color="C3", ms=6, clip_on=False, zorder=5)
                        far = v if (v > hi_lim or v < lo_lim) else (ci[1] if edge == hi_lim else ci[0])
                        ax.annotate(f"{far:.2g}", (x, edge), xytext=(0, 5 if va == "bottom" else -5),
                                    textcoords="offset points", ha="center", va=va, fontsize=6.5, color="C3",
                                    annotation_clip=False)
        if all(idx.get(f) is None or idx[f].first_order is None for f in table.factors):
            ax.text(0.5, 0.5, "undefined:\nthe statistic is constant\nover the design", ha="center", va="center",
                    fontsize=8, transform=ax.transAxes)
        low = max(min(shown), lo_lim)
        high = min(max(shown), hi_lim)
        pad = 0.08 * (high - low)
        ax.set_ylim(low - pad, high + pad)
        ax.set_xlim(-0.6, d - 0.4)
        ax.set_xticks(pos, [f.rsplit(".", 1)[0] for f in table.factors], rotation=35, ha="right", fontsize=7)
        ax.set_title(f"{measure}.{stat}", fontsize=9)
        ax.set_ylabel("Sobol' index (share of variance)", fontsize=8)
        ax.axhline(0, color="0.5", lw=0.5)
        ax.grid(axis="y", alpha=0.3)
    axes.ravel()[0].legend(fontsize=7)
    fig.suptitle(f"{table.study}: Sobol' indices (bootstrap 95%; ▲▼ cut at the axis limit)", fontsize=10)
    return fig
