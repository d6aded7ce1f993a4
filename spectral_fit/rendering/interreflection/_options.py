"""The interreflection's options and the checks of its public entry points' arguments.

The modes (``MODES``: "gather", "paper", "none"), where the gather's diffuse transfer is
evaluated (``DIFFUSE_AT``), and the validation of integers, materials (one per object, with
the environment's C channels), receivers (a :class:`~spectral_fit.geometry.GBuffer`), image
shapes (H, W) and output maps (C, D): each failure is an
:class:`~spectral_fit._runtime.errors.InputError` naming the field.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np

from ..._runtime.errors import InputError
from ...geometry import GBuffer
from ...lighting import EnvironmentMap, Material

__all__ = ["MODES"]

MODES = ("gather", "paper", "none")
DIFFUSE_AT = ("samples", "receivers")


def _check_mode(mode: str) -> str:
    if mode not in MODES:
        raise InputError(f"unknown interreflection mode {mode!r}; choose one of {MODES}",
                         field="mode")
    return mode


def _check_int(value: Any, name: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or not (
            lo <= int(value) <= hi):
        raise InputError(f"must be an integer in {lo}..{hi}, got {value!r}", field=name)
    return int(value)


def _check_materials(n: int, materials: Sequence[Material], env: EnvironmentMap) -> None:
    if len(materials) != n:
        raise InputError(f"{len(materials)} materials for {n} objects", field="materials")
    c = env.channels
    for k, m in enumerate(materials):
        if not isinstance(m, Material):
            raise InputError(f"expected a Material, got {type(m).__name__}",
                             field=f"materials[{k}]")
        if jnp.shape(m.reflectance)[-1] != c:
            raise InputError(f"reflectance has {jnp.shape(m.reflectance)[-1]} channels, the "
                             f"environment {c}", field=f"materials[{k}].reflectance")


def _check_receivers(receivers: GBuffer) -> None:
    if not isinstance(receivers, GBuffer):
        raise InputError(f"expected a GBuffer, got {type(receivers).__name__}",
                         field="receivers")


def _check_inputs(n: int, materials: Sequence[Material], env: EnvironmentMap,
                  receivers: GBuffer) -> None:
    _check_materials(n, materials, env)
    _check_receivers(receivers)


def _check_diffuse_at(diffuse_at: str) -> None:
    if diffuse_at not in DIFFUSE_AT:
        raise InputError(f"must be one of {DIFFUSE_AT}, got {diffuse_at!r}",
                         field="diffuse_at")


def _check_image_shape(image_shape: Any) -> tuple[int, int] | None:
    if image_shape is None:
        return None
    if len(image_shape) != 2:
        raise InputError(f"must be (H, W), got {image_shape!r}", field="image_shape")
    return (_check_int(image_shape[0], "image_shape", 1, 1 << 15),
            _check_int(image_shape[1], "image_shape", 1, 1 << 15))


def _output_channels(env: EnvironmentMap, output: Any) -> int:
    """D of an ``output`` map (C, D) (C without one); InputError for another shape."""
    if output is None:
        return env.channels
    shape = getattr(output, "shape", None)
    if shape is None or len(shape) != 2 or shape[0] != env.channels:
        raise InputError(f"must be a ({env.channels}, D) matrix (the environment's channels → "
                         f"the output's), got shape {shape}", field="output")
    return int(shape[1])
