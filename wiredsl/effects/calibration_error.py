"""Camera calibration error: the rig's parameters are drawn from the calibration uncertainty.

With an information matrix J^T J = V diag(w) V^T (the paper's second derivatives
of chi^2), a draw is phi = V (sigma n / sqrt(w)), n ~ N(0, I): with sigma = 1 its
covariance is exactly (J^T J)^-1. With a covariance matrix C = V diag(l) V^T it
is phi = V (sigma n sqrt(l)). Directions whose w is below `cutoff` times the
largest (or whose l is at or below zero from rounding) are unconstrained by the
calibration: they get no perturbation, and a warning names them. One draw per
trial perturbs the rig for every pose of that trial; the cameras are then
projected as perturbed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from wiredsl.effects.base import Effect, Params, Stats, keyed_normal, param, stream_key
from wiredsl.engine import geometry


class CalibrationErrorParams(Params):
    sigma: float = param(0.01, "number", "scale of the calibration's standard deviations (1: as measured; the "
                         "paper's 0.01 scaled its own matrix)", ge=0, le=1e6)
    cutoff: float = param(1e-9, "number", "singular values below cutoff * largest are treated as unconstrained",
                          gt=0, lt=1)


@dataclass(frozen=True)
class Sampler:
    """phi = basis @ n, n ~ N(0, I): the decomposed calibration uncertainty."""

    basis: np.ndarray  # (m, m): the symmetric root V diag(s) V^T, s = sigma / sqrt(w) (or sigma sqrt(l)), or 0
    unconstrained: list[str]  # the leading parameter of each unconstrained direction
    covariance: np.ndarray  # the covariance the draws have (for the manifest)


def sampler(p: CalibrationErrorParams, kind: str, matrix, order: list[str]) -> Sampler:
    """Decompose the calibration matrix once (only when this stage runs)."""
    w, V = _eigh(np.asarray(matrix, dtype=float))
    top = max(float(np.abs(w).max(initial=0.0)), 1e-300)
    if kind == "information":
        ok = w > p.cutoff * top
        scale = np.zeros_like(w)
        scale[ok] = p.sigma / np.sqrt(w[ok])
    else:  # a small variance is a well-known direction, not an unknown one: only rounding's negatives are dropped
        ok = w > 0  # (a real rig's covariance spans px^2 to m^2: 1e-10 of the largest is still a variance)
        scale = np.where(ok, p.sigma * np.sqrt(np.clip(w, 0.0, None)), 0.0)
    loose = [] if kind == "covariance" else [order[int(np.argmax(np.abs(V[:, i])))] for i in np.flatnonzero(~ok)]
    # The symmetric square root V diag(scale) V^T, not V diag(scale): eigh's vectors are defined only up to sign
    # (and to a rotation within a repeated eigenvalue's space), and LAPACK's kernels for different CPUs choose
    # differently, so V diag(scale) drew other perturbations from the same seed on another machine. The
    # symmetric root is the same matrix whichever vectors eigh returns (to rounding), with the same covariance.
    basis = (V * scale[None, :]) @ V.T
    return Sampler(basis, loose, basis @ basis.T)


def _eigh(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """eigh of the symmetrised matrix, kept for the last few matrices: a study's design points decompose the
    same calibration with different sigmas (the decomposition does not depend on sigma)."""
    key = (M.shape, M.tobytes())
    if key not in _EIGH:
        M = (M + M.T) / 2
        if len(_EIGH) >= 8:
            _EIGH.pop(next(iter(_EIGH)))
        _EIGH[key] = np.linalg.eigh(M)  # symmetric: eigen- and singular vectors coincide on the PSD part
    w, V = _EIGH[key]
    return w.copy(), V.copy()


_EIGH: dict = {}


def draws(s: Sampler, trials: np.ndarray, seed: int, point: int | None = None, attempt: int = 0) -> np.ndarray:
    """Each trial's parameter perturbation phi (T, m), the same for every pose and both cameras.

    Attempt a (a redraw after a refused one) uses normals a * m .. a * m + m - 1 of the trial's key.
    """
    m = s.basis.shape[1]
    key = stream_key(CalibrationError.name, np.asarray(trials), -1, -1, seed, point)
    n = keyed_normal(key[:, None], attempt * m + np.arange(m)[None, :])
    return (n[:, None, :] * s.basis[None, :, :]).sum(axis=2)  # row by row: no dependence on T


def draw(s: Sampler, trial: int, seed: int, point: int | None = None) -> np.ndarray:
    """One trial's perturbation phi (m,)."""
    return draws(s, np.array([trial]), seed, point)[0]


