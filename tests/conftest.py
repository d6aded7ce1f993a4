"""Fixtures shared by several test modules: scenes and environments that more than one module
builds the same way. The code they are made of lives in the ``helpers`` package (tests/helpers,
on the import path through ``pythonpath`` in pyproject.toml); modules that need only a function
or a constant import it from there. Imports of the package happen inside the fixtures, so that
collecting a module that uses none of them stays as cheap as before."""

from __future__ import annotations

from pathlib import Path

import pytest


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
