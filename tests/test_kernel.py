"""The compiled kernel against the numpy path (the readable reference): the same keyed draws give
identical discrete decisions (which strokes, fragments, vertices and corners survive, with their
metadata) and coordinates within 1e-9 px, on every buildable scene, over many trials, for the scene's
own pipelines and for every stage at the paper's values."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_replay import SCENES, pipelines

from wiredsl.engine.simulate import Options
from wiredsl.engine.world import build_world
from wiredsl.language.compile import compile_file
from wiredsl.montecarlo import Run

DISCRETE = ("start", "fid", "segment", "fragment", "kind", "clipped", "closed", "occluded", "trial", "corner_fid",
            "corner_trial")


def batches(run: Run, engine: str, trials) -> list:
    run.engine = engine
    return [out for _, out in run.batches(trials, 64)]


@pytest.mark.parametrize("path", SCENES)
def test_kernel_and_numpy_agree_on_every_scene_over_many_trials(path):
    scene, _, _ = compile_file(path)
    world = build_world(scene)
    for pipe in pipelines(scene):
        runs = {e: Run.create(scene, world, pipe, 99, Options()) for e in ("numpy", "kernel")}
        got = {e: batches(run, e, range(500, 692)) for e, run in runs.items()}
        assert runs["kernel"].uses_kernel() and not runs["numpy"].uses_kernel()
        worst, strokes = 0.0, 0
        for bn, bk in zip(got["numpy"], got["kernel"], strict=True):
            for (r, dn, _), (_, dk, _) in zip(bn, bk, strict=True):
                assert set(dn) == set(dk)
                for side, a in dn.items():
                    b = dk[side]
                    for name in DISCRETE:
                        assert np.array_equal(getattr(a, name), getattr(b, name)), (path, pipe.name, r.index, side,
                                                                                     name)
                    worst = max(worst, np.abs(a.pts - b.pts).max(initial=0),
                                np.abs(a.corners - b.corners).max(initial=0))
                    strokes += a.n_strokes
        assert strokes > 0 and worst < 1e-9, (path, pipe.name, worst)
        # the manifests' measured statistics agree too (sums in another order: to rounding)
        mn, mk = runs["numpy"].manifest(), runs["kernel"].manifest()
        assert mn["ran"] == mk["ran"]
        for sn, sk in zip(mn["stages"], mk["stages"], strict=True):
            assert sn["effect"] == sk["effect"]
            _close(sn["measured"], sk["measured"])


def _close(a, b):
    if isinstance(a, dict):
        assert set(a) == set(b)
        for k in a:
            _close(a[k], b[k])
    elif isinstance(a, float):
        assert b == pytest.approx(a, rel=1e-9, abs=1e-12)
    else:
        assert a == b


def test_the_kernel_runs_every_effect_by_the_function_the_registry_declares():
    """Each built-in effect with a kernel runs alone in the kernel and gives what its numpy code gives: so the
    function it declares (effects/<name>.py, defined beside it in <name>_kernel.py) is its numba stage, and its
    params and stats columns fit."""
    from wiredsl.effects import BUILTIN
    from wiredsl.scene import Pipeline, Stage

    with_kernel = {name: e for name, e in BUILTIN.items() if e.kernel is not None}
    homes = {e.kernel.function for e in with_kernel.values()}
    assert homes == {f"wiredsl.effects.{name}_kernel:stage" for name in with_kernel}
    # calibration_error: the kernel's projection, not a stage; motion_blur: numpy only (no kernel yet, issue 39 item 3:
    # a pipeline with it runs the stages from it on numpy on either engine, tests/test_blur.py)
    assert set(BUILTIN) - set(with_kernel) == {"calibration_error", "motion_blur"}
    scene, _, _ = compile_file("scenes/lab.wd")
    world = build_world(scene)
    for name, effect in with_kernel.items():
        params = {k: v for k, v in effect.Params().model_dump().items()}
        if name in ("corner_mismatch", "stereo_mismatch"):
            params["fraction"] = 0.5  # (the paper's 1% would leave most trials untouched)
        pipe = Pipeline(name=name, stages=[Stage(effect=name, params=params)])
        runs = {e: Run.create(scene, world, pipe, 5, Options(poses=(0, 3))) for e in ("numpy", "kernel")}
        got = {e: batches(run, e, range(16)) for e, run in runs.items()}
        assert runs["kernel"].manifest()["engines"] == {name: "kernel"}
        for bn, bk in zip(got["numpy"], got["kernel"], strict=True):
            for (_, dn, _), (_, dk, _) in zip(bn, bk, strict=True):
                for side, a in dn.items():
                    for field in DISCRETE:
                        assert np.array_equal(getattr(a, field), getattr(dk[side], field)), (name, side, field)
                    assert np.allclose(a.pts, dk[side].pts, atol=1e-9) and np.allclose(a.corners, dk[side].corners,
                                                                                         atol=1e-9)
        for sn, sk in zip(runs["numpy"].manifest()["stages"], runs["kernel"].manifest()["stages"], strict=True):
            _close(sn["measured"], sk["measured"])


def test_a_stage_without_a_kernel_and_those_after_it_run_on_numpy():
    """The stages before one without a kernel run compiled, it and those after it on numpy, on the kernel's output:
    the same trials as the numpy engine's (to rounding)."""
    from wiredsl.effects import BUILTIN
    from wiredsl.scene import Pipeline, Stage

    scene, _, _ = compile_file("scenes/lab.wd")

    class Slow(BUILTIN["lateral_shift"]):  # the same effect, without a compiled kernel
        kernel = None

    pipe = Pipeline(name="p", stages=[Stage(effect="edge_loss", params={"fraction": 0.3}),
                                      Stage(effect="lateral_shift", params={"range": 2.0}),
                                      Stage(effect="corner_loss", params={"keep": 0.5})])
    runs = {}
    for engine in ("kernel", "numpy"):
        run = runs[engine] = Run.create(scene, build_world(scene), pipe, 1, Options(poses=(0,)))
        run.stages[1] = (Slow, run.stages[1][1])
    got = {e: batches(run, e, range(4)) for e, run in runs.items()}
    assert runs["kernel"].uses_kernel() and [e.name for e, _ in runs["kernel"].compiled_stages()] == ["edge_loss"]
    assert runs["kernel"].manifest()["engines"] == {"edge_loss": "kernel", "lateral_shift": "numpy",
                                                    "corner_loss": "numpy"}
    for bk, bn in zip(got["kernel"], got["numpy"], strict=True):
        for (_, dk, _), (_, dn, _) in zip(bk, bn, strict=True):
            for side in dn:
                a, b = dk[side], dn[side]
                assert np.array_equal(a.start, b.start) and np.array_equal(a.fid, b.fid)
                assert np.array_equal(a.corner_fid, b.corner_fid) and len(a.fid) > 0
                assert np.abs(a.pts - b.pts).max(initial=0) < 1e-9


