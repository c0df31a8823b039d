"""Ellipse images as conics, and silhouettes as common tangents of two ellipse images.

An ellipse in the camera frame, E(t) = c + cos(t) U + sin(t) V (U = a u, V = b v),
maps the unit circle w = (cos t, sin t, 1) to the image by the homography
H = [U V c] (unit focal plane) or K H (pixels). Its dual conic
C* = H diag(1, 1, -1) H^T needs no inversion, so it stays finite when the
ellipse is seen edge-on (C* then has rank 2: the two end points of a segment).

The sides of a cone or cylinder between two of its circular sections appear as
the outer common tangents of the two ellipse images. A line tangent to ellipse
a at parameter s is l(s) = H_a^-T (cos s, sin s, -1); it touches ellipse b when
f(s) = l(s)^T C_b* l(s) = 0, a trigonometric polynomial of degree 2, solved
as the roots of a quartic in z = exp(i s) that lie on the unit circle. Each
tangent gives its two tangent points as ellipse parameters, so the silhouette
is returned as a 3D segment on the surface (a contour generator).
"""

from __future__ import annotations

import math

import numpy as np

D = np.diag([1.0, 1.0, -1.0])
UNIT_TOL = 1e-6  # how far from |z| = 1 a root may be and still be a real tangent


def homography(c: np.ndarray, U: np.ndarray, V: np.ndarray) -> np.ndarray:
    """H mapping (cos t, sin t, 1) to homogeneous unit-plane points of the ellipse."""
    return np.column_stack([U, V, c])


def dual_conic(H: np.ndarray) -> np.ndarray:
    return H @ D @ H.T


def ellipse_params(Cstar: np.ndarray) -> tuple[np.ndarray, np.ndarray, float] | None:
    """(centre, semi-axes (major, minor), angle of the major axis) of a dual conic, or None.

    None when the conic is not a real ellipse (a parabola or hyperbola: the ellipse
    crosses the camera's principal plane), or is degenerate (seen edge-on).
    """
    s = Cstar[2, 2]
    scale = np.abs(Cstar).max()
    if scale == 0 or not abs(s) > 1e-12 * scale:
        return None
    C = Cstar / -s  # now C[2, 2] = -1
    centre = -C[:2, 2]
    A_inv = C[:2, :2] + np.outer(centre, centre)
    A_inv = (A_inv + A_inv.T) / 2
    w, Q = np.linalg.eigh(A_inv)
    if not w[0] > 1e-12 * w[1]:
        return None
    axes = np.sqrt(w[::-1])
    major = Q[:, 1]
    angle = math.atan2(major[1], major[0])
    return centre, axes, angle


def parameter_on(H: np.ndarray, P: np.ndarray) -> float:
    """The ellipse parameter t whose image H (cos t, sin t, 1) is the point P (homogeneous).

    Minimises |[P]x H (cos t, sin t, 1)| over the circle itself, so it also holds when
    the ellipse is seen edge-on and H has rank 2 (a plain null vector of [P]x H could
    then be H's own null vector, which is not on the circle).
    """
    Px = np.array([[0.0, -P[2], P[1]], [P[2], 0.0, -P[0]], [-P[1], P[0], 0.0]])
    M = Px @ H
    M = M / (np.abs(M).max() or 1.0)

    a, b, m = M[:, 0], M[:, 1], M[:, 2]
    grid = np.linspace(-math.pi, math.pi, 361)
    r = a[:, None] * np.cos(grid) + b[:, None] * np.sin(grid) + m[:, None]
    t = float(grid[int(np.argmin((r * r).sum(axis=0)))])
    for _ in range(8):  # Newton on g'(t) = 2 r.r', from within one grid step of the minimum
        c, s = math.cos(t), math.sin(t)
        r0, r1, r2 = a * c + b * s + m, -a * s + b * c, -a * c - b * s
        g1, g2 = 2 * (r0 @ r1), 2 * (r1 @ r1 + r0 @ r2)
        if g2 <= 0:
            break
        step = g1 / g2
        t -= step
        if abs(step) < 1e-15:
            break
    return t


