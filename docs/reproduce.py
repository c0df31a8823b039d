"""The docs' measured numbers and figures, made by the commands the pages show beside them, and checked.

    python docs/reproduce.py --write [--reuse build/ci] [NAME ...]   # regenerate blocks and figures in place
    python docs/reproduce.py --check [--reuse build/ci] [NAME ...]   # regenerate and compare; exit 1 on a drift
    python docs/reproduce.py --list                                   # each block: its page, command and figures

A page holds `<!-- numbers: NAME -->` and `<!-- /numbers -->` on lines of their own; between them is what
BLOCKS[NAME] writes from its command's output: the command itself, then the numbers (a table, or a sentence made
from them, so a conclusion follows the numbers). `--check` compares a block's words exactly and each number
within NUMBER_TOL units of the last digit the page prints (a rounded figure may move in its last digit on
another CPU's floating point; a count may move by 1), each PNG figure with matplotlib's `compare_images` at
FIGURE_TOL (RMS over 0-255 grey levels; another seed of the render block is 14 off), and each SVG figure by what it
draws (its text: words exactly, coordinates as numbers), and a written .wd file so. `--reuse DIR` takes a study's
output from DIR (CI's `build/ci`, written by `.ci/run`'s own study commands) when its manifest's digest is the
study's (the scene with its includes, the study, wiredsl's version: `wiredsl.study.digest`), so CI pays only for
reading it; without it, or when they differ, the command runs in a temporary folder.

A block's command may be a page's own: `page_runs` runs a page's `<!-- run -->` blocks as tests/test_docs.py does
(the detector tutorial's fence: its stdout, its measured.wd, its predictions).

Not here: machine-dependent figures (CPU seconds and rates in docs/performance*.md and the CRN benchmark's
efficiency column, each beside the script that prints it: no tolerance holds them across machines). The
calibration table is checked against the covariance file the scene declares, not against a new calibration
(OpenCV's threads change its last digits); `--monte-carlo` re-calibrates to check that covariance.

    python docs/reproduce.py --scan [--write-inventory]   # numbers outside the blocks against INVENTORY

`--scan` lists every measured-looking number (a percentage, a figure with a unit, a decimal) of README.md and
docs/ that no block makes and fails on one that INVENTORY does not list (as a definition, a machine's figure, or
measured and not yet reproduced), or on an entry no page holds any more; tests/test_docs_numbers.py runs it.
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
import textwrap
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

    def example(self, command: str, ci_folder: str, result: str) -> Path:
        """`python SCRIPT ARGS -o DIR`'s output folder, for a script whose `result` (JSON) records its run's `digest`
        and which gives it as `digest(*parse(ARGS))`: CI's own (reuse/ci_folder) when that digest is the one the
        script gives ARGS now (the same arguments, scenes, code and wiredsl), else a fresh run."""
        if command not in self.made:
            self.made[command] = self._example(command, ci_folder, result)
        return self.made[command]

    def _example(self, command: str, ci_folder: str, result: str) -> Path:
        script, *args = command.split()[1:]
        if self.reuse is not None:
            r = self.reuse / ci_folder / result
            if r.is_file():
                mod = _module(script)
                if json.loads(r.read_text()).get("digest") == mod.digest(*mod.parse(args)):
                    print(f"numbers: reusing {r.parent} for {command}", file=sys.stderr)
                    return r.parent
                print(f"numbers: {r} is not `{command}` as it is now (its digest differs); running it",
                      file=sys.stderr)
        out = self.tmp / Path(script).stem
        print(f"numbers: {command}", file=sys.stderr)
        subprocess.run([sys.executable, script, *args, "-o", str(out)], cwd=ROOT, check=True)
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
            proc = subprocess.run([sys.executable, "-m", "wiredsl", *[a.strip("'") for a in command]], cwd=ROOT,
                                  check=True, capture_output=True, text=True)
            (out / "stdout.txt").write_text(proc.stdout)
            self.made[key] = out
        return self.made[key]


class BlockError(Exception):
    """A block cannot be made here (a plug-in its command needs is not installed, say): the message says why."""


def _module(script: str):
    """The checkout's SCRIPT (a path relative to it) imported as a module."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(Path(script).stem, ROOT / script)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


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


CHESS_DRAWN = (*CHESS_GAPS, "--calibration-error")  # the calibration's covariance drawn, as by default


def _fit(folder: Path) -> dict:
    return json.loads((folder / "fit.json").read_text())


def _para(text: str, indent: str = "") -> str:
    """A paragraph (or a list item, `indent` its first line's "- ") wrapped as the pages are, at 110 columns."""
    return textwrap.fill(" ".join(text.split()), 110, initial_indent=indent, subsequent_indent=" " * len(indent),
                         break_long_words=False, break_on_hyphens=False) + "\n"


def _bullets(lines: list[str]) -> str:
    """List items ("- " starts one, the lines after it continue it), each wrapped."""
    items = " ".join(lines).split(" - **")
    return "".join(_para(("**" if i else "") + item.removeprefix("- "), "- ") for i, item in enumerate(items))


def _estimates(fit: dict) -> dict[str, dict]:
    return {e["parameter"]: e for e in fit["estimates"]}


def _note(fit: dict, parameter: str, pattern: str) -> str:
    """A figure the fit's note on `parameter` states (what measured.wd's comment says)."""
    (e,) = [e for e in fit["estimates"] if e["parameter"] == parameter]
    return re.search(pattern, e["note"]).group(1)


def _corner_rms(folder: Path) -> dict[tuple[str, str], float]:
    """RMS px of each image's found corners within the inlier distance of the model's, by (frame, camera), and
    (all, all) over every image; from verification.json."""
    v = json.loads((folder / "verification.json").read_text())
    inlier = v["settings"]["corner_inlier_px"]
    acc: dict[tuple[str, str], list[float]] = {}
    for r in v["rows"]:
        if r["kind"] == "corner" and r["corner_error_px"] is not None and r["corner_error_px"] <= inlier:
            for key in ((r["frame"], r["camera"]), ("all", "all")):
                acc.setdefault(key, []).append(r["corner_error_px"])
    return {k: (sum(x * x for x in e) / len(e)) ** 0.5 for k, e in acc.items()}


def chess_verified_sentence(ctx: Context) -> str:
    """Figure 7 as the verification's stdout prints it (a line a detector)."""
    got = dict(re.findall(r"^(\w+)\tboard\t([\d.]+%) verified", (ctx.verify(*CHESS_GAPS) / "stdout.txt").read_text(),
                          re.M))
    return _para(f"Canny verifies {got['canny']} of the board's edges, LSD {got['lsd']} (the lines `wiredsl verify` "
                 "prints; "
            "the paper's Canny, on its seven objects: 71%). The\nfitted pipeline "
            "(`docs/figures/verify_opencv_stereo_measured.wd`):")


