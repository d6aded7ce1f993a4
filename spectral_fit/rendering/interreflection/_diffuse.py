"""The gather mode's diffuse transfer: the light the neighbours' samples send to a receiver
through point-to-patch form factors, less the environment they hide.

The senders' samples (:class:`_Senders`, per pair (P, M, ...), M = g²) carry a
view-independent radiance (C) and a view-dependent one tabulated towards a 3 × 3 grid of
directions spanning the receiver's bounding sphere (gloss (9, r) in the map's principal
channels, mirror (9, C)). The form factor F = cos_x cos_y A_y / (π √(r⁴ + (A_y/π)²))
(:func:`_form_factor_block`) weights them into Σ_y F L_y(→x) (:func:`_transfer`); the net
light subtracts the environment the neighbours hide, a quadrature over the receiver's
hemisphere marched through their depth maps (:func:`~._march._cover`), and the bright sources
they hide (:func:`_diffuse_net`).
It is evaluated at the samples themselves (:func:`_sample_diffuse_net`, interpolated to
receivers by :func:`_interpolate_net`) or at every receiver (:func:`_direct_diffuse`).

Every per-point quantity is computed batched and by components (no per-point vmapped
gathers, no arctan2/arccos per lookup, unrolled tap sums: XLA:CPU runs those as slow loops,
see docs/rendering.md), and everything that comes from the environment alone (the senders'
gloss, the hidden environment) stays in the map's r principal channels
(``env.spectral_basis``) until it has been summed. Positions m, radiance in the
environment's unit.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ...lighting import EnvironmentMap, dot3, irradiance, taps_sum
from ._march import (
    _CONE_NODES,
    _CONE_POINTS,
    _CONE_STEPS,
    _MARCH_STEPS,
    BrightPoints,
    _cover,
    _march,
    _sender_box,
    bright_points,
)
from ._pass1 import _MIN_COS, IRGeometry, _normalize, pair_list
from ._shading import _Shading, _source_terms, _specular, _times_reflectance

__all__: list[str] = []

#: receivers per chunk of the diffuse gather (receivers are sorted by object first)
_CHUNK = 512

#: the neighbour's view-dependent radiance is tabulated per sample towards a 3 × 3 grid of
#: directions spanning the receiver's bounding sphere (gnomonic coordinates in −1, 0, 1 × tanθc)
_VIEW_GRID = (-1.0, 0.0, 1.0)


def _view_frames(geom: IRGeometry) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Per sample (P, M): the unit axis a towards the receiver's centre, a tangent frame e1, e2,
    and T = tanθc of the receiver's bounding sphere seen from the sample."""
    return _view_frame_at(geom.s_pos, geom.centre_i[:, None, :], geom.radius_i[:, None],
                          geom.frame[:, None, 0, :])


