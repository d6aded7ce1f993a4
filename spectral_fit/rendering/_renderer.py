"""Multipass frame renderer: scene → spectral frame → XYZ → display RGB.

Two steps, so that a live loop or a fit never recompiles:

* :func:`prepare` (Python, once per scene shape) builds everything that does not change from
  frame to frame: the meshes (object frames, concatenated), the camera projection, the
  environment (prefiltered, in bands or K basis coefficients), the display, the exposure, the
  rasteriser's window capacities and the covered-pixel capacity. It returns a
  :class:`Prepared` pytree.
* :func:`render_frame` (jit-compiled, differentiable) renders one frame from a
  :class:`Prepared` and the TRACED per-frame inputs: the materials of all objects, their model
  matrices ``(O, 4, 4)``, the camera's view matrix ``(4, 4)`` and a visibility mask ``(O,)``.
  New poses, a hidden object or new material values reuse the same compiled program.

Per frame (eq. 5 + eq. 6 of Mochizuki & Tanaka in our physical reading):

1. vertices → world (per-object model matrix) → clip; hidden objects collapse to a point, so
   their triangles are degenerate and draw nothing;
2. rasterise all objects at once (:func:`~spectral_fit.geometry.rasterize` with planned
   capacities; only the triangles of the clusters that may face the eye,
   :mod:`spectral_fit.geometry`, bit-identical to a raster of all), compact the covered
   pixels (:func:`~spectral_fit.geometry.covered_pixels`), interpolate world positions and
   normals there (a :class:`~spectral_fit.geometry.GBuffer`);
3. shade each covered pixel with its object's material under the environment
   (:func:`~spectral_fit.lighting.shade`), radiance in W·sr⁻¹·m⁻²·nm⁻¹ per band or basis
   coefficient, and add the interreflection between objects
   (``spectral_fit.rendering.interreflection.interreflection``; modes "gather", "paper", "none");
4. background = the environment seen through each pixel (no video), looked up in a precomputed
   XYZ copy of the map (exact: the lookup is linear);
5. XYZ (absolute, cd/m², 683 lm/W) → display RGB (:func:`~spectral_fit.color.to_display`:
   exposure, clipping in linear RGB with the out-of-gamut fraction reported, tone curve).

Exposure ``"auto"``: the luminance of a perfect white Lambertian diffuser facing the camera
under the environment, E_irr(−forward)·683∫ȳ/π, is shown as display white (the scene white of
docs/conventions.md, 'Colorimetry and display'), so diffuse objects never clip.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
import warnings
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.backend import as_chunks, materialise, materialise_each, on_accelerator
from .._runtime.dispatch import array_jit
from .._runtime.errors import InputError
from .._runtime.process import single_threaded_blas
from ..geometry import (
    GBuffer,
    ObjectGeometry,
    build_clusters,
    capacity_ladder,
    eye_position,
    inverse_3x3,
    inverse_4x4,
    spatial_order,
)
from ..lighting import Material

__all__ = [
    "Prepared",
    "Frame",
    "PixelFrame",
    "prepare",
    "render_frame",
    "render_pixels",
    "render_senders",
    "mirror_needed",
    "with_output",
    "render",
    "scene_materials",
    "load_environment",
    "TRACE_COUNT",
    "camera_clip",
    "ir_fallback",
    "regrow",
    "all_visible",
    "plan_capacities",
]

#: number of times :func:`render_frame` has been traced (i.e. compiled), for tests and reports
TRACE_COUNT = {"render_frame": 0, "ir_senders": 0}

_IR_MODES = ("gather", "paper", "none")
#: environment shading qualities of frames (see :func:`prepare`)
QUALITIES = ("fast", "render", "exact")


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
    env: Any
    env_xyz: jax.Array
    to_xyz: jax.Array
    to_spectrum: jax.Array
    exposure: jax.Array
    materials: Material
    irradiance_lut: jax.Array | None
    split_map: Any
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
    raster_config: Any = eqx.field(static=True)
    ir_raster_config: Any = eqx.field(static=True)
    pixel_capacity: tuple[int, ...] = eqx.field(static=True)
    object_slices: tuple[tuple[int, int], ...] = eqx.field(static=True)
    triangle_slices: tuple[tuple[int, int], ...] = eqx.field(static=True)
    ir_object_slices: tuple[tuple[int, int], ...] = eqx.field(static=True)
    ir_triangle_slices: tuple[tuple[int, int], ...] = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)
    display: Any = eqx.field(static=True)
    scene_white_xy: tuple[float, float] | None = eqx.field(static=True)
    batch_size: int = eqx.field(static=True, default=32)
    quality: str = eqx.field(static=True, default="fast")
    split_settings: Any = eqx.field(static=True, default=None)
    cull: str = eqx.field(static=True, default="none")
    lens: jax.Array | None = None
    pixel_rays: jax.Array | None = None
    clusters: Any = None

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


# --------------------------------------------------------------------------------------------
# preparation (Python)


def load_environment(scene: Any, wavelengths: np.ndarray) -> np.ndarray:
    """The scene's environment map as spectral radiance (Hm, Wm, L) on ``wavelengths`` (nm),
    times the config's ``scale``: a spectral OpenEXR is resampled (linear), an RGB one is lifted
    with the config's upsampling method."""
    from ..color import resample
    from ..io import read_spectral_exr
    from ..lighting import read_rgb_environment

    spec = scene.environment
    try:
        wl_in, img = read_spectral_exr(spec.file)
    except InputError as exc:
        try:
            _, img = read_rgb_environment(spec.file, wavelengths, method=spec.upsampling)
        except InputError:
            raise exc from None
        return np.asarray(img, np.float64) * spec.scale
    if not (wl_in.size == wavelengths.size and np.allclose(wl_in, wavelengths)):
        img = resample(wl_in, img, wavelengths, path=spec.file, field="environment.file")
    return np.asarray(img, np.float64) * spec.scale


