"""Export a :class:`~spectral_fit.io.Scene` to a Mitsuba 3 scene (one per band triple).

The same config renders in both renderers: meshes from :mod:`spectral_fit.io` posed by each
object's model matrix (smooth vertex normals kept), the pinhole camera of ``[camera]`` (vertical
field of view, look-at), and the environment map with our mapping and rotation.

Environment placement. Our lookup (:func:`spectral_fit.lighting.lookup`) puts texel row k at
v = (k + ½)/H and is bilinear in (u, v), blending to the row mean at the poles. Mitsuba's
``envmap`` (checked numerically in the tests, Mitsuba 3.9) puts row k of an H′-row bitmap at
θ = πk/(H′ − 1), poles included, and column j at u = (j + ½)/W as we do. Giving it H′ = 2H + 1
rows at θ = πk/(2H), filled by OUR lookup, reproduces our lookup exactly (to float32 round-off):
those rows contain every knot of our piecewise-bilinear interpolant (the row centres at odd k,
the poles at k = 0 and 2H), and bilinear interpolation of a bilinear function between its own
knots is exact. (H + 1 rows at θ = πk/H misses the row centres and is
only close: ~1e-3 relative on smooth maps, more at sharp edges.) The map's rotation goes into
the emitter's ``to_world`` (world-from-map, as ours).

Camera. ``fov_y_deg`` goes to Mitsuba's ``perspective`` sensor as its vertical field of view.
``intrinsics`` (OpenCV fx, fy, cx, cy in pixels, pixel centres at integers) go to the same
sensor: field of view 2·atan(H / 2fy) and the principal point as Mitsuba's
``principal_point_offset_x/y`` (fractions of the film width/height, measured from the film's
centre towards its left/top edge: 0.5 − (cx + ½)/W and 0.5 − (cy + ½)/H; checked against our
rays in the tests). Unsupported (raise :class:`InputError`): non-square pixels (fx ≠ fy: the
perspective sensor has one focal length) and lens ``distortion`` other than all zeros.
"""

from __future__ import annotations

import dataclasses
import math
import re
from typing import Any

import numpy as np

from ..._runtime.errors import InputError
from ...io import Scene

__all__ = [
    "environment_texels",
    "mitsuba_envmap_rows",
    "band_groups",
    "Crop",
    "scene_dict",
    "sensor_optics",
]


def environment_texels(scene: Scene) -> np.ndarray:
    """The scene's environment (H, W, L) float32 radiance on the scene's wavelength grid, with
    ``environment.scale`` applied (map frame: the rotation is not applied)."""
    from ...color import resample
    from ...io import read_spectral_exr

    spec = scene.environment
    wl = scene.wavelengths
    try:
        wl_in, img = read_spectral_exr(spec.file)
    except InputError as exc:
        if not exc.reason.startswith("no spectral channels"):
            raise  # a broken spectral file stays an error; an RGB map is lifted below
        from ...lighting import read_rgb_environment

        wl_in, img = read_rgb_environment(spec.file, wl, method=spec.upsampling)
    img = np.asarray(img, np.float64)
    if not (wl_in.shape == wl.shape and np.allclose(wl_in, wl)):
        img = resample(wl_in, img, wl, path=spec.file, field="environment")
    return (img * spec.scale).astype(np.float32)


def mitsuba_envmap_rows(texels: np.ndarray) -> np.ndarray:
    """Our lookup of ``texels`` (H, W, C) resampled onto 2H + 1 rows at θ = πk/(2H) and the W
    column centres: the bitmap (2H + 1, W, C) that Mitsuba's ``envmap`` interpolates exactly as
    :func:`spectral_fit.lighting.lookup` does (module docstring)."""
    import jax
    import jax.numpy as jnp

    from ...lighting import EnvironmentMap, GlossQuadrature, lookup, uv_to_direction

    h, w, c = texels.shape
    env = EnvironmentMap.from_array(
        texels, quadrature=GlossQuadrature(levels=0, max_sources=0), compress_tol=0.0)
    v = np.arange(2 * h + 1) / (2.0 * h)
    u = (np.arange(w) + 0.5) / w
    d = uv_to_direction(u[None, :], v[:, None]).reshape(-1, 3)
    out = jax.jit(jax.vmap(lambda x: lookup(env, x)))(jnp.asarray(d, jnp.float32))
    return np.array(out, np.float32).reshape(2 * h + 1, w, c)  # a writable copy


