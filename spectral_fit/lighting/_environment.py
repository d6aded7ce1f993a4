"""The spectral environment map (:class:`EnvironmentMap`): an equirectangular map placed in the
world with everything the lighting integrals need precomputed, and lookups in it (JAX).

Maps are (H, W, C) in the convention of ``_equirect`` (docs/conventions.md, 'Conventions'). C
channels are spectral bands (radiance, W·sr⁻¹·m⁻²·nm⁻¹) or K basis coefficients of it. A map is
placed in the world by a rotation R (world-from-map): the world direction ω is looked up at
d = Rᵀω. Maps that put −Z at the image centre need a 180° rotation about +Y.

:meth:`EnvironmentMap.from_array` validates the map and precomputes its SH projection (``_sh``),
the bright sources taken out of it (``_sources``) and the prefiltered levels of the residual in
the map's principal spectra (``_prefilter``). The lighting integrals (all linear in the map, so
they run channel by channel) use them:

- irradiance E(N) = ∫ L(ω) max(0, N·ω) dω by order-2 spherical harmonics, or exactly by a texel
  sum (``_irradiance``);
- gloss ∫ L(ω) F(n, θd) D(μ, θh) G / (4 cosθr) dω (without β), by a fixed quadrature in the
  half-vector lobe frame on a prefiltered map (``_gloss``, settings :class:`GlossQuadrature`;
  the split-sum approximation for frames: ``_split_sum``);
- mirror F(n, θr) L(R), R = reflect(−V, N), by a bilinear lookup of the unfiltered map
  (``_shading``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.backend import materialise_each
from .._runtime.errors import InputError
from ._equirect import (
    bilinear_taps,
    direction_to_uv,
    fast_direction_to_uv,
    rotation_y,
    taps_sum,
    texel_directions,
)
from ._fastmath import select_static, smootherstep
from ._prefilter import _build_levels, _spectral_basis, level_atlas
from ._sh import sh_coefficients
from ._sources import _extract_sources, _source_cells, _tent_gauss_subpoints, _tent_subpoints

__all__ = [
    "GlossQuadrature",
    "QUALITIES",
    "EnvironmentMap",
    "lookup",
    "lookup_level",
    "fast_lookup",
    "levels_for",
    "to_map_fast",
]


@dataclasses.dataclass(frozen=True)
class GlossQuadrature:
    """Settings of the gloss lobe quadrature (static).

    Two qualities share one prefiltered map: ``"exact"`` (the default, for fitting and
    validation) and ``"render"`` (fewer lookups, for frames); see :func:`gloss_integral`.

    Attributes:
        radial, azimuthal: nodes (Gauss–Legendre) of the exact radiance quadrature: rings in
            s = θh/μ' (Gaussian) or tanθh/m' (Beckmann), and azimuths over each ring's visible
            arc. Each node costs two bilinear lookups of r channels.
        prefilter_ratio: r, the prefilter std in reflected directions as a fraction of the lobe's
            (√2 μ cosθr across the plane of incidence); the lobe is narrowed to compensate.
        render_radial, render_azimuthal, render_prefilter_ratio: the same for ``"render"``.
        albedo_radial, albedo_azimuthal: nodes of the scalar lobe-albedo quadrature (no lookups;
            the azimuthal nodes cover half of the symmetric visible arc).
        albedo_table: ``"render"`` interpolates the lobe albedo in √(1 − cosθr) from this many
            exact values per material (computed once per call, not per point).
        horizon_ratio: a node's prefilter std is at most this fraction of its elevation above
            the surface's horizon (so no light from behind the surface is blurred in).
        levels: number of prefiltered levels besides the unfiltered map (std ratio 2).
        max_sources: at most this many bright texels are taken out of the map as explicit
            sources whose gloss is summed exactly (0 disables it): small, very bright lamps
            that no prefiltered quadrature resolves.
        source_threshold: a texel is a source when its channel-summed |radiance| exceeds this
            multiple of the map's solid-angle-weighted mean.
        source_subpoints: 4 (at (±¼, ±¼) texel offsets) or 1 (the texel centre) points per
            source texel.
        nodes: the ``"exact"`` node rule: "grid" (default; :func:`_grid_nodes`, a
            ``grid_along`` × ``grid_across`` Cartesian grid on [−grid_extent, grid_extent]²
            in lobe widths, cut to the disc), "visible" (``radial`` rings × visible arcs,
            :func:`visible_nodes`; ``"render"`` always uses it) or "gauss" (Gauss–Laguerre
            rings × full azimuths over the whole narrowed lobe; kept for comparison).
        texel_sum_from, texel_sum_full: ``"exact"`` replaces the lobe quadrature of ⟨L⟩ by
            the direct texel sum over the unfiltered (residual) map for wide lobes: from μ =
            ``texel_sum_from`` the two are blended (C² in μ) until μ = ``texel_sum_full``,
            above which only the texel sum runs (see :func:`gloss_integral`).
        tent_points: tent_points² equal-weight points of each source texel's footprint in
            the bilinear map (:func:`_tent_subpoints`; ``source_tent_dirs``, kept for callers
            that sum equal-weight points).
        tent_gauss: ``"exact"`` sums each source texel's footprint in the bilinear map (the
            tent over ±1 texel) by a product Gauss rule with this many nodes per half of the
            tent per axis, (2·tent_gauss)² points (:func:`_tent_gauss_subpoints`).
        texel_sum_supersample: the wide-lobe texel sum runs over the residual map as the
            bilinear lookup defines it, sampled this many times finer per axis
            (``fine_texels``; 1: the texel centres, each texel a box).
    """

    radial: int = 16
    azimuthal: int = 32
    prefilter_ratio: float = 0.1
    render_radial: int = 8
    render_azimuthal: int = 16
    render_prefilter_ratio: float = 0.3
    albedo_radial: int = 16
    albedo_azimuthal: int = 8
    albedo_table: int = 48
    horizon_ratio: float = 0.2
    levels: int = 7
    max_sources: int = 32
    source_threshold: float = 30.0
    source_subpoints: int = 4
    nodes: str = "grid"
    grid_along: int = 128
    grid_across: int = 36
    grid_extent: float = 4.0
    texel_sum_from: float = 0.12
    texel_sum_full: float = 0.18
    tent_points: int = 4
    tent_gauss: int = 4
    texel_sum_supersample: int = 2


QUALITIES = ("exact", "render")


class EnvironmentMap(eqx.Module):
    """A spectral environment (H, W, C) placed in the world, with everything precomputed.

    Build it with :meth:`from_array` (validates, prefilters, projects to SH); the fields are then
    JAX arrays, so the map is a pytree that passes through ``jit``.

    Attributes:
        texels: (H, W, C) the map (bands or basis coefficients), unfiltered.
        rotation: (3, 3) world-from-map rotation.
        poles: (2, C) means of the first and last rows of ``texels``.
        sh: (9, C) SH coefficients of the radiance (map frame; R&H order).
        atlas: (T, r) all prefiltered levels of the residual map (bright sources replaced by
            their surroundings) flattened, each followed by its two pole means, in r <= C
            channels: coefficients in ``spectral_basis``.
        spectral_basis: (r, C) orthonormal rows: the map's own principal spectra, as many as
            needed for a relative error <= ``compress_tol`` on every texel (r = C, the
            identity, when ``compress_tol`` = 0). The gloss lookups run in these r channels.
        source_dirs: (S, k, 3) map-frame directions of k = 4 (or 1) sub-points of each source
            texel.
        source_flux: (S, r) excess radiance × solid angle / k of each source texel (per
            sub-point); residual + sources = the map exactly.
        source_tent_dirs: (S, T², 3) map-frame directions of T² equal-weight points
            (T = ``tent_points``, 4 by default) of each source texel's footprint in the
            bilinear map (the tent over ±1 texel), used by the radiance cache (None:
            ``source_dirs``).
        source_fine_dirs, source_fine_weights: (S, P, 3) map-frame directions and (S, P)
            weights (summing to about 1 per source) of the product Gauss rule over each source
            texel's bilinear footprint (:func:`_tent_gauss_subpoints`), used by the ``"exact"``
            gloss: the point's share of the texel's excess flux.
        source_flux_full: (S, C) excess radiance × solid angle of each source texel in the
            map's own channels (uncompressed; the ``"exact"`` gloss).
        source_render_dirs, source_render_weights: the same rule with one node per half of
            the tent per axis (2 × 2 points at ±⅓ texel; the ``"render"`` gloss).
        fine_texels: (s²·H·W, r) the residual map (level 0) looked up bilinearly at the
            texel centres of the s× finer grid, s = ``quadrature.texel_sum_supersample``
            (the wide-lobe texel sum of ``"exact"``).
        level_sigma: (M,) prefilter std (radians) per level, level 0 = unfiltered (0).
        product_tensor: (K, K, K) basis product tensor in coefficient mode, else None.
        level_shapes / level_offsets: static (H_k, W_k) and atlas offsets per level.
        quadrature: static :class:`GlossQuadrature`.
        diffuse: static, "sh" (default) or "exact" (texel sum over ``texels``).
    """

    texels: jax.Array
    rotation: jax.Array
    sh: jax.Array
    poles: jax.Array
    atlas: jax.Array
    spectral_basis: jax.Array
    source_dirs: jax.Array
    source_flux: jax.Array
    level_sigma: jax.Array
    product_tensor: jax.Array | None
    level_shapes: tuple[tuple[int, int], ...] = eqx.field(static=True)
    level_offsets: tuple[int, ...] = eqx.field(static=True)
    quadrature: GlossQuadrature = eqx.field(static=True, default=GlossQuadrature())
    diffuse: str = eqx.field(static=True, default="sh")
    source_tent_dirs: jax.Array | None = None
    source_fine_dirs: jax.Array | None = None
    source_fine_weights: jax.Array | None = None
    source_flux_full: jax.Array | None = None
    source_render_dirs: jax.Array | None = None
    source_render_weights: jax.Array | None = None
    fine_texels: jax.Array | None = None

    @property
    def channels(self) -> int:
        return int(self.texels.shape[-1])

    @classmethod
    def from_array(
        cls,
        texels: Any,
        *,
        rotation: Any = None,
        rotation_y_deg: float = 0.0,
        product_tensor: Any = None,
        quadrature: GlossQuadrature | None = None,
        diffuse: str = "sh",
        compress_tol: float = 1e-4,
        allow_negative: bool | None = None,
        dtype: Any = jnp.float32,
        path: str | None = None,
    ) -> EnvironmentMap:
        """Validate and precompute an environment.

        Args:
            texels: (H, W, C) radiance bands or basis coefficients; H >= 4, W >= 8, finite.
            rotation: (3, 3) world-from-map rotation (orthonormal, det +1); applied after
                ``rotation_y_deg`` (the total is ``rotation @ rotation_y(rotation_y_deg)``).
            rotation_y_deg: rotation about +Y (180 for maps with −Z at the image centre).
            product_tensor: (K, K, K) from :attr:`SpectralBasis.product_tensor` when the
                channels are basis coefficients (needed for the diffuse S·E product).
            compress_tol: largest relative error (per texel, Euclidean over channels) allowed
                when the prefiltered maps are stored in the map's own principal spectra (the
                gloss integral is linear in the map, so this bounds its relative error too,
                per texel contribution); 0 keeps all channels.
            allow_negative: accept negative texels (default: only in coefficient mode).
            path: named in error messages (the map's file).
        """
        try:
            img = np.asarray(texels, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(f"not numeric ({exc})", path=path, field="environment") from None
        if img.ndim != 3 or img.shape[0] < 4 or img.shape[1] < 8 or img.shape[2] < 1:
            raise InputError(f"expected an (H, W, C) map with H >= 4, W >= 8, got {img.shape}",
                             path=path, field="environment")
        if not np.all(np.isfinite(img)):
            raise InputError("NaN or infinite texels", path=path, field="environment")
        if allow_negative is None:
            allow_negative = product_tensor is not None
        if not allow_negative and np.any(img < 0):
            raise InputError(f"negative radiance {img.min():g}", path=path, field="environment")
        if diffuse not in ("sh", "exact"):
            raise InputError(f"diffuse must be 'sh' or 'exact', got {diffuse!r}",
                             field="diffuse")
        R = rotation_y(rotation_y_deg)
        if rotation is not None:
            Rg = np.asarray(rotation, dtype=np.float64)
            if (Rg.shape != (3, 3) or not np.all(np.isfinite(Rg))
                    or not np.allclose(Rg @ Rg.T, np.eye(3), atol=1e-5)
                    or np.linalg.det(Rg) < 0):
                raise InputError("must be a proper 3×3 rotation matrix", path=path,
                                 field="rotation")
            R = Rg @ R
        pt = None
        if product_tensor is not None:
            pt = np.asarray(product_tensor, dtype=np.float64)
            k = img.shape[2]
            if pt.shape != (k, k, k) or not np.all(np.isfinite(pt)):
                raise InputError(f"expected a finite ({k}, {k}, {k}) tensor, got {pt.shape}",
                                 path=path, field="product_tensor")
        quad = quadrature or GlossQuadrature()
        if quad.nodes not in ("grid", "visible", "gauss"):
            raise InputError(f"must be 'grid', 'visible' or 'gauss', got {quad.nodes!r}",
                             field="quadrature.nodes")
        if not 0.0 < quad.texel_sum_from < quad.texel_sum_full:
            raise InputError("need 0 < texel_sum_from < texel_sum_full, got "
                             f"{quad.texel_sum_from!r}, {quad.texel_sum_full!r}",
                             field="quadrature.texel_sum_from")
        if not (isinstance(quad.tent_points, int) and quad.tent_points >= 1):
            raise InputError(f"must be an integer >= 1, got {quad.tent_points!r}",
                             field="quadrature.tent_points")
        if not (isinstance(quad.texel_sum_supersample, int)
                and 1 <= quad.texel_sum_supersample <= 4):
            raise InputError(f"must be an integer in 1..4, got {quad.texel_sum_supersample!r}",
                             field="quadrature.texel_sum_supersample")
        if not (isinstance(quad.tent_gauss, int) and quad.tent_gauss >= 1):
            raise InputError(f"must be an integer >= 1, got {quad.tent_gauss!r}",
                             field="quadrature.tent_gauss")
        if quad.source_subpoints not in (1, 4):
            raise InputError(f"must be 1 or 4, got {quad.source_subpoints!r}",
                             field="quadrature.source_subpoints")
        residual, sdirs, sflux = _extract_sources(img, quad.max_sources,
                                                  quad.source_threshold, quad.source_subpoints)
        scells = _source_cells(img, quad.max_sources, quad.source_threshold)
        levels, sigmas = _build_levels(residual, quad.levels)
        if not (compress_tol >= 0 and math.isfinite(compress_tol)):
            raise InputError(f"must be finite and >= 0, got {compress_tol!r}",
                             field="compress_tol")
        atlas, shapes, offsets = level_atlas(levels)
        fine_dirs, fine_w = _tent_gauss_subpoints(img.shape[0], img.shape[1], scells,
                                                  quad.tent_gauss)
        rdirs, rw = _tent_gauss_subpoints(img.shape[0], img.shape[1], scells, 1)
        pbasis = _spectral_basis(np.concatenate([atlas, sflux]), compress_tol)
        atlas_r = atlas @ pbasis.T
        env = cls(
            texels=jnp.asarray(img, dtype),
            rotation=jnp.asarray(R, dtype),
            sh=jnp.asarray(sh_coefficients(img), dtype),
            poles=jnp.asarray(np.stack([img[0].mean(axis=0), img[-1].mean(axis=0)]), dtype),
            atlas=jnp.asarray(atlas_r, dtype),
            spectral_basis=jnp.asarray(pbasis, dtype),
            source_dirs=jnp.asarray(sdirs, dtype),
            source_flux=jnp.asarray(sflux @ pbasis.T, dtype),
            level_sigma=jnp.asarray(sigmas, dtype),
            product_tensor=None if pt is None else jnp.asarray(pt, dtype),
            level_shapes=tuple(shapes),
            level_offsets=tuple(offsets),
            quadrature=quad,
            diffuse=diffuse,
            source_tent_dirs=jnp.asarray(_tent_subpoints(img.shape[0], img.shape[1], scells,
                                                         quad.tent_points), dtype),
            source_fine_dirs=jnp.asarray(fine_dirs, dtype),
            source_fine_weights=jnp.asarray(fine_w, dtype),
            source_flux_full=jnp.asarray(sflux * sdirs.shape[1], dtype),
            source_render_dirs=jnp.asarray(rdirs, dtype),
            source_render_weights=jnp.asarray(rw, dtype),
        )
        ss = quad.texel_sum_supersample
        fine = jnp.asarray(texel_directions(img.shape[0] * ss, img.shape[1] * ss).reshape(-1, 3),
                           dtype)
        fine_texels = jax.jit(jax.vmap(lambda d, e=env: lookup_level(e, 0, d)))(fine)
        return eqx.tree_at(lambda e: e.fine_texels, env, fine_texels,
                           is_leaf=lambda x: x is None)


def lookup_level(env: EnvironmentMap, level: Any, d_map: Any,
                 uv: tuple[jax.Array, jax.Array] | None = None) -> jax.Array:
    """Bilinear lookup (r,) of prefiltered level ``level`` (traced int) of the residual map
    along map-frame unit direction ``d_map`` (3,), in the channels of ``env.spectral_basis``."""
    shapes = np.asarray(env.level_shapes, dtype=np.int32)
    hk = jnp.asarray(shapes[:, 0])[level]
    wk = jnp.asarray(shapes[:, 1])[level]
    off = jnp.asarray(np.asarray(env.level_offsets, dtype=np.int32))[level]
    return _bilinear(env.atlas, off, hk, wk, d_map, uv)


def _bilinear(flat: jax.Array, off: Any, hk: Any, wk: Any, d_map: Any,
              uv: tuple[jax.Array, jax.Array] | None = None) -> jax.Array:
    """Bilinear lookup in an (hk, wk) map stored row-major at ``flat[off:]`` and followed by its
    north and south pole means (``uv``: the direction's (u, v) if already known). Wraps in u;
    between the first (last) row centre and the pole it blends linearly towards the row's mean,
    placed at the pole, so the lookup is continuous on the whole sphere."""
    hk = jnp.asarray(hk, jnp.int32)
    wk = jnp.asarray(wk, jnp.int32)
    u, v = direction_to_uv(d_map) if uv is None else uv
    dtype = flat.dtype
    idx, w = bilinear_taps(u.astype(dtype), v.astype(dtype), off, hk, wk, lead=True)
    return jnp.einsum("i,ic->c", w, flat.at[idx].get(mode="promise_in_bounds"))


def _lookup_blend(env: EnvironmentMap, u: jax.Array, v: jax.Array, lo: jax.Array,
                  hi: jax.Array, w_hi: jax.Array) -> jax.Array:
    """(1 − w_hi)·level lo + w_hi·level hi, bilinear, at map coordinates (u, v) (M,): all eight
    taps of a node gathered at once from the atlas. Returns (M, r)."""
    shapes = [(int(h), int(w)) for h, w in env.level_shapes]
    lev = jnp.stack([lo, hi], axis=-1)  # (M, 2)
    hk = select_static([np.int32(h) for h, _ in shapes], lev)
    wk = select_static([np.int32(w) for _, w in shapes], lev)
    off = select_static([np.int32(o) for o in env.level_offsets], lev)
    idx, w = bilinear_taps(u[:, None], v[:, None], off, hk, wk)  # (M, 2, 4)
    w = w * jnp.stack([1.0 - w_hi, w_hi], axis=-1)[..., None]
    taps = env.atlas.at[idx.reshape(-1)].get(mode="promise_in_bounds")
    return jnp.einsum("mk,mkc->mc", w.reshape(-1, 8), taps.reshape(-1, 8, taps.shape[-1]))


def _to_map(env: EnvironmentMap, direction: jax.Array) -> jax.Array:
    return direction @ env.rotation  # = Rᵀ ω for a row vector


def lookup(env: EnvironmentMap, direction: Any) -> jax.Array:
    """Radiance (C,) of the unfiltered map along the world unit direction (3,) (bilinear)."""
    h, w, c = env.texels.shape
    flat = jnp.concatenate([env.texels.reshape(h * w, c), env.poles])
    return _bilinear(flat, 0, h, w, _to_map(env, jnp.asarray(direction)))


def fast_lookup(env: EnvironmentMap, direction: Any) -> jax.Array:
    """:func:`lookup` (bilinear, unfiltered map) with :func:`fast_direction_to_uv`, batched:
    world unit directions (..., 3) → (..., C)."""
    h, w, c = env.texels.shape
    flat = jnp.concatenate([env.texels.reshape(h * w, c), env.poles])
    u, v = fast_direction_to_uv(to_map_fast(env, jnp.asarray(direction)))
    if u.ndim:  # batched: compute (u, v) once, not inside every tap's index arithmetic
        u, v = materialise_each(u, v)
    return taps_sum(flat, *bilinear_taps(u, v, jnp.int32(0), jnp.int32(h), jnp.int32(w),
                                           lead=True), lead=True)


def to_map_fast(env: EnvironmentMap, d: jax.Array) -> jax.Array:
    """:func:`_to_map` (d @ R, d (..., 3)) by components."""
    r = env.rotation
    return jnp.stack([d[..., 0] * r[0, j] + d[..., 1] * r[1, j] + d[..., 2] * r[2, j]
                      for j in range(3)], axis=-1)


def levels_for(env: EnvironmentMap, target: jax.Array
                ) -> tuple[Any, Any, jax.Array, jax.Array]:
    """Two adjacent prefilter levels (lo, hi), the weight of hi, and the effective prefilter
    variance σ² = (1 − w)σ_lo² + w σ_hi², for a target std ``target``. The weight is a C²
    function of log σ_target (quintic smoothstep), so the result is C² in the target."""
    sig = env.level_sigma
    m = sig.shape[0]
    s1 = sig[1]
    t = jnp.log2(jnp.maximum(target, 1e-30) / s1)
    below = t < 0.0
    k = jnp.clip(jnp.floor(t), 0, m - 3).astype(jnp.int32)
    frac_log = t - k.astype(t.dtype)
    lo = jnp.where(below, 0, k + 1)
    hi = jnp.where(below, 1, k + 2)
    w = jnp.where(below, smootherstep(target / s1), smootherstep(frac_log))
    var = (1.0 - w) * sig[lo] ** 2 + w * sig[hi] ** 2
    return lo, hi, w, var
