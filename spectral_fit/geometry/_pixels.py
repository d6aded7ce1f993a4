"""Covered-pixel lists: the covered pixels of a raster compacted into a fixed-capacity list
(:class:`PixelList`, row-major order, flat index y·W + x), attributes interpolated at the listed
pixels ``(P, C)``, per-pixel values scattered back into an ``(H, W, C)`` image, and the
compaction of boolean flags it rests on (:func:`compact_flags`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._runtime.errors import InputError
from ._prefix import _count_cumsum
from ._raster import Raster
from ._raster_setup import _bary_at

__all__ = [
    "PixelList",
    "compact_flags",
    "covered_pixels",
    "interpolate_pixels",
    "scatter_pixels",
]


class PixelList(eqx.Module):
    """Covered pixels of a raster, compacted into a fixed-capacity list (row-major order).

    Attributes:
        index: ``(P,)`` int32 flat pixel index y·W + x (0 in unused slots).
        tri_id: ``(P,)`` int32 visible triangle (−1 in unused slots).
        count: int32 scalar: number of covered pixels (may exceed P: see ``overflow``).
        overflow: bool scalar: count > P (pixels beyond the capacity are missing).
    """

    index: jax.Array
    tri_id: jax.Array
    count: jax.Array
    overflow: jax.Array
    shape: tuple[int, int] = eqx.field(static=True)

    @property
    def valid(self) -> jax.Array:
        return self.tri_id >= 0


def compact_flags(flags: jax.Array, capacity: int) -> tuple[jax.Array, jax.Array]:
    """The positions of the first ``capacity`` True entries of ``flags`` ``(N,)`` bool, in
    increasing order, and how many True entries there are (int32 scalar; may exceed
    ``capacity``): ``jnp.nonzero(flags, size=capacity)`` without a prefix sum or a scatter
    over all N entries (XLA:CPU runs both as serial loops, which over a whole frame's pixels
    are among the costliest steps of a frame).

    The flags are packed 32 to a uint32 word (a reduction); a prefix sum of the words'
    population counts (N/32 entries), turned into a histogram over the slots and prefix-summed
    again, gives the word that holds each rank, and a 5-step binary search over prefix
    population counts the bit within it (the "select" of succinct bit vectors, Jacobson 1989).
    Work O(N + capacity); exact.

    Args:
        flags: ``(N,)`` bool.
        capacity: static number of output slots (≥ 1).
    Returns:
        ``(index, count)``: index ``(capacity,)`` int32 (0 in slots past ``count``).
    """
    flags = jnp.asarray(flags, bool).reshape(-1)
    n = flags.shape[0]
    nw = max(1, -(-n // 32))
    bits = jnp.pad(flags, (0, nw * 32 - n)).reshape(nw, 32)
    weights = jnp.left_shift(jnp.uint32(1), jnp.arange(32, dtype=jnp.uint32))
    words = jnp.sum(jnp.where(bits, weights, jnp.uint32(0)), axis=1, dtype=jnp.uint32)
    pop = lax.population_count(words).astype(jnp.int32)
    incl = _count_cumsum(pop)  # (nw,) inclusive: set bits up to and including each word
    count = incl[-1]
    rank = jnp.arange(1, capacity + 1, dtype=jnp.int32)  # 1-based rank of each slot
    # the word of rank r is the number of words with fewer than r set bits up to and
    # including them: a histogram of the words' inclusive counts, prefix-summed over the
    # slots (no search per slot: that cost capacity · log2(N/32) gathers)
    hist = jnp.zeros((capacity,), jnp.int32).at[incl].add(1, mode="drop")
    word = jnp.minimum(_count_cumsum(hist), nw - 1)
    x = words[word]
    r = rank - (incl[word] - pop[word])  # rank within the word, 1-based
    lo = jnp.zeros_like(rank)
    hi = jnp.full_like(rank, 31)
    for _ in range(5):  # smallest bit b with popcount(x & bits 0..b) >= r
        mid = (lo + hi) // 2
        below = jnp.left_shift(jnp.uint32(2), mid.astype(jnp.uint32)) - jnp.uint32(1)
        below = jnp.where(mid >= 31, jnp.uint32(0xFFFFFFFF), below)
        ge = lax.population_count(x & below).astype(jnp.int32) >= r
        hi = jnp.where(ge, mid, hi)
        lo = jnp.where(ge, lo, mid + 1)
    index = jnp.where(rank <= count, word * 32 + lo, 0)
    return index, count


def covered_pixels(raster: Raster, capacity: int) -> PixelList:
    """Compact the covered pixels of ``raster`` into a list of ``capacity`` entries (static),
    so that shading runs only where there is geometry. Check ``overflow`` (or size the
    capacity from a bound, e.g. H·W)."""
    if not isinstance(capacity, int | np.integer) or capacity < 1:
        raise InputError(f"must be a positive int, got {capacity!r}", field="capacity")
    h, w = raster.tri_id.shape
    flat = raster.tri_id.reshape(-1)
    index, count = compact_flags(flat >= 0, int(capacity))
    live = jnp.arange(capacity, dtype=jnp.int32) < count
    tri = jnp.where(live, flat[index], -1)
    return PixelList(index, tri, count, count > capacity, (h, w))


def pixel_barycentrics(pixels: PixelList, triangles, clip_xyzw) -> tuple[jax.Array, jax.Array]:
    """The perspective-correct barycentrics ``(P, 3)`` of the listed pixels' centres in their
    triangles (rows of ``triangles`` ``(T, 3)``; 0 in unused slots) and those triangles'
    vertex indices ``(P, 3)``; differentiable w.r.t. the clip positions ``(V, 4)``."""
    h, w = pixels.shape
    py, px = jnp.divmod(pixels.index, w)
    return _bary_at(jnp.asarray(clip_xyzw), jnp.asarray(triangles, jnp.int32),
                    pixels.tri_id, px.astype(jnp.float32) + 0.5,
                    py.astype(jnp.float32) + 0.5, (h, w))


def interpolate_pixels(attributes, pixels: PixelList, triangles, clip_xyzw) -> jax.Array:
    """Attributes ``(V, C)`` interpolated at the listed pixels → ``(P, C)`` (0 in unused
    slots); differentiable w.r.t. attributes and clip positions."""
    bary, idx = pixel_barycentrics(pixels, triangles, clip_xyzw)
    vals = jnp.einsum("nk,nkc->nc", bary, jnp.asarray(attributes)[idx])
    return jnp.where(pixels.valid[:, None], vals, 0.0)


def scatter_pixels(values, pixels: PixelList, background) -> jax.Array:
    """Write per-pixel ``values (P, C)`` into an image ``(H, W, C)`` filled with
    ``background`` (scalar or (C,), or an (H, W, C) image)."""
    h, w = pixels.shape
    values = jnp.asarray(values)
    c = values.shape[-1]
    bg = jnp.broadcast_to(jnp.asarray(background, values.dtype), (h, w, c)).reshape(-1, c)
    idx = jnp.where(pixels.valid, pixels.index, h * w)  # out of range: dropped
    return bg.at[idx].set(values, mode="drop").reshape(h, w, c)
