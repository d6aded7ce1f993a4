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

import math
import warnings
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._runtime.backend import materialise, on_accelerator
from .._runtime.errors import InputError

__all__ = [
    "clear_plans",
    "Raster",
    "RasterConfig",
    "PixelList",
    "rasterize",
    "rasterize_batch",
    "default_config",
    "plan_config",
    "plan_counts",
    "PlanCounts",
    "interpolate",
    "covered_pixels",
    "compact_flags",
    "interpolate_pixels",
    "scatter_pixels",
    "clip_to_pixel",
    "capacity_ladder",
    "raster_jit",
    "TILE_SIZES",
]

_INT_MAX = np.iinfo(np.int32).max
_CULL = ("none", "back", "front")


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


# ----------------------------------------------------------------------------- setup


def clip_to_pixel(clip: jax.Array, shape: tuple[int, int]) -> jax.Array:
    """Homogeneous pixel coordinates ``(..., 3)`` = (X, Y, w) of clip points ``(..., 4)``:
    X/w, Y/w are the pixel coordinates of our convention ((x/w + 1)/2·W, (1 − y/w)/2·H)."""
    h, w = shape
    x, y, ww = clip[..., 0], clip[..., 1], clip[..., 3]
    return jnp.stack([(x + ww) * (0.5 * w), (ww - y) * (0.5 * h), ww], axis=-1)


def _lex_less(a, b):
    """a < b lexicographically for component tuples a = (a0, a1, a2), b likewise."""
    return (a[0] < b[0]) | ((a[0] == b[0]) & ((a[1] < b[1]) | ((a[1] == b[1]) & (a[2] < b[2]))))


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _edge_setup(hv):
    """Canonical edge functions of triangles with homogeneous pixel vertices ``hv``: a list of 3
    corners, each a tuple (X, Y, w) of arrays.

    Returns ``n`` (3 edges × 3 components; edge i is opposite corner i, its edge function at
    pixel p is ``o_i · n_i · (px, py, 1)``), ``o`` (3 arrays of ±1) and the edges' vertices in
    canonical order (3 × (lo, hi), each a tuple (X, Y, w)).
    """
    ns, os_, ends = [], [], []
    for i in range(3):
        a, b = hv[(i + 1) % 3], hv[(i + 2) % 3]
        swap = _lex_less(b, a)
        lo = tuple(jnp.where(swap, bb, aa) for aa, bb in zip(a, b, strict=True))
        hi = tuple(jnp.where(swap, aa, bb) for aa, bb in zip(a, b, strict=True))
        ns.append(_cross(lo, hi))
        os_.append(jnp.where(swap, -1.0, 1.0).astype(a[0].dtype))
        ends.append((lo, hi))
    return ns, os_, ends


# columns of the per-triangle data rows (float32)
_C_EDGE = 0  # 3 edges × (X, Y, w of the canonical first vertex, then of the second)
_C_SIGN = 18  # 3 inside signs σ_i (inside: σ_i·e_i > 0)
_C_TIE = 21  # 3 values σ_i·(tie direction): the verdict where e_i == 0 exactly
_C_DEPTH = 24  # NDC depth plane (a, b, d_a, pxa, pya): z/w = d_a + a(px − pxa) + b(py − pya)
_C_VALID = 29  # 1 / 0
_C_BOX = 30  # pixel-centre index box x0, y0, nx, ny
_NCOL = 34


