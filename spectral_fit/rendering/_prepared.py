"""The prepared scene and what a frame program returns, as pytrees.

* :class:`Prepared`: everything :func:`~spectral_fit.rendering.render_frame` needs besides the
  per-frame inputs, built once per scene shape by :func:`~spectral_fit.rendering.prepare`, in
  named parts: the meshes (:class:`SceneMeshes`, once for the camera raster and once for the
  interreflection's pass 1), the camera (:class:`PreparedCamera`), the environment shading
  (:class:`PreparedLighting`), the radiance channels and their way to the display
  (:class:`PreparedColour`), the planned buffer sizes (:class:`PreparedBuffers`) and the
  interreflection's settings (:class:`PreparedInterreflection`);
* :class:`Frame`: one rendered frame (absolute XYZ with Y in cd/m², display RGB, coverage,
  object ids, optional spectral radiance in W·sr⁻¹·m⁻²·nm⁻¹, stats);
* :class:`PixelFrame`: the covered pixels of one frame, shaded, before the background, the
  scatter into an image and the display encoding;
* ``TRACE_COUNT``: how many times the frame programs have been traced.

Static attributes (``eqx.field(static=True)``) are part of the compiled program's identity: a
new value compiles the frame again; the arrays are traced.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any, NoReturn

import equinox as eqx
import jax

from ..lighting import Material

if TYPE_CHECKING:  # for annotations (imported where they are used)
    from ..color import Display
    from ..geometry import RasterConfig, TriangleClusters
    from ..lighting import EnvironmentMap, SplitSum, SplitSumMap

__all__ = [
    "Prepared",
    "SceneMeshes",
    "PreparedCamera",
    "PreparedLighting",
    "PreparedColour",
    "PreparedBuffers",
    "PreparedInterreflection",
    "Frame",
    "PixelFrame",
    "TRACE_COUNT",
]


#: number of times :func:`render_frame` has been traced (i.e. compiled), for tests and reports
TRACE_COUNT = {"render_frame": 0, "ir_senders": 0}

#: version of :class:`Prepared`'s layout (its parts and their fields), part of the
#: prepared-scene cache's keys: an entry pickled with another layout is never loaded
#: (1: one flat class; 2: the named parts)
PREPARED_LAYOUT = 9


class SceneMeshes(eqx.Module):
    """All objects' triangle meshes in their object frames, concatenated in config order.

    Attributes:
        vertices: (V, 3) float32 object-frame positions (m).
        normals: (V, 3) float32 object-frame unit normals.
        triangles: (T, 3) int32 indices into ``vertices`` (each object's rows within its own
            vertex range).
        vertex_object: (V,) int32 object of each vertex.
        tri_object: (T,) int32 object of each triangle.
        object_slices: static, per object its (start, stop) range of vertices.
        triangle_slices: static, per object its (start, stop) range of triangles.
    """

    vertices: jax.Array
    normals: jax.Array
    triangles: jax.Array
    vertex_object: jax.Array
    tri_object: jax.Array
    object_slices: tuple[tuple[int, int], ...] = eqx.field(static=True)
    triangle_slices: tuple[tuple[int, int], ...] = eqx.field(static=True)


class PreparedCamera(eqx.Module):
    """The camera the frame is seen through.

    Attributes:
        view: (4, 4) float32 default view matrix (world → OpenGL eye; m); a frame's ``view``
            replaces it.
        projection: (4, 4) float32 eye → clip.
        lens: (9,) float32 lens distortion (:func:`~spectral_fit.geometry.lens_parameters`:
            OpenCV's k1, k2, p1, p2, k3, k4, k5, k6 and the square of the model's fold
            radius), or None for an ideal pinhole (no ``camera.distortion``, or all zero).
            Vertices are distorted before rasterisation
            (:func:`~spectral_fit.geometry.distort_eye`).
        pixel_rays: (H·W, 3) float32 unit eye-space (OpenGL) ray of every pixel centre
            through the lens (:func:`~spectral_fit.geometry.pixel_rays`; the background's
            rays), or None with ``lens`` None.
        shape: static (H, W) frame size in pixels.
        cull: static face culling of the camera raster: "back" when every mesh is closed and
            wound outward (:func:`~spectral_fit.io.is_closed_outward`), else "none".
    """

    view: jax.Array
    projection: jax.Array
    lens: jax.Array | None
    pixel_rays: jax.Array | None
    shape: tuple[int, int] = eqx.field(static=True)
    cull: str = eqx.field(static=True)


class PreparedLighting(eqx.Module):
    """The environment and what its shading of the covered pixels looks up.

    Attributes:
        env: the :class:`~spectral_fit.lighting.EnvironmentMap` in the radiance channels
            (bands, W·sr⁻¹·m⁻²·nm⁻¹, or basis coefficients), prefiltered.
        irradiance_lut: (Hl·Wl + 2, C) float32 irradiance map over normal directions (map
            frame, the map's texel layout plus two pole rows), or None (irradiance from
            ``env``).
        split_map: the :class:`~spectral_fit.lighting.SplitSumMap` of quality "fast" (finely
            spaced prefiltered levels), else None.
        quality: static gloss of the environment shading: "fast", "render" or "exact" (see
            :func:`~spectral_fit.rendering.prepare`).
        split_settings: static :class:`~spectral_fit.lighting.SplitSum` of quality "fast",
            else None.
        batch_size: static shading batch of qualities "render" and "exact" (points per
            ``lax.map`` step of ``shade_points``).
    """

    env: EnvironmentMap
    irradiance_lut: jax.Array | None
    split_map: SplitSumMap | None
    quality: str = eqx.field(static=True)
    split_settings: SplitSum | None = eqx.field(static=True)
    batch_size: int = eqx.field(static=True)


class PreparedColour(eqx.Module):
    """The radiance channels (C of them: L bands, or K basis coefficients) and their way to
    the output space and the display.

    Attributes:
        to_xyz: (C, 3) float32 channels → the output space: absolute XYZ (683 lm/W · x̄ȳz̄ ·
            Δλ; in basis mode the basis components times that), or what
            :func:`~spectral_fit.rendering.with_output` put there (e.g. a video camera's
            linear RGB).
        env_xyz: (Hm·Wm + 2, 3) float32 the environment's texels, then its two pole means,
            in the output space (``env``'s texels times ``to_xyz``: the background lookup).
        to_spectrum: (C, L) float32 channels → bands (identity in band mode).
        exposure: () float32 luminance (cd/m²) shown as display white.
        wavelengths: static (L,) band centres (nm).
        spectral_mode: static "bands" or "basis".
        k: static number of channels C (L in band mode).
        display: static :class:`~spectral_fit.color.Display` the frame is encoded for.
        scene_white_xy: static (x, y) chromaticity shown as the display's white, or None.
    """

    to_xyz: jax.Array
    env_xyz: jax.Array
    to_spectrum: jax.Array
    exposure: jax.Array
    wavelengths: tuple[float, ...] = eqx.field(static=True)
    spectral_mode: str = eqx.field(static=True)
    k: int = eqx.field(static=True)
    display: Display = eqx.field(static=True)
    scene_white_xy: tuple[float, float] | None = eqx.field(static=True)


class PreparedBuffers(eqx.Module):
    """The sizes of the frame's fixed-size buffers, planned from the configured poses with
    headroom; an overflow is flagged in the frame's stats and these are grown
    (:func:`~spectral_fit.rendering.regrow`, the live session's replanning).

    Attributes:
        clusters: the camera raster's :class:`~spectral_fit.geometry.TriangleClusters` of
            ``Prepared.mesh`` (each object's triangles are in
            :func:`~spectral_fit.geometry.spatial_order`), culled per frame into a list of
            ``clusters.capacity`` slots; None without face culling or through a lens (every
            triangle is rasterised).
        raster_config: static :class:`~spectral_fit.geometry.RasterConfig` of the camera
            raster (windows per ladder size, blocks).
        ir_raster_config: static :class:`~spectral_fit.geometry.RasterConfig` of the
            interreflection's pass-1 rasters, or None (mode "none").
        pixel_capacity: static covered-pixel list size per object (O,).
    """

    clusters: TriangleClusters | None
    raster_config: RasterConfig = eqx.field(static=True)
    ir_raster_config: RasterConfig | None = eqx.field(static=True)
    pixel_capacity: tuple[int, ...] = eqx.field(static=True)


class PreparedInterreflection(eqx.Module):
    """The interreflection's settings (all static).

    Attributes:
        mode: "gather", "paper" or "none".
        bounces: number of bounces.
        texture_size: side of paper mode's pass-1 textures (texels).
        gather_size: g, samples per side of each sender's grid in gather mode.
        bodies: (O,) the body each object belongs to (the index of its first object): the
            parts of one mesh with several materials share a body, and the interreflection
            passes no light between them
            (:func:`~spectral_fit.rendering.interreflection.without_pairs`); () when every
            object is its own body.
        tail: "none" or "geometric": how a concave object's own light ends after
            ``bounces`` steps (:func:`~spectral_fit.rendering._occlusion.vertex_correction`).
    """

    mode: str = eqx.field(static=True)
    bounces: int = eqx.field(static=True)
    texture_size: int = eqx.field(static=True)
    gather_size: int = eqx.field(static=True, default=16)
    bodies: tuple[int, ...] = eqx.field(static=True, default=())
    tail: str = eqx.field(static=True, default="none")


class Prepared(eqx.Module):
    """Everything :func:`render_frame` needs besides the per-frame inputs.

    Attributes:
        mesh: the camera raster's :class:`SceneMeshes` (each object's triangles in
            :func:`~spectral_fit.geometry.spatial_order`).
        ir_mesh: the :class:`SceneMeshes` the interreflection's pass 1 rasterises
            (:func:`~spectral_fit.rendering._prepare._ir_mesh`: in gather mode spheres
            tessellated for its raster; otherwise the same object as ``mesh``).
        model: (O, 4, 4) float32 default world-from-object matrices (m; from the config); a
            frame's ``model`` replaces them.
        materials: the config's materials, stacked (leading axis O); a frame's
            ``materials`` replace them.
        camera: :class:`PreparedCamera` (view, projection, lens, pixel rays, frame shape,
            face culling).
        lighting: :class:`PreparedLighting` (environment, irradiance map, split-sum map,
            shading quality).
        colour: :class:`PreparedColour` (channels → output space and bands, background
            table, exposure, display, wavelengths).
        buffers: :class:`PreparedBuffers` (clusters, raster windows, covered-pixel lists).
        interreflection: :class:`PreparedInterreflection` (mode, bounces, texture size).
        names: static object names (O,).
        occlusion: the non-convex objects' precomputed self-visibility and self-transfer
            (:mod:`~spectral_fit.rendering._occlusion`), or None (every object convex, or
            ``prepare(occlusion=False)``).
        surfaces: one :class:`~spectral_fit.rendering.SurfaceTransfer` per ``[[surfaces]]``
            plane of the config, for the prepared poses (the objects' shadows and light on
            it; :func:`~spectral_fit.rendering.surface_layer`), or ().
        surface_changes: per plane, what the objects see of its change under them
            (:func:`~spectral_fit.rendering.table_changes` at the config's materials), added
            to their pixels by the frame, or ().
    """

    mesh: SceneMeshes
    ir_mesh: SceneMeshes
    model: jax.Array
    materials: Material
    camera: PreparedCamera
    lighting: PreparedLighting
    colour: PreparedColour
    buffers: PreparedBuffers
    interreflection: PreparedInterreflection
    names: tuple[str, ...] = eqx.field(static=True)
    occlusion: Any = None
    surfaces: tuple = ()
    surface_changes: tuple = ()

    @property
    def num_objects(self) -> int:
        """O, the number of objects."""
        return len(self.names)

    @property
    def channels(self) -> int:
        """C, the number of radiance channels (bands or basis coefficients)."""
        return int(self.colour.to_xyz.shape[0])

    def with_buffers(self, **changes: Any) -> Prepared:
        """This prepared scene with the named fields of its :class:`PreparedBuffers` replaced
        (``clusters``, ``raster_config``, ``ir_raster_config``, ``pixel_capacity``: grown
        buffers); the other parts are shared."""
        return dataclasses.replace(self, buffers=dataclasses.replace(self.buffers, **changes))

    def __getattr__(self, name: str) -> NoReturn:
        # only reached for names that are not attributes: say where a flat one of earlier
        # versions went (there are no aliases)
        moved = _MOVED.get(name)
        hint = f"; it is now prep.{moved}" if moved else ""
        raise AttributeError(f"'Prepared' object has no attribute {name!r}{hint}", name=name,
                             obj=self)


#: where each attribute of the earlier, flat :class:`Prepared` went (for the error message)
_MOVED = {
    **{n: f"mesh.{n}" for n in ("vertices", "normals", "triangles", "vertex_object",
                                "tri_object", "object_slices", "triangle_slices")},
    **{f"ir_{n}": f"ir_mesh.{n}" for n in ("vertices", "normals", "triangles",
                                           "vertex_object", "object_slices",
                                           "triangle_slices")},
    **{n: f"camera.{n}" for n in ("view", "projection", "lens", "pixel_rays", "shape",
                                  "cull")},
    **{n: f"lighting.{n}" for n in ("env", "irradiance_lut", "split_map", "quality",
                                    "split_settings", "batch_size")},
    **{n: f"colour.{n}" for n in ("to_xyz", "env_xyz", "to_spectrum", "exposure",
                                  "wavelengths", "spectral_mode", "k", "display",
                                  "scene_white_xy")},
    **{n: f"buffers.{n}" for n in ("clusters", "raster_config", "ir_raster_config",
                                   "pixel_capacity")},
    "ir_mode": "interreflection.mode", "ir_bounces": "interreflection.bounces",
    "ir_texture_size": "interreflection.texture_size",
}


class Frame(eqx.Module):
    """One rendered frame (a pytree).

    Attributes:
        xyz: (H, W, 3) absolute CIE XYZ (Y in cd/m²), background included.
        rgb: (H, W, 3) display-encoded RGB in [0, 1].
        linear_rgb: (H, W, 3) linear display RGB before clipping.
        mask: (H, W) bool, pixels covered by an object.
        object_id: (H, W) int32 object index per pixel (−1 = background).
        spectral: (H, W, L) spectral radiance (W·sr⁻¹·m⁻²·nm⁻¹) when requested, else None.
        stats: dict of scalars: ``out_of_gamut_fraction``, ``below_zero_fraction``,
            ``overexposed_fraction`` (over the covered pixels in the pixel lists: all of them
            unless ``pixel_overflow``), ``coverage`` (fraction of the frame),
            ``covered_pixels``, ``pixel_overflow``, ``raster_overflow`` and
            ``interreflection_overflow`` (buffers too small: the frame is incomplete).
    """

    xyz: jax.Array
    rgb: jax.Array
    linear_rgb: jax.Array
    mask: jax.Array
    object_id: jax.Array
    spectral: jax.Array | None
    stats: dict[str, jax.Array]


class PixelFrame(eqx.Module):
    """The covered pixels of one frame, shaded (the part of :class:`Frame` before the
    background, the scatter into an image and the display encoding; a pytree).

    Attributes:
        values: (N, K) radiance of each slot in the output channels (K = 3:
            ``prep.colour.to_xyz``'s space, absolute XYZ unless :func:`with_output` changed
            it; K = C with ``spectral``: the radiance channels, bands or basis
            coefficients), 0 in empty slots. N = sum of ``prep.buffers.pixel_capacity``.
        index: (N,) int32 flat pixel index y·W + x of each slot (0 in empty slots).
        valid: (N,) bool, slots that hold a covered pixel.
        mask: (H, W) bool, pixels covered by an object.
        object_id: (H, W) int32 object per pixel (−1 = none).
        stats: ``covered_pixels``, ``pixel_overflow``, ``raster_overflow``,
            ``interreflection_overflow`` (see :class:`Frame`); and the buffers' use against
            ``prep``'s plan: ``object_counts`` (O,) int32 covered pixels per object (against
            ``pixel_capacity``), ``raster_needed`` (len(tile_sizes) + 1,) int32 raster windows
            needed per ladder size, then blocks (against ``raster_config``; see
            :class:`~spectral_fit.geometry.Raster`).
    """

    values: jax.Array
    index: jax.Array
    valid: jax.Array
    mask: jax.Array
    object_id: jax.Array
    stats: dict[str, jax.Array]
