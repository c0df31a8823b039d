"""The command line: exit codes, streams, atomic writes, the installed package."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from wiredsl.cli import main

ROOT = Path(__file__).resolve().parent.parent


def run(*args: str):
    return CliRunner().invoke(main, list(args))


def test_exit_codes():
    assert run("check", "scenes/lab.wd").exit_code == 0
    assert run("check", "tests/invalid/zero_line.wd").exit_code == 1
    assert run("check").exit_code == 2  # usage: no file
    assert run("frobnicate").exit_code == 2
    assert run("check", "no/such/file.wd").exit_code == 1


def test_missing_file_is_a_diagnostic_not_a_traceback():
    r = run("check", "no/such/file.wd")
    assert r.stderr.startswith("wiredsl: error[E010]: no such file: no/such/file.wd")


def test_binary_file_is_a_diagnostic(tmp_path):
    f = tmp_path / "x.wd"
    f.write_bytes(b"\xff\xfe\x00garbage")
    r = run("check", str(f))
    assert r.exit_code == 1 and "is not UTF-8 text" in r.stderr and "Traceback" not in r.output


def test_check_reports_every_file_and_json_format():
    r = run("check", "--diagnostics", "json", "tests/invalid/zero_line.wd", "tests/invalid/unknown_model.wd")
    assert r.exit_code == 1
    codes = [d["code"] for d in json.loads(r.stderr)["diagnostics"]]
    assert codes == ["E120", "E104"]


def test_compile_writes_stdout_and_keeps_old_output_on_failure(tmp_path):
    r = run("compile", "scenes/cylinder.wd")
    assert r.exit_code == 0 and json.loads(r.stdout)["name"] == "cylinder" and r.stderr == ""
    out = tmp_path / "scene.json"
    out.write_text("previous")
    assert run("compile", "tests/invalid/zero_line.wd", "-o", str(out)).exit_code == 1
    assert out.read_text() == "previous"
    assert [p.name for p in tmp_path.iterdir()] == ["scene.json"]  # no temporary left behind


def test_outputs_have_ordinary_permissions(tmp_path):
    out = tmp_path / "scene.json"
    assert run("compile", "scenes/cylinder.wd", "-o", str(out)).exit_code == 0
    mask = os.umask(0)
    os.umask(mask)
    assert out.stat().st_mode & 0o777 == 0o666 & ~mask


def test_unwritable_output_is_a_clean_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    r = run("build", "scenes/cylinder.wd", "-o", str(blocker / "out"))
    assert r.exit_code == 1 and "cannot write" in r.stderr and "internal error" not in r.stderr


def test_fmt_check_and_rewrite(tmp_path):
    f = tmp_path / "s.wd"
    f.write_text("wiredsl   1\nmodel m {   line a from (0,0,0) to (1,0,0) }\n")
    assert run("fmt", "--check", str(f)).exit_code == 1
    assert run("fmt", str(f)).exit_code == 0
    assert f.read_text() == "wiredsl 1\nmodel m {\n  line a from (0, 0, 0) to (1, 0, 0)\n}\n"
    assert run("fmt", "--check", str(f)).exit_code == 0


def test_fmt_leaves_a_file_with_a_syntax_error_alone(tmp_path):
    f = tmp_path / "s.wd"
    f.write_text("wiredsl 1\nmodel m {\n")
    assert run("fmt", str(f)).exit_code == 1
    assert f.read_text() == "wiredsl 1\nmodel m {\n"


def test_schema_command_prints_the_committed_schema():
    r = run("schema", "features")
    assert json.loads(r.stdout)["$id"] == "urn:wiredsl:schema:features:1"


def test_validate_rejects_non_json_and_foreign_documents(tmp_path):
    (tmp_path / "a.json").write_text("{not json")
    (tmp_path / "b.json").write_text('{"hello": 1}')
    r = run("validate", str(tmp_path / "a.json"), str(tmp_path / "b.json"))
    assert r.exit_code == 1
    assert "a.json:1:2: error: not JSON" in r.stderr and "not a wiredsl document" in r.stderr


def test_validate_points_a_scene_source_at_check():
    r = run("validate", "scenes/lab.wd")
    assert r.exit_code == 1
    assert "scenes/lab.wd: error: a scene source, not a JSON document: check it with 'wiredsl check scenes/lab.wd'" \
        in r.stderr


@pytest.mark.parametrize("args", [["--format", "jsonl", "--trials", "3", "--seed", "1", "--engine", "numpy"],
                                  ["--no-effects"]])  # each writes several pipe buffers (400 kB, 170 kB)
def test_a_reader_that_stops_early_is_not_an_error(args):
    """Issue 15: `build --format jsonl -o - | head` exited 1 with "cannot write: Broken pipe"."""
    proc = subprocess.Popen([sys.executable, "-m", "wiredsl", "build", "scenes/lab.wd", "-o", "-", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.read(10)
    proc.stdout.close()  # as `head` does once it has its lines
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0 and b"Broken pipe" not in err and b"Traceback" not in err, err


def test_reference_lists_every_statement():
    from wiredsl.language.statements import CONTEXTS

    out = run("reference").stdout
    for sigs in CONTEXTS.values():
        for kw in sigs:
            assert f"`{kw}`" in out


def test_the_language_page_carries_the_generated_reference():
    """The site's language page is filled from the statement table at build time, as `wiredsl reference` prints it."""
    from wiredsl import docgen

    page = (ROOT / "docs/reference/language.md").read_text()
    assert "<!-- generated: statements -->" in page
    assert run("reference").stdout.strip() in docgen.expand(page)


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    quick = readme.split("## Quick start", 1)[1].split("\n## ", 1)[0]
    commands = [b.strip() for b in quick.split("```sh")[1:]]
    commands = [c.split("```")[0].strip() for c in commands]
    assert len(commands) == 2 and commands[0].endswith(".venv/bin/wiredsl build scenes/lab.wd")
    assert commands[1] in (ROOT / ".ci/run").read_text()