def chess_fit_prose(ctx: Context) -> str:
    """What the chessboard's fit says beyond its table: fragments, background, the shifts' law, the matcher and the
    corners' localisation error (fit.json and verification.json of the same run)."""
    run = ctx.verify(*CHESS_GAPS)
    fit, raw = _fit(run), _fit(ctx.verify(*CHESS_RAW))
    est = _estimates(fit)
    law, frag, matcher = fit["lateral_shift_law"], fit["fragments"], fit["stereo_matcher"]
    better = law["better"]
    other = "uniform" if better == "normal" else "normal"
    background = _note(fit, "lateral_shift.range", r"([\d.]+%) of them taken as the background")
    radius = est["corner_mismatch.radius"]
    rms = _corner_rms(run)["all", "all"]
    after = float(_note(fit, "corner_error.sigma", r"RMS ([\d.]+) px"))
    return _para(
        f"The board's grid lines break at every inner corner ({frag['runs_per_stroke']:.1f} verified runs a stroke), "
        "and every end of a model\nstroke meets another stroke, so the board has no free end to measure the detector's "
        "own loss at an edge's end\nand `gaps` (the default) takes none off; it leaves out the samples within 6 px of "
        "another stroke's end (the\njunctions, where the detector's response is not the edge's), which is why it reads "
        f"{_pct(est['edge_loss.fraction']['value'])} where\n`raw`, which keeps everything lost, reads "
        f"{_pct(_estimates(raw)['edge_loss.fraction']['value'])}. "
        f"Of the fragments' mean offsets, {background} are taken as the background (offsets\nuniform over the search "
        f"band: edges the model does not name), and the shifts of the rest are closer to {better}\nthan {other} "
        f"(Kolmogorov-Smirnov D {law[f'ks_{better}']['D']:.3f} against {law[f'ks_{other}']['D']:.3f})"
        + (", and the mismatch radius is not estimated (no displaced corner): the\npaper's 10 px is kept."
           if radius["value"] is None else f"; the mismatch radius is {radius['value']:.1f} px.")
        + f" In the stereo pairs the NCC matcher paired {matcher['wrong']} of {matcher['matched']} corners wrongly.\n"
        "The corners' localisation error is measured from their offsets after each image's affine map of them is "
        "taken\noff (a pose or calibration error moves all of an image's corners together: "
        f"{after:.2f} px RMS is left of the\n{rms:.2f} px), and the two cameras' errors of a corner correlate by "
        f"{est['corner_error.correlation']['value']:.2f}: they see it alike.")


def _frames(m: dict) -> list[tuple[str, float, list[float], float]]:
    """(frame, real value, its simulated trials, the real value's rank among them) of a pair measure, in order."""
    n = len(m["simulated"]) // len(m["real"])
    return [(r["frame"], r["value"], m["simulated"][i * n:(i + 1) * n], rank)
            for i, (r, rank) in enumerate(zip(m["real"], m["ranks"], strict=True))]


def chess_predict_bullets(ctx: Context) -> str:
    """The prediction's disagreements and agreements, each from prediction.json (and verification.json) of the runs
    the table shows, and of the same command with the calibration's covariance drawn."""
    import numpy as np

    g = lambda p: f"{p:.2g}" if p >= 1e-3 else f"{p:.0e}"  # noqa: E731
    agree = lambda p: p > 0.01  # noqa: E731  # the page's reading of a p-value
    gaps = json.loads((ctx.verify(*CHESS_GAPS) / "prediction.json").read_text())["measures"]
    raw = json.loads((ctx.verify(*CHESS_RAW) / "prediction.json").read_text())["measures"]
    drawn = json.loads((ctx.verify(*CHESS_DRAWN) / "prediction.json").read_text())["measures"]
    vf, vr, off = gaps["verified_fraction"], raw["verified_fraction"], gaps["offset_rms_px"]
    points = 100 * (vf["simulated_mean"] - vf["real_mean"])
    sd_real = float(np.std([r["value"] for r in off["real"]]))
    sd_sim = float(np.std(off["simulated"]))
    shape, err = gaps["corner_shape_3d"], gaps["corner_error_3d"]
    est = _estimates(_fit(ctx.verify(*CHESS_GAPS)))
    frames = _frames(shape)
    top = lambda values: sorted(frames, key=values, reverse=True)[:3]  # noqa: E731
    real_top = top(lambda f: f[1])
    sim_top = top(lambda f: float(np.median(f[2])))
    shared = len({f[0] for f in real_top} & {f[0] for f in sim_top})
    from scipy.stats import spearmanr

    rho = spearmanr([f[1] for f in frames], [float(np.median(f[2])) for f in frames]).statistic
    inside = [f for f in frames if 0.05 <= f[3] <= 0.95]
    outside = [f for f in frames if not 0.05 <= f[3] <= 0.95]
    rms = _corner_rms(ctx.verify(*CHESS_GAPS))
    right = {fr: v for (fr, cam), v in rms.items() if cam == "right"}
    worst = max(right, key=right.get)
    rest = [v for fr, v in right.items() if fr != worst]
    mm = lambda x: f"{x:.2f}"  # noqa: E731
    excepts = "; ".join(f"frame {f[0]}: {mm(f[1])} mm real, {mm(np.percentile(f[2], 5))}-{mm(np.percentile(f[2], 95))} "
                        "simulated" for f in outside)
    ef = _frames(err)
    off_by = [(f[0], f[1] - float(np.median(f[2]))) for f in ef if f[1] - float(np.median(f[2])) > 0.1]
    corners = all(agree(gaps[k]["ks"]["p"]) for k in ("corner_error_3d", "corner_shape_3d"))
    edges = all(agree(gaps[k]["ks"]["p"]) for k in ("verified_fraction", "offset_rms_px"))
    head = (f"The corners are {'' if corners else 'not '}predicted; the edges are {'' if edges else 'not'}"
            f"{', and each disagreement says why:' if not (corners and edges) else '.'}")
    still = abs(drawn["corner_shape_3d"]["simulated_mean"] - shape["simulated_mean"]) < 0.05
    lines = [
        f"- **The verified fraction, as fitted by default, is {abs(points):.1f} points too "
        f"{'high' if points > 0 else 'low'}** (KS p {g(vf['ks']['p'])}). The `gaps` reading",
        "  leaves out the junctions' samples and, the board having no free stroke end, takes no end loss off; the",
        "  simulation's strokes do not break at the inner corners as the real lines do, so what Canny loses there is",
        "  missing from the prediction. Fitted with `--edge-loss raw` (`verify_opencv_stereo_prediction_raw.png`), the",
        f"  means {'agree' if agree(vr['mann_whitney']['p']) else 'differ'} ({_pct(vr['simulated_mean'])} against "
        f"{_pct(vr['real_mean'])}, Mann-Whitney p {vr['mann_whitney']['p']:.2f}) and so "
        f"{'do' if agree(vr['ks']['p']) else 'do not'} the spreads (KS p {g(vr['ks']['p'])}): the fitted",
        "  `feature_spread` (each stroke's fraction drawn about its image's) gives each image the scatter of its "
        "strokes.",
        f"- **The lateral offsets {'agree' if agree(off['mann_whitney']['p']) else 'differ'} in the middle and "
        f"{'' if agree(off['ks']['p']) else 'not '}in the tails** "
        f"(RMS {off['simulated_mean']:.2f} px simulated against {off['real_mean']:.2f} px",
        f"  real, Mann-Whitney p {off['mann_whitney']['p']:.2f}, KS p {g(off['ks']['p'])}): with the mixture's "
        "background term simulated (`--predict` draws that",
        f"  share of each image's verified runs uniform over the band) the means "
        f"{'meet' if agree(off['mann_whitney']['p']) else 'do not meet'}, but the simulated images spread",
        f"  {'far wider' if sd_sim > 2 * sd_real else 'wider' if sd_sim > sd_real else 'less'} than the real ones "
        f"(a standard deviation over images and trials of {sd_sim:.2f} px against the real images' {sd_real:.2f} px). "
        "The",
        "  likely cause, not yet measured: the background share is drawn afresh for every trial and uniform over the",
        "  whole band, so some trials get many wide offsets, where a real image's background edges stay put.",
        f"- **The triangulated corners' shape is {'' if agree(shape['ks']['p']) else 'not '}predicted, frame by "
        "frame.** After the rigid fit the real error is",
        f"  {mm(min(f[1] for f in frames))} to {mm(max(f[1] for f in frames))} mm over the pairs (median "
        f"{mm(shape['real_median'])} mm), the simulated one from the fitted `corner_error`",
        f"  ({est['corner_error.sigma']['value']:.2f} px an axis, the cameras correlated by "
        f"{est['corner_error.correlation']['value']:.2f}) has a median of {mm(shape['simulated_median'])} mm, and the "
        "simulation follows the frames",
        f"  (rank correlation of the real values with the trials' medians {rho:.2f}): of the three frames the real "
        f"corners put highest",
        f"  ({', '.join(f[0] for f in real_top)}: {mm(min(f[1] for f in real_top))}-{mm(max(f[1] for f in real_top))} "
        f"mm) and the three it puts highest ({', '.join(f[0] for f in sim_top)}: medians",
        f"  {mm(min(np.median(f[2]) for f in sim_top))}-{mm(max(np.median(f[2]) for f in sim_top))} mm), {shared} "
        "are the same, since how far a pixel's error moves a triangulated point depends on the",
        f"  board's distance and slant. In {len(inside)} of the {len(frames)} pairs the real value lies within its "
        "frame's 5-95% of trials",
        f"  ({excepts}). Frame {worst}'s right image's corners lie {right[worst]:.2f} px RMS from the model's, where",
        f"  the other frames' lie {min(rest):.2f}-{max(rest):.2f} px, an error of the pose or the calibration more "
        "than of the detector.",
        f"- **The corner error against the model's corners is {err['real_mean'] - err['simulated_mean']:.2f} mm "
        f"{'larger' if err['real_mean'] > err['simulated_mean'] else 'smaller'} than predicted** (medians "
        f"{mm(err['real_median'])} and {mm(err['simulated_median'])}",
        f"  mm, means {mm(err['real_mean'])} and {mm(err['simulated_mean'])} mm: frames "
        f"{', '.join(f for f, _ in off_by[:-1])} and {off_by[-1][0]} are above their trials' medians by "
        f"{min(d for _, d in off_by):.2f}-{max(d for _, d in off_by):.2f} mm). It counts the",
        "  frame's pose, which for the real images is solvePnP's on the left image's corners and for the simulated "
        "ones",
        "  the truth; the simulation has no error of the pose. Nor of the rig (`--no-calibration-error`): with the",
        f"  calibration's covariance drawn (`{' '.join(CHESS_DRAWN[-1:])}`, as by default), the same command predicts "
        f"{mm(drawn['corner_error_3d']['simulated_mean'])} mm",
        f"  against the real {mm(drawn['corner_error_3d']['real_mean'])} (KS p "
        f"{g(drawn['corner_error_3d']['ks']['p'])})"
        f" and RMS lateral offsets of {drawn['offset_rms_px']['simulated_mean']:.2f} px against "
        f"{drawn['offset_rms_px']['real_mean']:.2f}, while the shape",
        f"  error {'hardly moves' if still else 'moves'} ({mm(drawn['corner_shape_3d']['simulated_mean'])} mm): a rig "
        "drawn away from the one "
        "these corners were fitted to moves every",
        "  projected edge and corner, which on these images it does not."]
    return _para(head) + "\n" + _bullets(lines)


