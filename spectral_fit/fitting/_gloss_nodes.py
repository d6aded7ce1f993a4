"""The fixed, μ-independent gloss quadrature nodes of shading points and their cached
radiance, built outside ``jit`` (:func:`build_gloss_nodes`; the node layout is described in
:mod:`spectral_fit.fitting`'s radiance cache: rings in log θh, azimuths from V's, explicit
source sub-points).

Shapes: P shading points, J rings, M azimuths, S source sub-points, r environment channels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from ._cache_geometry import _ray_spheres, _unit, _view_frames
from ._env_sampling import _prefiltered
from ._radiance_cache import GlossNodes, Sphere

__all__ = ["build_gloss_nodes"]


def _rings(theta0: float, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Ring angles θ_j = θ0 q^j up to π/2 and their radial weights h θ_j sinθ_j (trapezoid in
    t = log θ, h = log q), the geometric tail j < 0 added to the first."""
    if not (0 < theta0 < 0.5 and ratio > 1.0):
        raise InputError(f"theta0 in (0, 0.5) and ring_ratio > 1 required, got {theta0}, "
                         f"{ratio}", field="cache")
    h = math.log(ratio)
    J = int(math.floor(math.log(0.5 * math.pi / theta0) / h)) + 1
    theta = theta0 * ratio ** np.arange(J)
    w = h * theta * np.sin(theta)
    w[0] += h * theta0 ** 2 * ratio ** -2 / (1.0 - ratio ** -2)
    return theta, w