def rotation_vector(r: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation matrix of a rotation vector (3,)."""
    theta = float(np.linalg.norm(r))
    if theta < 1e-12:
        return np.eye(3)
    k = r / theta
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * K + (1 - math.cos(theta)) * (K @ K)


def perturb(scene, phi: np.ndarray, order: list[str]):
    """The scene with its rig's cameras and mounts moved by phi over the named parameters."""
    deltas = {"left": {}, "right": {}}
    for name, value in zip(order, phi, strict=True):
        side, _, key = name.partition(".")
        deltas[side][key] = float(value)
    rig = scene.rig
    cameras = {c.name: c for c in scene.cameras}
    mounts = {}
    renamed = []
    for side in ("left", "right"):
        mount = getattr(rig, side)
        d = deltas[side]
        cam = cameras[mount.camera]
        updates = {k: getattr(cam, k) + d[k] for k in CAMERA_KEYS if k in d and k != "k1"}
        if "k" in d:
            updates["k1"] = cam.k1 - d["k"]  # TINA's k = -k1
        new_cam = cam.model_copy(update={**updates, "name": f"{cam.name}:{side}"})
        renamed.append(new_cam)
        R = np.array(mount.rotation)
        t = np.array(mount.position) + R @ np.array([d.get("tx", 0.0), d.get("ty", 0.0), d.get("tz", 0.0)])
        R = R @ rotation_vector(np.array([d.get("rx", 0.0), d.get("ry", 0.0), d.get("rz", 0.0)]))
        mounts[side] = mount.model_copy(update={"camera": new_cam.name, "rotation": tuple(map(tuple, R)),
                                                "position": tuple(t)})
    new_rig = rig.model_copy(update=mounts)
    return scene.model_copy(update={"rig": new_rig, "cameras": [*scene.cameras, *renamed]})


def rotation_vectors(r: np.ndarray) -> np.ndarray:
    """Rodrigues for many rotation vectors (T, 3) -> (T, 3, 3)."""
    theta = np.linalg.norm(r, axis=1)
    k = np.divide(r, theta[:, None], out=np.zeros_like(r), where=theta[:, None] > 0)
    K = np.zeros((len(r), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    return np.eye(3)[None] + s * K + (1 - c) * (K @ K)


CAMERA_KEYS = geometry.CAMERA_KEYS
ATTEMPTS = 64  # draws tried for one trial before the calibration is refused as too uncertain for its cameras
SCALE_LIMIT = 1000.0  # a drawn pixel scale beyond this multiple of the nominal one is refused (no real camera)


def sensible(scene, phis: np.ndarray, order: list[str], rigs: dict | None = None) -> np.ndarray:
    """Which draws (T,) leave both cameras with positive pixel scales (f ax, f ay) no larger than
    SCALE_LIMIT times the nominal ones, and every perturbed parameter finite. `rigs`: `checked_rigs` of the
    draws, when the caller has them already."""
    ok = np.isfinite(phis).all(axis=1)
    for side, rig in (checked_rigs(scene, phis, order) if rigs is None else rigs).items():
        prm, cam = rig["params"], scene.camera(getattr(scene.rig, side).camera)
        with np.errstate(over="ignore", invalid="ignore"):
            for scale, nominal in ((prm["f"] * prm["ax"], cam.f * cam.ax), (prm["f"] * prm["ay"], cam.f * cam.ay)):
                ok &= (prm["f"] > 0) & (scale > 0) & (scale <= SCALE_LIMIT * abs(nominal))
            for key in CAMERA_KEYS:
                ok &= np.isfinite(prm[key])
            ok &= np.isfinite(rig["position"]).all(axis=1) & np.isfinite(rig["rotation"]).all(axis=(1, 2))
    return ok


def checked_rigs(scene, phis: np.ndarray, order: list[str]) -> dict:
    """`perturbed_rigs` of the draws with their non-finite values as 0: what `sensible` checks, and (every
    accepted draw being finite) the rigs a batch projects with."""
    return perturbed_rigs(scene, np.where(np.isfinite(phis), phis, 0.0), order)


def splice_rigs(rigs: dict, rows: np.ndarray, new: dict) -> None:
    """Replace the given trials' rows of `rigs` by `new` (the rigs of those trials' redraws), in place."""
    for side, rig in rigs.items():
        for key, value in new[side]["params"].items():
            rig["params"][key] = np.array(np.broadcast_to(rig["params"][key], rig["position"][:, 0].shape))
            rig["params"][key][rows] = value
        rig["rotation"][rows] = new[side]["rotation"]
        rig["position"][rows] = new[side]["position"]


def perturbed_rigs(scene, phis: np.ndarray, order: list[str]) -> dict:
    """Every trial's perturbed rig at once: for each side, camera parameter arrays (T,) and the mount
    rotation (T, 3, 3) and position (T, 3). The same arithmetic as `perturb`, vectorised over trials."""
    col = {name: i for i, name in enumerate(order)}
    T = len(phis)
    out = {}
    for side in ("left", "right"):
        mount = getattr(scene.rig, side)
        cam = scene.camera(mount.camera)

        def delta(key, side=side):
            i = col.get(f"{side}.{key}")
            return phis[:, i] if i is not None else np.zeros(T)

        params = {k: getattr(cam, k) + (delta(k) if k not in ("k1",) else 0.0) for k in CAMERA_KEYS}
        params["k1"] = cam.k1 - delta("k")  # TINA's k = -k1
        R = np.array(mount.rotation)
        dt = np.column_stack([delta("tx"), delta("ty"), delta("tz")])
        position = np.array(mount.position)[None] + (dt[:, None, :] * R[None, :, :]).sum(axis=2)  # row by row
        rotation = R[None] @ rotation_vectors(np.column_stack([delta("rx"), delta("ry"), delta("rz")]))
        out[side] = {"params": params, "rotation": rotation, "position": position, "camera": cam}
    return out


class CalibrationError(Effect):
    name = "calibration_error"
    acts_on = "cameras"
    Params = CalibrationErrorParams
    doc = __doc__

    @classmethod
    def is_identity(cls, p: CalibrationErrorParams) -> bool:
        return p.sigma == 0

    @classmethod
    def record(cls, stats: Stats, phis: np.ndarray, refused: int) -> None:
        """Running moments of the accepted draws (memory does not grow with trials) and the refused count."""
        m = stats.samples.setdefault(cls.name + ".moments", [0, 0.0, 0.0])
        m[0] += len(phis)
        m[1] = m[1] + phis.sum(axis=0)
        m[2] = m[2] + phis.T @ phis
        stats.add(cls.name, refused=refused)

    @classmethod
    def report(cls, p: CalibrationErrorParams, stats: Stats) -> dict:
        out = {"refused_draws": {"declared": 0, "measured": int(stats.sums[cls.name]["refused"])}}
        moments = stats.samples.get(cls.name + ".moments")
        declared = stats.samples.get(cls.name + ".covariance")
        if not moments or moments[0] < 2 or not declared:
            return out
        n, s1, s2 = moments
        C = np.atleast_2d(declared[0])
        S = np.atleast_2d((s2 - np.outer(s1, s1) / n) / (n - 1))  # one parameter stays a 1 x 1 matrix
        sd = np.sqrt(np.clip(np.diag(C), 0, None))
        worst = float(np.max(np.abs(np.sqrt(np.clip(np.diag(S), 0, None)) - sd) / np.where(sd > 0, sd, 1)))
        order = stats.samples.get(cls.name + ".order")
        return {**out, "std_relative_error": {"declared": 0.0, "measured": worst, "trials": int(n)},
                "covariance": {"order": list(order[0]) if order else None, "declared": C.tolist(),
                               "measured": S.tolist()}}
