"""Buffer sizes of the rasteriser: the window-size ladder, the capacities of its fixed window and
block lists (:class:`RasterConfig`), and their planning in NumPy from the poses to draw
(:func:`plan_counts`, :func:`plan_config`) without compiling anything.

Each triangle gets a conservative pixel-centre bounding box (of its near-clipped polygon) and is
tiled with square windows of side S from a ladder (default :data:`TILE_SIZES`): S is the
smallest ladder size ≥ the shorter side of the box (capped at the largest), the box is covered by
⌈nx/S⌉·⌈ny/S⌉ windows (:func:`_ladder_masks`, shared with the compiled rasteriser). The final
stage works on 8×8 pixel blocks (:data:`_TILE`). Capacities are counts of windows and blocks;
shapes are (H, W) in pixels.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .._runtime.errors import InputError
from ._raster_checks import _check_shape, _validate

__all__ = [
    "capacity_ladder",
    "RasterConfig",
    "TILE_SIZES",
    "default_config",
    "PlanCounts",
    "plan_counts",
    "plan_config",
]

_CULL = ("none", "back", "front")
_TILE = 8  # side of the square pixel blocks of the final (barycentric/depth) stage


def capacity_ladder(n: float, minimum: float = 16.0) -> int:
    """Smallest capacity ≥ max(n, minimum) on the quarter-octave ladder 2^k·{1, 1.25, 1.5,
    1.75}: buffer sizes from a small set, so that a grown capacity rarely means a new program."""
    n = max(float(minimum), float(n))
    k = math.floor(math.log2(n))
    for f in (1.0, 1.25, 1.5, 1.75, 2.0):
        c = int(f * (1 << k))
        if c >= n:
            return c
    raise AssertionError  # pragma: no cover


class RasterConfig(NamedTuple):
    """Static (hashable) buffer sizes of the rasteriser.

    Attributes:
        tile_sizes: window sides S of the ladder (pixels), ascending.
        capacities: windows per ladder size (same length as ``tile_sizes``).
        block_capacity: 8×8 pixel blocks holding visible triangles (final stage).
    """

    tile_sizes: tuple[int, ...]
    capacities: tuple[int, ...]
    block_capacity: int

    @classmethod
    def from_counts(cls, counts: PlanCounts, *, headroom: float = 1.5,
                    tile_sizes: tuple[int, ...] | None = None) -> RasterConfig:
        """Capacities ``headroom`` × the planned ``counts`` (+16), rounded up on the
        quarter-octave capacity ladder, for the window sizes ``tile_sizes`` the counts were
        made with (default :data:`TILE_SIZES`)."""
        sizes = TILE_SIZES if tile_sizes is None else tuple(tile_sizes)
        if len(sizes) != len(counts.windows):
            raise InputError(f"{len(counts.windows)} window counts for {len(sizes)} sizes",
                             field="tile_sizes")
        caps = tuple(capacity_ladder(headroom * n + 16) for n in counts.windows)
        return cls(sizes, caps, capacity_ladder(headroom * counts.blocks + 16))

    def grown(self, needed, headroom: float = 1.25, *, full: float = 1.0) -> RasterConfig:
        """Capacities raised to the ladder value ≥ ``headroom`` × ``needed`` where
        ``needed`` (windows per ladder size, then blocks) exceeds ``full`` × them (1: where
        they overflowed; below 1, ahead of an overflow, with ``headroom`` ≥ 1 / ``full``)."""
        needed = [int(n) for n in np.asarray(needed).tolist()]
        caps = [c if n <= full * c else capacity_ladder(headroom * n)
                for c, n in zip(self.capacities, needed[:-1], strict=True)]
        blocks = self.block_capacity
        if needed[-1] > full * blocks:
            blocks = capacity_ladder(headroom * needed[-1])
        return RasterConfig(self.tile_sizes, tuple(caps), blocks)


TILE_SIZES = (1, 4, 16)


def default_config(num_triangles: int, shape: tuple[int, int]) -> RasterConfig:
    """A generic configuration for ``num_triangles`` triangles on an (H, W) frame, used when
    no measured plan exists (e.g. inside a user's ``jit`` without ``config=``): T windows for
    every ladder size but the largest, which gets enough windows to tile half the frame, and
    blocks for half the frame."""
    h, w = shape
    t = num_triangles
    area = h * w
    big = TILE_SIZES[-1]
    caps = [t] * (len(TILE_SIZES) - 1) + [min(t, area / (2 * big * big) + 64)]
    blocks = (-(-h // _TILE)) * (-(-w // _TILE)) / 2
    return RasterConfig(TILE_SIZES, tuple(capacity_ladder(c) for c in caps),
                        capacity_ladder(blocks))


class PlanCounts(NamedTuple):
    """What one pose (or the worst of several) needs from the rasteriser's buffers.

    Attributes:
        windows: windows per ladder size (``tile_sizes`` of :func:`plan_counts`).
        blocks: 8×8 pixel blocks touched by the pixel boxes of the drawable triangles (a bound
            on the blocks holding visible triangles).
        pixels: pixels inside those boxes (a bound on the covered pixels).
    """

    windows: tuple[int, ...]
    blocks: int
    pixels: int


def _union_area(x0, y0, x1, y1, shape, scale):
    """Cells of side ``scale`` touched by the inclusive pixel boxes (x0..x1, y0..y1)."""
    h, w = shape
    hh, ww = -(-h // scale), -(-w // scale)
    diff = np.zeros((hh + 1, ww + 1), np.int64)
    a0, a1 = x0 // scale, x1 // scale + 1
    b0, b1 = y0 // scale, y1 // scale + 1
    for yy, xx, sgn in ((b0, a0, 1), (b0, a1, -1), (b1, a0, -1), (b1, a1, 1)):
        np.add.at(diff, (yy, xx), sgn)
    return int(np.sum(np.cumsum(np.cumsum(diff, 0), 1)[:hh, :ww] > 0))


def plan_counts(clip_xyzw, triangles, shape: tuple[int, int], *, cull: str = "none",
                tile_sizes: tuple[int, ...] = TILE_SIZES) -> PlanCounts:
    """Windows, blocks and pixels one pose needs, in NumPy (float64, no compilation).

    Per triangle: the rasteriser's drawability test (non-degenerate, culling, in front of the
    near plane) and its conservative pixel-centre box of the polygon clipped to z ≥ −w (the
    whole frame when part of it lies behind the eye), with the rasteriser's rounding margin;
    then the same ladder choice and window tiling as the rasteriser (:func:`_ladder_masks`).
    Float64 here against float32 there: a box could differ by one pixel when a bound lies
    within rounding of a pixel centre (the counts were identical to the rasteriser's own
    ``needed`` on the benchmark scenes, near-plane-crossing poses and random soups); the
    ``+16`` and the headroom of :func:`plan_config` absorb that, and overflow stays detected.
    Used by :func:`plan_config` and by the renderer's capacity planning.

    Args:
        clip_xyzw: ``(V, 4)`` clip positions.
        triangles: ``(T, 3)`` int indices.
        shape: ``(H, W)``.
        cull: as in :func:`rasterize`.
        tile_sizes: the ladder (default :data:`TILE_SIZES`).
    """
    h, w = _check_shape(shape)
    if cull not in _CULL:
        raise InputError(f"unknown cull mode {cull!r} (one of {_CULL})", field="cull")
    clip, tris = _validate(clip_xyzw, triangles, False)
    x, y, z, wc = np.asarray(clip, np.float64).T[:, np.asarray(tris).T]  # 4 × (3, T)
    hv = np.stack([(x + wc) * (0.5 * w), (wc - y) * (0.5 * h), wc])  # (3 comps, 3 corners, T)
    # det[hv0; hv1; hv2]: its sign gives the facing (front faces have det < 0)
    det = np.sum(hv[:, 0] * np.cross(hv[:, 1], hv[:, 2], axis=0), axis=0)
    valid = np.isfinite(det) & (det != 0)
    if cull == "back":
        valid &= det < 0
    elif cull == "front":
        valid &= det > 0
    # the polygon clipped to z >= -w: corners in front of the near plane and edge crossings
    d = z + wc
    dn = np.roll(d, -1, axis=0)
    den = d - dn
    t = d / np.where(den != 0, den, 1.0)
    cross = hv + t * (np.roll(hv, -1, axis=1) - hv)
    pts = np.concatenate([hv, cross], axis=1)  # (3 comps, 6 points, T)
    ok = np.concatenate([d >= 0, d * dn < 0], axis=0)
    front = pts[2] > 0
    full = np.any(ok & ~front, axis=0)
    valid &= np.any(ok, axis=0)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inv = 1.0 / np.where(ok & front, pts[2], 1.0)
        xy = pts[:2] * inv
        lo = np.min(np.where(ok, xy, np.inf), axis=1)  # (2, T)
        hi = np.max(np.where(ok, xy, -np.inf), axis=1)
    full |= ~np.all(np.isfinite(lo) & np.isfinite(hi), axis=0)
    size = np.asarray([[w], [h]], np.float64)
    lo = np.where(full, 0.0, lo)
    hi = np.where(full, size, hi)
    m = 1.0 / 64 + 1e-6 * np.maximum(np.abs(lo), np.abs(hi))
    i0 = np.maximum(np.ceil(np.clip(lo - 0.5 - m, -1.0, 1 << 15)), 0).astype(np.int64)
    i1 = np.minimum(np.floor(np.clip(hi - 0.5 + m, -2.0, 1 << 15)), size - 1).astype(np.int64)
    n = i1 - i0 + 1
    valid &= np.all(n > 0, axis=0)
    nx, ny = n
    masks = _ladder_masks(np.minimum(nx, ny), valid, tile_sizes)
    windows = tuple(int(np.sum(np.where(sel, -(-nx // s) * -(-ny // s), 0)))
                    for s, sel in zip(tile_sizes, masks, strict=True))
    x0, y0, x1, y1 = i0[0, valid], i0[1, valid], i1[0, valid], i1[1, valid]
    return PlanCounts(windows, _union_area(x0, y0, x1, y1, (h, w), _TILE),
                      _union_area(x0, y0, x1, y1, (h, w), 1))


def plan_config(clip_xyzw, triangles, shape: tuple[int, int], *, cull: str = "none",
                headroom: float = 1.5) -> RasterConfig:
    """Capacities measured on one or several poses, with ``headroom`` for motion.

    Runs :func:`plan_counts` (NumPy, no rasterisation, no compilation) on each pose: the
    windows per ladder size and the 8×8 pixel blocks touched by the triangles' bounding boxes
    (a bound on the blocks the final stage visits); takes the maximum over the poses and sizes
    each list to ``headroom`` × that (+16), rounded up on the ladder. Pass the result as
    ``config=`` inside a live loop or a ``jit``; overflow is still detected.

    Args:
        clip_xyzw: ``(V, 4)`` clip positions of one pose, or ``(P, V, 4)`` for P poses
            (e.g. the extremes of the expected motion).
        triangles: ``(T, 3)`` int indices.
        shape: ``(H, W)``.
        cull: as in :func:`rasterize`.
        headroom: factor ≥ 1 on the measured counts.
    """
    poses = np.ndim(clip_xyzw) == 3
    clips = clip_xyzw if poses else [clip_xyzw]
    counts = [plan_counts(c, triangles, shape, cull=cull) for c in clips]
    return RasterConfig.from_counts(
        PlanCounts(tuple(np.max([c.windows for c in counts], axis=0).tolist()),
                   max(c.blocks for c in counts), max(c.pixels for c in counts)),
        headroom=headroom)


def _ladder_masks(shorter, valid, sizes):
    """Which ladder size tiles each triangle (NumPy or JAX arrays): the smallest S ≥ the
    shorter side of its pixel box, the largest size for longer sides."""
    masks = []
    for b, s in enumerate(sizes):
        sel = valid & (shorter <= s) if b == 0 else valid & (shorter > sizes[b - 1])
        if 0 < b < len(sizes) - 1:
            sel &= shorter <= s
        masks.append(sel)
    return masks
