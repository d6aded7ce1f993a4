"""Preparing a scene (Python, once per scene shape): :func:`prepare` builds everything that does
not change from frame to frame, as a :class:`~spectral_fit.rendering.Prepared` pytree: the
meshes (object frames, concatenated; and those the interreflection's pass 1 rasterises), the
camera projection and lens, the environment (prefiltered, in bands or K basis coefficients),
the display, the exposure, the rasteriser's window capacities and the covered-pixel capacity.

Exposure ``"auto"``: the luminance of a perfect white Lambertian diffuser facing the camera
under the environment, E_irr(−forward)·683∫ȳ/π, is shown as display white (the scene white of
docs/conventions.md, 'Colorimetry and display'), so diffuse objects never clip.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from .._runtime.process import single_threaded_blas
from ..geometry import build_clusters, capacity_ladder, spatial_order
from ._camera import _check_lens_tessellation, _lens, _look_at_jit, _projection, camera_clip
from ._capacities import _ir_raster_config, _plan_clusters, plan_capacities
from ._environment import ground_surfaces, irradiance_table, load_environment
from ._materials import _stack, scene_materials
from ._prepared import (
    Prepared,
    PreparedBuffers,
    PreparedCamera,
    PreparedColour,
    PreparedInterreflection,
    PreparedLighting,
    SceneMeshes,
)

if TYPE_CHECKING:  # for annotations (imported where they are used)
    from ..io import Scene

__all__ = [
    "prepare",
]


_IR_MODES = ("gather", "paper", "none")


#: environment shading qualities of frames (see :func:`prepare`)
QUALITIES = ("fast", "render", "exact")


def _ir_mesh(obj: Any, mesh: Any, mode: str, gather_size: int = 16) -> Any:
    """The mesh the interreflection's pass 1 rasterises for ``obj`` (whose camera mesh is
    ``mesh``). Gather mode resolves a sender on a (SUPERSAMPLE · g)² = 64² raster (g =
    ``gather_size``, 16 in the figures that follow) framed on
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
    from .interreflection._pass1 import SUPERSAMPLE

    if mode != "gather":
        return mesh
    side = SUPERSAMPLE * gather_size
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


def _bodies(scene: Scene) -> tuple[int, ...]:
    """Each object's body (the index of the body's first object); () when each object is
    its own."""
    first: dict[str, int] = {}
    out = tuple(first.setdefault(o.body or f"\0{i}", i) for i, o in enumerate(scene.objects))
    return () if out == tuple(range(len(out))) else out


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


