"""Inclusive scans and prefix sums along the last axis of JAX arrays, written as loops and
blocked matrix products (XLA:CPU fuses the producers of ``lax.associative_scan``'s input into
every level and runs ``cumsum`` as a serial loop); used by the rasteriser's window and block
lists and by the compaction of flags.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jax import lax

from .._runtime.backend import on_accelerator


def _hs_scan(op, x, identity):
    """Inclusive Hillis–Steele scan along the last axis in a loop of ⌈log2 n⌉ steps."""
    n = x.shape[-1]
    if n == 1:
        return x
    steps = math.ceil(math.log2(n))
    pad = jnp.full(x.shape[:-1] + (n,), identity, x.dtype)

    def body(k, y):
        d = jnp.left_shift(1, k)
        shifted = lax.dynamic_slice_in_dim(jnp.concatenate([pad, y], axis=-1), n - d, n, axis=-1)
        return op(y, shifted)

    # unrolled on accelerators: a device loop costs a host round trip per step there
    return lax.fori_loop(0, steps, body, x, unroll=True if on_accelerator() else 1)


def _scan(op, x, identity, block: int = 64):
    """Inclusive scan of ``x`` along its last axis with an associative ``op``.

    Blocked: a Hillis–Steele scan inside blocks of ``block`` elements, then a scan of the block
    totals. Loops instead of ``lax.associative_scan`` because XLA:CPU fuses the producers of
    an associative scan's input into every level of it and recomputes them there (several
    times slower in the rasteriser); a loop carry is materialised.
    """
    n = x.shape[-1]
    if n <= block:
        return _hs_scan(op, x, identity)
    nb = -(-n // block)
    xp = jnp.concatenate([x, jnp.full(x.shape[:-1] + (nb * block - n,), identity, x.dtype)], -1)
    inner = _hs_scan(op, xp.reshape(x.shape[:-1] + (nb, block)), identity)
    tot = _scan(op, inner[..., -1], identity, block)
    off = jnp.concatenate([jnp.full(x.shape[:-1] + (1,), identity, x.dtype), tot[..., :-1]], -1)
    return op(off[..., None], inner).reshape(x.shape[:-1] + (nb * block,))[..., :n]


def _count_cumsum(x, block: int = 64):
    """Inclusive prefix sum of non-negative int32 counts ``x`` along the last axis.

    Blocked triangular matrix products in float32 (a library dot: no generated loop, cheap to
    compile): sums below 2^24 are exact (every partial sum of non-negative terms is at most
    the total); larger sums (only reached by lists far beyond any capacity) are rounded,
    which can only move them further beyond the capacity.
    """
    n = x.shape[-1]
    lead = x.shape[:-1]
    nb = -(-n // block)
    xp = jnp.pad(x.astype(jnp.float32), [(0, 0)] * len(lead) + [(0, nb * block - n)])
    upper = (lax.broadcasted_iota(jnp.int32, (block, block), 0)
             <= lax.broadcasted_iota(jnp.int32, (block, block), 1)).astype(jnp.float32)
    inner = jnp.matmul(xp.reshape(lead + (nb, block)), upper,
                       precision=lax.Precision.HIGHEST)
    if nb > 1:
        tot = _count_cumsum(inner[..., -1], block)
        off = jnp.concatenate([jnp.zeros(lead + (1,), jnp.float32), tot[..., :-1]], -1)
        inner = inner + off[..., None]
    return inner.reshape(lead + (nb * block,))[..., :n].astype(jnp.int32)
