"""Real surfaces (a table under the objects): the objects' shadows and light on them.

A ``[[surfaces]]`` plane of the config is not drawn as an object; it takes part in the light
transport in two ways:

1. what the objects see of it: the environment below its horizon is replaced by its uniform
   radiance ρ E_up / π (:func:`~spectral_fit.lighting.ground_plane`, at :func:`prepare`);
2. what the objects do to it (this module): at a point x of the plane, the objects hide part
   of the sky and show their own radiance instead,

       E(x) = E_up − Σ_k h_k(x) Φ_k + Σ_k h_k(x) Ω⊥_k L_obj(hit_k(x)),
       L_surface(x, λ) = ρ(λ) E(x, λ) / π,

   over D directions of the plane's upper hemisphere: K cosine-weighted directions (a
   Fibonacci spiral on the unit disc lifted to the hemisphere, Malley's method) whose cells
   (every environment texel belongs to its nearest direction) carry the environment's
   cosine-weighted flux Φ_k = ∫_cell L (n·ω) dω and projected solid angle Ω⊥_k, plus the
   sub-points of each bright source of the map (their own flux times n·ω, taken out of
   their cells): sharp shadows of small lamps. h_k(x) ∈ {0, 1}: an object lies along the ray
   from x in direction k. L_obj is the radiance of the vertex the ray meets towards x: its
   diffuse light α S(λ) E/π (E from the frame's irradiance map of the grounded
   environment, plus what the other objects change of it: their light less the sky they
   hide, from the gather interreflection) and its gloss and mirror along −d_k (as the frame
   shades its pixels).

Visibility (precomputed per pose, no gradient): for each direction the objects' meshes are
projected along it onto the plane (an oblique parallel projection: a point X goes to
X − s d with s = n·(X − p)/n·d its distance along d above the plane) and rasterised over a
T × T texel grid of a square region of the plane around the objects (the config's ``margin``
in bounding radii beyond their footprints); the front-most triangle (smallest s) is what the
texel's ray meets first. The rasteriser is the package's own (``rasterize_batch``, one
compiled program for all directions). The result is a :class:`SurfaceTransfer`: the hidden
environment per texel (T², C), the (vertex, direction) pairs the texels see and the
(texel, pair, Ω⊥) hits, padded to capacities on the ladder so that rebuilding it for a new
pose rarely recompiles.

Per frame (:func:`surface_texels`, differentiable in the materials): the objects' vertex
radiance, gathered into the texels, gives E(x); a camera pixel whose ray meets the plane in
front of the camera reads its texel bilinearly (:func:`surface_layer`); outside the region
the surface has its radiance without objects, ρ E_up / π.

What it leaves out: the objects' self-shadowing as seen from the plane (their vertex radiance
is that of a convex object), the darker table in their own shadow as they see it, and the
shadows that fall outside the region. Conventions: world frame, metres; radiance in the
environment's unit (W·sr⁻¹·m⁻²·nm⁻¹); texel (row, col) has plane coordinates
u = (col + ½)·2/T − 1, v = 1 − (row + ½)·2/T times the region's half side along t1, t2.
"""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.backend import materialise_each
from .._runtime.dispatch import array_jit
from .._runtime.errors import InputError

__all__ = ["SurfaceLayer", "SurfaceTexture", "SurfaceTransfer", "build_surface_transfer",
           "TableChange", "draw_surfaces", "surface_layer", "surface_pixels", "surface_vertices",
           "surface_ratio", "surface_ratio_lookup", "surface_ratio_textures", "surface_texels",
           "table_changes", "neighbour_irradiance",
           "surface_textures", "surface_transfer"]

#: cosine-weighted directions over each plane's hemisphere (their cells carry the environment)
DIRECTIONS = 160
#: views rasterised per compiled batch
_BATCH = 16
#: directions within this cosine of the plane's horizon are left out (their shadows run off
#: the region; their cells' flux is carried by the nearest direction above)
_MIN_COS = 0.03


class SurfaceTransfer(eqx.Module):
    """What the objects do to one plane, precomputed for one set of poses
    (:func:`build_surface_transfer`).

    Attributes:
        origin: (3,) the region's centre on the plane (world, m).
        axes: (3, 3) rows t1, t2, n: the region's axes and the plane's normal (world).
        half: () half side of the square region (m).
        reflectance: (L,) the plane's ρ(λ) on the scene's wavelengths.
        upper: (C,) E_up, the plane's irradiance without objects (environment channels).
        hidden: (T², C) irradiance the objects hide from each texel (environment channels).
        hit_texel, hit_pair: (Q,) int32 each hit's texel and (vertex, direction) pair
            (padding rows: weight 0).
        hit_weight: (Q,) float32 projected solid angle Ω⊥ (sr) of the hit's direction.
        pair_vertex: (U,) int32 interreflection-mesh vertex of each pair seen.
        pair_view: (U, 3) float32 world direction from that vertex back to the plane.
        pair_object: (U,) int32 its object (−1: padding).
        spheres: (O, 4) the objects' bounding spheres (centre, radius; 0: not present).
        resolution: T, texels per side (static).
    """

    origin: jax.Array
    axes: jax.Array
    half: jax.Array
    reflectance: jax.Array
    upper: jax.Array
    hidden: jax.Array
    hit_texel: jax.Array
    hit_pair: jax.Array
    hit_weight: jax.Array
    pair_vertex: jax.Array
    pair_view: jax.Array
    pair_object: jax.Array
    spheres: jax.Array
    resolution: int = eqx.field(static=True)


class SurfaceTexture(eqx.Module):
    """One plane's radiance with the objects present, in some output channels
    (:func:`surface_textures`): what the camera-side lookup needs, nothing of the materials.

    Attributes:
        origin, axes, half: the plane's region (as :class:`SurfaceTransfer`).
        texels: (T, T, K) radiance over the region (row 0 at +t2, column 0 at −t1).
        base: (K,) radiance without the objects (everywhere outside the region too).
    """

    origin: jax.Array
    axes: jax.Array
    half: jax.Array
    texels: jax.Array
    base: jax.Array


class SurfaceLayer(eqx.Module):
    """The surfaces as a camera sees them (:func:`surface_layer`).

    Attributes:
        radiance: (H, W, K) the surfaces' radiance with the objects present, in the output
            channels (0 where no surface is seen).
        base: (H, W, K) their radiance without the objects (0 where none is seen).
        mask: (H, W) bool: a surface is seen (in front of the camera); objects may cover it.
    """

    radiance: jax.Array
    base: jax.Array
    mask: jax.Array


