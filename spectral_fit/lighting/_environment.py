"""Spectral environment lighting on equirectangular maps, and shading under it (eq. 5).

Map convention (docs/conventions.md, 'Conventions'): texel (row k, column j) of an (H, W, C) map
has its centre at v = (k + 0.5)/H, u = (j + 0.5)/W, with polar angle θ = πv from +Y and azimuth
φ = 2πu, direction

    d = (sinφ sinθ, cosθ, −cosφ sinθ)        (row 0 at the top, i.e. around +Y).

C channels are spectral bands (radiance, W·sr⁻¹·m⁻²·nm⁻¹) or K basis coefficients of it. A map is
placed in the world by a rotation R (world-from-map): the world direction ω is looked up at
d = Rᵀω. Maps that put −Z at the image centre need a 180° rotation about +Y.

Lighting integrals (all linear in the map, so they run channel by channel):

- irradiance E(N) = ∫ L(ω) max(0, N·ω) dω by order-2 spherical harmonics (Ramamoorthi &
  Hanrahan 2001; 9 coefficients per channel), or exactly by a texel sum with exact texel solid
  angles Δφ (cosθ_top − cosθ_bottom);
- gloss ∫ L(ω) F(n, θd) D(μ, θh) G / (4 cosθr) dω (without β), by a fixed quadrature in the
  half-vector lobe frame on a prefiltered map (see :func:`gloss_integral`);
- mirror F(n, θr) L(R), R = reflect(−V, N), by a bilinear lookup of the unfiltered map.

The lookup is bilinear, wraps in u (seam), and near the poles blends towards the mean of the first
/ last row placed at the pole itself, so it is continuous everywhere on the sphere.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.backend import materialise as _materialise
from .._runtime.backend import materialise_each
from .._runtime.errors import InputError
from ._reflectance import (
    Material,
    beckmann_d,
    fresnel_dielectric,
    gaussian_d,
    gaussian_normalisation,
    smith_g,
    vcavity_g,
)

__all__ = [
    "white_reference",
    "SH_C1",
    "SH_C2",
    "SH_C3",
    "SH_C4",
    "SH_C5",
    "GlossQuadrature",
    "QUALITIES",
    "EnvironmentMap",
    "rotation_y",
    "texel_directions",
    "texel_solid_angles",
    "direction_to_uv",
    "uv_to_direction",
    "lookup",
    "lookup_level",
    "sh_coefficients",
    "irradiance_sh",
    "irradiance_exact",
    "irradiance",
    "gloss_integral",
    "mirror_radiance",
    "shade",
    "shade_points",
    "synthetic_environment",
    "SplitSum",
    "SplitSumMap",
    "fast_direction_to_uv",
    "fast_lookup",
    "lobe_moment_table",
    "gloss_split_sum",
    "atan2_poly",
    "bilinear_taps",
    "dot3",
    "levels_for",
    "lobe_albedo",
    "lobe_factor",
    "select_static",
    "sincos_poly",
    "smootherstep",
    "taps_sum",
    "to_map_fast",
    "visible_nodes",
    "uv_of",
    "padded_bilinear",
    "padded_table",
]

# Ramamoorthi & Hanrahan 2001, eq. 13.
SH_C1 = 0.429043
SH_C2 = 0.511664
SH_C3 = 0.743125
SH_C4 = 0.886227
SH_C5 = 0.247708


# --------------------------------------------------------------------------------------------
# Geometry of the equirectangular map (NumPy and JAX)


def rotation_y(degrees: float) -> np.ndarray:
    """Rotation matrix (3, 3) by ``degrees`` about +Y (right-handed: +Z turns towards +X)."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def uv_to_direction(u: Any, v: Any) -> np.ndarray:
    """Direction (..., 3) of map coordinates u = φ/2π, v = θ/π (NumPy, float64)."""
    phi, theta = np.broadcast_arrays(2.0 * np.pi * np.asarray(u, np.float64),
                                     np.pi * np.asarray(v, np.float64))
    st = np.sin(theta)
    return np.stack([np.sin(phi) * st, np.cos(theta), -np.cos(phi) * st], axis=-1)


def texel_directions(height: int, width: int) -> np.ndarray:
    """Directions (H, W, 3) of texel centres (float64)."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    return uv_to_direction(u[None, :], v[:, None])


def texel_solid_angles(height: int, width: int) -> np.ndarray:
    """Exact solid angles (H, W) of the texels, Δφ (cosθ_top − cosθ_bottom); they sum to 4π."""
    edges = np.cos(np.pi * np.arange(height + 1) / height)
    rows = (2.0 * np.pi / width) * (edges[:-1] - edges[1:])
    return np.broadcast_to(rows[:, None], (height, width)).copy()


def direction_to_uv(d: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(u, v) in [0, 1) × [0, 1] of unit directions (..., 3) in the map frame (JAX).

    Gradient-safe at the poles (the azimuth is then arbitrary, and has zero gradient).
    """
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    rho2 = x * x + z * z
    small = rho2 < 1e-20
    rho = jnp.sqrt(jnp.where(small, 1.0, rho2))
    rho = jnp.where(small, 0.0, rho)
    theta = jnp.arctan2(rho, y)
    phi = jnp.arctan2(jnp.where(small, 0.0, x), jnp.where(small, 1.0, -z))
    u = jnp.mod(phi / (2.0 * math.pi), 1.0)
    return u, theta / math.pi


# --------------------------------------------------------------------------------------------
# Prefiltering (NumPy, at construction)


