"""`wiredsl bench`: what each accuracy knob costs in time, measured on the user's own scene.

Four tables, every row measured in this run:
1. polyline tolerance: largest distance from the true image curve (densely sampled, independently of
   the adaptive sampler) to the emitted polylines, time per view, vertices per view;
2. view-dependency: meshes of several spacings (and the scene's own) against exact per-camera
   visibility: fraction of (pose, camera, feature) visibilities that differ, and the time each takes;
3. Monte-Carlo trials: standard error of a headline statistic (mean displacement of the corners that
   survive, ideal to disturbed, under the scene's pipeline) against wall time;
4. float32 against float64 projection: largest pixel difference, and time.
Rows that would not fit the time budget are not run, and say so.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from wiredsl.engine import geometry, visibility
from wiredsl.engine.simulate import Options, simulate, visibility_masks
from wiredsl.engine.world import World, ellipse_points
from wiredsl.montecarlo import Run
from wiredsl.run import start
from wiredsl.scene import Scene

TOLERANCES = (0.01, 0.03, 0.1, 0.3, 1.0, 2.0)
SPACINGS = (0.25, 0.5, 1.0, 2.0)
TRIALS = (10, 100, 1000, 10_000, 100_000)
PRECISION_POINTS = 1_000_000  # scene points projected in float32 and float64
MIN_SECONDS = 0.3  # a timed call is repeated until it has taken this long (above timer noise)
clock = time.perf_counter  # every row's timer (module-level so that a test can give a fake one)


@dataclass
class Table:
    title: str
    columns: list[str]
    rows: list[list] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    plot: tuple[int, int] | None = None  # (x column, y column) for the figure: cost against error
    short: str = ""  # the figure's panel title

    def markdown(self) -> str:
        out = [f"### {self.title}", "", "| " + " | ".join(self.columns) + " |",
               "|" + "---|" * len(self.columns)]
        out += ["| " + " | ".join(_fmt(v) for v in row) + " |" for row in self.rows]
        out += [""] + [f"{n}" for n in self.notes]
        return "\n".join(out).rstrip() + "\n"


def _fmt(v) -> str:
    if isinstance(v, float):
        if v == 0:
            return "0"
        return f"{v:.3g}" if abs(v) < 1e4 else f"{v:,.0f}"
    if isinstance(v, int):
        return f"{v:,}"
    return str(v)


def _timed(fn, min_seconds: float | None = None):
    """(result, seconds per call), repeating fast calls to measure them above timer noise."""
    min_seconds = MIN_SECONDS if min_seconds is None else min_seconds
    t0 = clock()
    result = fn()
    elapsed = clock() - t0
    reps = 1
    while elapsed < min_seconds and reps < 50:
        fn()
        reps += 1
        elapsed = clock() - t0
    return result, elapsed / reps


# --------------------------------------------------------------------------- 1. tolerance

def _true_curves(world: World, view, fid: int, segment: int) -> np.ndarray:
    """Dense true image points (inside the image, in front, within the fold) of one feature."""
    cam = view.camera
    if world.feature_kind[fid] == "ellipse":
        e = int(np.flatnonzero(world.ell_fid == fid)[0])
        t = np.linspace(world.ell_arc[e, 0], world.ell_arc[e, 1], 20001)
        P = ellipse_points(np.broadcast_to(world.ell_c[e], (len(t), 3)), np.broadcast_to(world.ell_U[e], (len(t), 3)),
                           np.broadcast_to(world.ell_V[e], (len(t), 3)), t)
    else:
        rows = np.flatnonzero((world.line_fid == fid) & (world.line_segment == segment))
        if len(rows) == 0:
            return np.zeros((0, 2))
        A, B = world.lines[rows[0]]
        t = np.linspace(0, 1, 20001)[:, None]
        P = A + t * (B - A)
    Pc = geometry.world_to_cam(P, view.R_cw, view.t_cw)
    if cam.distortion != "radtan":  # the near rule of an angle-bounded lens, a little inside its limit
        Pc = Pc[geometry.visible(Pc, geometry.MODELS.index(cam.distortion), geometry.lens_limit(cam) * 0.999)]
    else:
        Pc = Pc[Pc[:, 2] > geometry.NEAR * 1.01]
        xy = geometry.cam_to_plane(Pc)
        Pc = Pc[np.hypot(xy[:, 0], xy[:, 1]) < geometry.lens_limit(cam) * 0.999]
    uv = geometry.cam_to_pixels(Pc, cam)
    inside = (uv[:, 0] > 0.5) & (uv[:, 0] < cam.width - 0.5) & (uv[:, 1] > 0.5) & (uv[:, 1] < cam.height - 0.5)
    return uv[inside]


def _distance_to_polylines(points: np.ndarray, polylines: list[np.ndarray]) -> np.ndarray:
    best = np.full(len(points), np.inf)
    for poly in polylines:
        a, b = poly[:-1], poly[1:]
        d = b - a
        for lo in range(0, len(points), 4096):
            p = points[lo:lo + 4096]
            t = np.clip(((p[:, None] - a[None]) * d[None]).sum(-1) / np.maximum((d * d).sum(-1), 1e-300), 0, 1)
            dist = np.linalg.norm(p[:, None] - (a[None] + t[..., None] * d[None]), axis=-1).min(axis=1)
            best[lo:lo + 4096] = np.minimum(best[lo:lo + 4096], dist)
    return best


def tolerance_table(scene: Scene, world: World) -> Table:
    table = Table("Polyline tolerance: accuracy of curved features against time",
                  ["tolerance (px)", "max deviation (px)", "time per view (ms)", "vertices per view"], plot=(3, 1),
                  short="polyline tolerance")
    opts = Options(visibility="all")
    vis = visibility_masks(scene, world, opts)
    for tol in TOLERANCES:
        o = Options(tolerance=tol, visibility="all")
        results, seconds = _timed(lambda o=o: simulate(scene, o, world, vis))
        views = [v for r in results for v in (r.left, r.right) if v is not None]
        worst = 0.0
        vertices = 0
        for v in views:
            groups: dict[tuple[int, int], list[np.ndarray]] = {}
            for f in v.features:
                if f.kind == "polyline":
                    groups.setdefault((f.fid, f.segment), []).append(f.points)
                    vertices += len(f.points)
            for (fid, seg), polys in groups.items():
                truth = _true_curves(world, v, fid, seg)
                if len(truth):
                    worst = max(worst, float(_distance_to_polylines(truth, polys).max()))
        table.rows.append([tol, worst, 1000 * seconds / len(views), round(vertices / len(views))])
    table.notes.append("Deviation: every one of 20,001 true curve points a feature (projected exactly, inside the "
                       "image) to the nearest emitted polyline of that feature.")
    return table


# --------------------------------------------------------------------------- 2. view-dependency

def _grid(lo, hi, spacing):
    xs = np.arange(lo[0], hi[0] + 1e-9, spacing)
    ys = np.arange(lo[1], hi[1] + 1e-9, spacing)
    return np.array([(x, y) for y in ys for x in xs])


def viewdep_table(scene: Scene, world: World) -> Table:
    table = Table("View-dependency: manifold against exact per-camera visibility",
                  ["visibility from", "view-points", "wrong visibility (fraction)", "time for the path (s)",
                   "wrong image length vs hidden lines (fraction)"], plot=(3, 2),
                  short="view-point mesh spacing")
    rig = scene.rig
    eyes, keys = [], []
    poses = np.array(scene.path.poses, dtype=float)  # floor projections
    for i in range(len(poses)):
        for mount in (rig.left, rig.right):
            R_cw, t_cw = geometry.camera_from_world(scene.path.pose(i), mount.rotation, mount.position)
            eyes.append(-R_cw.T @ t_cw)
            keys.append(i)
    t0 = clock()
    exact = visibility.visible_features(world, np.array(eyes))
    exact_seconds = clock() - t0
    # the image length of every feature whole, and of its unoccluded parts (--visibility exact)
    whole, parts = (_image_lengths(world, simulate(scene, Options(visibility=v), world)) for v in ("all", "exact"))

    def wrong_length(vis: np.ndarray) -> float:
        """Fraction of the image length a per-feature list gets wrong: hidden parts shown, visible ones dropped."""
        return float(np.where(vis, whole - parts, parts).sum() / max(whole.sum(), 1e-300))

    table.rows.append(["exact (each camera at each pose)", "-", 0.0, exact_seconds, wrong_length(exact)])
    meshes = []
    if scene.viewpoints is not None:
        meshes.append((f"scene's mesh '{scene.viewpoints.name}'", np.array(scene.viewpoints.points, dtype=float)))
        lo, hi = meshes[0][1].min(axis=0), meshes[0][1].max(axis=0)
    else:
        lo, hi = poses[:, :2].min(axis=0) - 1, poses[:, :2].max(axis=0) + 1
    for s in SPACINGS:
        meshes.append((f"grid {s:g} m", _grid(lo, hi, s)))
    h = visibility.eye_height(scene)
    for name, pts in meshes:
        t0 = clock()
        nearest = visibility.nearest_viewpoint(pts, poses[:, :2])
        needed = sorted(set(nearest.tolist()))
        vis = visibility.visible_features(world, np.column_stack([pts[needed], np.full(len(needed), h)]))
        seconds = clock() - t0
        row_of = {k: j for j, k in enumerate(needed)}
        approx = np.array([vis[row_of[int(nearest[i])]] for i in keys])
        wrong = float((approx != exact).mean())
        table.rows.append([name, len(pts), wrong, seconds, wrong_length(approx)])
    table.notes.append("Wrong image length: the fraction of the features' image length that a whole-feature list "
                       "gets wrong against hidden-line removal (--visibility exact): hidden parts shown plus visible "
                       "parts left out, over the length of every feature shown whole.")
    table.notes.append("Wrong visibility: the fraction of (pose, camera, feature) visibilities that differ from the "
                       "exact ones. Time: computing the lists of the view-points this path's poses are nearest to "
                       "(a view-dependency file computes them once for every view-point and is then free).")
    return table


def _image_lengths(world: World, results) -> np.ndarray:
    """(pose x camera, feature) image length in pixels of the emitted strokes, views in eye order."""
    rows = []
    for r in results:
        for v in (r.left, r.right):
            length = np.zeros(world.n_features)
            for f in v.features:
                if f.kind in ("line", "polyline"):
                    length[f.fid] += np.linalg.norm(np.diff(f.points, axis=0), axis=1).sum()
            rows.append(length)
    return np.array(rows)


# --------------------------------------------------------------------------- 3. trials

def headline(run: Run, batch_out) -> np.ndarray:
    """Per trial of a batch: mean displacement (px) of the corners that survive, ideal to disturbed."""
    sums, counts = None, None
    for result, disturbed, _ in batch_out:
        for side, s in disturbed.items():
            ideal = getattr(run.ideal()[[r.index for r in run.ideal()].index(result.index)], side)
            ref = {f.fid: f.points[0] for f in ideal.features if f.kind == "corner"}
            n = int(s.corner_trial.max(initial=-1)) + 1
            if sums is None or len(sums) < n:
                grow = n - (0 if sums is None else len(sums))
                sums = np.concatenate([[] if sums is None else sums, np.zeros(grow)])
                counts = np.concatenate([[] if counts is None else counts, np.zeros(grow)])
            for p, fid, t in zip(s.corners, s.corner_fid, s.corner_trial, strict=True):
                if fid in ref:
                    sums[t] += np.linalg.norm(p - ref[fid])
                    counts[t] += 1
    return sums / np.maximum(counts, 1) if sums is not None else np.zeros(0)


def trials_table(scene: Scene, world: World, budget: float, seed: int = 1) -> Table:
    pipeline = scene.pipeline()
    name = pipeline.name if pipeline else "none"
    table = Table(f"Monte-Carlo trials: standard error of the mean corner displacement (pipeline '{name}') "
                  "against time", ["trials", "mean displacement (px)", "standard error (px)", "wall time (s)"],
                  plot=(3, 2), short="Monte-Carlo trials")
    if pipeline is None:
        table.notes.append("The scene has no default pipeline: nothing to measure.")
        return table
    if len(world.corners) == 0:
        table.notes.append("The scene has no corners: no displacement to measure.")
        return table
    spent = 0.0
    rate = None
    warm = Run.create(scene, world, pipeline, seed, Options())
    for _, out in warm.batches([0]):  # compiles and caches what a first batch needs: in no row's time
        headline(warm, out)
    for n in TRIALS:
        if rate is not None and spent + n / rate > budget:
            table.notes.append(f"{n:,} trials not run: at the measured {rate:,.0f} trials/s they would take "
                               f"{_fmt(n / rate)} s, over the budget of {budget:g} s (--budget).")
            continue
        run = start(scene, pipeline, seed=seed, world=world)
        t0 = clock()
        values = np.concatenate([headline(run, out) for _, out in run.batches(list(range(n)))])
        seconds = clock() - t0
        spent += seconds
        rate = n / seconds
        table.rows.append([n, float(values.mean()), float(values.std(ddof=1) / math.sqrt(n)), seconds])
    return table


# --------------------------------------------------------------------------- 4. float32

def precision_table(scene: Scene, world: World) -> Table:
    table = Table(f"float32 against float64: projection of {PRECISION_POINTS:,} scene points",
                  ["arithmetic", "max difference (px)", "time (ms)"], plot=(2, 1), short="float32 against float64")
    rng = np.random.default_rng(0)
    pts, _ = visibility.samples(world)  # points on every feature of the scene
    if len(pts) == 0:
        table.notes.append("The scene has no features: nothing to measure.")
        return table
    idx = rng.integers(0, len(pts), PRECISION_POINTS)
    other = rng.integers(0, len(pts), PRECISION_POINTS)
    t = rng.random((PRECISION_POINTS, 1))
    P = pts[idx] + t * (pts[other] - pts[idx])  # points on and between the scene's edges
    mount = scene.rig.left
    R_cw, t_cw = geometry.camera_from_world(scene.path.pose(0), mount.rotation, mount.position)
    cam = scene.camera(mount.camera)

    def project(dtype):
        Pc = geometry.world_to_cam(P.astype(dtype), R_cw.astype(dtype), t_cw.astype(dtype))
        Pc = Pc[Pc[:, 2] > 0.1]
        return geometry.cam_to_pixels(Pc, cam)

    ref, t64 = _timed(lambda: project(np.float64))
    got, t32 = _timed(lambda: project(np.float32))
    if len(ref) == 0:
        table.notes.append("No scene point is in front of the first pose's left camera: nothing to measure.")
        return table
    inside = (np.abs(ref[:, 0] - cam.width / 2) < cam.width) & (np.abs(ref[:, 1] - cam.height / 2) < cam.height)
    diff = float(np.abs(got.astype(np.float64) - ref)[inside].max())
    table.rows.append(["float64", 0.0, 1000 * t64])
    table.rows.append(["float32", diff, 1000 * t32])
    table.notes.append("Points within one image size of the image. The engine keeps float64 throughout: the "
                       "float32 error is shown against the time it would save.")
    return table


# --------------------------------------------------------------------------- the figure

def plot(tables: list[Table], fmt: str = "svg", dpi: int = 150) -> bytes:
    """Error against cost, one log-log panel per table (matplotlib, imported only here); SVG, PDF or PNG bytes.

    Points are joined in order of their x value. A zero error (float64 against itself, exact visibility) has no
    place on a log axis: it is drawn as a hollow triangle on a dotted floor a decade below the smallest
    error, labelled "0 (exact)", with break marks on the axis.
    """
    import io

    import matplotlib
    from matplotlib.figure import Figure

    rc = {"svg.hashsalt": "wiredsl", "font.size": 10, "axes.titlesize": 11, "axes.labelsize": 10,
          "svg.fonttype": "none"}
    with matplotlib.rc_context(rc):
        fig = Figure(figsize=(10, 7.2), layout="constrained")
        axes = fig.subplots(2, 2).ravel()
        for ax, t in zip(axes, tables, strict=False):
            _panel(ax, t)
        for ax in axes[len(tables):]:
            ax.set_visible(False)
        buf = io.BytesIO()
        meta = {"svg": {"Date": None}, "pdf": {"CreationDate": None, "Producer": None}}.get(fmt, {"Software": None})
        fig.savefig(buf, format=fmt, dpi=dpi, metadata=meta)
    return buf.getvalue()


def _panel(ax, t: Table) -> None:
    """One table's points, sorted by x, with a marked floor for zero errors."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    ax.set_title(t.short or t.title)
    rows = [r for r in t.rows if t.plot and isinstance(r[t.plot[0]], float | int)
            and isinstance(r[t.plot[1]], float | int) and r[t.plot[0]] > 0 and r[t.plot[1]] >= 0]
    if not t.plot or not rows:
        ax.text(0.5, 0.5, "nothing to measure", ha="center", va="center", transform=ax.transAxes)
        ax.set_xticks([])
        ax.set_yticks([])
        return
    rows.sort(key=lambda r: r[t.plot[0]])
    xs = np.array([r[t.plot[0]] for r in rows], dtype=float)
    ys = np.array([r[t.plot[1]] for r in rows], dtype=float)
    names = [_fmt(r[0]) for r in rows]
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(t.columns[t.plot[0]] + " (log)")
    ax.set_ylabel(t.columns[t.plot[1]] + " (log)")
    pos = ys > 0
    floor = 10 ** (math.floor(math.log10(ys[pos].min())) - 1) if pos.any() else 1e-3
    lo, hi = xs.min(), xs.max()
    ax.set_xlim(lo / 2, hi * 3)  # before plotting: rows of one x value would autoscale to a singular range
    ax.plot(xs[pos], ys[pos], "-o", color="#1f4e79", lw=1.5, ms=5)
    if (~pos).any():
        ax.axhline(floor, color="#888888", ls=":", lw=1)
        ax.plot(xs[~pos], np.full((~pos).sum(), floor), "v", color="#c62828", ms=8, mfc="none", mew=1.5)
        top = ys[pos].max() if pos.any() else floor * 10
        ax.set_ylim(floor / 3, top * 3)
        for y0 in (floor * 1.8, floor * 2.2):  # break marks: the axis does not reach zero
            ax.plot([-0.015, 0.015], [y0 / 1.1, y0 * 1.1], transform=ax.get_yaxis_transform(), color="#333333",
                    lw=1.2, clip_on=False)
    to_axes = ax.transScale + ax.transLimits  # data -> axes fraction, on the log scales (x limits are set)
    taken: list[tuple[float, float, float]] = []  # zero-error labels placed: (left, right, height) in points
    for x, name in sorted(zip(xs[~pos], np.array(names, dtype=object)[~pos], strict=True), key=lambda p: p[0]):
        text = f"{name.split(' (')[0]}: zero error"
        px, half = to_axes.transform([[x, floor]])[0, 0] * AXES_PT[0], 0.28 * LABEL_PT * len(text)
        dy = 8.0
        while any(left < px + half and px - half < right and h == dy for left, right, h in taken):
            dy += LABEL_PT + 3  # a neighbour's label is there: one line higher
        taken.append((px - half, px + half, dy))
        ax.annotate(text, (x, floor), xytext=(0, dy), textcoords="offset points", fontsize=LABEL_PT,
                    color="#c62828", ha="center")
    note = f"points labelled by {t.columns[0]}"
    ax.text(0.98, 0.97, note, transform=ax.transAxes, ha="right", va="top",
            fontsize=8.5, color="#444444")
    ax.grid(True, which="major", color="#e0e0e0", lw=0.8)
    w = 0.56 * LABEL_PT * len(note)  # the note's corner is no place for a label
    _labels(ax, xs[pos], ys[pos], [n for n, p in zip(names, pos, strict=True) if p],
            reserved=[(0.98 * AXES_PT[0] - w, 0.97 * AXES_PT[1] - LABEL_PT - 2, AXES_PT[0], AXES_PT[1])])
    for axis in (ax.xaxis, ax.yaxis):  # 1-2-5 ticks as plain numbers; no crowded minor labels
        axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        axis.set_minor_formatter(NullFormatter())


