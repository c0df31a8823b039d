"""The `wiredsl` command line (click). Data on stdout, diagnostics on stderr.

Exit codes: 0 ok, 1 invalid input, 2 usage error, 3 internal error (a bug).
"""

from __future__ import annotations

import contextlib
import gc
import json
import os
import sys

import click

from wiredsl import DEFAULT_VISIBILITY, VISIBILITIES, __version__, install_hint
from wiredsl.cli_base import (
    EXIT_INVALID,
    FiniteRange,
    auto_visibility,
    diagnostics_option,
    folder_name,
    guarded,
    report,
    setup_errors,
)

# Commands in modules of their own, imported when they run or help is asked for (their options cost the lab's
# build and check some 3 ms CPU of click's decorators): name -> (module, attribute).
LAZY_COMMANDS = {"export": ("wiredsl.export", "export"), "render": ("wiredsl.render_cli", "render"),
                 "verify": ("wiredsl.verify.cli", "verify")}


class _Group(click.Group):
    """click's group, with LAZY_COMMANDS listed always and imported on first use."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted({*super().list_commands(ctx), *LAZY_COMMANDS})

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name in LAZY_COMMANDS and name not in self.commands:
            import importlib

            module, attribute = LAZY_COMMANDS[name]
            self.add_command(getattr(importlib.import_module(module), attribute), name)
        return super().get_command(ctx, name)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="wiredsl")
def main() -> None:
    """Simulate what a stereo robot's vision system sees of a wire-frame world."""
    _tune_gc()


def entry() -> None:
    """The console script and `python -m wiredsl`: the command, then an exit without the interpreter's
    teardown. By then every output is written and closed (atomic writes; `guarded` flushes stdout where a
    closed pipe is caught, and the study's pools and clients are closed by their `with`); what teardown adds
    is freeing every object and module one by one, numba's above all: measured 0.36 s of CPU after a
    300-trial kernel build of the lab and 0.06 s after its plain build. The `atexit` functions still run
    (a plug-in's, coverage's), and under a profiler or a tracer (cProfile, a debugger) the exit is the usual
    one, so that they can report. `main` itself (click's CliRunner, a program calling it) exits as usual."""
    import atexit

    try:
        main()
        code = 0
    except SystemExit as exc:
        code = exc.code
    if sys.getprofile() is not None or sys.gettrace() is not None:
        sys.exit(code)
    if code is None:
        code = 0
    elif not isinstance(code, int):  # sys.exit("message"), as Python would print it
        print(code, file=sys.stderr)
        code = 1
    run_exitfuncs = getattr(atexit, "_run_exitfuncs", None)  # CPython's; what teardown would call first
    if run_exitfuncs is not None:
        run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            if not stream.closed:
                stream.flush()
        except (OSError, ValueError):  # the reader went away: nothing left to say to it
            pass
    os._exit(code)


GC_YOUNG = 200_000  # allocations between collections of the young generation (CPython's default: 700)


def _tune_gc() -> None:
    """Collect garbage cycles less often, as mypy does. A command builds many long-lived objects and few
    cycles (the parser's tables, pydantic's validators, numpy's and wiredsl's modules): with the default
    thresholds the collector scans them again and again and finds next to nothing (some 25 ms CPU of the lab's
    0.4 s build, 10 ms of its check). Cycles are still collected, every GC_YOUNG allocations."""
    if gc.get_threshold()[0] < GC_YOUNG:
        gc.set_threshold(GC_YOUNG, 30, 30)


@main.command()
@click.argument("files", nargs=-1, required=True, type=click.Path(dir_okay=False))
@diagnostics_option
@guarded
def check(files: tuple[str, ...], diagnostics: str) -> None:
    """Check scene FILES; exit 0 when all are valid, 1 with diagnostics."""
    from wiredsl.diagnostics import WiredslError, read_sources
    from wiredsl.language.compile import compile_file

    failed = False
    all_diags = []
    for f in files:
        try:
            scene, warnings, program = compile_file(f)
            all_diags += warnings
            if diagnostics == "text":  # each mesh's size and bounds, as scaled and placed
                for span, text in program.mesh_reports + program.motion_reports:
                    click.echo(f"{span}: note: {text}", err=True)
                if program.mesh_reports:  # and what exact visibility would cost a build of every pose
                    _exact_cost_note(scene, program)
        except WiredslError as err:
            all_diags += err.diagnostics
            failed = True
    report(all_diags, read_sources(all_diags), diagnostics)
    if failed:
        sys.exit(EXIT_INVALID)
    if diagnostics == "text":
        click.echo(f"{len(files)} file{'s' * (len(files) != 1)} ok", err=True)


@main.command("compile")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("-o", "--output", default="-", show_default=True, help="Output file, or - for stdout.")
@diagnostics_option
@guarded
def compile_cmd(file: str, output: str, diagnostics: str) -> None:
    """Compile FILE to the scene JSON (valid against schema/scene.schema.json)."""
    from wiredsl.files import json_text, write_atomic
    from wiredsl.language.compile import compile_file

    scene, warnings, program = compile_file(file)
    report(warnings, program.sources, diagnostics)
    text = json_text(scene.model_dump(mode="json"), where="scene")
    if output == "-":
        sys.stdout.write(text)
    else:
        write_atomic(_file_output(output), text)


