"""The language server end to end: a real LSP client (pytest-lsp) talks to `wiredsl lsp` over stdio."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import pytest_lsp
from lsprotocol import types as T
from pytest_lsp import ClientServerConfig, LanguageClient

from wiredsl import lsp
from wiredsl.diagnostics import WiredslError
from wiredsl.language import ast

ROOT = Path(__file__).resolve().parent.parent


@pytest_lsp.fixture(config=ClientServerConfig(server_command=[sys.executable, "-m", "wiredsl", "lsp"]), scope="module")
async def client(lsp_client: LanguageClient):
    await lsp_client.initialize_session(T.InitializeParams(
        capabilities=pytest_lsp.client_capabilities("visual-studio-code"), root_uri=ROOT.as_uri()))
    yield
    await lsp_client.shutdown_session()


async def _until(condition, seconds: float = 20.0) -> None:
    """Wait for diagnostics to arrive (they are notifications, in no promised order)."""
    import asyncio

    for _ in range(int(seconds / 0.02)):
        if condition():
            return
        await asyncio.sleep(0.02)
    raise AssertionError("the server did not publish the expected diagnostics")


def _pos(text: str, needle: str, offset: int = 0) -> T.Position:
    """The 0-based position of `needle` (plus offset characters) in text."""
    i = text.index(needle) + offset
    line = text.count("\n", 0, i)
    return T.Position(line, i - (text.rfind("\n", 0, i) + 1))


@pytest.fixture
def lab(tmp_path) -> Path:
    """A copy of the lab scene and its includes, free to edit."""
    shutil.copytree(ROOT / "scenes", tmp_path / "scenes")
    return tmp_path / "scenes" / "lab.wd"


async def _open(client: LanguageClient, path: Path, text: str | None = None) -> str:
    """Open a document (its text on disk unless given) and wait for its diagnostics."""
    uri = path.as_uri()
    text = path.read_text() if text is None else text
    client.text_document_did_open(T.DidOpenTextDocumentParams(T.TextDocumentItem(uri, "wiredsl", 1, text)))
    await _until(lambda: uri in client.diagnostics)
    return uri


async def _change(client: LanguageClient, uri: str, text: str, version: int) -> None:
    client.text_document_did_change(T.DidChangeTextDocumentParams(
        T.VersionedTextDocumentIdentifier(version=version, uri=uri), [T.TextDocumentContentChangeWholeDocument(text)]))
    await client.wait_for_notification(T.TEXT_DOCUMENT_PUBLISH_DIAGNOSTICS)


async def _hover(client: LanguageClient, uri: str, text: str, needle: str, offset: int = 0) -> str | None:
    h = await client.text_document_hover_async(T.HoverParams(T.TextDocumentIdentifier(uri), _pos(text, needle, offset)))
    return h.contents.value if h else None


@pytest.mark.asyncio(loop_scope="module")
async def test_syntax_errors_on_two_lines_are_both_published(client, lab):
    bad = lab.read_text().replace("scene lab", "scene lab )", 1).replace("k 0.02", "k 0.02 @")
    uri = await _open(client, lab, bad)
    assert [(d.code, d.range.start.line + 1) for d in client.diagnostics[uri]] == [
        ("E001", bad[: bad.index("scene lab )")].count("\n") + 1), ("E002", bad[: bad.index("@")].count("\n") + 1)]


@pytest.mark.asyncio(loop_scope="module")
async def test_a_semantic_error_has_the_code_and_span_of_check(client, lab):
    wrong = lab.read_text().replace("place bin as bin1", "place bim as bin1", 1)
    uri = await _open(client, lab, wrong)
    (d,) = client.diagnostics[uri]
    assert d.code == "E104" and d.range.start == _pos(wrong, "bim as bin1") and "did you mean 'bin'" in d.message


@pytest.mark.asyncio(loop_scope="module")
async def test_an_error_in_an_included_file_is_published_against_that_file_and_cleared(client, lab):
    model = lab.parent / "models" / "bin.wd"
    good = model.read_text()
    model.write_text(good.replace("between rim base", "between rimm base"))
    uri = await _open(client, lab)
    included = model.resolve().as_uri()
    await _until(lambda: included in client.diagnostics)
    assert [x.code for x in client.diagnostics[included]] == ["E104"] and not client.diagnostics[uri]
    model.write_text(good)
    client.text_document_did_save(T.DidSaveTextDocumentParams(T.TextDocumentIdentifier(uri)))
    await _until(lambda: len(client.diagnostics.get(included, [None])) == 0)


@pytest.mark.asyncio(loop_scope="module")
async def test_completion_offers_a_blocks_keywords_and_declared_names(client, lab):
    good = lab.read_text()
    text = good.replace("  k 0.02\n", "  k 0.02\n  fo\n", 1) + "place \n"
    uri = await _open(client, lab, text)
    items = await client.text_document_completion_async(T.CompletionParams(
        T.TextDocumentIdentifier(uri), _pos(text, "  fo\n", 4)))
    labels = {i.label for i in items.items}
    assert {"focal", "pixel", "k2"} <= labels and "line" not in labels
    items = await client.text_document_completion_async(T.CompletionParams(
        T.TextDocumentIdentifier(uri), T.Position(text.count("\n") - 1, 6)))
    assert {"bin", "table", "cabinet", "room", "door"} <= {i.label for i in items.items}


@pytest.mark.asyncio(loop_scope="module")
async def test_hover_on_a_keyword_and_a_pipeline_parameter(client, lab):
    good = lab.read_text()
    uri = await _open(client, lab)
    h = await _hover(client, uri, good, "place bin")
    assert "place <model> as <name>" in h and "an instance of a model" in h
    assert "range (default 3 px, the paper's)" in await _hover(client, uri, good, "lateral_shift range",
                                                                len("lateral_shift r"))


@pytest.mark.asyncio(loop_scope="module")
async def test_hover_on_every_kind_of_declared_name_shows_its_declaration(client, lab):
    """Issue 15: every hover on a name answered -32603 (AttributeError); now each shows where and what."""
    good = lab.read_text()
    uri = await _open(client, lab)
    cases = [  # (text under the cursor, offset into it, what the hover names, the declaring file and line)
        ("model room {", 6, "model `room`", "lab.wd", "model room {"),
        ("place room as walls", 14, "place `walls`", "lab.wd", "place room as walls"),
        ("place room as", 6, "model `room`", "lab.wd", "model room {"),
        ("camera cam_l {", 7, "camera `cam_l`", "lab.wd", "camera cam_l {"),
        ("like cam_l", 5, "camera `cam_l`", "lab.wd", "camera cam_l {"),
        ("left cam_l", 5, "camera `cam_l`", "lab.wd", "camera cam_l {"),
        ("rig head", 4, "rig `head`", "lab.wd", "rig head {"),
        ("viewpoints floor", 11, "viewpoints `floor`", "lab.wd", "viewpoints floor {"),
        ("path run", 5, "path `run`", "lab.wd", "path run {"),
        ("pipeline paper", 9, "pipeline `paper`", "lab.wd", "pipeline paper default {"),
        ("polyline floor closed", 9, "polyline `room.floor`", "lab.wd", "polyline floor closed through"),
        ("joins floor corner_ne", 6, "polyline `room.floor`", "lab.wd", "polyline floor closed through"),
        # Declared in an included file: the hover quotes that file's line.
        ("place bin as bin1", 6, "model `bin`", "models/bin.wd", "model bin {"),
        ("place shade as", 6, "model `shade`", "models/bin.wd", "model shade {"),
    ]
    for needle, offset, what, file, line in cases:
        h = await _hover(client, uri, good, needle, offset)
        assert h is not None, needle
        lines = (lab.parent / file).read_text().splitlines()
        row = next(i for i, x in enumerate(lines, 1) if x.strip().startswith(line))
        assert h.startswith(f"{what}, declared at ") and f"/scenes/{file}:{row}:" in h, (needle, h)
        assert f"```wiredsl\n{line}" in h, (needle, h)


@pytest.mark.asyncio(loop_scope="module")
async def test_hover_on_an_ellipse_named_by_a_silhouette(client, lab):
    model = lab.parent / "models" / "bin.wd"
    text = model.read_text()
    uri = await _open(client, model)
    h = await _hover(client, uri, text, "between rim", len("between r"))
    assert "ellipse `bin.rim`" in h and "ellipse rim centre (0, 0, 0.6)" in h


@pytest.mark.asyncio(loop_scope="module")
async def test_definition_of_a_model_a_camera_and_an_include(client, lab):
    good = lab.read_text()
    uri = await _open(client, lab)
    loc = await client.text_document_definition_async(T.DefinitionParams(
        T.TextDocumentIdentifier(uri), _pos(good, "place bin as", 7)))
    model = lab.parent / "models" / "bin.wd"
    assert loc.uri == model.resolve().as_uri()
    assert model.read_text().splitlines()[loc.range.start.line].startswith("model bin")
    loc = await client.text_document_definition_async(T.DefinitionParams(
        T.TextDocumentIdentifier(uri), _pos(good, "like cam_l", 6)))
    assert loc.uri == uri and loc.range.start == _pos(good, "cam_l {")
    loc = await client.text_document_definition_async(T.DefinitionParams(
        T.TextDocumentIdentifier(uri), _pos(good, '"models/bin.wd"', 3)))
    assert loc.uri == model.resolve().as_uri()


@pytest.mark.asyncio(loop_scope="module")
async def test_references_of_a_camera_are_its_declaration_and_every_use(client, lab):
    good = lab.read_text()
    uri = await _open(client, lab)
    refs = await client.text_document_references_async(T.ReferenceParams(
        text_document=T.TextDocumentIdentifier(uri), position=_pos(good, "cam_l {"),
        context=T.ReferenceContext(include_declaration=True)))
    assert sorted(r.range.start.line for r in refs) == [
        i for i, line in enumerate(good.splitlines()) if "cam_l" in line and not line.startswith("#")]


@pytest.mark.asyncio(loop_scope="module")
async def test_formatting_gives_the_canonical_file(client, lab):
    good = lab.read_text()
    uri = await _open(client, lab, good.replace("scene lab", "scene     lab", 1))
    edits = await client.text_document_formatting_async(T.DocumentFormattingParams(
        T.TextDocumentIdentifier(uri), T.FormattingOptions(tab_size=2, insert_spaces=True)))
    assert len(edits) == 1 and edits[0].new_text == good


@pytest.mark.asyncio(loop_scope="module")
async def test_outline_lists_declarations_with_their_features(client, lab):
    uri = await _open(client, lab)
    outline = await client.text_document_document_symbol_async(T.DocumentSymbolParams(T.TextDocumentIdentifier(uri)))
    names = {s.name: s for s in outline}
    assert {"room", "cam_l", "head", "floor", "run", "paper", "walls"} <= set(names)
    assert {c.name for c in names["room"].children} >= {"floor", "ceiling"}


@pytest.mark.asyncio(loop_scope="module")
async def test_requests_for_documents_never_opened_are_answered_empty(client, tmp_path):
    """Found by fuzzing the server: pygls read any other URI from disk, failing for a missing file (-32603)
    and without bound for file:///dev/zero."""
    for uri in ((tmp_path / "nothere.wd").as_uri(), "file:///dev/zero"):
        doc, at = T.TextDocumentIdentifier(uri), T.Position(0, 1)
        assert await client.text_document_hover_async(T.HoverParams(doc, at)) is None
        assert await client.text_document_completion_async(T.CompletionParams(doc, at)) is None
        assert await client.text_document_formatting_async(T.DocumentFormattingParams(
            doc, T.FormattingOptions(tab_size=2, insert_spaces=True))) is None
        client.text_document_did_save(T.DidSaveTextDocumentParams(doc))
    assert await client.text_document_hover_async(T.HoverParams(doc, at)) is None  # still serving


