"""Faults: real signals to a real `wiredsl build` process, a full disk, killed and concurrent runs, and writers
that refuse non-finite numbers. Whatever happens, no temporary is left and the output folder holds one whole run.
"""

from __future__ import annotations

import builtins
import copy
import errno
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from wiredsl.cli import main
from wiredsl.files import UnwritableValue, json_text, output_folder, write_atomic
from wiredsl.io import emit
from wiredsl.io import svg as svg_mod

ROOT = Path(__file__).resolve().parent.parent
LAB = str(ROOT / "scenes/lab.wd")


def _start(out: Path, *extra: str, **kw) -> subprocess.Popen:
    """A real `python -m wiredsl build` of many lab trials into `out` (long enough to be interrupted)."""
    return subprocess.Popen([sys.executable, "-m", "wiredsl", "build", LAB, "--seed", "1", "-o", str(out), *extra],
                            cwd=out.parent, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)}, **kw)


def _temporaries(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if ".wiredsl-" in p.name)


def _wait_for_dump(proc: subprocess.Popen, folder: Path, name: str, timeout: float = 120) -> Path:
    """Block until the run's temporary folder holds a non-empty dump (the run is mid-write); return the folder."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        for stage in _temporaries(folder):
            dumps = list(stage.glob(f"*{name}*"))
            if dumps and any(d.stat().st_size > 0 for d in dumps if d.exists()):
                return stage
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.02)
    proc.kill()
    raise AssertionError("the run never started writing")


@pytest.mark.parametrize(("signum", "fmt"), [(signal.SIGTERM, "jsonl"), (signal.SIGINT, "npz")])
def test_signal_mid_run_removes_temporaries_and_keeps_the_previous_run(tmp_path, signum, fmt):
    out = tmp_path / "out"
    out.mkdir()
    (out / "manifest.json").write_text('{"previous": true}')
    (out / "features.json").write_text("previous")
    proc = _start(out, "--trials", "100000", "--force", "--format", fmt, "--pose", "0")
    _wait_for_dump(proc, tmp_path, f"features.{fmt}")
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signum, err
    assert "Traceback" not in err and "Aborted" not in err and f"stopped by {signal.Signals(signum).name}" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # the temporary folder is gone
    assert sorted(p.name for p in out.iterdir()) == ["features.json", "manifest.json"]
    assert (out / "features.json").read_text() == "previous"


def test_a_killed_runs_temporaries_are_removed_by_the_next_run(tmp_path):
    out = tmp_path / "out"
    proc = _start(out, "--trials", "100000", "--force", "--format", "jsonl", "--pose", "0")
    stage = _wait_for_dump(proc, tmp_path, "features.jsonl")
    proc.kill()  # SIGKILL: nothing can clean up
    proc.communicate(timeout=60)
    assert stage.is_dir()
    r = CliRunner().invoke(main, ["build", LAB, "--no-effects", "--pose", "0", "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_concurrent_builds_into_one_folder_never_mix(tmp_path):
    out = tmp_path / "out"
    a = _start(out, "--format", "jsonl", "--trials", "30", "--pose", "1")
    b = _start(out, "--format", "json", "--seed", "2", "--pose", "3")
    for p in (a, b):
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
    names = sorted(p.name for p in out.iterdir())
    manifest = json.loads((out / "manifest.json").read_text())
    if "features.jsonl" in names:
        assert names == ["features.jsonl", "manifest.json", "pose_001.svg"] and manifest["trials"] == 30
    else:
        assert names == ["features.json", "manifest.json", "pose_003.svg"] and manifest["seed"] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def _limit_file_size(limit: int):
    def apply():
        import resource

        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # so a write beyond the limit fails (EFBIG), as on a full disk
    return apply


@pytest.mark.parametrize("fmt", ["json", "jsonl", "npz"])
def test_a_disk_that_refuses_writes_leaves_nothing(tmp_path, fmt):
    """A real process whose writes start failing mid-dump (RLIMIT_FSIZE): a clean error, exit 1, nothing left."""
    out = tmp_path / "out"
    proc = _start(out, "--format", fmt, "--pose", "0", *(["--trials", "60"] if fmt != "json" else []),
                  preexec_fn=_limit_file_size(100_000 if fmt != "json" else 20_000))
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 1, err
    assert f"cannot write {out}: File too large" in err and "Traceback" not in err and ".tmp" not in err
    assert list(tmp_path.iterdir()) == []


class _FullDisk:
    """A file on a disk that fills after `room` bytes: writes, flushes and close then fail with ENOSPC."""

    def __init__(self, fh, room: int):
        self.fh, self.room, self.used = fh, room, 0

    def _full(self):
        return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def write(self, data):
        self.used += len(data)
        if self.used > self.room:
            raise self._full()
        return self.fh.write(data)

    def flush(self):
        if self.used > self.room:
            raise self._full()
        self.fh.flush()

    def close(self):
        self.fh.close()
        if self.used > self.room:
            raise self._full()  # the close fails again, as it does when buffered data cannot be flushed

    def __getattr__(self, name):
        return getattr(self.fh, name)


@pytest.mark.parametrize("fmt", ["jsonl", "npz"])
def test_enospc_with_a_close_that_fails_again_leaves_nothing(tmp_path, monkeypatch, fmt):
    monkeypatch.setattr(emit, "open", lambda *a, **k: _FullDisk(builtins.open(*a, **k), 30_000), raising=False)
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["build", LAB, "--seed", "1", "--trials", "20", "--pose", "0", "--format", fmt,
                                  "-o", str(out)])
    assert r.exit_code == 1 and f"cannot write {out}: No space left on device" in r.stderr, r.output
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- writers refuse non-finite values

_NASTY = st.sampled_from([math.inf, -math.inf, math.nan, 1e300, -1e39, 3.5e38, 3.3e38, 1e-320])
_VALUES = st.one_of(st.floats(-1e4, 1e4), _NASTY, st.floats(allow_nan=True, allow_infinity=True))
_ARRAYS = hnp.arrays(np.float64, st.tuples(st.integers(2, 12), st.just(2)), elements=_VALUES)


def _lab_pose():
    from wiredsl.engine.simulate import Options, simulate
    from wiredsl.engine.world import build_world
    from wiredsl.language.compile import compile_file

    scene, _, _ = compile_file(LAB)
    world = build_world(scene)
    return scene, world, simulate(scene, Options(poses=(0,)), world)[0]


_LAB = []


def _with_points(a: np.ndarray):
    """The lab's pose 0 with its first polyline's vertices replaced by `a`."""
    if not _LAB:
        _LAB.append(_lab_pose())
    scene, world, result = _LAB[0]
    result = copy.deepcopy(result)
    f = next(f for f in result.left.features if f.kind == "polyline")
    f.points = a
    return scene, world, result


def _write(kind: str, a: np.ndarray, stage: Path) -> None:
    """Write `a` through one writer the way build does."""
    if kind == "json":
        write_atomic(stage / "x.json", json_text({"values": a.tolist()}))
    elif kind == "manifest":
        w = emit.NpzStream(stage / "features.npz")
        try:
            w.close(["a"], {"measured": {"sd": a.tolist()}})
        except BaseException:
            w.abort()
            raise
    elif kind == "npz":
        w = emit.NpzStream(stage / "features.npz")
        try:
            w.member("b00000_pts", a, np.float32)
            w.close(["a"], {})
        except BaseException:
            w.abort()
            raise
    elif kind == "npz batch":  # a view's vertices, cast to float32 and checked as each view is packed
        scene, world, result = _with_points(a)
        w = emit.NpzStream(stage / "features.npz")
        try:
            w.write_ideal([result], world)
            w.close(world.feature_ids, {})
        except BaseException:
            w.abort()
            raise
    elif kind == "jsonl":
        scene, world, result = _with_points(a)
        w = emit.JsonLines(stage / "features.jsonl")
        try:
            w.write(emit.features(scene, world, [result]))
            w.close()
        except BaseException:
            w.abort()
            raise
    elif kind == "svg":
        scene, world, result = _with_points(a)
        write_atomic(stage / "pose_000.svg", svg_mod.overlay(scene, world, result))


@pytest.mark.parametrize("kind", ["json", "manifest", "npz", "npz batch", "jsonl", "svg"])
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(a=_ARRAYS)
def test_writers_refuse_non_finite_values_and_leave_nothing(kind, a):
    finite = bool(np.isfinite(a).all())
    with np.errstate(over="ignore"):
        fits = finite and (not kind.startswith("npz") or bool(np.isfinite(a.astype(np.float32)).all()))
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        try:
            with output_folder(out) as stage:
                _write(kind, a, stage)
        except UnwritableValue as exc:
            assert not fits, exc
            assert list(Path(tmp).iterdir()) == []  # nothing at all: no output, no temporary
            return
        assert fits, "a non-finite or out-of-range value was written"
        for p in out.iterdir():
            if p.suffix == ".npz":
                with np.load(p) as z:
                    assert all(np.isfinite(z[k]).all() for k in z.files if z[k].dtype.kind == "f")
                    json.loads(str(z["manifest"]), parse_constant=lambda c: pytest.fail(f"{c} in manifest"))
            elif p.suffix == ".svg":
                text = p.read_text()
                assert "nan" not in text and "inf" not in text
            else:
                docs = p.read_text().splitlines() if p.suffix == ".jsonl" else [p.read_text()]
                for doc in docs:
                    json.loads(doc, parse_constant=lambda c: pytest.fail(f"{c} written"))


def test_a_crash_while_writing_the_manifest_leaves_no_temporary(tmp_path, monkeypatch):
    """Whatever fails inside a build (here the manifest), the staged folder goes with it."""
    from wiredsl.montecarlo import Run

    monkeypatch.setattr(Run, "manifest", lambda self: 1 / 0)
    for fmt in ("json", "npz"):
        r = CliRunner().invoke(main, ["build", LAB, "--seed", "1", "--pose", "0", "--format", fmt, "--trials",
                                      "1" if fmt == "json" else "2", "-o", str(tmp_path / "out")])
        assert r.exit_code == 3 and "ZeroDivisionError" in r.stderr, r.output
        assert list(tmp_path.iterdir()) == []


def test_stale_temporaries_of_dead_local_processes_go_others_stay(tmp_path):
    """Only this host's temporaries whose process is gone are removed; a live or another host's one stays."""
    from wiredsl import files

    done = subprocess.Popen([sys.executable, "-c", "pass"])
    done.wait()  # reaped: its pid no longer runs
    dead = tmp_path / f".out.wiredsl-{files._HOST}-{done.pid}-abcd1234.tmp"
    dead.mkdir()
    (dead / "features.jsonl").write_text("half")
    alive = tmp_path / f".out.wiredsl-{files._HOST}-{os.getppid()}-abcd1234.tmp"
    other = tmp_path / ".out.wiredsl-otherhost-1-abcd1234.tmp"
    alive.mkdir()
    other.mkdir()
    r = CliRunner().invoke(main, ["build", LAB, "--no-effects", "--pose", "0", "-o", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["out", alive.name, other.name])


def test_a_link_to_a_folder_stays_a_link(tmp_path):
    real = tmp_path / "real"
    real.mkdir()
    (tmp_path / "out").symlink_to(real)
    for pose in ("0", "1"):
        r = CliRunner().invoke(main, ["build", LAB, "--no-effects", "--pose", pose, "-o", str(tmp_path / "out")])
        assert r.exit_code == 0, r.output
    assert (tmp_path / "out").is_symlink()
    assert sorted(p.name for p in real.iterdir()) == ["features.json", "manifest.json", "pose_001.svg"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "real"]


@pytest.mark.parametrize("cmd", ["compile", "export-calibration"])
def test_a_non_finite_scene_value_is_never_written(tmp_path, monkeypatch, cmd):
    """Whatever the compiler lets through, `compile` and `export-calibration` refuse to write it."""
    from wiredsl.language import compile as compiler

    real = compiler.compile_file

    def with_infinite_focal(path):
        scene, warnings, program = real(path)
        cams = [c.model_copy(update={"f": math.inf}) for c in scene.cameras]
        return scene.model_copy(update={"cameras": cams}), warnings, program

    monkeypatch.setattr(compiler, "compile_file", with_infinite_focal)
    out = tmp_path / ("scene.json" if cmd == "compile" else "calibration")
    r = CliRunner().invoke(main, [cmd, str(ROOT / "scenes/cylinder.wd"), "-o", str(out)])
    assert r.exit_code == 1 and "nothing written" in r.stderr and "is inf" in r.stderr, r.output
    assert list(tmp_path.iterdir()) == []
    r = CliRunner().invoke(main, ["compile", str(ROOT / "scenes/cylinder.wd")])
    assert r.exit_code == 1 and r.stdout == ""


STUDY = """wiredsl 1
include "{lab}"
study shift {{
  pipeline edges
  vary lateral_shift.range from 0 to 4px steps 3
  vary calibration_error.sigma values [0, 0.03]
  trials 24
  poses [0, 4]
  seed 5
  measure kept
}}
"""
STUDY_RUN = """import sys
sys.path.insert(0, {tests!r})
import study_measures
from wiredsl.language import compile_study
compile_study.measure_registry = lambda: study_measures.REGISTRY
from wiredsl.language.compile import compile_file
from wiredsl.study import run_study

