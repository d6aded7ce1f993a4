"""Which receivers the gather's per-receiver work runs at, and in what order.

Receivers that are pixels of one image (``pixel`` (N,) flat index row·W + column, −1 = not a
pixel) evaluate the gloss quadrature at anchor pixels every ``GLOSS_STEP``-th row and column
only, the others being bilinear blends of the anchors around them unless the lobe's view of
the neighbour changes fast there (:func:`_image_anchors`); they sum the diffuse transfer at
themselves at every ``DIFFUSE_STEP``-th row and column, the others blending those anchors'
correction of the samples' interpolated light (:func:`_diffuse_anchors`); and the stable
partition
:func:`_partition` puts the receivers that need work (active, valid) first, so that chunks
past them are skipped.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..._runtime.backend import materialise
from ...lighting import dot3

__all__: list[str] = []

#: default screen-space step of the gloss quadrature for receivers that are pixels of an image
#: (``image_shape``): evaluated at every 2nd row and column, interpolated between
GLOSS_STEP = 2
#: ... unless the lobe's view of the neighbour changes by more than this many lobe widths
#: between a pixel and an anchor (:func:`_image_anchors`)
_GLOSS_SMOOTH = 0.7
#: screen-space step of the anchors at which receivers that are pixels of an image sum the
#: diffuse transfer themselves (:func:`_diffuse_anchors`)
DIFFUSE_STEP = 8
#: an anchor stands for a receiver when their normals agree to this cosine and the anchor
#: lies off the receiver's tangent plane by at most this fraction of their distance (one
#: face of one surface)
_ANCHOR_COS = 0.5
_ANCHOR_PLANE = 0.5


def _pixel_slots(pixel: jax.Array, obj: jax.Array, shape: tuple[int, int]) -> jax.Array:
    """(H·W,) int32: the receiver index of each pixel of the image ``shape`` (H, W), −1 where
    no receiver (``pixel`` (N,) flat index row·W + column, −1 = not a pixel; ``obj`` (N,),
    −1 = empty)."""
    h, w = shape
    n = pixel.shape[0]
    ok = (pixel >= 0) & (obj >= 0)
    return jnp.full((h * w,), -1, jnp.int32).at[jnp.where(ok, pixel, h * w)].set(
        jnp.arange(n, dtype=jnp.int32), mode="drop")


def _corners(slot: jax.Array, row: jax.Array, col: jax.Array, shape: tuple[int, int],
             step: int) -> list[tuple[jax.Array, jax.Array]]:
    """The four anchors (rows and columns multiples of ``step``) around pixels (row, col
    (N,)) of the image ``shape``: per corner the receiver index (N,) (−1 where no receiver
    or outside the image; ``slot``: :func:`_pixel_slots`) and the bilinear weight (N,)."""
    h, w = shape
    r0, c0 = row - row % step, col - col % step
    fy = (row % step).astype(jnp.float32) / step
    fx = (col % step).astype(jnp.float32) / step
    out = []
    for dr, dc, wk in ((0, 0, (1 - fy) * (1 - fx)), (0, step, (1 - fy) * fx),
                       (step, 0, fy * (1 - fx)), (step, step, fy * fx)):
        r, cc = r0 + dr, c0 + dc
        inside = (r < h) & (cc < w)
        out.append((jnp.where(inside, slot[jnp.where(inside, r * w + cc, 0)], -1), wk))
    return out


def _image_anchors(pixel: jax.Array, obj: jax.Array, shape: tuple[int, int], step: int,
                   pos: jax.Array, refl: jax.Array, gap: jax.Array, width: jax.Array,
                   at: tuple[jax.Array, ...] | None = None
                   ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Screen-space subsampling of receivers that are pixels of one image (``pixel`` (N,) flat
    index row·W + column, −1 = not a pixel; ``shape`` (H, W)): the anchors are the pixels
    whose row and column are multiples of ``step``; every other receiver is the bilinear
    blend of the (up to) four anchors around it.

    A receiver is evaluated itself (``own`` (N,) bool) when it is an anchor, when an anchor of
    non-zero weight is not a receiver on the same object (silhouettes, image borders,
    non-pixels), and where the lobe's view of the neighbour changes fast between it and an
    anchor: the change of the mirror direction ``refl`` (N, 3) plus the parallax |Δx| / ``gap``
    (N,) (distance to the nearest neighbour's bounding sphere) above ``_GLOSS_SMOOTH`` ×
    ``width`` (N,) (the lobe's angular width), e.g. near a sphere's silhouette where the normal
    turns fast from pixel to pixel. Returns ``own`` and, for the others, the anchors' receiver
    indices (N, 4) and bilinear weights (N, 4).

    ``at`` = (slots, pos, refl, obj) of all receivers (:func:`_pixel_slots` and their (M, 3),
    (M, 3), (M,) arrays) when the N receivers here are a part of them (a chunk): the anchors
    are looked up there and their indices are into those M; default: these N themselves."""
    h, w = shape
    ok = (pixel >= 0) & (obj >= 0)
    if at is None:
        at = (_pixel_slots(pixel, obj, shape), pos, refl, obj)
    slot, pos_all, refl_all, obj_all = at
    row, col = jnp.divmod(jnp.maximum(pixel, 0), w)
    idx, goods, wks = [], [], []
    for a, wk in _corners(slot, row, col, shape, step):
        am = jnp.maximum(a, 0)
        d_refl, d_pos = refl_all[am] - refl, pos_all[am] - pos
        change = jnp.sqrt(dot3(d_refl, d_refl)) + jnp.sqrt(dot3(d_pos, d_pos)) / gap
        goods.append((a >= 0) & (obj_all[am] == obj) & (change <= _GLOSS_SMOOTH * width))
        idx.append(am)
        wks.append(wk)
    # the four tests computed once into memory (N, 4): fused into the consumers, XLA:CPU
    # recomputed them for every tap and channel of the interpolation (one of the close-up
    # frame's largest fusions), and for the 'own' flag again beside each tap's weight
    good = materialise(jnp.stack(goods, -1), cut=True)
    wk = jnp.stack(wks, -1)
    bad = jnp.any((wk > 0.0) & ~good, axis=-1)
    anchor = (row % step == 0) & (col % step == 0)
    own = ~ok | anchor | bad
    wts = materialise(jnp.where(good, wk, 0.0), cut=True)
    return own, materialise(jnp.stack(idx, -1), cut=True), wts


