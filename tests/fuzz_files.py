"""A fuzz campaign over the input files (not part of the default suite): scenes/*.wd with extreme numbers, token
deletions and swaps, unicode, long lines, empty blocks and self-includes (check, then build, export or compile);
trajectory files of tests/data (TUM, EuRoC, KITTI with times) and calibration files of tests/data, mutated line by
line (check, then build or export); damaged images for `wiredsl verify` (truncated, empty, 1x1, huge or zero
headers, 16-bit, grey+alpha, RGBA, other formats, bad CRCs); and wiredsl's own JSON documents through `validate`.
Each run is in process with a time limit; exit 3, other exit codes, tracebacks, hangs, non-finite numbers in an
output and a failed run's leftovers are findings, each kept with its inputs in OUT.

    nice -n 10 python tests/fuzz_files.py OUT scenes,traj,calib,images,validate N [SEED]

(N inputs a part; the mutations are repeatable for a seed.)
"""

import json
import os
import random
import re
import shutil
import signal
import struct
import sys
import time
import traceback
import zlib
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
OUT = Path(sys.argv[1]).resolve()
os.chdir(ROOT)
from click.testing import CliRunner  # noqa: E402 - after the chdir: the scenes' includes are read from ROOT

from wiredsl.cli import main  # noqa: E402

OUT.mkdir(parents=True, exist_ok=True)
PARTS = sys.argv[2].split(",")
N = int(sys.argv[3])
SEED = int(sys.argv[4]) if len(sys.argv) > 4 else 1
rng = random.Random(SEED)
counts = Counter()
findings = []


class Hang(Exception):
    pass


def _alarm(*a):
    raise Hang


signal.signal(signal.SIGALRM, _alarm)

NONFINITE = re.compile(rb"(?<![A-Za-z_])(nan|NaN|-?inf|-?Infinity)(?![A-Za-z_])")


def scan_outputs(folder: Path) -> str | None:
    if not folder.exists():
        return None
    for p in folder.rglob("*"):
        if ".wiredsl-" in p.name or p.name.endswith(".tmp"):
            return f"temporary left: {p}"
        if not p.is_file():
            continue
        if p.suffix in (".json", ".jsonl", ".csv", ".txt", ".wd", ".svg"):
            data = p.read_bytes()
            m = NONFINITE.search(data)
            if m and p.suffix != ".svg":
                return f"non-finite {m.group(0)!r} in {p}"
            if p.suffix == ".svg" and re.search(rb'="[^"]*(nan|inf)[^"]*"', data, re.I):
                return f"non-finite in svg {p}"
        if p.suffix == ".npz":
            try:
                with np.load(p, allow_pickle=False) as z:
                    for k in z.files:
                        a = z[k]
                        if a.dtype.kind == "f" and not np.isfinite(a).all():
                            return f"non-finite in {p}:{k}"
            except Exception as e:
                return f"unreadable npz {p}: {e}"
    return None


def run(part, args, data_desc, inputs: dict, seconds=30, outdir=None):
    counts[f"{part}:inputs"] += 1
    cmd = args[0]
    counts[f"cmd:{cmd}"] += 1
    signal.alarm(seconds)
    try:
        r = CliRunner().invoke(main, args, catch_exceptions=True)
    except Hang:
        signal.alarm(0)
        found(part, "hang", args, inputs, f"over {seconds}s")
        return None
    finally:
        signal.alarm(0)
    if isinstance(r.exception, Hang):
        found(part, "hang", args, inputs, f"over {seconds}s")
        return r
    code = r.exit_code
    out = (r.stdout or "") + (r.stderr or "")
    tb = (
        "".join(traceback.format_exception(r.exception))
        if r.exception and not isinstance(r.exception, SystemExit)
        else ""
    )
    if code == 3 or tb:
        found(part, "internal", args, inputs, f"exit {code}\n{out[-1500:]}\n{tb[-3000:]}")
    elif code not in (0, 1, 2):
        found(part, f"exit{code}", args, inputs, out[-1500:])
    elif "Traceback" in out:
        found(part, "traceback", args, inputs, out[-2000:])
    if outdir is not None:
        bad = scan_outputs(Path(outdir))
        if bad:
            found(part, "output", args, inputs, bad)
        if code != 0 and Path(outdir).exists() and any(Path(outdir).iterdir()) and cmd != "study":
            # a failed run must leave no new output
            found(part, "halfwritten", args, inputs, f"exit {code} left {[p.name for p in Path(outdir).iterdir()]}")
    counts[f"{part}:exit{code}"] += 1
    return r


