"""Interreflection between objects: the paper's two-pass eq. (6) ("paper") and a physically
based gather ("gather"), both as radiance to ADD to the environment-only shading of eq. (5).

Both modes split into a geometry-only pass and a shading pass (nvdiffrast style), so a caller
whose geometry is fixed (the fitter) rasterises once and re-shades many times:

    geom = prepare_interreflection(objects, mode="gather")              # rasterise pass 1
    extra = interreflection_from(geom, materials, env, receivers)       # shade, (N, C)

and :func:`interreflection` is the composition. Every array has a static shape (ordered pairs
of objects, pass-1 buffers and sample lists of fixed size), so moving objects never recompiles;
everything is jit-able and differentiable w.r.t. every material parameter.

Pairs. For n objects there are P = n(n − 1) ordered pairs p = (i, j), i the object that
RECEIVES light and j the one that sends it, stored in the order p = i·(n − 1) + k with
j = k for k < i and j = k + 1 otherwise.

"paper" mode — eq. (6) of Mochizuki & Tanaka, literally:

    C(λ) = α I_d S + α T_d(λ, x, y) + {β I_gloss + χ I_mirror} E + γ T_s(λ, x, y).

Pass 1 renders object j with :func:`~spectral_fit.geometry.interreflection_camera` (at c_i,
looking at c_j, up +Y, 90° FOV, aspect 1, ``texture_size``²) into two spectral textures: T_d,
the diffuse-only radiance α_j S_j E_irr/π of j, and T_s, its specular-only radiance
β_j I_gloss + χ_j I_mirror, both shaded with the view direction towards c_i (the pass-1 eye).
Pass 2 projects the receiving fragment x through the same camera and, where the projection is
valid (in front of the eye, inside the view, and the fragment facing j: N·(c_j − x) > 0), adds
α_paper T_d + γ T_s looked up bilinearly at (x, y) (clamp to edge, texels outside j are 0). In
our scaling α_paper = α/π, γ is the material's ``gamma``. There are no bounces.

"gather" mode — our correction (docs/conventions.md). Pass 1 rasterises object j ORTHOGRAPHICALLY
along the axis c_i → c_j (so it covers the whole hemisphere of j that faces i, not only the cap seen
from c_i) at (4g)² and box-filters it into g × g surface samples y (g = ``gather_size``): area A_y,
area-weighted mean position and normal, and coverage. The shading pass then:

1. splits each sample's radiance into a view-independent part (j's diffuse α_j S_j E_irr/π,
   plus what it receives itself on later bounces) and a view-dependent part (gloss and mirror,
   :func:`_specular`: the lobe albedo times the environment prefiltered to the lobe width
   around the mirror direction, plus the bright sources exactly), the latter tabulated towards
   a 3 × 3 grid of directions spanning i's bounding sphere as seen from y;
2. gathers at each receiver x on i, per fragment (no shared projection centre), always with
   j's radiance towards x itself (view direction y → x, not towards the camera):
   - diffuse: α S_i(λ) [Σ_y F(x, y) L_y(→x) − (Σ_y F) ⟨L_env⟩ − hidden sources/π] with the
     point-to-patch form factor F = cos_x cos_y A_y / (π √(r⁴ + (A_y/π)²)) (the midpoint
     rule cos cos A/(π r²) to second order, bounded by cos_x cos_y at contact), L_y(→x) the
     view-independent part plus the view-dependent part interpolated bilinearly on the view
     grid, and ⟨L_env⟩ the cosine-weighted mean of the environment over the cone of j's
     bounding sphere (a small cone quadrature): the light that j hides. The sums run at i's
     own pass-1 samples facing j (pair (j, i)); a receiver projects onto that grid and
     interpolates the ratio of the bracket to the form factor of j's bounding sphere, times
     that form factor at the receiver (``diffuse_at="receivers"``: sums at every receiver);
   - gloss: β A(x) Σ_q w_q h_q [L_j(y_q → x) − L_env(ω_q)] over a quadrature ω_q of the
     receiver's own lobe D F G (V·H)/(N·V) (weights w_q, albedo A), each node ray intersected
     with j's bounding sphere (soft hit h_q, continuous at the silhouette) and j's radiance at
     the hit read from a mip pyramid of the samples (view-independent part, normal) plus
     :func:`_specular` evaluated there towards x;
   - mirror: χ F(n, θr) times the same along R;
3. ``bounces`` > 1: the samples themselves receive step 2 from the other objects' samples
   before the receivers gather (Jacobi iteration of the radiosity-like exchange).

Only receivers whose tangent plane has some of j's bounding sphere above it get anything; the
sum of both modes' terms over j ≠ i is returned. Empty receiver slots (``object == −1``) get 0.

Units: radiance in the environment's unit (bands) or its basis coefficients (coefficient
mode: the S·L product goes through ``env.product_tensor``, as in ``environment.shade``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._runtime.backend import materialise, materialise_each, on_accelerator, prefix_chunks
from ..._runtime.errors import InputError
from ...geometry import (
    TILE_SIZES,
    GBuffer,
    ObjectGeometry,
    RasterConfig,
    capacity_ladder,
    covered_pixels,
    default_config,
    interpolate,
    interpolate_pixels,
    interreflection_camera,
    look_at,
    plan_counts,
    project,
    rasterize,
)
from ...lighting import (
    EnvironmentMap,
    Material,
    atan2_poly,
    bilinear_taps,
    dot3,
    fast_direction_to_uv,
    fast_lookup,
    fresnel_dielectric,
    gloss_integral,
    gloss_split_sum,
    irradiance,
    levels_for,
    lobe_albedo,
    lobe_factor,
    lobe_moment_table,
    microfacet_fdg,
    mirror_radiance,
    select_static,
    sincos_poly,
    smootherstep,
    taps_sum,
    to_map_fast,
    visible_nodes,
)

__all__ = [
    "MODES",
    "IRGeometry",
    "prepare_interreflection",
    "plan_gather_pass1",
    "pass1_config",
    "GatherSenders",
    "gather_senders",
    "gather_receivers",
    "interreflection_from",
    "interreflection",
    "pair_list",
]

MODES = ("gather", "paper", "none")

#: pass-1 supersampling of the gather samples (raster side = SUPERSAMPLE · gather_size)
SUPERSAMPLE = 4
#: default gather size g (samples per side of a sender's grid)
GATHER_SIZE = 16
#: smallest |n·axis| used for the area of a grazing pass-1 texel (caps 1/cos at 20)
_MIN_COS = 0.05
#: the ortho window is the bounding sphere's radius times this
_MARGIN = 1.02
#: lobe-albedo quadrature of the receiver's gloss (radial × azimuthal nodes, scalar only),
#: tabulated at this many cosines per object
_ALBEDO_NODES = (16, 8)
_ALBEDO_TABLE = 33
#: receivers per chunk of the diffuse gather (receivers are sorted by object first)
_CHUNK = 512
#: footprint of a lookup: texel side = this × the lobe footprint std
_FOOTPRINT = 2.5


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


# --------------------------------------------------------------------------------------------
# helpers


def _normalize(v: jax.Array) -> jax.Array:
    return v / jnp.sqrt(jnp.maximum(jnp.sum(v * v, axis=-1, keepdims=True), 1e-30))


def _check_mode(mode: str) -> str:
    if mode not in MODES:
        raise InputError(f"unknown interreflection mode {mode!r}; choose one of {MODES}",
                         field="mode")
    return mode


def _check_int(value: Any, name: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or not (
            lo <= int(value) <= hi):
        raise InputError(f"must be an integer in {lo}..{hi}, got {value!r}", field=name)
    return int(value)


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
    since at most half its faces are front faces; T/4 + 16 plus four tilings of the target
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


def plan_gather_pass1(vertices: Any, triangles: Any, *, gather_size: int = GATHER_SIZE,
                      headroom: float = 1.5) -> RasterConfig:
    """Window capacities of the gather pass-1 raster of one sender mesh, for any pose.

    The pass-1 view is orthographic and framed on the sender's bounding sphere
    (:func:`_gather_samples`), so what it needs depends on the mesh and the view direction
    in the mesh's own frame only, not on distances or positions: counted
    (:func:`~spectral_fit.geometry.plan_counts`, NumPy) along the six axes of that frame, each
    at four rolls (once per distinct mesh), and sized ``headroom`` × the maximum (+16, on
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
    for d in _PLAN_DIRECTIONS:
        f = np.asarray(d)  # looking along f from 3r away
        s0 = np.cross(f, (0.0, 0.0, 1.0) if abs(f[1]) > 0.9 else (0.0, 1.0, 0.0))
        s0 /= np.linalg.norm(s0)
        u0 = np.cross(s0, f)
        for roll in np.radians(_PLAN_ROLLS_DEG):
            s, u = np.cos(roll) * s0 + np.sin(roll) * u0, np.cos(roll) * u0 - np.sin(roll) * s0
            view = np.eye(4)
            view[:3, :3] = np.stack([s, u, -f])
            view[:3, 3] = 3.0 * r * (view[:3, :3] @ f)  # −R·eye with eye = −3r f
            clip = _ortho_clip(view, v, _MARGIN * r, 1.9 * r, 4.1 * r, xp=np)
            counts = plan_counts(clip, tris, (side, side), cull="back")
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
    s_cov = blocks(hit.astype(jnp.float32)) / (ss * ss)
    near_i = ci + r_i * _normalize(s_pos - ci)
    s_view = _normalize(near_i - s_pos)
    # samples near j's rim cannot see that point; tilt their view just above the horizon
    # (the receivers that do see them are there)
    s_view = _normalize(s_view + jnp.maximum(0.0, _MIN_COS - jnp.sum(s_view * s_nrm, -1,
                                                                        keepdims=True)) * s_nrm)
    return frame, extent, s_pos, s_nrm, s_view, area, s_cov, ras.overflow


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


# --------------------------------------------------------------------------------------------
# pass 1 (geometry only)


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
    gather_size = _check_int(gather_size, "gather_size", 2, 64)
    if gather_size & (gather_size - 1):
        raise InputError(f"must be a power of two, got {gather_size}", field="gather_size")
    if not 0.0 < capacity_fraction <= 1.0:
        raise InputError(f"must be in (0, 1], got {capacity_fraction!r}",
                         field="capacity_fraction")
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
        "s_view", "s_area", "s_cov", "p_view_proj", "p_index", "p_pos", "p_nrm", "p_valid",
        "overflow")}
    for i, j in pairs:
        oi, oj = objects[i], objects[j]
        cols["centre_i"].append(jnp.asarray(oi.centre, jnp.float32))
        cols["centre_j"].append(jnp.asarray(oj.centre, jnp.float32))
        cols["radius_i"].append(radii[i])
        cols["radius_j"].append(radii[j])
        if mode == "gather":
            frame, extent, sp, sn, sv, sa, sc, of = _gather_samples(
                oi, oj, radii[i], radii[j], gather_size, raster_config)
            for k, v in zip(("s_pos", "s_nrm", "s_view", "s_area", "s_cov"),
                            (sp, sn, sv, sa, sc), strict=True):
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
        s_area=stack("s_area"), s_cov=stack("s_cov"),
        p_view_proj=stack("p_view_proj"), p_index=stack("p_index"), p_pos=stack("p_pos"),
        p_nrm=stack("p_nrm"), p_valid=stack("p_valid"),
        overflow=overflow, n_objects=n, mode=mode, texture_size=texture_size,
        gather_size=gather_size,
    )


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

    frame, extent, sp, sn, sv, sa, sc, of = jax.vmap(one)(c_i, senders, r_i, r_j)
    return IRGeometry(
        centre_i=c_i, centre_j=jnp.asarray(senders.centre, jnp.float32), radius_i=r_i,
        radius_j=r_j, frame=frame, extent=extent, s_pos=sp, s_nrm=sn, s_view=sv, s_area=sa,
        s_cov=sc, p_view_proj=None, p_index=None, p_pos=None, p_nrm=None, p_valid=None,
        overflow=jnp.any(of), n_objects=len(objects), mode="gather",
        texture_size=texture_size, gather_size=g)


