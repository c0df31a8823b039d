"""A Gymnasium environment: the robot of a wiredsl scene moved by an agent that sees what the rig's detectors see.

    import gymnasium, wiredsl.gym
    env = wiredsl.gym.WiredslEnv("scenes/lab.wd", task=wiredsl.gym.Task("reach", "bin1"))
    obs, info = env.reset(seed=1)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())

Observation (a dict of fixed-size arrays; C = `max_corners`, S = `max_segments`, camera 0 left, 1 right):

- `corners` float32 (2, C, 2): each camera's disturbed corners (u / width, v / height), in [0, 1], in the
  engine's order (by feature), the first C; `corner_mask` int8 (2, C): 1 where a slot holds a corner;
- `segments` float32 (2, S, 4): each camera's disturbed strokes as straight pieces between consecutive vertices
  (u0 / width, v0 / height, u1 / width, v1 / height), in stroke order, the first S; `segment_mask` int8 (2, S);
- `pose` float32: the robot's pose, (x, y, heading) for `motion="planar"`, its world-from-robot [R | t] row-major
  (12) for `motion="6dof"`.

Action: planar, Box(-1, 1, (2,)): forward distance (times `step_length` m) then turn (times `turn` rad); 6dof,
Box(-1, 1, (6,)): a move in the robot's frame (x, y, z times `step_length` m) then a turn about its own axes
(roll, pitch, yaw times `turn` rad). The disturbances of step k of an episode are wiredsl's keyed draws of
(seed, trial, step k): `reset(seed=...)` seeds the episode's `np_random` (Gymnasium's rule), which draws the
start pose's jitter and the episode's trial number, so an episode replays bit for bit from its seed and actions.

Tasks (`Task`): `reach` ends when the robot stands `distance` m from the target placement, facing it (within
`tolerance` m and `heading_tolerance` rad): reward the progress towards that pose each step, +10 on arrival,
-0.01 a step; `track` rewards each step in which both cameras see at least `min_features` of the target's
features, and ends when they have not for `patience` steps. Both end (terminated, -10) when the robot leaves the
view-points' area by more than `margin` m (or, 6dof, rises or sinks more than 1 m), and are truncated after
`max_steps`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import wiredsl

try:
    import gymnasium
    from gymnasium import spaces
except ImportError as _exc:  # as every other extra: name its install
    raise ImportError(f"wiredsl.gym needs gymnasium: {wiredsl.install_hint('gym')}") from _exc
from wiredsl.api import robot_pose
from wiredsl.engine import geometry
from wiredsl.io import layout

TRIALS = 2**31 - 1  # an episode's trial number is drawn in 0..TRIALS-1 (Simulator's range)
# gym.make("wiredsl/Scene-v0") with no arguments: the lab's reach task (the lab ships in the wheel as
# wiredsl/scenes/, and is scenes/ in a checkout)
_HERE = Path(__file__).resolve().parent
LAB = next((p for p in (_HERE / "scenes" / "lab.wd", _HERE.parent / "scenes" / "lab.wd") if p.is_file()),
           _HERE / "scenes" / "lab.wd")
HEIGHT = 1.0  # 6dof: the robot's frame may rise or sink this far (m) before the episode ends


@dataclass(frozen=True)
class Task:
    """What the agent is asked to do: `kind` "reach" or "track", about the placement `target`.

    Args:
        kind: "reach" (stand `distance` m from the target, the rig's cameras facing it) or "track" (keep at
            least `min_features` of its features in both cameras).
        target: the name of a placement of the scene.
        distance: reach: stand this far from the target's origin (m).
        tolerance: reach: within this of that point (m).
        heading_tolerance: reach: facing the target within this (rad).
        min_features: track: features of the target each camera must see.
        patience: track: steps without them before the episode ends.
    """

    kind: str
    target: str
    distance: float = 1.2  # reach: stand this far from the target's origin (m)
    tolerance: float = 0.15  # reach: within this of that point (m)
    heading_tolerance: float = 0.25  # reach: facing the target within this (rad)
    min_features: int = 1  # track: features of the target each camera must see
    patience: int = 3  # track: steps without them before the episode ends

    def __post_init__(self):
        if self.kind not in ("reach", "track"):
            raise ValueError(f"a task is 'reach' or 'track', not {self.kind!r}")
        for name in ("distance", "tolerance", "heading_tolerance"):  # inf made the reward NaN
            _number(f"Task {name}", getattr(self, name), low=0.0, open_low=name == "distance")
        _whole("Task min_features", self.min_features, 0)
        _whole("Task patience", self.patience, 1)


LARGEST = 1e9  # a length or angle argument at most this (the language's bound on lengths): 1e308 overflowed


def _number(name: str, value, low: float | None = None, open_low: bool = False) -> float:
    """A finite real number at least `low` (above it if `open_low`) and at most LARGEST, else ValueError."""
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool) \
        and math.isfinite(value) and abs(value) <= LARGEST
    if ok and low is not None:
        ok = value > low if open_low else value >= low
    if not ok:
        bound = "" if low is None else f" {'>' if open_low else '>='} {low:g}"
        raise ValueError(f"{name} must be a finite number{bound}, at most {LARGEST:g}, not {value!r}")
    return float(value)


def _whole(name: str, value, low: int) -> int:
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < low:
        raise ValueError(f"{name} must be a whole number >= {low}, not {value!r}")
    return int(value)


def _check_arguments(start_noise, max_steps, step_length, turn, max_corners, max_segments, margin) -> None:
    """The environment's numeric arguments: finite, in range (start_noise inf failed every reset)."""
    _number("start_noise", start_noise, 0.0)
    _number("step_length", step_length, 0.0, open_low=True)
    _number("turn", turn, 0.0)
    _number("margin", margin, 0.0)
    _whole("max_steps", max_steps, 1)
    _whole("max_corners", max_corners, 1)
    _whole("max_segments", max_segments, 1)


