"""The fuzz campaign's slow inputs (issue 23), each `wiredsl check`ed in its own process: CPU seconds and the
size of what it wrote on stderr. Before the fixes: the soup 2 minutes, the half-disc 15 s (8.9 s here), the
braces 33 s, the token 15 MB of diagnostics.

    python benchmarks/hostile_inputs.py
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

SCENE = """wiredsl 1
model m {{
  mesh read "{mesh}"
}}
place m as p at (3, 0, 0)
camera c {{
  focal 600px
  size (640px, 480px)
}}
rig r {{
  left c at (0, 0.06, 1) looking (1, 0, 0)
  right c at (0, -0.06, 1) looking (1, 0, 0)
}}
path run {{ {path} }}
"""


def write_obj(path: Path, V: np.ndarray, F: np.ndarray) -> None:
    with open(path, "w") as f:
        f.write("".join(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in V))
        f.write("".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in F))


def soup(path: Path, m: int = 200_000) -> None:
    """m triangles, none sharing a vertex: m regions, m faces, 3 m sharp edges."""
    rng = np.random.default_rng(1)
    T = rng.uniform(-1, 1, (m, 1, 3)) + rng.normal(0, 0.01, (m, 3, 3))
    write_obj(path, T.reshape(-1, 3), np.arange(3 * m).reshape(m, 3))


def half_disc(path: Path, n: int = 1500) -> None:
    """A flat half-disc whose boundary is 3,000 points: 1,500 on the arc, 1,500 collinear on the diameter."""
    D = np.column_stack([np.linspace(-1, 1, n), np.zeros(n), np.zeros(n)])
    th = np.linspace(np.pi, 0, n)
    A = np.column_stack([np.cos(th), np.sin(th), np.zeros(n)])
    F, i, j = [], 0, 0
    while i < n - 1 or j < n - 1:  # zip the two rows of points together
        if j < n - 1 and (i == n - 1 or A[j + 1, 0] <= D[i + 1, 0]):
            F.append((i, n + j + 1, n + j))
            j += 1
        else:
            F.append((i, i + 1, n + j))
            i += 1
    write_obj(path, np.vstack([D, A]), np.array(F))


def check(path: Path) -> tuple[float, int]:
    """CPU seconds of `wiredsl check path` in a new process, and the bytes it wrote on stderr."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    r = subprocess.run([sys.executable, "-m", "wiredsl", "check", str(path)], capture_output=True,
                       env={**os.environ, "XDG_CACHE_HOME": str(path.parent / "cache")})
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if r.returncode not in (0, 1):
        raise SystemExit(f"{path.name}: exit {r.returncode}\n{r.stderr.decode()[:2000]}")
    return after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, len(r.stderr)


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        soup(d / "soup.obj")
        half_disc(d / "half.obj")
        (d / "soup.wd").write_text(SCENE.format(mesh="soup.obj", path="pose (0, 0)"))
        (d / "half.wd").write_text(SCENE.format(mesh="half.obj", path="pose (0, 0)"))
        (d / "braces.wd").write_text("{" * 4_000_000)
        good = "1305031098.6659 1.3563 0.6305 1.6380 0.6132 0.5962 -0.3311 -0.3986\n"
        (d / "t.tum").write_text(good + "1305031098.7 1e" + "9" * 5_000_000 + " 0.6 1.6 0.6 0.5 -0.3 -0.3\n")
        (d / "token.wd").write_text(SCENE.format(mesh="half.obj", path='read "t.tum" format tum'))
        for name, what in (("soup", "200,000-triangle soup"), ("half", "half-disc, 3,000 boundary points"),
                           ("braces", "4 MB of '{'"), ("token", "5,000,000-digit trajectory token")):
            cpu, err = check(d / f"{name}.wd")
            print(f"{what:36s} {cpu:7.2f} s CPU  {err:>9,} bytes of diagnostics")


if __name__ == "__main__":
    main()
