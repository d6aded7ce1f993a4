"""Ray casting against triangle meshes: a bounding volume hierarchy built once (NumPy, an explicit
precomputation step) and traversed in JAX, one ray per call (callers ``jax.vmap``).

``build_bvh(vertices (V, 3), triangles (T, 3))`` returns a :class:`BVH`; ``closest_hit(bvh,
origin (3,), direction (3,))`` the nearest triangle along the ray as a :class:`RayHit`;
``occluded(bvh, origin, direction, t_max)`` whether anything lies on the segment. Positions are in
the mesh's own frame and units (metres in this package); directions need not be unit length
(``t`` is in units of the direction's length).

Layout: the nodes are stored in depth-first order with an escape index each (the node that follows
the node's subtree), so the traversal needs no stack: at node ``i`` a ray that meets the node's box
goes on to ``i + 1`` (the first child, or the next node after a leaf) and a ray that misses it
jumps to ``escape[i]``. The closest-hit query shrinks its search interval to the nearest hit found
so far, so boxes behind it are skipped. Every array has a shape fixed by the mesh (the node count
is at most 2T − 1), so one compiled program serves every ray of a mesh and every mesh of the same
size.

Visibility carries no gradient: the outputs are wrapped in ``stop_gradient`` (positions and
barycentrics that must be differentiable are recomputed from the returned triangle, as the
rasteriser's callers do). Triangles are intersected by the Möller–Trumbore test in float32;
single-sided or double-sided alike (a hit from behind counts).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError

__all__ = ["BVH", "RayHit", "build_bvh", "closest_hit", "occluded"]

#: triangles per leaf at most (the leaf's triangles are tested in one unrolled step)
LEAF_SIZE = 4
#: determinant below which a ray counts as parallel to a triangle's plane
_EPS_DET = 1e-12


class BVH(eqx.Module):
    """A bounding volume hierarchy over one triangle mesh (a pytree; build with
    :func:`build_bvh`).

    Attributes:
        lo, hi: (M, 3) float32 corners of each node's axis-aligned box (mesh units).
        escape: (M,) int32 index of the node after this node's subtree (M after the last).
        first: (M,) int32 first slot of a leaf's triangles in the reordered arrays; −1 for an
            inner node.
        count: (M,) int32 triangles in a leaf (0 for an inner node).
        v0, e1, e2: (S, 3) float32 first vertex and the two edges (v1 − v0, v2 − v0) of the
            triangles in leaf order, S = T + ``LEAF_SIZE`` (padding slots repeat triangle 0 and
            are never counted).
        triangle: (S,) int32 index of each slot's triangle in the mesh's own order.
    """

    lo: jax.Array
    hi: jax.Array
    escape: jax.Array
    first: jax.Array
    count: jax.Array
    v0: jax.Array
    e1: jax.Array
    e2: jax.Array
    triangle: jax.Array


class RayHit(eqx.Module):
    """The nearest hit of one ray (or of a batch under ``jax.vmap``: every field gains the
    batch axes).

    Attributes:
        t: () float32 distance along the ray in units of the direction's length; +inf for a
            miss.
        triangle: () int32 index of the triangle hit in the mesh's order; −1 for a miss.
        u, v: () float32 barycentric weights of the triangle's second and third vertex at the
            hit (the first vertex weighs 1 − u − v); 0 for a miss.
    """

    t: jax.Array
    triangle: jax.Array
    u: jax.Array
    v: jax.Array

    @property
    def hit(self) -> jax.Array:
        """() bool: whether the ray hit a triangle."""
        return self.triangle >= 0


def build_bvh(vertices: Any, triangles: Any, *, leaf_size: int = LEAF_SIZE) -> BVH:
    """Build the hierarchy of a triangle mesh (NumPy; once per mesh, outside ``jit``).

    Splits each node at the median of its triangles' centroids along the longest axis of their
    bounds, down to ``leaf_size`` triangles per leaf.

    Args:
        vertices: (V, 3) float positions.
        triangles: (T, 3) int vertex indices, T ≥ 1.
        leaf_size: most triangles per leaf, 1..``LEAF_SIZE``.

    Returns:
        :class:`BVH` with at most 2T − 1 nodes.
    """
    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(f"expected shape (V, 3), got {v.shape}", field="vertices")
    if not np.all(np.isfinite(v)):
        raise InputError("non-finite value", field="vertices")
    if t.ndim != 2 or t.shape[1] != 3 or t.shape[0] < 1:
        raise InputError(f"expected shape (T, 3) with T >= 1, got {t.shape}", field="triangles")
    if not np.issubdtype(t.dtype, np.integer) or t.min() < 0 or t.max() >= len(v):
        raise InputError(f"expected integer indices in 0..{len(v) - 1}", field="triangles")
    if not 1 <= int(leaf_size) <= LEAF_SIZE:
        raise InputError(f"must be in 1..{LEAF_SIZE}, got {leaf_size!r}", field="leaf_size")
    corners = v[t]  # (T, 3, 3)
    tri_lo, tri_hi = corners.min(1), corners.max(1)
    centroid = corners.mean(1)

    lo, hi, first, count, order = [], [], [], [], []
    # depth-first (pre-order): a node is appended before its children, the left child right
    # after its parent (pushed last, popped first), the right child after the left's subtree
    stack: list[np.ndarray] = [np.arange(len(t))]
    while stack:
        ids = stack.pop()
        lo.append(tri_lo[ids].min(0))
        hi.append(tri_hi[ids].max(0))
        if len(ids) <= leaf_size:
            first.append(len(order))
            count.append(len(ids))
            order.extend(ids.tolist())
        else:
            first.append(-1)
            count.append(0)
            c = centroid[ids]
            axis = int(np.argmax(c.max(0) - c.min(0)))
            s = ids[np.argsort(c[:, axis], kind="stable")]
            half = len(s) // 2
            stack.append(s[half:])
            stack.append(s[:half])
    # escape[i] = i + the size of i's subtree (1 for a leaf; 1 + both children's for an inner
    # node, whose left child is i + 1 and right child i + 1 + size(left))
    m = len(lo)
    size = np.ones(m, np.int64)
    for i in range(m - 1, -1, -1):
        if count[i] == 0:
            left = i + 1
            size[i] = 1 + size[left] + size[left + size[left]]
    escape = (np.arange(m) + size).astype(np.int32)
    order_a = np.asarray(order, np.int64)
    pad = np.zeros(LEAF_SIZE, np.int64) + order_a[0]
    slots = np.concatenate([order_a, pad])
    p = v[t[slots]]
    return BVH(lo=jnp.asarray(np.asarray(lo), jnp.float32),
               hi=jnp.asarray(np.asarray(hi), jnp.float32),
               escape=jnp.asarray(escape),
               first=jnp.asarray(np.asarray(first, np.int32)),
               count=jnp.asarray(np.asarray(count, np.int32)),
               v0=jnp.asarray(p[:, 0], jnp.float32),
               e1=jnp.asarray(p[:, 1] - p[:, 0], jnp.float32),
               e2=jnp.asarray(p[:, 2] - p[:, 0], jnp.float32),
               triangle=jnp.asarray(slots.astype(np.int32)))


def _box_entry(lo: jax.Array, hi: jax.Array, origin: jax.Array, inv_dir: jax.Array,
               t_min: jax.Array, t_max: jax.Array) -> jax.Array:
    """() bool: whether the ray meets the box [lo, hi] within [t_min, t_max] (slab test)."""
    a = (lo - origin) * inv_dir
    b = (hi - origin) * inv_dir
    near = jnp.max(jnp.minimum(a, b))
    far = jnp.min(jnp.maximum(a, b))
    return (near <= far) & (far >= t_min) & (near <= t_max)


def _leaf_hits(bvh: BVH, node: jax.Array, origin: jax.Array, direction: jax.Array,
               t_min: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Möller–Trumbore against the ``LEAF_SIZE`` slots of leaf ``node``: (t, slot, u, v) of the
    nearest valid hit in the leaf (t = +inf when none)."""
    slot = bvh.first[node] + jnp.arange(LEAF_SIZE, dtype=jnp.int32)
    live = jnp.arange(LEAF_SIZE) < bvh.count[node]
    v0, e1, e2 = bvh.v0[slot], bvh.e1[slot], bvh.e2[slot]
    p = jnp.cross(direction[None], e2)
    det = jnp.sum(e1 * p, -1)
    ok = jnp.abs(det) > _EPS_DET
    inv = 1.0 / jnp.where(ok, det, 1.0)
    s = origin[None] - v0
    u = jnp.sum(s * p, -1) * inv
    q = jnp.cross(s, e1)
    w = jnp.sum(direction[None] * q, -1) * inv
    t = jnp.sum(e2 * q, -1) * inv
    good = live & ok & (u >= 0.0) & (w >= 0.0) & (u + w <= 1.0) & (t >= t_min)
    t = jnp.where(good, t, jnp.inf)
    k = jnp.argmin(t)
    return t[k], slot[k], u[k], w[k]