def _ir_mesh(obj: Any, mesh: Any, mode: str) -> Any:
    """The mesh the interreflection's pass 1 rasterises for ``obj`` (whose camera mesh is
    ``mesh``). Gather mode resolves a sender on a (SUPERSAMPLE · g)² = 64² raster framed on
    its bounding sphere, where the paper's 100 × 100 UV sphere puts ~10,000 front faces on
    ~3,200 covered texels: an analytic sphere is tessellated for that raster instead, a UV
    sphere with at most 64 slices × 32 stacks (~3 texels per slice at the equator; its
    polygon lies within 0.0012 r = 0.04 texel of the sphere) and an icosphere subdivided at
    most until it has ≥ 64² triangles (4 times: 5,120). Same sphere, same samples to well
    below the raster's resolution (tests/test_interreflection.py), at a fifth of the
    pass-1 raster's triangles (about half the pass's cost). Meshes from files and
    the paper mode (eq. 6's textures, rasterised at texture_size in perspective) keep
    ``mesh``."""
    from ..io import icosphere, uv_sphere
    from .interreflection._pass1 import GATHER_SIZE, SUPERSAMPLE

    if mode != "gather":
        return mesh
    side = SUPERSAMPLE * GATHER_SIZE
    if obj.shape == "uv_sphere":
        stacks, slices = min(obj.stacks, side // 2), min(obj.slices, side)
        if (stacks, slices) != (obj.stacks, obj.slices):
            return uv_sphere(obj.radius, stacks, slices)
    elif obj.shape == "icosphere":
        s = 0
        while 20 * 4 ** s < side * side:
            s += 1
        if s < obj.subdivisions:
            return icosphere(obj.radius, s)
    return mesh


def scene_materials(scene: Any, *, basis: Any = None) -> list[Material]:
    """The config's materials (one per object), reflectance on the scene's band grid or
    projected on ``basis`` (a :class:`~spectral_fit.color.SpectralBasis`)."""
    from ..lighting import make_material

    out = []
    for obj in scene.objects:
        m = obj.material
        refl = np.asarray(m.reflectance, np.float64)
        if basis is not None:
            refl = basis.project(refl)
        out.append(make_material(alpha=m.alpha, beta=m.beta, chi=m.chi, mu=m.mu, n=m.n,
                                 gamma=m.gamma, reflectance=refl, distribution=m.distribution,
                                 geometry=m.geometry))
    return out


def _stack(materials: Sequence[Material]) -> Material:
    first = materials[0]
    return Material(**{f: jnp.stack([jnp.asarray(getattr(m, f), jnp.float32)
                                     for m in materials])
                       for f in ("alpha", "beta", "chi", "mu", "n", "gamma", "reflectance")},
                    distribution=first.distribution, geometry=first.geometry)


def _projection(scene: Any, shape: tuple[int, int]) -> np.ndarray:
    from ..geometry import intrinsics_matrix, intrinsics_to_projection, perspective

    cam = scene.camera
    h, w = shape
    if cam.intrinsics is None:
        return np.asarray(perspective(cam.fov_y_deg, w / h, cam.near, cam.far))
    i = cam.intrinsics
    sx, sy = w / scene.width, h / scene.height  # intrinsics are given for the config's size
    k = intrinsics_matrix(i["fx"] * sx, i["fy"] * sy, (i["cx"] + 0.5) * sx - 0.5,
                          (i["cy"] + 0.5) * sy - 0.5)
    return np.asarray(intrinsics_to_projection(k, w, h, cam.near, cam.far))


def _lens(scene: Any, proj: np.ndarray, shape: tuple[int, int]
          ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """The camera's lens vector (9,), pixel rays (H·W, 3) (:mod:`spectral_fit.geometry`) and
    OpenCV intrinsics (3, 3) for the projection ``proj`` at ``shape``, or three None for a
    pinhole. The distortion coefficients act on normalised coordinates, so they hold at any
    frame size."""
    from ..geometry import is_identity, lens_parameters, pixel_rays, projection_to_intrinsics

    dist = scene.camera.distortion
    if is_identity(dist):
        return None, None, None
    path = getattr(scene, "path", None)
    lens = lens_parameters(dist, path=path)
    k = np.asarray(projection_to_intrinsics(proj, shape[1], shape[0]), np.float64)
    return lens, pixel_rays(k, lens, shape, path=path), k


#: largest midpoint error (pixels) of a triangle edge under the lens before prepare warns
LENS_EDGE_TOLERANCE_PX = 0.25


def _check_lens_tessellation(scene: Any, k: np.ndarray, shape: tuple[int, int],
                             lens: np.ndarray, world: np.ndarray, view: np.ndarray,
                             triangles: np.ndarray, tsl: Sequence[tuple[int, int]]) -> None:
    """Warn when an object's triangles are too large for the vertex-distortion raster: an edge
    (of the configured pose, its midpoint in the frame) whose straight raster misses the
    lens's image of its midpoint by more than ``LENS_EDGE_TOLERANCE_PX``
    (:func:`~spectral_fit.geometry.edge_error_px`; ``k``: the intrinsics at ``shape``)."""
    from ..geometry import edge_error_px

    h, w = shape
    eye = world @ view[:3, :3].T.astype(np.float64) + view[:3, 3]
    for (ta, tb), obj in zip(tsl, scene.objects, strict=True):
        t = triangles[ta:tb]
        edges = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
        err, mid_px = edge_error_px(eye, edges, lens, k)
        u, v = mid_px[:, 0], mid_px[:, 1]
        front = 0.5 * (eye[edges[:, 0], 2] + eye[edges[:, 1], 2]) < -1e-9
        seen = front & (u > -0.1 * w) & (u < 1.1 * w) & (v > -0.1 * h) & (v < 1.1 * h)
        worst = float(err[seen].max()) if seen.any() else 0.0
        if worst > LENS_EDGE_TOLERANCE_PX:
            warnings.warn(
                f"{obj.name}: its triangles are large for this lens: a straight edge misses "
                f"the distorted image of its midpoint by up to {worst:.2f} px; tessellate it "
                "more finely (stacks/slices, or a denser mesh)", RuntimeWarning, stacklevel=3)


def camera_clip(projection: Any, view: Any, lens: Any, world: Any, xp: Any = jnp) -> Any:
    """Clip coordinates (V, 4) of world points (V, 3) seen by the camera: ``projection @
    view``, with the vertices distorted in eye space first when there is a ``lens``
    (:func:`~spectral_fit.geometry.distort_eye`). ``xp``: ``jax.numpy`` (traced) or ``numpy``
    (capacity planning)."""
    if lens is None:
        vp = projection @ view
        return world @ vp[:, :3].T + vp[:, 3]
    from ..geometry import distort_eye

    eye = distort_eye(world @ view[:3, :3].T + view[:3, 3], lens, xp)
    return eye @ projection[:, :3].T + projection[:, 3]


_DISPLAYS: dict[tuple, Any] = {}


def _display(spec: Any) -> Any:
    """The scene's Display, one instance per characterisation (it is a static argument of the
    compiled frame and compares by identity, so equal scenes must share it)."""
    from ..color import Display, fit_display_csv

    if spec.characterisation is not None:
        p = spec.characterisation
        key = ("csv", str(p), p.stat().st_mtime_ns)
    else:
        key = ("colourspace", spec.colourspace)
    if key not in _DISPLAYS:
        _DISPLAYS[key] = (fit_display_csv(spec.characterisation) if key[0] == "csv"
                          else Display.from_colourspace(spec.colourspace))
    return _DISPLAYS[key]


def _white_luminance(y_map: np.ndarray, rotation_y_deg: float, normal: np.ndarray) -> float:
    """Luminance (cd/m²) of a perfect white Lambertian with world normal ``normal`` under a
    map of luminance ``y_map`` (Hm, Wm): Σ Y max(0, N·ω) Δω / π (exact texel sum)."""
    from ..lighting import rotation_y, texel_directions, texel_solid_angles

    h, w = y_map.shape
    n_map = rotation_y(rotation_y_deg).T @ (normal / np.linalg.norm(normal))
    cos = np.maximum(texel_directions(h, w) @ n_map, 0.0)
    return float(np.sum(y_map * cos * texel_solid_angles(h, w)) / math.pi)


def plan_capacities(clip: np.ndarray, triangles: np.ndarray, shape: tuple[int, int], *,
                    headroom: float = 1.5, cull: str = "none") -> tuple[Any, int]:
    """Rasteriser window capacities and a bound on the covered pixels for one pose, in NumPy
    (no compilation): :func:`spectral_fit.geometry.plan_counts` (the rasteriser's own window
    counting, with its ``cull`` mode). Returns (RasterConfig, pixel bound); the capacities
    are ``headroom`` × the counts on the rasteriser's ladder."""
    from ..geometry import RasterConfig, plan_counts

    counts = plan_counts(clip, triangles, shape, cull=cull)
    return RasterConfig.from_counts(counts, headroom=headroom), counts.pixels


def irradiance_table(texels: np.ndarray, shape: tuple[int, int] = (32, 64),
                     source_texels: int = 64 * 128) -> np.ndarray:
    """The paper's irradiance map I_d: irradiance E(N) = Σ L(ω) max(0, N·ω) Δω (C channels,
    bands or basis coefficients; exact texel sum with exact texel solid angles) at the texel
    centres of an (Hl, Wl) equirectangular grid of normals in the MAP frame, then the two
    pole values. Returns (Hl·Wl + 2, C). The map is first averaged down (solid-angle weighted)
    to at most ``source_texels`` texels, which keeps every source's flux."""
    from ..lighting import texel_directions, texel_solid_angles, uv_to_direction

    img = np.asarray(texels, np.float64)
    h, w, c = img.shape
    f = 1
    while (h // (2 * f)) * (w // (2 * f)) >= source_texels and h % (2 * f) == 0 \
            and w % (2 * f) == 0:
        f *= 2
    sa = texel_solid_angles(h, w)
    if f > 1:
        wsum = sa.reshape(h // f, f, w // f, f).sum(axis=(1, 3))
        img = (img * sa[..., None]).reshape(h // f, f, w // f, f, c).sum(axis=(1, 3))
        img = img / wsum[..., None]
        h, w = h // f, w // f
        sa = texel_solid_angles(h, w)
    src = texel_directions(h, w).reshape(-1, 3)
    rad = img.reshape(-1, c) * sa.reshape(-1, 1)
    hl, wl = shape
    normals = np.concatenate([texel_directions(hl, wl).reshape(-1, 3),
                              uv_to_direction(0.0, 0.0)[None], uv_to_direction(0.0, 1.0)[None]])
    return np.maximum(normals @ src.T, 0.0) @ rad


def _ir_generic_config(mode: str, texture_size: int, triangles: int) -> Any:
    """The generic window capacities of a pass-1 raster of ``triangles`` triangles
    (:func:`~spectral_fit.rendering.interreflection._pass1.pass1_config`) on the pass-1 frame:
    64² for
    gather (4× supersampled 16² samples), ``texture_size``² for paper."""
    from .interreflection._pass1 import SUPERSAMPLE, pass1_config

    return pass1_config(triangles, texture_size if mode == "paper" else SUPERSAMPLE * 16)


def _ir_raster_config(mode: str, texture_size: int, triangles: int,
                      paper_clips: list[np.ndarray] | None = None,
                      paper_tris: list[np.ndarray] | None = None,
                      meshes: list[tuple[np.ndarray, np.ndarray]] | None = None) -> Any:
    """Window capacities of the interreflection pass-1 rasters (inside the compiled frame, so
    they cannot be grown there; an overflow is flagged and :func:`render` / the live session
    then fall back to :func:`_ir_generic_config`). Gather: planned per sender mesh for any
    pose (``meshes``: (vertices in the object's frame, triangles);
    :func:`~spectral_fit.rendering.interreflection._pass1.plan_gather_pass1`: 1.5× the most
    that 24 views (six
    axes, four rolls each) need;
    the generic sizes give the 4×4 windows 80× what the benchmark spheres use, a cost paid
    every frame); without meshes the generic sizes. Paper: the generic sizes, and at least twice
    what the configured poses need (:func:`plan_capacities` on each pair's view)."""
    if mode == "none":
        return None
    if mode == "gather" and meshes:
        from .interreflection._pass1 import plan_gather_pass1

        planned: dict[bytes, Any] = {}
        for v, t in meshes:  # identical meshes (the paper's two spheres) planned once
            key = hashlib.sha1(np.ascontiguousarray(v, np.float32).tobytes()
                               + np.ascontiguousarray(t, np.int32).tobytes()).digest()
            if key not in planned:
                planned[key] = plan_gather_pass1(v, t)
        cfgs = list(planned.values())
        return cfgs[0]._replace(
            capacities=tuple(max(c) for c in zip(*(g.capacities for g in cfgs), strict=True)))
    cfg = _ir_generic_config(mode, texture_size, triangles)
    for clip, tris in zip(paper_clips or [], paper_tris or [], strict=True):
        need, _ = plan_capacities(clip, tris, (texture_size, texture_size), headroom=2.0)
        cfg = cfg._replace(capacities=tuple(max(a, b) for a, b in
                                            zip(cfg.capacities, need.capacities, strict=True)))
    return cfg


def _look_at_impl(eye, target, up):
    from ..geometry import look_at

    return look_at(eye, target, up)


_look_at_jit = jax.jit(_look_at_impl)


@single_threaded_blas()  # NumPy's BLAS threads busy-wait: docs/rendering.md "Cold start"
def prepare(
    scene: Any,
    *,
    size: tuple[int, int] | None = None,
    mode: str | None = None,
    spectral_mode: str | None = None,
    k: int | None = None,
    bounces: int | None = None,
    texture_size: int | None = None,
    headroom: float = 1.5,
    pixel_capacity: int | None = None,
    batch_size: int = 32,
    environment: np.ndarray | None = None,
    diffuse: str = "map",
    irradiance_shape: tuple[int, int] = (32, 64),
    quality: str = "fast",
    split_settings: Any = None,
) -> Prepared:
    """Precompute a scene for :func:`render_frame` (explicit precomputation).

    Args:
        scene: a :class:`~spectral_fit.io.Scene` (``load_scene``) or a path to a config.
        size: (W, H) frame size in pixels, replacing the config's ``[frame]``.
        mode: interreflection mode "gather" | "paper" | "none" (default: the config's).
        spectral_mode: "bands" | "basis" (default: the config's); ``k`` basis size.
        bounces, texture_size: interreflection settings (default: the config's).
        headroom: capacities (raster windows, covered pixels) are this multiple of what the
            configured poses need, so that objects can move without recompiling; overflow is
            reported in ``Frame.stats`` (and :func:`render` grows the buffers and re-renders).
        pixel_capacity: covered-pixel list size per object (an int for all, or one per
            object; default: from the configured poses).
        batch_size: shading batch (points per ``lax.map`` step of ``shade_points``; small
            batches keep the gloss lookups in cache).
        environment: (Hm, Wm, L) spectral radiance on the scene grid to use instead of the
            config's file (the config's rotation applies, its scale does not).
        diffuse: irradiance of the diffuse term: "map" (default; the paper's irradiance map,
            a look-up table over normal directions of ``irradiance_shape`` texels, each the
            exact texel sum over the environment, looked up bilinearly), "sh" (order-2
            spherical harmonics: smooth but up to ~10 % of the peak off under a lamp) or
            "exact" (texel sum over the whole map per sample: the reference, slow).
        quality: gloss of the environment shading: "fast" (default; the pre-integrated
            split-sum approximation ``environment.gloss_split_sum``, a few prefiltered lookups
            per pixel), "render" (the quadrature with 8 × 16 nodes) or "exact" (the oracle-grade
            lobe grid, 128 × 24 half-vector nodes, and a texel sum for wide lobes; see
            ``environment.gloss_integral``). Accuracy and cost of each: docs/rendering.md and
            docs/lighting.md.
        split_settings: :class:`~spectral_fit.lighting.SplitSum` for "fast" (default
            settings when None).
    Raises:
        InputError: bad options (naming the option), unreadable files (naming the file).
    """
    from ..color import pca_basis, xyz_weights
    from ..io import Scene, load_scene
    from ..lighting import EnvironmentMap, SplitSum, SplitSumMap

    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    if size is None:
        shape = (scene.height, scene.width)
    else:
        try:
            w, h = (int(s) for s in size)
        except (TypeError, ValueError):
            raise InputError(f"expected (W, H), got {size!r}", field="size") from None
        if not (0 < w <= 16384 and 0 < h <= 16384):
            raise InputError(f"W and H must be in 1..16384, got {(w, h)}", field="size")
        shape = (h, w)
    ir_mode = scene.interreflection.mode if mode is None else mode
    if quality not in QUALITIES:
        raise InputError(f"must be one of {list(QUALITIES)}, got {quality!r}",
                         field="quality")
    if diffuse not in ("map", "sh", "exact"):
        raise InputError(f"must be 'map', 'sh' or 'exact', got {diffuse!r}", field="diffuse")
    if ir_mode not in _IR_MODES:
        raise InputError(f"must be one of {list(_IR_MODES)}, got {ir_mode!r}", field="mode")
    smode = scene.spectral.mode if spectral_mode is None else spectral_mode
    if smode not in ("bands", "basis"):
        raise InputError(f"must be 'bands' or 'basis', got {smode!r}", field="spectral_mode")
    wl = scene.wavelengths
    kk = int(scene.spectral.k if k is None else k)
    if smode == "basis" and not (1 <= kk <= wl.size):
        raise InputError(f"must be in 1..{wl.size}, got {kk}", field="k")
    nb = scene.interreflection.bounces if bounces is None else int(bounces)
    ts = scene.interreflection.texture_size if texture_size is None else int(texture_size)

    # meshes in object frames, concatenated (and those the interreflection's pass 1 uses)
    meshes = [obj.make_mesh() for obj in scene.objects]
    vertices, normals, triangles, vobj_a, tobj_a, vsl, tsl = _concat_meshes(meshes)
    # each object's triangles in a spatial order: runs of them are the clusters the frame
    # culls before its raster (spectral_fit.geometry)
    triangles = triangles[spatial_order(vertices, triangles, tsl)]
    model = np.stack([obj.model_matrix() for obj in scene.objects]).astype(np.float32)
    ir_meshes = [_ir_mesh(obj, m, ir_mode) for obj, m in zip(scene.objects, meshes,
                                                              strict=True)]
    # the camera culls back faces when no mesh has an opening or inward winding (the gather
    # pass 1 always does: it assumes closed senders): half the raster's windows
    from ..io import is_closed_outward

    cull = ("back" if all(is_closed_outward(m.vertices, m.triangles) for m in meshes)
            else "none")
    if all(a is b for a, b in zip(ir_meshes, meshes, strict=True)):
        ir_v, ir_n, ir_t, ir_o, ir_vsl, ir_tsl = vertices, normals, triangles, vobj_a, vsl, tsl
    else:
        ir_v, ir_n, ir_t, ir_o, _, ir_vsl, ir_tsl = _concat_meshes(ir_meshes)

    cam = scene.camera
    view = np.asarray(_look_at_jit(np.asarray(cam.position, np.float32),
                                   np.asarray(cam.look_at, np.float32),
                                   np.asarray(cam.up, np.float32)), np.float32)
    proj = _projection(scene, shape).astype(np.float32)

    # environment
    img = load_environment(scene, wl) if environment is None else np.asarray(environment)
    W = xyz_weights(wl)  # (L, 3) absolute
    basis = None
    if smode == "basis":
        basis = pca_basis(kk, wl)
        env = EnvironmentMap.from_array(basis.project(img), product_tensor=basis.product_tensor,
                                        rotation_y_deg=scene.environment.rotation_y_deg,
                                        compress_tol=scene.environment.compress_tol,
                                        path=str(scene.environment.file),
                                        diffuse="exact" if diffuse == "exact" else "sh")
        to_xyz = basis.components @ W
        to_spectrum = basis.components
    else:
        env = EnvironmentMap.from_array(img, rotation_y_deg=scene.environment.rotation_y_deg,
                                        compress_tol=scene.environment.compress_tol,
                                        path=str(scene.environment.file),
                                        diffuse="exact" if diffuse == "exact" else "sh")
        to_xyz = W
        to_spectrum = np.eye(wl.size)
    split_map = None
    if quality == "fast":
        split_settings = SplitSum() if split_settings is None else split_settings
        if not isinstance(split_settings, SplitSum):
            raise InputError(f"expected a SplitSum, got {type(split_settings).__name__}",
                             field="split_settings")
        split_map = SplitSumMap.from_environment(
            env, img if basis is None else basis.project(img),
            per_octave=split_settings.per_octave)
    xyz_map = img @ W
    lut = None
    if diffuse == "map":
        chan = img if basis is None else basis.project(img)
        lut = irradiance_table(chan, irradiance_shape)
    env_xyz = np.concatenate([xyz_map.reshape(-1, 3), xyz_map[0].mean(0)[None],
                              xyz_map[-1].mean(0)[None]])

    # display and exposure
    d = scene.display
    display = _display(d)
    if d.exposure_luminance == "auto":
        exposure = _white_luminance(img @ W[:, 1], scene.environment.rotation_y_deg,
                                    view[2, :3].astype(np.float64))
        if not exposure > 0:
            exposure = float(max(np.percentile(xyz_map[..., 1], 90), 1e-12))
    else:
        exposure = float(d.exposure_luminance)

    mats = _stack(scene_materials(scene, basis=basis))

    # capacities from the configured poses (NumPy: no compilation)
    world = np.einsum("vij,vj->vi", model[vobj_a][:, :3, :3].astype(np.float64),
                      vertices) + model[vobj_a][:, :3, 3]
    lens, rays, k_lens = _lens(scene, proj, shape)
    clip = camera_clip(proj.astype(np.float64), view.astype(np.float64), lens, world, np)
    if lens is not None:
        _check_lens_tessellation(scene, k_lens, shape, lens, world, view, triangles, tsl)
    cfg, _ = plan_capacities(clip, triangles, shape, headroom=headroom, cull=cull)
    clusters = (_plan_clusters(build_clusters(vertices, triangles, tsl), model, view, proj,
                               cull) if cull != "none" and lens is None else None)
    if pixel_capacity is None:
        caps = []
        for ta, tb in tsl:
            _, bound = plan_capacities(clip, triangles[ta:tb], shape, headroom=headroom,
                                       cull=cull)
            caps.append(min(shape[0] * shape[1], capacity_ladder(headroom * bound + 64, 64)))
        cap = tuple(caps)
    elif isinstance(pixel_capacity, int | np.integer):
        cap = (int(pixel_capacity),) * len(tsl)
    else:
        cap = tuple(int(c) for c in pixel_capacity)
        if len(cap) != len(tsl):
            raise InputError(f"need one capacity per object ({len(tsl)})",
                             field="pixel_capacity")
    paper_clips, paper_tris = [], []
    if ir_mode == "paper":
        from ..geometry import interreflection_camera

        centres = model[:, :3, 3]
        for i in range(len(model)):
            for j in range(len(model)):
                if i != j:
                    cam = interreflection_camera(centres[i], centres[j], aspect=1.0)
                    m = np.asarray(cam.view_projection, np.float64)
                    (a, b), (ta, tb) = vsl[j], tsl[j]
                    paper_clips.append(world[a:b] @ m[:, :3].T + m[:, 3])
                    paper_tris.append(triangles[ta:tb] - a)
    ir_cfg = _ir_raster_config(ir_mode, ts, max(b - a for a, b in ir_tsl), paper_clips,
                               paper_tris, [(ir_v[a:b], ir_t[ta:tb] - a) for (a, b),
                                            (ta, tb) in zip(ir_vsl, ir_tsl, strict=True)])

    return Prepared(
        vertices=jnp.asarray(vertices), normals=jnp.asarray(normals),
        triangles=jnp.asarray(triangles), vertex_object=jnp.asarray(vobj_a),
        tri_object=jnp.asarray(tobj_a), model=jnp.asarray(model),
        view=jnp.asarray(view), projection=jnp.asarray(proj), env=env,
        env_xyz=jnp.asarray(env_xyz, jnp.float32), to_xyz=jnp.asarray(to_xyz, jnp.float32),
        to_spectrum=jnp.asarray(to_spectrum, jnp.float32),
        exposure=jnp.asarray(exposure, jnp.float32), materials=mats,
        irradiance_lut=None if lut is None else jnp.asarray(lut, jnp.float32), shape=shape,
        wavelengths=tuple(float(x) for x in wl), spectral_mode=smode,
        k=kk if smode == "basis" else int(wl.size), ir_mode=ir_mode, ir_bounces=nb,
        ir_texture_size=ts, raster_config=cfg, ir_raster_config=ir_cfg,
        pixel_capacity=cap,
        object_slices=tuple(vsl), triangle_slices=tuple(tsl),
        names=tuple(o.name for o in scene.objects), display=display,
        scene_white_xy=None if d.scene_white_xy is None else tuple(d.scene_white_xy),
        batch_size=int(batch_size), quality=quality, split_map=split_map,
        split_settings=split_settings if quality == "fast" else None,
        ir_vertices=jnp.asarray(ir_v, jnp.float32), ir_normals=jnp.asarray(ir_n, jnp.float32),
        ir_triangles=jnp.asarray(ir_t, jnp.int32), ir_vertex_object=jnp.asarray(ir_o, jnp.int32),
        ir_object_slices=tuple(ir_vsl), ir_triangle_slices=tuple(ir_tsl), cull=cull,
        lens=None if lens is None else jnp.asarray(lens, jnp.float32),
        pixel_rays=None if rays is None else jnp.asarray(rays), clusters=clusters,
    )


def _plan_clusters(clusters: Any, model: np.ndarray, view: np.ndarray, proj: np.ndarray,
                   cull: str) -> Any:
    """``clusters`` with its kept-list capacity: the clusters kept at the pose, or seen
    from any direction (:func:`~spectral_fit.geometry.worst_direction_count`: objects that
    turn), whichever is more, + 5 %, on the capacity ladder."""
    from ..geometry import count_clusters, sized, worst_direction_count

    need = max(count_clusters(clusters, model, view, proj, cull=cull),
               worst_direction_count(clusters))
    return sized(clusters, 1.05 * need + 4)


def _concat_meshes(meshes: Sequence[Any]) -> tuple[Any, ...]:
    """:func:`~spectral_fit.io.concat_meshes` as the renderer keeps it: vertices (V, 3),
    normals (V, 3) float32, triangles (T, 3) int32, the object of each vertex (V,) and of each
    triangle (T,) int32, and the (start, stop) vertex and triangle ranges per mesh."""
    from ..io import concat_meshes

    mesh, toffs = concat_meshes(list(meshes))
    nv = np.cumsum([0] + [len(m.vertices) for m in meshes])
    vsl = [(int(a), int(b)) for a, b in zip(nv[:-1], nv[1:], strict=True)]
    tsl = [(int(a), int(b)) for a, b in zip(toffs[:-1], toffs[1:], strict=True)]
    vobj = np.repeat(np.arange(len(meshes), dtype=np.int32), np.diff(nv))
    tobj = np.repeat(np.arange(len(meshes), dtype=np.int32), np.diff(toffs))
    return (mesh.vertices.astype(np.float32), mesh.normals.astype(np.float32),
            mesh.triangles.astype(np.int32), vobj, tobj, vsl, tsl)


# --------------------------------------------------------------------------------------------
# one frame (traced)


def _to_world(vertices: jax.Array, vertex_object: jax.Array, model: jax.Array) -> jax.Array:
    m = model[vertex_object]  # (V, 4, 4)
    return jnp.einsum("vij,vj->vi", m[:, :3, :3], vertices) + m[:, :3, 3]


def _normals_to_world(normals: jax.Array, vertex_object: jax.Array, model: jax.Array
                      ) -> jax.Array:
    nm = jnp.swapaxes(inverse_3x3(model[:, :3, :3]), 1, 2)  # inverse transpose, (O, 3, 3)
    n = jnp.einsum("vij,vj->vi", nm[vertex_object], normals)
    return n / jnp.linalg.norm(n, axis=-1, keepdims=True)


def _as_stacked(materials: Any, n_objects: int) -> list[Material]:
    """Materials → a list of per-object Materials (accepts a stacked Material or a sequence)."""
    if isinstance(materials, Material):
        a = jnp.asarray(materials.alpha)
        if a.ndim == 0:
            if n_objects != 1:
                raise InputError(f"one material given for {n_objects} objects",
                                 field="materials")
            return [materials]
        if a.shape[0] != n_objects:
            raise InputError(f"{a.shape[0]} materials for {n_objects} objects",
                             field="materials")
        return [jax.tree.map(lambda x, i=i: x[i], materials) for i in range(n_objects)]
    mats = list(materials)
    if len(mats) != n_objects:
        raise InputError(f"{len(mats)} materials for {n_objects} objects", field="materials")
    return mats


def mirror_needed(materials: Any) -> bool:
    """Whether a frame of ``materials`` needs the perfect-mirror term (χ) at all: False only
    when every χ is a concrete 0 (not traced: under ``jax.grad``, ``vmap`` or a caller's
    ``jit`` it is True). The frame is then compiled without the mirror: the direct term's
    lookup along R and, the larger part, the neighbours' mirror radiance that the
    interreflection would otherwise carry in every channel (the paper's plastics have χ = 0).
    Exact: a term multiplied by a concrete 0 is left out, nothing else changes."""
    for x in _chi_leaves(materials):
        if isinstance(x, jax.core.Tracer):
            return True
        if not _all_zero(x):
            return True
    return False


#: the last device arrays :func:`_all_zero` read, with the answer (weak references): the frame's
#: default materials are the same arrays every frame, and reading them is a device → host copy
_ZERO_MEMO: list[tuple[Any, bool]] = []


def _all_zero(x: Any) -> bool:
    """Whether every element of the concrete array ``x`` is 0 (NaN is not)."""
    import weakref

    if not isinstance(x, jax.Array):
        return bool(np.all(np.asarray(x) == 0.0))
    for ref, answer in _ZERO_MEMO:
        if ref() is x:
            return answer
    answer = bool(np.all(np.asarray(x) == 0.0))
    _ZERO_MEMO.insert(0, (weakref.ref(x), answer))
    del _ZERO_MEMO[4:]
    return answer


def _chi_leaves(materials: Any) -> list[Any]:
    """χ of a stacked Material or of each Material of a sequence."""
    return [materials.chi] if isinstance(materials, Material) else [m.chi for m in materials]


def _without_mirror(mats: list[Material]) -> list[Material]:
    """The materials with χ a concrete 0 (see :func:`mirror_needed`): the shading and the
    interreflection then leave the mirror term out at trace time."""
    return [eqx.tree_at(lambda m: m.chi, m, np.zeros(np.shape(m.chi), np.float32))
            for m in mats]


def _shade_samples(mats: list[Material], env: Any, gb: GBuffer, batch: int,
                   lut: jax.Array | None = None, quality: str = "render",
                   capacities: tuple[int, ...] | None = None, split_map: Any = None,
                   split_settings: Any = None) -> jax.Array:
    """Environment shading (eq. 5) of the G-buffer samples, (N, C): the samples are laid out
    object by object (``capacities[o]`` slots for object o), and each object's slice is shaded
    with its material by :func:`~spectral_fit.lighting.shade_points`. With an irradiance map
    ``lut`` (:func:`irradiance_table`), the diffuse term α S I_d(N)/π takes its irradiance from
    the map (the gloss and mirror terms come from ``env`` as always)."""
    import dataclasses

    from ..lighting import shade_points

    if capacities is None:
        capacities = (gb.object.shape[0],)
        mats = mats[:1]
    if quality == "fast":
        return _shade_fast(mats, env, gb, lut, capacities, split_map, split_settings)
    table = None if lut is None else _lut_env(env, lut)
    out = []
    for m, cap, (nrm, v) in zip(mats, capacities, _object_slices(gb, capacities), strict=True):
        bs = max(1, min(batch, cap))
        if table is None:
            out.append(shade_points(m, env, nrm, v, batch_size=bs, quality=quality))
            continue
        spec = shade_points(dataclasses.replace(m, alpha=jnp.zeros_like(m.alpha)), env, nrm, v,
                            batch_size=bs, quality=quality)
        e = jax.vmap(lambda d: _lookup(table, d))(nrm)
        se = _filtered_irradiance(m, env, e)
        front = jnp.sum(nrm * v, axis=-1, keepdims=True) > 0.0
        out.append(spec + jnp.where(front, m.alpha / math.pi, 0.0) * se)
    return jnp.concatenate(out)


def _object_slices(gb: GBuffer, capacities: tuple[int, ...]):
    """Yield each object's (normals, views), both (capacity, 3), from the G-buffer whose samples
    are laid out object after object with the given capacities."""
    start = 0
    for cap in capacities:
        yield gb.normal[start:start + cap], gb.view[start:start + cap]
        start += cap


def _filtered_irradiance(m: Material, env: Any, e: jax.Array) -> jax.Array:
    """S(λ)·E (N, C): the irradiance ``e`` (N, C) filtered by the material's reflectance, per band
    or through the basis product tensor when the map is in K coefficients."""
    if env.product_tensor is None:
        return m.reflectance * e
    return jnp.einsum("i,nj,ijk->nk", m.reflectance, e, env.product_tensor)


def _gloss_and_mirror(env_gloss: Any, split_map: Any, env_mirror: Any, moments: jax.Array,
                      nrm: jax.Array, v: jax.Array, m: Material, settings: Any
                      ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Quality "fast" gloss and mirror of eq. (5) at points nrm, v (N, 3): the split-sum gloss
    per unit β looked up in ``env_gloss``'s channels, F(n, N·V) times the mirror radiance
    along R from ``env_mirror`` (N, C; None when ``env_mirror`` is None: no mirror term), and
    N·V (N, 1)."""
    from ..lighting import fast_lookup, fresnel_dielectric, gloss_split_sum

    gloss = gloss_split_sum(env_gloss, split_map, moments, nrm, v, m.mu, m.n,
                            settings=settings, distribution=m.distribution,
                            geometry=m.geometry)
    nv = (nrm[:, 0] * v[:, 0] + nrm[:, 1] * v[:, 1] + nrm[:, 2] * v[:, 2])[:, None]
    refl = 2.0 * nv * nrm - v
    # per-point factors computed once (not inside each of the C channels' expressions)
    fac = materialise(jnp.concatenate([fresnel_dielectric(nv, m.n), nv], axis=-1))
    mirror = None if env_mirror is None else fac[:, 0:1] * fast_lookup(env_mirror, refl)
    return gloss, mirror, fac[:, 1:2]


def _shade_fast(mats: list[Material], env: Any, gb: GBuffer, lut: jax.Array | None,
                capacities: tuple[int, ...], split_map: Any, settings: Any) -> jax.Array:
    """Quality "fast" of :func:`_shade_samples`: eq. (5) with the split-sum gloss
    (:func:`~spectral_fit.lighting.gloss_split_sum`; one moment table per object), the
    mirror by one lookup along R and the diffuse irradiance from the irradiance map ``lut``
    (or ``env``), all points of an object at once (few lookups per point: no batching)."""
    from ..lighting import fast_lookup, irradiance, lobe_moment_table

    table = None if lut is None else _lut_env(env, lut)
    out = []
    for m, (nrm, v) in zip(mats, _object_slices(gb, capacities), strict=True):
        kw = dict(distribution=m.distribution, geometry=m.geometry)
        moments = lobe_moment_table(m.mu, m.n, settings=settings, **kw)
        gloss, mirror, nv = _gloss_and_mirror(env, split_map,
                                              env if mirror_needed([m]) else None, moments,
                                              nrm, v, m, settings)
        if table is None:
            e = jax.vmap(lambda d: irradiance(env, d))(nrm)
        else:
            e = fast_lookup(table, nrm)
        se = _filtered_irradiance(m, env, e)
        front = nv > 0.0
        rad = (m.alpha / math.pi) * se + m.beta * gloss
        if mirror is not None:
            rad = rad + m.chi * mirror
        out.append(jnp.where(front, rad, 0.0))
    return jnp.concatenate(out)


def _lut_env(env: Any, flat: jax.Array, shape: tuple[int, int] | None = None) -> Any:
    """``env`` with its texels/poles replaced by a table laid out as texels + 2 pole rows
    (same rotation), for :func:`~spectral_fit.lighting.lookup`."""
    c = flat.shape[-1]
    if shape is None:
        n = flat.shape[0] - 2
        h = int(round(math.sqrt(n / 2)))
        shape = (h, n // h)
    return eqx.tree_at(lambda e: (e.texels, e.poles), env,
                       (flat[:-2].reshape(shape[0], shape[1], c), flat[-2:]))


def _lookup(table: Any, direction: jax.Array) -> jax.Array:
    from ..lighting import lookup

    return lookup(table, direction)


_IR_WARNED: set[str] = set()


def _interreflection(prep: Prepared, geoms: list[ObjectGeometry], mats: list[Material],
                     gb: GBuffer, to_out: jax.Array | None) -> tuple[jax.Array | None, jax.Array]:
    """Interreflection radiance (N, D) to add, in the output channels of ``to_out`` (C, D)
    (the C channels when ``to_out`` is None; None when off), and the pass-1 overflow flag."""
    no = jnp.zeros((), bool)
    if prep.ir_mode == "none" or len(geoms) < 2:
        return None, no
    try:
        from .interreflection._transport import interreflection_from
    except ImportError:
        if prep.ir_mode not in _IR_WARNED:
            _IR_WARNED.add(prep.ir_mode)
            warnings.warn(f"interreflection mode {prep.ir_mode!r} is not available in this "
                          "installation (spectral_fit.rendering.interreflection missing); "
                          "rendering without interreflection", RuntimeWarning, stacklevel=4)
        return None, no
    geom = _ir_pass1(prep, geoms)
    # paper mode's pass-1 textures shaded as the frame is: by the split sum in quality "fast"
    split = ((prep.split_map, prep.split_settings)
             if prep.ir_mode == "paper" and prep.split_map is not None else None)
    extra = interreflection_from(geom, mats, prep.env, gb, mode=prep.ir_mode,
                                 bounces=prep.ir_bounces, image_shape=prep.shape,
                                 output=to_out, split_sum=split)
    return extra, jnp.asarray(geom.overflow, bool)


def _ir_pass1(prep: Prepared, geoms: list[ObjectGeometry]) -> Any:
    """The interreflection's pass 1 (geometry only) of the objects, with ``prep``'s mode,
    texture size and planned raster capacities."""
    from .interreflection._pass1 import prepare_interreflection

    with jax.named_scope("ir_pass1"):
        return prepare_interreflection(geoms, mode=prep.ir_mode,
                                       texture_size=prep.ir_texture_size,
                                       raster_config=prep.ir_raster_config)


def _background(prep: Prepared, flat: jax.Array, view: jax.Array) -> jax.Array:
    """The environment seen through each pixel centre: bilinear lookups (H·W, C') of a table
    laid out as the map's texels + 2 pole rows (e.g. ``prep.env_xyz``). Per pixel the map-frame
    ray direction is an affine function of the pixel coordinates (one 3 × 3 matrix for the
    frame: inverse projection, camera rotation and map rotation), evaluated by components
    (:func:`_pinhole_ray_components`, not normalised); (u, v) as
    :func:`~spectral_fit.lighting.fast_direction_to_uv`'s; the lookup from the table laid
    out with a pole row above and below and a wrapped column
    (:func:`~spectral_fit.lighting.padded_bilinear`, bit-identical to the general one).
    Through a lens (``prep.pixel_rays``) each pixel's ray is looked up instead (rotated into
    the map frame)."""
    from ..lighting import fast_direction_to_uv, padded_bilinear, padded_table, uv_of

    env = prep.env
    hm, wm = env.texels.shape[:2]
    if prep.pixel_rays is not None:  # through the lens: the pixel centres' own rays
        # eye → world is view[:3, :3]ᵀ (a rotation), then the map's rotation
        m = view[:3, :3] @ env.rotation
        r = [prep.pixel_rays[:, i] for i in range(3)]
        dmap = jnp.stack([r[0] * m[0, j] + r[1] * m[1, j] + r[2] * m[2, j] for j in range(3)],
                         axis=-1)
        u, v = materialise_each(*fast_direction_to_uv(dmap))
    else:  # (u, v) straight from the rays' components, written once as two planes
        u, v = materialise_each(*(c.reshape(-1) for c in uv_of(
            *_pinhole_ray_components(prep, view, env.rotation))))
    return padded_bilinear(padded_table(flat, hm, wm), u, v, hm, wm)


def _pinhole_ray_components(prep: Prepared, view: jax.Array, rot: jax.Array
                            ) -> list[jax.Array]:
    """The map-frame rays of the pixel centres of ``prep``'s pinhole camera as three (H, W)
    components, not normalised (the (u, v) of a direction do not depend on its length; about
    unit length near the image centre); ``rot``: the map's rotation (see :func:`_background`).

    A far-plane point of NDC (x, y, 1, 1) minus the eye, as a function of the pixel's NDC
    (x, y), is linear in (x, y) after the perspective division by w = inv[3] · (x, y, 1, 1),
    and w does not depend on (x, y) for a projection whose last row is (0, 0, −1, 0) (any
    OpenGL pinhole, intrinsics included): one 3 × 3 map from (x, y, 1) to the direction. The
    components are evaluated inside the (u, v) kernel (no (H, W, 3) stack and normalisation
    written out first, which is slower; display RGB within 9e-6)."""
    h, w = prep.shape
    inv = inverse_4x4(prep.projection @ view)
    eye = eye_position(view)
    wrow = inv[3]
    cols = [inv[:3, 0], inv[:3, 1], inv[:3, 2] + inv[:3, 3]]
    wx, wy, w1 = wrow[0], wrow[1], wrow[2] + wrow[3]
    # d(x, y) = (x c0 + y c1 + c2) / den − eye with den = x wx + y wy + w1 (> 0: a constant
    # w1 for an OpenGL pinhole); times den (> 0, so the direction is unchanged):
    # d ∝ x (c0 − eye wx) + y (c1 − eye wy) + (c2 − eye w1), then rotated into the map frame
    a = [(cols[0][i] - eye[i] * wx) for i in range(3)]
    b = [(cols[1][i] - eye[i] * wy) for i in range(3)]
    c = [(cols[2][i] - eye[i] * w1) for i in range(3)]
    am, bm, cm = ([v[0] * rot[0, j] + v[1] * rot[1, j] + v[2] * rot[2, j] for j in range(3)]
                  for v in (a, b, c))
    # scaled to ~unit length at the centre ray (the uv's pole guard assumes unit-ish rays)
    s = jax.lax.rsqrt(cm[0] * cm[0] + cm[1] * cm[1] + cm[2] * cm[2]) * jnp.sign(w1)
    xs = 2.0 * (jnp.arange(w, dtype=jnp.float32) + 0.5) / w - 1.0
    ys = 1.0 - 2.0 * (jnp.arange(h, dtype=jnp.float32) + 0.5) / h
    x, y = xs[None, :], ys[:, None]
    return [x * (am[j] * s) + y * (bm[j] * s) + cm[j] * s for j in range(3)]


def _env_lookup(env: Any, flat: jax.Array, dirs: jax.Array) -> jax.Array:
    """Bilinear lookups (N, C') of a table laid out as the map's texels + 2 pole rows."""
    from ..lighting import fast_lookup

    return fast_lookup(_lut_env(env, flat, env.texels.shape[:2]), dirs)


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


def with_output(prep: Prepared, matrix: Any) -> Prepared:
    """``prep`` with its radiance-channels → output map replaced by ``matrix`` (C, 3) (e.g.
    channels → a video camera's linear RGB): :attr:`Frame.xyz` (and the background table, and
    the mirror lookups that the frame does in the output space) are then in that space."""
    m = np.asarray(matrix, np.float64)
    if m.shape != (prep.channels, 3) or not np.all(np.isfinite(m)):
        raise InputError(f"expected a finite ({prep.channels}, 3) matrix, got {m.shape}",
                         field="matrix")
    env = prep.env
    hm, wm, c = env.texels.shape
    flat = np.concatenate([np.asarray(env.texels, np.float64).reshape(hm * wm, c),
                           np.asarray(env.poles, np.float64)])
    return dataclasses.replace(prep, to_xyz=jnp.asarray(m, jnp.float32),
                               env_xyz=jnp.asarray(flat @ m, jnp.float32))


#: largest shading chunk with the accelerator layout (slots)
_ACCEL_CHUNK = 65536


def _chunk_size(capacity: int) -> int:
    """Slots per shading chunk: chunks beyond the covered-pixel count are skipped, so the
    shading cost follows the count (to within one chunk), not the planned capacity; chunks of
    a few thousand points also keep the gloss's intermediates in cache (about twice as fast
    on the close-up as one batch of all slots). With the accelerator layout
    (:mod:`spectral_fit._runtime.backend`) the chunks are as large as the capacity, up to 65,536
    slots."""
    if on_accelerator():
        return min(capacity, _ACCEL_CHUNK)
    if capacity >= 32768:
        return 4096
    if capacity >= 4096:
        return 2048
    return capacity


def _chunked(fn: Any, counts: Sequence[jax.Array], out_channels: int,
             arrays: Sequence[tuple[jax.Array, ...]]) -> list[jax.Array]:
    """``fn(o, *chunk)`` (B, K) over consecutive chunks of segment o's (cap_o, …) ``arrays[o]``
    for every segment o (one traced body for all segments: o is a traced int32), skipping
    (zeros) the chunks that start at or after ``counts[o]`` (the valid slots come first).
    With the accelerator layout all chunks run at once (``vmap``, nothing skipped): a device
    loop and a conditional per chunk cost more there than the skipped work.
    Returns the (cap_o, K) results per segment."""
    caps = [a[0].shape[0] for a in arrays]
    b = min(_chunk_size(c) for c in caps)
    nchunks = [-(-c // b) for c in caps]
    if sum(nchunks) == 1:
        return [fn(jnp.int32(0), *arrays[0])]
    padded = [as_chunks(seg, b) for seg in arrays]
    chunks = [jnp.concatenate(parts) for parts in zip(*padded, strict=True)]
    seg_of = jnp.asarray(np.repeat(np.arange(len(caps)), nchunks), jnp.int32)
    first = jnp.asarray(np.concatenate([np.arange(nc) * b for nc in nchunks]), jnp.int32)
    count = jnp.stack([jnp.asarray(c, jnp.int32) for c in counts])
    dtype = jnp.float32

    def body(x: tuple[jax.Array, ...]) -> jax.Array:
        o, start, *chunk = x
        return jax.lax.cond(start < count[o], lambda *c: fn(o, *c).astype(dtype),
                            lambda *c: jnp.zeros((b, out_channels), dtype), *chunk)

    if on_accelerator():
        out = jax.vmap(lambda o, *c: fn(o, *c).astype(dtype))(seg_of, *chunks)
    else:
        out = jax.lax.map(body, (seg_of, first, *chunks))
    res, at = [], 0
    for cap, nc in zip(caps, nchunks, strict=True):
        res.append(out[at:at + nc].reshape(nc * b, out_channels)[:cap])
        at += nc
    return res


def _shade_out(prep: Prepared, mats: list[Material], gb: GBuffer, counts: list[jax.Array],
               to_out: jax.Array, mirror_table: jax.Array) -> jax.Array:
    """Environment shading (eq. 5, quality "fast") of the G-buffer samples straight into the
    output channels (N, K): ``to_out`` (C, K) maps radiance channels to them. The gloss and
    mirror depend on λ only through the environment, so they are looked up in K channels (the
    split-sum levels' principal spectra times ``to_out``; ``mirror_table`` = the map's texels
    + 2 pole rows times ``to_out``); the diffuse term α S(λ) I_d(N)/π is one lookup of a
    per-object table (the irradiance map filtered by S(λ), times α/π, times ``to_out``, built
    per frame: 2,050 rows). In chunks of slots, chunks past each object's covered count
    skipped; the objects whose materials share a distribution and geometry share one traced
    shading body (their per-object tables and parameters selected by object), which halves
    the compilation of a two-object frame."""
    from ..lighting import fast_lookup, irradiance, lobe_moment_table

    env = prep.env
    settings = prep.split_settings
    k_out = int(to_out.shape[1])
    env_g = eqx.tree_at(lambda e: e.spectral_basis, env, env.spectral_basis @ to_out)
    mirror_env = _lut_env(env, mirror_table, env.texels.shape[:2])
    lut = prep.irradiance_lut
    slices = list(_object_slices(gb, prep.pixel_capacity))
    groups: dict[tuple[str, str], list[int]] = {}
    for i, m in enumerate(mats):
        groups.setdefault((m.distribution, m.geometry), []).append(i)
    out: list[Any] = [None] * len(mats)
    for (dist, geom), members in groups.items():
        kw = dict(distribution=dist, geometry=geom)
        group = [mats[i] for i in members]
        stacked = jax.tree.map(lambda *xs: jnp.stack([jnp.asarray(x, jnp.float32)
                                                      for x in xs]), *group)
        moments = jax.vmap(functools.partial(lobe_moment_table, settings=settings, **kw))(
            stacked.mu, stacked.n)  # (O, size, 4), one compiled table for the group
        group_mirror = mirror_env if mirror_needed(group) else None
        dflat = None
        if lut is not None:
            dflat = jnp.stack([(m.alpha / math.pi) * _filtered_irradiance(m, env, lut) @ to_out
                               for m in group])

        def shade(o: jax.Array, nn: jax.Array, vv: jax.Array, stacked: Material = stacked,
                  moments: jax.Array = moments, dflat: Any = dflat,
                  group_mirror: Any = group_mirror) -> jax.Array:
            m = jax.tree.map(lambda x: x[o], stacked)
            gloss, mirror, nv = _gloss_and_mirror(env_g, prep.split_map, group_mirror,
                                                  moments[o], nn, vv, m, settings)
            if dflat is None:
                e = jax.vmap(lambda d: irradiance(env, d))(nn)
                diffuse = (m.alpha / math.pi) * _filtered_irradiance(m, env, e) @ to_out
            else:
                diffuse = fast_lookup(_lut_env(env, dflat[o]), nn)
            rad = diffuse + m.beta * gloss
            if mirror is not None:
                rad = rad + m.chi * mirror
            return jnp.where(nv > 0.0, rad, 0.0)

        res = _chunked(shade, [counts[i] for i in members], k_out,
                       [slices[i] for i in members])
        for i, r in zip(members, res, strict=True):
            out[i] = r
    return jnp.concatenate(out)


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


def _ir_geometries(prep: Prepared, model: jax.Array, visible: jax.Array
                   ) -> list[ObjectGeometry]:
    """The objects as the interreflection sees them (its pass-1 meshes, placed by ``model``):
    a hidden object intact (no degenerate triangles, which gave NaN) but 1 km below the
    scene: its light and shadow on the others are ~1e-9 of a neighbour's."""
    centres = model[:, :3, 3]
    away = jnp.where(visible, 0.0, 1e3)[:, None] * jnp.array([0.0, -1.0, 0.0], jnp.float32)
    world_ir = (_to_world(prep.ir_vertices, prep.ir_vertex_object, model)
                + away[prep.ir_vertex_object])
    wnorm = _normals_to_world(prep.ir_normals, prep.ir_vertex_object, model)
    return [ObjectGeometry(vertices=world_ir[a:b], normals=wnorm[a:b],
                           triangles=prep.ir_triangles[ta:tb] - a, centre=centres[i] + away[i])
            for i, ((a, b), (ta, tb)) in enumerate(zip(prep.ir_object_slices,
                                                       prep.ir_triangle_slices, strict=True))]


def _senders_impl(prep: Prepared, materials: Any, model: jax.Array, visible: jax.Array,
                  mirror: bool = True) -> Any:
    from .interreflection._gather import gather_senders

    TRACE_COUNT["ir_senders"] += 1
    mats = _as_stacked(materials, prep.num_objects)
    if not mirror:
        mats = _without_mirror(mats)
    model = jnp.asarray(model, jnp.float32)
    visible = jnp.asarray(visible, bool)
    geom = _ir_pass1(prep, _ir_geometries(prep, model, visible))
    return gather_senders(geom, mats, prep.env, bounces=prep.ir_bounces)


_senders_jit = array_jit(_senders_impl)


def render_senders(prep: Prepared, materials: Any = None, *, model: Any = None,
                   visible: Any = None, mirror: bool | None = None) -> Any:
    """The camera-independent half of a gather-mode frame's interreflection (pass 1, the
    senders' shading, atlases, transfer and bounces;
    :class:`~spectral_fit.rendering.interreflection.GatherSenders`), for the objects at ``model`` /
    ``visible`` (defaults as :func:`render_frame`; traced, compiled once per ``prep``).
    Pass it to :func:`render_pixels` (``senders=``) for any number of camera views of that
    same object state: the result equals the frame that computes it itself. Its
    ``geometry.overflow`` is the pass-1 overflow flag. ``mirror``: as for
    :func:`render_frame`, and the same for the frames that use it."""
    if prep.ir_mode != "gather" or prep.num_objects < 2 or prep.ir_bounces < 1:
        raise InputError("needs a gather-mode interreflection of at least two objects and "
                         f"one bounce, got mode {prep.ir_mode!r} with {prep.num_objects} "
                         f"objects and {prep.ir_bounces} bounces", field="interreflection.mode")
    mats, model, _, visible = _check_frame_inputs(prep, materials, model, None, visible)
    return _senders_jit(prep, mats, model, visible, _mirror_flag(mats, mirror))


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
    h, w = prep.shape
    n_obj = prep.num_objects
    mats = _as_stacked(materials, n_obj)
    if not mirror:
        mats = _without_mirror(mats)
    model = jnp.asarray(model, jnp.float32)
    view = jnp.asarray(view, jnp.float32)
    visible = jnp.asarray(visible, bool)

    # 1. geometry in the world; hidden objects collapse onto their centre (draw nothing)
    world_full = _to_world(prep.vertices, prep.vertex_object, model)
    centres = model[:, :3, 3]
    vis_v = visible[prep.vertex_object]
    world = jnp.where(vis_v[:, None], world_full, centres[prep.vertex_object])
    wnorm = _normals_to_world(prep.normals, prep.vertex_object, model)
    clip = camera_clip(prep.projection, view, prep.lens, world)

    # 2. rasterise (the triangles of the clusters that may face the eye), compact covered
    # pixels, G-buffer; triangle ids below are rows of that list
    with jax.named_scope("raster"):
        tris, tri_object, clusters_needed, clusters_over = _frame_triangles(
            prep, model, view, visible)
        ras = rasterize(clip, tris, (h, w), cull=prep.cull,
                        config=prep.raster_config, check=False)
    # covered pixels, one fixed-capacity list per object (each object is shaded with its own
    # material, whose per-material precomputations then run once per object)
    with jax.named_scope("pixel_lists"):
        obj_img = jnp.where(ras.tri_id >= 0, tri_object[jnp.maximum(ras.tri_id, 0)], -1)
        pix, counts = _object_pixel_lists(ras.tri_id, obj_img, prep.pixel_capacity)
    attrs = jnp.concatenate([world, wnorm], axis=1)
    vals = interpolate_pixels(attrs, pix, tris, clip)
    pos = vals[:, :3]
    nrm = vals[:, 3:]
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

    # 3. shading + interreflection, in the output channels (XYZ, or all channels for the
    # spectral output): no (N, C) array unless the spectra are asked for
    if spectral:
        to_out = jnp.eye(prep.channels, dtype=jnp.float32)
        hm, wm, c = prep.env.texels.shape
        mirror_table = jnp.concatenate([prep.env.texels.reshape(hm * wm, c), prep.env.poles])
    else:
        to_out = prep.to_xyz
        mirror_table = prep.env_xyz
    with jax.named_scope("shading"):
        if prep.quality == "fast":
            radiance = _shade_out(prep, mats, gb, counts, to_out, mirror_table)
        else:
            radiance = _shade_samples(mats, prep.env, gb, prep.batch_size,
                                      prep.irradiance_lut, prep.quality, prep.pixel_capacity,
                                      prep.split_map, prep.split_settings) @ to_out
    # (in the output channels: the receivers' side of the gather works in those)
    if senders is not None:
        from .interreflection._gather import gather_receivers

        ir = gather_receivers(senders, mats, prep.env, gb, image_shape=prep.shape,
                              output=None if spectral else to_out)
        ir_overflow = jnp.asarray(senders.geometry.overflow, bool)
    else:
        geoms = _ir_geometries(prep, model, visible)
        ir, ir_overflow = _interreflection(prep, geoms, mats, gb, None if spectral else to_out)
    if ir is not None:
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
    ``prep.clusters`` the rows of the clusters that may face the eye
    (:func:`~spectral_fit.geometry.visible_clusters`; the raster is bit-identical to one of all
    triangles), else ``prep.triangles`` (the count is then 0)."""
    from ..geometry import cluster_rows, visible_clusters

    cl = prep.clusters
    if cl is None:
        return prep.triangles, prep.tri_object, jnp.int32(0), jnp.asarray(False)
    index, count = visible_clusters(cl, model, view, prep.projection, visible, cull=prep.cull)
    tris, obj = cluster_rows(cl, index)
    return tris, obj, count, count > cl.capacity


def _scatter(values: jax.Array, px: PixelFrame, image: jax.Array) -> jax.Array:
    """Write the slots' ``values`` (N, K) into ``image`` (H, W, K)."""
    h, w, k = image.shape
    idx = jnp.where(px.valid, px.index, h * w)  # out of range: dropped
    return image.reshape(h * w, k).at[idx].set(values, mode="drop").reshape(h, w, k)


# PixelFrame.stats that are arrays (the buffers' use), not in a Frame's scalar stats
_PLAN_STATS = ("object_counts", "raster_needed", "clusters_needed")


def _render_impl(prep: Prepared, materials: Any, model: jax.Array, view: jax.Array,
                 visible: jax.Array, spectral: bool, background: bool = True,
                 mirror: bool = True, senders: Any = None) -> Frame:
    from ..color import display_linear, encode, gamut_fractions

    h, w = prep.shape
    px = _pixels_impl(prep, materials, model, view, visible, spectral, mirror, senders)
    # 4. background and XYZ
    if background:
        with jax.named_scope("background"):
            bg_xyz = _background(prep, prep.env_xyz, view).reshape(h, w, 3)
    else:
        bg_xyz = jnp.zeros((h, w, 3), jnp.float32)
    spec = None
    if spectral:
        xyz_px = px.values @ prep.to_xyz
        xyz = _scatter(xyz_px, px, bg_xyz)
        if background:
            env = prep.env
            hm, wm, c = env.texels.shape
            flat = jnp.concatenate([env.texels.reshape(hm * wm, c), env.poles])
            bg = (_background(prep, flat, view) @ prep.to_spectrum).reshape(h, w, -1)
        else:
            bg = jnp.zeros((h, w, prep.to_spectrum.shape[1]), jnp.float32)
        spec = _scatter(px.values @ prep.to_spectrum, px, bg)
    else:
        xyz_px = px.values
        xyz = _scatter(xyz_px, px, bg_xyz)

    # 5. display
    with jax.named_scope("display"):
        kw = dict(exposure_luminance=prep.exposure, display=prep.display,
                  scene_white_xy=prep.scene_white_xy)
        linear = display_linear(xyz, **kw)
        rgb = encode(linear, prep.display)
        # the gamut fractions over the covered pixels' slots (N ≪ H·W) rather than the masked
        # image: four frame-wide reductions cost a noticeable share of the frame
        fractions = gamut_fractions(display_linear(xyz_px, **kw), px.valid)
    count = px.stats["covered_pixels"]
    stats = {
        "out_of_gamut_fraction": fractions[0],
        "below_zero_fraction": fractions[1],
        "overexposed_fraction": fractions[2],
        "coverage": count.astype(jnp.float32) / (h * w),
        **{k: v for k, v in px.stats.items() if k not in _PLAN_STATS},
    }
    return Frame(xyz=xyz, rgb=rgb, linear_rgb=linear, mask=px.mask,
                 object_id=px.object_id, spectral=spec, stats=stats)


_render_jit = array_jit(_render_impl)


@functools.cache
def all_visible(n: int) -> jax.Array:
    """(n,) True, made once (a new array per frame costs a dispatch on the frame's path);
    concrete even when first asked for inside a caller's trace (a cached tracer would leak)."""
    with jax.ensure_compile_time_eval():
        return jnp.ones((n,), bool)


def _check_frame_inputs(prep: Prepared, materials: Any, model: Any, view: Any, visible: Any
                        ) -> tuple[Any, jax.Array, jax.Array, jax.Array]:
    mats = prep.materials if materials is None else materials
    model = prep.model if model is None else model
    view = prep.view if view is None else view
    visible = all_visible(prep.num_objects) if visible is None else visible
    if not isinstance(model, jax.core.Tracer):
        m = np.shape(model)
        if m != (prep.num_objects, 4, 4):
            raise InputError(f"expected shape ({prep.num_objects}, 4, 4), got {m}",
                             field="model")
    if not isinstance(view, jax.core.Tracer) and np.shape(view) != (4, 4):
        raise InputError(f"expected shape (4, 4), got {np.shape(view)}", field="view")
    if not isinstance(visible, jax.core.Tracer) and np.shape(visible) != (prep.num_objects,):
        raise InputError(f"expected shape ({prep.num_objects},), got {np.shape(visible)}",
                         field="visible")
    if not isinstance(mats, Material):
        mats = _stack(_as_stacked(mats, prep.num_objects)) if len(
            {(m.distribution, m.geometry) for m in mats}) == 1 else list(mats)
    return (mats, _as_dtype(model, jnp.float32), _as_dtype(view, jnp.float32),
            _as_dtype(visible, jnp.bool_))


def _as_dtype(x: Any, dtype: Any) -> jax.Array:
    """``jnp.asarray(x, dtype)``, skipped for a ``jax.Array`` that has the dtype already (the
    per-frame inputs: the conversion is a dispatch of its own on the frame's path)."""
    if isinstance(x, jax.Array) and x.dtype == dtype:
        return x
    return jnp.asarray(x, dtype)


def render_pixels(prep: Prepared, materials: Any = None, *, model: Any = None,
                  view: Any = None, visible: Any = None, spectral: bool = False,
                  mirror: bool | None = None, senders: Any = None) -> PixelFrame:
    """The covered pixels of one frame, shaded (with interreflection), without background,
    image scatter or display encoding: for callers that put the pixels somewhere else (the
    live composite writes them straight into the video frame). Same inputs as
    :func:`render_frame`; meant to be called inside the caller's own ``jit``. Returns a
    :class:`PixelFrame`; its values are in ``prep.to_xyz``'s output space (:func:`with_output`)
    or, with ``spectral``, in the C radiance channels. ``mirror``: as for
    :func:`render_frame`; inside a caller's ``jit`` the materials are traced, so the default
    keeps the mirror term: pass :func:`mirror_needed` of the concrete materials from outside.
    ``senders``: :func:`render_senders` of the same ``prep``, materials, mirror switch and
    object state (``model``, ``visible``: the caller keeps them consistent), used instead of
    the frame's own pass 1 (gather mode only)."""
    mats, model, view, visible = _check_frame_inputs(prep, materials, model, view, visible)
    _check_senders(prep, senders)
    return _pixels_impl(prep, mats, model, view, visible, spectral,
                        _mirror_flag(mats, mirror), senders)


def _check_senders(prep: Prepared, senders: Any) -> None:
    if senders is not None and prep.ir_mode != "gather":
        raise InputError(f"senders given but the interreflection mode is {prep.ir_mode!r}",
                         field="senders")


def _mirror_flag(mats: Any, mirror: bool | None) -> bool:
    """The static mirror switch of a frame: ``mirror`` when given (False with a concrete χ
    that is not 0 is refused: it would drop light silently), else :func:`mirror_needed`."""
    needed = mirror_needed(mats)
    if mirror is None:
        return needed
    if not mirror and needed and not _traced_chi(mats):
        raise InputError("mirror=False but a material has χ != 0 (its mirror term would be "
                         "dropped)", field="materials.chi")
    return bool(mirror)


def _traced_chi(mats: Any) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in _chi_leaves(mats))


def render_frame(prep: Prepared, materials: Any = None, *, model: Any = None, view: Any = None,
                 visible: Any = None, spectral: bool = False, background: bool = True,
                 mirror: bool | None = None, senders: Any = None) -> Frame:
    """Render one frame (jit-compiled once per :class:`Prepared` shape; differentiable).

    Args:
        prep: from :func:`prepare`.
        materials: a stacked :class:`~spectral_fit.lighting.Material` (leading axis O) or a
            sequence of O Materials (reflectance in bands, or K coefficients in basis mode);
            default the config's. Traced: new values never recompile, except χ going from
            all zero to not (see ``mirror``).
        model: (O, 4, 4) world-from-object matrices (default the config's poses). Traced.
        view: (4, 4) world → OpenGL eye view matrix (default the config's camera). Traced.
        visible: (O,) bool per-object visibility (default all visible). Traced.
        spectral: also return the spectral radiance (H, W, L) (a separate compilation; the
            default frame never forms per-pixel spectra: it shades straight into XYZ).
        background: False: uncovered pixels are black (0) instead of the environment seen
            through them (for callers that replace them, e.g. by a video frame; a separate
            compilation).
        mirror: whether the frame is compiled with the perfect-mirror term (χ). Default
            (None): :func:`mirror_needed`: without it only when every χ is a concrete 0 (the
            paper's plastics; not under ``jax.grad``/``vmap``/``jit``, where χ is traced),
            which leaves out the neighbours' mirror radiance the interreflection would
            otherwise carry in every channel (a tenth of the frame); the first χ
            that is not 0 then compiles the frame with it. True: always with it (e.g. a slider
            for χ that should never recompile). False: every χ taken as 0 (refused when a
            concrete χ is not 0).
        senders: gather mode: the interreflection's camera-independent half from
            :func:`render_senders` for the same ``prep``, materials, mirror switch, ``model``
            and ``visible`` (the caller keeps them consistent), used instead of the frame's
            own pass 1: camera paths around objects that stay put compute it once (a separate
            compilation; the frame equals the one that computes it, to float rounding).

    Returns:
        :class:`Frame`. Gradients flow to every material parameter of every object (and to
        the model/view matrices through shading, not through visibility).
    """
    mats, model, view, visible = _check_frame_inputs(prep, materials, model, view, visible)
    _check_senders(prep, senders)
    return _render_jit(prep, mats, model, view, visible, bool(spectral), bool(background),
                       _mirror_flag(mats, mirror), senders)


def render(scene: Any, materials: Any = None, *, spectral: bool = False,
           **prepare_options: Any) -> Frame:
    """Convenience (stable API): :func:`prepare` + :func:`render_frame` with the config's
    poses. ``scene`` is a Scene or a config path; ``prepare_options`` go to :func:`prepare`
    (size, mode, spectral_mode, k, ...). When a buffer overflowed (objects moved closer than
    planned), the capacities are grown and the frame is rendered again, with a warning."""
    prep = prepare(scene, **prepare_options)
    frame = render_frame(prep, materials, spectral=spectral)
    return regrow(prep, frame, materials, spectral)


def regrow(prep: Prepared, frame: Frame, materials: Any, spectral: bool) -> Frame:
    for _ in range(4):
        pix_over = bool(frame.stats["pixel_overflow"])
        ras_over = bool(frame.stats["raster_overflow"])
        ir_cfg = ir_fallback(prep) if bool(frame.stats["interreflection_overflow"]) else None
        if not (pix_over or ras_over or ir_cfg is not None):
            return frame
        changes: dict[str, Any] = {}
        if ir_cfg is not None:
            changes["ir_raster_config"] = ir_cfg
        if pix_over:
            h, w = prep.shape
            counts = np.bincount(np.asarray(frame.object_id).reshape(-1) + 1,
                                 minlength=prep.num_objects + 1)[1:]
            changes["pixel_capacity"] = tuple(
                max(c, min(h * w, capacity_ladder(1.5 * int(n) + 64, 64)))
                for c, n in zip(prep.pixel_capacity, counts, strict=True))
        if ras_over and prep.clusters is not None:
            from ..geometry import count_clusters, grown_clusters

            grown = grown_clusters(prep.clusters, count_clusters(
                prep.clusters, prep.model, prep.view, prep.projection, cull=prep.cull), 1.5)
            if grown is not prep.clusters:
                changes["clusters"] = grown
        if ras_over:
            from ..geometry import rasterize

            world = _to_world(prep.vertices, prep.vertex_object, prep.model)
            r = rasterize(camera_clip(prep.projection, prep.view, prep.lens, world),
                          prep.triangles, prep.shape,
                          cull=prep.cull, config=prep.raster_config, check=False)
            changes["raster_config"] = prep.raster_config.grown(np.asarray(r.needed), 1.5)
        warnings.warn(f"render: buffers grown ({sorted(changes)}); recompiling",
                      RuntimeWarning, stacklevel=3)
        prep = _replace_static(prep, **changes)
        frame = render_frame(prep, materials, spectral=spectral)
    raise RuntimeError("render: buffers still overflow after growing them")


def ir_fallback(prep: Prepared) -> Any:
    """The pass-1 raster capacities after an interreflection overflow: at least the generic
    ones (:func:`_ir_generic_config`); None when they are there already (nothing to grow)."""
    cur = prep.ir_raster_config
    if cur is None:
        return None
    tris = max(tb - ta for ta, tb in prep.ir_triangle_slices)
    gen = _ir_generic_config(prep.ir_mode, prep.ir_texture_size, tris)
    new = cur._replace(capacities=tuple(max(a, b) for a, b in zip(
        cur.capacities, gen.capacities, strict=True)),
        block_capacity=max(cur.block_capacity, gen.block_capacity))
    return None if new == cur else new


def _replace_static(prep: Prepared, **changes: Any) -> Prepared:
    import dataclasses

    return dataclasses.replace(prep, **changes)
