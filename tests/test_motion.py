"""A robot that moves (issue 39): path speeds and velocities, the rolling shutter against a brute-force per-row
projection (OpenCV's own projection, scipy's rotations), on both engines, and a stereo pair's sync offset against
its closed form."""

from __future__ import annotations

import math
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from wiredsl.engine import geometry, motion
from wiredsl.engine.simulate import Options, simulate
from wiredsl.engine.world import build_world
from wiredsl.language.compile import compile_file
from wiredsl.montecarlo import Run

ROOT = Path(__file__).resolve().parents[1]

LENSES = {
    "pinhole": "focal 600px\n  size (640px, 480px)\n  centre (321.5px, 238.2px)\n  k1 -0.02\n  k2 0.001",
    "fisheye": "focal 230px\n  size (1024px, 768px)\n  centre (514.2px, 381.7px)\n  distortion equidistant\n"
               "  k1 -0.0049\n  k2 0.0011\n  k3 -0.0002\n  k4 0.00001\n  fov 190deg",
}


def scene_text(lens: str, speed: str, readout: str = "30ms", sync: str | None = None) -> str:
    sync_line = f"\n  sync {sync}" if sync else ""
    return textwrap.dedent("""\
        wiredsl 1
        scene moving
        model bar {{
          line slant from (0, -0.6, 0.3) to (0.3, 0.5, 1.9)
          line across from (0, -1.5, 1.0) to (0, 1.5, 1.1)
        }}
        place bar as b at (2.5m, 0, 0)
        camera cam {{
          {lens}
          readout {readout}
        }}
        rig head {{
          left cam at (0.1m, 0.06m, 1.0m) looking (1, 0, -0.1){sync}
          right cam at (0.1m, -0.06m, 1.0m) looking (1, 0, -0.1)
          calibration covariance order [left.f] matrix [[1e-24]]
        }}
        path run {{
          pose (0, 0) heading 0
          pose (0.3m, 0.05m) heading 12deg
          pose (0.6m, 0.2m) heading 30deg
          speed {speed}
        }}
        pipeline reproject {{
          calibration_error sigma 1
        }}
        """).format(lens=lens.replace("\n", "\n  "), sync=sync_line, readout=readout, speed=speed)


def compiled(tmp_path, text: str, name: str = "moving.wd"):
    p = tmp_path / name
    p.write_text(text)
    scene, _, _ = compile_file(p)
    return scene


def camera_at(scene, index: int, side: str, tau: float):
    """The camera's (R_cw, t_cw) at `tau` after its pose, from the velocities by scipy's rotation exponential."""
    v, w = motion.velocities_of(scene.path)  # (motion.velocities, once per path)
    R, t = geometry.world_from_robot(scene.path.pose(index))
    R = Rotation.from_rotvec(w[index] * tau).as_matrix() @ R
    t = t + v[index] * tau
    mount = getattr(scene.rig, side)
    R_wc = R @ np.array(mount.rotation)
    t_wc = R @ np.array(mount.position) + t
    return R_wc.T, -R_wc.T @ t_wc


def opencv_pixels(cam, R_cw, t_cw, X):
    """OpenCV's projection of world points X (n, 3): cv2.projectPoints, or cv2.fisheye.projectPoints."""
    K = np.array([[cam.f * cam.ax, 0, cam.cx], [0, cam.f * cam.ay, cam.cy], [0, 0, 1.0]])
    rvec = cv2.Rodrigues(R_cw)[0]
    X = np.asarray(X, float).reshape(-1, 1, 3)
    if cam.distortion == "equidistant":
        uv, _ = cv2.fisheye.projectPoints(X, rvec, t_cw.reshape(3, 1), K, np.array([cam.k1, cam.k2, cam.k3, cam.k4]))
        P = X.reshape(-1, 3) @ R_cw.T + t_cw
        behind = P[:, 2] <= 0  # OpenCV takes theta = atan(rho / Z), in front; Kannala-Brandt's atan2 beyond 90 deg
        if behind.any():
            rho = np.hypot(P[behind, 0], P[behind, 1])
            theta = np.arctan2(rho, P[behind, 2])
            t2 = theta * theta
            scale = theta * (1 + t2 * (cam.k1 + t2 * (cam.k2 + t2 * (cam.k3 + t2 * cam.k4)))) / rho
            uv = uv.reshape(-1, 2)
            uv[behind] = np.column_stack([cam.f * cam.ax * scale * P[behind, 0] + cam.cx,
                                          cam.f * cam.ay * scale * P[behind, 1] + cam.cy])
    else:
        uv, _ = cv2.projectPoints(X, rvec, t_cw, K, np.array([cam.k1, cam.k2, cam.p1, cam.p2, cam.k3]))
    return uv.reshape(-1, 2)


def brute_force_u(scene, index, side, A, B, row, near_u):
    """Where the 3D segment AB crosses image row `row` as the camera at that row's own time sees it: the row's
    time, that camera's pose, the segment sampled densely and the crossing nearest `near_u` refined by brentq."""
    cam = scene.camera(getattr(scene.rig, side).camera)
    R_cw, t_cw = camera_at(scene, index, side, (scene.rig.sync if side == "right" else 0.0)
                           + cam.readout * row / cam.height)

    def at(s):
        return opencv_pixels(cam, R_cw, t_cw, A + np.outer(s, B - A))

    s = np.linspace(-1e-3, 1 + 1e-3, 1001)  # the line a little beyond its ends: a vertex at an end is on it
    uv = at(s)
    d = uv[:, 1] - row
    flips = np.flatnonzero(np.sign(d[:-1]) != np.sign(d[1:]))
    best = None
    for j in flips:
        root = brentq(lambda x: at(np.array([x]))[0, 1] - row, s[j], s[j + 1], xtol=1e-15, rtol=1e-15)
        u = at(np.array([root]))[0, 0]
        if best is None or abs(u - near_u) < abs(best - near_u):
            best = u
    return best