def rig_yaw(rig) -> float:
    """The yaw (rad, about the robot's z) of the rig's mean viewing direction in the robot frame: 0 for a rig
    that looks forward (x), pi/2 for one that looks left."""
    look = sum(np.array(m.rotation, dtype=float)[:, 2] for m in (rig.left, rig.right))  # camera z in robot frame
    return math.atan2(float(look[1]), float(look[0]))


class WiredslEnv(gymnasium.Env):
    """The scene's robot, its rig's disturbed features as observations; see the module's docstring."""

    metadata = {"render_modes": []}

    def __init__(self, scene=None, task: Task | None = None, *, pipeline: str | None = None,
                 motion: str = "planar", seed: int = 0, start=None, start_noise: float = 0.2, max_steps: int = 60,
                 step_length: float = 0.25, turn: float = 0.3, max_corners: int = 32, max_segments: int = 128,
                 margin: float = 1.0, visibility: str | None = None):
        """The environment of `scene` (a path or a compiled Scene) and `task`.

        Args:
            scene: a scene file or compiled Scene; None (with task None): the lab, scenes/lab.wd.
            task: what the agent is asked to do; None: Task("reach", "bin1") on the lab (what
                `gymnasium.make("wiredsl/Scene-v0")` makes with no arguments).
            pipeline: the pipeline whose disturbances the agent sees (None: the scene's default).
            motion: "planar" (x, y, heading) or "6dof".
            seed: the Simulator's seed (an episode's draws are keyed by it, the trial and the step).
            start: the start pose (x, y, heading) or a 4x4 (None: the path's first pose).
            start_noise: the start pose's uniform jitter on x, y (m) and heading (rad).
            max_steps: steps after which an episode is truncated.
            step_length: m of a full forward action (planar) or move (6dof).
            turn: rad of a full turn action.
            max_corners: C, corners a camera's observation holds.
            max_segments: S, straight pieces a camera's observation holds.
            margin: m beyond the view-points' area at which an episode ends.
            visibility: the Simulator's (None: wiredsl.DEFAULT_VISIBILITY, "auto": exact hidden lines where the
                scene has faces); "scene" takes the view-point mesh's whole-feature lists, several times faster
                a step on the lab, with hidden lines drawn through faces.
        """
        if scene is None:
            scene = LAB
            task = task if task is not None else Task("reach", "bin1")
        if task is None:
            raise ValueError("give a task, e.g. Task('reach', 'bin1'): the default task is the lab's")
        _check_arguments(start_noise, max_steps, step_length, turn, max_corners, max_segments, margin)
        self.scene = wiredsl.compile(scene) if isinstance(scene, (str, bytes)) or hasattr(scene, "__fspath__") \
            else scene
        if motion not in ("planar", "6dof"):
            raise ValueError(f"motion is 'planar' or '6dof', not {motion!r}")
        self.task, self.motion = task, motion
        self.sim = wiredsl.Simulator(self.scene, seed=seed, pipeline=pipeline,
                                     visibility=wiredsl.DEFAULT_VISIBILITY if visibility is None else visibility)
        self.target = self.sim.select(placement=task.target)  # refuses an unknown placement by name
        placement = next(p for p in self.scene.placements if p.name == task.target)
        self.target_xy = np.array(placement.position[:2], dtype=float)
        if start is None:
            if self.scene.path is None:
                raise ValueError("the scene has no path: give start=(x, y, heading)")
            start = geometry.floor_pose(self.scene.path.pose(0))
        self.start = np.array(robot_pose(start)[:3] if len(np.ravel(start)) == 3 else geometry.floor_pose(start))
        self.start_noise, self.max_steps, self.step_length, self.turn = start_noise, max_steps, step_length, turn
        self.C, self.S = max_corners, max_segments
        if self.scene.viewpoints is not None:
            pts = np.array(self.scene.viewpoints.points, dtype=float)
            self.bounds = (pts.min(axis=0) - margin, pts.max(axis=0) + margin)
        else:
            self.bounds = (np.full(2, -np.inf), np.full(2, np.inf))
        away = self.start[:2] - self.target_xy
        self.goal_xy = self.target_xy + task.distance * away / max(np.linalg.norm(away), 1e-9)
        # at the goal the rig's cameras face the target: the robot turned by their viewing direction's yaw in
        # its frame (zero for a rig that looks forward; a side-looking rig stands side-on)
        self.goal_heading = math.atan2(*(self.target_xy - self.goal_xy)[::-1]) - rig_yaw(self.scene.rig)
        self.goal_heading = math.atan2(math.sin(self.goal_heading), math.cos(self.goal_heading))
        self.cameras = [self.scene.camera(self.scene.rig.left.camera), self.scene.camera(self.scene.rig.right.camera)]
        # where a last move can take it: a 6dof move is up to step_length along each of three axes at once
        reach = step_length * (1.0 if motion == "planar" else math.sqrt(3.0))
        blo, bhi = self.bounds[0] - reach, self.bounds[1] + reach
        # and where a reset can put it: the start, outside the area or not, and its jitter
        blo = np.minimum(blo, self.start[:2] - start_noise)
        bhi = np.maximum(bhi, self.start[:2] + start_noise)
        if motion == "planar":
            low, high = [blo[0], blo[1], -math.pi], [bhi[0], bhi[1], math.pi]
        else:
            low = [-1, -1, -1, blo[0], -1, -1, -1, blo[1], -1, -1, -1, -HEIGHT - reach]
            high = [1, 1, 1, bhi[0], 1, 1, 1, bhi[1], 1, 1, 1, HEIGHT + reach]
        self.observation_space = spaces.Dict({
            "corners": spaces.Box(0.0, 1.0, (2, self.C, 2), np.float32),
            "corner_mask": spaces.MultiBinary((2, self.C)),
            "segments": spaces.Box(0.0, 1.0, (2, self.S, 4), np.float32),
            "segment_mask": spaces.MultiBinary((2, self.S)),
            "pose": spaces.Box(np.array(low, np.float32), np.array(high, np.float32), dtype=np.float32),
        })
        self.action_space = spaces.Box(-1.0, 1.0, (2 if motion == "planar" else 6,), np.float32)
        self._column = {name: i for i, (name, _) in enumerate(layout.STROKE_COLUMNS)}
        self._pose = None

    # --- the robot ----------------------------------------------------------------------------------------

    def _floor(self) -> np.ndarray:
        """(x, y, heading) of the current pose."""
        if self.motion == "planar":
            return self._pose.copy()
        R, t = self._pose[:3, :3], self._pose[:3, 3]
        return np.array([t[0], t[1], math.atan2(R[1, 0], R[0, 0])])

    def _action(self, action) -> np.ndarray:
        """The action as (n,) floats, or ValueError saying what is wrong with it (nothing changed yet)."""
        n = self.action_space.shape[0]
        try:
            a = np.asarray(action)
            if a.dtype.kind not in "iuf":  # not bool, complex (its imaginary part dropped), text nor objects
                raise TypeError
            a = a.astype(float)
        except (TypeError, ValueError):
            raise ValueError(f"an action is {n} numbers in [-1, 1] ({self.motion} motion), not {action!r}") from None
        if a.shape != (n,):
            raise ValueError(f"an action is {n} numbers in [-1, 1] ({self.motion} motion), got shape {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"an action must be finite, got {a.tolist()}")
        return a

    def _move(self, action: np.ndarray) -> None:
        a = np.clip(np.asarray(action, dtype=float), -1.0, 1.0)
        if self.motion == "planar":
            x, y, h = self._pose
            d = a[0] * self.step_length
            x, y = x + d * math.cos(h), y + d * math.sin(h)
            self._pose = np.array([x, y, math.atan2(math.sin(h + a[1] * self.turn), math.cos(h + a[1] * self.turn))])
            return
        from scipy.spatial.transform import Rotation

        M = self._pose.copy()
        M[:3, 3] = M[:3, 3] + M[:3, :3] @ (a[:3] * self.step_length)
        M[:3, :3] = M[:3, :3] @ Rotation.from_euler("xyz", a[3:] * self.turn).as_matrix()
        self._pose = M

    def _engine_pose(self):
        return tuple(self._pose) if self.motion == "planar" else self._pose

    # --- observations -------------------------------------------------------------------------------------

    def _observation(self, batch) -> dict:
        out = {"corners": np.zeros((2, self.C, 2), np.float32), "corner_mask": np.zeros((2, self.C), np.int8),
               "segments": np.zeros((2, self.S, 4), np.float32), "segment_mask": np.zeros((2, self.S), np.int8)}
        size = [np.array([c.width, c.height], dtype=float) for c in self.cameras]
        rows, corners = batch["corner_rows"], batch["corners"]
        strokes, pts, start = batch["strokes"], batch["pts"], batch["start"]
        cam_col = self._column["camera"]
        for cam in (0, 1):
            xy = corners[rows[:, 2] == cam][: self.C] / size[cam]
            out["corners"][cam, : len(xy)] = np.clip(xy, 0.0, 1.0)
            out["corner_mask"][cam, : len(xy)] = 1
            pieces = [np.concatenate([pts[start[k]:start[k + 1] - 1], pts[start[k] + 1:start[k + 1]]], axis=1)
                      for k in np.flatnonzero(strokes[:, cam_col] == cam)]
            seg = np.concatenate(pieces)[: self.S] if pieces else np.zeros((0, 4))
            out["segments"][cam, : len(seg)] = np.clip(seg / np.tile(size[cam], 2), 0.0, 1.0)
            out["segment_mask"][cam, : len(seg)] = 1
        out["pose"] = np.asarray(self._pose, dtype=np.float32).reshape(-1)[: 3 if self.motion == "planar" else 12]
        return out

    def _seen(self, batch) -> int:
        """The fewest target features either camera sees."""
        ids = np.array([f in set(self.target) for f in batch.feature_ids])
        counts = []
        for cam in (0, 1):
            fids = np.concatenate([batch["strokes"][batch["strokes"][:, self._column["camera"]] == cam,
                                                    self._column["feature"]],
                                   batch["corner_rows"][batch["corner_rows"][:, 2] == cam, 3]])
            counts.append(len(np.unique(fids[ids[fids]])) if len(fids) else 0)
        return min(counts)

    def _look(self):
        batch = self.sim.observe(self._engine_pose(), trial=self._trial, step=self._step)
        return batch, self._observation(batch)

    # --- Gymnasium ----------------------------------------------------------------------------------------

    def _distance(self) -> float:
        return float(np.linalg.norm(self._floor()[:2] - self.goal_xy))

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        jitter = self.np_random.uniform(-1.0, 1.0, 3) * self.start_noise
        self._trial = int(self.np_random.integers(0, TRIALS))
        x, y, h = self.start + jitter
        h = math.atan2(math.sin(h), math.cos(h))
        if self.motion == "planar":
            self._pose = np.array([x, y, h])
        else:
            self._pose = np.eye(4)
            self._pose[:3, :3] = geometry.rot_z(h)
            self._pose[:3, 3] = (x, y, 0.0)
        self._step, self._lost, self._ended = 0, 0, False
        batch, obs = self._look()
        self._last = self._distance()
        return obs, self._info(batch)

    def _info(self, batch) -> dict:
        return {"trial": self._trial, "step": self._step, "distance": self._distance(), "seen": self._seen(batch),
                "goal": (float(self.goal_xy[0]), float(self.goal_xy[1]), self.goal_heading)}

    def step(self, action):
        if self._pose is None:
            raise RuntimeError("call reset() before step()")
        if self._ended:  # a further move could leave the observation space (the robot beyond the area's margin)
            raise RuntimeError("the episode has ended (terminated or truncated): call reset() before step()")
        self._move(self._action(action))  # a bad action is refused before the pose changes
        self._step += 1
        batch, obs = self._look()
        info = self._info(batch)
        x, y, h = self._floor()
        lo, hi = self.bounds
        terminated = False
        if self.task.kind == "reach":
            d = info["distance"]
            reward = (self._last - d) - 0.01
            self._last = d
            off = abs(math.atan2(math.sin(h - self.goal_heading), math.cos(h - self.goal_heading)))
            if d <= self.task.tolerance and off <= self.task.heading_tolerance:
                reward, terminated = reward + 10.0, True
        else:
            ok = info["seen"] >= self.task.min_features
            reward = 1.0 if ok else 0.0
            self._lost = 0 if ok else self._lost + 1
            terminated = self._lost >= self.task.patience
        z = 0.0 if self.motion == "planar" else self._pose[2, 3]
        if not (lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] and abs(z) <= HEIGHT):
            reward, terminated = reward - 10.0, True
        truncated = not terminated and self._step >= self.max_steps
        self._ended = terminated or truncated
        return obs, float(reward), terminated, truncated, info


gymnasium.register("wiredsl/Scene-v0", entry_point="wiredsl.gym:WiredslEnv")
