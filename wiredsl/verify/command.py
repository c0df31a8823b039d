"""`wiredsl verify`: images in, detectors run, the projected scene verified, the table, Figure 7 and (--fit) the
fitted pipeline out. Images are read one frame at a time (a stereo pair at most), so memory does not grow
with the number of images."""

from __future__ import annotations

import dataclasses
import os
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from wiredsl.diagnostics import Diagnostic, WiredslError
from wiredsl.files import remove_stale, temporary
from wiredsl.verify import fit as fitting
from wiredsl.verify import images as im
from wiredsl.verify import report, variation_fit
from wiredsl.verify import verification as ver
from wiredsl.verify.detectors import Detection, checked, params_of, registry
from wiredsl.verify.measured import pipeline_text

STAGE = "verify"  # the staging folder inside -o is a temporary of -o/verify (files.temporary)


@dataclass
class Request:
    scene: str
    images: list[tuple[str, str | None]]  # (glob, camera or None)
    detectors: list[str]
    params: list[str] = field(default_factory=list)
    poses: str = "path"  # path | board | FILE
    pose_format: str | None = None
    match: str = "auto"
    settings: ver.Settings = field(default_factory=ver.Settings)
    fit: bool = False
    seed: int = 0
    pipeline_name: str = "measured"
    refine: bool = False
    plot_format: str = "png"
    edge_loss: str = "gaps"  # gaps | raw: see fit.fit
    predict: bool = False  # simulate the frames with the fitted pipeline and compare (predict.py)
    trials: int = 50
    predict_pipeline: object = None  # a Pipeline, or a scene pipeline's name, to predict with instead of the fitted one
    calibration_error: bool = True  # the rig's declared calibration uncertainty simulated (measured.pipeline_text)
    holdout: str | None = None  # odd | even | kfold:K: fit on some frames, predict the others (holdout.py)
    spreads: bool = True  # fit the spreads between images and correlations along them (variation_fit.py)


@dataclass
class Outcome:
    written: list[str]
    fit: fitting.Fit | None
    frames: int
    images: int
    warnings: list[Diagnostic]
    summary: list[dict]
    notes: list[str]
    refined: list[dict] = field(default_factory=list)
    prediction: dict | None = None  # --predict: predict.compare's measures
    holdout: dict | None = None  # --holdout: per statistic, holdout.summary


def _detectors(names: list[str], params: list[str]):
    """[(name, class, params)] for --detector names and --param [DET.]KEY=VALUE pairs (usage errors raised as
    ValueError)."""
    from wiredsl.plugins import lookup

    reg = registry()
    chosen = []
    for name in names:
        cls, why = lookup(reg, name)
        if cls is None:
            if why:
                raise WiredslError([Diagnostic("error", "E180", why, None)])
            raise ValueError(f"unknown detector {name!r}: built in are {', '.join(reg.builtins)}; a plug-in is an "
                             "installed entry point of the group wiredsl.detectors")
        chosen.append((name, cls))
    out = []
    used = set()
    for name, cls in chosen:
        mine = []
        for k, pair in enumerate(params):
            key = pair.partition("=")[0].strip()
            det, dot, bare = key.rpartition(".")
            if dot and det == name:
                mine.append(f"{bare}={pair.partition('=')[2]}")
                used.add(k)
            elif not dot and key.replace("-", "_") in cls.Params.model_fields:
                mine.append(pair)
                used.add(k)
        out.append((name, cls, params_of(cls, mine)))
    unused = [params[k] for k in range(len(params)) if k not in used]
    if unused:
        raise ValueError(f"--param {unused[0]!r} matches no parameter of the detectors "
                         f"({', '.join(n for n, _ in chosen)})")
    return out