# --------------------------------------------------------------------------------------------
# materials per receiver


def _stack_materials(materials: Sequence[Material]) -> dict[str, jax.Array]:
    return {k: jnp.stack([jnp.asarray(getattr(m, k)) for m in materials])
            for k in ("alpha", "beta", "chi", "mu", "n", "gamma", "reflectance")}


def _times_reflectance(env: EnvironmentMap, s: jax.Array, x: jax.Array) -> jax.Array:
    """S ⊙ X per row (bands), or the basis product (coefficients)."""
    if env.product_tensor is None:
        return s * x
    return jnp.einsum("...i,...j,ijk->...k", s, x, env.product_tensor)


def _albedo_tables(materials: Sequence[Material]) -> jax.Array:
    """(n, T) receiver lobe albedos A(cosθr) = ∫ D F G (V·H)/(N·V) dω_H per object, at
    ``_ALBEDO_TABLE`` cosines in [0, 1], with the object's μ, n, D and G (differentiable)."""
    nodes = np.linspace(0.0, 1.0, _ALBEDO_TABLE)
    nodes[0] = 1e-3
    rows = []
    for m in materials:
        rows.append(jax.vmap(lambda c, m=m: lobe_albedo(
            c, m.mu, m.n, m.mu, distribution=m.distribution, geometry=m.geometry,
            fresnel=True, radial=_ALBEDO_NODES[0], azimuthal=_ALBEDO_NODES[1]))(
                jnp.asarray(nodes, jnp.result_type(m.mu, jnp.float32))))
    return jnp.stack(rows)


def _albedo_at(table: jax.Array, obj: jax.Array, nv: jax.Array) -> jax.Array:
    """Lobe albedo (...) of object ``obj`` at cosθr ``nv``: :func:`_albedo_tables` interpolated
    linearly in cosθr."""
    size = table.shape[1]
    x = jnp.clip(nv, 0.0, 1.0) * (size - 1)
    i0 = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, size - 2)
    f = x - i0.astype(x.dtype)
    flat = table.reshape(-1)
    base = jnp.maximum(obj, 0) * size + i0
    return (1.0 - f) * flat[base] + f * flat[base + 1]


# --------------------------------------------------------------------------------------------
# gather mode
#
# Every per-point quantity is computed batched and by components (no per-point vmapped
# gathers, no arctan2/arccos per lookup, unrolled tap sums: XLA:CPU runs those as slow loops,
# see docs/rendering.md), and everything that comes from the environment alone (the senders'
# gloss, the hidden environment) stays in the map's r principal channels
# (``env.spectral_basis``) until it has been summed.