def nearest_brute_force_u(scene, world, index, side, fid, row, u):
    """brute_force_u on each 3D segment of line or polyline `fid`: the crossing nearest u (None: none crosses)."""
    best = None
    for A, B in world.lines[world.line_fid == fid]:
        bf = brute_force_u(scene, index, side, A, B, row, u)
        if bf is not None and (best is None or abs(bf - u) < abs(best - u)):
            best = bf
    return best


def worst_against_brute_force(scene, results, world, stride: int = 1):
    """The largest distance of a line's vertex from the brute force's, over every `stride`-th vertex of each."""
    worst, n = 0.0, 0
    lines = set(world.line_fid.tolist())
    for r in results:
        for side in ("left", "right"):
            for f in getattr(r, side).features:
                if f.kind in ("line", "polyline") and f.fid in lines:
                    for u, v in f.points[::stride]:
                        bf = nearest_brute_force_u(scene, world, r.index, side, f.fid, v, u)  # None: no crossing
                        worst, n = max(worst, math.inf if bf is None else abs(bf - u)), n + 1
    return worst, n


def rolling_scene(tmp_path, where: str, lens: str, speed: str, readout: str = "30ms"):
    """The bar (scene_text) or scenes/lab.wd with 30 ms rolling shutters and the right camera 10 ms late, driven at
    `speed`; the lab's cameras given the lens `lens` (its pinhole's own, or LENSES['fisheye'])."""
    if where == "bar":
        return compiled(tmp_path, scene_text(LENSES[lens], speed, readout=readout), f"bar-{readout}.wd")
    scene = lab(tmp_path, "10ms", speed, readout=readout, lens=lens)
    # a pipeline of calibration draws that move no pixel by more than 1e-9 px: every trial re-projected
    (tmp_path / "lab-reprojected.wd").write_text('wiredsl 1\ninclude "lab.wd"\npipeline reproject {\n'
                                                 "  calibration_error sigma 1e-15\n}\n")
    return compile_file(tmp_path / "lab-reprojected.wd")[0] if scene else scene


# (scene, speed, poses): the lab at 4 m/s includes poses 5 and 6, beside the table, where the fixed point alone
# does not settle (q > 1 for points of the table next to the camera)
ROLLING_CASES = [("bar", "0.5m/s", None), ("bar", "3m/s", None), ("lab", "4m/s", [5, 6])]


@pytest.mark.parametrize("lens", sorted(LENSES))
@pytest.mark.parametrize(("where", "speed", "poses"), ROLLING_CASES)
def test_rolling_shutter_lines_agree_with_a_brute_force_projection_row_by_row(tmp_path, lens, where, speed, poses):
    scene = rolling_scene(tmp_path, where, lens, speed)
    world = build_world(scene)
    results = simulate(scene, Options(poses=poses), world)
    worst, n = worst_against_brute_force(scene, results, world, 1 if where == "bar" else 5)
    assert n > 30 and worst < 1e-6, (n, worst)
    # the same scene with a global shutter images the lines elsewhere: the test can fail
    still = rolling_scene(tmp_path, where, lens, speed, readout="0ms")
    fixed = {f.fid: f for f in simulate(still, Options(poses=poses))[1].left.features if f.kind != "corner"}
    moved = max(np.abs(a.points[[0, -1]] - fixed[a.fid].points[[0, -1]]).max() for a in results[1].left.features
                if a.fid in fixed)
    assert moved > 0.5


def test_a_turning_robots_sync_and_rolling_shutter_agree_with_the_brute_force(tmp_path):
    """The right camera 7 ms late on a path that turns: its rows from the robot's pose 7 ms + its row's time on."""
    scene = compiled(tmp_path, scene_text(LENSES["pinhole"], "3m/s", sync="7ms"))
    assert scene.rig.sync == 0.007 and np.abs(motion.velocities(scene.path)[1][:, 2]).max() > 0.5
    world = build_world(scene)
    worst, n = worst_against_brute_force(scene, simulate(scene, Options(), world), world)
    assert n > 40 and worst < 1e-6, (n, worst)


