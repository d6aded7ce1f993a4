"""Rays against a neighbour's pass-1 depth map (:func:`_march`): where a ray from a receiver
first meets the sender of a pair, from the pair's orthographic raster of the sender (its
coverage, front-surface height along the pair's axis and the depth of the solid behind it,
``IRGeometry.s_front``). Used by the gloss/mirror quadrature (the lobe's node rays) and by
the diffuse transfer (:func:`_cover`: the projected solid angle of a neighbour seen from a
point, which the sender's samples, made along the pair's axis, underestimate where the point
sees the neighbour from another side, and the environment the neighbour hides there).
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp

from ...lighting import EnvironmentMap, dot3, texel_directions, texel_solid_angles
from ._pass1 import _MAX_SLOPE, FRONT_CHANNELS, SUPERSAMPLE, IRGeometry, _normalize
from ._shading import _env_blur

__all__: list[str] = []


#: steps of the march of a lobe node's ray through the sender's depth map, over the ray's
#: chord of the sender's bounding sphere
_MARCH_STEPS = 16


def _depth_taps(pair: jax.Array, tx: jax.Array, ty: jax.Array, side: int
                ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Rows (..., 4) of the flattened (P·(side + 2)², ·) padded depth maps, bilinear
    weights (..., 4) at texel coordinates (tx, ty) (centres at integer + 0.5; outside: the
    zero border) and the offsets (..., 4) of (tx, ty) from each tap's centre along a row and
    down a column (texels)."""
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
    dx = jnp.stack([fx, fx - 1.0, fx, fx - 1.0], -1)
    dy = jnp.stack([fy, fy, fy - 1.0, fy - 1.0], -1)
    return idx, w, dx, dy


def _tap_sum(values: jax.Array, w: jax.Array) -> jax.Array:
    """Σ_i w_i v_i over the four taps (..., 4), unrolled (XLA:CPU runs a reduction over a
    short last axis as a slow loop). The values are gathered already: the march gathers the
    depth map's channels two at a time; :func:`~spectral_fit.lighting.taps_sum`'s gather per
    tap of three-channel rows made the plain march 2.4 times slower."""
    return (values[..., 0] * w[..., 0] + values[..., 1] * w[..., 1]
            + values[..., 2] * w[..., 2] + values[..., 3] * w[..., 3])


def _sender_box(geom: IRGeometry) -> jax.Array:
    """(P, 3, 2) the box, in each pair's frame about ``centre_j`` (s, u, the axis towards the
    receiver; low and high, m), that holds the covered texels of the sender's depth map and
    the axial range of its first solid layer, one texel wider on every side. Geometry only."""
    side = geom.gather_size * SUPERSAMPLE
    f = jax.lax.stop_gradient(geom.s_front).reshape(-1, side + 2, side + 2,
                                                    FRONT_CHANNELS)[:, 1:-1, 1:-1]
    hit = f[..., 0] > 0.0  # (P, side, side), rows from the top
    big = jnp.asarray(1e9, f.dtype)
    top = jnp.max(jnp.where(hit, f[..., 1], -big), (1, 2))
    bottom = jnp.min(jnp.where(hit, f[..., 1] - f[..., 2], big), (1, 2))
    idx = jnp.arange(side, dtype=f.dtype)
    cols, rows = jnp.any(hit, 1), jnp.any(hit, 2)  # (P, side)
    c_lo = jnp.min(jnp.where(cols, idx, side), 1)
    c_hi = jnp.max(jnp.where(cols, idx + 1.0, 0.0), 1)
    r_lo = jnp.min(jnp.where(rows, idx, side), 1)
    r_hi = jnp.max(jnp.where(rows, idx + 1.0, 0.0), 1)
    tex = 2.0 * geom.extent / side
    s_box = jnp.stack([-geom.extent + (c_lo - 1.0) * tex, -geom.extent + (c_hi + 1.0) * tex], -1)
    u_box = jnp.stack([geom.extent - (r_hi + 1.0) * tex, geom.extent - (r_lo - 1.0) * tex], -1)
    a_box = jnp.stack([bottom - tex, top + tex], -1)
    return jnp.stack([s_box, u_box, a_box], 1)


