"""Code shared by the test modules: scene and environment builders, brute-force oracles and
reference implementations, one module per area (``helpers.rendering``, ``helpers.fitting``,
...). pytest puts tests/ on the import path (``pythonpath`` in pyproject.toml), so test modules
import them as ``from helpers.rendering import write_scene``; fixtures built from them live in
tests/conftest.py.

This module holds the repository's paths, the environment of child Python processes (which
import ``spectral_fit`` from this checkout and the helpers package) and the loader of the
scripts/ that tests run."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path
from types import ModuleType

#: the repository root, tests/ and scripts/
ROOT = Path(__file__).resolve().parents[2]
TESTS = ROOT / "tests"
SCRIPTS = ROOT / "scripts"
#: the bundled maps: the benchmark's anchor map (31 bands) and the studio room (81 bands)
ANCHOR_ENV = ROOT / "measurements" / "benchmark" / "anchor_environment.exr"
STUDIO_ROOM = ROOT / "measurements" / "environment" / "studio_room.exr"


def subprocess_env(**extra: str) -> dict[str, str]:
    """``os.environ`` with the repository root and tests/ at the front of ``PYTHONPATH`` (a child
    ``python`` imports ``spectral_fit`` from this checkout and ``helpers``), plus ``extra``."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(ROOT), str(TESTS)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    env.update(extra)
    return env


def load_script(name: str) -> ModuleType:
    """The module of ``scripts/<name>.py``, loaded from its path (scripts/ is no package and
    is not put on the import path). Loaded once per process."""
    key = f"scripts.{name}"
    if key in sys.modules:
        return sys.modules[key]
    spec = importlib.util.spec_from_file_location(key, SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[key] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[key]
        raise
    return module
