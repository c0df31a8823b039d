"""Damaged and hostile inputs to `validate` and `wiredsl.load` (issue 15): each a clear diagnostic and exit 1,
never exit 3, never an unbounded read, never an unpickled object, never a NaN taken as a number."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import wiredsl
from wiredsl.cli import main
from wiredsl.io import layout, schema


@pytest.fixture(scope="module")
def dump(tmp_path_factory) -> Path:
    """A real two-trial npz dump of the lab scene."""
    out = tmp_path_factory.mktemp("dump")
    r = CliRunner().invoke(main, ["build", "scenes/lab.wd", "--format", "npz", "--trials", "2", "--seed", "1",
                                  "--pose", "0", "--no-svg", "-o", str(out)])
    assert r.exit_code == 0, r.output
    return out / "features.npz"


def npy(array: np.ndarray, allow_pickle: bool = False) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=allow_pickle)
    return buf.getvalue()


def npy_header(shape: tuple, descr: str = "<f4") -> bytes:
    text = f"{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}".encode()
    text += b" " * (117 - len(text)) + b"\n"
    return b"\x93NUMPY\x01\x00" + len(text).to_bytes(2, "little") + text


def with_member(dump: Path, out: Path, member: str, data: bytes, deflate: bool = False) -> Path:
    """A copy of the dump with one member's bytes replaced."""
    with zipfile.ZipFile(dump) as z, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED if deflate else 0) as w:
        for name in z.namelist():
            w.writestr(name, data if name == member else z.read(name))
    return out


def validate(*paths) -> tuple[int, str]:
    r = CliRunner().invoke(main, ["validate", *map(str, paths)])
    return r.exit_code, r.output


def test_the_dump_itself_validates_and_loads(dump):
    assert validate(dump) == (0, "1 dump valid\n")
    assert len(wiredsl.load(dump)) > 10


@pytest.mark.parametrize(("member", "data", "message"), [
    ("layout.npy", npy(np.array([{"x": 1}], dtype=object), allow_pickle=True), "holds Python objects (a pickle)"),
    ("layout.npy", npy_header((-1,), "zz")[:40], "damaged array header"),
    ("layout.npy", b"\x93NUMPY\x01\x00\x20\x00{'descr': 'zz', 'fortran_order': False, 'sh", "damaged array header"),
    ("b00000_pts.npy", npy_header((10**11, 2)) + bytes(64), "needs 800,000,000,000 bytes, the member holds 64"),
    ("b00000_pts.npy", b"not an array at all", "damaged array header"),
])
def test_a_damaged_member_is_a_diagnostic_for_validate_and_load(dump, tmp_path, member, data, message):
    bad = with_member(dump, tmp_path / "bad.npz", member, data)
    code, out = validate(bad)
    assert code == 1 and message in out and "internal error" not in out, out
    with pytest.raises(layout.NpzError, match=message.replace("(", r"\(").replace(")", r"\)")):
        wiredsl.load(bad)


def test_a_zip_bomb_member_is_refused_before_it_is_inflated(dump, tmp_path, monkeypatch):
    """8 MiB of zeros deflate to a few KiB; with the limit at 1 MiB the member is refused from its zip entry."""
    monkeypatch.setattr(layout, "MAX_MEMBER_BYTES", 1 << 20)
    bomb = with_member(dump, tmp_path / "bomb.npz", "b00000_pts.npy", npy_header((1 << 20, 2)) + bytes(8 << 20),
                       deflate=True)
    assert bomb.stat().st_size < 200_000
    code, out = validate(bomb)
    assert code == 1 and "over the limit of 1,048,576" in out
    with pytest.raises(layout.NpzError, match="over the limit"):
        wiredsl.load(bomb)


@pytest.mark.parametrize(("member", "change", "message"), [
    ("layout", lambda a: np.zeros(0, np.int64), "layout: shape (0,), expected ()"),  # the fuzz campaign's exit 3
    ("layout", lambda a: np.array(1), f"layout 1, this wiredsl reads {layout.NPZ_VERSION}"),
    ("b00000_strokes", lambda a: a[:, :7], "b00000_strokes: shape"),
    ("b00000_strokes", lambda a: np.where(np.arange(a.shape[1]) == 2, 5, a).astype(np.int32), "a camera other than"),
    ("b00000_corner_rows", lambda a: a[:-1], "corners and corner_rows differ in length"),
    ("feature_ids", lambda a: np.array(7), "feature_ids: dtype int64, expected unicode"),
    ("b00000_pts", lambda a: a.astype(np.complex64), "b00000_pts: dtype complex64, expected float32"),  # fuzz
])
def test_a_member_of_the_wrong_shape_or_values_is_a_diagnostic_not_a_crash(dump, tmp_path, member, change, message):
    arrays = dict(np.load(dump))
    arrays[member] = change(arrays[member])
    np.savez(tmp_path / "bad.npz", **arrays)
    code, out = validate(tmp_path / "bad.npz")
    assert code == 1 and message in out and "internal error" not in out, out
    with pytest.raises(ValueError, match="bad.npz"):
        wiredsl.load(tmp_path / "bad.npz")


