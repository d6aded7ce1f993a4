"""The readings' measuring fields sampled by ray casting: the pixel rays of a square R×R
camera per reading (field of view = the field angle), kept inside the inscribed disc, and
their first hits on the scene's triangles (NumPy, float64; world units metres).
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import ObjectGeometry

__all__ = ["cast_rays", "disc_pixels", "scene_triangles"]


def disc_pixels(res: int) -> np.ndarray:
    """Flat indices of the R×R spot image's pixels whose centres lie inside the inscribed
    disc (the measuring field), row-major."""
    c = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    X, Y = np.meshgrid(c, -c)
    return np.flatnonzero((X ** 2 + Y ** 2 <= 1.0).reshape(-1))


def scene_triangles(geoms: list[ObjectGeometry]
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The scene's meshes as one: vertices (V, 3), normals (V, 3) (float64), triangles
    (T, 3) into them and each triangle's object (T,) int32."""
    verts = np.concatenate([np.asarray(g.vertices, np.float64) for g in geoms])
    norms = np.concatenate([np.asarray(g.normals, np.float64) for g in geoms])
    tris, tri_obj, base = [], [], 0
    for o, g in enumerate(geoms):
        t = np.asarray(g.triangles)
        tris.append(t + base)
        tri_obj.append(np.full(len(t), o, np.int32))
        base += len(np.asarray(g.vertices))
    return verts, norms, np.concatenate(tris), np.concatenate(tri_obj)