def hemisphere_directions(k: int) -> np.ndarray:
    """(k, 3) cosine-weighted directions in a local frame (z up): a Fibonacci spiral of equal
    areas on the unit disc lifted to the hemisphere (Malley's method), so that each carries
    about π/k of projected solid angle."""
    i = np.arange(k) + 0.5
    r = np.sqrt(i / k)
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - r * r, 0.0))],
                    axis=1)


def _plane_axes(normal: np.ndarray) -> np.ndarray:
    n = normal / np.linalg.norm(normal)
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    t1 = np.cross(a, n)
    t1 /= np.linalg.norm(t1)
    return np.stack([t1, np.cross(n, t1), n])


def _region(spec: Any, axes: np.ndarray, world: np.ndarray,
            slices: tuple[tuple[int, int], ...]) -> tuple[np.ndarray, float]:
    """Centre (3,) on the plane and half side of the square region around the objects'
    footprints, ``spec.margin`` bounding radii beyond them."""
    p0 = np.asarray(spec.point, np.float64)
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for a, b in slices:
        uv = (world[a:b] - p0) @ axes[:2].T
        lo, hi = np.minimum(lo, uv.min(0)), np.maximum(hi, uv.max(0))
    pad = spec.margin * float(_spheres(world, slices)[:, 3].max())
    lo, hi = lo - pad, hi + pad
    mid = 0.5 * (lo + hi)
    return p0 + mid @ axes[:2], float(0.5 * np.max(hi - lo))