def _mip_levels(g: int) -> list[int]:
    sizes = [g]
    while sizes[-1] > 1:
        sizes.append(sizes[-1] // 2)
    return sizes


def _mip_layout(g: int) -> tuple[list[int], list[int], int]:
    """Sizes, offsets and total texels per pair of the padded mip atlas of a g × g grid."""
    sizes = _mip_levels(g)
    offs = [int(o) for o in np.cumsum([0] + [(s + 2) ** 2 for s in sizes])]
    return sizes, offs[:-1], offs[-1]


def _build_mips(values: jax.Array, g: int) -> jax.Array:
    """(P, g², C) premultiplied texels → (P·T, C) atlas of all mip levels of every pair (T
    texels per pair), each level padded by a one-texel zero border (so bilinear lookups fade
    to 0 outside j)."""
    p, _, c = values.shape
    # computed once into memory: otherwise XLA:CPU fuses the texels' whole expression (a
    # bounce's lum: the samples' gather and its interpolation) into every level's reduction
    # and evaluates it again there, g² times for the 1 × 1 level
    lev = materialise(values, cut=True).reshape(p, g, g, c)
    flat = []
    for s in _mip_levels(g):
        if lev.shape[1] != s:
            lev = lev.reshape(p, s, 2, s, 2, c).mean(axis=(2, 4))
            if on_accelerator():
                # each level from the stored previous one: fused into the atlas's one
                # kernel, the 1 × 1 level's thread summed all g² texels alone
                lev = jax.lax.optimization_barrier(lev)
        flat.append(jnp.pad(lev, ((0, 0), (1, 1), (1, 1), (0, 0))).reshape(p, -1, c))
    return jnp.concatenate(flat, axis=1).reshape(-1, c)


def _mip_taps(pair: jax.Array, tx: jax.Array, ty: jax.Array, level: jax.Array, g: int
              ) -> tuple[jax.Array, jax.Array]:
    """Atlas rows (..., 8) and weights (..., 8) of the trilinear lookup of pair ``pair``'s mip
    atlas (:func:`_build_mips`) at level-0 texel coordinates (tx, ty) (texel centres at
    integer + 0.5) and fractional ``level`` (clamped); C¹ smoothstep weights within and across
    levels (gradients). Elementwise in all arguments."""
    sizes, offs, per_pair = _mip_layout(g)
    nl = len(sizes)
    level = jnp.clip(level, 0.0, nl - 1.0)
    lo = jnp.minimum(jnp.floor(level).astype(jnp.int32), nl - 1)
    hi = jnp.minimum(lo + 1, nl - 1)
    wh = smootherstep(level - lo.astype(level.dtype))
    idx, wts = [], []
    for lev, wl in ((lo, 1.0 - wh), (hi, wh)):
        si = select_static([np.int32(s) for s in sizes], lev)
        scale = select_static([np.float32(s / g) for s in sizes], lev).astype(tx.dtype)
        base = pair * per_pair + select_static([np.int32(o) for o in offs], lev)
        x = tx * scale + 0.5  # −0.5 (texel centres) + 1 (border)
        y = ty * scale + 0.5
        x0f, y0f = jnp.floor(x), jnp.floor(y)
        fx, fy = smootherstep(x - x0f), smootherstep(y - y0f)
        x0 = jnp.clip(x0f.astype(jnp.int32), 0, si + 1)
        y0 = jnp.clip(y0f.astype(jnp.int32), 0, si + 1)
        x1 = jnp.minimum(x0 + 1, si + 1)
        y1 = jnp.minimum(y0 + 1, si + 1)
        row = si + 2
        idx += [base + y0 * row + x0, base + y0 * row + x1, base + y1 * row + x0,
                base + y1 * row + x1]
        wts += [wl * (1 - fy) * (1 - fx), wl * (1 - fy) * fx, wl * fy * (1 - fx), wl * fy * fx]
    return jnp.stack(idx, -1), jnp.stack(wts, -1)


def _env_blur(env: EnvironmentMap, dirs: jax.Array, sigma: jax.Array) -> jax.Array:
    """Environment radiance (..., r) along world unit directions ``dirs`` (..., 3), prefiltered
    to angular std ``sigma`` (...) (radians; the residual map without its bright sources), in
    the r channels of ``env.spectral_basis``: two adjacent prefiltered levels blended, eight
    bilinear taps gathered at once."""
    lead = dirs.shape[:-1]
    d = to_map_fast(env, dirs.reshape(-1, 3))
    u, v = fast_direction_to_uv(d)
    u, v = materialise_each(u, v)
    lo, hi, w_hi, _ = levels_for(env, jnp.broadcast_to(sigma, lead).reshape(-1))
    shapes = env.level_shapes
    levels = []
    for lev in (lo, hi):
        levels += [select_static([np.int32(h) for h, _ in shapes], lev),
                   select_static([np.int32(w) for _, w in shapes], lev),
                   select_static([np.int32(o) for o in env.level_offsets], lev)]
    # computed once per lookup: fused into the taps, the select chains would run once per
    # tap and per index/weight array
    levels = materialise_each(*levels)
    idx, wts = [], []
    for k, wl in ((0, 1.0 - w_hi), (1, w_hi)):
        hk, wk, off = levels[3 * k:3 * k + 3]
        i, w = bilinear_taps(u, v, off, hk, wk, lead=True)
        idx.append(i)
        wts.append(w * wl)
    out = taps_sum(env.atlas, jnp.concatenate(idx, 0), jnp.concatenate(wts, 0), lead=True)
    return out.reshape(*lead, -1)


def _source_terms(env: EnvironmentMap) -> tuple[jax.Array, jax.Array] | None:
    """World directions (S·k, 3) and flux (S·k, r) (``env.spectral_basis`` channels) of the
    environment's bright-source sub-points (None without sources)."""
    if not env.source_flux.shape[0]:
        return None
    k = env.source_dirs.shape[1]
    sdir = env.source_dirs.reshape(-1, 3) @ env.rotation.T
    return sdir, jnp.repeat(env.source_flux, k, axis=0)


def _gloss_weights(nrm: jax.Array, view: jax.Array, light: jax.Array, mu: jax.Array,
                   eta: jax.Array, distribution: str, geometry: str) -> jax.Array:
    """F D G / (4 cosθr) (the gloss BRDF times cosθi) for unit vectors (..., 3) (broadcast),
    0 unless both directions are above the surface."""
    fdg, nv, nl = microfacet_fdg(nrm, view, light, mu, eta, distribution, geometry)
    ok = (nl > 0.0) & (nv > 0.0)
    return jnp.where(ok, fdg / (4.0 * jnp.where(ok, nv, 1.0)), 0.0)


class _Shading(eqx.Module):
    """Per-call shading context of the gather: the objects' materials (stacked per object and
    as given), the environment, and the receivers' lobe-albedo tables."""

    mats: dict[str, jax.Array]
    env: EnvironmentMap
    albedo: jax.Array
    materials: tuple[Material, ...]
    mirror: bool = eqx.field(static=True)
    #: (C, D) linear map into the caller's output channels (None: the C channels)
    output: jax.Array | None = None

    @property
    def basis(self) -> jax.Array:
        """(r, D) the environment's principal channels → the output channels."""
        b = self.env.spectral_basis
        return b if self.output is None else b @ self.output

    @property
    def channels(self) -> int:
        """D: the number of output channels."""
        return self.env.channels if self.output is None else self.output.shape[1]

    def to_output(self, x: jax.Array) -> jax.Array:
        """(..., C) radiance → (..., D) output channels."""
        return x if self.output is None else x @ self.output

    def diffuse_matrices(self) -> jax.Array:
        """(n, C, D) per object: net diffuse light (C) → α S(λ) ⊙ net in the output channels
        (bands: α diag(S) M; coefficients: through the basis product tensor)."""
        mats = self.mats
        out = (jnp.eye(self.env.channels, dtype=jnp.float32) if self.output is None
               else self.output)
        s = mats["reflectance"]
        if self.env.product_tensor is None:
            m = s[:, :, None] * out[None]
        else:
            m = jnp.einsum("oi,ijk,kd->ojd", s, self.env.product_tensor, out)
        return mats["alpha"][:, None, None] * m


def _shading(materials: Sequence[Material], env: EnvironmentMap) -> _Shading:
    return _Shading(mats=_stack_materials(materials), env=env,
                    albedo=_albedo_tables(materials), materials=tuple(materials),
                    mirror=any(not _is_zero(m.chi) for m in materials))


def _specular(sh: _Shading, obj: jax.Array, nrm: jax.Array, view: jax.Array
              ) -> tuple[jax.Array, jax.Array | None]:
    """View-dependent radiance of object ``obj`` (K,) at normals ``nrm`` towards ``view``
    (K, 3): the gloss β (A(cosθr) L_σ(R) + Σ_sources F D G/(4cosθr) Φ) (K, r) in the r channels
    of ``env.spectral_basis``, and the mirror χ F(θr) L(R) (K, C) (None when every χ is a
    concrete 0).

    The gloss is the split-sum reading of eq. (5)'s gloss term: the lobe's directional albedo A
    (tabulated per object) times the environment prefiltered to the lobe's width
    σ = √2 μ √cosθr around the mirror direction R (within ±20 % of the full quadrature of
    :func:`~spectral_fit.lighting.gloss_integral` at grazing angles, a few % near the
    normal; unbiased on average), so that a neighbour's gloss can be evaluated towards every
    receiver point instead of towards one."""
    mats = sh.mats
    o = jnp.maximum(obj, 0)
    beta, chi, mu, eta = mats["beta"][o], mats["chi"][o], mats["mu"][o], mats["n"][o]
    nv = dot3(nrm, view)
    nvc = jnp.clip(nv, 0.0, 1.0)
    refl = 2.0 * nv[:, None] * nrm - view
    albedo = _albedo_at(sh.albedo, obj, nv)
    sigma = math.sqrt(2.0) * mu * jnp.sqrt(jnp.maximum(nvc, 0.05))
    gloss = albedo[:, None] * _env_blur(sh.env, refl, sigma)
    src = _source_terms(sh.env)
    if src is not None:
        sdir, sflux = src
        for k, m in enumerate(sh.materials):
            w = _gloss_weights(nrm[:, None], view[:, None], sdir[None], mu[:, None],
                               eta[:, None], m.distribution, m.geometry)
            gloss = gloss + jnp.where((o == k)[:, None], w @ sflux, 0.0)
    # faded out over the last few degrees above the horizon (continuous in N and V, so the
    # neighbour's silhouette does not switch it on and off)
    fade = smootherstep(nv / _HORIZON_FADE)
    out = (beta * fade)[:, None] * gloss
    mirror = None
    if sh.mirror:
        mirror = (chi * fresnel_dielectric(nvc, eta) * fade)[:, None] * fast_lookup(sh.env,
                                                                                 refl)
    return out, mirror


def _is_zero(x: Any) -> bool:
    """True only for a concrete zero (a traced value may be anything)."""
    try:
        return bool(np.all(np.asarray(x) == 0.0))
    except (TypeError, jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError):
        return False


#: cosθr below which a neighbour's view-dependent radiance fades to 0 at its horizon
_HORIZON_FADE = 0.05

#: the neighbour's view-dependent radiance is tabulated per sample towards a 3 × 3 grid of
#: directions spanning the receiver's bounding sphere (gnomonic coordinates in −1, 0, 1 × tanθc)
_VIEW_GRID = (-1.0, 0.0, 1.0)


def _view_frames(geom: IRGeometry) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Per sample (P, M): the unit axis a towards the receiver's centre, a tangent frame e1, e2,
    and T = tanθc of the receiver's bounding sphere seen from the sample."""
    to_c = geom.centre_i[:, None, :] - geom.s_pos
    dist = jnp.sqrt(jnp.maximum(jnp.sum(to_c * to_c, -1), 1e-30))
    a = to_c / dist[..., None]
    s = geom.frame[:, None, 0, :]
    e1 = _normalize(s - jnp.sum(s * a, -1, keepdims=True) * a)
    e2 = jnp.cross(a, e1)
    sin_c = jnp.clip(geom.radius_i[:, None] / dist, 0.05, 0.95)
    return a, e1, e2, sin_c / jnp.sqrt(1.0 - sin_c * sin_c)


def _sample_specular(geom: IRGeometry, sh: _Shading, frames: tuple[jax.Array, ...]
                     ) -> tuple[jax.Array, jax.Array | None]:
    """Each sample's view-dependent radiance towards the 3 × 3 view grid: gloss (P, M, 9, r)
    in the map's r channels and mirror (P, M, 9, C) (or None)."""
    a, e1, e2, tan_c = frames
    p_count, m_count = geom.s_area.shape
    senders = np.asarray([j for _, j in geom.pairs], np.int32)
    views = []
    for gu in _VIEW_GRID:
        for gv in _VIEW_GRID:
            views.append(_normalize(a + tan_c[..., None] * (gu * e1 + gv * e2)))
    v = jnp.stack(views, 2)  # (P, M, 9, 3)
    nrm = jnp.broadcast_to(geom.s_nrm[:, :, None], v.shape)
    # views below a rim sample's horizon: evaluated just above it
    v = _normalize(v + jnp.maximum(0.0, _MIN_COS - jnp.sum(v * nrm, -1, keepdims=True)) * nrm)
    obj = jnp.broadcast_to(jnp.asarray(senders)[:, None, None], v.shape[:3])
    g, m = _specular(sh, obj.reshape(-1), nrm.reshape(-1, 3), v.reshape(-1, 3))
    shape = (p_count, m_count, len(_VIEW_GRID) ** 2)
    live = (geom.s_area > 0)[..., None, None]
    g = jnp.where(live, g.reshape(*shape, -1), 0.0)
    if m is not None:
        m = jnp.where(live, m.reshape(*shape, -1), 0.0)
    return g, m


def _tents(x: jax.Array) -> list[jax.Array]:
    """Linear interpolation weights of x ∈ [−1, 1] on the nodes −1, 0, 1."""
    x = jnp.clip(x, -1.0, 1.0)
    return [jnp.maximum(-x, 0.0), 1.0 - jnp.abs(x), jnp.maximum(x, 0.0)]


class _Senders(eqx.Module):
    """The senders' samples as seen by the gather: per pair (P, M, ...) position, normal, area,
    view frames (axis, e1, e2, tanθc), view-independent radiance (C) and view-dependent gloss
    (9 view directions, r channels) and mirror (9, C, or None)."""

    pos: jax.Array
    nrm: jax.Array
    area: jax.Array
    frames: tuple[jax.Array, ...]
    lum: jax.Array
    spec: jax.Array
    mirror: jax.Array | None


def _form_factor_block(x: jax.Array, nx: jax.Array, snd: tuple[jax.Array, ...]
                       ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Point-to-patch form factors F (..., R, S) = cos_x cos_y A/(π √(r⁴ + (A/π)²)) between
    receivers (x, nx (..., R, 3)) and sender samples ``snd`` = (pos, nrm, area, axis, e1, e2,
    tanθc) (..., S, ...), and the view-grid tents (u, v: 3 each) of the direction y → x in each
    sample's view frame. Computed by components (elementwise, fused)."""
    ypos, ynrm, yarea, fa, fe1, fe2, ftan = snd
    d = [ypos[..., None, :, c] - x[..., :, None, c] for c in range(3)]  # y − x
    r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    cx = sum(nx[..., :, None, c] * d[c] for c in range(3))
    cy = -sum(ynrm[..., None, :, c] * d[c] for c in range(3))
    a = yarea[..., None, :] / math.pi
    w = jnp.maximum(cx, 0.0) * jnp.maximum(cy, 0.0) * a / jnp.maximum(
        r2 * jnp.sqrt(r2 * r2 + a * a), 1e-30)
    # view-dependent part: gnomonic coordinates of the direction y → x in y's view frame
    along = -sum(fa[..., None, :, c] * d[c] for c in range(3))
    den = jnp.maximum(along, 1e-9) * ftan[..., None, :]
    tu = _tents(-sum(fe1[..., None, :, c] * d[c] for c in range(3)) / den)
    tv = _tents(-sum(fe2[..., None, :, c] * d[c] for c in range(3)) / den)
    return w, tu, tv


def _transfer(w: jax.Array, tu: list[jax.Array], tv: list[jax.Array], lum: jax.Array,
              spec: jax.Array, mirror: jax.Array | None, basis: jax.Array
              ) -> tuple[jax.Array, jax.Array]:
    """Σ_y F L_y(→x) (..., R, C) and Σ_y F (..., R): the senders' view-independent radiance
    ``lum`` (..., S, C) plus their view-dependent part (``spec`` (..., S, 9, r), ``mirror``
    (..., S, 9, C)) interpolated on the view grid, weighted by the form factors ``w``."""
    ein = "...rs,...sc->...rc"
    lsum = jnp.einsum(ein, w, lum)
    ws = jnp.concatenate([w * tu[iu] * tv[iv] for iu in range(3) for iv in range(3)], -1)
    sp = jnp.swapaxes(spec, -3, -2).reshape(*spec.shape[:-3], -1, spec.shape[-1])
    lsum = lsum + jnp.einsum(ein, ws, sp) @ basis
    if mirror is not None:
        mp = jnp.swapaxes(mirror, -3, -2).reshape(*mirror.shape[:-3], -1, mirror.shape[-1])
        lsum = lsum + jnp.einsum(ein, ws, mp)
    return lsum, jnp.sum(w, -1)


#: cone quadrature of the environment a neighbour hides: rings (uniform in solid angle) ×
#: azimuths
_CONE_NODES = (2, 6)


def _hidden_mean(geom: IRGeometry, env: EnvironmentMap, pos: jax.Array, nrm: jax.Array,
                 o: jax.Array) -> jax.Array:
    """Cosine-weighted mean environment radiance (N, r) (map channels) over the cones of the
    receivers' neighbours' bounding spheres (above the receiver's horizon): the radiance the
    neighbours hide, per unit of their form factor. Nodes: ``_CONE_NODES`` rings × azimuths
    uniform in solid angle, the map prefiltered to the node spacing."""
    k_per = geom.n_objects - 1
    nr, na = _CONE_NODES
    ur = (np.arange(nr) + 0.5) / nr
    ph = 2.0 * np.pi * (np.arange(na) + 0.5 * (np.arange(nr)[:, None] % 2)) / na  # (nr, na)
    num = jnp.zeros((pos.shape[0], env.atlas.shape[-1]), pos.dtype)
    den = jnp.zeros((pos.shape[0],), pos.dtype)
    for k in range(k_per):
        pair = o * k_per + k
        oc = geom.centre_j[pair] - pos
        d = jnp.sqrt(jnp.maximum(jnp.sum(oc * oc, -1), 1e-30))
        a = oc / d[:, None]
        sin_c = jnp.clip(geom.radius_j[pair] / d, 1e-3, 0.999)
        cos_c = jnp.sqrt(1.0 - sin_c * sin_c)
        t1 = _normalize(jnp.cross(a, jnp.where(jnp.abs(a[:, 1:2]) < 0.9,
                                               jnp.array([0.0, 1.0, 0.0]),
                                               jnp.array([1.0, 0.0, 0.0]))))
        t2 = jnp.cross(a, t1)
        u = 1.0 - (1.0 - cos_c)[:, None] * jnp.asarray(ur, pos.dtype)[None]  # (N, nr)
        s = jnp.sqrt(jnp.maximum(1.0 - u * u, 0.0))
        cp = jnp.asarray(np.cos(ph), pos.dtype)
        sp = jnp.asarray(np.sin(ph), pos.dtype)
        dirs = (u[..., None, None] * a[:, None, None]
                + s[..., None, None] * (cp[None, ..., None] * t1[:, None, None]
                                        + sp[None, ..., None] * t2[:, None, None]))
        dirs = dirs.reshape(pos.shape[0], -1, 3)
        w = jnp.maximum(dot3(dirs, nrm[:, None]), 0.0) * (1.0 - cos_c)[:, None]
        spacing = atan2_poly(sin_c, cos_c) / (2.0 * nr)
        # the lookups computed once and summed node by node: a reduction over the nodes
        # fused the lookups' taps into every channel's sum
        lv = materialise(_env_blur(env, dirs, jnp.broadcast_to(spacing[:, None], w.shape)),
                         cut=True)
        num = num + sum(w[:, q, None] * lv[:, q] for q in range(w.shape[1]))
        den = den + jnp.sum(w, -1)
    return num / jnp.maximum(den, 1e-30)[:, None]


def _hidden_sources(geom: IRGeometry, env: EnvironmentMap, pos: jax.Array, o: jax.Array
                    ) -> jax.Array | None:
    """(N, S·k) 1 where a bright-source sub-point's direction hits a neighbour's bounding
    sphere seen from ``pos`` (None without sources)."""
    src = _source_terms(env)
    if src is None:
        return None
    sdir = src[0]
    occ = jnp.zeros((pos.shape[0], sdir.shape[0]), pos.dtype)
    for k in range(geom.n_objects - 1):
        pair = o * (geom.n_objects - 1) + k
        oc = geom.centre_j[pair] - pos
        tp = oc @ sdir.T
        miss2 = jnp.sum(oc * oc, -1)[:, None] - tp * tp
        occ = jnp.maximum(occ, ((tp > 0.0) & (miss2 < geom.radius_j[pair][:, None] ** 2)
                                ).astype(pos.dtype))
    return occ


def _diffuse_net(geom: IRGeometry, env: EnvironmentMap, lsum: jax.Array, fsum: jax.Array,
                 pos: jax.Array, nrm: jax.Array, o: jax.Array) -> jax.Array:
    """The light the neighbours add at receivers, before the receiver's α S/π (N, C):
    Σ_y F L_y(→x) − (Σ_y F) ⟨L_env⟩_hidden − (1/π) Σ hidden sources flux max(0, N·d_s)."""
    hm = _hidden_mean(geom, env, pos, nrm, o)
    net = lsum - fsum[:, None] * (hm @ env.spectral_basis)
    occ = _hidden_sources(geom, env, pos, o)
    if occ is not None:
        sdir, sflux = _source_terms(env)
        cosn = jnp.maximum(nrm @ sdir.T, 0.0)
        net = net - ((occ * cosn) @ sflux) @ env.spectral_basis / math.pi
    return net


def _sample_diffuse_net(geom: IRGeometry, snd: _Senders, env: EnvironmentMap) -> jax.Array:
    """:func:`_diffuse_net` (P, M, C) at every sample, gathered from all samples of the
    sample's own object's neighbours (dense, batched over pairs: P × M × (n − 1)M form
    factors)."""
    n_obj = geom.n_objects
    k_per = n_obj - 1
    p_count, m_count = geom.s_area.shape
    recv = np.asarray([j for _, j in geom.pairs], np.int32)  # the samples' own object
    src = (recv[:, None] * k_per + np.arange(k_per)[None, :])  # (P, k_per) sender pairs

    def senders(x: jax.Array) -> jax.Array:
        s = x[src]  # (P, k_per, M, ...)
        return s.reshape(p_count, k_per * m_count, *x.shape[2:])

    origin = jnp.mean(geom.centre_j, axis=0)
    blk = (senders(snd.pos - origin), senders(snd.nrm), senders(snd.area),
           *(senders(f) for f in snd.frames))
    w, tu, tv = _form_factor_block(geom.s_pos - origin, geom.s_nrm, blk)
    lsum, fsum = _transfer(w, tu, tv, senders(snd.lum), senders(snd.spec),
                           None if snd.mirror is None else senders(snd.mirror),
                           env.spectral_basis)
    obj = jnp.asarray(np.repeat(recv, m_count), jnp.int32)
    net = _diffuse_net(geom, env, lsum.reshape(-1, lsum.shape[-1]), fsum.reshape(-1),
                       geom.s_pos.reshape(-1, 3), geom.s_nrm.reshape(-1, 3), obj)
    return net.reshape(p_count, m_count, -1)


def _reverse_pairs(n: int) -> np.ndarray:
    """Index of pair (j, i) for every pair p = (i, j) (storage order of :func:`pair_list`)."""
    index = {pq: k for k, pq in enumerate(pair_list(n))}
    return np.asarray([index[(j, i)] for i, j in pair_list(n)], np.int32)


def _sphere_form_factor(pos: jax.Array, nrm: jax.Array, centre: jax.Array, radius: jax.Array
                        ) -> jax.Array:
    """Form factor (...) from a differential area (pos, unit nrm (..., 3)) to a sphere
    (centre (..., 3), radius (...)): sin²α cosθ while the sphere is wholly above the tangent
    plane (sinα = r/d, θ the centre's angle from the normal), and the C¹ horizon-clipped
    approximation sin²α (cosθ + sinα)²/(4 sinα) while it straddles it."""
    oc = centre - pos
    d2 = jnp.maximum(dot3(oc, oc), 1e-30)
    sin2 = jnp.minimum(radius * radius / d2, 1.0)
    sin_a = jnp.sqrt(sin2)
    cos_t = dot3(nrm, oc) * jax.lax.rsqrt(d2)
    part = (cos_t + sin_a) ** 2 / (4.0 * jnp.maximum(sin_a, 1e-12))
    return sin2 * jnp.where(cos_t >= sin_a, cos_t, jnp.where(cos_t > -sin_a, part, 0.0))


def _net_tables(geom: IRGeometry, net: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The two tables :func:`_interpolate_net` interpolates, from the samples' diffuse net
    light ``net`` (P, M, C): net × coverage (P·(g + 2)², C) and coverage × the form factor of
    the neighbour's bounding sphere (P·(g + 2)², 1), each pair's g × g grid with a border of
    zeros (made once per frame, not per chunk of receivers)."""
    g = geom.gather_size
    p_count = net.shape[0]
    # pair q = (j, i) holds samples on i; the sphere they look at is j's (centre_i[q])
    ff_s = _sphere_form_factor(geom.s_pos, geom.s_nrm, geom.centre_i[:, None],
                               geom.radius_i[:, None])
    cov = geom.s_cov * (geom.s_area > 0)

    # Σ w cov F_s (net_s/F_s) / Σ w cov F_s
    def table(x: jax.Array) -> jax.Array:
        x = x.reshape(p_count, g, g, x.shape[-1])
        return jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0))).reshape(-1, x.shape[-1])

    # two tables, each tap sum consumed whole (slicing one (N, C + 1) tap sum made XLA gather
    # every tap of every channel into memory first)
    return table(net * cov[..., None]), table((cov * ff_s)[..., None])


def _interpolate_net(geom: IRGeometry, net: jax.Array | None, pos: jax.Array, nrm: jax.Array,
                     obj: jax.Array, tables: tuple[jax.Array, jax.Array] | None = None
                     ) -> jax.Array:
    """The samples' diffuse net light (P, M, C) at receivers on the samples' objects (N, C)
    (``tables``: :func:`_net_tables` of ``net``, when made already).

    For each neighbour j of the receiver's object i, the receiver is projected orthographically
    along j → i onto the g × g samples of i that face j (pair (j, i)); there the ratio of the
    net light to the form factor F_j of j's bounding sphere (:func:`_sphere_form_factor`, the
    geometric part, which varies fast next to j) is interpolated bilinearly, weighted by
    coverage × F_j (so each sample stands for its covered part and samples that barely see j
    count little), and multiplied by F_j at the receiver. Receivers facing several neighbours
    blend their grids with weights ∝ N·(c_j − c_i)⁺ (each grid holds the light from all
    neighbours)."""
    g = geom.gather_size
    k_per = geom.n_objects - 1
    tex, tex_w = _net_tables(geom, net) if tables is None else tables
    c = tex.shape[-1]
    rev = jnp.asarray(_reverse_pairs(geom.n_objects))
    o = jnp.maximum(obj, 0)
    acc = jnp.zeros((pos.shape[0], c), tex.dtype)
    wsum = jnp.zeros((pos.shape[0],), tex.dtype)
    for k in range(k_per):
        q = rev[o * k_per + k]  # pair (j, i): samples on i facing j
        fr = geom.frame[q]
        rel = pos - geom.centre_j[q]
        ext = geom.extent[q]
        tx = (dot3(rel, fr[:, 0]) / ext + 1.0) * 0.5 * g + 0.5  # +1 border −0.5 centres
        ty = (1.0 - dot3(rel, fr[:, 1]) / ext) * 0.5 * g + 0.5
        x0f, y0f = jnp.floor(tx), jnp.floor(ty)
        fx, fy = tx - x0f, ty - y0f
        x0 = jnp.clip(x0f.astype(jnp.int32), 0, g + 1)
        y0 = jnp.clip(y0f.astype(jnp.int32), 0, g + 1)
        x1 = jnp.minimum(x0 + 1, g + 1)
        y1 = jnp.minimum(y0 + 1, g + 1)
        base = q * (g + 2) ** 2
        row = g + 2
        idx = jnp.stack([base + y0 * row + x0, base + y0 * row + x1, base + y1 * row + x0,
                         base + y1 * row + x1], -1)
        w = jnp.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], -1)
        ff = _sphere_form_factor(pos, nrm, geom.centre_i[q], geom.radius_i[q])
        lum = taps_sum(tex, idx, w) * (ff / jnp.maximum(taps_sum(tex_w, idx, w)[:, 0],
                                                         1e-30))[:, None]
        # the grid holds the hemisphere of i facing j (its axis is −fr[:, 2] = c_i − c_j)
        face = jnp.maximum(dot3(nrm, fr[:, 2]), 0.0)
        acc = acc + face[:, None] * lum
        wsum = wsum + face
    return acc / jnp.maximum(wsum, 1e-30)[:, None]


#: receiver's gloss lobe quadrature against the neighbour (radial × azimuthal nodes)
_LOBE_NODES = (2, 4)
#: its rings at equal shares of the lobe's radial mass (:func:`environment._lobe_rings`): with
#: 2 rings uniform in θh/μ the outer one carried e^−12 of the weight
_LOBE_RADIAL_RULE = "mass"
#: soft edge of a lobe node's hit on the neighbour's bounding sphere, as a fraction of the
#: lobe's angular std √2 μ (times the distance), capped at ``_EDGE_CAP`` × the neighbour's
#: radius (so a tiny or far neighbour's soft edge shrinks with it: no leak)
_EDGE = 0.35
_EDGE_CAP = 0.5


def _lobe_nodes(nrm: jax.Array, view: jax.Array, mu: jax.Array, eta: jax.Array, *,
                distribution: str, geometry: str) -> tuple[jax.Array, jax.Array]:
    """Reflected directions (Q, 3) and normalised weights (Q,) of a quadrature of the
    receiver's gloss lobe D F G (V·H)/(N·V) dω_H over its visible part (one receiver)."""
    nv = jnp.clip(jnp.dot(nrm, view), 0.0, 1.0)
    h, w, ch = visible_nodes(nrm, view, mu, jnp.zeros_like(mu), nv, distribution=distribution,
                              radial=_LOBE_NODES[0], azimuthal=_LOBE_NODES[1],
                              radial_rule=_LOBE_RADIAL_RULE)
    g, light = lobe_factor(nrm, view, h, ch, mu, eta, geometry=geometry, fresnel=True)
    f = w * g
    return light, f / jnp.maximum(jnp.sum(f), 1e-30)


def _neighbour_along(geom: IRGeometry, atlas: tuple[jax.Array, jax.Array], sh: _Shading,
                     pair: jax.Array, sender: jax.Array, pos: jax.Array, dirs: jax.Array,
                     wts: jax.Array, edge: jax.Array, sigma_env: jax.Array) -> jax.Array:
    """Σ_q wts_q h_q [L_j(y_q → x) − L_env(ω_q)] (N, C): the net radiance that the sender of
    ``pair`` (N,) adds along the rays (pos (N, 3), dirs (N, Q, 3)), weighted by ``wts``
    (N, Q). h: soft hit on its bounding sphere (edge half-width ``edge`` (N,) radians times the
    distance, at most ``_EDGE_CAP`` × its radius). The sender's radiance is the view-independent
    part from the sample mip atlas (with its normal) plus :func:`_specular` towards the
    receiver point; the environment it hides is prefiltered to ``sigma_env`` (N,)."""
    n, nq = dirs.shape[:2]
    g = geom.gather_size
    cj = geom.centre_j[pair]  # (N, 3)
    rj = geom.radius_j[pair][:, None]
    oc = cj - pos
    tp = dot3(oc[:, None], dirs)
    b2 = jnp.maximum(dot3(oc, oc)[:, None] - tp * tp, 1e-14)  # (floors keep gradients finite)
    b = jnp.sqrt(b2)
    half = jnp.maximum(jnp.minimum(edge[:, None] * tp, _EDGE_CAP * rj), 1e-6)
    hit = smootherstep(0.5 + (rj - b) / (2.0 * half)) * (tp > 0.0)
    t = jnp.maximum(tp - jnp.sqrt(jnp.maximum(rj * rj - b2, 1e-14)), 0.0)
    y = pos[:, None] + t[..., None] * dirs
    rel = _normalize(y - cj[:, None]) * rj[..., None]  # on the bounding sphere (rim if missed)
    fr = geom.frame[pair]  # (N, 3, 3)
    ext = geom.extent[pair][:, None]
    tx = (dot3(rel, fr[:, None, 0]) / ext + 1.0) * 0.5 * g
    ty = (1.0 - dot3(rel, fr[:, None, 1]) / ext) * 0.5 * g
    texel = 2.0 * ext / g
    level = 0.5 * jnp.log2(1.0 + (half / texel) ** 2)  # ≈ log2 of the footprint, smooth
    # computed once (XLA would otherwise recompute them inside every consumer)
    tx, ty, level, hit, *rel = materialise_each(tx, ty, level, hit, rel[..., 0], rel[..., 1],
                                                rel[..., 2])
    rel = jnp.stack(rel, -1)
    idx, w = _mip_taps(jnp.broadcast_to(pair[:, None], tx.shape), tx, ty, level, g)
    # two atlases, each tap sum consumed whole by one contraction: XLA:CPU then fuses the
    # gather into the tap sum (slicing one (N, Q, C + 4) result made it materialise all
    # (N, Q, 8, C + 4) taps, many times slower)
    lum_atlas, geo_atlas = atlas
    geo = materialise(taps_sum(geo_atlas, idx, w))  # (N, Q, 4): n·cov, cov
    cov = geo[..., 3]
    # the samples' normal where the atlas has coverage, the bounding sphere's elsewhere
    ny = _normalize(geo[..., :3] + (1.0 - jnp.clip(cov, 0.0, 1.0))[..., None] * rel
                    / rj[..., None])
    spec, mirror = _specular(sh, jnp.broadcast_to(sender[:, None], (n, nq)).reshape(-1),
                             ny.reshape(-1, 3), -dirs.reshape(-1, 3))
    hidden = _env_blur(sh.env, dirs, jnp.broadcast_to(sigma_env[:, None], (n, nq)))
    wq = wts * hit
    wc = wq * cov
    ein = "nq,nqc->nc"
    out = jnp.einsum(ein, wq, taps_sum(lum_atlas, idx, w))  # L·cov
    out = out + jnp.einsum(ein, wc, spec.reshape(n, nq, -1) - hidden) @ sh.basis
    if mirror is not None:
        out = out + sh.to_output(jnp.einsum(ein, wc, mirror.reshape(n, nq, -1)))
    return out


def _hidden_source_gloss(sh: _Shading, geom: IRGeometry, obj: jax.Array, pos: jax.Array,
                         nrm: jax.Array, view: jax.Array) -> jax.Array | None:
    """β Σ_s F D G/(4cosθr) Φ_s (N, C) over the bright sources hidden by a neighbour's bounding
    sphere (the part of the receiver's environment gloss that the neighbour blocks)."""
    o = jnp.maximum(obj, 0)
    occ = _hidden_sources(geom, sh.env, pos, o)
    if occ is None:
        return None
    sdir, sflux = _source_terms(sh.env)
    mats = sh.mats
    out = jnp.zeros((pos.shape[0], sflux.shape[-1]), pos.dtype)
    for k, m in enumerate(sh.materials):
        w = _gloss_weights(nrm[:, None], view[:, None], sdir[None], mats["mu"][o][:, None],
                           mats["n"][o][:, None], m.distribution, m.geometry)
        out = jnp.where((o == k)[:, None], (occ * w) @ sflux, out)
    return mats["beta"][o][:, None] * (out @ sh.basis)


#: the gloss quadrature runs over the receivers in this many equal chunks (the active ones
#: sorted first; chunks without an active receiver are skipped), each at least
#: ``_GLOSS_MIN_CHUNK`` receivers (or all of them): one traced copy of the quadrature (compile
#: time), at most one partly active chunk of wasted work, and few enough iterations that the
#: loop's per-iteration overhead does not count (small chunks of 128 receivers cost more CPU
#: on the benchmark frame)
_GLOSS_CHUNKS = 64
_GLOSS_MIN_CHUNK = 1024
#: with the accelerator layout (:mod:`spectral_fit._runtime.backend`) the receivers run in chunks of
#: up to this many, all of them when fewer (no sort, loop or conditional)
_GLOSS_ACCEL_CHUNK = 65536
#: a receiver's lobe is evaluated against a neighbour when its mirror direction is within the
#: neighbour's angular radius plus this many lobe widths μ (+ 0.05 rad): the lobe's reflected
#: directions have an angular std of about √2 μ, so beyond that the lobe keeps < e^-6 of its
#: weight (7 widths changed no receiver of the benchmark frame by more than 1e-7 of the peak)
_LOBE_REACH = 5.0


def _pixel_slots(pixel: jax.Array, obj: jax.Array, shape: tuple[int, int]) -> jax.Array:
    """(H·W,) int32: the receiver index of each pixel of the image ``shape`` (H, W), −1 where
    no receiver (``pixel`` (N,) flat index row·W + column, −1 = not a pixel; ``obj`` (N,),
    −1 = empty)."""
    h, w = shape
    n = pixel.shape[0]
    ok = (pixel >= 0) & (obj >= 0)
    return jnp.full((h * w,), -1, jnp.int32).at[jnp.where(ok, pixel, h * w)].set(
        jnp.arange(n, dtype=jnp.int32), mode="drop")


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
    r0, c0 = row - row % step, col - col % step
    fy = (row % step).astype(jnp.float32) / step
    fx = (col % step).astype(jnp.float32) / step
    idx, goods, wks = [], [], []
    for dr, dc, wk in ((0, 0, (1 - fy) * (1 - fx)), (0, step, (1 - fy) * fx),
                       (step, 0, fy * (1 - fx)), (step, step, fy * fx)):
        r, cc = r0 + dr, c0 + dc
        inside = (r < h) & (cc < w)
        a = jnp.where(inside, slot[jnp.where(inside, r * w + cc, 0)], -1)
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


def _lobe_gather(geom: IRGeometry, atlas: tuple[jax.Array, jax.Array], sh: _Shading,
                 pos: jax.Array, nrm: jax.Array, view: jax.Array, obj: jax.Array,
                 grid: tuple[jax.Array, tuple[int, int], int] | None = None) -> jax.Array:
    """Gloss and mirror interreflection (N, C): β A(x) Σ_q w_q (neighbour − hidden environment)
    over the receiver's lobe nodes, χ F(θr) (…) along R. Receivers whose lobe cannot reach a
    neighbour are sorted last, into chunks (``_GLOSS_CHUNKS``) that are skipped; with the
    accelerator layout (:mod:`spectral_fit._runtime.backend`) all receivers run at once.

    ``grid`` = (pixel (N,), image shape (H, W), step): the receivers are pixels of one image;
    the quadrature runs at every ``step``-th row and column only (:func:`_image_anchors`) and
    the pixels between are interpolated bilinearly (the gloss interreflection is a blurred
    image of the neighbour: smooth at the pixel scale)."""
    active, gap, refl = _lobe_reach(geom, sh, pos, nrm, view, obj)
    if grid is None:
        return _lobe_quadrature(geom, atlas, sh, pos, nrm, view, obj, active)
    own, a_idx, a_w = _image_anchors(grid[0], obj, grid[1], grid[2], pos, refl, gap,
                                     math.sqrt(2.0) * sh.mats["mu"][jnp.maximum(obj, 0)])
    res = _lobe_quadrature(geom, atlas, sh, pos, nrm, view, obj, active & own)
    return jnp.where(own[:, None], res, taps_sum(res, a_idx, a_w))


def _lobe_reach(geom: IRGeometry, sh: _Shading, pos: jax.Array, nrm: jax.Array,
                view: jax.Array, obj: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Which receivers' gloss lobes can reach a neighbour (their mirror direction within the
    neighbour's angular radius plus ``_LOBE_REACH`` lobe widths; N·V > 0): ``active`` (N,)
    bool, the distance ``gap`` (N,) to the nearest neighbour's bounding sphere, and the mirror
    directions ``refl`` (N, 3)."""
    k_per = geom.n_objects - 1
    mats = sh.mats
    o_all = jnp.maximum(obj, 0)
    nv_all = dot3(nrm, view)
    refl_all = 2.0 * nv_all[:, None] * nrm - view
    reach = jnp.zeros(obj.shape, bool)
    gap = jnp.full(obj.shape, jnp.inf, pos.dtype)
    for k in range(k_per):
        pair = o_all * k_per + k
        oc = geom.centre_j[pair] - pos
        d2 = jnp.maximum(dot3(oc, oc), 1e-30)
        gap = jnp.minimum(gap, jnp.maximum(jnp.sqrt(d2) - geom.radius_j[pair], 1e-6))
        # angle(R, c_j − x) < asin(r_j/d) + reach, by cosines (no arccos per receiver)
        lim = jnp.minimum(atan2_poly(geom.radius_j[pair],
                                      jnp.sqrt(jnp.maximum(d2 - geom.radius_j[pair] ** 2,
                                                           1e-30)))
                          + _LOBE_REACH * mats["mu"][o_all] + 0.05, math.pi)
        reach = reach | (dot3(oc, refl_all) > sincos_poly(lim)[1] * jnp.sqrt(d2))
    return (obj >= 0) & (nv_all > 0.0) & reach, gap, refl_all


def _lobe_quadrature(geom: IRGeometry, atlas: tuple[jax.Array, jax.Array], sh: _Shading,
                     pos: jax.Array, nrm: jax.Array, view: jax.Array, obj: jax.Array,
                     active: jax.Array) -> jax.Array:
    """The gloss and mirror interreflection (N, C) of :func:`_lobe_gather` at the ``active``
    (N,) receivers (zero at the others), by the lobe quadrature in chunks, the active
    receivers first and the chunks past them skipped (one chunk of all with the accelerator
    layout)."""
    k_per = geom.n_objects - 1
    c = sh.channels
    mats = sh.mats
    materials = sh.materials
    n = pos.shape[0]
    if on_accelerator():
        size = max(1, min(n, _GLOSS_ACCEL_CHUNK))
    else:
        size = max(1, min(n, max(_GLOSS_MIN_CHUNK, -(-n // _GLOSS_CHUNKS))))
    nc = -(-n // size)
    pad = nc * size - n

    senders = jnp.asarray([j for _, j in geom.pairs], jnp.int32)
    same = len({(m.distribution, m.geometry) for m in materials}) == 1

    def run(args: tuple[jax.Array, ...]) -> jax.Array:
        x, nn, vv, ob, act = args
        o = jnp.maximum(ob, 0)
        mu, eta = mats["mu"][o], mats["n"][o]
        beta, chi = mats["beta"][o], mats["chi"][o]
        nv = dot3(nn, vv)
        if same:
            m0 = materials[0]
            dirs, wts = jax.vmap(lambda a, b, m_, e_: _lobe_nodes(
                a, b, m_, e_, distribution=m0.distribution, geometry=m0.geometry))(
                    nn, vv, mu, eta)
        else:
            dirs = wts = None
            for k, m in enumerate(materials):
                d_k, w_k = jax.vmap(lambda a, b, m_, e_, m=m: _lobe_nodes(
                    a, b, m_, e_, distribution=m.distribution, geometry=m.geometry))(
                        nn, vv, mu, eta)
                sel = o == k
                dirs = d_k if dirs is None else jnp.where(sel[:, None, None], d_k, dirs)
                wts = w_k if wts is None else jnp.where(sel[:, None], w_k, wts)
        # computed once (XLA would otherwise recompute the nodes inside every consumer)
        dw = materialise(jnp.concatenate([dirs, wts[..., None]], -1))
        dirs, wts = dw[..., :3], dw[..., 3]
        albedo = _albedo_at(sh.albedo, ob, nv)
        lobe_sigma = math.sqrt(2.0) * mu
        acc = jnp.zeros((x.shape[0], c), x.dtype)
        for k in range(k_per):
            pair = o * k_per + k
            along = _neighbour_along(geom, atlas, sh, pair, senders[pair], x, dirs, wts,
                                     _EDGE * lobe_sigma, 0.5 * lobe_sigma)
            acc = acc + (beta * albedo)[:, None] * along
            if sh.mirror:
                rdir = 2.0 * nv[:, None] * nn - vv
                m_along = _neighbour_along(geom, atlas, sh, pair, senders[pair], x,
                                           rdir[:, None], jnp.ones_like(mu)[:, None],
                                           jnp.full_like(mu, 0.02), jnp.zeros_like(mu))
                fres = fresnel_dielectric(jnp.clip(nv, 0.0, 1.0), eta)
                acc = acc + (chi * fres)[:, None] * m_along
        return jnp.where(act[:, None], acc, 0.0)

    zz = jnp.asarray((0.0, 0.0, 1.0), nrm.dtype)
    if nc == 1:  # one chunk (accelerator layout, or few receivers): no sort, loop or cond
        res = run((pos, jnp.where(active[:, None], nrm, zz), jnp.where(active[:, None], view, zz),
                   obj, active))
    else:
        # the active receivers first, each part in index order (a stable partition, found
        # by counting: a sort of the N keys cost more than the whole rest of the bookkeeping)
        rank, order = _partition(active)
        count = jnp.sum(active.astype(jnp.int32))
        slots = jnp.concatenate([order, jnp.full((pad,), n, jnp.int32)]).reshape(nc, size)

        def do(sl: jax.Array) -> jax.Array:
            # the chunk's receivers are gathered here: skipped chunks gather nothing
            ix = jnp.minimum(sl, n - 1)
            act = active[ix] & (sl < n)
            return run((pos[ix], jnp.where(act[:, None], nrm[ix], zz),
                        jnp.where(act[:, None], view[ix], zz), obj[ix], act))

        def step(_: None, a: tuple[jax.Array, jax.Array]) -> tuple[None, jax.Array]:
            i, sl = a
            # chunks past the active receivers are skipped; each iteration passes only its
            # own (size, C) result (a carried (N, C) buffer was copied through every
            # conditional, a large cost over the 64 iterations)
            return None, jax.lax.cond(i * size < count, do,
                                      lambda _: jnp.zeros((size, c), pos.dtype), sl)

        _, ys = jax.lax.scan(step, None, (jnp.arange(nc, dtype=jnp.int32), slots))
        # back to the receivers' order: receiver i's result is row rank[i] (a gather)
        res = materialise(ys.reshape(nc * size, c)[rank], cut=True)
    return res


def _sees(geom: IRGeometry, pos: jax.Array, nrm: jax.Array, obj: jax.Array) -> jax.Array:
    """(N,) bool: some neighbour's bounding sphere rises above the receiver's tangent plane."""
    k_per = geom.n_objects - 1
    sees = jnp.zeros(obj.shape, bool)
    for k in range(k_per):
        pair = jnp.maximum(obj, 0) * k_per + k
        sees = sees | (dot3(nrm, geom.centre_j[pair] - pos) > -geom.radius_j[pair])
    return sees & (obj >= 0)


def _reflect_diffuse(sh: _Shading, net: jax.Array, obj: jax.Array) -> jax.Array:
    """α S(λ) ⊙ net (N, C) per receiver object ``obj`` (N,), in ``sh``'s output channels."""
    o = jnp.maximum(obj, 0)
    mats = sh.mats
    return sh.to_output(mats["alpha"][o][:, None]
                        * _times_reflectance(sh.env, mats["reflectance"][o], net))


def _receive(geom: IRGeometry, sh: _Shading, atlas: tuple[jax.Array, jax.Array],
             diffuse: jax.Array, pos: jax.Array, nrm: jax.Array, view: jax.Array,
             obj: jax.Array, *,
             grid: tuple[jax.Array, tuple[int, int], int] | None = None) -> jax.Array:
    """Interreflection (N, D) at receivers (pos, nrm, view (N, 3), obj (N,)) in ``sh``'s output
    channels, given their diffuse term ``diffuse`` (N, D) (α S ⊙ the net light they receive,
    :func:`_reflect_diffuse`) and the senders' mip ``atlas`` (in the output channels)."""
    # gloss and mirror: quadrature of the receiver's lobe, each node ray against the senders
    out = diffuse + _lobe_gather(geom, atlas, sh, pos, nrm, view, obj, grid)
    out, ok = _less_hidden_sources(geom, sh, out, pos, nrm, view, obj)
    return jnp.where(ok[:, None], out, 0.0)


def _less_hidden_sources(geom: IRGeometry, sh: _Shading, out: jax.Array, pos: jax.Array,
                         nrm: jax.Array, view: jax.Array, obj: jax.Array
                         ) -> tuple[jax.Array, jax.Array]:
    """``out`` (N, D) less the environment's gloss that the neighbours hide
    (:func:`_hidden_source_gloss`), and (N,) whether each receiver gets interreflection at
    all (it sees a neighbour and faces its view)."""
    hsrc = _hidden_source_gloss(sh, geom, obj, pos, nrm, view)
    if hsrc is not None:
        out = out - hsrc
    return out, _sees(geom, pos, nrm, obj) & (dot3(nrm, view) > 0.0)


def _direct_diffuse(geom: IRGeometry, snd: _Senders, env: EnvironmentMap, pos: jax.Array,
                    nrm: jax.Array, obj: jax.Array) -> jax.Array:
    """:func:`_diffuse_net` (N, C) at arbitrary receivers, each gathering from all samples of
    its object's neighbours (receivers sorted by object, chunks of ``_CHUNK``; chunks of
    receivers that see no neighbour are skipped). The reference for the interpolated
    :func:`_interpolate_net`, and ``diffuse_at="receivers"``."""
    n_obj = geom.n_objects
    k_per = n_obj - 1
    p_count, m_count = geom.s_area.shape
    km = k_per * m_count
    origin = jnp.mean(geom.centre_j, axis=0)

    def per_obj(x: jax.Array) -> jax.Array:
        return x.reshape(n_obj, km, *x.shape[2:])

    blocks = (per_obj(snd.pos - origin), per_obj(snd.nrm), per_obj(snd.area),
              *(per_obj(f) for f in snd.frames))
    lum, spec = per_obj(snd.lum), per_obj(snd.spec)
    mirror = None if snd.mirror is None else per_obj(snd.mirror)
    n = pos.shape[0]
    key = jnp.where(_sees(geom, pos, nrm, obj), obj, n_obj)
    order = jnp.argsort(key)
    nc = -(-n // _CHUNK)
    pad = nc * _CHUNK - n
    xs = jnp.pad((pos - origin)[order], ((0, pad), (0, 0))).reshape(nc, _CHUNK, 3)
    ns = jnp.concatenate([nrm[order], jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0], nrm.dtype),
                                                       (pad, 3))]).reshape(nc, _CHUNK, 3)
    ks = jnp.pad(key[order], (0, pad), constant_values=n_obj).reshape(nc, _CHUNK)
    c = env.channels

    def block(o: int, x0: jax.Array, nx: jax.Array, sel: jax.Array) -> jax.Array:
        w, tu, tv = _form_factor_block(x0, nx, tuple(b[o] for b in blocks))
        w = jnp.where(sel[:, None], w, 0.0)
        lsum, fsum = _transfer(w, tu, tv, lum[o], spec[o], None if mirror is None else
                               mirror[o], env.spectral_basis)
        net = _diffuse_net(geom, env, lsum, fsum, x0 + origin, nx,
                           jnp.full(x0.shape[:1], o, jnp.int32))
        return jnp.where(sel[:, None], net, 0.0)

    def chunk(args: tuple[jax.Array, jax.Array, jax.Array]) -> jax.Array:
        x0, nx, kk = args
        acc = jnp.zeros((_CHUNK, c), lum.dtype)
        for o in range(n_obj):
            sel = kk == o
            acc = acc + jax.lax.cond(jnp.any(sel), lambda s, o=o: block(o, x0, nx, s),
                                     lambda s: jnp.zeros((_CHUNK, c), lum.dtype), sel)
        return acc

    res = jax.lax.map(chunk, (xs, ns, ks)).reshape(nc * _CHUNK, c)[:n]
    return jnp.zeros((n, c), lum.dtype).at[order].set(res)


def _sample_diffuse(geom: IRGeometry, sh: _Shading) -> jax.Array:
    """(P, M, C) view-independent radiance α_j S_j E_irr(n_y)/π of each sample."""
    p_count, m_count = geom.s_area.shape
    senders = [j for _, j in geom.pairs]
    e = jax.vmap(lambda nn: irradiance(sh.env, nn))(geom.s_nrm.reshape(-1, 3))
    e = e.reshape(p_count, m_count, -1)
    sid = jnp.asarray(senders, jnp.int32)
    refl = sh.mats["reflectance"][sid][:, None, :]
    return (sh.mats["alpha"][sid] / math.pi)[:, None, None] * _times_reflectance(sh.env, refl,
                                                                                   e)


DIFFUSE_AT = ("samples", "receivers")
#: default screen-space step of the gloss quadrature for receivers that are pixels of an image
#: (``image_shape``): evaluated at every 2nd row and column, interpolated between
GLOSS_STEP = 2
#: ... unless the lobe's view of the neighbour changes by more than this many lobe widths
#: between a pixel and an anchor (:func:`_image_anchors`)
_GLOSS_SMOOTH = 0.7


class GatherSenders(eqx.Module):
    """The camera-independent half of the gather interreflection of one scene state
    (:func:`gather_senders`): pass-1 geometry, the senders' samples with their radiance after
    all the bounces, their mip atlases and the diffuse net light at the samples. A pytree of
    arrays; :func:`gather_receivers` turns it into the light at any receivers. It depends on
    the objects' poses, the materials and the environment, not on the camera.

    Attributes:
        geometry: :class:`IRGeometry` (gather mode).
        senders: the senders' samples as the last gather saw them.
        atlas: (radiance (P, A, C), normal·coverage and coverage (P, A, 4)) mip atlases.
        net: (P, M, C) diffuse net light at the samples, or None (``diffuse_at`` =
            "receivers" with one bounce).
    """

    geometry: IRGeometry
    senders: _Senders
    atlas: tuple[jax.Array, jax.Array]
    net: jax.Array | None


def gather_senders(geometry: IRGeometry, materials: Sequence[Material], env: EnvironmentMap,
                   *, bounces: int = 1, diffuse_at: str = "samples") -> GatherSenders:
    """The senders' side of :func:`interreflection_from` in gather mode (pass-1 shading, mip
    atlases, the sample-to-sample transfer and the bounces): everything that does not depend
    on the receivers, so a caller whose objects and materials did not change (a camera
    moving around static objects) computes it once and calls :func:`gather_receivers` per
    frame. ``gather_receivers(gather_senders(g, m, e), m, e, r)`` equals
    ``interreflection_from(g, m, e, r)`` exactly."""
    if geometry.mode != "gather":
        raise InputError(f"needs a gather-mode geometry, got {geometry.mode!r}", field="mode")
    _check_materials(geometry.n_objects, materials, env)
    bounces = _check_int(bounces, "bounces", 1, 64)
    _check_diffuse_at(diffuse_at)
    return _gather_senders(geometry, materials, env, bounces, diffuse_at)


def _gather_senders(geom: IRGeometry, materials: Sequence[Material], env: EnvironmentMap,
                    bounces: int, diffuse_at: str) -> GatherSenders:
    pairs = geom.pairs
    senders = [j for _, j in pairs]
    p_count, m_count = geom.s_area.shape
    sh = _shading(materials, env)
    live = geom.s_area > 0
    frames = _view_frames(geom)
    with jax.named_scope("ir_sample_shading"):
        spec, mirror = _sample_specular(geom, sh, frames)
        l0 = jnp.where(live[..., None], _sample_diffuse(geom, sh), 0.0)
    cov = geom.s_cov[..., None]

    def senders_with(lum: jax.Array) -> tuple[_Senders, jax.Array]:
        snd = _Senders(pos=geom.s_pos, nrm=geom.s_nrm, area=geom.s_area, frames=frames,
                       lum=lum, spec=spec, mirror=mirror)
        with jax.named_scope("ir_atlas"):
            atlas = (_build_mips(lum * cov, geom.gather_size),
                     _build_mips(jnp.concatenate([geom.s_nrm * cov, cov], -1),
                                 geom.gather_size))
        return snd, atlas

    lum = l0
    snd, atlas = senders_with(lum)
    s_obj = jnp.where(live.reshape(-1), jnp.asarray(np.repeat(senders, m_count), jnp.int32),
                      -1)
    s_pos, s_nrm = geom.s_pos.reshape(-1, 3), geom.s_nrm.reshape(-1, 3)
    net = None
    for b in range(bounces):
        if diffuse_at == "samples" or b < bounces - 1:
            with jax.named_scope("ir_sample_transfer"):
                net = _sample_diffuse_net(geom, snd, env)
        if b == bounces - 1:
            break
        with jax.named_scope("ir_sample_bounce"):
            extra = _receive(geom, sh, atlas,
                             _reflect_diffuse(sh, net.reshape(-1, net.shape[-1]), s_obj),
                             s_pos, s_nrm, geom.s_view.reshape(-1, 3), s_obj)
        lum = l0 + jnp.where(live[..., None], extra.reshape(l0.shape), 0.0)
        snd, atlas = senders_with(lum)
    return GatherSenders(geometry=geom, senders=snd, atlas=atlas,
                         net=net if diffuse_at == "samples" else None)


def gather_receivers(state: GatherSenders, materials: Sequence[Material], env: EnvironmentMap,
                     receivers: GBuffer, *, image_shape: tuple[int, int] | None = None,
                     gloss_step: int = GLOSS_STEP, output: Any = None) -> jax.Array:
    """The receivers' side of the gather interreflection: radiance (N, C) (or (N, D) with
    ``output``) to add at ``receivers``, from :func:`gather_senders`'s state of the same
    objects, ``materials`` and ``env`` (options as :func:`interreflection_from`; the
    diffuse transfer is evaluated where the state was made for)."""
    geom = state.geometry
    _check_materials(geom.n_objects, materials, env)
    _check_receivers(receivers)
    gloss_step = _check_int(gloss_step, "gloss_step", 1, 64)
    image_shape = _check_image_shape(image_shape)
    diffuse_at = "samples" if state.net is not None else "receivers"
    return _gather_receivers(state, materials, env, receivers, diffuse_at, image_shape,
                             gloss_step, output)


def _gather_receivers(state: GatherSenders, materials: Sequence[Material],
                      env: EnvironmentMap, receivers: GBuffer, diffuse_at: str,
                      image_shape: tuple[int, int] | None, gloss_step: int,
                      output: jax.Array | None) -> jax.Array:
    geom, snd, atlas, net = state.geometry, state.senders, state.atlas, state.net
    senders = [j for _, j in geom.pairs]
    sh = _shading(materials, env)
    pos, nrm, obj = receivers.position, receivers.normal, receivers.object
    # the receivers' terms in the output channels: the diffuse net light of each pair's
    # samples reflected by their object (α S ⊙ net, then the output map) before it is
    # interpolated, the senders' atlas mapped before it is gathered from (all linear)
    sh = dataclasses.replace(sh, output=None if output is None else jnp.asarray(output,
                                                                              jnp.float32))
    if output is not None:
        atlas = (atlas[0] @ sh.output, atlas[1])
    grid = None if image_shape is None or gloss_step < 2 else (receivers.pixel, image_shape,
                                                                gloss_step)
    tables = None
    with jax.named_scope("ir_receiver_diffuse"):
        if diffuse_at == "samples":
            refl = sh.diffuse_matrices()[jnp.asarray(senders, jnp.int32)]  # (P, C, D)
            tables = _net_tables(geom, jnp.einsum("pmc,pcd->pmd", net, refl))
            diffuse = None
        else:
            diffuse = _reflect_diffuse(sh, _direct_diffuse(geom, snd, env, pos, nrm, obj),
                                       obj)
    if not on_accelerator() and pos.shape[0] > _RECEIVER_CHUNK:
        return _receive_valid_first(geom, sh, atlas, tables, diffuse, pos, nrm,
                                    receivers.view, obj, grid)
    if diffuse is None:
        with jax.named_scope("ir_receiver_diffuse"):
            diffuse = _interpolate_net(geom, net, pos, nrm, obj, tables=tables)
    with jax.named_scope("ir_receiver_gloss"):
        return _receive(geom, sh, atlas, diffuse, pos, nrm, receivers.view, obj, grid=grid)


#: CPU layout: receivers per chunk of the per-receiver terms of :func:`_receive_valid_first`
_RECEIVER_CHUNK = 4096


def _receive_valid_first(geom: IRGeometry, sh: _Shading, atlas: tuple[jax.Array, jax.Array],
                         tables: tuple[jax.Array, jax.Array] | None,
                         diffuse: jax.Array | None, pos: jax.Array, nrm: jax.Array,
                         view: jax.Array, obj: jax.Array,
                         grid: tuple[jax.Array, tuple[int, int], int] | None) -> jax.Array:
    """:func:`_receive` (N, D) for many receivers on the CPU layout, at a cost that follows
    the number of valid receivers (obj >= 0) rather than N: a renderer's receivers are
    fixed-capacity slot lists, of which the covered pixels fill ~55–60 % (the capacities'
    headroom). The valid receivers are put first (a stable partition), their per-receiver
    terms (the interpolated diffuse net light, ``tables`` from :func:`_net_tables`, or the
    given ``diffuse`` (N, D); the hidden sources; the lobe's reach; the image anchors) run in
    chunks of ``_RECEIVER_CHUNK`` with the chunks past them skipped, the lobe quadrature runs
    on the active ones as in :func:`_lobe_gather`, and the result goes back to the slots'
    order. Equal to :func:`_receive` (the same arithmetic per receiver)."""
    valid = obj >= 0
    rank, order = _partition(valid)
    count = jnp.sum(valid.astype(jnp.int32))
    pos, nrm, view, obj = pos[order], nrm[order], view[order], obj[order]
    if diffuse is not None:
        diffuse = diffuse[order]
    step = 0
    at = None
    pixel = jnp.full(obj.shape, -1, jnp.int32)
    if grid is not None:
        pixel, shape, step = grid[0][order], grid[1], grid[2]
        refl_all = 2.0 * dot3(nrm, view)[:, None] * nrm - view
        at = (_pixel_slots(pixel, obj, shape), pos, refl_all, obj)
    mu = sh.mats["mu"]

    def terms(x: jax.Array, nn: jax.Array, vv: jax.Array, ob: jax.Array, px: jax.Array,
              *dif: jax.Array) -> tuple[jax.Array, ...]:
        with jax.named_scope("ir_receiver_diffuse"):
            base = dif[0] if dif else _interpolate_net(geom, None, x, nn, ob, tables=tables)
        with jax.named_scope("ir_receiver_gloss"):
            base, ok = _less_hidden_sources(geom, sh, base, x, nn, vv, ob)
            active, gap, refl = _lobe_reach(geom, sh, x, nn, vv, ob)
            if at is None:
                return base, ok, active
            own, a_idx, a_w = _image_anchors(px, ob, shape, step, x, refl, gap,
                                             math.sqrt(2.0) * mu[jnp.maximum(ob, 0)], at=at)
            return base, ok, active & own, own, a_idx, a_w

    extra = [] if diffuse is None else [diffuse]
    out = prefix_chunks(terms, count, [pos, nrm, view, obj, pixel, *extra],
                        size=_RECEIVER_CHUNK)
    base, ok, active = out[:3]
    with jax.named_scope("ir_receiver_gloss"):
        res = _lobe_quadrature(geom, atlas, sh, pos, nrm, view, obj, active)
        if at is not None:
            own, a_idx, a_w = out[3:]
            res = jnp.where(own[:, None], res, taps_sum(res, a_idx, a_w))
        return jnp.where(ok[:, None], base + res, 0.0)[rank]


def _gather_mode(geom: IRGeometry, materials: Sequence[Material], env: EnvironmentMap,
                 receivers: GBuffer, bounces: int, diffuse_at: str = "samples",
                 image_shape: tuple[int, int] | None = None, gloss_step: int = 1,
                 output: jax.Array | None = None) -> jax.Array:
    state = _gather_senders(geom, materials, env, bounces, diffuse_at)
    return _gather_receivers(state, materials, env, receivers, diffuse_at, image_shape,
                             gloss_step, output)


# --------------------------------------------------------------------------------------------
# paper mode


def _paper_textures(geom: IRGeometry, materials: Sequence[Material], env: EnvironmentMap,
                    split: tuple[Any, Any] | None = None) -> tuple[jax.Array, jax.Array]:
    """Pass 1 shading: T_d, T_s (P, T², C) of each sender seen from the receiver's centre.
    The gloss uses the environment module's "render" quadrature (8 × 16 nodes: the textures
    are a 64² approximation of the sender anyway, and "exact" costs far more per texel), or
    with ``split`` = (:class:`~spectral_fit.lighting.SplitSumMap`, its
    :class:`~spectral_fit.lighting.SplitSum` settings) the frame's split-sum gloss
    (:func:`~spectral_fit.lighting.gloss_split_sum`, quality "fast": many times cheaper
    than the quadrature over the textures' texels, its texels' gloss within the split sum's
    accuracy of the quadrature; it is 0 below the texel's horizon, as the quadrature)."""
    t2 = geom.texture_size ** 2
    c = env.channels
    tds, tss = [], []
    for p, (_, j) in enumerate(geom.pairs):
        m = materials[j]
        nrm = geom.p_nrm[p]
        view = _normalize(geom.centre_i[p] - geom.p_pos[p])

        def texel(nn: jax.Array, vv: jax.Array, m: Material = m) -> tuple[jax.Array, jax.Array]:
            e = irradiance(env, nn)
            td = (m.alpha / math.pi) * _times_reflectance(env, m.reflectance, e)
            ts = m.chi * mirror_radiance(env, nn, vv, m.n)
            if split is None:
                ts = ts + m.beta * gloss_integral(
                    env, nn, vv, m.mu, m.n, distribution=m.distribution,
                    geometry=m.geometry, quality="render")
            front = jnp.dot(nn, vv) > 0.0
            return td, jnp.where(front, ts, 0.0)

        td, ts = jax.vmap(texel)(nrm, view)
        if split is not None:
            split_map, settings = split
            table = lobe_moment_table(m.mu, m.n, distribution=m.distribution,
                                      geometry=m.geometry, settings=settings)
            ts = ts + m.beta * gloss_split_sum(env, split_map, table, nrm, view, m.mu, m.n,
                                               distribution=m.distribution,
                                               geometry=m.geometry, settings=settings)
        valid = geom.p_valid[p][:, None]
        idx = jnp.where(geom.p_valid[p], geom.p_index[p], t2)
        tds.append(jnp.zeros((t2, c), td.dtype).at[idx].set(jnp.where(valid, td, 0.0),
                                                            mode="drop"))
        tss.append(jnp.zeros((t2, c), ts.dtype).at[idx].set(jnp.where(valid, ts, 0.0),
                                                            mode="drop"))
    return jnp.stack(tds), jnp.stack(tss)


def _bilinear_clamped(tex: jax.Array, pair: jax.Array, t: int, px: jax.Array, py: jax.Array
                      ) -> jax.Array:
    """GL_LINEAR + CLAMP_TO_EDGE lookup (C,) of texture ``tex[pair]`` (T², C) at pixel
    coordinates (px, py) (texel centres at integer + 0.5)."""
    x = px - 0.5
    y = py - 0.5
    x0f, y0f = jnp.floor(x), jnp.floor(y)
    fx, fy = x - x0f, y - y0f
    x0 = jnp.clip(x0f.astype(jnp.int32), 0, t - 1)
    x1 = jnp.clip(x0f.astype(jnp.int32) + 1, 0, t - 1)
    y0 = jnp.clip(y0f.astype(jnp.int32), 0, t - 1)
    y1 = jnp.clip(y0f.astype(jnp.int32) + 1, 0, t - 1)
    idx = jnp.stack([y0 * t + x0, y0 * t + x1, y1 * t + x0, y1 * t + x1])
    w = jnp.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx])
    return w @ tex[pair, idx]