@pytest.mark.parametrize("engine", ["numpy", "kernel"])
@pytest.mark.parametrize("lens", sorted(LENSES))
@pytest.mark.parametrize(("where", "speed", "trials"), [("bar", "3m/s", [0, 1]), ("lab", "4m/s", [6])])
def test_rolling_shutter_reprojected_by_both_engines_agrees_with_the_brute_force(tmp_path, engine, lens, where, speed,
                                                                                 trials):
    scene = rolling_scene(tmp_path, where, lens, speed)
    world = build_world(scene)
    run = Run.create(scene, world, scene.pipeline("reproject"), 5, Options())
    run.engine = engine
    assert run.uses_kernel() == (engine == "kernel")
    (_, out), = list(run.batches(trials, 2))  # every pose (the lab's 5 and 6 too), trial 0 of the batch checked
    lines = set(world.line_fid.tolist())
    worst, n = 0.0, 0
    for r, sets, _ in out:
        for side, s in sets.items():
            cam = scene.camera(getattr(scene.rig, side).camera)
            for i in np.flatnonzero(s.trial == 0):
                fid = int(s.fid[i])
                if fid not in lines:
                    continue
                for u, v in s.pts[s.start[i]:s.start[i + 1]][::1 if where == "bar" else 5]:
                    if min(u, v, cam.width - u, cam.height - v) < 1e-6:
                        continue  # a cut at the image border: on the chord between two re-projected vertices
                    bf = nearest_brute_force_u(scene, world, r.index, side, fid, v, u)
                    worst, n = max(worst, math.inf if bf is None else abs(bf - u)), n + 1
    # the bar's draws' covariance of 1e-24 px^2 moves nothing by more than 1e-11 px, nor the lab's sigma 1e-15
    assert n > 30 and worst < 1e-6, (n, worst)


@pytest.mark.parametrize("sync", ["7ms", "7ms jitter 2ms"])
def test_both_engines_agree_under_a_rolling_shutter_and_sync(tmp_path, sync):
    scene = compiled(tmp_path, scene_text(LENSES["pinhole"], "2m/s", sync=sync).replace("1e-24", "4"))
    world = build_world(scene)
    got = {}
    for engine in ("numpy", "kernel"):
        run = Run.create(scene, world, scene.pipeline("reproject"), 11, Options())
        run.engine = engine
        got[engine] = [out for _, out in run.batches(range(8), 8)]
    for (rn, dn, _), (_, dk, _) in zip(got["numpy"][0], got["kernel"][0], strict=True):
        for side in dn:
            a, b = dn[side], dk[side]
            for name in ("start", "fid", "segment", "fragment", "kind", "clipped", "trial", "corner_fid"):
                assert np.array_equal(getattr(a, name), getattr(b, name)), (rn.index, side, name)
            assert np.abs(a.pts - b.pts).max(initial=0) < 1e-9


def test_the_row_time_solver_converges_as_stated():
    """r = row(t(r)) for a point moving across rows at a known speed: the fixed point's error shrinks by q = readout
    |dr/dt| / height an iteration; a point whose image crosses more rows in a readout than the image has (q > 1),
    where the iteration oscillates away, is solved by the bracket to the same 1e-9 px; a point beyond the image all
    readout long takes the nearest row's time, and one above the image at the first row's time that comes down
    faster than the readout sweeps is imaged where it meets the sweep."""
    height, readout = 480.0, 0.03

    def run(rate, start=100.0):  # the image row of a point that moves `rate` px/s down the image: start + rate t
        calls = []

        def pixels(X):
            calls.append(1)
            return np.stack([X[..., 0], X[..., 1]], axis=-1)
        X = np.array([[5.0, start, 0.0]])
        # v moves the world point against the robot: a robot moving by -v makes its row grow by `rate` a second
        uv = motion.rolling_pixels(X, pixels, readout, height, np.zeros(3), np.array([0.0, -rate, 0.0]),
                                   np.zeros(3))
        return uv[0, 1], len(calls)

    def exact(rate, start=100.0):  # r = start + rate readout r / height
        return start / (1 - rate * readout / height)

    row, calls = run(1000.0)  # q = 0.03 * 1000 / 480 = 0.0625
    assert abs(row - exact(1000.0)) < 1e-9
    # each iteration gains log10(1 / q) = 1.2 digits from an error of 6.7 px: 1e-9 px needs about 9
    assert calls - 1 <= math.ceil(math.log(6.7 / 1e-9) / math.log(1 / 0.0625)) + 1
    for rate in (-12000.0, -20000.0, -100000.0):  # q = 0.75, 1.25, 6.25 up the image: the bracket (measured 4-5)
        row, calls = run(rate)
        assert abs(row - exact(rate)) < 1e-9 and calls < 20, (rate, row, calls)
    row, _ = run(48000.0)  # q = 3 down the image from row 100: below the last row all readout, f(H) = 1540
    assert abs(row - (100.0 + 48000.0 * readout)) < 1e-9
    row, _ = run(-1000.0, -50.0)  # above the image all readout: the first row's time, its row at time 0
    assert row == -50.0
    row, _ = run(48000.0, -50.0)  # above the image at first, coming down at q = 3: meets the sweep at row 25
    assert abs(row - exact(48000.0, -50.0)) < 1e-9 and abs(row - 25.0) < 1e-9