_PROBE = """
import importlib.metadata as md, json, re, sys
from pathlib import Path
site = Path(sys.argv[1])
before = set(sys.modules)
import wiredsl
from wiredsl.cli import main
try:
    main([*sys.argv[2:]], standalone_mode=False)
except SystemExit as e:
    if e.code:
        raise
name = lambda req: re.split(r"[ ;\\[<>=!~(]", req, maxsplit=1)[0]
canon = lambda d: re.sub(r"[-_.]+", "-", d).lower()
meta = next(site.glob("wiredsl-*.dist-info")) / "METADATA"
declared = [name(l.split(":", 1)[1].strip()) for l in meta.read_text().splitlines()
            if l.startswith("Requires-Dist:") and "extra ==" not in l]
allowed, todo = set(), list(declared)
while todo:  # the declared requirements and what they require in turn
    d = canon(todo.pop())
    if d not in allowed:
        allowed.add(d)
        todo += [name(r) for r in (md.requires(d) or []) if "extra ==" not in r]
owners = md.packages_distributions()
imported = {m.split(".")[0] for m in set(sys.modules) - before} - {"wiredsl"}
undeclared = sorted({canon(d) for m in imported for d in owners.get(m, [])} - allowed)
print(json.dumps({"file": wiredsl.__file__, "undeclared": undeclared}))
"""


