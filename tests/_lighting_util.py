"""Brute-force gloss oracle shared by the lighting tests: the texel sum of L F D G /(4 cosθr) Δω
over a supersampled map (each texel a box of constant radiance), float64 NumPy, with its own
closed forms of F, D and G (independent of spectral_fit.reflectance)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from scipy.special import erf

from spectral_fit.environment import (
    EnvironmentMap,
    rotation_y,
    texel_directions,
    texel_solid_angles,
)
from spectral_fit.exr import read_spectral_exr

ANCHOR = Path(__file__).resolve().parents[1] / "measurements" / "benchmark" / \
    "anchor_environment.exr"


def anchor_map():
    """The benchmark's anchor map as the lighting tests use it: (img (H, W, C) float64, the
    EnvironmentMap with its 180° rotation, the world direction (3,) of its brightest texel)."""
    _, img = read_spectral_exr(ANCHOR)
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


def _bilinear_taps(h, w, ss):
    """The bilinear reconstruction of an (h, w) map at the centres of its ss× finer grid, as
    (F, 4) indices into the map's texels flattened (h·w) plus its two pole means (h·w, the
    first row's mean at v = 0; h·w + 1, the last row's at v = 1) and (F, 4) weights. Written
    from the DESIGN §3 convention (texel centres at k + ½, wrap in u, linear towards the pole
    mean between the pole and the first/last row centre), independently of the library."""
    v = (np.arange(h * ss) + 0.5) / (h * ss)
    u = (np.arange(w * ss) + 0.5) / (w * ss)
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

    A, B, FY = ra[:, None], rb[:, None], fy[:, None]
    idx = np.stack(np.broadcast_arrays(index(A, xa[None]), index(A, xb[None]),
                                       index(B, xa[None]), index(B, xb[None])), axis=-1)
    wgt = np.stack(np.broadcast_arrays((1 - FY) * (1 - fx)[None], (1 - FY) * fx[None],
                                       FY * (1 - fx)[None], FY * fx[None]), axis=-1)
    return idx.reshape(-1, 4), wgt.reshape(-1, 4)


_GEOMETRY = {}


def brute_gloss(img, n, v, mu, eta, *, rotation=None, ss=2, distribution="gaussian",
                geometry="vcavity", model="bilinear"):
    """∫ L F D G /(4 cosθr) dω (C,) for world unit N, V under the (H, W, C) map placed by
    ``rotation`` (world-from-map), by a texel sum over the map upsampled ss×: ``model``
    "bilinear" upsamples it as the library's lookup defines the map between texel centres
    (the map the library integrates), "box" repeats each texel (constant radiance per texel).
    The two differ only for lobes narrower than a few texels. The integrand's weights are
    accumulated onto the map's own texels, so the cost does not grow with the channels."""
    rotation = np.eye(3) if rotation is None else np.asarray(rotation)
    h, w, c = img.shape
    key = (h, w, ss)
    if key not in _GEOMETRY:
        _GEOMETRY[key] = (texel_directions(h * ss, w * ss).reshape(-1, 3),
                          texel_solid_angles(h * ss, w * ss).reshape(-1))
    d, sa = _GEOMETRY[key]
    d = d @ rotation.T
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
    f = np.where(nl > 0, fresnel(vh, eta) * D * G / (4 * nv), 0.0) * sa
    flat = np.asarray(img, np.float64).reshape(-1, c)
    if model == "box":
        return f.reshape(h, ss, w, ss).sum(axis=(1, 3)).reshape(-1) @ flat
    if (key, "taps") not in _GEOMETRY:
        _GEOMETRY[(key, "taps")] = _bilinear_taps(h, w, ss)
    idx, wt = _GEOMETRY[(key, "taps")]
    m = f > 0
    coarse = np.bincount(idx[m].reshape(-1), weights=(wt[m] * f[m, None]).reshape(-1),
                         minlength=h * w + 2)
    poles = np.stack([img[0].mean(axis=0), img[-1].mean(axis=0)])
    return coarse[: h * w] @ flat + coarse[h * w:] @ poles


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
