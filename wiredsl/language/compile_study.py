"""Stage 3 for `study` blocks: factors, design, trials, poses and measures, checked against the
pipelines, the effects' parameter models and the measures' registry.

A factor may name a stage its pipeline lacks: the study then inserts that stage (with its
paper defaults for the parameters it does not vary) at its data-flow position, so one study
can rank all seven sources while starting from a pipeline that has only some of them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import pydantic

from wiredsl.diagnostics import NOT_INSTALLED, Collector, Span, did_you_mean
from wiredsl.effects import REGISTRY
from wiredsl.language import ast
from wiredsl.language.bind import Bound, Value, bind, quantity
from wiredsl.plugins import lookup, params_of
from wiredsl.scene import Factor, MeasureUse, Pipeline, Study

MAX_POINTS = 100_000  # design points of one study
# Camera parameters a study may vary as `camera.<name>.<param>`: (unit kind, lower bound, doc).
CAMERA_FACTORS = {
    "f": ("image", 0.0, "focal length in pixels"), "ax": ("number", 0.0, "aspect scale x"),
    "ay": ("number", 0.0, "aspect scale y"), "cx": ("image", None, "optical centre x"),
    "cy": ("image", None, "optical centre y"), "k": ("number", None, "TINA's radial coefficient (k1 = -k)"),
    "k1": ("number", None, "OpenCV's k1"), "k2": ("number", None, "OpenCV's k2"),
    "p1": ("number", None, "OpenCV's p1"), "p2": ("number", None, "OpenCV's p2"),
    "k3": ("number", None, "k3 (OpenCV's, or the fisheye's)"),
    "k4": ("number", None, "k4 (rational, or the fisheye's)"),
    "k5": ("number", None, "OpenCV's rational k5"), "k6": ("number", None, "OpenCV's rational k6"),
    "xi": ("number", None, "xi (unified, ds)"), "alpha": ("number", None, "alpha (eucm, ds)"),
    "beta": ("number", 0.0, "beta (eucm)"), "w": ("number", 0.0, "w (fov, rad)"),
    "readout": ("time", None, "rolling shutter: the first row's exposure to the last's (s), on a path with times"),
}
MAX_SPEED = 100.0  # m/s: as the compiler's `speed` (language/compile.py)
# Factors of the robot's motion a study may vary, `path.speed` and `rig.sync`: (unit kind, doc).
MOTION_FACTORS = {
    "path.speed": ("speed", "the robot's speed along the written poses (each pose's time: its distance over it)"),
    "rig.sync": ("time", "the right camera's exposure time minus the left's"),
}
MAX_TRIALS = 10**9  # design points x trials


def measure_registry() -> Mapping:
    """The measures a study may name: `wiredsl.measures.REGISTRY`, built-in then installed (a mapping)."""
    from wiredsl.measures import REGISTRY as measures

    return measures


def compile_study(b: Bound, pipelines: dict[str, Pipeline], n_poses: int | None, units_of, out: Collector,
                  cameras: dict | tuple[str, ...] = (), path=None) -> Study | None:
    """One `study NAME { ... }` block as a Study; None after reporting its errors (`path`: the scene's compiled
    path, for factors of its motion)."""
    n_errors = len(out.errors)
    seen: dict[str, Span] = {}
    bounds: list[Bound] = []
    for stmt in b.stmt.block or ():
        sb = bind(stmt, "study", units_of(stmt), out)
        if sb is None or not sb.ok:
            continue
        if stmt.keyword not in ("vary", "measure"):
            if stmt.keyword in seen:
                out.error("E103", f"'{stmt.keyword}' given twice in study '{b.name}'", stmt.keyword_span,
                          f"first at {seen[stmt.keyword]}")
                continue
            seen[stmt.keyword] = stmt.keyword_span
        bounds.append(sb)
    first = {sb.stmt.keyword: sb for sb in reversed(bounds)}

    pipeline = None
    if "pipeline" in first:
        pb = first["pipeline"]
        pipeline = pb.pos(0)
        if pipeline not in pipelines and pipeline != "paper":  # paper: the built-in one (scene.paper_pipeline)
            out.unknown(f"unknown pipeline '{pipeline}' in study '{b.name}'", pb.positional[0].span,
                        did_you_mean(pipeline, pipelines)
                        or "pipelines: " + ", ".join([*pipelines, "the built-in paper"]))
    else:
        defaults = [p.name for p in pipelines.values() if p.default] or (
            list(pipelines) if len(pipelines) == 1 else [])
        pipeline = defaults[0] if defaults else None

    kind = first["design"].pos(0) if "design" in first else "grid"
    if path is not None and path.times is None and path.transforms is None and any(
            sb.stmt.keyword == "vary" and isinstance(sb.stmt.args[0], ast.Ref)
            and sb.stmt.args[0].parts == ("path", "speed") for sb in bounds):
        # `vary path.speed` drives written poses that declare no speed (the lab's): each design point times them
        # at its own speed (design.scene_at), so the study's readouts and sync have a motion to act on
        timed = path.timed(1.0)
        # no two neighbours at one place (1e-9 m at 1 m/s: the compiler's GEOM_EPS)
        if all(b - a > 1e-9 for a, b in zip(timed.times[:-1], timed.times[1:], strict=True)):
            path = timed
    factors = []
    labels: dict[str, Span] = {}
    for sb in bounds:
        if sb.stmt.keyword == "vary":
            f = _factor(sb, kind, units_of(sb.stmt), out, cameras, path)
            if f is not None:
                if f.label in labels:
                    out.error("E103", f"'{f.label}' varied twice in study '{b.name}'", sb.positional[0].span,
                              f"first at {labels[f.label]}")
                    continue
                labels[f.label] = sb.positional[0].span
                factors.append(f)

    points, design_seed = None, 0
    if "design" in first:
        db = first["design"]
        design_seed = int(db.get("seed", 0))
        if db.has("points"):
            points = int(db.get("points"))
            if kind == "grid":
                out.error("E171", "a grid design has no 'points': its size is the product of the factors' values",
                          db.span("points"), "use 'design sobol points N' or 'design lhs points N'")
            elif points < 1:
                out.error("E170", f"design of study '{b.name}' has no points", db.span("points"),
                          "give at least 1 base sample")
            elif points & (points - 1):
                low = 1 << (points.bit_length() - 1)
                out.error("E171", f"a {kind} design needs a power of 2 base samples (Sobol' indices), got {points}",
                          db.span("points"), f"use {low} or {2 * low}")
        elif kind != "grid":
            out.error("E102", f"'design {kind}' needs 'points' (base samples n; the design runs n (d + 2))",
                      db.stmt.span, "e.g. design sobol points 16 seed 7")
        if kind != "grid" and not factors and not out.errors[n_errors:]:
            out.error("E170", f"a {kind} design of study '{b.name}' has no factors to fill", db.stmt.keyword_span,
                      "add 'vary stage.param from A to B'")
    trials = 16
    if "trials" in first:
        trials = int(first["trials"].pos(0))
        if trials < 1:
            out.error("E170", f"study '{b.name}' runs no trials", first["trials"].positional[0].span,
                      "give at least 1 trial per design point")
    seed = int(first["seed"].pos(0)) if "seed" in first else 0
    draws = first["draws"].pos(0) if "draws" in first else "common"
    poses = None
    if "poses" in first:
        vals: list[Value] = first["poses"].pos(0)
        poses = []
        for v in vals:
            if n_poses is not None and not 0 <= v.value < n_poses:
                out.error("E110", f"pose {v.value} is not in 0..{n_poses - 1}", v.span)
            elif v.value in poses:
                out.error("E103", f"pose {v.value} given twice", v.span)
            else:
                poses.append(v.value)
        if not vals:
            out.error("E170", f"study '{b.name}' runs no poses", first["poses"].positional[0].span,
                      "leave 'poses' out to run every pose")
    measures = [m for sb in bounds if sb.stmt.keyword == "measure" for m in [_measure(sb, units_of(sb.stmt), out)]
                if m is not None]
    if not any(sb.stmt.keyword == "measure" for sb in bounds):
        out.error("E102", f"study '{b.name}' needs at least one 'measure'", b.name_span,
                  "e.g. measure " + (next(iter(measure_registry()), "pgh")))

    if len(out.errors) == n_errors:
        n_points = _size(kind, factors, points)
        if n_points > MAX_POINTS:
            out.error("E151", f"study '{b.name}' has {n_points:,} design points, over the limit of {MAX_POINTS:,}",
                      first["design"].stmt.span if "design" in first else b.name_span,
                      "fewer values or base samples")
        elif n_points * trials > MAX_TRIALS:
            out.error("E151", f"study '{b.name}' runs {n_points * trials:,} trials, over the limit of "
                              f"{MAX_TRIALS:,}", first["trials"].positional[0].span, "fewer trials per point")
    if len(out.errors) != n_errors:
        return None
    return Study(name=b.name, pipeline=pipeline, factors=factors, design=kind, points=points,
                 design_seed=design_seed, seed=seed, draws=draws, trials=trials, poses=poses, measures=measures)


def _size(kind: str, factors: list[Factor], points: int | None) -> int:
    if kind == "grid":
        return math.prod(len(f.values) if f.values is not None else f.steps for f in factors)
    return points * (len(factors) + 2)


def _factor(sb: Bound, kind: str, units: dict[str, str], out: Collector, cameras: dict | tuple[str, ...] = (),
            path=None) -> Factor | None:
    """A `vary stage.param ...` (or `camera.<name>.<param>`, `path.speed`, `rig.sync`) statement: the target and
    parameter known, the values in range."""
    ref = sb.stmt.args[0]
    span = sb.positional[0].span
    if isinstance(ref, ast.Ref) and len(ref.parts) == 3 and ref.parts[0] == "camera":
        if ref.parts[2] == "readout" and (path is None or path.times is None):
            _no_motion(out, path, "varying a readout needs the robot's motion, and the scene's path has no times",
                       span, "give the path a 'speed' (e.g. speed 0.5m/s), or read a trajectory file with timestamps")
            return None
        return _camera_factor(sb, ref, kind, units, out, cameras)
    if isinstance(ref, ast.Ref) and ref.parts in (("path", "speed"), ("rig", "sync")):
        return _motion_factor(sb, ref, kind, units, out, path)
    if not isinstance(ref, ast.Ref) or len(ref.parts) != 2 or "*" in ref.parts:
        out.error("E106", f"expected 'stage.param' or 'camera.<name>.<param>', got '{sb.pos(0)}'", span,
                  "e.g. lateral_shift.range")
        return None
    stage, param = ref.parts
    effect, problem = lookup(REGISTRY, stage)
    if problem is not None:
        out.error("E180", problem, span)
        return None
    if effect is None:
        out.error("E104", f"unknown stage '{stage}'", span, did_you_mean(stage, REGISTRY)
                  or f"{NOT_INSTALLED}; stages: " + ", ".join(REGISTRY))
        return None
    fields = effect.Params.model_fields
    if param not in fields:
        out.error("E104", f"unknown parameter '{param}' of stage '{stage}'", span,
                  did_you_mean(param, fields) or "parameters: " + ", ".join(fields))
        return None
    value_kind = (fields[param].json_schema_extra or {}).get("kind", "number")

    def check(v: float) -> str | None:
        try:
            params_of("effect", effect, REGISTRY, {param: v})
        except pydantic.ValidationError as exc:
            err = exc.errors()[0]
            ctx = err.get("ctx", {})
            return next((f"{w} {ctx[k]:g}" for k, w in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<"))
                         if k in ctx), err["msg"])
        return None

    return _values(sb, stage, param, value_kind, check, kind, units, out)


def _no_motion(out: Collector, path, message: str, span: Span, hint: str) -> None:
    """E102 for a factor of the robot's motion the path cannot give; held back with the unknown names when there
    is no path because an include failed (the path may be the missing file's, as the lab study's is)."""
    if path is None and out.hold_unknown:
        out.unknown(message, span, hint)
    else:
        out.error("E102", message, span, hint)


def _motion_factor(sb: Bound, ref: ast.Ref, kind: str, units: dict[str, str], out: Collector, path
                   ) -> Factor | None:
    """`path.speed` (the written poses' speed: their times scale with it) or `rig.sync` (the stereo pair's offset)."""
    span = sb.positional[0].span
    if ref.parts == ("path", "speed"):
        if path is None or path.speed is None:
            _no_motion(out, path, "varying path.speed needs a path of written poses, no two neighbours at one place",
                       span, "a trajectory file's times are its own; a robot that turns on the spot needs times per "
                             "pose")
            return None
        return _values(sb, "path", "speed", "speed", lambda v: None if 0 < v <= MAX_SPEED else
                       f"in (0, {MAX_SPEED:g}] m/s", kind, units, out)
    if path is None or path.times is None:
        _no_motion(out, path, "varying rig.sync needs the robot's motion, and the scene's path has no times", span,
                   "give the path a 'speed' (e.g. speed 0.5m/s), or read a trajectory file with timestamps")
        return None
    return _values(sb, "rig", "sync", "time", lambda v: None if abs(v) <= 1.0 else "within 1 s", kind, units, out)


def _camera_factor(sb: Bound, ref: ast.Ref, kind: str, units: dict[str, str], out: Collector,
                   cameras: dict | tuple[str, ...]) -> Factor | None:
    """`camera.<name>.<param>`: a camera's own parameter (what the robot has and believes), not an error."""
    _, name, param = ref.parts
    span = sb.positional[0].span
    if name not in cameras:
        out.unknown(f"unknown camera '{name}'", span, did_you_mean(name, cameras)
                    or "cameras: " + (", ".join(cameras) or "none"))
        return None
    if param not in CAMERA_FACTORS:
        out.error("E104", f"unknown camera parameter '{param}'", span,
                  did_you_mean(param, CAMERA_FACTORS) or "parameters: " + ", ".join(CAMERA_FACTORS))
        return None
    cam = cameras.get(name) if isinstance(cameras, dict) else None
    from wiredsl.engine.geometry import MODEL_KEYS

    model = getattr(cam, "distortion", None)
    if model is not None and param not in ("f", "ax", "ay", "cx", "cy", "readout") and not (
            param in MODEL_KEYS[model] or (param == "k" and "k1" in MODEL_KEYS[model])):
        out.error("E104", f"camera '{name}' has the {model} lens model, which has no '{param}'", span,
                  f"its numbers are {', '.join(MODEL_KEYS[model])}" + (" (and k, which is -k1)"
                                                                         if "k1" in MODEL_KEYS[model] else ""))
        return None
    value_kind, low, _ = CAMERA_FACTORS[param]
    if param == "readout":
        return _values(sb, f"camera.{name}", param, value_kind, lambda v: None if 0 <= v <= 1.0 else "in [0, 1] s",
                       kind, units, out)
    return _values(sb, f"camera.{name}", param, value_kind,
                   lambda v: f"> {low:g}" if low is not None and not v > low else None, kind, units, out)


