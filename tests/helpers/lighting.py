"""Brute-force gloss oracle shared by the lighting tests: the texel sum of L F D G /(4 cosθr) Δω
over a supersampled map (each texel a box of constant radiance), float64 NumPy, with its own
closed forms of F, D and G (independent of spectral_fit.lighting)."""

from __future__ import annotations

import math

import numpy as np
from scipy.special import erf

from helpers import ANCHOR_ENV
from spectral_fit.io import read_spectral_exr
from spectral_fit.lighting import EnvironmentMap, rotation_y, texel_directions, texel_solid_angles


def anchor_map():
    """The benchmark's anchor map as the lighting tests use it: (img (H, W, C) float64, the
    EnvironmentMap with its 180° rotation, the world direction (3,) of its brightest texel)."""
    _, img = read_spectral_exr(ANCHOR_ENV)
    img = np.asarray(img, np.float64)
    env = EnvironmentMap.from_array(img, rotation_y_deg=180.0)
    lum = img.sum(-1)
    i, j = np.unravel_index(np.argmax(lum), lum.shape)
    lamp = rotation_y(180.0) @ texel_directions(*img.shape[:2])[i, j]
    return img, env, lamp


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def fresnel(c, eta):
    c = np.clip(np.abs(c), 0.0, 1.0)
    g = np.sqrt(eta * eta + c * c - 1.0)
    return 0.5 * ((g - c) / (g + c)) ** 2 * (1 + ((c * (g + c) - 1) / (c * (g - c) + 1)) ** 2)


def gaussian_k(mu):
    """1 / ∫ exp(−θ²/μ²) cosθ dω over the hemisphere (trapezoid, 20001 points)."""
    t = np.linspace(0.0, min(math.pi / 2, 8 * mu), 20001)
    return 1.0 / np.trapezoid(2 * math.pi * np.exp(-(t / mu) ** 2) * np.cos(t) * np.sin(t), t)


def smith_g1(c, m):
    c = np.clip(c, 1e-9, 1.0)
    a = c / (m * np.sqrt(np.maximum(1 - c * c, 1e-18)))
    lam = (erf(a) - 1) / 2 + np.exp(-a * a) / (2 * a * math.sqrt(math.pi))
    return 1.0 / (1.0 + lam)


def bilinear_taps(h, w, ss):
    """The bilinear reconstruction of an (h, w) map at the centres of its ss× finer grid, as
    (F, 4) indices into the map's texels flattened (h·w) plus its two pole means (h·w, the
    first row's mean at v = 0; h·w + 1, the last row's at v = 1) and (F, 4) weights. Written
    from our map convention (texel centres at k + ½, wrap in u, linear towards the pole
    mean between the pole and the first/last row centre), independently of the library."""
    v = (np.arange(h * ss) + 0.5) / (h * ss)
    u = (np.arange(w * ss) + 0.5) / (w * ss)
    return _taps_uv(h, w, *np.broadcast_arrays(u[None, :], v[:, None]))


def _taps_uv(h, w, u, v):
    """(F, 4) indices and weights of the bilinear reconstruction (as in :func:`bilinear_taps`)
    at map coordinates u, v (any equal shapes, F elements)."""
    u, v = np.asarray(u, np.float64).reshape(-1), np.asarray(v, np.float64).reshape(-1)
    ty, tx = v * h - 0.5, u * w - 0.5
    x0 = np.floor(tx).astype(int)
    fx = tx - x0
    xa, xb = x0 % w, (x0 + 1) % w
    ra = np.floor(ty).astype(int)
    rb = ra + 1
    fy = ty - ra
    north, south = ty < 0, ty >= h - 1
    ra, rb, fy = np.where(north, -1, ra), np.where(south, -2, rb), fy.copy()
    fy = np.where(north, (ty + 0.5) / 0.5, np.where(south, (ty - (h - 1)) / 0.5, fy))

    def index(r, col):
        return np.where(r == -1, h * w, np.where(r == -2, h * w + 1, r * w + col))

    idx = np.stack([index(ra, xa), index(ra, xb), index(rb, xa), index(rb, xb)], axis=-1)
    wgt = np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], axis=-1)
    return idx, wgt


_GEOMETRY = {}