def test_the_fold_test_on_squares_decides_as_hypot_does_at_the_limit():
    """The kernel's lens-limit test compares x^2 + y^2 with limit^2 and asks hypot only near the limit: its
    decision is math.hypot(x, y) < limit's on points at and around the limit (within a few ulps of it, where
    the squares' rounding could flip a naive comparison), far inside and outside it, and for inf and NaN."""
    import math

    from wiredsl.engine.kernel import _within

    rng = np.random.default_rng(3)
    cases = 0
    for limit in (1e-3, 0.7, 1.0, math.sqrt(2.0), 3.7, 1e3, math.inf):
        for theta in rng.uniform(0, 2 * math.pi, 40):
            c, s = math.cos(theta), math.sin(theta)
            for r in [limit, 0.5 * limit, 2 * limit] + [math.nextafter(limit, 0) * (1 + k * 2.0**-52)
                                                        for k in range(-4, 5)]:
                x, y = r * c, r * s
                if not (math.isfinite(x) and math.isfinite(y)):
                    continue
                assert _within(x * x + y * y, x, y, limit) == (math.hypot(x, y) < limit), (limit, x, y)
                cases += 1
    for x, y in ((math.inf, 0.0), (math.nan, 1.0), (0.0, 0.0), (1e200, 1e200), (1e-200, 0.0)):
        assert _within(x * x + y * y, x, y, 1.0) == (math.hypot(x, y) < 1.0)
    assert cases > 2000