if __name__ == "__main__":
    scene = compile_file(sys.argv[1])[0]
    measures = {{"kept": study_measures.SlowKept if sys.argv[3] == "slow" else study_measures.Kept}}
    run_study(scene, scene.study("shift"), sys.argv[2], executor="processes", workers=2, registry=measures,
              shard_trials=2)
"""


def test_a_study_killed_by_sigkill_resumes_to_the_uninterrupted_table_nothing_lost_or_twice(tmp_path):
    """kill -9 of the study's process mid-run (its workers orphaned, a journal record perhaps torn): the next run
    computes exactly the shards the killed run's journal does not hold whole, and the table is the uninterrupted
    run's, byte for byte."""
    from wiredsl.study import journal

    scene = tmp_path / "s.wd"
    scene.write_text(STUDY.format(lab=Path(LAB).as_posix()))
    script = tmp_path / "run.py"
    script.write_text(STUDY_RUN.format(tests=str(ROOT / "tests")))
    import study_measures

    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = tmp_path / "killed"
    # held from 10 shards on: still running when it is killed, however loaded the machine
    proc = subprocess.Popen([sys.executable, str(script), str(scene), str(out), "slow"],
                            env={**study_measures.SlowKept.hold(out, 10), "PYTHONPATH": str(ROOT)},
                            start_new_session=True, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 300
        while len(journal.replay(out)) < 10 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert proc.poll() is None, proc.stderr.read()  # still running
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait(60) == -signal.SIGKILL, proc.stderr.read()
    finally:
        with __import__("contextlib").suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)  # the orphaned workers and fork server of that run
    proc.stderr.close()
    (killed,) = journal.files(out)
    done = [key for key, _ in journal.decode(killed.read_bytes())]
    total = 3 * 2 * 12  # points (3 shifts x 2 sigmas) x shards of 2 trials
    assert 10 <= len(done) < total and len(set(done)) == len(done) and not (out / "table.csv").exists()
    subprocess.run([sys.executable, str(script), str(scene), str(out), "fast"], env=env, check=True)
    (resumed,) = set(journal.files(out)) - {killed}
    redone = [key for key, _ in journal.decode(resumed.read_bytes())]
    assert len(set(redone)) == len(redone) and not set(redone) & set(done) and len(done) + len(redone) == total
    subprocess.run([sys.executable, str(script), str(scene), str(tmp_path / "whole"), "fast"], env=env, check=True)
    for name in ("table.csv", "table.json", "manifest.json"):
        assert (out / name).read_bytes() == (tmp_path / "whole" / name).read_bytes(), name


