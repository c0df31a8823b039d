"""What the speed work must not change: the npz writer's output, pinned by a small run's reference file."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from wiredsl.cli import main

# The lab's npz of `build scenes/lab.wd --trials 9 --format npz --seed 7 --pose 1 --pose 4 --engine numpy`, as
# the writer wrote it (tests/golden/lab_trials.npz, without the manifest, which names the tool's version). What
# is exact is compared exactly: every integer and text member (the strokes table, starts, corner and feature ids:
# which strokes, fragments and corners a trial has). Floating-point members are compared within tolerances: the
# same seed gives the same bytes on one machine, but BLAS's kernels for another CPU (OpenBLAS's SkylakeX against
# Haswell, say) sum matrix products in another order, which moves the last bits; CI runs this test under several
# OPENBLAS_CORETYPE values. Regenerate with WIREDSL_UPDATE_GOLDEN=1 after a change that is meant to change it.
REFERENCE = Path("tests/golden/lab_trials.npz")
ARGS = ["build", "scenes/lab.wd", "--trials", "9", "--format", "npz", "--seed", "7", "--pose", "1", "--pose", "4",
        "--engine", "numpy", "--no-svg"]
# absolute tolerances of the float members: image points are float32 (1e-7 of 640 px is 6e-5 px); the view
# cameras carry the calibration draws (an eigendecomposition: 1e-9 apart between OpenBLAS kernels, measured);
# poses are rotations and metres
TOLERANCE = {"pts": 1e-4, "corners": 1e-4, "view_cameras": 1e-6, "view_poses": 1e-9, "conics": 1e-6}


def _members(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as z:
        return {name: z[name] for name in z.files if name != "manifest"}


def test_the_npz_writer_writes_what_it_wrote_before(tmp_path):
    result = CliRunner().invoke(main, [*ARGS, "-o", str(tmp_path / "a")])
    assert result.exit_code == 0, result.output
    got = _members(tmp_path / "a" / "features.npz")
    if os.environ.get("WIREDSL_UPDATE_GOLDEN") == "1":
        np.savez_compressed(REFERENCE, **got)
    want = _members(REFERENCE)
    assert sorted(got) == sorted(want)
    floats = 0
    for name in sorted(want):
        g, w = got[name], want[name]
        assert g.dtype == w.dtype and g.shape == w.shape, name
        if w.dtype.kind == "f":
            tol = TOLERANCE[name.split("_", 1)[1]]
            assert np.isfinite(g).all() and np.abs(g.astype(float) - w.astype(float)).max(initial=0.0) <= tol, name
            floats += w.size
        else:
            assert np.array_equal(g, w), name  # exact: hash-like, and tells which member moved
    assert floats > 1000  # the comparison holds the points, not only the tables


def test_the_golden_would_catch_a_moved_point(tmp_path):
    """The tolerance is tight enough to fail: the reference with one point moved by 0.001 px is refused."""
    want = _members(REFERENCE)
    pts = next(k for k in want if k.endswith("_pts"))
    moved = want[pts].copy()
    moved[len(moved) // 2, 0] += np.float32(1e-3)
    assert np.abs(moved.astype(float) - want[pts].astype(float)).max() > TOLERANCE["pts"]


def test_batches_are_sized_to_the_scene_and_trials_do_not_depend_on_them():
    from wiredsl import montecarlo as mc
    from wiredsl.engine.simulate import Options
    from wiredsl.engine.world import build_world
    from wiredsl.language.compile import compile_file

    scene, _, _ = compile_file("scenes/lab.wd")
    world = build_world(scene)
    run = mc.Run.create(scene, world, scene.pipeline("edges"), 3, Options(poses=(1,)))
    assert run.batch_size() == mc.BATCH  # one pose: every trial of a full batch fits
    whole = mc.Run.create(scene, world, scene.pipeline("edges"), 3, Options())
    # the lab's 14 views: 128 trials' strokes fit in BATCH_BYTES, 256 would not
    assert whole.batch_size() == 128
    sizes = [len(b) for b, _ in whole.batches(range(300))]
    assert sizes == [128, 128, 44]
    one = next(iter(run.batches([5])))[1][0][1]["left"]
    many = [out for b, out in run.batches(range(300)) if 5 in b][0][0][1]["left"]
    k = list(range(300)).index(5) % run.batch_size()
    assert np.array_equal(one.pts, many.pts[np.repeat(many.trial == k, np.diff(many.start))])


def test_rounded_arrays_are_pythons_round_to_the_last_bit():
    from wiredsl.io.emit import rounded

    rng = np.random.default_rng(5)
    ties = (rng.integers(-10**9, 10**9, 20_000) + 0.5) / 1e6  # half-way in decimal: the hard cases
    values = np.concatenate([ties, rng.uniform(-2000, 2000, 20_000), rng.normal(0, 1e-6, 2000), [-0.0, -1e-9, 2.5e15]])
    got = rounded(values, "x")
    want = [round(float(x), 6) for x in values]
    assert [float(x).hex() for x in got] == [(w + 0.0).hex() for w in want]
    assert not np.signbit(got[values == 0]).any()


def test_a_dump_on_stdout_is_utf8_whatever_the_terminals_encoding(tmp_path):
    import json
    import os
    import shutil
    import subprocess
    import sys

    shutil.copytree("scenes/models", tmp_path / "models")
    shutil.copy("scenes/lab.info", tmp_path / "lab.info")
    shutil.copy("scenes/lab.wd", tmp_path / "läb.wd")
    p = subprocess.run([sys.executable, "-m", "wiredsl", "build", "läb.wd", "--no-effects", "--pose", "0", "-o", "-"],
                       cwd=tmp_path, capture_output=True, timeout=120, env={**os.environ, "PYTHONIOENCODING": "ascii"})
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout.decode("utf-8"))["scene"]["file"] == "läb.wd"


def test_npz_fragment_numbers_are_the_dumps_in_either_order():
    """The writer's fragment numbers (adjacent groups: ranks within runs; any other order: a stable sort) against
    the JSON dump's own numbering (`engine/trials.features_of`, a count a stroke), on random stroke sets whose
    (trial, feature, segment) groups are adjacent and on the same sets shuffled within each trial."""
    from collections import Counter

    from wiredsl.engine import imageset as im
    from wiredsl.io.emit import _json_fragments

    def dumps(s):
        out = np.empty(s.n_strokes, dtype=int)
        for t in np.unique(s.trial):
            idx = np.flatnonzero(s.trial == t)
            groups, seen = Counter((s.fid[i], s.segment[i]) for i in idx), Counter()
            for i in idx:
                key = (s.fid[i], s.segment[i])
                out[i] = seen[key] if s.fragment[i] >= 0 or groups[key] > 1 else -1
                seen[key] += 1
        return out

    rng = np.random.default_rng(7)
    adjacent = shuffled = 0
    for _ in range(200):
        n = int(rng.integers(1, 40))
        trial = np.sort(rng.integers(0, 4, n))
        fid, seg = rng.integers(0, 5, n), rng.integers(-1, 2, n)
        order = np.lexsort((seg, fid, trial)) if rng.random() < 0.5 else np.arange(n)
        s = im.ImageSet(pts=np.zeros((2 * n, 2)), start=np.arange(0, 2 * n + 1, 2), fid=fid[order],
                        segment=seg[order], fragment=rng.integers(-1, 2, n), kind=np.zeros(n, int),
                        clipped=np.zeros(n, bool), closed=np.zeros(n, bool), trial=trial,
                        corners=np.zeros((0, 2)), corner_fid=np.zeros(0, int), corner_trial=np.zeros(0, int),
                        occluded=np.zeros(n, bool))
        key = (s.trial * 10 + s.fid) * 10 + s.segment
        runs = key[np.r_[True, key[1:] != key[:-1]]]
        adjacent, shuffled = adjacent + (len(set(runs)) == len(runs)), shuffled + (len(set(runs)) < len(runs))
        assert _json_fragments(s).tolist() == dumps(s).tolist()
    assert adjacent > 50 and shuffled > 50  # both paths taken
