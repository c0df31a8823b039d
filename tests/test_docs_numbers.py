"""docs/reproduce.py: a documented number or figure that drifts from what its block's command makes fails the check.

The blocks here are cheap stand-ins (a fixed table, a matplotlib line) for the real ones, whose commands are
studies (CI runs `docs/reproduce.py --check --reuse build/ci` on its own study outputs)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
spec = importlib.util.spec_from_file_location("docs_reproduce", ROOT / "docs" / "reproduce.py")
numbers = sys.modules["docs_reproduce"] = importlib.util.module_from_spec(spec)  # dataclasses look it up
spec.loader.exec_module(numbers)

PAGE = "intro\n\n<!-- numbers: t -->\n<!-- /numbers -->\n\nafter\n"


def _setup(tmp_path: Path, table: list[str], ys: list[float]):
    """A page with block `t` (its text `table`, its figure a line through `ys`) in tmp_path/root."""
    pytest.importorskip("matplotlib")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def figure(ctx) -> Path:
        fig, ax = plt.subplots(figsize=(3, 2), dpi=60)
        ax.plot(ys)
        out = tmp_path / "fresh.png"
        fig.savefig(out)
        plt.close(fig)
        return out

    block = numbers.Block("page.md", "make t", lambda ctx: "\n".join(table) + "\n", {"fig.png": figure})
    return {"t": block}, numbers.Context(None, tmp_path)


def _check(root: Path, blocks, ctx) -> list[str]:
    return numbers.run(root, blocks, ctx, write=False, known=blocks)


def test_written_blocks_hold_and_drifted_ones_fail(tmp_path):
    root = tmp_path / "root"
    root.mkdir()
    (root / "page.md").write_text(PAGE)
    table = ["`make t`:", "| a | b |", "|---|---|", "| 0.555 ± 0.119 | 27 of 30 |",
             "lateral shift (0.68) then calibration (0.20)"]
    blocks, ctx = _setup(tmp_path, table, [0, 1, 2])
    assert numbers.run(root, blocks, ctx, write=True, known=blocks) == []
    assert "| 0.555 ± 0.119 | 27 of 30 |" in (root / "page.md").read_text()
    assert (root / "fig.png").is_file()
    assert _check(root, blocks, ctx) == []

    page = (root / "page.md").read_text()
    # the last digit may move by one (another CPU's rounding); more is a drift, reported at the block's line
    (root / "page.md").write_text(page.replace("0.555", "0.556"))
    assert _check(root, blocks, ctx) == []
    (root / "page.md").write_text(page.replace("0.555", "0.447"))
    (drift,) = _check(root, blocks, ctx)
    assert drift.startswith("page.md:3: t: 0.447 on the page, 0.555 now")
    (root / "page.md").write_text(page.replace("27 of 30", "29 of 30"))
    assert _check(root, blocks, ctx) == ["page.md:3: t: 29 on the page, 27 now"]
    # a conclusion whose order flipped is a drift of words, numbers aside
    flipped = page.replace("lateral shift (0.68) then calibration", "calibration (0.68) then lateral shift")
    (root / "page.md").write_text(flipped)
    (drift,) = _check(root, blocks, ctx)
    assert "the words differ" in drift

    # the figure drawn from other data
    (root / "page.md").write_text(page)
    blocks, ctx = _setup(tmp_path, table, [0, 2, 1])
    (drift,) = _check(root, blocks, ctx)
    assert drift.startswith("fig.png (t): differs from what `make t` draws")


def test_missing_and_unknown_blocks_are_named(tmp_path):
    root = tmp_path / "root"
    root.mkdir()
    blocks, ctx = _setup(tmp_path, ["x 1"], [0, 1])
    (root / "page.md").write_text("no block here\n<!-- numbers: nope -->\n<!-- /numbers -->\n")
    assert _check(root, blocks, ctx) == ["page.md: no block `<!-- numbers: t -->`",
                                         "page.md:2: unknown numbers block 'nope': one of t"]


def test_every_real_block_is_on_its_page():
    for name, b in numbers.BLOCKS.items():
        assert f"<!-- numbers: {name} -->" in (ROOT / b.page).read_text(), name


def test_an_svg_figure_is_compared_by_what_it_draws(tmp_path):
    root = tmp_path / "root"
    root.mkdir()
    (root / "page.md").write_text(PAGE)
    svg = tmp_path / "fresh.svg"
    blocks = {"t": numbers.Block("page.md", "make t", lambda ctx: "![f](fig.svg)\n", {"fig.svg": lambda ctx: svg})}
    ctx = numbers.Context(None, tmp_path)
    svg.write_text('<svg><line x1="10.25" y1="3"/><title>pose 3</title></svg>')
    assert numbers.run(root, blocks, ctx, write=True, known=blocks) == []
    svg.write_text('<svg><line x1="10.26" y1="3"/><title>pose 3</title></svg>')  # its last digit: holds
    assert _check(root, blocks, ctx) == []
    svg.write_text('<svg><line x1="10.75" y1="3"/><title>pose 3</title></svg>')
    assert _check(root, blocks, ctx) == ["fig.svg (t): differs from what `make t` draws: 10.25 on the page, 10.75 now"]
    svg.write_text('<svg><line x1="10.25" y1="3"/><line x1="1" y1="2"/><title>pose 3</title></svg>')  # one more
    (drift,) = _check(root, blocks, ctx)
    assert "the words differ" in drift


def test_a_number_outside_a_block_fails_the_scan_until_listed(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "README.md").write_text("wiredsl 0.2.0: the paper's pipeline.\n")
    page = ("Canny verifies 87.3% of the edges, 0.21 px RMS.\n\n<!-- numbers: t -->\nLSD 90.0%\n<!-- /numbers -->\n\n"
            "```\nmeasured 12.5%\n```\n\nIn code, `--band 6px` or `0.5`; a [link](a-1.5.md). Apache-2.0.\n")
    (tmp_path / "docs" / "page.md").write_text(page)
    assert [(p, i, n) for p, i, n, _ in numbers.outside_blocks(tmp_path)] == [
        ("docs/page.md", 1, "87.3%"), ("docs/page.md", 1, "0.21 px")]
    (first, second) = numbers.scan(tmp_path)
    assert first.startswith("docs/page.md:1: '87.3%' is outside any numbers block") and "'0.21 px'" in second
    assert numbers.scan(tmp_path, write=True) == [] and numbers.scan(tmp_path) == []
    assert "unreviewed\tdocs/page.md\t87.3%\tCanny verifies" in (tmp_path / numbers.INVENTORY).read_text()
    # a figure hand-edited on the page is a new number, and its old entry is stale
    (tmp_path / "docs" / "page.md").write_text(page.replace("0.21 px", "0.23 px"))
    new, stale = numbers.scan(tmp_path)
    assert "'0.23 px' is outside" in new and "'docs/page.md\\t0.21 px\\t" in stale and "no longer" in stale


def test_every_number_outside_a_block_is_listed():
    """README.md's and docs/'s measured-looking numbers are made by blocks, or listed in the inventory with their
    class (`python docs/reproduce.py --scan`)."""
    assert numbers.scan(ROOT) == []


def test_no_number_outside_a_block_is_left_unreviewed():
    """Issue 35: every measured number of the docs is a block's, or a definition or a machine's figure beside its
    script; none is listed as measured and not reproduced."""
    rows = [r for r in (ROOT / numbers.INVENTORY).read_text().splitlines() if r and not r.startswith("#")]
    assert [r for r in rows if r.startswith("unreviewed\t")] == []


def test_the_plugin_block_fails_naming_the_install_when_the_plugin_is_missing(monkeypatch, capsys):
    import importlib.metadata

    real = importlib.metadata.version

    def version(dist: str) -> str:
        if dist == numbers.PNP_PLUGIN[0]:
            raise importlib.metadata.PackageNotFoundError(dist)
        return real(dist)

    monkeypatch.setattr(importlib.metadata, "version", version)
    assert numbers.main(["--check", "pnp-sobol"]) == 1
    err = capsys.readouterr().err
    assert "numbers: error: pnp-sobol needs the plug-in package 'wiredsl-pnp', which is not installed: pip install " \
           "./examples/pnp_plugin" in err
    assert "Traceback" not in err


def test_an_example_is_reused_only_when_its_digest_is_the_commands(tmp_path):
    """Context.example reads CI's run of a script when its result's digest is what the script gives the page's
    arguments now; other arguments, or a stale digest, or no result run it again."""
    command = "python examples/closed_loop/drive_to_bin.py --trials 1 --shifts 0 --no-plot"
    ci = tmp_path / "ci" / "loop"
    subprocess.run([sys.executable, *command.split()[1:], "-o", str(ci)], cwd=ROOT, check=True, capture_output=True)
    assert numbers.Context(tmp_path / "ci", tmp_path).example(command, "loop", "closed_loop.json") == ci
    # another --trials than CI ran: not reused (run afresh, into the context's own folder)
    other = command.replace("--trials 1", "--trials 2")
    (tmp_path / "a").mkdir()
    fresh = numbers.Context(tmp_path / "ci", tmp_path / "a").example(other, "loop", "closed_loop.json")
    assert fresh != ci and len(json.loads((fresh / "closed_loop.json").read_text())["rows"]) == 1
    assert json.loads((fresh / "closed_loop.json").read_text())["arguments"]["trials"] == 2
    # a result from another version of the code (its digest differs): not reused either
    doc = json.loads((ci / "closed_loop.json").read_text())
    (ci / "closed_loop.json").write_text(json.dumps({**doc, "digest": "0" * 64}))
    (tmp_path / "b").mkdir()
    assert numbers.Context(tmp_path / "ci", tmp_path / "b").example(command, "loop", "closed_loop.json") != ci
    # none there: run
    (tmp_path / "c").mkdir()
    assert numbers.Context(tmp_path / "ci", tmp_path / "c").example(command, "none", "closed_loop.json") \
        == tmp_path / "c" / "drive_to_bin"
