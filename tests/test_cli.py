"""The command line: exit codes, streams, atomic writes, the installed package."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

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
    r = run("check", "--format", "json", "tests/invalid/zero_line.wd", "tests/invalid/unknown_model.wd")
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


def test_reference_lists_every_statement():
    from wiredsl.language.statements import CONTEXTS

    out = run("reference").stdout
    for sigs in CONTEXTS.values():
        for kw in sigs:
            assert f"`{kw}`" in out


def test_readme_reference_is_current():
    """The README carries the generated reference; regenerate it when the table changes."""
    readme = (ROOT / "README.md").read_text()
    assert run("reference").stdout.strip() in readme


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
