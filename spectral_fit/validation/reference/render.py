"""Spectral ground truth with the band trick and the patch layout of the references.

An L-band render is ⌈L/3⌉ rgb renders of ONE BSDF equal to our whole model: render g carries
bands 3g, 3g+1, 3g+2 in its r, g, b channels (environment and reflectances packed the same way;
F, D, G do not depend on λ, so the three channels are three exact monochromatic renders).
Path depth (Mitsuba's ``max_depth``): 2 = single bounce (environment → surface → camera; the
neighbour still occludes the environment), 16 = converged interreflection.

Noise: each render is split into ``passes`` independent passes (seeds ``seed + p``); the spread
of the passes gives the standard error of their mean. The same seeds are used for every band
triple and for both depths, so Monte Carlo noise is correlated across bands and between the
depth-2 and depth-16 renders (smooth spectra; a low-noise interreflection difference).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import Any

import numpy as np

from ..._runtime.errors import InputError
from ...io import Scene
from .export import Crop, band_groups, environment_texels, mitsuba_envmap_rows, scene_dict

__all__ = [
    "SpectralRender",
    "render_spectral",
    "camera_rays",
    "sphere_hits",
    "objects_crop",
    "sphere_patches",
]


@dataclasses.dataclass(frozen=True)
class SpectralRender:
    """Band-trick renders of one crop.

    Attributes:
        wavelengths: (L,) nm.
        depths: the path depths rendered, e.g. (2, 16).
        passes: (D, P, h, w, L) float32 radiance (W·sr⁻¹·m⁻²·nm⁻¹ in the map's units) per depth
            and independent pass.
        crop: the window rendered.
        seconds: wall time of all renders; ``variant``: the Mitsuba variant; ``spp``: samples
            per pixel per pass.
    """

    wavelengths: np.ndarray
    depths: tuple[int, ...]
    passes: np.ndarray
    crop: Crop
    seconds: float
    variant: str
    spp: int

    def mean(self, depth: int) -> np.ndarray:
        """(h, w, L) mean over the passes at ``depth``."""
        return self.passes[self.depths.index(depth)].mean(axis=0)


def render_spectral(
    scene: Scene,
    *,
    spp: int = 64,
    passes: int = 4,
    depths: tuple[int, ...] = (2, 16),
    seed: int = 0,
    crop: Crop | None = None,
    analytic_spheres: bool = False,
    environment: float | np.ndarray | None = None,
    progress: Any = None,
) -> SpectralRender:
    """Render the scene's spectral radiance (all bands of ``scene.wavelengths``) with Mitsuba.

    Args:
        spp: samples per pixel of each pass; ``passes``: independent passes (seeds
            ``seed .. seed + passes − 1``).
        depths: path depths (Mitsuba ``max_depth``), each rendered with the same seeds.
        crop: window of the frame (default: the whole frame).
        analytic_spheres: exact spheres instead of the objects' meshes.
        environment: None (the scene's map), a float (uniform radiance in every band), or an
            (H, W, L) map in the scene's bands (map frame).
        progress: optional callable(str) for log lines.
    Returns:
        :class:`SpectralRender` with (D, passes, h, w, L) radiance.
    """
    from .backend import current_variant, init_mitsuba

    mi, _ = init_mitsuba()
    if spp < 1 or passes < 1 or not depths:
        raise InputError("spp and passes must be >= 1 and depths non-empty", field="spp")
    wl = scene.wavelengths
    nb = wl.size
    crop = crop or Crop(0, 0, scene.width, scene.height)
    t0 = time.perf_counter()
    if environment is None:
        rows = mitsuba_envmap_rows(environment_texels(scene))
    elif isinstance(environment, int | float):
        rows = None
    else:
        env = np.asarray(environment, np.float32)
        if env.ndim != 3 or env.shape[2] != nb:
            raise InputError(f"expected (H, W, {nb}), got {env.shape}", field="environment")
        rows = mitsuba_envmap_rows(env)
    meshes = {} if analytic_spheres else {o.name: o.make_mesh(world=True) for o in scene.objects}
    integrators = {d: mi.load_dict({"type": "path", "max_depth": int(d)}) for d in depths}
    out = np.zeros((len(depths), passes, crop.height, crop.width, nb), np.float32)
    for gi, idx in enumerate(band_groups(nb)):
        env_rgb = float(environment) if rows is None else rows[..., idx]  # type: ignore[arg-type]
        refl = {o.name: np.asarray(o.material.reflectance)[idx] for o in scene.objects}
        d = scene_dict(scene, env_rgb=env_rgb, reflectances=refl, spp=spp, crop=crop,
                       analytic_spheres=analytic_spheres, meshes=meshes)
        mscene = mi.load_dict(d)
        for di, depth in enumerate(depths):
            for p in range(passes):
                img = np.asarray(mi.render(mscene, integrator=integrators[depth],
                                           seed=seed + p, spp=spp), np.float32)
                out[di, p][..., idx] = img[..., :3]
        if progress is not None:
            progress(f"bands {wl[idx[0]]:g}-{wl[idx[-1]]:g} nm done "
                     f"({gi + 1}/{math.ceil(nb / 3)}, {time.perf_counter() - t0:.1f} s)")
    return SpectralRender(wavelengths=wl, depths=tuple(depths), passes=out, crop=crop,
                          seconds=time.perf_counter() - t0, variant=current_variant() or "",
                          spp=spp)


# --------------------------------------------------------------------------------------------
# Camera rays and sphere patches (NumPy, float64)


@functools.lru_cache(maxsize=32)
def _view_matrix(position: tuple, look: tuple, up: tuple) -> np.ndarray:
    """gluLookAt view matrix (as :func:`spectral_fit.geometry.look_at`, in NumPy float64 so that
    data-only callers need not start JAX; the degenerate look-along-up case goes to JAX)."""
    eye = np.asarray(position, np.float64)
    f = np.asarray(look, np.float64) - eye
    f /= np.linalg.norm(f)
    u0 = np.asarray(up, np.float64) / np.linalg.norm(up)
    s = np.cross(f, u0)
    if np.linalg.norm(s) < 1e-6:
        from ...geometry import look_at

        return np.asarray(look_at(position, look, up), np.float64)
    s /= np.linalg.norm(s)
    rot = np.stack([s, np.cross(s, f), -f])
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = -rot @ eye
    return m


def camera_rays(scene: Scene, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World origin (3,) and unit directions (..., 3) through frame pixel coordinates (x, y)
    (pixel centres at integer + 0.5, row 0 on top), from :func:`camera.look_at`;
    the vertical field of view, or the OpenCV intrinsics (principal point (cx + ½, cy + ½) in
    these coordinates), of a pinhole (distortion is not applied)."""
    cam = scene.camera
    view = _view_matrix(tuple(cam.position), tuple(cam.look_at), tuple(cam.up))
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    if cam.intrinsics is None:
        t = math.tan(math.radians(cam.fov_y_deg) / 2.0)
        fx = fy = 0.5 * scene.height / t
        px, py = 0.5 * scene.width, 0.5 * scene.height
    else:
        i = cam.intrinsics
        fx, fy, px, py = i["fx"], i["fy"], i["cx"] + 0.5, i["cy"] + 0.5
    eye = np.stack(np.broadcast_arrays((x - px) / fx, (py - y) / fy, -np.ones_like(x)), -1)
    d = eye @ view[:3, :3]  # rotᵀ · eye direction
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return np.asarray(cam.position, np.float64), d


def sphere_hits(origin: np.ndarray, dirs: np.ndarray, centre: Any, radius: float
                ) -> np.ndarray:
    """Ray parameter t (...,) of the first hit of rays ``origin + t·dirs`` with a sphere
    (inf where missed)."""
    oc = origin - np.asarray(centre, np.float64)
    b = dirs @ oc
    c = oc @ oc - radius * radius
    disc = b * b - c
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    return np.where((disc > 0) & (t > 0), t, np.inf)


def _spheres(scene: Scene) -> list[tuple[int, Any, float]]:
    out = []
    for i, o in enumerate(scene.objects):
        if o.shape in ("uv_sphere", "icosphere"):
            out.append((i, np.asarray(o.position, np.float64), o.radius * o.scale))
    if not out:
        raise InputError("no sphere objects to place patches on", path=scene.path,
                         field="objects")
    return out


def objects_crop(scene: Scene, margin: int = 4) -> Crop:
    """The smallest pixel window holding every sphere object's silhouette, plus ``margin``."""
    ys, xs = np.mgrid[0:scene.height, 0:scene.width] + 0.5
    o, d = camera_rays(scene, xs, ys)
    hit = np.zeros(xs.shape, bool)
    for _, c, r in _spheres(scene):
        hit |= np.isfinite(sphere_hits(o, d, c, r))
    rows, cols = np.nonzero(hit)
    if rows.size == 0:
        raise InputError("no object is in view", path=scene.path, field="camera")
    x0 = max(int(cols.min()) - margin, 0)
    y0 = max(int(rows.min()) - margin, 0)
    x1 = min(int(cols.max()) + 1 + margin, scene.width)
    y1 = min(int(rows.max()) + 1 + margin, scene.height)
    return Crop(x0, y0, x1 - x0, y1 - y0)


def sphere_patches(scene: Scene, *, size: int = 5, step: int | None = None,
                   shrink: float = 0.995) -> dict[str, np.ndarray]:
    """Square patches of ``size`` × ``size`` pixels tiling each sphere's silhouette (frame
    grid of pitch ``step``, default ``size``), kept where all four outer corners of the patch
    see that sphere (radius × ``shrink``, so the mesh's facets cover it too) before any other.

    Returns a dict: ``boxes`` (P, 4) int32 x0, y0, x1, y1 (exclusive) in frame pixels,
    ``object`` (P,) int32 index into ``scene.objects``, ``normal`` (P, 3) and ``point`` (P, 3)
    the sphere's normal and point hit by the ray through the patch centre, ``view`` (P, 3)
    the unit direction from that point to the camera.
    """
    step = step or size
    spheres = _spheres(scene)
    boxes, objs, normals, points, views = [], [], [], [], []
    x0s = np.arange(0, scene.width - size + 1, step)
    y0s = np.arange(0, scene.height - size + 1, step)
    gx, gy = np.meshgrid(x0s, y0s)
    corners = [(0, 0), (size, 0), (0, size), (size, size)]
    o, _ = camera_rays(scene, gx, gy)
    t_all = []
    for _, c, r in spheres:
        per = []
        for cx, cy in corners:
            _, dc = camera_rays(scene, gx + cx, gy + cy)
            per.append(sphere_hits(o, dc, c, r * shrink))
        t_all.append(np.stack(per))  # (4, ny, nx)
    # nearest sphere along each corner ray, with the unshrunk radius for occluders
    t_full = []
    for _, c, r in spheres:
        per = []
        for cx, cy in corners:
            _, dc = camera_rays(scene, gx + cx, gy + cy)
            per.append(sphere_hits(o, dc, c, r))
        t_full.append(np.stack(per))
    t_full_arr = np.stack(t_full)  # (S, 4, ny, nx)
    for si, (oi, c, r) in enumerate(spheres):
        t = t_all[si]
        others = np.delete(t_full_arr, si, axis=0)
        nearer = (others < t[None]).any(axis=0) if len(others) else np.zeros_like(t, bool)
        ok = np.isfinite(t).all(axis=0) & ~nearer.any(axis=0)
        xx, yy = gx[ok], gy[ok]
        _, dc = camera_rays(scene, xx + size / 2, yy + size / 2)
        th = sphere_hits(o, dc, c, r)
        p = o + th[:, None] * dc
        boxes.append(np.stack([xx, yy, xx + size, yy + size], -1))
        objs.append(np.full(xx.size, oi))
        normals.append((p - c) / r)
        points.append(p)
        views.append(-dc)
    return {
        "boxes": np.concatenate(boxes).astype(np.int32).reshape(-1, 4),
        "object": np.concatenate(objs).astype(np.int32),
        "normal": np.concatenate(normals).reshape(-1, 3),
        "point": np.concatenate(points).reshape(-1, 3),
        "view": np.concatenate(views).reshape(-1, 3),
    }
