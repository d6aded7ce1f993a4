"""Bright sources taken out of an environment map at construction (NumPy, float64).

Texels whose channel-summed |value| exceeds a multiple of the map's solid-angle-weighted mean
(small, very bright lamps that no prefiltered quadrature resolves; at most a given number,
brightest first) are replaced in a residual map by their surroundings and carried as explicit
sources: the excess radiance × solid angle, at sub-points of each source texel or at quadrature
points over its footprint in the bilinear map (the tent over ±1 texel), as map-frame unit
directions (S, P, 3) and weights (S, P). Residual + sources = the map exactly. Maps are (H, W, C)
equirectangular (``_equirect``); the settings are those of :class:`GlossQuadrature`.
"""

from __future__ import annotations

import numpy as np

from ._equirect import texel_solid_angles, uv_to_direction

__all__: list[str] = []


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
