"""A bounded fuzzing campaign (not part of the default suite): the language, `validate`, `wiredsl.load`, builds
of small scenes and the language server's input. Counts exit 3 (internal errors), hangs (an input taking longer
than its time limit), non-finite outputs and leaked numpy RuntimeWarnings; keeps every finding's input.

    nice -n 10 python tests/fuzz_campaign.py --budget 25000 --minutes 40 --out /tmp/fuzz

Each part draws from the strategies of tests/test_fuzz.py (hypothesis, not derandomised) or mutates real
dumps; `--seed` makes the byte mutations repeatable. Findings are written as files in --out, one per input,
with a summary.json; the exit status is 1 when anything was found.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
import traceback
import warnings
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from click.testing import CliRunner  # noqa: E402
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from wiredsl.cli import main  # noqa: E402


class Hang(Exception):
    pass


def _alarm(signum, frame):
    raise Hang


class Campaign:
    def __init__(self, out: Path, deadline: float):
        self.out = out
        self.deadline = deadline
        self.counts: Counter[str] = Counter()
        self.findings: list[dict] = []
        out.mkdir(parents=True, exist_ok=True)

    def expired(self) -> bool:
        return time.monotonic() > self.deadline

    def found(self, part: str, kind: str, data: bytes | str, detail: str) -> None:
        name = f"{part}-{kind}-{len(self.findings):04d}"
        raw = data.encode("utf-8", "surrogatepass") if isinstance(data, str) else data
        (self.out / name).write_bytes(raw)
        self.findings.append({"part": part, "kind": kind, "file": name, "detail": detail[-2000:]})
        self.counts[f"{part}:{kind}"] += 1
        print(f"FOUND {part} {kind}: {detail.strip().splitlines()[-1][:200] if detail.strip() else ''}",
              file=sys.stderr, flush=True)

    def invoke(self, part: str, args: list[str], data: bytes | str, seconds: int = 20):
        """CliRunner in-process with a time limit, RuntimeWarnings raised; classifies the result."""
        self.counts[f"{part}:inputs"] += 1
        signal.signal(signal.SIGALRM, _alarm)
        signal.alarm(seconds)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error", RuntimeWarning)
                r = CliRunner().invoke(main, args, catch_exceptions=True)
        except Hang:
            self.found(part, "hang", data, " ".join(args))
            return None
        finally:
            signal.alarm(0)
        if isinstance(r.exception, Hang):
            self.found(part, "hang", data, " ".join(args))
            return None
        if r.exit_code not in (0, 1, 2) or "internal error" in r.output or "Traceback" in r.output:
            kind = "warning" if "RuntimeWarning" in r.output or isinstance(r.exception, RuntimeWarning) else "exit3"
            tb = "".join(traceback.format_exception(r.exception)) if r.exception else ""
            self.found(part, kind, data, f"{' '.join(args)} -> exit {r.exit_code}\n{r.output}\n{tb}")
            return None
        if "NaN" in r.stdout or "Infinity" in r.stdout:
            with contextlib.suppress(ValueError):
                json.loads(r.stdout, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
                return r
            self.found(part, "nonfinite", data, " ".join(args) + "\n" + r.stdout[:2000])
        return r


def fuzz_settings(n: int):
    return settings(max_examples=n, deadline=None, database=None, suppress_health_check=list(HealthCheck))


# --------------------------------------------------------------------------- the language

def language(c: Campaign, n: int, work: Path) -> None:
    import test_fuzz as tf

    f = work / "_fuzz.wd"

    def run(text: str) -> None:
        if c.expired():
            return
        f.write_text(text, encoding="utf-8", errors="surrogatepass")
        for cmd in (["check"], ["compile"], ["fmt", "--check"]):
            c.invoke("language", [*cmd, "--diagnostics", "json", str(f)], text)

    given(text=st.one_of(tf.generated_scene(), tf.mutated_scene()))(fuzz_settings(n)(lambda text: run(text)))()


def builds(c: Campaign, n: int, work: Path) -> None:
    """Small scenes with extreme values, built with effects (RuntimeWarnings count as findings)."""
    import test_fuzz as tf

    f = work / "_small.wd"
    pipe = ("pipeline all {\n calibration_error sigma 0.05\n edge_loss fraction 30%\n lateral_shift range 3px\n"
            " approx_error sigma 0.5px\n}\n")

    def run(text: str, effects: bool) -> None:
        if c.expired():
            return
        f.write_text(text + (pipe if effects else ""), encoding="utf-8")
        out = Path(tempfile.mkdtemp(dir=work))
        r = c.invoke("build", ["build", str(f), "-o", str(out), "--no-svg", "--seed", "1", "--trials", "2",
                               "--format", "jsonl", *([] if effects else ["--no-effects"])], text, seconds=60)
        if r is not None and r.exit_code == 0:
            for line in (out / "features.jsonl").read_text().splitlines():
                try:
                    json.loads(line, parse_constant=lambda k: (_ for _ in ()).throw(ValueError(k)))
                except ValueError:
                    c.found("build", "nonfinite", text, line[:2000])
                    break

    given(text=tf.small_scene(), effects=st.booleans())(fuzz_settings(n)(lambda text, effects: run(text, effects)))()


# --------------------------------------------------------------------------- validate and load

def _dumps(work: Path) -> dict[str, bytes]:
    out = work / "dumps"
    for fmt in ("json", "jsonl", "npz"):
        r = CliRunner().invoke(main, ["build", str(ROOT / "scenes/lab.wd"), "--pose", "0", "--pose", "3",
                                      "--trials", "1" if fmt == "json" else "2", "--seed", "3", "--no-svg",
                                      "--format", fmt, "-o",
                                      str(out / fmt)])
        assert r.exit_code == 0, r.output
    files = {f"features.{fmt}": (out / fmt / f"features.{fmt}").read_bytes() for fmt in ("json", "jsonl", "npz")}
    files["manifest.json"] = (out / "json" / "manifest.json").read_bytes()
    return files


def _mutate_text(rng: random.Random, text: str) -> str:
    ops = rng.randint(1, 4)
    for _ in range(ops):
        op = rng.choice(["number", "truncate", "delete", "nest", "token", "dup", "key"])
        if op == "number":
            import re
            nums = list(re.finditer(r"-?\d+(\.\d+)?([eE][-+]?\d+)?", text))
            if nums:
                m = rng.choice(nums)
                new = rng.choice(["NaN", "Infinity", "-Infinity", "1e999", "-1e999", "1e308", "5e-324", "-0",
                                  "99999999999999999999", "\"x\"", "null", "true", "[]", "{}", "1.5", "-1"])
                text = text[:m.start()] + new + text[m.end():]
        elif op == "truncate":
            text = text[:rng.randint(0, len(text))]
        elif op == "delete":
            i = rng.randint(0, max(len(text) - 1, 0))
            text = text[:i] + text[i + rng.randint(1, 50):]
        elif op == "nest":
            depth = rng.choice([10, 500, 5000, 50000])
            i = rng.randint(0, len(text))
            text = text[:i] + "[" * depth + "1" + "]" * depth + text[i:]
        elif op == "token":
            i = rng.randint(0, len(text))
            text = text[:i] + rng.choice([",", "}", "]", "\"", ":", "\\u0000", "\x00", "\ud800", "\n"]) + text[i:]
        elif op == "dup":
            i, j = sorted(rng.randint(0, len(text)) for _ in range(2))
            text = text[:j] + text[i:j] + text[j:]
        else:
            text = text.replace(rng.choice(["\"document\"", "\"poses\"", "\"left\"", "\"points\"", "\"camera\"",
                                            "\"trial\"", "\"index\""]), rng.choice(["\"x\"", "\"\"", "1"]), 1)
    return text


def _mutate_npz(rng: random.Random, raw: bytes) -> bytes:
    import io
    import zipfile

    import numpy as np

    op = rng.choice(["bytes", "member", "member", "truncate"])
    if op == "bytes":
        b = bytearray(raw)
        for _ in range(rng.randint(1, 20)):
            b[rng.randrange(len(b))] = rng.randrange(256)
        return bytes(b)
    if op == "truncate":
        return raw[:rng.randint(0, len(raw))]
    z = zipfile.ZipFile(io.BytesIO(raw))
    names = z.namelist()
    victim = rng.choice(names)
    arrays = {n: np.load(io.BytesIO(z.read(n)), allow_pickle=False) for n in names}
    a = arrays[victim]
    choice = rng.choice(["nan", "shape", "dtype", "drop", "huge", "header", "object", "empty", "neg"])
    buf = io.BytesIO()
    if choice == "nan" and a.dtype.kind == "f" and a.size:
        a = a.copy()
        a.flat[rng.randrange(a.size)] = rng.choice([np.nan, np.inf, -np.inf, 1e300])
    elif choice == "shape" and a.size:
        a = a.reshape(-1)[: max(a.size - 1, 0)]
    elif choice == "dtype":
        a = a.astype(rng.choice(["float16", "int8", "uint64", "complex64", "U3"]), copy=False) \
            if a.dtype.kind in "fiu" else np.zeros(3)
    elif choice == "drop":
        del arrays[victim]
        victim = None
    elif choice == "huge" and a.dtype.kind in "iu" and a.size:
        a = a.copy()
        a.flat[rng.randrange(a.size)] = rng.choice([np.iinfo(a.dtype).max, -1, 10**6])
    elif choice == "neg" and a.dtype.kind in "iu" and a.size:
        a = a.copy()
        a.flat[rng.randrange(a.size)] = -rng.randint(1, 100) if a.dtype.kind == "i" else 0
    elif choice == "empty":
        a = a[:0] if a.ndim else a
    elif choice == "object":
        np.save(buf, np.array([{"x": 1}], dtype=object), allow_pickle=True)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as w:
        for n, arr in arrays.items():
            if n == victim and choice == "object":
                w.writestr(n, buf.getvalue())
            elif n == victim and choice == "header":
                b = io.BytesIO()
                np.save(b, arr)
                data = bytearray(b.getvalue())
                for _ in range(3):
                    data[rng.randrange(8, min(len(data), 120))] = rng.randrange(32, 127)
                w.writestr(n, bytes(data))
            else:
                b = io.BytesIO()
                np.save(b, a if n == victim else arr)
                w.writestr(n, b.getvalue())
    return out.getvalue()


def validate(c: Campaign, n: int, work: Path, seed: int) -> None:
    import wiredsl

    rng = random.Random(seed)
    dumps = _dumps(work)
    for i in range(n):
        if c.expired():
            return
        name = rng.choice(sorted(dumps))
        raw = dumps[name]
        data = _mutate_npz(rng, raw) if name.endswith(".npz") else \
            _mutate_text(rng, raw.decode()).encode("utf-8", "surrogatepass")
        f = work / f"v{i % 7}_{name}"
        f.write_bytes(data)
        c.invoke("validate", ["validate", str(f)], data)
        c.counts["load:inputs"] += 1
        signal.signal(signal.SIGALRM, _alarm)
        signal.alarm(20)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error", RuntimeWarning)
                records = wiredsl.load(f)
            for r in records:  # load passes a JSON dump's values through: look at whatever lists there are
                pts = r.get("points") if isinstance(r.get("points"), list) else []
                for v in pts + [r.get("at") if isinstance(r.get("at"), list) else []]:
                    if isinstance(v, list) and any(isinstance(x, float) and not math.isfinite(x) for x in v):
                        c.found("load", "nonfinite", data, str(r)[:500])
                        break
        except Hang:
            c.found("load", "hang", data, name)
        except (ValueError, OSError, KeyError, EOFError) as exc:  # a clear refusal of a damaged dump
            # KeyError / JSONDecodeError name what is missing; anything else is a finding
            if type(exc).__name__ not in ("JSONDecodeError", "NpzError", "DumpError", "ValueError",
                                          "UnicodeDecodeError", "KeyError", "BadZipFile", "OSError", "EOFError"):
                c.found("load", "exception", data, traceback.format_exc())
            else:
                c.counts[f"load:refused:{type(exc).__name__}"] += 1
        except Exception:  # noqa: BLE001
            c.found("load", "exception", data, traceback.format_exc())
        finally:
            signal.alarm(0)


# --------------------------------------------------------------------------- the language server

def _frame(body: bytes) -> bytes:
    return b"Content-Length: %d\r\n\r\n" % len(body) + body


class Reader:
    """The server's messages: a thread drains its stdout all the time (a server blocked writing a long answer
    would otherwise stop reading its input, and the campaign's writes would block: a hang of the harness)."""

    def __init__(self, proc):
        import queue
        import threading

        self.proc, self.messages = proc, queue.Queue()

        def pump():
            buf = b""
            while chunk := os.read(proc.stdout.fileno(), 1 << 16):
                buf += chunk
                while b"\r\n\r\n" in buf:
                    head, rest = buf.split(b"\r\n\r\n", 1)
                    length = int(head.split(b"Content-Length:")[1].split(b"\r\n")[0])
                    if len(rest) < length:
                        break
                    self.messages.put(json.loads(rest[:length]))
                    buf = rest[length:]

        threading.Thread(target=pump, daemon=True).start()

    def next(self, seconds: float) -> dict | None:
        import queue

        try:
            return self.messages.get(timeout=max(seconds, 1e-3))
        except queue.Empty:
            return None

    def drain(self, seconds: float = 0.0) -> list[dict]:
        out = []
        while (m := self.next(seconds)) is not None:
            out.append(m)
        return out