@pytest.mark.parametrize(("Y", "roots"), [(0.05, (312.43, 460.90)), (0.065, (360.0, 413.33))])
def test_a_point_imaged_at_two_rows_takes_the_earliest_on_both_engines(tmp_path, Y, roots):
    """A point 1 m ahead, 5 or 6.5 cm below the axis, the robot driving at it at 30 m/s: its image runs down the
    image faster and faster, and meets the readout's sweep twice (g(0) > 0 and g(H) > 0, an even number of roots).
    Both engines image it at the earlier row, the first the sensor reads it at, found by dense sampling of g with
    the pinhole formula and brentq (independent of the solver). The first case's fixed point contracts (q = 0.33
    at the earlier root); the second's does not (0.69), and the grid finds the earlier bracket."""
    from wiredsl.engine import kernel

    speed = 30.0
    text = scene_text("focal 600px\n  size (640px, 480px)\n  centre (320px, 240px)", "1m/s")
    cam = compiled(tmp_path, text).camera("cam")
    readout, H = 0.03, 480.0
    g = lambda r: 240.0 + 600.0 * Y / (1.0 - speed * readout * r / H) - r  # noqa: E731
    rs = np.linspace(0.0, H, 47777)
    gs = g(rs)
    flips = np.flatnonzero((gs[:-1] > 0) != (gs[1:] > 0))
    found = [brentq(g, rs[j], rs[j + 1], xtol=1e-13) for j in flips]
    assert len(found) == 2 and np.allclose(found, roots, atol=0.01) and gs[0] > 0 and gs[-1] > 0, found
    X = np.array([[0.0, Y, 1.0], [0.2, Y, 1.0]])  # the second point right of the first: the same rows
    v = np.array([0.0, 0.0, speed])  # camera frame = world frame, the robot's origin at the camera
    table = geometry.camera_table(cam)
    numpy_uv = motion.rolling_pixels(X, lambda P: geometry.project(P, table), readout, H, np.zeros(3), v, np.zeros(3))
    row = np.array([table[k] for k in geometry.CAMERA_ROW], dtype=float)
    kernel_uv, ok = np.empty((2, 2)), np.empty(2, dtype=bool)
    kernel._project_rolling(X, np.eye(3), np.zeros(3), row, table["limit"], np.array(
        [readout, H, 0, 0, 0, *v, 0, 0, 0], dtype=float), kernel_uv, ok)
    assert ok.all()
    for uv in (numpy_uv, kernel_uv):
        assert np.abs(uv[:, 1] - found[0]).max() < 1e-6, (uv, found)
        tau = readout * uv[:, 1] / H  # and the column is the pinhole's at that row's time
        assert np.abs(uv[:, 0] - (320.0 + 600.0 * X[:, 0] / (1.0 - speed * tau))).max() < 1e-6
    assert np.abs(numpy_uv - kernel_uv).max() < 1e-9


def test_velocities_of_a_straight_run_and_of_an_arc(tmp_path):
    text = scene_text(LENSES["pinhole"], "2m/s").replace(
        "pose (0, 0) heading 0\n  pose (0.3m, 0.05m) heading 12deg\n  pose (0.6m, 0.2m) heading 30deg",
        "straight from (0, 0) to (1m, 1m) step 0.1m")
    scene = compiled(tmp_path, text)
    v, w = motion.velocities(scene.path)
    assert np.allclose(v, [2 / math.sqrt(2), 2 / math.sqrt(2), 0], atol=1e-12) and np.allclose(w, 0, atol=1e-12)
    # poses on a circle of radius 2 m, 5 deg apart, facing along it: speed 2 m/s turns at 1 rad/s
    arc = "\n  ".join(f"pose ({2 * math.sin(a):.12f}m, {2 - 2 * math.cos(a):.12f}m) heading {math.degrees(a):.12f}deg"
                      for a in np.radians(np.arange(0, 60, 5)))
    scene = compiled(tmp_path, scene_text(LENSES["pinhole"], "2m/s").replace(
        "pose (0, 0) heading 0\n  pose (0.3m, 0.05m) heading 12deg\n  pose (0.6m, 0.2m) heading 30deg", arc))
    v, w = motion.velocities(scene.path)
    speed = np.linalg.norm(v, axis=1)
    # the poses are timed by their chords (2 sin 2.5 deg * 2 = 0.9997 of the arc): the interior tangents are
    # the circle's to the chords' O(h^2)
    assert np.allclose(speed[1:-1], 2 * (2 * math.sin(math.radians(2.5))) / math.radians(5) * 1, rtol=1e-3)
    assert np.allclose(w[1:-1, 2], 2 / 2 * (2 * math.sin(math.radians(2.5))) / math.radians(5), rtol=1e-3)


def lab(tmp_path, sync: str, speed: str = "1m/s", readout: str | None = None, lens: str = "pinhole",
        name: str = "lab.wd"):
    """scenes/lab.wd driven at `speed`, its right camera exposed `sync` after the left; with a `readout`, both
    cameras' rolling shutters, and with lens 'fisheye', both cameras LENSES['fisheye'] (the left's centre)."""
    text = (ROOT / "scenes/lab.wd").read_text().replace('include "', f'include "{ROOT}/scenes/').replace(
        'file "lab.info"', f'file "{ROOT}/scenes/lab.info"')
    text = text.replace("step 0.4m", f"step 0.4m\n  speed {speed}").replace("  right cam_r at",
                                                                          f"  sync {sync}\n  right cam_r at")
    if lens == "fisheye":
        pinhole = "  focal 6mm\n  pixel 0.01mm\n  size (640px, 480px)\n  centre (321.5px, 238.2px)\n  k 0.02\n"
        assert pinhole in text and "  k 0.018\n" in text
        fisheye = LENSES["fisheye"].replace("\n", "\n  ")
        text = text.replace(pinhole, "  " + fisheye + "\n").replace("  k 0.018\n", "")
    if readout is not None:
        text = text.replace("camera cam_l {\n", f"camera cam_l {{\n  readout {readout}\n").replace(
            "camera cam_r like cam_l {\n", f"camera cam_r like cam_l {{\n  readout {readout}\n")
    return compiled(tmp_path, text, name)