@single_threaded_blas()  # NumPy's BLAS threads busy-wait: docs/rendering.md "Cold start"
def prepare(
    scene: Scene | str | os.PathLike[str],
    *,
    size: tuple[int, int] | None = None,
    mode: str | None = None,
    spectral_mode: str | None = None,
    k: int | None = None,
    bounces: int | None = None,
    texture_size: int | None = None,
    gather_size: int | None = None,
    headroom: float = 1.5,
    pixel_capacity: int | None = None,
    batch_size: int = 32,
    environment: np.ndarray | None = None,
    diffuse: str = "map",
    irradiance_shape: tuple[int, int] = (32, 64),
    quality: str = "fast",
    split_settings: Any = None,
    occlusion: bool = True,
    occlusion_resolution: int = 24,
    surfaces: bool = True,
) -> Prepared:
    """Precompute a scene for :func:`render_frame` (explicit precomputation).

    Args:
        scene: a :class:`~spectral_fit.io.Scene` (``load_scene``) or a path to a config.
        size: (W, H) frame size in pixels, replacing the config's ``[frame]``.
        mode: interreflection mode "gather" | "paper" | "none" (default: the config's).
        spectral_mode: "bands" | "basis" (default: the config's); ``k`` basis size.
        bounces, texture_size, gather_size: interreflection settings (default: the
            config's).
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
        occlusion: precompute what each non-convex object hides from itself (its
            self-visibility over ``occlusion_resolution``² directions and its self-transfer,
            docs/any_shape.md) and render with it; False: every object lit as if convex.
            Convex objects cost nothing either way.
        occlusion_resolution: R of the self-visibility's octahedral direction grid.
        surfaces: precompute the ``[[surfaces]]`` planes' shadows and light for the
            configured poses (``Prepared.surfaces``); False: only the objects see the planes
            (a live session places the objects from markers and builds them then).
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
    res_ok = isinstance(occlusion_resolution, int | np.integer)
    if not (res_ok and 4 <= occlusion_resolution <= 128):
        raise InputError(f"must be an int in 4..128, got {occlusion_resolution!r}",
                         field="occlusion_resolution")
    ts = scene.interreflection.texture_size if texture_size is None else int(texture_size)
    from .interreflection._pass1 import check_gather_size

    gs = check_gather_size(scene.interreflection.gather_size if gather_size is None
                           else gather_size)

    # meshes in object frames, concatenated (and those the interreflection's pass 1 uses)
    meshes = [obj.make_mesh() for obj in scene.objects]
    vertices, normals, triangles, vobj_a, tobj_a, vsl, tsl = _concat_meshes(meshes)
    # each object's triangles in a spatial order: runs of them are the clusters the frame
    # culls before its raster (spectral_fit.geometry)
    triangles = triangles[spatial_order(vertices, triangles, tsl)]
    model = np.stack([obj.model_matrix() for obj in scene.objects]).astype(np.float32)
    ir_meshes = [_ir_mesh(obj, m, ir_mode, gs) for obj, m in zip(scene.objects, meshes,
                                                                  strict=True)]
    # the camera culls back faces when no mesh has an opening or inward winding (the gather
    # pass 1 always does: it assumes closed senders): half the raster's windows
    from ..io import is_closed_outward

    cull = ("back" if all(is_closed_outward(m.vertices, m.triangles) for m in meshes)
            else "none")
    ir_same = all(a is b for a, b in zip(ir_meshes, meshes, strict=True))
    if ir_same:
        ir_v, ir_t, ir_vsl, ir_tsl = vertices, triangles, vsl, tsl
    else:
        ir_v, ir_n, ir_t, ir_o, ir_to, ir_vsl, ir_tsl = _concat_meshes(ir_meshes)

    cam = scene.camera
    view = np.asarray(_look_at_jit(np.asarray(cam.position, np.float32),
                                   np.asarray(cam.look_at, np.float32),
                                   np.asarray(cam.up, np.float32)), np.float32)
    proj = _projection(scene, shape).astype(np.float32)

    # environment
    img = load_environment(scene, wl) if environment is None else np.asarray(environment)
    img = ground_surfaces(scene, img)  # what the objects see below a table: the table
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
                                            (ta, tb) in zip(ir_vsl, ir_tsl, strict=True)],
                               gather_size=gs)

    occ = None
    if occlusion:
        from ._occlusion import build_self_transfer

        occ = build_self_transfer(vertices, triangles, normals, vsl, tsl, env,
                                  resolution=int(occlusion_resolution))
    mesh = SceneMeshes(
        vertices=jnp.asarray(vertices), normals=jnp.asarray(normals),
        triangles=jnp.asarray(triangles), vertex_object=jnp.asarray(vobj_a),
        tri_object=jnp.asarray(tobj_a), object_slices=tuple(vsl), triangle_slices=tuple(tsl))
    ir_mesh = mesh if ir_same else SceneMeshes(
        vertices=jnp.asarray(ir_v, jnp.float32), normals=jnp.asarray(ir_n, jnp.float32),
        triangles=jnp.asarray(ir_t, jnp.int32), vertex_object=jnp.asarray(ir_o, jnp.int32),
        tri_object=jnp.asarray(ir_to, jnp.int32), object_slices=tuple(ir_vsl),
        triangle_slices=tuple(ir_tsl))
    planes = ()
    if scene.surfaces and surfaces:
        from ._surfaces import surface_transfer

        planes = surface_transfer(scene.surfaces, env, ir_mesh, model)
    prep = Prepared(
        mesh=mesh, ir_mesh=ir_mesh, model=jnp.asarray(model), materials=mats,
        camera=PreparedCamera(
            view=jnp.asarray(view), projection=jnp.asarray(proj),
            lens=None if lens is None else jnp.asarray(lens, jnp.float32),
            pixel_rays=None if rays is None else jnp.asarray(rays), shape=shape, cull=cull),
        lighting=PreparedLighting(
            env=env, irradiance_lut=None if lut is None else jnp.asarray(lut, jnp.float32),
            split_map=split_map, quality=quality,
            split_settings=split_settings if quality == "fast" else None,
            batch_size=int(batch_size)),
        colour=PreparedColour(
            to_xyz=jnp.asarray(to_xyz, jnp.float32), env_xyz=jnp.asarray(env_xyz, jnp.float32),
            to_spectrum=jnp.asarray(to_spectrum, jnp.float32),
            exposure=jnp.asarray(exposure, jnp.float32),
            wavelengths=tuple(float(x) for x in wl), spectral_mode=smode,
            k=kk if smode == "basis" else int(wl.size), display=display,
            scene_white_xy=None if d.scene_white_xy is None else tuple(d.scene_white_xy)),
        buffers=PreparedBuffers(clusters=clusters, raster_config=cfg, ir_raster_config=ir_cfg,
                                pixel_capacity=cap),
        interreflection=PreparedInterreflection(mode=ir_mode, bounces=nb, texture_size=ts,
                                                gather_size=gs,
                                                bodies=_bodies(scene),
                                                tail=scene.interreflection.tail),
        names=tuple(o.name for o in scene.objects),
        occlusion=occ,
        surfaces=planes,
    )
    if planes:  # what the objects see of the table's change under them (their shadows)
        import dataclasses

        from ._surfaces import table_changes

        prep = dataclasses.replace(prep, surface_changes=table_changes(prep))
    return prep



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
