"""Effects and measures from installed packages (entry points), and scene files that cannot import code.

The package is a real distribution: a module and a `.dist-info` with `entry_points.txt`, put on sys.path, which
is what `pip install` leaves in site-packages; importlib.metadata finds it as it finds any installed package.
"""

from __future__ import annotations

import builtins
import json
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from helpers import make_dist, plugins_on_path

import wiredsl
from wiredsl import plugins
from wiredsl.cli import main

ROOT = Path(__file__).resolve().parent.parent

MODULE = '''
from typing import ClassVar

import numpy as np

from wiredsl.effects.base import Effect, KernelStage, Params, param
from wiredsl.engine import imageset as im
from wiredsl.measures.base import Measure


class CentreNoiseParams(Params):
    sigma: float = param(0.5, "image", "corner noise at the image's corner (grows from 0 at the centre)", ge=0)


class CentreNoise(Effect):
    """Corner localisation noise that grows with the distance from the image centre."""

    name = "centre_noise"
    acts_on = "corner detection"
    Params = CentreNoiseParams
    doc = "corner noise growing from the image centre outwards"

    @classmethod
    def is_identity(cls, p):
        return p.sigma == 0

    @classmethod
    def disturb(cls, p, s, ctx):
        n = ctx.draws(cls.name, s.corner_trial, per_item=2, normal=True)
        r = np.hypot(*(s.corners - [320.0, 240.0]).T)[:, None] / 400.0
        return im.replace(s, corners=s.corners + p.sigma * r * n)


class Wrong(CentreNoise):
    name = "wrong_shape"

    @classmethod
    def disturb(cls, p, s, ctx):
        return im.replace(s, corners=s.corners[:, :1])


class BadKernel(CentreNoise):
    name = "bad_kernel"
    kernel = KernelStage("wdplug.kernel:stage", ("sigma", "nope"), ())


class CornerCountParams(Params):
    scale: float = param(1.0, "number", "multiplies the count", gt=0)


class CornerCount(Measure):
    name = "corner_count"
    Params = CornerCountParams
    statistics: ClassVar[tuple[str, ...]] = ("corners",)
    doc = "left corners a trial"

    @classmethod
    def measure(cls, p, prepared, pose, disturbed, n_trials):
        return {"corners": p.scale * np.bincount(disturbed["left"].corner_trial, minlength=n_trials)}


class NanMeasure(CornerCount):
    name = "nan_measure"

    @classmethod
    def measure(cls, p, prepared, pose, disturbed, n_trials):
        return {"corners": np.full(n_trials, np.nan)}


class NotAnEffect:
    name = "not_an_effect"
'''

ENTRY_POINTS = '''
[wiredsl.effects]
centre_noise = wdplug:CentreNoise
wrong_shape = wdplug:Wrong
broken_import = wdplug.missing:Thing
not_an_effect = wdplug:NotAnEffect
bad_kernel = wdplug:BadKernel
edge_loss = wdplug:CentreNoise

[wiredsl.measures]
corner_count = wdplug:CornerCount
nan_measure = wdplug:NanMeasure
'''


@pytest.fixture
def installed(tmp_path, monkeypatch):
    """The wdplug distribution installed (on sys.path) for this test only."""
    with plugins_on_path(monkeypatch, make_dist(tmp_path / "site", "wdplug", MODULE, ENTRY_POINTS),
                         modules=("wdplug",)):
        yield tmp_path / "site"


LAB_PLUS = textwrap.dedent('''\
    wiredsl 1
    include "{lab}"
    pipeline plug {{
      corner_loss keep 0.9
      centre_noise sigma 4px
    }}
    ''')


def scene_file(tmp_path: Path, body: str) -> Path:
    f = tmp_path / "plug.wd"
    f.write_text(LAB_PLUS.format(lab=ROOT / "scenes" / "lab.wd") + body)
    return f


def test_a_plugin_effect_runs_in_a_build_on_numpy_and_the_manifest_says_so(installed, tmp_path):
    f = scene_file(tmp_path, "")
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["build", str(f), "--pipeline", "plug", "--seed", "3", "--trials", "4",
                                  "--format", "npz", "--no-svg", "-o", str(out), "--engine", "kernel"])
    assert r.exit_code == 0, r.output
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["engine"] == "kernel"  # the stages before the plug-in's compiled, it and those after on numpy
    assert manifest["engines"] == {"corner_loss": "kernel", "centre_noise": "numpy"}
    assert any("from centre_noise on run on numpy: no compiled kernel for centre_noise" in w
               for w in manifest["warnings"])
    scene = wiredsl.compile(str(f))
    ideal = next(wiredsl.simulate(scene, trials=1, seed=3, pipeline=scene.pipeline("plug").model_copy(
        update={"stages": []})))
    moved = wiredsl.load(out / "features.npz", arrays=True)["corners"]
    assert len(moved) and not np.isin(moved, ideal["corners"].astype(np.float32)).all()  # the noise moved them


