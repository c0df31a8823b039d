"""The `board` statement (a calibration board as a model) and `board_poses` (each image's pose from it)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

import wiredsl
from wiredsl.cli import main
from wiredsl.diagnostics import WiredslError
from wiredsl.engine import geometry
from wiredsl.scene import Pipeline
from wiredsl.verify.board import board_poses

BOARD = """wiredsl 1
scene boards
{board}
place target as b1 at (1.1m, -0.26m, 1.15m) rotate y 90deg rotate x 90deg rotate z 12deg
camera eye {{
  focal 640px
  size (640px, 480px)
  centre (318.2px, 243.9px)
  k1 -0.05
}}
rig pair {{
  left eye at (0, 0.05m, 1.2m) looking (1, 0, 0)
  right eye at (0, -0.05m, 1.2m) looking (1, 0, 0)
}}
path here {{
  pose (0, 0) heading 0deg
  pose (0.08m, 0.05m) heading 6deg
  pose (-0.1m, -0.04m) heading -5deg
}}
"""
CHESS = "board target chessboard inner (9, 6) square 30mm"
CHARUCO = "board target charuco squares (7, 5) square 40mm marker 30mm dictionary DICT_5X5_100"
ACIRCLES = "board target acircles dots (4, 5) spacing 30mm diameter 20mm"
CIRCLES = "board target circles dots (7, 5) spacing 35mm diameter 18mm"


def _scene(tmp_path: Path, board: str) -> Path:
    path = tmp_path / "boards.wd"
    path.write_text(BOARD.format(board=board))
    return path


def test_a_chessboard_is_a_model_of_corners_lines_and_a_face():
    scene = wiredsl.compile(BOARD.format(board="board target chessboard inner (4, 3) square 25mm margin 1cm"))
    m = scene.model("target")
    assert m.board.kind == "chessboard" and (m.board.columns, m.board.rows) == (5, 4) and m.board.inner == (4, 3)
    # the inner corners in OpenCV's order (row by row), the first at the origin
    want = [(i * 0.025, j * 0.025, 0.0) for j in range(3) for i in range(4)]
    assert np.allclose([c.at for c in m.corners], want)
    assert [c.name for c in m.corners][:5] == ["c0_0", "c0_1", "c0_2", "c0_3", "c1_0"]
    assert m.corners[5].joins == ["v1", "h1"]
    names = {ln.name for ln in m.lines}
    assert {"v0", "v3", "h0", "h2"} <= names and "v4" not in names
    # every border segment lies along a dark outer square: square (a, b) is dark when a + b is even
    for ln in m.lines:
        if ln.name[0] in "tblr" and not ln.name.startswith("h"):
            mid = (np.array(ln.start) + np.array(ln.end))[:2] / 2 / 0.025 + 1  # in squares from the outer corner
            inward = {"t": (0, 0.5), "b": (0, -0.5), "l": (0.5, 0), "r": (-0.5, 0)}[ln.name[0]]
            a, b = np.floor(mid + inward).astype(int)
            assert (a + b) % 2 == 0, ln.name
    (face,) = m.faces
    assert np.allclose(face.vertices, [(-0.035, -0.035, 0), (0.11, -0.035, 0), (0.11, 0.085, 0), (-0.035, 0.085, 0)])
    # an ordinary model's dump has no board key
    assert "board" not in scene.model_dump(mode="json")["models"][0] or scene.models[0].board is not None


@pytest.mark.parametrize("board", [CHESS, CHARUCO, ACIRCLES, CIRCLES],
                         ids=["chessboard", "charuco", "acircles", "circles"])
def test_rendered_boards_give_back_the_poses_they_were_rendered_from(tmp_path, board):
    path = _scene(tmp_path, board)
    r = CliRunner().invoke(main, ["render", str(path), "-o", str(tmp_path / "r"), "--edges", "none", "--blur", "0.7",
                                  "--noise", "1.5", "--seed", "3"])
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "r" / "render.json").read_text())
    scene = wiredsl.compile(path)
    model = scene.model("target")
    place = scene.placements[0]
    points = model.board.centres() if model.board.circles else np.array([c.at for c in model.corners])
    X = points @ np.array(place.rotation).T + np.array(place.position)
    for side in ("left", "right"):
        files = [tmp_path / "r" / f"{side}_{k:03d}.png" for k in range(3)]
        found = board_poses(scene, files, side)
        assert found.diagnostics == [] and len(found.found) == 3
        for k, p in enumerate(found.poses):
            view = doc["poses"][k]["images"][side]
            R, t = np.array(view["R_cw"]), np.array(view["t_cw"])
            # the detected corners against OpenCV's projection of the board under the rendered pose
            cam = doc["cameras"][side]
            uv, _ = cv2.projectPoints(X[p.ids], cv2.Rodrigues(R)[0], t, np.array(cam["K"]),
                                      np.array([cam["coefficients"][c] for c in ("k1", "k2", "p1", "p2", "k3")]))
            uv = uv.reshape(-1, 2)
            if "circles dots (7, 5)" in board and (uv[-1, 0], uv[-1, 1]) < (uv[0, 0], uv[0, 1]):
                R, t = _half_turn(R, t, X)  # a symmetric grid's pose is the one whose first dot is leftmost
                uv = uv[::-1]
            err = np.linalg.norm(uv - p.corners, axis=1)
            # (a dot's centroid is off the projection of its centre by a few hundredths of a pixel here)
            assert np.sqrt(np.mean(err ** 2)) < 0.25 and p.rms < 0.25, (err.max(), p.rms)
            assert len(p.ids) == {"chessboard": 54, "charuco": 24, "acircles": 20, "circles": 35}[model.board.kind] \
                or "charuco" in board and len(p.ids) >= 12
            # a board 30 cm wide at 1.1 m, its corners found to 0.15 px: its tilt is known to a few tenths of a degree
            angle = np.degrees(np.arccos(np.clip((np.trace(p.R_cw @ R.T) - 1) / 2, -1, 1)))
            assert angle < 0.8 and np.linalg.norm(p.t_cw - t) < 0.015, (angle, p.t_cw - t)
            # the robot pose the engine takes, through the mount, is the path's pose
            if np.allclose(R, np.array(view["R_cw"])):  # (not for a symmetric grid seen turned: the other pose)
                Rw, tw = geometry.world_from_robot(p.robot_pose)
                Rp, tp = geometry.world_from_robot(scene.path.pose(k))
                assert np.linalg.norm(tw - tp) < 0.03 and np.abs(Rw - Rp).max() < 0.015


def _half_turn(R_cw, t_cw, X):
    """The camera pose that sees the board points X (n, 3, world) turned half a turn about their centre's normal:
    the pose from which dot k is where dot n - 1 - k was."""
    c = X.mean(axis=0)
    _, _, vt = np.linalg.svd(X - c)
    n = vt[2]
    H = 2 * np.outer(n, n) - np.eye(3)  # a half turn about n: v -> 2 (v.n) n - v
    # X_cam = R (H (X - c) + c) + t: the world turned, seen from the same camera
    return R_cw @ H, R_cw @ (c - H @ c) + t_cw


def test_a_board_missing_from_images_is_located_and_too_few_is_an_error(tmp_path):
    path = _scene(tmp_path, CHESS)
    r = CliRunner().invoke(main, ["render", str(path), "-o", str(tmp_path / "r"), "--edges", "none", "--seed", "1",
                                  "--cameras", "left"])
    assert r.exit_code == 0, r.output
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((480, 640), 128, np.uint8))
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.full((240, 320), 128, np.uint8))
    junk = tmp_path / "junk.jpg"
    junk.write_bytes(b"\xff\xd8\xff not a jpeg")
    scene = wiredsl.compile(path)
    good = [tmp_path / "r" / f"left_{k:03d}.png" for k in range(3)]
    found = board_poses(scene, [*good, blank], "left")
    assert len(found.found) == 3 and not found.poses[3].found
    (d,) = found.diagnostics
    assert d.code == "W196" and d.span.file == str(blank) and "9 x 6 inner corners" in d.message
    with pytest.raises(WiredslError) as err:
        board_poses(scene, [good[0], blank, small, junk], "left")
    codes = [x.code for x in err.value.diagnostics]
    assert codes == ["W196", "E199", "E199", "E197"]
    assert "found in 1 of 4 images (at least 2 needed)" in err.value.diagnostics[-1].message
    assert "320 x 240 px" in err.value.diagnostics[1].message
    with pytest.raises(WiredslError) as err:
        board_poses(scene, good, "nosuchcamera")
    assert err.value.diagnostics[0].code == "E198"


def test_a_circle_grid_is_a_model_of_dots_in_opencvs_order():
    """OpenCV's object points (its calibration sample's): a symmetric grid's dot (row j, column i) at (i, j) s, an
    asymmetric one's at (2 i + j % 2, j) s; each dot an ellipse (a circle) of the declared diameter."""
    for decl, want in ((ACIRCLES, [((2 * i + j % 2) * 0.03, j * 0.03) for j in range(5) for i in range(4)]),
                       (CIRCLES, [(i * 0.035, j * 0.035) for j in range(5) for i in range(7)])):
        m = wiredsl.compile(BOARD.format(board=decl)).model("target")
        assert m.lines == [] and m.corners == [] and len(m.ellipses) == len(want)
        assert np.allclose([e.centre[:2] for e in m.ellipses], want) and not np.any([e.centre[2] for e in m.ellipses])
        assert np.allclose(m.board.centres()[:, :2], want)
        r = 0.01 if m.board.kind == "acircles" else 0.009
        assert all(e.a == e.b == pytest.approx(r) for e in m.ellipses)
        assert m.ellipses[5].name == ("o1_1" if m.board.kind == "acircles" else "o0_5")
        # the face spans the dots and a margin (one spacing) beyond their edges
        (face,) = m.faces
        lo, hi = np.min(face.vertices, axis=0), np.max(face.vertices, axis=0)
        s = m.board.square
        assert np.allclose(lo[:2], np.min(want, axis=0) - r - s) and np.allclose(hi[:2], np.max(want, axis=0) + r + s)