def _box_chord(box: jax.Array, org: list[jax.Array], dirs: list[jax.Array]
               ) -> tuple[jax.Array, jax.Array]:
    """Ray parameters (N, Q) where rays with origin coordinates ``org`` (3 × (N, 1)) and
    direction coordinates ``dirs`` (3 × (N, Q)) enter and leave the boxes ``box`` (N, 3, 2)
    (the slab method; far < near where a ray misses its box)."""
    near = jnp.full(dirs[0].shape, -jnp.inf, dirs[0].dtype)
    far = jnp.full(dirs[0].shape, jnp.inf, dirs[0].dtype)
    for a in range(3):
        lo, hi = box[:, a, 0:1], box[:, a, 1:2]
        flat = jnp.abs(dirs[a]) < 1e-12
        inv = 1.0 / jnp.where(flat, 1.0, dirs[a])
        ta, tb = (lo - org[a]) * inv, (hi - org[a]) * inv
        inside = (org[a] >= lo) & (org[a] <= hi)
        near = jnp.maximum(near, jnp.where(flat, jnp.where(inside, -jnp.inf, jnp.inf),
                                           jnp.minimum(ta, tb)))
        far = jnp.minimum(far, jnp.where(flat, jnp.where(inside, jnp.inf, -jnp.inf),
                                         jnp.maximum(ta, tb)))
    return near, far


def _front_surface(taps: jax.Array, w: jax.Array, dx: jax.Array, dy: jax.Array,
                   cov: jax.Array, texel: jax.Array) -> jax.Array:
    """The depth map's front-surface height (...) at a point from its four taps (..., 4, C)
    (``IRGeometry.s_front`` channels), bilinear weights ``w``, offsets ``dx``, ``dy`` from
    the taps' centres (..., 4) (texels; :func:`_depth_taps`), interpolated coverage ``cov``
    (...) and the texel's size (m, broadcast). Each covered tap's plane is extrapolated to the
    point; where the taps' slopes fall across them (a ridge, as every crease of a convex
    sender seen from outside) the height is the lowest of those planes, where they rise (a
    valley) the highest, and on a plane their bilinear blend: a crease is kept exactly, where
    bilinear heights cut it by up to a quarter texel times the change of slope (grazing rays
    then pass in front of a box's edge they hit) and a blend of the planes overshoots it by
    an eighth."""
    # covered taps whose face is not seen edge-on (an edge-on face's slope is clamped: its
    # plane does not bound the surface, and its height is not extrapolated); unrolled over
    # the four taps (XLA:CPU runs reductions over a short last axis as slow loops: the
    # reductions took three times the rest of the march)
    steep = _STEEP * texel
    big = jnp.asarray(1e9, taps.dtype)
    on, plane, gxs, gys = [], [], [], []
    for i in range(4):
        gx, gy = taps[..., i, 3], taps[..., i, 4]
        o = (taps[..., i, 0] > 0.5) & (jnp.abs(gx) < steep) & (jnp.abs(gy) < steep)
        on.append(o)
        gxs.append(gx)
        gys.append(gy)
        plane.append(taps[..., i, 1] + jnp.where(o, gx * dx[..., i] + gy * dy[..., i], 0.0))
    blend = _tap_sum(jnp.stack(plane, -1), w) / jnp.maximum(cov, 1e-6)
    low = functools.reduce(jnp.minimum, [jnp.where(on[i], plane[i], big) for i in range(4)])
    high = functools.reduce(jnp.maximum, [jnp.where(on[i], plane[i], -big) for i in range(4)])
    # the fall of the slope across the four edges between those taps
    falls = [jnp.where(on[a] & on[b], g[a] - g[b], 0.0)
             for g, a, b in ((gxs, 0, 1), (gxs, 2, 3), (gys, 0, 2), (gys, 1, 3))]
    tol = _CREASE * texel
    # a ridge where no edge rises, a valley where none falls (a saddle, or a smooth mesh's
    # facets turning both ways across the taps, keeps the blend)
    total = sum(falls)
    ridge = jnp.where(functools.reduce(jnp.minimum, falls) > -tol,
                      jnp.clip(total / tol, 0.0, 1.0), 0.0)
    valley = jnp.where(functools.reduce(jnp.maximum, falls) < tol,
                       jnp.clip(-total / tol, 0.0, 1.0), 0.0)
    any_on = on[0] | on[1] | on[2] | on[3]
    low, high = jnp.where(any_on, low, blend), jnp.where(any_on, high, blend)
    return blend + ridge * (low - blend) + valley * (high - blend)


