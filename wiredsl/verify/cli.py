"""The `verify` command's options (click only at import; the work is in command.py, imported when it runs)."""

from __future__ import annotations

import math

import click

from wiredsl import install_hint
from wiredsl.cli_base import FiniteRange, diagnostics_option, guarded, report


@click.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--images", "globs", multiple=True, required=True,
              help="Images to verify (a glob; repeatable). Camera and frame from the names: left_003.png, right01.jpg.")
@click.option("--camera", "cameras", multiple=True,
              help="The camera (left, right, or a rig camera's name) of the --images at the same position.")
@click.option("--poses", default="path", show_default=True,
              help="path: the scene's path pose of the number in each image's name; FILE: a trajectory file of the "
                   "camera's poses (world_from_camera, OpenCV axes); board: solvePnP on the scene's calibration board.")
@click.option("--format", "pose_format", type=click.Choice(["tum", "euroc", "kitti", "csv"]), default=None,
              help="The pose file's format (default: from its content).")
@click.option("--match", type=click.Choice(["auto", "time", "order"]), default="auto", show_default=True,
              help="Pose file to images: by the timestamps in the image names, or in order (auto: time when the "
                   "names are times within the file's span).")
@click.option("--detector", "detectors", multiple=True, required=True,
              help="canny, lsd, harris, shi-tomasi, or an installed plug-in (entry points wiredsl.detectors); "
                   "repeatable.")
@click.option("--param", "params", multiple=True, help="A detector parameter, [DETECTOR.]KEY=VALUE (repeatable).")
@click.option("--step", type=FiniteRange(0.25, 100), default=2.0, show_default=True,
              help="px between samples along a model edge.")
@click.option("--band", type=FiniteRange(0.5, 100), default=6.0, show_default=True,
              help="px searched either side of a sample, along the edge's normal.")
@click.option("--angle", type=FiniteRange(1, 90), default=20.0, show_default=True,
              help="deg: largest angle between a detected gradient and the model edge's normal.")
@click.option("--radius", type=FiniteRange(0.5, 1000), default=10.0, show_default=True,
              help="px: a model corner is found when a detected corner is this near (the paper's 10 px).")
@click.option("--inlier", type=FiniteRange(0.1, 1000), default=2.0, show_default=True,
              help="px: a found corner farther than this from the model's is displaced (a corner mismatch).")
@click.option("--refine", is_flag=True, help="Refine each pose to align the model with the detected edges first.")
@click.option("--fit", "do_fit", is_flag=True, help="Fit each effect's parameters and write the pipeline (.wd).")
@click.option("--edge-loss", "edge_loss", type=click.Choice(["gaps", "raw"]), default="gaps", show_default=True,
              help="Fit edge_loss to the gaps (the detector's own loss at each gap's ends taken off), or to all "
                   "that was lost (1 - the verified fraction).")
@click.option("--calibration-error/--no-calibration-error", "calibration_error", default=True, show_default=True,
              help="With --fit: start the pipeline with calibration_error sigma 1 when the rig declares its "
                   "calibration's uncertainty. --no-calibration-error when these images calibrated the rig: "
                   "their corners already fit it.")
@click.option("--predict", is_flag=True,
              help="With --fit: simulate the frames with the fitted pipeline and compare the verified fraction, "
                   "lateral offset and stereo 3D corner and shape errors with the real detector's "
                   "(prediction.json, plot).")
@click.option("--predict-pipeline", default=None, metavar="NAME",
              help="With --predict: simulate the scene's pipeline NAME instead of the fitted one (the paper's "
                   "magnitudes against your detector, say).")
@click.option("--trials", type=click.IntRange(1, 100000), default=50, show_default=True,
              help="Simulated trials a frame for --predict.")
@click.option("--holdout", default=None, metavar="SPLIT",
              help="Fit on some frames and predict the others image by image: odd (fit on the even-numbered "
                   "frames in name order, predict the odd), even, or kfold:K (frame i in fold i mod K). A frame is "
                   "a stereo pair or one image. Writes holdout.json and the plot.")
@click.option("--spreads/--no-spreads", default=True, show_default=True,
              help="With --fit or --holdout: fit each magnitude's spread between images (and between an image's "
                   "features, for the edge loss) and its correlation along the frames; --no-spreads: constants only.")
