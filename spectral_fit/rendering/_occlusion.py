"""Objects of any shape lit by the environment they do not hide from themselves: self-occlusion
and self-interreflection of rigid meshes, precomputed in each object's own frame.

Precomputation (:func:`build_self_transfer`, NumPy, once per scene): each object's
:func:`~spectral_fit.geometry.self_visibility` (K = R² octahedral directions; convex objects
are recognised and skipped: nothing of theirs is hidden above a tangent plane) becomes

- ``weights`` W (V_o, K): Ω_k max(0, n_v·d_k) h_vk, the cosine-weighted solid angle of the
  directions the object hides from vertex v (h = 1 hidden);
- ``transfer`` T (V_o, P_o): where those directions land on the object, as shares of P_o
  patches (the vertices themselves up to ``MAX_PATCHES``, else groups of nearby vertices by
  farthest-point seeds): T_vp = Σ_k W_vk Σ_j b_vkj [patch(t_vk, j) = p], b the barycentrics of
  the hit point in the hit triangle t_vk;
- ``hidden`` (V, K) uint8 for lookups along any direction (bright sources, mirror directions).

Per frame (:func:`vertex_correction`, traced; every shape fixed by the meshes and R):

1. the environment along the K directions turned into the world by the object's pose: the
   residual map prefiltered to the directions' spacing (``env_level``), plus each bright
   source sub-point tested against the bilinear visibility of every vertex;
2. the hidden irradiance E_h(v) = W L + Σ_s (1 − vis_v(ω_s)) max(0, n_v·ω_s) Φ_s is taken off
   the irradiance of the vertex's normal (the irradiance map's, as the shading uses);
3. ``bounces`` Jacobi steps of the object's own diffuse light: E ← E₀ + T B(E), with
   B = α S(λ) E / π averaged per patch (area-weighted) — the light of the directions the object
   hides is its own diffuse radiance there (its gloss towards the receiver is left out);
4. the vertex's change of diffuse radiance α S (E − E_map)/π in the output channels (V, D),
   which the frame interpolates over the triangles and adds to the shading of its pixels.

The gloss and mirror terms are scaled per pixel by the visibility of the mirror direction
(:func:`own_reflection`: the pixel's triangle's three vertices, bilinear in the octahedral
map, blended by the pixel's barycentrics), and the hidden share reflects the object's own
diffuse radiance at the vertex nearest the hit instead, times β A(θr) + χ F (not in mode
"none", which is the direct light alone).

Errors: the hidden set is resolved to the directions' spacing (~0.15 rad at R = 24; the
cosine-weighted visible fraction of a hemispherical bowl's inside, ½ exactly, comes out within
±0.04 per vertex); the self-interreflection is diffuse only; visibility carries no gradient
(the correction is differentiable w.r.t. every material parameter).
"""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

__all__: list[str] = []

#: at most this many senders per object in the self-transfer (else patches of vertices)
MAX_PATCHES = 256


class SelfTransfer(eqx.Module):
    """The precomputed self-visibility and self-transfer of the scene's non-convex objects
    (object frames; see the module docstring).

    Attributes:
        directions: (K, 3) float32 object-frame directions.
        row: (V,) int32 row of each of ``prep.mesh``'s vertices in ``hidden`` and
            ``hit_vertex`` (−1 for the vertices of convex objects).
        hidden: (V', K) uint8, the listed objects' vertices one object after another.
        hit_vertex: (V', K) int32 the vertex (an index into ``prep.mesh``) of the hit
            triangle nearest the hit point where hidden, else the vertex itself.
        weights: per listed object (V_o, K) float32 Ω cos⁺ h.
        transfer: per listed object (V_o, P_o) float32.
        patch_of: per listed object (V_o,) int32 patch of each vertex.
        patch_share: per listed object (V_o,) float32 the vertex's share of its patch's area.
        objects: static indices of the listed (non-convex) objects.
        resolution: static R.
        env_level: static prefilter level of the environment along the directions.
    """

    directions: jax.Array
    row: jax.Array
    hidden: jax.Array
    hit_vertex: jax.Array
    weights: tuple[jax.Array, ...]
    transfer: tuple[jax.Array, ...]
    patch_of: tuple[jax.Array, ...]
    patch_share: tuple[jax.Array, ...]
    objects: tuple[int, ...] = eqx.field(static=True)
    resolution: int = eqx.field(static=True)
    env_level: int = eqx.field(static=True)