# a page's blocks to run or write, as tests/test_docs.py finds them
RUNNABLE = re.compile(r"^<!-- (run|file: ([\w./-]+)) -->\n```(\w*)[^\n]*\n(.*?)^```", re.S | re.M)


def page_runs(ctx: Context, page: str) -> tuple[Path, list[str]]:
    """A page's `<!-- run -->` and `<!-- file: -->` blocks run in order in one folder, as tests/test_docs.py runs them
    (the checkout's scenes/, examples/ and tests/data/ beside them): the folder and each run block's stdout."""
    if ("page", page) not in ctx.made:
        cwd = ctx.tmp / f"runs-{len(ctx.made)}"
        (cwd / "tests").mkdir(parents=True)
        for name in ("scenes", "examples"):
            (cwd / name).symlink_to(ROOT / name)
        (cwd / "tests" / "data").symlink_to(ROOT / "tests" / "data")
        env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
               "MPLBACKEND": "Agg", "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
        outs = []
        for m in RUNNABLE.finditer((ROOT / page).read_text()):
            if m.group(2):
                (cwd / m.group(2)).write_text(m.group(4))
                continue
            argv = (["bash", "-euo", "pipefail", "-c", m.group(4)] if m.group(3) == "sh"
                    else [sys.executable, "-c", m.group(4)])
            print(f"numbers: {page}'s block at line {(ROOT / page).read_text().count(chr(10), 0, m.start()) + 1}",
                  file=sys.stderr)
            outs.append(subprocess.run(argv, cwd=cwd, env=env, check=True, capture_output=True, text=True).stdout)
        ctx.made["page", page] = (cwd, outs)
    return ctx.made["page", page]


DETECTOR_PAGE = "docs/tutorials/measure-your-detector.md"
BOARD_PAGE = "docs/how-to/calibration-board.md"
FENCE = "tests/data/verify/fence.wd"


def _injected() -> dict[str, float]:
    """The fence's `injected` pipeline, by parameter (`edge_loss.fraction`: 0.25), as the scene declares it."""
    from wiredsl import api

    p = api.compile(ROOT / FENCE).pipeline("injected")
    return {f"{s.effect}.{k}": v for s in p.stages for k, v in s.params.items() if isinstance(v, int | float)}