def found(part, kind, args, inputs, detail):
    i = len(findings)
    d = OUT / f"{part}-{kind}-{i:04d}"
    d.mkdir()
    for name, blob in inputs.items():
        (d / name.replace("/", "_")).write_bytes(
            blob if isinstance(blob, bytes) else blob.encode("utf-8", "surrogateescape")
        )
    (d / "args.json").write_text(json.dumps(args))
    (d / "detail.txt").write_text(detail)
    findings.append({"part": part, "kind": kind, "dir": str(d), "detail": detail[-300:]})
    counts[f"{part}:{kind}"] += 1
    print(
        f"FOUND {part} {kind} {args[:2]}: {detail.strip().splitlines()[-1][:200] if detail.strip() else ''}", flush=True
    )


# ------------------------------------------------------------------ text mutation
EXTREMES = [
    "1e308",
    "-1e308",
    "1e309",
    "-0",
    "-0.0",
    "1e-320",
    "4.9e-324",
    "0",
    "nan",
    "inf",
    "-inf",
    "99999999999999999999",
    "1e19",
    "-1",
    "1e-9",
    "123456789012345678901234567890",
    "0x10",
    "1_000",
    "+1",
    ".5",
    "5.",
    "1e",
    "--1",
    "١٢",
    "½",
    "1,5",
]


def mutate_text(text: str) -> str:
    toks = re.split(r"(\s+|[(),\[\]{}\"])", text)
    kinds = rng.choice(
        [
            "number",
            "number",
            "number",
            "delete",
            "swap",
            "dup",
            "unicode",
            "longline",
            "empty_block",
            "truncate",
            "blank_lines",
            "crlf",
        ]
    )
    nums = [i for i, t in enumerate(toks) if re.fullmatch(r"[-+]?\d[\d.eE+-]*[a-z°]*", t or "")]
    if kinds == "number" and nums:
        for _ in range(rng.randint(1, 3)):
            i = rng.choice(nums)
            unit = re.sub(r"^[-+]?\d[\d.eE+-]*", "", toks[i])
            toks[i] = rng.choice(EXTREMES) + (unit if rng.random() < 0.6 else "")
    elif kinds == "delete" and toks:
        for _ in range(rng.randint(1, 3)):
            i = rng.randrange(len(toks))
            toks[i] = ""
    elif kinds == "swap" and len(toks) > 2:
        i, j = rng.randrange(len(toks)), rng.randrange(len(toks))
        toks[i], toks[j] = toks[j], toks[i]
    elif kinds == "dup" and toks:
        i = rng.randrange(len(toks))
        toks.insert(i, toks[i] * rng.choice([2, 50, 5000]))
    elif kinds == "unicode" and toks:
        i = rng.randrange(len(toks))
        toks[i] = rng.choice(["\u2028", "é", "\u0000", "\ufeff", "𝟙", "\udcff", "\u202e", "Ω"]) + toks[i]
    elif kinds == "longline":
        i = rng.randrange(len(toks))
        toks[i] = toks[i] + " " + "9" * rng.choice([1000, 100000])
    elif kinds == "empty_block":
        return re.sub(r"\{[^{}]*\}", "{}", text, count=rng.randint(1, 3))
    elif kinds == "truncate":
        return text[: rng.randrange(len(text) + 1)]
    elif kinds == "blank_lines":
        lines = text.splitlines(True)
        i = rng.randrange(len(lines) + 1)
        lines.insert(i, "\n" * 3)
        return "".join(lines)
    elif kinds == "crlf":
        return text.replace("\n", "\r\n") if rng.random() < 0.5 else text.replace("\n", "\r")
    return "".join(toks)