def cast_rays(bvh: Any, origin: np.ndarray, dirs: np.ndarray, verts: np.ndarray,
              norms: np.ndarray, tris: np.ndarray, tri_obj: np.ndarray, chunk: int = 4096,
              two_sided: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First hits of rays (N, 3) from one origin (3,): object (N,) (−1: none, −2: a
    triangle's back), position and unit normal (N, 3) (:func:`spectral_fit.geometry.closest_hit`
    through ``bvh``, the hierarchy over the scene's triangles ``tris`` with vertices
    ``verts``, normals ``norms`` and objects ``tri_obj`` (:func:`scene_triangles`); rays
    padded to whole chunks, one compiled size). ``two_sided``: a back counts like a front
    (its object, the normal turned towards the origin)."""
    N = dirs.shape[0]
    tri = np.full(N, -1)
    uv = np.zeros((N, 2))
    o = jnp.asarray(origin, jnp.float32)
    for a in range(0, N, chunk):
        d = dirs[a:a + chunk]
        n = d.shape[0]
        d = np.concatenate([d, np.repeat(d[-1:], chunk - n, 0)])
        h = _closest_hits(bvh, o, jnp.asarray(d, jnp.float32))
        tri[a:a + n] = np.asarray(h.triangle)[:n]
        uv[a:a + n] = np.stack([np.asarray(h.u), np.asarray(h.v)], -1)[:n]
    hit = tri >= 0
    idx = tris[np.maximum(tri, 0)]
    w = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], -1)
    p = np.einsum("pk,pkc->pc", w, verts[idx])
    n_ = np.einsum("pk,pkc->pc", w, norms[idx])
    n_ /= np.maximum(np.linalg.norm(n_, axis=1, keepdims=True), 1e-12)
    obj = np.where(hit, tri_obj[np.maximum(tri, 0)], -1)
    # a hit from behind (inside a closed object, or an open mesh's back) sees no front face
    front = np.sum(n_ * dirs, -1) < 0.0
    if two_sided:
        n_ = np.where(front[:, None], n_, -n_)
    else:
        obj = np.where(front, obj, np.where(hit, -2, -1))
    return obj, np.where(hit[:, None], p, 0.0), np.where(hit[:, None], n_, 0.0)


@jax.jit
def _closest_hits(bvh: Any, origin: jax.Array, dirs: jax.Array) -> Any:
    from ..geometry import closest_hit

    return jax.vmap(lambda d: closest_hit(bvh, origin, d))(dirs)


def _ray_cast(origin: np.ndarray, dirs: np.ndarray, tri: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """Nearest front-facing hit of rays (N, 3) from ``origin`` with triangles (T, 3, 3)
    (counter-clockwise seen from outside): (N,) triangle index or −1, (N, 3) barycentrics."""
    v0, v1, v2 = tri[:, 0], tri[:, 1], tri[:, 2]
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(dirs[:, None, :], e2[None])  # (N, T, 3)
    det = np.einsum("ntc,tc->nt", p, e1)
    front = det > 1e-18  # ray against the outward normal e1 × e2
    inv = 1.0 / np.where(front, det, 1.0)
    s = origin[None, :] - v0  # (T, 3)
    u = np.einsum("ntc,tc->nt", p, s) * inv
    q = np.cross(s, e1)  # (T, 3)
    v = (dirs @ q.T) * inv
    t = np.einsum("tc,tc->t", q, e2)[None] * inv
    hit = front & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
    t = np.where(hit, t, np.inf)
    k = np.argmin(t, axis=1)
    n = np.arange(dirs.shape[0])
    ok = np.isfinite(t[n, k])
    uu, vv = u[n, k], v[n, k]
    bary = np.stack([1.0 - uu - vv, uu, vv], -1)
    return np.where(ok, k, -1), np.where(ok[:, None], bary, 0.0)


def _spot_samples(geoms: list[ObjectGeometry], positions: np.ndarray, aims: np.ndarray,
                  fields_deg: np.ndarray, res: int) -> dict[str, np.ndarray]:
    """Sample every reading's measuring field: the pixel rays of a square R×R camera whose
    field of view is the field angle (:func:`spectral_fit.geometry.look_at` pose, OpenGL pixel
    centres), kept inside the inscribed disc.

    The rays are intersected exactly with the triangles that can touch the field's cone (a
    cone test on each triangle's bounding sphere; typically a few dozen), in NumPy
    (Möller–Trumbore, front faces only, nearest hit). This gives the same first hits and
    perspective-correct barycentrics as rasterising the view with ``spectral_fit.geometry``
    (compared in the tests), without compiling the rasteriser for these tiny views (far
    slower than the ray casting). Returns per reading b and disc pixel k: position, normal,
    view, object (−1: the ray misses every object), ray direction.
    """
    verts, norms, tris, tri_obj = scene_triangles(geoms)
    corners = verts[tris]  # (T, 3, 3)
    centroid = corners.mean(axis=1)
    radius = np.linalg.norm(corners - centroid[:, None], axis=-1).max(axis=1)
    B = len(positions)
    sel = []
    for b in range(B):
        axis = aims[b] - positions[b]
        axis = axis / np.linalg.norm(axis)
        rel = centroid - positions[b]
        d = np.linalg.norm(rel, axis=1)
        cosang = (rel @ axis) / np.maximum(d, 1e-12)
        ang = np.arccos(np.clip(cosang, -1.0, 1.0))
        half = math.radians(fields_deg[b]) / 2.0 * math.sqrt(2.0)  # the square's corners
        grow = np.arcsin(np.clip(radius / np.maximum(d, 1e-12), 0.0, 1.0))
        sel.append(np.flatnonzero((ang <= half + grow + 1e-3) & (d > radius)))
    views = np.asarray(_look_at_many(jnp.asarray(positions, jnp.float32),
                                     jnp.asarray(aims, jnp.float32)), np.float64)
    rots = [views[b, :3, :3] for b in range(B)]
    keep = disc_pixels(res)
    c = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    X, Y = np.meshgrid(c, -c)
    xs, ys = X.reshape(-1)[keep], Y.reshape(-1)[keep]
    nd = keep.size
    tri_id = np.full((B, nd), -1, np.int64)
    bary = np.zeros((B, nd, 3))
    for b in range(B):
        t = math.tan(math.radians(fields_deg[b]) / 2.0)
        d_w = np.stack([xs * t, ys * t, -np.ones_like(xs)], -1) @ rots[b]
        d_w /= np.linalg.norm(d_w, axis=1, keepdims=True)
        if len(sel[b]):
            k, w = _ray_cast(positions[b], d_w, corners[sel[b]])
            tri_id[b] = np.where(k >= 0, k, -1)
            bary[b] = w
    out: dict[str, list[np.ndarray]] = {k: [] for k in ("pos", "nrm", "view", "obj", "ray")}
    for b in range(B):
        t = math.tan(math.radians(fields_deg[b]) / 2.0)
        d_w = np.stack([xs * t, ys * t, -np.ones_like(xs)], -1) @ rots[b]  # Rᵀ d
        d_w /= np.linalg.norm(d_w, axis=1, keepdims=True)
        hit = tri_id[b] >= 0
        gtri = sel[b][np.where(hit, tri_id[b], 0)] if len(sel[b]) else np.zeros_like(tri_id[b])
        idx = tris[gtri]
        pos = np.einsum("pk,pkc->pc", bary[b], verts[idx])
        nrm = np.einsum("pk,pkc->pc", bary[b], norms[idx])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
        vw = positions[b][None, :] - pos
        vw /= np.maximum(np.linalg.norm(vw, axis=1, keepdims=True), 1e-12)
        out["pos"].append(np.where(hit[:, None], pos, 0.0))
        out["nrm"].append(np.where(hit[:, None], nrm, np.array([0.0, 1.0, 0.0])))
        out["view"].append(np.where(hit[:, None], vw, np.array([0.0, 1.0, 0.0])))
        out["obj"].append(np.where(hit, tri_obj[gtri], -1))
        out["ray"].append(d_w)
    res_ = {k: np.stack(v) for k, v in out.items()}
    res_["xy"] = np.stack([xs, ys], -1)
    return res_


@jax.jit
def _look_at_many(eyes: jax.Array, targets: jax.Array) -> jax.Array:
    """(B, 4, 4) :func:`spectral_fit.geometry.look_at` view matrices, one compiled call (the
    eager per-reading calls cost ~25 dispatches each)."""
    from ..geometry import look_at

    return jax.vmap(look_at)(eyes, targets)
