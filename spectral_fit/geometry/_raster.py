"""Triangle rasteriser in pure JAX: visibility without gradient, differentiable interpolation.

Contract (nvdiffrast-like)
--------------------------
``rasterize(clip_xyzw (V, 4), triangles (T, 3), (H, W))`` returns a :class:`Raster` with, per
pixel, ``tri_id`` (int32, −1 = no triangle), perspective-correct barycentrics ``bary`` (H, W, 3)
of the visible triangle's three vertices, and ``depth`` = NDC z/w (−1 near … +1 far; 1 where
nothing is drawn). Visibility carries no gradient; :func:`interpolate` recomputes barycentrics
in JAX from the winning triangle's clip-space vertices at each pixel centre and is
differentiable with respect to the attributes AND the vertex positions.

Conventions (docs/conventions.md, 'Conventions'): OpenGL clip space, pixel centres at integer + 0.5,
NDC (x, y) maps to pixel coordinates ((x + 1)/2·W, (1 − y)/2·H), row 0 at the top.

Coverage rule
-------------
A pixel is covered by a triangle when its centre p lies inside the triangle AND the point of
the triangle seen through p lies inside the clip volume's depth range (−w ≤ z ≤ w, which
implies w > 0). Inside-ness is tested with homogeneous 2D edge functions (Olano & Greer 1997)
evaluated directly on clip coordinates, so triangles that cross the near plane or the plane of
the eye need no clipping: the per-pixel depth test clips them exactly, and nothing behind the
camera is drawn. The near plane only enters the conservative bounding box.

Watertightness: the edge function of an edge is computed ONCE per edge orientation in a
canonical vertex order (lexicographic on the vertex's homogeneous pixel coordinates), so the
two triangles sharing an edge see bit-identical values of opposite sign. A pixel centre
exactly on an edge (edge function = 0) belongs to the side the edge function takes at the
centre moved by +ε in x (then +ε² in y): a top-left-like rule that assigns it to exactly one of
the two triangles. Hence shared edges never crack or double-cover. Float32 rounding can only
matter for a pixel centre within ~1e−5 px of a shared VERTEX (the lines through it are not
exactly concurrent after rounding); fixed-point snapping would close that gap but needs 64-bit
integers.

Visibility: nearest depth wins; equal depths go to the smaller triangle id (deterministic).
Implemented as two 32-bit scatter-min passes (depth, then the id among candidates at the
winning depth), so no 64-bit keys and no global ``jax_enable_x64``.

Algorithm and fixed buffers
---------------------------
Each triangle gets a conservative pixel bounding box (of its near-clipped polygon) and is
tiled with square windows of side S from a ladder (default 1, 4, 16): S is the smallest ladder
size ≥ the shorter side of the box (capped at the largest), the box is covered by
⌈nx/S⌉·⌈ny/S⌉ windows. Culled, off-screen, degenerate and empty-box triangles get no window.
Each ladder size has a fixed window CAPACITY (:class:`RasterConfig`, planned in NumPy by
:func:`plan_counts` without compiling anything); the windows of all sizes are listed together
with prefix sums, one scatter and one running max (no sort), evaluated densely, and resolved
with windowed scatter-min. Buffers never depend on the pose, so moving objects never
recompiles.

Overflow: ``Raster.overflow`` is True when some ladder size needed more windows than its
capacity (``Raster.needed`` gives the counts). :func:`rasterize`, called outside ``jit``,
checks the flag and re-runs with the next power-of-two capacities (one recompile, a
``RuntimeWarning``, remembered for later calls of the same sizes), so nothing is ever silently
dropped. Inside a user's ``jit`` the flag is returned and the caller must check it.

Limits: float32 throughout; the frame must satisfy H, W ≤ 16384 and T < 2^31; the triangle
id is recovered exactly (no quantisation). Depth ties between different triangles (coplanar
overlaps) resolve to the smaller id.
"""

from __future__ import annotations

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._runtime.errors import InputError
from ._raster_checks import _check_shape, _is_tracer, _validate
from ._raster_plan import _CULL, RasterConfig, default_config, plan_config
from ._raster_setup import _triangle_setup
from ._raster_windows import _buffer_shape, _evaluate, _finish, _resolve, _window_lists

__all__ = [
    "clear_plans",
    "Raster",
    "rasterize",
    "rasterize_batch",
    "raster_jit",
]


class Raster(eqx.Module):
    """Per-pixel visibility of one view.

    Attributes:
        tri_id: ``(H, W)`` int32 id of the visible triangle, −1 where none.
        bary: ``(H, W, 3)`` float32 perspective-correct barycentrics (0 where none).
        depth: ``(H, W)`` float32 NDC depth z/w (1 where none).
        overflow: bool scalar: some window list overflowed (result incomplete; see module doc).
        needed: ``(len(tile_sizes),)`` int32 windows needed per ladder size.
    """

    tri_id: jax.Array
    bary: jax.Array
    depth: jax.Array
    overflow: jax.Array
    needed: jax.Array

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.tri_id.shape[-2:])

    @property
    def mask(self) -> jax.Array:
        """``(H, W)`` bool: a triangle is visible."""
        return self.tri_id >= 0