def test_a_plugin_measure_ranks_in_a_study(installed, tmp_path):
    f = scene_file(tmp_path, textwrap.dedent('''
        study s {
          pipeline plug
          vary centre_noise.sigma values [0, 8px]
          trials 4
          poses [0]
          measure corner_count scale 2
        }
        '''))
    r = CliRunner().invoke(main, ["study", str(f), "s", "-o", str(tmp_path / "st"), "--executor", "inprocess",
                                  "--no-plots"])
    assert r.exit_code == 0, r.output
    table = json.loads((tmp_path / "st" / "table.json").read_text())
    assert "corner_count" in json.dumps(table)
    # the stage without a kernel is said, without suggesting an option `study` does not have (issue 35, item 6)
    assert "'centre_noise' (wdplug" in r.stderr and "no compiled kernel" in r.stderr and "--engine" not in r.stderr


def test_check_reference_and_schema_know_a_plugins_parameters(installed, tmp_path):
    bad = scene_file(tmp_path, "").read_text().replace("sigma 4px", "sigma 4px wobble 2")
    (tmp_path / "bad.wd").write_text(bad)
    r = CliRunner().invoke(main, ["check", str(tmp_path / "bad.wd")])
    assert r.exit_code == 1 and "wobble" in r.stderr and "sigma" in r.stderr
    ref = CliRunner().invoke(main, ["reference"]).output
    assert "`centre_noise`" in ref and "[sigma <sigma>]" in ref
    from wiredsl.io import schema

    assert "CentreNoiseParams" in json.dumps(schema.generate("scene"))
    from wiredsl import lsp

    text = bad.replace(" sigma 4px wobble 2", " ")
    lines = text.splitlines()
    line = next(i for i, s in enumerate(lines, 1) if "centre_noise" in s)
    assert "image centre outwards" in lsp.hover(None, text, "x.wd", line, 3)
    assert "centre_noise" in [c.label for c in lsp.completions(None, text, line, 1)]
    sigma = [c for c in lsp.completions(None, text, line, len(lines[line - 1]) + 1) if c.label == "sigma"]
    assert sigma and "default 0.5 px" in sigma[0].detail


def test_broken_plugins_get_a_diagnostic_naming_their_package(installed, tmp_path):
    for stage, why in (("broken_import", "failed to import: ModuleNotFoundError"),
                       ("not_an_effect", "is not a subclass of wiredsl.Effect"),
                       ("bad_kernel", "its kernel takes 'nope', not among its parameters")):
        f = tmp_path / f"{stage}.wd"
        f.write_text(f'wiredsl 1\ninclude "{ROOT / "scenes" / "lab.wd"}"\npipeline p {{\n  {stage}\n}}\n')
        r = CliRunner().invoke(main, ["check", str(f)])
        assert r.exit_code == 1, r.output
        assert "E180" in r.stderr and "package 'wdplug' 0.3" in r.stderr and why in r.stderr, r.stderr
    f = tmp_path / "wrong.wd"
    f.write_text(f'wiredsl 1\ninclude "{ROOT / "scenes" / "lab.wd"}"\npipeline p {{\n  wrong_shape\n}}\n')
    r = CliRunner().invoke(main, ["build", str(f), "--pipeline", "p", "--seed", "1", "--no-svg",
                                  "-o", str(tmp_path / "o")])
    assert r.exit_code == 1 and "E181" in r.stderr and "wdplug" in r.stderr and "(n, 2)" in r.stderr, r.output
    f = scene_file(tmp_path, "study s {\n pipeline plug\n vary centre_noise.sigma values [1px]\n trials 2\n poses [0]\n"
                                "measure nan_measure\n}\n")
    r = CliRunner().invoke(main, ["study", str(f), "-o", str(tmp_path / "st"), "--executor", "inprocess",
                                  "--no-plots"])
    assert r.exit_code == 1 and "E181" in r.stderr and "non-finite" in r.stderr and "wdplug" in r.stderr, r.output


