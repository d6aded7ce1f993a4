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
   hides is its own radiance there: diffuse, plus what its gloss and mirror send towards the
   receiver (:func:`_gloss_irradiance`, :func:`_own_gloss`: per pair of ``GLOSS_PATCHES``
   patches and bin of the angle at the sender, the environment along the sender's mirror
   direction where the object leaves it open, else the object's own light there: its diffuse
   radiance and the gloss the patch met sends back, :func:`_own_gloss`);
4. the vertex's change of diffuse radiance α S (E − E_map)/π in the output channels (V, D),
   which the frame interpolates over the triangles and adds to the shading of its pixels.

The gloss and mirror terms are scaled per pixel by the visibility of the mirror direction,
the gloss lobe's read at three directions over it (:func:`own_reflection`: the pixel's
triangle's three vertices, bilinear in the octahedral map, blended by the pixel's
barycentrics), and the hidden share reflects the object's own
light instead, times β A(θr) + χ F: the diffuse radiance at the vertex nearest the hit and
the gloss the hit's patch sends towards the pixel's (not in mode "none", which is the direct
light alone).

Errors: the hidden set is resolved to the directions' spacing (~0.15 rad at R = 24; the
cosine-weighted visible fraction of a hemispherical bowl's inside, ½ exactly, comes out within
±0.04 per vertex); the gloss part of the self-transfer is 0.8–1.3 of ray casting per vertex
inside a mirroring integrating sphere (48 patches, 3 angle bins, the sky reflected once; twice:
0.9–1.25); visibility carries no gradient
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
#: patches per object of the self-transfer's gloss (senders and receivers: their pairs are
#: shaded every frame)
GLOSS_PATCHES = 48
#: bins of cosθ at the sender in the self-transfer's gloss
GLOSS_BINS = np.array([0.0, 0.3, 0.6, 1.0 + 1e-6])
#: the refractive index whose Fresnel factor picks a triple's representative angle
NOMINAL_N = 1.5


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
        patch_transfer: per listed object (P_o, P_o) float32 ``transfer``'s rows averaged
            over each patch (area shares): the Jacobi steps' patch-to-patch transfer.
        gloss_transfer: per listed object (N_o,) float32 the nonzero entries T_vq of
            ``transfer`` over the object's G_o gloss patches (V_o × G_o, sparse: a vertex's
            hidden directions land on a few of them).
        gloss_transfer_at: per listed object (N_o, 2) int32 each entry's vertex v and pair
            p·G_o + q (p the vertex's own gloss patch, q where its hidden directions land),
            sorted by v.
        gloss_normal: per listed object (G_o, 3) float32 each gloss patch's mean normal.
        gloss_pair: per listed object (U_o,) int32 the pair p·G_o + q (receiver patch p,
            sender q) of each of the U_o (pair, angle bin) triples that carry light: per
            pair, the hidden directions' angles at the sender fall into bins of cosθ
            (``GLOSS_BINS``), and a bin that none falls into carries nothing.
        gloss_share: per listed object (U_o,) float32 the triple's bin's share of the pair's
            transfer.
        gloss_view: per listed object (U_o, 3) float32 a direction from sender q towards
            receiver patch p (the pair's mean azimuth) at the angle whose Fresnel factor is
            the mean of the triple's directions that land on the object (object frame): the
            angle of the albedo with which q reflects the object's own light.
        gloss_visible: per listed object (U_o,) float32 how much of the triple's mirror
            directions leave the object: each hidden direction of the pair mirrored about the
            normal of the vertex it meets, that vertex's bilinear visibility of it, weighted as
            the transfer.
        gloss_hit: per listed object (U_o, G_o) float32 where that mirror direction lands on
            the object instead, as shares of the gloss patches (each row sums to
            1 − ``gloss_visible``).
        gloss_from_patch: per listed object (G_o, P_o) float32 each gloss patch's area shares
            of the patches (a patch radiance's mean over a gloss patch).
        gloss_to_patches: per listed object (P_o, U_o) float32 what radiance sent along each
            triple adds to the patches' irradiance (the vertices' gloss irradiance,
            :func:`_gloss_to_vertices`, averaged over each patch as the Jacobi steps do).
        gloss_next: per listed object (H_o, 2) int32, for each of the H_o nonzero shares of
            ``gloss_hit`` (u, g) whose hit sends light back, sorted by u: the triple u and the
            triple whose radiance arrives along that share: the hit patch g sending towards
            u's sender q, in the bin of the angle at g: the gloss of the hit, reflected again by
            the sender (the light a cup's walls pass on from wall to wall). Sparse, as most of
            a triple's mirror directions leave the object or land on a few patches.
        gloss_next_share: per listed object (H_o,) float32 those shares of ``gloss_hit``.
        gloss_open_view: per listed object (U_o, 3) float32 the view of the environment the
            triple sends: mirrored about ``gloss_normal[q]``, the mean of the mirror directions
            of the triple's hidden directions (each about its own hit's normal) weighted by how
            much of each leaves the object (``gloss_view`` where none does).
        gloss_slot: (V,) int32 each of ``prep.mesh``'s vertices' gloss patch, numbered over
            the listed objects one after another (−1 for the vertices of convex objects).
        gloss_triple: (G, G, J) int32 the triple (receiver slot, sender slot, bin of the angle
            at the sender) in the listed objects' triples one object after another (its U
            rows), the nearest bin that carries light where the bin itself carries none, and U
            where the pair carries none (two objects, or patches that never see each other).
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
    patch_transfer: tuple[jax.Array, ...]
    gloss_transfer: tuple[jax.Array, ...]
    gloss_transfer_at: tuple[jax.Array, ...]
    gloss_normal: tuple[jax.Array, ...]
    gloss_pair: tuple[jax.Array, ...]
    gloss_share: tuple[jax.Array, ...]
    gloss_view: tuple[jax.Array, ...]
    gloss_visible: tuple[jax.Array, ...]
    gloss_hit: tuple[jax.Array, ...]
    gloss_from_patch: tuple[jax.Array, ...]
    gloss_to_patches: tuple[jax.Array, ...]
    gloss_next: tuple[jax.Array, ...]
    gloss_next_share: tuple[jax.Array, ...]
    gloss_open_view: tuple[jax.Array, ...]
    gloss_slot: jax.Array
    gloss_triple: jax.Array
    objects: tuple[int, ...] = eqx.field(static=True)
    resolution: int = eqx.field(static=True)
    env_level: int = eqx.field(static=True)


def _vertex_areas(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    a = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    out = np.zeros(len(v))
    for j in range(3):
        np.add.at(out, t[:, j], a / 3.0)
    return out


def _patch_features(v: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(V, 6) what groups vertices into patches: position and normal times half the
    object's bounding radius, so that the two sides of a thin wall (a cup's inside and
    outside, 4 mm apart and facing away) fall into different patches."""
    r = float(np.linalg.norm(v - v.mean(axis=0), axis=1).max())
    return np.concatenate([v, 0.5 * r * n], axis=1)


def _patches(v: np.ndarray, count: int) -> np.ndarray:
    """(V,) patch of each row of ``v`` (V, F) (vertex features): the nearest of ``count``
    farthest-point seeds."""
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
    gloss: list[tuple[np.ndarray, ...]] = []
    gloss_of: list[np.ndarray] = []
    for o, ((a, b), (ta, tb)) in enumerate(zip(vertex_slices, triangle_slices, strict=True)):
        v = np.asarray(vertices[a:b], np.float64)
        t = np.asarray(triangles[ta:tb], np.int64) - a
        n = np.asarray(normals[a:b], np.float64)
        sv = self_visibility(v, t, n, resolution=resolution)
        if sv.convex or not sv.hidden.any():
            continue
        cos = np.clip(n @ sv.directions.T.astype(np.float64), 0.0, None)
        w = sv.solid_angle[None, :] * cos * sv.hidden
        feat = _patch_features(v, n)
        p_of = _patches(feat, MAX_PATCHES)
        n_p = int(p_of.max()) + 1
        area = _vertex_areas(v, t)
        patch_area = np.bincount(p_of, weights=area, minlength=n_p)
        share = area / np.maximum(patch_area[p_of], 1e-30)
        tr = np.zeros((len(v), n_p))
        rows, cols = np.nonzero(w > 0)
        hit = sv.hit_triangle[rows, cols]
        for j in range(3):
            np.add.at(tr, (rows, p_of[t[hit, j]]), w[rows, cols] * sv.hit_bary[rows, cols, j])
        t_pp = np.zeros((n_p, n_p))
        np.add.at(t_pp, p_of, share[:, None] * tr)
        g_of = _patches(feat, GLOSS_PATCHES)
        gloss_of.append(g_of)
        gloss.append((t_pp.astype(np.float32),
                      *_gloss_used(*_gloss_pairs(v, n, area, sv, w, rows, cols, t, hit, g_of),
                                   p_of=p_of, vertex_share=share, area=area)))
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
    tables = [g[-1] for g in gloss]
    per_object = (tuple(jnp.asarray(x) for x in col)
                  for col in zip(*(g[:-1] for g in gloss), strict=True))
    slot, triple = _gloss_slots(tables, [len(g[4]) for g in gloss],
                                [vertex_slices[o] for o in objs], gloss_of,
                                len(vertices))
    return SelfTransfer(jnp.asarray(dirs), jnp.asarray(row),
                        jnp.asarray(np.concatenate(hidden_rows)),
                        jnp.asarray(np.concatenate(hit_rows)), tuple(weights),
                        tuple(transfers), tuple(patch_of), tuple(shares), *per_object,
                        jnp.asarray(slot), jnp.asarray(triple),
                        tuple(objs), int(resolution), env_level_for(env, resolution))


def _gloss_slots(tables: list[np.ndarray], counts: list[int], slices: list[tuple[int, int]],
                 g_ofs: list[np.ndarray], v_total: int) -> tuple[np.ndarray, np.ndarray]:
    """:class:`SelfTransfer`'s ``gloss_slot`` (V,) and ``gloss_triple`` (G, G, J) from each
    listed object's triple table (G_o, G_o, J) (local triples, U_o = ``counts`` where none),
    vertex range and gloss patches (V_o,)."""
    n_j = len(GLOSS_BINS) - 1
    n_total = sum(t.shape[0] for t in tables)
    u_total = sum(counts)
    slot = np.full(v_total, -1, np.int32)
    triple = np.full((n_total, n_total, n_j), u_total, np.int32)
    g0 = u0 = 0
    for tab, u_o, (a, b), g_of in zip(tables, counts, slices, g_ofs, strict=True):
        n_g = tab.shape[0]
        slot[a:b] = g0 + g_of
        triple[g0:g0 + n_g, g0:g0 + n_g] = np.where(tab < u_o, u0 + tab, u_total)
        g0, u0 = g0 + n_g, u0 + u_o
    return slot, triple


def _gloss_used(tg: np.ndarray, g_of: np.ndarray, normal: np.ndarray, share: np.ndarray,
                view: np.ndarray, visible: np.ndarray, lands: np.ndarray,
                land_bin: np.ndarray, open_view: np.ndarray, *, p_of: np.ndarray,
                vertex_share: np.ndarray, area: np.ndarray) -> tuple[np.ndarray, ...]:
    """:func:`_gloss_pairs`' arrays (``tg`` (V, G), ``g_of`` (V,), ``normal`` (G, 3) and, per
    (pair, bin), ``share`` (G, G, J), ``view`` (G, G, J, 3), ``visible`` (G, G, J), ``lands``
    (G·G·J, G), ``land_bin`` (G·G·J, G) the bin of the angle at each landing patch,
    ``open_view`` (G, G, J, 3) the view of the environment the triple sends) kept for
    the U triples that carry light, with the maps from the gloss patches to the P patches
    ``p_of`` (V,) (``vertex_share`` (V,): each vertex's area share of its patch; ``area``
    (V,)): the :class:`SelfTransfer` fields from ``gloss_transfer`` to ``gloss_open_view``, and
    the object's triple table (G, G, J) (:func:`_triple_table`)."""
    n_g = normal.shape[0]
    n_j = share.shape[-1]
    n_p = int(p_of.max()) + 1
    used = np.flatnonzero(share.reshape(-1) > 0)  # (U,) flat (p, q, j)
    pair = (used // n_j).astype(np.int32)
    p_u, q_u = pair // n_g, pair % n_g
    s_u = share.reshape(-1)[used]
    from_patch = np.zeros((n_g, n_p))
    np.add.at(from_patch, (g_of, p_of), area)
    from_patch /= np.maximum(from_patch.sum(axis=1, keepdims=True), 1e-30)
    # patches' share-weighted sum of the vertices' Σ_q T_vq (per pair p(v), q): (P, G, G)
    by_pair = np.zeros((n_p, n_g, n_g))
    np.add.at(by_pair, (p_of, g_of), vertex_share[:, None] * tg.astype(np.float64))
    to_patches = by_pair[:, p_u, q_u] * s_u[None]
    table = _triple_table(share)
    # the radiance arriving at sender q from where its mirror direction lands (patch g): g's
    # own triple towards q, in the bin of the angle there
    nxt = table[q_u[:, None], np.arange(n_g)[None], land_bin[used]]  # (U, G); U: none
    hits = lands[used]
    u_of, g_at = np.nonzero((hits > 0) & (nxt < len(used)))  # row-major: sorted by u
    f32 = np.float32
    v_at, q_at = np.nonzero(tg)  # row-major: sorted by the vertex
    return (tg[v_at, q_at].astype(f32),
            np.stack([v_at, g_of[v_at] * n_g + q_at], axis=-1).astype(np.int32),
            normal.astype(f32), pair, s_u.astype(f32),
            view.reshape(-1, 3)[used].astype(f32), visible.reshape(-1)[used].astype(f32),
            hits.astype(f32), from_patch.astype(f32), to_patches.astype(f32),
            np.stack([u_of, nxt[u_of, g_at]], axis=-1).astype(np.int32),
            hits[u_of, g_at].astype(f32), open_view.reshape(-1, 3)[used].astype(f32), table)


def _triple_table(share: np.ndarray) -> np.ndarray:
    """(G, G, J) int32 the index among the triples that carry light (``share`` (G, G, J) > 0,
    in flat order) of each (receiver, sender, bin); where that bin carries none, the pair's
    nearest bin that does; U (one past the last) where the pair carries none."""
    n_g, _, n_j = share.shape
    carries = share > 0
    index = np.cumsum(carries.reshape(-1)).reshape(share.shape) - 1
    u = int(carries.sum())
    out = np.full(share.shape, u, np.int64)
    for j in range(n_j):
        for k in sorted(range(n_j), key=lambda k: (abs(k - j), -k)):
            free = out[..., j] == u
            out[..., j] = np.where(free & carries[..., k], index[..., k], out[..., j])
    return out.astype(np.int32)


def _gloss_pairs(v: np.ndarray, n: np.ndarray, area: np.ndarray, sv: Any, w: np.ndarray,
                 rows: np.ndarray, cols: np.ndarray, t: np.ndarray, hit: np.ndarray,
                 g_of: np.ndarray) -> tuple[np.ndarray, ...]:
    """One object's gloss self-transfer over its G gloss patches ``g_of`` (V,) (see
    :class:`SelfTransfer`): the hidden directions (``rows``, ``cols``: vertex and direction
    of each; ``hit`` their hit triangles, rows of ``t`` (T, 3)) as shares of sender
    patches (V, G); each patch's mean normal (G, 3); per pair (receiver p, sender q) and
    bin j of the angle at the sender (J = len(GLOSS_BINS) − 1 bins of cosθ), the bin's share
    of the pair's transfer (G, G, J), a direction from q towards p (the pair's mean
    azimuth; the angle of the directions that land on the object, ``gloss_view``)
    (G, G, J, 3), the share of the mirror directions that leaves the object (G, G, J) and
    where the rest lands, as shares of the G patches (G·G·J, G) (:func:`_gloss_landing`),
    the bin of the angle at each landing patch (G·G·J, G), and the view of the environment
    the triple sends (G, G, J, 3) (``gloss_open_view``). Resolving cosθ matters: Fresnel
    rises steeply towards grazing angles, and the hits next to a receiver, all grazing, point
    every way about it (their mean direction is along the normal)."""

    n_g = int(g_of.max()) + 1
    n_j = len(GLOSS_BINS) - 1
    tg = np.zeros((len(v), n_g))
    d_hit = -sv.directions.astype(np.float64)[cols]  # from the hit back to the receiver
    toward = np.zeros((n_g, n_g, 3))
    cos_sum = np.zeros((n_g, n_g, n_j))
    bin_w = np.zeros((n_g, n_g, n_j))
    for j in range(3):
        wj = w[rows, cols] * sv.hit_bary[rows, cols, j]
        q = g_of[t[hit, j]]
        np.add.at(tg, (rows, q), wj)
        aw = wj * area[rows]
        np.add.at(toward, (g_of[rows], q), aw[:, None] * d_hit)
        c = np.clip(np.sum(d_hit * n[t[hit, j]], axis=1), 0.0, 1.0)
        k = _bin_of(c)
        np.add.at(bin_w, (g_of[rows], q, k), aw)
        np.add.at(cos_sum, (g_of[rows], q, k), aw * c)
    normal = np.zeros((n_g, 3))
    np.add.at(normal, g_of, area[:, None] * n)
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-30)
    total = bin_w.sum(axis=-1, keepdims=True)
    share = bin_w / np.maximum(total, 1e-30)
    mid = 0.5 * (GLOSS_BINS[:-1] + GLOSS_BINS[1:])
    cos_b = np.where(bin_w > 0, cos_sum / np.maximum(bin_w, 1e-30), mid)
    tang = toward - np.sum(toward * normal[None], -1, keepdims=True) * normal[None]
    axis = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    spare = np.broadcast_to(np.cross(normal, axis)[None], tang.shape)  # any tangent of q
    tang = np.where(np.linalg.norm(tang, axis=-1, keepdims=True) > 1e-9 * np.maximum(
        np.linalg.norm(toward, axis=-1, keepdims=True), 1e-30), tang, spare)
    tang /= np.maximum(np.linalg.norm(tang, axis=-1, keepdims=True), 1e-30)
    sin_b = np.sqrt(1.0 - cos_b ** 2)
    view = cos_b[..., None] * normal[None, :, None] + sin_b[..., None] * tang[:, :, None]
    mirror = 2.0 * cos_b[..., None] * normal[None, :, None] - view  # (G, G, J, 3)
    visible, lands, escape, cos_e, cos_l = _gloss_landing(n, area, sv, w, rows, cols, t, hit,
                                                          g_of)
    used = share > 0
    visible = np.where(used, visible, 0.0)
    lands = np.where(used[..., None], lands, 0.0)
    # the view whose mirror direction about q's normal leaves the object where the triple's
    # directions do (the environment the triple sends): their mean angle to the normal, the
    # azimuth of their mean (a mean of directions spread in azimuth points nearer the normal
    # than any of them); where none leaves, the bin's view
    nq = normal[None, :, None]
    e_t = escape - np.sum(escape * nq, -1, keepdims=True) * nq
    size = np.linalg.norm(e_t, axis=-1, keepdims=True)
    e_t = np.where(size > 1e-9, e_t / np.maximum(size, 1e-30), -tang[:, :, None])
    open_view = (cos_e[..., None] * nq
                 - np.sqrt(np.maximum(1.0 - cos_e ** 2, 0.0))[..., None] * e_t)
    open_view = np.where((visible > 0)[..., None], open_view, view)
    # the view of what the object sends back (its own light, reflected with the lobe's albedo
    # at this angle): the landing directions' Fresnel-matched angle, the pair's azimuth
    land_view = (cos_l[..., None] * nq
                 + np.sqrt(np.maximum(1.0 - cos_l ** 2, 0.0))[..., None] * tang[:, :, None])
    view = np.where((visible < 1)[..., None], land_view, view)
    # the angle at each landing patch between its normal and the way back to the sender
    back = np.clip(-(mirror.reshape(-1, 3) @ normal.T), 0.0, 1.0)  # (G·G·J, G)
    land_bin = _bin_of(back)
    f32 = np.float32
    return (tg.astype(f32), g_of.astype(np.int32), normal.astype(f32), share.astype(f32),
            view.astype(f32), visible.astype(f32), lands.reshape(-1, n_g).astype(f32),
            land_bin, open_view.astype(f32))


def _gloss_landing(n: np.ndarray, area: np.ndarray, sv: Any, w: np.ndarray,
                   rows: np.ndarray, cols: np.ndarray, t: np.ndarray, hit: np.ndarray,
                   g_of: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the gloss triples' mirror directions go, from the hidden directions themselves
    (``rows``, ``cols``, ``hit`` as :func:`_gloss_pairs`; weights ``w`` (V, K) times the
    receiver's ``area``): each direction from vertex v that meets the object at vertex h
    (the hit triangle's corner nearest the hit) is mirrored about h's normal, and h's
    visibility of the mirrored direction (bilinear in its octahedral map) says how much of it
    leaves the object, and where the rest lands (the hit triangles' corners, as gloss
    patches). Per triple (receiver patch, sender patch, bin of the angle at h) (G, G, J):
    the share that leaves, the shares that land (G, G, J, G), the mean leaving direction
    (G, G, J, 3) (weighted, not unit), and the cosines (G, G, J) whose Fresnel factor (at
    ``NOMINAL_N``) is the mean of the leaving directions' and of the landing ones' (at their
    angles to their normals; F is convex in cosθ, so the mean angle's would be low). Every
    direction of a pair counts with its own angle, so a triple whose few leaving directions
    point elsewhere than its mean (up, out of a cup's opening) sends the environment of
    those."""
    from ..geometry import octahedral_taps
    from ..lighting import fresnel_dielectric

    n_g = int(g_of.max()) + 1
    n_j = len(GLOSS_BINS) - 1
    h = t[hit, np.argmax(sv.hit_bary[rows, cols], axis=-1)]
    d = -sv.directions.astype(np.float64)[cols]  # from the hit back to the receiver
    c = np.clip(np.sum(d * n[h], axis=1), 0.0, 1.0)
    r = 2.0 * c[:, None] * n[h] - d
    r /= np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-30)
    u = (g_of[rows] * n_g + g_of[h]) * n_j + _bin_of(c)
    wt = w[rows, cols] * area[rows]
    idx, tw = (np.asarray(x) for x in octahedral_taps(r, sv.resolution))  # (S, 4)
    hid = sv.hidden[h[:, None], idx].astype(bool)
    leaves = 1.0 - np.sum(tw * hid, axis=1)
    m = n_g * n_g * n_j
    total = np.bincount(u, wt, minlength=m)
    visible = np.bincount(u, wt * leaves, minlength=m) / np.maximum(total, 1e-30)
    escape = np.stack([np.bincount(u, wt * leaves * r[:, k], minlength=m) for k in range(3)],
                      axis=-1)
    grid = np.linspace(0.0, 1.0, 257)
    f_grid = np.asarray(fresnel_dielectric(grid, NOMINAL_N), np.float64)  # falling
    f_c = np.interp(c, grid, f_grid)

    def matched(weight: np.ndarray) -> np.ndarray:
        f_mean = np.bincount(u, weight * f_c, minlength=m) / np.maximum(
            np.bincount(u, weight, minlength=m), 1e-30)
        return np.interp(f_mean, f_grid[::-1], grid[::-1]).reshape(n_g, n_g, n_j)

    cos_e, cos_l = matched(wt * leaves), matched(wt * (1.0 - leaves))
    lands = np.zeros((m, n_g))
    ss, kk = np.nonzero(hid)
    tri = t[sv.hit_triangle[h[ss], idx[ss, kk]]]
    bary = sv.hit_bary[h[ss], idx[ss, kk]]
    for corner in range(3):
        np.add.at(lands, (u[ss], g_of[tri[:, corner]]),
                  wt[ss] * tw[ss, kk] * bary[:, corner])
    lands /= np.maximum(total, 1e-30)[:, None]
    return (visible.reshape(n_g, n_g, n_j), lands.reshape(n_g, n_g, n_j, n_g),
            escape.reshape(n_g, n_g, n_j, 3), cos_e, cos_l)


def _bin_of(cos: Any) -> Any:
    """The bin of ``GLOSS_BINS`` (cosθ at a sender) of each cosine (NumPy or JAX arrays)."""
    xp = jnp if isinstance(cos, jax.Array) else np
    k = xp.searchsorted(xp.asarray(GLOSS_BINS[1:-1], cos.dtype), cos, side="right")
    return k.astype(xp.int32)


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
                      to_out: jax.Array, quality: str = "fast", split_map: Any = None,
                      split_settings: Any = None, tail: str = "none"
                      ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The change (V, D) of every vertex's diffuse radiance in the output channels of
    ``to_out`` (C, D) that its own object's shape makes (hidden environment, own diffuse
    light; rows of convex objects 0), that diffuse radiance itself (V, D) (0 for convex
    objects), and the radiance (U + 1, D) the objects' gloss and mirror send along their
    triples (``gloss_triple``'s rows; the last row 0, as every row without ``bounces``).
    ``normals`` object-frame, ``world_normals`` (V, 3) world; ``lut`` the frame's irradiance
    map table (or None: the environment's own irradiance). With ``bounces``, the
    light the object's own gloss and mirror send into its hidden directions is added first
    (:func:`_gloss_irradiance`; ``quality``, ``split_map``, ``split_settings`` as the
    frame's shading). ``tail="geometric"`` (with ``bounces`` >= 3) completes the object's own
    light after the last step: the steps of a power series shrink by the ratio q of its
    leading eigenvalue, so the rest sums to Δ q / (1 − q), Δ the last step and q the ratio of
    the last two steps' sums over the patches (per band; in basis mode of their norms),
    clipped to [0, 0.95]. A white cup's inside (albedo 0.9, 85 % of its view its own wall)
    needs some 16 steps otherwise."""
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
    sent = []
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
        glossy = jnp.zeros((st.gloss_pair[i].shape[0], d_out), jnp.float32)
        if bounces:
            # the light the object's gloss and mirror send along the triples: from the
            # environment (fixed) and from its own diffuse radiance (linear in B)
            spec, albedo = _gloss_irradiance(st, i, m, env, rot, quality=quality,
                                             split_map=split_map,
                                             split_settings=split_settings)

            # the Jacobi steps e ← e0 + G + T B(e), B the patches' share-weighted diffuse
            # radiance, G the gloss along the triples, run on the patches: B is linear in e,
            # so B_{k+1} = B(E0) + B(T_pp B_k) with E0 and T_pp = T the patch shares of e0 and
            # of T's rows (P × P: each step costs P² instead of V × P), the triples' light
            # reaching the patches by ``gloss_to_patches``; the vertices read the last B once.
            # The triples' radiance g = spec + own gloss of (B, g) steps along with B.
            to_p = st.gloss_to_patches[i]  # (P, U)
            e_p = jax.ops.segment_sum(e0 * st.patch_share[i][:, None], st.patch_of[i],
                                      num_segments=to_p.shape[0]) + to_p @ spec
            b0 = (m.alpha / math.pi) * _filtered_irradiance(m, env, e_p)  # (P, C)
            patch, sent_i = b0, spec
            steps = []
            for _ in range(bounces - 1):
                sent_i = spec + _own_gloss(st, i, albedo, patch, sent_i)
                e_own = st.patch_transfer[i] @ patch + to_p @ (sent_i - spec)
                new = b0 + (m.alpha / math.pi) * _filtered_irradiance(m, env, e_own)
                steps.append(new - patch)
                patch = new
            if tail == "geometric" and len(steps) >= 2:
                patch = patch + _series_rest(steps[-2], steps[-1],
                                             per_channel=env.product_tensor is None)
            sent_i = spec + _own_gloss(st, i, albedo, patch, sent_i)
            e = e0 + st.transfer[i] @ patch + _gloss_to_vertices(st, i, sent_i)
            glossy = sent_i @ to_out
        delta = ((m.alpha / math.pi) * _filtered_irradiance(m, env, e - e_map)) @ to_out
        full = ((m.alpha / math.pi) * _filtered_irradiance(m, env, e)) @ to_out
        out = out.at[a:b].set(delta)
        own = own.at[a:b].set(full)
        sent.append(glossy)
    return out, own, jnp.concatenate([*sent, jnp.zeros((1, d_out), jnp.float32)])


def _series_rest(prev: jax.Array, last: jax.Array, *, per_channel: bool) -> jax.Array:
    """What a converging power series adds after its ``last`` step (P, C), given the step
    before (``prev``): last · q / (1 − q), q = the steps' ratio (their sums over the rows per
    channel, or their norms), clipped to [0, 0.95]."""
    if per_channel:
        q = jnp.sum(last, 0) / jnp.maximum(jnp.sum(prev, 0), 1e-30)
    else:
        q = jnp.linalg.norm(last) / jnp.maximum(jnp.linalg.norm(prev), 1e-30)
    q = jnp.clip(q, 0.0, 0.95)
    return last * (q / (1.0 - q))


def _gloss_irradiance(st: SelfTransfer, i: int, m: Any, env: Any, rot: jax.Array, *,
                      quality: str, split_map: Any, split_settings: Any
                      ) -> tuple[jax.Array, jax.Array]:
    """What the listed object ``i``'s own gloss and mirror send along its U triples (see
    :class:`SelfTransfer`) from the environment, (U, C), and the senders' lobe albedo
    (U, 1) for :func:`_own_gloss`: the sender's gloss and mirror radiance
    (:func:`~._shading.specular_at`, the frame's shading) at its mean normal towards the
    triple's direction, times the share of its mirror direction the object leaves open; the
    albedo β A(θ) + χ F(θ) at that angle (:func:`~._shading.lobe_albedo`, as
    :func:`own_reflection` reflects the object's own light). ``rot`` (3, 3) the object's
    rotation. The walls of a cup pass the sky and each other's light on this way (Fresnel
    is large at the grazing angles between them)."""
    from ..lighting import lobe_moment_table
    from ._materials import mirror_needed
    from ._shading import lobe_albedo, specular_at

    n_g = st.gloss_normal[i].shape[0]
    senders = (st.gloss_normal[i] @ rot.T)[st.gloss_pair[i] % n_g]  # (U, 3)
    view = st.gloss_view[i] @ rot.T  # (U, 3)
    moments = lobe_moment_table(m.mu, m.n, settings=split_settings,
                                distribution=m.distribution, geometry=m.geometry)
    spec = specular_at(m, env, senders, st.gloss_open_view[i] @ rot.T, quality=quality,
                       split_map=split_map, split_settings=split_settings,
                       moments=moments)  # (U, C)
    nv = jnp.sum(senders * view, axis=-1, keepdims=True)  # (U, 1)
    albedo = lobe_albedo(m, moments, nv, mirror=mirror_needed([m]))
    return spec * st.gloss_visible[i][:, None], jnp.where(nv > 0.0, albedo, 0.0)


def _gloss_to_vertices(st: SelfTransfer, i: int, radiance: jax.Array) -> jax.Array:
    """The irradiance (V_o, C) of the listed object ``i``'s vertices from the radiance
    (U, C) its gloss patches send along the triples: Σ_q T_vq Σ_j s_pqj L_pqj, p the
    vertex's gloss patch, T ``gloss_transfer`` (sparse: ``gloss_transfer_at``), s
    ``gloss_share``."""
    n_g = st.gloss_normal[i].shape[0]
    pair = jax.ops.segment_sum(st.gloss_share[i][:, None] * radiance, st.gloss_pair[i],
                               num_segments=n_g * n_g)  # (G·G, C)
    at = st.gloss_transfer_at[i]
    return jax.ops.segment_sum(st.gloss_transfer[i][:, None] * pair[at[:, 1]], at[:, 0],
                               num_segments=st.weights[i].shape[0], indices_are_sorted=True)


def _own_gloss(st: SelfTransfer, i: int, albedo: jax.Array, patch: jax.Array,
               sent: jax.Array | None = None) -> jax.Array:
    """The radiance (U, C) the listed object ``i``'s gloss and mirror send along its triples
    from its own light: each sender reflects, with ``albedo`` (U, 1)
    (:func:`_gloss_irradiance`), what its mirror direction meets of the object
    (``gloss_hit``): the diffuse radiance ``patch`` (P_o, C) (per patch, averaged over the
    gloss patches) and, with ``sent`` (U, C) (the triples' radiance of the step before), the
    gloss of the patch it meets sent back towards the sender (``gloss_next``)."""
    seen = st.gloss_hit[i] @ (st.gloss_from_patch[i] @ patch)  # (U, C)
    if sent is not None:
        nxt = st.gloss_next[i]  # (H, 2): sparse, sorted by the receiving triple
        seen = seen + jax.ops.segment_sum(st.gloss_next_share[i][:, None] * sent[nxt[:, 1]],
                                          nxt[:, 0], num_segments=sent.shape[0],
                                          indices_are_sorted=True)
    return albedo * seen


def own_reflection(st: SelfTransfer, *, model: jax.Array, vertex_object: jax.Array,
                   pixels: Any, triangles: jax.Array, clip: jax.Array, normal: jax.Array,
                   view: jax.Array, vertex_radiance: jax.Array | None,
                   sent: jax.Array | None = None, object_normals: jax.Array | None = None,
                   mats: list[Any] | None = None, split_settings: Any = None
                   ) -> tuple[jax.Array, jax.Array | None]:
    """What each pixel's own object puts in its mirror direction: the visibility (N,) of the
    direction (1 where nothing of the object is in the way, and for convex objects), and the
    object's radiance seen there times the hidden share (N, D) (from ``vertex_radiance``
    (V, D), the diffuse radiance at the vertex nearest each hit, and with ``sent`` (U + 1, D)
    (:func:`vertex_correction`'s third value) and ``object_normals`` (V, 3) (object frame)
    the gloss and mirror of the hit's gloss patch towards the pixel's, in the bin of the angle
    at the hit; None: not computed). With ``mats`` (the objects' materials) the gloss lobe's
    visibility is read over the lobe (:func:`_lobe_directions`: 3 directions about its mean
    direction along the plane of incidence, spread by its angular variance there) and the
    mirror's along the mirror direction, the two blended by their albedos β A(θr) and
    χ F(θr); what hides the lobe is what hides the mirror direction, scaled to the lobe's
    hidden share. Without ``mats``, everything along the mirror direction. Bilinear
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
    seen = None
    if vertex_radiance is not None:
        hit = st.hit_vertex[rr, idx[:, None, :]]  # (N, 3, 4)
        radiance = vertex_radiance[hit]
        if sent is not None:
            back = -st.directions[idx]  # (N, 4, 3) from the hit towards the pixel, object frame
            cos = jnp.clip(jnp.einsum("njkc,nkc->njk", object_normals[hit], back), 0.0, 1.0)
            recv = jnp.maximum(st.gloss_slot[tri], 0)[:, :, None]
            radiance = radiance + sent[st.gloss_triple[recv, jnp.maximum(st.gloss_slot[hit], 0),
                                                       _bin_of(cos)]]
        seen = jnp.einsum("njk,njkd->nd", wt, radiance)
    if mats is None:
        return vis, seen
    obj = vertex_object[tri[:, 0]]
    w_gloss, w_mirror, dirs, w_dirs = _lobe_directions(mats, obj, normal, view,
                                                       split_settings=split_settings)
    vis_l = jnp.zeros_like(vis)
    for d, w in zip(dirs, w_dirs, strict=True):
        wt_d, _, _ = _hidden_weights(st, model, vertex_object, pixels, bary, tri, d)
        vis_l = vis_l + w * (1.0 - jnp.sum(wt_d, axis=(1, 2)))
    seen_l = None
    if seen is not None:  # what hides the mirror direction, for the lobe's hidden share
        hid_m = 1.0 - vis
        seen_l = seen * jnp.where(hid_m > 1e-3, (1.0 - vis_l) / jnp.maximum(hid_m, 1e-3),
                                  0.0)[:, None]
    total = w_gloss + w_mirror
    safe = jnp.where(total > 0.0, total, 1.0)
    g, m_ = jnp.where(total > 0.0, w_gloss / safe, 0.0), jnp.where(total > 0.0, w_mirror / safe,
                                                                   1.0)
    vis = g * vis_l + m_ * vis
    if seen is not None:
        seen = g[:, None] * seen_l + m_[:, None] * seen
    return vis, seen


#: nodes and weights of the 3-point Gauss–Hermite rule of a unit normal distribution
_HERMITE = ((-math.sqrt(3.0), 1.0 / 6.0), (0.0, 2.0 / 3.0), (math.sqrt(3.0), 1.0 / 6.0))


def _lobe_directions(mats: list[Any], obj: jax.Array, normal: jax.Array, view: jax.Array, *,
                     split_settings: Any
                     ) -> tuple[jax.Array, jax.Array, list[jax.Array], list[jax.Array]]:
    """Per pixel (object ``obj`` (N,), world ``normal`` and ``view`` (N, 3)): the albedos
    (N,) of its material's gloss β A(θr) and mirror χ F(θr), and 3 world directions (N, 3)
    with weights (N,) over its gloss lobe: the lobe's mean direction (the mirror direction
    tilted by the off-specular shift δ in the plane of incidence) moved by ±√3 σ and 0 within
    that plane, the lobe's long axis at grazing angles (σ² the lobe's angular variance
    there; 3-point Gauss–Hermite weights), those below the surface's horizon left out and
    the rest renormalised (the split sum's moments,
    :func:`~spectral_fit.lighting.split_sum_moments`). The directions carry no gradient; the
    albedos do."""
    from ..lighting import fresnel_dielectric, lobe_moment_table, split_sum_moments

    nv = jnp.clip(jnp.sum(normal * view, -1), 0.0, 1.0)
    mom = jnp.zeros((nv.shape[0], 4), jnp.float32)
    beta = jnp.zeros_like(nv)
    chi_f = jnp.zeros_like(nv)
    for o, m in enumerate(mats):
        table = lobe_moment_table(m.mu, m.n, settings=split_settings,
                                  distribution=m.distribution, geometry=m.geometry)
        mine = obj == o
        mom = jnp.where(mine[:, None], split_sum_moments(table, nv), mom)
        beta = jnp.where(mine, m.beta, beta)
        chi_f = jnp.where(mine, m.chi * fresnel_dielectric(nv, m.n), chi_f)
    w_gloss = beta * mom[:, 0]
    n_, v_ = jax.lax.stop_gradient(normal), jax.lax.stop_gradient(view)
    mom = jax.lax.stop_gradient(mom)
    refl = 2.0 * nv[:, None] * n_ - v_
    t = refl - jnp.sum(refl * n_, -1, keepdims=True) * n_
    spare = jnp.where(jnp.abs(n_[:, :1]) < 0.9, jnp.array([[1.0, 0.0, 0.0]]),
                      jnp.array([[0.0, 1.0, 0.0]]))
    spare = spare - jnp.sum(spare * n_, -1, keepdims=True) * n_
    size = jnp.linalg.norm(t, axis=-1, keepdims=True)
    t = jnp.where(size > 1e-6, t, spare)
    t = t / jnp.maximum(jnp.linalg.norm(t, axis=-1, keepdims=True), 1e-12)
    theta = jnp.arccos(jnp.clip(nv, 0.0, 1.0)) + mom[:, 1]
    c, s = jnp.cos(theta)[:, None], jnp.sin(theta)[:, None]
    mean = c * n_ + s * t
    along = -s * n_ + c * t
    sd_t = jnp.sqrt(jnp.maximum(mom[:, 2], 0.0))[:, None]
    dirs, weights = [], []
    for a, wa in _HERMITE:
        d = mean + a * sd_t * along
        d = d / jnp.maximum(jnp.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
        dirs.append(d)
        weights.append(jnp.where(jnp.sum(d * n_, -1) > 0.0, wa, 0.0))
    total = sum(weights)
    weights = [w / jnp.where(total > 0.0, total, 1.0) for w in weights]
    return w_gloss, chi_f, dirs, weights


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
                         position: jax.Array, visible: jax.Array,
                         bodies: tuple[int, ...] = ()) -> jax.Array:
    """How much of the other objects each pixel's own object leaves in view (N,): the
    visibility of the direction towards each other object's centre (as :func:`own_reflection`
    reads its mirror direction's), averaged with weights 1/d² over the visible other
    objects (1 for convex objects). The light the neighbours exchange with a pixel
    (interreflection, and the environment they hide) is scaled by it: the inside of a cup
    receives nothing from a neighbour behind its wall. Other parts of the pixel's own body
    (``bodies``: (O,) each object's body, () every object its own) are left out of the
    average: they exchange no light through the interreflection, and their centres lie
    inside the body (a cup's glaze), behind its own walls. No gradient."""
    from ..geometry import pixel_barycentrics

    bary, tri = pixel_barycentrics(pixels, triangles, clip)
    obj = vertex_object[tri[:, 0]]
    centres = model[:, :3, 3]
    num = jnp.zeros(position.shape[:1], jnp.float32)
    den = jnp.zeros(position.shape[:1], jnp.float32)
    body = jnp.asarray(bodies if bodies else range(model.shape[0]), jnp.int32)
    for k in range(model.shape[0]):
        d = centres[k][None] - position
        d2 = jnp.maximum(jnp.sum(d * d, -1), 1e-12)
        wk = jnp.where((body[obj] != body[k]) & visible[k], 1.0 / d2, 0.0)
        wt, _, _ = _hidden_weights(st, model, vertex_object, pixels, bary, tri,
                                   d * jax.lax.rsqrt(d2)[:, None])
        num = num + wk * (1.0 - jnp.sum(wt, axis=(1, 2)))
        den = den + wk
    return jax.lax.stop_gradient(jnp.where(den > 0.0, num / jnp.maximum(den, 1e-30), 1.0))
