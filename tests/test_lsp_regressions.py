"""The frames the fuzz campaign saved (tests/fuzz_regressions/lsp/) replayed to a real `wiredsl lsp`: no
internal error (-32603) in any answer, the server alive, a valid request answered after them, and a clean exit."""

from __future__ import annotations

import re
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

pytest.importorskip("pygls")
from fuzz_campaign import Reader, _ask, _send  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
FRAMES = sorted((ROOT / "tests" / "fuzz_regressions" / "lsp").glob("*.frames"))


def complete(data: bytes) -> bytes:
    """The frames up to the last one whose declared body is all there: the campaign saved each batch as sent,
    up to the frame after which the server went wrong, and a body cut short (or declared 99999999999 bytes
    long) would rightly swallow the valid request this test sends after it."""
    i = end = 0
    while (m := re.match(rb"((?:[^\r\n]*\r\n)*?)\r\n", data[i:])) is not None:
        j = i + m.end()
        length = re.search(rb"Content-Length:\s*(-?\d+)\s*(?:\r\n|$)", m.group(1) + b"\r\n")
        n = int(length.group(1)) if length else -1
        if n < 0:  # no usable length: the server skips the header block alone
            i = end = j
            continue
        if j + n > len(data):
            break
        i = end = j + n
    return data[:end]


def _said(proc, errlog) -> str:
    """Why the server did not answer, for the failure's message: whether it is still running, and its stderr."""
    errlog.seek(0)
    return f"server {'running' if proc.poll() is None else f'exited {proc.returncode}'}; stderr: " + \
        errlog.read().decode(errors="replace")[-3000:]


@pytest.mark.parametrize("frames", FRAMES, ids=[f.stem for f in FRAMES])
def test_saved_frames_leave_the_server_answering(frames):
    errlog = tempfile.TemporaryFile()
    proc = subprocess.Popen([sys.executable, "-m", "wiredsl", "lsp"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=errlog, cwd=ROOT)
    reader = Reader(proc)
    try:
        init, _ = _ask(proc, reader, 0, "initialize", {"processId": None, "rootUri": None, "capabilities": {}}, 60)
        assert init is not None and "result" in init, _said(proc, errlog)
        _send(proc, {"jsonrpc": "2.0", "method": "initialized", "params": {}})
        lab = ROOT / "scenes" / "lab.wd"
        _send(proc, {"jsonrpc": "2.0", "method": "textDocument/didOpen", "params": {"textDocument": {
            "uri": lab.as_uri(), "languageId": "wiredsl", "version": 1, "text": lab.read_text()}}})
        sent = complete(frames.read_bytes())
        proc.stdin.write(sent)
        proc.stdin.flush()
        if b'"method": "shutdown"' in sent:  # a client asked it to shut down: it then takes only `exit`
            _send(proc, {"jsonrpc": "2.0", "method": "exit"})
            assert proc.wait(timeout=60) == 0
            internal = [m for m in reader.drain(0.5) if (m.get("error") or {}).get("code") == -32603]
            assert not internal, internal[:3]
            return
        answer, seen = _ask(proc, reader, 10**9, "textDocument/hover", {
            "textDocument": {"uri": lab.as_uri()}, "position": {"line": 21, "character": 9}}, 90)
        assert answer is not None, "no answer to a valid request after the saved frames; " + _said(proc, errlog)
        internal = [m for m in seen + [answer] if (m.get("error") or {}).get("code") == -32603]
        assert not internal, internal[:3]
        done, _ = _ask(proc, reader, 10**9 + 1, "shutdown", None, 30)
        assert done is not None
        _send(proc, {"jsonrpc": "2.0", "method": "exit"})
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