def test_installed_package_runs_outside_the_checkout(tmp_path):
    """Build a wheel, install it (not editable) on its own, run `build` from elsewhere.

    The base interpreter plays no part: the wheel goes into a folder of its own,
    which is put first on the path of this test's interpreter, and every
    third-party distribution the run imports must be among the wheel's declared
    requirements (so a dependency the code uses but pyproject.toml forgets fails
    here, whatever the machine has installed).
    """
    wheels = tmp_path / "wheels"
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w",
                            str(wheels), str(ROOT)], capture_output=True, text=True)
    assert built.returncode == 0, built.stderr
    site = tmp_path / "site"
    installed = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site),
                                str(next(wheels.glob("*.whl")))], capture_output=True, text=True)
    assert installed.returncode == 0, installed.stderr
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site)}
    r = subprocess.run([sys.executable, "-c", _PROBE, str(site), "build", str(ROOT / "scenes/lab.wd"),
                        "-o", str(elsewhere / "out")], cwd=elsewhere, capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr
    probe = json.loads(r.stdout.strip().splitlines()[-1])
    assert probe["file"].startswith(str(site))  # the installed copy, not the checkout
    assert not probe["undeclared"], f"`wiredsl build` imports distributions not required by the wheel: {probe}"
    assert (elsewhere / "out" / "features.json").is_file()
    r = subprocess.run([sys.executable, "-m", "wiredsl", "schema", "scene"], cwd=elsewhere, capture_output=True,
                       text=True, env=env)
    assert json.loads(r.stdout)["$id"] == "urn:wiredsl:schema:scene:1"


# Runs a `wiredsl` command in the probe's process (a probe prints what it saw after it)
_RUN = """
import json, sys
from wiredsl.cli import main
try:
    main(sys.argv[1:], standalone_mode=False)
except SystemExit as e:
    if e.code:
        raise
"""
_IMPORTED = _RUN + "print(json.dumps(sorted(sys.modules)))\n"

# Never on the lab's check or one-trial build: the optional extras, the readers of files the lab does not have,
# and the parts of wiredsl other commands use (each costs the cold start its import; see benchmarks/cold_start.py).
NOT_FOR_THE_LAB = {
    "numba", "llvmlite", "scipy", "matplotlib", "trimesh", "yaml", "dask", "pygls", "jsonschema", "cv2", "numpy.ma",
    "importlib.metadata",  # pydantic's plug-in loader imports it with the first validator (~13 ms with its scan)
    "socket",  # files.py names its temporaries by the host: os.uname() gives it without socket's import (~2 ms)
    "wiredsl.api", "wiredsl.bench", "wiredsl.lsp", "wiredsl.study", "wiredsl.measures", "wiredsl.engine.kernel",
    "wiredsl.engine.mesh", "wiredsl.io.calibration", "wiredsl.io.trajectory", "wiredsl.io.mesh", "wiredsl.io.load",
    "wiredsl.io.schema", "wiredsl.language.compile_study", "wiredsl.language.fmt", "wiredsl.io.render",
    "wiredsl.export", "wiredsl.render_cli", "wiredsl.verify",  # commands imported when they run (cli.LAZY_COMMANDS)
    "wiredsl.io.features",  # the dump's models: a build writes it from arrays and makes only the manifest's
    *(f"wiredsl.effects.{e}_kernel" for e in ("approx_error", "corner_loss", "corner_mismatch", "edge_loss",
                                               "lateral_shift", "stereo_mismatch")),
}
NOT_FOR_CHECK = {"orjson", "wiredsl.run", "wiredsl.engine.world", "wiredsl.engine.simulate", "wiredsl.engine.trials",
                 "wiredsl.montecarlo", "wiredsl.io.emit", "wiredsl.io.manifest", "wiredsl.io.svg"}


@pytest.mark.parametrize("args, absent", [
    (["check", "scenes/lab.wd"], NOT_FOR_THE_LAB | NOT_FOR_CHECK),
    (["build", "scenes/lab.wd", "--no-svg", "-o", "{out}"], NOT_FOR_THE_LAB | {"wiredsl.io.svg"}),
])
def test_the_labs_check_and_build_import_only_what_they_use(args, absent, tmp_path):
    args = [a.format(out=tmp_path / "out") for a in args]
    r = subprocess.run([sys.executable, "-c", _IMPORTED, *args], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    imported = set(json.loads(r.stdout.strip().splitlines()[-1]))
    assert "wiredsl.language.compile" in imported and "pydantic.main" in imported  # the probe saw the command run
    loaded = sorted(m for m in imported if m in absent or any(m.startswith(f"{a}.") for a in absent))
    assert not loaded, f"`wiredsl {' '.join(args)}` imported {loaded}"


_VALIDATED = _RUN + """
from pydantic._internal._mock_val_ser import MockValSer
from wiredsl.effects.base import Params
from wiredsl.scene import Node
def every(c):
    for s in c.__subclasses__():
        yield s
        yield from every(s)
print(json.dumps(sorted({c.__name__ for base in (Node, Params) for c in every(base)
                          if not isinstance(c.__pydantic_validator__, MockValSer)})))
"""


def test_the_labs_build_makes_no_validator_for_the_nodes_the_compiler_checked(tmp_path):
    """The compiler makes the scene's nodes and the stages' parameters from checked values (`scene.trusted`,
    `scene.checked`), the dumps are made from the fields (`scene.dumped`), and every model's validator is built when
    first used (`defer_build`): neither a one-trial build of the lab nor its check builds a validator (the first
    costs pydantic's plug-in loader, some 13 ms: it imports importlib.metadata and scans the installed packages'
    entry points)."""
    from wiredsl import scene
    from wiredsl.effects import BUILTIN

    assert {"Camera", "Scene", "Line"} <= {c.__name__ for c in scene.Node.__subclasses__()}  # the probe's classes
    from wiredsl.effects.base import Params

    assert all(issubclass(e.Params, Params) for e in BUILTIN.values())  # the probe sees every stage's parameters
    for args in (["build", "scenes/lab.wd", "--engine", "numpy", "-o", str(tmp_path / "out")],
                 ["check", "scenes/lab.wd"]):
        r = subprocess.run([sys.executable, "-c", _VALIDATED, *args], cwd=ROOT, capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        assert json.loads(r.stdout.strip().splitlines()[-1]) == [], args


# --------------------------------------------------------------------------- options and output folders

def test_diagnostics_option_on_every_command_and_format_only_for_dumps(tmp_path):
    for cmd in (["check"], ["compile"], ["fmt", "--check"], ["build"], ["viewdep"], ["bench"], ["export-calibration"],
                ["study"]):
        r = run(*cmd, "--diagnostics", "json", "tests/invalid/syntax_unclosed.wd")
        assert r.exit_code == 1, (cmd, r.output)
        assert json.loads(r.stderr)["diagnostics"][0]["line"] > 0, cmd
    assert run("check", "--format", "json", "scenes/lab.wd").exit_code == 2  # the old name is gone
    assert run("build", "scenes/lab.wd", "--format", "text", "-o", "-").exit_code == 2


def test_o_naming_a_file_or_a_dump_name_is_a_usage_error(tmp_path):
    f = tmp_path / "f"
    f.write_text("mine")
    r = run("build", "scenes/cylinder.wd", "-o", str(f))
    assert r.exit_code == 2 and "must be a folder" in r.stderr and f.read_text() == "mine"
    r = run("build", "scenes/cylinder.wd", "-o", str(tmp_path / "out.json"))
    assert r.exit_code == 2 and "looks like a file name" in r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]
    for cmd, name in (("export-calibration", "x.yaml"), ("study", "table.csv")):  # folder commands as build
        r = run(cmd, "scenes/lab.wd" if cmd != "study" else "scenes/studies/lab_study.wd", "-o", str(tmp_path / name))
        assert r.exit_code == 2 and "looks like a file name; -o names the output folder" in r.stderr, cmd
        r = run(cmd, "scenes/lab.wd", "-o", str(f))
        assert r.exit_code == 2 and f"must name a folder: {f} is a file" in r.stderr, cmd
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]  # issue 15: x.yaml was made a folder
    for cmd in ("viewdep", "compile"):  # one-file commands: -o must not be a folder, and no temporary name leaks
        r = run(cmd, "scenes/lab.wd", "-o", f"{tmp_path}/")
        assert r.exit_code == 2 and "must name a file, not a folder" in r.stderr and ".tmp" not in r.stderr, cmd


def test_output_folder_holds_exactly_one_run(tmp_path):
    out = tmp_path / "out"
    assert run("build", "scenes/lab.wd", "-o", str(out), "--seed", "1").exit_code == 0
    (out / "viewdep.json").write_text("{}")  # other commands' outputs are carried over
    (out / "calibration").mkdir()
    (out / "calibration" / "stereo.yaml").write_text("%YAML:1.0")
    r = run("build", "scenes/lab.wd", "-o", str(out), "--seed", "1", "--pose", "2", "--trials", "2",
            "--format", "jsonl")
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in out.iterdir()) == ["calibration", "features.jsonl", "manifest.json", "pose_002.svg",
                                                     "viewdep.json"]
    assert (out / "calibration" / "stereo.yaml").read_text() == "%YAML:1.0"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no temporaries beside it
    assert json.loads((out / "manifest.json").read_text())["trials"] == 2