def mutate_lines(text: str) -> str:
    """for data files: mutate a few lines (numbers extreme, columns dropped/added, duplicated lines)."""
    lines = text.splitlines()
    if not lines:
        return rng.choice(["", "\n", "0 0 0 0 0 0 0 1\n"])
    k = rng.choice(
        ["num", "num", "num", "dropcol", "addcol", "dupline", "swaplines", "sep", "text", "truncate", "empty", "huge"]
    )
    for _ in range(rng.randint(1, 3)):
        i = rng.randrange(len(lines))
        parts = re.split(r"([ ,\t]+)", lines[i])
        nums = [j for j, t in enumerate(parts) if re.fullmatch(r"[-+]?[\d.]+(e[-+]?\d+)?", t, re.I)]
        if k == "num" and nums:
            parts[rng.choice(nums)] = rng.choice(EXTREMES)
            lines[i] = "".join(parts)
        elif k == "dropcol" and nums:
            parts[rng.choice(nums)] = ""
            lines[i] = "".join(parts)
        elif k == "addcol":
            lines[i] += rng.choice([" 1", ",1", " x", "\t0"])
        elif k == "dupline":
            lines.insert(i, lines[i])
        elif k == "swaplines":
            j = rng.randrange(len(lines))
            lines[i], lines[j] = lines[j], lines[i]
        elif k == "sep":
            lines[i] = lines[i].replace(" ", rng.choice([",", ";", "\t", "  ", ""]))
        elif k == "text":
            lines[i] = rng.choice(["# comment", "hello", "", "\x00\x01", "é ü", lines[i] + " # trailing"])
        elif k == "huge":
            lines[i] = lines[i] + " " + "1" * 100000
    if k == "truncate":
        t = "\n".join(lines)
        return t[: rng.randrange(len(t) + 1)]
    if k == "empty":
        return "\n".join(line for line in lines if line.startswith("#"))
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------ parts
WORK = OUT / "work"
shutil.rmtree(WORK, ignore_errors=True)
WORK.mkdir()


def part_scenes(n):
    srcs = {p: p.read_text() for p in sorted(Path("scenes").glob("*.wd")) if p.name not in ("meshes.wd",)}
    names = list(srcs)
    # a copy of scenes/ so includes resolve
    base = WORK / "scenes"
    shutil.copytree("scenes", base, ignore=shutil.ignore_patterns("meshes", "models"))
    shutil.copytree("scenes/models", base / "models")
    for _ in range(n):
        src = rng.choice(names)
        text = srcs[src]
        for _ in range(rng.randint(1, 2)):
            text = mutate_text(text)
        if rng.random() < 0.05:  # include cycles / deep includes
            text = f'include "{src.name}"\n' + text
        f = base / f"m_{src.name}"
        f.write_text(text, encoding="utf-8", errors="surrogateescape")
        inp = {src.name: text}
        r = run("scene", ["check", str(f)], src, inp, 20)
        if r is None or r.exit_code != 0:
            continue
        cmd = rng.choice(["build", "build", "export", "compile"])
        out = WORK / "out"
        shutil.rmtree(out, ignore_errors=True)
        if cmd == "build":
            args = ["build", str(f), "--seed", "1", "--no-svg" if rng.random() < 0.5 else "--force", "-o", str(out)]
            if rng.random() < 0.5:
                args += ["--trials", "3", "--format", rng.choice(["npz", "jsonl"])]
            if "handheld" not in src.name and rng.random() < 0.7:
                args += ["--pose", "0"]
            run("scene", args, src, inp, 60, out)
        elif cmd == "export":
            run(
                "scene",
                ["export", str(f), "--format", rng.choice(["colmap", "rosbag2"]), "--seed", "1", "-o", str(out)],
                src,
                inp,
                60,
                out,
            )
        else:
            run("scene", ["compile", str(f), "-o", str(out / "c.json")], src, inp, 30, out)


TRAJ = {
    "tum": ("tests/data/trajectories/tum_fr1_xyz_rgbdslam.txt", "format tum"),
    "tumgt": ("tests/data/trajectories/tum_fr1_xyz_groundtruth.txt", "format tum"),
    "euroc": ("tests/data/trajectories/euroc_MH_01_easy_groundtruth.csv", ""),
    "kitti": ("tests/data/trajectories/kitti_00_poses.txt", 'format kitti times "times.txt"'),
}

