"""The docs' measured numbers and figures, made by the commands the pages show beside them, and checked.

    python docs/reproduce.py --write [--reuse build/ci] [NAME ...]   # regenerate blocks and figures in place
    python docs/reproduce.py --check [--reuse build/ci] [NAME ...]   # regenerate and compare; exit 1 on a drift
    python docs/reproduce.py --list                                   # each block: its page, command and figures

A page holds `<!-- numbers: NAME -->` and `<!-- /numbers -->` on lines of their own; between them is what
BLOCKS[NAME] writes from its command's output: the command itself, then the numbers (a table, or a sentence made
from them, so a conclusion follows the numbers). `--check` compares a block's words exactly and each number
within NUMBER_TOL units of the last digit the page prints (a rounded figure may move in its last digit on
another CPU's floating point; a count may move by 1), each PNG figure with matplotlib's `compare_images` at
FIGURE_TOL (RMS over 0-255 grey levels; another seed of the render block is 14 off), and each SVG figure by what
it draws (its text: words exactly, coordinates as numbers). `--reuse DIR` takes a study's output from DIR
(CI's `build/ci`, written by `.ci/run`'s own study commands) when its manifest's digest is the study's (the
scene with its includes, the study, wiredsl's version: `wiredsl.study.digest`), so CI pays only for reading it;
without it, or when they differ, the command runs in a temporary folder.

Not here: machine-dependent figures (CPU seconds and rates in docs/performance*.md and the CRN benchmark's
efficiency column, each beside the script that prints it: no tolerance holds them across machines) and the fence's
measured.wd excerpt in the detector tutorial (as wiredsl 0.2.0 wrote it). The calibration table is checked against
the covariance file the scene declares, not against a new calibration (OpenCV's threads change its last digits).
"""

from __future__ import annotations

import argparse
import ast
import itertools
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
NUMBER_TOL = 1  # units of the page's last printed digit
FIGURE_TOL = 2.0  # compare_images' RMS, grey levels
BLOCK = re.compile(r"^<!-- numbers: ([\w-]+) -->\n(.*?)^<!-- /numbers -->$", re.M | re.S)
NUMBER = re.compile(r"(?<![\w.])-?\d+(?:\.\d+)?(?:e[-+]?\d+)?")


@dataclass(frozen=True)
class Block:
    page: str  # relative to the checkout
    command: str  # as the page shows it
    make: Callable[[Context], str]  # the block's Markdown between the markers
    figures: dict[str, Callable[[Context], Path]] = field(default_factory=dict)  # docs/figures/x.png -> fresh file


