"""Malformed calibration files of every format (mutations of the real corpus, of cv2.FileStorage's JSON
and XML, of Kalibr's results-cam.txt) through the compiler and `wiredsl check`: a diagnostic or a camera,
never an internal error. `python tests/test_calibration_fuzz.py N` runs N mutations (the longer campaign)."""

from __future__ import annotations

import random
import sys
from pathlib import Path

from click.testing import CliRunner

from wiredsl.diagnostics import WiredslError

CORPUS = Path(__file__).parent / "data" / "calibration"
RESULTS = """\
Calibration results
====================
Camera-system parameters:
\tcam0 (/cam0/image_raw):
\t type: <class 'aslam_cv.libaslam_cv_python.DistortedPinholeCameraGeometry'>
\t distortion: [-0.29  0.085  0.0009 -0.0004] +- [0.001 0.002 0.0001 0.0001]
\t projection: [530.  531.5 401.5 268. ] +- [0.3 0.3 0.2 0.2]
\t reprojection error: [0.000012, -0.000003] +- [0.120000, 0.090000]

\tcam1 (/cam1/image_raw):
\t type: <class 'aslam_cv.libaslam_cv_python.EquidistantDistortedPinholeCameraGeometry'>
\t distortion: [-0.29  0.085  0.0009 -0.0004] +- [0.001 0.002 0.0001 0.0001]
\t projection: [530.  531.5 401.5 268. ] +- [0.3 0.3 0.2 0.2]

\tbaseline T_1_0:
\t q: [ 0.003 -0.005  0.001  0.99998] +- [0.0001 0.0001 0.0001]
\t t: [-0.0627  0.0006 -0.0004] +- [0.0001 0.0001 0.0001]
"""
JSON = """{
    "image_width": 640,
    "image_height": 480,
    "camera_matrix": {
        "type_id": "opencv-matrix",
        "rows": 3,
        "cols": 3,
        "dt": "d",
        "data": [ 6.1250000000000000e+02, 0., 3.1825000000000000e+02, 0., 6.2475000000000000e+02,
            2.4150000000000000e+02, 0., 0., 1. ]
    },
    "distortion_coefficients": {
        "type_id": "opencv-matrix",
        "rows": 1,
        "cols": 5,
        "dt": "d",
        "data": [ -2.1e-01, 1.3e-02, 4.0e-04, -2.0e-04, 3.1e-02 ]
    }
}
"""
XML = """<?xml version="1.0"?>
<opencv_storage>
<image_width>640</image_width>
<image_height>480</image_height>
<M1 type_id="opencv-matrix">
  <rows>3</rows>
  <cols>3</cols>
  <dt>d</dt>
  <data>
    612.5 0. 318.25 0. 624.75 241.5 0. 0. 1.</data></M1>
<D1 type_id="opencv-matrix">
  <rows>1</rows>
  <cols>5</cols>
  <dt>d</dt>
  <data>
    -0.21 0.013 4e-04 -2e-04 0.031</data></D1>
<M2 type_id="opencv-matrix">
  <rows>3</rows>
  <cols>3</cols>
  <dt>d</dt>
  <data>
    612.5 0. 318.25 0. 624.75 241.5 0. 0. 1.</data></M2>
<D2 type_id="opencv-matrix">
  <rows>1</rows>
  <cols>5</cols>
  <dt>d</dt>
  <data>
    -0.21 0.013 4e-04 -2e-04 0.031</data></D2>
<R type_id="opencv-matrix">
  <rows>3</rows>
  <cols>3</cols>
  <dt>d</dt>
  <data>
    1. 0. 0. 0. 1. 0. 0. 0. 1.</data></R>
<T type_id="opencv-matrix">
  <rows>3</rows>
  <cols>1</cols>
  <dt>d</dt>
  <data>
    -0.12 0. 0.</data></T>
</opencv_storage>
"""


def seeds() -> list[tuple[str, str, tuple[bool, bool]]]:
    """(file name, text, (whether it is a stereo pair with extrinsics, whether it lacks the image size)) of
    every format: the corpus, FileStorage JSON and XML, Kalibr's results."""
    from wiredsl.io.calibration import read

    out = [(p.name, p.read_text()) for p in sorted(CORPUS.iterdir()) if p.suffix in (".yaml", ".yml")]
    out += [("cam.json", JSON), ("stereo.xml", XML)]
    cams = [read(CORPUS / n if (CORPUS / n).exists() else _tmp(n, t)) for n, t in out]
    kinds = [(any(c.R is not None for c in cs), cs[0].width is None) for cs in cams]
    return [(n, t, k) for (n, t), k in zip(out, kinds, strict=True)] + [("results-cam.txt", RESULTS, (False, True))]


def _tmp(name: str, text: str) -> Path:
    import tempfile

    path = Path(tempfile.mkdtemp()) / name
    path.write_text(text)
    return path