def sums_of(results: list[ver.ImageResult], cfg: ver.Settings, edge_det: str | None,
            corner_det: str | None) -> fitting.ImageSums:
    """What one image (its results by detector) gives the fit: the first edge and the first corner detector."""
    s = fitting.ImageSums()
    for r in results:
        if r.detector == edge_det and r.stats is not None:
            st = r.stats
            s.tested, s.verified = float(st.tested.sum()), float(st.verified.sum())
            s.length, s.lost_middle, s.lost_ends = (float(st.tested_length.sum()), float(st.lost_middle.sum()),
                                                    float(st.lost_ends.sum()))
            s.ends, s.gap_ends = float(st.ends.sum()), float(st.gap_ends.sum())
            ok = (st.run_length >= fitting.MIN_RUN_PX) & (st.run_n >= 4) & np.isfinite(st.run_noise)
            d = st.run_mean[ok]
            s.strokes, s.d1, s.d2, s.offsets = int(ok.sum()), float(d.sum()), float((d * d).sum()), d.tolist()
            s.offset_noise = st.run_noise[ok].tolist()
            s.offset_length = st.run_length[ok].tolist()
            s.offset_line = ((np.diff(r.strokes.start) == 2)[st.run_stroke[ok]]).tolist() if ok.any() else []
            s.noise = float(np.nansum(st.run_noise[ok]))
            tested = st.tested > 0
            s.runs, s.run_strokes = float(st.runs[tested].sum()), int(tested.sum())
            # approx_error from the lines alone (two vertices: the effect tilts each by its ends' moves); a
            # polyline's vertices move each on its own, which a line fitted along a run does not see
            line = (np.diff(r.strokes.start) == 2)[st.run_stroke] if len(st.run_stroke) else np.zeros(0, bool)
            use = ok & line & np.isfinite(st.run_end_diff) & np.isfinite(st.run_end_noise)
            e = st.run_end_diff[use]
            s.fitted, s.fitted2 = len(e), float((e * e).sum())
            s.fitted_noise = float(st.run_end_noise[use].sum())
        if r.detector == corner_det and r.corners is not None:
            c = r.corners
            s.corners, s.found = float(len(c.fid)), float(c.found.sum())
            far = c.found & (c.error > cfg.inlier)
            s.displaced, s.displaced_r = float(far.sum()), float(c.error[far].sum())
            near, e, dof = ver.corner_residuals(c, cfg.inlier)
            s.located, s.loc_dof, s.loc2 = float(near.sum()), dof, float((e * e).sum())
            if r.stereo is not None:
                s.matched, s.wrong = float(len(r.stereo[1])), float(r.stereo[1].sum())
    return s


def pair_sums(s: fitting.ImageSums, left: ver.CornerMatch, right: ver.CornerMatch, inlier: float) -> None:
    """A stereo pair's corners located in both images (by feature id): the sums of the products of their two
    cameras' residuals (`corner_residuals`), for the correlation of the cameras' localisation errors."""
    (nl, el, _), (nr, er, _) = ver.corner_residuals(left, inlier), ver.corner_residuals(right, inlier)
    _, il, ir = np.intersect1d(left.fid[nl], right.fid[nr], return_indices=True)
    a, b = el[il], er[ir]
    s.pairs, s.pair_lr, s.pair_ll, s.pair_rr = float(len(il)), float((a * b).sum()), float((a * a).sum()), \
        float((b * b).sum())


