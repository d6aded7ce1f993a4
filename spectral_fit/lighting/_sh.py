"""Order-2 real spherical harmonics of an environment map (Ramamoorthi & Hanrahan 2001).

:func:`sh_coefficients` projects an (H, W, C) equirectangular map (NumPy, float64) onto the 9
basis functions (R&H order), each texel a box of constant radiance; ``SH_C1`` … ``SH_C5`` are
the constants of R&H's eq. 13, which gives the irradiance from them (``_irradiance``).
"""

from __future__ import annotations

import numpy as np

from ._equirect import texel_solid_angles

__all__ = [
    "SH_C1",
    "SH_C2",
    "SH_C3",
    "SH_C4",
    "SH_C5",
    "sh_coefficients",
]

# Ramamoorthi & Hanrahan 2001, eq. 13.
SH_C1 = 0.429043
SH_C2 = 0.511664
SH_C3 = 0.743125
SH_C4 = 0.886227
SH_C5 = 0.247708


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
