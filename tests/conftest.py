"""Fixtures shared by several test modules: scenes and environments that more than one module
builds the same way. The code they are made of lives in the ``helpers`` package (tests/helpers,
on the import path through ``pythonpath`` in pyproject.toml); modules that need only a function
or a constant import it from there. Imports of the package happen inside the fixtures, so that
collecting a module that uses none of them stays as cheap as before."""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import pytest

# SPECTRAL_FIT_TEST_FAST_COMPILE=1: XLA's backend (LLVM) optimisation level 0 for the programs
# the tests compile. A gather frame of the test scene then compiles in about half the time,
# while its code runs slower; whether a whole run gains depends on the mix of tests, so it is
# opt-in. The numbers the tests check are IEEE arithmetic either way; the benchmarks and
# `spectral-fit validate` always run with XLA's defaults. Set here, before JAX starts its
# backend; child processes inherit it.
if os.environ.get("SPECTRAL_FIT_TEST_FAST_COMPILE", "") not in ("", "0") and (
        "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", "")):
    os.environ["XLA_FLAGS"] = " ".join(
        [os.environ.get("XLA_FLAGS", ""), "--xla_backend_optimization_level=0"]).strip()


# Modules whose tests share expensive module fixtures or compiled programs (a compiled
# gather-mode scene, an OpenGL context and its frames, two lens frames, the renderer tests' frame
# programs, the interreflection tests' pass 1 and gather programs, the fitting tests' problem and
# solvers): with ``-n N`` each of them runs on one worker, so they are built once per run, not
# once per worker.
ONE_WORKER_MODULES = frozenset({
    "tests/test_fitting.py",
    "tests/test_gl_baseline.py",
    "tests/test_interreflection.py",
    "tests/test_ir_reuse.py",
    "tests/test_lens.py",
    "tests/test_renderer.py",
})


def _scope_of(nodeid: str) -> str:
    """The unit of work a test belongs to: its module for ``ONE_WORKER_MODULES``, else the test
    itself (so the rest balances test by test, as with pytest-xdist's default ``load``)."""
    module = nodeid.split("::", 1)[0]
    return module if module in ONE_WORKER_MODULES else nodeid


if importlib.util.find_spec("xdist") is not None:

    def pytest_xdist_make_scheduler(config, log):
        """With ``-n N`` and the default distribution, schedule by ``_scope_of``. (xdist's own
        ``--dist loadgroup`` groups by a suffix it writes into the node ids, which pytest 9.2's
        read-only node ids ignore: its groups are silently split across workers.) The largest
        units go first (``LoadScopeScheduling`` orders them by size), single tests fill the
        workers up at the end."""
        if config.getvalue("dist") != "load":
            return None
        from xdist.scheduler import LoadScopeScheduling

        class ModuleGroupScheduling(LoadScopeScheduling):
            def _split_scope(self, nodeid: str) -> str:
                return _scope_of(nodeid)

        return ModuleGroupScheduling(config, log)


def pytest_configure(config):
    """``SPECTRAL_FIT_TEST_COMPILE_LOG=FOLDER``: each process appends one line per JAX trace,
    lowering and XLA compilation (a persistent-cache hit included) to ``FOLDER/<worker>.tsv``:
    the test, the event, the function's name and the seconds it took, for finding what the
    tests' time goes to (``scripts/compile_profile.py`` sums it)."""
    folder = os.environ.get("SPECTRAL_FIT_TEST_COMPILE_LOG", "")
    if not folder:
        return
    import jax.monitoring

    Path(folder).mkdir(parents=True, exist_ok=True)
    log = open(Path(folder) / f"{os.environ.get('PYTEST_XDIST_WORKER', 'main')}.tsv", "a",
               buffering=1, encoding="utf-8")

    def listener(event: str, seconds: float, **kwargs) -> None:
        test = os.environ.get("PYTEST_CURRENT_TEST", "").rsplit(" (", 1)[0]
        log.write(f"{test}\t{event}\t{kwargs.get('fun_name', '')}\t{seconds:.4f}\n")

    jax.monitoring.register_event_duration_secs_listener(listener)


@pytest.fixture(scope="session", autouse=True)
def _compilation_cache():
    """JAX's persistent compilation cache on for the whole run, in the folder the product uses
    (``spectral_fit.enable_compilation_cache``: ``$SPECTRAL_FIT_JAX_CACHE`` or
    ``~/.cache/spectral_fit/jax``, a subfolder per library versions; an empty variable turns it
    off). Many tests compile the same frame programs (the same scene, mode and frame size) in
    separate processes: each worker loads what another one compiled, and so do the
    ``spectral-fit`` commands that tests run in child processes (they use the same folder).
    Programs that compile in under a second are not stored."""
    from spectral_fit.rendering import enable_compilation_cache

    enable_compilation_cache(min_compile_time_s=1.0)
    yield


@pytest.fixture(scope="session")
def anchor_lighting():
    """The benchmark's anchor map as the lighting tests use it (``helpers.lighting.anchor_map``):
    (img (H, W, C) float64, the EnvironmentMap with its 180° rotation, the world direction (3,)
    of its brightest texel). Read only: one per worker process, shared by its modules."""
    from helpers.lighting import anchor_map

    return anchor_map()


@pytest.fixture(scope="module")
def scene_folder(tmp_path_factory) -> Path:
    """A module's folder for the two-sphere configs of ``helpers.rendering.write_scene``: the
    first config written there also writes the mirror-symmetric benchmark environment, the
    others reuse it."""
    return tmp_path_factory.mktemp("scenes")


@pytest.fixture()
def small_scene_config(tmp_path) -> Path:
    """The small fitting scene of ``helpers.fitting.write_small_scene`` (two icospheres, a
    16×32 synthetic environment, 16 bands) in this test's tmp folder: its scene.toml."""
    from helpers.fitting import write_small_scene

    return write_small_scene(tmp_path)
