"""Make a :class:`~spectral_fit.validation.reference.data.Reference` from a scene config (used by
``scripts/make_references.py`` and by the generator's smoke test)."""

from __future__ import annotations

import dataclasses
import datetime as _dt
import os
from typing import Any

import numpy as np

from ..._runtime.paths import REPO_ROOT
from ...io import Scene
from .data import Reference
from .render import objects_crop, render_spectral, sphere_patches

__all__ = ["make_reference", "preview_png", "scene_sha256"]

#: config tables the path tracer does not read (our renderer's own settings): a reference
#: stays valid when only these change
RENDERER_TABLES = ("interreflection", "display")


def scene_sha256(path: str | os.PathLike[str]) -> str:
    """SHA-256 of what a reference depends on in a scene config: its parsed TOML without the
    tables of :data:`RENDERER_TABLES` (comments, layout and our renderer's settings do not
    count; the files it names are digested separately)."""
    import hashlib
    import json
    import tomllib

    with open(path, "rb") as f:
        data = tomllib.load(f)
    for key in RENDERER_TABLES:
        data.pop(key, None)
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()

_REPO = REPO_ROOT


def _patch_means(stack: np.ndarray, boxes: np.ndarray, crop: Any) -> np.ndarray:
    """(..., P, L) means over patch boxes of crop images (..., h, w, L)."""
    out = []
    for x0, y0, x1, y1 in boxes:
        blk = stack[..., y0 - crop.y0:y1 - crop.y0, x0 - crop.x0:x1 - crop.x0, :]
        out.append(blk.mean(axis=(-3, -2)))
    return np.stack(out, axis=-2)


def _depth_statistics(means: np.ndarray, wl: np.ndarray) -> dict[str, np.ndarray]:
    """Per-patch statistics of ``means`` (2, K, P, L), the K passes' patch means at path depths
    2 and 16: ``direct`` / ``total`` (P, L) and their standard errors ``noise_direct`` /
    ``noise`` over the passes (NaN with one pass), the interreflection share of the luminance
    ``frac`` = (Y₁₆ − Y₂)/Y₁₆ (P,) and its standard error ``frac_se``, and the relative
    noise ``rel`` (P, L) of ``total``."""
    from ...color import xyz_weights

    k = means.shape[1]

    def se(x: np.ndarray) -> np.ndarray:
        return x.std(axis=0, ddof=1) / np.sqrt(k) if k > 1 else np.full(x.shape[1:], np.nan)

    total = means[1].mean(axis=0)
    wy = xyz_weights(wl)[:, 1]
    y2, y16 = means[0] @ wy, means[1] @ wy  # (K, P)
    noise = se(means[1])
    return {
        "direct": means[0].mean(axis=0), "total": total,
        "noise_direct": se(means[0]), "noise": noise,
        "frac": (y16.mean(0) - y2.mean(0)) / np.maximum(y16.mean(0), 1e-30),
        "frac_se": se((y16 - y2) / np.maximum(y16, 1e-30)),
        "rel": noise / np.maximum(np.abs(total), 1e-30),
    }


def _config_name(scene: Scene) -> str:
    """The scene's config path relative to the repository (as given where that fails)."""
    try:
        return os.path.relpath(scene.path, _REPO) if scene.path else ""
    except ValueError:
        return str(scene.path)


def _sampling_metadata(spp: int, passes: int, seed: int) -> dict[str, Any]:
    """The metadata entries that say how a reference was sampled."""
    return {
        "spp_per_pass": int(spp),
        "passes": int(passes),
        "spp": int(spp * passes),
        "seeds": [int(seed + p) for p in range(passes)],
        "depths": [2, 16],
        "integrator": "path (Russian roulette from depth 5, Mitsuba default), box pixel filter",
    }