def _send(proc, msg: dict) -> None:
    proc.stdin.write(_frame(json.dumps(msg).encode()))
    proc.stdin.flush()


def _ask(proc, reader: Reader, req_id: int, method: str, params: dict, seconds: float = 15.0):
    """(the answer or None, the other messages read meanwhile)."""
    _send(proc, {"jsonrpc": "2.0", "id": req_id, "method": method, "params": params})
    end = time.monotonic() + seconds
    seen = []
    while time.monotonic() < end:
        msg = reader.next(end - time.monotonic())
        if msg is None:
            break
        if msg.get("id") == req_id:
            return msg, seen
        seen.append(msg)
    return None, seen


def _random_frame(rng: random.Random, uri: str, text: str) -> bytes:
    methods = ["textDocument/hover", "textDocument/completion", "textDocument/definition", "textDocument/references",
               "textDocument/formatting", "textDocument/documentSymbol", "textDocument/didChange",
               "textDocument/didOpen", "workspace/symbol", "$/cancelRequest", "nonsense/method", "shutdown"]
    kind = rng.random()
    if kind < 0.03:  # a broken frame
        return rng.choice([b"Content-Length: 99999999999\r\n\r\n{}", b"Content-Length: -5\r\n\r\n",
                           b"Content-Length: abc\r\n\r\n{}", b"Garbage\r\n\r\n",
                           b"Content-Length: 10\r\n\r\n{\"a\":", _frame(b"not json"), _frame(b"[]"),
                           _frame(b"null"), _frame(bytes(rng.randrange(256) for _ in range(20))),
                           _frame(b'{"jsonrpc": "2.0", "id": 1}')])
    method = rng.choice(methods[:-1] if rng.random() < 0.98 else methods)
    pos = {"line": rng.choice([0, 1, 5, 20, -1, 10**9, rng.randint(0, 60)]),
           "character": rng.choice([0, 3, 12, -1, 10**9, rng.randint(0, 80)])}
    doc = {"uri": rng.choice([uri, uri, "file:///nonexistent/x.wd", "not a uri", ""])}
    params: object
    if method == "textDocument/didChange":
        t = list(text)
        for _ in range(rng.randint(1, 8)):
            i = rng.randint(0, len(t))
            t[i:i + rng.randint(0, 5)] = rng.choice(["{", "}", "(", ")", "\n", "include \"", "1e999", "", "\0", "é"])
        params = {"textDocument": {**doc, "version": rng.randint(2, 10**6)},
                  "contentChanges": [{"text": "".join(t)}]}
    elif method == "textDocument/didOpen":
        params = {"textDocument": {**doc, "languageId": "wiredsl", "version": 1, "text": text}}
    else:
        params = {"textDocument": doc, "position": pos, "context": {"includeDeclaration": True},
                  "options": {"tabSize": 2, "insertSpaces": True}, "query": "", "id": 3}
    if rng.random() < 0.15:  # wrong types
        params = rng.choice([None, [], "x", 1, {"textDocument": 5}, {"position": "x"}])
    msg = {"jsonrpc": "2.0", "method": method, "params": params}
    if not method.startswith("textDocument/did") and method != "$/cancelRequest":
        msg["id"] = rng.randint(1000, 10**6)
    return _frame(json.dumps(msg).encode())


