"""The gather mode's gloss and mirror interreflection at receivers: the receiver's own lobe.

β A(x) Σ_q w_q h_q [L_j(y_q → x) − L_env(ω_q)] over a quadrature ω_q of the receiver's lobe
D F G (V·H)/(N·V) (:func:`_lobe_nodes`), each node ray marched through the neighbour's
pass-1 depth map (hit h_q, :func:`_march`) and the neighbour's radiance at the hit read from
its mip atlas plus :func:`_specular` towards x (:func:`_neighbour_along`); the mirror χ F(θr) times
the same along R; less the bright sources' gloss that the neighbours hide
(:func:`_hidden_source_gloss`). Only receivers whose lobe can reach a neighbour
(:func:`_lobe_reach`) run the quadrature, in chunks with the active ones first
(:func:`_lobe_quadrature`); receivers that are pixels of an image may take it from anchors
(:func:`_lobe_gather`). Shapes (N, C) per receiver, in the shading context's output
channels; computed batched and by components as the diffuse transfer (see ``_diffuse``).
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp

from ..._runtime.backend import materialise, materialise_each, on_accelerator
from ...lighting import (
    atan2_poly,
    dot3,
    fresnel_dielectric,
    lobe_factor,
    sincos_poly,
    taps_sum,
    visible_nodes,
)
from ._atlas import _mip_taps
from ._diffuse import _grid_tents, _hidden_sources, _view_frame_at
from ._march import _march
from ._pass1 import IRGeometry, _normalize
from ._schedule import _image_anchors, _partition
from ._shading import (
    _albedo_at,
    _env_blur,
    _gloss_weights,
    _Shading,
    _source_terms,
    _specular,
)

__all__: list[str] = []

#: receiver's gloss lobe quadrature against the neighbour (radial × azimuthal nodes)
_LOBE_NODES = (2, 4)
#: its rings at equal shares of the lobe's radial mass (:func:`environment._lobe_rings`): with
#: 2 rings uniform in θh/μ the outer one carried e^−12 of the weight
_LOBE_RADIAL_RULE = "mass"
#: footprint of a lobe node's hit on the neighbour, for its mip lookup: this fraction of the
#: lobe's angular std √2 μ, times the distance
_EDGE = 0.35


def _lobe_nodes(nrm: jax.Array, view: jax.Array, mu: jax.Array, eta: jax.Array, *,
                distribution: str, geometry: str) -> tuple[jax.Array, jax.Array]:
    """Reflected directions (Q, 3) and normalised weights (Q,) of a quadrature of the
    receiver's gloss lobe D F G (V·H)/(N·V) dω_H over its visible part (one receiver)."""
    nv = jnp.clip(jnp.dot(nrm, view), 0.0, 1.0)
    h, w, ch = visible_nodes(nrm, view, mu, jnp.zeros_like(mu), nv, distribution=distribution,
                              radial=_LOBE_NODES[0], azimuthal=_LOBE_NODES[1],
                              radial_rule=_LOBE_RADIAL_RULE)
    g, light = lobe_factor(nrm, view, h, ch, mu, eta, geometry=geometry, fresnel=True)
    f = w * g
    return light, f / jnp.maximum(jnp.sum(f), 1e-30)