def _view_frame_at(pos: jax.Array, centre: jax.Array, radius: jax.Array, s: jax.Array
                   ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """The view grid's frame at points ``pos`` (..., 3) of a sender (:func:`_view_frames`):
    the receiver's bounding sphere (``centre`` (..., 3), ``radius`` (...)) and the pair's
    first raster axis ``s`` (..., 3), broadcast together."""
    to_c = centre - pos
    dist = jnp.sqrt(jnp.maximum(jnp.sum(to_c * to_c, -1), 1e-30))
    a = to_c / dist[..., None]
    e1 = _normalize(s - jnp.sum(s * a, -1, keepdims=True) * a)
    e2 = jnp.cross(a, e1)
    sin_c = jnp.clip(radius / dist, 0.05, 0.95)
    return a, e1, e2, sin_c / jnp.sqrt(1.0 - sin_c * sin_c)


def _grid_views(geom: IRGeometry, frames: tuple[jax.Array, ...]) -> jax.Array:
    """Each sample's 3 × 3 view grid (P, M, 9, 3): unit directions a + tanθc (u e1 + v e2),
    u, v in ``_VIEW_GRID`` (index 3·iu + iv), those below a rim sample's horizon lifted just
    above it."""
    a, e1, e2, tan_c = frames
    views = []
    for gu in _VIEW_GRID:
        for gv in _VIEW_GRID:
            views.append(_normalize(a + tan_c[..., None] * (gu * e1 + gv * e2)))
    v = jnp.stack(views, 2)  # (P, M, 9, 3)
    nrm = jnp.broadcast_to(geom.s_nrm[:, :, None], v.shape)
    return _normalize(v + jnp.maximum(0.0, _MIN_COS - jnp.sum(v * nrm, -1, keepdims=True))
                      * nrm)


def _grid_tents(frame: tuple[jax.Array, ...], d: jax.Array) -> jax.Array:
    """Weights (..., 9) of unit directions ``d`` (..., 3) on a sample's view grid (order of
    :func:`_grid_views`), the grid's ``frame`` = (a, e1, e2, tanθc) broadcast to ``d``."""
    a, e1, e2, tan_c = frame
    den = jnp.maximum(dot3(d, a), 1e-9) * tan_c
    tu, tv = _tents(dot3(d, e1) / den), _tents(dot3(d, e2) / den)
    return jnp.stack([tu[iu] * tv[iv] for iu in range(3) for iv in range(3)], -1)


def _sample_specular(geom: IRGeometry, sh: _Shading, frames: tuple[jax.Array, ...]
                     ) -> tuple[jax.Array, jax.Array | None]:
    """Each sample's view-dependent radiance towards the 3 × 3 view grid: gloss (P, M, 9, r)
    in the map's r channels and mirror (P, M, 9, C) (or None)."""
    p_count, m_count = geom.s_area.shape
    senders = np.asarray([j for _, j in geom.pairs], np.int32)
    v = _grid_views(geom, frames)  # (P, M, 9, 3)
    nrm = jnp.broadcast_to(geom.s_nrm[:, :, None], v.shape)
    obj = jnp.broadcast_to(jnp.asarray(senders)[:, None, None], v.shape[:3])
    g, m = _specular(sh, obj.reshape(-1), nrm.reshape(-1, 3), v.reshape(-1, 3))
    shape = (p_count, m_count, len(_VIEW_GRID) ** 2)
    live = (geom.s_area > 0)[..., None, None]
    g = jnp.where(live, g.reshape(*shape, -1), 0.0)
    if m is not None:
        m = jnp.where(live, m.reshape(*shape, -1), 0.0)
    return g, m


def _tents(x: jax.Array) -> list[jax.Array]:
    """Linear interpolation weights of x ∈ [−1, 1] on the nodes −1, 0, 1."""
    x = jnp.clip(x, -1.0, 1.0)
    return [jnp.maximum(-x, 0.0), 1.0 - jnp.abs(x), jnp.maximum(x, 0.0)]


class _Senders(eqx.Module):
    """The senders' samples as seen by the gather: per pair (P, M, ...) position, normal, area,
    view frames (axis, e1, e2, tanθc), view-independent radiance (C) and view-dependent gloss
    (9 view directions, r channels) and mirror (9, C, or None)."""

    pos: jax.Array
    nrm: jax.Array
    area: jax.Array
    frames: tuple[jax.Array, ...]
    lum: jax.Array
    spec: jax.Array
    mirror: jax.Array | None


def _form_factor_block(x: jax.Array, nx: jax.Array, snd: tuple[jax.Array, ...]
                       ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Point-to-patch form factors F (..., R, S) = cos_x cos_y A/(π √(r⁴ + (A/π)²)) between
    receivers (x, nx (..., R, 3)) and sender samples ``snd`` = (pos, nrm, area, axis, e1, e2,
    tanθc) (..., S, ...), and the view-grid tents (u, v: 3 each) of the direction y → x in each
    sample's view frame. Computed by components (elementwise, fused)."""
    ypos, ynrm, yarea, fa, fe1, fe2, ftan = snd
    d = [ypos[..., None, :, c] - x[..., :, None, c] for c in range(3)]  # y − x
    r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    cx = sum(nx[..., :, None, c] * d[c] for c in range(3))
    cy = -sum(ynrm[..., None, :, c] * d[c] for c in range(3))
    a = yarea[..., None, :] / math.pi
    w = jnp.maximum(cx, 0.0) * jnp.maximum(cy, 0.0) * a / jnp.maximum(
        r2 * jnp.sqrt(r2 * r2 + a * a), 1e-30)
    # view-dependent part: gnomonic coordinates of the direction y → x in y's view frame
    along = -sum(fa[..., None, :, c] * d[c] for c in range(3))
    den = jnp.maximum(along, 1e-9) * ftan[..., None, :]
    tu = _tents(-sum(fe1[..., None, :, c] * d[c] for c in range(3)) / den)
    tv = _tents(-sum(fe2[..., None, :, c] * d[c] for c in range(3)) / den)
    return w, tu, tv


def _transfer(w: jax.Array, tu: list[jax.Array], tv: list[jax.Array], lum: jax.Array,
              spec: jax.Array, mirror: jax.Array | None, basis: jax.Array
              ) -> tuple[jax.Array, jax.Array]:
    """Σ_y F L_y(→x) (..., R, C) and Σ_y F (..., R): the senders' view-independent radiance
    ``lum`` (..., S, C) plus their view-dependent part (``spec`` (..., S, 9, r), ``mirror``
    (..., S, 9, C)) interpolated on the view grid, weighted by the form factors ``w``."""
    ein = "...rs,...sc->...rc"
    lsum = jnp.einsum(ein, w, lum)
    ws = jnp.concatenate([w * tu[iu] * tv[iv] for iu in range(3) for iv in range(3)], -1)
    sp = jnp.swapaxes(spec, -3, -2).reshape(*spec.shape[:-3], -1, spec.shape[-1])
    lsum = lsum + jnp.einsum(ein, ws, sp) @ basis
    if mirror is not None:
        mp = jnp.swapaxes(mirror, -3, -2).reshape(*mirror.shape[:-3], -1, mirror.shape[-1])
        lsum = lsum + jnp.einsum(ein, ws, mp)
    return lsum, jnp.sum(w, -1)


def _hidden_sources(geom: IRGeometry, env: EnvironmentMap, pos: jax.Array, o: jax.Array, *,
                    weight: jax.Array | None = None, least: float = 0.0,
                    cap: int | None = None) -> jax.Array | None:
    """(N, S·k) 1 where a bright-source sub-point's direction from ``pos`` (N, 3) world meets a
    neighbour of the receivers' objects ``o`` (N,); None without sources. Geometry only (no
    gradient).

    A ray that meets a neighbour's bounding sphere (:func:`_behind_spheres`) is marched
    through the neighbour's depth map with its creases in ``_CONE_STEPS`` steps
    (:func:`~._march._march`): the neighbour's actual shape casts the source's shadow, and
    its edge is found to a fraction of a texel (the lobe rays' coarser march lost a tenth of
    a box's shadow). Only rays whose ``weight`` (N, S·k) exceeds ``least`` count, and only
    the ``cap`` points (default ``_SOURCE_MARCHED``) with the largest such weight are
    marched; the rest keep the bounding spheres' answer, and a call with no such ray marches
    nothing."""
    src = _source_terms(env)
    if src is None:
        return None
    pos = jax.lax.stop_gradient(pos)
    sdir = jax.lax.stop_gradient(src[0])
    behind = _behind_spheres(geom, pos, sdir, o)
    score = behind if weight is None else behind * jax.lax.stop_gradient(weight)
    score = jnp.max(jnp.where(score > least, score, 0.0), -1)  # (N,)
    n = pos.shape[0]
    cap = _SOURCE_MARCHED if cap is None else cap

    def march(p: jax.Array, ob: jax.Array) -> jax.Array:
        dirs = jnp.broadcast_to(sdir, (p.shape[0], *sdir.shape))
        box = _sender_box(geom)
        occ = jnp.zeros(dirs.shape[:2], p.dtype)
        for k in range(geom.n_objects - 1):
            pair = ob * (geom.n_objects - 1) + k
            _, hit = _march(geom, pair, p, dirs, steps=_CONE_STEPS, creases=True, box=box)
            occ = jnp.maximum(occ, hit)
        return occ

    def marched() -> jax.Array:
        if cap >= n:
            return behind * march(pos, o)
        top, idx = jax.lax.top_k(score, cap)
        sel = behind[idx] * march(pos[idx], o[idx])
        return behind.at[idx].set(jnp.where((top > 0.0)[:, None], sel, behind[idx]))

    occ = jax.lax.cond(jnp.any(score > 0.0), marched, lambda: behind)
    return jax.lax.stop_gradient(occ)


#: at most this many points per call of :func:`_hidden_sources` are marched (in the paper's
#: frame 19 of 512 samples and 62 of 4,096 receivers have a source behind the other sphere;
#: marching all of them made the frame 5 times slower)
_SOURCE_MARCHED = 128


def _behind_spheres(geom: IRGeometry, pos: jax.Array, dirs: jax.Array, o: jax.Array
                    ) -> jax.Array:
    """(N, Q) 1 where the directions ``dirs`` (Q, 3) from ``pos`` (N, 3) meet the bounding
    sphere of a neighbour of the receivers' objects ``o`` (N,) ahead of the point."""
    occ = jnp.zeros((pos.shape[0], dirs.shape[0]), pos.dtype)
    for k in range(geom.n_objects - 1):
        pair = o * (geom.n_objects - 1) + k
        oc = geom.centre_j[pair] - pos
        tp = oc @ dirs.T
        miss2 = jnp.sum(oc * oc, -1)[:, None] - tp * tp
        occ = jnp.maximum(occ, ((tp > 0.0) & (miss2 < geom.radius_j[pair][:, None] ** 2)
                                ).astype(pos.dtype))
    return occ


def _diffuse_net(geom: IRGeometry, env: EnvironmentMap, lsum: jax.Array, hidden: jax.Array,
                 pos: jax.Array, nrm: jax.Array, o: jax.Array) -> jax.Array:
    """The light the neighbours add at receivers, before the receiver's α S/π (N, C):
    Σ_y F L_y(→x) (``lsum``) − (1/π) ∫ hit L_env cos (``hidden`` (N, C), :func:`_covers`)
    − (1/π) Σ hidden sources flux max(0, N·d_s) (:func:`_hidden_sources`)."""
    net = lsum - hidden
    src = _source_terms(env)
    if src is not None:
        sdir, sflux = src
        cosn = jnp.maximum(nrm @ sdir.T, 0.0)
        occ = _hidden_sources(geom, env, pos, o, weight=cosn)
        net = net - ((occ * cosn) @ sflux) @ env.spectral_basis / math.pi
    return net


def _coverage_factor(omega: jax.Array, w: jax.Array) -> jax.Array:
    """(R, k) the factor that brings receivers' form factors ``w`` (R, k·M) to each of k
    neighbours (M samples each) to the neighbour's projected solid angle ``omega`` (R, k)
    (sr; :func:`~._march._cover`, marched through the neighbour's depth map) over π Σ F of
    its samples: the samples are the neighbour seen along the pair's axis, and a point off
    that axis sees parts of it they lack (a quarter of a ring's solid angle from the wall of a
    cup beside it). Within [0, ``_COVERAGE_MAX``]; 1 where Σ F is negligible. Geometry only
    (no gradient)."""
    r, k = omega.shape
    fsum = math.pi * jnp.sum(jax.lax.stop_gradient(w).reshape(r, k, -1), -1)
    ok = fsum > 1e-3
    return jnp.where(ok, jnp.clip(omega / jnp.where(ok, fsum, 1.0), 0.0, _COVERAGE_MAX), 1.0)


def _covers(geom: IRGeometry, env: EnvironmentMap, pair: jax.Array, x: jax.Array,
            nx: jax.Array, *, nodes: tuple[int, int] | None = None,
            steps: int = _MARCH_STEPS, irr: jax.Array | None = None,
            bright: BrightPoints | None = None, creases: bool = False
            ) -> tuple[jax.Array, jax.Array]:
    """:func:`~._march._cover` of the neighbours ``pair`` (R, k) of receivers ``x`` (R, 3)
    world, unit normals ``nx`` (R, 3): their projected solid angles (R, k) and the
    environment they hide, summed over the k neighbours, in the map's C channels (R, C): in
    bands, per channel at most the receiver's whole irradiance/π (what is hidden is part of
    the sky; a quadrature node that catches a lamp would otherwise take more than there
    is). ``irr`` (R, C): that irradiance where the caller has it already; ``bright``: the
    map's bright part as points (:func:`~._march.bright_points`)."""
    r, k = pair.shape
    omega, hidden = _cover(geom, env, pair.reshape(-1), jnp.repeat(x, k, axis=0),
                           jnp.repeat(nx, k, axis=0), nodes=nodes, steps=steps, bright=bright,
                           creases=creases)
    hidden = jnp.sum(hidden.reshape(r, k, -1), 1) @ env.spectral_basis
    if env.product_tensor is None:  # bands (a basis's coefficients may be negative)
        if irr is None:
            irr = _irradiance_at(env, nx)
        sky = jax.lax.stop_gradient(jnp.maximum(irr, 0.0)) / math.pi
        hidden = jnp.clip(hidden, 0.0, sky)
    return omega.reshape(r, k), hidden


def _irradiance_at(env: EnvironmentMap, nrm: jax.Array) -> jax.Array:
    """(..., C) the environment's irradiance at unit normals ``nrm`` (..., 3)."""
    e = jax.vmap(lambda n: irradiance(env, n))(nrm.reshape(-1, 3))
    return e.reshape(*nrm.shape[:-1], -1)


def _sample_coverage(geom: IRGeometry, env: EnvironmentMap, irr: jax.Array
                     ) -> tuple[jax.Array, jax.Array]:
    """At every sample (P, M), towards each neighbour of its object: the neighbour's
    projected solid angle (P, M, n − 1) (sr), and the environment the neighbours hide
    (P·M, C) (:func:`_covers`; ``irr`` (P, M, C): the samples' irradiance,
    :func:`_irradiance_at`); once per frame (the bounces reuse them)."""
    k_per = geom.n_objects - 1
    p_count, m_count = geom.s_area.shape
    live = (geom.s_area > 0)[..., None]
    pos = jnp.where(live, geom.s_pos, geom.centre_j[:, None])
    nrm = jnp.where(live, geom.s_nrm, geom.frame[:, None, 2])
    recv = np.asarray([j for _, j in geom.pairs], np.int32)
    src = recv[:, None] * k_per + np.arange(k_per)[None, :]  # (P, k_per)
    pair = jnp.asarray(np.repeat(src, m_count, axis=0))  # (P·M, k_per)
    omega, hidden = _covers(geom, env, pair, pos.reshape(-1, 3), nrm.reshape(-1, 3),
                            irr=irr.reshape(p_count * m_count, -1))
    live = live.reshape(-1, 1)
    return (jnp.where(live, omega, 0.0).reshape(p_count, m_count, k_per),
            jnp.where(live, hidden, 0.0))


#: the largest coverage factor (:func:`_coverage_factor`)
_COVERAGE_MAX = 2.0


def _sample_diffuse_net(geom: IRGeometry, snd: _Senders, env: EnvironmentMap,
                        cover: tuple[jax.Array, jax.Array]) -> jax.Array:
    """:func:`_diffuse_net` (P, M, C) at every sample, gathered from all samples of the
    sample's own object's neighbours (dense, batched over pairs: P × M × (n − 1)M form
    factors, scaled per neighbour to its projected solid angle by :func:`_coverage_factor`),
    less the environment those hide; ``cover`` = (projected solid angles (P, M, n − 1),
    hidden environment (P·M, C)) from :func:`_sample_coverage`."""
    n_obj = geom.n_objects
    k_per = n_obj - 1
    p_count, m_count = geom.s_area.shape
    recv = np.asarray([j for _, j in geom.pairs], np.int32)  # the samples' own object
    src = (recv[:, None] * k_per + np.arange(k_per)[None, :])  # (P, k_per) sender pairs

    def senders(x: jax.Array) -> jax.Array:
        s = x[src]  # (P, k_per, M, ...)
        return s.reshape(p_count, k_per * m_count, *x.shape[2:])

    origin = jnp.mean(geom.centre_j, axis=0)
    blk = (senders(snd.pos - origin), senders(snd.nrm), senders(snd.area),
           *(senders(f) for f in snd.frames))
    w, tu, tv = _form_factor_block(geom.s_pos - origin, geom.s_nrm, blk)
    omega, hidden = cover
    factor = _coverage_factor(omega.reshape(-1, k_per), w.reshape(p_count * m_count, -1))
    w = w * jnp.repeat(factor.reshape(p_count, m_count, k_per), m_count, axis=-1)
    lsum, _ = _transfer(w, tu, tv, senders(snd.lum), senders(snd.spec),
                        None if snd.mirror is None else senders(snd.mirror),
                        env.spectral_basis)
    obj = jnp.asarray(np.repeat(recv, m_count), jnp.int32)
    net = _diffuse_net(geom, env, lsum.reshape(-1, lsum.shape[-1]), hidden,
                       geom.s_pos.reshape(-1, 3), geom.s_nrm.reshape(-1, 3), obj)
    return net.reshape(p_count, m_count, -1)


def _reverse_pairs(n: int) -> np.ndarray:
    """Index of pair (j, i) for every pair p = (i, j) (storage order of :func:`pair_list`)."""
    index = {pq: k for k, pq in enumerate(pair_list(n))}
    return np.asarray([index[(j, i)] for i, j in pair_list(n)], np.int32)


def _sphere_form_factor(pos: jax.Array, nrm: jax.Array, centre: jax.Array, radius: jax.Array
                        ) -> jax.Array:
    """Form factor (...) from a differential area (pos, unit nrm (..., 3)) to a sphere
    (centre (..., 3), radius (...)): sin²α cosθ while the sphere is wholly above the tangent
    plane (sinα = r/d, θ the centre's angle from the normal), and the C¹ horizon-clipped
    approximation sin²α (cosθ + sinα)²/(4 sinα) while it straddles it."""
    oc = centre - pos
    d2 = jnp.maximum(dot3(oc, oc), 1e-30)
    sin2 = jnp.minimum(radius * radius / d2, 1.0)
    sin_a = jnp.sqrt(sin2)
    cos_t = dot3(nrm, oc) * jax.lax.rsqrt(d2)
    part = (cos_t + sin_a) ** 2 / (4.0 * jnp.maximum(sin_a, 1e-12))
    return sin2 * jnp.where(cos_t >= sin_a, cos_t, jnp.where(cos_t > -sin_a, part, 0.0))


def _net_tables(geom: IRGeometry, net: jax.Array
                ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The tables :func:`_interpolate_net` interpolates, from the samples' diffuse net light
    ``net`` (P, M, C): net × coverage (P·(g + 2)², C), coverage × the form factor of the
    neighbour's bounding sphere (P·(g + 2)², 1) and the samples' normals (P·(g + 2)², 3),
    each pair's g × g grid with a border of zeros (made once per frame, not per chunk of
    receivers)."""
    g = geom.gather_size
    p_count = net.shape[0]
    # pair q = (j, i) holds samples on i; the sphere they look at is j's (centre_i[q])
    ff_s = _sphere_form_factor(geom.s_pos, geom.s_nrm, geom.centre_i[:, None],
                               geom.radius_i[:, None])
    cov = geom.s_cov * (geom.s_area > 0)

    # Σ w cov F_s (net_s/F_s) / Σ w cov F_s
    def table(x: jax.Array) -> jax.Array:
        x = x.reshape(p_count, g, g, x.shape[-1])
        return jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0))).reshape(-1, x.shape[-1])

    # separate tables, each tap sum consumed whole (slicing one (N, C + 1) tap sum made XLA
    # gather every tap of every channel into memory first)
    return (table(net * cov[..., None]), table((cov * ff_s)[..., None]),
            table(jax.lax.stop_gradient(geom.s_nrm)))


#: the interpolation of the samples' net light weights each of its four samples by
#: (ε + max(0, n_sample · n_receiver))^``_NORMAL_POWER``: on a sharp-edged neighbour the
#: samples of one grid cell can lie on faces at right angles, whose net light differs many
#: times over (a slab's face towards its neighbour sees only the neighbour, its side face
#: half the sky), and a receiver takes it from the samples of its own face; on a smooth
#: object adjacent samples' normals differ by ~10° (g = 16) and the weights barely change
_NORMAL_POWER = 4
_NORMAL_EPS = 1e-3


def _interpolate_net(geom: IRGeometry, net: jax.Array | None, pos: jax.Array, nrm: jax.Array,
                     obj: jax.Array, tables: tuple[jax.Array, ...] | None = None
                     ) -> jax.Array:
    """The samples' diffuse net light (P, M, C) at receivers on the samples' objects (N, C)
    (``tables``: :func:`_net_tables` of ``net``, when made already).

    For each neighbour j of the receiver's object i, the receiver is projected orthographically
    along j → i onto the g × g samples of i that face j (pair (j, i)); there the ratio of the
    net light to the form factor F_j of j's bounding sphere (:func:`_sphere_form_factor`, the
    geometric part, which varies fast next to j) is interpolated bilinearly, weighted by
    coverage × F_j (so each sample stands for its covered part and samples that barely see j
    count little) and by the agreement of the sample's normal with the receiver's
    (:data:`_NORMAL_POWER`: across a sharp edge the receiver takes its own face's samples),
    and multiplied by F_j at the receiver. Receivers facing several neighbours
    blend their grids with weights ∝ N·(c_j − c_i)⁺ (each grid holds the light from all
    neighbours). (What a receiver's own object hides of j — the inside of a cup behind its
    wall — is the renderer's part: its precomputed self-visibility.)"""
    g = geom.gather_size
    k_per = geom.n_objects - 1
    tex, tex_w, tex_n = _net_tables(geom, net) if tables is None else tables
    c = tex.shape[-1]
    rev = jnp.asarray(_reverse_pairs(geom.n_objects))
    o = jnp.maximum(obj, 0)
    acc = jnp.zeros((pos.shape[0], c), tex.dtype)
    wsum = jnp.zeros((pos.shape[0],), tex.dtype)
    for k in range(k_per):
        q = rev[o * k_per + k]  # pair (j, i): samples on i facing j
        fr = geom.frame[q]
        rel = pos - geom.centre_j[q]
        ext = geom.extent[q]
        tx = (dot3(rel, fr[:, 0]) / ext + 1.0) * 0.5 * g + 0.5  # +1 border −0.5 centres
        ty = (1.0 - dot3(rel, fr[:, 1]) / ext) * 0.5 * g + 0.5
        x0f, y0f = jnp.floor(tx), jnp.floor(ty)
        fx, fy = tx - x0f, ty - y0f
        x0 = jnp.clip(x0f.astype(jnp.int32), 0, g + 1)
        y0 = jnp.clip(y0f.astype(jnp.int32), 0, g + 1)
        x1 = jnp.minimum(x0 + 1, g + 1)
        y1 = jnp.minimum(y0 + 1, g + 1)
        base = q * (g + 2) ** 2
        row = g + 2
        idx = jnp.stack([base + y0 * row + x0, base + y0 * row + x1, base + y1 * row + x0,
                         base + y1 * row + x1], -1)
        w = jnp.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], -1)
        # the samples of the receiver's own face first (:data:`_NORMAL_POWER`)
        ns = tex_n[idx]  # (N, 4, 3)
        cos_n = jnp.maximum(sum(ns[..., a] * nrm[:, None, a] for a in range(3)), 0.0)
        w = w * (_NORMAL_EPS + cos_n) ** _NORMAL_POWER
        ff = _sphere_form_factor(pos, nrm, geom.centre_i[q], geom.radius_i[q])
        lum = taps_sum(tex, idx, w) * (ff / jnp.maximum(taps_sum(tex_w, idx, w)[:, 0],
                                                         1e-30))[:, None]
        # the grid holds the hemisphere of i facing j (its axis is −fr[:, 2] = c_i − c_j)
        face = jnp.maximum(dot3(nrm, fr[:, 2]), 0.0)
        acc = acc + face[:, None] * lum
        wsum = wsum + face
    return acc / jnp.maximum(wsum, 1e-30)[:, None]


def _sees(geom: IRGeometry, pos: jax.Array, nrm: jax.Array, obj: jax.Array) -> jax.Array:
    """(N,) bool: some neighbour's bounding sphere rises above the receiver's tangent plane."""
    k_per = geom.n_objects - 1
    sees = jnp.zeros(obj.shape, bool)
    for k in range(k_per):
        pair = jnp.maximum(obj, 0) * k_per + k
        sees = sees | (dot3(nrm, geom.centre_j[pair] - pos) > -geom.radius_j[pair])
    return sees & (obj >= 0)


def _direct_diffuse(geom: IRGeometry, snd: _Senders, env: EnvironmentMap, pos: jax.Array,
                    nrm: jax.Array, obj: jax.Array, *, nodes: tuple[int, int] = _CONE_NODES,
                    steps: int = _CONE_STEPS, points: int = _CONE_POINTS,
                    chunk: int = _CHUNK) -> jax.Array:
    """:func:`_diffuse_net` (N, C) at arbitrary receivers, each gathering from all samples of
    its object's neighbours (receivers sorted by object, chunks of ``chunk``; chunks of
    receivers that see no neighbour, or whose ``obj`` is −1, are skipped), the hidden
    environment by a quadrature of ``nodes`` (rings, azimuths) and the map's bright part as
    ``points`` (:func:`~._march.bright_points`), marched in ``steps``. The
    reference for the interpolated :func:`_interpolate_net`, ``diffuse_at="receivers"``, and
    the screen-space anchors' correction of the interpolation."""
    n_obj = geom.n_objects
    k_per = n_obj - 1
    p_count, m_count = geom.s_area.shape
    km = k_per * m_count
    origin = jnp.mean(geom.centre_j, axis=0)

    def per_obj(x: jax.Array) -> jax.Array:
        return x.reshape(n_obj, km, *x.shape[2:])

    blocks = (per_obj(snd.pos - origin), per_obj(snd.nrm), per_obj(snd.area),
              *(per_obj(f) for f in snd.frames))
    lum, spec = per_obj(snd.lum), per_obj(snd.spec)
    mirror = None if snd.mirror is None else per_obj(snd.mirror)
    n = pos.shape[0]
    key = jnp.where(_sees(geom, pos, nrm, obj), obj, n_obj)
    order = jnp.argsort(key)
    nc = -(-n // chunk)
    pad = nc * chunk - n
    xs = jnp.pad((pos - origin)[order], ((0, pad), (0, 0))).reshape(nc, chunk, 3)
    ns = jnp.concatenate([nrm[order], jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0], nrm.dtype),
                                                       (pad, 3))]).reshape(nc, chunk, 3)
    ks = jnp.pad(key[order], (0, pad), constant_values=n_obj).reshape(nc, chunk)
    c = env.channels
    bright = bright_points(env, points)

    def block(o: int, x0: jax.Array, nx: jax.Array, sel: jax.Array) -> jax.Array:
        w, tu, tv = _form_factor_block(x0, nx, tuple(b[o] for b in blocks))
        pair = jnp.broadcast_to(jnp.arange(k_per, dtype=jnp.int32) + o * k_per,
                                (x0.shape[0], k_per))
        omega, hidden = _covers(geom, env, pair, x0 + origin, nx, nodes=nodes, steps=steps,
                                bright=bright, creases=True)
        w = w * jnp.repeat(_coverage_factor(omega, w), m_count, axis=-1)
        w = jnp.where(sel[:, None], w, 0.0)
        lsum, _ = _transfer(w, tu, tv, lum[o], spec[o], None if mirror is None else
                            mirror[o], env.spectral_basis)
        net = _diffuse_net(geom, env, lsum, hidden, x0 + origin, nx,
                           jnp.full(x0.shape[:1], o, jnp.int32))
        return jnp.where(sel[:, None], net, 0.0)

    def one_chunk(args: tuple[jax.Array, jax.Array, jax.Array]) -> jax.Array:
        x0, nx, kk = args
        acc = jnp.zeros((chunk, c), lum.dtype)
        for o in range(n_obj):
            sel = kk == o
            acc = acc + jax.lax.cond(jnp.any(sel), lambda s, o=o: block(o, x0, nx, s),
                                     lambda s: jnp.zeros((chunk, c), lum.dtype), sel)
        return acc

    res = jax.lax.map(one_chunk, (xs, ns, ks)).reshape(nc * chunk, c)[:n]
    return jnp.zeros((n, c), lum.dtype).at[order].set(res)


def _sample_diffuse(geom: IRGeometry, sh: _Shading, e: jax.Array) -> jax.Array:
    """(P, M, C) view-independent radiance α_j S_j E_irr(n_y)/π of each sample, from its
    irradiance ``e`` (P, M, C) (:func:`_irradiance_at` of the samples' normals)."""
    senders = [j for _, j in geom.pairs]
    sid = jnp.asarray(senders, jnp.int32)
    refl = sh.mats["reflectance"][sid][:, None, :]
    return (sh.mats["alpha"][sid] / math.pi)[:, None, None] * _times_reflectance(sh.env, refl,
                                                                                   e)