BROKEN = (b"Content-Length: 99999999999", b"Content-Length: -5", b"Content-Length: abc", b"Garbage",
          b"Content-Length: 10\r\n")  # frames after which the stream is out of step: the session ends there


def language_server(c: Campaign, n: int, work: Path, seed: int) -> None:
    """Random JSON-RPC frames to a real `wiredsl lsp`, 200 a session; every answer is read, an internal error
    (-32603) is a finding, and after each session a valid request must still be answered."""
    rng = random.Random(seed)
    scenes = work / "lsp_scenes"
    if not scenes.exists():
        import shutil
        shutil.copytree(ROOT / "scenes", scenes)
    uri = (scenes / "lab.wd").as_uri()
    text = (scenes / "lab.wd").read_text()
    sent = 0
    while sent < n and not c.expired():
        errlog = tempfile.TemporaryFile()  # pygls logs every error it answers: a pipe would fill and block it
        proc = subprocess.Popen([sys.executable, "-m", "wiredsl", "lsp"], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=errlog)
        reader = Reader(proc)
        try:
            init, _ = _ask(proc, reader, 0, "initialize", {"processId": None, "rootUri": None, "capabilities": {}},
                           60)
            if init is None:
                c.found("lsp", "hang", b"initialize", "no answer to initialize")
                return
            _send(proc, {"jsonrpc": "2.0", "method": "initialized", "params": {}})
            _send(proc, {"jsonrpc": "2.0", "method": "textDocument/didOpen", "params": {
                "textDocument": {"uri": uri, "languageId": "wiredsl", "version": 1, "text": text}}})
            batch: list[bytes] = []
            answers: list[dict] = []
            broken = False
            for _ in range(200):
                frame = _random_frame(rng, uri, text)
                batch.append(frame)
                c.counts["lsp:inputs"] += 1
                sent += 1
                try:
                    proc.stdin.write(frame)
                    proc.stdin.flush()
                except BrokenPipeError:
                    break
                answers += reader.drain(0.0)
                if any(frame.startswith(k) for k in BROKEN):
                    broken = True
                    break
            if broken:  # the server must stay alive (or exit cleanly); its stream is out of step
                time.sleep(0.5)
                answers += reader.drain(0.2)
                probe = {"result": None}
            else:
                probe, seen = _ask(proc, reader, 999_999_999, "textDocument/documentSymbol",
                                   {"textDocument": {"uri": uri}}, 60)
                answers += seen
            alive = proc.poll() is None
            errlog.seek(0)
            err = errlog.read().decode(errors="replace")
            internal = [m for m in answers if (m.get("error") or {}).get("code") == -32603]
            if not alive and proc.returncode not in (0, 1):
                c.found("lsp", "exit", b"".join(batch), f"server exited {proc.returncode}: {err}")
            elif probe is None:
                c.found("lsp", "hang", b"".join(batch), "no answer to a valid request after this batch")
            for m in internal:
                c.found("lsp", "internal", b"".join(batch), json.dumps(m["error"])[:1500])
            if "MemoryError" in err or "internal error" in err:  # pygls logs the errors it answered: not these
                c.found("lsp", "traceback", b"".join(batch), err)
        finally:
            with contextlib.suppress(Exception):
                proc.kill()
            proc.wait()
            for s in (proc.stdin, proc.stdout, errlog):
                with contextlib.suppress(Exception):
                    s.close()


