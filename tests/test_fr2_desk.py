"""Issue 35: the TUM reader on the real fr2/desk ground truth (tests/data/trajectories/, 20,957 rows, one repeated
timestamp), against evo's reading of it. evo's rules (evo/tools/file_interface.py read_tum_trajectory_file, stated
as test_trajectory._evo_tum): `#` lines dropped, every row kept, stamps, xyz and the quaternion; evo 1.36's
association keeps the first row of a repeated stamp (1.38.1 the last). wiredsl: W148 once, at the repeat, the
first pose of the pair kept, and every other pose evo's."""

from __future__ import annotations

import gzip
import hashlib
from pathlib import Path

import numpy as np
from test_trajectory import _evo_tum, scene_file

from wiredsl.io import trajectory
from wiredsl.language.compile import compile_file

GZ = Path(__file__).parent / "data" / "trajectories" / "rgbd_dataset_freiburg2_desk-groundtruth.txt.gz"


def test_fr2_desk_reads_as_evo_keeping_the_first_pose_of_the_repeated_stamp(tmp_path):
    raw = gzip.decompress(GZ.read_bytes())
    assert hashlib.sha256(raw).hexdigest() == "0d8e0119a4e9592b886c5ca954472c3270c01814dd2059fbe196d5c24c8f3d17"
    text = raw.decode()
    stamps, xyz, R = _evo_tum(text)
    assert len(stamps) == 20957
    (k,) = np.flatnonzero(stamps[1:] == stamps[:-1])  # the one repeat: rows k and k + 1
    assert f"{stamps[k]:.4f}" == "1311868229.5760" and not np.array_equal(xyz[k], xyz[k + 1])
    keep = np.ones(len(stamps), dtype=bool)
    keep[k + 1] = False  # evo 1.36: the first row of the pair
    line = 3 + k + 2  # the file line of the repeating row (3 comment lines, 1-based)

    f = scene_file(tmp_path, '  read "gt.txt"', {"gt.txt": text})
    scene, diags, _ = compile_file(f)
    warned = [d for d in diags if d.code == "W148"]  # (W146 too: a handheld camera's up is not the scene's)
    assert [(d.code, d.span.line) for d in warned] == [("W148", line)], [d.message for d in warned]
    assert f"line {line} repeats the timestamp of line {line - 1}" in warned[0].message
    traj = trajectory.read(text)
    assert len(traj.positions) == 20956 and traj.repeated == ((line, line - 1),)
    np.testing.assert_array_equal(traj.positions, xyz[keep])
    np.testing.assert_allclose(traj.rotations, R[keep], atol=1e-12)
    np.testing.assert_allclose(traj.times, stamps[keep] - stamps[0], atol=1e-6)
    assert len(scene.path.transforms) == 20956