#: a depth-map slope (height per texel / texel) at or above this one is clamped in pass 1
_STEEP = 0.99 * _MAX_SLOPE
#: a fall of the depth map's slopes across its taps (in height per texel, summed over their
#: four edges) of this many texels counts as a whole crease (:func:`_front_surface`)
_CREASE = 0.02


def _march(geom: IRGeometry, pair: jax.Array, pos: jax.Array, dirs: jax.Array, *,
           steps: int = _MARCH_STEPS, creases: bool = False, box: jax.Array | None = None
           ) -> tuple[jax.Array, jax.Array]:
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
    first layer through a second one (the far side of a ring) is not hit. With ``creases``
    the steps span only the chord inside the sender's box (``box``: :func:`_sender_box`,
    computed here when not given) and the front surface keeps its creases
    (:func:`_front_surface`)."""
    side = geom.gather_size * SUPERSAMPLE
    # the slopes only where the creases are kept (the environment a neighbour hides); the
    # lobe's rays read the bilinear heights (the slopes' taps and planes doubled the march)
    sf = geom.s_front.reshape(-1, FRONT_CHANNELS)
    # gathered as tables of at most two channels each: XLA:CPU gathers rows of one or two
    # floats several times faster per element than rows of three or five
    tables = [sf[:, 0:2], sf[:, 2:3]] + ([sf[:, 3:5]] if creases else [])
    cj = geom.centre_j[pair][:, None]  # (N, 1, 3)
    rj = geom.radius_j[pair][:, None]  # (N, 1)
    fr = geom.frame[pair]  # (N, 3, 3)
    ext = geom.extent[pair][:, None, None]
    oc = cj - pos[:, None]
    tp = dot3(oc, dirs)
    b2 = dot3(oc, oc) - tp * tp
    h2 = rj * rj - b2
    half = jnp.where(h2 > 0.0, jnp.sqrt(jnp.where(h2 > 0.0, h2, 1.0)), 0.0)  # (finite grads)
    rel0 = pos[:, None] - cj  # (N, 1, 3)
    org = [dot3(rel0, fr[:, None, a]) for a in range(3)]  # (N, 1) each
    step_dir = [dot3(dirs, fr[:, None, a]) for a in range(3)]  # (N, Q) each
    # the chord of the bounding sphere, clipped to the box of the sender's depth map (its
    # covered texels and the axial range of its first solid layer): the steps as fine as the
    # sender's own size allows (a slab's corner crossed by a grazing ray is a few mm long)
    t0 = jnp.maximum(tp - half, 0.0)
    t1 = jnp.maximum(tp + half, t0)
    if creases:
        box = _sender_box(geom) if box is None else box  # (the caller's, computed once)
        near, far = jax.lax.stop_gradient(_box_chord(box[pair], org, step_dir))
        t0_box, t1_box = jnp.maximum(t0, near), jnp.minimum(t1, far)
        ok = t1_box > t0_box  # (finite then; a ray that misses the box keeps the sphere's chord)
        t0, t1 = jnp.where(ok, t0_box, t0), jnp.where(ok, t1_box, t1)
        half = jnp.where(ok, half, 0.0)
    k = (jnp.arange(steps, dtype=pos.dtype) + 0.5) / steps
    t = t0[..., None] + (t1 - t0)[..., None] * k  # (N, Q, K)
    coord = [org[a][..., None] + t * step_dir[a][..., None]
             for a in range(3)]  # (N, Q, K) each: along s, u and the axis towards i
    tx = (coord[0] / ext + 1.0) * 0.5 * side
    ty = (1.0 - coord[1] / ext) * 0.5 * side
    idx, w, dx, dy = _depth_taps(jnp.broadcast_to(pair[:, None, None], tx.shape), tx, ty, side)
    taps = jnp.concatenate([tb[idx] for tb in tables], -1)  # (N, Q, K, 4, 5 or 3)
    cov = _tap_sum(taps[..., 0], w)
    if creases:
        surf = _front_surface(taps, w, dx, dy, cov, ext * (2.0 / side))
    else:
        surf = _tap_sum(taps[..., 1], w) / jnp.maximum(cov, 1e-6)
    depth = _tap_sum(taps[..., 2], w) / jnp.maximum(cov, 1e-6)
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


class BrightPoints(eqx.Module):
    """The bright part of an environment's residual map as points of equal flux (built by
    :func:`bright_points` once per frame): ``dirs`` (K, 3) world unit directions, ``flux``
    (K, r) radiance × solid angle (sr) in the map's r principal channels, and ``level`` ()
    the brightness (mean over the map's channels) above which a texel's excess belongs to
    the points; below it the map is left to the quadrature's nodes."""

    dirs: jax.Array
    flux: jax.Array
    level: jax.Array


#: a texel of the residual map brighter than this many times the map's mean brightness gives
#: its excess over that level to the bright points (:func:`bright_points`)
_BRIGHT = 4.0
#: at most this many texels (of the map's level 0) give their excess to the bright points
_BRIGHT_TEXELS = 512
#: bright points at receivers (the diffuse anchors of an image, ``diffuse_at="receivers"``)
_CONE_POINTS = 64


def bright_points(env: EnvironmentMap, count: int) -> BrightPoints:
    """``count`` points of equal flux that carry the bright part of the environment's residual
    map (level 0 of its atlas, its sources apart): every texel's excess brightness over
    ``_BRIGHT`` × the map's mean or over the ``_BRIGHT_TEXELS``-th brightest texel, whichever is
    higher, stratified along the texels' cumulative excess flux (in the map's rows), each
    point at its texel's centre with that texel's spectrum. The excess of a bright region of
    sky a neighbour's edge cuts is then shared by many rays (each marched as a node of
    :func:`_cover` is), where a node of the hemisphere's quadrature that flips from seen to
    hidden took a sixth of it at once. Which texels carry the points is not differentiable;
    their flux is, in the map."""
    h, w = env.level_shapes[0]
    off = env.level_offsets[0]
    lev = env.atlas[off:off + h * w]  # (H·W, r)
    b = _brightness(env, lev)
    dw = jnp.repeat(jnp.asarray(texel_solid_angles(h, 1)[:, 0] / w, lev.dtype), w)  # per row
    level = _BRIGHT * jnp.sum(jnp.maximum(b, 0.0) * dw) / (4.0 * math.pi)
    # at most _BRIGHT_TEXELS texels above the level: a compact bright region; a broad one (a
    # studio's softbox) is left to the nodes, which spread over it better than the points
    level = jax.lax.stop_gradient(jnp.maximum(level, _count_level(b, _BRIGHT_TEXELS)))
    excess = jnp.maximum(b - level, 0.0) * dw  # (H·W,) flux above the level
    cdf = jnp.cumsum(jax.lax.stop_gradient(excess))
    total = cdf[-1]
    at = (jnp.arange(count, dtype=lev.dtype) + 0.5) / count * total
    idx = jnp.clip(jnp.searchsorted(cdf, at), 0, h * w - 1)
    centres = jnp.asarray(texel_directions(h, w).reshape(-1, 3), lev.dtype)  # map frame
    dirs = centres[idx] @ env.rotation.T
    bt = b[idx]
    shape = lev[idx] / jnp.where(bt > 0.0, bt, 1.0)[:, None]  # (K, r): brightness 1
    flux = (jnp.sum(excess) / count) * shape
    return BrightPoints(dirs=dirs, flux=jnp.where(total > 0.0, flux, 0.0), level=level)


def _count_level(b: jax.Array, count: int, iterations: int = 30) -> jax.Array:
    """The lowest value (to 2⁻³⁰ of the range) that at most ``count`` entries of ``b`` (n,)
    exceed, by bisection (a top-k of the map sorted all its texels: a few ms a frame)."""
    b = jax.lax.stop_gradient(b)

    def halve(_: int, lo_hi: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, jax.Array]:
        lo, hi = lo_hi
        mid = 0.5 * (lo + hi)
        many = jnp.sum((b > mid).astype(jnp.int32)) > count
        return jnp.where(many, mid, lo), jnp.where(many, hi, mid)

    lo, hi = jnp.min(b), jnp.max(b)
    return jax.lax.fori_loop(0, iterations, halve, (lo, hi))[1]


def _brightness(env: EnvironmentMap, radiance: jax.Array) -> jax.Array:
    """(...) the brightness of radiance (..., r) in the map's principal channels: its mean
    over the map's own channels (the level of :func:`bright_points`)."""
    return radiance @ jnp.mean(env.spectral_basis, 1)


def _below_level(env: EnvironmentMap, radiance: jax.Array, level: jax.Array) -> jax.Array:
    """Radiance (..., r) scaled down to the brightness ``level`` where it is brighter (the
    part the bright points leave to the nodes)."""
    b = _brightness(env, radiance)
    return radiance * jnp.minimum(1.0, level / jnp.maximum(b, 1e-30))[..., None]


def _cover(geom: IRGeometry, env: EnvironmentMap, pair: jax.Array, pos: jax.Array,
           nrm: jax.Array, *, nodes: tuple[int, int] | None = None,
           steps: int = _MARCH_STEPS, bright: BrightPoints | None = None,
           creases: bool = False) -> tuple[jax.Array, jax.Array]:
    """What the sender of ``pair`` (N,) takes from the sky of points ``pos`` (N, 3) with unit
    normals ``nrm`` (N, 3): its projected solid angle Ω (N,) (sr)
    and the environment it hides, (1/π) ∫ max(0, n·ω) hit(ω) L_env(ω) dω (N, r) in the map's
    r principal channels (``nodes``, default ``_COVER_NODES``, :func:`_cover_nodes`;
    ``steps`` of the march). Without ``bright`` each node's radiance is prefiltered to
    ``_BLUR`` of the nodes' spacing (a wider prefilter carries the light of the seen
    directions beside the neighbour's edge into the hidden nodes: a third more hidden light
    beside a cup under a bright band of sky). With ``bright`` (:func:`bright_points`) the
    nodes read the map's own texels up to its level and the points' rays, marched alike,
    the rest (a prefiltered map cut at the level would count a bright region's halo twice).
    The hits come from the sender's depth map (:func:`_march`), so the sender's actual shape
    hides the sky, not its bounding sphere nor the few sender samples a near point sees at
    grazing angles.
    Geometry only for the hits (no gradient); the radiance is differentiable in the map."""
    pos, nrm = jax.lax.stop_gradient(pos), jax.lax.stop_gradient(nrm)
    nr, na = nodes or _COVER_NODES
    dirs, w, spacing = _cover_nodes(geom, pair, pos, nrm, (nr, na))
    sigma = jnp.clip(_BLUR * spacing, 1e-3, 0.5)
    box = _sender_box(geom) if creases else None  # once, not per group of nodes
    if bright is not None:  # the map's own texels, so that the level cuts what the points take
        sigma = jnp.full_like(sigma, 1e-3)
    # the nodes in groups of whole rings of about _COVER_GROUP nodes, one after the other: the
    # march's taps of every node at once outgrow the caches (2.25 times the nodes cost 4.6
    # times the time)
    per = max(1, min(nr, _COVER_GROUP // na))
    groups = -(-nr // per)
    q = per * na
    pad = groups * q - nr * na

    def group(args: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, jax.Array]:
        d, ww = args
        _, hit = _march(geom, pair, pos, d, steps=steps, creases=creases, box=box)
        wh = jax.lax.stop_gradient(ww * hit)
        lv = _env_blur(env, d, jnp.broadcast_to(sigma[:, None], hit.shape))  # (N, q, r)
        if bright is not None:
            lv = _below_level(env, lv, bright.level)
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
    if bright is not None:
        bd = jnp.broadcast_to(bright.dirs, (pos.shape[0], *bright.dirs.shape))
        _, hit = _march(geom, pair, pos, bd, steps=steps, creases=creases, box=box)
        wh = jax.lax.stop_gradient(hit * jnp.maximum(dot3(bd, nrm[:, None]), 0.0))  # (N, K)
        hidden = hidden + wh @ bright.flux
    return omega, hidden / math.pi