SC = Path("scenes").resolve().as_posix()
HANDHELD = Path("scenes/handheld.wd").read_text().split("# The file gives")[0]


def part_traj(n):
    head = {k: "\n".join(Path(p).read_text().splitlines()[:60]) + "\n" for k, (p, _) in TRAJ.items()}
    times = "\n".join(Path("tests/data/trajectories/kitti_00_times.txt").read_text().splitlines()[:60]) + "\n"
    for k in range(n):
        kind = rng.choice(list(TRAJ))
        d = WORK / f"t{k % 3}"
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir()
        data = mutate_lines(head[kind])
        tdata = mutate_lines(times) if kind == "kitti" and rng.random() < 0.3 else times
        name = "traj" + Path(TRAJ[kind][0]).suffix
        (d / name).write_text(data, encoding="utf-8", errors="surrogateescape")
        (d / "times.txt").write_text(tdata, encoding="utf-8", errors="surrogateescape")
        extra = rng.choice(["", " every 0.25s", " every 1e-9s"])
        body = rng.choice(["\n  body camera left", "", "\n  body at (0.05m, 0, 0.3m) rotate z 10deg"])
        world = (
            "\n  world rotate x -90deg rotate z -90deg"
            if kind == "kitti"
            else "\n  world at (3.3m, 2.6m, 0) rotate z 180deg"
        )
        scene = HANDHELD.replace("scene handheld", "scene t").replace('include "', f'include "{SC}/') + (
            f'path p {{\n  read "{name}" {TRAJ[kind][1]}{extra}{body}{world}\n}}\n'
        )
        (d / "s.wd").write_text(scene)
        inp = {name: data, "times.txt": tdata, "s.wd": scene}
        r = run("traj", ["check", str(d / "s.wd")], kind, inp, 20)
        if r is None or r.exit_code != 0:
            continue
        out = d / "out"
        args = rng.choice(
            [
                ["build", str(d / "s.wd"), "--seed", "1", "--no-svg", "-o", str(out)],
                ["build", str(d / "s.wd"), "--seed", "1", "--trials", "2", "--format", "npz", "-o", str(out)],
                [
                    "export",
                    str(d / "s.wd"),
                    "--format",
                    rng.choice(["rosbag2", "colmap"]),
                    "--no-effects",
                    "-o",
                    str(out),
                ],
            ]
        )
        run("traj", args, kind, inp, 60, out)


CALIB = sorted(Path("tests/data/calibration").glob("*.y*ml")) + sorted(Path("tests/data/calibration").glob("*.json"))


def part_calib(n):
    for k in range(n):
        src = rng.choice(CALIB)
        d = WORK / f"c{k % 3}"
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir()
        text = src.read_text()
        for _ in range(rng.randint(1, 2)):
            text = mutate_lines(text) if rng.random() < 0.5 else mutate_text(text)
        (d / src.name).write_text(text, encoding="utf-8", errors="surrogateescape")
        scene = (
            f'wiredsl 1\nscene c\ncamera cam_l {{ read "{src.name}" }}\ncamera cam_r {{ read "{src.name}" }}\n'
            "rig r {\n  left cam_l at (0, 0, 0) looking (1, 0, 0)\n"
            "  right cam_r at (0, -0.1m, 0) looking (1, 0, 0)\n}\n"
            "model box {\n  line a from (2, -0.5, 0) to (2, 0.5, 0)\n  line b from (2, 0.5, 0) to (2, 0.5, 1)\n}\n"
            "path p {\n  pose (0, 0) heading 0\n}\n"
        )
        (d / "s.wd").write_text(scene)
        inp = {src.name: text, "s.wd": scene}
        r = run("calib", ["check", str(d / "s.wd")], src.name, inp, 20)
        if r is None or r.exit_code != 0:
            continue
        out = d / "out"
        run("calib", ["build", str(d / "s.wd"), "--seed", "1", "-o", str(out)], src.name, inp, 60, out)


