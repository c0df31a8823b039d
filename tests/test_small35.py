"""Issue 35, item 11: small things, each as it was met."""

from __future__ import annotations

import types

from wiredsl import study as st


def _job(point, lo, hi):
    return types.SimpleNamespace(shard=types.SimpleNamespace(point=point, lo=lo, hi=hi))


def test_a_studys_first_progress_line_has_no_rate_from_its_start_up(monkeypatch):
    """Was: "0 trials/s, ETA 608 s" after the first shard (its time is the workers' start-up and the kernel's
    compiling); the study took 70 s. The rate is measured from the first shard on."""
    clock = iter([0.0, 30.0, 31.0, 32.0, 33.0])
    monkeypatch.setattr(st.time, "perf_counter", lambda: next(clock))
    said = []
    jobs = [_job(p, 0, 64) for p in range(4)]
    progress = st.Progress(jobs, said.append)
    for j in jobs:
        progress.pending(j)
    for j in jobs:
        progress(j.shard, 64)
    assert said[0] == "study: 1/4 points, 64/256 trials, measuring the rate"
    assert said[1] == "study: 2/4 points, 128/256 trials, 64 trials/s, ETA 2 s"  # 64 trials in the 1 s after
    assert said[-1].startswith("study: 4/4 points, 256/256 trials, 64 trials/s, ETA 0 s")


def test_a_slow_rate_is_not_shown_as_zero(monkeypatch):
    clock = iter([0.0, 1.0, 11.0])
    monkeypatch.setattr(st.time, "perf_counter", lambda: next(clock))
    said = []
    jobs = [_job(0, 0, 2), _job(1, 0, 2)]
    progress = st.Progress(jobs, said.append)
    for j in jobs:
        progress.pending(j)
    for j in jobs:
        progress(j.shard, 2)
    assert said[-1] == "study: 2/2 points, 4/4 trials, 0.2 trials/s, ETA 0 s"


def test_a_worker_process_does_not_announce_compiling(monkeypatch, capsys):
    """Was: "compiling..." once per worker of a study."""
    import multiprocessing

    from wiredsl.engine import kernel

    batch = types.SimpleNamespace(signatures=[], _cache=None)
    monkeypatch.setattr(kernel, "_announced", False)
    monkeypatch.setattr(multiprocessing, "parent_process", lambda: object())  # as in a pool's worker
    kernel.announce_compile(batch)
    assert capsys.readouterr().err == ""
    monkeypatch.setattr(multiprocessing, "parent_process", lambda: None)  # the study's own process
    kernel.announce_compile(batch)
    assert "compiling the Monte-Carlo kernel" in capsys.readouterr().err


def test_captions_bounds_and_counts_read_as_numbers_and_words(tmp_path):
    """Was: SVG captions `y = -0.00 m`, mesh bounds `-1.225e-17`, "1 silhouettes"."""
    from click.testing import CliRunner

    from wiredsl.cli import main

    scene = tmp_path / "s.wd"  # a path along x at y = -0.001: its caption said -0.00
    scene.write_text(open("tests/data/table_box_cup.wd").read().replace(
        "straight from (1.5m, -1m) to (1.5m, 1m) step 0.5m", "straight from (1.5m, -0.001m) to (1.6m, -0.001m) "
        "step 0.1m"))
    r = CliRunner().invoke(main, ["build", str(scene), "--no-effects", "-o", str(tmp_path / "o")])
    assert r.exit_code == 0, r.output
    caption = (tmp_path / "o" / "pose_000.svg").read_text()
    assert "y = 0.00 m" in caption and "-0.00" not in caption
    r = CliRunner().invoke(main, ["check", "scenes/meshes.wd"])
    notes = [x for x in r.stderr.splitlines() if ": note: mesh " in x]
    assert notes and not any("e-1" in x for x in notes), notes  # the crate's base at z = 0, not -1.225e-17
    assert any("from (-0.3, -0.2, 0) to (0.3, 0.2, 0.4) m" in x for x in notes)
    assert any("1 silhouette," in x for x in notes) and not any("1 silhouettes" in x for x in notes)


def test_fmts_continuations_are_documented_and_the_init_ci_says_how_to_pass_its_check(tmp_path):
    """Was: `fmt` wrote backslash continuations that the language reference did not describe, and a scene written
    by hand failed `fmt --check` (and so the `init` project's CI) without saying so."""
    import subprocess
    from pathlib import Path

    from wiredsl.language.fmt import format_text

    page = Path("docs/reference/language.md").read_text()
    assert "a `\\` at the end of a line continues the statement" in page and "wiredsl fmt --check" in page
    long = "wiredsl 1\nmodel m {\n  polyline p through " + " ".join(f"({i}, 0, 0)" for i in range(14)) + "\n}\n"
    formatted = format_text(long)
    assert any(line.endswith("\\") for line in formatted.splitlines())  # what the page now describes
    from wiredsl import init

    ci = init.fill(init.CI_SCRIPT, {"package": "p"})
    line = next(x for x in ci.splitlines() if x.startswith("wiredsl fmt --check"))
    assert "wiredsl fmt scenes/*.wd" in line
    script = tmp_path / "ci.sh"
    script.write_text("set -euo pipefail\nwiredsl() { return 1; }\n" + line + "\n")
    r = subprocess.run(["bash", str(script)], capture_output=True, text=True)
    assert r.returncode == 1 and "run 'wiredsl fmt scenes/*.wd'" in r.stderr
