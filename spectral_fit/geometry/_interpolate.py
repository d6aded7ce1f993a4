"""Differentiable interpolation of vertex attributes over a rasterised frame: the winning
triangle's perspective-correct barycentrics recomputed in JAX at each pixel centre, so that
gradients reach the attributes ``(V, C)`` and the clip positions ``(V, 4)``; the result is
``(H, W, C)`` with 0 where no triangle is visible.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from ._raster import Raster
from ._raster_checks import _is_tracer
from ._raster_setup import _bary_at

__all__ = ["interpolate"]


def interpolate(attributes, raster: Raster, triangles, clip_xyzw=None) -> jax.Array:
    """Interpolate vertex attributes ``(V, C)`` over the frame → ``(H, W, C)`` (0 where no
    triangle).

    With ``clip_xyzw`` (V, 4) the perspective-correct barycentrics are recomputed from the
    winning triangle's clip vertices at each pixel centre, so the result is differentiable
    w.r.t. ``attributes`` AND ``clip_xyzw``; without it the (gradient-free) ``raster.bary`` is
    used and only the attributes are differentiated. Unbatched: ``jax.vmap`` it over views.
    """
    _check_interp_args(attributes, triangles, clip_xyzw)
    attributes = jnp.asarray(attributes)
    triangles = jnp.asarray(triangles, jnp.int32)
    h, w = raster.tri_id.shape
    tri = raster.tri_id.reshape(-1)
    hit = tri >= 0
    if clip_xyzw is None:
        bary = raster.bary.reshape(-1, 3)
        idx = triangles[jnp.where(hit, tri, 0)]
    else:
        py, px = jnp.divmod(jnp.arange(h * w, dtype=jnp.int32), w)
        bary, idx = _bary_at(jnp.asarray(clip_xyzw), triangles, tri, px.astype(jnp.float32)
                             + 0.5, py.astype(jnp.float32) + 0.5, (h, w))
    vals = jnp.einsum("nk,nkc->nc", bary, attributes[idx])
    vals = jnp.where(hit[:, None], vals, 0.0)
    return vals.reshape(h, w, -1)


def _check_interp_args(attributes, triangles, clip_xyzw) -> None:
    """Python-boundary checks of :func:`interpolate`'s concrete arguments."""
    if not _is_tracer(attributes):
        a = np.shape(attributes)
        if len(a) != 2:
            raise InputError(f"expected shape (V, C), got {a}", field="attributes")
    if not _is_tracer(triangles):
        t = np.asarray(triangles)
        if t.ndim != 2 or t.shape[1] != 3 or not np.issubdtype(t.dtype, np.integer):
            raise InputError(f"expected integer indices (T, 3), got {t.dtype} {t.shape}",
                             field="triangles")
    if clip_xyzw is not None and not _is_tracer(clip_xyzw):
        c = np.shape(clip_xyzw)
        if len(c) != 2 or c[1] != 4:
            raise InputError(f"expected shape (V, 4), got {c}", field="clip_xyzw")
        if not _is_tracer(attributes) and np.shape(attributes)[0] != c[0]:
            raise InputError(f"{np.shape(attributes)[0]} rows for {c[0]} vertices",
                             field="attributes")
    if not _is_tracer(attributes) and not _is_tracer(triangles):
        t = np.asarray(triangles)
        if t.size and (t.min() < 0 or t.max() >= np.shape(attributes)[0]):
            raise InputError(f"triangle indices reach {t.max()} but there are "
                             f"{np.shape(attributes)[0]} rows", field="attributes")
