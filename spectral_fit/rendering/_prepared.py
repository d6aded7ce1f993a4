"""The prepared scene and what a frame program returns, as pytrees.

* :class:`Prepared`: everything :func:`~spectral_fit.rendering.render_frame` needs besides the
  per-frame inputs, built once per scene shape by :func:`~spectral_fit.rendering.prepare`;
* :class:`Frame`: one rendered frame (absolute XYZ with Y in cd/m², display RGB, coverage,
  object ids, optional spectral radiance in W·sr⁻¹·m⁻²·nm⁻¹, stats);
* :class:`PixelFrame`: the covered pixels of one frame, shaded, before the background, the
  scatter into an image and the display encoding;
* ``TRACE_COUNT``: how many times the frame programs have been traced.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import equinox as eqx
import jax

from ..lighting import Material

if TYPE_CHECKING:  # for annotations (imported where they are used)
    from ..color import Display
    from ..geometry import RasterConfig, TriangleClusters
    from ..lighting import EnvironmentMap, SplitSum, SplitSumMap

__all__ = [
    "Prepared",
    "Frame",
    "PixelFrame",
    "TRACE_COUNT",
]


#: number of times :func:`render_frame` has been traced (i.e. compiled), for tests and reports
TRACE_COUNT = {"render_frame": 0, "ir_senders": 0}


class Prepared(eqx.Module):
    """Everything :func:`render_frame` needs besides the per-frame inputs.

    Array attributes:
        vertices: (V, 3) object-frame positions of all objects' vertices (m), concatenated.
        normals: (V, 3) object-frame unit normals.
        triangles: (T, 3) int32 indices into ``vertices``.
        vertex_object: (V,) int32 object of each vertex; tri_object: (T,) likewise per triangle.
        model: (O, 4, 4) default world-from-object matrices (from the config).
        view: (4, 4) default view matrix (world → OpenGL eye).
        projection: (4, 4) eye → clip.
        env: the :class:`~spectral_fit.lighting.EnvironmentMap` (bands or coefficients).
        env_xyz: (Hm·Wm + 2, 3) absolute XYZ of the map's texels, then its two pole means (the
            background lookup).
        to_xyz: (C, 3) radiance channels → absolute XYZ (683 lm/W · x̄ȳz̄ · Δλ; in basis mode
            the basis components times that).
        to_spectrum: (C, L) channels → bands (identity in band mode).
        exposure: scalar, luminance (cd/m²) shown as display white.
        materials: the config's materials, stacked (leading axis O).
        irradiance_lut: (Hl·Wl + 2, C) irradiance map over normal directions (map frame, the
            map's texel layout plus two pole rows), or None (irradiance from ``env``).
        split_map: the :class:`~spectral_fit.lighting.SplitSumMap` of quality "fast"
            (finely spaced prefiltered levels), else None.
        ir_vertices, ir_normals, ir_triangles, ir_vertex_object: the same for the meshes the
            interreflection's pass 1 rasterises (:func:`_ir_mesh`: in gather mode spheres
            tessellated for its raster; otherwise the arrays above).
        lens: (9,) the camera's lens distortion (:func:`~spectral_fit.geometry.lens_parameters`:
            OpenCV's k1, k2, p1, p2, k3, k4, k5, k6 and the square of the model's fold
            radius), or None for an ideal pinhole (no ``camera.distortion``, or all zero).
            Vertices are distorted before rasterisation
            (:func:`~spectral_fit.geometry.distort_eye`).
        pixel_rays: (H·W, 3) unit eye-space (OpenGL) ray of every pixel centre through the
            lens (:func:`~spectral_fit.geometry.pixel_rays`; the background's rays), or None
            with ``lens`` None.
        clusters: the camera raster's :class:`~spectral_fit.geometry.TriangleClusters`
            (each object's triangles are in :func:`~spectral_fit.geometry.spatial_order`),
            culled per frame; None without face culling or through a lens (every triangle
            is rasterised).
    Static attributes: shape (H, W), wavelengths (tuple, nm), spectral_mode, k, ir_mode,
    ir_bounces, ir_texture_size, raster_config, pixel_capacity (covered-pixel list size per
    object), object_slices ((start, stop) vertex ranges), triangle_slices, ir_object_slices,
    ir_triangle_slices (the same of the pass-1 meshes), names, display (a Display),
    scene_white_xy, batch_size, quality, split_settings (a
    :class:`~spectral_fit.lighting.SplitSum`), cull (the camera raster's face culling:
    "back" when every mesh is closed and wound outward,
    :func:`~spectral_fit.io.is_closed_outward`, else "none").
    """

    vertices: jax.Array
    normals: jax.Array
    triangles: jax.Array
    vertex_object: jax.Array
    tri_object: jax.Array
    model: jax.Array
    view: jax.Array
    projection: jax.Array
    env: EnvironmentMap
    env_xyz: jax.Array
    to_xyz: jax.Array
    to_spectrum: jax.Array
    exposure: jax.Array
    materials: Material
    irradiance_lut: jax.Array | None
    split_map: SplitSumMap | None
    ir_vertices: jax.Array
    ir_normals: jax.Array
    ir_triangles: jax.Array
    ir_vertex_object: jax.Array
    shape: tuple[int, int] = eqx.field(static=True)
    wavelengths: tuple[float, ...] = eqx.field(static=True)
    spectral_mode: str = eqx.field(static=True)
    k: int = eqx.field(static=True)
    ir_mode: str = eqx.field(static=True)
    ir_bounces: int = eqx.field(static=True)
    ir_texture_size: int = eqx.field(static=True)
    raster_config: RasterConfig = eqx.field(static=True)
    ir_raster_config: RasterConfig = eqx.field(static=True)
    pixel_capacity: tuple[int, ...] = eqx.field(static=True)
    object_slices: tuple[tuple[int, int], ...] = eqx.field(static=True)
    triangle_slices: tuple[tuple[int, int], ...] = eqx.field(static=True)
    ir_object_slices: tuple[tuple[int, int], ...] = eqx.field(static=True)
    ir_triangle_slices: tuple[tuple[int, int], ...] = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)
    display: Display = eqx.field(static=True)
    scene_white_xy: tuple[float, float] | None = eqx.field(static=True)
    batch_size: int = eqx.field(static=True, default=32)
    quality: str = eqx.field(static=True, default="fast")
    split_settings: SplitSum | None = eqx.field(static=True, default=None)
    cull: str = eqx.field(static=True, default="none")
    lens: jax.Array | None = None
    pixel_rays: jax.Array | None = None
    clusters: TriangleClusters | None = None

    @property
    def num_objects(self) -> int:
        return len(self.names)

    @property
    def channels(self) -> int:
        return int(self.to_xyz.shape[0])


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
        values: (N, K) radiance of each slot in the output channels (K = 3: ``prep.to_xyz``'s
            space, absolute XYZ unless :func:`with_output` changed it; K = C with
            ``spectral``: the radiance channels, bands or basis coefficients), 0 in empty
            slots. N = sum of ``prep.pixel_capacity``.
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
