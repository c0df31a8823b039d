"""Extreme but legal values (issue 15): no numpy RuntimeWarning (the suite makes them errors), answers that
agree with a high-precision oracle."""

from __future__ import annotations

from pathlib import Path

import mpmath as mp
import numpy as np
import pytest
from click.testing import CliRunner

from wiredsl.cli import main
from wiredsl.engine.geometry import fold_radius


def fold_reference(k1: float, k2: float) -> float:
    """Smallest r > 0 with d/dr r (1 + k1 r^2 + k2 r^4) = 0, in 1500-digit arithmetic (inf if none)."""
    with mp.workdps(1500):
        k1, k2 = mp.mpf(k1), mp.mpf(k2)
        if k2 == 0:
            return float(mp.sqrt(-1 / (3 * k1))) if k1 < 0 else float("inf")
        disc = 9 * k1 ** 2 - 20 * k2
        if disc < 0:
            return float("inf")
        positive = [s for s in ((-3 * k1 + sign * mp.sqrt(disc)) / (10 * k2) for sign in (1, -1)) if s > 0]
        return float(mp.sqrt(min(positive))) if positive else float("inf")


@pytest.mark.parametrize(("k1", "k2"), [(-0.1, 0.01), (1e300, 0.0), (-1e300, 0.0), (-1e300, 1e300), (-1e-300, 0.0),
                                        (-5.0, -1e308), (1e308, -1e308), (-0.2, 0.004), (0.0, -1e-9),
                                        (-1e200, 1e150), (-1e300, -1e300)])
def test_fold_radius_of_extreme_distortion_matches_mpmath(k1, k2):
    """b^2 overflowed for |k1| > 1e154 (a RuntimeWarning with numpy scalars) and underflowed for |k1| < 1e-154."""
    got = fold_radius(np.float64(k1), np.float64(k2))
    want = fold_reference(k1, k2)
    assert got == pytest.approx(want, rel=1e-12) if np.isfinite(want) else got == want


def test_fold_radius_of_arrays_is_each_ones_own():
    """Every trial's fold radius at once (a batch's perturbed cameras) gives the doubles of one call each."""
    rng = np.random.default_rng(3)
    k1 = np.concatenate([[-0.1, 1e300, -1e300, -1e-300, 0.0, -0.0, -5.0, 1e308, -0.2, 0.3],
                         rng.normal(0, 0.3, 200), -(10.0 ** rng.uniform(-300, 300, 50))])
    k2 = np.concatenate([[0.01, 0.0, 1e300, 0.0, -1e-9, 0.0, -1e308, -1e308, 0.004, 0.0],
                         rng.normal(0, 0.3, 200), 10.0 ** rng.uniform(-300, 300, 50) * rng.choice([-1, 0, 1], 50)])
    got = fold_radius(k1, k2)
    assert got.shape == k1.shape and np.isinf(got).any() and np.isfinite(got).any()
    assert got.tolist() == [fold_radius(a, b) for a, b in zip(k1.tolist(), k2.tolist(), strict=True)]
    for g, a, b in zip(got.tolist(), k1.tolist(), k2.tolist(), strict=True):
        want = fold_reference(a, b)
        assert g == pytest.approx(want, rel=1e-12) if np.isfinite(want) else g == want


@pytest.mark.parametrize(("k", "engine"), [("1e300", "kernel"), ("-1e300", "kernel"), ("-1e-300", "kernel"),
                                           ("1e300", "numpy"), ("-1e300", "numpy"),
                                           ("-1e-300", "numpy")])
def test_a_build_with_extreme_distortion_gives_no_runtime_warning(tmp_path, k, engine):
    pytest.importorskip("numba") if engine == "kernel" else None
    text = Path("scenes/lab.wd").read_text().replace("  k 0.02\n", f"  k {k}\n", 1)
    assert f"k {k}" in text
    (tmp_path / "models").symlink_to(Path("scenes/models").resolve())
    (tmp_path / "lab.info").symlink_to(Path("scenes/lab.info").resolve())
    (tmp_path / "lk.wd").write_text(text)
    r = CliRunner().invoke(main, ["build", str(tmp_path / "lk.wd"), "--trials", "2", "--pose", "0", "--format",
                                  "jsonl", "--no-svg", "-o", str(tmp_path / "out"), "--seed", "1",
                                  "--engine", engine])
    assert r.exit_code == 0, r.output
    if engine == "numpy":  # the same features as the kernel's, far vertices cut away by both alike
        pytest.importorskip("numba")
        r = CliRunner().invoke(main, ["build", str(tmp_path / "lk.wd"), "--trials", "2", "--pose", "0", "--format",
                                      "jsonl", "--no-svg", "-o", str(tmp_path / "k"), "--seed", "1", "--engine",
                                      "kernel"])
        assert r.exit_code == 0, r.output
        import wiredsl

        ours, theirs = (wiredsl.load(tmp_path / d / "features.jsonl") for d in ("out", "k"))
        assert [(f["kind"], f["source"], len(f.get("points") or [0])) for f in ours] == [
            (f["kind"], f["source"], len(f.get("points") or [0])) for f in theirs]
        for a, b in zip(ours, theirs, strict=True):
            assert np.allclose(a.get("points", a.get("at")), b.get("points", b.get("at")), rtol=0, atol=1e-9)