def fence_fit(ctx: Context) -> str:
    """Section 2's verification of the fence images: its stdout, its measured.wd, and which injected values the
    fitted intervals hold."""
    folder, outs = page_runs(ctx, DETECTOR_PAGE)
    verify = folder / "build/fence/verify"
    measured = (verify / "measured.wd").read_text()
    body = measured[measured.index("\npipeline measured {") + 1:]
    est = _estimates(_fit(verify))
    injected = _injected()
    held = [k for k, v in injected.items() if est.get(k, {}).get("low95") is not None
            and est[k]["low95"] <= v <= est[k]["high95"]]
    missed = [k for k in injected if k not in held]
    words = lambda k: k.replace(".", " ").replace("_", " ")  # noqa: E731
    value = lambda k, v: f"{v:g} px" if k.endswith((".range", ".radius", ".sigma")) else _pct(v, 0)  # noqa: E731
    ce = est["corner_error.sigma"]
    rms = float(_note(_fit(verify), "corner_error.sigma", r"RMS ([\d.]+) px"))
    return ("stdout has one line per edge detector and object (Figure 7 as text; the corner detector's counts are "
            "in\n`verification.json` and the fit):\n\n```\n" + outs[1].strip() + "\n```\n\n"
            + _para("and `build/fence/verify` holds `verification.csv` / `.json` (one row per image, feature and "
                    "detector), `figure7.png`, `fit.json` and `measured.wd`, whose pipeline these commands write as:")
            + "\n```\n" + body.rstrip() + "\n```\n\n"
            + _para(f"Injected were {', '.join(f'{words(k)} {value(k, v)}' for k, v in injected.items())}"
                    + ("" if "corner_error.sigma" in injected else ", and no corner localisation error") + ": "
                    + (f"all but the {' and the '.join(words(k) for k in missed)} lie in "
                                               "their intervals" if missed else "all lie in their intervals")
                    + f" (the {ce['value']:.2f} px of `corner_error` is Harris's own on the marks, most of the "
                    f"{rms:.2f} px RMS put down to the mismatches that land within 2 px)."
                    + (" The radius is short because the nearest detected corner is taken, and a checker mark moved "
                       "by r px has corners of its own (its sides' ends, 8 px from its centre) nearer than r to where "
                       "the model puts it." if "corner_mismatch.radius" in missed
                       and est["corner_mismatch.radius"]["high95"] < injected["corner_mismatch.radius"] else "")))