def closed_form_errors(scene, world, result, offset: float, speed: float) -> dict[int, float]:
    """Each corner's 3D error when the right camera is exposed `offset` late on a robot driving straight at
    `speed`: that camera has moved d = speed offset along the heading, so it sees the corner at X_r - d (its own
    frame; the lab's two cameras share their axes, baseline b along x), and the depth that the horizontal disparity
    gives, Z' = b / (x_l - x_r'), puts the corner at Z' (x_l, y_l, 1) on the left camera's ray."""
    R, T = scene.rig.stereo_extrinsics()
    assert np.allclose(R, np.eye(3)) and np.allclose(T[1:], 0)
    b = -T[0]
    heading = result.pose[2]
    d = speed * offset * np.array([math.cos(heading), math.sin(heading), 0.0])
    out = {}
    for fid, X in zip(world.corner_fid.tolist(), world.corners, strict=True):
        Xl = result.left.R_cw @ X + result.left.t_cw
        Xr = Xl + T - result.left.R_cw @ d
        Z = b / (Xl[0] / Xl[2] - Xr[0] / Xr[2])
        out[fid] = float(np.linalg.norm(Z * np.array([Xl[0] / Xl[2], Xl[1] / Xl[2], 1.0]) - Xl))
    return out


def test_a_stereo_sync_offset_of_10ms_on_the_lab_at_1mps_gives_the_closed_form_3d_error(tmp_path):
    """stereo3d's corner error (DLT with the nominal rig, the robot's belief) against the closed form: every pose's
    mean, and each corner, within 7% (measured: 5.7% at most; the closed form triangulates with the horizontal
    disparity alone, the DLT also weighs the vertical disparity the forward step adds). An offset 30% off would
    miss by 30%: the check can fail."""
    from wiredsl.measures.stereo3d import Stereo3D, Stereo3DParams, triangulate, undistort

    scene = lab(tmp_path, "10ms")
    world = build_world(scene)
    run = Run.create(scene, world, None, 0, Options())
    p = Stereo3DParams()
    prep = Stereo3D.prepare(p, run)
    (_, results), = list(run.batches([0]))
    checked = 0
    for result, disturbed, _ in results:
        predicted = closed_form_errors(scene, world, result, 0.010, 1.0)
        both = np.intersect1d(disturbed["left"].corner_fid, disturbed["right"].corner_fid)
        if len(both) == 0:
            continue
        got = Stereo3D.measure(p, prep, result, disturbed, 1)
        expected = np.mean([predicted[f] for f in both.tolist()])
        assert got["corners"][0] == len(both)
        assert abs(got["corner_error"][0] - expected) < 0.07 * expected, (result.index, got["corner_error"], expected)
        assert expected > 0.015  # centimetres: the effect is there to be predicted
        for f in both.tolist():  # and each corner on its own, triangulated as stereo3d does
            uv = {side: disturbed[side].corners[disturbed[side].corner_fid == f] for side in ("left", "right")}
            x = {side: undistort(uv[side], prep.cameras[(result.index, side)].model)[0] for side in uv}
            X, _ = triangulate(prep.cameras[(result.index, "left")].P, prep.cameras[(result.index, "right")].P,
                               x["left"], x["right"])
            err = float(np.linalg.norm(X[0] - world.corners[list(world.corner_fid).index(f)]))
            assert abs(err - predicted[f]) < 0.07 * predicted[f], (result.index, f, err, predicted[f])
            checked += 1
    assert checked >= 20
    # without the offset the same corners are exact: the error is the offset's
    still = Run.create(compile_file(ROOT / "scenes/lab.wd")[0], world, None, 0, Options())
    (_, results), = list(still.batches([0]))
    prep = Stereo3D.prepare(p, still)
    assert max(Stereo3D.measure(p, prep, r, d, 1)["corner_error"][0] for r, d, _ in results) < 1e-6


def corner_errors_by_trial(prep, result, disturbed, world) -> dict[int, dict[int, float]]:
    """{corner fid: {trial: 3D error}} of the corners seen in both images, triangulated as stereo3d does."""
    from wiredsl.measures.stereo3d import triangulate, undistort

    left, right = prep.cameras[(result.index, "left")], prep.cameras[(result.index, "right")]
    sl, sr = disturbed["left"], disturbed["right"]
    F = len(world.feature_ids)
    _, il, ir = np.intersect1d(sl.corner_trial.astype(np.int64) * F + sl.corner_fid,
                               sr.corner_trial.astype(np.int64) * F + sr.corner_fid, return_indices=True)
    X, _ = triangulate(left.P, right.P, undistort(sl.corners[il], left.model)[0],
                       undistort(sr.corners[ir], right.model)[0])
    truth = dict(zip(world.corner_fid.tolist(), world.corners, strict=True))
    out: dict[int, dict[int, float]] = {}
    for x, f, k in zip(X, sl.corner_fid[il].tolist(), sl.corner_trial[il].tolist(), strict=True):
        out.setdefault(f, {})[k] = float(np.linalg.norm(x - truth[f]))
    return out


