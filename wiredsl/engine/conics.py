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

Every function works on stacks of ellipses at once ((n, 3, 3) homographies): the
quartics of all silhouettes of all views are solved together as the eigenvalues
of their companion matrices, so projecting a view has no Python loop per feature.
"""

from __future__ import annotations

import math

import numpy as np

D = np.diag([1.0, 1.0, -1.0])
UNIT_TOL = 1e-6  # how far from |z| = 1 a root may be and still be a real tangent


def homography(c: np.ndarray, U: np.ndarray, V: np.ndarray) -> np.ndarray:
    """H mapping (cos t, sin t, 1) to homogeneous unit-plane points of the ellipse: columns U, V, c.

    Shapes (3,) each give (3, 3); (n, 3) each give (n, 3, 3).
    """
    return np.stack([U, V, c], axis=-1)


def dual_conic(H: np.ndarray) -> np.ndarray:
    """C* = H diag(1, 1, -1) H^T, for one (3, 3) or a stack (n, 3, 3)."""
    return (H * np.array([1.0, 1.0, -1.0])) @ np.swapaxes(H, -1, -2)


def image_ellipses(H: np.ndarray):
    """(ok (n,), centre (n, 2), semi-axes (major, minor) (n, 2), angle of the major axis in (-pi/2, pi/2] (n,))
    of the images of the unit circle under stacks H (n, 3, 3) (`homography`, a camera matrix applied); not ok
    when an image is not a real ellipse (a parabola or hyperbola: the ellipse meets the camera's principal plane)
    or is degenerate (seen edge-on).

    No conic is formed. A Lorentz boost L (L D L^T = D: it maps the circle onto itself) with H L's third row
    (0, 0, h) makes the image the affine ellipse centre + M (cos s, sin s), M = (H L)[:2, :2] / h; its axes are
    M's singular values and the major axis is M's first left singular vector, both in closed form. A conic's
    entries are squares of the image's size, and its centre term cancels against them: for an ellipse seen
    nearly edge-on that cancellation, and LAPACK's choice of eigenvector sign, moved the major axis by 5e-4
    rad between OpenBLAS kernels. Here every step is a few flops of the image's own size.
    """
    n = len(H)
    finite = np.isfinite(H).all(axis=(1, 2))
    Hs = np.where(finite[:, None, None], H, np.eye(3))
    r = Hs[:, 2, :]  # the principal plane's row: r . (cos t, sin t, 1) = 0 where the circle meets it
    rho = np.hypot(r[:, 0], r[:, 1])
    r3 = np.abs(r[:, 2])
    q = (r3 - rho) * (r3 + rho)  # > 0: the circle lies wholly on one side of the principal plane
    ok = finite & (q > 1e-12 * (r3 * r3 + rho * rho))
    sign = np.where(r[:, 2] < 0, -1.0, 1.0)
    beta = np.where(ok[:, None], r[:, :2] / np.where(ok, r[:, 2], 1.0)[:, None], 0.0)
    gamma = np.where(ok, r3 / np.sqrt(np.where(ok, q, 1.0)), 1.0)
    L = np.zeros((n, 3, 3))
    L[:, :2, :2] = np.eye(2) + (gamma**2 / (gamma + 1))[:, None, None] * beta[:, :, None] * beta[:, None, :]
    L[:, :2, 2] = L[:, 2, :2] = -gamma[:, None] * beta
    L[:, 2, 2] = gamma
    HL = Hs @ L
    h = sign * r3 / gamma  # (H L)[2, 2]; the third row's first two entries are zero by construction
    M = HL[:, :2, :2] / h[:, None, None]
    centre = HL[:, :2, 2] / h[:, None]
    # closed-form SVD of 2x2 M: M = R(phi) diag(s1, s2) R(-theta)
    e, f = (M[:, 0, 0] + M[:, 1, 1]) / 2, (M[:, 0, 0] - M[:, 1, 1]) / 2
    g, k = (M[:, 1, 0] + M[:, 0, 1]) / 2, (M[:, 1, 0] - M[:, 0, 1]) / 2
    qq, rr = np.hypot(e, k), np.hypot(f, g)
    axes = np.stack([qq + rr, np.abs(qq - rr)], axis=1)
    ok &= axes[:, 1] > 1e-6 * axes[:, 0]
    angle = (np.arctan2(g, f) + np.arctan2(k, e)) / 2
    angle = np.pi / 2 - (np.pi / 2 - angle) % np.pi  # a direction: into (-pi/2, pi/2]
    axes = np.where(ok[:, None], axes, 1.0)
    return ok, np.where(ok[:, None], centre, 0.0), axes, np.where(ok, angle, 0.0)


def parameters_on(H: np.ndarray, P: np.ndarray) -> np.ndarray:
    """For stacks H (k, 3, 3) and P (k, 3): the parameters t with H (cos t, sin t, 1) ~ P.

    Minimises |[P]x H (cos t, sin t, 1)| over the circle itself, so it also holds when
    the ellipse is seen edge-on and H has rank 2 (a plain null vector of [P]x H could
    then be H's own null vector, which is not on the circle).
    """
    k = len(H)
    Px = np.zeros((k, 3, 3))
    Px[:, 0, 1], Px[:, 0, 2], Px[:, 1, 2] = -P[:, 2], P[:, 1], -P[:, 0]
    Px[:, 1, 0], Px[:, 2, 0], Px[:, 2, 1] = P[:, 2], -P[:, 1], P[:, 0]
    M = Px @ H
    big = np.abs(M).max(axis=(1, 2), initial=0.0)
    M = M / np.where(big > 0, big, 1.0)[:, None, None]
    a, b, m = M[:, :, 0], M[:, :, 1], M[:, :, 2]
    t = _grid_minimum(a, b, m)
    active = np.ones(k, dtype=bool)
    for _ in range(8):  # Newton on g'(t) = 2 r.r', from within one grid step of the minimum
        c, s = np.cos(t)[:, None], np.sin(t)[:, None]
        r0, r1, r2 = a * c + b * s + m, -a * s + b * c, -a * c - b * s
        g1, g2 = 2 * (r0 * r1).sum(axis=1), 2 * ((r1 * r1).sum(axis=1) + (r0 * r2).sum(axis=1))
        active &= g2 > 0
        step = np.where(active, g1 / np.where(active, g2, 1.0), 0.0)
        t = t - step
        active &= np.abs(step) >= 1e-15
        if not active.any():
            break
    return t


GRID = np.linspace(-math.pi, math.pi, 361)  # where parameters_on starts: every degree
GRID_ROWS = 32  # rows of parameters_on's grid evaluated at once: temporaries below malloc's 128 KiB mapping threshold


def _grid_minimum(a: np.ndarray, b: np.ndarray, m: np.ndarray) -> np.ndarray:
    """The point of GRID where |a cos t + b sin t + m|^2 is least, for rows (k, 3) of a, b and m; the sum
    of the three squares taken in their order, a block of rows at a time."""
    cos, sin = np.cos(GRID), np.sin(GRID)
    best = np.zeros(len(a), dtype=int)
    for lo in range(0, len(a), GRID_ROWS):
        rows = slice(lo, lo + GRID_ROWS)
        total = None
        for i in range(3):
            r = a[rows, i, None] * cos + b[rows, i, None] * sin + m[rows, i, None]
            total = r * r if total is None else total + r * r
        best[rows] = np.argmin(total, axis=1)
    return GRID[best]


def _conditioning(H: np.ndarray) -> np.ndarray:
    """Smallest over largest singular value of each (n, 3, 3); 0 for non-finite or zero matrices."""
    finite = np.isfinite(H).all(axis=(1, 2))
    s = np.linalg.svd(np.where(finite[:, None, None], H, 0.0), compute_uv=False) if len(H) else np.zeros((0, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(finite & (s[:, 0] > 0), s[:, -1] / np.where(s[:, 0] > 0, s[:, 0], 1.0), 0.0)


def common_tangents(Ha: np.ndarray, Hb: np.ndarray):
    """Outer common tangents of pairs of ellipse images, stacks (n, 3, 3).

    Returns (owner (k,), t_a (k,), t_b (k,)): the pair and the ellipse parameters of the tangent points.
    A pair has none when one image lies inside the other (e.g. the camera inside the surface).
    """
    n = len(Ha)
    ca, cb = _conditioning(Ha), _conditioning(Hb)
    swap = ca < cb
    H1 = np.where(swap[:, None, None], Hb, Ha)
    H2 = np.where(swap[:, None, None], Ha, Hb)
    ok = np.maximum(ca, cb) >= 1e-12  # both seen exactly edge-on: no surface to outline
    H1_inv = np.linalg.inv(np.where(ok[:, None, None], H1, np.eye(3))) if n else np.zeros((0, 3, 3))
    Cb = dual_conic(H2)
    M = H1_inv @ Cb @ np.swapaxes(H1_inv, 1, 2)
    M = (M + np.swapaxes(M, 1, 2)) / 2
    ok &= np.isfinite(M).all(axis=(1, 2))
    big = np.abs(np.where(ok[:, None, None], M, 0.0)).max(axis=(1, 2), initial=0.0)
    ok &= big > 0
    M = np.where(ok[:, None, None], M, np.eye(3)) / np.where(ok, big, 1.0)[:, None, None]
    a0 = (M[:, 0, 0] + M[:, 1, 1]) / 2 + M[:, 2, 2]
    a1, b1 = -2 * M[:, 0, 2], -2 * M[:, 1, 2]
    a2, b2 = (M[:, 0, 0] - M[:, 1, 1]) / 2, M[:, 0, 1]
    # f(s) = a0 + a1 cos s + b1 sin s + a2 cos 2s + b2 sin 2s; z^2 f as a polynomial in z = e^{is}
    coeffs = np.stack([(a2 - 1j * b2) / 2, (a1 - 1j * b1) / 2, a0 + 0j, (a1 + 1j * b1) / 2, (a2 + 1j * b2) / 2], 1)
    roots = _quartic_roots(coeffs, ok)
    unit = np.abs(np.abs(roots) - 1.0) <= UNIT_TOL  # NaN (no root) is never on the circle
    row, col = np.nonzero(unit)
    z = roots[row, col]
    s = np.angle(z)
    A0, A1, B1, A2, B2 = a0[row], a1[row], b1[row], a2[row], b2[row]
    active = np.ones(len(s), dtype=bool)
    for _ in range(3):  # polish on the real function
        d = -A1 * np.sin(s) + B1 * np.cos(s) - 2 * A2 * np.sin(2 * s) + 2 * B2 * np.cos(2 * s)
        active &= d != 0
        f = A0 + A1 * np.cos(s) + B1 * np.sin(s) + A2 * np.cos(2 * s) + B2 * np.sin(2 * s)
        s = np.where(active, s - f / np.where(active, d, 1.0), s)
    w = np.stack([np.cos(s), np.sin(s), -np.ones(len(s))], axis=1)
    inv = H1_inv[row]
    line = np.einsum("kji,kj->ki", inv, w)  # H1^-T w
    centre_a, centre_b = H1[row, :, 2], H2[row, :, 2]
    # outer tangent: both ellipses (their centres) on the same side of the tangent plane through the eye
    # (the line is that plane's normal); a 3D test, so it holds for centres behind the camera's plane too
    side_a = np.sign((line * centre_a).sum(axis=1))
    side_b = np.sign((line * centre_b).sum(axis=1))
    outer = side_a == side_b
    row, s, line = row[outer], s[outer], line[outer]
    Pb = np.einsum("kij,kj->ki", Cb[row], line)
    tb = parameters_on(H2[row], Pb)
    sw = swap[row]
    return row, np.where(sw, tb, s), np.where(sw, s, tb)


def _quartic_roots(coeffs: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Roots (n, 4) of the quartics coeffs (n, 5) (highest power first), NaN where fewer or not ok.

    The companion matrices' eigenvalues, as np.roots computes them, for all rows at once;
    rows whose leading or trailing coefficient vanishes go through np.roots itself.
    """
    n = len(coeffs)
    out = np.full((n, 4), np.nan + 0j)
    full = ok & (coeffs[:, 0] != 0) & (coeffs[:, 4] != 0) & np.isfinite(coeffs).all(axis=1)
    rows = np.flatnonzero(full)
    if len(rows):
        C = np.zeros((len(rows), 4, 4), dtype=complex)
        C[:, 1:, :-1] = np.eye(3)
        C[:, 0, :] = -coeffs[rows, 1:] / coeffs[rows, :1]
        out[rows] = np.linalg.eigvals(C)
    for r in np.flatnonzero(ok & ~full & np.isfinite(coeffs).all(axis=1)):  # degenerate: rare
        z = np.roots(coeffs[r])
        out[r, :len(z)] = z
    return out


def silhouette_segments_batch(ca, Ua, Va, cb, Ub, Vb, arc_a, full_a, arc_b, full_b):
    """Silhouette sides of n ellipse pairs (camera frame, (n, 3) each; arcs (n, 2), full (n,) bool).

    Returns (owner (k,), A (k, 3), B (k, 3)): the pair and the side's end points on ellipse a and b,
    in the order the tangents were found for each pair.
    """
    owner, ta, tb = common_tangents(homography(ca, Ua, Va), homography(cb, Ub, Vb))
    keep = (full_a[owner] | in_arc(ta, arc_a[owner])) & (full_b[owner] | in_arc(tb, arc_b[owner]))
    o, ta, tb = owner[keep], ta[keep], tb[keep]
    A = ca[o] + np.cos(ta)[:, None] * Ua[o] + np.sin(ta)[:, None] * Va[o]
    B = cb[o] + np.cos(tb)[:, None] * Ub[o] + np.sin(tb)[:, None] * Vb[o]
    return o, A, B


def in_arc(t: np.ndarray, arc: np.ndarray) -> np.ndarray:
    """Whether parameters t (k,) lie on the arcs (k, 2) [t0, t1] (mod 2 pi)."""
    t0, t1 = arc[:, 0], arc[:, 1]
    return (t1 - t0 >= 2 * math.pi - 1e-12) | (np.mod(t - t0, 2 * math.pi) <= t1 - t0)
