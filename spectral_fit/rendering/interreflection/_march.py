"""Rays against a neighbour's pass-1 depth map (:func:`_march`): where a ray from a receiver
first meets the sender of a pair, from the pair's orthographic raster of the sender (its
coverage, front-surface height along the pair's axis and the depth of the solid behind it,
``IRGeometry.s_front``). Used by the gloss/mirror quadrature (the lobe's node rays) and by
the diffuse transfer (:func:`_cover`: the projected solid angle of a neighbour seen from a
point, which the sender's samples, made along the pair's axis, underestimate where the point
sees the neighbour from another side, and the environment the neighbour hides there).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from ...lighting import EnvironmentMap, dot3
from ._pass1 import SUPERSAMPLE, IRGeometry, _normalize
from ._shading import _env_blur

__all__: list[str] = []


#: steps of the march of a lobe node's ray through the sender's depth map, over the ray's
#: chord of the sender's bounding sphere
_MARCH_STEPS = 16


def _depth_taps(pair: jax.Array, tx: jax.Array, ty: jax.Array, side: int
                ) -> tuple[jax.Array, jax.Array]:
    """Rows (..., 4) of the flattened (P·(side + 2)², ·) padded depth maps and bilinear
    weights (..., 4) at texel coordinates (tx, ty) (centres at integer + 0.5; outside: the
    zero border)."""
    x = jnp.clip(tx + 0.5, 0.0, side + 1.0)  # −0.5 (texel centres) + 1 (border)
    y = jnp.clip(ty + 0.5, 0.0, side + 1.0)
    x0f, y0f = jnp.floor(x), jnp.floor(y)
    fx, fy = x - x0f, y - y0f
    x0 = jnp.minimum(x0f.astype(jnp.int32), side + 1)
    y0 = jnp.minimum(y0f.astype(jnp.int32), side + 1)
    x1 = jnp.minimum(x0 + 1, side + 1)
    y1 = jnp.minimum(y0 + 1, side + 1)
    row = side + 2
    base = pair * row * row
    idx = jnp.stack([base + y0 * row + x0, base + y0 * row + x1, base + y1 * row + x0,
                     base + y1 * row + x1], -1)
    w = jnp.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], -1)
    return idx, w


def _march(geom: IRGeometry, pair: jax.Array, pos: jax.Array, dirs: jax.Array, *,
           steps: int = _MARCH_STEPS) -> tuple[jax.Array, jax.Array]:
    """Where the rays (pos (N, 3), dirs (N, Q, 3)) first meet the sender of ``pair`` (N,):
    the ray parameter t (N, Q) (m) and whether they do (N, Q) float. The sender is its pass-1
    raster (``geom.s_front``: coverage, front-surface height along the pair's axis and the
    depth of the solid behind it, at the raster's full resolution, bilinear; covered where
    the interpolated coverage exceeds ½, the silhouette to a fraction of a texel): the ray
    is stepped ``steps`` times over its chord of the sender's bounding sphere, and
    meets the sender at the first step that is covered and inside the first solid layer
    (behind the front surface by at most its depth, or 1.5 steps for a thin sheet), refined
    to the crossing of the surface between that step and the previous one (t differentiable
    through that refinement; which step is found is not). A ray that passes behind the
    first layer through a second one (the far side of a ring) is not hit."""
    side = geom.gather_size * SUPERSAMPLE
    front = geom.s_front.reshape(-1, 3)
    cj = geom.centre_j[pair][:, None]  # (N, 1, 3)
    rj = geom.radius_j[pair][:, None]  # (N, 1)
    fr = geom.frame[pair]  # (N, 3, 3)
    ext = geom.extent[pair][:, None, None]
    oc = cj - pos[:, None]
    tp = dot3(oc, dirs)
    b2 = dot3(oc, oc) - tp * tp
    h2 = rj * rj - b2
    half = jnp.where(h2 > 0.0, jnp.sqrt(jnp.where(h2 > 0.0, h2, 1.0)), 0.0)  # (finite grads)
    t0 = jnp.maximum(tp - half, 0.0)
    t1 = jnp.maximum(tp + half, t0)
    k = (jnp.arange(steps, dtype=pos.dtype) + 0.5) / steps
    t = t0[..., None] + (t1 - t0)[..., None] * k  # (N, Q, K)
    rel0 = pos[:, None] - cj  # (N, 1, 3)
    coord = [dot3(rel0, fr[:, None, a])[..., None] + t * dot3(dirs, fr[:, None, a])[..., None]
             for a in range(3)]  # (N, Q, K) each: along s, u and the axis towards i
    tx = (coord[0] / ext + 1.0) * 0.5 * side
    ty = (1.0 - coord[1] / ext) * 0.5 * side
    idx, w = _depth_taps(jnp.broadcast_to(pair[:, None, None], tx.shape), tx, ty, side)
    taps = front[idx]  # (N, Q, K, 4, 3)
    cov = jnp.sum(taps[..., 0] * w, -1)
    surf = jnp.sum(taps[..., 1] * w, -1) / jnp.maximum(cov, 1e-6)
    depth = jnp.sum(taps[..., 2] * w, -1) / jnp.maximum(cov, 1e-6)
    step = (t1 - t0)[..., None] / steps
    thick = jnp.maximum(1.5 * step * jnp.abs(dot3(dirs, fr[:, None, 2]))[..., None], depth)
    below = coord[2] - surf  # > 0: in front of the surface (towards the receiver)
    inside = (cov > 0.5) & (below <= 0.0) & (below >= -thick) & (half[..., None] > 0.0)
    first = jnp.argmax(inside, -1)  # (N, Q)
    hit = jnp.any(inside, -1)
    tk = jnp.take_along_axis(t, first[..., None], -1)[..., 0]
    bk = jnp.take_along_axis(below, first[..., None], -1)[..., 0]
    prev = jnp.maximum(first - 1, 0)
    bp = jnp.take_along_axis(below, prev[..., None], -1)[..., 0]
    tpv = jnp.take_along_axis(t, prev[..., None], -1)[..., 0]
    frac = jnp.where((first > 0) & (bp > 0.0), bp / jnp.maximum(bp - bk, 1e-12), 1.0)
    t_hit = jnp.where(first > 0, tpv + frac * (tk - tpv), tk)
    return t_hit, hit.astype(pos.dtype)



def _mirror_hidden(geom: IRGeometry, views: jax.Array, sigma: jax.Array) -> jax.Array:
    """The share (P, M, V) of each sample's gloss lobe towards each of its ``views``
    (P, M, V, 3) that its object's neighbours hide: five rays, the mirror direction about
    the sample's normal (weight 0.4) and four tilted from it by the lobe's width ``sigma``
    (P, M, V) radians (0.15 each), each marched through every neighbour's depth map as
    :func:`_march` does (the sender of pair p is the receiving object of the pairs (j, k),
    k over its neighbours). Geometry alone, no gradient."""
    k_per = geom.n_objects - 1
    p_count, m_count, n_v = views.shape[:3]
    sender = jnp.asarray([j for _, j in geom.pairs], jnp.int32)
    nrm = geom.s_nrm[:, :, None]
    refl = _normalize(2.0 * jnp.sum(views * nrm, -1, keepdims=True) * nrm - views)
    t1 = _normalize(jnp.cross(refl, jnp.broadcast_to(nrm, refl.shape))
                    + jnp.where(jnp.abs(refl[..., :1]) < 0.9, 1.0, 0.0) * 1e-3
                    * jnp.asarray([1.0, 0.0, 0.0]))
    t2 = jnp.cross(refl, t1)
    tilt = jnp.tan(jnp.clip(sigma, 0.0, 1.0))[..., None]
    rays = [refl] + [_normalize(refl + sg * tilt * tv) for tv in (t1, t2) for sg in (-1.0, 1.0)]
    weight = jnp.asarray([0.4, 0.15, 0.15, 0.15, 0.15])
    dirs = jnp.stack(rays, -2).reshape(-1, n_v * 5, 3)  # (P·M, V·5, 3)
    pos = geom.s_pos.reshape(-1, 3)
    hit = jnp.zeros(dirs.shape[:2], pos.dtype)
    for k in range(k_per):
        pair = jnp.repeat(sender * k_per + k, m_count)
        hit = jnp.maximum(hit, _march(geom, pair, pos, dirs)[1])
    share = jnp.sum(hit.reshape(-1, n_v, 5) * weight, -1)
    return jax.lax.stop_gradient(share.reshape(p_count, m_count, n_v))


#: the quadrature of :func:`_cover` at receivers (the diffuse anchors of an image, and
#: ``diffuse_at="receivers"``): rings × azimuths, and the steps of its march
_CONE_NODES = (12, 24)
_CONE_STEPS = 24
#: the quadrature of :func:`_cover` at every sender sample (rings × azimuths): the environment
#: a neighbour hides and its projected solid angle, once per sample and frame
_COVER_NODES = (6, 12)
#: the prefilter of the map at the nodes of :func:`_cover`, a fraction of their spacing
_BLUR = 0.25
#: :func:`_cover` marches its nodes in groups of whole rings of about this many
_COVER_GROUP = 32


def _cover_nodes(geom: IRGeometry, pair: jax.Array, pos: jax.Array, nrm: jax.Array,
                 nodes: tuple[int, int]) -> tuple[jax.Array, jax.Array, jax.Array]:
    """A stratified quadrature of ∫ f(ω) max(0, n·ω) dω over the directions in which points
    ``pos`` (N, 3) with unit normals ``nrm`` (N, 3) can see the sender of ``pair`` (N,):
    unit directions (N, Q, 3), weights (N, Q) (sr, the cosine included) and the nodes'
    angular spacing (N,) (rad). The nodes cover the cone of the sender's bounding sphere
    (rings uniform in cos θ about its axis) where that cone is narrower than the point's
    hemisphere, else the hemisphere itself (rings uniform in sin²θ about the normal, the
    cosine-weighted layout: a point close to a large neighbour, or inside its bounding
    sphere, would otherwise spend half its nodes below its horizon)."""
    nr, na = nodes
    oc = geom.centre_j[pair] - pos
    d = jnp.sqrt(jnp.maximum(dot3(oc, oc), 1e-30))
    cos_a = jnp.sqrt(jnp.maximum(1.0 - (geom.radius_j[pair] / d) ** 2, 0.0))
    cos_a = jnp.where(d > geom.radius_j[pair], cos_a, -1.0)  # the whole sphere from inside
    cone = 2.0 * (1.0 - cos_a) < 1.0  # its solid angle below the hemisphere's projected π
    axis = jnp.where(cone[:, None], oc / d[:, None], nrm)
    t = jnp.where(jnp.abs(axis[:, 0:1]) < 0.9, jnp.asarray([[1.0, 0.0, 0.0]], pos.dtype),
                  jnp.asarray([[0.0, 1.0, 0.0]], pos.dtype))
    e1 = _normalize(jnp.cross(axis, t))
    e2 = jnp.cross(axis, e1)
    u = (jnp.arange(nr, dtype=pos.dtype) + 0.5) / nr  # (R,)
    ct_cone = 1.0 - u[None] * (1.0 - cos_a[:, None])  # (N, R)
    ct_hemi = jnp.sqrt(1.0 - u)[None]  # sin²θ uniform: equal projected solid angle
    ct = jnp.where(cone[:, None], ct_cone, ct_hemi)
    st = jnp.sqrt(jnp.maximum(1.0 - ct * ct, 0.0))
    step = 2.0 * math.pi / na
    phi = (jnp.arange(na, dtype=pos.dtype) + 0.5) * step
    # every other ring turned by half a step (the nodes less aligned)
    phi = phi[None, :] + (jnp.arange(nr) % 2)[:, None] * (0.5 * step)  # (R, A)
    cp, sp = jnp.cos(phi)[None], jnp.sin(phi)[None]
    dirs = (ct[..., None, None] * axis[:, None, None]
            + (st[..., None] * cp)[..., None] * e1[:, None, None]
            + (st[..., None] * sp)[..., None] * e2[:, None, None])  # (N, R, A, 3)
    dirs = dirs.reshape(pos.shape[0], nr * na, 3)
    cosn = jnp.maximum(dot3(dirs, nrm[:, None]), 0.0)
    dw_cone = 2.0 * math.pi * (1.0 - cos_a) / (nr * na)
    w = jnp.where(cone[:, None], dw_cone[:, None] * cosn,
                  jnp.full_like(cosn, math.pi / (nr * na)))
    spacing = jnp.sqrt(jnp.where(cone, dw_cone, 2.0 * math.pi / (nr * na)))
    return dirs, w, spacing


def _cover(geom: IRGeometry, env: EnvironmentMap, pair: jax.Array, pos: jax.Array,
           nrm: jax.Array, *, nodes: tuple[int, int] | None = None,
           steps: int = _MARCH_STEPS) -> tuple[jax.Array, jax.Array]:
    """What the sender of ``pair`` (N,) takes from the sky of points ``pos`` (N, 3) with unit
    normals ``nrm`` (N, 3): its projected solid angle Ω (N,) (sr)
    and the environment it hides, (1/π) ∫ max(0, n·ω) hit(ω) L_env(ω) dω (N, r) in the map's
    r principal channels, each node's radiance prefiltered to ``_BLUR`` of the nodes' spacing
    (a wider prefilter carries the light of the seen directions beside the neighbour's edge
    into the hidden nodes: a third more hidden light beside a cup under a bright band of sky)
    (``nodes``, default ``_COVER_NODES``, :func:`_cover_nodes`; ``steps`` of the march).
    The hits come from the sender's depth map (:func:`_march`), so the sender's actual shape
    hides the sky, not its bounding sphere nor the few sender samples a near point sees at
    grazing angles.
    Geometry only for the hits (no gradient); the radiance is differentiable in the map."""
    pos, nrm = jax.lax.stop_gradient(pos), jax.lax.stop_gradient(nrm)
    nr, na = nodes or _COVER_NODES
    dirs, w, spacing = _cover_nodes(geom, pair, pos, nrm, (nr, na))
    sigma = jnp.clip(_BLUR * spacing, 1e-3, 0.5)
    # the nodes in groups of whole rings of about _COVER_GROUP nodes, one after the other: the
    # march's taps of every node at once outgrow the caches (2.25 times the nodes cost 4.6
    # times the time)
    per = max(1, min(nr, _COVER_GROUP // na))
    groups = -(-nr // per)
    q = per * na
    pad = groups * q - nr * na

    def group(args: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, jax.Array]:
        d, ww = args
        _, hit = _march(geom, pair, pos, d, steps=steps)
        wh = jax.lax.stop_gradient(ww * hit)
        lv = _env_blur(env, d, jnp.broadcast_to(sigma[:, None], hit.shape))  # (N, q, r)
        return jnp.sum(wh, -1), jnp.einsum("nq,nqc->nc", wh, lv)

    if groups == 1:
        omega, hidden = group((dirs, w))
    else:
        d = jnp.pad(dirs, ((0, 0), (0, pad), (0, 0)), constant_values=1.0)
        ww = jnp.pad(w, ((0, 0), (0, pad)))
        d = jnp.moveaxis(_normalize(d).reshape(-1, groups, q, 3), 1, 0)
        ww = jnp.moveaxis(ww.reshape(-1, groups, q), 1, 0)
        om, hd = jax.lax.map(group, (d, ww))
        omega, hidden = jnp.sum(om, 0), jnp.sum(hd, 0)
    return omega, hidden / math.pi

