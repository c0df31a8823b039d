"""Pose refinement (`--refine`): move an image's camera so that the projected model lies on the detected edges.

The paper's verification assumes an accurate projection; a pose from odometry or a board is rarely that
accurate. A few Gauss-Newton steps on the signed lateral offsets: each step measures the offsets of the
verified samples (verification.search_edges), takes the derivative of every sample's position along its
normal with respect to the camera's six pose parameters by projecting the view again with each parameter
moved a little (the engine's projection, hidden lines included), and solves the weighted least-squares step
(Huber weights at 1 px, a damping of 1e-6 of the normal matrix's trace). The camera is perturbed in its own
frame: P' = exp([w]) P + tau. Reported: the rotation (deg) and translation (m) it moved, and the
RMS offset before and after.
"""

from __future__ import annotations

import math

import numpy as np

from wiredsl.verify import verification as ver

STEPS = 4
EPS_ROT = 1e-4  # rad
EPS_T = 1e-4  # m
HUBER = 1.0  # px


def _rodrigues(w: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(w))
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + math.sin(th) / th * K + (1 - math.cos(th)) / th**2 * K @ K


def _moved(R: np.ndarray, t: np.ndarray, d: np.ndarray):
    E = _rodrigues(d[:3])
    return E @ R, E @ t + d[3:]


def _keys(st: ver.Strokes) -> list[tuple]:
    return list(zip(st.fid.tolist(), st.segment.tolist(), st.part.tolist(), strict=True))


def points_at(st: ver.Strokes, stroke: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Points at arc fractions u (n,) along the given strokes (n,) of a view's strokes."""
    d = np.diff(st.pts, axis=0)
    seg_len = np.hypot(d[:, 0], d[:, 1])
    junction = np.zeros(len(seg_len), bool)
    junction[st.start[1:-1] - 1] = True
    seg_len[junction] = 0.0
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    base = cum[st.start[:-1]]
    L = cum[st.start[1:] - 1] - base
    g = base[stroke] + u * L[stroke]
    seg = np.clip(np.searchsorted(cum[1:], g, side="left"), 0, len(seg_len) - 1)
    t = d[seg] / np.maximum(seg_len[seg], 1e-300)[:, None]
    return st.pts[seg] + t * (g - cum[seg])[:, None]


def refine_view(project, view, det, shape, cfg: ver.Settings):
    """(refined view, report). `project(R_cw, t_cw)` is the engine's view of the same camera at that pose."""
    R0, t0 = np.asarray(view.R_cw, float), np.asarray(view.t_cw, float)
    R, t = R0, t0
    before = after = None
    best = view
    for _ in range(STEPS):
        st = ver.strokes_of(best)
        sm = ver.sample_strokes(st, cfg.step)
        m = ver.search_edges(sm, det, shape, cfg)
        ok = m.verified & m.tested
        if ok.sum() < 12:
            break
        o = m.offset[ok]
        rms = float(np.sqrt(np.mean(o * o)))
        before = rms if before is None else before
        after = rms
        idx = np.flatnonzero(ok)
        stroke, u = sm.stroke[idx], (sm.s[idx] / np.maximum(sm.L[sm.stroke[idx]], 1e-12))
        keys = _keys(st)
        J = np.zeros((len(idx), 6))
        usable = np.ones(len(idx), bool)
        for k in range(6):
            d = np.zeros(6)
            d[k] = EPS_ROT if k < 3 else EPS_T
            v2 = project(*_moved(R, t, d))
            st2 = ver.strokes_of(v2)
            where = {key: j for j, key in enumerate(_keys(st2))}
            j2 = np.array([where.get(keys[s], -1) for s in stroke.tolist()])
            usable &= j2 >= 0
            P2 = points_at(st2, np.maximum(j2, 0), u) if st2.n else np.zeros((len(idx), 2))
            J[:, k] = ((P2 - sm.P[idx]) * sm.N[idx]).sum(1) / d[k]
        if usable.sum() < 12:
            break
        w = np.where(np.abs(o) <= HUBER, 1.0, HUBER / np.maximum(np.abs(o), 1e-12)) * usable
        A = (J * w[:, None]).T @ J
        b = (J * w[:, None]).T @ o
        A += np.eye(6) * 1e-6 * max(np.trace(A), 1e-12)
        try:
            step = np.linalg.solve(A, b)
        except np.linalg.LinAlgError:
            break
        if not np.all(np.isfinite(step)):
            break
        R, t = _moved(R, t, step)
        best = project(R, t)
        if np.abs(step[:3]).max() < 1e-7 and np.abs(step[3:]).max() < 1e-7:
            break
    if after is not None:  # the offsets at the final pose
        sm = ver.sample_strokes(ver.strokes_of(best), cfg.step)
        m = ver.search_edges(sm, det, shape, cfg)
        ok = m.verified & m.tested
        if ok.any():
            after = float(np.sqrt(np.mean(m.offset[ok] ** 2)))
    dR = R @ R0.T
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(dR) - 1) / 2))))
    # the camera centre moved: c = -R^T t
    shift = float(np.linalg.norm(-R.T @ t + R0.T @ t0))
    return best, {"rotation_deg": angle, "translation": shift, "rms_offset_before_px": before,
                  "rms_offset_after_px": after}
