"""Self-visibility of a rigid mesh, precomputed in its own frame: for every vertex and every
direction of an octahedral grid, whether the mesh itself hides that direction, and what it
sees there instead (the triangle hit and its barycentrics).

``self_visibility(vertices (V, 3), triangles (T, 3), normals (V, 3))`` returns a
:class:`SelfVisibility`. It is an explicit precomputation step (it does not depend on the
object's pose, so a rigid object needs it once): the mesh is rasterised orthographically along
each of the K = R² directions (shadow maps, one per direction, the rasteriser of this package)
and each vertex is tested against the front-most surface over it (from half a shadow-map
pixel off the surface along its normal). A vertex p is hidden in
direction d when the surface seen from far away along d at p's position lies above p along d,
by both the front triangle's plane evaluated at p's exact position and the depth at the
pixel's centre (both tests: a neighbouring triangle of p through p's own position is never an
occluder of p, and a sub-pixel offset of the depth sample cannot make one). Open meshes count
from both sides.

Directions are the texel centres of an octahedral map (Praun & Hoppe 2003; Engelhardt &
Dachsbacher 2008's parametrisation of the sphere): u, v ∈ [−1, 1], the upper octahedron on the
square's inner diamond, the lower folded onto the corners. The map's texels have unequal solid
angles (within a factor of ~2), which :attr:`SelfVisibility.solid_angle` carries.

Convex meshes are recognised first (:func:`is_convex`: connected and convex at every edge):
nothing of such a mesh hides any direction above a vertex's tangent plane, and their result
says so without rasterising. A closed mesh wound outward keeps only the triangles facing back
along each direction, so the hit is the first surface the vertex's ray meets wherever the ray
crosses the object's material once; other meshes keep every triangle (the hit is then the
outermost surface over the vertex).

No gradient: visibility is a constant of the mesh (positions and shading that must be
differentiable are computed elsewhere).
"""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError

__all__ = ["SelfVisibility", "is_convex", "octahedral_directions", "octahedral_taps",
           "octahedral_uv", "point_visibility", "self_visibility"]

#: default octahedral grid side R (K = R² directions over the sphere, ~0.15 rad apart)
RESOLUTION = 24
#: default side of each direction's shadow map (pixels over the mesh's bounding sphere)
RASTER_SIZE = 192
#: views rasterised per compiled batch
_BATCH = 16
#: a surface counts as above the vertex when higher by this fraction of the bounding radius
_EPS = 2e-4


class SelfVisibility(eqx.Module):
    """What a rigid mesh hides from its own vertices (object frame; build with
    :func:`self_visibility`).

    Attributes:
        directions: (K, 3) float32 unit directions (object frame) of the octahedral texel
            centres, K = R², row-major in (v, u).
        solid_angle: (K,) float32 solid angle of each texel (sr; sums to 4π).
        hidden: (V, K) bool: the mesh hides direction k from vertex v.
        hit_triangle: (V, K) int32 triangle seen in direction k from vertex v where hidden
            (the front-most one over v along the direction), −1 where not.
        hit_bary: (V, K, 3) float32 barycentrics of the point of ``hit_triangle`` over v
            (0 where not hidden).
        convex: static bool: the mesh was found convex (``hidden`` is all False; no raster).
        resolution: static R.
    """

    directions: Any
    solid_angle: Any
    hidden: Any
    hit_triangle: Any
    hit_bary: Any
    convex: bool = eqx.field(static=True)
    resolution: int = eqx.field(static=True)