DROPPED = """import os, signal, sys, time
sys.path.insert(0, {tests!r})
command, how = sys.argv[1], sys.argv[2]


def landing(real):
    \"\"\"`real`, whose first call sends SIGINT or SIGTERM to its own process and then acts as compiled code may when
    the signal's exception lands in it (numba's callbacks, a C library's): wraps it in a SystemError, or drops it.\"\"\"
    def call(*args, **kwargs):
        if not landing.sent:
            landing.sent = True
            try:
                os.kill(os.getpid(), int(os.environ["SIGNUM"]))
                time.sleep(30)  # the handler raises in here
            except BaseException as exc:
                if how == "wrap":
                    raise SystemError("returned a result with an exception set") from exc
        return real(*args, **kwargs)
    return call


landing.sent = False
if command == "study":
    import study_measures
    from wiredsl.language import compile_study

    class Landing(study_measures.Kept):
        measure = classmethod(landing(study_measures.Kept.measure.__func__))

    compile_study.measure_registry = lambda: {{"kept": Landing}}
elif command == "build":
    from wiredsl import montecarlo

    montecarlo.Run._batch = landing(montecarlo.Run._batch)
else:
    from wiredsl.verify import verification

    verification.verify_image = landing(verification.verify_image)
from wiredsl.cli import entry

sys.argv = ["wiredsl", *sys.argv[3:]]
entry()
"""