def test_a_folder_of_other_files_is_replaced_only_with_force(tmp_path):
    out = tmp_path / "thesis"
    out.mkdir()
    (out / "chapter1.tex").write_text("precious")
    r = run("build", "scenes/cylinder.wd", "-o", str(out), "--no-effects")
    assert r.exit_code == 2 and "chapter1.tex" in r.stderr and "--force" in r.stderr
    assert [p.name for p in out.iterdir()] == ["chapter1.tex"]
    assert run("build", "scenes/cylinder.wd", "-o", str(out), "--no-effects", "--force").exit_code == 0
    assert "chapter1.tex" not in [p.name for p in out.iterdir()]
    r = run("build", "scenes/cylinder.wd", "-o", ".", "--force")  # never the working folder itself
    assert r.exit_code == 2 and "working" in r.stderr


def test_default_locations_are_under_build(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert run("build", str(ROOT / "scenes/lab.wd"), "--pose", "0", "--seed", "1").exit_code == 0
    r = run("viewdep", str(ROOT / "scenes/lab.wd"))
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp_path / "build" / "lab").iterdir()) == \
        ["features.json", "manifest.json", "pose_000.svg", "viewdep.json"]
    assert run("validate", "build/lab/viewdep.json").exit_code == 0


def test_npz_writes_the_first_trials_svgs_and_no_effects_a_manifest(tmp_path):
    import numpy as np

    r = run("build", "scenes/lab.wd", "--format", "npz", "--trials", "3", "--seed", "4", "--pose", "1", "-o",
            str(tmp_path / "npz"))
    assert r.exit_code == 0, r.output
    svg = (tmp_path / "npz" / "pose_001.svg").read_text()
    r = run("build", "scenes/lab.wd", "--trial", "0", "--seed", "4", "--pose", "1", "-o", str(tmp_path / "one"))
    assert svg == (tmp_path / "one" / "pose_001.svg").read_text()  # the SVG shows trial 0, as the json run does
    with np.load(tmp_path / "npz" / "features.npz") as z:
        assert json.loads(str(z["manifest"]))["seed"] == 4
    r = run("build", "scenes/lab.wd", "--no-effects", "--seed", "5", "--pose", "0", "-o", str(tmp_path / "ideal"))
    assert r.exit_code == 0
    manifest = json.loads((tmp_path / "ideal" / "manifest.json").read_text())
    assert manifest["stages"] == [] and manifest["seed"] == 5 and manifest["pipeline"] is None


