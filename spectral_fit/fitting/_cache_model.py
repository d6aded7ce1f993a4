"""The model evaluated on a radiance cache (JAX): gloss from the cached nodes with its custom
JVP, and the radiance of the samples, of the probes and of the readings' fields for physical
parameters ``values (O, 6)`` (α, β, χ, μ, n, γ) as weighted sums of cached radiances with
weights from the reflection model's F, D, G.

Shapes: P shading points, Q probes, H gloss nodes that hit a neighbour, B readings, O
objects, r environment channels (principal spectra), L bands.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp

from ..lighting import fresnel_dielectric, microfacet_d, microfacet_g
from ._radiance_cache import GlossNodes, RadianceCache

__all__ = [
    "gloss_from_nodes",
    "cached_radiance",
    "field_radiance",
    "probe_radiance",
]


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
    """Outgoing radiance (Q, L) at the probes: α' S' E'/π + β' gloss' + χ' F L'(R), plus the
    diffuse light of the probes among themselves (``cache.probe_bounces`` Jacobi steps)."""
    S = reflectance[cache.probe_object]
    kd = (vq[:, 0:1] / math.pi) * S
    direct = (kd * cache.probe_irradiance + vq[:, 1:2] * (glq @ cache.spectral_basis)
              + vq[:, 2:3] * fq[:, None] * cache.probe_mirror)
    out = direct
    if cache.transfer_weight.shape[0]:
        for _ in range(cache.probe_bounces):
            out = direct + kd * jax.ops.segment_sum(
                cache.transfer_weight[:, None] * out[cache.transfer_col], cache.transfer_row,
                num_segments=direct.shape[0])
    return out


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
    """Mean radiance (B, L) over each reading's field, ``cache.average`` of the samples'
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
    out = A.apply(direct) + A.apply(v[:, 1:2] * gl_all[:P]) @ cache.spectral_basis
    if interreflection and cache.n_probes:
        lout = _probe_out(cache, v_all[P:], reflectance, gl_all[P:], f_all[P:])  # (Q, L)
        lz = jnp.concatenate([lout, jnp.zeros((1, lout.shape[1]), lout.dtype)])
        B, Q = A.rows, lout.shape[0]
        coef = cache.probe_diffuse.T @ ((values[:, 0:1] / math.pi) * reflectance)  # (Q, L)
        if cache.hit_sample.shape[0]:
            C = jax.ops.segment_sum(cache.hit_average * v[cache.hit_sample, 1] * wh,
                                    cache.hit_probe, num_segments=Q)
            coef = coef + C[:, None]
        out = out + jax.ops.segment_sum(coef * lout, cache.probe_group, num_segments=B)
        out = out + A.apply(v[:, 2:3] * Fm * lz[cache.mirror_probe])
    return out


def probe_radiance(cache: RadianceCache, values: jax.Array, reflectance: jax.Array,
                   models: Sequence[tuple[str, str]]) -> jax.Array:
    """Outgoing radiance (Q, L) of the neighbours at the probes towards the receivers, for
    physical parameters ``values (O, 6)`` (one bounce: environment light only)."""
    P = cache.irradiance.shape[0]
    gl_all, _, v_all = _gloss_all(cache, values, jnp.zeros((P,), jnp.int32), models)
    f_all = fresnel_dielectric(cache.nodes.nv, v_all[:, 4])
    return _probe_out(cache, v_all[P:], reflectance, gl_all[P:], f_all[P:])
