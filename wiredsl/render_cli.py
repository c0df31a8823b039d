"""The `render` command's options (click only at import; the drawing is in render.py, imported when it runs)."""

from __future__ import annotations

import click

from wiredsl.cli_base import diagnostics_option, folder_name, guarded, report, setup_errors


def _grey_range(lo: float, hi: float):
    """A click callback: a finite number in [lo, hi] (FloatRange lets NaN through)."""
    def check(ctx, param, value):
        if value is not None and not lo <= value <= hi:
            raise click.BadParameter(f"must be a number in [{lo:g}, {hi:g}]")
        return value

    return check


@click.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("-o", "--output", default=None, help="Output folder (default build/<scene name>/render/).")
@click.option("--pipeline", "pipeline_name", default=None, help="Draw the features as this pipeline disturbs them "
              "(default: the scene's default).")
@click.option("--no-effects", is_flag=True, help="Draw the ideal projection, whatever the scene's pipelines.")
@click.option("--seed", type=click.IntRange(0, 2**63 - 1), default=None,
              help="Seed of the pipeline's draws (trial 0) and of the noise (default: drawn, and recorded).")
@click.option("--blur", type=float, default=0.0, show_default=True, callback=_grey_range(0, 50),
              help="Gaussian blur, sigma in px.")
@click.option("--noise", type=float, default=0.0, show_default=True, callback=_grey_range(0, 128),
              help="Gaussian sensor noise, sigma in grey levels.")
@click.option("--edges", type=click.Choice(["step", "line", "none"]), default="step", show_default=True,
              help="A feature as a step edge (a band beside it), as a line centred on it, or not drawn.")
@click.option("--width", "stroke_width", type=float, default=4.0, show_default=True, callback=_grey_range(0.1, 50),
              help="Width of the band beside a step edge, or of a line, in px.")
@click.option("--faces", type=click.Choice(["shaded", "none"]), default="shaded", show_default=True,
              help="Shade the models' faces (their outlines are edges no pipeline disturbs), or leave them out.")
@click.option("--corners", type=click.Choice(["none", "mark"]), default="none", show_default=True,
              help="Mark each (kept, disturbed) corner with a small checker, which corner detectors find.")
@click.option("--background", type=float, default=128.0, show_default=True, callback=_grey_range(0, 255),
              help="Background grey.")
@click.option("--ink", type=float, default=30.0, show_default=True, callback=_grey_range(0, 255),
              help="Grey of the features.")
@click.option("--supersample", type=click.IntRange(1, 8), default=3, show_default=True,
              help="Rays a pixel side for the faces (their outlines and a board's squares are anti-aliased so).")
@click.option("--pose", "poses", type=int, multiple=True, help="Render only this pose (repeatable).")
@click.option("--cameras", type=click.Choice(["both", "left"]), default="both", show_default=True)
@click.option("--visibility", type=click.Choice(["exact", "scene", "all"]), default="exact", show_default=True,
              help="Hidden features: removed by the faces (exact), the view-points' lists (scene), or none.")
@click.option("--force", is_flag=True, help="Replace an output folder that holds files wiredsl did not write, and "
              "render beyond the CPU and memory budget (600 s, 1.5 GB estimated).")
@diagnostics_option
@guarded
def render(file: str, output: str | None, pipeline_name: str | None, no_effects: bool, seed: int | None,
           blur: float, noise: float, edges: str, stroke_width: float, faces: str, corners: str, background: float,
           ink: float, supersample: int, poses: tuple[int, ...], cameras: str, visibility: str, force: bool,
           diagnostics: str) -> None:
    """Draw what the cameras see as 8-bit PNGs, <camera>_<pose>.png, and render.json (a test and teaching device)."""
    import secrets
    from pathlib import Path

    from wiredsl import run as runs
    from wiredsl.io import render as rd
    from wiredsl.language.compile import compile_file

    if output is not None:
        folder_name(Path(output), (".png", ".json"), "one PNG a view and render.json are written into it")
    scene, warnings, program = compile_file(file)
    report(warnings, program.sources, diagnostics)
    with setup_errors():
        chosen = runs.check_poses(scene, poses) if poses else None
        choice = runs.choose_pipeline(scene, pipeline_name, no_effects)
    if choice.note is not None:
        click.echo(f"note: {choice.note}", err=True)
    seed = seed if seed is not None else secrets.randbits(63)
    look = rd.Look(blur=blur, noise=noise, edges=edges, width=stroke_width, ink=ink, background=background,
                   faces=faces, corners=corners, supersample=supersample, boards=rd.scene_boards(scene))
    out = Path(output) if output is not None else Path("build") / scene.name / "render"
    with setup_errors():
        images = rd.write(out, scene, pipeline=choice.pipeline, seed=seed, look=look, poses=chosen, cameras=cameras,
                          visibility=visibility, force=force)
    click.echo(f"wrote {len(images)} image{'s' * (len(images) != 1)} and render.json to {out} (seed {seed}, "
               + (f"pipeline {choice.pipeline.name})" if choice.pipeline else "ideal projection)"), err=True)
