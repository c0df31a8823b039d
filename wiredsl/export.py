"""`wiredsl export`: a build's ideal or disturbed observations as a COLMAP text model or a ROS 2 bag.

The run comes from `wiredsl.run` through the API's batches (io/observations.py); the writers are
io/export_colmap.py and io/export_rosbag.py. The output folder is written whole or not at all (a temporary
folder renamed into place): `ideal/` for the ideal projection, `trial_00000/`, ... for a pipeline's trials,
and manifest.json (what was run: scene, pipeline, seed, trials, format, versions).
"""

from __future__ import annotations

import sys

import click

from wiredsl import DEFAULT_VISIBILITY, VISIBILITIES, install_hint
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

FORMATS = ("colmap", "rosbag2")
MAX_EXPORT_TRIALS = 100_000  # one folder a trial


@click.command("export")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--format", "fmt", type=click.Choice(FORMATS), required=True,
              help="colmap: cameras.txt, images.txt, points3D.txt; rosbag2: a ROS 2 bag (sqlite3) a trial.")
@click.option("-o", "--output", default=None, help="Output folder (default build/<scene name>/<format>/).")
@click.option("--no-effects", is_flag=True, help="Export the ideal projection, whatever the scene's pipelines.")
@click.option("--pipeline", "pipeline_name", default=None, help="The pipeline whose trials are exported "
              "(default: the scene's default).")
@click.option("--trials", type=click.IntRange(1, MAX_EXPORT_TRIALS), default=1, show_default=True,
              help="Trials 0..N-1 of the run, one folder each.")
@click.option("--trial", "only_trial", type=click.IntRange(0, MAX_EXPORT_TRIALS - 1), default=None,
              help="Export trial K alone (folder trial_K): the same draws as build --seed S --trial K. With "
                   "--trials N, K must be below N.")
@click.option("--seed", type=click.IntRange(0, 2**63 - 1), default=None,
              help="The run's seed (default: drawn, and recorded in manifest.json).")
@click.option("--period", type=FiniteRange(1e-6, 3600), default=0.1, show_default=True,
              help="rosbag2: seconds between the path's poses (pose i is stamped 1 s + i * period), for a path "
                   "without timestamps (a path read from a trajectory file keeps the file's own).")
@click.option("--undistort", is_flag=True, help="colmap: a PINHOLE camera and undistorted 2D points, for any lens "
              "(needed for the lenses COLMAP has no model for: ds, unified with distortion).")
@click.option("--visibility", type=click.Choice(VISIBILITIES), default=DEFAULT_VISIBILITY, show_default=True,
              help="Hidden lines, as in build: scene (the view-points' lists), exact, all, or auto (where the scene "
                   "has faces and computed lists, exact unless its estimated CPU is over 60 s, then scene with W129; "
                   "else scene). The manifest's `visibility` says which was used.")
@click.option("--force", is_flag=True, help="Replace an output folder that holds files wiredsl did not write.")
@diagnostics_option
@guarded
def export(file: str, fmt: str, output: str | None, no_effects: bool, pipeline_name: str | None, trials: int,
           only_trial: int | None, seed: int | None, period: float, undistort: bool, visibility: str, force: bool,
           diagnostics: str) -> None:
    """Write what the rig observes along the path (the ideal projection, or a pipeline's trials) in the formats
    SfM and SLAM code reads: a COLMAP text model or a ROS 2 bag."""
    import importlib.util
    import secrets
    from pathlib import Path

    from wiredsl import run as runs
    from wiredsl.language.compile import compile_file

    ctx = click.get_current_context(silent=True)
    trials_given = ctx is not None and ctx.get_parameter_source("trials") not in (
        None, click.core.ParameterSource.DEFAULT)
    if only_trial is not None and trials_given and only_trial >= trials:
        raise click.BadParameter(f"trial {only_trial} is not in 0..{trials - 1} (a run of --trials {trials})",
                                 param_hint="--trial")
    if undistort and fmt != "colmap":
        raise click.BadParameter("--undistort is for --format colmap", param_hint="--undistort")
    need = {"colmap": None, "rosbag2": "rosbags"}[fmt]
    if need and importlib.util.find_spec(need) is None:
        raise click.UsageError(f"--format {fmt} needs the {need} library: {install_hint('formats')}")
    if output is not None:
        folder_name(Path(output), (".txt", ".db3", ".yaml", ".json"), "ideal/ or trial_NNNNN/ folders and "
                     "manifest.json are written into it")
    scene, warnings, program = compile_file(file)
    report(warnings, program.sources, diagnostics)
    with setup_errors():
        choice = runs.choose_pipeline(scene, pipeline_name, no_effects)
    if choice.note is not None:
        click.echo(f"note: {choice.note}", err=True)
    pipeline = choice.pipeline if choice.pipeline is not None and choice.pipeline.stages else None
    if pipeline is None and (trials != 1 or seed is not None or only_trial is not None):
        click.echo("note: the ideal projection has one trial and no draws: --trials, --trial and --seed are not "
                   "used", err=True)
        only_trial = None
    seed = (seed if seed is not None else secrets.randbits(63)) if pipeline is not None else 0
    if visibility == "auto":  # build's rule and warning: every pose, both cameras
        from wiredsl.engine.world import build_world

        visibility = auto_visibility(scene, build_world(scene), program, None, "both", 1, diagnostics)
    out = Path(output) if output is not None else Path("build") / scene.name / fmt
    try:
        counts = write(out, scene, fmt, pipeline, trials, seed, period, undistort, force, only_trial, visibility)
    except ExportError as exc:
        click.echo(f"wiredsl: error: {exc}", err=True)
        sys.exit(EXIT_INVALID)
    what = (f"pipeline {pipeline.name}, " + (f"trial {only_trial}" if only_trial is not None else
                                              f"{trials} trial{'s' * (trials != 1)}") + f", seed {seed}") \
        if pipeline else "ideal projection"
    click.echo(f"wrote {out} ({fmt}, {what})", err=True)
    for note in counts:
        click.echo(f"note: {note}", err=True)