def band_groups(n_bands: int) -> list[np.ndarray]:
    """Indices (3,) of the bands carried by each of the ⌈L/3⌉ rgb renders (the last group is
    padded by repeating its last band)."""
    groups = []
    for g in range(math.ceil(n_bands / 3)):
        idx = np.arange(3 * g, 3 * g + 3)
        groups.append(np.minimum(idx, n_bands - 1))
    return groups


@dataclasses.dataclass(frozen=True)
class Crop:
    """A pixel window of the frame: columns x0..x0+width, rows y0..y0+height (row 0 on top)."""

    x0: int
    y0: int
    width: int
    height: int


def sensor_optics(scene: Scene) -> dict[str, float]:
    """The projection of the scene's camera as Mitsuba ``perspective`` sensor properties
    (``fov``, ``fov_axis`` and, for intrinsics, ``principal_point_offset_x/y``).

    Raises:
        InputError: non-square pixels (|fx − fy| > 1e-6·fy) or lens distortion (field
            ``camera.intrinsics`` / ``camera.distortion``).
    """
    cam = scene.camera
    if cam.distortion is not None and any(float(c) != 0.0 for c in cam.distortion):
        raise InputError("the reference renderer has no lens distortion (pinhole cameras "
                         "only)", path=scene.path, field="camera.distortion")
    if cam.intrinsics is None:
        return {"fov": float(cam.fov_y_deg), "fov_axis": "y"}
    i = {k: float(v) for k, v in cam.intrinsics.items()}
    if abs(i["fx"] - i["fy"]) > 1e-6 * i["fy"]:
        raise InputError(f"the reference renderer needs square pixels (fx == fy), got fx = "
                         f"{i['fx']:g}, fy = {i['fy']:g}", path=scene.path,
                         field="camera.intrinsics")
    w, h = scene.width, scene.height
    return {"fov": math.degrees(2.0 * math.atan(0.5 * h / i["fy"])), "fov_axis": "y",
            "principal_point_offset_x": 0.5 - (i["cx"] + 0.5) / w,
            "principal_point_offset_y": 0.5 - (i["cy"] + 0.5) / h}


def _mi_mesh(mi: Any, dr: Any, name: str, mesh: Any, bsdf: Any) -> Any:
    v = np.ascontiguousarray(mesh.vertices, np.float32)
    t = np.ascontiguousarray(mesh.triangles, np.uint32)
    n = np.ascontiguousarray(mesh.normals, np.float32)
    props = mi.Properties()
    props["bsdf"] = bsdf
    m = mi.Mesh(name, len(v), len(t), props=props, has_vertex_normals=True,
                has_vertex_texcoords=False)
    params = mi.traverse(m)
    for key, arr in (("vertex_positions", v), ("faces", t), ("vertex_normals", n)):
        params[key] = type(params[key])(np.ravel(arr))  # flat buffers (JIT or scalar types)
    params.update()
    return m