class Context:
    """Where the blocks' commands run (or are reused from), each once."""

    def __init__(self, reuse: Path | None, tmp: Path):
        self.reuse, self.tmp, self.made = reuse, tmp, {}

    def study(self, scene: str, study: str, ci_folder: str) -> Path:
        """`wiredsl study SCENE STUDY`'s output folder: CI's own (reuse/ci_folder) when it is that study."""
        if (scene, study) not in self.made:
            self.made[scene, study] = self._study(scene, study, ci_folder)
        return self.made[scene, study]

    def _study(self, scene: str, study: str, ci_folder: str) -> Path:
        if self.reuse is not None:
            m = self.reuse / ci_folder / "manifest.json"
            if m.is_file():
                from wiredsl import api
                from wiredsl.study import digest

                compiled = api.compile(ROOT / scene)
                (s,) = [s for s in compiled.studies if s.name == study]
                if json.loads(m.read_text()).get("digest") == digest(compiled, s):
                    print(f"numbers: reusing {m.parent} for {scene} {study}", file=sys.stderr)
                    return m.parent
                print(f"numbers: {m} is not {scene} {study} as it is now (its digest differs); running it",
                      file=sys.stderr)
        out = self.tmp / f"{Path(scene).stem}-{study}"
        print(f"numbers: wiredsl study {scene} {study}", file=sys.stderr)
        subprocess.run([sys.executable, "-m", "wiredsl", "study", scene, study, "-o", str(out)], cwd=ROOT, check=True)
        return out


    def wiredsl(self, command: str, scene: str, *args: str, page: str | None = None) -> Path:
        """`wiredsl COMMAND SCENE ARGS`'s output folder (build, render); with `page`, SCENE is first written from
        the page's `<!-- file: SCENE -->` block (as tests/test_docs.py runs a tutorial) and run beside it."""
        key = (command, scene, *args, page)
        if key not in self.made:
            cwd = ROOT
            if page is not None:
                cwd = self.tmp / f"page-{len(self.made)}"
                cwd.mkdir()
                m = re.search(rf"^<!-- file: {re.escape(scene)} -->\n```\w*\n(.*?)^```", (ROOT / page).read_text(),
                              re.S | re.M)
                (cwd / scene).write_text(m.group(1))
            out = self.tmp / f"build-{len(self.made)}"
            print(f"numbers: wiredsl {command} {scene} {' '.join(args)}", file=sys.stderr)
            subprocess.run([sys.executable, "-m", "wiredsl", command, scene, *args, "-o", str(out)], cwd=cwd,
                           check=True, capture_output=True)
            self.made[key] = out
        return self.made[key]


    def roundtrip(self) -> dict[str, str]:
        """The detector round trip's hits per fitted parameter ("28/30"), as its test prints them."""
        if "roundtrip" not in self.made:
            print(f"numbers: {ROUNDTRIP}", file=sys.stderr)
            proc = subprocess.run([sys.executable, *ROUNDTRIP.split()[1:]], cwd=ROOT, capture_output=True, text=True)
            if proc.returncode != 0:
                raise subprocess.CalledProcessError(proc.returncode, [sys.executable, *ROUNDTRIP.split()[1:]])
            (line,) = [x for x in proc.stdout.splitlines() if x.startswith("{'edge_loss.fraction'")]
            self.made["roundtrip"] = ast.literal_eval(line)
        return self.made["roundtrip"]


    def verify(self, *args: str) -> Path:
        """`wiredsl verify` of OpenCV's stereo chessboard (CHESSBOARD, then `args`)'s output folder."""
        key = ("verify", *args)
        if key not in self.made:
            out = self.tmp / f"verify-{len(self.made)}"
            command = [*CHESSBOARD.split()[1:], *args, "-o", str(out)]
            print(f"numbers: wiredsl {' '.join(command)}", file=sys.stderr)
            subprocess.run([sys.executable, "-m", "wiredsl", *[a.strip("'") for a in command]], cwd=ROOT, check=True,
                           capture_output=True)
            self.made[key] = out
        return self.made[key]


CHESSBOARD = ("wiredsl verify scenes/chessboard.wd --images 'tests/data/opencv_stereo/*.jpg' --poses board --fit "
              "--predict --no-calibration-error --trials 50 --seed 0")
CHESS_GAPS = ("--detector", "canny", "--detector", "lsd", "--detector", "harris")
CHESS_RAW = ("--detector", "canny", "--detector", "harris", "--edge-loss", "raw")


def _pct(x: float, digits: int = 1) -> str:
    return "0" if x == 0 else f"{100 * x:.{digits}f}%"


def chess_fit_table(ctx: Context) -> str:
    """The chessboard's fitted pipeline (its fit.json), the raw edge-loss reading from the second run beside it."""
    est = {e["parameter"]: e for e in json.loads((ctx.verify(*CHESS_GAPS) / "fit.json").read_text())["estimates"]}
    raw = {e["parameter"]: e for e in json.loads((ctx.verify(*CHESS_RAW) / "fit.json").read_text())["estimates"]}

    def row(label: str, e: dict, fmt: Callable[[float], str], paper: str) -> str:
        if e["value"] is None:
            return f"| {label} | not estimated ({e['note']}) | | {paper} |"
        return f"| {label} | {fmt(e['value'])} | {fmt(e['low95'])} - {fmt(e['high95'])} | {paper} |"

    px = lambda x: f"{x:.2f} px"  # noqa: E731
    mm = est["corner_mismatch.fraction"]
    found = re.search(r"of (\d+) found corners", mm["note"]).group(1)
    return "\n".join([
        f"`{CHESSBOARD} {' '.join(CHESS_GAPS)}` (and `{' '.join(CHESS_RAW)}` for the raw reading), its `fit.json`:",
        "", "| parameter | fitted | 95% interval | paper |", "|---|---|---|---|",
        row("edge_loss fraction (gaps)", est["edge_loss.fraction"], _pct, "29%"),
        row("edge_loss fraction (everything lost, `--edge-loss raw`)", raw["edge_loss.fraction"], _pct, ""),
        row("lateral_shift range", est["lateral_shift.range"], px, "3 px"),
        row("approx_error sigma", est["approx_error.sigma"], px, "0.15 px"),
        row("corner_loss keep (Harris)", est["corner_loss.keep"], _pct, "85%"),
        row("corner_error sigma (Harris)", est["corner_error.sigma"], px, "(none)"),
        row("corner_error correlation (left with right)", est["corner_error.correlation"], lambda x: f"{x:.2f}",
            "(none)"),
        f"| corner_mismatch fraction | {round(mm['value'] * int(found))} of {int(found):,} | {_pct(mm['low95'])} - "
        f"{_pct(mm['high95'], 2)} | 1% |"]) + "\n"