def _inverse_direction(direction: jax.Array) -> jax.Array:
    tiny = jnp.float32(1e-30)
    safe = jnp.where(jnp.abs(direction) < tiny, jnp.where(direction < 0, -tiny, tiny), direction)
    return 1.0 / safe


def closest_hit(bvh: BVH, origin: Any, direction: Any, *, t_min: float = 0.0,
                t_max: float = float("inf")) -> RayHit:
    """The nearest triangle hit by the ray ``origin + t · direction``, t in [t_min, t_max].

    Args:
        bvh: from :func:`build_bvh`.
        origin: (3,) ray origin (mesh units).
        direction: (3,) ray direction (any non-zero length).
        t_min, t_max: the searched interval of t (``t_min`` > 0 keeps a ray that leaves a
            surface from hitting that surface).

    Returns:
        :class:`RayHit` (no gradient). Unbatched: ``jax.vmap`` over rays.
    """
    origin = jnp.asarray(origin, jnp.float32)
    direction = jnp.asarray(direction, jnp.float32)
    inv_dir = _inverse_direction(direction)
    m = bvh.lo.shape[0]
    t_lo = jnp.float32(t_min)

    def cond(state: tuple) -> jax.Array:
        return state[0] < m

    def body(state: tuple) -> tuple:
        i, best_t, best_slot, best_u, best_v = state
        enter = _box_entry(bvh.lo[i], bvh.hi[i], origin, inv_dir, t_lo, best_t)
        leaf = bvh.count[i] > 0
        t, slot, u, v = jax.lax.cond(enter & leaf,
                                     lambda: _leaf_hits(bvh, i, origin, direction, t_lo),
                                     lambda: (jnp.float32(jnp.inf), jnp.int32(0),
                                              jnp.float32(0.0), jnp.float32(0.0)))
        closer = t < best_t
        return (jnp.where(enter, i + 1, bvh.escape[i]),
                jnp.where(closer, t, best_t), jnp.where(closer, slot, best_slot),
                jnp.where(closer, u, best_u), jnp.where(closer, v, best_v))

    init = (jnp.int32(0), jnp.float32(t_max), jnp.int32(-1), jnp.float32(0.0),
            jnp.float32(0.0))
    _, t, slot, u, v = jax.lax.while_loop(cond, body, init)
    hit = slot >= 0
    tri = jnp.where(hit, bvh.triangle[jnp.maximum(slot, 0)], -1)
    return jax.lax.stop_gradient(RayHit(t=jnp.where(hit, t, jnp.inf), triangle=tri,
                                        u=jnp.where(hit, u, 0.0), v=jnp.where(hit, v, 0.0)))