def _triangle_setup(clip, triangles, shape, cull):
    """Per-triangle data packed in one float32 array (T, _NCOL), computed component-wise
    (columns: see the ``_C_*`` constants)."""
    h, w = shape
    comp = [clip[:, j] for j in range(4)]
    corners = [[comp[j][triangles[:, k]] for j in range(4)] for k in range(3)]
    hv = [((c[0] + c[3]) * (0.5 * w), (c[3] - c[1]) * (0.5 * h), c[3]) for c in corners]
    # Dividing by a runtime 1.0 materialises a value: XLA:CPU does not duplicate an
    # "expensive" op (a divide) into several consumers, whereas it recomputes chains of cheap
    # ops inside every consumer kernel (the setup would run several times slower).
    one = jnp.where(clip[0, 3] == clip[0, 3], jnp.float32(1.0), jnp.float32(2.0))
    n, o, ends = _edge_setup(hv)
    # det = det[hv0; hv1; hv2], evaluated with the origin moved to the projection of the
    # corner with the largest w (a column operation: same value, no large cancelling terms).
    # Its sign decides which side of the edges is inside (and that the point seen is in
    # front of the eye), so it must be right even for edge-on slivers at a silhouette.
    wmax = jnp.maximum(jnp.maximum(corners[0][3], corners[1][3]), corners[2][3])
    anchor = [corners[k][3] == wmax for k in range(3)]
    xa = jnp.where(anchor[0], hv[0][0], jnp.where(anchor[1], hv[1][0], hv[2][0]))
    ya = jnp.where(anchor[0], hv[0][1], jnp.where(anchor[1], hv[1][1], hv[2][1]))
    inv_wa = 1.0 / jnp.where(wmax > 0, wmax, 1.0)
    pxa = jnp.where(wmax > 0, xa * inv_wa, 0.0) / one
    pya = jnp.where(wmax > 0, ya * inv_wa, 0.0) / one
    rel = [(v[0] - pxa * v[2], v[1] - pya * v[2], v[2]) for v in hv]
    c12 = _cross(rel[1], rel[2])
    det = (rel[0][0] * c12[0] + rel[0][1] * c12[1] + rel[0][2] * c12[2]) / one
    # In pixel coordinates y points down, so a front face (counter-clockwise in NDC) has det < 0.
    valid = jnp.isfinite(det) & (det != 0)
    if cull == "back":
        valid &= det < 0
    elif cull == "front":
        valid &= det > 0
    s = jnp.sign(det)
    inv_det = 1.0 / jnp.where(valid, det, 1.0)
    z = [c[2] for c in corners]
    # NDC depth z/w is affine in pixel coordinates: z/w = d_a + a·(px − pxa) + b·(py − pya),
    # anchored at the projection of the corner with the largest w (exact to rounding there);
    # the gradient comes from edge normals of the anchored coordinates (little cancellation)
    # and only acts over the distance to the anchor (a plane stored as a·px + b·py + c loses
    # ~1e−5 for edge-on triangles far from the frame's origin).
    cr = [_cross(rel[(i + 1) % 3], rel[(i + 2) % 3]) for i in range(3)]
    zc = [sum(z[i] * cr[i][k] for i in range(3)) * inv_det for k in range(2)]
    # The constant term of the depth plane from the homogeneous formula cancels badly (its
    # terms are ~X·Y of the pixel coordinates; errors ~1e-4 in NDC depth for small, distant
    # triangles). Anchor the plane at the corner with the largest w instead: z/w there is
    # exact to rounding, and the gradient's error only acts over the triangle's extent.
    za = jnp.where(anchor[0], z[0], jnp.where(anchor[1], z[1], z[2]))
    zc += [jnp.where(wmax > 0, za * inv_wa, sum(z[i] * cr[i][2] for i in range(3)) * inv_det),
           pxa, pya]
    sigma = [o[i] * s for i in range(3)]
    # tie rule: a centre exactly on an edge goes to the side the edge function takes at the
    # centre moved by +ε in x (then +ε² in y); n_i[0], n_i[1] are its x and y derivatives
    tie = [jnp.sign(sigma[i] * jnp.where(n[i][0] != 0, n[i][0], n[i][1])) for i in range(3)]
    comps = [c for lo, hi in ends for c in (*lo, *hi)] + sigma + tie + zc

    # conservative box: the polygon clipped to z >= -w
    d = [c[2] + c[3] for c in corners]
    pts, ok = [], []
    for i in range(3):
        j = (i + 1) % 3
        pts.append(hv[i])
        ok.append(d[i] >= 0)
        den = d[i] - d[j]
        t = d[i] / jnp.where(den != 0, den, 1.0)
        pts.append(tuple(hv[i][k] + t * (hv[j][k] - hv[i][k]) for k in range(3)))
        ok.append((d[i] * d[j]) < 0)
    big = jnp.float32(1e9)
    xmin = ymin = big
    xmax = ymax = -big
    bad_w = jnp.zeros_like(valid)
    any_ok = jnp.zeros_like(valid)
    for (px_, py_, pw), k in zip(pts, ok, strict=True):
        front = pw > 0
        bad_w |= k & ~front
        any_ok |= k
        inv = 1.0 / jnp.where(k & front, pw, 1.0)
        x, y = px_ * inv, py_ * inv
        xmin = jnp.minimum(xmin, jnp.where(k, x, big))
        xmax = jnp.maximum(xmax, jnp.where(k, x, -big))
        ymin = jnp.minimum(ymin, jnp.where(k, y, big))
        ymax = jnp.maximum(ymax, jnp.where(k, y, -big))
    xmin, xmax, ymin, ymax = (v / one for v in (xmin, xmax, ymin, ymax))
    full = bad_w | ~(jnp.isfinite(xmin) & jnp.isfinite(xmax) & jnp.isfinite(ymin)
                     & jnp.isfinite(ymax))
    xmin = jnp.where(full, 0.0, xmin)
    ymin = jnp.where(full, 0.0, ymin)
    xmax = jnp.where(full, w, xmax)
    ymax = jnp.where(full, h, ymax)
    valid &= any_ok
    # pixel-centre index ranges with a margin against rounding of the box
    mx = 1.0 / 64 + 1e-6 * jnp.maximum(jnp.abs(xmin), jnp.abs(xmax))
    my = 1.0 / 64 + 1e-6 * jnp.maximum(jnp.abs(ymin), jnp.abs(ymax))
    lim = jnp.float32(1 << 15)
    x0 = jnp.ceil(jnp.clip(xmin - 0.5 - mx, -1.0, lim)).astype(jnp.int32)
    x1 = jnp.floor(jnp.clip(xmax - 0.5 + mx, -2.0, lim)).astype(jnp.int32)
    y0 = jnp.ceil(jnp.clip(ymin - 0.5 - my, -1.0, lim)).astype(jnp.int32)
    y1 = jnp.floor(jnp.clip(ymax - 0.5 + my, -2.0, lim)).astype(jnp.int32)
    x0, y0 = jnp.maximum(x0, 0), jnp.maximum(y0, 0)
    x1, y1 = jnp.minimum(x1, w - 1), jnp.minimum(y1, h - 1)
    nx, ny = x1 - x0 + 1, y1 - y0 + 1
    valid &= (nx > 0) & (ny > 0)
    f32 = jnp.float32
    cols = comps + [valid.astype(f32), x0.astype(f32), y0.astype(f32), nx.astype(f32),
                    ny.astype(f32)]
    if on_accelerator():
        # the columns computed together, one thread per triangle: the GPU fused the whole
        # setup into the stack, each thread computing one (triangle, column) element, so the
        # 34 columns' shared work (corners, determinant, clipped box) ran in every column
        # and neighbouring threads took different branches
        cols = list(jax.lax.optimization_barrier(tuple(cols)))
    data = jnp.stack(cols, axis=1)
    # materialised once, instead of recomputed per gathered window (a divide by the runtime
    # 1.0 here would cost one more pass over the rows)
    return materialise(data)