def chess_predict_table(ctx: Context) -> str:
    """The chessboard's prediction (prediction.json of both runs): real against simulated, each measure."""
    gaps = json.loads((ctx.verify(*CHESS_GAPS) / "prediction.json").read_text())["measures"]
    raw = json.loads((ctx.verify(*CHESS_RAW) / "prediction.json").read_text())["measures"]
    g = lambda p: f"{p:.2f}" if p >= 0.1 else f"{p:.2g}" if p >= 1e-3 else f"{p:.0e}"  # noqa: E731

    def row(label: str, m: dict, fmt: Callable[[float], str]) -> str:
        return (f"| {label} | {fmt(m['real_mean'])} | {fmt(m['simulated_mean'])} | {g(m['ks']['p'])} | "
                f"{g(m['mann_whitney']['p'])} |")

    px, mm = (lambda x: f"{x:.2f} px"), (lambda x: f"{x:.2f} mm")
    return "\n".join([
        "| measure | real (mean) | simulated (mean) | KS p | Mann-Whitney p |", "|---|---|---|---|---|",
        row("verified fraction (`--edge-loss gaps`)", gaps["verified_fraction"], _pct),
        row("verified fraction (`--edge-loss raw`)", raw["verified_fraction"], _pct),
        row("RMS lateral offset", gaps["offset_rms_px"], px),
        row("triangulated corner error, RMS", gaps["corner_error_3d"], mm),
        row("3D shape error after a rigid fit, RMS", gaps["corner_shape_3d"], mm)]) + "\n"


HOLDOUT = "python benchmarks/holdout_chessboard.py"


def holdout_table(ctx: Context) -> str:
    """The held-out table benchmarks/holdout_chessboard.py prints (its four verify --holdout runs)."""
    print(f"numbers: {HOLDOUT}", file=sys.stderr)
    out = subprocess.run([sys.executable, *HOLDOUT.split()[1:]], cwd=ROOT, capture_output=True, text=True, check=True)
    return "\n".join(line for line in out.stdout.splitlines() if line.startswith("|")) + "\n"


CIRCLES = "python benchmarks/circle_grids.py --figure docs/figures/verify_by_kind.png"


def _circle_grids(ctx: Context) -> tuple[str, Path]:
    """benchmarks/circle_grids.py's tables and figure, run once."""
    if "circle-grids" not in ctx.made:
        print(f"numbers: {CIRCLES}", file=sys.stderr)
        fig = ctx.tmp / "verify_by_kind.png"
        out = subprocess.run([sys.executable, "benchmarks/circle_grids.py", "--figure", str(fig)], cwd=ROOT,
                             capture_output=True, text=True, check=True)
        ctx.made["circle-grids"] = (out.stdout, fig)
    return ctx.made["circle-grids"]


