"""Material-independent radiance caches for fitting (eqs. 5 and 6).

Geometry, poses and the environment are fixed while materials are fitted, so everything that
does not depend on (α, β, χ, μ, n) is computed once, here, and the model for any parameters is
a weighted sum of cached radiances with weights built from the reflection model's own F, D, G
(:mod:`spectral_fit.lighting`).

Gloss (eq. 5's β term) at a shading point with normal N and view V:

    ∫ L(ω) F(n, θd) D(μ, θh) G / (4 cosθr) dω  =  ∫ D(μ, θh) F(n, V·H) G (V·H)/(N·V) L(l(H)) dω_H

(dω = 4 (V·H) dω_H, l(H) = 2 (V·H) H − V). The half vectors H are sampled on a FIXED,
μ-independent set of nodes: rings around N at θh_j = θ0 q^j (geometric spacing, the trapezoid
rule in log θh, which integrates a Gaussian lobe of any width μ >> θ0 to high accuracy) with the
geometric tail below θ0 folded into the first ring, and on each ring M azimuths from V's
azimuth: equally spaced on fully visible rings, Gauss–Legendre over the visible arc
(N·l(H) > 0) otherwise. Each node's radiance L_k is looked up ONCE from the environment's
prefiltered residual map (:class:`~spectral_fit.lighting.EnvironmentMap`, its own principal
spectra) at a prefilter std matched to the node's footprint in reflected directions (limited
near the horizon); the map's bright source texels are kept as explicit directions with their
exact flux (by default 16 equal-weight points of each one's footprint in the bilinear map;
``CacheOptions.sources="gauss"`` takes the product Gauss points the environment module's exact
gloss sums). Then

    gloss(μ, n) = Σ_k D(μ, θh_k) F(n, (V·H)_k) G_k c_k L_k + Σ_s D F G /(4 N·V) Φ_s,

c_k = Δω_H,k (V·H)_k/(N·V): smooth in μ and n, so its derivatives are exact autodiff.

Interreflection (eq. 6 in the "gather" reading): every node direction, the mirror
direction and every environment texel of the irradiance sum is ray-cast once against the OTHER
objects (spheres, analytically). Directions that hit a neighbour take the neighbour's outgoing
radiance instead of the environment: for each reading and neighbour a fixed set of probes
(directions from the spot's centre spread over the neighbour's silhouette) holds the hit point,
its normal and the direction back to the spot, with their own gloss nodes (the samples'
layout, stored after the samples' in one :class:`GlossNodes`, so one evaluation of the node
weights serves samples, probes and the sample nodes that hit a neighbour),
visible-environment irradiance and mirror radiance, so the neighbour's radiance
α' S' E'/π + β' gloss'(μ', n') + χ' F L' is a function of the neighbour's parameters and its
derivative is in the Jacobian. A hit takes the radiance of the nearest probe (one bounce: the
neighbour is lit by the environment it sees, the receiver's own light is not fed back).

Shapes: P shading points, J rings, M azimuths, S source sub-points, r environment channels
(principal spectra), L bands, Q probes.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from ..lighting import fresnel_dielectric, microfacet_d, microfacet_g

__all__ = [
    "CacheOptions",
    "GlossNodes",
    "RadianceCache",
    "Sphere",
    "build_gloss_nodes",
    "build_radiance_cache",
    "gloss_from_nodes",
    "cached_radiance",
    "field_radiance",
    "probe_radiance",
]


@dataclasses.dataclass(frozen=True)
class CacheOptions:
    """Node layout of the caches (static).

    Attributes:
        theta0: smallest ring's θh (radians); the lobe mass inside is folded into it.
        ring_ratio: q, ratio of consecutive ring angles (trapezoid step log q in log θh).
        azimuths: M, nodes per ring.
        prefilter: a node's prefilter std = this × √(its solid angle in reflected directions).
        horizon_ratio: a node's prefilter std is at most this × its elevation above the
            surface's horizon (no light from behind the surface is blurred in).
        subsamples: s; a node's radiance is the mean of s × s sub-samples over its cell
            (1: one prefiltered lookup per node). 3 lowers the median gloss error at wide
            lobes by ~40 % (docs/fitting.md) for 9× the lookups in the preparation.
        probes: probes per reading and neighbour (interreflection); their gloss nodes have
            the samples' layout (one array, one evaluation of the node weights).
        sources: each bright source texel of the map as 16 equal-weight points of its
            footprint in the bilinear map ("tent", default) or the environment module's
            product Gauss rule over that footprint ("gauss", 64 points, what its exact gloss
            sums; the bundled session's red β then comes out at +2.8 % instead of +1.8 %).
    """

    theta0: float = 0.003
    ring_ratio: float = 1.35
    azimuths: int = 16
    prefilter: float = 0.35
    horizon_ratio: float = 0.2
    subsamples: int = 1
    probes: int = 64
    sources: str = "tent"


@dataclasses.dataclass(frozen=True)
class Sphere:
    """An occluder: object index, world centre (3,) and radius (metres)."""

    object: int
    centre: np.ndarray
    radius: float


class GlossNodes(eqx.Module):
    """Gloss quadrature nodes of P shading points with their cached radiance (a pytree).

    Attributes:
        cos_h: (J,) cosθh of the rings.
        vh, nl: (P, J, M) V·H and N·l(H) per node.
        nv: (P,) N·V.
        base: (P, J, M) Δω_H (V·H)/(N·V) (0 for invisible nodes).
        radiance: (P, J, M, r) environment radiance at l(H) in the map's principal spectra
            (0 where a neighbour hides the environment).
        src_nh, src_vh, src_nl: (P, S) cosines of the source sub-points' half vectors.
        src_base: (P, S) 1/(4 N·V), 0 where the source is below the horizon or hidden.
        src_flux: (S, r) excess flux of the source sub-points.
    """

    cos_h: jax.Array
    vh: jax.Array
    nl: jax.Array
    nv: jax.Array
    base: jax.Array
    radiance: jax.Array
    src_nh: jax.Array
    src_vh: jax.Array
    src_nl: jax.Array
    src_base: jax.Array
    src_flux: jax.Array


class RadianceCache(eqx.Module):
    """Everything material-independent of the fit's field samples (a pytree).

    Attributes:
        nodes: :class:`GlossNodes` of the P samples followed by the Q probes (one node
            layout; ``sample_nodes`` and ``probe_nodes`` are the two parts).
        irradiance: (P, L) E(λ, N) of the visible environment (exact texel sum, texels hidden
            by a neighbour left out).
        mirror: (P, L) environment radiance along R (0 if a neighbour hides it).
        spectral_basis: (r, L) the map's principal spectra.
        probe_object: (Q,) object of each probe (Q may be 0).
        probe_irradiance, probe_mirror: (Q, L) as ``irradiance``/``mirror`` at the probes.
        mirror_probe: (P,) probe seen along R, −1 for none.
        diffuse_probe: (P, Q) cosine-weighted solid angle of each probe's share of the
            hemisphere hidden by neighbours (irradiance from neighbours = this @ radiance).
        hit_sample, hit_probe: (H,) sample and probe of every gloss node that hits a neighbour.
        hit_node: (H,) that node's flat index in the sample's J·M nodes.
        average: (B, P) field averaging weights of the readings (0 for samples on no object
            or facing away).
        probe_group: (Q,) the reading each probe belongs to.
        probe_diffuse: (O, Q) ``average @ diffuse_probe`` per receiving object, summed over
            each probe's reading (every reading only sees its own probes).
        hit_average: (H,) the averaging weight of each hit's sample (the gloss hits are
            summed straight into field means).
    """

    nodes: GlossNodes
    irradiance: jax.Array
    mirror: jax.Array
    spectral_basis: jax.Array
    probe_object: jax.Array
    probe_irradiance: jax.Array
    probe_mirror: jax.Array
    mirror_probe: jax.Array
    diffuse_probe: jax.Array
    hit_sample: jax.Array
    hit_probe: jax.Array
    hit_node: jax.Array
    average: jax.Array
    probe_group: jax.Array
    probe_diffuse: jax.Array
    hit_average: jax.Array

    @property
    def n_probes(self) -> int:
        return int(self.probe_object.shape[0])

    @property
    def sample_nodes(self) -> GlossNodes:
        """:class:`GlossNodes` of the P samples (the first P points of ``nodes``)."""
        return _node_rows(self.nodes, 0, int(self.irradiance.shape[0]))

    @property
    def probe_nodes(self) -> GlossNodes:
        """:class:`GlossNodes` of the Q probes (hit point, normal, direction back)."""
        P = int(self.irradiance.shape[0])
        return _node_rows(self.nodes, P, P + self.n_probes)


_SHARED_NODE_FIELDS = ("cos_h", "src_flux")


def _node_rows(nodes: GlossNodes, start: int, stop: int) -> GlossNodes:
    """The points start:stop of ``nodes`` (the ring angles and source fluxes are shared)."""
    return GlossNodes(**{f.name: getattr(nodes, f.name) if f.name in _SHARED_NODE_FIELDS
                         else getattr(nodes, f.name)[start:stop]
                         for f in dataclasses.fields(nodes)})


def _concat_nodes(a: GlossNodes, b: GlossNodes) -> GlossNodes:
    """The points of ``a`` followed by those of ``b`` (same layout, same map)."""
    return GlossNodes(**{f.name: getattr(a, f.name) if f.name in _SHARED_NODE_FIELDS
                         else jnp.concatenate([getattr(a, f.name), getattr(b, f.name)])
                         for f in dataclasses.fields(a)})


# ----------------------------------------------------------------------------- geometry (NumPy)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def _view_frames(N: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tangent T along V's projection on the tangent plane (any tangent if V ∥ N), B = N × T."""
    p = V - np.sum(N * V, -1, keepdims=True) * N
    alt = np.where(np.abs(N[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]),
                   np.array([[0.0, 1.0, 0.0]]))
    alt = alt - np.sum(N * alt, -1, keepdims=True) * N
    ok = np.sum(p * p, -1, keepdims=True) > 1e-18
    T = _unit(np.where(ok, p, alt))
    return T, np.cross(N, T)


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