LABEL_PT = 8.5  # the points' label size
AXES_PT = (290.0, 190.0)  # a panel's plotting area in points, about (a 10 x 7.2 in figure of 2 x 2 panels)


def _labels(ax, xs: np.ndarray, ys: np.ndarray, names: list[str], reserved: list[tuple] = ()) -> None:
    """Label each point where its text overlaps no other label and no point: the first free place of right-below,
    right-above, left-above, left-below, further below, further above. Points at the same place share a label."""
    ax.get_xlim(), ax.get_ylim()  # settle the autoscaled limits first
    to_axes = ax.transScale + ax.transLimits  # data -> axes fraction, on the log scales
    at = to_axes.transform(np.column_stack([xs, ys])) * AXES_PT
    groups: dict[tuple[float, float], list[int]] = {}
    for i, (px, py) in enumerate(at):
        groups.setdefault((round(px, 1), round(py, 1)), []).append(i)
    boxes = [(px - 4, py - 4, px + 4, py + 4) for px, py in at] + list(reserved)  # the markers, the note
    for members in groups.values():
        i = members[0]
        text = " = ".join(names[j] for j in members)
        w, h = 0.56 * LABEL_PT * len(text), LABEL_PT
        px, py = at[i]
        for dx, dy in ((6, -13), (6, 5), (-6 - w, 5), (-6 - w, -13), (6, -24), (6, 16), (-6 - w, -24),
                       (-6 - w, 16)):
            box = (px + dx, py + dy, px + dx + w, py + dy + h)
            free = all(box[2] <= b[0] or b[2] <= box[0] or box[3] <= b[1] or b[3] <= box[1] for b in boxes)
            inside = 0 <= box[0] and box[2] <= AXES_PT[0] and 0 <= box[1] and box[3] <= AXES_PT[1]
            if free and inside:
                break
        boxes.append(box)
        ax.annotate(text, (xs[i], ys[i]), xytext=(dx, dy), textcoords="offset points", fontsize=LABEL_PT,
                    color="#444444")


def run_all(scene: Scene, world: World, budget: float, progress=lambda msg: None) -> list[Table]:
    tables = []
    for name, make in (("tolerance", lambda: tolerance_table(scene, world)),
                       ("view-dependency", lambda: viewdep_table(scene, world)),
                       ("trials", lambda: trials_table(scene, world, budget)),
                       ("float32", lambda: precision_table(scene, world))):
        progress(f"measuring {name} ...")
        tables.append(make())
    return tables