@pytest.mark.parametrize(("args", "says"), [
    (["--trial", str(2**31)], "0<=x<=2147483647"),
    (["--trial", str(2**64)], "0<=x<=2147483647"),
    (["--tolerance", "1e-300"], "[0.001, 100] px"),
    (["--tolerance", "nan"], "[0.001, 100] px"),
    (["--tolerance", "1000"], "[0.001, 100] px"),
    (["--trials", "100000000", "--format", "npz", "-o", "OUT"], "TB of npz"),
    (["--trials", "100000000", "--format", "jsonl"], "TB of jsonl"),
    (["--format", "npz"], "npz cannot go to stdout"),
])
def test_bounds_are_usage_errors(args, says, tmp_path):
    args = [str(tmp_path / "o") if a == "OUT" else a for a in args]
    r = run("build", "scenes/lab.wd", "-o", "-", *args) if "-o" not in args else run("build", "scenes/lab.wd", *args)
    assert r.exit_code == 2 and says in r.stderr, r.output
    assert list(tmp_path.iterdir()) == []


def test_size_estimate_matches_a_real_run(tmp_path):
    """The refusal's estimate (bytes a trial, measured on the first trial) is within 10% of what trials add."""
    import re

    for fmt in ("jsonl", "npz"):
        big = run("build", "scenes/lab.wd", "--seed", "2", "--trials", "100000000", "--format", fmt, "--pose", "1",
                  "-o", str(tmp_path / fmt))
        per = re.search(r"\(([\d.]+) kB a trial", big.stderr)
        assert big.exit_code == 2 and per, big.stderr
        size = {}
        for n in (10, 40):  # the difference leaves out what does not grow with N (npz: feature ids, manifest)
            assert run("build", "scenes/lab.wd", "--seed", "2", "--trials", str(n), "--format", fmt, "--no-svg",
                       "--pose", "1", "-o", str(tmp_path / fmt)).exit_code == 0
            size[n] = (tmp_path / fmt / f"features.{fmt}").stat().st_size
        real = (size[40] - size[10]) / 30
        assert 0.9 < float(per[1]) * 1000 / real < 1.1, (fmt, per[1], real)