def _partition(first: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Stable partition of N items, those with ``first`` (N,) bool before the others, each
    part in index order (= ``argsort(where(first, 0, 1))``): the rank (N,) of every item and
    the permutation ``order`` (N,) (order[rank[i]] = i)."""
    n = first.shape[0]
    ones = first.astype(jnp.int32)
    before = jnp.cumsum(ones) - ones  # items with ``first`` before i
    idx = jnp.arange(n, dtype=jnp.int32)
    rank = jnp.where(first, before, jnp.sum(ones) + idx - before)
    order = jnp.zeros((n,), jnp.int32).at[rank].set(idx, unique_indices=True)
    return rank, order


def _diffuse_anchors(pixel: jax.Array, obj: jax.Array, shape: tuple[int, int], step: int,
                     pos: jax.Array, nrm: jax.Array
                     ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Screen-space anchors of the diffuse transfer for receivers that are pixels of one
    image (``pixel`` (N,) flat index row·W + column, −1 = not a pixel; ``obj`` (N,), −1 =
    empty; ``shape`` (H, W); positions ``pos`` and unit normals ``nrm`` (N, 3)): the pixels
    whose row and column are multiples of ``step`` are anchors; every other receiver blends
    the (up to) four anchors around it bilinearly, those that lie on its own face only (the
    same object, normals within ``_ANCHOR_COS``, off its tangent plane by at most
    ``_ANCHOR_PLANE`` × their distance), the weights renormalised.

    Returns ``evaluate`` (N,) bool (the anchors), the anchors' receiver indices (N, 4) and
    their weights (N, 4), summing to 1 where an anchor of the receiver's face is among them,
    else 0 (an edge of the face narrower than the step: the receiver keeps the
    interpolation)."""
    h, w = shape
    ok = (pixel >= 0) & (obj >= 0)
    slot = _pixel_slots(pixel, obj, shape)
    row, col = jnp.divmod(jnp.maximum(pixel, 0), w)
    idx, wks = [], []
    for a, wk in _corners(slot, row, col, shape, step):
        am = jnp.maximum(a, 0)
        d = pos[am] - pos
        good = ((a >= 0) & (obj[am] == obj) & (dot3(nrm[am], nrm) >= _ANCHOR_COS)
                & (jnp.abs(dot3(nrm, d)) <= _ANCHOR_PLANE * jnp.sqrt(dot3(d, d)) + 1e-7))
        idx.append(am)
        wks.append(jnp.where(good, wk, 0.0))
    wts = jnp.stack(wks, -1)
    total = jnp.sum(wts, -1)
    evaluate = ok & (row % step == 0) & (col % step == 0)
    wts = materialise(wts / jnp.maximum(total, 1e-6)[:, None], cut=True)
    return evaluate, materialise(jnp.stack(idx, -1), cut=True), wts