def _visible_arc(nv: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """φ_max (P, J): azimuths |φ| <= φ_max (from V's) of ring θ reflect V above the surface:
    sin2θ sinθr cosφ > −cosθr cos2θ."""
    sin_r = np.sqrt(np.maximum(1.0 - nv * nv, 0.0))[:, None]
    a = 2.0 * np.sin(theta) * np.cos(theta) * sin_r
    b = -nv[:, None] * np.cos(2.0 * theta)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(np.abs(a) > 1e-300, b / a, np.sign(b) * 2.0)
    return np.where(c <= -1.0, math.pi, np.where(c >= 1.0, 0.0, np.arccos(np.clip(c, -1, 1))))


def build_gloss_nodes(env: Any, positions: np.ndarray, normals: np.ndarray, views: np.ndarray,
                      *, objects: np.ndarray, spheres: Sequence[Sphere] = (),
                      occlusion: Any = None, theta0: float = 0.003,
                      ring_ratio: float = 1.35, azimuths: int = 16,
                      prefilter: float = 0.35, horizon_ratio: float = 0.2,
                      subsamples: int = 1, sources: str = "tent", dtype: Any = jnp.float32
                      ) -> tuple[GlossNodes, dict[str, np.ndarray]]:
    """Gloss nodes of P shading points (see the module docstring), outside ``jit``.

    Args:
        env: :class:`~spectral_fit.lighting.EnvironmentMap`.
        positions, normals, views: (P, 3) world points, unit normals, unit directions towards
            the observer.
        objects: (P,) object of each point (its own sphere never occludes it).
        spheres: occluders; node directions that hit one get no environment radiance.
        occlusion: a :class:`~spectral_fit.fitting._occluders.PointOcclusion` of these P
            points (objects of any shape), used instead of ``spheres`` when given.
        subsamples: s; each node's radiance is the mean of s × s sub-samples over its cell
            (1: one lookup at the node, prefiltered to the cell's size).
        sources: how the map's bright source texels are summed (:class:`CacheOptions`).

    Returns:
        (nodes, hits): ``hits`` holds, for the nodes that hit an occluder, flat node indices
        ``node`` (into P·J·M), ``sphere`` (the occluder: an index into ``spheres``, or into
        the occlusion's spheres then meshes) and world ``point`` (·, 3).
    """
    P = positions.shape[0]
    N = _unit(np.asarray(normals, np.float64))
    V = _unit(np.asarray(views, np.float64))
    X = np.asarray(positions, np.float64)
    nv = np.clip(np.sum(N * V, -1), 0.0, 1.0)
    theta, rw = _rings(theta0, ring_ratio)
    J, M = theta.size, int(azimuths)
    phi_max = _visible_arc(nv, theta)  # (P, J)
    xg, wg = np.polynomial.legendre.leggauss(M)
    full = phi_max >= math.pi - 1e-12
    stag = 0.5 * (np.arange(J) % 2)[None, :, None]
    phi_full = -math.pi + 2.0 * math.pi * (np.arange(M)[None, None, :] + 0.5 + stag) / M
    phi = np.where(full[..., None], phi_full, phi_max[..., None] * xg[None, None, :])
    aw = np.where(full[..., None], 2.0 * math.pi / M, phi_max[..., None] * wg[None, None, :])
    T, B = _view_frames(N, V)
    ct, st = np.cos(theta)[None, :, None], np.sin(theta)[None, :, None]
    sin_r = np.sqrt(np.maximum(1.0 - nv * nv, 0.0))[:, None, None]
    vh = ct * nv[:, None, None] + st * sin_r * np.cos(phi)
    nl = 2.0 * vh * ct - nv[:, None, None]
    live = np.asarray(objects) >= 0  # points on no object get no nodes
    ok = (vh > 0.0) & (nl > 0.0) & (nv[:, None, None] > 0.0) & (aw > 0.0) & live[:, None, None]
    dwh = rw[None, :, None] * aw
    base = np.where(ok, dwh * vh / np.where(nv > 0.0, nv, 1.0)[:, None, None], 0.0)
    # reflected directions
    H = (ct[..., None] * N[:, None, None, :]
         + st[..., None] * (np.cos(phi)[..., None] * T[:, None, None, :]
                            + np.sin(phi)[..., None] * B[:, None, None, :]))
    Ldir = _unit(2.0 * vh[..., None] * H - V[:, None, None, :])
    area = 4.0 * np.maximum(vh, 0.0) * dwh
    elev = np.arcsin(np.clip(nl, 0.0, 1.0))
    sigma = np.minimum(prefilter * np.sqrt(area), horizon_ratio * elev)
    flat_ok = ok.reshape(-1)
    rad = np.zeros((P * J * M, env.atlas.shape[1]), np.float32)
    dirs = Ldir.reshape(-1, 3)
    hit_idx = np.full(P * J * M, -1, np.int64)
    hit_pt = np.zeros((P * J * M, 3))
    if occlusion is not None:
        sel = np.flatnonzero(flat_ok)
        hi_, hp_, _ = occlusion.trace(sel // (J * M), dirs[sel])
        hit_idx[sel] = hi_
        hit_pt[sel] = hp_
    elif spheres:
        orig = np.broadcast_to(X[:, None, None, :], Ldir.shape).reshape(-1, 3)
        skip = np.broadcast_to(np.asarray(objects)[:, None, None], ok.shape).reshape(-1)
        sel = np.flatnonzero(flat_ok)
        hi_, ht = _ray_spheres(orig[sel], dirs[sel], spheres, skip[sel])
        hit_idx[sel] = hi_
        hit_pt[sel] = orig[sel] + np.where(hi_ >= 0, ht, 0.0)[:, None] * dirs[sel]
    look = flat_ok & (hit_idx < 0)
    sel = np.flatnonzero(look)
    if sel.size and subsamples <= 1:
        rad[sel] = _prefiltered(env, dirs[sel], sigma.reshape(-1)[sel])
    elif sel.size:
        # the mean radiance over each node's cell: s × s sub-samples spread over the cell
        # (log θh × azimuth), each prefiltered to its own sub-cell
        k = int(subsamples)
        off = (np.arange(k) + 0.5) / k - 0.5
        pi_, ji, mi = np.unravel_index(sel, (P, J, M))
        dphi = np.where(full[pi_, ji], 2.0 * math.pi / M, aw[pi_, ji, mi])
        th = theta[ji][:, None, None] * np.exp(math.log(ring_ratio) * off)[None, :, None]
        ph = phi[pi_, ji, mi][:, None, None] + dphi[:, None, None] * off[None, None, :]
        th, ph = np.broadcast_arrays(th, ph)
        Ns, Ts, Bs, Vs = (a[pi_][:, None, None, :] for a in (N, T, B, V))
        Hs = (np.cos(th)[..., None] * Ns + np.sin(th)[..., None]
              * (np.cos(ph)[..., None] * Ts + np.sin(ph)[..., None] * Bs))
        vhs = np.sum(Hs * Vs, -1)
        Ls = _unit(2.0 * vhs[..., None] * Hs - Vs)
        nls = np.sum(Ls * Ns, -1)
        vis = (nls > 0.0) & (vhs > 0.0)
        sig = np.minimum(sigma.reshape(-1)[sel][:, None, None] / k,
                         horizon_ratio * np.arcsin(np.clip(nls, 0.0, 1.0)))
        got = _prefiltered(env, Ls.reshape(-1, 3), sig.reshape(-1)).reshape(
            sel.size, k * k, -1)
        wv = vis.reshape(sel.size, k * k, 1).astype(np.float32)
        mean = (got * wv).sum(1) / np.maximum(wv.sum(1), 1.0)
        fallback = wv.sum(1)[:, 0] == 0
        rad[sel] = np.where(fallback[:, None], _prefiltered(
            env, dirs[sel], sigma.reshape(-1)[sel]) if fallback.any() else 0.0, mean)
    hits = np.flatnonzero(flat_ok & (hit_idx >= 0))
    hit_info = {"node": hits, "sphere": hit_idx[hits], "point": hit_pt[hits]}
    # explicit sources: points of each source texel's footprint in the bilinear map, each
    # with its share of the texel's excess flux: 16 equal-weight points ("tent") or the
    # environment module's product Gauss rule ("gauss", as its exact gloss sums them)
    if sources not in ("tent", "gauss"):
        raise InputError(f"must be 'tent' or 'gauss', got {sources!r}", field="cache.sources")
    sd = np.asarray(env.source_dirs, np.float64)
    k = sd.shape[1]  # env.source_flux is per one of these k sub-points
    share = np.full(sd.shape[:2], 1.0)
    fine = getattr(env, "source_fine_dirs", None)
    if sources == "gauss" and fine is not None and fine.shape[0]:
        sd = np.asarray(fine, np.float64)
        share = k * np.asarray(env.source_fine_weights, np.float64)
    elif env.source_tent_dirs is not None and env.source_tent_dirs.shape[0]:
        sd = np.asarray(env.source_tent_dirs, np.float64)
        share = np.full(sd.shape[:2], k / sd.shape[1])
    S = sd.shape[0] * sd.shape[1]
    if S:
        d = sd.reshape(-1, 3) @ np.asarray(env.rotation, np.float64).T
        flux = (np.asarray(env.source_flux, np.float64)[:, None, :]
                * share[:, :, None]).reshape(S, -1)
        Hs = _unit(d[None] + V[:, None])
        s_nh = np.einsum("psc,pc->ps", Hs, N)
        s_vh = np.einsum("psc,pc->ps", Hs, V)
        s_nl = d @ N.T
        s_nl = s_nl.T
        vis = (s_nl > 0.0) & (nv[:, None] > 0.0) & live[:, None]
        if occlusion is not None:
            k, _, _ = occlusion.trace(np.arange(P)[:, None],
                                      np.broadcast_to(d[None], (P, S, 3)))
            vis &= k < 0
        elif spheres:
            o = np.broadcast_to(X[:, None], (P, S, 3))
            k, _ = _ray_spheres(o, np.broadcast_to(d[None], (P, S, 3)), spheres,
                                np.asarray(objects)[:, None])
            vis &= k < 0
        s_base = np.where(vis, 0.25 / np.where(nv > 0.0, nv, 1.0)[:, None], 0.0)
    else:
        s_nh = s_vh = s_nl = s_base = np.zeros((P, 0))
        flux = np.zeros((0, env.atlas.shape[1]))
    nodes = GlossNodes(
        cos_h=jnp.asarray(np.cos(theta), dtype), vh=jnp.asarray(vh, dtype),
        nl=jnp.asarray(nl, dtype), nv=jnp.asarray(nv, dtype), base=jnp.asarray(base, dtype),
        radiance=jnp.asarray(rad.reshape(P, J, M, env.atlas.shape[1]), dtype),
        src_nh=jnp.asarray(s_nh, dtype), src_vh=jnp.asarray(s_vh, dtype),
        src_nl=jnp.asarray(s_nl, dtype), src_base=jnp.asarray(s_base, dtype),
        src_flux=jnp.asarray(flux, dtype))
    return nodes, hit_info