def _ray_spheres(origins: np.ndarray, dirs: np.ndarray, spheres: Sequence[Sphere],
                 skip: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest sphere hit of rays (..., 3): (…,) index into ``spheres`` or −1 and distance t.
    Spheres whose object equals ``skip`` (broadcast against the rays) are ignored."""
    best = np.full(dirs.shape[:-1], np.inf)
    idx = np.full(dirs.shape[:-1], -1, np.int64)
    for i, s in enumerate(spheres):
        oc = origins - s.centre
        b = np.sum(oc * dirs, -1)
        c = np.sum(oc * oc, -1) - s.radius ** 2
        disc = b * b - c
        t = -b - np.sqrt(np.maximum(disc, 0.0))
        hit = (disc > 0.0) & (t > 1e-7) & (skip != s.object)
        closer = hit & (t < best)
        best = np.where(closer, t, best)
        idx = np.where(closer, i, idx)
    return idx, best


def _level_blend(env: Any, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Adjacent prefilter levels (lo, hi) and hi's weight whose blended variance is σ²."""
    sig = np.asarray(env.level_sigma, np.float64)
    s = np.clip(sigma, 0.0, sig[-1])
    hi = np.clip(np.searchsorted(sig, s, side="right"), 1, sig.size - 1)
    lo = hi - 1
    w = (s ** 2 - sig[lo] ** 2) / (sig[hi] ** 2 - sig[lo] ** 2)
    return lo.astype(np.int32), hi.astype(np.int32), np.clip(w, 0.0, 1.0)


@eqx.filter_jit
def _lookup_levels(env: Any, dirs: jax.Array, lo: jax.Array, hi: jax.Array, w: jax.Array
                   ) -> jax.Array:
    from ..lighting import lookup_level

    def one(d: jax.Array, a: jax.Array, b: jax.Array, ww: jax.Array) -> jax.Array:
        dm = d @ env.rotation  # world → map frame
        return (1.0 - ww) * lookup_level(env, a, dm) + ww * lookup_level(env, b, dm)

    return jax.vmap(one)(dirs, lo, hi, w)


def _pad(x: np.ndarray, size: int) -> np.ndarray:
    """``x`` padded to ``size`` rows by repeating its last row (one compiled size)."""
    return np.concatenate([x, np.repeat(x[-1:], size - x.shape[0], 0)])


def _prefiltered(env: Any, dirs: np.ndarray, sigma: np.ndarray, chunk: int = 32768
                 ) -> np.ndarray:
    """Residual-map radiance (N, r) along world directions (N, 3) prefiltered to std σ (N,)."""
    lo, hi, w = _level_blend(env, sigma)
    out = np.zeros((dirs.shape[0], env.atlas.shape[1]), np.float32)
    dt = env.atlas.dtype
    for a in range(0, dirs.shape[0], chunk):
        sl = slice(a, a + chunk)
        n = dirs[sl].shape[0]
        got = _lookup_levels(env, jnp.asarray(_pad(dirs[sl], chunk), dt),
                             jnp.asarray(_pad(lo[sl], chunk)), jnp.asarray(_pad(hi[sl], chunk)),
                             jnp.asarray(_pad(w[sl], chunk), dt))
        out[sl] = np.asarray(got)[:n]
    return out


def _texel_table(env: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World directions (T, 3), solid angles (T,) and radiance (T, C) of the unfiltered map."""
    from ..lighting import texel_directions, texel_solid_angles

    h, w, c = env.texels.shape
    R = np.asarray(env.rotation, np.float64)
    dirs = texel_directions(h, w).reshape(-1, 3) @ R.T
    return dirs, texel_solid_angles(h, w).reshape(-1), np.asarray(env.texels,
                                                                   np.float64).reshape(-1, c)


def _env_lookup(env: Any, dirs: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """Unfiltered bilinear radiance (N, C) along world directions (N, 3)."""
    out = np.zeros((dirs.shape[0], env.texels.shape[-1]))
    for a in range(0, dirs.shape[0], chunk):
        d = dirs[a:a + chunk]
        n = d.shape[0]
        d = np.concatenate([d, np.repeat(d[-1:], chunk - n, 0)])
        out[a:a + n] = np.asarray(_lookup_jit(env, jnp.asarray(d, env.texels.dtype)))[:n]
    return out


@eqx.filter_jit
def _lookup_jit(env: Any, dirs: jax.Array) -> jax.Array:
    from ..lighting import lookup

    return jax.vmap(lambda d: lookup(env, d))(dirs)


def build_gloss_nodes(env: Any, positions: np.ndarray, normals: np.ndarray, views: np.ndarray,
                      *, objects: np.ndarray, spheres: Sequence[Sphere] = (),
                      theta0: float = 0.003, ring_ratio: float = 1.35, azimuths: int = 16,
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
        subsamples: s; each node's radiance is the mean of s × s sub-samples over its cell
            (1: one lookup at the node, prefiltered to the cell's size).
        sources: how the map's bright source texels are summed (:class:`CacheOptions`).

    Returns:
        (nodes, hits): ``hits`` holds, for the nodes that hit an occluder, flat node indices
        ``node`` (into P·J·M), ``sphere`` (index into ``spheres``) and world ``point`` (·, 3).
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
    hit_t = np.full(P * J * M, np.inf)
    if spheres:
        orig = np.broadcast_to(X[:, None, None, :], Ldir.shape).reshape(-1, 3)
        skip = np.broadcast_to(np.asarray(objects)[:, None, None], ok.shape).reshape(-1)
        sel = np.flatnonzero(flat_ok)
        hi_, ht = _ray_spheres(orig[sel], dirs[sel], spheres, skip[sel])
        hit_idx[sel], hit_t[sel] = hi_, ht
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
    orig_h = np.repeat(X, J * M, axis=0)[hits] if hits.size else np.zeros((0, 3))
    hit_info = {"node": hits, "sphere": hit_idx[hits],
                "point": orig_h + hit_t[hits, None] * dirs[hits]}
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
        if spheres:
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


# ----------------------------------------------------------------------------- model (JAX)


def _node_weights(cos_h: jax.Array, vh: jax.Array, nl: jax.Array, nv: jax.Array,
                  base: jax.Array, mu: jax.Array, n: jax.Array, distribution: str,
                  geometry: str) -> jax.Array:
    """D(μ, θh) F(n, V·H) G · base, broadcasting (the reflectance module's F, D, G)."""
    D = microfacet_d(cos_h, mu, distribution)
    G = microfacet_g(cos_h, nv, nl, vh, mu, geometry)
    return D * G * fresnel_dielectric(vh, n) * base


def _gloss_weights(nodes: GlossNodes, mu: jax.Array, n: jax.Array, distribution: str,
                   geometry: str) -> tuple[jax.Array, jax.Array]:
    """Node weights (P, J, M) and source weights (P, S) for per-point μ, n (P,)."""
    m3, n3, nv3 = mu[:, None, None], n[:, None, None], nodes.nv[:, None, None]
    w = _node_weights(nodes.cos_h[None, :, None], nodes.vh, nodes.nl, nv3, nodes.base, m3, n3,
                      distribution, geometry)
    ws = _node_weights(nodes.src_nh, nodes.src_vh, nodes.src_nl, nodes.nv[:, None],
                       nodes.src_base, mu[:, None], n[:, None], distribution, geometry)
    return w, ws


def gloss_from_nodes(nodes: GlossNodes, mu: jax.Array, n: jax.Array, *,
                     distribution: str = "gaussian", geometry: str = "vcavity") -> jax.Array:
    """Gloss per unit β (P, r) of the cached environment radiance, in the map's principal
    spectra (multiply by the map's ``spectral_basis`` for bands), for per-point μ, n (P,).

    Differentiable in μ and n with a custom JVP: the two partial derivatives of every point
    (exact forward-mode autodiff of F, D, G) are contracted with the cached radiance in the
    same pass as the value, and any number of tangents (Jacobian columns) combine them. With
    a μ-independent G (V-cavity) the sum is factored by ring: D(μ, θh_j) multiplies
    Σ_m F G c L over the ring, so ∂/∂μ costs one ring sum and ∂/∂n one more contraction.
    """
    dt = nodes.vh.dtype
    return _gloss_impl(jnp.asarray(mu, dt), jnp.asarray(n, dt), nodes, distribution, geometry)


def _contract(nodes: GlossNodes, w: jax.Array) -> jax.Array:
    """(P, k, J, M) weights → (P, k, r): one batched matrix product per point."""
    P = nodes.vh.shape[0]
    rad = nodes.radiance.reshape(P, -1, nodes.radiance.shape[-1])  # (P, J·M, r)
    return jnp.matmul(w.reshape(P, w.shape[1], -1), rad)


def _src_weights(nodes: GlossNodes, m: jax.Array, nn: jax.Array, distribution: str,
                 geometry: str) -> jax.Array:
    return _node_weights(nodes.src_nh, nodes.src_vh, nodes.src_nl, nodes.nv[:, None],
                         nodes.src_base, m[:, None], nn[:, None], distribution, geometry)


_GLOSS_FNS: dict[tuple[str, str], Any] = {}


def _gloss_impl(m: jax.Array, nn: jax.Array, nodes: GlossNodes, distribution: str,
                geometry: str) -> jax.Array:
    """The gloss of :func:`gloss_from_nodes` (no hit weights)."""
    empty = jnp.zeros((0,), jnp.int32)
    return _gloss_hits_impl(m, nn, nodes, empty, empty, distribution, geometry)[0]


def _gloss_hits_impl(m: jax.Array, nn: jax.Array, nodes: GlossNodes, hit_point: jax.Array,
                     hit_node: jax.Array, distribution: str, geometry: str
                     ) -> tuple[jax.Array, jax.Array]:
    """Gloss (P, r) of every point and the weights D F G · base (H,) of the nodes
    ``hit_node`` (flat index into J·M) of points ``hit_point``, as a ``jax.custom_jvp`` of
    explicit array arguments (nothing traced is closed over), one function per
    (distribution, geometry)."""
    key = (distribution, geometry)
    if key not in _GLOSS_FNS:
        _GLOSS_FNS[key] = _make_gloss(distribution, geometry)
    return _GLOSS_FNS[key](m, nn, nodes, hit_point, hit_node)


def _make_gloss(distribution: str, geometry: str) -> Any:
    @jax.custom_jvp
    def g(m: jax.Array, nn: jax.Array, nodes: GlossNodes, hit_point: jax.Array,
          hit_node: jax.Array) -> tuple[jax.Array, jax.Array]:
        w, ws = _gloss_weights(nodes, m, nn, distribution, geometry)
        wh = w.reshape(w.shape[0], -1)[hit_point, hit_node]
        return _contract(nodes, w[:, None])[:, 0] + ws @ nodes.src_flux, wh

    @g.defjvp
    def g_jvp(primals: tuple[Any, ...], tangents: tuple[Any, ...]
              ) -> tuple[tuple[jax.Array, jax.Array], tuple[jax.Array, jax.Array]]:
        m, nn, nodes, hp, hn = primals
        dm, dn = tangents[0], tangents[1]  # the cache and the hit indices are constant
        one = jnp.ones_like(m)
        zero = jnp.zeros_like(m)
        if geometry == "smith":  # G depends on μ: no factoring
            ws, wsm = jax.jvp(lambda a: _src_weights(nodes, a, nn, distribution, geometry),
                              (m,), (one,))
            _, wsn = jax.jvp(lambda b: _src_weights(nodes, m, b, distribution, geometry),
                             (nn,), (one,))
            f = lambda a, b: _gloss_weights(nodes, a, b, distribution, geometry)[0]  # noqa: E731
            w, wm = jax.jvp(f, (m, nn), (one, zero))
            _, wn = jax.jvp(f, (m, nn), (zero, one))
            W = jnp.stack([w, wm, wn], axis=1)
        else:
            # G is μ-independent: D(μ) and F(n) and their derivatives factor out. One D
            # over the rings and the sources' half vectors, one F over every node's V·H.
            P, J = nodes.vh.shape[0], nodes.vh.shape[1]
            cos_all = jnp.concatenate([jnp.broadcast_to(nodes.cos_h[None, :], (P, J)),
                                       nodes.src_nh], axis=1)  # (P, J + S)
            D, Dm = jax.jvp(lambda a: microfacet_d(cos_all, a[:, None], distribution), (m,),
                            (one,))
            vh_all = jnp.concatenate([nodes.vh.reshape(P, -1), nodes.src_vh], axis=1)
            F, Fn = jax.jvp(lambda b: fresnel_dielectric(vh_all, b[:, None]), (nn,), (one,))
            nk = nodes.vh.shape[1] * nodes.vh.shape[2]
            G = microfacet_g(nodes.cos_h[None, :, None], nodes.nv[:, None, None], nodes.nl,
                             nodes.vh, m[:, None, None], geometry)
            gb = (G * nodes.base).reshape(P, nk)
            gbs = microfacet_g(nodes.src_nh, nodes.nv[:, None], nodes.src_nl, nodes.src_vh,
                               m[:, None], geometry) * nodes.src_base
            shp = nodes.vh.shape
            D3, Dm3 = D[:, :J, None], Dm[:, :J, None]
            Fk, Fnk = (F[:, :nk] * gb).reshape(shp), (Fn[:, :nk] * gb).reshape(shp)
            W = jnp.stack([D3 * Fk, Dm3 * Fk, D3 * Fnk], axis=1)
            Fs, Fns = F[:, nk:] * gbs, Fn[:, nk:] * gbs
            ws, wsm, wsn = D[:, J:] * Fs, Dm[:, J:] * Fs, D[:, J:] * Fns
        out = _contract(nodes, W)
        sv, sm, sn = (x @ nodes.src_flux for x in (ws, wsm, wsn))
        val, d_mu, d_n = out[:, 0], out[:, 1], out[:, 2]
        wh3 = W.reshape(W.shape[0], 3, -1)[hp, :, hn]  # (H, 3)
        return ((val + sv, wh3[:, 0]),
                ((d_mu + sm) * dm[:, None] + (d_n + sn) * dn[:, None],
                 wh3[:, 1] * dm[hp] + wh3[:, 2] * dn[hp]))

    return g


def _gloss_all(cache: RadianceCache, values: jax.Array, objects: jax.Array,
               models: Sequence[tuple[str, str]]) -> tuple[jax.Array, jax.Array, jax.Array]:
    """One evaluation of the gloss nodes of the samples and the probes (they share one node
    layout and one array): gloss (P + Q, r), the weights D F G · base (H,) of the sample
    nodes that hit a neighbour, and the per-point parameters (P + Q, 6)."""
    obj_all = jnp.concatenate([objects, cache.probe_object])
    v = values[obj_all]
    hp, hn = cache.hit_sample, cache.hit_node
    kinds = sorted(set(models))
    gl = wh = None
    for dist, geom in kinds:
        g, w = _gloss_hits_impl(v[:, 3], v[:, 4], cache.nodes, hp, hn, dist, geom)
        if gl is None:
            gl, wh = g, w
            continue
        sel = jnp.asarray([m == (dist, geom) for m in models])[obj_all]
        gl = jnp.where(sel[:, None], g, gl)
        wh = jnp.where(sel[hp], w, wh)
    return gl, wh, v


def _probe_out(cache: RadianceCache, vq: jax.Array, reflectance: jax.Array,
               glq: jax.Array, fq: jax.Array) -> jax.Array:
    """Outgoing radiance (Q, L) at the probes: α' S' E'/π + β' gloss' + χ' F L'(R)."""
    S = reflectance[cache.probe_object]
    return ((vq[:, 0:1] / math.pi) * S * cache.probe_irradiance
            + vq[:, 1:2] * (glq @ cache.spectral_basis) + vq[:, 2:3] * fq[:, None]
            * cache.probe_mirror)


def cached_radiance(cache: RadianceCache, values: jax.Array, reflectance: jax.Array,
                    objects: jax.Array, models: Sequence[tuple[str, str]],
                    *, interreflection: bool = True) -> tuple[jax.Array, jax.Array]:
    """Radiance (P, L) of the samples for physical parameters ``values (O, 6)`` (α, β, χ, μ,
    n, γ) and Lambert reflectances ``reflectance (O, L)``, eq. (5) (+ the interreflection of
    eq. 6 when ``interreflection``), and its interreflection part (P, L).

    Args:
        objects: (P,) object of each sample (>= 0; mask invalid samples outside).
        models: (distribution, geometry) per object (static).
    """
    P = cache.irradiance.shape[0]
    gl_all, wh, v_all = _gloss_all(cache, values, objects, models)
    f_all = fresnel_dielectric(cache.nodes.nv, v_all[:, 4])
    v, Fm = v_all[:P], f_all[:P, None]
    S = reflectance[objects]
    out = ((v[:, 0:1] / math.pi) * S * cache.irradiance
           + v[:, 1:2] * (gl_all[:P] @ cache.spectral_basis) + v[:, 2:3] * Fm * cache.mirror)
    ir = jnp.zeros_like(out)
    if interreflection and cache.n_probes:
        lout = _probe_out(cache, v_all[P:], reflectance, gl_all[P:], f_all[P:])  # (Q, L)
        lz = jnp.concatenate([lout, jnp.zeros((1, lout.shape[1]), lout.dtype)])
        # diffuse: irradiance from the neighbours
        ir = ir + (v[:, 0:1] / math.pi) * S * (cache.diffuse_probe @ lout)
        # mirror along R into a neighbour
        ir = ir + v[:, 2:3] * Fm * lz[cache.mirror_probe]
        # gloss nodes that hit a neighbour
        if cache.hit_sample.shape[0]:
            w = v[cache.hit_sample, 1] * wh
            ir = ir + jax.ops.segment_sum(w[:, None] * lout[cache.hit_probe],
                                          cache.hit_sample, num_segments=P)
    return out + ir, ir


def field_radiance(cache: RadianceCache, values: jax.Array, reflectance: jax.Array,
                   objects: jax.Array, models: Sequence[tuple[str, str]],
                   *, interreflection: bool = True) -> jax.Array:
    """Mean radiance (B, L) over each reading's field, ``cache.average @`` the samples'
    radiance of :func:`cached_radiance`, with every term linear in a per-object parameter
    summed into field means before the spectral product (the fit's forward model: the
    interreflection hits are reduced to a (B, Q) matrix of scalars, then one product with
    the probes' radiance). The gloss of the samples, of the probes and the weights of the
    nodes that hit a neighbour come from one evaluation of the node weights."""
    P = cache.irradiance.shape[0]
    A = cache.average
    gl_all, wh, v_all = _gloss_all(cache, values, objects, models)
    f_all = fresnel_dielectric(cache.nodes.nv, v_all[:, 4])
    v, Fm = v_all[:P], f_all[:P, None]
    S = reflectance[objects]
    direct = (v[:, 0:1] / math.pi) * S * cache.irradiance + v[:, 2:3] * Fm * cache.mirror
    out = A @ direct + (A @ (v[:, 1:2] * gl_all[:P])) @ cache.spectral_basis
    if interreflection and cache.n_probes:
        lout = _probe_out(cache, v_all[P:], reflectance, gl_all[P:], f_all[P:])  # (Q, L)
        lz = jnp.concatenate([lout, jnp.zeros((1, lout.shape[1]), lout.dtype)])
        B, Q = A.shape[0], lout.shape[0]
        coef = cache.probe_diffuse.T @ ((values[:, 0:1] / math.pi) * reflectance)  # (Q, L)
        if cache.hit_sample.shape[0]:
            C = jax.ops.segment_sum(cache.hit_average * v[cache.hit_sample, 1] * wh,
                                    cache.hit_probe, num_segments=Q)
            coef = coef + C[:, None]
        out = out + jax.ops.segment_sum(coef * lout, cache.probe_group, num_segments=B)
        out = out + A @ (v[:, 2:3] * Fm * lz[cache.mirror_probe])
    return out


def probe_radiance(cache: RadianceCache, values: jax.Array, reflectance: jax.Array,
                   models: Sequence[tuple[str, str]]) -> jax.Array:
    """Outgoing radiance (Q, L) of the neighbours at the probes towards the receivers, for
    physical parameters ``values (O, 6)`` (one bounce: environment light only)."""
    P = cache.irradiance.shape[0]
    gl_all, _, v_all = _gloss_all(cache, values, jnp.zeros((P,), jnp.int32), models)
    f_all = fresnel_dielectric(cache.nodes.nv, v_all[:, 4])
    return _probe_out(cache, v_all[P:], reflectance, gl_all[P:], f_all[P:])


# ----------------------------------------------------------------------------- building


def _visible_irradiance(env: Any, X: np.ndarray, N: np.ndarray, objects: np.ndarray,
                        spheres: Sequence[Sphere], chunk: int = 64
                        ) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray, np.ndarray,
                                                          np.ndarray]]]:
    """Exact texel-sum irradiance (P, C) of the environment visible from each point, and per
    chunk the hidden texels: (point index, cos·Δω, hit sphere, hit point).

    A texel direction is hidden by a sphere when it lies inside the sphere's silhouette cone
    from the point (angle to the centre <= asin(radius/distance)); computed in float32."""
    dirs, sa, tex = _texel_table(env)
    d32 = dirs.astype(np.float32)
    tex32 = tex.astype(np.float32)
    P = X.shape[0]
    E = np.zeros((P, tex.shape[1]))
    hidden = []
    for a in range(0, P, chunk):
        sl = slice(a, min(P, a + chunk))
        w = np.maximum(N[sl].astype(np.float32) @ d32.T, 0.0) * sa[None].astype(np.float32)
        for si, s in enumerate(spheres):
            rel = s.centre[None] - X[sl]
            dist = np.linalg.norm(rel, axis=1)
            use = (objects[sl] != s.object) & (dist > s.radius)
            if not use.any():
                continue
            axis = rel / np.maximum(dist, 1e-300)[:, None]
            cos_half = np.sqrt(np.maximum(1.0 - (s.radius / np.maximum(dist, 1e-300)) ** 2,
                                          0.0))
            inside = (axis.astype(np.float32) @ d32.T >= cos_half[:, None]) & use[:, None]
            pi, ti = np.nonzero(inside & (w > 0.0))
            if pi.size:
                hw = w[pi, ti].astype(np.float64)
                w[pi, ti] = 0.0
                o = X[sl][pi]
                oc = o - s.centre
                bq = np.sum(oc * dirs[ti], -1)
                t = -bq - np.sqrt(np.maximum(bq * bq - np.sum(oc * oc, -1) + s.radius ** 2,
                                             0.0))
                hidden.append((pi + a, hw, np.full(pi.size, si), o + t[:, None] * dirs[ti]))
        E[sl] = w @ tex32
    return E, hidden