def circle_grids(ctx: Context) -> str:
    """The circle grids' tables, and how many held-out statistics have at least 80% of their images inside."""
    text, _ = _circle_grids(ctx)
    tables = "\n".join(line if line.startswith("|") else "" for line in text.splitlines()).strip() + "\n"
    held = [t for t in tables.split("\n\n") if t.startswith("| held out")][0].splitlines()[2:]
    cells = [c for line in held for c in line.split("|")[2:-1]]
    fractions = [int(c.split("/")[0]) / int(c.split("/")[1].split()[0]) for c in cells if "/" in c]
    good = sum(f >= 0.8 for f in fractions)
    return (f"`{CIRCLES}` (a `wiredsl verify --fit --holdout odd` run a set, 50 trials an image, seed 0):\n\n"
            f"{tables}\nHeld out, {good} of the {len(fractions)} statistics of the two sets have at least 80% of "
            f"their images inside the simulated central 90% band.\n")


CALIBRATION = "scenes/chessboard.wd"  # its rig's declared covariance (scenes/calib/opencv_stereo.cov) and T


def calibration_table(ctx: Context) -> str:
    """The standard deviations of the chessboard rig's calibration, from the covariance its scene declares
    (written by docs/scripts/calibrate_opencv_stereo.py); the baseline's along OpenCV's T."""
    import cv2
    import numpy as np

    from wiredsl import api

    cal = api.compile(ROOT / CALIBRATION).rig.calibration
    sd = dict(zip(cal.order, np.sqrt(np.diag(np.asarray(cal.matrix))), strict=True))
    fs = cv2.FileStorage(str(ROOT / "scenes/calib/opencv_stereo.yml"), cv2.FILE_STORAGE_READ)
    T = fs.getNode("T").mat().reshape(3)
    fs.release()
    idx = [cal.order.index(f"right.t{a}") for a in "xyz"]
    C = np.asarray(cal.matrix)[np.ix_(idx, idx)]
    u = T / np.linalg.norm(T)
    base = float(np.sqrt(u @ C @ u))
    px, mm = (lambda x: f"{x:.2f} px"), (lambda x: f"{1000 * x:.2g} mm")
    mrad = [1000 * sd[f"right.r{a}"] for a in "xyz"]
    return "\n".join([
        f"From the covariance `{CALIBRATION}` declares (`docs/scripts/calibrate_opencv_stereo.py` writes it):", "",
        "| parameter | standard deviation |", "|---|---|",
        f"| `f` (left, right) | {px(sd['left.f'])}, {px(sd['right.f'])} |",
        f"| `cx`, `cy` | {px(sd['left.cx'])}, {px(sd['left.cy'])} (left); {px(sd['right.cx'])}, "
        f"{px(sd['right.cy'])} (right) |",
        f"| baseline ({1000 * np.linalg.norm(T):.2f} mm) | {mm(base)} (`tx` {mm(sd['right.tx'])}, `ty` "
        f"{mm(sd['right.ty'])}, `tz` {mm(sd['right.tz'])}) |",
        f"| rotation `rx`, `ry`, `rz` | {mrad[0]:.2f} mrad, {mrad[1]:.2f} mrad, {mrad[2]:.2f} mrad "
        f"({', '.join(f'{np.degrees(m / 1000):.3f}' for m in mrad)} deg) |"]) + "\n"


ROUNDTRIP = "python -m pytest -q -s -n 0 -p no:cacheprovider tests/test_verify_roundtrip.py"


def roundtrip_sentence(ctx: Context) -> str:
    hits = ctx.roundtrip()
    counts = [hits[k].split("/")[0] for k in ("edge_loss.fraction", "lateral_shift.range", "corner_loss.keep",
                                               "corner_error.sigma", "corner_mismatch.fraction")]
    n = hits["edge_loss.fraction"].split("/")[1]
    return (f"The test suite does this for {n} random settings (injected parameters, blur 0.6-1.5 px, noise\n"
            "0-4 grey levels, a corner localisation error of 0.3-1 px; `tests/test_verify_roundtrip.py`): the fitted\n"
            "edge loss, shift range, corner keep, corner localisation sigma and corner mismatch fraction must each\n"
            "hold the injected value within their 95% interval in at least 90% of them; they hold it in\n"
            f"{', '.join(counts[:-1])} and {counts[-1]} of the {n} (`{ROUNDTRIP}` prints them).\n")


CRN = "python benchmarks/study_crn.py --trials 8"


