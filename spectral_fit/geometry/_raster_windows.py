"""The rasteriser's fixed-capacity lists and its per-window raster: windows listed per ladder
size without sorting, their pixels evaluated densely (coverage and NDC depth), visibility resolved
by two 32-bit scatter-min passes (nearest depth, then the smallest triangle id), and the final
stage's barycentrics and depth in the 8×8 pixel blocks that hold a visible triangle.

Window origins are (y, x) pixel indices into a padded (H', W') buffer; depth is NDC z/w, +inf
where a window pixel is not covered; the id buffer holds ``_INT_MAX`` where nothing is drawn.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jax import lax

from ._prefix import _count_cumsum, _scan
from ._raster_plan import _TILE, _ladder_masks
from ._raster_setup import _C_BOX, _C_DEPTH, _C_VALID, _bary_at, _cover, _plane

_INT_MAX = np.iinfo(np.int32).max


def _window_dn():
    return lax.ScatterDimensionNumbers(
        update_window_dims=(1, 2), inserted_window_dims=(), scatter_dims_to_operand_dims=(0, 1))


def _gather_windows(buf, idx, s):
    dn = lax.GatherDimensionNumbers(offset_dims=(1, 2), collapsed_slice_dims=(),
                                    start_index_map=(0, 1))
    return lax.gather(buf, idx, dn, (s, s), mode=lax.GatherScatterMode.PROMISE_IN_BOUNDS)


def _window_counts(data, config):
    """Windows per triangle and ladder size: (m (NB, T), tx (NB, T)) (static divisors)."""
    valid = data[:, _C_VALID] > 0
    nx = data[:, _C_BOX + 2].astype(jnp.int32)
    ny = data[:, _C_BOX + 3].astype(jnp.int32)
    sizes = config.tile_sizes
    ms, txs = [], []
    masks = _ladder_masks(jnp.minimum(nx, ny), valid, sizes)
    for s, sel in zip(sizes, masks, strict=True):
        tx = lax.div(nx + (s - 1), jnp.int32(s))
        ty = lax.div(ny + (s - 1), jnp.int32(s))
        ms.append(jnp.where(sel, tx * ty, 0))
        txs.append(tx)
    return jnp.stack(ms), jnp.stack(txs)


def _window_lists(data, config):
    """Per ladder size: (S, window origins (C, 2) (y, x), triangle ids (C,), triangle data
    (C, _NCOL), live (C,), windows needed).

    Listing without sorting, for all ladder sizes at once (one list of Σ capacities slots,
    size b's slots after those of the smaller sizes): an inclusive prefix sum of the window
    counts gives each triangle its first slot; one scatter writes the key b·T + id there and
    a running max fills the slots of its further windows (keys grow along the list, so one
    scan serves every size). The sizes' lists are static slices of the result.
    """
    t = data.shape[0]
    sizes, caps = config.tile_sizes, config.capacities
    nb = len(sizes)
    offs = [sum(caps[:b]) for b in range(nb + 1)]
    m, tx = _window_counts(data, config)  # (NB, T)
    csum = _count_cumsum(m)
    start = csum - m  # first slot of each triangle within its size's list
    total = csum[:, -1]  # (NB,)
    slot0 = jnp.asarray(offs[:-1], jnp.int32)[:, None]
    keep = (m > 0) & (start < jnp.asarray(caps, jnp.int32)[:, None])
    pos = jnp.where(keep, start + slot0, offs[-1]).reshape(-1)
    keys = lax.broadcasted_iota(jnp.int32, (nb, t), 0) * t + lax.broadcasted_iota(
        jnp.int32, (nb, t), 1)
    first = jnp.zeros((offs[-1],), jnp.int32).at[pos].max(keys.reshape(-1), mode="drop")
    key = _scan(jnp.maximum, first, 0)
    # per slot: its ladder size b, the slot number within that size's list, S and the total
    k = jnp.arange(offs[-1], dtype=jnp.int32)
    b = sum((k >= o).astype(jnp.int32) for o in offs[1:-1])
    local_slot = k - sum(jnp.where(b == i, o, 0) for i, o in enumerate(offs[:-1]))
    s_slot = sum(jnp.where(b == i, s, 0) for i, s in enumerate(sizes))
    live = local_slot < sum(jnp.where(b == i, total[i], 0) for i in range(nb))
    key = jnp.clip(key, b * t, b * t + (t - 1))  # dead slots: any triangle of the size
    tri = key - b * t
    box = data[:, _C_BOX:_C_BOX + 2].astype(jnp.int32)[tri]  # (ΣC, 2) x0, y0
    local = local_slot - start.reshape(-1)[key]  # window number within its triangle
    txt = jnp.maximum(tx.reshape(-1)[key], 1)
    # row = local // txt in float32: exact while row·txt < 2^22 (always here: at most
    # 16384 windows per triangle below the largest size, 513² at the largest)
    row = jnp.floor((local.astype(jnp.float32) + 0.5) / txt.astype(jnp.float32))
    row = row.astype(jnp.int32)
    col = local - row * txt
    ox = jnp.where(live, box[:, 0] + col * s_slot, 0)
    oy = jnp.where(live, box[:, 1] + row * s_slot, 0)
    # materialised once: otherwise XLA recomputes the chain above in every window pixel
    idx = jnp.stack([oy, ox], -1)
    out = []
    for i, s in enumerate(sizes):
        tri_b = tri[offs[i]:offs[i + 1]]
        # the rows are gathered by each consumer (fused; not materialised)
        out.append((s, idx[offs[i]:offs[i + 1]], tri_b, data[tri_b], live[offs[i]:offs[i + 1]],
                    total[i]))
    return out


def _evaluate(lists):
    """Depth of every window pixel, +inf where not covered: list of (C, S, S)."""
    out = []
    for s, idx, _, d, live, _ in lists:
        ar = jnp.arange(s, dtype=jnp.float32) + 0.5
        pxs = idx[:, 1].astype(jnp.float32)[:, None, None] + ar[None, None, :]
        pys = idx[:, 0].astype(jnp.float32)[:, None, None] + ar[None, :, None]
        inside, depth = _cover(d, pxs, pys)
        inside &= live[:, None, None]
        out.append(jnp.where(inside, depth, jnp.inf))
    return out


def _buffer_shape(shape, config):
    h, w = shape
    pad = max(config.tile_sizes)
    hp = -(-(h + pad) // _TILE) * _TILE
    wp = -(-(w + pad) // _TILE) * _TILE
    return hp, wp


def _resolve(lists, dvals, bshape):
    """Two 32-bit scatter-min passes: nearest depth, then the smallest id at that depth."""
    zbuf = jnp.full(bshape, jnp.inf, jnp.float32)
    for (_, idx, _, _, _, _), dval in zip(lists, dvals, strict=True):
        zbuf = lax.scatter_min(zbuf, idx, dval, _window_dn(), indices_are_sorted=False,
                               unique_indices=False,
                               mode=lax.GatherScatterMode.PROMISE_IN_BOUNDS)
    ibuf = jnp.full(bshape, _INT_MAX, jnp.int32)
    for (s, idx, tri, _, _, _), dval in zip(lists, dvals, strict=True):
        zw = _gather_windows(zbuf, idx, s)
        win = (dval == zw) & (dval < jnp.inf)
        ids = jnp.where(win, tri[:, None, None], _INT_MAX)
        ibuf = lax.scatter_min(ibuf, idx, ids, _window_dn(), indices_are_sorted=False,
                               unique_indices=False,
                               mode=lax.GatherScatterMode.PROMISE_IN_BOUNDS)
    return ibuf


def _finish(data, clip, triangles, ibuf, shape, block_capacity):
    """Raster fields: barycentrics and depth of the winners, computed only in the 8×8 pixel
    blocks that contain a visible triangle (a fixed-capacity list of blocks). Blocks of the
    last row/column are shifted inside the frame when H or W is not a multiple of 8 (they
    then overlap their neighbour, which only rewrites identical values)."""
    h, w = shape
    bh, bw = min(_TILE, h), min(_TILE, w)
    th, tw = -(-h // _TILE), -(-w // _TILE)
    ids_frame = ibuf[:h, :w]
    tri_id = jnp.where(ids_frame != _INT_MAX, ids_frame, -1)
    occ = ibuf[:th * _TILE, :tw * _TILE] != _INT_MAX
    yy = lax.broadcasted_iota(jnp.int32, occ.shape, 0)
    xx = lax.broadcasted_iota(jnp.int32, occ.shape, 1)
    occ &= (yy < h) & (xx < w)
    occupied = jnp.any(occ.reshape(th, _TILE, tw, _TILE), axis=(1, 3)).reshape(-1)
    csum = _count_cumsum(occupied.astype(jnp.int32))
    nblocks = csum[-1]
    slot = jnp.where(occupied, csum - 1, block_capacity)
    blocks = jnp.full((block_capacity,), th * tw, jnp.int32).at[slot].set(
        jnp.arange(th * tw, dtype=jnp.int32), mode="drop")
    live = blocks < th * tw
    oy = jnp.minimum((blocks // tw) * _TILE, h - bh)
    ox = jnp.minimum((blocks % tw) * _TILE, w - bw)
    idx = jnp.stack([jnp.where(live, oy, 0), jnp.where(live, ox, 0)], -1)
    dn = lax.GatherDimensionNumbers(offset_dims=(1, 2), collapsed_slice_dims=(),
                                    start_index_map=(0, 1))
    ids = lax.gather(ibuf, idx, dn, (bh, bw),
                     mode=lax.GatherScatterMode.PROMISE_IN_BOUNDS)  # (B, bh, bw)
    hit = ids != _INT_MAX
    tid = jnp.where(hit, ids, 0)
    zplane = data[:, _C_DEPTH:_C_DEPTH + 5][tid]  # (B, bh, bw, 5)
    pxs = idx[:, 1].astype(jnp.float32)[:, None, None] + (jnp.arange(bw) + 0.5)[None, None, :]
    pys = idx[:, 0].astype(jnp.float32)[:, None, None] + (jnp.arange(bh) + 0.5)[None, :, None]
    pxs = jnp.broadcast_to(pxs, ids.shape)
    pys = jnp.broadcast_to(pys, ids.shape)
    bary_b, _ = _bary_at(clip, triangles, jnp.where(hit, ids, -1).reshape(-1),
                         pxs.reshape(-1), pys.reshape(-1), shape)
    bary_b = bary_b.reshape(ids.shape + (3,))  # (B, bh, bw, 3)
    depth_b = jnp.where(hit, _plane(zplane, pxs, pys), 1.0)
    # unused slots point outside the frame and are dropped
    sidx = jnp.where(live[:, None], idx, jnp.asarray([h, w], jnp.int32))
    mode = lax.GatherScatterMode.FILL_OR_DROP
    dn3 = lax.ScatterDimensionNumbers(update_window_dims=(1, 2, 3), inserted_window_dims=(),
                                      scatter_dims_to_operand_dims=(0, 1))
    bary = lax.scatter(jnp.zeros((h, w, 3), jnp.float32), sidx, bary_b, dn3,
                       indices_are_sorted=True, unique_indices=False, mode=mode)
    depth = lax.scatter(jnp.ones((h, w), jnp.float32), sidx, depth_b, _window_dn(),
                        indices_are_sorted=True, unique_indices=False, mode=mode)
    return tri_id, bary, depth, nblocks