def _downsample2(img: np.ndarray) -> np.ndarray:
    """Halve an (H, W, C) equirectangular map by solid-angle-weighted 2×2 averaging."""
    h, w = img.shape[:2]
    sa = texel_solid_angles(h, w)[:, :1]  # (H, 1)
    pair = img.reshape(h // 2, 2, w // 2, 2, -1).mean(axis=3)  # columns: equal solid angle
    wgt = sa.reshape(h // 2, 2, 1, 1)
    return (pair * wgt).sum(axis=1) / wgt.sum(axis=1)


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
        source_tent_dirs: (S, 16, 3) map-frame directions of 16 equal-weight points of each
            source texel's footprint in the bilinear map (the tent over ±1 texel), used by
            the radiance cache (None: ``source_dirs``).
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
        flat, shapes, offsets = [], [], []
        off = 0
        for lev in levels:
            h, w, c = lev.shape
            poles = np.stack([lev[0].mean(axis=0), lev[-1].mean(axis=0)])
            flat.append(np.concatenate([lev.reshape(h * w, c), poles]))
            shapes.append((h, w))
            offsets.append(off)
            off += h * w + 2
        atlas = np.concatenate(flat)
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


def _spectral_basis(x: np.ndarray, tol: float) -> np.ndarray:
    """Orthonormal principal spectra (r, C) of the rows of ``x`` (uncentred), with r the least
    for which every row's relative reconstruction error is <= ``tol`` (rows below 1e-9 of the
    largest norm ignored). ``tol`` = 0 returns the identity."""
    c = x.shape[1]
    if tol <= 0:
        return np.eye(c)
    _, _, vt = np.linalg.svd(x.T @ x)
    vt = vt * np.where(vt.sum(axis=1, keepdims=True) < 0, -1.0, 1.0)
    coef2 = (x @ vt.T) ** 2  # (T, C)
    norm2 = np.sum(x * x, axis=1)
    keep = norm2 > 1e-18 * norm2.max() if norm2.max() > 0 else np.zeros_like(norm2, bool)
    if not keep.any():
        return vt[:1]
    resid = norm2[keep, None] - np.cumsum(coef2[keep], axis=1)  # error² after r components
    worst = np.max(resid / norm2[keep, None], axis=0)
    ok = np.nonzero(worst <= tol * tol)[0]
    r = int(ok[0]) + 1 if ok.size else c
    return vt[:r]


def _extract_sources(img: np.ndarray, max_sources: int, threshold: float, subpoints: int = 4
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split the map into a residual without compact bright sources plus explicit source texels.

    A texel is a source when its channel-summed |value| exceeds ``threshold`` × the map's mean
    (at most ``max_sources``, brightest first). Its residual value is the mean of the non-source
    texels in its 5×5 neighbourhood (wrapping in u); the excess (value − residual) × solid angle
    is carried by 4 sub-points at (±¼, ±¼) texel offsets (``subpoints`` = 4) or by the texel
    centre (1). Residual + sources = the map exactly, and the residual is smooth enough for the
    prefiltered lobe quadrature."""
    h, w, c = img.shape
    cand = _source_cells(img, max_sources, threshold)
    if cand.shape[0] == 0:
        return img, np.zeros((0, subpoints, 3)), np.zeros((0, c))
    sa = texel_solid_angles(h, w)
    is_src = np.zeros((h, w), bool)
    is_src[cand[:, 0], cand[:, 1]] = True
    residual = img.copy()
    for r, col in cand:
        rows = np.clip(np.arange(r - 2, r + 3), 0, h - 1)
        cols = np.arange(col - 2, col + 3) % w
        mask = ~is_src[np.ix_(rows, cols)]
        block = img[np.ix_(rows, cols)]
        residual[r, col] = block[mask].mean(axis=0) if mask.any() else np.median(
            img.reshape(-1, c), axis=0)
    excess = (img - residual)[cand[:, 0], cand[:, 1]] * sa[cand[:, 0], cand[:, 1]][:, None]
    offs = (np.array([[-0.25, -0.25], [-0.25, 0.25], [0.25, -0.25], [0.25, 0.25]])
            if subpoints == 4 else np.zeros((1, 2)))
    v = (cand[:, 0:1] + 0.5 + offs[None, :, 0]) / h
    u = (cand[:, 1:2] + 0.5 + offs[None, :, 1]) / w
    return residual, uv_to_direction(u, v), excess / subpoints


def _source_cells(img: np.ndarray, max_sources: int, threshold: float) -> np.ndarray:
    """(S, 2) rows and columns of the source texels of :func:`_extract_sources`: channel-summed
    |value| above ``threshold`` × the map's solid-angle-weighted mean, brightest first, at most
    ``max_sources``."""
    h, w, _ = img.shape
    sa = texel_solid_angles(h, w)
    lum = np.abs(img).sum(axis=-1)
    mean = (lum * sa).sum() / sa.sum()
    cand = np.argwhere(lum > threshold * max(mean, 1e-300))
    if max_sources <= 0 or cand.size == 0:
        return np.zeros((0, 2), int)
    return cand[np.argsort(-lum[cand[:, 0], cand[:, 1]])[:max_sources]]


def _tent_points(m: int) -> np.ndarray:
    """m equal-weight points of the tent (1 − |x|) on [−1, 1] (texels): the mid-quantiles
    (i + ½)/m of its distribution (m = 4: ±0.134, ±0.5)."""
    q = (np.arange(m) + 0.5) / m
    return np.where(q < 0.5, np.sqrt(2.0 * q) - 1.0, 1.0 - np.sqrt(2.0 * (1.0 - q)))


def _tent_subpoints(h: int, w: int, cells: np.ndarray, m: int = 4) -> np.ndarray:
    """(S, m², 3) map-frame directions of m × m equal-weight points of each source texel's
    footprint in the bilinear reconstruction of the map (the tent over ±1 texel around its
    centre, in u and v): a texel's excess radiance E spreads as E·tent, whose integral is E
    times about the texel's solid angle, so each point carries 1/m² of the excess flux."""
    if cells.shape[0] == 0:
        return np.zeros((0, m * m, 3))
    x = _tent_points(m)
    dv, du = np.meshgrid(x, x, indexing="ij")
    v = np.clip((cells[:, 0:1] + 0.5 + dv.reshape(1, -1)) / h, 0.0, 1.0)
    u = (cells[:, 1:2] + 0.5 + du.reshape(1, -1)) / w
    return uv_to_direction(u, v)


def _tent_gauss_rule(m: int) -> tuple[np.ndarray, np.ndarray]:
    """2m nodes and weights (summing to 1) on [−1, 1] for the weight 1 − |x| (the tent):
    Gauss–Jacobi (α = 1, β = 0) on each half, exact for polynomials of degree 2m − 1 on
    each linear piece (the tent's kink at 0 falls between the halves)."""
    from scipy.special import roots_jacobi

    x, w = roots_jacobi(m, 1.0, 0.0)  # weight (1 − x) on [−1, 1]
    t, wt = 0.5 * (x + 1.0), 0.25 * w  # weight (1 − t) on [0, 1]; Σ wt = ½
    return np.concatenate([-t[::-1], t]), np.concatenate([wt[::-1], wt])


def _tent_gauss_subpoints(h: int, w: int, cells: np.ndarray, m: int = 4
                          ) -> tuple[np.ndarray, np.ndarray]:
    """(S, 4m², 3) map-frame directions and (S, 4m²) weights of a product Gauss rule over each
    source texel's footprint in the bilinear map: its excess radiance E spreads as
    E·tent(Δu)·tent(Δv) (texel units, ±1 texel), so its flux is E ∫ tent tent dω with
    dω = sinθ dθ dφ. The weights are w_u w_v sinθ_k (π/H)(2π/W) divided by the texel's solid
    angle, i.e. each point's share of the flux E·Δω_texel that ``source_flux`` carries (their
    sum is 1 up to the variation of sinθ across the footprint). Points beyond a pole are
    dropped (zero weight)."""
    x, wx = _tent_gauss_rule(m)
    k = x.size
    if cells.shape[0] == 0:
        return np.zeros((0, k * k, 3)), np.zeros((0, k * k))
    dv, du = np.meshgrid(x, x, indexing="ij")
    wv, wu = np.meshgrid(wx, wx, indexing="ij")
    v = (cells[:, 0:1] + 0.5 + dv.reshape(1, -1)) / h
    u = (cells[:, 1:2] + 0.5 + du.reshape(1, -1)) / w
    inside = (v > 0.0) & (v < 1.0)
    v = np.clip(v, 0.0, 1.0)
    sa = texel_solid_angles(h, w)[cells[:, 0], 0][:, None]
    wgt = (wv * wu).reshape(1, -1) * np.sin(np.pi * v) * (2.0 * np.pi * np.pi / (h * w)) / sa
    return uv_to_direction(u, v), np.where(inside, wgt, 0.0)


def _sphere_blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """Isotropic Gaussian blur of an (H, W, C) equirectangular map on the sphere: every output
    texel is the solid-angle-weighted mean of all texels with weights exp(−γ²/2σ²), γ the great
    circle angle between texel centres. The weights between two rows depend only on the azimuth
    difference (a circulant), so each row pair is a circular convolution, done by FFT along the
    rows: exact on the texel-centre sampling, at any latitude and across the poles."""
    if sigma <= 0:
        return img
    h, w, c = img.shape
    theta = np.pi * (np.arange(h) + 0.5) / h
    phi = 2.0 * np.pi * np.arange(w) / w
    ct, st = np.cos(theta), np.sin(theta)
    cosg = (ct[:, None, None] * ct[None, :, None]
            + st[:, None, None] * st[None, :, None] * np.cos(phi)[None, None, :])
    gamma = np.arccos(np.clip(cosg, -1.0, 1.0))
    k = np.exp(-0.5 * (gamma / sigma) ** 2) * st[None, :, None]  # (H_out, H_in, W)
    norm = k.sum(axis=(1, 2))  # (H_out,)
    kf = np.fft.rfft(k, axis=2)  # (H, H, W/2+1)
    ff = np.fft.rfft(img, axis=1)  # (H, W/2+1, C)
    # out_i(φ) = Σ_j Σ_φ' k_ij(φ − φ') img_j(φ')  (k is even in φ)
    of = np.matmul(kf.transpose(2, 0, 1), ff.transpose(1, 0, 2))  # (W/2+1, H, C)
    out = np.fft.irfft(of.transpose(1, 0, 2), n=w, axis=1)
    return out / norm[:, None, None]


def _sphere_blur_many(img: np.ndarray, sigmas: list[float]) -> list[np.ndarray]:
    """:func:`_sphere_blur` of one map at several stds, sharing the great-circle angles
    between texel rows and the map's FFT (same result as separate calls)."""
    h, w, c = img.shape
    theta = np.pi * (np.arange(h) + 0.5) / h
    phi = 2.0 * np.pi * np.arange(w) / w
    ct, st = np.cos(theta), np.sin(theta)
    cosg = (ct[:, None, None] * ct[None, :, None]
            + st[:, None, None] * st[None, :, None] * np.cos(phi)[None, None, :])
    gamma2 = np.arccos(np.clip(cosg, -1.0, 1.0)) ** 2
    ff = np.fft.rfft(img, axis=1).transpose(1, 0, 2)  # (W/2+1, H, C)
    out = []
    for sigma in sigmas:
        if sigma <= 0:
            out.append(img)
            continue
        k = np.exp(-0.5 * gamma2 / (sigma * sigma)) * st[None, :, None]
        norm = k.sum(axis=(1, 2))
        of = np.matmul(np.fft.rfft(k, axis=2).transpose(2, 0, 1), ff)
        out.append(np.fft.irfft(of.transpose(1, 0, 2), n=w, axis=1) / norm[:, None, None])
    return out


def _build_levels(img: np.ndarray, n_levels: int) -> tuple[list[np.ndarray], np.ndarray]:
    """Level 0 = the map; level k >= 1: blurred to std σ_k = Δ·2^(k−1) (Δ = π/H, one texel)
    by an exact spherical Gaussian (:func:`_sphere_blur`), stored at the coarsest resolution
    (halvings of the map) with texels <= σ_k/2. Each level is made from the map itself: halved
    by solid-angle-weighted 2×2 averages (each halving adds the variance Δ_new²/16 of a pair
    average), then blurred by the rest of the variance."""
    h0 = img.shape[0]
    delta = math.pi / h0
    levels, sigmas = [img], [0.0]
    cur, var = img, 0.0
    for k in range(1, n_levels + 1):
        sigma = delta * 2.0 ** (k - 1)
        while (cur.shape[0] % 2 == 0 and cur.shape[1] % 2 == 0 and cur.shape[0] >= 8
               and 2.0 * math.pi / cur.shape[0] <= sigma / 2.0 + 1e-12):
            d_new = 2.0 * math.pi / cur.shape[0]
            if var + d_new**2 / 16.0 > sigma**2:
                break
            cur = _downsample2(cur)
            var += d_new**2 / 16.0  # a pair average of texels Δ_new/2 apart
        levels.append(_sphere_blur(cur, math.sqrt(max(sigma**2 - var, 0.0))))
        sigmas.append(sigma)
    return levels, np.asarray(sigmas)


# --------------------------------------------------------------------------------------------
# Lookup (JAX)


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


def _wrap(i: jax.Array, w: jax.Array) -> jax.Array:
    """``i mod w`` for ``i`` in [−w, 2w) (a texel column one beyond either edge), by selects:
    ``jnp.mod`` with a per-lookup ``w`` (the level's width) is an integer division per element
    on the CPU. Clipped to [0, w − 1] outside that range (e.g. a NaN coordinate), so a
    gather with it stays in bounds."""
    i = jnp.where(i < 0, i + w, i)
    return jnp.clip(jnp.where(i >= w, i - w, i), 0, w - 1)


def _tap_coords(u: jax.Array, v: jax.Array, hk: jax.Array, wk: jax.Array
                ) -> tuple[jax.Array, ...]:
    """The texel coordinates of a bilinear lookup at map coordinates (u, v) in a level of
    (hk, wk) texels (int32, scalars or per lookup): the column x0 (wrapped into [0, wk)), its
    weight fx towards x0 + 1, the row y0 (−1 above the first row centre, hk − 1 below the
    last), the flags north (y0 < 0) and south (y0 ≥ hk − 1), and the weight wy1 of row
    y0 + 1, blended linearly towards the pole mean past the first and last row centres."""
    dtype = u.dtype
    tx = u * wk.astype(dtype) - 0.5
    ty = v * hk.astype(dtype) - 0.5
    x0f = jnp.floor(tx)
    fx = tx - x0f
    x0 = _wrap(x0f.astype(jnp.int32), wk)
    y0f = jnp.floor(ty)
    fy = ty - y0f
    y0 = y0f.astype(jnp.int32)
    north = y0 < 0
    south = y0 >= hk - 1
    wy1 = jnp.clip(jnp.where(north, 2.0 * fy - 1.0, jnp.where(south, 2.0 * fy, fy)), 0.0, 1.0)
    return x0, fx, y0, north, south, wy1


def bilinear_taps(u: jax.Array, v: jax.Array, off: jax.Array, hk: jax.Array, wk: jax.Array,
                   *, lead: bool = False) -> tuple[jax.Array, jax.Array]:
    """Atlas rows (..., 4) and weights (..., 4) of the bilinear lookup of :func:`_bilinear`
    (wrapped in u; between the first (last) row centre and the pole blended linearly towards
    the pole mean stored after the level), elementwise in (u, v) and the level's (off, hk, wk).
    ``lead``: as (4, ...) instead, for :func:`taps_sum` with ``lead`` (a stack on the last
    axis is a concatenate XLA:CPU writes element by element, which is slower)."""
    x0, fx, y0, north, south, wy1 = _tap_coords(u, v, hk, wk)
    x1 = jnp.where(x0 + 1 >= wk, 0, x0 + 1)
    r0 = off + jnp.clip(y0, 0, hk - 1) * wk
    r1 = off + jnp.clip(y0 + 1, 0, hk - 1) * wk
    pole_n = off + hk * wk
    ax = 0 if lead else -1
    idx = jnp.stack([jnp.where(north, pole_n, r0 + x0), jnp.where(north, pole_n, r0 + x1),
                     jnp.where(south, pole_n + 1, r1 + x0),
                     jnp.where(south, pole_n + 1, r1 + x1)], axis=ax)
    w = jnp.stack([(1 - wy1) * (1 - fx), (1 - wy1) * fx, wy1 * (1 - fx), wy1 * fx], axis=ax)
    return idx, w


def padded_table(flat: jax.Array, hm: int, wm: int) -> jax.Array:
    """A map's table laid out for :func:`padded_bilinear`: ``flat`` ((Hm·Wm + 2, C), the
    texels then the north and south pole means, as :func:`bilinear_taps` reads it) as
    (Hm + 2) rows of (Wm + 1) texels: a row of the north pole mean, the map's rows, a row of
    the south pole mean, each row followed by a copy of its first texel (the wrap in u).
    Returns ((Hm + 2)·(Wm + 1), C)."""
    c = flat.shape[-1]
    tex = flat[:hm * wm].reshape(hm, wm, c)
    rows = jnp.concatenate([jnp.broadcast_to(flat[hm * wm], (1, wm, c)), tex,
                            jnp.broadcast_to(flat[hm * wm + 1], (1, wm, c))])
    return jnp.concatenate([rows, rows[:, :1]], axis=1).reshape(-1, c)


def padded_bilinear(table: jax.Array, u: jax.Array, v: jax.Array, hm: int, wm: int
                    ) -> jax.Array:
    """The bilinear lookup of :func:`bilinear_taps` + :func:`taps_sum` (one level of size
    (Hm, Wm); wrapped in u, blended towards the pole means past the first and last row
    centres) at map coordinates u, v (N,), from :func:`padded_table`'s layout: the four taps
    are the texels at b, b + 1, b + Wm + 1 and b + Wm + 2 of one base index b, so the index
    arithmetic (done again for every channel of the result) is a third of the general one's.
    The same texels, weights and summation order: bit-identical to the general lookup, and
    cheaper for the frame's background. Returns (N, C)."""
    wp = wm + 1
    x0, fx, y0, _, _, wy1 = _tap_coords(u, v, jnp.int32(hm), jnp.int32(wm))
    base = (jnp.clip(y0, -1, hm - 1) + 1) * wp + x0
    out = table.at[base].get(mode="promise_in_bounds") * ((1 - wy1) * (1 - fx))[..., None]
    out = out + table.at[base + 1].get(mode="promise_in_bounds") * ((1 - wy1) * fx)[..., None]
    out = out + table.at[base + wp].get(mode="promise_in_bounds") * (wy1 * (1 - fx))[..., None]
    return out + table.at[base + wp + 1].get(mode="promise_in_bounds") * (wy1 * fx)[..., None]


def select_static(table: Any, index: jax.Array) -> jax.Array:
    """``table[index]`` for a short static table and an index in range, as masked constants
    (elementwise, so it fuses into the surrounding arithmetic instead of becoming a
    gather)."""
    out = jnp.full(index.shape, table[0])
    for k in range(1, len(table)):
        out = jnp.where(index == k, table[k], out)
    return out


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


# --------------------------------------------------------------------------------------------
# Irradiance


def _sh_basis(d: np.ndarray) -> np.ndarray:
    """Real SH basis functions up to l = 2 (R&H 2001 order: Y00, Y1-1, Y10, Y11, Y2-2, Y2-1,
    Y20, Y21, Y22) at directions (..., 3) in the map frame, with R&H's (x, y, z) = (d_x, d_y,
    d_z) (the basis is complete at each order, so the frame does not matter)."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return np.stack([
        0.282095 * np.ones_like(x),
        0.488603 * y, 0.488603 * z, 0.488603 * x,
        1.092548 * x * y, 1.092548 * y * z, 0.315392 * (3 * z * z - 1),
        1.092548 * x * z, 0.546274 * (x * x - y * y),
    ], axis=-1)


def sh_coefficients(texels: np.ndarray) -> np.ndarray:
    """SH coefficients L_lm (9, C) of an (H, W, C) map, NumPy float64.

    Each texel is a box of constant radiance; the basis functions are integrated over it with
    3 × 3 Gauss–Legendre points in (cosθ, φ) (area-uniform coordinates), so a uniform map gives
    exactly L_00 = √(4π) and zero higher coefficients."""
    h, w = texels.shape[:2]
    x, wx = np.polynomial.legendre.leggauss(3)
    x, wx = 0.5 * (x + 1.0), 0.5 * wx
    edges = np.cos(np.pi * np.arange(h + 1) / h)  # cosθ at row edges, decreasing
    Y = np.zeros((h, w, 9))
    for xi, wi in zip(x, wx, strict=True):
        cos_t = edges[:-1] + (edges[1:] - edges[:-1]) * xi  # (H,)
        sin_t = np.sqrt(np.maximum(1.0 - cos_t**2, 0.0))
        for xj, wj in zip(x, wx, strict=True):
            phi = 2.0 * np.pi * (np.arange(w) + xj) / w
            d = np.stack(np.broadcast_arrays(
                np.sin(phi)[None, :] * sin_t[:, None], cos_t[:, None],
                -np.cos(phi)[None, :] * sin_t[:, None]), axis=-1)
            Y += wi * wj * _sh_basis(d)
    Y *= texel_solid_angles(h, w)[..., None]
    return np.einsum("hwi,hwc->ic", Y, np.asarray(texels, np.float64))


def irradiance_sh(env: EnvironmentMap, normal: Any) -> jax.Array:
    """Irradiance (C,) on a surface of world unit normal (3,), R&H 2001 eq. 13."""
    n = _to_map(env, jnp.asarray(normal))
    x, y, z = n[0], n[1], n[2]
    L = env.sh
    return (SH_C1 * L[8] * (x * x - y * y) + SH_C3 * L[6] * z * z + SH_C4 * L[0]
            - SH_C5 * L[6]
            + 2.0 * SH_C1 * (L[4] * x * y + L[7] * x * z + L[5] * y * z)
            + 2.0 * SH_C2 * (L[3] * x + L[1] * y + L[2] * z))


def irradiance_exact(env: EnvironmentMap, normal: Any) -> jax.Array:
    """Irradiance (C,) by the texel sum Σ L max(0, N·ω) Δω over the unfiltered map."""
    h, w, c = env.texels.shape
    dirs = jnp.asarray(texel_directions(h, w).reshape(-1, 3), env.texels.dtype)
    sa = jnp.asarray(texel_solid_angles(h, w).reshape(-1), env.texels.dtype)
    n = _to_map(env, jnp.asarray(normal))
    wgt = jnp.maximum(dirs @ n, 0.0) * sa
    return wgt @ env.texels.reshape(-1, c)


def irradiance(env: EnvironmentMap, normal: Any) -> jax.Array:
    """Irradiance (C,) by the environment's ``diffuse`` mode ("sh" or "exact")."""
    if env.diffuse == "exact":
        return irradiance_exact(env, normal)
    return irradiance_sh(env, normal)


# --------------------------------------------------------------------------------------------
# Gloss


def _frame(n: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Orthonormal tangents (T, B) of unit n (Duff et al. 2017, branchless)."""
    sign = jnp.where(n[2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + n[2])
    b = n[0] * n[1] * a
    t = jnp.stack([1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]])
    bt = jnp.stack([b, sign + n[1] * n[1] * a, -n[1]])
    return t, bt


def _view_frame(N: jax.Array, V: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Tangent T along V's projection on the tangent plane, B = N × T (Duff's frame if V ∥ N)."""
    p = V - jnp.dot(N, V) * N
    p2 = jnp.dot(p, p)
    ok = p2 > 1e-12
    t0, _ = _frame(N)
    T = jnp.where(ok, p / jnp.sqrt(jnp.where(ok, p2, 1.0)), t0)
    return T, jnp.cross(N, T)


def smootherstep(x: jax.Array) -> jax.Array:
    x = jnp.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


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


_S_MAX = 4.5  # lobe truncation in s = θh/μ (Gaussian) or tanθh/m (Beckmann): e^-20 of the peak


def _lobe_rings(nv: jax.Array, width: jax.Array, xr: np.ndarray, wr: np.ndarray, *,
                distribution: str, radial_rule: str = "uniform") -> tuple[jax.Array, ...]:
    """Radial rings of a microfacet lobe of ``width``: s = θh/width (Gaussian) or tanθh/width
    (Beckmann) at Gauss–Legendre nodes ``xr`` (weights ``wr``, both on [0, 1]) scaled to
    [0, s_max], s_max from the horizon (θh <= π/4 + θr/2) and the truncation s <= 4.5.

    ``radial_rule`` "uniform": the nodes uniform in s (weight s e^{−s²} in the integrand);
    "mass": uniform in the radial mass t = 1 − e^{−s²} (s = √(−ln(1 − t)), ds s e^{−s²} =
    dt/2), every ring at the lobe's weight — for few rings (with 2 uniform rings on [0, 4.5]
    the outer one, at s = 3.5, carries e^−12 of the weight and the lobe is one ring at s ≈ 1).

    Returns (R,) arrays: s, the ring weight s e^{−s²} ds, cosθh, sinθh and the Jacobian
    factor sinθh/θh (Gaussian) or 1/cosθh (Beckmann) of dω_H in s ds dφ."""
    dtype = nv.dtype
    theta_r = jnp.arccos(jnp.clip(nv, 1e-7, 1.0 - 1e-7))
    theta_max = jnp.minimum(0.25 * math.pi + 0.5 * theta_r, 0.5 * math.pi - 1e-4)
    if distribution == "gaussian":
        s_max = jnp.minimum(theta_max / width, _S_MAX)
    elif distribution == "beckmann":
        s_max = jnp.minimum(jnp.tan(theta_max) / width, _S_MAX)
    else:
        raise InputError(f"unknown distribution {distribution!r}", field="distribution")
    if radial_rule == "uniform":
        s = s_max * jnp.asarray(xr, dtype)  # (R,)
        ring = s_max * jnp.asarray(wr, dtype) * s * jnp.exp(-s * s)  # s e^{-s²} ds
    elif radial_rule == "mass":
        t_max = -jnp.expm1(-s_max * s_max)
        s = jnp.sqrt(-jnp.log1p(-t_max * jnp.asarray(xr, dtype)))
        ring = 0.5 * t_max * jnp.asarray(wr, dtype)
    else:
        raise InputError(f"unknown radial rule {radial_rule!r}", field="radial_rule")
    if distribution == "gaussian":
        th = width * s
        sin_h, cos_h = sincos_poly(th)
        jac = jnp.where(th > 1e-4, sin_h / jnp.where(th > 1e-4, th, 1.0), 1.0 - th * th / 6.0)
    else:
        tan_h = width * s
        cos_h = 1.0 / jnp.sqrt(1.0 + tan_h * tan_h)
        sin_h = tan_h * cos_h
        jac = 1.0 / cos_h
    return s, ring, cos_h, sin_h, jac


def _visible_arc(nv: jax.Array, cos_h: jax.Array, sin_h: jax.Array) -> jax.Array:
    """φ_max (R,) of each ring θh: the half vectors at azimuth |φ'| <= φ_max (from V's
    azimuth) reflect V above the surface, N·L > 0 ⟺ sin2θh sinθr cosφ' > −cosθr cos2θh
    (π when the whole ring is visible, 0 when none of it is)."""
    sin_r = jnp.sqrt(jnp.maximum(1.0 - nv * nv, 0.0))
    a = 2.0 * sin_h * cos_h * sin_r
    bnum = -nv * (cos_h * cos_h - sin_h * sin_h)
    full = bnum < -jnp.abs(a) * (1.0 - 1e-6)
    empty = bnum > jnp.abs(a) * (1.0 - 1e-6)
    c = jnp.where(full | empty, 0.0, bnum / jnp.where(full | empty, 1.0, a))
    return jnp.where(full, math.pi, jnp.where(empty, 0.0, jnp.arccos(c)))


def lobe_albedo(
    nv: jax.Array, width: jax.Array, n: jax.Array, mu: jax.Array, *, distribution: str,
    geometry: str, fresnel: bool, radial: int, azimuthal: int,
) -> jax.Array:
    """A = ∫ D(width) F G (V·H)/(N·V) dω_H over the half vectors whose reflection is above the
    surface (the gloss lobe's directional albedo), a function of cosθr = ``nv`` only.

    Rings θh(s) with Gauss–Legendre in s on [0, s_max] (weight s e^{−s²} of the distribution),
    s_max from the horizon (θh <= π/4 + θr/2) and the truncation s <= 4.5; on each ring
    Gauss–Legendre in the azimuth φ' (from V's azimuth) over the visible arc 0 <= φ' <= φ_max,
    where N·L > 0 ⟺ sin2θh sinθr cosφ' > −cosθr cos2θh (the integrand is even in φ', so half
    the arc is integrated and doubled). The integrand vanishes or jumps only at the domain
    boundary, so the rule converges fast, and the nodes move smoothly with μ and θr. Only
    scalars: V·H = cosθh cosθr + sinθh sinθr cosφ', N·L = 2 (V·H) cosθh − cosθr."""
    g, *_ = _lobe_grid(nv, width, mu, n, distribution=distribution, geometry=geometry,
                       fresnel=fresnel, radial=radial, azimuthal=azimuthal)
    return jnp.sum(g)


def _lobe_grid(nv: jax.Array, width: jax.Array, mu: jax.Array, n: jax.Array, *,
               distribution: str, geometry: str, fresnel: bool, radial: int, azimuthal: int
               ) -> tuple[jax.Array, ...]:
    """The node set of :func:`lobe_albedo` and :func:`_lobe_moments` (see the former): the
    weights w F G (V·H)/(N·V) (R, A) of the distribution of roughness ``width`` with the
    geometry and Fresnel factor of ``mu`` and ``n``, and per node V·H, N·L (R, A), the ring's
    cosθh, sinθh (R,), sinθr and the azimuth φ' (R, A). Scalars only."""
    dtype = nv.dtype
    xr, wr = np.polynomial.legendre.leggauss(radial)
    xa, wa = np.polynomial.legendre.leggauss(azimuthal)
    xr, wr = 0.5 * (xr + 1.0), 0.5 * wr
    xa = 0.5 * (xa + 1.0)  # [0, 1]; the weights (sum 2) double the half arc
    nv = jnp.clip(nv, 0.0, 1.0)
    _, ws, cos_h, sin_h, jac = _lobe_rings(nv, width, xr, wr, distribution=distribution)
    if distribution == "gaussian":
        # D dω_H = K(μ) e^{−s²} sinθh dθh dφ = K μ² e^{−s²} s ds dφ · sinθh/θh
        ws = ws * gaussian_normalisation(width) * width * width * jac
    else:
        # D dω_H = e^{−s²} s ds dφ / (π cosθh)
        ws = ws * jac / math.pi
    sin_r = jnp.sqrt(jnp.maximum(1.0 - nv * nv, 0.0))
    phi_max = _visible_arc(nv, cos_h, sin_h)  # (R,)
    phi = phi_max[:, None] * jnp.asarray(xa, dtype)[None, :]  # (R, A)
    w = (ws * phi_max)[:, None] * jnp.asarray(wa, dtype)[None, :]
    vh = cos_h[:, None] * nv + (sin_h * sin_r)[:, None] * sincos_poly(phi)[1]
    nl = 2.0 * vh * cos_h[:, None] - nv
    ch = jnp.broadcast_to(cos_h[:, None], vh.shape)
    g = w * _microfacet_factor(nv, nl, vh, ch, mu, n, geometry=geometry, fresnel=fresnel)
    return g, vh, nl, cos_h, sin_h, sin_r, phi


def _microfacet_factor(nv: jax.Array, nl: jax.Array, vh: jax.Array, nh: jax.Array,
                       mu: jax.Array, n: jax.Array, *, geometry: str, fresnel: bool
                       ) -> jax.Array:
    """F G (V·H)/(N·V) from the cosines (broadcasting)."""
    if geometry == "vcavity":
        G = vcavity_g(nh, nv, nl, vh)
    elif geometry == "smith":
        G = smith_g(nv, nl, vh, vh, mu)
    elif geometry == "none":
        G = jnp.where((vh > 0.0) & (nl > 0.0), 1.0, 0.0)
    else:
        raise InputError(f"unknown geometry term {geometry!r}", field="geometry")
    F = fresnel_dielectric(vh, n) if fresnel else 1.0
    nv_safe = jnp.where(nv > 0.0, nv, 1.0)
    return F * G * jnp.maximum(vh, 0.0) / nv_safe


def lobe_factor(
    N: jax.Array, V: jax.Array, H: jax.Array, cos_h: jax.Array, mu: jax.Array, n: jax.Array,
    *, geometry: str, fresnel: bool,
) -> tuple[jax.Array, jax.Array]:
    """F G (V·H)/(N·V) at half vectors H (M, 3) (the rest of the integrand after D dω_H and
    dω_L = 4 (V·H) dω_H), and the reflected directions L (M, 3)."""
    nv = jnp.dot(N, V)
    vh = H @ V
    L = 2.0 * vh[:, None] * H - V
    nl = L @ N
    return _microfacet_factor(nv, nl, vh, cos_h, mu, n, geometry=geometry, fresnel=fresnel), L


def _narrowed_nodes(
    N: jax.Array, V: jax.Array, width: jax.Array, var: jax.Array, nv: jax.Array, *,
    distribution: str, radial: int, azimuthal: int,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Nodes and relative weights of the lobe narrowed for a reflected-direction prefilter of
    variance ``var`` per axis: an anisotropic Gaussian in the lobe's tangent coordinates
    (exponential map θh for the Gaussian D, tanθh for Beckmann) with squared widths
    width² − var/2 along V's azimuth (reflection doubles angles in the plane of incidence) and
    width² − var/(2cos²θr) across it (there it multiplies them by 2cosθd ≈ 2cosθr).
    Gauss–Laguerre in s² × equally spaced azimuths (rings staggered). Weights are relative
    (the caller normalises)."""
    dtype = N.dtype
    t_nodes, t_w = np.polynomial.laguerre.laggauss(radial)
    phi = 2.0 * np.pi * (np.arange(azimuthal)[None, :] + 0.5
                         + 0.5 * (np.arange(radial)[:, None] % 2)) / azimuthal
    s = np.sqrt(t_nodes)[:, None]
    cx = jnp.asarray((s * np.cos(phi)).reshape(-1), dtype)
    cy = jnp.asarray((s * np.sin(phi)).reshape(-1), dtype)
    wq = jnp.asarray(np.broadcast_to(t_w[:, None], phi.shape).reshape(-1), dtype)
    floor = 0.01 * width * width
    wt = jnp.sqrt(jnp.maximum(width * width - 0.5 * var, floor))
    wb = jnp.sqrt(jnp.maximum(width * width - 0.5 * var / jnp.maximum(nv * nv, 1e-4), floor))
    x, y = wt * cx, wb * cy
    r = jnp.sqrt(x * x + y * y)
    r_safe = jnp.where(r > 1e-12, r, 1.0)
    if distribution == "gaussian":
        theta = r
        sin_h, cos_h = sincos_poly(theta)
        jac = jnp.where(r > 1e-4, sin_h / r_safe, 1.0 - r * r / 6.0)
    else:
        cos_h = 1.0 / jnp.sqrt(1.0 + r * r)
        sin_h = r * cos_h
        jac = 1.0 / cos_h  # D dω_H ∝ e^{−s²} s ds dφ / cosθh
        sin_h = jnp.where(r > 1e-12, sin_h, 0.0)
    T, B = _view_frame(N, V)
    ux = jnp.where(r > 1e-12, x / r_safe, 1.0)
    uy = jnp.where(r > 1e-12, y / r_safe, 0.0)
    H = cos_h[:, None] * N + sin_h[:, None] * (ux[:, None] * T + uy[:, None] * B)
    return H, wq * jac, cos_h


def visible_nodes(
    N: jax.Array, V: jax.Array, mu: jax.Array, var: jax.Array, nv: jax.Array, *,
    distribution: str, radial: int, azimuthal: int, radial_rule: str = "uniform",
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Half vectors (M, 3), relative weights (M,) and cosθh (M,) of a quadrature of the gloss
    lobe narrowed for a reflected-direction prefilter of variance ``var`` per axis, restricted to
    the half vectors whose reflection is above the surface.

    The narrowed lobe is an anisotropic Gaussian in the lobe's tangent coordinates (θh for the
    Gaussian D, tanθh for Beckmann) with squared widths w_t² = μ² − var/2 along V's azimuth
    (reflection doubles angles in the plane of incidence) and w_b² = μ² − var/(2cos²θr) across
    it. Nodes: rings at s = θh/w_t (or tanθh/w_t), Gauss–Legendre in s on [0, s_max] with the
    radial weight s e^{−s²} ds (:func:`_lobe_rings`), s_max from
    the horizon (θh <= π/4 + θr/2) and the truncation s <= 4.5; on each ring Gauss–Legendre in
    the azimuth φ' (from V's azimuth) over the whole visible arc |φ'| <= φ_max(θh) (N·L > 0 ⟺
    sin2θh sinθr cosφ' > −cosθr cos2θh). The across-axis narrowing enters the weights as
    exp(−s² sin²φ' (w_t²/w_b² − 1)). The nodes move smoothly with μ, N and V and never sample
    the map below the horizon, so the quadrature converges on the visible lobe alone.
    ``radial_rule``: see :func:`_lobe_rings` ("mass" for few rings)."""
    dtype = N.dtype
    xr, wr = np.polynomial.legendre.leggauss(radial)
    xa, wa = np.polynomial.legendre.leggauss(azimuthal)
    xr, wr = 0.5 * (xr + 1.0), 0.5 * wr
    nv = jnp.clip(nv, 0.0, 1.0)
    floor = 0.01 * mu * mu
    wt2 = jnp.maximum(mu * mu - 0.5 * var, floor)
    wb2 = jnp.maximum(mu * mu - 0.5 * var / jnp.maximum(nv * nv, 1e-4), floor)
    wt = jnp.sqrt(wt2)
    s, wring, cos_h, sin_h, jac = _lobe_rings(nv, wt, xr, wr, distribution=distribution,
                                              radial_rule=radial_rule)
    phi_max = _visible_arc(nv, cos_h, sin_h)  # (R,)
    phi = phi_max[:, None] * jnp.asarray(xa, dtype)[None, :]  # (R, A), xa in [-1, 1]
    wgt = (wring * jac * phi_max)[:, None] * jnp.asarray(wa, dtype)[None, :]
    sp, cp = sincos_poly(phi)
    wgt = wgt * jnp.exp(-(s * s)[:, None] * sp * sp * (wt2 / wb2 - 1.0))
    T, B = _view_frame(N, V)
    tang = cp[..., None] * T + sp[..., None] * B  # (R, A, 3)
    H = cos_h[:, None, None] * N + sin_h[:, None, None] * tang
    ch = jnp.broadcast_to(cos_h[:, None], phi.shape)
    return H.reshape(-1, 3), wgt.reshape(-1), ch.reshape(-1)


def _albedo_table(mu: jax.Array, n: jax.Array, size: int, *, distribution: str, geometry: str,
                  fresnel: bool, radial: int, azimuthal: int) -> jax.Array:
    """Exact lobe albedos (size,) at cosθr = 1 − x², x = j/(size − 1) (see :func:`lobe_albedo`).
    Independent of the point, so under ``jax.vmap`` over points it is computed once."""
    x = np.linspace(0.0, 1.0, size)
    c = np.maximum(1.0 - x * x, 1e-3)
    dtype = jnp.result_type(mu, jnp.float32)
    return jax.vmap(lambda cc: lobe_albedo(cc, mu, n, mu, distribution=distribution,
                                            geometry=geometry, fresnel=fresnel, radial=radial,
                                            azimuthal=azimuthal))(jnp.asarray(c, dtype))


def _interp_table(table: jax.Array, nv: jax.Array) -> jax.Array:
    """Catmull–Rom cubic interpolation (C¹) of :func:`_albedo_table` at cosθr = ``nv``; the
    albedo is even in θr, hence smooth in x = √(1 − cosθr)."""
    size = table.shape[0]
    x = jnp.sqrt(jnp.clip(1.0 - nv, 0.0, 1.0)) * (size - 1)
    i = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, size - 2)
    t = x - i.astype(x.dtype)
    # mirror at x = 0 (even function), clamp at the grazing end
    p0 = table[jnp.abs(i - 1)]
    p1 = table[i]
    p2 = table[i + 1]
    p3 = table[jnp.minimum(i + 2, size - 1)]
    return p1 + 0.5 * t * (p2 - p0 + t * (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3
                                          + t * (3.0 * (p1 - p2) + p3 - p0)))


def gloss_integral(
    env: EnvironmentMap,
    normal: Any,
    view: Any,
    mu: Any,
    n: Any,
    *,
    distribution: str = "gaussian",
    geometry: str = "vcavity",
    fresnel: bool = True,
    quality: str = "exact",
) -> jax.Array:
    """Gloss radiance per unit β (C,): ∫ L(ω) F(n, θd) D(μ, θh) G / (4 cosθr) dω (the gloss
    term of eq. 5).

    Method. With dω_L = 4 (V·H) dω_H the integral is ∫ D(H) g(H) L(l(H)) dω_H,
    g = F G (V·H)/(N·V), over the half vectors whose reflection l(H) is above the surface. It is
    split as A · ⟨L⟩:

    - A = ∫ D g dω_H, the lobe's directional albedo, by a fine scalar quadrature
      (``albedo_radial`` × ``albedo_azimuthal`` nodes; no map lookups). ``"render"``
      interpolates it from a per-material table in cosθr (:func:`_albedo_table`).
    - ⟨L⟩ = ∫ D' g L_σ / ∫ D' g, the g-weighted mean radiance over the lobe, by a quadrature on
      the visible part of the lobe (:func:`visible_nodes`) of a prefiltered copy L_σ of the
      map (exact spherical Gaussian, std σ = r·√2·μ·cosθr in reflected directions, two adjacent
      levels blended smoothly in log σ) with the lobe D' narrowed so that narrowed lobe ⊛
      prefilter has the true lobe's width; near the surface's horizon each node's σ is cut to
      ``horizon_ratio`` × its elevation.
    - ``"exact"``, wide lobes: ⟨L⟩ = Σ w_t L_t / Σ w_t, the direct sum over the unfiltered
      (bilinear) map sampled at the centres of a 2× finer grid, w_t = F D G/(4 cosθr) Δω_t
      (:func:`_texel_mean`; four integrand evaluations per texel, no lookups; 1× — each
      texel a box — was up to 3 % off for μ = 0.2 at θr = 80°, where the lobe is two texels
      across). The narrowing above is exact only for
      a Gaussian lobe in a flat tangent plane; for wide lobes g, the horizon and the sphere's
      curvature change the lobe on the scale of σ and the prefiltered quadrature is biased
      (∝ σ²: 3–9 % at μ = 0.5 with r = 0.3, up to 26 % on the room map), while the texel
      sum's error (the integrand's variation inside one texel) falls as the lobe widens.
      From μ = ``texel_sum_from`` (0.12) to ``texel_sum_full`` (0.18) the two are blended
      with a C² weight in μ; only the branches a given μ needs run (``jax.lax.cond``).
    - ``"exact"``, narrow lobes: the nodes are a Cartesian grid in the half-vector tangent
      plane (:func:`_grid_nodes`, 128 along the plane of incidence × 36 across, r = 0.1),
      dense along the plane of incidence so that at grazing views, where the prefilter must
      be as narrow as the lobe is across (∝ cosθr), the map is still sampled finely; the
      across-narrowing uses each column's own V·H. (The polar rule of
      :func:`visible_nodes`, kept for ``"render"``, aliased there: up to 6.8 % at θr = 75°.)
      The prefilter is kept small (r = 0.1): narrowing the lobe restores its variance, not
      its exact shape (the reflected lobe is not the flat Gaussian the narrowing assumes,
      and two blended levels are a mix of two Gaussians), and an edge of high contrast in
      the lobe's tail weighs that difference: on the room map at μ = 0.07, θr = 45° (the
      dim bands next to the window) a 512 × 256 grid gives 0.1 % at r = 0.05, 0.5 % at
      0.1, 1.0–1.2 % at 0.15–0.3. r = 0.1 needs the 36 columns against aliasing (24: 1.5 %).
    - Bright sources taken out of the map (:func:`_extract_sources`) are added exactly
      at sub-points: in ``"exact"`` by a product Gauss rule (8 × 8 points) over each source
      texel's footprint in the bilinear map (:func:`_tent_gauss_subpoints`), in the map's
      own channels; in ``"render"`` its ``source_subpoints`` in the compressed channels.

    The nodes move smoothly with μ, n, N, V and the texel weights are smooth functions of them,
    so the result is smooth in μ and n (no tables in μ or n; the level blend and the method
    blend are C²; the bilinear lookups make it piecewise smooth, with slope jumps of ~1/M of
    the lobe where one of the M nodes crosses a texel line). ``quality`` picks the node
    counts and r: ``"exact"`` (128 × 36 grid, r = 0.1, texel sum for wide lobes) or
    ``"render"`` (8 × 16 polar nodes, r = 0.3; see
    docs/lighting.md for the measured accuracy of each). Zero if N·V <= 0.

    Args:
        normal, view: world unit vectors (3,).
        mu: Gaussian width μ (radians) or Beckmann slope m, > 0.
        n: refractive index > 1.
        geometry: "vcavity", "smith" or "none" (G = 1, for furnace tests).
        fresnel: False sets F = 1 (furnace tests).
        quality: "exact" or "render" (static).
    """
    if quality not in QUALITIES:
        raise InputError(f"unknown quality {quality!r}; choose one of {QUALITIES}",
                         field="quality")
    N = jnp.asarray(normal)
    V = jnp.asarray(view)
    dtype = env.atlas.dtype
    N = N.astype(dtype)
    V = V.astype(dtype)
    mu = jnp.asarray(mu, dtype)
    n = jnp.asarray(n, dtype)
    quad = env.quadrature
    kw = dict(geometry=geometry, fresnel=fresnel)
    nv_raw = jnp.dot(N, V)
    nv = jnp.clip(nv_raw, 0.0, 1.0)
    # A: directional albedo of the lobe (true width)
    akw = dict(distribution=distribution, radial=quad.albedo_radial,
               azimuthal=quad.albedo_azimuthal, **kw)
    if quality == "render":
        albedo = _interp_table(_albedo_table(mu, n, quad.albedo_table, **akw), nv)
        radial, azimuthal, ratio = (quad.render_radial, quad.render_azimuthal,
                                    quad.render_prefilter_ratio)
    else:
        albedo = lobe_albedo(nv_raw, mu, n, mu, **akw)
        radial, azimuthal, ratio = quad.radial, quad.azimuthal, quad.prefilter_ratio
    mean_kw = dict(distribution=distribution, **kw)
    if quality == "render":
        rule = "visible" if quad.nodes == "grid" else quad.nodes
        mean = _lobe_mean(env, N, V, mu, n, nv, radial=radial, azimuthal=azimuthal,
                          ratio=ratio, node_rule=rule, **mean_kw)
    else:
        # wide lobes: the texel sum; narrow ones: the lobe quadrature; C² blend in between.
        # Only the branches needed for this μ run (both, if μ is batched under vmap).
        a, b = quad.texel_sum_from, quad.texel_sum_full

        def lobe() -> jax.Array:
            return _lobe_mean(env, N, V, mu, n, nv, radial=radial, azimuthal=azimuthal,
                              ratio=ratio, **mean_kw)

        def texels() -> jax.Array:
            return _texel_mean(env, N, V, mu, n, **mean_kw)

        def blend() -> jax.Array:
            t = smootherstep((mu - a) / (b - a))
            return (1.0 - t) * lobe() + t * texels()

        if isinstance(mu, jax.core.Tracer):
            mean = jax.lax.cond(mu <= a, lobe, lambda: jax.lax.cond(mu >= b, texels, blend))
        else:  # a concrete μ (eager calls): choose here, so nothing is traced per call
            mu_c = float(mu)
            mean = lobe() if mu_c <= a else texels() if mu_c >= b else blend()
    out = albedo * mean
    tent = "exact" if quality == "exact" else "render"
    full = env.source_flux_full is not None and (
        env.source_fine_dirs if tent == "exact" else env.source_render_dirs) is not None
    if env.source_flux.shape[0] and not full:
        out = out + _source_gloss(env, N, V, mu, n, distribution=distribution, **kw)
    spec = out @ env.spectral_basis
    if env.source_flux.shape[0] and full:
        # in the map's own channels: the principal-spectra compression bounds the error per
        # texel over all channels, not per band (up to 0.4 % in the dim bands of a lamp)
        spec = spec + _source_gloss(env, N, V, mu, n, distribution=distribution, tent=tent,
                                    **kw)
    return jnp.where(nv_raw > 0.0, spec, 0.0)


def _grid_nodes(
    N: jax.Array, V: jax.Array, mu: jax.Array, var: jax.Array, nv: jax.Array, *,
    distribution: str, along: int, across: int, extent: float,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Half vectors (M, 3), relative weights (M,) and cosθh (M,) of a Cartesian quadrature of
    the gloss lobe narrowed for a reflected-direction prefilter of variance ``var`` per axis.

    Tangent coordinates (x, y) of H around N (exponential map θh for the Gaussian D, tanθh for
    Beckmann), x along V's azimuth (the plane of incidence), y across it. The narrowed lobe is
    exp(−x²/w_t² − y²/w_b²) with w_t² = μ² − var/2, w_b² = μ² − var/(2cos²θr) (reflection
    maps a step in x to 2 in reflected directions and a step in y to ≈ 2cosθr). Nodes: a
    uniform ``along`` × ``across`` midpoint grid on [−extent, extent]² in (x/w_t, y/w_b)
    (the trapezoid rule, spectrally accurate for the Gaussian). The reflected directions are
    then spaced 4·extent·w_t/along along the plane of incidence and
    4·extent·w_b·cosθr/across across it, so at grazing views, where the isotropic prefilter
    must be as narrow as the lobe across (∝ cosθr), the many nodes along keep the spacing
    at 0.88/cosθr prefilter stds (r = 0.1; 5 at θr = 80°, where the lobe itself is then
    only a few texels across; the polar rule of :func:`visible_nodes` had ~20 there and
    aliased). Half vectors that reflect V below the surface
    get zero weight from G in the caller's lobe factor (the integrand goes to zero
    continuously at the horizon). Nodes move smoothly with μ, N and V."""
    dtype = N.dtype
    nv = jnp.clip(nv, 0.0, 1.0)
    floor = 0.01 * mu * mu
    wt = jnp.sqrt(jnp.maximum(mu * mu - 0.5 * var, floor))
    gx = extent * ((np.arange(along) + 0.5) * (2.0 / along) - 1.0)
    gy = extent * ((np.arange(across) + 0.5) * (2.0 / across) - 1.0)
    X, Y = np.meshgrid(gx, gy, indexing="ij")
    X, Y = X.reshape(-1), Y.reshape(-1)
    keep = X * X + Y * Y <= extent * extent  # outside the disc the weight is < e^-extent²
    X, Y = X[keep], Y[keep]
    wq = jnp.asarray(np.exp(-(X * X + Y * Y)), dtype)
    x = wt * jnp.asarray(X, dtype)
    # across the plane of incidence a step in y moves the reflected direction by 2 (V·H); along
    # the lobe V·H = cos(θr − θx) changes (strongly at grazing views), so the across width is
    # narrowed per column with the local factor. Nodes at y = w_b(x)·Y keep the weights
    # exp(−X² − Y²): the narrowed column's density (μ/w_b) e^{−y²/w_b²} times dy = w_b dY.
    theta_x = x if distribution == "gaussian" else jnp.arctan(x)
    sin_r = jnp.sqrt(jnp.maximum(1.0 - nv * nv, 1e-12))  # gradient-safe at V = N
    sx, cx_ = sincos_poly(theta_x)
    c = nv * cx_ + sin_r * sx  # cos(θr − θx)
    wb = jnp.sqrt(jnp.maximum(mu * mu - 0.5 * var / jnp.maximum(c * c, 1e-4), floor))
    y = wb * jnp.asarray(Y, dtype)
    r = jnp.sqrt(x * x + y * y)
    r_safe = jnp.where(r > 1e-12, r, 1.0)
    if distribution == "gaussian":
        sin_h, cos_h = sincos_poly(r)
        jac = jnp.where(r > 1e-4, sin_h / r_safe, 1.0 - r * r / 6.0)
    elif distribution == "beckmann":
        cos_h = 1.0 / jnp.sqrt(1.0 + r * r)
        sin_h = r * cos_h
        jac = 1.0 / cos_h  # D dω_H ∝ e^{−(x²+y²)/m²} dx dy / cosθh
    else:
        raise InputError(f"unknown distribution {distribution!r}", field="distribution")
    T, B = _view_frame(N, V)
    ux = x / r_safe
    uy = y / r_safe
    H = cos_h[:, None] * N + (sin_h * ux)[:, None] * T + (sin_h * uy)[:, None] * B
    # past θh = π/2 a half vector is below the surface: no weight (D = 0 there)
    w = jnp.where(cos_h > 0.0, wq * jac, 0.0)
    return H, w, cos_h


def _lobe_mean(env: EnvironmentMap, N: jax.Array, V: jax.Array, mu: jax.Array, n: jax.Array,
               nv: jax.Array, *, radial: int, azimuthal: int, ratio: float, distribution: str,
               geometry: str, fresnel: bool, node_rule: str | None = None) -> jax.Array:
    """⟨L⟩ (r,): the g-weighted mean of the prefiltered residual map over the narrowed lobe
    (:func:`visible_nodes`), zero where the lobe has no weight."""
    quad = env.quadrature
    sigma = ratio * math.sqrt(2.0) * mu * jnp.maximum(nv, 0.05)
    _, _, _, var = levels_for(env, sigma)
    rule = node_rule or quad.nodes
    if rule == "grid":
        Hb, wb, chb = _grid_nodes(N, V, mu, var, nv, distribution=distribution,
                                  along=quad.grid_along, across=quad.grid_across,
                                  extent=quad.grid_extent)
    else:
        nodes = visible_nodes if rule == "visible" else _narrowed_nodes
        Hb, wb, chb = nodes(N, V, mu, var, nv, distribution=distribution,
                            radial=radial, azimuthal=azimuthal)
    gb, L = lobe_factor(N, V, Hb, chb, mu, n, geometry=geometry, fresnel=fresnel)
    f = wb * gb
    # near the surface's horizon the prefilter would blur in light from behind the surface:
    # there each node's prefilter std is cut to a fraction of its elevation above the horizon
    elev = jnp.maximum(L @ N, 0.0)
    lo, hi, w_hi, _ = levels_for(env, jnp.minimum(sigma, quad.horizon_ratio * elev))
    u, v = direction_to_uv(_to_map(env, L))
    radiance = _lookup_blend(env, u, v, lo, hi, w_hi)  # (M, r)
    total = jnp.sum(f)
    return (f @ radiance) / jnp.where(total > 0.0, total, 1.0)


def _texel_mean(env: EnvironmentMap, N: jax.Array, V: jax.Array, mu: jax.Array, n: jax.Array,
                *, distribution: str, geometry: str, fresnel: bool) -> jax.Array:
    """⟨L⟩ (r,) by the direct texel sum over the unfiltered residual map as the bilinear
    lookup defines it, sampled at the texel centres of an s× finer grid (``fine_texels``,
    s = ``texel_sum_supersample``; s = 1: level 0 of the atlas, each texel a box):
    Σ w_t L_t / Σ w_t with w_t = F D G /(4 cosθr) Δω_t at the fine centres. Its error is the
    variation of the integrand inside one fine texel, so it is accurate for lobes a few
    texels wide (μ >~ 0.12 on a 128-row map at s = 2, up to θr = 80°); it costs s² integrand
    evaluations per texel and no lookups."""
    h, w = env.level_shapes[0]
    dtype = env.atlas.dtype
    ss = env.quadrature.texel_sum_supersample
    values = env.atlas[: h * w] if env.fine_texels is None else env.fine_texels
    if env.fine_texels is None:
        ss = 1
    dirs = jnp.asarray(texel_directions(h * ss, w * ss).reshape(-1, 3), dtype)
    sa = jnp.asarray(texel_solid_angles(h * ss, w * ss).reshape(-1), dtype)
    # work in the map frame: rotate N and V instead of every texel direction
    wgt = _integrand(dirs, _to_map(env, N), _to_map(env, V), mu, n, distribution=distribution,
                     geometry=geometry, fresnel=fresnel) * sa
    total = jnp.sum(wgt)
    return (wgt @ values) / jnp.where(total > 0.0, total, 1.0)


def _integrand(d: jax.Array, N: jax.Array, V: jax.Array, mu: jax.Array, n: jax.Array, *,
               distribution: str, geometry: str, fresnel: bool) -> jax.Array:
    """F D G / (4 cosθr) (M,) for light directions d (M, 3) (the gloss integrand per unit
    radiance and solid angle), zero where N·L <= 0 or N·V <= 0."""
    nv = jnp.dot(N, V)
    nl = d @ N
    Hs = d + V
    Hs = Hs / jnp.sqrt(jnp.maximum(jnp.sum(Hs * Hs, axis=-1, keepdims=True), 1e-30))
    nh = Hs @ N
    vh = Hs @ V
    if distribution == "gaussian":
        D = gaussian_d(nh, mu)
    else:
        D = beckmann_d(nh, mu)
    if geometry == "vcavity":
        G = vcavity_g(nh, nv, nl, vh)
    elif geometry == "smith":
        G = smith_g(nv, nl, vh, vh, mu)
    else:
        G = jnp.where((vh > 0.0) & (nl > 0.0), 1.0, 0.0)
    F = fresnel_dielectric(vh, n) if fresnel else 1.0
    ok = (nl > 0.0) & (nv > 0.0)
    return jnp.where(ok, F * D * G / (4.0 * jnp.where(nv > 0.0, nv, 1.0)), 0.0)


def _source_gloss(env: EnvironmentMap, N: jax.Array, V: jax.Array, mu: jax.Array, n: jax.Array,
                  *, distribution: str, geometry: str, fresnel: bool, tent: str | None = None
                  ) -> jax.Array:
    """Σ over source sub-points of F D G / (4 cosθr) · excess flux (the exact integrand), in
    the r compressed channels (``source_subpoints`` points inside each source texel), or with
    ``tent`` in the map's C channels: the product Gauss rule over each source texel's
    footprint in the bilinear map (:func:`_tent_gauss_subpoints`, ``source_flux_full``);
    lobes narrower than a few texels (small μ, grazing views) need the footprint.
    ``tent`` = "exact": (2·tent_gauss)² points per source texel; "render": 2 × 2."""
    if tent:
        dirs, pw = ((env.source_fine_dirs, env.source_fine_weights) if tent == "exact"
                    else (env.source_render_dirs, env.source_render_weights))
        d = dirs.reshape(-1, 3) @ env.rotation.T  # world directions (S·P, 3)
        wgt = _integrand(d, N, V, mu, n, distribution=distribution, geometry=geometry,
                         fresnel=fresnel).reshape(dirs.shape[:2])
        return jnp.sum(wgt * pw, axis=1) @ env.source_flux_full
    dirs = env.source_dirs
    d = dirs.reshape(-1, 3) @ env.rotation.T  # world directions (S·k, 3)
    flux = jnp.repeat(env.source_flux, dirs.shape[1], axis=0)
    wgt = _integrand(d, N, V, mu, n, distribution=distribution, geometry=geometry,
                     fresnel=fresnel)
    return wgt @ flux


# --------------------------------------------------------------------------------------------
# Split-sum gloss (quality "fast", for frames)

def _along_rule(k: int) -> tuple[np.ndarray, np.ndarray]:
    """k binomial nodes (positions in standard deviations, weights): C(k−1, j)/2^(k−1) at
    (j − (k−1)/2)·2/√(k−1), unit variance (a discrete Gaussian)."""
    j = np.arange(k)
    w = np.array([math.comb(k - 1, int(i)) for i in j], np.float64) / 2.0 ** (k - 1)
    x = (j - 0.5 * (k - 1)) * (2.0 / math.sqrt(k - 1) if k > 1 else 0.0)
    return x, w


#: parity in x = √(1 − cosθr) of the columns of :func:`lobe_moment_table` (A, δ, var_t, var_b)
_MOMENT_PARITY = (1.0, -1.0, 1.0, 1.0)


@dataclasses.dataclass(frozen=True)
class SplitSum:
    """Settings of the split-sum gloss :func:`gloss_split_sum` (static).

    Attributes:
        table: entries of the per-material moment table in x = √(1 − cosθr) (Catmull–Rom).
        radial, azimuthal: Gauss–Legendre nodes of the scalar moment quadrature (rings ×
            half visible arc, as :func:`lobe_albedo`); no map lookups.
        along: lookups (1–8) along the lobe's long axis (the plane of incidence), binomial
            weights, for its spread beyond the isotropic prefilter of each lookup.
        min_ratio: each lookup's prefilter std is at least this fraction of the lobe's long
            axis std (at grazing views the lobe is narrow across the plane of incidence;
            a wider prefilter keeps the sum of ``along`` lookups smooth along it).
        horizon_ratio: each lookup's prefilter std is at most this fraction of its elevation
            above the surface's horizon.
        per_octave: prefiltered levels per octave of std (:class:`SplitSumMap`).
    """

    table: int = 32
    radial: int = 16
    azimuthal: int = 16
    along: int = 4
    min_ratio: float = 0.5
    horizon_ratio: float = 0.5
    per_octave: int = 4


def _lobe_moments(
    nv: jax.Array, mu: jax.Array, n: jax.Array, *, distribution: str, geometry: str,
    fresnel: bool, radial: int, azimuthal: int,
) -> jax.Array:
    """(A, δ, var_t, var_b) of the gloss lobe in reflected directions at cosθr = ``nv``.

    With weights D F G (V·H)/(N·V) dω_H over the half vectors that reflect V above the surface
    (the integrand of :func:`gloss_integral` without the radiance): A = ∫ weight (the
    directional albedo); the weighted mean reflected direction m lies in the plane of
    incidence at polar angle θr + δ (δ > 0: away from the normal, the off-specular shift);
    var_t and var_b are the weighted means of the squared components of the reflected
    direction across m within the plane of incidence and perpendicular to it (the lobe's
    angular variances, long and short axis). Same nodes as :func:`lobe_albedo`; scalars only.
    """
    g, vh, nl, _, sin_h, sin_r, phi = _lobe_grid(
        nv, mu, mu, n, distribution=distribution, geometry=geometry, fresnel=fresnel,
        radial=radial, azimuthal=azimuthal)
    nv = jnp.clip(nv, 0.0, 1.0)
    sphi, cphi = sincos_poly(phi)
    # reflected direction L = 2 (V·H) H − V in the frame (T, B, N), V = (sinθr, 0, cosθr)
    lt = 2.0 * vh * sin_h[:, None] * cphi - sin_r
    lb = 2.0 * vh * sin_h[:, None] * sphi
    a = jnp.sum(g)
    a_safe = jnp.where(a > 0.0, a, 1.0)
    mt = jnp.sum(g * lt) / a_safe
    mn = jnp.sum(g * nl) / a_safe
    theta_m = atan2_poly(-mt, mn)
    delta = theta_m - jnp.arccos(nv)
    # coordinates of L in the tangent plane at m (azimuthal equidistant: angle γ from m),
    # e1 = (cosθm, 0, sinθm) in the plane of incidence, e2 = B across it
    sm, cm = sincos_poly(theta_m)
    l1 = lt * cm + nl * sm
    lm = jnp.clip(nl * cm - lt * sm, -1.0, 1.0)  # cos γ
    sin_g = jnp.sqrt(jnp.maximum(l1 * l1 + lb * lb, 1e-30))
    # (atan2_poly: XLA:CPU's atan2 is a scalar call, a large share of the tables' cost;
    # results within 1.2e-7 of it)
    scale = atan2_poly(sin_g, lm) / sin_g  # γ / sin γ
    var_t = jnp.sum(g * (l1 * scale) ** 2) / a_safe
    var_b = jnp.sum(g * (lb * scale) ** 2) / a_safe
    return jnp.stack([a, delta, var_t, var_b])


def lobe_moment_table(mu: Any, n: Any, *, distribution: str = "gaussian",
                      geometry: str = "vcavity", fresnel: bool = True,
                      settings: SplitSum | None = None) -> jax.Array:
    """Moments (size, 4) of the gloss lobe, columns (A, δ, var_t, var_b) of
    :func:`_lobe_moments`, at cosθr = 1 − x², x = j/(size − 1) (the last at cosθr = 1e-3).

    One table per material and frame (it depends on μ and n only, not on the point: under
    ``jax.vmap`` over points it is computed once); smooth and differentiable in μ and n.
    """
    s = settings or SplitSum()
    x = np.linspace(0.0, 1.0, s.table)
    c = np.maximum(1.0 - x * x, 1e-3)
    mu = jnp.asarray(mu)
    dtype = jnp.result_type(mu, jnp.float32)
    mu = mu.astype(dtype)
    n = jnp.asarray(n, dtype)
    return jax.vmap(lambda cc: _lobe_moments(
        cc, mu, n, distribution=distribution, geometry=geometry, fresnel=fresnel,
        radial=s.radial, azimuthal=s.azimuthal))(jnp.asarray(c, dtype))


def _interp_moments(table: jax.Array, nv: jax.Array) -> jax.Array:
    """Catmull–Rom interpolation (C¹) of the columns of :func:`lobe_moment_table` at
    cosθr = ``nv``, continued through x = 0 as even (A, variances) or odd (δ) functions."""
    size = table.shape[0]
    x = jnp.sqrt(jnp.clip(1.0 - nv, 0.0, 1.0)) * (size - 1)
    i = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, size - 2)
    t = (x - i.astype(x.dtype))[..., None]
    parity = jnp.asarray(_MOMENT_PARITY, table.dtype)
    p0 = table[jnp.abs(i - 1)] * jnp.where((i >= 1)[..., None], 1.0, parity)
    p1 = table[i]
    p2 = table[i + 1]
    p3 = table[jnp.minimum(i + 2, size - 1)]
    return p1 + 0.5 * t * (p2 - p0 + t * (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3
                                          + t * (3.0 * (p1 - p2) + p3 - p0)))


def sincos_poly(x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(sin x, cos x) by elementwise arithmetic: Cody–Waite reduction by π/2 (three-part π/2)
    and the Cephes sinf/cosf polynomials on [−π/4, π/4] (|error| < 1e-7 for |x| < 100).
    XLA:CPU calls libm's scalar sinf/cosf per element (several times slower); the gloss
    quadratures evaluate them per point and per node."""
    k = jnp.round(x * (2.0 / math.pi))
    r = ((x - k * 1.5703125) - k * 4.837512969970703125e-4) - k * 7.54978995489188216e-8
    r2 = r * r
    s = r + r * r2 * (-1.6666654611e-1 + r2 * (8.3321608736e-3 + r2 * -1.9515295891e-4))
    c = 1.0 - 0.5 * r2 + r2 * r2 * (4.166664568298827e-2 + r2 * (
        -1.388731625493765e-3 + r2 * 2.443315711809948e-5))
    q = k.astype(jnp.int32) & 3
    odd = (q & 1) == 1
    sn = jnp.where(odd, c, s)
    cs = jnp.where(odd, s, c)
    return jnp.where(q >= 2, -sn, sn), jnp.where((q == 1) | (q == 2), -cs, cs)


def atan2_poly(y: jax.Array, x: jax.Array) -> jax.Array:
    """atan2(y, x) by elementwise arithmetic: reduction to [0, tan π/8] and the Cephes atanf
    polynomial (|error| < 3e-7 rad). XLA:CPU vectorises it; its own atan2 (and arccos) is a
    scalar library call, far slower per element than exp or a division."""
    ax, ay = jnp.abs(x), jnp.abs(y)
    hi = jnp.maximum(ax, ay)
    a = jnp.minimum(ax, ay) / jnp.where(hi > 0.0, hi, 1.0)
    big = a > 0.41421356237
    z = jnp.where(big, (a - 1.0) / (a + 1.0), a)
    z2 = z * z
    p = ((((8.05374449538e-2 * z2 - 1.38776856032e-1) * z2 + 1.99777106478e-1) * z2
          - 3.33329491539e-1) * z2) * z + z
    r = jnp.where(big, 0.25 * math.pi + p, p)
    r = jnp.where(ay > ax, 0.5 * math.pi - r, r)
    r = jnp.where(x < 0.0, math.pi - r, r)
    return jnp.where(y < 0.0, -r, r)


def fast_direction_to_uv(d: jax.Array) -> tuple[jax.Array, jax.Array]:
    """:func:`direction_to_uv` (same conventions, gradient-safe at the poles) with the
    vectorisable :func:`atan2_poly`; differs from it by < 1e-7 in u and v."""
    return uv_of(d[..., 0], d[..., 1], d[..., 2])


def uv_of(x: jax.Array, y: jax.Array, z: jax.Array) -> tuple[jax.Array, jax.Array]:
    """:func:`fast_direction_to_uv` of the direction with components (x, y, z)."""
    rho2 = x * x + z * z
    small = rho2 < 1e-20
    rho = jnp.sqrt(jnp.where(small, 1.0, rho2))
    rho = jnp.where(small, 0.0, rho)
    theta = atan2_poly(rho, y)
    phi = atan2_poly(jnp.where(small, 0.0, x), jnp.where(small, 1.0, -z))
    u = phi * (0.5 / math.pi)
    u = jnp.where(u < 0.0, u + 1.0, u)
    return u, theta * (1.0 / math.pi)


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


def taps_sum(flat: jax.Array, idx: jax.Array, w: jax.Array, *, lead: bool = False
              ) -> jax.Array:
    """Σ_k w[..., k] flat[idx[..., k]]: (..., K) taps → (..., C), unrolled over k (XLA:CPU
    runs a reduction over a short middle axis, or a batched dot of tiny matrices, as a slow
    loop, much slower than this sum of products), one gather per tap: a gather of all K taps
    at once has the (..., K) indices written to memory first, whereas a tap's own gather
    computes its index in place. ``lead``: the taps on the leading axis,
    ``idx``, ``w`` (K, ...)."""
    if lead:
        out = flat.at[idx[0]].get(mode="promise_in_bounds") * w[0][..., None]
        for k in range(1, idx.shape[0]):
            out = out + flat.at[idx[k]].get(mode="promise_in_bounds") * w[k][..., None]
        return out
    out = flat.at[idx[..., 0]].get(mode="promise_in_bounds") * w[..., 0, None]
    for k in range(1, idx.shape[-1]):
        out = out + flat.at[idx[..., k]].get(mode="promise_in_bounds") * w[..., k, None]
    return out


def dot3(a: jax.Array, b: jax.Array) -> jax.Array:
    """a·b over the last axis (3) by components (vectorises; see :func:`taps_sum`)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def to_map_fast(env: EnvironmentMap, d: jax.Array) -> jax.Array:
    """:func:`_to_map` (d @ R, d (..., 3)) by components."""
    r = env.rotation
    return jnp.stack([d[..., 0] * r[0, j] + d[..., 1] * r[1, j] + d[..., 2] * r[2, j]
                      for j in range(3)], axis=-1)


class SplitSumMap(eqx.Module):
    """Finely spaced prefiltered levels of an environment's residual map (bright sources
    removed, as in :class:`EnvironmentMap`) for :func:`gloss_split_sum`: level 0 the map,
    level k >= 1 an exact spherical Gaussian blur of std σ_k = (π/H)·2^((k−1)/p), p levels per
    octave, stored at the coarsest halving of the map with texels <= σ_k/2. A prefilter of any
    std between two levels is their blend (matched variance), whose shape error against one
    Gaussian falls with p (a point source's peak: +23 % at p = 1, +3 % at p = 4).

    Attributes:
        atlas: (T, r) all levels flattened, each followed by its two pole means, in the
            channels of the environment's ``spectral_basis``.
        level_table: (M, 3) int32 (offset, H_k, W_k) per level.
        level_sigma: (M,) std per level (radians), level 0 = 0.
        per_octave: static p.
    """

    atlas: jax.Array
    level_table: jax.Array
    level_sigma: jax.Array
    per_octave: int = eqx.field(static=True, default=4)

    @classmethod
    def from_environment(cls, env: EnvironmentMap, texels: Any = None, *,
                         per_octave: int = 4) -> SplitSumMap:
        """Build the levels (NumPy, at preparation) from ``texels`` (H, W, C), default
        ``env.texels`` (pass the float64 map when at hand)."""
        if not (isinstance(per_octave, int) and 1 <= per_octave <= 16):
            raise InputError(f"must be an int in 1..16, got {per_octave!r}",
                             field="per_octave")
        img = np.asarray(env.texels if texels is None else texels, np.float64)
        quad = env.quadrature
        residual, _, _ = _extract_sources(img, quad.max_sources, quad.source_threshold,
                                          quad.source_subpoints)
        basis = np.asarray(env.spectral_basis, np.float64)
        residual = residual @ basis.T  # blurring is linear: work in the r principal spectra
        h0 = residual.shape[0]
        delta = math.pi / h0
        count = int(math.ceil(per_octave * math.log2(0.5 * math.pi / delta))) + 1
        sigmas = [0.0] + [delta * 2.0 ** (k / per_octave) for k in range(count)]
        pyramid = [(residual, 0.0)]  # halvings and the variance each adds
        cur, var = residual, 0.0
        while cur.shape[0] % 2 == 0 and cur.shape[1] % 2 == 0 and cur.shape[0] >= 8:
            d_new = 2.0 * math.pi / cur.shape[0]
            cur = _downsample2(cur)
            var += d_new**2 / 16.0
            pyramid.append((cur, var))
        # each level from the coarsest halving with texels <= σ/2, blurred by the rest of the
        # variance; the levels sharing a halving share its kernel geometry and FFT
        jobs: dict[int, list[tuple[int, float]]] = {}
        for k, sigma in enumerate(sigmas[1:], start=1):
            b = 0
            for i, (cand, cvar) in enumerate(pyramid[1:], start=1):
                if math.pi / cand.shape[0] <= sigma / 2.0 + 1e-12 and cvar <= sigma**2:
                    b = i
            jobs.setdefault(b, []).append((k, math.sqrt(max(sigma**2 - pyramid[b][1], 0.0))))
        levels = {0: residual}
        for b, todo in jobs.items():
            blurred = _sphere_blur_many(pyramid[b][0], [sg for _, sg in todo])
            levels.update({k: lev for (k, _), lev in zip(todo, blurred, strict=True)})
        flat, table = [], []
        off = 0
        for k in range(len(sigmas)):
            lev = levels[k]
            h, w, c = lev.shape
            poles = np.stack([lev[0].mean(axis=0), lev[-1].mean(axis=0)])
            flat.append(np.concatenate([lev.reshape(h * w, c), poles]))
            table.append((off, h, w))
            off += h * w + 2
        dtype = env.atlas.dtype
        return cls(atlas=jnp.asarray(np.concatenate(flat), dtype),
                   level_table=jnp.asarray(np.asarray(table, np.int32)),
                   level_sigma=jnp.asarray(sigmas, dtype), per_octave=per_octave)


def _split_levels(pre: SplitSumMap, sigma: jax.Array
                  ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Adjacent levels (lo, hi) of ``pre`` around std ``sigma`` and the weight of hi: the
    variance-matching weight (σ² − σ_lo²)/(σ_hi² − σ_lo²) through a quintic smoothstep (C²
    in σ; below level 1, a smoothstep in σ/σ_1 from the unfiltered map)."""
    sig = pre.level_sigma
    m = sig.shape[0]
    s1 = sig[1]
    t = jnp.log2(jnp.maximum(sigma, 1e-30) / s1) * pre.per_octave
    below = t < 0.0
    k = jnp.clip(jnp.floor(t), 0, m - 3).astype(jnp.int32)
    lo = jnp.where(below, 0, k + 1)
    hi = jnp.where(below, 1, k + 2)
    slo, shi = sig[lo], sig[hi]
    frac = (sigma * sigma - slo * slo) / (shi * shi - slo * slo)
    w = jnp.where(below, smootherstep(sigma / s1), smootherstep(frac))
    return lo, hi, w


def _split_lookup(pre: SplitSumMap, u: jax.Array, v: jax.Array, lo: jax.Array,
                  hi: jax.Array, w_hi: jax.Array) -> jax.Array:
    """(1 − w_hi)·level lo + w_hi·level hi of ``pre`` at map coordinates (u, v), bilinear,
    all eight taps gathered at once; every argument (...) → (..., r)."""
    plo = pre.level_table[lo]  # (..., 3): offset, H_k, W_k
    phi = pre.level_table[hi]
    i0, w0 = bilinear_taps(u, v, plo[..., 0], plo[..., 1], plo[..., 2], lead=True)
    i1, w1 = bilinear_taps(u, v, phi[..., 0], phi[..., 1], phi[..., 2], lead=True)
    idx = jnp.concatenate([i0, i1], axis=0)
    w = jnp.concatenate([w0 * (1.0 - w_hi), w1 * w_hi], axis=0)
    return taps_sum(pre.atlas, idx, w, lead=True)


def gloss_split_sum(
    env: EnvironmentMap,
    pre: SplitSumMap,
    table: jax.Array,
    normal: Any,
    view: Any,
    mu: Any,
    n: Any,
    *,
    distribution: str = "gaussian",
    geometry: str = "vcavity",
    fresnel: bool = True,
    settings: SplitSum | None = None,
) -> jax.Array:
    """Gloss radiance per unit β (..., C), the same integral as :func:`gloss_integral`
    (the gloss term of eq. 5), by a pre-integrated ("split-sum") approximation:

        gloss ≈ A(θr) · Σ_k w_k L_σ(d_k) + Σ_sources (exact),

    A the lobe's directional albedo and the lobe's shape in reflected directions from
    ``table`` (:func:`lobe_moment_table` of the material, interpolated in cosθr): its mean
    direction (the mirror direction shifted by δ away from the normal, the off-specular peak)
    and its angular variances along (var_t) and across (var_b) the plane of incidence.
    L_σ is the prefiltered residual map ``pre`` (:class:`SplitSumMap`, two levels blended)
    with σ² = max(var_b, (min_ratio)² var_t); the ``settings.along`` lookups d_k lie on the
    great circle through the mean direction in the plane of incidence, binomial weights, spread
    so that the total variance along is var_t. Each lookup's σ is capped at
    ``horizon_ratio`` × its elevation above the surface's horizon. The bright source texels of
    ``env`` (see :class:`GlossQuadrature`) are summed exactly as in :func:`gloss_integral`.
    Zero if N·V <= 0. Smooth in μ and n (the table's nodes move smoothly with them; the level
    blend is C² in σ). Accuracy vs :func:`gloss_integral` and brute force: docs/rendering.md.

    Batched: ``normal`` and ``view`` may have any leading shape (..., 3) (also under
    ``jax.vmap``); the code is elementwise over it, with the lookups unrolled, because XLA:CPU
    runs small dots and short reductions as slow loops.

    Args:
        env: the environment (rotation, spectral basis, sources).
        pre: its :class:`SplitSumMap`.
        table: (size, 4) from :func:`lobe_moment_table` for this μ, n, D, G.
        normal, view: world unit vectors (..., 3).
        mu, n: the material's μ and n (scalars; for the exact source sum).
        settings: :class:`SplitSum` (static).
    """
    s = settings or SplitSum()
    if not (isinstance(s.along, int) and 1 <= s.along <= 8):
        raise InputError(f"must be an int in 1..8, got {s.along!r}", field="along")
    dtype = pre.atlas.dtype
    N = jnp.asarray(normal).astype(dtype)
    V = jnp.asarray(view).astype(dtype)
    table = jnp.asarray(table, dtype)
    n3 = [N[..., i] for i in range(3)]
    v3 = [V[..., i] for i in range(3)]
    nv_raw = n3[0] * v3[0] + n3[1] * v3[1] + n3[2] * v3[2]
    nv = jnp.clip(nv_raw, 0.0, 1.0)
    mom = _interp_moments(table, nv)
    albedo, delta, var_t, var_b = (mom[..., j] for j in range(4))
    # tangent T along V's projection (Duff's frame when V ∥ N)
    p = [v3[i] - nv_raw * n3[i] for i in range(3)]
    p2 = p[0] * p[0] + p[1] * p[1] + p[2] * p[2]
    ok = p2 > 1e-12
    sign = jnp.where(n3[2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + n3[2])
    t0 = [1.0 + sign * n3[0] * n3[0] * a, sign * n3[0] * n3[1] * a, -sign * n3[0]]
    inv_p = jax.lax.rsqrt(jnp.where(ok, p2, 1.0))
    T = [jnp.where(ok, p[i] * inv_p, t0[i]) for i in range(3)]
    sr = jnp.sqrt(jnp.maximum(1.0 - nv * nv, 0.0))
    sd, cd = sincos_poly(delta)
    # each materialised block below is computed once per point (or per lookup); without the
    # barriers XLA fuses it into, and recomputes it in, each of its consumers
    albedo, var_t, var_b, cd, sd, sr, nv, *T = materialise_each(
        albedo, var_t, var_b, cd, sd, sr, nv, *T)
    # mirror direction R = nv N − sr T; P = ∂R/∂θr = −sr N − nv T (away from the normal);
    # mean direction d = cosδ R + sinδ P; e1 = cosδ P − sinδ R
    R = [nv * n3[i] - sr * T[i] for i in range(3)]
    P = [-sr * n3[i] - nv * T[i] for i in range(3)]
    d = [cd * R[i] + sd * P[i] for i in range(3)]
    e1 = [cd * P[i] - sd * R[i] for i in range(3)]
    # prefilter of each lookup: the lobe's variance across, at least (min_ratio σ_t)²; the
    # rest of the variance along comes from the spread of the lookups
    var_t = jnp.maximum(var_t, 1e-12)
    var_n = jnp.maximum(jnp.maximum(var_b, (s.min_ratio * s.min_ratio) * var_t), 1e-12)
    spread = jnp.sqrt(jnp.maximum(var_t - var_n, 1e-12))
    # a spherical Gaussian exp(−γ²/2σ²) has the angular variance σ²(1 − σ²/3) per axis
    sigma0 = jnp.sqrt(var_n * (1.0 + var_n / 3.0))
    offs, wts = _along_rule(s.along)
    rot = env.rotation
    # materialise the per-point quantities once: XLA would otherwise fuse (and recompute)
    # them into every lookup's index arithmetic
    packed = materialise_each(*d, *e1, *n3, spread, sigma0)
    d, e1, n3 = packed[0:3], packed[3:6], packed[6:9]
    spread, sigma0 = packed[9], packed[10]
    ang = jnp.asarray(offs, dtype) * spread[..., None]  # (..., k)
    sa, ca = materialise_each(*sincos_poly(ang))
    dk = [ca * d[i][..., None] + sa * e1[i][..., None] for i in range(3)]  # (..., k) each
    elev = jnp.maximum(dk[0] * n3[0][..., None] + dk[1] * n3[1][..., None]
                       + dk[2] * n3[2][..., None], 0.0)
    sigma = jnp.minimum(sigma0[..., None], s.horizon_ratio * elev)
    *dm, sigma = materialise_each(*(dk[0] * rot[0, j] + dk[1] * rot[1, j] + dk[2] * rot[2, j]
                                    for j in range(3)), sigma)
    lo, hi, w_hi = _split_levels(pre, sigma)
    u, v = uv_of(*dm)
    shape = u.shape
    u, v, w_hi, lo, hi = materialise_each(u, v, w_hi, lo.astype(dtype), hi.astype(dtype))
    lo, hi = lo.astype(jnp.int32), hi.astype(jnp.int32)
    rad = _split_lookup(pre, u.reshape(-1), v.reshape(-1), lo.reshape(-1), hi.reshape(-1),
                        w_hi.reshape(-1)).reshape(*shape, -1)  # (..., k, r)
    mean = float(wts[0]) * rad[..., 0, :]
    for j in range(1, s.along):
        mean = mean + float(wts[j]) * rad[..., j, :]
    out = albedo[..., None] * mean
    if env.source_flux.shape[0]:
        mu_ = jnp.asarray(mu, dtype)
        n_ = jnp.asarray(n, dtype)

        def one(nn: jax.Array, vv: jax.Array) -> jax.Array:
            return _source_gloss(env, nn, vv, mu_, n_, distribution=distribution,
                                 geometry=geometry, fresnel=fresnel)

        lead = N.shape[:-1]
        src = jax.vmap(one)(N.reshape(-1, 3), V.reshape(-1, 3))
        out = out + src.reshape(*lead, -1)
    # to the map's channels: the tap sums materialised once (XLA would otherwise fuse them
    # into each of the C outputs and recompute them C/r times), then a sum of r products
    # (a matrix product here went to a library call that cost more than the sum for C <= 8)
    basis = env.spectral_basis
    out = _materialise(out)
    if basis.shape[1] > 8:
        lead = out.shape[:-1]
        spec = (out.reshape(-1, out.shape[-1]) @ basis).reshape(*lead, -1)
    else:
        spec = out[..., 0:1] * basis[0]
        for i in range(1, basis.shape[0]):
            spec = spec + out[..., i:i + 1] * basis[i]
    return jnp.where((nv_raw > 0.0)[..., None], spec, 0.0)

# --------------------------------------------------------------------------------------------
# Mirror and shading


def mirror_radiance(env: EnvironmentMap, normal: Any, view: Any, n: Any) -> jax.Array:
    """Mirror radiance per unit χ (C,): F(n, θr) · L(R), R = reflect(−V, N) = 2(N·V)N − V."""
    N = jnp.asarray(normal)
    V = jnp.asarray(view)
    nv = jnp.dot(N, V)
    R = 2.0 * nv * N - V
    out = fresnel_dielectric(nv, n) * lookup(env, R)
    return jnp.where(nv > 0.0, out, 0.0)


def shade(material: Material, env: EnvironmentMap, normal: Any, view: Any, *,
          quality: str = "exact") -> jax.Array:
    """Radiance (C,) leaving a surface point towards V under the environment, eq. (5) in
    our physical reading:

        α S(λ) E_irr(λ, N)/π + β ∫ L F D G /(4 cosθr) dω + χ F(n, θr) L(λ, R).

    (The paper's E(λ) factor of the gloss and mirror terms is the environment's own radiance
    here.) Bands: ``material.reflectance`` and the map are (L,) / (H, W, L). Coefficients: both
    are K basis coefficients and the result is the K coefficients of the radiance (the S·E
    product through ``env.product_tensor``). Unbatched: ``jax.vmap`` over points and/or
    materials. Zero if N·V <= 0.

    Args:
        normal, view: world unit vectors (3,), away from the surface.
        quality: gloss quadrature, "exact" (fitting, validation) or "render" (frames); see
            :func:`gloss_integral`.
    """
    N = jnp.asarray(normal)
    V = jnp.asarray(view)
    E = irradiance(env, N)
    if env.product_tensor is None:
        se = material.reflectance * E
    else:
        se = jnp.einsum("i,j,ijk->k", material.reflectance, E, env.product_tensor)
    diffuse = (material.alpha / math.pi) * se
    gloss = gloss_integral(env, N, V, material.mu, material.n,
                           distribution=material.distribution, geometry=material.geometry,
                           quality=quality)
    mirror = mirror_radiance(env, N, V, material.n)
    out = diffuse + material.beta * gloss + material.chi * mirror
    return jnp.where(jnp.dot(N, V) > 0.0, out, 0.0)


def shade_points(material: Material, env: EnvironmentMap, normals: Any, views: Any, *,
                 batch_size: int = 32, quality: str = "exact") -> jax.Array:
    """:func:`shade` over many points, (P, 3) normals and views → (P, C), evaluated in batches
    of ``batch_size`` points (``jax.lax.map``): small batches keep each batch's gloss nodes and
    map taps (points × nodes × 8 × channels) in cache, which on a CPU is several times faster
    than one large batch (such as 4096 points).
    jit/grad-able; the same numbers as ``jax.vmap(shade)``. ``quality``: see :func:`shade`."""
    normals = jnp.asarray(normals)
    views = jnp.asarray(views)
    return jax.lax.map(lambda nv: shade(material, env, nv[0], nv[1], quality=quality),
                       jnp.stack([normals, views], axis=1), batch_size=batch_size)


def white_reference(environment: np.ndarray) -> np.ndarray:
    """(L,) radiance of a white Lambertian facing world +Y (the table) under an
    equirectangular map (Hm, Wm, L) (our mapping: row k at polar angle π(k + ½)/Hm):
    E(+Y)/π = (1/π) ∑ L cosθ sinθ Δθ Δφ over the upper hemisphere. Rotations about +Y do not
    change it."""
    env = np.asarray(environment, np.float64)
    hm, wm = env.shape[:2]
    theta = (np.arange(hm) + 0.5) * np.pi / hm
    wgt = np.cos(theta) * np.sin(theta) * (np.pi / hm) * (2 * np.pi / wm)
    wgt = np.where(theta < np.pi / 2, wgt, 0.0)
    e = np.einsum("h,hwl->l", wgt, env)
    return e / np.pi


# --------------------------------------------------------------------------------------------
# A realistic synthetic environment (tests, benchmarks, demos)


def synthetic_environment(
    height: int = 64,
    width: int = 128,
    wavelengths: Any = None,
    *,
    lamp_radius_deg: float = 4.0,
    lamp_direction: tuple[float, float, float] = (0.4, 0.8, -0.45),
    lamp_luminance_ratio: float = 50.0,
    supersample: int = 4,
) -> np.ndarray:
    """A realistic spectral environment (H, W, L) in W·sr⁻¹·m⁻²·nm⁻¹ (NumPy float64).

    Sky above the horizon: CIE D65 with a brightness gradient (brighter at the horizon) and a
    bluish zenith (CIE illuminant D-series 10000 K). Floor below: a grey-brown reflectance
    (a CIE 2017 colour-evaluation sample) under D65 with a grey/red checker. A small warm lamp
    disc (CIE illuminant A) of ``lamp_radius_deg``, ``lamp_luminance_ratio`` × the sky's mean
    luminance. Texels are averaged over ``supersample``² subsamples (anti-aliased disc and
    horizon).
    """
    import colour

    from ..color import default_wavelengths, illuminant

    wl = default_wavelengths() if wavelengths is None else np.asarray(wavelengths, np.float64)
    d65 = illuminant("D65", wl) / 100.0 * 0.02  # ~ 0.02 W/(sr m² nm) at 560 nm
    cct = colour.temperature.CCT_to_xy_CIE_D(10000.0 * 1.4388 / 1.4380)
    d10k = np.asarray(colour.sd_CIE_illuminant_D_series(cct)[wl], np.float64)
    d10k = d10k / np.interp(560.0, wl, d10k) * 0.02
    lamp = illuminant("A", wl)
    lamp = lamp / np.interp(560.0, wl, lamp) * 0.02 * lamp_luminance_ratio
    from ..color import reflectances_5nm

    w5, refl = reflectances_5nm()
    floor_a = np.interp(wl, w5, refl[20])
    floor_b = np.interp(wl, w5, refl[2])

    ss = supersample
    v = (np.arange(height * ss) + 0.5) / (height * ss)
    u = (np.arange(width * ss) + 0.5) / (width * ss)
    d = uv_to_direction(u[None, :], v[:, None])
    y = d[..., 1]
    sky_w = np.clip(y, 0.0, 1.0)
    sky = ((1.0 - sky_w)[..., None] * d65 * 1.3 + sky_w[..., None] * d10k * 0.8)
    check = ((np.floor(u * 16)[None, :] + np.floor(v * 8)[:, None]) % 2)[..., None]
    floor = (0.35 * d65) * (check * floor_a + (1.0 - check) * floor_b)
    img = np.where((y > 0.0)[..., None], sky, floor)
    ld = np.asarray(lamp_direction, np.float64)
    ld = ld / np.linalg.norm(ld)
    disc = (d @ ld) > math.cos(math.radians(lamp_radius_deg))
    img = np.where(disc[..., None], lamp, img)
    return img.reshape(height, ss, width, ss, -1).mean(axis=(1, 3))
