"""An environment seen from above a real plane (NumPy, float64, once per scene).

An object standing on a table does not see the environment below the table: it sees the table.
An infinite Lambertian plane of reflectance ρ(λ) under an environment L(ω) at infinity has the
radiance

    L_plane(λ) = ρ(λ) E_up(λ) / π,    E_up = ∫_{n·ω > 0} L(ω) (n·ω) dω,

the same everywhere on it and in every direction, and from any point above it the plane fills
exactly the directions below its horizon (n·ω < 0). :func:`ground_plane` replaces the map's
texels there by L_plane: every term that looks the environment up (diffuse, gloss, mirror,
the bright sources, the self-visibility's hidden directions) then sees the table. What the
uniform value leaves out is where the table is not uniform: the objects' own shadows and light
on it (those are added where the table is drawn or composited, :mod:`spectral_fit.rendering`).

Texels that straddle the horizon are split by the share of their area below it (measured on
an s × s grid of sub-points per texel).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ._equirect import uv_to_direction

__all__ = ["ground_plane", "upper_irradiance"]


def _below_share(height: int, width: int, normal: np.ndarray, sub: int) -> np.ndarray:
    """Share (H, W) of each texel's area below the plane through the origin with unit
    ``normal`` (map frame), from ``sub`` × ``sub`` sub-points spaced evenly in (u, cosθ)."""
    share = np.zeros((height, width))
    edges = np.cos(np.pi * np.arange(height + 1) / height)
    offs = (np.arange(sub) + 0.5) / sub
    for a in offs:
        cos_t = edges[:-1] + a * (edges[1:] - edges[:-1])  # equal-area rows within a texel
        v = np.arccos(np.clip(cos_t, -1.0, 1.0)) / np.pi
        for b in offs:
            u = (np.arange(width) + b) / width
            d = uv_to_direction(u[None, :], v[:, None])
            share += (d @ normal < 0.0)
    return share / (sub * sub)


def _cosine_weights(height: int, width: int, normal: np.ndarray, sub: int) -> np.ndarray:
    """∫ (n·ω)⁺ dω over each texel (H, W): the exact first moment ∫ ω dω of each of its
    ``sub`` × ``sub`` sub-cells (in φ and θ) dotted with n, clipped at 0 per sub-cell (exact
    for texels wholly above the horizon)."""
    theta = np.pi * np.arange(height * sub + 1) / (height * sub)
    phi = 2.0 * np.pi * np.arange(width * sub + 1) / (width * sub)
    t0, t1 = theta[:-1], theta[1:]
    i_ss = 0.5 * ((t1 - np.sin(t1) * np.cos(t1)) - (t0 - np.sin(t0) * np.cos(t0)))
    i_cs = 0.5 * (np.sin(t1) ** 2 - np.sin(t0) ** 2)
    p0, p1 = phi[:-1], phi[1:]
    i_sin = np.cos(p0) - np.cos(p1)
    i_cos = np.sin(p1) - np.sin(p0)
    # ω = (sinφ sinθ, cosθ, −cosφ sinθ), dω = sinθ dθ dφ
    m = (normal[0] * i_ss[:, None] * i_sin[None, :]
         + normal[1] * i_cs[:, None] * (p1 - p0)[None, :]
         - normal[2] * i_ss[:, None] * i_cos[None, :])
    m = np.maximum(m, 0.0)
    return m.reshape(height, sub, width, sub).sum(axis=(1, 3))


def upper_irradiance(texels: Any, normal: Any, *, subsamples: int = 4) -> np.ndarray:
    """Irradiance E_up (C,) of a plane with unit ``normal`` (3,) (map frame) from the
    environment ``texels`` (H, W, C) above it: Σ L ∫_texel (n·ω)⁺ dω, the cosine integrated
    exactly over each texel's ``subsamples``² sub-cells (W·m⁻²·nm⁻¹ for radiance in
    W·sr⁻¹·m⁻²·nm⁻¹)."""
    img = np.asarray(texels, np.float64)
    h, w, _ = img.shape
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    return np.einsum("hw,hwc->c", _cosine_weights(h, w, n, subsamples), img)


def ground_plane(texels: Any, normal: Any, reflectance: Any, *, subsamples: int = 4
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The environment as seen from above an infinite Lambertian plane.

    Args:
        texels: (H, W, L) spectral radiance of the environment (map frame, equirectangular).
        normal: (3,) the plane's normal in the MAP frame (towards the objects).
        reflectance: (L,) the plane's spectral reflectance ρ(λ), or a scalar.
        subsamples: s, texels crossing the horizon are split on s × s sub-points.

    Returns:
        (texels (H, W, L) with every direction below the horizon showing ρ E_up / π, the
        plane's radiance L_plane (L,)).
    """
    img = np.asarray(texels, np.float64)
    h, w, c = img.shape
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    rho = np.broadcast_to(np.asarray(reflectance, np.float64), (c,))
    plane = rho * upper_irradiance(img, n, subsamples=subsamples) / np.pi
    below = _below_share(h, w, n, subsamples)[..., None]
    return img * (1.0 - below) + below * plane, plane