@click.option("--pipeline-name", default="measured", show_default=True, help="The fitted pipeline's name.")
@click.option("--seed", type=click.IntRange(0, 2**63 - 1), default=0, show_default=True,
              help="Seed of the fit's bootstrap resamples and of --predict's simulated trials.")
@click.option("--plot-format", type=click.Choice(["png", "svg", "pdf"]), default="png", show_default=True)
@click.option("-o", "--output", required=True, help="Output folder.")
@diagnostics_option
@guarded
def verify(file, globs, cameras, poses, pose_format, match, detectors, params, step, band, angle, radius, inlier,
           refine, do_fit, edge_loss, calibration_error, predict, predict_pipeline, trials, holdout, spreads,
           pipeline_name, seed, plot_format, output, diagnostics) -> None:
    """Verify the scene's projected model against detected features in images (the paper's Figure 7), and with
    --fit estimate each effect's parameters as a pipeline."""
    from pathlib import Path

    try:
        import cv2  # noqa: F401
    except ImportError:
        raise click.UsageError(f"verify needs OpenCV: {install_hint('images')}") from None
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise click.UsageError(f"verify's Figure 7 needs matplotlib: {install_hint('plot')}") from None
    if len(cameras) > len(globs):
        raise click.BadParameter("more --camera than --images", param_hint="--camera")
    if predict_pipeline is not None and not predict:
        raise click.BadParameter("needs --predict", param_hint="--predict-pipeline")
    if predict and not do_fit:
        raise click.BadParameter("needs --fit (the prediction simulates the fitted pipeline)", param_hint="--predict")
    if not pipeline_name.isidentifier():
        raise click.BadParameter("must be a name (letters, digits, _)", param_hint="--pipeline-name")
    out = Path(output)
    if out.exists() and not out.is_dir():
        raise click.BadParameter(f"must name a folder: {out} is a file", param_hint="-o")
    from wiredsl.verify import command
    from wiredsl.verify.verification import Settings

    pairs = [(g, cameras[k] if k < len(cameras) else None) for k, g in enumerate(globs)]
    req = command.Request(file, pairs, list(detectors), list(params), poses, pose_format, match,
                          Settings(step, band, math.radians(angle), radius, inlier), do_fit, seed, pipeline_name,
                          refine, plot_format, edge_loss, predict, trials, predict_pipeline, calibration_error,
                          holdout, spreads)
    try:
        outcome = command.run(req, out, command.progress_printer())
    except ValueError as exc:
        raise click.UsageError(str(exc)) from None
    report(outcome.warnings, {}, diagnostics)
    for s in outcome.summary:
        click.echo(f"{s['detector']}\t{s['object']}\t{100 * s['verified_fraction']:.1f}% verified\t"
                   f"{s['images']} images", err=False)
    if outcome.refined:
        import statistics

        r = outcome.refined
        before = [m["rms_offset_before_px"] for m in r if m["rms_offset_before_px"] is not None]
        after = [m["rms_offset_after_px"] for m in r if m["rms_offset_after_px"] is not None]
        offset = (f"median RMS offset {statistics.median(before):.3g} -> {statistics.median(after):.3g} px"
                  if before and after else "no edge found to measure an offset by")  # (not "nan -> nan")
        click.echo(f"refined {len(r)} poses: median move {statistics.median(m['rotation_deg'] for m in r):.3g} deg, "
                   f"{statistics.median(m['translation'] for m in r):.3g} m; {offset}", err=True)
    for key, e in (outcome.prediction or {}).items():
        if e["ks"] is not None:
            click.echo(f"predict\t{key}\treal {e['real_mean']:.4g}\tsimulated {e['simulated_mean']:.4g}\t"
                       f"KS p {e['ks']['p']:.3g}\tMann-Whitney p {e['mann_whitney']['p']:.3g}")
    for key, s in (outcome.holdout or {}).items():
        click.echo(f"holdout\t{key}\t{s['inside']} of {s['images']} inside their 90% band\t"
                   f"({100 * s['inside_fraction']:.0f}%)\tmean percentile {s['mean_percentile']:.2f}")
    for note in outcome.notes:
        click.echo(f"note: {note}", err=True)
    click.echo(f"wrote {out}: {', '.join(outcome.written)}", err=True)
