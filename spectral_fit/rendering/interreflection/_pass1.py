"""Pass 1 of the interreflection (geometry only): each object as seen from the others.

Pairs. For n objects there are P = n(n − 1) ordered pairs p = (i, j), i the object that
RECEIVES light and j the one that sends it, stored in the order p = i·(n − 1) + k with
j = k for k < i and j = k + 1 otherwise (:func:`pair_list`).

"gather" mode rasterises sender j ORTHOGRAPHICALLY along the axis c_i → c_j (a window of
``_MARGIN`` × j's bounding-sphere radius) at (``SUPERSAMPLE`` · g)² and box-filters it into
g × g surface samples (area m², area-weighted mean position m and unit normal, coverage);
"paper" mode rasterises j through :func:`~spectral_fit.geometry.interreflection_camera` (at
c_i, 90° FOV, ``texture_size``²) and keeps the covered texels' positions and normals. Both
collect into one :class:`IRGeometry` of static shapes (:func:`prepare_interreflection`), so
moving objects never recompiles; :func:`pass1_config` and :func:`plan_gather_pass1` size the
pass-1 rasters' window capacities.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._runtime.errors import InputError
from ...geometry import (
    TILE_SIZES,
    ObjectGeometry,
    RasterConfig,
    capacity_ladder,
    covered_pixels,
    default_config,
    fibonacci_directions,
    interpolate,
    interpolate_pixels,
    interreflection_camera,
    look_at,
    plan_counts,
    project,
    rasterize,
)
from ._options import _check_int, _check_mode

__all__ = [
    "IRGeometry",
    "prepare_interreflection",
    "plan_gather_pass1",
    "pass1_config",
    "pair_list",
]

#: pass-1 supersampling of the gather samples (raster side = SUPERSAMPLE · gather_size)
SUPERSAMPLE = 4
#: channels of the pass-1 depth map (``IRGeometry.s_front``)
FRONT_CHANNELS = 5
#: the largest slope of the depth map's front surface (a face this steep or steeper against
#: the pair's axis is seen edge-on: its height is not extrapolated further)
_MAX_SLOPE = 4.0
#: default gather size g (samples per side of a sender's grid)
GATHER_SIZE = 16
#: smallest |n·axis| used for the area of a grazing pass-1 texel (caps 1/cos at 20)
_MIN_COS = 0.05
#: the ortho window is the bounding sphere's radius times this
_MARGIN = 1.02


def check_gather_size(value: Any) -> int:
    """``value`` as the gather size g: a power of two in 2..64, else an
    :class:`~spectral_fit._runtime.errors.InputError` naming ``gather_size``."""
    g = _check_int(value, "gather_size", 2, 64)
    if g & (g - 1):
        raise InputError(f"must be a power of two, got {g}", field="gather_size")
    return g


def pair_list(n: int) -> list[tuple[int, int]]:
    """Ordered pairs (receiver i, sender j), i ≠ j, in storage order p = i·(n − 1) + k."""
    return [(i, j) for i in range(n) for j in range(n) if j != i]


class IRGeometry(eqx.Module):
    """Geometry-only interreflection data of n objects (pass 1), for P = n(n − 1) ordered pairs
    (see :func:`pair_list`). Fields not needed by ``mode`` are None.

    Attributes:
        centre_i, centre_j: (P, 3) centres of the receiving / sending object (m).
        radius_i, radius_j: (P,) their bounding-sphere radii about the centres (m).
        frame: (P, 3, 3) rows s, u, a: the pass-1 eye's right, up and forward (a ∥ c_j − c_i).
        extent: (P,) half side of the orthographic window of the gather pass (m).
        s_pos, s_nrm, s_view: (P, M, 3) gather samples (M = g²): position, unit normal, unit
            direction towards the receiver's nearest bounding-sphere point (tilted to at least
            3° above the sample's horizon).
        s_area: (P, M) surface area of each sample (m², 0 = empty).
        s_cov: (P, M) covered fraction of each sample's pass-1 texels.
        s_front: (P, (S + 2)², 5) the pass-1 raster itself (S = ``SUPERSAMPLE`` · g texels a
            side, rows from the top, padded by a one-texel zero border): coverage (0 or 1),
            coverage × the front surface's height above c_j along the axis towards the
            receiver (m), the depth of the solid behind it (m: to the nearest back face;
            0 where none) and the front surface's change of height per texel along a row and
            down a column (m; from its triangle's plane): the sender's depth map at full
            resolution, which the gloss rays march through.
        p_view_proj: (P, 4, 4) paper mode's pass-1 camera (projection @ view).
        p_index: (P, Q) flat texel index of the covered pass-1 texels (Q = capacity).
        p_pos, p_nrm: (P, Q, 3) their world positions and unit normals.
        p_valid: (P, Q) bool.
        overflow: bool scalar: a pass-1 buffer overflowed (results incomplete).
        n_objects, mode, texture_size, gather_size: static.
    """

    centre_i: jax.Array
    centre_j: jax.Array
    radius_i: jax.Array
    radius_j: jax.Array
    frame: jax.Array
    extent: jax.Array
    s_pos: jax.Array | None
    s_nrm: jax.Array | None
    s_view: jax.Array | None
    s_area: jax.Array | None
    s_cov: jax.Array | None
    s_front: jax.Array | None
    p_view_proj: jax.Array | None
    p_index: jax.Array | None
    p_pos: jax.Array | None
    p_nrm: jax.Array | None
    p_valid: jax.Array | None
    overflow: jax.Array
    n_objects: int = eqx.field(static=True)
    mode: str = eqx.field(static=True)
    texture_size: int = eqx.field(static=True)
    gather_size: int = eqx.field(static=True)

    @property
    def pairs(self) -> list[tuple[int, int]]:
        return pair_list(self.n_objects)


def without_pairs(geom: IRGeometry, bodies: tuple[int, ...]) -> IRGeometry:
    """``geom`` with the pairs of two parts of one body emptied (no samples, no depth map):
    no light or shadow passes between them through this pass.

    Parts of one mesh (materials of their own, one pose) touch along their shared edges and
    their bounding spheres nest (a cup's glaze inside its body), while pass 1 represents the
    sender as seen along the axis between the two centres, which holds for objects apart;
    between two parts it let light through the wall. Their exchange is left out (what a cup's
    inside and outside exchange is the light across its lip; the inside's own bounces and
    every other object's light stay).

    Args:
        geom: pass 1 of O objects.
        bodies: (O,) each object's body; () keeps every pair.
    """
    if not bodies:
        return geom
    keep_np = np.asarray([bodies[i] != bodies[j] for i, j in geom.pairs], bool)
    if keep_np.all():
        return geom
    keep = jnp.asarray(keep_np)
    f = keep.astype(jnp.float32)
    changes = {}
    if geom.s_area is not None:
        changes.update(s_area=geom.s_area * f[:, None], s_cov=geom.s_cov * f[:, None],
                       s_front=geom.s_front * f[:, None, None])
    if geom.p_valid is not None:
        changes.update(p_valid=geom.p_valid & keep[:, None])
    names = tuple(changes)
    return eqx.tree_at(lambda g: tuple(getattr(g, k) for k in names), geom,
                       tuple(changes[k] for k in names))


def _normalize(v: jax.Array) -> jax.Array:
    return v / jnp.sqrt(jnp.maximum(jnp.sum(v * v, axis=-1, keepdims=True), 1e-30))


def _bounding_radius(obj: ObjectGeometry) -> jax.Array:
    v = jnp.asarray(obj.vertices, jnp.float32) - jnp.asarray(obj.centre, jnp.float32)
    return jnp.sqrt(jnp.max(jnp.sum(v * v, axis=-1)))


def _ortho_clip(view: jax.Array, vertices: jax.Array, extent: jax.Array, near: jax.Array,
                far: jax.Array, xp: Any = jnp) -> jax.Array:
    """Clip coordinates (V, 4) of an orthographic eye: x, y / extent, depth −z_eye ∈ [near,
    far] → [−1, 1], w = 1 (``xp``: jax.numpy, or numpy for planning)."""
    q = vertices @ view[:3, :3].T + view[:3, 3]
    z = 2.0 * (-q[:, 2] - near) / (far - near) - 1.0
    return xp.stack([q[:, 0] / extent, q[:, 1] / extent, z, xp.ones_like(z)], axis=-1)


def pass1_config(num_triangles: int, side: int) -> RasterConfig:
    """Generic window capacities of a pass-1 raster (side × side, back faces culled) of a
    sender with ``num_triangles`` triangles, used where no per-mesh plan exists (the direct
    calls of this module without ``raster_config``, and the renderer's fallback after a
    planned capacity overflowed): per size of the rasteriser's window ladder
    (``raster.TILE_SIZES``) the larger of :func:`~spectral_fit.geometry.default_config`'s
    (T windows, the largest size enough for half the target) and a closed mesh's (T/2 + 16,
    since at most half its faces face one way; T/4 + 16 plus four tilings of the target
    for the largest size), and every 8×8 block of the target. A pose needing more still
    sets the overflow flag."""
    side = int(side)
    base = default_config(num_triangles, (side, side))
    half = max(16, num_triangles // 2 + 16)
    tiling = (-(-side // TILE_SIZES[-1])) ** 2
    closed = (*([half] * (len(TILE_SIZES) - 1)), max(16, num_triangles // 4 + 16) + 4 * tiling)
    caps = tuple(int(max(a, b)) for a, b in zip(base.capacities, closed, strict=True))
    return RasterConfig(TILE_SIZES, caps, (-(-side // 8)) ** 2)


#: views (object frame) at which :func:`plan_gather_pass1` counts the windows: the six axes,
#: each at four rolls. On the 100 × 100 UV sphere their maximum, 10,424 / 724 / 0 windows per
#: ladder size, was above that of 150 random orientations (10,431 / 702 / 0; 99th percentile
#: 10,357 / 672 / 0); the axes at one roll gave 260 for the 4 × 4 windows: the roll matters
_PLAN_DIRECTIONS = ((1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, -1.0, 0.0),
                    (0.0, 0.0, 1.0), (0.0, 0.0, -1.0))
_PLAN_ROLLS_DEG = (0.0, 22.5, 45.0, 67.5)
#: and at this many oblique directions (a Fibonacci sphere), each at two rolls: a box seen
#: along its axes shows its faces whole, obliquely its edges in many small windows (the
#: 70 × 90 × 12 mm slab at g = 16: 1,024 one-texel windows planned from the axes, 1,830
#: needed at the worst of 200 random orientations)
_PLAN_OBLIQUE = 32


def plan_gather_pass1(vertices: Any, triangles: Any, *, gather_size: int = GATHER_SIZE,
                      headroom: float = 1.5) -> RasterConfig:
    """Window capacities of the gather pass-1 raster of one sender mesh, for any pose.

    The pass-1 view is orthographic and framed on the sender's bounding sphere
    (:func:`_gather_samples`), so what it needs depends on the mesh and the view direction
    in the mesh's own frame only, not on distances or positions: counted
    (:func:`~spectral_fit.geometry.plan_counts`, NumPy) along the six axes of that frame, each
    at four rolls, and along ``_PLAN_OBLIQUE`` oblique directions at two (once per distinct
    mesh), and sized ``headroom`` × the maximum (+16, on
    the capacity ladder). A pose needing more still
    sets the overflow flag (the renderer then falls back to generic capacities).

    Args:
        vertices: ``(V, 3)`` in the mesh's frame (any scale; its origin the object's centre).
        triangles: ``(T, 3)`` int.
        gather_size: g (the raster is (SUPERSAMPLE · g)²).
        headroom: factor over the counted maximum.
    Returns:
        :class:`~spectral_fit.geometry.RasterConfig` with every 8×8 block of the raster.
    """
    v = np.asarray(vertices, np.float64)
    tris = np.asarray(triangles)
    side = SUPERSAMPLE * int(gather_size)
    r = float(np.sqrt(np.max(np.sum(v * v, axis=-1)))) if v.size else 1.0
    r = max(r, 1e-9)
    windows = np.zeros(len(TILE_SIZES), np.int64)
    views = [(d, _PLAN_ROLLS_DEG) for d in _PLAN_DIRECTIONS] + [
        (d, _PLAN_ROLLS_DEG[::2]) for d in fibonacci_directions(_PLAN_OBLIQUE)]
    for d, rolls in views:
        f = np.asarray(d)  # looking along f from 3r away
        s0 = np.cross(f, (0.0, 0.0, 1.0) if abs(f[1]) > 0.9 else (0.0, 1.0, 0.0))
        s0 /= np.linalg.norm(s0)
        u0 = np.cross(s0, f)
        for roll in np.radians(rolls):
            s, u = np.cos(roll) * s0 + np.sin(roll) * u0, np.cos(roll) * u0 - np.sin(roll) * s0
            view = np.eye(4)
            view[:3, :3] = np.stack([s, u, -f])
            view[:3, 3] = 3.0 * r * (view[:3, :3] @ f)  # −R·eye with eye = −3r f
            clip = _ortho_clip(view, v, _MARGIN * r, 1.9 * r, 4.1 * r, xp=np)
            for cull in ("back", "front"):  # the front and the back layer
                counts = plan_counts(clip, tris, (side, side), cull=cull)
                windows = np.maximum(windows, counts.windows)
    caps = tuple(capacity_ladder(headroom * int(n) + 16) for n in windows)
    return RasterConfig(TILE_SIZES, caps, (-(-side // 8)) ** 2)


def _gather_samples(obj_i: ObjectGeometry, obj_j: ObjectGeometry, r_i: jax.Array,
                    r_j: jax.Array, g: int, config: Any) -> tuple[jax.Array, ...]:
    """Orthographic pass 1 of sender j along c_i → c_j, box-filtered to g × g samples."""
    ss = SUPERSAMPLE
    side = g * ss
    ci = jnp.asarray(obj_i.centre, jnp.float32)
    cj = jnp.asarray(obj_j.centre, jnp.float32)
    view = look_at(ci, cj)
    frame = view[:3, :3]
    axis = -frame[2]
    dist = jnp.linalg.norm(cj - ci)
    extent = _MARGIN * r_j
    near = dist - 1.1 * r_j
    far = dist + 1.1 * r_j
    verts = jnp.asarray(obj_j.vertices, jnp.float32)
    tris = jnp.asarray(obj_j.triangles, jnp.int32)
    clip = _ortho_clip(view, verts, extent, near, far)
    if config is None:
        config = pass1_config(int(tris.shape[0]), side)
    ras = rasterize(clip, tris, (side, side), cull="back", config=config)
    hit = (ras.tri_id >= 0)
    # barycentrics recomputed from the clip positions (independent of the raster's block list)
    pos = interpolate(verts, ras, tris, clip)
    nrm = _normalize(interpolate(jnp.asarray(obj_j.normals, jnp.float32), ras, tris, clip))
    cos_a = jnp.abs(jnp.sum(nrm * axis, axis=-1))
    texel = (2.0 * extent / side) ** 2
    a = jnp.where(hit, texel / jnp.maximum(cos_a, _MIN_COS), 0.0)  # (side, side)

    def blocks(x: jax.Array) -> jax.Array:
        return x.reshape(g, ss, g, ss, *x.shape[2:]).sum(axis=(1, 3)).reshape(g * g,
                                                                              *x.shape[2:])

    area = blocks(a)
    ok = area > 0.0
    safe = jnp.where(ok, area, 1.0)
    s_pos = jnp.where(ok[:, None], blocks(a[..., None] * pos) / safe[:, None], cj)
    s_nrm = _normalize(jnp.where(ok[:, None], blocks(a[..., None] * nrm), axis))
    hitf = hit.astype(jnp.float32)
    s_cov = blocks(hitf) / (ss * ss)
    height = jnp.sum((pos - cj) * frame[2], -1)
    # the nearest back face behind each front one: where the first solid interval along the
    # axis ends (its depth: 0 where there is none, an open mesh's edge or a single sheet)
    ras_b = rasterize(clip, tris, (side, side), cull="front", config=config)
    height_b = jnp.sum((interpolate(verts, ras_b, tris, clip) - cj) * frame[2], -1)
    depth = jnp.where(hit & (ras_b.tri_id >= 0) & (height_b < height), height - height_b, 0.0)
    # the front surface's slopes per texel step from its triangles' planes, so that a lookup
    # between texel centres extrapolates each tap's own plane (a crease between two faces is
    # kept, where bilinear heights cut it by up to a quarter texel times the change of slope)
    tv = verts[tris]
    fn = _normalize(jnp.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0]))[
        jnp.maximum(ras.tri_id, 0)]  # (side, side, 3)
    m_s, m_u, m_a = (jnp.sum(fn * frame[k], -1) for k in range(3))
    m_a = jnp.where(m_a < 0.0, -1.0, 1.0) * jnp.maximum(jnp.abs(m_a), 1.0 / _MAX_SLOPE)
    tex = 2.0 * extent / side
    slope_col = jnp.where(hit, jnp.clip(-m_s / m_a, -_MAX_SLOPE, _MAX_SLOPE) * tex, 0.0)
    slope_row = jnp.where(hit, jnp.clip(m_u / m_a, -_MAX_SLOPE, _MAX_SLOPE) * tex, 0.0)
    front = jnp.pad(jnp.stack([hitf, jnp.where(hit, height, 0.0), depth, slope_col, slope_row],
                              -1), ((1, 1), (1, 1), (0, 0))).reshape(-1, FRONT_CHANNELS)
    near_i = ci + r_i * _normalize(s_pos - ci)
    s_view = _normalize(near_i - s_pos)
    # samples near j's rim cannot see that point; tilt their view just above the horizon
    # (the receivers that do see them are there)
    s_view = _normalize(s_view + jnp.maximum(0.0, _MIN_COS - jnp.sum(s_view * s_nrm, -1,
                                                                        keepdims=True)) * s_nrm)
    return frame, extent, s_pos, s_nrm, s_view, area, s_cov, front, ras.overflow | ras_b.overflow


def _paper_texels(obj_i: ObjectGeometry, obj_j: ObjectGeometry, t: int, capacity: int,
                  config: Any) -> tuple[jax.Array, ...]:
    """Paper pass 1 (geometry): j seen from c_i through the 90° interreflection camera."""
    cam = interreflection_camera(jnp.asarray(obj_i.centre, jnp.float32),
                                 jnp.asarray(obj_j.centre, jnp.float32), aspect=1.0)
    verts = jnp.asarray(obj_j.vertices, jnp.float32)
    tris = jnp.asarray(obj_j.triangles, jnp.int32)
    clip = project(cam, verts)
    if config is None:
        config = pass1_config(int(tris.shape[0]), t)
    ras = rasterize(clip, tris, (t, t), cull="back", config=config)
    pix = covered_pixels(ras, capacity)
    pos = interpolate_pixels(verts, pix, tris, clip)
    nrm = _normalize(interpolate_pixels(jnp.asarray(obj_j.normals, jnp.float32), pix, tris,
                                        clip))
    return (cam.view_projection, pix.index, pos, nrm, pix.valid,
            ras.overflow | pix.overflow)


def prepare_interreflection(
    objects: Sequence[ObjectGeometry],
    *,
    mode: str = "gather",
    texture_size: int = 128,
    gather_size: int = GATHER_SIZE,
    capacity_fraction: float = 0.35,
    raster_config: Any = None,
) -> IRGeometry:
    """Geometry-only pass 1 of the interreflection (rasterise once, shade many times).

    Args:
        objects: n objects in world space (vertices (V, 3) m, normals, triangles, centre).
        mode: "gather" (orthographic sample grids) or "paper" (eq. 6's 90° perspective views);
            "none" keeps only the pair frames.
        texture_size: paper mode: side of the pass-1 textures (texels).
        gather_size: gather mode: g, samples per side (a power of two, 2..64); the pass-1
            raster is (4g)².
        capacity_fraction: paper mode: covered texels kept per view, as a fraction of
            ``texture_size``² (j subtends at most 26 % of the view for two equal spheres that
            do not intersect); more sets ``overflow``.
        raster_config: :class:`~spectral_fit.geometry.RasterConfig` of the pass-1 rasters
            (default: :func:`pass1_config`).

    Returns:
        :class:`IRGeometry` with P = n(n − 1) pairs. Jit-able (shapes depend only on n,
        the meshes' sizes and the static options).
    """
    _check_mode(mode)
    n = len(objects)
    if n < 1:
        raise InputError("no objects", field="objects")
    texture_size = _check_int(texture_size, "texture_size", 2, 4096)
    gather_size = check_gather_size(gather_size)
    if not 0.0 < capacity_fraction <= 1.0:
        raise InputError(f"must be in (0, 1], got {capacity_fraction!r}",
                         field="capacity_fraction")
    objects = tuple(objects)
    if not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(objects)):
        # called outside a traced function: one compiled program, not an op-by-op dispatch
        # of every step of the rasters (same arithmetic as inside a caller's jit)
        return _pass1_jit(objects, mode=mode, texture_size=texture_size,
                          gather_size=gather_size, capacity_fraction=capacity_fraction,
                          raster_config=raster_config)
    return _pass1(objects, mode, texture_size, gather_size, capacity_fraction, raster_config)


def _pass1(objects: tuple[ObjectGeometry, ...], mode: str, texture_size: int,
           gather_size: int, capacity_fraction: float, raster_config: Any) -> IRGeometry:
    """:func:`prepare_interreflection` after its checks."""
    n = len(objects)
    radii = [_bounding_radius(o) for o in objects]
    pairs = pair_list(n)
    # (paper mode keeps one raster per pair: batched, its raster's conditionals become
    # selects, which is slower)
    if mode == "gather" and len(pairs) > 1 and _same_shapes(objects):
        return _gather_pass1_batched(objects, pairs, radii, gather_size, raster_config,
                                     texture_size)
    cap = max(1, int(math.ceil(capacity_fraction * texture_size * texture_size)))
    cols: dict[str, list[Any]] = {k: [] for k in (
        "centre_i", "centre_j", "radius_i", "radius_j", "frame", "extent", "s_pos", "s_nrm",
        "s_view", "s_area", "s_cov", "s_front", "p_view_proj", "p_index", "p_pos", "p_nrm",
        "p_valid", "overflow")}
    for i, j in pairs:
        oi, oj = objects[i], objects[j]
        cols["centre_i"].append(jnp.asarray(oi.centre, jnp.float32))
        cols["centre_j"].append(jnp.asarray(oj.centre, jnp.float32))
        cols["radius_i"].append(radii[i])
        cols["radius_j"].append(radii[j])
        if mode == "gather":
            frame, extent, sp, sn, sv, sa, sc, sf, of = _gather_samples(
                oi, oj, radii[i], radii[j], gather_size, raster_config)
            for k, v in zip(("s_pos", "s_nrm", "s_view", "s_area", "s_cov", "s_front"),
                            (sp, sn, sv, sa, sc, sf), strict=True):
                cols[k].append(v)
        else:
            frame = look_at(jnp.asarray(oi.centre, jnp.float32),
                            jnp.asarray(oj.centre, jnp.float32))[:3, :3]
            extent = _MARGIN * radii[j]
            of = jnp.asarray(False)
        if mode == "paper":
            vp, idx, pp, pn, pv, of2 = _paper_texels(oi, oj, texture_size, cap, raster_config)
            for k, v in zip(("p_view_proj", "p_index", "p_pos", "p_nrm", "p_valid"),
                            (vp, idx, pp, pn, pv), strict=True):
                cols[k].append(v)
            of = of | of2
        cols["frame"].append(frame)
        cols["extent"].append(extent)
        cols["overflow"].append(of)

    def stack(k: str, shape: tuple[int, ...] = (), dtype: Any = jnp.float32) -> Any:
        if not cols[k]:
            return jnp.zeros((0, *shape), dtype) if k in (
                "centre_i", "centre_j", "radius_i", "radius_j", "frame", "extent") else None
        return jnp.stack(cols[k])

    overflow = jnp.any(jnp.stack(cols["overflow"])) if cols["overflow"] else jnp.asarray(False)
    return IRGeometry(
        centre_i=stack("centre_i", (3,)), centre_j=stack("centre_j", (3,)),
        radius_i=stack("radius_i"), radius_j=stack("radius_j"),
        frame=stack("frame", (3, 3)), extent=stack("extent"),
        s_pos=stack("s_pos"), s_nrm=stack("s_nrm"), s_view=stack("s_view"),
        s_area=stack("s_area"), s_cov=stack("s_cov"), s_front=stack("s_front"),
        p_view_proj=stack("p_view_proj"), p_index=stack("p_index"), p_pos=stack("p_pos"),
        p_nrm=stack("p_nrm"), p_valid=stack("p_valid"),
        overflow=overflow, n_objects=n, mode=mode, texture_size=texture_size,
        gather_size=gather_size,
    )


@eqx.filter_jit
def _pass1_jit(objects: tuple[ObjectGeometry, ...], *, mode: str, texture_size: int,
               gather_size: int, capacity_fraction: float, raster_config: Any) -> IRGeometry:
    return _pass1(objects, mode, texture_size, gather_size, capacity_fraction, raster_config)


def _same_shapes(objects: Sequence[ObjectGeometry]) -> bool:
    """Whether every object's mesh arrays have the first one's shapes (then the pairs' pass-1
    rasters are one batched program)."""
    first = [np.shape(x) for x in jax.tree_util.tree_leaves(objects[0])]
    return all([np.shape(x) for x in jax.tree_util.tree_leaves(o)] == first
               for o in objects[1:])


def _gather_pass1_batched(objects: Sequence[ObjectGeometry], pairs: list[tuple[int, int]],
                          radii: list[jax.Array], g: int, config: Any, texture_size: int
                          ) -> IRGeometry:
    """Gather-mode pass 1 of every pair (i, j) as one ``jax.vmap`` of :func:`_gather_samples`
    over the pairs (meshes of equal shapes): the same samples as one raster per pair, to float
    rounding, in a program with one raster instead of P (a smaller stored program that loads
    sooner; no slower per frame)."""
    senders = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[objects[j] for _, j in pairs])
    c_i = jnp.stack([jnp.asarray(objects[i].centre, jnp.float32) for i, _ in pairs])
    r_i = jnp.stack([radii[i] for i, _ in pairs])
    r_j = jnp.stack([radii[j] for _, j in pairs])

    def one(c: jax.Array, obj_j: ObjectGeometry, a: jax.Array, b: jax.Array) -> tuple:
        obj_i = ObjectGeometry(vertices=obj_j.vertices, normals=obj_j.normals,
                               triangles=obj_j.triangles, centre=c)  # only its centre is used
        return _gather_samples(obj_i, obj_j, a, b, g, config)

    frame, extent, sp, sn, sv, sa, sc, sf, of = jax.vmap(one)(c_i, senders, r_i, r_j)
    return IRGeometry(
        centre_i=c_i, centre_j=jnp.asarray(senders.centre, jnp.float32), radius_i=r_i,
        radius_j=r_j, frame=frame, extent=extent, s_pos=sp, s_nrm=sn, s_view=sv, s_area=sa,
        s_cov=sc, s_front=sf, p_view_proj=None, p_index=None, p_pos=None, p_nrm=None,
        p_valid=None,
        overflow=jnp.any(of), n_objects=len(objects), mode="gather",
        texture_size=texture_size, gather_size=g)