def _lsp_process(stdin: bytes) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "wiredsl", "lsp"], input=stdin, capture_output=True, timeout=60)


def _message(obj: dict) -> bytes:
    body = json.dumps(obj).encode()
    return b"Content-Length: %d\r\n\r\n" % len(body) + body


INITIALIZE = _message({"jsonrpc": "2.0", "id": 1, "method": "initialize",
                       "params": {"processId": None, "rootUri": None, "capabilities": {}}})


def test_absurd_headers_neither_exhaust_memory_nor_stop_the_server():
    """Issue 15: `Content-Length: 99999999999` was a MemoryError. Garbage headers are ignored, the next
    message is answered; a length over the limit is skipped without being held in memory."""
    garbage = b"".join(h + b"\r\n\r\n{}\r\n" for h in (
        b"Content-Length: -5", b"Content-Length: 1e9", b"Content-Length: \xff\xfe", b"X" * 200_000))
    done = _lsp_process(garbage + INITIALIZE + b"Content-Length: 99999999999\r\n\r\n{}")
    assert done.returncode == 0, done.stderr
    assert b'"id": 1' in done.stdout and b'"capabilities"' in done.stdout, done.stdout[:300]
    assert b"Traceback" not in done.stderr and b"MemoryError" not in done.stderr
    assert b"skipping a message of 99,999,999,999 bytes, over the limit of 16,777,216" in done.stderr


