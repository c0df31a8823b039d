"""A study's plots (matplotlib, imported only here): each statistic against each varied parameter
with 95% confidence bands, and for space-filling designs the Sobol' indices as bars."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np

from wiredsl.io.files import write_atomic
from wiredsl.scene import Study
from wiredsl.study.report import StudyTable

Z95 = 1.959963984540054
MAX_LINES = 6  # a grid's other factors beyond this many combinations are averaged over


def _pyplot():
    try:
        import matplotlib
    except ImportError as exc:
        raise RuntimeError("plots need matplotlib: pip install 'wiredsl[plot]', or run with --no-plots") from exc
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, metadata={"Software": None})
    write_atomic(path, buf.getvalue())


def write_all(table: StudyTable, study: Study, folder: Path) -> list[str]:
    """Every plot of the study into `folder`; returns the written names."""
    plt = _pyplot()
    written = []
    stats = list(dict.fromkeys((r.measure, r.statistic) for r in table.rows))
    for measure, stat in stats:
        if not table.factors:
            break
        rows = [r for r in table.rows if (r.measure, r.statistic) == (measure, stat)]
        d = len(table.factors)
        cols = min(d, 4)
        fig, axes = plt.subplots(-(-d // cols), cols, figsize=(4.2 * cols, 3.3 * -(-d // cols)), squeeze=False)
        for ax, f in itertools.zip_longest(axes.ravel(), table.factors):
            if f is None:
                ax.axis("off")
                continue
            (_grid if study.design == "grid" else _scatter)(ax, rows, f, table.factors)
            ax.set_xlabel(_label(f))
            ax.set_ylabel(f"{measure}.{stat}")
            ax.grid(alpha=0.3)
        fig.suptitle(f"{table.study}: {measure}.{stat} (mean, 95% band)", fontsize=10)
        fig.tight_layout()
        name = f"{measure}.{stat}.png"
        _save(fig, folder / name)
        plt.close(fig)
        written.append(f"plots/{name}")
    if table.sobol:
        written.append(_sobol(plt, table, stats, folder))
    return written


def _label(factor: str) -> str:
    """The factor with the SI unit of its kind (the unit the table's values are in)."""
    from wiredsl.effects import REGISTRY

    stage, param = factor.rsplit(".", 1)
    if stage.startswith("camera."):
        from wiredsl.language.compile_study import CAMERA_FACTORS

        kind = CAMERA_FACTORS[param][0]
    else:
        kind = (REGISTRY[stage].Params.model_fields[param].json_schema_extra or {}).get("kind")
    unit = {"image": "px", "angle": "rad", "length": "m"}.get(kind, "")
    return f"{factor} ({unit})" if unit else factor


def _grid(ax, rows, f: str, factors: list[str]) -> None:
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
        label = ", ".join(f"{g.rsplit('.', 1)[0]}={v:g}" for g, v in zip(others, combo, strict=True)) or None
        line, = ax.plot(xs, mean, marker="o", ms=3, label=label)
        ax.fill_between(xs, mean - Z95 * sem, mean + Z95 * sem, color=line.get_color(), alpha=0.2, lw=0)
    if others:
        ax.legend(fontsize=7)


def _scatter(ax, rows, f: str, factors: list[str]) -> None:
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
    ax.fill_between(mids, means - half, means + half, color=line.get_color(), alpha=0.25, lw=0)


def _sobol(plt, table: StudyTable, stats, folder: Path) -> str:
    """First-order and total indices of every statistic, one panel each, with bootstrap 95% intervals."""
    n = len(stats)
    cols = min(n, 3)
    nrows = -(-n // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(4.6 * cols, 3.2 * nrows), squeeze=False)
    d = len(table.factors)
    for ax, (measure, stat) in itertools.zip_longest(axes.ravel(), stats):
        if measure is None:
            ax.axis("off")
            continue
        idx = {s.factor: s for s in table.sobol if (s.measure, s.statistic) == (measure, stat)}
        pos = np.arange(d)
        for shift, key, colour in ((-0.2, "first_order", "C0"), (0.2, "total_order", "C1")):
            vals = np.array([np.nan if getattr(idx[f], key) is None else getattr(idx[f], key)
                             for f in table.factors])  # undefined (a constant statistic): no bar
            cis = [getattr(idx[f], key + "_ci") for f in table.factors]
            err = None
            if all(c is not None for c in cis):
                lo = np.array([c[0] for c in cis])
                hi = np.array([c[1] for c in cis])
                err = np.stack([np.clip(vals - lo, 0, None), np.clip(hi - vals, 0, None)])
            ax.bar(pos + shift, vals, 0.4, yerr=err, color=colour, capsize=2,
                   label="first order" if key == "first_order" else "total")
        lo, hi = ax.get_ylim()  # indices are shares of variance: a heavy-tailed statistic's wild interval is cut
        ax.set_ylim(max(lo, -0.5), min(hi, 1.5))
        ax.set_xticks(pos, [f.rsplit(".", 1)[0] for f in table.factors], rotation=35, ha="right", fontsize=7)
        ax.set_title(f"{measure}.{stat}", fontsize=9)
        ax.axhline(0, color="0.5", lw=0.5)
        ax.grid(axis="y", alpha=0.3)
    axes.ravel()[0].legend(fontsize=7)
    fig.suptitle(f"{table.study}: Sobol' indices (bootstrap 95%)", fontsize=10)
    fig.tight_layout()
    _save(fig, folder / "sobol.png")
    plt.close(fig)
    return "plots/sobol.png"