def test_plugins_lists_packages_and_clashes(installed):
    r = CliRunner().invoke(main, ["plugins"])
    assert r.exit_code == 1
    lines = {tuple(line.split("\t")[:3]): line for line in r.output.splitlines()}
    assert lines[("effect", "centre_noise", "wdplug 0.3")].endswith("\tok")
    assert lines[("measure", "corner_count", "wdplug 0.3")].endswith("\tok")
    assert "named like the built-in one" in lines[("effect", "edge_loss", "wdplug 0.3")]
    assert "failed to import" in lines[("effect", "broken_import", "wdplug 0.3")]


def test_two_packages_claiming_a_name_are_both_named(tmp_path, monkeypatch):
    sites = [make_dist(tmp_path / pkg, pkg, MODULE, f"[wiredsl.effects]\ncentre_noise = {pkg}:CentreNoise\n")
             for pkg in ("wdone", "wdtwo")]
    with plugins_on_path(monkeypatch, *sites, modules=("wdone", "wdtwo")):
        f = tmp_path / "s.wd"
        f.write_text(f'wiredsl 1\ninclude "{ROOT / "scenes" / "lab.wd"}"\npipeline p {{\n  centre_noise\n}}\n')
        r = CliRunner().invoke(main, ["check", str(f)])
        assert r.exit_code == 1 and "'wdone'" in r.stderr and "'wdtwo'" in r.stderr, r.stderr


def test_built_in_names_never_scan_installed_packages(monkeypatch):
    def refuse(kind):
        raise AssertionError(f"scanned the entry points of {kind}s for a built-in name")

    from wiredsl.language import compile_study
    from wiredsl.measures import REGISTRY

    monkeypatch.setattr(compile_study, "measure_registry", lambda: REGISTRY)  # (the tests' own measure aside)
    monkeypatch.setattr(plugins, "installed", refuse)
    wiredsl.compile("scenes/studies/lab_study.wd")


HOSTILE = '''wiredsl 1
include "{lab}"
pipeline p {{
  os.system
  {mod}
  __import__
}}
study s {{
  vary {mod}.x values [1]
  measure {mod}
  measure os.system
}}
'''


def test_a_scene_file_cannot_make_check_import_anything(tmp_path, monkeypatch):
    """Names a file writes are looked up among installed entry points only: nothing the file names is imported."""
    trap = tmp_path / "trap"
    trap.mkdir()
    (trap / "wdtrap.py").write_text("raise SystemExit('imported by a scene file')\n")
    monkeypatch.syspath_prepend(str(trap))
    for command in ("check", "compile", "fmt"):  # the modules each command imports lazily, once
        CliRunner().invoke(main, [command, "scenes/lab.wd"] + (["--check"] if command == "fmt" else []))
    imported: list[str] = []
    real = builtins.__import__

    def spy(name, *args, **kwargs):
        imported.append(name)
        return real(name, *args, **kwargs)

    f = tmp_path / "hostile.wd"
    f.write_text(HOSTILE.format(lab=ROOT / "scenes" / "lab.wd", mod="wdtrap"))
    before = set(sys.modules)
    monkeypatch.setattr(builtins, "__import__", spy)
    for command in (["check", str(f)], ["compile", str(f)], ["fmt", "--check", str(f)]):
        r = CliRunner().invoke(main, command)
        assert r.exit_code in (0, 1), r.output
    monkeypatch.setattr(builtins, "__import__", real)
    assert "wdtrap" not in sys.modules and not any("wdtrap" in n or n.startswith("os.") for n in imported)
    assert not {m for m in set(sys.modules) - before if not m.startswith(("importlib", "email", "zipfile", "csv"))}


KERNEL_EFFECT = '''
import numpy as np

from wiredsl.effects.base import Effect, KernelStage, Params, param
from wiredsl.engine import imageset as im


class JitterParams(Params):
    sigma: float = param(1.0, "image", "corner noise (normal, each axis)", ge=0)
    shift: float = param(0.0, "image", "every stroke moved right by this", ge=0)


class Jitter(Effect):
    name = "jitter"
    acts_on = "corner detection"
    Params = JitterParams
    doc = "normal corner noise and a rightward shift of the strokes"
    kernel = KernelStage("wdkern.kernel:stage", ("sigma", "shift"), (("count", "add"), ("sum_sq", "add")))

    @classmethod
    def is_identity(cls, p):
        return p.sigma == 0 and p.shift == 0

    @classmethod
    def disturb(cls, p, s, ctx):
        d = p.sigma * ctx.draws(cls.name, s.corner_trial, per_item=2, normal=True)
        ctx.stats.add(cls.name, count=len(d), sum_sq=float((d * d).sum()))
        return im.replace(s, corners=s.corners + d, pts=s.pts + [p.shift, 0.0])

    @classmethod
    def report(cls, p, stats):
        s = stats.sums[cls.name]
        return {"rms": float(np.sqrt(s["sum_sq"] / max(2 * s["count"], 1)))}
'''