def _raster_single(clip, triangles, shape, cull, config):
    clip = lax.stop_gradient(clip.astype(jnp.float32))
    data = _triangle_setup(clip, triangles, shape, cull)
    lists = _window_lists(data, config)
    dvals = _evaluate(lists)
    ibuf = _resolve(lists, dvals, _buffer_shape(shape, config))
    tri_id, bary, depth, nblocks = _finish(data, clip, triangles, ibuf, shape,
                                           config.block_capacity)
    needed = jnp.stack([lst[5] for lst in lists] + [nblocks]).astype(jnp.int32)
    caps = jnp.asarray((*config.capacities, config.block_capacity), jnp.int32)
    overflow = jnp.any(needed > caps)
    return Raster(tri_id, bary, depth, overflow, needed)


raster_jit = jax.jit(_raster_single, static_argnames=("shape", "cull", "config"))


def _raster_batch_impl(clip, triangles, shape, cull, config):
    return jax.vmap(lambda c: _raster_single(c, triangles, shape, cull, config))(clip)


_raster_batch_jit = jax.jit(_raster_batch_impl, static_argnames=("shape", "cull", "config"))

# configurations planned or grown, per (T, shape, cull, user config, batched)
_LADDER: dict[tuple, RasterConfig] = {}


def clear_plans() -> None:
    """Forget the capacities :func:`rasterize` planned or grew in this process, so that the
    next call plans from scratch (as a fresh process does)."""
    _LADDER.clear()


def _run(jitted, clip, triangles, shape, cull, config, check):
    if cull not in _CULL:
        raise InputError(f"unknown cull mode {cull!r} (one of {_CULL})", field="cull")
    shape = _check_shape(shape)
    batched = jitted is _raster_batch_jit
    clip, triangles = _validate(clip, triangles, batched)
    t = int(triangles.shape[0])
    traced = _is_tracer(clip, triangles)
    if config is not None and (len(config.tile_sizes) != len(config.capacities)
                               or not config.tile_sizes):
        raise InputError("tile_sizes and capacities must have the same non-zero length",
                         field="config")
    key = (t, shape, cull, config, batched)
    cfg = _LADDER.get(key)
    if cfg is None:
        if config is not None:
            cfg = config
        elif traced:
            cfg = default_config(t, shape)
        else:
            cfg = plan_config(clip, triangles, shape, cull=cull)  # all views when batched
        if not traced:
            _LADDER[key] = cfg
    out = jitted(clip, triangles, shape=shape, cull=cull, config=cfg)
    if not check or _is_tracer(out.overflow):
        return out
    for _ in range(8):
        if not bool(jnp.any(out.overflow)):
            return out
        needed = np.max(np.asarray(out.needed).reshape(-1, len(cfg.capacities) + 1), axis=0)
        cfg = cfg.grown(needed)
        _LADDER[key] = cfg
        warnings.warn(f"rasterize: capacities grown to {cfg.capacities}, blocks "
                      f"{cfg.block_capacity} (needed {needed.tolist()}); recompiling",
                      RuntimeWarning, stacklevel=3)
        out = jitted(clip, triangles, shape=shape, cull=cull, config=cfg)
    raise RuntimeError("rasterize: buffers still overflow after growing the capacities")


def rasterize(clip_xyzw, triangles, shape: tuple[int, int], *, cull: str = "none",
              config: RasterConfig | None = None, check: bool = True) -> Raster:
    """Rasterise triangles given in OpenGL clip space (see the module docstring).

    Args:
        clip_xyzw: ``(V, 4)`` float clip-space vertex positions (e.g. from ``camera.project``).
        triangles: ``(T, 3)`` int vertex indices; counter-clockwise in NDC = front face.
        shape: ``(H, W)`` frame size in pixels (static).
        cull: "none" (default), "back" (drop back faces) or "front".
        config: window capacities (default :func:`default_config`); static.
        check: outside ``jit``, re-run with grown capacities when a window list overflowed.

    Returns:
        :class:`Raster`. No gradient flows through it (use :func:`interpolate`).

    Raises:
        InputError: wrong shapes or dtypes, non-finite positions, indices out of range
            (checked when the arguments are concrete, i.e. not inside a ``jit`` trace).
    """
    return _run(raster_jit, clip_xyzw, triangles, shape, cull, config, check)


def rasterize_batch(clip_xyzw, triangles, shape: tuple[int, int], *, cull: str = "none",
                    config: RasterConfig | None = None, check: bool = True) -> Raster:
    """:func:`rasterize` of B views (or B poses) of one triangle list: ``clip_xyzw (B, V, 4)``
    → Raster with a leading batch axis on every field. Several meshes are rasterised together
    by concatenating them (``mesh.concat_meshes``; ids are offset per mesh)."""
    return _run(_raster_batch_jit, clip_xyzw, triangles, shape, cull, config, check)