def octahedral_uv(d: Any) -> tuple[Any, Any]:
    """Octahedral map coordinates (u, v) ∈ [−1, 1]² of unit directions ``d`` (..., 3) (NumPy or
    JAX arrays): the upper hemisphere (z ≥ 0) on the diamond |u| + |v| ≤ 1, the lower folded
    onto the corners."""
    xp = jnp if isinstance(d, jax.Array) else np
    d = xp.asarray(d)
    n = xp.abs(d[..., 0]) + xp.abs(d[..., 1]) + xp.abs(d[..., 2])
    x = d[..., 0] / n
    y = d[..., 1] / n
    sx = xp.where(x >= 0, 1.0, -1.0)
    sy = xp.where(y >= 0, 1.0, -1.0)
    lower = d[..., 2] < 0
    u = xp.where(lower, (1.0 - xp.abs(y)) * sx, x)
    v = xp.where(lower, (1.0 - xp.abs(x)) * sy, y)
    return u, v


def _decode(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Unit directions (..., 3) of octahedral coordinates (u, v)."""
    z = 1.0 - np.abs(u) - np.abs(v)
    x = np.where(z < 0, (1.0 - np.abs(v)) * np.sign(u), u)
    y = np.where(z < 0, (1.0 - np.abs(u)) * np.sign(v), v)
    d = np.stack([x, y, z], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def fibonacci_directions(n: int) -> np.ndarray:
    """(n, 3) unit directions spread evenly over the sphere (the Fibonacci lattice: z in n
    equal steps, the golden angle between successive azimuths; +Z the lattice's pole)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = math.pi * (1.0 + math.sqrt(5.0)) * k
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def octahedral_directions(resolution: int, *, supersample: int = 8
                          ) -> tuple[np.ndarray, np.ndarray]:
    """The texel-centre directions (R², 3) (row-major in (v, u)) and the solid angle (R²,) of
    each texel of an R × R octahedral map (the solid angle by averaging the map's area element
    over ``supersample``² points per texel; the total is 4π within 1e-4)."""
    r = int(resolution)
    if r < 2:
        raise InputError(f"octahedral resolution must be at least 2, got {resolution}")
    c = (np.arange(r) + 0.5) / r * 2.0 - 1.0
    uu, vv = np.meshgrid(c, c, indexing="xy")
    dirs = _decode(uu, vv).reshape(-1, 3)
    s = int(supersample)
    f = ((np.arange(r * s) + 0.5) / (r * s)) * 2.0 - 1.0
    fu, fv = np.meshgrid(f, f, indexing="xy")
    # area element of the map: |∂d/∂u × ∂d/∂v| for d = p/|p|, p the (folded) octahedron point;
    # p lies on |x| + |y| + |z| = 1 whose parametrisation by (u, v) has a Jacobian of unit
    # determinant projected onto xy, so dω = |p·n̂| / |p|³ du dv with n̂ the face normal
    # (±1, ±1, ±1)/√3 scaled by √3 (the face's area over its xy projection)
    z = 1.0 - np.abs(fu) - np.abs(fv)
    x = np.where(z < 0, (1.0 - np.abs(fv)) * np.sign(fu), fu)
    y = np.where(z < 0, (1.0 - np.abs(fu)) * np.sign(fv), fv)
    p = np.stack([x, y, z], axis=-1)
    norm = np.linalg.norm(p, axis=-1)
    element = 1.0 / norm ** 3  # |p·n| = 1/√3·√3 for every face: p lies on the face plane
    cell = (2.0 / (r * s)) ** 2
    omega = (element * cell).reshape(r, s, r, s).sum(axis=(1, 3)).reshape(-1)
    return dirs.astype(np.float32), omega.astype(np.float32)


def _oriented_face_normals(vertices: np.ndarray, triangles: np.ndarray,
                           normals: np.ndarray) -> np.ndarray:
    """(T, 3) unit face normals, each turned to agree with its vertices' mean normal."""
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    fn = np.cross(b - a, c - a)
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
    mean = normals[triangles].sum(axis=1)
    return np.where((np.sum(fn * mean, axis=1) < 0)[:, None], -fn, fn)


def is_convex(vertices: Any, triangles: Any, normals: Any, *, tol: float = 1e-6) -> bool:
    """Whether the mesh is convex with its normals outward, by a local test: it is one
    connected piece and at every edge shared by two triangles each one's far corner lies on
    or behind the other's plane (faces oriented along the vertex normals), within ``tol``
    times the mesh's size; an edge shared by more than two triangles fails. A connected
    surface convex at every edge is convex, so no direction above a vertex's tangent plane
    meets the mesh. O(T log T)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles, np.int64)
    fn = _oriented_face_normals(v, t, np.asarray(normals, np.float64))
    size = float(np.ptp(v, axis=0).max()) or 1.0
    n_t = len(t)
    # the topology of the positions: vertices split for their normals or texture (a box's
    # hard edges) welded where they coincide
    tw = _welded(v, t)
    edges = np.concatenate([tw[:, [0, 1]], tw[:, [1, 2]], tw[:, [2, 0]]])
    n_w = int(tw.max()) + 1
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n_w, n_w))
    _, label = connected_components(graph, directed=False)
    if len(np.unique(label[np.unique(tw)])) > 1:
        return False
    far = np.concatenate([t[:, 2], t[:, 0], t[:, 1]])
    face = np.tile(np.arange(n_t), 3)
    key = np.sort(edges, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, far, face = key[order], far[order], face[order]
    same = np.all(key[1:] == key[:-1], axis=1)
    if np.any(same[1:] & same[:-1]):
        return False  # an edge of three or more triangles
    i = np.nonzero(same)[0]
    a, b = face[i], face[i + 1]
    lim = tol * size
    d1 = np.sum((v[far[i + 1]] - v[t[a, 0]]) * fn[a], axis=1)
    d2 = np.sum((v[far[i]] - v[t[b, 0]]) * fn[b], axis=1)
    return bool(np.all(d1 <= lim) and np.all(d2 <= lim))


def _welded(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(T, 3) the triangles over vertices welded where their positions coincide (vertices
    split for normals or texture joined again)."""
    size = float(np.ptp(v, axis=0).max()) or 1.0
    _, weld = np.unique(np.round(v / (size * 1e-7)).astype(np.int64), axis=0,
                        return_inverse=True)
    return weld.reshape(-1)[t]


def _closed_outward(vertices: Any, triangles: Any) -> bool:
    """Whether the mesh (vertices welded by position) is closed and consistently wound with
    its outside counter-clockwise: every directed edge appears once and its reverse once, and
    the enclosed signed volume is positive."""
    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles, np.int64)
    tw = _welded(v, t)
    e = np.concatenate([tw[:, [0, 1]], tw[:, [1, 2]], tw[:, [2, 0]]])
    e = e[e[:, 0] != e[:, 1]]  # degenerate triangles' collapsed edges
    fwd = np.unique(e, axis=0, return_counts=True)
    if np.any(fwd[1] != 1):
        return False
    a = {tuple(x) for x in fwd[0].tolist()}
    if any((y, x) not in a for x, y in a):
        return False
    p0, p1, p2 = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    return float(np.sum(np.einsum("ij,ij->i", p0, np.cross(p1, p2)))) > 0.0


def _frames(directions: np.ndarray) -> np.ndarray:
    """(K, 3, 3) rows e1, e2, d: an orthonormal frame per direction (d the third row)."""
    d = directions.astype(np.float64)
    a = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(d, a)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(d, e1)
    return np.stack([e1, e2, d], axis=1)


@jax.jit
def _light_coords(points: jax.Array, frames: jax.Array, centre: jax.Array,
                  radius: jax.Array) -> jax.Array:
    """Points in each view's coordinates (B, V, 3): x, y across and s along the direction, in
    units of the bounding radius."""
    return jnp.einsum("vc,bkc->bvk", (points - centre) / radius, frames)


def _clip(q: jax.Array) -> jax.Array:
    """Clip positions (..., 4) of view coordinates (..., 3): the front-most surface along the
    direction (largest s) has the smallest depth."""
    return jnp.concatenate([q[..., :2], -q[..., 2:3], jnp.ones_like(q[..., :1])], axis=-1)


@jax.jit
def _test_vertices(q: jax.Array, mesh_q: jax.Array, triangles: jax.Array, tri_id: jax.Array,
                   depth: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Per view (B) and test point (V; ``q`` (B, V, 3) in view coordinates): hidden (bool),
    the front triangle over the point (−1 if not hidden) and the point's barycentrics in it
    (B, V, 3); ``mesh_q`` (B, V, 3) the mesh's vertices in the same coordinates."""
    b, h, w = tri_id.shape
    px = jnp.clip(jnp.floor((q[..., 0] + 1.0) * 0.5 * w), 0, w - 1).astype(jnp.int32)
    py = jnp.clip(jnp.floor((1.0 - q[..., 1]) * 0.5 * h), 0, h - 1).astype(jnp.int32)
    flat = py * w + px
    tri = jnp.take_along_axis(tri_id.reshape(b, -1), flat, axis=1)
    s_centre = -jnp.take_along_axis(depth.reshape(b, -1), flat, axis=1)
    corners = jax.vmap(lambda qq, t: qq[triangles[jnp.maximum(t, 0)]])(mesh_q, tri)  # (B,V,3,3)
    a, bb, c = corners[..., 0, :], corners[..., 1, :], corners[..., 2, :]
    e1 = bb[..., :2] - a[..., :2]
    e2 = c[..., :2] - a[..., :2]
    r = q[..., :2] - a[..., :2]
    det = e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0]
    safe = jnp.where(jnp.abs(det) > 1e-20, det, 1.0)
    l1 = (r[..., 0] * e2[..., 1] - r[..., 1] * e2[..., 0]) / safe
    l2 = (e1[..., 0] * r[..., 1] - e1[..., 1] * r[..., 0]) / safe
    bary = jnp.stack([1.0 - l1 - l2, l1, l2], axis=-1)
    s_plane = jnp.sum(bary * corners[..., 2], axis=-1)
    s_self = q[..., 2]
    hidden = ((tri >= 0) & (jnp.abs(det) > 1e-20) & (s_plane > s_self + _EPS)
              & (s_centre > s_self + _EPS))
    bary = jnp.clip(bary, 0.0, 1.0)
    bary = bary / jnp.maximum(jnp.sum(bary, axis=-1, keepdims=True), 1e-12)
    return hidden, jnp.where(hidden, tri, -1), jnp.where(hidden[..., None], bary, 0.0)


def _plan(vj: jax.Array, tj: jax.Array, frames: np.ndarray, centre: np.ndarray,
          radius: float, size: tuple[int, int], cull: str) -> Any:
    """Raster capacities for the shadow maps: the most any direction needs (measured in NumPy
    for every direction, no compilation: a few ms each), so one compiled raster serves them
    all (a thin wall seen edge-on needs several times the windows of the average view)."""
    from ._raster_plan import plan_config

    clip = _clip(_light_coords(vj, jnp.asarray(frames), jnp.asarray(centre),
                               jnp.float32(radius)))
    return plan_config(np.asarray(clip), np.asarray(tj), size, cull=cull, headroom=1.1)


def _check_mesh(v: np.ndarray, t: np.ndarray, who: str) -> None:
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(f"{who}: vertices must be (V, 3), got {v.shape}")
    if t.ndim != 2 or t.shape[1] != 3 or len(t) == 0:
        raise InputError(f"{who}: triangles must be (T, 3) with T > 0, got {t.shape}")
    if not np.all(np.isfinite(v)):
        raise InputError(f"{who}: non-finite vertex positions")
    if t.min() < 0 or t.max() >= len(v):
        raise InputError(f"{who}: triangle indices outside 0..{len(v) - 1}")


def _unit_rows(n: np.ndarray) -> np.ndarray:
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def _rasterised_visibility(v: np.ndarray, t: np.ndarray, points: np.ndarray,
                           point_normals: np.ndarray, resolution: int, raster_size: int,
                           progress: Any) -> SelfVisibility:
    """The shadow-map test of every point against the mesh along each octahedral direction
    (see the module docstring): hidden, the front triangle over the point and its
    barycentrics, (P, K)."""
    from ._raster import rasterize_batch

    dirs, omega = octahedral_directions(resolution)
    k = len(dirs)
    # a closed mesh wound outward keeps only the triangles facing back along each direction
    # (towards the points below them): along a ray that crosses the object's material once
    # (a cup's wall, a torus's tube) the front-most of those is the first surface the ray
    # meets, not the far side of the object; any other mesh keeps every triangle (hidden is
    # right either way, the hit is the outermost surface)
    cull = "front" if _closed_outward(v, t) else "none"
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre = 0.5 * (lo + hi)
    radius = float(np.linalg.norm(v - centre, axis=1).max()) * 1.02 or 1.0
    frames = _frames(dirs).astype(np.float32)
    # each point is tested half a shadow-map pixel off the surface along its normal: a point
    # on an edge of a cavity (a box's inside corner) then lies inside the walls' coverage,
    # not on their silhouette
    lifted = points + (radius / raster_size) * _unit_rows(point_normals)
    n_p = len(points)
    hidden = np.zeros((n_p, k), bool)
    hit_tri = np.full((n_p, k), -1, np.int32)
    hit_bary = np.zeros((n_p, k, 3), np.float32)
    tj = jnp.asarray(t)
    vj = jnp.asarray(v)
    lj = jnp.asarray(lifted.astype(np.float32))
    size = (int(raster_size), int(raster_size))
    config = _plan(vj, tj, frames, centre, radius, size, cull)
    for start in range(0, k, _BATCH):
        fr = frames[start:start + _BATCH]
        pad = _BATCH - len(fr)
        fr = np.concatenate([fr, np.repeat(fr[-1:], pad, axis=0)]) if pad else fr
        frj = jnp.asarray(fr)
        mesh_q = _light_coords(vj, frj, jnp.asarray(centre), jnp.float32(radius))
        q = _light_coords(lj, frj, jnp.asarray(centre), jnp.float32(radius))
        ras = rasterize_batch(_clip(mesh_q), tj, size, cull=cull, config=config)
        hid, tri, bary = _test_vertices(q, mesh_q, tj, ras.tri_id, ras.depth)
        stop = min(start + _BATCH, k)
        m = stop - start
        hidden[:, start:stop] = np.asarray(hid[:m]).T
        hit_tri[:, start:stop] = np.asarray(tri[:m]).T
        hit_bary[:, start:stop] = np.asarray(bary[:m]).transpose(1, 0, 2)
        if progress is not None:
            progress(stop, k)
    return SelfVisibility(dirs, omega, hidden, hit_tri, hit_bary, False, int(resolution))


def self_visibility(vertices: Any, triangles: Any, normals: Any, *,
                    resolution: int = RESOLUTION, raster_size: int = RASTER_SIZE,
                    progress: Any = None) -> SelfVisibility:
    """Precompute what the mesh hides from its own vertices (see the module docstring).

    Args:
        vertices: (V, 3) float object-frame positions (m).
        triangles: (T, 3) int vertex indices.
        normals: (V, 3) float unit vertex normals (outward; they orient the convexity test).
        resolution: R, the octahedral grid's side (K = R² directions).
        raster_size: side of each direction's shadow map over the bounding sphere (pixels);
            occluders thinner than about 2 bounding radii / ``raster_size`` may be missed.
        progress: optional callable(done, total) called after each batch of views.

    Returns:
        :class:`SelfVisibility` (NumPy arrays).

    Raises:
        InputError: wrong shapes, non-finite positions or indices out of range.
    """
    v = np.asarray(vertices, np.float32)
    t = np.asarray(triangles, np.int32)
    n = np.asarray(normals, np.float32)
    _check_mesh(v, t, "self_visibility")
    if n.shape != v.shape:
        raise InputError(f"self_visibility: vertices and normals must be (V, 3), got "
                         f"{v.shape} and {n.shape}")
    if not np.all(np.isfinite(n)):
        raise InputError("self_visibility: non-finite vertex normals")
    if is_convex(v, t, n):
        dirs, omega = octahedral_directions(resolution)
        k = len(dirs)
        return SelfVisibility(dirs, omega, np.zeros((len(v), k), bool),
                              np.full((len(v), k), -1, np.int32),
                              np.zeros((len(v), k, 3), np.float32), True, int(resolution))
    return _rasterised_visibility(v, t, v, n, resolution, raster_size, progress)


def point_visibility(vertices: Any, triangles: Any, points: Any, normals: Any, *,
                     resolution: int = RESOLUTION, raster_size: int = RASTER_SIZE,
                     progress: Any = None) -> SelfVisibility:
    """What a mesh hides from arbitrary points (on it, or on other objects beside it), by the
    same shadow-map test as :func:`self_visibility`, in the frame of the given positions
    (world, when both are): for each point and each of the K = R² octahedral directions,
    whether the mesh lies along the ray from the point (lifted half a shadow-map pixel along
    its normal), the front triangle there and the point's barycentrics in it. No convexity
    shortcut: a convex mesh hides what lies behind it from points off it.

    Args:
        vertices: (V, 3) float positions (m).
        triangles: (T, 3) int vertex indices.
        points: (P, 3) float query positions, same frame.
        normals: (P, 3) float unit normals of the surfaces the points lie on (the lift).
        resolution, raster_size, progress: as :func:`self_visibility`.

    Returns:
        :class:`SelfVisibility` whose ``hidden``, ``hit_triangle`` and ``hit_bary`` have one
        row per point (``convex`` False).

    Raises:
        InputError: wrong shapes, non-finite values or indices out of range.
    """
    v = np.asarray(vertices, np.float32)
    t = np.asarray(triangles, np.int32)
    p = np.asarray(points, np.float32)
    n = np.asarray(normals, np.float32)
    _check_mesh(v, t, "point_visibility")
    if p.ndim != 2 or p.shape[1] != 3 or n.shape != p.shape:
        raise InputError(f"point_visibility: points and normals must be (P, 3), got "
                         f"{p.shape} and {n.shape}")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(n))):
        raise InputError("point_visibility: non-finite points or normals")
    return _rasterised_visibility(v, t, p, n, resolution, raster_size, progress)


def octahedral_taps(d: Any, resolution: int) -> tuple[Any, Any]:
    """Bilinear taps of an R × R octahedral map (texels row-major in (v, u), as
    :func:`octahedral_directions`) at unit directions ``d`` (..., 3) (NumPy or JAX arrays, the
    result alike): indices (..., 4) int32 and weights (..., 4) summing to 1 (clamped at the
    square's border)."""
    xp = jnp if isinstance(d, jax.Array) else np
    r = int(resolution)
    u, v = octahedral_uv(d if xp is np else jnp.asarray(d))
    x = xp.clip((u + 1.0) * 0.5 * r - 0.5, 0.0, r - 1.0)
    y = xp.clip((v + 1.0) * 0.5 * r - 0.5, 0.0, r - 1.0)
    x0 = xp.minimum(xp.floor(x), r - 2).astype(xp.int32)
    y0 = xp.minimum(xp.floor(y), r - 2).astype(xp.int32)
    fx = x - x0
    fy = y - y0
    idx = xp.stack([y0 * r + x0, y0 * r + x0 + 1, (y0 + 1) * r + x0, (y0 + 1) * r + x0 + 1],
                   axis=-1)
    w = xp.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], axis=-1)
    return idx, w