@pytest.mark.parametrize(("decl", "code", "says"), [
    ("board target circles dots (7, 5) spacing 35mm", "E102", "needs 'diameter'"),
    ("board target acircles dots (4, 5) diameter 20mm", "E102", "needs 'spacing'"),
    ("board target circles inner (7, 5) spacing 35mm diameter 10mm", "E103", "takes 'dots', not 'inner'"),
    ("board target circles dots (7, 5) square 35mm spacing 35mm diameter 10mm", "E103", "'square' is a"),
    ("board target chessboard inner (9, 6) square 30mm diameter 10mm", "E103", "'diameter' is a"),
    ("board target circles dots (7, 5) spacing 35mm diameter 35mm", "E110", "smaller than it"),
    ("board target acircles dots (4, 5) spacing 30mm diameter 43mm", "E110", "smaller than it"),  # > 30 sqrt 2
    ("board target circles dots (7, 5) spacing 35mm diameter 0.1mm", "E110", "at least 0.05"),
    ("board target circles dots (2, 5) spacing 35mm diameter 10mm", "E110", "dots must be 3.."),
])
def test_a_bad_circle_grid_is_a_located_error(decl, code, says):
    with pytest.raises(WiredslError) as err:
        wiredsl.compile(BOARD.format(board=decl))
    d = next(d for d in err.value.diagnostics if d.severity == "error")  # (then the placement of no model)
    assert d.code == code and says in d.message, d.message
    assert d.span is not None and d.span.line == 3