def run(req: Request, out: Path, progress=None) -> Outcome:
    from wiredsl.engine import occlusion
    from wiredsl.engine.simulate import Options, project_pose, project_view, require_buildable
    from wiredsl.engine.world import build_world
    from wiredsl.language.compile import compile_file

    scene, warnings, program = compile_file(req.scene)
    require_buildable(scene, path=req.poses == "path")
    if isinstance(req.predict_pipeline, str):  # (--predict-pipeline NAME: said before any image is read)
        named = scene.pipeline(req.predict_pipeline)
        if named is None:
            raise ValueError(f"--predict-pipeline: the scene has no pipeline '{req.predict_pipeline}' (it has: "
                             f"{', '.join(p.name for p in scene.pipelines) or 'none'})")
        req = dataclasses.replace(req, predict_pipeline=named)
    dets = _detectors(req.detectors, req.params)
    frames = im.frames_of(req.images, scene.rig)
    if req.poses == "path":
        im.assign_path(frames, scene)
        pose_note = "the scene's path, by the number in each image's name"
    elif req.poses == "board":
        pose_note, frames = _board_poses(frames, scene, warnings)
    else:
        side = _pose_side(frames)
        match = im.assign_file(frames, scene, req.poses, req.pose_format, req.match, side)
        pose_note = f"{req.poses} ({req.pose_format or 'format from its content'}, matched by {match}; the poses " \
                    f"of the {side} camera)"
    if req.holdout:  # a bad split is a usage error before any frame is verified
        from wiredsl.verify.holdout import parse_split

        parse_split(req.holdout, len(frames))
    world = build_world(scene)
    occluders = occlusion.Occluders.of_world(world)
    opts = Options(visibility="exact")
    ellipses = set(world.ell_fid.tolist())
    cfg = req.settings
    edge_det = next((n for n, c, _ in dets if c.finds == "edges"), None)
    corner_det = next((n for n, c, _ in dets if c.finds == "corners"), None)
    rows: list[tuple] = []
    fractions = report.ObjectFractions()
    sums: list[fitting.ImageSums] = []
    extras, sums_frame, held = [], [], []  # per image: spreads' extras and frame index; per frame: holdout's
    notes: set[str] = set()
    refined: list[dict] = []
    n_images = 0
    observed = []
    unverified: list[tuple[str, float]] = []  # images where most of the model is unverified
    for i, frame in enumerate(frames):
        im.check_finite_pose(frame)
        pose = project_pose(scene, world, frame.pose, i, opts, occluders=occluders)
        views = {"left": pose.left, "right": pose.right}
        per_side: dict[str, tuple] = {}
        for side, path in frame.images.items():
            view = views[side]
            cam = view.camera
            grey = im.read_grey(path, cam.width, cam.height, warnings)
            found = {}
            for name, cls, params in dets:
                found[name] = _detect(cls, name, grey, params)
                if found[name].note:
                    notes.add(f"{name}: {found[name].note}")
            if req.refine and edge_det is not None:
                from wiredsl.verify import refine

                def project(R, t, cam=cam):
                    return project_view(world, cam, R, t, world.mask(None), opts.tolerance, occluders)

                view, moved = refine.refine_view(project, view, found[edge_det], grey.shape, cfg)
                refined.append({"image": path, **moved})
            results = [ver.verify_image(view, found[name], grey.shape, cfg,
                                        ver.ImageResult(path, side, frame.label, name, world.feature_ids), ellipses)
                       for name, _, _ in dets]
            share = _verified_share(results, edge_det, corner_det)
            if share is not None and share < UNVERIFIED:
                unverified.append((path, share))
            per_side[side] = (grey if corner_det is not None and len(frame.images) == 2 else None, found, results,
                              grey.shape)
            n_images += 1
        if corner_det is not None and len(per_side) == 2:
            (gl, fl, rl, _), (gr, fr_, rr, _) = per_side["left"], per_side["right"]
            lm = next(r for r in rl if r.detector == corner_det).corners
            rm = next(r for r in rr if r.detector == corner_det).corners
            left_res = next(r for r in rl if r.detector == corner_det)
            left_res.stereo = ver.stereo_mismatches(gl, gr, lm, rm, fl[corner_det].corners, fr_[corner_det].corners,
                                                    cfg.radius)
        if req.predict:
            observed.append(_observed(frame, views, per_side, edge_det, corner_det, cfg))
        if req.holdout:
            from wiredsl.verify import holdout

            held.append(holdout.observe(frame, views, per_side, edge_det, corner_det, cfg, _objects(world)))
        for side, (_, _, results, _) in per_side.items():
            for r in results:
                rows.extend(report.rows_of(r))
                fractions.add(r)
            sums.append(sums_of(results, cfg, edge_det, corner_det))
            extras.append(variation_fit.extras_of(results, side, edge_det, corner_det, variation_fit.MIN_STROKE_SAMPLES,
                                                  cfg.inlier))
            sums_frame.append(i)
            if side == "left" and corner_det is not None and len(per_side) == 2:
                pair_sums(sums[-1], *(next(r for r in per_side[s][2] if r.detector == corner_det).corners
                                      for s in ("left", "right")), cfg.inlier)
        if progress is not None:
            progress(i + 1, len(frames))
    if unverified:
        warnings.append(_unverified_warning(unverified, n_images, pose_note))
    out.mkdir(parents=True, exist_ok=True)
    # staged: published together at the end. Named as every temporary of wiredsl's (host, pid), so that a later
    # run removes the stage of one that was killed (SIGKILL leaves no chance to clean up)
    remove_stale(out / STAGE)
    final, out = out, temporary(out / STAGE, ".tmp")
    out.mkdir()
    try:
        summary = fractions.summary()
        meta = {"scene": str(req.scene), "images": n_images, "frames": len(frames), "poses": pose_note,
                "detectors": [{"name": n, "params": p.model_dump()} for n, _, p in dets],
                "settings": {"step_px": cfg.step, "band_px": cfg.band, "angle_deg": float(np.degrees(cfg.angle)),
                             "corner_radius_px": cfg.radius, "corner_inlier_px": cfg.inlier},
                "objects": summary, "notes": sorted(notes), "refined": refined}
        written = report.write_table(out, rows, meta)
        caption = (f"{Path(req.scene).name}; {n_images} images; detectors {', '.join(n for n, _, _ in dets)}; "
                   f"samples every {cfg.step:g} px, searched +-{cfg.band:g} px, gradient within "
                   f"{np.degrees(cfg.angle):.0f} deg")
        if summary:
            name = f"figure7.{req.plot_format}"
            report.figure7(fractions, out / name, caption, req.plot_format)
            written.append(name)
        result = None
        if req.fit:
            from wiredsl.files import json_text, write_atomic

            result = fitting.fit(sums, req.seed, cfg.inlier, cfg.radius, req.edge_loss, band=cfg.band)
            if req.spreads:
                variation_fit.add(result, extras, sums_frame, [f.pose for f in frames], req.seed, req.edge_loss)
            det_text = "; ".join(f"{n} ({', '.join(f'{k} {v}' for k, v in p.model_dump().items())})"
                                 for n, _, p in dets)
            provenance = [f"Fitted by `wiredsl verify` from {n_images} images of {len(frames)} frames "
                          f"({', '.join(g for g, _ in req.images)}) against {Path(req.scene).name}.",
                          f"Detectors: {det_text}.", f"Poses: {pose_note}.",
                          f"Intervals: 95% bootstrap over images ({fitting.B} resamples, seed {req.seed}; "
                          "percentiles widened by sqrt(n / (n - 1)) t / z for n images).",
                          "Include this file in the scene and build with --pipeline " + req.pipeline_name + "."]
            cal = scene.rig.calibration
            text = pipeline_text(result, req.pipeline_name, provenance,
                                 None if cal is None else f"{cal.kind} over {len(cal.order)} parameters",
                                 req.calibration_error)
            write_atomic(out / f"{req.pipeline_name}.wd", text)
            write_atomic(out / "fit.json", json_text({**result.to_json(), "seed": req.seed, "bootstrap": fitting.B},
                                                     indent=1))
            written += [f"{req.pipeline_name}.wd", "fit.json"]
        prediction = held_doc = None
        if req.predict:
            # the fitted pipeline's shift comes with the fit's background term (edges the model does not name)
            bg = result.background if result is not None and req.predict_pipeline is None else 0.0
            prediction = _predict(req, out, scene, world, observed, cfg, n_images, bg)
            written += ["prediction.json", f"prediction.{req.plot_format}"]
        if req.holdout:
            from wiredsl.verify import holdout

            cal = scene.rig.calibration
            held_doc, names = holdout.run(req, out, scene, world, held, sums, sums_frame, cfg,
                                   None if cal is None else f"{cal.kind} over {len(cal.order)} parameters",
                                   corner_det is not None, _objects(world), extras if req.spreads else None)
            written += names
        _publish(out, final, written, req)
    finally:
        shutil.rmtree(out, ignore_errors=True)
    return Outcome(written, result, len(frames), n_images, warnings, summary, sorted(notes), refined, prediction,
                   held_doc["summary"] if held_doc else None)


