"""Triangle clusters, culled per frame before the camera raster.

The rasteriser's triangle setup (:mod:`spectral_fit.geometry`) and its window counting cost the
same for every triangle, drawn or not, and a closed object seen from outside turns at most about
half its triangles towards the eye (the benchmark frame: 15,160 of 39,600). The renderer
therefore hands the rasteriser only the triangles of the *clusters* that may face the eye:

1. **Order** (:func:`spatial_order`, once): each object's triangles are sorted along a Morton
   curve of their object-space centroids, so that runs of consecutive triangles are compact
   patches of surface whose normals point roughly one way.
2. **Clusters** (:func:`build_clusters`, once): each object's sorted run is cut into clusters
   of :data:`CLUSTER_SIZE` triangles (its last cluster padded with degenerate triangles); per
   triangle, its object-space plane (unit normal n, offset n·q₀) is stored.
3. **Cull** (:func:`visible_clusters`, per frame, traced): the eye is moved into each object's
   frame, e_o = M⁻¹ e; a cluster is kept when one of its triangles may face it, with a margin,
   and the kept clusters are compacted (in order) into a list of ``capacity`` slots
   (:func:`~spectral_fit.geometry.compact_flags`).
4. **Rows** (:func:`cluster_rows`): the kept clusters' triangles (``capacity · S`` rows, dead
   slots degenerate) and the object of each row, in place of the full triangle list.

**Why the test is exact up to its margin.** For a pinhole camera (clip x, y and w linear in
the eye-space point with no constant term: any OpenGL perspective or intrinsics projection),
the homogeneous pixel corners of a point p are hv(p) = L (p − e) with L = S P₃ V₃ (S the
clip → pixel map of our convention, det S = −W·H/4; P₃ the projection's x, y, w rows on eye-space
xyz; V₃ the view's rotation). With p = M₃ q + t, the rasteriser's orientation determinant of a
triangle (q₀, q₁, q₂) is therefore

    det[hv₀; hv₁; hv₂] = det(L) det(M₃) · (q₀ − e_o) · ((q₁ − q₀) × (q₂ − q₀))
                       = −κ · |n| (n̂·e_o − n̂·q₀),      κ = det(L) det(M₃),

whatever the sign of w (also for triangles that cross the eye plane). The rasteriser draws a
triangle with ``cull="back"`` only when that determinant is < 0, i.e. when
sign(κ)·(n̂·e_o − n̂·q₀) > 0. A cluster is kept when some triangle has
sign(κ)·(n̂·e_o − n̂·q₀) > −:data:`MARGIN`·(|q₀| + |e_o|): the eye may lie up to 1 % of the
object's scale behind a triangle's plane (about 0.6° of its view direction) and the triangle's
cluster is still kept, many orders of magnitude above the float32 rounding of either side. A
culled cluster thus holds only triangles the rasteriser would have dropped itself, and the
kept triangles keep their order, so the frame is bit-identical to a raster of all triangles
(tested). Projections with a constant term in x, y or w (not a pinhole) keep every cluster.

The frame's other face-culling mode ("none": a mesh with openings or inward winding) and
frames through a lens model (the distortion is not projective) use no clusters.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["CLUSTER_SIZE", "MARGIN", "TriangleClusters", "build_clusters", "cluster_rows",
           "count_clusters", "grown_clusters", "sized", "spatial_order", "visible_clusters",
           "worst_direction_count"]

#: triangles per cluster
CLUSTER_SIZE = 64

#: how far (relative to |q₀| + |e_o|, object frame) the eye may lie behind a triangle's plane
#: with the triangle's cluster still kept
MARGIN = 1e-2

#: plane offset of the padding rows: never kept
_NEVER = 1e30


class TriangleClusters(eqx.Module):
    """Clusters of consecutive triangles of one object each (see the module docstring).

    Attributes:
        triangles: ``(C + 1, S, 3)`` int32 vertex indices of each cluster's triangles (rows
            past an object's last triangle are degenerate (0, 0, 0)); cluster C is all
            degenerate (what an unused slot of the kept list reads).
        plane: ``(C, S, 4)`` float32 object-frame plane of each triangle: unit normal n̂ and
            its offset n̂·q₀ (q₀ its first corner); (0, 0, 0, 1e30) in padding rows.
        scale: ``(C, S)`` float32 |q₀| of each triangle (its margin's share).
        cluster_object: ``(C + 1,)`` int32 object of each cluster (−1 for cluster C).
        cluster_slices: per object, its (start, stop) cluster range (static).
        capacity: slots of the kept-cluster list (static).
    """

    triangles: jax.Array
    plane: jax.Array
    scale: jax.Array
    cluster_object: jax.Array
    cluster_slices: tuple[tuple[int, int], ...] = eqx.field(static=True)
    capacity: int = eqx.field(static=True)

    @property
    def size(self) -> int:
        """Triangles per cluster, S."""
        return int(self.triangles.shape[1])

    @property
    def num_clusters(self) -> int:
        """Clusters, C (without the degenerate one)."""
        return int(self.triangles.shape[0]) - 1


def _morton3(q: np.ndarray) -> np.ndarray:
    """Morton (Z-order) codes of (N, 3) int64 cell coordinates in [0, 1024)."""
    out = np.zeros(q.shape[0], np.int64)
    for bit in range(10):
        for axis in range(3):
            out |= ((q[:, axis] >> bit) & 1) << (3 * bit + axis)
    return out


def spatial_order(vertices: np.ndarray, triangles: np.ndarray,
                  slices: Sequence[tuple[int, int]]) -> np.ndarray:
    """A permutation of the triangles ``(T, 3)`` that keeps every object's range
    ``slices[o]`` in place and sorts the triangles within it along a Morton curve of their
    centroids (``vertices`` (V, 3), a 1024³ grid over the object's bounding box; ties keep
    their order). Returns ``(T,)`` int64 indices: ``triangles[perm]`` is the sorted list."""
    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles)
    perm = np.arange(t.shape[0], dtype=np.int64)
    for ta, tb in slices:
        if tb - ta < 2:
            continue
        cen = v[t[ta:tb]].mean(axis=1)
        lo, hi = cen.min(axis=0), cen.max(axis=0)
        cell = np.floor((cen - lo) / np.maximum(hi - lo, 1e-30) * 1023.0).astype(np.int64)
        perm[ta:tb] = ta + np.argsort(_morton3(np.clip(cell, 0, 1023)), kind="stable")
    return perm


def _planes(v: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, 4) unit normal and offset, (T,) |q₀| of triangles ``tri`` over vertices ``v``
    (float64; a degenerate triangle gets a zero normal and offset: always kept)."""
    q = v[tri]
    n = np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    nh = np.where(length > 0, n / np.where(length > 0, length, 1.0), 0.0)
    return (np.concatenate([nh, np.sum(nh * q[:, 0], axis=1, keepdims=True)], axis=1),
            np.linalg.norm(q[:, 0], axis=1))


def build_clusters(vertices: np.ndarray, triangles: np.ndarray,
                   slices: Sequence[tuple[int, int]], *, size: int = CLUSTER_SIZE,
                   capacity: int | None = None) -> TriangleClusters:
    """Cut each object's triangle range ``slices[o]`` of ``triangles`` (T, 3) (already in
    :func:`spatial_order`) into clusters of ``size`` triangles, with their object-frame
    planes from ``vertices`` (V, 3). ``capacity``: slots of the kept list (default all C)."""
    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles, np.int64)
    tris, planes, scales, objs, cslices = [], [], [], [], []
    c0 = 0
    for o, (ta, tb) in enumerate(slices):
        n = tb - ta
        nc = max(1, -(-n // size))
        pad = nc * size - n
        pl, sc = _planes(v, t[ta:tb])
        tris.append(np.concatenate([t[ta:tb], np.zeros((pad, 3), np.int64)]))
        planes.append(np.concatenate([pl, np.tile([[0.0, 0.0, 0.0, _NEVER]], (pad, 1))]))
        scales.append(np.concatenate([sc, np.zeros(pad)]))
        objs.append(np.full(nc, o, np.int32))
        cslices.append((c0, c0 + nc))
        c0 += nc
    tri = np.concatenate(tris + [np.zeros((size, 3), np.int64)]).reshape(c0 + 1, size, 3)
    cap = c0 if capacity is None else int(min(max(capacity, 1), c0))
    return TriangleClusters(
        triangles=jnp.asarray(tri, jnp.int32),
        plane=jnp.asarray(np.concatenate(planes).reshape(c0, size, 4), jnp.float32),
        scale=jnp.asarray(np.concatenate(scales).reshape(c0, size), jnp.float32),
        cluster_object=jnp.asarray(np.concatenate(objs + [np.full(1, -1, np.int32)])),
        cluster_slices=tuple(cslices), capacity=cap)


def _det3(m: Any, xp: Any = jnp) -> Any:
    """Determinants of 3×3 matrices (..., 3, 3) in closed form."""
    return (m[..., 0, 0] * (m[..., 1, 1] * m[..., 2, 2] - m[..., 1, 2] * m[..., 2, 1])
            - m[..., 0, 1] * (m[..., 1, 0] * m[..., 2, 2] - m[..., 1, 2] * m[..., 2, 0])
            + m[..., 0, 2] * (m[..., 1, 0] * m[..., 2, 1] - m[..., 1, 1] * m[..., 2, 0]))


def _facing_sign(model: Any, view: Any, projection: Any, cull: str, xp: Any = jnp) -> Any:
    """(O,) ±1 per object: the sign that makes ``sign · (n̂·e_o − n̂·q₀)`` positive for the
    triangles the rasteriser keeps with ``cull`` ("back" or "front"): sign(κ), negated for
    "front" (see the module docstring)."""
    p3 = xp.stack([projection[0, :3], projection[1, :3], projection[3, :3]])
    k = -xp.sign(_det3(p3, xp) * _det3(view[:3, :3], xp)) * xp.sign(_det3(model[:, :3, :3], xp))
    return -k if cull == "front" else k


def _pinhole(projection: Any) -> Any:
    """Whether clip x, y and w have no constant term (the orientation identity holds)."""
    return (projection[0, 3] == 0) & (projection[1, 3] == 0) & (projection[3, 3] == 0)


def _eye_in_objects(model: Any, view: Any, xp: Any = jnp) -> Any:
    """(O, 3) the eye of ``view`` in each object's frame: M⁻¹ e."""
    if xp is np:
        a, t = view[:3, :3], view[:3, 3]
        e = -np.linalg.solve(a, t)
        return np.stack([np.linalg.solve(m[:3, :3], e - m[:3, 3]) for m in model])
    from ._camera import eye_position, inverse_3x3

    e = eye_position(view)
    inv = inverse_3x3(model[:, :3, :3])
    return jnp.einsum("oij,oj->oi", inv, e[None, :] - model[:, :3, 3])


def visible_clusters(clusters: TriangleClusters, model: jax.Array, view: jax.Array,
                     projection: jax.Array, visible: jax.Array, *, cull: str = "back"
                     ) -> tuple[jax.Array, jax.Array]:
    """The clusters that may hold a triangle the rasteriser draws, compacted in order.

    Args:
        clusters: from :func:`build_clusters`.
        model: (O, 4, 4) world-from-object matrices.
        view: (4, 4) world → OpenGL eye.
        projection: (4, 4) eye → clip.
        visible: (O,) bool; a hidden object's clusters are dropped.
        cull: the raster's face culling, "back" or "front" (static).

    Returns:
        ``(index, count)``: index ``(capacity,)`` int32 cluster numbers (the degenerate
        cluster C in slots past ``count``), count the kept clusters (int32; more than the
        capacity means the list overflowed and clusters past it are missing).
    """
    from ._pixels import compact_flags

    if cull not in ("back", "front"):
        raise ValueError(f"cull must be 'back' or 'front', got {cull!r}")
    eo = _eye_in_objects(model, view)
    sign = _facing_sign(model, view, projection, cull)
    pinhole = _pinhole(projection)
    keeps = []
    for o, (ca, cb) in enumerate(clusters.cluster_slices):
        p = clusters.plane[ca:cb]
        side = (p[..., 0] * eo[o, 0] + p[..., 1] * eo[o, 1] + p[..., 2] * eo[o, 2]
                - p[..., 3]) * sign[o]
        dist = jnp.sqrt(eo[o, 0] * eo[o, 0] + eo[o, 1] * eo[o, 1] + eo[o, 2] * eo[o, 2])
        tol = MARGIN * (clusters.scale[ca:cb] + dist)
        keep = jnp.any(side > -tol, axis=1) | (~pinhole & (p[:, 0, 3] < _NEVER))
        keeps.append(keep & visible[o])
    index, count = compact_flags(jnp.concatenate(keeps), clusters.capacity)
    live = jnp.arange(clusters.capacity, dtype=jnp.int32) < count
    return jnp.where(live, index, clusters.num_clusters), count


def cluster_rows(clusters: TriangleClusters, index: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The triangles of the clusters ``index`` (K,) and the object of each: ``(K·S, 3)``
    int32 vertex indices and ``(K·S,)`` int32 objects (−1 in the degenerate cluster's rows).
    The rows are written once (a cut: the rasteriser's setup reads them in many kernels)."""
    from .._runtime.backend import materialise

    s = clusters.size
    tri = materialise(clusters.triangles[index].reshape(-1, 3), cut=True)
    obj = jnp.repeat(clusters.cluster_object[index], s)
    return tri, obj


def count_clusters(clusters: TriangleClusters, model: np.ndarray, view: np.ndarray,
                   projection: np.ndarray, *, cull: str = "back") -> int:
    """:func:`visible_clusters`' count for one pose, in NumPy (float64, no compilation)."""
    plane = np.asarray(clusters.plane, np.float64)
    scale = np.asarray(clusters.scale, np.float64)
    model = np.asarray(model, np.float64)
    view = np.asarray(view, np.float64)
    projection = np.asarray(projection, np.float64)
    if not bool(_pinhole(projection)):
        return clusters.num_clusters
    eo = _eye_in_objects(model, view, np)
    sign = _facing_sign(model, view, projection, cull, np)
    total = 0
    for o, (ca, cb) in enumerate(clusters.cluster_slices):
        p = plane[ca:cb]
        side = (p[..., :3] @ eo[o] - p[..., 3]) * sign[o]
        tol = MARGIN * (scale[ca:cb] + np.linalg.norm(eo[o]))
        total += int(np.sum(np.any(side > -tol, axis=1)))
    return total


def worst_direction_count(clusters: TriangleClusters, *, directions: int = 256) -> int:
    """The most clusters kept, summed over the objects, when each object is seen from
    infinitely far along any of ``directions`` Fibonacci-sphere directions (its own worst
    one): a bound on the count under any rotation of a convex object (a nearer eye sees
    less of it), used to size the kept list for objects that turn."""
    from ._visibility import fibonacci_directions

    dirs = fibonacci_directions(directions)  # (D, 3)
    plane = np.asarray(clusters.plane, np.float64)
    total = 0
    for ca, cb in clusters.cluster_slices:
        n = plane[ca:cb, :, :3]  # (c, S, 3); padding rows have n = 0: 0 > −MARGIN
        real = plane[ca:cb, :, 3] < _NEVER
        side = np.einsum("csk,dk->dcs", n, dirs)  # eye at infinity along d: sign n̂·d
        keep = np.any((side > -MARGIN) & real[None], axis=2)  # (D, c)
        total += int(keep.sum(axis=1).max())
    return total


def sized(clusters: TriangleClusters, needed: float, *, at_least: int = 0) -> TriangleClusters:
    """``clusters`` with a kept list of the capacity-ladder value ≥ ``needed``
    (:func:`spectral_fit.geometry` ladder), at least ``at_least``, at most all C clusters; the
    same object when that is its capacity already."""
    from ._raster_plan import capacity_ladder

    cap = min(clusters.num_clusters, max(int(at_least), capacity_ladder(needed)))
    return clusters if cap == clusters.capacity else dataclasses.replace(clusters, capacity=cap)


def grown_clusters(clusters: TriangleClusters | None, needed: int, headroom: float = 1.25, *,
                   full: float = 1.0) -> TriangleClusters | None:
    """``clusters`` with its kept list grown to ``headroom`` × ``needed`` (a frame's count of
    kept clusters) where ``needed`` exceeds ``full`` × the capacity (1: where it overflowed;
    below 1, ahead of an overflow); else (or for None) the same object."""
    if clusters is None or needed <= full * clusters.capacity:
        return clusters
    return sized(clusters, headroom * needed, at_least=clusters.capacity)