def test_a_scene_without_a_board_is_an_error():
    scene = wiredsl.compile(BOARD.format(board="model target {\n  corner c at (0, 0, 0)\n}"))
    with pytest.raises(WiredslError) as err:
        board_poses(scene, [], "left")
    assert err.value.diagnostics[0].code == "E198" and "no placed board" in err.value.diagnostics[0].message


# ----------------------------------------------------------------------------- OpenCV's stereo sample images

STEREO = Path(__file__).resolve().parent / "data" / "opencv_stereo"
CHESSBOARD = Path(__file__).resolve().parent.parent / "scenes" / "chessboard.wd"


def _numbers() -> list[int]:
    return sorted(int(p.stem[4:]) for p in STEREO.glob("left[0-9][0-9].jpg"))


def test_the_board_is_found_in_opencvs_stereo_images_with_a_small_reprojection_error():
    scene = wiredsl.compile(CHESSBOARD)
    numbers = _numbers()
    assert len(numbers) == 13 and 10 not in numbers
    left = board_poses(scene, [STEREO / f"left{n:02d}.jpg" for n in numbers], "left")
    right = board_poses(scene, [STEREO / f"right{n:02d}.jpg" for n in numbers], "right")
    assert len(left.found) == 13 and len(right.found) == 13 and not left.diagnostics
    assert max(p.rms for p in left.poses + right.poses) < 0.4  # px, each image's own pose
    # the scene's ideal projection (its path: the left poses that docs/scripts/calibrate_opencv_stereo.py found
    # with OpenCV alone; its rig: that script's stereoCalibrate) against the corners detected in both images
    (batch,) = wiredsl.simulate(scene, trials=1, seed=0, pipeline=Pipeline(name="ideal"))
    projected = {(r["pose"], r["camera"], r["source"]): np.array(r["at"])
                 for r in batch.records() if r["kind"] == "corner"}
    names = [c.name for c in scene.model("target").corners]
    errors = {"left": [], "right": []}
    for k, (a, b) in enumerate(zip(left.poses, right.poses, strict=True)):
        for side, found in (("left", a), ("right", b)):
            for i, uv in zip(found.ids, found.corners, strict=True):
                key = (k, side, f"board.{names[i]}")
                if key in projected:
                    errors[side].append(np.linalg.norm(projected[key] - uv))
        # the right image's own pose, carried to the robot through the right mount, is the left one's
        Rl, tl = geometry.world_from_robot(a.robot_pose)
        Rr, tr = geometry.world_from_robot(b.robot_pose)
        assert np.linalg.norm(tl - tr) < 0.01 and np.abs(Rl - Rr).max() < 0.02, (k, tl - tr)
        # and the left one is the path's pose (the script's solvePnP, read back through the trajectory file)
        Rp, tp = geometry.world_from_robot(scene.path.pose(k))
        assert np.linalg.norm(tl - tp) < 1e-3 and np.abs(Rl - Rp).max() < 1e-3
    for side in ("left", "right"):
        e = np.array(errors[side])
        assert len(e) == 13 * 54
        assert np.sqrt(np.mean(e ** 2)) < 0.5 and np.median(e) < 0.35, (side, np.sqrt(np.mean(e ** 2)))