def fence_predict(ctx: Context) -> str:
    """Section 5's two predictions on the fence images: their stdout lines, and what they say."""
    folder, outs = page_runs(ctx, DETECTOR_PAGE)
    gaps, raw = (json.loads((folder / f"build/fence/{d}/prediction.json").read_text())["measures"]
                 for d in ("predict", "predict_raw"))
    fit_gaps, fit_raw = (_estimates(_fit(folder / f"build/fence/{d}")) for d in ("predict", "predict_raw"))
    lines = lambda out: [x for x in out.splitlines() if x.startswith("predict\t")]  # noqa: E731
    both = lines(outs[-1])
    first, second = both[:len(both) // 2], both[len(both) // 2:]
    agree = lambda p: p > 0.01  # noqa: E731
    orw = raw["offset_rms_px"]
    same = all(abs(gaps[k]["simulated_mean"] - raw[k]["simulated_mean"]) < 1e-9 for k in ("corner_error_3d",
                                                                                          "corner_shape_3d"))
    vg, vr = gaps["verified_fraction"], raw["verified_fraction"]
    end_loss = float(_note(_fit(folder / "build/fence/predict"), "edge_loss.fraction", r"end \(([\d.]+) px"))
    return ("Each prints a line a measure after the Figure 7 line (the corner errors in mm):\n\n```\n"
            + "\n".join(first) + "\n```\n\nand, with `--edge-loss raw`,\n\n```\n"
            + next(x for x in second if "\tverified_fraction\t" in x) + "\n```\n\n"
            + _para(f"(the offset line nearly the same, simulated {orw['simulated_mean']:.3f} px, KS p "
                    f"{orw['ks']['p']:.3f}; the corner lines {'the same' if same else 'close'}). The offsets and the "
                    "triangulated corners are "
                    + ("predicted either way" if all(agree(m[k]["ks"]["p"]) for m in (gaps, raw)
                                                      for k in ("offset_rms_px", "corner_error_3d", "corner_shape_3d"))
                       else "not all predicted")
                    + f"; the corner errors are large here (about {gaps['corner_error_3d']['real_mean'] / 10:.0f} cm "
                    "RMS) because the images were drawn with a fifth of the corners moved by up to 8 px, which the "
                    "fitted `corner_mismatch` simulates too. With the default `--edge-loss gaps` the fitted "
                    f"{_pct(fit_gaps['edge_loss.fraction']['value'])} is the loss the pipeline injected, but the "
                    f"simulation verifies {_pct(vg['simulated_mean'])} of the model where Canny verified "
                    f"{_pct(vg['real_mean'])}: Canny also loses about "
                    f"{end_loss:.1f}"
                    " px at each end of each gap, which the simulated strokes do not. `--edge-loss raw` fits "
                    f"everything Canny lost ({_pct(fit_raw['edge_loss.fraction']['value'])}), and the verified "
                    f"fractions {'agree' if agree(vr['ks']['p']) else 'still differ'}."))


CALIBRATION_CHECK = "python docs/scripts/calibrate_opencv_stereo.py --monte-carlo 800"


def _script(ctx: Context, command: str, *extra: str) -> str:
    """`python SCRIPT ARGS` (the page's command, then `extra`) run in the checkout, once: its stdout."""
    key = ("script", command, *extra)
    if key not in ctx.made:
        print(f"numbers: {command} {' '.join(extra)}", file=sys.stderr)
        ctx.made[key] = subprocess.run([sys.executable, *command.split()[1:], *extra], cwd=ROOT, capture_output=True,
                                       text=True, check=True).stdout
    return ctx.made[key]


def calibration_check(ctx: Context) -> str:
    """The script's calibration and its covariance against re-calibrations of noisier corners (the JSON line
    `--monte-carlo` prints last)."""
    got = json.loads(_script(ctx, CALIBRATION_CHECK).splitlines()[-1])
    ratio, joint = got["ratio"], got["joint_ratio"]
    off = max(abs(r - 1) for r in ratio.values())
    f = sorted([joint["left.f"], joint["right.f"]])
    return _para(
        f"`{CALIBRATION_CHECK}` (writes nothing): the script's calibration has a stereoCalibrate rms of "
        f"{got['rms']:.3f} px and a {got['baseline_mm']:.1f} mm baseline at the assumed square, and its corner "
        f"noise is {got['sigma']:.3f} px (n = {got['n']}, p = {got['p']}). Calibrating the detected corners plus "
        f"fresh N(0, sigma^2) noise as the script does, {got['runs']} times (seed {got['seed']}), spreads every "
        f"parameter within {100 * off:.0f}% of the standard deviations above (Monte-Carlo over linearised "
        f"{min(ratio.values()):.2f} to {max(ratio.values()):.2f}), and the {got['big_correlations']} large "
        f"correlations (|rho| > 0.5) agree within {got['correlation_difference']:.2f}; "
        "`tests/test_calibration_covariance.py` does it 200 times (within 20%, and 0.15). Linearising a single "
        "joint estimate of everything instead would understate what this two-stage calibration delivers, `tz` by "
        f"{joint['right.tz']:.1f} times, `f` by {f[0]:.1f} and {f[1]:.1f} times and `rx` by {joint['right.rx']:.1f} "
        "times.")


CHESSBOARD_FIGURE = "python docs/scripts/chessboard_figure.py"


def chessboard_figure(ctx: Context) -> str:
    fig = _module("docs/scripts/chessboard_figure.py")
    return ("![left01.jpg; the scene rendered from its pose (--no-effects --edges none); the same through the paper "
            "pipeline (--edges step --faces none)](../figures/chessboard_real_and_rendered.png)\n\n"
            + _para(f"Drawn by `{CHESSBOARD_FIGURE}`: `{fig.REAL}` beside `{fig.RENDERS[0]}` and `{fig.RENDERS[1]}` "
                    "(each image at half size)."))


def _chessboard_png(ctx: Context) -> Path:
    out = ctx.tmp / "chessboard_real_and_rendered.png"
    _script(ctx, CHESSBOARD_FIGURE, "-o", str(out))
    return out


def board_poses_sentence(ctx: Context) -> str:
    """What the calibration board page's `board_poses` example prints (its run block, run as the page shows it)."""
    _, outs = page_runs(ctx, BOARD_PAGE)
    found = [line.split() for line in outs[0].splitlines()]
    rms = [f[-2] for f in found]
    return _para(f"It prints a line an image: {'both are' if all(f[1] == 'True' for f in found) else 'not all are'} "
                 f"found, with an RMS of {' and '.join(rms)} px.")


HOLDOUT = "python benchmarks/holdout_chessboard.py"


def holdout_table(ctx: Context) -> str:
    """The held-out table benchmarks/holdout_chessboard.py prints (its four verify --holdout runs)."""
    print(f"numbers: {HOLDOUT}", file=sys.stderr)
    out = subprocess.run([sys.executable, *HOLDOUT.split()[1:]], cwd=ROOT, capture_output=True, text=True, check=True)
    return "\n".join(line for line in out.stdout.splitlines() if line.startswith("|")) + "\n"


BLUR = "python benchmarks/blur_magnitudes.py"


def blur_table(ctx: Context) -> str:
    """benchmarks/blur_magnitudes.py's table, and where Canny starts to lose the smeared edges."""
    print(f"numbers: {BLUR}", file=sys.stderr)
    out = subprocess.run([sys.executable, *BLUR.split()[1:]], cwd=ROOT, capture_output=True, text=True, check=True)
    table = [line for line in out.stdout.splitlines() if line.startswith("|")]
    rows = [[c.strip() for c in line.split("|")[1:-1]] for line in table[2:]]
    kept = [float(r[2]) for r in rows if float(r[3].split("[")[1].split(",")[0]) == 0]  # its interval holds 0
    lost = [(float(r[2]), float(r[3].split()[0])) for r in rows if float(r[3].split()[0]) >= 0.5]
    first = min(lost) if lost else None
    return (f"`{BLUR}` (seed 39; ten images a setting):\n\n" + "\n".join(table) + "\n\n"
            f"Canny's loss is nil (its interval holds 0) up to {max(kept):g} px of blur across the edge, and"
            + (f" {100 * first[1]:.0f}% from {first[0]:g} px: a cliff, not a slope, where the smeared step's gradient "
               "falls below the high threshold." if first else " nowhere 50% or more.") + "\n")


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


MESH_CAD_OR_SCAN = "python docs/scripts/mesh_cad_or_scan.py"


def mesh_cad_or_scan(ctx: Context) -> str:
    """The script's table of planar shares and features, and what its JSON line says of the threshold's margins."""
    out = _script(ctx, MESH_CAD_OR_SCAN).splitlines()
    got = json.loads(out[-1])
    cad = {k: v for k, (v, scan) in got["shares"].items() if not scan}
    scans = {k: v for k, (v, scan) in got["shares"].items() if scan and v > 0}
    low, high = min(cad, key=cad.get), max(scans, key=scans.get)
    threshold, rounded = got["threshold"], got["rounded"].values()
    where = {"scenes/meshes/cone.ply": "the cone of `scenes/meshes/`, a fan base and a side of slivers"}.get(
        low, f"`{low}`")
    share = lambda p: f"{100 * p:.0f}%" if p >= 0.1 else f"{100 * p:.2f}%"  # noqa: E731
    return (f"`{MESH_CAD_OR_SCAN}`:\n\n" + "\n".join(x for x in out if x.startswith("|")) + "\n\n"
            + _para(f"The smallest CAD share met, {share(cad[low])} ({where}), is {cad[low] / threshold:.1f} times the "
                    f"threshold; the largest scan share, {share(scans[high])}, {scans[high] / threshold:.2f} of it. "
                    "Rounding does not blur it: the four parts moved 100 m from their origin and rounded to float32 "
                    f"(binary STL's numbers) still measure {100 * min(rounded):.0f}-{100 * max(rounded):.0f}%."))


CONTOUR_SMOOTHING = "python docs/scripts/contour_smoothing.py"


def contour_smoothing(ctx: Context) -> str:
    """The noisy sphere's contour chains and their distance from its outline, smoothed and not (the script's line)."""
    got = json.loads(_script(ctx, CONTOUR_SMOOTHING))
    smooth, raw = got["2"], got["0"]
    return _para(f"On the noisy sphere of `tests/test_mesh_features.py` ({got['triangles']:,} triangles, noise of "
                 f"0.1 of an edge; `{CONTOUR_SMOOTHING}`), the contour is {smooth['chains']} chains within "
                 f"{smooth['off_deg']:.0f} deg of the analytic outline, against {raw['chains']} bits up to "
                 f"{raw['off_deg']:.0f} deg off from the triangles' own normals.")


EPIPOLAR_PINHOLE = "python docs/scripts/epipolar_pinhole.py"


def epipolar_pinhole(ctx: Context) -> str:
    """How far the pinhole line is from the epipolar curve (the script's line; tests/test_effects.py checks the
    fisheye's three figures in this text too)."""
    got = json.loads(_script(ctx, EPIPOLAR_PINHOLE))
    return _para(
        "The pinhole line the band used before would be far off on `scenes/fisheye.wd`'s cameras (first pose; each "
        "pixel's own ray moved along the baseline and projected through the lens, against the pinhole direction; "
        f"`{EPIPOLAR_PINHOLE}`): the two agree within {got['within_100px']:.1f} deg up to 100 px from the centre, but "
        f"differ by {got['median']:.1f} deg at the median pixel, and by more than the default 5 deg band at "
        f"{got['over_5deg']:.0%} of the pixels, so that band dropped other features than an epipolar matcher would "
        f"miss. Under the lab's mild barrel distortion the line is at most {got['lab_max']:.2f} deg off.")


LBRACKET = "python docs/scripts/lbracket_features.py"


def lbracket_features(ctx: Context) -> str:
    """The real L bracket's features at the defaults (the script's line)."""
    g = json.loads(_script(ctx, LBRACKET))
    radii = [f"{r:g}" for r in g["radii_mm"]]
    poly = f"{g['polylines']} polylines, " if g["polylines"] else ""
    return _para(
        "A real part, an L bracket with counterbored holes exported from CAD (`tests/meshes/lbracket.stl`, "
        f"{g['triangles']} triangles, origin and licence in `tests/meshes/README.md`), gives {g['lines']} lines, {poly}"
        f"{g['corners']} corners, {g['rims']} rims (radii {', '.join(radii[:-1])} and {radii[-1]} mm: holes and their "
        f"counterbores), {g['silhouettes']} silhouettes (the holes' walls), {g['faces']} faces and {g['occluders']} "
        f"occluding triangles (`{LBRACKET}`).")


GYM_EVALUATE = "python examples/gym/evaluate.py --episodes 10"


def gym_evaluate(ctx: Context) -> str:
    """The goal-seeking controller against random actions, as the example prints them."""
    got = {m.group(1): (float(m.group(2)), float(m.group(3)), float(m.group(4))) for m in re.finditer(
        r"^\s*(\w+): success ([\d.]+), mean return (-?[\d.]+), mean steps ([\d.]+)", _script(ctx, GYM_EVALUATE), re.M)}
    (gs, gr, gn), (rs, rr, rn) = got["goal"], got["random"]
    goal = "reached it every time" if gs == 1 else f"reached it in {gs:.0%} of the episodes"
    rand = "never did" if rs == 0 else f"did in {rs:.0%}"
    return _para(f"With `--episodes 10` (`{GYM_EVALUATE}`) the controller that steers to the goal pose {goal} (mean "
                 f"{gn:.1f} steps, return {gr:.1f}) and random actions {rand} (return {rr:.1f}, {rn:.1f} steps).")


MESH_NOISE = "python docs/scripts/mesh_noise.py"


def mesh_noise(ctx: Context) -> str:
    """When the box and the gear read as scans and when they gain false creases (the script's line)."""
    got = json.loads(_script(ctx, MESH_NOISE))
    pct = lambda x: f"{100 * x:g}%"  # noqa: E731
    told, before = [], True
    for name, words in (("box", "a box split four times"), ("gear", "a 30-tooth gear")):
        rows = got[name]["rows"]
        clean = rows[0]["lines"]
        scan = next(r for r in rows if r["scan"])
        creases = [r for r in rows if r["lines"] > clean]
        before = before and bool(creases) and scan["level"] < creases[0]["level"]
        more = "; ".join(f"{r['lines']} at {pct(r['level'])}" for r in creases[1:3])
        told.append(f"{words} ({got[name]['triangles']:,} triangles, {clean} lines clean) reads as a scan from "
                    f"{pct(scan['level'])} of the largest height and gains its first false creases at "
                    f"{pct(creases[0]['level'])} ({creases[0]['lines']} lines" + (f"; {more})" if more else ")")
                    if creases else f"{words} reads as a scan from {pct(scan['level'])} and gains no false crease")
    return _para(f"False creases come later (`{MESH_NOISE}`, one seed): {told[0]}; {told[1]}. "
                 + ("So a noisy part is budgeted before its noise can swarm." if before else
                    "So a noisy part can swarm before it is budgeted."))


NPZ_SHARE = "wiredsl build scenes/lab.wd --pipeline paper --trials 256 --seed 1 --format npz"


def npz_share(ctx: Context) -> str:
    """What the views, the conics and layout 2's three stroke columns take of an npz dump (its members' bytes)."""
    import zipfile

    import numpy as np

    npz = ctx.wiredsl(*NPZ_SHARE.split()[1:]) / "features.npz"
    sizes: dict[str, int] = {}
    with zipfile.ZipFile(npz) as z:
        for i in z.infolist():
            name = i.filename.removesuffix(".npy").split("_", 1)[-1] if i.filename.startswith("b") else i.filename
            sizes[name] = sizes.get(name, 0) + i.file_size
    with np.load(npz) as a:
        columns = a[next(k for k in a.files if k.endswith("_strokes"))].shape[1]
    views = sum(v for k, v in sizes.items() if k.startswith(("view", "conic")))
    added = views + 3 / columns * sizes["strokes"]
    total = npz.stat().st_size
    return _para(f"These views, the conics and the three stroke columns that layout 2 added make up "
                 f"{added / total:.0%} of the file ({added / 2**20:.2f} of {total / 2**20:.1f} MiB for 256 lab "
                 f"trials of `paper`, `{NPZ_SHARE}`).")


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


CLOSED_LOOP = "python examples/closed_loop/drive_to_bin.py --trials 100"


def closed_loop_table(ctx: Context) -> str:
    """The closed loop's success rate and steps per lateral shift (its closed_loop.json, CI's run reused)."""
    rows = json.loads((ctx.example(CLOSED_LOOP, "closed_loop", "closed_loop.json") / "closed_loop.json")
                      .read_text())["rows"]
    cell = lambda x: "" if x is None else f"{x:.1f}"  # noqa: E731  (no successful trial: no steps)
    return "\n".join([
        f"`{CLOSED_LOOP}`, its `closed_loop.json`:", "",
        "| lateral shift range (px) | " + " | ".join(f"{r['lateral_shift_px']:g}" for r in rows) + " |",
        "|---|" + "---|" * len(rows),
        "| success rate | " + " | ".join(f"{r['success_rate']:.2f}" for r in rows) + " |",
        "| mean steps (successful trials) | " + " | ".join(cell(r["mean_steps"]) for r in rows) + " |"]) + "\n"


PNP = ("examples/pnp_plugin/scenes/pnp_lab.wd", "pose_sources", "pnp_study")
PNP_PLUGIN = ("wiredsl-pnp", "pip install ./examples/pnp_plugin")  # its distribution, and how to install it
PNP_STATS = [("rotation_error", "the rotation error"), ("position_error", "the position error")]


def _words(factor: str) -> str:
    return factor.rsplit(".", 1)[0].replace("_", " ")


def pnp_sobol(ctx: Context) -> str:
    """The pnp plug-in's Sobol' study: which corner sources its pose errors and its solving depend on."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        version(PNP_PLUGIN[0])
    except PackageNotFoundError:
        raise BlockError(f"pnp-sobol needs the plug-in package {PNP_PLUGIN[0]!r}, which is not installed: "
                         f"{PNP_PLUGIN[1]}") from None
    sobol = [s for s in json.loads((ctx.study(*PNP) / "table.json").read_text())["sobol"] if s["measure"] == "pnp"]

    def ranked(stat: str) -> list[dict]:
        return sorted([s for s in sobol if s["statistic"] == stat and s["total_order"] is not None],
                      key=lambda s: -s["total_order"])

    def listing(got: list[dict]) -> str:
        named = [f"{_words(s['factor'])} {s['total_order']:.2f}" for s in got]
        return ", ".join(named[:-1]) + " and " + named[-1]

    def ci(x: list[float]) -> str:
        return f"{x[0]:.2f} to {x[1]:.2f}"

    by = {stat: ranked(stat) for stat, _ in PNP_STATS}
    text = [f"From `wiredsl study {PNP[0]} {PNP[1]}`'s `table.json`, the total-order indices of "
            + ", and of ".join(f"{words} are {listing(by[stat])}" for stat, words in PNP_STATS) + "."]
    alone = {stat: [s for s in by[stat] if s["first_order_ci"] and s["first_order_ci"][0] > 0] for stat in by}
    told = "; ".join(f"{s['first_order']:.2f}, {ci(s['first_order_ci'])}, for {words}"
                     for stat, words in PNP_STATS for s in alone[stat])
    factors = {s["factor"] for a in alone.values() for s in a}
    if len(factors) == 1 and all(alone.values()):
        text.append(f"Only {_words(factors.pop())} has a first-order index whose 95% interval excludes 0 ({told}): "
                    "it is the only source that moves the errors by itself.")
    elif factors:
        text.append(f"The first-order indices whose 95% interval excludes 0: {told}.")
    else:
        text.append("No first-order index has a 95% interval that excludes 0.")
    wide = max((s for a in by.values() for s in a), key=lambda s: s["total_order_ci"][1] - s["total_order_ci"][0])
    wide_in = next(words for stat, words in PNP_STATS if wide["statistic"] == stat)
    apart = all(a[0]["total_order_ci"][0] > max(s["total_order_ci"][1] for s in a[1:]) for a in by.values())
    if apart:
        text.append("Each error's leading total-order interval lies above the other three's.")
    else:
        text.append(f"The total-order intervals overlap (the widest, {_words(wide['factor'])}'s for {wide_in}, "
                    f"runs from {ci(wide['total_order_ci'])}), so with this few base points the order of the "
                    "total-order indices is not a finding.")
    (solved, *_) = ranked("solved")
    text.append(f"Whether a pose is found at all (`solved`) is driven by {_words(solved['factor'])} (total order "
                f"{solved['total_order']:.2f}, 95% interval {ci(solved['total_order_ci'])}).")
    return _para(" ".join(text))


SPEED = ("scenes/studies/lab_study.wd", "speed", "speed")
SPEED_MORE = 0.10  # "adds more than 10% to the corner error": the sentence's threshold over the slowest point's
SPEED_FLAT = 0.02  # recognition "does not limit the speed" while its range over the study is narrower than this


def speed_table(ctx: Context) -> str:
    """The speed study's corner and median 3D errors, in sync and 10 ms late, and the speed each first costs
    more than SPEED_MORE over the slowest point's corner error."""
    rows = _rows(ctx.study(*SPEED))
    speeds = sorted({r["values"]["path.speed"] for r in rows})
    syncs = sorted({r["values"]["rig.sync"] for r in rows})
    late = syncs[-1]

    def at(measure: str, stat: str, speed: float, sync: float) -> dict:
        (r,) = [r for r in rows if (r["measure"], r["statistic"]) == (measure, stat)
                and r["values"]["path.speed"] == speed and r["values"]["rig.sync"] == sync]
        return r

    ms = f"{late * 1000:g} ms late"
    lines = [f"`{BLOCKS['study-speed-table'].command}`, from its `table.csv` (mean ± se over its trials):", "",
             f"| speed (m/s) | corner error, in sync (m) | corner error, {ms} (m) | median 3D error, in sync (m) | "
             f"median 3D error, {ms} (m) | corners a view, {ms} | PGH recognition, {ms} |",
             "|---|---|---|---|---|---|---|"]
    pm = lambda r: f"{_f3(r['mean'])} ± {_f3(r['sem'])}"  # noqa: E731
    for v in speeds:
        lines.append(f"| {v:g} | {pm(at('stereo3d', 'corner_error', v, 0))} | "
                     f"{pm(at('stereo3d', 'corner_error', v, late))} | {pm(at('stereo3d', 'error_median', v, 0))} | "
                     f"{pm(at('stereo3d', 'error_median', v, late))} | "
                     f"{at('stereo3d', 'corners', v, late)['mean']:.2f} | "
                     f"{at('pgh', 'recognition', v, late)['mean']:.1%} |")

    def first_over(sync: float) -> str:
        base = at("stereo3d", "corner_error", speeds[0], sync)["mean"]
        over = [v for v in speeds if at("stereo3d", "corner_error", v, sync)["mean"] > (1 + SPEED_MORE) * base]
        return f"from {over[0]:g} m/s" if over else f"at none up to {speeds[-1]:g} m/s"

    def times(sync: float) -> float:
        return at("stereo3d", "corner_error", speeds[-1], sync)["mean"] / at(
            "stereo3d", "corner_error", speeds[0], sync)["mean"]

    rec = [at("pgh", "recognition", v, s)["mean"] for v in speeds for s in syncs]
    readout = rows[0]["values"]["camera.cam_l.readout"]
    end = speeds[-1]
    limit = (": the 3D data, not recognition, limit the robot's speed" if max(rec) - min(rec) < SPEED_FLAT
             else "")
    lines += ["", f"With both cameras in sync, the {readout * 1000:g} ms rolling shutters add more than "
                  f"{SPEED_MORE:.0%} to the corner error of the slowest point ({speeds[0]:g} m/s) {first_over(0)}, "
                  f"and {times(0):.2f} times it at {end:g} m/s; with the right camera {ms}, {first_over(late)}, "
                  f"and {times(late):.2f} times it at {end:g} m/s. PGH recognition stays between {min(rec):.1%} "
                  f"and {max(rec):.1%} at every speed and offset{limit}."]
    return "\n".join(lines) + "\n"


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
    "chessboard-verified": Block(DETECTOR_PAGE, CHESSBOARD, chess_verified_sentence,
                                 {"docs/figures/verify_opencv_stereo_figure7.png": lambda ctx: ctx.verify(*CHESS_GAPS)
                                  / "figure7.png"}),
    "chessboard-fit": Block(DETECTOR_PAGE, CHESSBOARD, chess_fit_table,
                            {"docs/figures/verify_opencv_stereo_measured.wd": lambda ctx: ctx.verify(*CHESS_GAPS)
                             / "measured.wd"}),
    "chessboard-fit-prose": Block(DETECTOR_PAGE, CHESSBOARD, chess_fit_prose),
    "chessboard-predict-bullets": Block(DETECTOR_PAGE, CHESSBOARD, chess_predict_bullets),
    "fence-fit": Block(DETECTOR_PAGE, "the page's own commands (section 2)", fence_fit),
    "fence-predict": Block(DETECTOR_PAGE, "the page's own commands (section 5)", fence_predict),
    "board-poses": Block(BOARD_PAGE, "the page's own example", board_poses_sentence),
    "calibration-check": Block("docs/how-to/calibration-board.md", CALIBRATION_CHECK, calibration_check),
    "chessboard-figure": Block("docs/how-to/calibration-board.md", CHESSBOARD_FIGURE, chessboard_figure,
                               {"docs/figures/chessboard_real_and_rendered.png": _chessboard_png}),
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
    "blur-table": Block("docs/tutorials/path.md", BLUR, blur_table),
    "circle-grids": Block("docs/how-to/calibration-board.md", CIRCLES, circle_grids,
                          {"docs/figures/verify_by_kind.png": lambda ctx: _circle_grids(ctx)[1]}),
    "mesh-cad-or-scan": Block("docs/how-to/meshes-at-full-size.md", MESH_CAD_OR_SCAN, mesh_cad_or_scan),
    "contour-smoothing": Block("docs/how-to/meshes-at-full-size.md", CONTOUR_SMOOTHING, contour_smoothing),
    "epipolar-pinhole": Block("docs/explanation/uncertainty.md", EPIPOLAR_PINHOLE, epipolar_pinhole),
    "lbracket-features": Block("docs/tutorials/mesh.md", LBRACKET, lbracket_features),
    "gym-evaluate": Block("docs/tutorials/closed-loop.md", GYM_EVALUATE, gym_evaluate),
    "mesh-noise": Block("docs/how-to/meshes-at-full-size.md", MESH_NOISE, mesh_noise),
    "npz-share": Block("docs/reference/dumps.md", NPZ_SHARE, npz_share),
    "closed-loop-table": Block("docs/tutorials/closed-loop.md", CLOSED_LOOP, closed_loop_table),
    "pnp-sobol": Block("docs/reference/plugins.md", f"wiredsl study {PNP[0]} {PNP[1]}", pnp_sobol),
    "study-speed-table": Block(
        "docs/tutorials/path.md", "wiredsl study scenes/studies/lab_study.wd speed", speed_table,
        {"docs/figures/study_speed_corner_error.png": _plot(SPEED, "stereo3d.corner_error.png")}),
    "study-sources-sobol": Block(
        "docs/tutorials/study.md", "wiredsl study scenes/studies/lab_study.wd sources", sobol_sentence,
        {"docs/figures/study_sources_sobol.png": _plot(SOURCES, "sobol.png")}),
}