def test_the_cache_keeps_the_most_recently_used_generated_loops(tmp_path, monkeypatch):
    """Generated loop modules are pruned to KEPT_LOOPS by last use (access time), each with numba's cache files
    of it; other files in the folder are left alone."""
    import os

    from wiredsl.engine import kernel as kn

    cache = tmp_path / "__pycache__"
    cache.mkdir()
    for i in range(5):
        (tmp_path / f"wiredsl_stages_{i}.py").write_text("# loop\n")
        for ext in ("nbi", "nbc"):
            (cache / f"wiredsl_stages_{i}.view_batch-9.py311.{ext}").write_bytes(b"x")
        os.utime(tmp_path / f"wiredsl_stages_{i}.py", ns=(10**18 + [3, 0, 4, 1, 2][i] * 10**9, 10**18))
    (tmp_path / "notes.txt").write_text("mine")
    monkeypatch.setattr(kn, "KEPT_LOOPS", 2)
    kn._prune(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir() if p.is_file()) == [
        "notes.txt", "wiredsl_stages_0.py", "wiredsl_stages_2.py"]  # used last: 2 (at 4), then 0 (at 3)
    assert sorted(p.name.split(".")[0] for p in cache.iterdir()) == ["wiredsl_stages_0"] * 2 + ["wiredsl_stages_2"] * 2


def test_auto_loads_the_kernel_only_for_runs_large_enough_to_pay_for_it(tmp_path):
    """`build --engine auto` runs a few trials on numpy (numba's load would cost more than it saves) and records
    it; a run of the lab's size crosses KERNEL_PAYS at some 75 trials; --trial K replays in the kernel."""
    import json

    from click.testing import CliRunner

    from wiredsl.cli import main
    from wiredsl.montecarlo import KERNEL_PAYS

    pytest.importorskip("numba")
    scene, _, _ = compile_file("scenes/lab.wd")
    run = Run.create(scene, build_world(scene), scene.pipeline("paper"), 1, Options())
    vertices, _ = run.trial_size()
    assert not run.kernel_pays(KERNEL_PAYS // vertices) and run.kernel_pays(KERNEL_PAYS // vertices + 1)
    assert 40 < KERNEL_PAYS / vertices < 150
    run.engine = "numpy"
    assert not run.kernel_pays(10**6)  # an engine chosen by hand stays
    for args, engine in ((["--trials", "3"], "numpy"), (["--trial", "2"], "kernel"), (["--trials", "3", "--engine",
                                                                                       "kernel"], "kernel")):
        out = tmp_path / "-".join(args)
        r = CliRunner().invoke(main, ["build", "scenes/lab.wd", "--pose", "1", "--format", "jsonl", "--no-svg",
                                      "--seed", "4", "-o", str(out), *args])
        assert r.exit_code == 0, r.output
        assert json.loads((out / "manifest.json").read_text())["engine"] == engine
    # trial 2 of the 3-trial (numpy) run, replayed with the run's --trials: its engine, the same bytes
    out = tmp_path / "replay"
    r = CliRunner().invoke(main, ["build", "scenes/lab.wd", "--pose", "1", "--no-svg", "--seed", "4", "-o", str(out),
                                  "--trials", "3", "--trial", "2"])
    assert r.exit_code == 0, r.output
    assert json.loads((out / "manifest.json").read_text())["engine"] == "numpy"
    line = (tmp_path / "--trials-3" / "features.jsonl").read_text().splitlines()[2]
    assert json.loads((out / "features.json").read_text()) == json.loads(line)
    for args, engine in ((["--trials", "1", "--trial", "0"], "numpy"), (["--trial", "0"], "kernel")):
        r = CliRunner().invoke(main, ["build", "scenes/lab.wd", "--pose", "1", "--no-svg", "--seed", "4", "-o",
                                      str(out), *args])  # --trials 1 given: the one-trial run's engine
        assert r.exit_code == 0 and json.loads((out / "manifest.json").read_text())["engine"] == engine, r.output
    r = CliRunner().invoke(main, ["build", "scenes/lab.wd", "--seed", "4", "--trials", "3", "--trial", "3", "-o",
                                  str(out)])
    assert r.exit_code == 2 and "trial 3 is not in 0..2 (a run of --trials 3)" in r.output


def test_the_generated_loop_is_keyed_on_the_contents_of_every_file_its_stages_call(tmp_path, monkeypatch):
    """A stage calling a numba helper of another module (as `from m import f` and as `m.f`): editing the helper's
    file changes the generated loop's key even when its time stamp and size are put back, and the loop then
    gives the new helper's result; touching the files without editing them keeps the key (no recompile)."""
    import importlib
    import os
    import sys

    from wiredsl.engine import kernel as kn

    pkg = tmp_path / "wdhash"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    helper = "from numba import njit\n\n\n@njit(cache=True)\ndef shift():\n    return {}\n"
    (pkg / "helpers.py").write_text(helper.format("1.0"))
    (pkg / "more.py").write_text(helper.format("10.0"))
    (pkg / "kernel.py").write_text(
        "from numba import njit\n\nimport wdhash.more as more\nfrom wdhash.helpers import shift\n\n\n"
        "@njit(cache=True)\ndef stage(pts, start, meta, corners, cfid, key, params, epipole, right, st):\n"
        "    return pts + shift() + more.shift(), start, meta, corners, cfid\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))

    def loop() -> tuple[str, float]:
        for m in [m for m in sys.modules if m.startswith("wdhash")]:
            del sys.modules[m]
        importlib.invalidate_caches()
        kn._composed.clear()
        batch = kn.compose(("wdhash.kernel:stage",))
        pts = kn.run_view(np.array([[0.0, 0.0], [1.0, 1.0]]), np.array([0, 2]), np.zeros((1, kn.NMETA), np.int64),
                          np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros((2, 3)), np.zeros((0, 3)), np.eye(3)[None],
                          np.zeros((1, 3)), np.ones((1, 18)), np.ones(1), 10.0, 10.0, False, ("wdhash.kernel:stage",),
                          np.zeros((1, 3)), np.ones((1, 1), np.uint64), np.ones(3), True, np.zeros((1, 6)))[0]
        return batch.__module__, float(pts[0, 0])

    first, got = loop()
    assert got == 11.0
    paths = [pkg / n for n in ("helpers.py", "more.py", "kernel.py")]
    for p in paths:  # touched, not edited: the same loop
        os.utime(p, ns=(p.stat().st_atime_ns, p.stat().st_mtime_ns + 10**9))
    assert loop() == (first, 11.0)
    keys = {first}
    for p, new, value in ((paths[0], "2.0", 12.0), (paths[1], "20.0", 22.0)):
        st = p.stat()
        p.write_text(helper.format(new))
        os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns))  # the same size and time stamp: only the text differs
        assert p.stat().st_size == st.st_size or new == "20.0"
        key, got = loop()
        assert key not in keys and got == value
        keys.add(key)


