"""The per-frame inputs of the frame programs: their defaults from the
:class:`~spectral_fit.rendering.Prepared` scene (the config's materials, model matrices (O, 4,
4) and view (4, 4); every object visible), the checks of their shapes (naming the field), their
dtypes (float32 matrices, bool visibility) and the check of the senders' mode.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from ..lighting import Material
from ._materials import _as_stacked, _stack
from ._prepared import Prepared

__all__ = [
    "all_visible",
]


@functools.cache
def all_visible(n: int) -> jax.Array:
    """(n,) True, made once (a new array per frame costs a dispatch on the frame's path);
    concrete even when first asked for inside a caller's trace (a cached tracer would leak)."""
    with jax.ensure_compile_time_eval():
        return jnp.ones((n,), bool)


def _check_frame_inputs(prep: Prepared, materials: Any, model: Any, view: Any, visible: Any
                        ) -> tuple[Any, jax.Array, jax.Array, jax.Array]:
    mats = prep.materials if materials is None else materials
    model = prep.model if model is None else model
    view = prep.camera.view if view is None else view
    visible = all_visible(prep.num_objects) if visible is None else visible
    if not isinstance(model, jax.core.Tracer):
        m = np.shape(model)
        if m != (prep.num_objects, 4, 4):
            raise InputError(f"expected shape ({prep.num_objects}, 4, 4), got {m}",
                             field="model")
    if not isinstance(view, jax.core.Tracer) and np.shape(view) != (4, 4):
        raise InputError(f"expected shape (4, 4), got {np.shape(view)}", field="view")
    if not isinstance(visible, jax.core.Tracer) and np.shape(visible) != (prep.num_objects,):
        raise InputError(f"expected shape ({prep.num_objects},), got {np.shape(visible)}",
                         field="visible")
    if not isinstance(mats, Material):
        mats = _stack(_as_stacked(mats, prep.num_objects)) if len(
            {(m.distribution, m.geometry) for m in mats}) == 1 else list(mats)
    return (mats, _as_dtype(model, jnp.float32), _as_dtype(view, jnp.float32),
            _as_dtype(visible, jnp.bool_))


def _as_dtype(x: Any, dtype: Any) -> jax.Array:
    """``jnp.asarray(x, dtype)``, skipped for a ``jax.Array`` that has the dtype already (the
    per-frame inputs: the conversion is a dispatch of its own on the frame's path)."""
    if isinstance(x, jax.Array) and x.dtype == dtype:
        return x
    return jnp.asarray(x, dtype)


def _check_senders(prep: Prepared, senders: Any) -> None:
    if senders is not None and prep.interreflection.mode != "gather":
        raise InputError("senders given but the interreflection mode is "
                         f"{prep.interreflection.mode!r}",
                         field="senders")
