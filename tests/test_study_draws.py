"""`draws common` in a study: every design point draws the same disturbances (common random numbers)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from study_measures import REGISTRY

from wiredsl.cli import main
from wiredsl.language.compile import compile_file
from wiredsl.study import jobs, journal, run_study, shards

TEXT = """wiredsl 1
include "{lab}"
study twins {{
  pipeline edges
  vary lateral_shift.range values [2px, 2px, 3px]
  trials 6
  poses [1, 3]
  seed 4
  {draws}
  measure kept
}}
"""


def _scene(tmp_path: Path, draws: str):
    path = tmp_path / f"{draws.replace(' ', '_') or 'default'}.wd"
    path.write_text(TEXT.format(lab=Path("scenes/lab.wd").resolve().as_posix(), draws=draws))
    scene, diags, _ = compile_file(path)
    assert scene is not None, diags
    return path, scene


def _per_point(scene, folder: Path) -> list[dict[str, np.ndarray]]:
    study = scene.study("twins")
    run_study(scene, study, folder, executor="inprocess", registry=REGISTRY)
    X, all_jobs = jobs(scene, study, folder, REGISTRY)
    stored = journal.replay(folder, {shards.key(j) for j in all_jobs})
    out: list[dict[str, list]] = [{} for _ in range(len(X))]
    for j in all_jobs:
        for k, v in stored[shards.key(j)].items():
            out[j.shard.point].setdefault(k, []).append(v)
    return [{k: np.concatenate(v, axis=1) for k, v in p.items()} for p in out]


@pytest.mark.parametrize("draws, same", [("draws common", True), ("draws independent", False), ("", True)])
def test_equal_points_draw_equal_trials_only_with_common_draws(tmp_path, draws, same):
    """Common draws are the default (benchmarks/study_crn.py: the same precision of Sobol' indices for 5 to 50
    times fewer CPU-seconds on the lab)."""
    _, scene = _scene(tmp_path, draws)
    assert scene.study("twins").draws == ("common" if same else "independent")
    p = _per_point(scene, tmp_path / "out")
    # points 0 and 1 have the same parameters: with common draws every trial is the same, else each its own
    assert np.array_equal(p[0]["kept.length"], p[1]["kept.length"]) is same
    # and the third point's trials move each stroke by 1.5x the same draws, not by new ones: its lengths differ
    assert not np.array_equal(p[0]["kept.length"], p[2]["kept.length"])


def test_common_draws_are_the_plain_runs_draws_and_a_trial_replays_alone(tmp_path):
    """With common draws a point's trial k is `build`'s trial k of the point's pipeline and the study's seed (no
    point in the key), and `build --study --point --trial` replays it: point 2 (range 3 px) is the lab's `edges`
    pipeline at its defaults (edge_loss, lateral_shift range 3 px)."""
    import json

    path, _ = _scene(tmp_path, "draws common")
    outs = {}
    for name, args in (("study", ["--study", "twins", "--point", "2", "--trial", "3"]),
                       ("plain", ["--seed", "4", "--trials", "4", "--pipeline", "edges"]),
                       ("other", ["--study", "twins", "--point", "0", "--trial", "3"])):
        r = CliRunner().invoke(main, ["build", str(path), "-o", str(tmp_path / name), "--format", "jsonl",
                                      "--pose", "1", "--no-svg", *args])
        assert r.exit_code == 0, r.output
        outs[name] = [json.loads(line) for line in (tmp_path / name / "features.jsonl").read_text().splitlines()]
    study, plain, other = outs["study"][0], outs["plain"][3], outs["other"][0]
    assert study["trial"] == plain["trial"] == 3
    assert study["poses"] == plain["poses"]
    assert other["poses"] != study["poses"]  # range 2 px: the same draws move the strokes less


def test_draws_takes_common_or_independent_and_says_where(tmp_path):
    path = tmp_path / "bad.wd"
    path.write_text(TEXT.format(lab=Path("scenes/lab.wd").resolve().as_posix(), draws="draws sometimes"))
    r = CliRunner().invoke(main, ["check", str(path)])
    assert r.exit_code == 1
    assert f"{path}:9:9" in r.output and "sometimes" in r.output and "common" in r.output, r.output
