"""Python-boundary checks of the rasteriser's concrete inputs: frame shape (H, W), clip
positions ``(V, 4)`` (or ``(B, V, 4)``) and triangle indices ``(T, 3)``; traced arguments (inside
a ``jit``) are passed through unchecked.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError


def _is_tracer(*xs) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in xs)


def _check_shape(shape) -> tuple[int, int]:
    try:
        h, w = (int(s) for s in shape)
    except (TypeError, ValueError):
        raise InputError(f"expected (H, W), got {shape!r}", field="shape") from None
    if not (0 < h <= 16384 and 0 < w <= 16384):
        raise InputError(f"H and W must be in 1..16384, got {(h, w)}", field="shape")
    return h, w


def _validate(clip, triangles, batched: bool):
    """Python-boundary checks of concrete inputs; returns (clip, triangles) as JAX arrays."""
    if not _is_tracer(clip):
        c = np.asarray(clip)
        want = "(B, V, 4)" if batched else "(V, 4)"
        if c.ndim != (3 if batched else 2) or c.shape[-1] != 4:
            raise InputError(f"expected shape {want}, got {c.shape}", field="clip_xyzw")
        if not np.issubdtype(c.dtype, np.floating):
            raise InputError(f"expected floating point, got {c.dtype}", field="clip_xyzw")
        if not np.all(np.isfinite(c)):
            bad = np.argwhere(~np.isfinite(c))[0].tolist()
            raise InputError(f"non-finite value at index {bad}", field="clip_xyzw")
        nv = c.shape[-2]
    else:
        nv = clip.shape[-2]
    if not _is_tracer(triangles):
        t = np.asarray(triangles)
        if t.ndim != 2 or t.shape[1] != 3:
            raise InputError(f"expected shape (T, 3), got {t.shape}", field="triangles")
        if t.shape[0] == 0:
            raise InputError("no triangles", field="triangles")
        if not np.issubdtype(t.dtype, np.integer):
            raise InputError(f"expected integer indices, got {t.dtype}", field="triangles")
        if t.min() < 0 or t.max() >= nv:
            raise InputError(f"index out of range [0, {nv}): min {t.min()}, max {t.max()}",
                             field="triangles")
    return jnp.asarray(clip, jnp.float32), jnp.asarray(triangles, jnp.int32)