def test_a_dump_with_nan_is_refused_by_validate_and_load(dump, tmp_path):
    arrays = dict(np.load(dump))
    arrays["b00000_pts"][3, 1] = np.nan
    np.savez(tmp_path / "nan.npz", **arrays)
    code, out = validate(tmp_path / "nan.npz")
    assert code == 1 and "non-finite" in out
    with pytest.raises(ValueError, match="NaN or infinity"):
        wiredsl.load(tmp_path / "nan.npz")


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity"])
@pytest.mark.parametrize("where", ["points", "focal", "translation"])
def test_validate_refuses_nan_and_infinity_in_a_json_dump(tmp_path, token, where):
    """Python's json reads NaN and Infinity; JSON has neither. Points, focal lengths and translations."""
    out = tmp_path / "b"
    r = CliRunner().invoke(main, ["build", "scenes/lab.wd", "--pose", "0", "--no-svg", "--no-effects", "-o", str(out)])
    assert r.exit_code == 0, r.output
    text = (out / "features.json").read_text()
    doc = json.loads(text)
    view = doc["poses"][0]["left"]
    if where == "points":
        first = next(f for f in view["polylines"] if f["points"])
        needle = json.dumps(first["points"][0][0])
    elif where == "focal":
        needle = json.dumps(view["camera"]["f"])
    else:
        needle = json.dumps(view["translation"][0])
    assert needle in text
    (tmp_path / "d.json").write_text(text.replace(needle, token, 1))
    code, msg = validate(tmp_path / "d.json")
    assert code == 1 and f"{token} is not a JSON number" in msg, msg
    line = text[:text.index(needle)].count("\n") + 1
    assert f"d.json:{line}:" in msg
    with pytest.raises(ValueError, match=f"{token} is not a JSON number"):  # load's DumpError
        wiredsl.load(tmp_path / "d.json")
    # and a document built in Python, not parsed: the schema check names the value
    doc_nan = json.loads(text.replace(needle, token, 1), parse_constant=float)
    assert any("is not a finite number" in p for p in schema.problems(doc_nan))


def test_validate_and_load_refuse_an_integer_of_too_many_digits_at_its_place(tmp_path):
    """The fuzz campaign: a manifest whose trial count was 100,000 nines was exit 3 (int() refuses over 4,300
    digits with a ValueError the reader let through); now a located diagnostic, and load's DumpError."""
    out = tmp_path / "b"
    r = CliRunner().invoke(main, ["build", "scenes/lab.wd", "--pose", "0", "--no-svg", "--no-effects", "-o", str(out)])
    assert r.exit_code == 0, r.output
    text = (out / "manifest.json").read_text()
    needle = '"trials": 1'
    assert needle in text
    (tmp_path / "manifest.json").write_text(text.replace(needle, '"trials": ' + "9" * 100_000, 1))
    code, msg = validate(tmp_path / "manifest.json")
    line = text[:text.index(needle)].count("\n") + 1
    assert code == 1 and f"manifest.json:{line}:" in msg and "integer of 100,000 digits" in msg, msg
    text = (out / "features.json").read_text()
    (tmp_path / "f.json").write_text(text.replace('"seed": ', '"seed": 1' + "0" * 5000, 1))
    with pytest.raises(ValueError, match="integer of 5,0"):
        wiredsl.load(tmp_path / "f.json")


def test_validate_refuses_json_nested_beyond_the_reader(tmp_path):
    (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    code, out = validate(tmp_path / "deep.json")
    assert code == 1 and "nested too deeply" in out


@pytest.mark.parametrize("kind", ["/dev/zero", "fifo"])
def test_validate_refuses_devices_fifos_and_folders_without_reading_them(tmp_path, kind):
    """A real /dev/zero and a real FIFO, in a subprocess with a timeout: refused at once, memory bounded."""
    if kind == "fifo":
        path = tmp_path / "pipe.json"
        os.mkfifo(path)
    else:
        path = Path(kind)
    if not os.path.exists(path):
        pytest.skip(f"no {kind} here")
    p = subprocess.run([sys.executable, "-m", "wiredsl", "validate", str(path)], capture_output=True, text=True,
                       timeout=30)
    assert p.returncode == 1, p.stderr
    assert "not a regular file (a FIFO, device or socket)" in p.stderr, p.stderr


def test_a_scene_whose_path_is_not_utf8_builds_its_svgs(tmp_path):
    """A file named b'lab\\xff.wd' (its name decodes to a lone surrogate): the SVGs show U+FFFD there."""
    import shutil

    for p in Path("scenes").iterdir():  # the scene with its includes beside it
        (shutil.copytree if p.is_dir() else shutil.copy)(p, tmp_path / p.name)
    name = os.fsdecode(b"lab\xff.wd")
    shutil.copy("scenes/lab.wd", tmp_path / name)
    p = subprocess.run([sys.executable, "-m", "wiredsl", "build", name, "--pose", "0", "-o", "out"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    svg = (tmp_path / "out" / "pose_000.svg").read_bytes().decode("utf-8")
    assert "lab\ufffd.wd" in svg and svg.startswith("<svg")


REGRESSIONS = sorted(Path(__file__).parent.joinpath("fuzz_regressions").glob("*.npz"))


@pytest.mark.parametrize("path", REGRESSIONS, ids=[p.name for p in REGRESSIONS])
def test_every_input_the_fuzz_campaign_crashed_on_is_now_a_diagnostic(path):
    """The inputs tests/fuzz_campaign.py found (exit 3 in validate, an exception in load), kept as they were."""
    code, out = validate(path)
    assert code == 1 and "internal error" not in out and out.startswith(f"{path}: error: "), out
    with pytest.raises(ValueError, match=str(path.name)):
        wiredsl.load(path)
