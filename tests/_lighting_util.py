"""Brute-force gloss oracle shared by the lighting tests: the texel sum of L F D G /(4 cosθr) Δω
over a supersampled map (each texel a box of constant radiance), float64 NumPy, with its own
closed forms of F, D and G (independent of spectral_fit.reflectance)."""

from __future__ import annotations

import math

import numpy as np
from scipy.special import erf

from spectral_fit.environment import texel_directions, texel_solid_angles


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


def brute_gloss(img, n, v, mu, eta, *, rotation=None, ss=2, distribution="gaussian",
                geometry="vcavity"):
    """∫ L F D G /(4 cosθr) dω (C,) for world unit N, V under the (H, W, C) map placed by
    ``rotation`` (world-from-map), by a texel sum over the map upsampled ss× (box)."""
    rotation = np.eye(3) if rotation is None else np.asarray(rotation)
    h, w, c = img.shape
    L = np.repeat(np.repeat(img, ss, axis=0), ss, axis=1).reshape(-1, c)
    d = texel_directions(h * ss, w * ss).reshape(-1, 3) @ rotation.T
    sa = texel_solid_angles(h * ss, w * ss).reshape(-1)
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
    m = f > 0
    return f[m] @ L[m]


def configs(lamp, mu, k, seed, theta_max_deg=60.0):
    """k (N, V) pairs, θr up to ``theta_max_deg``; every other one puts the mirror direction
    within ~μ of ``lamp`` (the hard case: the lobe straddles the lamp's edge)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(k):
        th = math.radians(rng.uniform(0, theta_max_deg))
        if i % 2 == 0:
            r = unit(lamp + rng.normal(size=3) * mu)
            x = rng.normal(size=3)
            a = unit(x - (x @ r) * r)
            v = math.cos(2 * th) * r + math.sin(2 * th) * a
            n = unit(v + r)
        else:
            n = unit(rng.normal(size=3))
            a = unit(np.cross(n, [0.3, 0.5, 0.7]))
            b = np.cross(n, a)
            p = rng.uniform(0, 2 * math.pi)
            v = math.cos(th) * n + math.sin(th) * (math.cos(p) * a + math.sin(p) * b)
        out.append((n, v))
    return out
