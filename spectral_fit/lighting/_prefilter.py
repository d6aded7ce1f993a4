"""Prefiltered levels of an environment map, built at construction (NumPy, float64).

Level 0 is the map; a level of std σ (radians) is an exact isotropic Gaussian blur on the sphere
(:func:`_sphere_blur`), stored at the coarsest solid-angle-weighted halving of the map
(:func:`_downsample2`) whose texels are <= σ/2. Maps are (H, W, C) equirectangular
(``_equirect``), the C channels blurred independently (the blur is linear). Also the map's
principal spectra (:func:`_spectral_basis`), the channels in which the levels are stored.
"""

from __future__ import annotations

import math

import numpy as np

from ._equirect import texel_solid_angles

__all__: list[str] = []


def _downsample2(img: np.ndarray) -> np.ndarray:
    """Halve an (H, W, C) equirectangular map by solid-angle-weighted 2×2 averaging."""
    h, w = img.shape[:2]
    sa = texel_solid_angles(h, w)[:, :1]  # (H, 1)
    pair = img.reshape(h // 2, 2, w // 2, 2, -1).mean(axis=3)  # columns: equal solid angle
    wgt = sa.reshape(h // 2, 2, 1, 1)
    return (pair * wgt).sum(axis=1) / wgt.sum(axis=1)


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


def _row_angles(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """sin θ (H,) of the texel rows and the great-circle angle (H_out, H_in, W) between the
    centre of a texel in row i and the texels of row j, by azimuth difference (radians)."""
    theta = np.pi * (np.arange(h) + 0.5) / h
    phi = 2.0 * np.pi * np.arange(w) / w
    ct, st = np.cos(theta), np.sin(theta)
    cosg = (ct[:, None, None] * ct[None, :, None]
            + st[:, None, None] * st[None, :, None] * np.cos(phi)[None, None, :])
    return st, np.arccos(np.clip(cosg, -1.0, 1.0))


def _sphere_blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """Isotropic Gaussian blur of an (H, W, C) equirectangular map on the sphere: every output
    texel is the solid-angle-weighted mean of all texels with weights exp(−γ²/2σ²), γ the great
    circle angle between texel centres. The weights between two rows depend only on the azimuth
    difference (a circulant), so each row pair is a circular convolution, done by FFT along the
    rows: exact on the texel-centre sampling, at any latitude and across the poles."""
    if sigma <= 0:
        return img
    h, w, c = img.shape
    st, gamma = _row_angles(h, w)
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
    st, gamma = _row_angles(h, w)
    gamma2 = gamma ** 2
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


def level_atlas(levels) -> tuple[np.ndarray, list[tuple[int, int]], list[int]]:
    """Levels (H_k, W_k, C) flattened into one atlas ``(sum(H_k·W_k + 2), C)``: each level's
    texels (row-major) followed by its two pole means (the first and last rows' means), as the
    lookups expect. Returns the atlas, the (H_k, W_k) per level and each level's offset."""
    flat, shapes, offsets = [], [], []
    off = 0
    for lev in levels:
        h, w, c = lev.shape
        poles = np.stack([lev[0].mean(axis=0), lev[-1].mean(axis=0)])
        flat.append(np.concatenate([lev.reshape(h * w, c), poles]))
        shapes.append((h, w))
        offsets.append(off)
        off += h * w + 2
    return np.concatenate(flat), shapes, offsets
