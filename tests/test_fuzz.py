"""Grammar-aware fuzzing of check, compile and build through the command line.

Scenes are generated from the statement table (`wiredsl/language/statements.py`)
and made by mutating the valid scenes in `scenes/`, and run through check,
compile and `fmt --check`: tokens swapped, deleted and
duplicated; non-finite, overflowing and denormal numbers, NUL bytes, odd paths
and random unicode inserted. Whatever the input, a command must exit 0 or 1
(never 3, the internal-error code), print no traceback, give every diagnostic
a line and column, and print no NaN or Infinity.

CI runs a fixed, derandomised sample. A longer campaign:
`WIREDSL_FUZZ_EXAMPLES=20000 python -m pytest tests/test_fuzz.py -n0 --hypothesis-show-statistics`.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from wiredsl.cli import main
from wiredsl.diagnostics import WiredslError
from wiredsl.language.fmt import format_text
from wiredsl.language.statements import CONTEXTS, Sig, Slot

CAMPAIGN = int(os.environ.get("WIREDSL_FUZZ_EXAMPLES", "0"))


def fuzz_settings(ci_examples: int):
    """A fixed sample in CI; WIREDSL_FUZZ_EXAMPLES=N runs N random examples instead."""
    return settings(max_examples=CAMPAIGN or ci_examples, deadline=None, derandomize=not CAMPAIGN, database=None,
                    suppress_health_check=list(HealthCheck), print_blob=True)


# --------------------------------------------------------------------------- values

HOSTILE_NUMBERS = ["1e999", "-1e999", "1e308", "-1e308", "1e-320", "5e-324", "-0", "0", "1e9", "1e10", "9" * 400,
                   "0." + "0" * 400 + "1", "1e-300", "4", "0.35", "29", "1e-9", "123456789012345678901234567890"]
UNITS = ["", "", "", "mm", "cm", "m", "deg", "rad", "px", "%", "furlong", "e"]
NAMES = ["a", "b", "c", "m", "p", "q", "r", "v", "cam", "left", "right", "top", "base", "rim", "g0_0", "*", "nan",
         "inf", "Infinity", "NaN"]
PATHS = ["x.wd", "models/bin.wd", "lab.info", "/dev/zero", "/dev/null", ".", "..", "a\0b", "", "nowhere/x.wd",
         "_fuzz.wd", "\u00e9\u00e8.wd", "a" * 300]
JUNK = ["\0", "{", "}", "(", ")", "[", "]", ",", ".", "*", "\n", "\\\n", '"', "#", "\u2028", "\ufeff", "\x85",
        "\r", "\t", "\U0001f600", "\u0661", "\u00b2", "1e999", "nan", "inf", "-", "+", "%", "'"]

number = st.builds(lambda n, u: n + u, st.one_of(st.sampled_from(HOSTILE_NUMBERS),
                                                 st.floats(allow_nan=False, allow_infinity=False).map(repr),
                                                 st.integers(-10**6, 10**6).map(str)),
                   st.sampled_from(UNITS)).filter(lambda t: re.fullmatch(r"[+-]?[\d.][\w.%+-]*", t) is not None)
name = st.sampled_from(NAMES)
string = st.sampled_from(PATHS).map(lambda p: '"' + p + '"')


def tuple_of(n: int, elem=number) -> st.SearchStrategy[str]:
    return st.lists(elem, min_size=max(0, n - 1), max_size=n + 1).map(lambda xs: "(" + ", ".join(xs) + ")")


def slot_value(slot: Slot) -> st.SearchStrategy[str]:
    """Text for one slot of the statement table; mostly of the right kind, sometimes not."""
    kind = slot.kind
    if kind.startswith("vec"):
        right = tuple_of(int(kind[3]))
    elif kind in ("name", "ref"):
        right = name
    elif kind == "word":
        right = st.sampled_from([*slot.choices, "furlong"])
    elif kind == "str":
        right = string
    elif kind == "refs":
        right = st.lists(name, min_size=1, max_size=3).map(" ".join)
    elif kind == "pts":
        right = st.lists(tuple_of(3), min_size=1, max_size=5).map(" ".join)
    elif kind == "names":
        right = st.lists(st.sampled_from(["left.f", "right.f", "left.cx", "right.tx", "left.rz", "x.y"]),
                         max_size=3).map(lambda xs: "[" + ", ".join(xs) + "]")
    elif kind == "matrix":
        right = st.integers(0, 3).flatmap(lambda n: st.lists(
            st.lists(number, min_size=n, max_size=n).map(lambda r: "[" + ", ".join(r) + "]"),
            min_size=n, max_size=n).map(lambda rows: "[" + ", ".join(rows) + "]"))
    else:  # scalars
        right = number
    return st.one_of(right, right, right, number, name, string, tuple_of(2))


@st.composite
def statement(draw, context: str, depth: int = 0) -> str:
    sig: Sig = draw(st.sampled_from(list(CONTEXTS[context].values())))
    parts = [sig.keyword] + [draw(slot_value(s)) for s in sig.positional]
    for key, clause in sig.clauses.items():
        for _ in range(draw(st.integers(0, 2 if clause.repeat else 1)) if not clause.required or
                       draw(st.integers(0, 9)) == 0 else 1):
            parts += [key] + [draw(slot_value(s)) for s in clause.slots]
    if sig.block and depth < 2 and (sig.block_required or draw(st.booleans())):
        inner = draw(st.lists(statement(sig.block, depth + 1), max_size=4))
        parts.append("{\n" + "\n".join(inner) + "\n}")
    return " ".join(parts)


@st.composite
def generated_scene(draw) -> str:
    lines = ["wiredsl 1"] + draw(st.lists(statement("top"), min_size=1, max_size=8))
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- mutations of valid scenes

SCENES = {p.name: p.read_text(encoding="utf-8") for p in sorted(Path(__file__).parent.parent.glob("scenes/*.wd"))}
TOKEN = re.compile(r'\s+|"[^"\n]*"|[^\s(),\[\]{}"]+|.', re.S)
junk = st.one_of(st.sampled_from(JUNK + HOSTILE_NUMBERS + NAMES + [f'"{p}"' for p in PATHS]), st.text(max_size=3))


@st.composite
def mutated_scene(draw) -> str:
    tokens = TOKEN.findall(SCENES[draw(st.sampled_from(sorted(SCENES)))])
    for _ in range(draw(st.integers(1, 6))):
        op = draw(st.sampled_from(["delete", "swap", "duplicate", "number", "insert", "replace"]))
        i = draw(st.integers(0, len(tokens) - 1))
        if op == "delete":
            del tokens[i]
        elif op == "swap":
            j = draw(st.integers(0, len(tokens) - 1))
            tokens[i], tokens[j] = tokens[j], tokens[i]
        elif op == "duplicate":
            tokens.insert(i, tokens[i])
        elif op == "number":  # a number of the scene becomes a hostile one, keeping its unit
            nums = [k for k, t in enumerate(tokens) if re.fullmatch(r"[+-]?[\d.]+[a-z%]*", t)]
            if nums:
                k = draw(st.sampled_from(nums))
                tokens[k] = draw(st.sampled_from(HOSTILE_NUMBERS)) + re.sub(r"^[+-]?[\d.]+", "", tokens[k])
        elif op == "insert":
            tokens.insert(i, " " + draw(junk) + " ")
        else:
            tokens[i] = draw(junk)
        if not tokens:
            tokens = ["wiredsl 1"]
    return "".join(tokens)


# --------------------------------------------------------------------------- the properties

@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    """A copy of scenes/ (so mutated scenes find their includes and matrix files) to write into."""
    root = tmp_path_factory.mktemp("fuzz") / "scenes"
    shutil.copytree(Path(__file__).parent.parent / "scenes", root)
    return root


def _no_constant(c: str):
    raise AssertionError(f"{c} in JSON output")


def assert_clean(result, command: str) -> None:
    """Exit 0 or 1, no traceback, located diagnostics, finite JSON."""
    out = result.output
    assert result.exit_code in (0, 1), f"{command}: exit {result.exit_code}\n{out}\n{result.exception!r}"
    assert "Traceback" not in out and "internal error" not in out, out
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise result.exception
    stderr = result.stderr.strip()
    if stderr.startswith("{"):
        for d in json.loads(stderr, parse_constant=_no_constant)["diagnostics"]:
            assert d.get("line", 0) >= 1 and d.get("column", 0) >= 1, d
    if command == "compile" and result.exit_code == 0:
        json.loads(result.stdout, parse_constant=_no_constant)  # NaN and Infinity would be parse constants


def run_on(text: str, workdir: Path) -> None:
    f = workdir / "_fuzz.wd"
    f.write_text(text, encoding="utf-8", errors="surrogatepass")
    for command in ("check", "compile", "fmt"):
        args = [command, "--check"] if command == "fmt" else [command]
        result = CliRunner().invoke(main, [*args, "--diagnostics", "json", str(f)])
        assert_clean(result, command)
    try:
        once = format_text(text, str(f))
    except WiredslError:
        return
    assert format_text(once, str(f)) == once  # fmt is idempotent on whatever it accepts


@fuzz_settings(ci_examples=120)
@given(text=generated_scene())
def test_generated_scenes_never_crash(text, workdir):
    run_on(text, workdir)


@fuzz_settings(ci_examples=120)
@given(text=mutated_scene())
def test_mutated_scenes_never_crash(text, workdir):
    run_on(text, workdir)


@fuzz_settings(ci_examples=60)
@given(data=st.binary(max_size=200))
def test_arbitrary_bytes_never_crash(data, workdir):
    f = workdir / "_bytes.wd"
    f.write_bytes(b"wiredsl 1\n" + data)
    for command in ("check", "compile"):
        assert_clean(CliRunner().invoke(main, [command, "--diagnostics", "json", str(f)]), command)
    assert_clean(CliRunner().invoke(main, ["fmt", "--check", str(f)]), "fmt")


# --------------------------------------------------------------------------- build of small valid scenes

SMALL = """wiredsl 1
units angle {angle_unit}
model thing {{
  line edge from (0, 0, 0) to ({lx}, {ly}, {lz})
  ellipse rim centre (0, 0, {ez}) normal ({nx}, {ny}, 1) axis ({ny}, {mnx}, 0) radii ({a}, {b})
  ellipse base centre (0, 0, 0) normal (0, 0, 1) axis (1, 0, 0) radii ({a}, {a})
  silhouette side between rim base
  corner tip at (0, 0, 0) joins edge
}}
place thing as t1 at ({px}, {py}, 0) ypr ({yaw}, {pitch}, {roll})
camera c {{
  focal {focal}
  pixel 0.01mm
  size ({w}px, {h}px)
  k {k}
}}
rig r {{
  left c at (0, 0.1, 1) looking (1, 0, {tilt})
  right c at (0, -0.1, 1) looking (1, 0, {tilt})
}}
path p {{
  pose (0, 0) heading {heading}
}}
"""

def mostly(usual, *rare) -> st.SearchStrategy[float]:
    """Usual values (so most scenes compile and are seen) and, one time in four, extreme ones."""
    return st.one_of(usual, usual, usual, st.sampled_from(rare))


# Far, huge and very eccentric curves, long focal lengths and strong distortion: before the engine bounded
# a curve's vertices (E151), these ran its adaptive sampling for minutes.
finite = mostly(st.floats(-10, 10), 1e9, -1e9, 5e-324, 1e-300, 1e6)
small_or_huge = mostly(st.floats(1e-2, 3), 1e-8, 1e-6, 1e3, 1e6, 1e9)
position = mostly(st.floats(-10, 10), 1e6, -1e9, 5e-324)


@st.composite
def small_scene(draw) -> str:
    nx, ny = draw(st.floats(-5, 5)), draw(st.floats(-5, 5))
    return SMALL.format(
        angle_unit=draw(st.sampled_from(["deg", "rad"])), lx=draw(finite), ly=draw(finite), lz=draw(finite),
        ez=draw(mostly(st.floats(-3, 3), 1e3, -1e9)), nx=nx, ny=ny, mnx=-nx,
        a=draw(small_or_huge), b=draw(small_or_huge),
        px=draw(position), py=draw(position),
        yaw=draw(st.floats(-1e3, 1e3)), pitch=draw(st.floats(-1e3, 1e3)), roll=draw(st.floats(-1e3, 1e3)),
        focal=draw(st.sampled_from(["6mm", "600px", "1px", "1e9px", "4", "1e-6mm", "50mm"])),
        w=draw(st.integers(1, 4000)), h=draw(st.integers(1, 4000)),
        k=draw(mostly(st.floats(-1, 1), 1e6, -1e6, 1e-300, 0.0)),
        tilt=draw(mostly(st.floats(-1, 1), 1e9, -1e9, 1e-300)), heading=draw(st.floats(-360, 360)))


@fuzz_settings(ci_examples=12)
@given(text=small_scene())
def test_build_of_small_scenes_never_crashes(text, workdir, tmp_path_factory):
    f = workdir / "_small.wd"
    f.write_text(text, encoding="utf-8")
    out = tmp_path_factory.mktemp("build")
    result = CliRunner().invoke(main, ["build", str(f), "-o", str(out), "--no-effects", "--no-svg"])
    assert_clean(result, "build")
    if result.exit_code == 0:
        doc = json.loads((out / "features.json").read_text(encoding="utf-8"), parse_constant=_no_constant)
        assert all(math.isfinite(v) for v in _numbers(doc))


def _numbers(doc):
    if isinstance(doc, dict):
        for v in doc.values():
            yield from _numbers(v)
    elif isinstance(doc, list):
        for v in doc:
            yield from _numbers(v)
    elif isinstance(doc, float):
        yield doc
