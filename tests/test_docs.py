"""The documentation site: its tutorials' code runs as written, its generated reference covers the code's tables,
and every page is in the navigation. (The strict build and the browser check run in CI: .ci/run.)

A fenced block is run when the line before it is `<!-- run -->` (sh: bash; python: this interpreter), and
written to a file when it is `<!-- file: NAME -->`; a page's blocks run in order in one temporary folder with
the checkout's scenes/, examples/ and tests/data/ beside them (docs/how-to/docs.md).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
BLOCK = re.compile(r"^<!-- (run|file: ([\w./-]+)) -->\n```(\w*)[^\n]*\n(.*?)^```", re.S | re.M)


def runnable(page: Path) -> list[tuple[str, str | None, str, str]]:
    """(action, file name, language, code) of every marked block of a page, in order."""
    return [(m.group(1).split(":")[0], m.group(2), m.group(3), m.group(4))
            for m in BLOCK.finditer(page.read_text(encoding="utf-8"))]


PAGES = sorted(p for p in DOCS.rglob("*.md") if runnable(p))


def test_the_tutorials_have_runnable_code():
    names = {p.relative_to(DOCS).as_posix() for p in PAGES}
    assert {f"tutorials/{n}.md" for n in ("first-scene", "camera", "path", "mesh", "study", "closed-loop",
                                                   "measure-your-detector")} <= names
    assert "how-to/new-project.md" in names
    for page in PAGES:  # a marker before anything but a fence would silently not run
        text = page.read_text(encoding="utf-8")
        assert text.count("<!-- run -->") + text.count("<!-- file: ") == len(runnable(page)), page


@pytest.mark.parametrize("page", PAGES, ids=[p.relative_to(DOCS).as_posix() for p in PAGES])
def test_page_code_runs(page: Path, tmp_path: Path):
    for name in ("scenes", "examples"):
        (tmp_path / name).symlink_to(ROOT / name)
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "data").symlink_to(ROOT / "tests" / "data")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
           "MPLBACKEND": "Agg"}
    for action, name, lang, code in runnable(page):
        if action == "file":
            target = tmp_path / name
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(code, encoding="utf-8")
            continue
        assert lang in ("sh", "python"), f"{page}: a block to run must be sh or python, not {lang!r}"
        argv = ["bash", "-euo", "pipefail", "-c", code] if lang == "sh" else [sys.executable, "-c", code]
        proc = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
        shown = f"{page.name}: block failed\n{code}\n--- stdout\n{proc.stdout}\n--- stderr\n{proc.stderr}"
        assert proc.returncode == 0, shown
        assert "Traceback" not in proc.stderr, proc.stderr


def test_every_generated_block_is_known_and_used():
    from wiredsl import docgen

    used = set()
    for page in DOCS.rglob("*.md"):
        used |= set(docgen.MARKER.findall(page.read_text(encoding="utf-8")))
    assert used == set(docgen.GENERATORS), (used, set(docgen.GENERATORS))
    with pytest.raises(KeyError, match="unknown generated block"):
        docgen.expand("<!-- generated: nothing -->")


def test_the_diagnostics_table_holds_every_code_the_source_gives():
    """CODES (the diagnostics page's table) names each code the compiler and commands give, and no other."""
    from wiredsl import docgen
    from wiredsl.diagnostics import CODES

    given = set()
    for path in (ROOT / "wiredsl").rglob("*.py"):
        if path.name != "diagnostics.py":
            given |= set(re.findall(r"[\"']([EW]\d{3})[\"']", path.read_text(encoding="utf-8")))
    assert given, "no codes found in the source"
    assert given == set(CODES), (sorted(given - set(CODES)), sorted(set(CODES) - given))
    table = docgen.diagnostics()
    assert all(f"| {code} |" in table for code in CODES)


def test_the_effects_and_measures_pages_list_every_parameter_with_its_unit():
    from wiredsl import docgen
    from wiredsl.effects import BUILTIN as EFFECTS
    from wiredsl.measures import BUILTIN as MEASURES

    text = docgen.effects() + docgen.measures()
    for reg in (EFFECTS, MEASURES):
        for name, cls in reg.items():
            assert f"### `{name}`" in text
            section = text.split(f"### `{name}`", 1)[1].split("\n### ", 1)[0]  # its own table (spread: several)
            for key, f in cls.Params.model_fields.items():
                row = next(line for line in section.splitlines() if line.startswith(f"| `{key}` | {f.default} |"))
                assert f.json_schema_extra["kind"] in row
    assert "| `range` | 3.0 | image (px) |" in text  # lateral_shift: the paper's 3 px


def test_the_cli_page_lists_every_command_and_option():
    import click

    from wiredsl import docgen
    from wiredsl.cli import main

    text = docgen.cli()
    for name in main.list_commands(None):  # the lazily imported commands too (cli.LAZY_COMMANDS)
        cmd = main.get_command(None, name)
        assert f"### `wiredsl {name}`" in text
        for p in cmd.params:
            if isinstance(p, click.Option):
                assert any(o in text for o in p.opts), (name, p.opts)


def test_every_page_is_in_the_navigation_and_every_link_of_the_readme_exists():
    yaml = pytest.importorskip("yaml")
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text(encoding="utf-8").replace("!!python", "#"))

    def pages(nav):
        for item in nav:
            value = next(iter(item.values())) if isinstance(item, dict) else item
            yield from (pages(value) if isinstance(value, list) else [value])

    listed = set(pages(config["nav"]))
    present = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md")}
    assert listed == present, (sorted(listed - present), sorted(present - listed))
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    links = re.findall(r"\]\((docs/[^)#]+)", readme)
    assert links and all((ROOT / link).exists() for link in links), links