def _png(arr: np.ndarray, bitdepth=8, color=0, w=None, h=None) -> bytes:
    hgt, wid = arr.shape[:2]
    raw = b"".join(b"\x00" + arr[y].tobytes() for y in range(hgt))

    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d))

    ihdr = struct.pack(">IIBBBBB", w or wid, h or hgt, bitdepth, color, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


def part_images(n):
    import cv2

    L = Path("tests/data/opencv_stereo/left01.jpg").read_bytes()
    R = Path("tests/data/opencv_stereo/right01.jpg").read_bytes()
    grey = cv2.imread("tests/data/opencv_stereo/left01.jpg", cv2.IMREAD_GRAYSCALE)
    png = cv2.imencode(".png", grey)[1].tobytes()

    def variants():
        k = rng.choice(
            [
                "trunc",
                "zero",
                "1x1",
                "flip",
                "hugehdr",
                "16bit",
                "rgba",
                "ga",
                "rgb",
                "wrongsize",
                "text",
                "bmp",
                "tiff",
                "pnm",
                "webp",
                "header_only",
                "pngtrunc",
                "badcrc",
                "zerodim",
                "float_exr",
                "allsame",
                "ext_mismatch",
            ]
        )
        if k == "trunc":
            return k, ".jpg", L[: rng.randrange(len(L))]
        if k == "zero":
            return k, ".jpg", b""
        if k == "1x1":
            return k, ".png", cv2.imencode(".png", np.zeros((1, 1), np.uint8))[1].tobytes()
        if k == "flip":
            b = bytearray(rng.choice([L, png]))
            for _ in range(rng.randint(1, 20)):
                i = rng.randrange(min(len(b), rng.choice([64, 400, len(b)])))
                b[i] = rng.randrange(256)
            return k, ".jpg" if b[:2] == b"\xff\xd8" else ".png", bytes(b)
        if k == "hugehdr":
            return (
                k,
                ".png",
                _png(
                    np.zeros((2, 2), np.uint8),
                    w=rng.choice([2**31 - 1, 65535, 100000, 0, 1]),
                    h=rng.choice([2**31 - 1, 65535, 100000, 0, 1]),
                ),
            )
        if k == "16bit":
            return k, ".png", cv2.imencode(".png", (grey.astype(np.uint16) * rng.choice([1, 257, 0])))[1].tobytes()
        if k == "rgba":
            return k, ".png", cv2.imencode(".png", cv2.cvtColor(grey, cv2.COLOR_GRAY2BGRA))[1].tobytes()
        if k == "ga":
            return k, ".png", _png(np.dstack([grey, grey]).astype(np.uint8), color=4)
        if k == "rgb":
            return k, ".jpg", cv2.imencode(".jpg", cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))[1].tobytes()
        if k == "wrongsize":
            return k, ".png", cv2.imencode(".png", grey[: rng.randint(1, 479), : rng.randint(1, 639)])[1].tobytes()
        if k == "text":
            return k, ".png", b"hello, not an image\n"
        if k == "bmp":
            return k, ".bmp", cv2.imencode(".bmp", grey)[1].tobytes()
        if k == "tiff":
            return (
                k,
                ".tiff",
                cv2.imencode(".tiff", grey if rng.random() < 0.5 else grey.astype(np.float32))[1].tobytes(),
            )
        if k == "pnm":
            return k, ".pgm", cv2.imencode(".pgm", grey)[1].tobytes()
        if k == "webp":
            return k, ".webp", cv2.imencode(".webp", grey)[1].tobytes()
        if k == "header_only":
            return k, ".png", png[:33]
        if k == "pngtrunc":
            return k, ".png", png[: rng.randrange(33, len(png))]
        if k == "badcrc":
            b = bytearray(png)
            b[29] ^= 0xFF
            return k, ".png", bytes(b)
        if k == "zerodim":
            return k, ".png", _png(np.zeros((1, 1), np.uint8), w=0, h=0)
        if k == "float_exr":
            return (
                k,
                ".png",
                _png(np.zeros((4, 4), np.uint8), bitdepth=rng.choice([1, 2, 4, 16, 7]), color=rng.choice([0, 2, 3, 5])),
            )
        if k == "allsame":
            return k, ".png", cv2.imencode(".png", np.full_like(grey, rng.choice([0, 255])))[1].tobytes()
        if k == "ext_mismatch":
            return k, ".png", L

    for k in range(n):
        d = WORK / f"i{k % 3}"
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir()
        kind, ext, data = variants()
        which = rng.choice(["left", "right", "both"])
        lname = f"left01{ext}" if which in ("left", "both") else "left01.jpg"
        rname = f"right01{ext}" if which in ("right", "both") else "right01.jpg"
        (d / lname).write_bytes(data if which in ("left", "both") else L)
        (d / rname).write_bytes(data if which in ("right", "both") else R)
        out = d / "out"
        args = [
            "verify",
            "scenes/chessboard.wd",
            "--images",
            str(d / lname),
            "--images",
            str(d / rname),
            "--poses",
            rng.choice(["board", "board", "path"]),
            "--detector",
            rng.choice(["canny", "lsd", "harris"]),
            "-o",
            str(out),
        ]
        if rng.random() < 0.15:
            args.insert(-2, "--fit")
        counts[f"img:{kind}"] += 1
        run("image", args, kind, {lname: data}, 60, out)


