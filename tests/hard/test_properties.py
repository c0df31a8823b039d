"""Hypothesis properties over random cameras and geometry: finite output, and continuity away from
genuine discontinuities (the near plane, the fold radius, the image border)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from wiredsl.engine import geometry
from wiredsl.scene import Camera

cameras = st.builds(
    lambda f, ax, ay, cx, cy, k1, k2, p1, p2: Camera(name="c", f=f, ax=ax, ay=ay, cx=cx, cy=cy, k1=k1, k2=k2, p1=p1,
                                                     p2=p2, width=640, height=480),
    st.floats(50, 5000), st.floats(0.5, 2), st.floats(0.5, 2), st.floats(0, 640), st.floats(0, 480),
    st.floats(-0.5, 0.5), st.floats(-0.2, 0.2), st.floats(-0.01, 0.01), st.floats(-0.01, 0.01))
points = st.tuples(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3), st.floats(-1e3, 1e3))


@settings(max_examples=300, deadline=None)
@given(cam=cameras, a=points, b=points)
def test_clipped_projection_is_always_finite(cam, a, b):
    A, B = np.array([a], float), np.array([b], float)
    r = geometry.fold_radius(cam.k1, cam.k2)
    t0, t1, keep = geometry.clip_segments_cone(A, B, geometry.NEAR, r * (1 - 1e-9))
    if keep[0]:
        P = A + np.array([t0[0], t1[0]])[:, None] * (B - A)
        assert np.isfinite(geometry.cam_to_pixels(P, cam)).all()


@settings(max_examples=300, deadline=None)
@given(cam=cameras, p=st.tuples(st.floats(-2, 2), st.floats(-2, 2), st.floats(0.05, 1e4)),
       d=st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)))
def test_small_changes_give_small_changes(cam, p, d):
    """A point moved by 1e-9 of its depth moves in the image by at most a bound set by the camera's
    scale (f), away from the fold radius where the mapping's derivative vanishes."""
    P = np.array([p[0] * p[2], p[1] * p[2], p[2]])
    r = math.hypot(p[0], p[1])
    fold = geometry.fold_radius(cam.k1, cam.k2)
    if r > 0.9 * fold:
        return  # near the fold the mapping is not one-to-one: a genuine discontinuity
    Q = P + 1e-9 * p[2] * np.array(d)
    uv = geometry.cam_to_pixels(np.stack([P, Q]), cam)
    bound = 1e-9 * cam.f * max(cam.ax, cam.ay) * 10 * (1 + r) ** 6
    assert np.linalg.norm(uv[1] - uv[0]) <= bound