def _paper_mode(geom: IRGeometry, materials: Sequence[Material], env: EnvironmentMap,
                receivers: GBuffer, split: tuple[Any, Any] | None = None) -> jax.Array:
    td, ts = _paper_textures(geom, materials, env, split)
    t = geom.texture_size
    k_per = geom.n_objects - 1
    obj = receivers.object
    ok = obj >= 0
    o = jnp.maximum(obj, 0)
    mats = _stack_materials(materials)
    a_paper = mats["alpha"][o] / math.pi
    gamma = mats["gamma"][o]
    pos, nrm = receivers.position, receivers.normal
    out = jnp.zeros((pos.shape[0], env.channels), td.dtype)
    for k in range(k_per):
        pair = o * k_per + k
        vp = geom.p_view_proj[pair]  # (N, 4, 4)
        clip = jnp.einsum("nij,nj->ni", vp[:, :, :3], pos) + vp[:, :, 3]
        w = clip[:, 3]
        wsafe = jnp.where(w > 0, w, 1.0)
        nx, ny = clip[:, 0] / wsafe, clip[:, 1] / wsafe
        facing = jnp.sum(nrm * (geom.centre_j[pair] - pos), -1) > 0.0
        valid = ok & (w > 0) & (jnp.abs(nx) <= 1.0) & (jnp.abs(ny) <= 1.0) & facing
        px = (nx + 1.0) * 0.5 * t
        py = (1.0 - ny) * 0.5 * t
        look = jax.vmap(lambda p_, a, b, tex: _bilinear_clamped(tex, p_, t, a, b),
                        in_axes=(0, 0, 0, None))
        add = a_paper[:, None] * look(pair, px, py, td) + gamma[:, None] * look(pair, px, py,
                                                                                 ts)
        out = out + jnp.where(valid[:, None], add, 0.0)
    return out


