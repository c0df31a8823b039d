"""Packed strokes: the vectorised cuts agree with the per-polyline reference implementation."""

from __future__ import annotations

import numpy as np
import pytest

from wiredsl.engine import geometry
from wiredsl.engine import imageset as im


def pack(polys: list[np.ndarray], closed=None) -> im.ImageSet:
    counts = [len(p) for p in polys]
    z = np.zeros(len(polys), dtype=int)
    return im.ImageSet(np.concatenate(polys), np.concatenate([[0], np.cumsum(counts)]).astype(int),
                       np.arange(len(polys)), z - 1, z - 1, z + 1, z.astype(bool),
                       np.zeros(len(polys), bool) if closed is None else np.asarray(closed), z,
                       np.zeros((0, 2)), np.zeros(0, int), np.zeros(0, int))


@pytest.mark.parametrize("seed", range(5))
def test_clip_rect_matches_the_per_polyline_clipper(seed):
    rng = np.random.default_rng(seed)
    polys = [rng.uniform(-200, 800, size=(rng.integers(2, 9), 2)) for _ in range(200)]
    out = im.clip_rect(pack(polys), 640, 480)
    ref = [(i, piece, cut) for i, p in enumerate(polys) for piece, cut in geometry.clip_polyline_rect(p, 640, 480)]
    assert out.n_strokes == len(ref)
    for k, (i, piece, cut) in enumerate(ref):
        assert out.fid[k] == i and bool(out.clipped[k]) == cut
        assert out.pts[out.start[k]:out.start[k + 1]] == pytest.approx(piece, abs=1e-9)


def test_keep_vertex_runs_cuts_at_invalid_vertices_and_keeps_the_rest_exactly():
    p = np.column_stack([np.arange(6.0), np.zeros(6)])
    s = pack([p, p + [0, 10]])
    ok = np.array([True, True, False, True, True, True, True, True, True, True, True, True])
    out = im.keep_vertex_runs(s, ok)
    pieces = [out.pts[out.start[k]:out.start[k + 1]].tolist() for k in range(out.n_strokes)]
    assert pieces == [p[:2].tolist(), p[3:].tolist(), (p + [0, 10]).tolist()]
    assert out.clipped.tolist() == [True, True, False]


def test_unroll_closed_traverses_a_loop_twice():
    square = np.array([[0.0, 0], [1, 0], [1, 1], [0, 1], [0, 0]])
    out = im.unroll_closed(pack([square], closed=[True]))
    assert len(out.pts) == 2 * len(square) + 1 and not out.closed.any()
    assert im.arc_lengths(out)[1][0] == pytest.approx(2 * 4.0)