def _fibonacci_cap(axis: np.ndarray, half: float, n: int) -> np.ndarray:
    """n unit directions spread evenly over the spherical cap of half-angle ``half``."""
    i = np.arange(n) + 0.5
    c = 1.0 - (1.0 - math.cos(half)) * i / n
    s = np.sqrt(np.maximum(1.0 - c * c, 0.0))
    ang = i * math.pi * (3.0 - math.sqrt(5.0))
    t, b = _view_frames(axis[None], axis[None] * 0 + np.array([[0.3, 0.5, 0.81]]))
    t, b = t[0], b[0]
    return _unit(c[:, None] * axis + s[:, None] * (np.cos(ang)[:, None] * t
                                                    + np.sin(ang)[:, None] * b))


def build_radiance_cache(env: Any, positions: np.ndarray, normals: np.ndarray,
                         views: np.ndarray, objects: np.ndarray, groups: np.ndarray, *,
                         average: np.ndarray | None = None, spheres: Sequence[Sphere] = (),
                         options: CacheOptions | None = None, dtype: Any = jnp.float32
                         ) -> RadianceCache:
    """Precompute the :class:`RadianceCache` of P field samples (outside ``jit``).

    Args:
        env: :class:`~spectral_fit.lighting.EnvironmentMap` (bands).
        positions, normals, views: (P, 3) world samples (invalid ones: any values).
        objects: (P,) object per sample, −1 for none.
        groups: (P,) reading of each sample (probes are made per reading and neighbour).
        average: (B, P) field averaging weights (default: the mean of each group's samples).
        spheres: the objects as spheres for occlusion and interreflection (empty: no
            interreflection, no occlusion).
    """
    opts = options or CacheOptions()
    X = np.asarray(positions, np.float64)
    N = _unit(np.asarray(normals, np.float64))
    V = _unit(np.asarray(views, np.float64))
    obj = np.asarray(objects, np.int64)
    grp = np.asarray(groups, np.int64)
    valid = obj >= 0
    P = X.shape[0]
    C = env.texels.shape[-1]
    nodes, hits = build_gloss_nodes(
        env, X, N, V, objects=obj, spheres=spheres if spheres else (), theta0=opts.theta0,
        ring_ratio=opts.ring_ratio, azimuths=opts.azimuths, prefilter=opts.prefilter,
        horizon_ratio=opts.horizon_ratio, subsamples=opts.subsamples, sources=opts.sources,
        dtype=dtype)
    nv = np.sum(N * V, -1)
    R = _unit(2.0 * nv[:, None] * N - V)
    irr = np.zeros((P, C))
    mir = np.zeros((P, C))
    iv = np.flatnonzero(valid)
    E, hidden = _visible_irradiance(env, X[iv], N[iv], obj[iv], spheres)
    irr[iv] = E
    mk = np.full(P, -1)
    mt = np.full(P, np.inf)
    if spheres:
        mk[iv], mt[iv] = _ray_spheres(X[iv], R[iv], spheres, obj[iv])
    mvis = valid & (mk < 0)
    mir[mvis] = _env_lookup(env, R[mvis])
    # probes: per reading and neighbour, directions from the spot centre over its silhouette
    probe_dirs, probe_pts, probe_sph, probe_grp, probe_orig = [], [], [], [], []
    if spheres:
        for b in np.unique(grp[valid]):
            sel = valid & (grp == b)
            xb = X[sel].mean(axis=0)
            ob = int(np.bincount(obj[sel]).argmax())
            for si, s in enumerate(spheres):
                if s.object == ob:
                    continue
                d = np.linalg.norm(s.centre - xb)
                if d <= s.radius:
                    continue
                half = math.asin(s.radius / d) * 0.999
                u = _fibonacci_cap((s.centre - xb) / d, half, opts.probes)
                k, t = _ray_spheres(np.broadcast_to(xb, u.shape), u, [s], np.array(-1))
                u, t = u[k >= 0], t[k >= 0]
                probe_dirs.append(u)
                probe_pts.append(xb + t[:, None] * u)
                probe_sph.append(np.full(u.shape[0], si))
                probe_grp.append(np.full(u.shape[0], b))
                probe_orig.append(np.broadcast_to(xb, u.shape))
    Q = int(sum(u.shape[0] for u in probe_dirs))
    if Q:
        pd = np.concatenate(probe_dirs)
        pp = np.concatenate(probe_pts)
        ps = np.concatenate(probe_sph)
        pg = np.concatenate(probe_grp)
        po = np.concatenate(probe_orig)
        centre_of = {int(b): X[valid & (grp == b)].mean(axis=0) for b in np.unique(pg)}

        def nearest(sample: np.ndarray, sph: np.ndarray, pts: np.ndarray) -> np.ndarray:
            """Nearest probe (by direction from the spot centre) of each hit; −1 if none."""
            out = np.full(sample.shape[0], -1)
            for b in np.unique(grp[sample]):
                for si in np.unique(sph):
                    m = (grp[sample] == b) & (sph == si)
                    cand = np.flatnonzero((pg == b) & (ps == si))
                    if not m.any() or cand.size == 0:
                        continue
                    u = _unit(pts[m] - centre_of[int(b)])
                    out[np.flatnonzero(m)] = cand[np.argmax(u @ pd[cand].T, axis=1)]
            return out

        # diffuse: hidden texels → probes
        dpr = np.zeros((P, Q))
        for pi, hw, hk, pts in hidden:
            pi = iv[pi]
            q = nearest(pi, hk, pts)
            ok = q >= 0
            np.add.at(dpr, (pi[ok], q[ok]), hw[ok])
        # mirror
        mprobe = np.full(P, -1)
        mh = np.flatnonzero(valid & (mk >= 0))
        if mh.size:
            mprobe[mh] = nearest(mh, mk[mh], X[mh] + mt[mh, None] * R[mh])
        # gloss hits
        J, M = nodes.vh.shape[1], nodes.vh.shape[2]
        hs = hits["node"] // (J * M)
        hq = nearest(hs, hits["sphere"], hits["point"])
        keep = hq >= 0
        hn = hits["node"][keep]
        hs, hq = hs[keep], hq[keep]
        hnode = hn % (J * M)
        # keep the probes something refers to
        used = (dpr.sum(axis=0) > 0.0)
        used[mprobe[mprobe >= 0]] = True
        used[hq] = True
        new = np.cumsum(used) - 1
        Q = int(used.sum())
        dpr = dpr[:, used]
        mprobe = np.where(mprobe >= 0, new[np.maximum(mprobe, 0)], -1)
        hq = new[hq]
        pd, pp, ps, pg, po = pd[used], pp[used], ps[used], pg[used], po[used]
        pobj = np.array([spheres[i].object for i in ps])
        pc = np.stack([spheres[i].centre for i in ps]) if Q else np.zeros((0, 3))
        pN = _unit(pp - pc)
        pV = _unit(po - pp)
        pnodes, _ = build_gloss_nodes(
            env, pp, pN, pV, objects=pobj, spheres=spheres, theta0=opts.theta0,
            ring_ratio=opts.ring_ratio, azimuths=opts.azimuths,
            prefilter=opts.prefilter, horizon_ratio=opts.horizon_ratio, sources=opts.sources,
            dtype=dtype)
        pE, _ = _visible_irradiance(env, pp, pN, pobj, spheres)
        pnv = np.sum(pN * pV, -1)
        pR = _unit(2.0 * pnv[:, None] * pN - pV)
        k, _ = _ray_spheres(pp, pR, spheres, pobj)
        pM = np.zeros((Q, C))
        pM[k < 0] = _env_lookup(env, pR[k < 0])
    else:
        pobj = np.zeros(0, np.int64)
        pnodes, _ = build_gloss_nodes(env, np.zeros((0, 3)), np.zeros((0, 3)) + [0, 1, 0],
                                      np.zeros((0, 3)) + [0, 1, 0], objects=pobj,
                                      theta0=opts.theta0, ring_ratio=opts.ring_ratio,
                                      azimuths=opts.azimuths, sources=opts.sources,
                                      dtype=dtype)
        pE = pM = np.zeros((0, C))
        pg = np.zeros(0, np.int64)
        dpr = np.zeros((P, 0))
        mprobe = np.full(P, -1)
        hs = hq = np.zeros(0, np.int64)
        hnode = np.zeros(0, np.int64)
    mprobe = np.where(mprobe >= 0, mprobe, Q)  # index Q: a zero row
    if average is None:
        nb = int(grp.max()) + 1 if grp.size else 0
        average = np.zeros((nb, P))
        for b in range(nb):
            average[b, grp == b] = 1.0 / max(1, int(np.sum(grp == b)))
    avg = np.asarray(average, np.float64) * (valid & (nv > 0.0))[None, :]
    O = int(max([obj.max() + 1 if obj.size else 0] + [s.object + 1 for s in spheres]))
    fdq = np.zeros((O, Q))
    for o in range(O):
        full = avg @ (dpr * (obj == o)[:, None])  # (B, Q)
        fdq[o] = full[pg, np.arange(Q)] if Q else 0.0
    h_avg = avg[grp[hs], hs] if hs.size else np.zeros(0)
    f = lambda a: jnp.asarray(a, dtype)  # noqa: E731
    return RadianceCache(
        nodes=_concat_nodes(nodes, pnodes), irradiance=f(irr), mirror=f(mir),
        spectral_basis=f(np.asarray(env.spectral_basis, np.float64)),
        probe_object=jnp.asarray(pobj, jnp.int32),
        probe_irradiance=f(pE), probe_mirror=f(pM), mirror_probe=jnp.asarray(mprobe, jnp.int32),
        diffuse_probe=f(dpr), hit_sample=jnp.asarray(hs, jnp.int32),
        hit_probe=jnp.asarray(hq, jnp.int32), hit_node=jnp.asarray(hnode, jnp.int32),
        average=f(avg), probe_group=jnp.asarray(pg, jnp.int32), probe_diffuse=f(fdq),
        hit_average=f(h_avg))