def crn_table(ctx: Context) -> str:
    """The benchmark's standard errors (the seed's, any machine's); its CPU seconds, this machine's, left out."""
    print(f"numbers: {CRN}", file=sys.stderr)
    out = subprocess.run([sys.executable, *CRN.split()[1:]], cwd=ROOT, capture_output=True, text=True, check=True)
    rows, ratios = [], []
    for line in out.stdout.splitlines():
        f = line.split()
        if len(f) == 5 and f[0].count(".") == 1:
            rows.append(f"| {f[0]} | {f[1]} | {f[2]} | {f[3]} |")
            if f[3] != "exact":
                ratios.append((float(f[3]), f[0]))
        elif len(f) == 3 and f[1:] == ["undefined", "(constant)"]:
            rows.append(f"| {f[0]} | undefined (constant) | | |")
    ratios.sort()
    mid = statistics.median(r for r, _ in ratios)
    return "\n".join([
        f"`{CRN}` (each first-order index's standard error, bootstrap over trials with 200 resamples, the median "
        "over the 7 factors):", "", "| statistic | SE independent | SE common | SE ratio |", "|---|---|---|---|",
        *rows, "",
        f"Common draws' standard errors are {ratios[0][0]:.2f} ({ratios[0][1]}) to {ratios[-1][0]:.2f} "
        f"({ratios[-1][1]}) times smaller (median {mid:.2f}), so the same standard error takes "
        f"{ratios[0][0] ** 2:.1f} to {ratios[-1][0] ** 2:.0f} times fewer trials (at the 1/sqrt(trials) rate); "
        "the script also prints the CPU seconds of each run and the efficiency in CPU-seconds (the squared ratio "
        "times their ratio), which are this machine's and are not shown here."]) + "\n"


def _rows(folder: Path) -> list[dict]:
    return json.loads((folder / "table.json").read_text())["rows"]


def _f3(x: float) -> str:
    """Three significant figures, as a table prints them (0.037, 0.555, 1.27)."""
    return f"{x:.3f}" if abs(x) < 1 else f"{x:.3g}"


SHIFT_CAL = ("scenes/studies/lab_study.wd", "shift_calibration", "study")
SOURCES = ("scenes/studies/lab_study.wd", "sources", "sources")
SHIFT_ROWS = [(0, 0), (0, 0.04), (2, 0), (4, 0), (6, 0), (6, 0.04)]  # (px, sigma): the excerpt's design points


def shift_table(ctx: Context) -> str:
    rows = _rows(ctx.study(*SHIFT_CAL))
    lines = [f"`{BLOCKS['study-shift-table'].command}`, excerpt of its `table.csv`:", "",
             "| lateral_shift.range (px) | calibration_error.sigma | pgh.recognition mean ± se | q05 / q50 / q95 "
             "| stereo3d.error_median mean ± se (m) | q05 / q50 / q95 |", "|---|---|---|---|---|---|"]

    def at(stat: str, px: float, sigma: float) -> dict:
        (r,) = [r for r in rows if (r["measure"], r["statistic"]) == stat
                and abs(r["values"]["lateral_shift.range"] - px) < 1e-9
                and abs(r["values"]["calibration_error.sigma"] - sigma) < 1e-9]
        return r

    rec, err = ("pgh", "recognition"), ("stereo3d", "error_median")
    for px, sigma in SHIFT_ROWS:
        cells = [f"{px:g}", f"{sigma:g}"]
        for stat in (rec, err):
            r = at(stat, px, sigma)
            cells += [f"{_f3(r['mean'])} ± {_f3(r['sem'])}", " / ".join(_f3(r[q]) for q in ("q05", "q50", "q95"))]
        lines.append("| " + " | ".join(cells) + " |")
    # the conclusion, from the same rows: recognition's fall with the shift, and what shift the calibration's
    # 0.04 alone costs as much 3D error as
    shifts = sorted({r["values"]["lateral_shift.range"] for r in rows})
    cal = at(err, 0, 0.04)["mean"]
    by_shift = [(px, at(err, px, 0)["mean"]) for px in shifts]
    below = [px for px, e in by_shift if e <= cal]
    above = [px for px, e in by_shift if e > cal]
    like = (f"more than a {below[-1]:g} px shift does" if not above else
            f"as much as a shift between {below[-1]:g} and {above[0]:g} px" if below else
            f"less than a {above[0]:g} px shift does")
    lines += ["", f"Recognition goes from {at(rec, 0, 0)['mean']:.0%} to {at(rec, shifts[-1], 0)['mean']:.0%} as the "
              f"shift range grows to {shifts[-1]:g} px, and is {at(rec, 0, 0.04)['mean']:.0%} with a 0.04 calibration "
              f"sigma alone. The median 3D error grows with "
              f"both: a 0.04 calibration sigma alone ({_f3(cal)} m) costs {like} "
              f"({', '.join(f'{px:g} px: {_f3(e)} m' for px, e in by_shift)})."]
    return "\n".join(lines) + "\n"


