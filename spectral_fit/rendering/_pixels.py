"""Steps 1–3 of a frame (traced): vertices → world → clip (hidden objects collapse to a point),
the raster of the clusters that may face the eye, one covered-pixel list per object, the
G-buffer, and the shading and interreflection of the covered pixels in the output channels, as
a :class:`~spectral_fit.rendering.PixelFrame`; :func:`render_pixels` for callers that put the
pixels somewhere themselves (the live composite).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from .._runtime.backend import materialise
from ..geometry import GBuffer, eye_position
from ._camera import _normals_to_world, _to_world, camera_clip
from ._inputs import _check_frame_inputs, _check_senders
from ._ir_stage import _interreflection, _ir_geometries
from ._materials import _as_stacked, _mirror_flag, _without_mirror
from ._prepared import TRACE_COUNT, PixelFrame, Prepared
from ._shading import _shade_out, _shade_samples, own_reflection_out

__all__ = [
    "render_pixels",
]


def _object_pixel_lists(tri_id: jax.Array, obj_img: jax.Array, capacities: tuple[int, ...]
                        ) -> tuple[Any, list[jax.Array]]:
    """The covered pixels of each object compacted into its own list of ``capacities[o]``
    slots (row-major order), the lists one after the other: the
    :func:`~spectral_fit.geometry.covered_pixels` of each object's part of the raster, by
    :func:`~spectral_fit.geometry.compact_flags` per object (no prefix sum or scatter over the
    frame: XLA:CPU runs those as serial loops). ``tri_id``, ``obj_img`` (H, W) int32
    (−1 = none). Returns the :class:`~spectral_fit.geometry.PixelList` (count = all objects'
    covered pixels, overflow = any object's list overflowed) and the per-object covered
    counts (may exceed capacity)."""
    from ..geometry import PixelList, compact_flags

    h, w = tri_id.shape
    flat = tri_id.reshape(-1)
    obj = obj_img.reshape(-1)
    parts, lives, counts = [], [], []
    for o, cap in enumerate(capacities):
        index, count = compact_flags(obj == o, cap)
        parts.append(index)
        lives.append(jnp.arange(cap, dtype=jnp.int32) < count)
        counts.append(count)
    index = jnp.concatenate(parts)
    tri = jnp.where(jnp.concatenate(lives), flat[index], -1)
    overflow = jnp.any(jnp.stack([c > cap for c, cap in zip(counts, capacities, strict=True)]))
    return PixelList(index, tri, sum(counts), overflow, (h, w)), counts


def _pixels_impl(prep: Prepared, materials: Any, model: jax.Array, view: jax.Array,
                 visible: jax.Array, spectral: bool, mirror: bool = True,
                 senders: Any = None) -> PixelFrame:
    """Steps 1–3 of the frame (traced): geometry, raster, covered pixels, G-buffer, shading
    and interreflection of the covered pixels, in the output channels (see
    :class:`PixelFrame`). ``mirror`` False (static): every χ taken as 0, the mirror term left
    out (see :func:`mirror_needed`). ``senders``: the gather interreflection's senders' half
    (:func:`render_senders`) instead of computing it here."""
    from ..geometry import interpolate_pixels, rasterize

    TRACE_COUNT["render_frame"] += 1
    h, w = prep.camera.shape
    n_obj = prep.num_objects
    mats = _as_stacked(materials, n_obj)
    if not mirror:
        mats = _without_mirror(mats)
    model = jnp.asarray(model, jnp.float32)
    view = jnp.asarray(view, jnp.float32)
    visible = jnp.asarray(visible, bool)

    # 1. geometry in the world; hidden objects collapse onto their centre (draw nothing)
    mesh = prep.mesh
    world_full = _to_world(mesh.vertices, mesh.vertex_object, model)
    centres = model[:, :3, 3]
    vis_v = visible[mesh.vertex_object]
    world = jnp.where(vis_v[:, None], world_full, centres[mesh.vertex_object])
    wnorm = _normals_to_world(mesh.normals, mesh.vertex_object, model)
    clip = camera_clip(prep.camera.projection, view, prep.camera.lens, world)

    # 2. rasterise (the triangles of the clusters that may face the eye), compact covered
    # pixels, G-buffer; triangle ids below are rows of that list
    with jax.named_scope("raster"):
        tris, tri_object, clusters_needed, clusters_over = _frame_triangles(
            prep, model, view, visible)
        ras = rasterize(clip, tris, (h, w), cull=prep.camera.cull,
                        config=prep.buffers.raster_config, check=False)
    # covered pixels, one fixed-capacity list per object (each object is shaded with its own
    # material, whose per-material precomputations then run once per object)
    with jax.named_scope("pixel_lists"):
        obj_img = jnp.where(ras.tri_id >= 0, tri_object[jnp.maximum(ras.tri_id, 0)], -1)
        pix, counts = _object_pixel_lists(ras.tri_id, obj_img,
                                           prep.buffers.pixel_capacity)
    # output channels (XYZ, or all channels for the spectral output): no (N, C) array unless
    # the spectra are asked for
    if spectral:
        to_out = jnp.eye(prep.channels, dtype=jnp.float32)
        env = prep.lighting.env
        hm, wm, c = env.texels.shape
        mirror_table = jnp.concatenate([env.texels.reshape(hm * wm, c), env.poles])
    else:
        to_out = prep.colour.to_xyz
        mirror_table = prep.colour.env_xyz
    # the objects' own shape: each vertex's change of diffuse radiance (hidden environment,
    # own light), interpolated with the geometry
    occ = prep.occlusion
    attrs = [world, wnorm]
    if occ is not None:
        from ._occlusion import vertex_correction

        # mode "none" is the direct light alone: the environment the objects do not hide,
        # none of their own light (neither diffuse bounces nor its reflection)
        own_light = prep.interreflection.mode != "none"
        with jax.named_scope("self_occlusion"):
            corr, own_radiance, own_sent = vertex_correction(
                occ, env=prep.lighting.env, lut=prep.lighting.irradiance_lut, mats=mats,
                model=model, normals=mesh.normals, world_normals=wnorm,
                vertex_slices=mesh.object_slices,
                bounces=prep.interreflection.bounces if own_light else 0, to_out=to_out,
                tail=prep.interreflection.tail,
                quality=prep.lighting.quality, split_map=prep.lighting.split_map,
                split_settings=prep.lighting.split_settings)
        attrs.append(corr)
    if prep.surface_changes:  # the table's change under the objects, as they see it
        from ._surfaces import surface_vertices

        attrs.append(surface_vertices(prep, prep.surface_changes, mats, to_out))
    vals = interpolate_pixels(jnp.concatenate(attrs, axis=1), pix, tris, clip)
    pos = vals[:, :3]
    nrm = vals[:, 3:6]
    nrm = nrm / jnp.maximum(jnp.linalg.norm(nrm, axis=-1, keepdims=True), 1e-12)
    eye = eye_position(view)
    vdir = eye - pos
    vdir = vdir / jnp.maximum(jnp.linalg.norm(vdir, axis=-1, keepdims=True), 1e-12)
    # silhouette pixels whose interpolated (smooth) normal turns away from the eye: bend the
    # normal towards V until N·V = 0.01, instead of shading them black
    nv = jnp.sum(nrm * vdir, axis=-1, keepdims=True)
    bent = nrm + jnp.maximum(0.01 - nv, 0.0) * vdir
    nrm = bent / jnp.maximum(jnp.linalg.norm(bent, axis=-1, keepdims=True), 1e-12)
    # empty slots: a harmless configuration (N = V = +Z), so no NaN enters any gradient
    zdir = jnp.array([0.0, 0.0, 1.0], jnp.float32)
    nrm = jnp.where(pix.valid[:, None], nrm, zdir)
    vdir = jnp.where(pix.valid[:, None], vdir, zdir)
    obj = jnp.where(pix.valid, tri_object[jnp.maximum(pix.tri_id, 0)], -1)
    gb = GBuffer(position=pos, normal=nrm, view=vdir, object=obj,
                 pixel=jnp.where(pix.valid, pix.index, -1))

    # 3. shading + interreflection, in the output channels
    spec_vis = spec_seen = None
    if occ is not None:
        from ._occlusion import own_reflection

        spec_vis, spec_seen = own_reflection(
            occ, model=model, vertex_object=mesh.vertex_object, pixels=pix, triangles=tris,
            clip=clip, normal=nrm, view=vdir,
            vertex_radiance=own_radiance if own_light else None,
            sent=own_sent if own_light else None, object_normals=mesh.normals, mats=mats,
            split_settings=prep.lighting.split_settings)
    with jax.named_scope("shading"):
        lit = prep.lighting
        # the environment's gloss of each pixel, for the gather to take off the share of it
        # that a neighbour hides (fast quality; the other qualities keep the lobe nodes' own
        # reading of the hidden sky)
        own_gloss = None
        if lit.quality == "fast":
            with_gloss = prep.interreflection.mode == "gather" and n_obj > 1
            radiance = _shade_out(prep, mats, gb, counts, to_out, mirror_table, spec_vis,
                                  spec_seen, with_gloss=with_gloss)
            if with_gloss:
                radiance, own_gloss = radiance
        else:
            radiance = _shade_samples(mats, lit.env, gb, lit.batch_size, lit.irradiance_lut,
                                      lit.quality, prep.buffers.pixel_capacity,
                                      lit.split_map, lit.split_settings,
                                      spec_vis=spec_vis) @ to_out
            if spec_seen is not None:
                radiance = radiance + own_reflection_out(mats, gb, prep.buffers.pixel_capacity,
                                                         spec_seen)
    if occ is not None or prep.surface_changes:  # the interpolated vertex changes
        radiance = radiance + jnp.where(pix.valid[:, None], vals[:, 6:].reshape(
            vals.shape[0], -1, radiance.shape[1]).sum(axis=1), 0.0)
    if prep.surface_changes:  # what their gloss and mirror see of the table's change
        from ._surfaces import surface_pixels

        with jax.named_scope("surfaces"):
            radiance = radiance + surface_pixels(prep, prep.surface_changes, mats, gb, to_out)
    # (in the output channels: the receivers' side of the gather works in those)
    if senders is not None:
        from .interreflection._gather import gather_receivers

        ir = gather_receivers(senders, mats, prep.lighting.env, gb,
                              image_shape=prep.camera.shape,
                              output=None if spectral else to_out, own_gloss=own_gloss)
        ir_overflow = jnp.asarray(senders.geometry.overflow, bool)
    else:
        geoms = _ir_geometries(prep, model, visible)
        ir, ir_overflow = _interreflection(prep, geoms, mats, gb, None if spectral else to_out,
                                           own_gloss)
    if ir is not None:
        if occ is not None and n_obj > 1:
            from ._occlusion import neighbour_visibility

            # what the pixel's own object hides of its neighbours (a cup's inside)
            ir = ir * neighbour_visibility(
                occ, model=model, vertex_object=mesh.vertex_object, pixels=pix,
                triangles=tris, clip=clip, position=pos, visible=visible,
                bodies=prep.interreflection.bodies)[:, None]
        radiance = radiance + ir
    # materialised: otherwise the interreflection's tail (its chunks' results put back in
    # slot order, the anchors' interpolation) was fused into each consumer's every channel
    # (the live composite's tone curve, the frame's scatter) and computed again there
    radiance = materialise(jnp.where(pix.valid[:, None], radiance, 0.0), cut=True)
    stats = {
        "covered_pixels": pix.count,
        "pixel_overflow": pix.overflow,
        "raster_overflow": ras.overflow | clusters_over,
        "interreflection_overflow": ir_overflow,
        "object_counts": jnp.stack([jnp.asarray(c, jnp.int32) for c in counts]),
        "raster_needed": ras.needed,
        "clusters_needed": clusters_needed,
    }
    return PixelFrame(values=radiance, index=pix.index, valid=pix.valid,
                      mask=ras.tri_id >= 0, object_id=obj_img, stats=stats)


def _frame_triangles(prep: Prepared, model: jax.Array, view: jax.Array, visible: jax.Array
                     ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """The camera raster's triangle list: (T', 3) vertex indices, (T',) object of each row,
    the clusters kept (int32) and whether their list overflowed (bool). With
    ``prep.buffers.clusters`` the rows of the clusters that may face the eye
    (:func:`~spectral_fit.geometry.visible_clusters`; the raster is bit-identical to one of all
    triangles), else ``prep.mesh.triangles`` (the count is then 0)."""
    from ..geometry import cluster_rows, visible_clusters

    cl = prep.buffers.clusters
    if cl is None:
        return prep.mesh.triangles, prep.mesh.tri_object, jnp.int32(0), jnp.asarray(False)
    index, count = visible_clusters(cl, model, view, prep.camera.projection, visible,
                                    cull=prep.camera.cull)
    tris, obj = cluster_rows(cl, index)
    return tris, obj, count, count > cl.capacity


def render_pixels(prep: Prepared, materials: Any = None, *, model: Any = None,
                  view: Any = None, visible: Any = None, spectral: bool = False,
                  mirror: bool | None = None, senders: Any = None) -> PixelFrame:
    """The covered pixels of one frame, shaded (with interreflection), without background,
    image scatter or display encoding: for callers that put the pixels somewhere else (the
    live composite writes them straight into the video frame). Same inputs as
    :func:`render_frame`; meant to be called inside the caller's own ``jit``. Returns a
    :class:`PixelFrame`; its values are in ``prep.colour.to_xyz``'s output space
    (:func:`with_output`) or, with ``spectral``, in the C radiance channels. ``mirror``: as for
    :func:`render_frame`; inside a caller's ``jit`` the materials are traced, so the default
    keeps the mirror term: pass :func:`mirror_needed` of the concrete materials from outside.
    ``senders``: :func:`render_senders` of the same ``prep``, materials, mirror switch and
    object state (``model``, ``visible``: the caller keeps them consistent), used instead of
    the frame's own pass 1 (gather mode only)."""
    mats, model, view, visible = _check_frame_inputs(prep, materials, model, view, visible)
    _check_senders(prep, senders)
    return _pixels_impl(prep, mats, model, view, visible, spectral,
                        _mirror_flag(mats, mirror), senders)