class ExportError(ValueError):
    """The scene cannot be exported in the format asked (no rig, no path, a lens the format lacks)."""


def write(out, scene, fmt: str, pipeline, n_trials: int, seed: int, period: float, undistort: bool = False,
          force: bool = False, only_trial: int | None = None, visibility: str = "scene") -> list[str]:
    """Write the export folder `out` whole (atomically); the notes to tell the user (observations left out).
    `only_trial`: trial K of the run alone; `visibility`: the projection's mode (scene, exact or all)."""
    from wiredsl import __version__
    from wiredsl.files import json_text, output_folder
    from wiredsl.io import export_colmap, observations

    try:
        src, each = trials(scene, pipeline, n_trials, seed, only=only_trial, visibility=visibility)
        if fmt == "colmap" and not undistort:
            for side in observations.CAMERAS:
                export_colmap.colmap_camera(src.cameras[side])
        period_ns = round(period * 1e9)
        if fmt == "rosbag2":
            from wiredsl.io import export_rosbag

            export_rosbag.check_stamps(export_rosbag.stamps(src, period_ns).values())
    except (ValueError, export_colmap.ColmapLensError) as exc:
        raise ExportError(str(exc)) from None
    left_out, lost = 0, 0
    folders = []
    with output_folder(out, force) as stage:
        for trial in each:
            name = f"trial_{trial.trial:05d}" if pipeline is not None else "ideal"
            folders.append(name)
            if fmt == "colmap":
                model = export_colmap.model(src, trial, undistort)
                (stage / name).mkdir()
                for fname, text in model.files.items():
                    (stage / name / fname).write_text(text, encoding="utf-8")
                left_out += model.behind
                lost += model.undistorted_out
            else:
                from wiredsl.io import export_rosbag

                left_out += export_rosbag.write(stage / name, src, trial, period_ns)
        manifest = {"wiredsl": __version__, "scene": scene.name, "format": fmt,
                    "pipeline": pipeline.name if pipeline is not None else None, "seed": seed,
                    "trials": n_trials if pipeline is not None and only_trial is None else 1, "folders": folders,
                    "visibility": visibility, "versions": _versions(fmt)}
        if only_trial is not None and pipeline is not None:
            manifest["trial"] = only_trial
        manifest["clock"] = "trajectory" if src.stamps_ns is not None else "period"
        if fmt == "rosbag2":
            manifest["period_ns"] = period_ns
        if fmt == "colmap":
            manifest["undistort"] = undistort
        (stage / "manifest.json").write_text(json_text(manifest, indent=1) + "\n", encoding="utf-8")
    notes = []
    if left_out:
        notes.append(f"{left_out} corner observation{'s' * (left_out != 1)} behind a camera's image plane (a lens "
                     "wider than 180 deg) left out: the format projects only points in front")
    if lost:
        notes.append(f"{lost} corner observation{'s' * (lost != 1)} whose pixel has no ray in the lens's valid "
                     "region left out (--undistort)")
    return notes


def trials(scene, pipeline, n_trials: int, seed: int, engine: str = "auto", only: int | None = None,
           visibility: str = "scene") -> tuple:
    """The shared observations.Source and each trial's views (observations.Trial), trial by trial (a batch of
    trials in memory at a time). Here, not in io/: it runs the simulation (api, run), which io must not import.

    `pipeline` None: the ideal projection (one trial, numbered 0), whatever the scene's default pipeline.
    `only`: trial `only` of the run alone (its own draws: what `build --trial K` replays). `visibility`: the
    projection's mode (scene, exact or all; `wiredsl export` resolves auto as build does)."""
    from wiredsl import run as runs
    from wiredsl.api import _batches
    from wiredsl.engine.simulate import Options
    from wiredsl.engine.world import build_world
    from wiredsl.io.observations import CAMERAS, camera_from_world, source, split
    from wiredsl.scene import Pipeline

    world = build_world(scene)
    src = source(scene, world)
    chosen = pipeline if pipeline is not None else Pipeline(name="ideal", stages=[])
    opts = Options(poses=runs.check_poses(scene, None), visibility=visibility)
    fid_corner = {int(f): i for i, f in enumerate(world.corner_fid)}

    def each():
        nominal = {(p, s): camera_from_world(src, p, s) for p in src.poses for s in CAMERAS}
        for batch in _batches(scene, n_trials if pipeline is not None else 1, seed, chosen, opts, engine, world=world,
                              only=only if pipeline is not None else None):
            yield from split(batch, nominal, fid_corner)

    return src, each()


def _versions(fmt: str) -> dict:
    from importlib.metadata import PackageNotFoundError, version

    import wiredsl
    from wiredsl.io.export_colmap import CHECKED_WITH

    out = {"wiredsl": wiredsl.__version__}  # the writer; and the library it writes through, or the reader checked
    if fmt == "rosbag2":
        try:
            out["rosbags"] = version("rosbags")
        except PackageNotFoundError:
            out["rosbags"] = None
    else:
        out["colmap"] = CHECKED_WITH
    return out