def occluded(bvh: BVH, origin: Any, direction: Any, t_max: Any, *,
             t_min: float = 0.0) -> jax.Array:
    """() bool: whether any triangle lies on ``origin + t · direction``, t in [t_min, t_max]
    (an any-hit query: stops at the first hit found). Unbatched: ``jax.vmap`` over rays; no
    gradient."""
    origin = jnp.asarray(origin, jnp.float32)
    direction = jnp.asarray(direction, jnp.float32)
    inv_dir = _inverse_direction(direction)
    m = bvh.lo.shape[0]
    t_lo = jnp.float32(t_min)
    t_hi = jnp.asarray(t_max, jnp.float32)

    def cond(state: tuple) -> jax.Array:
        return (state[0] < m) & ~state[1]

    def body(state: tuple) -> tuple:
        i, _ = state
        enter = _box_entry(bvh.lo[i], bvh.hi[i], origin, inv_dir, t_lo, t_hi)
        leaf = bvh.count[i] > 0
        t = jax.lax.cond(enter & leaf,
                         lambda: _leaf_hits(bvh, i, origin, direction, t_lo)[0],
                         lambda: jnp.float32(jnp.inf))
        return jnp.where(enter, i + 1, bvh.escape[i]), t <= t_hi

    _, found = jax.lax.while_loop(cond, body, (jnp.int32(0), jnp.asarray(False)))
    return jax.lax.stop_gradient(found)