UNVERIFIED = 0.5  # an image whose model is verified less than this is warned of (W192): its pose is likely wrong
LEAST_TESTED = 20  # edge samples (model corners) an image needs for its share to be judged


def _verified_share(results: list[ver.ImageResult], edge_det: str | None, corner_det: str | None) -> float | None:
    """The share of an image's model the detectors verified: its edge samples (the first edge detector), else its
    model corners found (the first corner detector); None with too little of the model in view to judge."""
    for r in results:
        if r.detector == edge_det and r.stats is not None and r.stats.tested.sum() >= LEAST_TESTED:
            return float(r.stats.verified.sum() / r.stats.tested.sum())
    for r in results:
        if r.detector == corner_det and r.corners is not None and len(r.corners.fid) >= LEAST_TESTED:
            return float(r.corners.found.mean())
    return None


def _unverified_warning(unverified: list[tuple[str, float]], n_images: int, pose_note: str) -> Diagnostic:
    """W192 at the first image where most of the model is unverified, naming every such image."""
    shown = ", ".join(f"{Path(p).name} ({100 * v:.0f}%)" for p, v in unverified[:8])
    more = f" and {len(unverified) - 8} more" if len(unverified) > 8 else ""
    return Diagnostic("warning", "W192", f"most of the model is unverified in {len(unverified)} of {n_images} "
                      f"images: {shown}{more} (verified share; poses: {pose_note})", im.at(unverified[0][0]),
                      "an image paired with another image's pose verifies little: check that each image's number "
                      "is its path pose (--poses path), or its line in the pose file")