def test_a_message_over_the_limit_is_skipped_and_the_next_one_answered():
    big = lsp.MAX_MESSAGE_BYTES + 10
    bye = _message({"jsonrpc": "2.0", "id": 2, "method": "shutdown"}) + _message({"jsonrpc": "2.0", "method": "exit"})
    done = _lsp_process(b"Content-Length: %d\r\n\r\n" % big + b" " * big + INITIALIZE + bye)
    assert b'"id": 1' in done.stdout and b'"capabilities"' in done.stdout, done.stdout[:300]
    assert b'"id": 2' in done.stdout
    # exit ends it cleanly; stderr says what was skipped (pygls adds that it ignored the stand-in), no error
    err = done.stderr.decode()
    assert done.returncode == 0 and err.startswith(
        "wiredsl lsp: skipping a message of 16,777,226 bytes, over the limit of 16,777,216\n"), err
    assert "Traceback" not in err and "error" not in err.lower(), err


def test_check_reports_every_syntax_error_of_a_file():
    text = "wiredsl 1\nscene a )\nmodel m {\n  line a from (0, 0, 0) to (1, 0, 0) }\n}\nscene @\n"
    with pytest.raises(WiredslError) as err:
        ast.parse_text(text, "t.wd")
    assert [(d.code, d.span.line, d.span.col) for d in err.value.diagnostics] == [
        ("E001", 2, 9), ("E001", 5, 1), ("E002", 6, 7)]