SOBOL_SENTENCE = [("pgh", "match", "the PGH match score"), ("pgh", "recognition", "the recognition rate"),
                  ("stereo3d", "error_median", "the median 3D error"),
                  ("stereo3d", "corners", "the corners reconstructed")]
FACTOR_WORDS = {"approx_error": "approximation error", "calibration_error": "calibration"}
SOBOL_MIN = 0.15  # first-order indices below this are not named


def sobol_sentence(ctx: Context) -> str:
    sobol = json.loads((ctx.study(*SOURCES) / "table.json").read_text())["sobol"]
    parts = []
    for measure, stat, words in SOBOL_SENTENCE:
        got = sorted(((s["first_order"], s["factor"].rsplit(".", 1)[0]) for s in sobol
                      if (s["measure"], s["statistic"]) == (measure, stat) and s["first_order"] is not None
                      and s["first_order"] >= SOBOL_MIN), reverse=True)
        named = [f"{FACTOR_WORDS.get(f, f.replace('_', ' '))} ({v:.2f})" for v, f in got]
        if not named:
            parts.append(f"for {words}, no source above {SOBOL_MIN}")
            continue
        parts.append(f"for {words}, " + (named[0] if len(named) == 1 else
                                        ", ".join(named[:-1]) + " then " + named[-1]))
    return (f"From `{BLOCKS['study-sources-sobol'].command}`'s `table.json`, the sources in order of their "
            f"first-order index (those of at least {SOBOL_MIN}): " + "; ".join(parts) + ".\n")


def _plot(spec: tuple[str, str, str], name: str) -> Callable[[Context], Path]:
    return lambda ctx: ctx.study(*spec) / "plots" / name


def _render(page: str, alt: str, figure: str, command: str, svg: str, from_page: bool = False) -> Block:
    """A block showing one figure a `wiredsl build` or `render` command writes (an SVG a pose, a PNG a camera and
    pose): the image, then the command and its file."""
    sub, scene, *args = command.split()[1:]
    rel = Path(os.path.relpath(ROOT / "docs/figures" / figure, (ROOT / page).parent)).as_posix()
    return Block(page, command, lambda ctx: f"![{alt}]({rel})\n\nDrawn by `{command}` (its `{svg}`).\n",
                 {f"docs/figures/{figure}": lambda ctx: ctx.wiredsl(sub, scene, *args, page=page if from_page else None)
                  / Path(svg).name})