def _published_names(req: Request) -> set[str]:
    """Every file a verify run may write into its -o folder."""
    plots = ("png", "svg", "pdf")
    return {"verification.csv", "verification.json", "fit.json", "prediction.json", f"{req.pipeline_name}.wd",
            "holdout.json", *(f"figure7.{x}" for x in plots), *(f"prediction.{x}" for x in plots),
            *(f"holdout.{x}" for x in plots)}


def _objects(world) -> list[str]:
    """Each feature's object (the name before the dot of its id), by feature index."""
    return [str(f).split(".")[0] for f in world.feature_ids]


def _publish(stage: Path, out: Path, written: list[str], req: Request) -> None:
    """Move the run's files from the staging folder into -o, after a last look for a signal that was dropped,
    and remove the files of an earlier run that this one did not write (an older fit.json beside a new table
    would be stale). Other files in -o are left alone. A failure before this point leaves -o as it was."""
    from wiredsl import check_stop

    check_stop()
    for name in written:
        os.replace(stage / name, out / name)
    for name in sorted(_published_names(req) - set(written)):
        (out / name).unlink(missing_ok=True)


def _observed(frame, views, per_side, edge_det, corner_det, cfg):
    """A frame's real measures for the prediction (predict.py)."""
    from wiredsl.verify import predict

    o = predict.Observed(frame.label, tuple(frame.pose))
    for side, (_, _, results, shape) in per_side.items():
        o.shape[side] = shape
        r = next((r for r in results if r.detector == edge_det), None)
        o.values[side] = predict.edge_values(r.stats if r is not None else None)
    if corner_det is not None and len(per_side) == 2:
        found = {s: per_side[s][1][corner_det].corners for s in ("left", "right")}
        o.pair = predict.corner_errors_3d(views["left"], views["right"], found["left"], found["right"], cfg.radius)
    return o