def test_a_file_without_syntax_errors_parses_as_before():
    for path in sorted((ROOT / "scenes").rglob("*.wd")):
        assert ast.parse_text(path.read_text(), str(path)).statements


def test_the_textmate_grammar_is_generated_from_the_statement_table():
    committed = json.loads((ROOT / "editors" / "wiredsl.tmLanguage.json").read_text())
    regenerate = "wiredsl lsp --print-grammar > editors/wiredsl.tmLanguage.json"
    assert committed == lsp.textmate_grammar(), regenerate

    keywords = next(p["match"] for p in committed["patterns"] if p["name"].startswith("keyword.control"))
    for word in ("camera", "silhouette", "edge_loss", "straight"):
        assert re.search(keywords, "  " + word + " x")
    assert not re.search(keywords, "  cameras x")


def test_completion_contexts_are_read_from_braces_even_in_broken_text():
    text = "model m {\n  line a from (0, 0, 0) to (1\n  \n}\ncamera c {\n  \n"
    assert lsp.context_at(text, 3) == ("model", "m")
    assert lsp.context_at(text, 6) == ("camera", "c")
    assert lsp.context_at(text, 5) == ("top", None)


def test_positions_count_lines_as_the_lexer_does():
    """A comment holding U+2028 is not a line break: contexts and completions stay on the right line."""
    text = "# a\u2028b\nmodel m {\n  \n}\n"
    assert lsp.context_at(text, 3) == ("model", "m")
    assert {c.label for c in lsp.completions(None, text, 3, 3)} >= {"line", "ellipse"}


def _readme_lua(marker: str) -> str:
    """The editor page's Neovim snippet that contains `marker` (docs/how-to/editor.md)."""
    blocks = re.findall(r"```lua\n(.*?)```", (ROOT / "docs/how-to/editor.md").read_text(), re.S)
    (block,) = [b for b in blocks if marker in b]
    return block


_NVIM_REPORT = """
function WiredslTestReport(out)
  local ok = vim.wait(60000, function() return #vim.diagnostic.get(0) > 0 end, 50)
  local lines = {}
  for _, d in ipairs(vim.diagnostic.get(0)) do
    table.insert(lines, string.format("%d:%d:%s", d.lnum + 1, d.col + 1, tostring(d.code)))
  end
  if not ok then table.insert(lines, "timeout") end
  vim.fn.writefile(lines, out)
  vim.cmd("qa!")
end
"""


def _nvim_version() -> tuple[int, ...] | None:
    nvim = shutil.which("nvim")
    if nvim is None:
        return None
    first = subprocess.run([nvim, "--version"], capture_output=True, text=True, timeout=30).stdout.split("\n")[0]
    return tuple(int(x) for x in re.search(r"v(\d+)\.(\d+)\.(\d+)", first).groups())


@pytest.mark.parametrize("marker, needs", [("vim.lsp.start_client", (0, 7)), ("vim.lsp.start(", (0, 10))],
                         ids=["neovim-0.7-to-0.9", "neovim-0.10"])
def test_the_readmes_neovim_snippet_gets_diagnostics_from_the_real_server(tmp_path, marker, needs):
    version = _nvim_version()
    if version is None:
        pytest.skip("nvim is not installed (CI installs it with apt-get where it can: Debian 12 gives 0.7.2)")
    if version < needs:
        pytest.skip(f"this snippet needs Neovim {'.'.join(map(str, needs))} or later; nvim here is "
                    f"{'.'.join(map(str, version))}")
    (tmp_path / "init.lua").write_text(_readme_lua(marker) + _NVIM_REPORT)
    (tmp_path / "s.wd").write_text("wiredsl 1\nmodel m {\n  line a from (0, 0, 0) to (0, 0, 0)\n}\n")
    home = tmp_path / "home"  # Neovim's state, cache and logs stay in the test's folder
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
           **{k: str(home) for k in ("XDG_CONFIG_HOME", "XDG_DATA_HOME", "XDG_STATE_HOME", "XDG_CACHE_HOME")}}
    subprocess.run(["nvim", "--headless", "-u", "init.lua", "-i", "NONE", "-n", "s.wd",
                    "-c", 'lua WiredslTestReport("out.txt")'], cwd=tmp_path, env=env, timeout=120,
                   capture_output=True)
    assert (tmp_path / "out.txt").read_text().split() == ["3:3:E120"]
