"""Path-traced reference of objects resting on a real surface (default configs/on_table.toml)
and the ΔE00 of our frames against it, per 5×5-pixel patch and region.

    python scripts/table_reference.py --size 720 480 --spp 64 --passes 4 --out out/table_ref
    python scripts/table_reference.py --size 180 120 --spp 16 --passes 1 --out /tmp/t  # quick

Reference (Mitsuba 3, :mod:`spectral_fit.validation.reference`): the objects carry our whole
reflection model as one BSDF; each plane of the config's ``[[surfaces]]`` is a large finite
rectangle (``--table-size``, default 20 m × 20 m, centred on its ``point``) with a Lambertian
BSDF of its reflectance in the scene's bands (band trick: three bands per rgb render, as for the
objects). Three renders: depth 16 with and without the objects (the surfaces alone) over
the whole frame, depth 2 with the objects over the window around them (8 pixels of margin).
Only the patch means of every 5×5 square of the frame grid (columns and rows 1, 6, 11, …) are
kept, per pass, with the depth-16 frames in XYZ for the pictures; they are cached in
``<out>/table_mitsuba.npz`` and reused by a later run with the same settings (``--fresh``
renders again).

Patches (owner): object index k when the patch and a one-pixel border around it all show
object k; ``TABLE`` (−1) when they all show a surface (its ray meets the rectangle and no object
covers the pixel); ``MIXED`` (−2) when the patch itself shows a surface and one object k (its
border may show only that object or the surface); ``OTHER`` (−3) otherwise (environment, two
objects, object edges). The object masks are our rasteriser's (the same meshes as the
reference's). Table and mixed patches are "near" object k when the point of the surface seen at
the patch centre lies within ``--radii`` (2) bounding radii of object k's centre projected onto
the plane (distance along the plane; bounding sphere: the sphere itself, or for a mesh the
sphere about the centre of its bounding box through its farthest vertex).

Regions scored (ΔE00, CIELAB against the scene white, :func:`scene_white_xyz`): object
patches with the interreflection share (Y₁₆ − Y₂)/Y₁₆ of the reference below / above
``--threshold`` (2 %; the table's light on the objects counts as interreflection), table
patches near an object, table patches farther away, mixed patches. Our frames: the objects alone
(config without its surfaces; its object patches only) and, when the renderer has
``spectral_fit.rendering.surface_layer``, the frame with the surfaces: objects from
``render_frame`` of the full config, surface pixels from the layer's ``radiance``. The
differential form (what a composite over a photograph of the table uses): the reference's
(with objects) / (surfaces only) against our ``radiance / base``, per channel, as the relative
error |ours − ref| / ref in %, with the reference's own standard error of that ratio. Without
a surface layer (or a config reader that knows ``[[surfaces]]``) the JSON says ``"surfaces":
"not available"`` and only the objects-only frame is scored.

Writes ``<out>/table_reference.npz`` (patch boxes, owners, regions, per-band patch means with
and without the objects and their standard errors, our patch means, the per-pixel object ids and
surface mask), ``<out>/table_reference.json`` (the statistics; ``reference_table``: the
reference's own table, its luminance without the objects and the with / without ratio, i.e.
how uniform the surfaces-only table is and how deep the shadows are), ``<out>/table_de.png``
(false-colour ΔE00 per patch; the ratio's error per table patch) and
``<out>/table_reference.png`` (the depth-16 reference in sRGB, with our display exposure;
``table_reference_surfaces_only.png`` without the objects).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from spectral_fit.validation.reference.patches import (  # noqa: E402,F401  (also used by tests)
    MIXED,
    OTHER,
    PATCH,
    TABLE,
    bounding_sphere,
    grid_means,
    label_patches,
    near_object,
    object_spheres,
    patch_grid,
    plane_frame,
    plane_hits,
)

DE_KEYS = {"objects only (no surfaces)": "objects_only", "with surfaces": "with_surfaces"}

# --------------------------------------------------------------------------------------------
# config


def read_config(path: Path, size: tuple[int, int] | None, bands: Any
                ) -> tuple[Any, Any, list[dict[str, Any]]]:
    """(scene without its surfaces, scene with them or None when the config reader does not
    know ``[[surfaces]]``, the surfaces: name, point, normal, reflectance (L,) on the scene's
    bands)."""
    from spectral_fit._runtime.errors import InputError
    from spectral_fit.io import parse_scene
    from spectral_fit.io._scene import _Reader, _reflectance

    data = tomllib.loads(path.read_text())
    if size:
        data.setdefault("frame", {}).update(width=size[0], height=size[1])
    if bands:
        data.setdefault("spectral", {}).update(start_nm=bands[0], end_nm=bands[1],
                                               step_nm=bands[2])
    raw = data.get("surfaces", [])
    bare = {k: v for k, v in data.items() if k != "surfaces"}
    scene = parse_scene(bare, path=path)
    try:
        full = parse_scene(data, path=path) if raw else None
        if full is not None and not getattr(full, "surfaces", ()):
            full = None
    except InputError:
        full = None
    surfaces = []
    for i, t in enumerate(raw):
        r = _Reader(t, f"surfaces[{i}]", path)
        if r.raw("shape", "plane") != "plane":
            raise InputError("only planes", path=path, field=f"surfaces[{i}].shape")
        n = np.asarray(r.vector("normal", 3, [0.0, 1.0, 0.0]), np.float64)
        refl, src = _reflectance(r, scene.wavelengths)
        surfaces.append({"name": str(r.raw("name", f"surface{i}")),
                         "point": np.asarray(r.vector("point", 3, [0.0, 0.0, 0.0])),
                         "normal": n / np.linalg.norm(n),
                         "reflectance": np.asarray(refl, np.float64), "source": src})
    if not surfaces:
        raise InputError("the config has no [[surfaces]] plane", path=path, field="surfaces")
    return scene, full, surfaces


def plane_irradiance(env: np.ndarray, rotation_y_deg: float, normal: Any) -> np.ndarray:
    """Irradiance (L,) of a plane with world ``normal`` under the map's texels ``env``
    (Hm, Wm, L) on its side: Σ L max(0, N·ω) Δω (an infinite plane, alone, sees no other
    surface; times reflectance / π its radiance)."""
    from spectral_fit.lighting import rotation_y, texel_directions, texel_solid_angles

    h, w, _ = env.shape
    n = rotation_y(rotation_y_deg).T @ (np.asarray(normal, np.float64)
                                        / np.linalg.norm(normal))
    wgt = np.maximum(texel_directions(h, w) @ n, 0.0) * texel_solid_angles(h, w)
    return np.einsum("hw,hwl->l", wgt, env)


# --------------------------------------------------------------------------------------------
# the reference (Mitsuba)


def rectangle(mi: Any, surface: dict[str, Any], refl3: np.ndarray, half: float) -> dict:
    """A Mitsuba ``rectangle`` of side 2·``half`` about the surface's point, facing its normal,
    with a Lambertian BSDF of reflectance ``refl3`` (three bands)."""
    fr = plane_frame(surface["normal"])
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = half * fr[0], half * fr[1], fr[2]
    m[:3, 3] = surface["point"]
    return {"type": "rectangle", "to_world": mi.ScalarTransform4f(m.tolist()),
            "bsdf": {"type": "diffuse",
                     "reflectance": {"type": "rgb", "value": [float(x) for x in refl3]}}}


def render_reference(scene: Any, surfaces: list[dict[str, Any]], *, spp: int, passes: int,
                     half: float, crop2: Any, seed: int = 0, progress: Any = print,
                     crop16: Any = None, surfaces_alone: bool = True) -> dict[str, Any]:
    """Band-trick renders: depth 16 with and without the objects over the whole frame (or the
    window ``crop16``; ``surfaces_alone=False`` skips the render without them, its grid then
    zero), depth 2 with them over the window ``crop2`` (:class:`Crop`; only the objects'
    patches need it).
    Returns ``grid`` (3, passes, ny, nx, L) patch means of every grid patch (depth 16, depth 2
    (0 outside ``crop2``), surfaces alone), ``xyz16`` / ``xyz_surfaces`` (H, W, 3) the
    depth-16 frames with and without the objects in absolute XYZ, ``seconds`` and
    ``variant``."""
    from spectral_fit.color import xyz_weights
    from spectral_fit.validation.reference.backend import current_variant, init_mitsuba
    from spectral_fit.validation.reference.export import (
        band_groups,
        environment_texels,
        mitsuba_envmap_rows,
        scene_dict,
    )

    mi, _ = init_mitsuba()
    wl = scene.wavelengths
    h, w = scene.height, scene.width
    ys, xs = patch_grid(h, w)
    rows = mitsuba_envmap_rows(environment_texels(scene))
    meshes = {o.name: o.make_mesh(world=True) for o in scene.objects}
    integ = {d: mi.load_dict({"type": "path", "max_depth": d}) for d in (2, 16)}
    grid = np.zeros((3, passes, ys.size, xs.size, wl.size), np.float32)
    full16 = np.zeros((2, h, w, wl.size), np.float32)
    t0 = time.perf_counter()
    groups = band_groups(wl.size)
    for gi, idx in enumerate(groups):
        extra = {f"surface_{i}": rectangle(mi, s, s["reflectance"][idx], half)
                 for i, s in enumerate(surfaces)}
        refl = {o.name: np.asarray(o.material.reflectance)[idx] for o in scene.objects}
        for r, depth, objects, crop in ((0, 16, True, crop16), (1, 2, True, crop2),
                                        (2, 16, False, crop16))[:3 if surfaces_alone else 2]:
            d = scene_dict(scene, env_rgb=rows[..., idx], reflectances=refl, spp=spp,
                           meshes=meshes, objects=objects, extra_shapes=dict(extra), crop=crop)
            ms = mi.load_dict(d)
            acc = np.zeros((h, w, 3), np.float64)
            for p in range(passes):
                img = np.zeros((h, w, 3), np.float32)
                part = np.asarray(mi.render(ms, integrator=integ[depth], seed=seed + p,
                                            spp=spp), np.float32)[..., :3]
                if crop is None:
                    img[:] = part
                else:
                    img[crop.y0:crop.y0 + crop.height, crop.x0:crop.x0 + crop.width] = part
                grid[r, p][..., idx] = grid_means(img)
                acc += img
            if depth == 16:
                full16[0 if objects else 1][..., idx] = (acc / passes).astype(np.float32)
        progress(f"[mitsuba] bands {wl[idx[0]]:g}-{wl[idx[-1]]:g} nm "
                 f"({gi + 1}/{len(groups)}, {time.perf_counter() - t0:.0f} s)")
    wxyz = xyz_weights(wl)
    return {"grid": grid, "xyz16": (full16[0] @ wxyz).astype(np.float32),
            "xyz_surfaces": (full16[1] @ wxyz).astype(np.float32),
            "seconds": time.perf_counter() - t0, "variant": current_variant() or ""}


# --------------------------------------------------------------------------------------------
# ours


def our_surface_frame(scene_full: Any) -> dict[str, np.ndarray] | None:
    """Our frame with the config's surfaces, or None when the renderer has no surface layer:
    ``spectral`` (H, W, L) the objects' radiance, ``object_id`` (H, W), ``radiance`` (H, W, C)
    the surfaces' radiance with the objects present, ``mask`` (H, W) a surface is seen (objects
    may cover it), ``base`` (H, W, C) or (C,) the surfaces' radiance without the objects,
    ``to_xyz`` (C, 3) those channels to XYZ and ``rgb`` (H, W, 3) the displayed frame. The one
    place that calls the surface API (its channels: the bands when the layer takes ``out``, an
    (L, C) matrix from spectral radiance, else its default, absolute XYZ)."""
    try:
        from spectral_fit.rendering import surface_layer
    except ImportError:
        return None
    if scene_full is None:
        return None
    import jax

    from spectral_fit.color import xyz_weights
    from spectral_fit.rendering import prepare, render_frame

    prep = prepare(scene_full)
    frame = jax.block_until_ready(render_frame(prep, spectral=True))
    wl = scene_full.wavelengths
    try:
        layer = surface_layer(prep, out=np.eye(wl.size, dtype=np.float32))
    except TypeError:
        layer = surface_layer(prep)
    layer = jax.block_until_ready(layer)
    rad = np.asarray(layer.radiance, np.float64)
    c = rad.shape[-1]
    if c == wl.size:
        to_xyz = xyz_weights(wl)
    elif c == 3:
        to_xyz = np.eye(3)  # the output space: absolute XYZ
    else:
        to_xyz = np.asarray(prep.colour.to_xyz, np.float64)
    return {"spectral": np.asarray(frame.spectral, np.float64),
            "object_id": np.asarray(frame.object_id), "radiance": rad,
            "mask": np.asarray(layer.mask, bool), "base": np.asarray(layer.base, np.float64),
            "to_xyz": to_xyz, "rgb": np.asarray(frame.rgb)}


# --------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, default=REPO / "configs" / "on_table.toml")
    ap.add_argument("--size", type=int, nargs=2, default=(720, 480), metavar=("W", "H"))
    ap.add_argument("--bands", type=float, nargs=3, metavar=("START", "END", "STEP"))
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--passes", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--table-size", type=float, default=20.0,
                    help="side (m) of the square standing for each plane in the reference")
    ap.add_argument("--threshold", type=float, default=0.02)
    ap.add_argument("--radii", type=float, default=2.0)
    ap.add_argument("--vmax", type=float, default=3.0, help="ΔE00 at the top of the colours")
    ap.add_argument("--out", type=Path, default=Path("out/table_reference"))
    ap.add_argument("--fresh", action="store_true")
    args = ap.parse_args(argv)

    sys.path.insert(0, str(REPO))
    import jax

    from spectral_fit._runtime.fileio import atomic_write_text
    from spectral_fit.color import radiance_to_xyz, to_display, xyz_weights
    from spectral_fit.rendering import load_environment, prepare, render_frame
    from spectral_fit.validation import delta_e_patches, scene_white_xyz
    from spectral_fit.validation._compare import _stats

    scene, scene_full, surfaces = read_config(args.config, tuple(args.size), args.bands)
    wl = scene.wavelengths
    h, w = scene.height, scene.width
    half = 0.5 * args.table_size
    args.out.mkdir(parents=True, exist_ok=True)

    # our objects-only frame: also the per-pixel object ids of the patches
    prep = prepare(scene)
    frame = jax.block_until_ready(render_frame(prep, spectral=True))
    spec_obj = np.asarray(frame.spectral, np.float64)
    obj = np.asarray(frame.object_id)
    view = np.asarray(prep.camera.view)
    col = prep.colour
    print("[ours] objects only", flush=True)

    from spectral_fit.validation.reference.render import camera_rays

    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    origin, dirs = camera_rays(scene, xs, ys)
    hits = [plane_hits(origin, dirs, s["point"], s["normal"], half) for s in surfaces]
    depth = np.stack([np.linalg.norm(p - origin, axis=-1) for p in hits])  # NaN = miss
    nearest = np.where(np.isfinite(depth).any(0), np.nanargmin(np.where(
        np.isfinite(depth), depth, np.inf), axis=0), -1)
    surface_px = (nearest >= 0) & (obj < 0)
    boxes, owner, obj_of = label_patches(obj, surface_px)

    # the surface point at each patch centre (first surface hit), its nearby object
    cx = 0.5 * (boxes[:, 0] + boxes[:, 2])
    cy = 0.5 * (boxes[:, 1] + boxes[:, 3])
    _, dc = camera_rays(scene, cx, cy)
    pts = np.full((len(boxes), 3), np.nan)
    best = np.full(len(boxes), np.inf)
    region = np.full(len(boxes), -1, np.int32)
    seen = np.full(len(boxes), -1, np.int32)  # the surface seen at the patch centre
    centres, radii = object_spheres(scene)
    for si, s in enumerate(surfaces):
        p = plane_hits(origin, dc, s["point"], s["normal"], half)
        dist = np.linalg.norm(p - origin, axis=-1)
        closer = np.isfinite(dist) & (dist < best)
        pts[closer] = p[closer]
        best[closer] = dist[closer]
        near = near_object(p, centres, radii, s["point"], s["normal"], args.radii)
        region[closer] = near[closer]
        seen[closer] = si
    near_table = (owner == TABLE) & (region >= 0)
    far_table = (owner == TABLE) & (region < 0)
    mixed = owner == MIXED

    # the reference
    cache = args.out / "table_mitsuba.npz"
    key = json.dumps({"config": str(args.config.resolve()),
                      "text": args.config.read_text(), "size": list(args.size),
                      "bands": args.bands, "spp": args.spp, "passes": args.passes,
                      "seed": args.seed, "table_size": args.table_size})
    if cache.exists() and not args.fresh and str(np.load(cache)["key"]) == key:
        with np.load(cache) as z:
            ref = {k: z[k] for k in ("grid", "xyz16", "xyz_surfaces")}
            ref["seconds"], ref["variant"] = float(z["seconds"]), str(z["variant"])
        print("[mitsuba] reused", cache, flush=True)
    else:
        from spectral_fit.validation.reference.export import Crop

        rows_, cols_ = np.nonzero(obj >= 0)
        x0, y0 = max(int(cols_.min()) - 8, 0), max(int(rows_.min()) - 8, 0)
        x1, y1 = min(int(cols_.max()) + 9, w), min(int(rows_.max()) + 9, h)
        ref = render_reference(scene, surfaces, spp=args.spp, passes=args.passes, half=half,
                               crop2=Crop(x0, y0, x1 - x0, y1 - y0), seed=args.seed,
                               progress=lambda s: print(s, flush=True))
        np.savez_compressed(cache, key=key, **ref)
    grid = ref["grid"].reshape(3, args.passes, -1, wl.size).astype(np.float64)  # (3, K, P, L)
    ref16, ref2, ref_s = grid[:, :].mean(axis=1)
    k = args.passes
    se16 = grid[0].std(0, ddof=1) / math.sqrt(k) if k > 1 else np.full(ref16.shape, np.nan)

    wxyz = xyz_weights(wl)
    wy = wxyz[:, 1]
    share = (ref16 @ wy - ref2 @ wy) / np.maximum(ref16 @ wy, 1e-30)
    high = share > args.threshold
    env = load_environment(scene, wl)
    white = scene_white_xyz(env @ wxyz, scene.environment.rotation_y_deg, view[2, :3])
    xyz_ref = radiance_to_xyz(ref16, wl)
    is_obj = owner >= 0

    def pm(img: np.ndarray) -> np.ndarray:
        return grid_means(img).reshape(-1, img.shape[-1])

    out: dict[str, Any] = {
        "config": str(args.config), "size": list(args.size), "spp": args.spp,
        "passes": args.passes, "table_size_m": args.table_size,
        "surfaces_in_reference": [{"name": s["name"], "point": s["point"].tolist(),
                                   "normal": s["normal"].tolist(),
                                   "reflectance": s["source"]} for s in surfaces],
        "mitsuba_seconds": round(float(ref["seconds"]), 1), "variant": ref["variant"],
        "white_xyz": white.tolist(), "threshold": args.threshold, "radii": args.radii,
        "patches": {"objects": int(is_obj.sum()), "objects, interreflection > 2 %":
                    int((is_obj & high).sum()), "table near": int(near_table.sum()),
                    "table far": int(far_table.sum()), "mixed": int(mixed.sum()),
                    "per object": {o.name: int((owner == i).sum())
                                   for i, o in enumerate(scene.objects)},
                    "table near, per object": {o.name: int((near_table & (region == i)).sum())
                                               for i, o in enumerate(scene.objects)}},
        "reference_noise": {"median relative standard error, depth 16": float(np.nanmedian(
            (se16 / np.maximum(ref16, 1e-30))[is_obj | near_table]))} if k > 1 else {},
        "frames": {},
    }
    ys_ = ref_s @ wy
    ratio_y = (ref16 @ wy) / np.maximum(ys_, 1e-30)
    env_np = np.asarray(env, np.float64)
    analytic = {}
    for si, sf in enumerate(surfaces):
        lum = sf["reflectance"] * plane_irradiance(env_np, scene.environment.rotation_y_deg,
                                                   sf["normal"]) / math.pi
        sel = (owner == TABLE) & (region < 0) & (seen == si)
        analytic[sf["name"]] = {
            "luminance (cd/m²)": float(lum @ wy),
            "reference / analytic, table far, median over patches, per band": (
                np.round(np.median(ref_s[sel], axis=0) / np.maximum(lum, 1e-30), 5).tolist()
                if sel.any() else None)}
    out["reference_table"] = {
        "surfaces alone, analytic (infinite plane under the map's hemisphere)": analytic,
        "surfaces-only luminance, table near (cd/m²)": _stats(ys_[near_table]),
        "surfaces-only luminance, table far (cd/m²)": _stats(ys_[far_table]),
        "luminance with / without the objects, table near": _stats(ratio_y[near_table]),
        "luminance with / without the objects, table far": _stats(ratio_y[far_table]),
        "minimum with / without, per object (table near)": {
            o.name: (float(ratio_y[sel].min()) if (sel := near_table & (region == i)).any()
                     else None) for i, o in enumerate(scene.objects)}}
    disp = dict(exposure_luminance=float(col.exposure), display=col.display,
                scene_white_xy=col.scene_white_xy)
    de_maps: dict[str, np.ndarray] = {}
    rgbs: dict[str, np.ndarray] = {}

    def object_stats(de: np.ndarray) -> dict[str, Any]:
        return {"objects, interreflection < 2 %": _stats(de[is_obj & ~high]),
                "objects, interreflection > 2 %": _stats(de[is_obj & high]),
                "objects, all": _stats(de[is_obj]),
                "per object": {o.name: _stats(de[owner == i])
                               for i, o in enumerate(scene.objects)}}

    # objects only: their patches
    de = np.full(len(boxes), np.nan)
    de[is_obj] = delta_e_patches(radiance_to_xyz(pm(spec_obj)[is_obj], wl), xyz_ref[is_obj],
                                 white)
    out["frames"]["objects only (no surfaces)"] = object_stats(de)
    de_maps["objects only (no surfaces)"] = de
    rgbs["objects only (no surfaces)"] = np.asarray(frame.rgb)
    ours_patches = {"objects_only": pm(spec_obj)}

    ratio_err = None
    ours = our_surface_frame(scene_full)
    if ours is None:
        out["surfaces"] = "not available"
        why = ("the config reader does not know [[surfaces]]" if scene_full is None else
               "spectral_fit.rendering has no surface_layer")
        out["surfaces_note"] = f"only the objects' patches of the objects-only frame: {why}"
    else:
        out["surfaces"] = "available"
        obj_s = ours["object_id"]
        px_xyz = np.where((obj_s >= 0)[..., None], ours["spectral"] @ wxyz,
                          np.where(ours["mask"][..., None], ours["radiance"] @ ours["to_xyz"],
                                   np.nan))
        xyz_ours = pm(px_xyz)
        covered = pm(ours["mask"][..., None].astype(np.float64))[:, 0] > 0.999
        ok = np.isfinite(xyz_ours).all(-1)
        de = np.full(len(boxes), np.nan)
        de[ok] = delta_e_patches(xyz_ours[ok], xyz_ref[ok], white)
        de[~(is_obj | near_table | far_table | mixed)] = np.nan
        r = object_stats(de)
        r["table near"] = _stats(de[near_table & ok])
        r["table near, per object"] = {o.name: _stats(de[near_table & ok & (region == i)])
                                       for i, o in enumerate(scene.objects)}
        r["table far"] = _stats(de[far_table & ok])
        r["mixed"] = _stats(de[mixed & ok])
        r["table patches outside our surface layer"] = int(
            ((near_table | far_table) & ~covered).sum())
        # the differential form: with / without the objects, per channel
        to_c = np.linalg.pinv(ours["to_xyz"]) if ours["radiance"].shape[-1] != wl.size else None
        base = ours["base"]
        base = pm(base) if base.ndim == 3 else base
        ratio_ours = pm(ours["radiance"]) / np.maximum(base, 1e-30)
        ref_c, ref_sc = (ref16, ref_s) if to_c is None else (xyz_ref @ to_c,
                                                             radiance_to_xyz(ref_s, wl) @ to_c)
        ratio_ref = ref_c / np.maximum(ref_sc, 1e-30)
        err = 100.0 * np.abs(ratio_ours - ratio_ref) / np.maximum(np.abs(ratio_ref), 1e-30)
        # the reference's own noise on that ratio (standard error over the passes, %)
        g16, gs = grid[0], grid[2]  # (K, P, L)
        if to_c is not None:
            g16, gs = radiance_to_xyz(g16, wl) @ to_c, radiance_to_xyz(gs, wl) @ to_c
        rp = g16 / np.maximum(gs, 1e-30)
        ratio_se = (100.0 * rp.std(0, ddof=1) / math.sqrt(k) / np.maximum(np.abs(ratio_ref),
                                                                          1e-30)
                    if k > 1 else np.full(ratio_ref.shape, np.nan))
        diff = {}
        for name, sel in (("table near", near_table & covered),
                          *((f"table near {o.name}", near_table & covered & (region == i))
                            for i, o in enumerate(scene.objects)),
                          ("table far", far_table & covered)):
            e = err[sel]
            if e.size == 0:
                diff[name] = {"n": 0}
                continue
            band_med = np.median(e, axis=0)
            worst = int(band_med.argmax())
            diff[name] = {"averaged over channels": _stats(e.mean(axis=1)),
                          "worst channel": {"channel": (float(wl[worst]) if to_c is None
                                                        else "XYZ"[worst]),
                                            **_stats(e[:, worst])},
                          "reference standard error %, median": {
                              "averaged over channels": float(np.median(
                                  ratio_se[sel].mean(axis=1))),
                              "worst channel": float(np.median(ratio_se[sel][:, worst]))}}
        r["differential ratio error %"] = diff
        out["frames"]["with surfaces"] = r
        de_maps["with surfaces"] = de
        # our frame with the surfaces drawn (the objects' exposure), as the reference's
        rgbs["with surfaces"] = np.clip(np.nan_to_num(np.asarray(
            to_display(np.where(np.isfinite(px_xyz), px_xyz, 0.0), **disp).rgb)), 0, 1)
        ours_patches["with_surfaces_xyz"] = xyz_ours
        ours_patches["with_surfaces_ratio"] = ratio_ours
        ratio_err = np.where((near_table | far_table) & covered, err.mean(axis=1), np.nan)

    atomic_write_text(args.out / "table_reference.json", json.dumps(out, indent=2) + "\n")
    np.savez_compressed(
        args.out / "table_reference.npz", wavelengths=wl, boxes=boxes, owner=owner,
        object_of=obj_of, region=region, surface_seen=seen, surface_point=pts, share=share,
        ref16=ref16, ref2=ref2, ref_surfaces=ref_s, se16=se16, object_id=obj,
        surface_mask=surface_px, object_names=np.asarray([o.name for o in scene.objects]),
        **{f"de_{DE_KEYS[k]}": v for k, v in de_maps.items()},
        **{f"ours_{k}": v for k, v in ours_patches.items()})

    ref_rgb = np.asarray(to_display(ref["xyz16"].astype(np.float64), **disp).rgb)
    ref_rgb_s = np.asarray(to_display(ref["xyz_surfaces"].astype(np.float64), **disp).rgb)
    import matplotlib.image

    matplotlib.image.imsave(args.out / "table_reference.png",
                            (np.clip(np.nan_to_num(ref_rgb), 0, 1) * 255 + 0.5).astype(np.uint8))
    matplotlib.image.imsave(args.out / "table_reference_surfaces_only.png",
                            (np.clip(np.nan_to_num(ref_rgb_s), 0, 1) * 255 + 0.5)
                            .astype(np.uint8))
    figure(args.out / "table_de.png", ref_rgb, rgbs, de_maps, boxes, owner, region, high,
           vmax=args.vmax, ratio_ref=ratio_y, ratio_err=ratio_err)
    print(json.dumps(out, indent=2))
    return 0


def figure(path: Path, ref_rgb: np.ndarray, rgbs: dict[str, np.ndarray],
           de_maps: dict[str, np.ndarray], boxes: np.ndarray, owner: np.ndarray,
           region: np.ndarray, high: np.ndarray, *, vmax: float = 3.0,
           ratio_ref: np.ndarray | None = None, ratio_err: np.ndarray | None = None) -> None:
    """Reference | region map on top; per frame of ours: the frame | its ΔE00 per patch; then
    (with ``ratio_err``) the reference's luminance with / without the objects | our ratio's
    error (%, averaged over channels) per table patch."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from spectral_fit._runtime.fileio import atomic_path

    h, w = ref_rgb.shape[:2]
    ys, xs = patch_grid(h, w)
    ext = (1, 1 + xs.size * PATCH, 1 + ys.size * PATCH, 1)

    def grid(v: np.ndarray) -> np.ndarray:
        return np.asarray(v, np.float64).reshape(ys.size, xs.size)

    # regions: 0 other, 1 table far, 2 table near, 3 mixed, 4 object < 2 %, 5 object > 2 %
    reg = np.zeros(len(owner))
    reg[owner == TABLE] = 1
    reg[(owner == TABLE) & (region >= 0)] = 2
    reg[owner == MIXED] = 3
    reg[owner >= 0] = 4
    reg[(owner >= 0) & high] = 5
    n = 1 + len(rgbs) + (ratio_err is not None)
    fig, axes = plt.subplots(n, 2, figsize=(12, 3.9 * n), squeeze=False)
    axes[0, 0].imshow(ref_rgb)
    axes[0, 0].set_title("reference, path depth 16")
    cmap_r = matplotlib.colors.ListedColormap(
        ["#222222", "#777777", "#bbbbbb", "#3b75af", "#e0a030", "#c03030"])
    axes[0, 1].imshow(grid(reg), cmap=cmap_r, vmin=-0.5, vmax=5.5, extent=ext,
                      interpolation="nearest")
    axes[0, 1].set_title("patches: table far / near (grey), mixed (blue), objects < / > 2 % "
                         "interreflection (orange / red)", fontsize=8)
    cmap = plt.get_cmap("inferno").copy()
    cmap.set_bad((0, 0, 0, 0))
    for row, (name, rgb) in enumerate(rgbs.items(), start=1):
        axes[row, 0].imshow(rgb)
        axes[row, 0].set_title(f"ours: {name}")
        ax = axes[row, 1]
        ax.imshow(np.asarray(rgb).mean(-1), cmap="gray", vmin=0, vmax=1, extent=(0, w, h, 0))
        de = de_maps[name]
        im = ax.imshow(np.ma.masked_invalid(grid(de)), cmap=cmap, vmin=0, vmax=vmax,
                       extent=ext, interpolation="nearest")
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        fin = de[np.isfinite(de)]
        med = f"median {np.median(fin):.2f}, p90 {np.percentile(fin, 90):.2f}" if fin.size else ""
        ax.set_title(f"ΔE00 per 5×5 patch ({med})", fontsize=9)
        fig.colorbar(im, ax=ax, fraction=0.03, label="ΔE00")
    if ratio_err is not None:
        ax = axes[-1, 0]
        table = owner == TABLE
        grey = plt.get_cmap("gray").copy()
        grey.set_bad("#3b75af")
        im = ax.imshow(np.ma.masked_invalid(grid(np.where(table, ratio_ref, np.nan))),
                       cmap=grey, vmin=0.3, vmax=1.02, extent=ext, interpolation="nearest")
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_title("reference: table luminance with / without the objects (blue: not table)",
                     fontsize=9)
        fig.colorbar(im, ax=ax, fraction=0.03)
        ax = axes[-1, 1]
        cmap_e = plt.get_cmap("inferno").copy()
        cmap_e.set_bad("#3b75af")
        im = ax.imshow(np.ma.masked_invalid(grid(ratio_err)), cmap=cmap_e, vmin=0.0, vmax=5.0,
                       extent=ext, interpolation="nearest")
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_title("ours: |ratio − reference's| / reference's, % (mean over channels)",
                     fontsize=9)
        fig.colorbar(im, ax=ax, fraction=0.03, label="%")
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