def _conditioning(H: np.ndarray) -> float:
    s = np.linalg.svd(H, compute_uv=False)
    return s[-1] / s[0] if s[0] > 0 else 0.0


def common_tangent_params(Ha: np.ndarray, Hb: np.ndarray) -> list[tuple[float, float]]:
    """Outer common tangents of two ellipse images: [(t_a, t_b)] parameters of the tangent points.

    Empty when there are none (one image inside the other, e.g. the camera inside the surface).
    """
    swap = _conditioning(Ha) < _conditioning(Hb)
    if swap:
        Ha, Hb = Hb, Ha
    if _conditioning(Ha) < 1e-12:
        return []  # both seen exactly edge-on: no surface to outline
    Ha_inv = np.linalg.inv(Ha)
    Cb = dual_conic(Hb)
    M = Ha_inv @ Cb @ Ha_inv.T
    M = (M + M.T) / 2
    M = M / np.abs(M).max()
    a0 = (M[0, 0] + M[1, 1]) / 2 + M[2, 2]
    a1, b1 = -2 * M[0, 2], -2 * M[1, 2]
    a2, b2 = (M[0, 0] - M[1, 1]) / 2, M[0, 1]
    # f(s) = a0 + a1 cos s + b1 sin s + a2 cos 2s + b2 sin 2s; z^2 f as a polynomial in z = e^{is}
    coeffs = [(a2 - 1j * b2) / 2, (a1 - 1j * b1) / 2, a0, (a1 + 1j * b1) / 2, (a2 + 1j * b2) / 2]
    roots = np.roots(coeffs)

    def f(s):
        return a0 + a1 * np.cos(s) + b1 * np.sin(s) + a2 * np.cos(2 * s) + b2 * np.sin(2 * s)

    def df(s):
        return -a1 * np.sin(s) + b1 * np.cos(s) - 2 * a2 * np.sin(2 * s) + 2 * b2 * np.cos(2 * s)

    centre_a = Ha[:, 2]
    centre_b = Hb[:, 2]
    out = []
    for z in roots:
        if abs(abs(z) - 1.0) > UNIT_TOL:
            continue
        s = float(np.angle(z))
        for _ in range(3):  # polish on the real function
            d = df(s)
            if d == 0:
                break
            s -= f(s) / d
        l = Ha_inv.T @ np.array([math.cos(s), math.sin(s), -1.0])
        # outer tangent: both ellipses (their centres) on the same side of the line
        if np.sign(l @ centre_a) * np.sign(centre_a[2]) != np.sign(l @ centre_b) * np.sign(centre_b[2]):
            continue
        Pb = Cb @ l
        tb = parameter_on(Hb, Pb)
        out.append((tb, s) if swap else (s, tb))
    return out


def silhouette_segments(ca, Ua, Va, cb, Ub, Vb, arc_a=None, arc_b=None):
    """Camera-frame 3D segments (start on a, end on b) of the visible sides between two ellipses."""
    Ha, Hb = homography(ca, Ua, Va), homography(cb, Ub, Vb)
    segs = []
    for ta, tb in common_tangent_params(Ha, Hb):
        if (arc_a is not None and not _in_arc(ta, arc_a)) or (arc_b is not None and not _in_arc(tb, arc_b)):
            continue
        A = ca + math.cos(ta) * Ua + math.sin(ta) * Va
        B = cb + math.cos(tb) * Ub + math.sin(tb) * Vb
        segs.append((A, B))
    return segs


def _in_arc(t: float, arc: tuple[float, float]) -> bool:
    t0, t1 = arc
    if t1 - t0 >= 2 * math.pi - 1e-12:
        return True
    return (t - t0) % (2 * math.pi) <= (t1 - t0)