def _plane(zp, px, py):
    """NDC depth at pixel coordinates from the anchored plane (a, b, d_a, pxa, pya)."""
    return zp[..., 2] + zp[..., 0] * (px - zp[..., 3]) + zp[..., 1] * (py - zp[..., 4])


def _cover(rows, px, py):
    """Coverage and depth of pixel centres (px, py) (..., S, S) for triangle rows (..., _NCOL).

    Edge functions are evaluated relative to the pixel, e = (X_lo − px·w_lo)(Y_hi − py·w_hi)
    − (Y_lo − py·w_lo)(X_hi − px·w_hi), from the edge's two vertices in canonical order: the
    two triangles sharing an edge run the identical float operations on identical operands
    (so they see bit-identical values, whatever FMA contraction the compiler applies), and
    no large terms cancel (the error is ~1e−7 of the pixel's distance to the vertices)."""
    r = rows[..., None, None, :]
    inside = None
    for i in range(3):
        c = _C_EDGE + 6 * i
        xl = r[..., c] - px * r[..., c + 2]
        yl = r[..., c + 1] - py * r[..., c + 2]
        xh = r[..., c + 3] - px * r[..., c + 5]
        yh = r[..., c + 4] - py * r[..., c + 5]
        e = xl * yh - yl * xh
        ins = jnp.where(e != 0, r[..., _C_SIGN + i] * e, r[..., _C_TIE + i]) > 0
        inside = ins if inside is None else inside & ins
    depth = _plane(r[..., _C_DEPTH:_C_DEPTH + 5], px, py)
    inside = inside & (depth >= -1.0) & (depth <= 1.0)
    return inside, depth