def scene_dict(
    scene: Scene,
    *,
    env_rgb: np.ndarray,
    reflectances: dict[str, np.ndarray],
    spp: int,
    max_depth: int = 16,
    crop: Crop | None = None,
    analytic_spheres: bool = False,
    meshes: dict[str, Any] | None = None,
    sensors: list[dict[str, Any]] | None = None,
    objects: bool = True,
    extra_shapes: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """A Mitsuba scene dict for one band triple (Mitsuba must be initialised).

    Args:
        env_rgb: (2H + 1, W, 3) three bands of :func:`mitsuba_envmap_rows`' output; or a
            float (uniform environment of that radiance, for furnace tests).
        reflectances: object name -> (3,) S in the three bands.
        spp: samples per pixel; ``max_depth``: Mitsuba's path depth (2 = single bounce).
        crop: render only this window of the frame.
        analytic_spheres: render sphere objects as exact spheres instead of their meshes.
        meshes: object name -> world-space Mesh, to reuse (default: each object's
            ``ObjectSpec.make_mesh(world=True)``).
        sensors: Mitsuba sensor dicts replacing the scene's camera (e.g. instruments);
            ``mi.render(scene, sensor=i)`` picks one.
        objects: False leaves the scene's objects out (e.g. a white standard read alone).
        extra_shapes: further Mitsuba shapes by key (e.g. a white standard).
    """
    from ...lighting import rotation_y
    from .backend import init_mitsuba
    from .bsdf import PLUGIN

    mi, dr = init_mitsuba()
    optics = sensor_optics(scene)
    cam = scene.camera
    film: dict[str, Any] = {"type": "hdrfilm", "width": scene.width, "height": scene.height,
                            "rfilter": {"type": "box"}, "pixel_format": "rgb",
                            "component_format": "float32"}
    if crop is not None:
        film.update(crop_offset_x=int(crop.x0), crop_offset_y=int(crop.y0),
                    crop_width=int(crop.width), crop_height=int(crop.height))
    d: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": int(max_depth)},
        "sensor": {
            "type": "perspective",
            **optics,
            "near_clip": float(cam.near),
            "far_clip": float(cam.far),
            "to_world": mi.ScalarTransform4f().look_at(
                origin=list(cam.position), target=list(cam.look_at), up=list(cam.up)),
            "film": film,
            "sampler": {"type": "independent", "sample_count": int(spp)},
        },
    }
    if isinstance(env_rgb, int | float):
        d["environment"] = {"type": "constant",
                            "radiance": {"type": "rgb", "value": float(env_rgb)}}
    else:
        rows = np.array(env_rgb, np.float32, order="C")  # writable, C order (nanobind)
        if rows.ndim != 3 or rows.shape[2] != 3:
            raise InputError(f"expected (2H+1, W, 3), got {rows.shape}", field="env_rgb")
        to_world = np.eye(4)
        to_world[:3, :3] = rotation_y(scene.environment.rotation_y_deg)
        d["environment"] = {
            "type": "envmap",
            "bitmap": mi.Bitmap(rows, pixel_format=mi.Bitmap.PixelFormat.RGB),
            "to_world": mi.ScalarTransform4f(to_world.tolist()),
            "scale": 1.0,
        }
    if sensors is not None:
        del d["sensor"]
        for i, sd in enumerate(sensors):
            d[f"sensor_{i:03d}"] = sd
    d.update(extra_shapes or {})
    for obj in scene.objects if objects else ():
        m = obj.material
        s = np.asarray(reflectances[obj.name], np.float64)
        bsdf = {"type": PLUGIN, "alpha": m.alpha, "beta": m.beta, "chi": m.chi, "mu": m.mu,
                "n": m.n, "distribution": m.distribution, "geometry": m.geometry,
                "s0": float(s[0]), "s1": float(s[1]), "s2": float(s[2])}
        key = "obj_" + re.sub(r"\W", "_", obj.name)  # Mitsuba's keys: no "." (a part's)
        if analytic_spheres and obj.shape in ("uv_sphere", "icosphere"):
            d[key] = {"type": "sphere", "center": list(obj.position),
                      "radius": float(obj.radius * obj.scale), "bsdf": bsdf}
        else:
            mesh = (meshes or {}).get(obj.name) or obj.make_mesh(world=True)
            d[key] = _mi_mesh(mi, dr, key, mesh, mi.load_dict(bsdf))
    return d