def _vertex_areas(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    a = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    out = np.zeros(len(v))
    for j in range(3):
        np.add.at(out, t[:, j], a / 3.0)
    return out


def _patches(v: np.ndarray, count: int) -> np.ndarray:
    """(V,) patch of each vertex: the nearest of ``count`` farthest-point seeds."""
    if count >= len(v):
        return np.arange(len(v), dtype=np.int32)
    seeds = [0]
    dist = np.linalg.norm(v - v[0], axis=1)
    for _ in range(count - 1):
        i = int(np.argmax(dist))
        seeds.append(i)
        dist = np.minimum(dist, np.linalg.norm(v - v[i], axis=1))
    s = v[np.asarray(seeds)]
    best = np.zeros(len(v), np.int32)
    bd = np.full(len(v), np.inf)
    for k in range(0, len(s), 256):
        d = np.linalg.norm(v[:, None] - s[None, k:k + 256], axis=-1)
        j = np.argmin(d, axis=1)
        dj = d[np.arange(len(v)), j]
        better = dj < bd
        best[better] = (k + j[better]).astype(np.int32)
        bd[better] = dj[better]
    return best


def env_level_for(env: Any, resolution: int) -> int:
    """The prefilter level of ``env`` whose std is nearest half the spacing of R² directions."""
    target = 0.5 * math.sqrt(4.0 * math.pi / resolution ** 2)
    sig = np.asarray(env.level_sigma, np.float64)
    return int(np.argmin(np.abs(sig - target)))


def build_self_transfer(vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray,
                        vertex_slices: list[tuple[int, int]],
                        triangle_slices: list[tuple[int, int]], env: Any, *,
                        resolution: int) -> SelfTransfer | None:
    """The :class:`SelfTransfer` of the scene's objects (concatenated mesh arrays and each
    object's vertex and triangle ranges; each object's
    :func:`~spectral_fit.geometry.self_visibility` over R = ``resolution`` directions per side,
    its default shadow maps), or None when every object is convex."""
    from ..geometry import octahedral_directions, self_visibility

    dirs, _ = octahedral_directions(resolution)
    row = np.full(len(vertices), -1, np.int32)
    hidden_rows, hit_rows = [], []
    objs, weights, transfers, patch_of, shares = [], [], [], [], []
    for o, ((a, b), (ta, tb)) in enumerate(zip(vertex_slices, triangle_slices, strict=True)):
        v = np.asarray(vertices[a:b], np.float64)
        t = np.asarray(triangles[ta:tb], np.int64) - a
        n = np.asarray(normals[a:b], np.float64)
        sv = self_visibility(v, t, n, resolution=resolution)
        if sv.convex or not sv.hidden.any():
            continue
        cos = np.clip(n @ sv.directions.T.astype(np.float64), 0.0, None)
        w = sv.solid_angle[None, :] * cos * sv.hidden
        p_of = _patches(v, MAX_PATCHES)
        n_p = int(p_of.max()) + 1
        area = _vertex_areas(v, t)
        patch_area = np.bincount(p_of, weights=area, minlength=n_p)
        share = area / np.maximum(patch_area[p_of], 1e-30)
        tr = np.zeros((len(v), n_p))
        rows, cols = np.nonzero(w > 0)
        hit = sv.hit_triangle[rows, cols]
        for j in range(3):
            np.add.at(tr, (rows, p_of[t[hit, j]]), w[rows, cols] * sv.hit_bary[rows, cols, j])
        row[a:b] = sum(len(h) for h in hidden_rows) + np.arange(b - a, dtype=np.int32)
        hidden_rows.append(sv.hidden.astype(np.uint8))
        near = np.take_along_axis(t[np.maximum(sv.hit_triangle, 0)],
                                  np.argmax(sv.hit_bary, axis=-1)[..., None], axis=-1)[..., 0]
        own = np.arange(b - a)[:, None]
        hit_rows.append((a + np.where(sv.hidden, near, own)).astype(np.int32))
        objs.append(o)
        weights.append(jnp.asarray(w, jnp.float32))
        transfers.append(jnp.asarray(tr, jnp.float32))
        patch_of.append(jnp.asarray(p_of, jnp.int32))
        shares.append(jnp.asarray(share, jnp.float32))
    if not objs:
        return None
    return SelfTransfer(jnp.asarray(dirs), jnp.asarray(row),
                        jnp.asarray(np.concatenate(hidden_rows)),
                        jnp.asarray(np.concatenate(hit_rows)), tuple(weights),
                        tuple(transfers), tuple(patch_of), tuple(shares), tuple(objs),
                        int(resolution), env_level_for(env, resolution))


def _to_object(model: jax.Array, d_world: jax.Array) -> jax.Array:
    """World directions (..., 3) into the object frame of ``model`` (4, 4), unit length."""
    from ..geometry import inverse_3x3

    d = d_world @ inverse_3x3(model[:3, :3]).T
    return d / jnp.maximum(jnp.linalg.norm(d, axis=-1, keepdims=True), 1e-30)


def _visible_along(hidden: jax.Array, d_obj: jax.Array, resolution: int) -> jax.Array:
    """Bilinear visibility (1 − hidden) of every vertex row of ``hidden`` (V, K) along
    object-frame directions ``d_obj`` (S, 3) → (V, S)."""
    from ..geometry import octahedral_taps

    idx, w = octahedral_taps(d_obj, resolution)  # (S, 4)
    h = hidden[:, idx.reshape(-1)].astype(jnp.float32).reshape(hidden.shape[0], *idx.shape)
    return 1.0 - jnp.einsum("vsk,sk->vs", h, w)


def vertex_correction(st: SelfTransfer, *, env: Any, lut: Any, mats: list[Any],
                      model: jax.Array, normals: jax.Array, world_normals: jax.Array,
                      vertex_slices: tuple[tuple[int, int], ...], bounces: int,
                      to_out: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The change (V, D) of every vertex's diffuse radiance in the output channels of
    ``to_out`` (C, D) that its own object's shape makes (hidden environment, own diffuse
    light; rows of convex objects 0), and that diffuse radiance itself (V, D) (0 for convex
    objects). ``normals`` object-frame, ``world_normals`` (V, 3) world; ``lut`` the frame's
    irradiance map table (or None: the environment's own irradiance)."""
    from ..lighting import lookup_level
    from ._shading import _filtered_irradiance, _irradiance_at, _lut_env

    d_out = int(to_out.shape[1])
    v_total = normals.shape[0]
    src_map = env.source_dirs.reshape(-1, 3)  # (S·k, 3) map frame
    src_world = src_map @ env.rotation.T
    src_flux = jnp.repeat(env.source_flux, env.source_dirs.shape[1], axis=0)  # (S·k, r)
    table = None if lut is None else _lut_env(env, lut)
    out = jnp.zeros((v_total, d_out), jnp.float32)
    own = jnp.zeros((v_total, d_out), jnp.float32)
    for i, o in enumerate(st.objects):
        a, b = vertex_slices[o]
        m = mats[o]
        rot = model[o][:3, :3]
        d_world = st.directions @ rot.T
        d_world = d_world / jnp.linalg.norm(d_world, axis=-1, keepdims=True)
        d_map = d_world @ env.rotation
        env_k = jax.vmap(lambda d: lookup_level(env, st.env_level, d))(d_map)  # (K, r)
        e_hidden_r = st.weights[i] @ env_k  # (V_o, r)
        if src_world.shape[0]:  # the bright sources each object hides from its vertices
            start = sum(int(w.shape[0]) for w in st.weights[:i])  # its rows, in order
            src_obj = _to_object(model[o], src_world)  # (S·k, 3)
            vis_s = _visible_along(st.hidden[start:start + (b - a)], src_obj,
                                   st.resolution)  # (V_o, S·k)
            cos_s = jnp.clip(normals[a:b] @ src_obj.T, 0.0, None)
            e_hidden_r = e_hidden_r + ((1.0 - vis_s) * cos_s) @ src_flux
        e_hidden = e_hidden_r @ env.spectral_basis  # (V_o, C)
        e_map = _irradiance_at(env, table, world_normals[a:b])
        e0 = e_map - e_hidden
        if env.product_tensor is None:  # bands: the grid's rounding may not make light negative
            e0 = jnp.maximum(e0, 0.0)
        e = e0
        if bounces:
            # the Jacobi steps e ← e0 + T B(e), B the patches' share-weighted diffuse radiance,
            # run on the patches: B is linear in e, so B_{k+1} = B(E0) + B(T_pp B_k) with
            # E0 and T_pp = T the patch shares of e0 and of T's rows (P × P: each step costs
            # P² instead of V × P); the vertices read the last B once
            n_p = st.transfer[i].shape[1]

            def patches(x: jax.Array, share: jax.Array = st.patch_share[i],
                        of: jax.Array = st.patch_of[i], n_p: int = n_p) -> jax.Array:
                return jax.ops.segment_sum(x * share[:, None], of, num_segments=n_p)

            t_pp = patches(st.transfer[i])  # (P, P)
            b0 = (m.alpha / math.pi) * _filtered_irradiance(m, env, patches(e0))  # (P, C)
            patch = b0
            for _ in range(bounces - 1):
                patch = b0 + (m.alpha / math.pi) * _filtered_irradiance(m, env, t_pp @ patch)
            e = e0 + st.transfer[i] @ patch
        delta = ((m.alpha / math.pi) * _filtered_irradiance(m, env, e - e_map)) @ to_out
        full = ((m.alpha / math.pi) * _filtered_irradiance(m, env, e)) @ to_out
        out = out.at[a:b].set(delta)
        own = own.at[a:b].set(full)
    return out, own


def own_reflection(st: SelfTransfer, *, model: jax.Array, vertex_object: jax.Array,
                   pixels: Any, triangles: jax.Array, clip: jax.Array, normal: jax.Array,
                   view: jax.Array, vertex_radiance: jax.Array | None
                   ) -> tuple[jax.Array, jax.Array | None]:
    """What each pixel's own object puts in its mirror direction: the visibility (N,) of the
    direction (1 where nothing of the object is in the way, and for convex objects), and the
    object's diffuse radiance seen there times the hidden share (N, D) (from
    ``vertex_radiance`` (V, D) at the vertex nearest each hit; None: not computed). Bilinear
    in the octahedral map at the three vertices of each listed pixel's triangle (``pixels`` a
    :class:`~spectral_fit.geometry.PixelList` over rows of ``triangles``, ``clip`` the
    vertices' clip positions), blended by the pixel's barycentrics
    (:func:`~spectral_fit.geometry.pixel_barycentrics`, as the frame interpolates its
    attributes). The visibility carries no gradient; the radiance does."""
    from ..geometry import pixel_barycentrics

    bary, tri = pixel_barycentrics(pixels, triangles, clip)  # (N, 3) each
    refl = 2.0 * jnp.sum(normal * view, -1, keepdims=True) * normal - view
    wt, rr, idx = _hidden_weights(st, model, vertex_object, pixels, bary, tri, refl)
    vis = 1.0 - jnp.sum(wt, axis=(1, 2))
    if vertex_radiance is None:
        return vis, None
    seen = jnp.einsum("njk,njkd->nd", wt, vertex_radiance[st.hit_vertex[rr, idx[:, None, :]]])
    return vis, seen


def _hidden_weights(st: SelfTransfer, model: jax.Array, vertex_object: jax.Array,
                    pixels: Any, bary: jax.Array, tri: jax.Array, dirs: jax.Array
                    ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Per pixel, how much of the world direction ``dirs`` (N, 3) its own object hides, as
    weights (N, 3, 4) over its triangle's vertices (barycentrics ``bary`` (N, 3), vertex
    indices ``tri`` (N, 3)) × the direction's four octahedral taps (their sum: the hidden
    share, 0 for convex objects); with the visibility rows (N, 3, 1) and taps (N, 4). No
    gradient (visibility)."""
    from ..geometry import octahedral_taps

    obj = vertex_object[tri[:, 0]]
    d_obj = jax.vmap(_to_object)(model[obj], dirs)
    idx, w = octahedral_taps(d_obj, st.resolution)  # (N, 4)
    rows = st.row[tri]  # (N, 3)
    listed = (rows >= 0) & (pixels.tri_id >= 0)[:, None]
    rr = jnp.maximum(rows, 0)[:, :, None]
    h = jnp.where(listed[:, :, None], st.hidden[rr, idx[:, None, :]].astype(jnp.float32), 0.0)
    return jax.lax.stop_gradient(bary[:, :, None] * h * w[:, None, :]), rr, idx


def neighbour_visibility(st: SelfTransfer, *, model: jax.Array, vertex_object: jax.Array,
                         pixels: Any, triangles: jax.Array, clip: jax.Array,
                         position: jax.Array, visible: jax.Array) -> jax.Array:
    """How much of the other objects each pixel's own object leaves in view (N,): the
    visibility of the direction towards each other object's centre (as :func:`own_reflection`
    reads its mirror direction's), averaged with weights 1/d² over the visible other
    objects (1 for convex objects). The light the neighbours exchange with a pixel
    (interreflection, and the environment they hide) is scaled by it: the inside of a cup
    receives nothing from a neighbour behind its wall. No gradient."""
    from ..geometry import pixel_barycentrics

    bary, tri = pixel_barycentrics(pixels, triangles, clip)
    obj = vertex_object[tri[:, 0]]
    centres = model[:, :3, 3]
    num = jnp.zeros(position.shape[:1], jnp.float32)
    den = jnp.zeros(position.shape[:1], jnp.float32)
    for k in range(model.shape[0]):
        d = centres[k][None] - position
        d2 = jnp.maximum(jnp.sum(d * d, -1), 1e-12)
        wk = jnp.where((obj != k) & visible[k], 1.0 / d2, 0.0)
        wt, _, _ = _hidden_weights(st, model, vertex_object, pixels, bary, tri,
                                   d * jax.lax.rsqrt(d2)[:, None])
        num = num + wk * (1.0 - jnp.sum(wt, axis=(1, 2)))
        den = den + wk
    return jax.lax.stop_gradient(jnp.where(den > 0.0, num / jnp.maximum(den, 1e-30), 1.0))