def _neighbour_along(geom: IRGeometry, atlas: tuple[Any, ...], sh: _Shading,
                     pair: jax.Array, sender: jax.Array, pos: jax.Array, dirs: jax.Array,
                     wts: jax.Array, edge: jax.Array, sigma_env: jax.Array
                     ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """What the sender of ``pair`` (N,) changes along the rays (pos (N, 3), dirs (N, Q, 3)),
    weighted by ``wts`` (N, Q), as three (N, C) parts: the sender's light Σ_q wts_q h_q L_j(y_q
    → x), the sky it hides Σ_q wts_q h_q L_env(ω_q), and the sky at all the nodes Σ_q wts_q
    L_env(ω_q) (the net change is the first less the second). h and y: where the ray meets
    the sender's depth map (:func:`_march`); the sender's radiance there is the
    view-independent part from the sample mip atlas (at the footprint of the lobe's spread
    ``edge`` (N,) radians times the distance, with its normal and coverage) plus
    :func:`_specular` towards the receiver point; the environment it hides is prefiltered to
    ``sigma_env`` (N,)."""
    n, nq = dirs.shape[:2]
    g = geom.gather_size
    lum_atlas, geo_atlas, view_atlas = atlas
    cj = geom.centre_j[pair]  # (N, 3)
    t, hit = _march(geom, pair, pos, dirs)
    d = pos[:, None] + t[..., None] * dirs - cj[:, None]  # the hit, from the sender's centre
    rel = _normalize(d)
    fr = geom.frame[pair]  # (N, 3, 3)
    ext = geom.extent[pair][:, None]
    tx = (dot3(d, fr[:, None, 0]) / ext + 1.0) * 0.5 * g
    ty = (1.0 - dot3(d, fr[:, None, 1]) / ext) * 0.5 * g
    texel = 2.0 * ext / g
    half = jnp.maximum(edge[:, None] * t, 1e-6)
    level = 0.5 * jnp.log2(1.0 + (half / texel) ** 2)  # ≈ log2 of the footprint, smooth
    # computed once (XLA would otherwise recompute them inside every consumer)
    tx, ty, level, hit, *rel = materialise_each(tx, ty, level, hit, rel[..., 0], rel[..., 1],
                                                rel[..., 2])
    rel = jnp.stack(rel, -1)
    idx, w = _mip_taps(jnp.broadcast_to(pair[:, None], tx.shape), tx, ty, level, g)
    # two atlases, each tap sum consumed whole by one contraction: XLA:CPU then fuses the
    # gather into the tap sum (slicing one (N, Q, C + 4) result made it materialise all
    # (N, Q, 8, C + 4) taps, many times slower)
    geo = materialise(taps_sum(geo_atlas, idx, w))  # (N, Q, 4): n·cov, cov
    cov = geo[..., 3]
    # the samples' normal where the atlas has coverage, the outward direction elsewhere
    ny = _normalize(geo[..., :3] + (1.0 - jnp.clip(cov, 0.0, 1.0))[..., None] * rel)
    spec, mirror = _specular(sh, jnp.broadcast_to(sender[:, None], (n, nq)).reshape(-1),
                             ny.reshape(-1, 3), -dirs.reshape(-1, 3))
    hidden = _env_blur(sh.env, dirs, jnp.broadcast_to(sigma_env[:, None], (n, nq)))
    wq = wts * hit
    wc = wq * cov
    ein = "nq,nqc->nc"
    lum = taps_sum(lum_atlas, idx, w)  # L·cov
    if view_atlas is not None:  # a bounce's change of the sender's gloss, towards x
        lum = lum + _bounced_gloss(geom, sh, view_atlas, idx, w, pair, pos, t, dirs, cov,
                                   lum, spec, mirror)
    out = jnp.einsum(ein, wq, lum)
    out = out + jnp.einsum(ein, wc, spec.reshape(n, nq, -1)) @ sh.basis
    if mirror is not None:
        out = out + sh.to_output(jnp.einsum(ein, wc, mirror.reshape(n, nq, -1)))
    return (out, jnp.einsum(ein, wc, hidden) @ sh.basis,
            jnp.einsum(ein, wts, hidden) @ sh.basis)


def _bounced_gloss(geom: IRGeometry, sh: _Shading, view_atlas: tuple[jax.Array, jax.Array],
                   idx: jax.Array,
                   w: jax.Array, pair: jax.Array, pos: jax.Array, t: jax.Array,
                   dirs: jax.Array, cov: jax.Array, lum: jax.Array, spec: jax.Array,
                   mirror: jax.Array | None) -> jax.Array:
    """The bounce's change of the sender's gloss (N, Q, C) times coverage at the hits of the
    rays (pos (N, 3) + t (N, Q) dirs (N, Q, 3)) on the sender of ``pair`` (N,), towards the
    receiver point: the change towards the receiving object (``IRGeometry.s_view``) read
    from ``view_atlas`` at the mip taps (``idx``, ``w``) of the hits, times the share its
    view grid shows in the direction of the point (tents on the grid at the hit). In bands,
    at most the sender's radiance towards the point there (``lum`` (N, Q, C), L·cov, plus
    ``spec``, ``mirror`` (N·Q, ·) of :func:`_specular` times ``cov`` (N, Q)) is taken
    away."""
    n, nq = dirs.shape[:2]
    hit_pos = pos[:, None] + t[..., None] * dirs
    frame = _view_frame_at(hit_pos, geom.centre_i[pair][:, None], geom.radius_i[pair][:, None],
                           geom.frame[pair][:, None, 0])
    tents = _grid_tents(frame, -dirs)  # (N, Q, 9)
    # each atlas's tap sum consumed whole (see :func:`_neighbour_along`)
    shown = jnp.sum(tents * taps_sum(view_atlas[1], idx, w), -1) / jnp.maximum(cov, 1e-6)
    change = taps_sum(view_atlas[0], idx, w) * jnp.clip(shown, 0.0, 1.0)[..., None]
    if sh.env.product_tensor is None:  # bands: the radiance towards x stays non-negative
        own = cov[..., None] * (spec.reshape(n, nq, -1) @ sh.basis)
        if mirror is not None:
            own = own + cov[..., None] * sh.to_output(mirror).reshape(n, nq, -1)
        change = jnp.maximum(change, -jax.lax.stop_gradient(jnp.maximum(lum + own, 0.0)))
    return change


def _hidden_source_gloss(sh: _Shading, geom: IRGeometry, obj: jax.Array, pos: jax.Array,
                         nrm: jax.Array, view: jax.Array) -> jax.Array | None:
    """β Σ_s F D G/(4cosθr) Φ_s (N, C) over the bright sources a neighbour hides (the part of
    the receiver's environment gloss that the neighbour blocks; which sub-points:
    :func:`~._diffuse._hidden_sources`, marched where the gloss weight β F D G/(4cosθr) of a
    sub-point behind a neighbour's bounding sphere exceeds ``_SOURCE_GLOSS_MIN``)."""
    src = _source_terms(sh.env)
    if src is None:
        return None
    sdir, sflux = src
    o = jnp.maximum(obj, 0)
    mats = sh.mats
    w = jnp.zeros((pos.shape[0], sdir.shape[0]), pos.dtype)
    for k, m in enumerate(sh.materials):
        wk = _gloss_weights(nrm[:, None], view[:, None], sdir[None], mats["mu"][o][:, None],
                            mats["n"][o][:, None], m.distribution, m.geometry)
        w = jnp.where((o == k)[:, None], wk, w)
    w = mats["beta"][o][:, None] * w
    occ = _hidden_sources(geom, sh.env, pos, o, weight=w, least=_SOURCE_GLOSS_MIN)
    return ((occ * w) @ sflux) @ sh.basis


#: the gloss weight (1/sr) of a bright-source sub-point below which
#: :func:`_hidden_source_gloss` lets the neighbours' bounding spheres decide whether it is
#: hidden (such a sub-point changes the receiver's radiance by less than 1 % of what a white
#: Lambertian surface facing it reflects of it)
_SOURCE_GLOSS_MIN = 0.01 / math.pi


#: the gloss quadrature runs over the receivers in this many equal chunks (the active ones
#: sorted first; chunks without an active receiver are skipped), each at least
#: ``_GLOSS_MIN_CHUNK`` receivers (or all of them): one traced copy of the quadrature (compile
#: time), at most one partly active chunk of wasted work, and few enough iterations that the
#: loop's per-iteration overhead does not count (small chunks of 128 receivers cost more CPU
#: on the benchmark frame)
_GLOSS_CHUNKS = 64
_GLOSS_MIN_CHUNK = 1024
#: with the accelerator layout (:mod:`spectral_fit._runtime.backend`) the receivers run in chunks of
#: up to this many, all of them when fewer (no sort, loop or conditional)
_GLOSS_ACCEL_CHUNK = 65536
#: a receiver's lobe is evaluated against a neighbour when its mirror direction is within the
#: neighbour's angular radius plus this many lobe widths μ (+ 0.05 rad): the lobe's reflected
#: directions have an angular std of about √2 μ, so beyond that the lobe keeps < e^-6 of its
#: weight (7 widths changed no receiver of the benchmark frame by more than 1e-7 of the peak)
_LOBE_REACH = 5.0


def _lobe_gather(geom: IRGeometry, atlas: tuple[Any, ...], sh: _Shading,
                 pos: jax.Array, nrm: jax.Array, view: jax.Array, obj: jax.Array,
                 grid: tuple[jax.Array, tuple[int, int], int] | None = None,
                 own: jax.Array | None = None) -> jax.Array:
    """Gloss and mirror interreflection (N, C): β A(x) Σ_q w_q (neighbour − hidden environment)
    over the receiver's lobe nodes, χ F(θr) (…) along R. Receivers whose lobe cannot reach a
    neighbour are sorted last, into chunks (``_GLOSS_CHUNKS``) that are skipped; with the
    accelerator layout (:mod:`spectral_fit._runtime.backend`) all receivers run at once.

    ``grid`` = (pixel (N,), image shape (H, W), step): the receivers are pixels of one image;
    the quadrature runs at every ``step``-th row and column only (:func:`_image_anchors`) and
    the pixels between are interpolated bilinearly (the gloss interreflection is a blurred
    image of the neighbour: smooth at the pixel scale)."""
    active, gap, refl = _lobe_reach(geom, sh, pos, nrm, view, obj)
    if grid is None:
        return _lobe_quadrature(geom, atlas, sh, pos, nrm, view, obj, active, own)
    itself, a_idx, a_w = _image_anchors(grid[0], obj, grid[1], grid[2], pos, refl, gap,
                                        math.sqrt(2.0) * sh.mats["mu"][jnp.maximum(obj, 0)])
    res = _lobe_quadrature(geom, atlas, sh, pos, nrm, view, obj, active & itself, own)
    return jnp.where(itself[:, None], res, taps_sum(res, a_idx, a_w))


def _lobe_reach(geom: IRGeometry, sh: _Shading, pos: jax.Array, nrm: jax.Array,
                view: jax.Array, obj: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Which receivers' gloss lobes can reach a neighbour (their mirror direction within the
    neighbour's angular radius plus ``_LOBE_REACH`` lobe widths; N·V > 0): ``active`` (N,)
    bool, the distance ``gap`` (N,) to the nearest neighbour's bounding sphere, and the mirror
    directions ``refl`` (N, 3)."""
    k_per = geom.n_objects - 1
    mats = sh.mats
    o_all = jnp.maximum(obj, 0)
    nv_all = dot3(nrm, view)
    refl_all = 2.0 * nv_all[:, None] * nrm - view
    reach = jnp.zeros(obj.shape, bool)
    gap = jnp.full(obj.shape, jnp.inf, pos.dtype)
    for k in range(k_per):
        pair = o_all * k_per + k
        oc = geom.centre_j[pair] - pos
        d2 = jnp.maximum(dot3(oc, oc), 1e-30)
        gap = jnp.minimum(gap, jnp.maximum(jnp.sqrt(d2) - geom.radius_j[pair], 1e-6))
        # angle(R, c_j − x) < asin(r_j/d) + reach, by cosines (no arccos per receiver)
        lim = jnp.minimum(atan2_poly(geom.radius_j[pair],
                                      jnp.sqrt(jnp.maximum(d2 - geom.radius_j[pair] ** 2,
                                                           1e-30)))
                          + _LOBE_REACH * mats["mu"][o_all] + 0.05, math.pi)
        reach = reach | (dot3(oc, refl_all) > sincos_poly(lim)[1] * jnp.sqrt(d2))
    return (obj >= 0) & (nv_all > 0.0) & reach, gap, refl_all


def _lobe_quadrature(geom: IRGeometry, atlas: tuple[Any, ...], sh: _Shading,
                     pos: jax.Array, nrm: jax.Array, view: jax.Array, obj: jax.Array,
                     active: jax.Array, own: jax.Array | None = None) -> jax.Array:
    """The gloss and mirror interreflection (N, C) of :func:`_lobe_gather` at the ``active``
    (N,) receivers (zero at the others), by the lobe quadrature in chunks, the active
    receivers first and the chunks past them skipped (one chunk of all with the accelerator
    layout).

    ``own`` (N, C): the environment's gloss and mirror the frame shaded at each receiver.
    With it, the sky the neighbours hide is taken off as the nodes' hidden sky times
    min(1, own / the nodes' sky over the whole lobe), per channel: at most the hidden share
    of the receiver's own gloss (the nodes and the frame's split sum read the lobe's sky
    differently at grazing angles; a band whose diffuse light is dim went below zero)."""
    k_per = geom.n_objects - 1
    c = sh.channels
    mats = sh.mats
    materials = sh.materials
    n = pos.shape[0]
    if on_accelerator():
        size = max(1, min(n, _GLOSS_ACCEL_CHUNK))
    else:
        size = max(1, min(n, max(_GLOSS_MIN_CHUNK, -(-n // _GLOSS_CHUNKS))))
    nc = -(-n // size)
    pad = nc * size - n

    senders = jnp.asarray([j for _, j in geom.pairs], jnp.int32)
    same = len({(m.distribution, m.geometry) for m in materials}) == 1

    def run(args: tuple[jax.Array, ...]) -> jax.Array:
        x, nn, vv, ob, act, *mine = args
        o = jnp.maximum(ob, 0)
        mu, eta = mats["mu"][o], mats["n"][o]
        beta, chi = mats["beta"][o], mats["chi"][o]
        nv = dot3(nn, vv)
        if same:
            m0 = materials[0]
            dirs, wts = jax.vmap(lambda a, b, m_, e_: _lobe_nodes(
                a, b, m_, e_, distribution=m0.distribution, geometry=m0.geometry))(
                    nn, vv, mu, eta)
        else:
            dirs = wts = None
            for k, m in enumerate(materials):
                d_k, w_k = jax.vmap(lambda a, b, m_, e_, m=m: _lobe_nodes(
                    a, b, m_, e_, distribution=m.distribution, geometry=m.geometry))(
                        nn, vv, mu, eta)
                sel = o == k
                dirs = d_k if dirs is None else jnp.where(sel[:, None, None], d_k, dirs)
                wts = w_k if wts is None else jnp.where(sel[:, None], w_k, wts)
        # computed once (XLA would otherwise recompute the nodes inside every consumer)
        dw = materialise(jnp.concatenate([dirs, wts[..., None]], -1))
        dirs, wts = dw[..., :3], dw[..., 3]
        albedo = _albedo_at(sh.albedo, ob, nv)
        lobe_sigma = math.sqrt(2.0) * mu
        acc = jnp.zeros((x.shape[0], c), x.dtype)
        hid = sky = None
        g_w = (beta * albedo)[:, None]
        if sh.mirror:
            rdir = 2.0 * nv[:, None] * nn - vv
            m_w = (chi * fresnel_dielectric(jnp.clip(nv, 0.0, 1.0), eta))[:, None]
        for k in range(k_per):
            pair = o * k_per + k
            along = _neighbour_along(geom, atlas, sh, pair, senders[pair], x, dirs, wts,
                                     _EDGE * lobe_sigma, 0.5 * lobe_sigma)
            m_along = None
            if sh.mirror:
                m_along = _neighbour_along(geom, atlas, sh, pair, senders[pair], x,
                                           rdir[:, None], jnp.ones_like(mu)[:, None],
                                           jnp.full_like(mu, 0.02), jnp.zeros_like(mu))
            acc = acc + g_w * along[0]
            h, sk = g_w * along[1], g_w * along[2]
            if m_along is not None:
                acc = acc + m_w * m_along[0]
                h, sk = h + m_w * m_along[1], sk + m_w * m_along[2]
            hid = h if hid is None else hid + h
            sky = sk  # the same nodes for every neighbour
        if hid is not None:
            if mine:  # the hidden sky as a share of the receiver's own environment gloss
                share = jnp.where(sky > 1e-30, mine[0] / jnp.where(sky > 1e-30, sky, 1.0), 1.0)
                hid = hid * jnp.clip(share, 0.0, 1.0)
            acc = acc - hid
        return jnp.where(act[:, None], acc, 0.0)

    zz = jnp.asarray((0.0, 0.0, 1.0), nrm.dtype)
    if nc == 1:  # one chunk (accelerator layout, or few receivers): no sort, loop or cond
        res = run((pos, jnp.where(active[:, None], nrm, zz), jnp.where(active[:, None], view, zz),
                   obj, active, *([] if own is None else [own])))
    else:
        # the active receivers first, each part in index order (a stable partition, found
        # by counting: a sort of the N keys cost more than the whole rest of the bookkeeping)
        rank, order = _partition(active)
        count = jnp.sum(active.astype(jnp.int32))
        slots = jnp.concatenate([order, jnp.full((pad,), n, jnp.int32)]).reshape(nc, size)

        def do(sl: jax.Array) -> jax.Array:
            # the chunk's receivers are gathered here: skipped chunks gather nothing
            ix = jnp.minimum(sl, n - 1)
            act = active[ix] & (sl < n)
            return run((pos[ix], jnp.where(act[:, None], nrm[ix], zz),
                        jnp.where(act[:, None], view[ix], zz), obj[ix], act,
                        *([] if own is None else [own[ix]])))

        def step(_: None, a: tuple[jax.Array, jax.Array]) -> tuple[None, jax.Array]:
            i, sl = a
            # chunks past the active receivers are skipped; each iteration passes only its
            # own (size, C) result (a carried (N, C) buffer was copied through every
            # conditional, a large cost over the 64 iterations)
            return None, jax.lax.cond(i * size < count, do,
                                      lambda _: jnp.zeros((size, c), pos.dtype), sl)

        _, ys = jax.lax.scan(step, None, (jnp.arange(nc, dtype=jnp.int32), slots))
        # back to the receivers' order: receiver i's result is row rank[i] (a gather)
        res = materialise(ys.reshape(nc * size, c)[rank], cut=True)
    return res
