"""Rays against a neighbour's pass-1 depth map (:func:`_march`): where a ray from a receiver
first meets the sender of a pair, from the pair's orthographic raster of the sender (its
coverage, front-surface height along the pair's axis and the depth of the solid behind it,
``IRGeometry.s_front``). Used by the gloss/mirror quadrature (the lobe's node rays) and by
the diffuse transfer's coverage (:func:`_cone_coverage`: the projected solid angle of a
neighbour seen from a point, which the sender's samples, made along the pair's axis,
underestimate where the point sees the neighbour from another side).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from ...lighting import dot3
from ._pass1 import SUPERSAMPLE, IRGeometry, _normalize

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


def _march(geom: IRGeometry, pair: jax.Array, pos: jax.Array, dirs: jax.Array
           ) -> tuple[jax.Array, jax.Array]:
    """Where the rays (pos (N, 3), dirs (N, Q, 3)) first meet the sender of ``pair`` (N,):
    the ray parameter t (N, Q) (m) and whether they do (N, Q) float. The sender is its pass-1
    raster (``geom.s_front``: coverage, front-surface height along the pair's axis and the
    depth of the solid behind it, at the raster's full resolution, bilinear; covered where
    the interpolated coverage exceeds ½, the silhouette to a fraction of a texel): the ray
    is stepped ``_MARCH_STEPS`` times over its chord of the sender's bounding sphere, and
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
    k = (jnp.arange(_MARCH_STEPS, dtype=pos.dtype) + 0.5) / _MARCH_STEPS
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
    step = (t1 - t0)[..., None] / _MARCH_STEPS
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



#: the cone quadrature of :func:`_cone_coverage`: rings (uniform in cos θ) × azimuths
_CONE_NODES = (8, 16)


def _cone_coverage(geom: IRGeometry, pair: jax.Array, pos: jax.Array, nrm: jax.Array
                   ) -> jax.Array:
    """(N,) the projected solid angle ∫ max(0, n·ω) hit(ω) dω (sr) of the sender of ``pair``
    (N,) seen from points ``pos`` (N, 3) with unit normals ``nrm`` (N, 3): a stratified
    quadrature over the cone of the sender's bounding sphere (the whole sphere of directions
    from inside it), each node ray marched through the sender's depth map (:func:`_march`).
    Geometry only: no gradient flows through it."""
    pos, nrm = jax.lax.stop_gradient(pos), jax.lax.stop_gradient(nrm)
    nr, na = _CONE_NODES
    oc = geom.centre_j[pair] - pos
    d = jnp.sqrt(jnp.maximum(dot3(oc, oc), 1e-30))
    axis = oc / d[:, None]
    cos_a = jnp.sqrt(jnp.maximum(1.0 - (geom.radius_j[pair] / d) ** 2, 0.0))  # 0 inside
    cos_a = jnp.where(d > geom.radius_j[pair], cos_a, -1.0)
    t = jnp.where(jnp.abs(axis[:, 0:1]) < 0.9, jnp.asarray([[1.0, 0.0, 0.0]], pos.dtype),
                  jnp.asarray([[0.0, 1.0, 0.0]], pos.dtype))
    e1 = _normalize(jnp.cross(axis, t))
    e2 = jnp.cross(axis, e1)
    u = (jnp.arange(nr, dtype=pos.dtype) + 0.5) / nr  # (R,)
    ct = 1.0 - u[None] * (1.0 - cos_a[:, None])  # (N, R)
    st = jnp.sqrt(jnp.maximum(1.0 - ct * ct, 0.0))
    phi = (jnp.arange(na, dtype=pos.dtype) + 0.5) * (2.0 * math.pi / na)
    # every other ring turned by half a step (the nodes less aligned)
    phi = phi[None, :] + (jnp.arange(nr) % 2)[:, None] * (math.pi / na)  # (R, A)
    cp, sp = jnp.cos(phi), jnp.sin(phi)
    dirs = (ct[..., None, None] * axis[:, None, None]
            + (st[..., None] * cp[None])[..., None] * e1[:, None, None]
            + (st[..., None] * sp[None])[..., None] * e2[:, None, None])  # (N, R, A, 3)
    dirs = dirs.reshape(pos.shape[0], nr * na, 3)
    _, hit = _march(geom, pair, pos, dirs)
    dw = 2.0 * math.pi * (1.0 - cos_a) / (nr * na)
    return dw * jnp.sum(hit * jnp.maximum(dot3(dirs, nrm[:, None]), 0.0), -1)