def numbers_drift(page: str, fresh: str, tol: float = NUMBER_TOL) -> list[str]:
    """How `fresh` differs from `page`: words exactly, numbers within `tol` units of the page's last digit."""
    if NUMBER.sub("#", " ".join(page.split())) != NUMBER.sub("#", " ".join(fresh.split())):  # a rewrap is no drift
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
    if page.suffix in (".svg", ".wd"):  # the data it draws (a file it writes), as text: numbers within their last digit
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


# ------------------------------------------------------------------ numbers outside the blocks

INVENTORY = "docs/numbers-outside-blocks.tsv"
MEASURED = re.compile(r"(?<![\w.])(?<![A-Za-z]-)\d[\d,]*(?:\.\d+)?(?![\d.]*\.\d)"
                      r"(?:\s?(?:%|px\b|mm\b|cm\b|ms\b|s\b|m\b|deg\b|mrad\b|x\b|times\b))"
                      r"|(?<![\w.])(?<![A-Za-z]-)\d+\.\d+(?![\d.]*\.\d)")
HIDDEN = [BLOCK, re.compile(r"^<!-- generated: [\w-]+ -->\n.*?^<!-- /generated -->$", re.M | re.S),
          re.compile(r"^ *```.*?^ *```", re.M | re.S), re.compile(r"<!--.*?-->", re.S), re.compile(r"`[^`\n]*`"),
          re.compile(r"\]\([^)]*\)")]  # blocks, generated reference, fences, comments, code spans, link targets