KERNEL_STAGE = '''
from numba import njit

from wiredsl.engine.kernel import _normal_pair


@njit(cache=True)
def stage(pts, start, meta, corners, cfid, key, params, epipole, right, stats):
    sigma, shift = params[0], params[1]
    out = corners.copy()
    for c in range(len(corners)):
        gx, gy = _normal_pair(key, c)  # normals 2c and 2c + 1: ctx.draws(..., per_item=2, normal=True)
        dx, dy = sigma * gx, sigma * gy
        out[c, 0] = corners[c, 0] + dx
        out[c, 1] = corners[c, 1] + dy
        stats[0] += 1
        stats[1] += dx * dx + dy * dy
    moved = pts.copy()
    for i in range(len(pts)):
        moved[i, 0] = pts[i, 0] + shift
    return moved, start, meta, out, cfid
'''


WORKSPACE_STAGE = (KERNEL_STAGE.replace("stats):", "stats, ws):").replace("+ shift", "+ ws[0]") + '''

@njit(cache=True)
def workspace(params, epipole, right, camera, trials):
    """The view's shift, once a batch: the parameter where the view has a camera row (the nominal width)."""
    out = np.zeros(2)
    out[0] = params[1] if camera[0] > 0 else -1.0
    out[1] = trials
    return out
''').replace("from numba import njit", "import numpy as np\nfrom numba import njit")


@pytest.mark.parametrize("workspace", [False, True])
def test_a_plugin_effect_ships_its_own_kernel_and_runs_on_the_kernel_engine(tmp_path, monkeypatch, workspace):
    """A plug-in's numba stage (its own module, named by its KernelStage) is composed with the built-ins' in the
    compiled loop and gives what its numpy code gives; importing the effect does not import numba's code. With a
    workspace function (KernelStage.workspace), the stage gets the array it made for the view as its last
    argument (here the shift, read from it instead of the parameters)."""
    effect = KERNEL_EFFECT.replace('(("count", "add"), ("sum_sq", "add")))',
                                   '(("count", "add"), ("sum_sq", "add")),\n                         '
                                   'workspace="wdkern.kernel:workspace")') if workspace else KERNEL_EFFECT
    assert (effect != KERNEL_EFFECT) == workspace
    site = make_dist(tmp_path / "site", "wdkern", effect, "[wiredsl.effects]\njitter = wdkern:Jitter\n")
    (site / "wdkern" / "kernel.py").write_text(WORKSPACE_STAGE if workspace else KERNEL_STAGE)
    with plugins_on_path(monkeypatch, site, modules=("wdkern",)):
        f = tmp_path / "k.wd"
        f.write_text(LAB_PLUS.format(lab=ROOT / "scenes" / "lab.wd").replace("centre_noise sigma 4px",
                                                                              "jitter sigma 2px shift 0.5px"))
        scene = wiredsl.compile(str(f))
        assert "wdkern" in sys.modules and "wdkern.kernel" not in sys.modules
        out = tmp_path / "out"
        r = CliRunner().invoke(main, ["build", str(f), "--pipeline", "plug", "--seed", "3", "--trials", "4",
                                      "--format", "npz", "--no-svg", "-o", str(out), "--engine", "kernel"])
        assert r.exit_code == 0, r.output
        manifest = json.loads((out / "manifest.json").read_text())
        assert manifest["engine"] == "kernel" and manifest["engines"] == {"corner_loss": "kernel", "jitter": "kernel"}
        got = {e: list(wiredsl.simulate(scene, trials=6, seed=3, pipeline="plug", poses=(0, 3), engine=e))
               for e in ("numpy", "kernel")}
        moved = 0
        for bn, bk in zip(got["numpy"], got["kernel"], strict=True):
            assert set(bn.keys()) == set(bk.keys())
            for name in bn.keys():
                a, b = np.asarray(bn[name]), np.asarray(bk[name])
                if a.dtype.kind == "f":
                    assert a.shape == b.shape and np.abs(a - b).max(initial=0) < 1e-9, name
                else:
                    assert np.array_equal(a, b), name
            moved += len(bn["corners"])
        assert moved > 0