VARIED = {"edge_loss": "fraction from 10% to 40%", "lateral_shift": "range from 0 to 4px",
          "approx_error": "sigma from 0 to 0.3px", "corner_loss": "keep from 0.5 to 1",
          "corner_error": "sigma from 0 to 2px", "corner_mismatch": "fraction from 0 to 50%",
          "stereo_mismatch": "disparity from 0 to 20px"}


def test_every_built_in_stage_list_runs_the_one_loop_compiled_once(tmp_path):
    """Was (issue 36's replay): a random valid study, 6 points x 2 trials in process, ran over 60 s: the first
    compile of its stage list's own loop. Every pipeline of built-in stages (any subset, order the language allows
    and parameters) now runs the one loop of the built-in table, compiled once (by the suite's warm-up,
    tests/conftest.py): random stage lists' studies compile no numba code of wiredsl's, and complete."""
    from click.testing import CliRunner
    from numba.core import event

    from wiredsl.cli import main
    from wiredsl.effects import BUILTIN
    from wiredsl.engine import kernel as kn

    staged = [name for name, e in BUILTIN.items() if e.kernel is not None]
    assert set(staged) == set(VARIED)
    table = kn.builtin_table()
    rng = np.random.default_rng(36)
    compiled = []

    class Compiles(event.Listener):
        def on_start(self, e):
            compiled.append(e.data["dispatcher"].py_func)

        def on_end(self, e):
            pass

    for case in range(3):
        chosen = sorted(rng.choice(len(staged), size=rng.integers(1, 5), replace=False))
        names = [staged[i] for i in chosen]
        assert kn.stage_table(tuple(t for t in table if t[0] in {f"wiredsl.effects.{n}_kernel:stage" for n in names})) \
            == table
        varied = names[rng.integers(len(names))]
        scene = tmp_path / f"s{case}.wd"
        scene.write_text(f'wiredsl 1\ninclude "{Path("scenes/lab.wd").resolve().as_posix()}"\n\n'
                         "pipeline random {\n" + "".join(f"  {n}\n" for n in names) + "}\n\n"
                         "study s {\n  pipeline random\n"
                         f"  vary {varied}.{VARIED[varied]} steps 6\n"
                         f"  trials 2\n  poses [0, 3]\n  seed {case}\n  measure kept\n}}\n")
        out = tmp_path / f"st{case}"
        with event.install_listener("numba:compile", Compiles()):
            r = CliRunner().invoke(main, ["study", str(scene), "s", "-o", str(out), "--executor", "inprocess",
                                          "--no-plots"])
        assert r.exit_code == 0, (names, r.output)
        manifest = json.loads((out / "manifest.json").read_text())
        assert manifest["engines"] == {n: "kernel" for n in names}, manifest["engines"]
        ours = [f"{f.__module__}.{f.__qualname__}" for f in compiled if f.__module__.startswith("wiredsl")]
        assert ours == [], (names, ours)