BLOCKS: dict[str, Block] = {
    "readme-figure": _render(
        "README.md", "The lab scene seen by both cameras of the rig: disturbed features in colour over the ideal "
        "ones in grey, and the map", "lab_pose_003_overlay.svg", "wiredsl build scenes/lab.wd --seed 1",
        "build/lab/pose_003.svg"),
    "first-figure": _render(
        "docs/tutorials/first-scene.md", "The crate seen by both cameras at the last pose, and the map of the path",
        "first_pose_004.svg", "wiredsl build first.wd --seed 1", "build/first/pose_004.svg", from_page=True),
    "box-figure": _render(
        "docs/explanation/engine.md", "the box, pose 1, visibility layout", "box_pose_001_visibility.svg",
        "wiredsl build scenes/box.wd --layout visibility", "build/box/pose_001.svg"),
    "meshes-figure": _render(
        "docs/tutorials/mesh.md", "a world read from meshes: crate (OBJ), can (STL) on it, cone (PLY) behind a ball "
        "(GLB); hidden lines removed", "meshes_pose_001_exact.svg",
        "wiredsl build scenes/meshes.wd --no-effects --visibility exact --pose 1", "build/meshes/pose_001.svg"),
    "render-figure": _render(
        "docs/how-to/render.md", "The lab, pose 2, left camera, through the paper pipeline (blur 0.8 px, noise 2 grey "
        "levels)", "render_lab.png",
        "wiredsl render scenes/lab.wd --pipeline paper --seed 1 --blur 0.8 --noise 2 --pose 2 --cameras left",
        "build/lab/render/left_002.png"),
    "chessboard-fit": Block("docs/tutorials/measure-your-detector.md", CHESSBOARD, chess_fit_table,
                            {"docs/figures/verify_opencv_stereo_figure7.png": lambda ctx: ctx.verify(*CHESS_GAPS)
                             / "figure7.png"}),
    "chessboard-predict": Block("docs/tutorials/measure-your-detector.md", CHESSBOARD, chess_predict_table,
                                {"docs/figures/verify_opencv_stereo_prediction.png":
                                 lambda ctx: ctx.verify(*CHESS_GAPS) / "prediction.png",
                                 "docs/figures/verify_opencv_stereo_prediction_raw.png":
                                 lambda ctx: ctx.verify(*CHESS_RAW) / "prediction.png"}),
    "holdout-table": Block("docs/tutorials/measure-your-detector.md", HOLDOUT, holdout_table),
    "calibration-table": Block("docs/how-to/calibration-board.md", "python docs/scripts/calibrate_opencv_stereo.py",
                               calibration_table),
    "roundtrip-counts": Block("docs/tutorials/measure-your-detector.md", ROUNDTRIP, roundtrip_sentence),
    "crn-table": Block("docs/tutorials/study.md", CRN, crn_table),
    "study-shift-table": Block(
        "docs/tutorials/study.md", "wiredsl study scenes/studies/lab_study.wd shift_calibration", shift_table,
        {"docs/figures/study_shift_recognition.png": _plot(SHIFT_CAL, "pgh.recognition.png"),
         "docs/figures/study_shift_error.png": _plot(SHIFT_CAL, "stereo3d.error_median.png")}),
    "circle-grids": Block("docs/how-to/calibration-board.md", CIRCLES, circle_grids,
                          {"docs/figures/verify_by_kind.png": lambda ctx: _circle_grids(ctx)[1]}),
    "study-sources-sobol": Block(
        "docs/tutorials/study.md", "wiredsl study scenes/studies/lab_study.wd sources", sobol_sentence,
        {"docs/figures/study_sources_sobol.png": _plot(SOURCES, "sobol.png")}),
}


def numbers_drift(page: str, fresh: str, tol: float = NUMBER_TOL) -> list[str]:
    """How `fresh` differs from `page`: words exactly, numbers within `tol` units of the page's last digit."""
    if NUMBER.sub("#", page) != NUMBER.sub("#", fresh):
        a, b = NUMBER.sub("#", page).splitlines(), NUMBER.sub("#", fresh).splitlines()
        diff = next(f"page: {x!r}\n      now:  {y!r}" for x, y in itertools.zip_longest(a, b, fillvalue="") if x != y)
        return [f"the words differ:\n      {diff}"]
    out = []
    for x, y in zip(NUMBER.findall(page), NUMBER.findall(fresh), strict=True):
        digits = len(x.split("e")[0].partition(".")[2])
        scale = 10.0 ** (int(x.split("e")[1]) if "e" in x else 0)
        if abs(float(x) - float(y)) > tol * 10.0 ** -digits * scale * (1 + 1e-9):
            out.append(f"{x} on the page, {y} now")
    return out


def figure_drift(page: Path, fresh: Path, tol: float = FIGURE_TOL) -> str | None:
    """None when the figures agree (a PNG within `tol` RMS grey levels, an SVG's numbers within 1 in their last
    digit and its words exactly), else why not."""
    from matplotlib.testing.compare import compare_images

    if not page.is_file():
        return f"{page} is missing"
    if page.suffix == ".svg":  # the data it draws, as text: coordinates within their last digit
        return "; ".join(numbers_drift(page.read_text(), fresh.read_text(), NUMBER_TOL)[:3]) or None
    try:
        return compare_images(str(page), str(fresh), tol=tol)
    except Exception as exc:  # different sizes: compare_images raises ImageComparisonFailure
        return str(exc)