def make_reference(
    scene: Scene,
    name: str,
    *,
    spp: int = 512,
    passes: int = 8,
    seed: int = 0,
    patch_size: int = 5,
    threshold: float = 0.05,
    analytic_spheres: bool = False,
    progress: Any = None,
) -> Reference:
    """Render ``scene`` at path depths 2 and 16 (``passes`` × ``spp`` samples per pixel over the
    objects' crop) and reduce it to per-patch mean spectra (see :class:`Reference`).

    Patches: ``patch_size``² pixel squares tiling each sphere (:func:`sphere_patches`). A patch
    is labelled "interreflection" when its interreflection share (Y₁₆ − Y₂)/Y₁₆ exceeds
    ``threshold`` and 3 of its standard errors.
    """
    import mitsuba as mi

    from ...color import xyz_weights

    crop = objects_crop(scene)
    pt = sphere_patches(scene, size=patch_size)
    r = render_spectral(scene, spp=spp, passes=passes, depths=(2, 16), seed=seed, crop=crop,
                        analytic_spheres=analytic_spheres, progress=progress)
    wl = r.wavelengths
    st = _depth_statistics(_patch_means(r.passes, pt["boxes"], crop), wl)
    frac, frac_se, rel = st["frac"], st["frac_se"], st["rel"]
    labels = np.where((frac > threshold) & (frac > 3.0 * np.nan_to_num(frac_se)),
                      "interreflection", "direct")
    xyz = r.mean(16) @ xyz_weights(wl)
    meta = {
        "variant": r.variant,
        "mitsuba": mi.__version__,
        **_sampling_metadata(spp, passes, seed),
        "render_seconds": round(float(r.seconds), 1),
        "renders": int(2 * passes * -(-wl.size // 3)),
        "crop": [crop.x0, crop.y0, crop.width, crop.height],
        "frame": [scene.width, scene.height],
        "patch_size": int(patch_size),
        "threshold": float(threshold),
        "analytic_spheres": bool(analytic_spheres),
        "date": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "median_relative_noise": float(np.median(rel)),
        "p95_relative_noise": float(np.percentile(rel, 95)),
        "ir_fraction_max": float(frac.max()),
        "ir_patches": int((labels == "interreflection").sum()),
    }
    return Reference(
        name=name, config=_config_name(scene), wavelengths=wl, boxes=pt["boxes"],
        object_names=tuple(o.name for o in scene.objects), object_index=pt["object"],
        normals=pt["normal"], points=pt["point"], views=pt["view"],
        spectra=st["total"], noise=st["noise"], direct=st["direct"],
        noise_direct=st["noise_direct"], ir_fraction=frac, ir_noise=frac_se, labels=labels,
        preview_xyz=xyz.astype(np.float32), metadata=meta)


def preview_png(ref: Reference, path: str | os.PathLike[str], *, boxes: bool = True) -> None:
    """Write an sRGB PNG of ``ref.preview_xyz`` (99th-percentile luminance → white; patch
    outlines: white = direct, cyan = interreflection, orange = table)."""
    import colour

    from ..._runtime.fileio import atomic_path

    xyz = np.asarray(ref.preview_xyz, np.float64)
    scale = max(float(np.percentile(xyz[..., 1], 99)), 1e-30)
    with np.errstate(invalid="ignore"):
        lin = colour.XYZ_to_sRGB(xyz / scale, apply_cctf_encoding=False)
        rgb = colour.cctf_encoding(np.clip(lin, 0, 1))
    img = (np.nan_to_num(rgb) * 255 + 0.5).astype(np.uint8)
    if boxes:
        x0c, y0c = ref.metadata["crop"][:2]
        step = int(ref.metadata.get("preview_step", 1))
        colours = {"interreflection": (0, 255, 255), "table": (255, 160, 0)}
        for (x0, y0, x1, y1), lab in zip(ref.boxes, ref.labels, strict=True):
            col = colours.get(str(lab), (255, 255, 255))
            xa, ya = (x0 - x0c) // step, (y0 - y0c) // step
            xb, yb = (x1 - x0c - 1) // step, (y1 - y0c - 1) // step
            img[ya, xa:xb + 1] = col
            img[yb, xa:xb + 1] = col
            img[ya:yb + 1, xa] = col
            img[ya:yb + 1, xb] = col
    import matplotlib.image

    with atomic_path(path, suffix=".png") as tmp:
        matplotlib.image.imsave(tmp, img)


# --------------------------------------------------------------------------------------------
# Scenes of any shape (meshes, real surfaces): patches of the frame's 5×5 grid


def raster_patches(scene: Scene, *, radii: float = 2.0, surface_half: float = 10.0
                   ) -> dict[str, Any]:
    """The frame grid's patches (:func:`~.patches.patch_grid`) labelled from our rasteriser's
    object ids (the same meshes as the reference's) and, for a scene with ``[[surfaces]]``,
    the planes seen through the pixel centres.

    Returns a dict: ``object_id`` (H, W) int32 (−1 = no object), ``surface`` (H, W) bool (a
    plane within ``surface_half`` m of its point is seen and no object covers the pixel),
    ``boxes`` (G, 4), ``owner`` (G,) (object index, or TABLE / MIXED / OTHER of
    :mod:`.patches`), ``near`` (G,) the object a table patch's centre lies within ``radii``
    bounding radii of (along the plane; −1 for none), ``crop`` the objects' window
    (:class:`~.export.Crop`, 4 pixels of margin, as scripts/any_shape_reference.py).
    """
    import jax

    from ...rendering import prepare, render_frame
    from .export import Crop
    from .patches import TABLE, label_patches, near_object, object_spheres, plane_hits
    from .render import camera_rays

    bare = dataclasses.replace(scene, surfaces=()) if getattr(scene, "surfaces", ()) else scene
    prep = prepare(bare, mode="none", occlusion=False)
    obj = np.asarray(jax.block_until_ready(render_frame(prep)).object_id, np.int32)
    h, w = obj.shape
    surfaces = tuple(getattr(scene, "surfaces", ()))
    surface = np.zeros((h, w), bool)
    if surfaces:
        ys, xs = np.mgrid[0:h, 0:w] + 0.5
        origin, dirs = camera_rays(scene, xs, ys)
        for s in surfaces:
            surface |= np.isfinite(plane_hits(origin, dirs, s.point, s.normal,
                                              surface_half)).all(-1)
        surface &= obj < 0
    boxes, owner, _ = label_patches(obj, surface)
    near = np.full(len(boxes), -1, np.int32)
    if surfaces:
        cx = 0.5 * (boxes[:, 0] + boxes[:, 2])
        cy = 0.5 * (boxes[:, 1] + boxes[:, 3])
        origin, dc = camera_rays(scene, cx, cy)
        centres, rad = object_spheres(scene)
        best = np.full(len(boxes), np.inf)
        for s in surfaces:
            p = plane_hits(origin, dc, s.point, s.normal, surface_half)
            dist = np.linalg.norm(p - origin, axis=-1)
            closer = np.isfinite(dist) & (dist < best)
            best[closer] = dist[closer]
            near[closer] = near_object(p, centres, rad, s.point, s.normal, radii)[closer]
        near[owner != TABLE] = -1
    rows, cols = np.nonzero(obj >= 0)
    x0, y0 = max(int(cols.min()) - 4, 0), max(int(rows.min()) - 4, 0)
    x1, y1 = min(int(cols.max()) + 5, w), min(int(rows.max()) + 5, h)
    return {"object_id": obj, "surface": surface, "boxes": boxes, "owner": owner,
            "near": near, "crop": Crop(x0, y0, x1 - x0, y1 - y0)}


def render_grid(scene: Scene, crop: Any, *, spp: int, passes: int, seed: int = 0,
                progress: Any = None) -> dict[str, Any]:
    """Mitsuba renders of ``scene`` (no surfaces) at path depths 2 and 16 over ``crop`` (the
    band trick, :func:`.render.render_spectral`), reduced to the frame grid's patch means.

    Returns ``grid`` (2, passes, ny, nx, L) float32 (depth 2, depth 16; zero for patches
    outside the crop), ``xyz16`` (H, W, 3) the depth-16 mean in absolute XYZ (zero outside
    the crop), ``seconds``, ``variant``.
    """
    from ...color import xyz_weights
    from .patches import grid_means, patch_grid
    from .render import render_spectral

    r = render_spectral(scene, spp=spp, passes=passes, depths=(2, 16), seed=seed, crop=crop,
                        progress=progress)
    h, w = scene.height, scene.width
    ys, xs = patch_grid(h, w)
    grid = np.zeros((2, passes, ys.size, xs.size, r.wavelengths.size), np.float32)
    frame = np.zeros((h, w, r.wavelengths.size), np.float32)
    for d in range(2):
        for p in range(passes):
            frame[crop.y0:crop.y0 + crop.height, crop.x0:crop.x0 + crop.width] = r.passes[d, p]
            grid[d, p] = grid_means(frame)
    xyz16 = np.zeros((h, w, 3), np.float32)
    xyz16[crop.y0:crop.y0 + crop.height, crop.x0:crop.x0 + crop.width] = (
        r.mean(16) @ xyz_weights(r.wavelengths))
    return {"grid": grid, "xyz16": xyz16, "seconds": float(r.seconds), "variant": r.variant}


def patch_noise_de(passes_xyz: np.ndarray, white: np.ndarray) -> np.ndarray:
    """(P,) standard error of the patch colour as ΔE00, from per-pass XYZ (K, P, 3): the rms
    ΔE00 of the passes about their mean, over √(K − 1), times 1/√K (NaN for K < 2)."""
    from ...color import delta_e00, xyz_to_lab

    k = passes_xyz.shape[0]
    if k < 2:
        return np.full(passes_xyz.shape[1], np.nan)
    lab_mean = xyz_to_lab(passes_xyz.mean(axis=0), white)
    de = np.stack([np.asarray(delta_e00(xyz_to_lab(x, white), lab_mean)) for x in passes_xyz])
    return np.sqrt((de ** 2).sum(axis=0) / (k - 1) / k)


def make_mesh_reference(
    scene: Scene,
    name: str,
    patches: dict[str, Any],
    render: dict[str, Any],
    *,
    spp: int,
    passes: int,
    seed: int = 0,
    threshold: float = 0.02,
    radii: float = 2.0,
    preview_size: int = 160,
) -> Reference:
    """A grid-layout :class:`Reference` of a scene of any shape from :func:`raster_patches`
    (``patches``) and the depth-2 / depth-16 patch grid of its render (``render``:
    :func:`render_grid`'s dict, or a reused render of the same layout).

    Kept: object patches (owner ≥ 0) and table patches within ``radii`` bounding radii of an
    object. Labels from the reference alone: "interreflection" where (Y₁₆ − Y₂)/Y₁₆ exceeds
    ``threshold``, else "direct"; "table" for table patches. The preview is the depth-16 XYZ
    over the kept patches' window (6 pixels of margin), averaged over step × step blocks so
    that its longer side is at most ``preview_size``.
    """
    import hashlib
    from pathlib import Path

    from ...color import radiance_to_xyz, xyz_weights
    from ...rendering import load_environment
    from .. import scene_white_xyz
    from .backend import init_mitsuba
    from .patches import TABLE
    from .render import _view_matrix

    mi, _ = init_mitsuba()

    owner, near = patches["owner"], patches["near"]
    keep = (owner >= 0) | ((owner == TABLE) & (near >= 0))
    boxes = patches["boxes"][keep]
    wl = scene.wavelengths
    grid = np.asarray(render["grid"], np.float64)
    g = grid.reshape(2, grid.shape[1], -1, wl.size)[:, :, keep]  # (2, K, P, L)
    st = _depth_statistics(g, wl)
    direct, noise_direct, frac, frac_se = (st["direct"], st["noise_direct"], st["frac"],
                                           st["frac_se"])
    missing = (g[0] == 0.0).all(axis=(0, 2))  # outside the depth-2 window (table patches)
    for a in (direct, noise_direct, frac, frac_se):
        a[missing] = np.nan
    obj_index = owner[keep]
    labels = np.where(obj_index < 0, "table",
                      np.where(frac > threshold, "interreflection", "direct"))
    view = _view_matrix(tuple(scene.camera.position), tuple(scene.camera.look_at),
                        tuple(scene.camera.up))
    env = np.asarray(load_environment(scene, wl), np.float64)
    white = scene_white_xyz(env @ xyz_weights(wl), scene.environment.rotation_y_deg, view[2, :3])
    noise_de = patch_noise_de(radiance_to_xyz(g[1], wl), white)
    # preview: the kept patches' window, block-averaged
    h, w = scene.height, scene.width
    x0, y0 = max(int(boxes[:, 0].min()) - 6, 0), max(int(boxes[:, 1].min()) - 6, 0)
    x1, y1 = min(int(boxes[:, 2].max()) + 6, w), min(int(boxes[:, 3].max()) + 6, h)
    step = max(1, -(-max(x1 - x0, y1 - y0) // preview_size))
    x1, y1 = x0 + (x1 - x0) // step * step, y0 + (y1 - y0) // step * step
    xyz = np.asarray(render["xyz16"], np.float64)[y0:y1, x0:x1]
    xyz = xyz.reshape((y1 - y0) // step, step, (x1 - x0) // step, step, 3).mean(axis=(1, 3))
    rel = st["rel"]
    obj_ir = (obj_index >= 0) & (labels == "interreflection")
    meta = {
        "layout": "grid",
        "variant": render.get("variant") or "not recorded",
        "mitsuba": mi.__version__,
        "source": render.get("source", ""),
        **_sampling_metadata(spp, passes, seed),
        "render_seconds": (round(float(render["seconds"]), 1)
                           if np.isfinite(render.get("seconds", np.nan)) else None),
        "renders": int(2 * passes * -(-wl.size // 3)),
        "config_sha256": hashlib.sha256(Path(scene.path).read_bytes()).hexdigest(),
        "scene_sha256": scene_sha256(scene.path),
        "meshes_sha256": {o.name: hashlib.sha256(Path(o.mesh).read_bytes()).hexdigest()
                          for o in scene.objects if o.mesh is not None},
        "crop": [x0, y0, x1 - x0, y1 - y0],
        "preview_step": int(step),
        "frame": [w, h],
        "patch_size": 5,
        "patch_rule": "5x5 squares of the frame grid from column/row 1 whose pixels and a "
                      "one-pixel border show one object (our rasteriser's object ids), or a "
                      f"real surface within {radii:g} bounding radii of an object",
        "threshold": float(threshold),
        "radii": float(radii),
        "surfaces": [{"name": s.name, "point": list(s.point), "normal": list(s.normal),
                      "reflectance": s.reflectance_source}
                     for s in getattr(scene, "surfaces", ())],
        "white_xyz": [float(v) for v in white],
        "date": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "median_relative_noise": float(np.median(rel)),
        "p95_relative_noise": float(np.percentile(rel, 95)),
        "noise_de_median": float(np.median(noise_de)),
        "noise_de_p95": float(np.percentile(noise_de, 95)),
        "noise_de_max": float(noise_de.max()),
        "ir_fraction_max": float(np.nanmax(np.where(obj_index >= 0, frac, np.nan))),
        "ir_patches": int(obj_ir.sum()),
        "table_patches": int((obj_index < 0).sum()),
    }
    nan3 = np.full((len(boxes), 3), np.nan)
    return Reference(
        name=name, config=_config_name(scene), wavelengths=wl, boxes=boxes,
        object_names=tuple(o.name for o in scene.objects), object_index=obj_index,
        normals=nan3, points=nan3, views=nan3,
        spectra=st["total"], noise=st["noise"], direct=direct, noise_direct=noise_direct,
        ir_fraction=frac, ir_noise=frac_se, labels=labels,
        preview_xyz=xyz.astype(np.float32), metadata=meta,
        near=np.where(obj_index < 0, near[keep], -1), noise_de=noise_de)