WORDS = ["nan", ".nan", "-.inf", "1e999", "-0", "0", "1e308", "-1e308", "1e-320", "[]", "{}", "[[1]]", "{a: 1}", "~",
         "true", "'x'", '"', "[", "]", "{", "}", ":", "- ", "!!opencv-matrix", "*a", "&a", "%YAML:1.0", "\t", "\x00",
         "\u00e9", "rows: 0", "cols: -3", "dt: 2f", "data:[", "cam7:", "T_cn_cnm1: 3", "distortion_model: omni",
         "camera_model: eucm", "<rows>2</rows>", "+- [", "] +- [1 2]", "12345678901234567890"]


def mutate(text: str, rng: random.Random) -> str:
    """One to three random edits: a number, a word, a line, brackets, indentation, truncation."""
    for _ in range(rng.randint(1, 3)):
        kind = rng.randrange(8)
        lines = text.split("\n")
        i = rng.randrange(len(lines))
        if kind == 0:  # a number replaced
            import re

            nums = list(re.finditer(r"-?\d+\.?\d*(?:e[-+]?\d+)?", text))
            if nums:
                m = rng.choice(nums)
                text = text[:m.start()] + rng.choice(WORDS[:10] + [str(rng.uniform(-1e3, 1e3))]) + text[m.end():]
        elif kind == 1:  # a line deleted
            del lines[i]
            text = "\n".join(lines)
        elif kind == 2:  # a line duplicated elsewhere
            lines.insert(rng.randrange(len(lines) + 1), lines[i])
            text = "\n".join(lines)
        elif kind == 3:  # a word inserted
            j = rng.randrange(len(text) + 1)
            text = text[:j] + rng.choice(WORDS) + text[j:]
        elif kind == 4:  # indentation changed
            lines[i] = rng.choice(["", " ", "\t", "        "]) + lines[i].lstrip()
            text = "\n".join(lines)
        elif kind == 5:  # truncated
            text = text[:rng.randrange(len(text) + 1)]
        elif kind == 6:  # a character changed
            if text:
                j = rng.randrange(len(text))
                text = text[:j] + rng.choice("[]{}:,- \n\"'#&*!%0.e") + text[j + 1:]
        else:  # a value turned into another type
            if ":" in lines[i]:
                key = lines[i].split(":", 1)[0]
                lines[i] = key + ": " + rng.choice(WORDS)
                text = "\n".join(lines)
    return text


def scene_text(name: str, kind: tuple[bool, bool]) -> str:
    """A scene reading the file: a stereo file gives both cameras and the right mount, Kalibr's results
    the rig's calibration, another file one camera."""
    pair, sizeless = kind
    left = f'read "{name}"' + ("\n  size (640px, 480px)" if sizeless else "")
    right = left.replace(f'"{name}"', f'"{name}" entry second') if pair else left
    mount = f'right c2 relative "{name}"' if pair else "right c2 at (0, -0.06, 1) looking (1, 0, 0)"
    if name == "results-cam.txt":
        left = right = "focal 500px\n  size (640px, 480px)"
        mount += '\n  calibration covariance kalibr "results-cam.txt"'
    from helpers import camera_scene

    return camera_scene(left, mount, more=f"camera c2 {{\n  {right}\n}}\n")


def run(n: int, folder: Path, seed: int = 0) -> dict[str, int]:
    """n mutations compiled in-process: counts of outcomes; an internal error raises."""
    from helpers import compile_text

    rng = random.Random(seed)
    base = seeds()
    counts = {"ok": 0, "diagnostic": 0}
    for k in range(n):
        name, text, pair = base[k % len(base)]
        bad = mutate(text, rng)
        (folder / name).write_text(bad, encoding="utf-8", errors="surrogatepass")
        try:
            compile_text(scene_text(name, pair), str(folder / "s.wd"))
            counts["ok"] += 1
        except WiredslError:
            counts["diagnostic"] += 1
        except Exception as exc:  # noqa: BLE001 (an internal error: keep the input for the report)
            (folder / f"crash-{k}-{name}").write_text(bad)
            raise AssertionError(f"mutation {k} of {name} (seed {seed}): {type(exc).__name__}: {exc}") from exc
    return counts


def test_two_hundred_mutations_compile_or_get_a_diagnostic(tmp_path):
    counts = run(200, tmp_path, seed=17)  # about 25 ms each, PyYAML's pure-Python parser most of it
    assert counts["diagnostic"] > 50 and counts["ok"] > 5  # the mutations reach both outcomes


def test_wiredsl_check_exits_0_or_1_on_mutated_files(tmp_path):
    from wiredsl.cli import main

    rng = random.Random(5)
    for name, text, pair in seeds()[::3]:
        (tmp_path / name).write_text(mutate(text, rng))
        (tmp_path / "s.wd").write_text(scene_text(name, pair))
        r = CliRunner().invoke(main, ["check", str(tmp_path / "s.wd")])
        assert r.exit_code in (0, 1), r.output


if __name__ == "__main__":
    import tempfile
    import time

    sys.path.insert(0, str(Path(__file__).parent))
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        print(run(int(sys.argv[1]), Path(d), seed=int(sys.argv[2]) if len(sys.argv) > 2 else 1),
              f"{time.perf_counter() - t0:.1f} s")