def _values(sb: Bound, stage: str, param: str, value_kind: str, check, kind: str, units: dict[str, str],
            out: Collector) -> Factor | None:
    """The factor's values (a list, or a range with steps for a grid), converted and range-checked."""
    has_values, has_range = sb.has("values"), sb.has("from") or sb.has("to")
    if has_values and has_range:
        out.error("E103", "give either 'values' or 'from ... to', not both", sb.span("values"))
        return None
    if not has_values and not has_range:
        out.error("E102", f"'vary {stage}.{param}' needs 'values [...]' or 'from A to B'", sb.stmt.span,
                  f"e.g. {sb.sig.example}")
        return None

    def convert(arg: ast.Arg) -> float | None:
        if not isinstance(arg, ast.Number):
            out.error("E106", f"expected a number for {stage}.{param}, got '{getattr(arg, 'name', '...')}'", arg.span)
            return None
        n_before = len(out.errors)
        v = quantity(arg, value_kind, units, out)
        if len(out.errors) != n_before:
            return None
        bound = check(v)
        if bound is not None:
            out.error("E110", f"{stage} {param}: must be {bound}, got {arg.text}", arg.span)
            return None
        return v

    if has_values:
        if sb.has("steps"):
            out.error("E103", "'steps' goes with 'from ... to', not with 'values'", sb.span("steps"))
            return None
        items = sb.get("values")
        if not items:
            out.error("E170", f"'vary {stage}.{param}' has no values", sb.span("values"), "give at least one")
            return None
        if kind != "grid":
            out.error("E171", f"a {kind} design fills ranges: give 'from A to B', not a list", sb.span("values"))
            return None
        values = [convert(a) for a in items]
        if None in values:
            return None
        return Factor(stage=stage, param=param, values=values)
    if not (sb.has("from") and sb.has("to")):
        missing = "to" if sb.has("from") else "from"
        out.error("E102", f"'vary {stage}.{param}' needs '{missing}'", sb.stmt.span, f"e.g. {sb.sig.example}")
        return None
    lo, hi = convert(sb.get("from")), convert(sb.get("to"))
    if lo is None or hi is None:
        return None
    if not lo < hi:
        out.error("E110", f"range of {stage}.{param} must rise: from {sb.get('from').text} to {sb.get('to').text}",
                  sb.span("to"))
        return None
    steps = None
    if kind == "grid":
        if not sb.has("steps"):
            out.error("E171", f"a grid over a range needs 'steps' for {stage}.{param}", sb.stmt.span,
                      "e.g. from 0 to 6px steps 4, or a list: values [0, 2px, 4px]")
            return None
        steps = int(sb.get("steps"))
        if steps < 1:
            out.error("E170", f"'vary {stage}.{param}' has no steps", sb.span("steps"), "give at least 1")
            return None
    elif sb.has("steps"):
        out.error("E171", f"a {kind} design draws its own values: no 'steps'", sb.span("steps"))
        return None
    values = None if steps is None else ([lo] if steps == 1 else
                                         [lo + (hi - lo) * i / (steps - 1) for i in range(steps)])
    return Factor(stage=stage, param=param, low=lo, high=hi, steps=steps, values=values)