@pytest.mark.parametrize("how", ["wrap", "drop"])
@pytest.mark.parametrize(("command", "signum"), [("build", signal.SIGTERM), ("study", signal.SIGTERM),
                                                 ("verify", signal.SIGINT)])
def test_a_signal_that_compiled_code_wraps_or_drops_still_stops_the_command(tmp_path, command, signum, how):
    """A signal landing in code that wraps its exception (numba's unpickling callback: a SystemError) or drops it
    (a C callback that prints "Exception ignored" and returns) still stops the command: exit 128 + signal, one
    line, no traceback, and the output folder as it was. Dropped, the command once ran on to exit 0 and wrote
    every output, deaf to a second signal (its handler ignores both while it cleans up)."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "manifest.json").write_text("previous")
    args = {"build": ["build", LAB, "--trials", "40", "--format", "npz", "--no-svg", "--force", "-o", str(out)],
            "study": ["study", str(tmp_path / "s.wd"), "shift", "--executor", "inprocess", "--no-plots", "-o",
                      str(out)],
            "verify": ["verify", "scenes/chessboard.wd", "--images", "tests/data/opencv_stereo/left01.jpg",
                       "--images", "tests/data/opencv_stereo/right01.jpg", "--poses", "board", "--detector",
                       "canny", "-o", str(out)]}[command]
    (tmp_path / "s.wd").write_text(STUDY.format(lab=Path(LAB).as_posix()))
    script = tmp_path / "dropped.py"
    script.write_text(DROPPED.format(tests=str(ROOT / "tests")))
    p = subprocess.run([sys.executable, str(script), command, how, *args], cwd=ROOT, capture_output=True,
                       text=True, timeout=300, env={**os.environ, "PYTHONPATH": str(ROOT), "SIGNUM": str(int(signum))})
    assert p.returncode == 128 + signum, p.stderr
    assert p.stderr.strip().splitlines()[-1] == \
        f"wiredsl: stopped by {signal.Signals(signum).name}; temporary files removed", p.stderr
    assert "Traceback" not in p.stderr and "internal error" not in p.stderr
    left = sorted(p.name for p in out.iterdir())
    kept = [".plugins.json", "manifest.json", "shards"] if command == "study" else ["manifest.json"]  # (a resume's)
    assert left == kept, left
    assert (out / "manifest.json").read_text() == "previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dropped.py", "out", "s.wd"]