def brute_gloss(img, n, v, mu, eta, *, rotation=None, ss=2, distribution="gaussian",
                geometry="vcavity", model="bilinear", refine=1, refine_tol=1e-3):
    """∫ L F D G /(4 cosθr) dω (C,) for world unit N, V under the (H, W, C) map placed by
    ``rotation`` (world-from-map), by a texel sum over the map upsampled ss×: ``model``
    "bilinear" upsamples it as the library's lookup defines the map between texel centres
    (the map the library integrates), "box" repeats each texel (constant radiance per texel).
    The two differ only for lobes narrower than a few texels. The integrand's weights are
    accumulated onto the map's own texels, so the cost does not grow with the channels.

    ``refine`` > 1 (bilinear model): the map texels where the integrand per solid angle
    reaches ``refine_tol`` × its maximum somewhere (the lobe's core) are summed ss·refine×
    finer instead (adaptive supersampling, for lobes less than a texel across: narrow lobes
    at grazing views on a small bright source)."""
    rotation = np.eye(3) if rotation is None else np.asarray(rotation)
    h, w, c = img.shape
    key = (h, w, ss)
    if key not in _GEOMETRY:
        _GEOMETRY[key] = (texel_directions(h * ss, w * ss).reshape(-1, 3),
                          texel_solid_angles(h * ss, w * ss).reshape(-1))
    d, sa = _GEOMETRY[key]
    f = _integrand(d @ rotation.T, sa, n, v, mu, eta, distribution, geometry)
    flat = np.asarray(img, np.float64).reshape(-1, c)
    if model == "box":
        return f.reshape(h, ss, w, ss).sum(axis=(1, 3)).reshape(-1) @ flat
    if (key, "taps") not in _GEOMETRY:
        _GEOMETRY[(key, "taps")] = bilinear_taps(h, w, ss)
    idx, wt = _GEOMETRY[(key, "taps")]
    extra = None
    if refine > 1:
        dens = (f / sa).reshape(h, ss, w, ss).max(axis=(1, 3))
        rows, cols = np.nonzero(dens >= refine_tol * dens.max())
        cell = np.zeros((h, w), bool)
        cell[rows, cols] = True
        f = np.where(np.repeat(np.repeat(cell, ss, 0), ss, 1).reshape(-1), 0.0, f)
        s = ss * refine
        k = (np.arange(s) + 0.5) / s
        fv = (rows[:, None, None] + k[None, :, None]) / h  # (K, s, 1)
        fu = np.broadcast_to((cols[:, None, None] + k[None, None, :]) / w, (rows.size, s, s))
        edges = (rows[:, None] + np.arange(s + 1)[None, :] / s) * (math.pi / h)
        sa_row = (2 * math.pi / (w * s)) * (np.cos(edges[:, :-1]) - np.cos(edges[:, 1:]))
        sa_f = np.broadcast_to(sa_row[:, :, None], fu.shape).reshape(-1)
        fv = np.broadcast_to(fv, fu.shape).reshape(-1)
        st = np.sin(math.pi * fv)
        df = np.stack([np.sin(2 * math.pi * fu.reshape(-1)) * st, np.cos(math.pi * fv),
                       -np.cos(2 * math.pi * fu.reshape(-1)) * st], axis=-1)
        extra = (_integrand(df @ rotation.T, sa_f, n, v, mu, eta, distribution, geometry),
                 *_taps_uv(h, w, fu, fv))
    coarse = _accumulate(f, idx, wt, h * w + 2)
    if extra is not None:
        coarse += _accumulate(*extra, h * w + 2)
    poles = np.stack([img[0].mean(axis=0), img[-1].mean(axis=0)])
    return coarse[: h * w] @ flat + coarse[h * w:] @ poles


def _accumulate(f, idx, wt, size):
    m = f > 0
    return np.bincount(idx[m].reshape(-1), weights=(wt[m] * f[m, None]).reshape(-1),
                       minlength=size)


def _integrand(d, sa, n, v, mu, eta, distribution, geometry):
    """L-free integrand F D G /(4 cosθr) Δω at world directions d (F, 3) of cells sa (F,)."""
    nl, nv = d @ n, float(n @ v)
    hv = d + v
    hv /= np.linalg.norm(hv, axis=1, keepdims=True)
    nh, vh = hv @ n, hv @ v
    if distribution == "gaussian":
        D = gaussian_k(mu) * np.exp(-(np.arccos(np.clip(nh, -1, 1)) / mu) ** 2)
    else:
        c2 = np.clip(nh, 1e-9, 1) ** 2
        D = np.exp(-(1 - c2) / (c2 * mu * mu)) / (math.pi * mu * mu * c2 * c2)
    D = np.where(nh > 0, D, 0.0)
    if geometry == "vcavity":
        vhs = np.where(vh > 0, vh, 1.0)
        G = np.clip(np.minimum(1, np.minimum(2 * nh * nv / vhs, 2 * nh * nl / vhs)), 0, 1)
    else:
        G = smith_g1(nv, mu) * smith_g1(nl, mu)
    G = np.where(vh > 0, G, 0.0)
    return np.where(nl > 0, fresnel(vh, eta) * D * G / (4 * nv), 0.0) * sa


def configs(lamp, mu, k, seed, theta_max_deg=60.0):
    """k (N, V) pairs, θr up to ``theta_max_deg``; every other one puts the mirror direction
    within ~μ of ``lamp`` (the hard case: the lobe straddles the lamp's edge)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(k):
        th = math.radians(rng.uniform(0, theta_max_deg))
        if i % 2 == 0:
            out.append(_near(lamp, mu, th, rng))
        else:
            out.append(_anywhere(th, rng))
    return out


def grazing_configs(lamp, mu, seed, angles_deg=(70.0, 75.0, 80.0)):
    """Two (N, V) pairs per θr in ``angles_deg``: one with the mirror direction within ~μ of
    ``lamp``, one anywhere."""
    rng = np.random.default_rng(seed)
    out = []
    for a in angles_deg:
        th = math.radians(a)
        out += [_near(lamp, mu, th, rng), _anywhere(th, rng)]
    return out


def _near(lamp, mu, th, rng):
    r = unit(lamp + rng.normal(size=3) * mu)
    x = rng.normal(size=3)
    a = unit(x - (x @ r) * r)
    v = math.cos(2 * th) * r + math.sin(2 * th) * a
    return unit(v + r), v


def _anywhere(th, rng):
    n = unit(rng.normal(size=3))
    a = unit(np.cross(n, [0.3, 0.5, 0.7]))
    b = np.cross(n, a)
    p = rng.uniform(0, 2 * math.pi)
    v = math.cos(th) * n + math.sin(th) * (math.cos(p) * a + math.sin(p) * b)
    return n, v