def _predict(req: Request, out: Path, scene, world, observed, cfg, n_images: int, background: float = 0.0) -> dict:
    """--predict: the frames simulated with the fitted pipeline (or req.predict_pipeline), compared image by
    image with the real detector's measures; prediction.json and the prediction plot."""
    import os
    import tempfile

    from wiredsl.files import json_text, write_atomic
    from wiredsl.language.compile import compile_file
    from wiredsl.verify import predict

    pipeline = req.predict_pipeline
    if pipeline is None:
        with tempfile.NamedTemporaryFile("w", suffix=".wd", dir=out, delete=False) as f:
            f.write(f'wiredsl 1\ninclude "{Path(req.scene).resolve()}"\n'
                    f'include "{(out / (req.pipeline_name + ".wd")).resolve()}"\n')
        try:
            pipeline = compile_file(f.name)[0].pipeline(req.pipeline_name)
        finally:
            os.unlink(f.name)
    sim = predict.simulate(scene, world, pipeline, observed, cfg, req.trials, req.seed, background=background)
    comp = predict.compare(observed, sim)
    predict.per_image(comp, observed, sim)
    stages = ", ".join(f"{s.effect} " + " ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                                                  for k, v in s.params.items()) for s in pipeline.stages)
    caption = (f"{Path(req.scene).name}; {n_images} images; pipeline {pipeline.name} ({stages}); {req.trials} "
               f"trials a frame, seed {req.seed}")
    name = f"prediction.{req.plot_format}"
    predict.plot(comp, out / name, caption, req.plot_format)
    doc = {"pipeline": pipeline.name, "stages": [s.model_dump() for s in pipeline.stages], "trials": req.trials,
           "seed": req.seed,
           "measures": {k: {kk: vv for kk, vv in e.items() if not kk.startswith("_")} for k, e in comp.items()}}
    write_atomic(out / "prediction.json", json_text(doc, indent=1))
    return doc["measures"]


def _detect(cls, name: str, grey: np.ndarray, params) -> Detection:
    from wiredsl.verify.detectors import BUILTIN

    try:
        det = cls.detect(grey, params)
        return checked(det, grey.shape, name)
    except (ValueError, TypeError, ArithmeticError, IndexError, KeyError, AttributeError) as exc:
        if name in BUILTIN:
            raise
        from wiredsl.plugins import failure

        raise failure("detector", name, registry(), f"failed: {type(exc).__name__}: {exc}") from None


def _pose_side(frames: list[im.Frame]) -> str:
    """The camera a pose file's poses are of: the left, unless every image is the right camera's."""
    return "right" if all(set(f.images) == {"right"} for f in frames) else "left"


def _board_poses(frames: list[im.Frame], scene, warnings: list[Diagnostic]) -> tuple[str, list[im.Frame]]:
    """`--poses board`: each frame's pose from the board in its left image (its right one in a right-only
    frame), found by board.py (solvePnP with the scene's camera). Frames without the board are left out with a
    warning (W196); a board found in fewer than half of the frames is E197. One image is read at a time."""
    from wiredsl.verify import board

    kept, missed = [], []
    for frame in frames:
        side = "left" if "left" in frame.images else "right"
        path = frame.images[side]
        cam = scene.camera(getattr(scene.rig, side).camera)
        grey = im.read_grey(path, cam.width, cam.height, warnings)
        try:
            found = board.board_poses(scene, [(path, grey)], side, least=0.0)
        except WiredslError as err:  # not found in this one image: its warning, and the frame is left out
            if any(d.severity == "error" and d.code != "E197" for d in err.diagnostics):
                raise
            warnings.extend(d for d in err.diagnostics if d.severity == "warning")
            missed.append(path)
            continue
        pose = found.poses[0]
        if pose.found and pose.robot_pose is not None:
            frame.pose = pose.robot_pose
            frame.pose_from = f"board in {path} (reprojection {pose.rms:.3g} px rms)"
            kept.append(frame)
        else:
            warnings.extend(found.diagnostics)
            missed.append(path)
    if not kept or len(kept) < board.LEAST_FRACTION * len(frames):
        shown = ", ".join(Path(m).name for m in missed[:5]) + (", ..." if len(missed) > 5 else "")
        raise WiredslError([*warnings, Diagnostic(
            "error", "E197", f"the board is found in {len(kept)} of {len(frames)} frames (at least half needed); "
            f"not in: {shown}", None, "check the board's size in the scene (inner corners across and down), the "
            "lighting, and that the whole board is in view")])
    return f"the scene's board, by solvePnP ({len(kept)} of {len(frames)} frames)", kept


def progress_printer(stream=None):
    """A progress bar on stderr (a terminal: redrawn in place; otherwise a line every 10%)."""
    stream = stream or sys.stderr
    tty = stream.isatty()
    state = {"last": -1}

    def show(done: int, total: int) -> None:
        if tty:
            width = 30
            k = int(width * done / total)
            stream.write(f"\rverify [{'#' * k}{'.' * (width - k)}] {done}/{total} frames")
            if done == total:
                stream.write("\n")
            stream.flush()
        else:
            tenth = 10 * done // total
            if tenth != state["last"] and (tenth > state["last"]):
                state["last"] = tenth
                if total >= 20:
                    stream.write(f"verify: {done}/{total} frames\n")

    return show