def _cells(env: Any, dirs: np.ndarray, src_dirs: np.ndarray, src_flux: np.ndarray,
           normal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per direction (K): the environment's flux Φ_k (K, C) over its cell of the upper
    hemisphere without the bright sources, the cell's projected solid angle Ω⊥_k (K,), and
    the sources' sub-points' flux (S', C) times their cosine (world directions)."""
    from ..lighting import texel_directions, texel_solid_angles

    img = np.asarray(env.texels, np.float64)
    h, w, c = img.shape
    rot = np.asarray(env.rotation, np.float64)
    tex = texel_directions(h, w).reshape(-1, 3) @ rot.T
    cos = tex @ normal
    sa = texel_solid_angles(h, w).reshape(-1)
    up = cos > 0.0
    near = np.argmax(tex[up] @ dirs.T, axis=1)
    wts = (sa * cos)[up]
    flux = np.zeros((len(dirs), c))
    np.add.at(flux, near, img.reshape(-1, c)[up] * wts[:, None])
    proj = np.bincount(near, weights=wts, minlength=len(dirs))
    if len(src_dirs):
        cs = np.maximum(src_dirs @ normal, 0.0)
        s_near = np.argmax(src_dirs @ dirs.T, axis=1)
        np.add.at(flux, s_near, -src_flux * cs[:, None])
        return flux, proj, src_flux * cs[:, None]
    return flux, proj, np.zeros((0, c))


def build_surface_transfer(spec: Any, env: Any, vertices: np.ndarray, triangles: np.ndarray,
                           slices: tuple[tuple[int, int], ...], *,
                           directions: int = DIRECTIONS, capacity: int | None = None,
                           spheres: Any = None, progress: Any = None) -> SurfaceTransfer:
    """Precompute what the objects hide from, and show to, a plane (see the module docstring).

    Args:
        spec: the plane (:class:`~spectral_fit.io.SurfaceSpec`: point, normal, reflectance,
            margin, resolution).
        env: the frame's :class:`~spectral_fit.lighting.EnvironmentMap` (its unfiltered
            texels, rotation and bright sources).
        vertices: (V, 3) the objects' interreflection-mesh vertices in the WORLD (posed).
        triangles: (T, 3) int vertex indices; ``slices`` the vertex range of each object.
        directions: K, cosine-weighted directions over the hemisphere.
        capacity: hit capacity (default: the count on the capacity ladder).
        spheres: (O, 4) every object's bounding sphere (centre, radius; radius 0: not
            present), for what the objects hide of the plane from each other
            (:class:`TableChange`); default: those of ``slices``.
        progress: optional callable(done, total) after each batch of views.

    Returns:
        :class:`SurfaceTransfer` (JAX arrays).

    Raises:
        InputError: an object lies below the plane.
    """
    from ..geometry import capacity_ladder, plan_config, rasterize_batch

    world = np.asarray(vertices, np.float64)
    tris = np.asarray(triangles, np.int32)
    normal = np.asarray(spec.normal, np.float64)
    axes = _plane_axes(normal)
    p0 = np.asarray(spec.point, np.float64)
    height = (world - p0) @ normal
    for i, (a, b) in enumerate(slices):
        if height[a:b].max() <= 0.0:
            raise InputError(f"object {i} lies wholly below the plane (normal {spec.normal})",
                             field=f"surfaces.{spec.name}")
    origin, half = _region(spec, axes, world, slices)
    t = int(spec.resolution)
    local = hemisphere_directions(int(directions))
    local = local[local[:, 2] > _MIN_COS]
    dirs = local @ axes
    src_dirs = np.asarray(env.source_dirs, np.float64).reshape(-1, 3) @ np.asarray(
        env.rotation, np.float64).T
    k_sub = max(int(env.source_dirs.shape[1]), 1)
    src_flux = np.repeat(np.asarray(env.source_flux_full, np.float64) / k_sub, k_sub, axis=0)
    keep = src_dirs @ normal > _MIN_COS
    src_dirs, src_flux = src_dirs[keep], src_flux[keep]
    flux, proj, sflux = _cells(env, dirs, src_dirs, src_flux, normal)
    views = np.concatenate([dirs, src_dirs]) if len(src_dirs) else dirs
    view_flux = np.concatenate([flux, sflux])
    n_dir = len(dirs)

    # oblique projections onto the region: (u, v) across, depth s along the direction
    hgt = np.maximum(height, 0.0)
    cosd = views @ normal  # (D,)
    s = hgt[None, :] / cosd[:, None]  # (D, V)
    s_max = float(s.max()) * 1.01 + 1e-9
    foot = world[None] - s[..., None] * views[:, None, :] - origin
    clip = np.stack([foot @ axes[0] / half, foot @ axes[1] / half,
                     2.0 * s / s_max - 1.0, np.ones_like(s)], axis=-1).astype(np.float32)
    size = (t, t)
    config = plan_config(clip, tris, size, cull="none", headroom=1.1)
    tj = jnp.asarray(tris)
    hidden_count = np.zeros((len(views), t * t), np.float32)
    hit_t, hit_v, hit_k = [], [], []
    for start in range(0, len(views), _BATCH):
        stop = min(start + _BATCH, len(views))
        batch = clip[start:stop]
        if stop - start < _BATCH:
            batch = np.concatenate([batch, np.repeat(batch[-1:], _BATCH - (stop - start), 0)])
        ras = rasterize_batch(jnp.asarray(batch), tj, size, cull="none", config=config)
        tri_id = np.asarray(ras.tri_id[:stop - start]).reshape(stop - start, -1)
        bary = np.asarray(ras.bary[:stop - start]).reshape(stop - start, t * t, 3)
        hit = tri_id >= 0
        hidden_count[start:stop] = hit
        for j in range(stop - start):
            if start + j >= n_dir:
                continue  # a source's direction: its solid angle shows no object light
            texels = np.nonzero(hit[j])[0]
            corner = np.argmax(bary[j, texels], axis=1)
            hit_t.append(texels)
            hit_v.append(tris[tri_id[j, texels], corner])
            hit_k.append(np.full(len(texels), start + j))
        if progress is not None:
            progress(stop, len(views))
    hidden = hidden_count.T @ view_flux  # (T², C)
    pt = np.concatenate(hit_t) if hit_t else np.zeros(0, np.int64)
    pv = np.concatenate(hit_v) if hit_v else np.zeros(0, np.int64)
    pk = np.concatenate(hit_k) if hit_k else np.zeros(0, np.int64)
    # the (vertex, direction) pairs seen: each is shaded once (its diffuse and its gloss
    # towards the plane); every hit is a (texel, pair) entry weighted by Ω⊥ of its direction
    uniq, inv = np.unique(pv.astype(np.int64) * n_dir + pk, return_inverse=True)
    u_cap = capacity_ladder(len(uniq), 64)
    q_cap = capacity_ladder(len(pt), 64) if capacity is None else int(capacity)
    if q_cap < len(pt):
        raise InputError(f"capacity {q_cap} below the {len(pt)} hits needed",
                         field="capacity")
    u_vertex = np.zeros(u_cap, np.int64)
    u_vertex[:len(uniq)] = uniq // n_dir
    u_view = np.zeros((u_cap, 3))
    u_view[:, 1] = 1.0
    u_view[:len(uniq)] = -dirs[uniq % n_dir]  # from the object back to the texel
    u_object = np.full(u_cap, -1, np.int64)
    vobj = np.zeros(len(world), np.int64)
    for i, (a, b) in enumerate(slices):
        vobj[a:b] = i
    u_object[:len(uniq)] = vobj[uniq // n_dir] if len(uniq) else 0
    pad = q_cap - len(pt)
    from ..lighting import upper_irradiance

    upper = upper_irradiance(np.asarray(env.texels, np.float64),
                             np.asarray(env.rotation, np.float64).T @ normal)
    return SurfaceTransfer(
        origin=jnp.asarray(origin, jnp.float32), axes=jnp.asarray(axes, jnp.float32),
        half=jnp.asarray(half, jnp.float32),
        reflectance=jnp.asarray(spec.reflectance, jnp.float32),
        upper=jnp.asarray(upper, jnp.float32), hidden=jnp.asarray(hidden, jnp.float32),
        hit_texel=jnp.asarray(np.concatenate([pt, np.zeros(pad, np.int64)]), jnp.int32),
        hit_pair=jnp.asarray(np.concatenate([inv.reshape(-1), np.zeros(pad, np.int64)]),
                             jnp.int32),
        hit_weight=jnp.asarray(np.concatenate([proj[pk], np.zeros(pad)]), jnp.float32),
        pair_vertex=jnp.asarray(u_vertex, jnp.int32),
        pair_view=jnp.asarray(u_view, jnp.float32),
        pair_object=jnp.asarray(u_object, jnp.int32),
        spheres=jnp.asarray(_spheres(world, slices) if spheres is None else spheres,
                            jnp.float32),
        resolution=t)


def _spheres(world: np.ndarray, slices: Any) -> np.ndarray:
    """(O, 4) bounding spheres (centre of the box, largest distance) of the slices."""
    out = np.zeros((len(slices), 4))
    for i, (a, b) in enumerate(slices):
        v = world[a:b]
        c = 0.5 * (v.min(0) + v.max(0))
        out[i] = (*c, float(np.linalg.norm(v - c, axis=1).max()))
    return out


def surface_transfer(surfaces: Any, env: Any, ir_mesh: Any, model: Any, *,
                     visible: Any = None, progress: Any = None
                     ) -> tuple[SurfaceTransfer, ...]:
    """The :class:`SurfaceTransfer` of every plane of ``surfaces`` (a scene's
    :class:`~spectral_fit.io.SurfaceSpec` s) for the objects of ``ir_mesh`` (the prepared
    scene's ``ir_mesh``) at ``model`` (O, 4, 4), under ``env`` (``prep.lighting.env``);
    ``visible`` (O,) bool: only those objects cast shadows (default all). Rebuild it when the
    objects move relative to the planes (no gradient); the per-frame work
    (:func:`surface_layer`) stays the same program while the pair capacity holds."""
    m = np.asarray(model, np.float64)
    obj = np.asarray(ir_mesh.vertex_object)
    v = np.asarray(ir_mesh.vertices, np.float64)
    world = np.einsum("vij,vj->vi", m[obj][:, :3, :3], v) + m[obj][:, :3, 3]
    tris = np.asarray(ir_mesh.triangles)
    slices = tuple(ir_mesh.object_slices)
    spheres = _spheres(world, slices)
    if visible is not None:
        keep = np.asarray(visible, bool)
        tris = tris[keep[np.asarray(ir_mesh.tri_object)]]
        slices = tuple(sl for sl, k in zip(slices, keep, strict=True) if k)
        spheres[~keep, 3] = 0.0
    return tuple(build_surface_transfer(s, env, world, tris, slices, spheres=spheres,
                                        progress=progress) for s in surfaces)


def surface_texels(prep: Any, st: SurfaceTransfer, materials: Any, model: jax.Array, *,
                   passes: int = 2, neighbours: jax.Array | None = None) -> jax.Array:
    """The plane's irradiance E(x) (T², C) in the environment's channels with the objects at
    ``model`` (their radiance from their materials; the hidden environment from ``st``'s
    poses). ``passes`` 2: the objects' radiance towards the plane is computed again with
    what they see of the plane's own change (:class:`TableChange`: a sphere's underside
    over its contact shadow is darker than over a uniform table); 1: over a uniform table.
    ``neighbours`` (V, C): what the other objects change of the irradiance at each vertex of
    ``prep.ir_mesh`` (:func:`neighbour_irradiance`), added to the vertices' irradiance map
    (None: nothing)."""
    return _texels_jit(prep, st, materials, jnp.asarray(model, jnp.float32),
                       passes=max(int(passes), 1), neighbours=neighbours)


def _surface_texels(prep: Any, st: SurfaceTransfer, materials: Any, model: jax.Array, *,
                    passes: int, neighbours: jax.Array | None) -> jax.Array:
    """:func:`surface_texels`, traced (compiled once per scene: eagerly its operations were
    each compiled apart, ~20 s in every new process)."""
    from ._materials import _as_stacked
    from ._shading import _filtered_irradiance, _irradiance_at, _lut_env, specular_at

    mats = _as_stacked(prep.materials if materials is None else materials, prep.num_objects)
    mesh = prep.ir_mesh
    env = prep.lighting.env
    lut = prep.lighting.irradiance_lut
    table = None if lut is None else _lut_env(env, lut)
    world, nrm = _posed(mesh, model)
    e_map = _irradiance_at(env, table, nrm)
    if neighbours is not None:
        e_map = e_map + neighbours
    n_pair = nrm[st.pair_vertex]
    lt = prep.lighting
    spec = [specular_at(m, env, n_pair, st.pair_view, quality=lt.quality,
                        split_map=lt.split_map, split_settings=lt.split_settings)
            for m in mats]
    t2 = st.resolution * st.resolution
    change = None
    for step in range(max(int(passes), 1)):
        e_v, dl_r = e_map, None
        if change is not None:  # what the vertices see of the plane's change
            d_e, dl_r = change.at(world, nrm, mesh.vertex_object, st.pair_vertex,
                                  st.pair_view)
            e_v = e_map + d_e
        # each (vertex, direction) pair's radiance towards the plane: its diffuse light and
        # its gloss and mirror along that direction (each object's material on its pairs)
        diffuse = jnp.concatenate(
            [(m.alpha / math.pi) * _filtered_irradiance(m, env, e_v[a:b])
             for (a, b), m in zip(mesh.object_slices, mats, strict=True)], axis=0)
        light = diffuse[st.pair_vertex]
        for i, m in enumerate(mats):
            own = spec[i]
            if dl_r is not None:
                own = own + change.reflected(m, n_pair, st.pair_view, dl_r)
            light = light + jnp.where((st.pair_object == i)[:, None], own, 0.0)
        seen = jax.ops.segment_sum(st.hit_weight[:, None] * light[st.hit_pair], st.hit_texel,
                                   num_segments=t2)
        e = st.upper[None, :] + seen - st.hidden
        if step + 1 < passes:  # the next pass sees this one's change
            change = TableChange.of(st, e, env)
    return e


def _posed(mesh: Any, model: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The mesh's vertices (V, 3) and unit normals (V, 3) placed in the world by ``model``
    (O, 4, 4)."""
    from ._camera import _normals_to_world, _to_world

    return (_to_world(mesh.vertices, mesh.vertex_object, model),
            _normals_to_world(mesh.normals, mesh.vertex_object, model))


_texels_jit = array_jit(_surface_texels)


def neighbour_irradiance(prep: Any, materials: Any = None, *, model: Any = None,
                         visible: Any = None) -> jax.Array | None:
    """(V, C) the change of the irradiance at each vertex of ``prep.ir_mesh`` (posed by
    ``model``) that the other objects make: their light, less the environment they hide
    (the gather interreflection's samples' net light after its bounces, interpolated as the
    frame's pixels get it; :func:`~spectral_fit.rendering.render_senders`,
    ``interreflection.gather_irradiance``). The objects' radiance towards a plane takes it:
    a sphere's side facing its neighbour is darker, and so is the table in the gap between
    them. None unless the interreflection is the gather mode with two objects or more."""
    from ._ir_stage import render_senders

    ir = prep.interreflection
    if ir.mode != "gather" or prep.num_objects < 2 or ir.bounces < 1:
        return None
    model = jnp.asarray(prep.model if model is None else model, jnp.float32)
    state = render_senders(prep, materials, model=model, visible=visible)
    if state.net is None:
        return None
    return _vertex_net_jit(state, prep.ir_mesh, model)


def _vertex_net(state: Any, mesh: Any, model: jax.Array) -> jax.Array:
    from .interreflection import gather_irradiance

    world, nrm = _posed(mesh, model)
    return gather_irradiance(state, world, nrm, mesh.vertex_object)


_vertex_net_jit = array_jit(_vertex_net)


def _neighbours(prep: Any, materials: Any, model: Any, neighbours: Any) -> jax.Array | None:
    """``neighbours`` as given, or :func:`neighbour_irradiance` for "auto"."""
    if isinstance(neighbours, str):
        if neighbours != "auto":
            raise InputError(f"expected 'auto', None or an array, got {neighbours!r}",
                             field="neighbours")
        return neighbour_irradiance(prep, materials, model=model)
    return neighbours


class TableChange(eqx.Module):
    """What a point above the plane sees of the plane's change L(x) − ρ E_up/π (the
    objects' shadows and light on it), which the grounded environment does not carry.

    Attributes:
        fine: (T, T, C) the change of radiance over the region (environment channels).
        coarse: (G², C) the same averaged over G × G cells, and ``centres`` (G², 3) their
            world centres, ``area`` () their area (m²): the diffuse sum far from a point.
        near: (G·S, G·S, C) the same over cells S times smaller, ``near_centres``
            (G·S, G·S, 3), ``near_area`` (): the diffuse sum next to a point (the 3 × 3
            coarse cells around its foot on the plane), where a contact shadow changes within
            a coarse cell.
        origin, axes, half: the region (as :class:`SurfaceTransfer`).
        spheres: (O, 4) the objects' bounding spheres: a cell behind another object than
            the point's own is hidden from it (exact for spheres).
        vertex_irradiance: (V, C) the diffuse change at the camera mesh's vertices at the
            poses it was built for (:func:`table_changes`), or None.
    """

    fine: jax.Array
    coarse: jax.Array
    centres: jax.Array
    area: jax.Array
    near: jax.Array
    near_centres: jax.Array
    near_area: jax.Array
    origin: jax.Array
    axes: jax.Array
    half: jax.Array
    spheres: jax.Array
    vertex_irradiance: jax.Array | None = None

    @staticmethod
    def of(st: SurfaceTransfer, e: jax.Array, env: Any, cells: int = 16,
           split: int = 4) -> TableChange:
        """From the plane's irradiance ``e`` (T², C) (bands: ρ applies per channel; in basis
        coefficients the change is not carried, zero): ``cells`` × ``cells`` coarse cells,
        each split into ``split`` × ``split`` near-field cells (at most the texels)."""
        t = st.resolution
        if env.product_tensor is None:
            dl = (e - st.upper[None, :]) * (st.reflectance / math.pi)[None, :]
        else:
            dl = jnp.zeros_like(e)
        return TableChange.from_fine(dl.reshape(t, t, -1), origin=st.origin, axes=st.axes,
                                     half=st.half, spheres=st.spheres, cells=cells,
                                     split=split)

    @staticmethod
    def from_fine(fine: jax.Array, *, origin: jax.Array, axes: jax.Array, half: Any,
                  spheres: jax.Array, cells: int = 16, split: int = 4) -> TableChange:
        """From the change of radiance ``fine`` (T, T, C) over the square region of half
        side ``half`` about ``origin`` (``axes`` (3, 3): t1, t2, normal; texel row 0 at +t2,
        the module's convention) and the objects' bounding ``spheres`` (O, 4)."""
        fine = jnp.asarray(fine, jnp.float32)
        axes = jnp.asarray(axes, jnp.float32)
        origin = jnp.asarray(origin, jnp.float32)
        half = jnp.asarray(half, jnp.float32)
        t = fine.shape[0]
        g = min(int(cells), t)
        while t % g:
            g -= 1
        sub = max(min(int(split), t // g), 1)
        while (t // g) % sub:
            sub -= 1

        def cells_of(n: int) -> tuple[jax.Array, jax.Array]:
            f = t // n
            mean = fine.reshape(n, f, n, f, -1).mean(axis=(1, 3))
            c = (jnp.arange(n, dtype=jnp.float32) + 0.5) * 2.0 / n - 1.0
            u = jnp.tile(c, n)  # column index fastest, row 0 at +t2
            v = -jnp.repeat(c, n)
            centres = origin + half * (u[:, None] * axes[0] + v[:, None] * axes[1])
            return mean, centres.reshape(n, n, 3)

        coarse, centres = cells_of(g)
        near, near_centres = cells_of(g * sub)
        return TableChange(fine=fine, coarse=coarse.reshape(g * g, -1),
                           centres=centres.reshape(g * g, 3), area=(2.0 * half / g) ** 2,
                           near=near, near_centres=near_centres,
                           near_area=(2.0 * half / (g * sub)) ** 2, origin=origin,
                           axes=axes, half=half, spheres=jnp.asarray(spheres, jnp.float32))

    def _kernel(self, points: jax.Array, normals: jax.Array, owner: jax.Array | None,
                centres: jax.Array, area: jax.Array) -> jax.Array:
        """(N, M) cosθ_p cosθ_x A / max(d², A/π) from each point to cells of area ``area``
        at ``centres`` ((M, 3) shared, or (N, M, 3) per point), 0 behind the point's tangent
        plane and where the segment passes through an object other than ``owner``."""
        rel = (centres[None] if centres.ndim == 2 else centres) - points[:, None, :]
        dist2 = jnp.sum(rel * rel, -1)
        inv = jax.lax.rsqrt(jnp.maximum(dist2, 1e-12))
        cos_p = jnp.maximum(jnp.sum(rel * normals[:, None, :], -1), 0.0) * inv
        cos_x = jnp.maximum(-(rel @ self.axes[2]), 0.0) * inv
        k = cos_p * cos_x * (area / jnp.maximum(dist2, area / math.pi))
        if owner is not None:
            for j in range(self.spheres.shape[0]):
                c, r = self.spheres[j, :3], self.spheres[j, 3]
                # the segment p → x against sphere j: its closest point to the centre
                pc = c - points  # (N, 3)
                s_ = jnp.clip(jnp.einsum("ngk,nk->ng", rel, pc) / jnp.maximum(dist2, 1e-12),
                              0.0, 1.0)
                q = points[:, None, :] + s_[..., None] * rel - c
                hit = (jnp.sum(q * q, -1) < r * r) & (owner != j)[:, None]
                k = jnp.where(hit, 0.0, k)
        return k

    def diffuse(self, points: jax.Array, normals: jax.Array, owner: jax.Array | None = None
                ) -> jax.Array:
        """The change (N, C) of the irradiance at ``points`` (N, 3) with ``normals`` (N, 3):
        Σ_cells ΔL cosθ_p cosθ_x A / max(d², A/π) over the cells in front of the point's
        tangent plane (a point on a cell sees it as its hemisphere: no singularity at the
        contact), cells behind an object other than the point's ``owner`` (N,) int left
        out. The coarse cells everywhere but the 3 × 3 around the point's foot on the
        plane, which are summed over their near-field cells."""
        g = math.isqrt(self.coarse.shape[0])
        sub = self.near.shape[0] // g
        # the coarse cell under each point and its 3 × 3 block (cells outside: none)
        rel = points - self.origin
        col = jnp.floor((_dot(rel.T, self.axes[0]) / self.half + 1.0) * 0.5 * g)
        row = jnp.floor((1.0 - _dot(rel.T, self.axes[1]) / self.half) * 0.5 * g)
        cell = jnp.arange(g * g)
        block = ((jnp.abs(cell // g - row[:, None]) <= 1)
                 & (jnp.abs(cell % g - col[:, None]) <= 1))  # (N, G²)
        k = self._kernel(points, normals, owner, self.centres, self.area)
        far = jnp.where(block, 0.0, k) @ self.coarse
        off = jnp.arange(-1, 2, dtype=jnp.int32)
        br = jnp.clip(row, -2, g + 1).astype(jnp.int32)[:, None] + off  # (N, 3)
        bc = jnp.clip(col, -2, g + 1).astype(jnp.int32)[:, None] + off
        in_r, in_c = (br >= 0) & (br < g), (bc >= 0) & (bc < g)
        br, bc = jnp.clip(br, 0, g - 1), jnp.clip(bc, 0, g - 1)
        m = points.shape[0]
        # the same block in near-field cells: row a·S + i, column b·S + j
        step = jnp.arange(sub, dtype=jnp.int32)
        rr = (br * sub)[:, :, None] + step  # (N, 3, S)
        cc = (bc * sub)[:, :, None] + step
        shape = (m, 3, sub, 3, sub)
        rows = jnp.broadcast_to(rr[:, :, :, None, None], shape).reshape(m, -1)
        cols = jnp.broadcast_to(cc[:, None, None, :, :], shape).reshape(m, -1)
        ok = jnp.broadcast_to(in_r[:, :, None, None, None] & in_c[:, None, None, :, None],
                              shape).reshape(m, -1)
        k_n = self._kernel(points, normals, owner, self.near_centres[rows, cols],
                           self.near_area)
        return far + jnp.einsum("nm,nmc->nc", jnp.where(ok, k_n, 0.0), self.near[rows, cols])

    def mirrored(self, points: jax.Array, normals: jax.Array, views: jax.Array,
                 owner: jax.Array | None = None, table: jax.Array | None = None
                 ) -> jax.Array:
        """The change (N, C) of the radiance along each point's mirror direction where it
        meets the plane inside the region (else 0, and 0 where the ray passes through
        another object than the point's ``owner`` (N,) first). ``table``: the fine change
        in other channels (T, T, D), e.g. already in a frame's output channels (then
        (N, D)). Products of (N, 3) arrays with single vectors as elementwise sums (a
        matrix product with an inner size of 3 is slow on the CPU: :func:`_dot`)."""
        nv = jnp.sum(normals * views, -1, keepdims=True)
        r = 2.0 * nv * normals - views
        down = _dot(r.T, self.axes[2])
        t = (self.origin @ self.axes[2] - _dot(points.T, self.axes[2])) / jnp.where(
            down < -1e-6, down, -1e-6)
        hit = points + t[:, None] * r
        u = (_dot(hit.T, self.axes[0]) - self.origin @ self.axes[0]) / self.half
        v = (_dot(hit.T, self.axes[1]) - self.origin @ self.axes[1]) / self.half
        fine = self.fine if table is None else table
        val = _bilinear(fine, u, v, jnp.zeros((fine.shape[-1],), jnp.float32))
        seen = (down < -1e-6) & (t > 0.0)
        if owner is not None:
            for j in range(self.spheres.shape[0]):
                pc = self.spheres[j, :3] - points
                along = jnp.clip(jnp.sum(pc * r, -1), 0.0, jnp.maximum(t, 0.0))
                q = pc - along[:, None] * r
                blocked = (jnp.sum(q * q, -1) < self.spheres[j, 3] ** 2) & (owner != j)
                seen = seen & ~blocked
        return jnp.where(seen[:, None], val, 0.0)

    @staticmethod
    def reflected(m: Any, normals: jax.Array, views: jax.Array, change: jax.Array
                  ) -> jax.Array:
        """β A(θ) + χ F(θ) times the mirrored change (N, C): what the gloss and mirror of
        material ``m`` reflect of it (the lobe treated as a whole along its mirror
        direction)."""
        return _reflecting(m, normals, views) * change

    def at(self, world: jax.Array, nrm: jax.Array, owner: jax.Array, pair_vertex: jax.Array,
           pair_view: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(the diffuse change (V, C) at every vertex, the mirrored change (U, C) of every
        (vertex, direction) pair)."""
        return (_diffuse_chunks(self, world, nrm, owner),
                self.mirrored(world[pair_vertex], nrm[pair_vertex], pair_view,
                              owner[pair_vertex]))


def table_changes(prep: Any, transfers: tuple[SurfaceTransfer, ...] | None = None,
                  materials: Any = None, model: Any = None, *,
                  neighbours: Any = "auto") -> tuple[TableChange, ...]:
    """Each plane's :class:`TableChange` for the objects' ``materials`` (default the
    config's) at ``model`` (default the prepared poses), with its diffuse part at the
    camera mesh's vertices: what :func:`surface_vertices` and :func:`surface_pixels` add to
    the objects. :func:`prepare` keeps it for the configured materials
    (``Prepared.surface_changes``). ``neighbours``: as :func:`surface_texels` ("auto":
    :func:`neighbour_irradiance` of these materials and poses)."""
    model = jnp.asarray(prep.model if model is None else model, jnp.float32)
    neighbours = _neighbours(prep, materials, model, neighbours)
    env = prep.lighting.env
    mesh = prep.mesh
    world, nrm = _posed(mesh, model)
    out = []
    for st in (prep.surfaces if transfers is None else transfers):
        ch = TableChange.of(st, surface_texels(prep, st, materials, model,
                                               neighbours=neighbours), env)
        out.append(eqx.tree_at(lambda c: c.vertex_irradiance, ch,
                               _diffuse_chunks(ch, world, nrm, mesh.vertex_object),
                               is_leaf=lambda x: x is None))
    return tuple(out)


#: points per compiled call of :func:`_diffuse_chunks`
_CHUNK = 4096


def _diffuse_chunk(change: TableChange, points: jax.Array, normals: jax.Array,
                   owner: jax.Array) -> jax.Array:
    return change.diffuse(points, normals, owner)


_diffuse_jit = array_jit(_diffuse_chunk)


def _diffuse_chunks(change: TableChange, points: jax.Array, normals: jax.Array,
                    owner: jax.Array) -> jax.Array:
    """``change.diffuse`` (N, C) in chunks of :data:`_CHUNK` points (the last one padded), one
    compiled program for every chunk (eagerly, its many small operations each compiled
    apart took ~15 s at a scene's first preparation)."""
    n = points.shape[0]
    parts = []
    for a in range(0, n, _CHUNK):
        k = min(_CHUNK, n - a)
        pad = _CHUNK - k
        args = [jnp.pad(x[a:a + k], ((0, pad),) + ((0, 0),) * (x.ndim - 1))
                for x in (points, normals, owner)]
        if pad:  # padded points: at the origin with a unit normal (their result is dropped)
            args[1] = args[1].at[k:, 1].set(1.0)
        parts.append(_diffuse_jit(change, *args)[:k])
    return jnp.concatenate(parts, axis=0)


def surface_vertices(prep: Any, changes: tuple[TableChange, ...], mats: list[Any],
                     to_out: jax.Array) -> jax.Array:
    """The change (V, D) of the camera mesh's vertices' diffuse radiance in the output
    channels ``to_out`` (C, D) from the planes' ``changes`` (their ``vertex_irradiance``):
    interpolated over the triangles with the geometry, as the self-occlusion's change."""
    from ._shading import _filtered_irradiance

    env = prep.lighting.env
    e = sum(c.vertex_irradiance for c in changes)  # (V, C)
    out = []
    for (a, b), m in zip(prep.mesh.object_slices, mats, strict=True):
        out.append(((m.alpha / math.pi) * _filtered_irradiance(m, env, e[a:b])) @ to_out)
    return jnp.concatenate(out, axis=0)


def surface_pixels(prep: Any, changes: tuple[TableChange, ...], mats: list[Any], gb: Any,
                   to_out: jax.Array) -> jax.Array:
    """The change (N, D) of the covered pixels' gloss and mirror (G-buffer ``gb``, laid out
    object after object with ``prep.buffers.pixel_capacity``) in the output channels
    ``to_out`` (C, D) where their mirror direction meets a plane's ``changes`` (their diffuse
    part: :func:`surface_vertices`): β A(θ) + χ F(θ) of each object's pixels (one scalar per
    pixel) times the change looked up in the output channels (the planes' fine change
    projected first: D channels per lookup, not C). Differentiable in ``mats`` through the
    pixels' own reflection; the change itself is that of the materials it was computed with
    (a second-order term)."""
    from ._shading import _object_slices

    albedo = jnp.concatenate([_reflecting(m, nrm, v) for m, (nrm, v) in
                              zip(mats, _object_slices(gb, prep.buffers.pixel_capacity),
                                  strict=True)])  # (N, 1)
    out = jnp.zeros((gb.position.shape[0], to_out.shape[1]), jnp.float32)
    for change in changes:
        table = change.fine @ to_out  # (T, T, D)
        out = out + change.mirrored(gb.position, gb.normal, gb.view, gb.object, table=table)
    return albedo * out


def _reflecting(m: Any, normals: jax.Array, views: jax.Array) -> jax.Array:
    """β A(θ) + χ F(θ) (N, 1) of material ``m`` at the points' normals and views (N, 3):
    the share of a change around the mirror direction its gloss and mirror reflect."""
    from ..lighting import lobe_moment_table
    from ._materials import mirror_needed
    from ._shading import lobe_albedo

    moments = lobe_moment_table(m.mu, m.n, distribution=m.distribution, geometry=m.geometry)
    nv = jnp.clip(jnp.sum(normals * views, -1, keepdims=True), 0.0, 1.0)
    return lobe_albedo(m, moments, nv, mirror=mirror_needed([m]))


def _dot(components: Any, b: jax.Array) -> jax.Array:
    """Σ_i components[i] · b[i] over three components ((N,) arrays, or the rows of an
    (N, 3) array's transpose) and a vector (3,): elementwise, where a matrix product with
    an inner size of 3 is slow on the CPU."""
    return components[0] * b[0] + components[1] * b[1] + components[2] * b[2]


def _pixel_rays(prep: Any, view: jax.Array) -> tuple[tuple[jax.Array, ...], jax.Array]:
    """The world-frame ray directions of the pixel centres (not normalised) as three
    components (H·W,) each, and the eye (3,)."""
    from ..geometry import eye_position
    from ._background import _pinhole_ray_components

    rays = prep.camera.pixel_rays
    if rays is not None:  # (H·W, 3) eye-space rays through the lens: rotated to the world
        rot = view[:3, :3]
        comp = [rays[:, 0] * rot[0, j] + rays[:, 1] * rot[1, j] + rays[:, 2] * rot[2, j]
                for j in range(3)]
    else:
        comp = [c.reshape(-1) for c in
                _pinhole_ray_components(prep, view, jnp.eye(3, dtype=jnp.float32))]
    return tuple(comp), eye_position(view)


def surface_textures(prep: Any, transfers: tuple[SurfaceTransfer, ...], materials: Any = None,
                     *, model: Any = None, out: Any = None,
                     neighbours: Any = "auto") -> tuple[SurfaceTexture, ...]:
    """Each plane's radiance ρ E(x)/π over its region, in output channels.

    Args:
        prep: the prepared scene.
        transfers: one :class:`SurfaceTransfer` per plane (``prep.surfaces`` or
            :func:`surface_transfer`).
        materials: the objects' materials (default: the config's).
        model: (O, 4, 4) the objects' poses for their radiance (default: the prepared ones;
            the shadows are those of the transfers' poses).
        out: (L, K) spectral radiance → output channels (default: absolute XYZ); e.g. a video
            camera's spectral weights.
        neighbours: (V, C) what the other objects change of the irradiance at the vertices
            of ``prep.ir_mesh`` (:func:`neighbour_irradiance`, computed once and passed to
            both this and :func:`table_changes`); "auto": computed here; None: left out.

    Returns:
        one :class:`SurfaceTexture` per plane (differentiable in ``materials``).
    """
    from ..color import xyz_weights

    model = jnp.asarray(prep.model if model is None else model, jnp.float32)
    col = prep.colour
    if out is None:
        out = jnp.asarray(xyz_weights(np.asarray(col.wavelengths)), jnp.float32)
    out = jnp.asarray(out, jnp.float32)
    neighbours = _neighbours(prep, materials, model, neighbours) if transfers else None
    result = []
    for st in transfers:
        e = surface_texels(prep, st, materials, model, neighbours=neighbours)  # (T², C)
        scale = st.reflectance / math.pi
        t = st.resolution
        tex = (((e @ col.to_spectrum) * scale) @ out).reshape(t, t, -1)
        base = ((st.upper @ col.to_spectrum) * scale) @ out
        result.append(SurfaceTexture(origin=st.origin, axes=st.axes, half=st.half,
                                     texels=tex, base=base))
    return tuple(result)


def surface_layer(prep: Any, transfers: tuple[SurfaceTransfer, ...] | None = None,
                  materials: Any = None, *, model: Any = None, view: Any = None,
                  out: Any = None, textures: tuple[SurfaceTexture, ...] | None = None
                  ) -> SurfaceLayer:
    """The surfaces seen through each pixel centre, with and without the objects.

    Args:
        prep: the prepared scene.
        transfers: one :class:`SurfaceTransfer` per plane (default ``prep.surfaces``).
        materials, model, out: as :func:`surface_textures`.
        view: (4, 4) world → eye (default: the config's camera).
        textures: the planes' :class:`SurfaceTexture` s already computed (then
            ``transfers``, ``materials``, ``model`` and ``out`` are not used): a live session
            computes them once per placement of the objects.

    Returns:
        :class:`SurfaceLayer` (H, W, K); where several planes are seen, the nearest.
    """
    if textures is None:
        textures = surface_textures(prep, prep.surfaces if transfers is None else transfers,
                                    materials, model=model, out=out)
    h, w = prep.camera.shape
    k = textures[0].base.shape[0] if textures else 3
    rad, base, seen = _plane_lookups(prep, view, textures, k)
    return SurfaceLayer(radiance=rad.reshape(h, w, k), base=base.reshape(h, w, k),
                        mask=seen.reshape(h, w))


def surface_ratio_textures(textures: tuple[SurfaceTexture, ...]) -> tuple[SurfaceTexture, ...]:
    """Each plane's texture as the ratio (with / without the objects) per texel and channel,
    clipped to [0, 4], exactly 1 where the texel's radiance equals the plane's radiance
    without the objects; ``base`` is 1. The plane's radiance without the objects is one
    value per channel, so the bilinear lookup of the ratio equals the ratio of the lookups:
    a live session divides once per placement (T² texels), not per pixel per frame."""
    out = []
    for tx in textures:
        ok = tx.base > 1e-6
        r = jnp.where(ok, tx.texels / jnp.where(ok, tx.base, 1.0), 1.0)
        out.append(eqx.tree_at(lambda t: (t.texels, t.base), tx,
                               (jnp.clip(r, 0.0, 4.0), jnp.ones_like(tx.base))))
    return tuple(out)


def surface_ratio_lookup(prep: Any, textures: tuple[SurfaceTexture, ...], *,
                         view: Any = None) -> jax.Array:
    """(H, W, K) the ratio the objects make on the surfaces through each pixel centre, read
    from :func:`surface_ratio_textures`; exactly 1 where no plane is seen or outside the
    planes' regions. ``view``: (4, 4) world → eye (default: the config's camera). Equal to
    :func:`surface_ratio` of :func:`surface_layer` in the layer's own channels, without an
    object mask."""
    h, w = prep.camera.shape
    k = textures[0].base.shape[0]
    rad, _, seen = _plane_lookups(prep, view, textures, k)
    return jnp.where(seen[:, None], rad, 1.0).reshape(h, w, k)


def _plane_lookups(prep: Any, view: Any, textures: tuple[SurfaceTexture, ...], k: int
                   ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(texture values (H·W, K) of the nearest plane seen through each pixel centre, that
    plane's ``base`` (H·W, K), seen (H·W,)); 0 where none is seen. Ray–plane intersections
    from the rays' three components (H·W,) each, as elementwise sums (no (N, 3) products)."""
    view = jnp.asarray(prep.camera.view if view is None else view, jnp.float32)
    d, eye = _pixel_rays(prep, view)
    n_px = d[0].shape[0]
    best = jnp.full((n_px,), jnp.inf)
    rad = jnp.zeros((n_px, k), jnp.float32)
    base = jnp.zeros_like(rad)
    for tx in textures:
        n = tx.axes[2]
        denom = _dot(d, n)
        dist = ((tx.origin - eye) @ n) / jnp.where(jnp.abs(denom) > 1e-12, denom, 1e-12)
        hit = (dist > 0.0) & (denom < 0.0) & (dist < best)
        rel = eye - tx.origin  # p − origin = rel + dist · d
        u = (rel @ tx.axes[0] + dist * _dot(d, tx.axes[0])) / tx.half
        v = (rel @ tx.axes[1] + dist * _dot(d, tx.axes[1])) / tx.half
        val = _bilinear(tx.texels, u, v, tx.base)
        rad = jnp.where(hit[:, None], val, rad)
        base = jnp.where(hit[:, None], tx.base[None, :], base)
        best = jnp.where(hit, dist, best)
    return rad, base, jnp.isfinite(best)


def _bilinear(tex: jax.Array, u: jax.Array, v: jax.Array, outside: jax.Array) -> jax.Array:
    """Bilinear lookups (N, K) of ``tex`` (T, T, K) at region coordinates ``u``, ``v`` (N,)
    in [−1, 1] (the module's texel convention); ``outside`` (K,) beyond the region. The
    four neighbours of every texel are packed side by side ((T − 1)², 4K), one gather per
    lookup; interpolated as a + f (b − a), so equal neighbours give their value exactly.
    The texel coordinates are computed into memory first (``materialise_each(cut=True)``):
    XLA:CPU otherwise recomputes their whole expression (a frame's rays and the ray–plane
    intersection) inside the gather and each of its consumers, 4× the lookup's time at
    720×480."""
    t, kc = tex.shape[0], tex.shape[-1]
    x, y = materialise_each((u + 1.0) * 0.5 * t - 0.5, (1.0 - v) * 0.5 * t - 0.5, cut=True)
    inside = (x > -0.5) & (x < t - 0.5) & (y > -0.5) & (y < t - 0.5)
    x0 = jnp.clip(jnp.floor(x), 0, t - 2)
    y0 = jnp.clip(jnp.floor(y), 0, t - 2)
    fx = jnp.clip(x - x0, 0.0, 1.0)[:, None]
    fy = jnp.clip(y - y0, 0.0, 1.0)[:, None]
    packed = jnp.concatenate([tex[:-1, :-1], tex[:-1, 1:], tex[1:, :-1], tex[1:, 1:]],
                             axis=-1).reshape((t - 1) * (t - 1), 4 * kc)
    g = packed[y0.astype(jnp.int32) * (t - 1) + x0.astype(jnp.int32)]
    t00, t01, t10, t11 = (g[:, i * kc:(i + 1) * kc] for i in range(4))
    top = t00 + fx * (t01 - t00)
    bottom = t10 + fx * (t11 - t10)
    return jnp.where(inside[:, None], top + fy * (bottom - top), outside[None, :])


def draw_surfaces(prep: Any, frame: Any, layer: SurfaceLayer) -> Any:
    """``frame`` (:class:`~spectral_fit.rendering.Frame`) with the surfaces drawn where no
    object covers a pixel: their radiance (``layer`` in absolute XYZ, :func:`surface_layer`'s
    default channels) instead of the environment, then the frame's display encoding. For a
    render without a video: in mixed reality the surface is the real table and only the
    change the objects make is composited (:func:`spectral_fit.live.relight`)."""
    from ..color import display_linear, encode

    col = prep.colour
    show = layer.mask & ~frame.mask
    xyz = jnp.where(show[..., None], layer.radiance, frame.xyz)
    linear = display_linear(xyz, exposure_luminance=col.exposure, display=col.display,
                            scene_white_xy=col.scene_white_xy)
    return eqx.tree_at(lambda f: (f.xyz, f.linear_rgb, f.rgb), frame,
                       (xyz, linear, encode(linear, col.display)))


def surface_ratio(prep: Any, layer: SurfaceLayer, object_mask: Any = None, *,
                  channels: str = "xyz") -> jax.Array:
    """(H, W, 3) the change the objects make on the surfaces, as a ratio per channel (with /
    without the objects) of the frame's linear display RGB (``channels`` "xyz": ``layer`` in
    absolute XYZ, :func:`surface_layer`'s default) or of the layer's own channels ("linear":
    e.g. a video camera's linear RGB); 1 where no surface is seen or ``object_mask`` (H, W)
    covers the pixel. The ratio form of differential rendering: a real table's pixel times
    it shows the objects' shadow and light whatever the table's true reflectance and the
    camera's exposure (both cancel in the ratio; docs/surfaces.md)."""
    from ..color import display_linear

    if channels not in ("xyz", "linear"):
        raise InputError(f"must be 'xyz' or 'linear', got {channels!r}", field="channels")
    with_, without = layer.radiance, layer.base
    if channels == "xyz":
        col = prep.colour
        kw = dict(exposure_luminance=col.exposure, display=col.display,
                  scene_white_xy=col.scene_white_xy)
        with_, without = display_linear(with_, **kw), display_linear(without, **kw)
    show = layer.mask if object_mask is None else layer.mask & ~jnp.asarray(object_mask, bool)
    ok = show[..., None] & (without > 1e-6)
    r = jnp.where(ok, with_ / jnp.where(ok, without, 1.0), 1.0)
    return jnp.clip(r, 0.0, 4.0)