# --------------------------------------------------------------------------------------------
# public entry points


def _check_materials(n: int, materials: Sequence[Material], env: EnvironmentMap) -> None:
    if len(materials) != n:
        raise InputError(f"{len(materials)} materials for {n} objects", field="materials")
    c = env.channels
    for k, m in enumerate(materials):
        if not isinstance(m, Material):
            raise InputError(f"expected a Material, got {type(m).__name__}",
                             field=f"materials[{k}]")
        if jnp.shape(m.reflectance)[-1] != c:
            raise InputError(f"reflectance has {jnp.shape(m.reflectance)[-1]} channels, the "
                             f"environment {c}", field=f"materials[{k}].reflectance")


def _check_receivers(receivers: GBuffer) -> None:
    if not isinstance(receivers, GBuffer):
        raise InputError(f"expected a GBuffer, got {type(receivers).__name__}",
                         field="receivers")


def _check_inputs(n: int, materials: Sequence[Material], env: EnvironmentMap,
                  receivers: GBuffer) -> None:
    _check_materials(n, materials, env)
    _check_receivers(receivers)


def _check_diffuse_at(diffuse_at: str) -> None:
    if diffuse_at not in DIFFUSE_AT:
        raise InputError(f"must be one of {DIFFUSE_AT}, got {diffuse_at!r}",
                         field="diffuse_at")


