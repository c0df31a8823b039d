from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(autouse=True)
def _at_root(monkeypatch):
    """Run every test from the checkout's root, so that reported paths are stable."""
    monkeypatch.chdir(ROOT)


def pytest_configure(config):
    """Compile the Monte-Carlo kernel once (its shared parts and every built-in stage's function, through the
    built-ins' stage list), before any test worker starts, so that the workers share the compiled code through
    numba's cache instead of each compiling it."""
    import importlib.util

    if hasattr(config, "workerinput") or importlib.util.find_spec("numba") is None:
        return
    from wiredsl.effects import BUILTIN
    from wiredsl.engine import kernel

    kernels = [e.kernel for e in BUILTIN.values() if e.kernel is not None]
    kernel.warm(tuple(k.function for k in kernels), tuple(k.camera for k in kernels),
                tuple(k.workspace for k in kernels))


@pytest.fixture(autouse=True, scope="session")
def _study_measures():
    """The studies' test measure (tests/study_measures.py) joins whatever measures are installed."""
    import sys

    if str(ROOT / "tests") not in sys.path:  # worker processes find the test measure by module name
        sys.path.insert(0, str(ROOT / "tests"))
    import study_measures

    from wiredsl.language import compile_study

    installed = compile_study.measure_registry
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(compile_study, "measure_registry", lambda: {**installed(), **study_measures.REGISTRY})
        yield


@pytest.fixture(params=["numpy", "kernel"])
def engine(request, monkeypatch):
    """Run a test on both engines: with "kernel", every built-in stage applied by hand (`Effect.apply`) runs in
    the compiled kernel instead (`montecarlo.kernel_apply`), with the same draws."""
    if request.param == "kernel":
        pytest.importorskip("numba")
        from wiredsl.effects.base import Effect
        from wiredsl.montecarlo import kernel_apply

        on_numpy = Effect.apply.__func__

        def apply(cls, params, features, ctx):
            if cls.kernel is None:
                return on_numpy(cls, params, features, ctx)
            return kernel_apply(cls, params, features, ctx)

        monkeypatch.setattr(Effect, "apply", classmethod(apply))
    return request.param


@pytest.fixture(autouse=True, scope="session")
def _trusted_models_checked():
    """Every model the compiler makes without validation (`wiredsl.scene.trusted`) is also validated, in every test
    that compiles in this process: the two must be equal, type for type and bit for bit."""
    from wiredsl import scene

    scene.CHECK_TRUSTED = True
    yield
    scene.CHECK_TRUSTED = False
