"""The language server end to end: a real LSP client (pytest-lsp) talks to `wiredsl lsp` over stdio."""

from __future__ import annotations

import json
import re
import shutil
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


@pytest_lsp.fixture(config=ClientServerConfig(server_command=[sys.executable, "-m", "wiredsl", "lsp"]))
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


@pytest.mark.asyncio
async def test_a_real_client_gets_diagnostics_completion_hover_definition_and_formatting(client, tmp_path):
    scenes = tmp_path / "scenes"
    shutil.copytree(ROOT / "scenes", scenes)
    path = scenes / "lab.wd"
    good = path.read_text()
    # Two syntax errors on two lines, both reported.
    bad = good.replace("scene lab", "scene lab )", 1).replace("k 0.02", "k 0.02 @")
    uri = path.as_uri()
    client.text_document_did_open(T.DidOpenTextDocumentParams(T.TextDocumentItem(uri, "wiredsl", 1, bad)))
    await client.wait_for_notification(T.TEXT_DOCUMENT_PUBLISH_DIAGNOSTICS)
    diags = client.diagnostics[uri]
    assert [(d.code, d.range.start.line + 1) for d in diags] == [
        ("E001", bad[: bad.index("scene lab )")].count("\n") + 1), ("E002", bad[: bad.index("@")].count("\n") + 1)]

    # A semantic error: the same code and span as `wiredsl check`.
    wrong = good.replace("place bin as bin1", "place bim as bin1", 1)
    client.text_document_did_change(T.DidChangeTextDocumentParams(
        T.VersionedTextDocumentIdentifier(version=2, uri=uri), [T.TextDocumentContentChangeWholeDocument(wrong)]))
    await client.wait_for_notification(T.TEXT_DOCUMENT_PUBLISH_DIAGNOSTICS)
    (d,) = client.diagnostics[uri]
    start = _pos(wrong, "bim as bin1")
    assert d.code == "E104" and d.range.start == start and "did you mean 'bin'" in d.message

    # An error inside an included file is published against that file.
    (scenes / "models" / "bin.wd").write_text((scenes / "models" / "bin.wd").read_text().replace(
        "between rim base", "between rimm base"))
    client.text_document_did_change(T.DidChangeTextDocumentParams(
        T.VersionedTextDocumentIdentifier(version=3, uri=uri), [T.TextDocumentContentChangeWholeDocument(good)]))
    included = (scenes / "models" / "bin.wd").resolve().as_uri()
    await _until(lambda: included in client.diagnostics)
    assert [x.code for x in client.diagnostics[included]] == ["E104"]
    assert not client.diagnostics[uri]
    (scenes / "models" / "bin.wd").write_text((ROOT / "scenes/models/bin.wd").read_text())
    client.text_document_did_save(T.DidSaveTextDocumentParams(T.TextDocumentIdentifier(uri)))
    await _until(lambda: len(client.diagnostics.get(included, [None])) == 0)  # cleared once fixed

    # Completion: statement keywords at the start of a line in a camera block, names after `place`.
    text = good.replace("  k 0.02\n", "  k 0.02\n  fo\n", 1)
    client.text_document_did_change(T.DidChangeTextDocumentParams(
        T.VersionedTextDocumentIdentifier(version=4, uri=uri), [T.TextDocumentContentChangeWholeDocument(text)]))
    await client.wait_for_notification(T.TEXT_DOCUMENT_PUBLISH_DIAGNOSTICS)
    items = await client.text_document_completion_async(T.CompletionParams(
        T.TextDocumentIdentifier(uri), _pos(text, "  fo\n", 4)))
    labels = {i.label for i in items.items}
    assert {"focal", "pixel", "k2"} <= labels and "line" not in labels
    text = good + "place \n"
    client.text_document_did_change(T.DidChangeTextDocumentParams(
        T.VersionedTextDocumentIdentifier(version=5, uri=uri), [T.TextDocumentContentChangeWholeDocument(text)]))
    await client.wait_for_notification(T.TEXT_DOCUMENT_PUBLISH_DIAGNOSTICS)
    items = await client.text_document_completion_async(T.CompletionParams(
        T.TextDocumentIdentifier(uri), T.Position(text.count("\n") - 1, 6)))
    assert {"bin", "table", "cabinet", "room", "door"} <= {i.label for i in items.items}

    client.text_document_did_change(T.DidChangeTextDocumentParams(
        T.VersionedTextDocumentIdentifier(version=6, uri=uri), [T.TextDocumentContentChangeWholeDocument(good)]))
    await client.wait_for_notification(T.TEXT_DOCUMENT_PUBLISH_DIAGNOSTICS)

    # Hover: a statement's signature and meaning; a pipeline parameter's default.
    h = await client.text_document_hover_async(T.HoverParams(T.TextDocumentIdentifier(uri), _pos(good, "place bin")))
    assert "place <model> as <name>" in h.contents.value and "an instance of a model" in h.contents.value
    h = await client.text_document_hover_async(T.HoverParams(
        T.TextDocumentIdentifier(uri), _pos(good, "lateral_shift range", len("lateral_shift r"))))
    assert "range (default 3 px, the paper's)" in h.contents.value

    # Go to definition: a placement's model lives in an included file; a camera's `like`.
    loc = await client.text_document_definition_async(T.DefinitionParams(
        T.TextDocumentIdentifier(uri), _pos(good, "place bin as", 7)))
    assert loc.uri == (scenes / "models" / "bin.wd").resolve().as_uri()
    model_line = (scenes / "models" / "bin.wd").read_text().splitlines()[loc.range.start.line]
    assert model_line.startswith("model bin")
    loc = await client.text_document_definition_async(T.DefinitionParams(
        T.TextDocumentIdentifier(uri), _pos(good, "like cam_l", 6)))
    assert loc.uri == uri and loc.range.start == _pos(good, "cam_l {")
    loc = await client.text_document_definition_async(T.DefinitionParams(
        T.TextDocumentIdentifier(uri), _pos(good, '"models/bin.wd"', 3)))
    assert loc.uri == (scenes / "models" / "bin.wd").resolve().as_uri()

    # Find references: the camera cam_l is declared once and used by `like` and the rig.
    refs = await client.text_document_references_async(T.ReferenceParams(
        text_document=T.TextDocumentIdentifier(uri), position=_pos(good, "cam_l {"),
        context=T.ReferenceContext(include_declaration=True)))
    assert len(refs) == 1 + good.count("cam_l") - 1  # the declaration and every use

    # Formatting through `wiredsl fmt`.
    messy = good.replace("scene lab", "scene     lab", 1)
    client.text_document_did_change(T.DidChangeTextDocumentParams(
        T.VersionedTextDocumentIdentifier(version=7, uri=uri), [T.TextDocumentContentChangeWholeDocument(messy)]))
    await client.wait_for_notification(T.TEXT_DOCUMENT_PUBLISH_DIAGNOSTICS)
    edits = await client.text_document_formatting_async(T.DocumentFormattingParams(
        T.TextDocumentIdentifier(uri), T.FormattingOptions(tab_size=2, insert_spaces=True)))
    assert len(edits) == 1 and edits[0].new_text == good

    # Outline: models with their features.
    outline = await client.text_document_document_symbol_async(T.DocumentSymbolParams(T.TextDocumentIdentifier(uri)))
    names = {s.name: s for s in outline}
    assert {"room", "cam_l", "head", "floor", "run", "paper", "bin1"} <= set(names)
    assert {c.name for c in names["room"].children} >= {"floor", "ceiling"}


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