def test_a_sync_jitter_spreads_the_3d_error_as_the_closed_form_predicts(tmp_path):
    """`sync 10ms jitter 3ms` on the lab at 1 m/s: each trial and pose draws the right camera's offset from
    N(10 ms, 3 ms), and each corner's 3D error is the closed form's at the trial's own offset (within 12%: the
    10 ms test's 7% grows with the offset). Over 96 trials the errors' mean and standard deviation match the
    closed form's under the normal (Gauss-Hermite quadrature over the offset), a spread of over a fifth of the
    mean that a sync without jitter does not have."""
    from wiredsl.measures.stereo3d import Stereo3D, Stereo3DParams

    N = 96
    scene = lab(tmp_path, "10ms jitter 3ms")
    assert (scene.rig.sync, scene.rig.jitter) == (0.010, 0.003)
    world = build_world(scene)
    run = Run.create(scene, world, None, 0, Options())
    prep = Stereo3D.prepare(Stereo3DParams(), run)
    (_, results), = list(run.batches(range(N), N))
    nodes, weights = np.polynomial.hermite_e.hermegauss(24)  # E f(x), x ~ N(0, 1): sum(w f(nodes)) / sqrt(2 pi)
    weights = weights / math.sqrt(2 * math.pi)
    offsets_all, checked, spreads, worst = [], 0, [], 0.0
    for result, disturbed, _ in results:
        offsets = motion.sync_offsets(scene.rig, np.arange(N), result.index, 0)
        offsets_all.append(offsets)
        by_offset = [closed_form_errors(scene, world, result, float(o), 1.0) for o in offsets]
        quadrature = [closed_form_errors(scene, world, result, 0.010 + 0.003 * float(x), 1.0) for x in nodes]
        for f, errs in corner_errors_by_trial(prep, result, disturbed, world).items():
            if len(errs) < N:  # a corner some offsets take out of the image
                continue
            got = np.array([errs[k] for k in range(N)])
            predicted = np.array([by_offset[k][f] for k in range(N)])
            worst = max(worst, float(np.max(np.abs(got - predicted) / predicted)))
            q = np.array([d[f] for d in quadrature])
            mean = float(weights @ q)
            sd = math.sqrt(float(weights @ (q - mean) ** 2))
            assert abs(got.mean() - mean) < 0.07 * mean + 3 * sd / math.sqrt(N), (result.index, f, got.mean(), mean)
            assert abs(got.std(ddof=1) - sd) < 0.07 * sd + 3 * sd / math.sqrt(2 * (N - 1)), (result.index, f,
                                                                                               got.std(), sd)
            spreads.append(sd / mean)
            checked += 1
    # measured: 10.9% at most (the closed form leaves out the vertical disparity, whose share grows with the
    # offset: 5.7% at 10 ms, the draws reach 19 ms), a spread of 0.29 of the mean at least
    assert checked >= 20 and worst < 0.12 and min(spreads) > 0.2, (checked, worst, min(spreads))
    offsets_all = np.concatenate(offsets_all)  # the draws: N(10 ms, 3 ms)
    assert abs(offsets_all.mean() - 0.010) < 3 * 0.003 / math.sqrt(len(offsets_all))
    assert abs(offsets_all.std(ddof=1) / 0.003 - 1) < 3 / math.sqrt(2 * len(offsets_all))


def test_a_sync_jitter_is_keyed_and_costs_nothing_undeclared(tmp_path):
    """The same seed gives identical bytes, a trial replays alone as in its batch, another seed draws other
    offsets; `jitter 0ms` builds the scene, and runs it, exactly as without the clause."""
    scene = lab(tmp_path, "10ms jitter 2ms")
    world = build_world(scene)

    def right(seed, trials, poses=(3, 6)):  # the right camera's sets at two poses, the trials in one batch
        run = Run.create(scene, world, None, seed, Options())
        (_, out), = list(run.batches(trials, len(trials)))
        return [d["right"] for r, d, _ in out if r.index in poses]

    def trial_of(s, k):
        keep = s.corner_trial == k
        return s.corners[keep].tobytes() + s.corner_fid[keep].tobytes()

    batch = right(7, list(range(6)))
    again = right(7, list(range(6)))
    assert all(a.corners.tobytes() == b.corners.tobytes() and a.pts.tobytes() == b.pts.tobytes()
               for a, b in zip(batch, again, strict=True))
    alone = right(7, [4])
    assert all(trial_of(a, 4) == trial_of(b, 0) for a, b in zip(batch, alone, strict=True))
    assert all(trial_of(a, 4) != trial_of(b, 4) for a, b in zip(batch, right(8, list(range(6))), strict=True))
    assert len({trial_of(batch[0], k) for k in range(6)}) == 6  # each trial its own offset
    plain = lab(tmp_path, "10ms", name="plain.wd")
    zero = lab(tmp_path, "10ms jitter 0ms", name="zero.wd")
    assert zero.rig.jitter == 0 and zero.model_dump() == plain.model_dump() | {"source": zero.source}
    assert not Run.create(zero, world, None, 7, Options()).jittered()


def test_a_speed_alone_changes_no_image(tmp_path):
    """Times without a readout or a sync: every feature of the lab bit for bit as without them."""
    text = (ROOT / "scenes/lab.wd").read_text().replace('include "', f'include "{ROOT}/scenes/').replace(
        'file "lab.info"', f'file "{ROOT}/scenes/lab.info"').replace("step 0.4m", "step 0.4m\n  speed 1m/s")
    moving, still = compiled(tmp_path, text, "lab.wd"), compile_file(ROOT / "scenes/lab.wd")[0]
    assert moving.path.times is not None
    for a, b in zip(simulate(moving), simulate(still), strict=True):
        for side in ("left", "right"):
            fa, fb = getattr(a, side).features, getattr(b, side).features
            assert len(fa) == len(fb) > 0
            assert all(x.fid == y.fid and x.kind == y.kind and x.points.tobytes() == y.points.tobytes()
                       for x, y in zip(fa, fb, strict=True))


