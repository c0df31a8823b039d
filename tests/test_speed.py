"""What the speed work must not change: the npz writer's bytes, pinned by a hash of a small run's members."""

from __future__ import annotations

import hashlib
import zipfile

from click.testing import CliRunner

from wiredsl.cli import main

# sha256 of every member but the manifest (it names the tool's version), in name order, of
# `build scenes/lab.wd --trials 9 --format npz --seed 7 --pose 1 --pose 4 --engine numpy`; computed on the
# writer that looped over trials and camera models, before it was vectorised.
GOLDEN = "f8cc8ccf4f2e18498856cbe289581e4062c2d4b452d4b5a93d0a6601ffaa81ac"


def members_hash(path) -> str:
    h = hashlib.sha256()
    with zipfile.ZipFile(path) as z:
        for name in sorted(z.namelist()):
            if name != "manifest.npy":
                h.update(name.encode())
                h.update(z.read(name))
    return h.hexdigest()


def test_the_npz_writer_writes_the_same_bytes_as_before(tmp_path):
    args = ["build", "scenes/lab.wd", "--trials", "9", "--format", "npz", "--seed", "7", "--pose", "1", "--pose", "4",
            "--engine", "numpy", "--no-svg"]
    result = CliRunner().invoke(main, [*args, "-o", str(tmp_path / "a")])
    assert result.exit_code == 0, result.output
    assert members_hash(tmp_path / "a" / "features.npz") == GOLDEN