def _check_image_shape(image_shape: Any) -> tuple[int, int] | None:
    if image_shape is None:
        return None
    if len(image_shape) != 2:
        raise InputError(f"must be (H, W), got {image_shape!r}", field="image_shape")
    return (_check_int(image_shape[0], "image_shape", 1, 1 << 15),
            _check_int(image_shape[1], "image_shape", 1, 1 << 15))


def _output_channels(env: EnvironmentMap, output: Any) -> int:
    """D of an ``output`` map (C, D) (C without one); InputError for another shape."""
    if output is None:
        return env.channels
    shape = getattr(output, "shape", None)
    if shape is None or len(shape) != 2 or shape[0] != env.channels:
        raise InputError(f"must be a ({env.channels}, D) matrix (the environment's channels → "
                         f"the output's), got shape {shape}", field="output")
    return int(shape[1])


def interreflection_from(
    geometry: IRGeometry,
    materials: Sequence[Material],
    env: EnvironmentMap,
    receivers: GBuffer,
    *,
    mode: str | None = None,
    bounces: int = 1,
    diffuse_at: str = "samples",
    image_shape: tuple[int, int] | None = None,
    gloss_step: int = GLOSS_STEP,
    output: Any = None,
    split_sum: tuple[Any, Any] | None = None,
) -> jax.Array:
    """Shading pass of the interreflection: radiance (N, C) to ADD to
    ``shade(materials[obj], env, normal, view)`` at every receiver (eq. 6).

    Args:
        geometry: from :func:`prepare_interreflection` (same objects, same order).
        materials: one :class:`Material` per object (bands (L,) or K coefficients, matching
            ``env``).
        env: the environment (bands, or basis coefficients with its product tensor).
        receivers: N surface samples (position m, unit normal, unit view, object index; −1 =
            empty slot → zeros).
        mode: "gather", "paper" or "none" (default: the geometry's mode).
        bounces: gather mode: number of light exchanges (1 = the neighbours' environment
            lighting only); ignored by "paper" (eq. 6 has one).
        diffuse_at: gather mode: where the diffuse transfer (form-factor sums) is evaluated:
            "samples" (default: at the receiving objects' own pass-1 samples, interpolated to
            the receivers) or "receivers" (at every receiver; ~10× the cost on a frame).
        image_shape: gather mode: (H, W) of the image whose pixels the receivers are
            (``receivers.pixel`` = row·W + column): the gloss/mirror quadrature then runs at
            every ``gloss_step``-th row and column and is interpolated bilinearly between
            (receivers at silhouettes, and those that are not pixels, are evaluated
            themselves). None: at every receiver.
        gloss_step: that subsampling step in pixels (1 = none).
        output: optional (C, D) linear map into the caller's output channels (the frame's
            channels → XYZ or camera RGB): returns ``result @ output``. Gather mode then
            works in the D channels from the receivers on (the samples' net light is
            reflected and mapped before it is interpolated, the senders' atlas before it is
            gathered from), which is cheaper than mapping the (N, C) result when D < C.
        split_sum: paper mode: (:class:`~spectral_fit.lighting.SplitSumMap` of ``env``,
            its :class:`~spectral_fit.lighting.SplitSum` settings): the pass-1 textures'
            gloss by the split sum, as the frame's quality "fast" shades (default: the
            "render" quadrature, ~100× the cost).

    Returns:
        (N, C) float32, W·sr⁻¹·m⁻²·nm⁻¹ per band (or coefficients); (N, D) with ``output``.
    """
    mode = geometry.mode if mode is None else _check_mode(mode)
    n = geometry.n_objects
    _check_inputs(n, materials, env, receivers)
    bounces = _check_int(bounces, "bounces", 0, 64)
    _check_diffuse_at(diffuse_at)
    gloss_step = _check_int(gloss_step, "gloss_step", 1, 64)
    image_shape = _check_image_shape(image_shape)
    zeros = jnp.zeros((receivers.object.shape[0], _output_channels(env, output)), jnp.float32)
    if mode == "none" or n < 2 or bounces == 0:
        return zeros
    if mode != geometry.mode:
        raise InputError(f"the geometry was prepared for mode {geometry.mode!r}, not {mode!r}",
                         field="mode")
    if mode == "paper":
        out = _paper_mode(geometry, materials, env, receivers, split_sum)
        return out if output is None else out @ jnp.asarray(output, jnp.float32)
    return _gather_mode(geometry, materials, env, receivers, bounces, diffuse_at,
                        image_shape, gloss_step, output)