def test_the_language_server_takes_a_board_for_a_model(tmp_path):
    from wiredsl import lsp

    text = (Path(__file__).resolve().parent.parent / "scenes" / "chessboard.wd").read_text()
    index = lsp.analyse(str(tmp_path / "chessboard.wd"), text)
    lines = text.splitlines()
    row = next(i for i, line in enumerate(lines) if line.startswith("place target")) + 1
    declared = next(i for i, line in enumerate(lines) if line.startswith("board target")) + 1
    found = lsp.definition(index, index.path, row, lines[row - 1].index("target") + 2)
    assert found is not None and found[1].line == declared
    shown = lsp.hover(index, text, index.path, declared, 2)
    assert shown is not None and "calibration board" in shown


def test_hostile_images_are_diagnostics_before_anything_is_decoded(tmp_path):
    import struct
    import zlib

    scene = wiredsl.compile(CHESSBOARD)
    bomb = tmp_path / "bomb.png"  # a header claiming 30000 x 30000 px, with one row of data
    ihdr = struct.pack(">IIBBBBB", 30000, 30000, 8, 0, 0, 0, 0)
    chunk = lambda tag, data: (struct.pack(">I", len(data)) + tag + data  # noqa: E731
                               + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF))
    bomb.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 30001))
                     + chunk(b"IEND", b""))
    empty = tmp_path / "empty.jpg"
    empty.write_bytes(b"")
    deep = tmp_path / "deep.png"
    cv2.imwrite(str(deep), np.full((480, 640), 40000, np.uint16))  # 16-bit: OpenCV reads it as 8-bit grey
    cut = tmp_path / "cut.jpg"
    cut.write_bytes((STEREO / "left01.jpg").read_bytes()[:3000])  # a JPEG cut short
    good = [STEREO / f"left{n:02d}.jpg" for n in _numbers()]
    found = board_poses(scene, [*good, bomb, empty, deep, cut], "left")
    by_file = {Path(d.span.file).name: d for d in found.diagnostics}
    assert "30000 x 30000 px" in by_file["bomb.png"].message and by_file["bomb.png"].code == "E199"
    assert by_file["empty.jpg"].code == "E199"
    assert by_file["deep.png"].code == "W196" and by_file["cut.jpg"].code in ("E199", "W196")
    assert len(found.found) == 13