def outside_blocks(root: Path) -> list[tuple[str, int, str, str]]:
    """Every measured-looking number (a percentage, a figure with a unit, a decimal) of README.md and docs/*.md that
    no block makes: (page, line, the number, the words before it on its line)."""
    found = []
    for path in sorted([root / "README.md", *(root / "docs").rglob("*.md")]):
        if not path.is_file():
            continue
        text = path.read_text()
        for rx in HIDDEN:  # blanked, its lines kept
            text = rx.sub(lambda m: re.sub(r"[^\n]", " ", m.group(0)), text)
        for i, line in enumerate(text.splitlines(), 1):
            for m in MEASURED.finditer(line):
                before = " ".join(line[:m.start()].split()[-5:])
                found.append((path.relative_to(root).as_posix(), i, m.group(0), before))
    return found


def inventory_key(page: str, number: str, before: str) -> str:
    return f"{page}\t{number}\t{before}"


def scan(root: Path, write: bool = False) -> list[str]:
    """The numbers outside the blocks against the inventory (INVENTORY: each one a reader has been told is a
    definition, a machine's figure beside its script, or not yet reproduced): what is in neither, and what the
    inventory lists that the pages no longer hold. `write` rewrites the inventory to what the pages hold, keeping
    each kept entry's class and giving a new one `unreviewed`."""
    path = root / INVENTORY
    listed = {}
    if path.is_file():
        for line in path.read_text().splitlines():
            if line and not line.startswith("#"):
                cls, key = line.split("\t", 1)
                listed[key] = cls
    found = outside_blocks(root)
    keys = {inventory_key(p, n, b): (p, i, n) for p, i, n, b in found}
    if write:
        rows = [f"{listed.get(k, 'unreviewed')}\t{k}" for k in sorted(keys)]
        head = ["# Measured-looking numbers in README.md and docs/ that no docs/reproduce.py block makes, one a line:",
                "# class, page, number, the words before it. Classes: definition (a default, a unit, a version, an",
                "# input, the paper's value), machine (a CPU figure beside the script that prints it), unreviewed",
                "# (measured, not yet reproduced: make it a block, cite a block, or remove it).",
                "# `python docs/reproduce.py --scan` checks it; `--scan --write` rewrites it."]
        from wiredsl.files import write_atomic

        write_atomic(path, "\n".join(head + rows) + "\n")
        return []
    out = [f"{p}:{i}: {n!r} is outside any numbers block and not in {INVENTORY}: make it a block, cite a block's "
           "number, or list it (a definition)" for k, (p, i, n) in keys.items() if k not in listed]
    out += [f"{INVENTORY}: {k!r} is no longer on its page (remove it)" for k in listed if k not in keys]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = ap.add_mutually_exclusive_group(required=True)
    mode.add_argument("--write", action="store_true", help="regenerate every block and figure in place")
    mode.add_argument("--check", action="store_true", help="regenerate and compare; exit 1 on a drift")
    mode.add_argument("--list", action="store_true", help="each block, its page, command and figures")
    mode.add_argument("--scan", action="store_true", help=f"numbers outside the blocks against {INVENTORY} (with "
                      "--write-inventory: rewrite it)")
    ap.add_argument("--write-inventory", action="store_true", help="with --scan: rewrite the inventory")
    ap.add_argument("--reuse", type=Path, help="a folder of study outputs (CI's build/ci) to read, not rerun")
    ap.add_argument("names", nargs="*", help="only these blocks (default: all)")
    a = ap.parse_args(argv)
    unknown = [n for n in a.names if n not in BLOCKS]
    if unknown:
        ap.error(f"unknown block {unknown[0]!r}: one of {', '.join(BLOCKS)}")
    blocks = {n: b for n, b in BLOCKS.items() if not a.names or n in a.names}
    if a.scan:
        problems = scan(ROOT, write=a.write_inventory)
        for p in problems:
            print(f"numbers: {p}", file=sys.stderr)
        return 1 if problems else 0
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
        except BlockError as exc:
            print(f"numbers: error: {exc}", file=sys.stderr)
            return 1
    for p in problems:
        print(f"numbers: drift: {p}", file=sys.stderr)
    if a.check and not problems:
        print(f"numbers: {len(blocks)} blocks and their figures hold", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