def run(root: Path, blocks: dict[str, Block], ctx: Context, write: bool,
        known: dict[str, Block] | None = None) -> list[str]:
    """Every block regenerated; written in place (write) or compared: the drifts, each with its page and line.

    `blocks` are those to make, `known` every name a page may hold (default BLOCKS)."""
    known = BLOCKS if known is None else known
    problems, cost = [], {}
    for page in sorted({b.page for b in blocks.values()}):
        text = (root / page).read_text()
        found = {m.group(1): m for m in BLOCK.finditer(text)}
        for name in [n for n, b in blocks.items() if b.page == page and n not in found]:
            problems.append(f"{page}: no block `<!-- numbers: {name} -->`")
        for name in found:
            if name not in known:
                line = text.count("\n", 0, found[name].start()) + 1
                problems.append(f"{page}:{line}: unknown numbers block {name!r}: one of {', '.join(known)}")

        def fill(m: re.Match, page: str = page, text: str = text) -> str:
            name = m.group(1)
            if name not in blocks:
                return m.group(0)
            start = time.perf_counter()
            fresh = blocks[name].make(ctx)
            cost[name] = cost.get(name, 0.0) + time.perf_counter() - start
            line = text.count("\n", 0, m.start()) + 1
            if not write:
                problems.extend(f"{page}:{line}: {name}: {p}" for p in numbers_drift(m.group(2), fresh))
            return f"<!-- numbers: {name} -->\n{fresh}<!-- /numbers -->"

        new = BLOCK.sub(fill, text)
        if write and new != text:
            (root / page).write_text(new)
            print(f"numbers: wrote {page}", file=sys.stderr)
        for name in [n for n in found if n in blocks]:
            for fig, make in blocks[name].figures.items():
                start = time.perf_counter()
                fresh = make(ctx)
                cost[name] = cost.get(name, 0.0) + time.perf_counter() - start
                if write:
                    shutil.copyfile(fresh, root / fig)
                    print(f"numbers: wrote {fig}", file=sys.stderr)
                elif (why := figure_drift(root / fig, fresh)) is not None:
                    problems.append(f"{fig} ({name}): differs from what `{blocks[name].command}` draws: {why}")
    for name, s in cost.items():  # a command two blocks share is paid by the first
        print(f"numbers: {name}: {s:.1f} s", file=sys.stderr)
    return problems


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = ap.add_mutually_exclusive_group(required=True)
    mode.add_argument("--write", action="store_true", help="regenerate every block and figure in place")
    mode.add_argument("--check", action="store_true", help="regenerate and compare; exit 1 on a drift")
    mode.add_argument("--list", action="store_true", help="each block, its page, command and figures")
    ap.add_argument("--reuse", type=Path, help="a folder of study outputs (CI's build/ci) to read, not rerun")
    ap.add_argument("names", nargs="*", help="only these blocks (default: all)")
    a = ap.parse_args(argv)
    unknown = [n for n in a.names if n not in BLOCKS]
    if unknown:
        ap.error(f"unknown block {unknown[0]!r}: one of {', '.join(BLOCKS)}")
    blocks = {n: b for n, b in BLOCKS.items() if not a.names or n in a.names}
    if a.list:
        for n, b in blocks.items():
            print(f"{n}\t{b.page}\t{b.command}\t{' '.join(b.figures)}")
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        try:
            problems = run(ROOT, blocks, Context(a.reuse, Path(tmp)), a.write)
        except subprocess.CalledProcessError as exc:
            print(f"numbers: error: {' '.join(exc.cmd[2:])} exited {exc.returncode}", file=sys.stderr)
            return 1
    for p in problems:
        print(f"numbers: drift: {p}", file=sys.stderr)
    if a.check and not problems:
        print(f"numbers: {len(blocks)} blocks and their figures hold", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