def interreflection(
    objects: Sequence[ObjectGeometry],
    materials: Sequence[Material],
    env: EnvironmentMap,
    receivers: GBuffer,
    *,
    mode: str = "gather",
    texture_size: int = 128,
    bounces: int = 1,
    image_shape: tuple[int, int] | None = None,
    gloss_step: int = GLOSS_STEP,
    output: Any = None,
) -> jax.Array:
    """Interreflection radiance (N, C) to ADD to the environment-only shading of every receiver
    sample: :func:`prepare_interreflection` then :func:`interreflection_from`.

    Modes: "paper" — eq. (6) literally (α_paper T_d + γ T_s, pass-1 textures of
    ``texture_size``² from the receiver's centre); "gather" — the neighbours' full radiance
    through the receiver's BRDF with per-fragment parallax, minus the environment they hide,
    ``bounces`` exchanges; "none" — zeros. ``image_shape``, ``gloss_step``,
    ``output``: see :func:`interreflection_from`. See the module docstring.
    """
    _check_mode(mode)
    if mode == "none":
        _check_inputs(len(objects), materials, env, receivers)
        return jnp.zeros((receivers.object.shape[0], _output_channels(env, output)),
                         jnp.float32)
    geom = prepare_interreflection(objects, mode=mode, texture_size=texture_size)
    return interreflection_from(geom, materials, env, receivers, mode=mode, bounces=bounces,
                                image_shape=image_shape, gloss_step=gloss_step, output=output)