def test_a_scene_without_motion_builds_as_before_and_imports_nothing_new():
    code = ("import sys; from wiredsl.language.compile import compile_file; from wiredsl.engine.simulate import "
            "simulate; s = compile_file('scenes/lab.wd')[0]; simulate(s); "
            "print('wiredsl.engine.motion' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


@pytest.mark.parametrize(("line", "message"), [
    ("readout -5ms", "error[E110]: a readout time must be in [0, 1000] ms, got -5 ms"),
    ("readout 2s", "error[E110]: a readout time must be in [0, 1000] ms, got 2000 ms"),
    ("readout 30px", "error[E107]: expected a time, got an image distance '30px'"),
])
def test_bad_readouts_are_located(tmp_path, line, message):
    _bad(tmp_path, scene_text(LENSES["pinhole"], "1m/s").replace("readout 30ms", line), line, message)


@pytest.mark.parametrize(("line", "message"), [
    ("speed 0m/s", "error[E110]: a speed must be in (0, 100] m/s, got 0 m/s"),
    ("speed 1000km/h", "error[E110]: a speed must be in (0, 100] m/s, got 277.778 m/s"),
    ("speed -1m/s", "error[E110]: a speed must be in (0, 100] m/s, got -1 m/s"),
    ("speed 1e999m/s", "error[E109]: number '1e999m/s' is too large to represent"),
    ("speed 5m", "error[E107]: expected a speed, got a length '5m'"),
])
def test_bad_speeds_are_located(tmp_path, line, message):
    _bad(tmp_path, scene_text(LENSES["pinhole"], "1m/s").replace("speed 1m/s", line), line, message)


def test_a_readout_without_times_and_a_bad_sync_are_located(tmp_path):
    text = scene_text(LENSES["pinhole"], "1m/s").replace("  speed 1m/s\n", "")
    _bad(tmp_path, text, "30ms", "error[E102]: the readout of camera 'cam' needs the robot's motion, and path "
                                 "'run' has no times")
    _bad(tmp_path, scene_text(LENSES["pinhole"], "1m/s", sync="3s"), "3s",
         "error[E110]: a sync offset must be within 1000 ms, got 3000 ms")
    _bad(tmp_path, scene_text(LENSES["pinhole"], "1m/s", sync="10ms jitter -2ms"), "-2ms",
         "error[E110]: a sync jitter must be in [0, 1000] ms, got -2 ms")
    _bad(tmp_path, scene_text(LENSES["pinhole"], "1m/s", sync="10ms jitter 2s"), "2s",
         "error[E110]: a sync jitter must be in [0, 1000] ms, got 2000 ms")
    _bad(tmp_path, scene_text(LENSES["pinhole"], "1m/s", sync="10ms jitter 2px"), "jitter 2px",
         "error[E107]: expected a time, got an image distance '2px'")
    still = scene_text(LENSES["pinhole"], "1m/s", sync="0ms jitter 2ms").replace("  speed 1m/s\n", "").replace(
        "  readout 30ms\n", "")
    _bad(tmp_path, still, "2ms", "error[E102]: the sync jitter of rig 'head' needs the robot's motion, and path "
                                 "'run' has no times")


def wiredsl(*args: str):
    """The command line, in this process (click's runner): exit code and stderr."""
    from click.testing import CliRunner

    from wiredsl.cli import main

    r = CliRunner().invoke(main, list(args))
    return r.exit_code, r.stderr


def _bad(tmp_path, text: str, token: str, message: str):
    p = tmp_path / "bad.wd"
    p.write_text(text)
    code, err = wiredsl("check", str(p))
    assert code == 1 and "Traceback" not in err
    line_no = next(i for i, t in enumerate(text.splitlines(), 1) if token in t)
    col = text.splitlines()[line_no - 1].index(token.split()[-1]) + 1
    assert f"{p}:{line_no}:{col}: {message}" in err, err


def test_check_reports_the_speeds(tmp_path):
    p = tmp_path / "moving.wd"
    p.write_text(scene_text(LENSES["pinhole"], "0.5m/s"))
    out = subprocess.run([sys.executable, "-m", "wiredsl", "check", str(p)], cwd=ROOT, capture_output=True,
                         text=True)
    assert out.returncode == 0
    # the middle pose's speed is the parabola's through the three chord-timed poses: below the declared 0.5 m/s
    assert f"{p}:21:6: note: path 'run': 3 poses over 1.279 s; speed 0.494 to 0.5 m/s (fastest at pose 0), " \
           "turning at most 26.8 deg/s" in out.stderr


def test_a_study_over_the_robots_speed_runs_on_the_lab(tmp_path):
    """`vary path.speed`: each design point's poses timed by its speed, so the 10 ms sync's 3D error grows with it
    (to first order in proportion: the right camera's step is speed x offset)."""
    import json

    lab(tmp_path, "10ms")  # writes tmp_path/lab.wd
    (tmp_path / "study.wd").write_text('wiredsl 1\ninclude "lab.wd"\npipeline still {\n  lateral_shift range 0px\n}\n'
                                       "study speed {\n  pipeline still\n  vary path.speed values [0.5m/s, 1m/s, "
                                       "2m/s]\n  trials 1\n  poses [0, 3]\n  measure stereo3d\n}\n")
    code, err = wiredsl("study", str(tmp_path / "study.wd"), "speed", "-o", str(tmp_path / "out"), "--executor",
                        "inprocess", "--no-plots")
    assert code == 0, err
    table = json.loads((tmp_path / "out" / "table.json").read_text())
    errors = [row["mean"] for row in sorted(table["rows"], key=lambda r: r["point"])
              if row["statistic"] == "corner_error"]
    assert [row["values"]["path.speed"] for row in table["rows"] if row["statistic"] == "corner_error"] == [0.5, 1, 2]
    # measured 0.030, 0.060, 0.104 m: twice the step gives twice the error, then 1.7 times (the error is linear in
    # the step only to first order)
    assert len(errors) == 3 and errors[0] > 0.005 and 1.8 < errors[1] / errors[0] < 2.2 \
        and 1.5 < errors[2] / errors[1] < 2.0, errors


@pytest.mark.parametrize(("vary", "token", "message"), [
    ("vary camera.cam.readout values [-1ms]", "-1ms", "error[E110]: camera.cam readout: must be in [0, 1] s, got -1ms"),
    ("vary path.speed values [0.5m/s, 200m/s]", "200m/s",
     "error[E110]: path speed: must be in (0, 100] m/s, got 200m/s"),
    ("vary rig.sync values [2s]", "2s", "error[E110]: rig sync: must be within 1 s, got 2s"),
    ("vary path.speed values [3km]", "3km", "error[E108]: unknown unit 'km' in '3km'"),
])
def test_bad_motion_factors_are_located(tmp_path, vary, token, message):
    text = scene_text(LENSES["pinhole"], "1m/s") + f"study s {{\n  {vary}\n  measure stereo3d\n}}\n"
    _bad(tmp_path, text, token, message)


def test_motion_factors_need_a_moving_robot(tmp_path):
    """A readout or a sync needs times: the path's `speed`, or a study that varies `path.speed` (which times
    written poses that declare none); a speed cannot time two poses at one place."""
    text = scene_text(LENSES["pinhole"], "1m/s").replace("  speed 1m/s\n", "").replace("  readout 30ms\n", "")
    study = ("study s {\n  vary path.speed values [1m/s]\n  vary camera.cam.readout values [1ms]\n  measure "
             "stereo3d\n}\n")
    (tmp_path / "ok.wd").write_text(text + study)
    code, err = wiredsl("check", str(tmp_path / "ok.wd"))
    assert code == 0, err
    still = text.replace("pose (0.3m, 0.05m) heading 12deg", "pose (0, 0) heading 12deg")
    _bad(tmp_path, still + study, "path.speed",
         "error[E102]: varying path.speed needs a path of written poses, no two neighbours at one place")
    _bad(tmp_path, text + "study s {\n  vary camera.cam.readout values [1ms]\n  measure stereo3d\n}\n",
         "camera.cam.readout", "error[E102]: varying a readout needs the robot's motion, and the scene's path has "
                               "no times")
    _bad(tmp_path, text + "study s {\n  vary rig.sync values [1ms]\n  measure stereo3d\n}\n",
         "rig.sync", "error[E102]: varying rig.sync needs the robot's motion, and the scene's path has no times")


def test_a_rolling_shutters_3d_error_on_the_lab_grows_with_the_robots_speed(tmp_path):
    """A small lab_study.wd 'speed': scenes/lab.wd as it is (no speed), the study driving it (`vary path.speed`)
    with 30 ms readouts and the right camera 10 ms late, under noisy corners (the paper's corner loss and approximation
    error): each faster
    point's corner error exceeds the slower one's by more than twice their standard errors combined, and PGH
    (whose view-point references are of a robot standing still) recognises at every speed."""
    import json

    (tmp_path / "study.wd").write_text(
        f'wiredsl 1\ninclude "{ROOT}/scenes/lab.wd"\npipeline jitter {{\n  corner_loss keep 0.85\n'
        "  approx_error sigma 0.15px\n}\nstudy speed {\n  pipeline jitter\n"
        "  vary path.speed values [0.5m/s, 2m/s, 4m/s]\n  vary rig.sync values [10ms]\n"
        "  vary camera.cam_l.readout values [30ms]\n  vary camera.cam_r.readout values [30ms]\n  trials 8\n"
        "  poses [0, 2, 4]\n  measure pgh\n  measure stereo3d\n}\n")
    code, err = wiredsl("study", str(tmp_path / "study.wd"), "speed", "-o", str(tmp_path / "out"), "--executor",
                        "inprocess", "--no-plots")
    assert code == 0, err
    table = json.loads((tmp_path / "out" / "table.json").read_text())
    rows = sorted((r for r in table["rows"] if r["statistic"] == "corner_error"), key=lambda r: r["point"])
    assert [r["values"]["path.speed"] for r in rows] == [0.5, 2, 4]
    means, sems = [r["mean"] for r in rows], [r["sem"] for r in rows]
    print(means, sems)
    for a, b in zip(range(2), range(1, 3), strict=True):
        assert means[b] - means[a] > 2 * math.hypot(sems[a], sems[b]), (means, sems)
    assert all(r["mean"] > 0.5 for r in table["rows"] if r["statistic"] == "recognition")