@main.command()
@click.argument("files", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("--check", "check_only", is_flag=True, help="Only report files that are not in canonical form.")
@diagnostics_option
@guarded
def fmt(files: tuple[str, ...], check_only: bool, diagnostics: str) -> None:
    """Rewrite FILES in canonical form, keeping comments (--check: exit 1 if any would change)."""
    from pathlib import Path

    from wiredsl.files import write_atomic
    from wiredsl.language.ast import read_source
    from wiredsl.language.fmt import format_text

    changed = []
    for f in files:
        text = read_source(Path(f))
        new = format_text(text, f)
        if new != text:
            changed.append(f)
            if not check_only:
                write_atomic(f, new)
    for f in changed:
        click.echo(f"{'would reformat' if check_only else 'reformatted'} {f}", err=True)
    if check_only and changed:
        sys.exit(EXIT_INVALID)


@main.command()
@click.argument("name", type=click.Choice(["scene", "features", "viewdep", "manifest", "study", "study-manifest"]))
@guarded
def schema(name: str) -> None:
    """Print the JSON Schema of a scene, a features dump, a view-dependency file, a build manifest or a study
    table."""
    from wiredsl.io.schema import text

    sys.stdout.write(text(name))


@main.command()
@click.argument("dumps", nargs=-1, required=True, type=click.Path(dir_okay=False))
@guarded
def validate(dumps: tuple[str, ...]) -> None:
    """Validate scenes, feature dumps (JSON, JSON lines, npz) and manifests against the schemas."""
    from wiredsl.files import read_regular, regular_size
    from wiredsl.io.layout import npz_problems
    from wiredsl.io.schema import problems

    bad = 0
    for path in dumps:
        try:  # regular files only: /dev/zero or a FIFO is refused before it is opened
            regular_size(path, 2**63)
            if _is_zip(path) or path.endswith(".npz"):  # features.npz: its layout and its manifest
                msgs = npz_problems(path)
                for m in msgs[:20]:
                    click.echo(f"{path}: error: {m}", err=True)
                bad += bool(msgs)
                continue
            text = read_regular(path, MAX_JSON_BYTES).decode("utf-8")
        except (OSError, ValueError) as exc:  # UnreadableFile and UnicodeDecodeError are ValueErrors
            click.echo(f"{path}: error: cannot read: {getattr(exc, 'strerror', None) or exc}", err=True)
            bad += 1
            continue
        docs = _documents(path, text)
        for where, doc in docs:
            msgs = [doc] if isinstance(doc, str) else problems(doc)
            for m in msgs[:20]:
                click.echo(f"{where}: error: {m}", err=True)
            if len(msgs) > 20:
                click.echo(f"{where}: ... and {len(msgs) - 20} more", err=True)
            bad += bool(msgs)
    if bad:
        sys.exit(EXIT_INVALID)
    click.echo(f"{len(dumps)} dump{'s' * (len(dumps) != 1)} valid", err=True)


def _is_zip(path: str) -> bool:
    try:
        with open(path, "rb") as fh:
            return fh.read(4) == b"PK\x03\x04"
    except OSError:
        return False


def _documents(path: str, text: str) -> list[tuple[str, object]]:
    """(location, document or error message) for a JSON or JSON-lines file."""
    from wiredsl.files import json_loads

    try:
        return [(path, json_loads(text))]
    except json.JSONDecodeError as exc:
        if path.endswith(".jsonl"):
            out = []
            for i, line in enumerate(text.splitlines(), 1):
                if line.strip():
                    try:
                        out.append((f"{path}:{i}", json_loads(line)))
                    except json.JSONDecodeError as e:
                        out.append((f"{path}:{i}:{e.colno}", f"not JSON: {e.msg}"))
            return out
        if path.endswith(".wd") or text.lstrip().startswith(("wiredsl", "#")):
            return [(path, f"a scene source, not a JSON document: check it with 'wiredsl check {path}'")]
        return [(f"{path}:{exc.lineno}:{exc.colno}", f"not JSON: {exc.msg}")]


@main.command()
@guarded
def reference() -> None:
    """Print the language reference (Markdown), generated from the statement table."""
    from wiredsl.language.statements import reference as table

    click.echo(table())


@main.command()
def plugins() -> None:
    """List the effects, measures and detectors that installed packages add (entry points wiredsl.effects,
    wiredsl.measures, wiredsl.detectors).

    One line a plug-in on stdout: kind, name, package and version, module:attribute, and ok or why it cannot be
    used; exit 1 when one cannot."""
    from wiredsl.effects import REGISTRY as effects
    from wiredsl.measures import REGISTRY as measures
    from wiredsl.plugins import installed, lookup
    from wiredsl.verify.detectors import registry as detectors

    rows, bad = [], 0
    for kind, registry in (("effect", effects), ("measure", measures), ("detector", detectors())):
        clashes = registry.clashes()
        for p in installed(kind):
            why = next((c for c in clashes if f"'{p.name}' from {p.origin}" in c), None)
            if why is None:
                why = lookup(registry, p.name)[1]
            bad += why is not None
            rows.append(f"{kind}\t{p.name}\t{p.package} {p.version}\t{p.value}\t{'ok' if why is None else why}")
    click.echo("\n".join(rows) if rows else "no plug-ins installed (entry points wiredsl.effects, "
                                             "wiredsl.measures, wiredsl.detectors)")
    if bad:
        sys.exit(EXIT_INVALID)


@main.command()
@click.argument("name")
@click.option("--plugin", is_flag=True, help="A plug-in package (an effect with its kernel, a measure, their "
              "tests, entry points) instead of a scene project.")
@guarded
def init(name: str, plugin: bool) -> None:
    """Start a project in the folder NAME: a scene with a study and a CI script, or with --plugin a plug-in
    package template that installs and passes its own tests (wiredsl/init.py)."""
    from wiredsl.init import InitError, create

    try:
        path = create(name, plugin=plugin)
    except InitError as exc:
        click.echo(f"wiredsl: error: {exc}", err=True)
        sys.exit(EXIT_INVALID)
    click.echo(f"wrote {path}/: " + ("pip install -e './{0}[test]' && (cd {0} && pytest)" if plugin
                                      else "cd {0} && bash ci.sh").format(name))

TOLERANCE_PX = (1e-3, 100.0)  # finer than 1e-3 px costs vertices (memory, time) without bound, for nothing seen
MAX_TRIAL = 2**31 - 1  # npz stores the trial in an int32 column
OUTPUT_LIMIT = 50 * 10**9  # bytes a run may write without --force
MAX_JSON_BYTES = 1 << 30  # a JSON or JSON-lines file `validate` reads (a JSON dump holds one trial)
DUMP_SUFFIXES = (".json", ".jsonl", ".npz", ".svg")


def _tolerance(ctx, param, value: float) -> float:
    lo, hi = TOLERANCE_PX
    if not lo <= value <= hi:  # NaN fails too
        raise click.BadParameter(f"must be in [{lo:g}, {hi:g}] px")
    return value


def _file_output(output: str) -> str:
    """-o of a command that writes one file: it must not name a folder."""
    from pathlib import Path

    if not output:
        raise click.BadParameter("must not be empty", param_hint="-o")
    if output.endswith(("/", os.sep)) or Path(output).is_dir():
        raise click.BadParameter(f"must name a file, not a folder: {output}", param_hint="-o")
    return output


def _folder_output(output: str | None, scene_name: str, force: bool):
    """The build's output folder (None: the dump goes to stdout), refused early if it cannot be replaced."""
    from pathlib import Path

    from wiredsl.files import check_output_folder

    if output == "-":
        return None
    if output == "":
        raise click.BadParameter("must not be empty", param_hint="-o")
    out = Path(output) if output is not None else Path("build") / scene_name
    check_output_folder(out, force)
    return folder_name(out, DUMP_SUFFIXES, "the dump is written into it as features.json, .jsonl or .npz")


def _size(n: float) -> str:
    for unit in ("bytes", "kB", "MB", "GB"):
        if n < 1000:
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"


def trial_bytes(out_format: str, run, trial: int, doc_for) -> int:
    """Bytes one trial adds to a jsonl or npz dump, measured by running `trial` alone (not written)."""
    import dataclasses
    from collections import Counter

    from wiredsl.effects.base import Stats
    from wiredsl.io import emit

    # The run's ideal projection, but its own counters and caches: the run's manifest is left as it would be.
    probe = dataclasses.replace(run, trace=Counter(), stats=Stats(), warnings=[], _sampler=None, _epipoles={},
                                _ideal=run.ideal())
    if not probe.stages:
        outs = [(r, None, None) for r in probe.ideal()]
    else:
        _, outs = next(probe.batches([trial]))
    if out_format == "jsonl":
        res = emit.disturbed_results(outs, 0) if probe.stages else [r for r, _, _ in outs]
        return sum(len(emit.to_json(doc_for([r], trial), indent=None).encode()) for r in res)
    from wiredsl.io import layout

    if not probe.stages:  # npz holds the ideal projection once, as trial 0, whatever N
        return 0
    n = 0
    for _, disturbed, _ in outs:
        for s in disturbed.values():  # float32 vertices; int32 rows and an int64 offset; corners; the view
            n += (4 * 2 * len(s.pts) + (4 * len(layout.STROKE_COLUMNS) + 8) * s.n_strokes
                  + (4 * 2 + 4 * len(layout.CORNER_COLUMNS)) * len(s.corners)
                  + 4 * len(layout.VIEW_COLUMNS) + 8 * len(layout.CAMERA_COLUMNS) + 8 * 12)
    return n


def _check_size(out_format: str, n_trials: int, per_trial: int, out_dir) -> None:
    """Refuse (usage error) a run whose estimated output exceeds OUTPUT_LIMIT or the free space."""
    import shutil
    from pathlib import Path

    total = per_trial * n_trials
    room, why = OUTPUT_LIMIT, f"the {_size(OUTPUT_LIMIT)} a run may write"
    if out_dir is not None:
        where = Path(out_dir).absolute()
        while not where.exists():
            where = where.parent
        free = shutil.disk_usage(where).free
        if free < room:
            room, why = free, f"the free space on {where} ({_size(free)})"
    if total > room:
        raise click.BadParameter(f"{n_trials} trials would write about {_size(total)} of {out_format} "
                                 f"({_size(per_trial)} a trial, measured on its first trial), more than "
                                 f"{why}; run fewer trials or pass --force", param_hint="--trials")


@main.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("-o", "--output", default=None,
              help="Output folder (default build/<scene name>/), replaced whole by the run; - for the dump on stdout.")
@click.option("--pipeline", "pipeline_name", default=None, help="The pipeline to run (default: the scene's default).")
@click.option("--no-effects", is_flag=True, help="The ideal projection, whatever the scene's pipelines.")
@click.option("--seed", type=click.IntRange(0, 2**63 - 1), default=None,
              help="Seed of every random stream (default: drawn at random and recorded).")
@click.option("--trials", type=click.IntRange(1, 10**8), default=1, show_default=True, help="Monte-Carlo trials.")
@click.option("--trial", "only_trial", type=click.IntRange(0, MAX_TRIAL), default=None,
              help="Replay trial K of a run alone (same seed): exactly that trial's output. With the run's "
                   "--trials N, on the engine that run chose.")
@click.option("--pose", "poses", type=int, multiple=True, help="Build only this pose (repeatable).")
@click.option("--format", "out_format", type=click.Choice(["json", "jsonl", "npz"]), default="json",
              show_default=True, help="json: one dump (one trial); jsonl: a line a trial and pose; npz: bulk arrays.")
@click.option("--svg/--no-svg", default=True, show_default=True,
              help="Write one SVG a pose (of the run's first trial).")
@click.option("--layout", type=click.Choice(["overlay", "side-by-side", "visibility"]), default="overlay",
              show_default=True, help="The SVGs' layout: overlay: disturbed over ideal (Figures 3, 9); side-by-side: "
              "original beside disturbed (Figure 9); visibility: without and with view-dependency (Figure 4).")
@click.option("--cameras", type=click.Choice(["both", "left"]), default="both", show_default=True,
              help="Project the right camera too, or only the left.")
@click.option("--tolerance", type=float, default=0.1, show_default=True, callback=_tolerance,
              help=f"Largest deviation (px, {TOLERANCE_PX[0]:g} to {TOLERANCE_PX[1]:g}) of an emitted polyline "
                   "from the true image curve.")
@click.option("--visibility", type=click.Choice(VISIBILITIES), default=DEFAULT_VISIBILITY, show_default=True,
              help="scene: the nearest view-point's list; exact: hidden lines removed at each camera; all: no "
                   "occlusion; auto: where the scene has faces and its view-points' lists are computed (`visibility "
                   "auto`, or no view-points), exact unless its estimated CPU is over 60 s (then scene, with warning "
                   "W129); else scene. The manifest's `visibility` says which was used.")
@click.option("--engine", type=click.Choice(["auto", "kernel", "numpy"]), default="auto", show_default=True,
              help="Monte-Carlo engine: the compiled kernel (needs wiredsl[fast]) or the numpy reference; auto: the "
                   "kernel, when numba is installed, for --trial and for runs large enough to pay for loading it "
                   "(some 75 trials of scenes/lab.wd), unless its compiled loop is not in numba's cache yet and "
                   "compiling it (about 43 s of CPU once) would not pay in this run (under some 10,000 trials of "
                   "scenes/lab.wd): then numpy, said on stderr. Both draw the same numbers; the manifest's `engine` "
                   "says which ran.")
@click.option("--exact-calibration", is_flag=True,
              help="Project each trial's perturbed rig from scratch (slow) instead of re-projecting the ideal "
                   "strokes with every trial's cameras at once.")
@click.option("--force", is_flag=True,
              help="Replace an output folder that holds other files; run beyond the output size limit.")
@click.option("--study", "study_name", default=None,
              help="Replay a study's design point (--point I) and trial (--trial K): its pipeline and seed.")
@click.option("--point", type=click.IntRange(0, None), default=None, help="With --study: the design point I.")
@diagnostics_option
@guarded
def build(file: str, output: str | None, pipeline_name: str | None, no_effects: bool, seed: int | None, trials: int,
          only_trial: int | None, poses: tuple[int, ...], out_format: str, svg: bool, cameras: str, tolerance: float,
          visibility: str, engine: str, exact_calibration: bool, layout: str, force: bool,
          diagnostics: str, study_name: str | None = None, point: int | None = None) -> None:
    """Project the scene for every pose of its path, through its uncertainty pipeline; write the dumps."""
    import time

    from wiredsl import run as runs
    from wiredsl.engine.simulate import Options
    from wiredsl.engine.world import build_world
    from wiredsl.files import json_text, output_folder, write_atomic
    from wiredsl.io import emit
    from wiredsl.language.compile import compile_file

    if only_trial is not None and seed is None and study_name is None and not no_effects:
        raise click.UsageError("--trial K replays trial K of a run: give that run's --seed (see its manifest.json)")
    ctx = click.get_current_context(silent=True)
    trials_given = ctx is not None and ctx.get_parameter_source("trials") not in (
        None, click.core.ParameterSource.DEFAULT)  # --trials N beside --trial K: the run K is replayed from
    if only_trial is not None and trials_given and only_trial >= trials:
        raise click.BadParameter(f"trial {only_trial} is not in 0..{trials - 1} (a run of --trials {trials})",
                                 param_hint="--trial")
    scene, warnings, program = compile_file(file)
    report(warnings, program.sources, diagnostics)
    with setup_errors():
        chosen_poses = runs.check_poses(scene, poses) if poses else None
        choice = runs.choose_pipeline(scene, pipeline_name, no_effects)
    pipeline = choice.pipeline
    if choice.note is not None:
        click.echo(f"note: {choice.note}", err=True)
    trial_list = range(only_trial, only_trial + 1) if only_trial is not None else range(trials)
    if layout == "side-by-side" and pipeline is None:
        raise click.BadParameter("side-by-side shows the original beside the disturbed world: give a pipeline",
                                 param_hint="--layout")
    if layout == "visibility" and visibility == "all":
        raise click.BadParameter("the visibility layout compares --visibility all with scene or exact",
                                 param_hint="--layout")
    if out_format == "json" and len(trial_list) > 1:
        raise click.BadParameter("one JSON dump holds one trial: use --format jsonl or npz for several",
                                 param_hint="--trials")
    out_dir = _folder_output(output, scene.name, force)
    if out_format == "npz" and out_dir is None:
        raise click.BadParameter("npz cannot go to stdout", param_hint="-o")
    world = build_world(scene)
    if visibility == "auto":
        visibility = auto_visibility(scene, world, program, chosen_poses, cameras, trials if exact_calibration else 1,
                                      diagnostics)
    opts = Options(tolerance=tolerance, visibility=visibility, poses=chosen_poses, right=cameras == "both")
    with setup_errors():
        if study_name is not None or point is not None:
            run, pipeline, trial_list = _study_point(scene, world, study_name, point, only_trial, seed,
                                                     pipeline_name, no_effects, opts, poses, out_format)
            run.engine, run.exact_calibration = runs.check_engine(engine), exact_calibration
            seed = run.seed
        else:
            run = runs.start(scene, pipeline, seed=seed, options=opts, world=world, engine=engine,
                             exact_calibration=exact_calibration)
    replaying_alone = only_trial is not None and not trials_given  # --trial K alone: the kernel, as before
    if engine == "auto" and (forced := runs.numpy_forced(run, len(trial_list))):
        click.echo(forced, err=True)
    if engine == "auto" and not replaying_alone and (cold := runs.settle_auto_engine(
            run, trials if only_trial is not None else len(trial_list))):  # a replay: as its run of --trials N
        click.echo(cold, err=True)  # the kernel is not compiled yet and would not pay for compiling in this run
    shown = only_trial if only_trial is not None else trial_list[0]  # the trial the SVGs show
    if run.uses_kernel():
        _numba_without_blas()
    effects = bool(run.stages)
    if effects:
        seed = run.seed  # drawn by start() when not given
    records = emit.stage_records(run)

    def doc_for(results, k):
        return emit.features_doc(scene, world, results, pipeline=pipeline.name if pipeline else None, stages=records,
                             seed=seed if effects else None, trial=k if effects else None)

    if len(trial_list) > 1 and not force:
        _check_size(out_format, len(trial_list), trial_bytes(out_format, run, trial_list[0], doc_for), out_dir)
    started = time.perf_counter()
    if not effects:
        results = run.ideal()
        batches = [(trial_list, [(r, None, None) for r in results])]
    else:
        batches = run.batches(trial_list)
    show = sys.stderr.isatty() and len(trial_list) > 1
    what = {"json": "features.json", "jsonl": "features.jsonl", "npz": "features.npz"}[out_format]
    with output_folder(out_dir, force) if out_dir is not None else contextlib.nullcontext() as stage:
        writer = None
        if out_format == "jsonl" and stage is not None:
            writer = emit.JsonLines(stage / what)
        elif out_format == "npz":
            writer = emit.NpzStream(stage / what)
        try:
            with click.progressbar(length=len(trial_list), label="trials", file=sys.stderr if show else _Null()) as bar:
                for batch, batch_out in batches:
                    if out_format == "npz" and effects:
                        writer.write_batch(batch, batch_out, world)
                    elif out_format == "npz":  # the ideal projection as trial 0, in the same layout
                        writer.write_ideal([r for r, _, _ in batch_out], world)
                    for k, t in enumerate(batch):
                        if only_trial is not None and t != only_trial:  # a study replay runs its whole shard
                            continue
                        if out_format == "npz" and not (t == shown and svg):
                            break
                        res = emit.disturbed_results(batch_out, k) if effects else [r for r, _, _ in batch_out]
                        if t == shown and svg and stage is not None:
                            _write_svgs(stage, res, run, pipeline.name if effects else None,
                                        seed if effects else None, t if effects else None, visibility, layout)
                        if out_format == "jsonl":
                            for r in res:
                                line = doc_for([r], t)
                                if writer is None:
                                    _stdout_utf8(emit.to_json(line, indent=None))
                                else:
                                    writer.write(line)
                        elif out_format == "json":
                            text = emit.to_json(doc_for(res, t))
                            if stage is None:
                                _stdout_utf8(text)
                            else:
                                write_atomic(stage / what, text, tidy=False)
                    bar.update(len(batch))
            manifest = emit.manifest_doc(tool_version=__version__, scene=emit.scene_ref(scene),
                                         pipeline=pipeline.name if pipeline else None, seed=seed,
                                         trials=1 if only_trial is not None else len(trial_list),
                                         first_trial=shown, visibility=visibility, **run.manifest())
            if out_format == "npz":
                writer.close(world.feature_ids, manifest)
            elif writer is not None:
                writer.close()
        except BaseException:
            if writer is not None:
                writer.abort()
            raise
        if stage is not None:
            write_atomic(stage / "manifest.json", json_text(manifest, sort_keys=True, where="manifest"), tidy=False)
    seconds = time.perf_counter() - started
    for w in run.warnings:
        click.echo(f"warning: {w}", err=True)
    if out_dir is not None:
        n_written = 1 if only_trial is not None else len(trial_list)  # a study replay runs its shard, writes one
        click.echo(f"wrote {out_dir / what} in {seconds:.1f} s ({n_written} trial{'s' * (n_written != 1)}, "
                   f"seed {seed if effects else '-'}"
                   + (f", pipeline {pipeline.name}: {', '.join(e.name for e, _ in run.stages)}" if effects else
                      ", ideal projection") + ")", err=True)


def _exact_cost_note(scene, program) -> None:
    """`check`'s note on a scene with meshes: exact visibility's estimated CPU for a build of every pose with
    both cameras, and what `--visibility auto` chooses (run.exact_cost_note)."""
    from wiredsl import run as runs
    from wiredsl.engine.world import build_world

    views = (len(scene.path.poses) if scene.path is not None else 0) * (2 if scene.rig is not None else 1)
    note = runs.exact_cost_note(scene, build_world(scene), views)
    if note is not None:
        click.echo(f"{program.mesh_reports[0][0]}: note: {note}", err=True)


def _stdout_utf8(text: str) -> None:
    """A dump on stdout in UTF-8 (JSON's encoding) whatever the terminal's: orjson writes non-ASCII as is."""
    buffer = getattr(sys.stdout, "buffer", None)
    if buffer is None:
        sys.stdout.write(text)
        return
    sys.stdout.flush()
    buffer.write(text.encode("utf-8", "surrogateescape"))
    buffer.flush()


def _numba_without_blas() -> None:
    """Load numba's array functions without looking for a BLAS: the compiled kernels call none, and the look-up
    imports scipy.linalg (0.15-0.2 s CPU, a third of loading the cached kernel). For this command's process
    only: a library user's own numba code in the same process keeps its np.dot."""
    if "numba.np.arraymath" in sys.modules or "scipy.linalg.cython_blas" in sys.modules:
        return  # too late, or scipy.linalg already paid for
    sys.modules["scipy.linalg.cython_blas"] = None  # an import of it raises ImportError: "no BLAS"
    try:
        import numba.np.arraymath  # noqa: F401
    finally:
        del sys.modules["scipy.linalg.cython_blas"]


def _study_point(scene, world, study_name, point, only_trial, seed, pipeline_name, no_effects, opts, poses,
                 out_format):
    """The Run of a study's design point, as the study runs it (`build --study NAME --point I --trial K`)."""
    import dataclasses

    from wiredsl.study import design, shards

    if study_name is None or point is None or only_trial is None:
        raise click.UsageError("replaying a study needs --study NAME, --point I and --trial K together")
    if seed is not None or pipeline_name is not None or no_effects or out_format == "npz":
        if out_format == "npz":
            raise click.UsageError("a study replay is one trial: use --format json or jsonl")
        raise click.UsageError("--study sets the pipeline and the seed: leave out --seed, --pipeline, --no-effects")
    study = scene.study(study_name)
    if study is None:
        names = ", ".join(s.name for s in scene.studies) or "none"
        raise click.BadParameter(f"no study '{study_name}' in the scene (it has: {names})", param_hint="--study")
    X = design.matrix(study)
    if point >= len(X):
        raise click.BadParameter(f"point {point} is not in 0..{len(X) - 1}", param_hint="--point")
    if only_trial >= study.trials:
        raise click.BadParameter(f"trial {only_trial} is not in 0..{study.trials - 1}", param_hint="--trial")
    study_opts = shards.options(study, scene, world)  # the study's visibility too: the point as the study ran it
    opts = dataclasses.replace(opts, poses=tuple(sorted(set(poses))) or study_opts.poses,
                               visibility=study_opts.visibility)
    run = shards.point_run(scene, world, study, point, X[point], opts)
    lo, hi = shards.span_of(only_trial, study.trials)
    return run, design.pipeline_at(scene, study, X[point]), list(range(lo, hi))


class _Null:
    """A file that swallows the progress bar when stderr is not a terminal."""

    def write(self, _):
        pass

    def flush(self):
        pass

    def isatty(self):
        return False


def _write_svgs(folder, results, run, *caption) -> None:
    """One SVG a pose of these results, in the chosen layout (disturbed over ideal when the pipeline ran);
    `caption` is the svg.Info's fields (io.svg is imported only when SVGs are written)."""
    from wiredsl.files import write_atomic
    from wiredsl.io import svg as svg_mod

    info = svg_mod.Info(*caption)
    for name, text in svg_mod.pose_figures(run, results, info.layout, info).items():
        write_atomic(folder / name, text, tidy=False)


@main.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("-o", "--output", default=None, help="Output file (default build/<scene name>/viewdep.json).")
@click.option("--threshold", type=FiniteRange(0, 1), default=0.3, show_default=True,
              help="Fraction of a feature's sample points that must be seen for it to count as visible.")
@diagnostics_option
@guarded
def viewdep(file: str, output: str | None, threshold: float, diagnostics: str) -> None:
    """Compute which features each view-point sees, and write the view-dependency file."""
    from pathlib import Path

    from wiredsl import __version__
    from wiredsl.diagnostics import Diagnostic, WiredslError
    from wiredsl.engine import visibility
    from wiredsl.engine.world import build_world
    from wiredsl.files import write_atomic
    from wiredsl.io import emit
    from wiredsl.io.features import ViewDependency
    from wiredsl.language.compile import compile_file

    if output is not None:
        _file_output(output)
    scene, warnings, program = compile_file(file)
    report(warnings, program.sources, diagnostics)
    vp = scene.viewpoints
    if vp is None:
        raise WiredslError([Diagnostic("error", "E102", f"scene '{scene.name}' has no viewpoints mesh", None)])
    world = build_world(scene)
    vis = visibility.visible_features(world, visibility.viewpoint_eyes(scene), threshold)
    doc = ViewDependency(tool_version=__version__, scene=emit.scene_ref(scene), threshold=threshold,
                         eye_height=visibility.eye_height(scene),
                         viewpoints=visibility.as_lists(world, vp.names, vis))
    out = Path(output) if output is not None else Path("build") / scene.name / "viewdep.json"
    write_atomic(out, emit.to_json(doc))
    click.echo(f"wrote {out} ({len(vp.names)} view-points, {world.n_features} features)", err=True)
    if vp.file:
        wanted = Path(scene.source).parent / vp.file
        if not (wanted.exists() and wanted.resolve() == out.resolve()):
            click.echo(f"note: {file} reads its view-point lists from {wanted}; write them there with "
                       f"'wiredsl viewdep {file} -o {wanted}'", err=True)

@main.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("-o", "--output", default=None,
              help="The plot: .svg, .pdf, or .png for a raster (default build/<scene name>/bench.svg). Needs "
                   "wiredsl[plot].")
@click.option("--budget", type=FiniteRange(1, None), default=60.0, show_default=True,
              help="Seconds the Monte-Carlo table may spend; rows beyond it are not run.")
@click.option("--dpi", type=click.IntRange(20, 1200), default=150, show_default=True,
              help="The plot's resolution in dots per inch (a .png).")
@diagnostics_option
@guarded
def bench(file: str, output: str | None, budget: float, dpi: int, diagnostics: str) -> None:
    """Measure what each accuracy knob costs in time on a scene: four tables (stdout) and a plot."""
    import platform
    from pathlib import Path

    from wiredsl import bench as bench_mod
    from wiredsl.engine.simulate import require_buildable
    from wiredsl.engine.world import build_world
    from wiredsl.files import write_atomic
    from wiredsl.language.compile import compile_file

    scene, warnings, program = compile_file(file)
    report(warnings, program.sources, diagnostics)
    require_buildable(scene)
    world = build_world(scene)
    out = Path(_file_output(output)) if output is not None else Path("build") / scene.name / "bench.svg"
    if out.suffix.lower() not in (".svg", ".png", ".pdf"):
        raise click.BadParameter("the plot is written as .svg, .pdf or .png", param_hint="-o")
    try:
        import matplotlib  # noqa: F401  (checked before the minutes of measuring, not after)
    except ImportError:
        raise click.UsageError(f"the bench plot needs matplotlib: {install_hint('plot')}") from None
    tables = bench_mod.run_all(scene, world, budget, progress=lambda m: click.echo(m, err=True))
    click.echo(f"## wiredsl bench {file}\n\nMachine: {platform.machine()}, {os.cpu_count()} cores, "
               f"Python {platform.python_version()}, numpy {__import__('numpy').__version__}.\n")
    for t in tables:
        click.echo(t.markdown())
    write_atomic(out, bench_mod.plot(tables, out.suffix.lower()[1:], dpi))
    click.echo(f"wrote {out}", err=True)


@main.command()
@click.option("--print-grammar", is_flag=True,
              help="Print the TextMate grammar for syntax highlighting (editors/wiredsl.tmLanguage.json) and exit.")
@guarded
def lsp(print_grammar: bool) -> None:
    """Run the language server on stdin/stdout (needs the `lsp` extra: pip install '.[lsp]' in wiredsl's
    checkout)."""
    from wiredsl import lsp as server

    if print_grammar:
        click.echo(json.dumps(server.textmate_grammar(), indent=2))
        return
    try:
        import pygls  # noqa: F401
    except ImportError:
        raise click.UsageError(f"the language server needs pygls: {install_hint('lsp')}") from None
    server.serve()


@main.command("export-calibration")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("-o", "--output", default=None, help="Output folder (default build/<scene name>/calibration/).")
@click.option("--trial", type=click.IntRange(0, 2**31 - 1), default=None,
              help="Write the rig as trial K drew it (needs --seed and a calibration_error stage).")
@click.option("--seed", type=click.IntRange(0, 2**63 - 1), default=None, help="The run's seed (with --trial).")
@click.option("--pipeline", "pipeline_name", default=None, help="The pipeline whose calibration_error draws the rig.")
@diagnostics_option
@guarded
def export_calibration(file: str, output: str | None, trial: int | None, seed: int | None,
                       pipeline_name: str | None, diagnostics: str) -> None:
    """Write the rig's cameras as calibration files: OpenCV (stereo.yaml) and ROS (left.yaml, right.yaml) for
    pinhole and fisheye lenses, Kalibr (camchain.yaml), basalt (basalt_calib.json) and camodocal
    (left_camodocal.yaml, right_camodocal.yaml) for the lenses each format has."""
    from pathlib import Path

    from wiredsl.effects import calibration_error as calib
    from wiredsl.files import write_atomic
    from wiredsl.io.calibration import rig_files
    from wiredsl.language.compile import compile_file

    if output is not None:
        folder_name(Path(output), (".yaml", ".yml", ".json", ".xml"),
                     "stereo.yaml, left.yaml, right.yaml, camchain.yaml, basalt_calib.json and the "
                     "camodocal files are written into it")
    scene, warnings, program = compile_file(file)
    report(warnings, program.sources, diagnostics)
    if scene.rig is None:
        raise click.UsageError(f"{file} has no rig to export")
    if trial is not None:
        if seed is None:
            raise click.UsageError("--trial needs the run's --seed (see its manifest.json)")
        from wiredsl import run as runs

        with setup_errors():
            run = runs.start(scene, runs.choose_pipeline(scene, pipeline_name).pipeline, seed=seed)
        if run.sampler() is None:
            raise click.UsageError("no calibration_error stage with a rig calibration: each trial has the nominal rig")
        # the run's own checked draw (a refused draw is redrawn), so the files are the rig the trial saw
        scene = calib.perturb(scene, run.calibration_draws([trial])[0], scene.rig.calibration.order)
    out = Path(output) if output else Path("build") / scene.name / "calibration"
    files = rig_files(scene)
    for name, text in files.items():
        write_atomic(out / name, text)
    click.echo(f"wrote {out}/" + ", ".join(files) + (f" (trial {trial}, seed {seed})"
               if trial is not None else " (nominal rig)"), err=True)


@main.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.argument("name", required=False)
@click.option("-o", "--output", default=None, help="Output directory (default build/<scene name>-<study name>/).")
@click.option("--executor", type=click.Choice(["processes", "inprocess", "dask"]), default="processes",
              show_default=True, help="processes: local processes on every core; dask: a Dask cluster.")
@click.option("--workers", type=click.IntRange(1, None), default=None, help="Local processes (default: every core).")
@click.option("--scheduler", default=None, help="With --executor dask: the scheduler's address (tcp://host:8786).")
@click.option("--plots/--no-plots", default=True, show_default=True, help="Write the plots (needs matplotlib).")
@click.option("--plot-format", type=click.Choice(["png", "svg", "pdf"]), default="png", show_default=True,
              help="The plots' format: png (raster), or svg / pdf (vector, for publication).")
@click.option("--dpi", type=click.IntRange(20, 1200), default=150, show_default=True,
              help="The plots' resolution in dots per inch (png; embedded rasters in svg / pdf).")
@click.option("--fresh", is_flag=True, help="Recompute every shard, whatever the output folder holds.")
@diagnostics_option
@guarded
def study(file: str, name: str | None, output: str | None, executor: str, workers: int | None,
          scheduler: str | None, plots: bool, plot_format: str, dpi: int, fresh: bool, diagnostics: str) -> None:
    """Run a study of FILE (NAME, or its only one): shards, then table.csv/json, manifest.json and plots."""
    from pathlib import Path

    from wiredsl.engine.simulate import require_buildable
    from wiredsl.language.compile import compile_file
    from wiredsl.study import run_study

    if output is not None:
        folder_name(Path(output), (".csv", ".json", ".png", ".svg"), "table.csv, table.json and plots/ are written "
                     "into it")
    scene, warnings, program = compile_file(file)
    report(warnings, program.sources, diagnostics)
    found = scene.study(name)
    if found is None:
        names = ", ".join(s.name for s in scene.studies) or "none"
        raise click.BadParameter(f"no study {f'{name!r} ' if name else ''}to run in {file} "
                                 f"({'name one: ' if scene.studies else 'it has '}{names})", param_hint="NAME")
    if executor == "dask" and not scheduler:
        raise click.BadParameter("--executor dask needs --scheduler ADDRESS", param_hint="--scheduler")
    require_buildable(scene)
    if plots:
        try:
            import matplotlib  # noqa: F401  (checked before the study runs, not after)
        except ImportError:
            raise click.UsageError(f"the study's plots need matplotlib: {install_hint('plot')}, or give "
                                   "--no-plots") from None
    out = Path(output) if output else Path("build") / f"{scene.name}-{found.name}"
    table = run_study(scene, found, out, executor=executor, workers=workers, scheduler=scheduler,
                      echo=lambda m: click.echo(m, err=True), fresh=fresh, program=program)
    written = ["table.csv", "table.json", "manifest.json"] + (["sobol.csv"] if table.sobol else [])
    if plots:
        from wiredsl.study import plots as plots_mod

        written += plots_mod.write_all(table, found, out / "plots", fmt=plot_format, dpi=dpi)
        if not table.factors:
            click.echo(f"study {found.name} varies nothing: one point, no plots against factors and no Sobol' "
                       "indices (table.csv holds its statistics)", err=True)
    click.echo(f"wrote {out}: " + ", ".join(written), err=True)