def _window_dn():
    return lax.ScatterDimensionNumbers(
        update_window_dims=(1, 2), inserted_window_dims=(), scatter_dims_to_operand_dims=(0, 1))


def _gather_windows(buf, idx, s):
    dn = lax.GatherDimensionNumbers(offset_dims=(1, 2), collapsed_slice_dims=(),
                                    start_index_map=(0, 1))
    return lax.gather(buf, idx, dn, (s, s), mode=lax.GatherScatterMode.PROMISE_IN_BOUNDS)


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


_TILE = 8  # side of the square pixel blocks of the final (barycentric/depth) stage


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


# ----------------------------------------------------------------------------- validation


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


# ----------------------------------------------------------------------------- interpolation


def _bary_at(clip, triangles, tri_id, px, py, shape):
    """Differentiable perspective-correct barycentrics (N, 3) of triangles ``tri_id (N,)``
    (−1 allowed: zeros) at pixel coordinates (px, py) (N,)."""
    hit = tri_id >= 0
    idx = triangles[jnp.where(hit, tri_id, 0)]  # (N, 3)
    hv = clip_to_pixel(clip[idx], shape)  # (N, 3, 3)
    # edge functions with the pixel moved to the origin (X − px·w, Y − py·w): no large
    # cancelling terms, so the barycentrics keep float32 precision on small triangles
    rx = hv[..., 0] - px[:, None] * hv[..., 2]
    ry = hv[..., 1] - py[:, None] * hv[..., 2]
    gam = jnp.stack([rx[:, (i + 1) % 3] * ry[:, (i + 2) % 3]
                     - ry[:, (i + 1) % 3] * rx[:, (i + 2) % 3] for i in range(3)], -1)
    tot = jnp.sum(gam, -1)
    tot = jnp.where(hit & (tot != 0), tot, 1.0)
    return jnp.where(hit[:, None], gam / tot[:, None], 0.0), idx


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


def interpolate_pixels(attributes, pixels: PixelList, triangles, clip_xyzw) -> jax.Array:
    """Attributes ``(V, C)`` interpolated at the listed pixels → ``(P, C)`` (0 in unused
    slots); differentiable w.r.t. attributes and clip positions."""
    h, w = pixels.shape
    py, px = jnp.divmod(pixels.index, w)
    bary, idx = _bary_at(jnp.asarray(clip_xyzw), jnp.asarray(triangles, jnp.int32),
                         pixels.tri_id, px.astype(jnp.float32) + 0.5,
                         py.astype(jnp.float32) + 0.5, (h, w))
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