def _measure(sb: Bound, units: dict[str, str], out: Collector) -> MeasureUse | None:
    """A `measure NAME [param value]...` statement, checked against the measure's parameter model."""
    name, span = sb.pos(0), sb.positional[0].span
    registry = measure_registry()
    measure, problem = lookup(registry, name)
    if problem is not None:
        out.error("E180", problem, span)
        return None
    if measure is None:
        out.error("E104", f"unknown measure '{name}'", span,
                  did_you_mean(name, registry) or (f"{NOT_INSTALLED}; measures: " + ", ".join(registry) if registry
                                                   else "no measures are installed (wiredsl.measures)"))
        return None
    fields = measure.Params.model_fields
    args: list[ast.Arg] = sb.pos(1)
    params: dict[str, float | str] = {}
    spans: dict[str, Span] = {}
    i = 0
    while i < len(args):
        key = args[i]
        if not isinstance(key, ast.Ref) or len(key.parts) != 1 or key.name not in fields:
            word = key.name if isinstance(key, ast.Ref) else None
            out.error("E101", f"unknown parameter '{word}' of measure '{name}'" if word else
                      f"expected a parameter name of measure '{name}'", key.span,
                      (did_you_mean(word, fields) if word else None) or "parameters: " + (", ".join(fields) or "none"))
            return None
        if key.name in params:
            out.error("E103", f"'{key.name}' given twice in 'measure {name}'", key.span)
            return None
        if i + 1 >= len(args):
            out.error("E102", f"'{key.name}' needs a value", key.span)
            return None
        val = args[i + 1]
        if isinstance(val, ast.Number):
            kind = (fields[key.name].json_schema_extra or {}).get("kind", "number")
            params[key.name] = quantity(val, kind, units, out)
        elif isinstance(val, ast.Ref) and len(val.parts) == 1:
            params[key.name] = val.name
        else:
            out.error("E106", f"expected a number or a word for '{key.name}'", val.span)
            return None
        spans[key.name] = val.span
        i += 2
    try:
        params_of("measure", measure, registry, params)
    except pydantic.ValidationError as exc:
        for err in exc.errors():
            key = str(err["loc"][0]) if err["loc"] else ""
            out.error("E110", f"measure {name} {key}: {err['msg']}", spans.get(key, span))
        return None
    return MeasureUse(name=name, params=params)