COLD_BUILD = """
import json, sys
from numba.core import event
compiled = []
class Compiles(event.Listener):
    def on_start(self, e):
        compiled.append(e.data["dispatcher"].py_func.__qualname__)
    def on_end(self, e):
        pass
event.register("numba:compile", Compiles())
from wiredsl.cli import main
try:
    main(sys.argv[1:], standalone_mode=False)
finally:
    print(json.dumps(compiled), file=sys.__stdout__)
"""


def test_auto_on_an_empty_cache_runs_a_small_run_on_numpy_compiling_nothing(tmp_path):
    """With numba's and wiredsl's caches empty (a fresh install), `build --engine auto` of a run too small for the
    compile to pay for itself (run.COLD_KERNEL_PAYS) runs numpy, compiles nothing, says so in one line, records
    numpy in the manifest, and writes the kernel's output (within 1e-9 px); with the loop cached (the suite's
    warm-up) auto loads it."""
    import json
    import os
    import subprocess
    import sys

    from click.testing import CliRunner

    from wiredsl import run as runs
    from wiredsl.cli import main
    from wiredsl.engine import kernel as kn

    pytest.importorskip("numba")
    args = ["build", "scenes/lab.wd", "--format", "npz", "--no-svg", "--seed", "4", "--trials", "120"]  # > KERNEL_PAYS
    script = tmp_path / "cold.py"
    script.write_text(COLD_BUILD)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"), "XDG_CACHE_HOME": str(tmp_path / "cache"),
           "PYTHONPATH": str(Path.cwd())}
    p = subprocess.run([sys.executable, str(script), *args, "-o", str(tmp_path / "cold")], env=env,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout.splitlines()[-1]) == []  # not one function compiled
    notes = [line for line in p.stderr.splitlines() if "numpy engine for this run" in line]
    assert len(notes) == 1 and "compiling" not in p.stderr, p.stderr
    assert json.loads((tmp_path / "cold" / "manifest.json").read_text())["engine"] == "numpy"
    r = CliRunner().invoke(main, [*args, "-o", str(tmp_path / "warm")])  # this process: the loop is cached
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "warm" / "manifest.json").read_text())["engine"] == "kernel"
    cold, warm = np.load(tmp_path / "cold" / "features.npz"), np.load(tmp_path / "warm" / "features.npz")
    assert cold.files == warm.files
    for k in cold.files:
        if k != "manifest":  # it names the engine
            assert cold[k].dtype == warm[k].dtype and cold[k].shape == warm[k].shape, k
            if cold[k].dtype.kind == "f":  # the engines agree within 1e-9 px (module docstring), not bit for bit
                assert np.allclose(cold[k], warm[k], rtol=0, atol=1e-9, equal_nan=False), k
            else:  # counts, ids, flags: exact
                assert np.array_equal(cold[k], warm[k]), k
    # the rule: a cached loop, or a run large enough, keeps the kernel
    scene, _, _ = compile_file("scenes/lab.wd")
    run = Run.create(scene, build_world(scene), scene.pipeline("paper"), 1, Options())
    assert kn.loop_cached(tuple((e.kernel.function, e.kernel.camera, e.kernel.workspace)
                                for e, _ in run.compiled_stages()))
    assert runs.cold_kernel_line(run, 3) is None and run.uses_kernel()
    big = int(runs.COLD_KERNEL_PAYS // run.trial_size()[0]) + 1
    assert 2_000 < big < 50_000
    run.uses_kernel = lambda: True
    kn_cached, kn.loop_cached = kn.loop_cached, lambda stages: False
    try:
        assert runs.cold_kernel_line(run, big) is None  # large: compiles, as before
        line = runs.cold_kernel_line(run, big - 1)
        assert line is not None and f"{big:,} trials" in line and run.engine == "numpy"
    finally:
        kn.loop_cached = kn_cached