# --------------------------------------------------------------------------- the campaign

def main_(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budget", type=int, default=25000, help="inputs in all (split over the parts)")
    ap.add_argument("--minutes", type=float, default=40.0, help="stop drawing new inputs after this long")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "wiredsl-fuzz")
    ap.add_argument("--parts", default="language,validate,lsp,build")
    args = ap.parse_args(argv)
    os.chdir(ROOT)
    c = Campaign(args.out, time.monotonic() + 60 * args.minutes)
    share = {"language": 0.36, "validate": 0.36, "lsp": 0.24, "build": 0.04}
    parts = args.parts.split(",")
    total = sum(share[p] for p in parts)
    started = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp) / "scenes"
        import shutil
        shutil.copytree(ROOT / "scenes", work)
        for p in parts:
            n = int(args.budget * share[p] / total)
            t0 = time.monotonic()
            if p == "language":
                language(c, n // 3 + 1, work)  # three commands an input
                c.counts["language:scenes"] = c.counts["language:inputs"] // 3
            elif p == "validate":
                validate(c, n // 2, work, args.seed)  # validate and load each input
            elif p == "lsp":
                language_server(c, n, work, args.seed)
            elif p == "build":
                builds(c, n, work)
            print(f"{p}: {time.monotonic() - t0:.0f} s, {dict((k, v) for k, v in c.counts.items() if k.startswith(p))}",
                  file=sys.stderr, flush=True)
    inputs = sum(v for k, v in c.counts.items() if k.endswith(":inputs"))
    summary = {"inputs": inputs, "seconds": round(time.monotonic() - started), "counts": dict(c.counts),
               "findings": c.findings}
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps({k: v for k, v in summary.items() if k != "findings"}, indent=1))
    return 1 if c.findings else 0


if __name__ == "__main__":
    sys.exit(main_())