def test_o_naming_a_fifo_writes_into_it_and_empty_o_is_refused(tmp_path):
    """A device or FIFO (say /dev/null) is written into, never renamed over."""
    import threading

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    got = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_text()))
    reader.start()
    assert run("compile", "scenes/cylinder.wd", "-o", str(fifo)).exit_code == 0
    reader.join(10)
    assert json.loads(got[0])["name"] == "cylinder" and fifo.is_fifo()
    for cmd in ("build", "compile", "viewdep"):
        r = run(cmd, "scenes/lab.wd", "-o", "")
        assert r.exit_code == 2 and "must not be empty" in r.stderr, cmd


def test_the_size_estimate_leaves_the_run_as_it_was(tmp_path):
    """Measuring a trial before the run changes no byte of its outputs (--force skips the measuring)."""
    outs = []
    for extra in ([], ["--force"]):
        out = tmp_path / f"o{len(outs)}"
        r = run("build", "scenes/lab.wd", "--seed", "6", "--trials", "3", "--format", "jsonl", "--pose", "2", "-o",
                str(out), *extra)
        assert r.exit_code == 0, r.output
        outs.append({p.name: p.read_bytes() for p in out.iterdir()})
    assert outs[0] == outs[1]


def test_a_replayed_trial_needs_its_runs_seed():
    r = run("build", "scenes/lab.wd", "--trial", "3", "-o", "-")
    assert r.exit_code == 2 and "--seed" in r.output


def test_a_study_without_matplotlib_is_refused_before_it_runs(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib now raises ImportError
    r = run("study", "scenes/studies/lab_study.wd", "shift_calibration", "-o", str(tmp_path / "s"))
    assert r.exit_code == 2 and "pip install '.[plot]'" in r.output and "--no-plots" in r.output
    assert not (tmp_path / "s").exists()  # nothing ran


def test_the_console_entry_exits_without_teardown_yet_writes_and_codes_as_main(tmp_path):
    """`python -m wiredsl` (cli.entry) skips the interpreter's teardown: its exit codes (0, 1 invalid input, 2
    usage), its stdout through a pipe (the whole dump) and its files are those of `main`."""
    import wiredsl

    py = [sys.executable, "-m", "wiredsl"]
    full = subprocess.run([*py, "build", "scenes/lab.wd", "--no-svg", "-o", "-"], cwd=ROOT, capture_output=True)
    assert full.returncode == 0 and json.loads(full.stdout)["document"] == "features"
    bad = subprocess.run([*py, "check", "tests/invalid/zero_line.wd"], cwd=ROOT, capture_output=True, text=True)
    assert bad.returncode == 1 and "error[" in bad.stderr
    assert subprocess.run([*py, "build", "--bogus"], cwd=ROOT, capture_output=True).returncode == 2
    out = tmp_path / "out"
    r = subprocess.run([*py, "build", "scenes/lab.wd", "--trials", "300", "--format", "npz", "--seed", "1", "--no-svg",
                        "-o", str(out)], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert [k for k in wiredsl.load(out / "features.npz", arrays=True)] and json.loads(
        (out / "manifest.json").read_text())["trials"] == 300
    # a plug-in's (or coverage's) atexit function still runs; under cProfile the exit is the usual one
    script = ("import atexit, sys\natexit.register(lambda: print('atexit ran'))\nfrom wiredsl.cli import entry\n"
              "sys.argv = ['wiredsl', 'check', 'scenes/lab.wd']\nentry()\n")
    r = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout == "atexit ran\n" and r.stderr == "1 file ok\n", (r.stdout, r.stderr)
    r = subprocess.run([sys.executable, "-m", "cProfile", "-m", "wiredsl", "check", "scenes/lab.wd"], cwd=ROOT,
                       capture_output=True, text=True)
    assert r.returncode == 0 and "function calls" in r.stdout