def part_validate(n):
    src = WORK / "docs"
    src.mkdir(exist_ok=True)
    docs = {}
    CliRunner().invoke(
        main, ["build", "scenes/lab.wd", "--seed", "1", "--pose", "0", "--no-svg", "-o", str(src / "b")]
    )
    CliRunner().invoke(
        main,
        [
            "build",
            "scenes/lab.wd",
            "--seed",
            "1",
            "--pose",
            "0",
            "--trials",
            "2",
            "--format",
            "jsonl",
            "--no-svg",
            "-o",
            str(src / "j"),
        ],
    )
    CliRunner().invoke(main, ["compile", "scenes/lab.wd", "-o", str(src / "scene.json")])
    CliRunner().invoke(
        main,
        [
            "verify",
            "scenes/chessboard.wd",
            "--images",
            "tests/data/opencv_stereo/left01.jpg",
            "--images",
            "tests/data/opencv_stereo/right01.jpg",
            "--poses",
            "board",
            "--detector",
            "canny",
            "-o",
            str(src / "v"),
        ],
    )
    for p in [
        src / "v/verification.json",
        src / "b/features.json",
        src / "b/manifest.json",
        src / "j/features.jsonl",
        src / "j/manifest.json",
        src / "scene.json",
    ]:
        if p.exists():
            docs[p.parent.name + "_" + p.name] = p.read_text()
    names = sorted(docs)
    for _ in range(n):
        name = rng.choice(names)
        text = docs[name]
        if rng.random() < 0.5:
            text = mutate_text(text)
        else:
            # JSON-aware: replace a random number with an extreme one
            nums = list(re.finditer(r"-?\d+(\.\d+)?([eE][-+]?\d+)?", text))
            if nums:
                m = rng.choice(nums)
                text = (
                    text[: m.start()]
                    + rng.choice(
                        [
                            "1e308",
                            "-0",
                            "1e-320",
                            "1e309",
                            "NaN",
                            "Infinity",
                            "-1",
                            "99999999999999999999999",
                            "0.5",
                            "true",
                            "null",
                            '"x"',
                            "[]",
                            "{}",
                        ]
                    )
                    + text[m.end() :]
                )
        f = WORK / ("v_" + name.split("_", 1)[1])
        f.write_text(text, encoding="utf-8", errors="surrogateescape")
        run("validate", ["validate", str(f)], name, {name: text}, 20)


for part in PARTS:
    t0 = time.monotonic()
    {"scenes": part_scenes, "traj": part_traj, "calib": part_calib, "images": part_images, "validate": part_validate}[
        part
    ](N)
    print(f"part {part}: {N} in {time.monotonic() - t0:.0f}s", flush=True)
(OUT / "summary.json").write_text(json.dumps({"counts": counts, "findings": findings}, indent=1))
print(json.dumps(counts, indent=1))
