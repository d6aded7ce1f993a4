"""The fit's forward model (spot readings through the radiance cache) against a committed
path-traced reference, patch by patch.

For a subsample of the reference's object patches (5 × 5 pixels of the 720 × 480 frame; spread
over objects and over the interreflection share, deterministic), one spot per patch: the
instrument at the scene camera's position, aimed at the world point seen at the patch's centre
(the camera ray through the centre cast against the scene's world meshes, checked to meet the
patch's object from the front), with a field angle whose disc has the area of the patch (its
angular size at the camera). The model's noiseless readings with the scene's own materials
(:func:`spectral_fit.fitting.simulate_readings`) with interreflection "auto" (the config's
mode) are compared with the reference's depth-16 patch means, and with interreflection "none"
with its depth-2 (single bounce) means: per patch the luminance ratio Y_model / Y_ref, the mean
over bands of model / reference, the worst band's ratio, and ΔE00 in CIELAB against the scene
white (as ``spectral-fit validate``). Prints median / p90 / max of |ratio − 1| and ΔE00 overall,
split by the reference's interreflection share (≤ 2 % / > 2 %) and per object; writes JSON.

    python scripts/fit_model_vs_reference.py any_shape --output /tmp/fitref/any_shape.json
    PYTHONPATH=/tmp/fitref/head python scripts/fit_model_vs_reference.py any_shape ...

(the second line runs another checkout of the package, e.g. a ``git worktree`` of HEAD).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

IR_SPLIT = 0.02


def select_patches(obj: np.ndarray, ir: np.ndarray, max_patches: int) -> np.ndarray:
    """Indices of at most ``max_patches`` object patches (obj ≥ 0): an equal share per object
    (what one object cannot fill goes to the others), within an object half from the patches
    with interreflection share ≤ 2 % and half from those above, each half evenly spaced over
    its patches sorted by share (the extremes included). Deterministic."""
    objects = [o for o in np.unique(obj) if o >= 0]
    counts = {o: int(np.sum(obj == o)) for o in objects}
    quota = {o: 0 for o in objects}
    left = max_patches
    while left > 0:
        open_ = [o for o in objects if quota[o] < counts[o]]
        if not open_:
            break
        for o in open_:
            if left == 0:
                break
            quota[o] += 1
            left -= 1
    chosen: list[int] = []
    for o in objects:
        idx = np.flatnonzero(obj == o)
        groups = [idx[ir[idx] <= IR_SPLIT], idx[ir[idx] > IR_SPLIT]]
        groups = [g[np.argsort(ir[g], kind="stable")] for g in groups]
        q = quota[o]
        take = [min(len(groups[0]), (q + 1) // 2), 0]
        take[1] = min(len(groups[1]), q - take[0])
        take[0] = min(len(groups[0]), q - take[1])
        for g, k in zip(groups, take, strict=True):
            if k > 0:
                pick = np.unique(np.round(np.linspace(0, len(g) - 1, k)).astype(int))
                chosen.extend(g[pick].tolist())
    return np.array(sorted(chosen), dtype=int)


def camera_rays(cam: Any, width: int, height: int, xy: np.ndarray) -> np.ndarray:
    """Unit world directions (N, 3) of the scene camera's rays through pixel coordinates
    ``xy`` (N, 2) (x right, y down; pixel (i, j)'s centre at (j + 0.5, i + 0.5))."""
    from spectral_fit.geometry import look_at

    x, y = xy[:, 0], xy[:, 1]
    if cam.intrinsics is not None:
        k = cam.intrinsics
        d = np.stack([(x - 0.5 - k["cx"]) / k["fx"], -(y - 0.5 - k["cy"]) / k["fy"],
                      -np.ones_like(x)], -1)
    else:
        ty = math.tan(math.radians(cam.fov_y_deg) / 2.0)
        d = np.stack([(2.0 * x / width - 1.0) * ty * width / height,
                      (1.0 - 2.0 * y / height) * ty, -np.ones_like(x)], -1)
    R = np.asarray(look_at(cam.position, cam.look_at, cam.up), np.float64)[:3, :3]
    d = d @ R
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def cast(scene: Any, origin: np.ndarray, dirs: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First hits of rays from ``origin`` against the scene's world meshes: object (N,)
    (−1 none, −2 a back face), point (N, 3), the shading normal (N, 3)."""
    from spectral_fit.fitting import cast_rays, scene_triangles
    from spectral_fit.geometry import build_bvh

    verts, norms, tris, tri_obj = scene_triangles(
        [ob.make_mesh(world=True) for ob in scene.objects])
    return cast_rays(build_bvh(verts, tris), origin, dirs, verts, norms, tris, tri_obj)


def _stats(x: np.ndarray) -> dict[str, Any]:
    x = np.asarray(x, np.float64)
    if x.size == 0:
        return {"n": 0}
    return {"n": int(x.size), "median": float(np.median(x)), "p90": float(np.percentile(x, 90)),
            "max": float(np.max(x))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", nargs="?", default="any_shape",
                    help="committed reference name (any_shape, four_objects, two_spheres, ...)")
    ap.add_argument("--max-patches", type=int, default=60)
    ap.add_argument("--field-scale", type=float, default=2 / math.sqrt(math.pi),
                    help="field angle / the patch's angular side (default: equal area)")
    ap.add_argument("--spot-resolution", type=int, default=8)
    ap.add_argument("--output", "-o", default=None, help="JSON file")
    ap.add_argument("--label", default="", help="a name for this run in the JSON/table")
    a = ap.parse_args(argv)

    import spectral_fit
    from spectral_fit.color import delta_e00, radiance_to_xyz, xyz_to_lab, xyz_weights
    from spectral_fit.fitting import FitOptions, simulate_readings
    from spectral_fit.geometry import look_at
    from spectral_fit.io import load_scene
    from spectral_fit.lighting import rotation_y, texel_directions, texel_solid_angles
    from spectral_fit.rendering import load_environment
    from spectral_fit.validation.reference import load_reference

    pkg = str(Path(spectral_fit.__file__).resolve().parent)
    print(f"spectral_fit from {pkg}")
    ref = load_reference(a.scene)
    cfg = Path(ref.config)
    if not cfg.is_absolute():
        cfg = Path(pkg).parent / cfg
    scene = load_scene(cfg)
    wl = np.asarray(scene.wavelengths, np.float64)
    wl_ref = np.asarray(ref.wavelengths, np.float64)
    names = list(ref.object_names)
    if names != [o.name for o in scene.objects]:
        raise SystemExit(f"reference objects {names} differ from the config's")
    W, H = (int(s) for s in ref.metadata.get("frame", (scene.width, scene.height)))
    if (W, H) != (scene.width, scene.height):
        raise SystemExit(f"reference frame {(W, H)} differs from the config's")

    obj_all = np.asarray(ref.object_index)
    ir_all = np.asarray(ref.ir_fraction, np.float64)
    sel = select_patches(obj_all, ir_all, a.max_patches)
    boxes = np.asarray(ref.boxes, np.float64)[sel]
    centre = np.stack([(boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2], -1)
    cam = scene.camera
    origin = np.asarray(cam.position, np.float64)
    dirs = camera_rays(cam, W, H, centre)
    hit_obj, pts, nrm = cast(scene, origin, dirs)
    # the patch's angular size: angles between the rays through its opposite edges
    def ang(p, q):
        d1, d2 = camera_rays(cam, W, H, p), camera_rays(cam, W, H, q)
        return np.degrees(np.arccos(np.clip(np.sum(d1 * d2, -1), -1, 1)))
    side = 0.5 * (ang(np.stack([boxes[:, 0], centre[:, 1]], -1),
                      np.stack([boxes[:, 2], centre[:, 1]], -1))
                  + ang(np.stack([centre[:, 0], boxes[:, 1]], -1),
                        np.stack([centre[:, 0], boxes[:, 3]], -1)))
    field = a.field_scale * side
    good = hit_obj == obj_all[sel]
    if not good.all():
        print(f"dropped {int((~good).sum())} patches whose centre ray misses their object: "
              f"{sel[~good].tolist()} (hit {hit_obj[~good].tolist()})")
    sel, pts, nrm, field, dirs = sel[good], pts[good], nrm[good], field[good], dirs[good]
    obj = obj_all[sel]
    ir = ir_all[sel]
    spots = [{"object": names[o], "aim": p.tolist(), "position": origin.tolist(),
              "field_angle_deg": float(f), "kind": "object"}
             for o, p, f in zip(obj, pts, field, strict=True)]
    print(f"{a.scene}: {len(sel)} of {len(obj_all)} patches "
          f"({', '.join(f'{n} {int(np.sum(obj == i))}' for i, n in enumerate(names))}; "
          f"share > 2 %: {int(np.sum(ir > IR_SPLIT))}); field {field.min():.3f}–"
          f"{field.max():.3f}°; mode {scene.interreflection.mode}")

    def resample(x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, np.float64)
        if wl_ref.size == wl.size and np.allclose(wl_ref, wl):
            return x
        return np.stack([np.interp(wl, wl_ref, r) for r in x])

    refs = {"auto": resample(np.asarray(ref.spectra, np.float64)[sel]),
            "none": resample(np.asarray(ref.direct, np.float64)[sel])}
    model: dict[str, np.ndarray] = {}
    times: dict[str, float] = {}
    for mode in ("auto", "none"):
        t0 = time.perf_counter()
        opts = FitOptions(interreflection=mode, spot_resolution=a.spot_resolution)
        model[mode] = np.asarray(simulate_readings(scene, spots, options=opts), np.float64)
        times[mode] = time.perf_counter() - t0
        print(f"  model ({mode}): {times[mode]:.1f} s")

    # scene white (as spectral-fit validate): a white Lambertian facing the camera
    env = np.asarray(load_environment(scene, wl), np.float64)
    xyz_map = env @ xyz_weights(wl)
    hm, wm, _ = xyz_map.shape
    nv = np.asarray(look_at(cam.position, cam.look_at, cam.up), np.float64)[2, :3]
    nmap = rotation_y(scene.environment.rotation_y_deg).T @ (nv / np.linalg.norm(nv))
    wgt = np.maximum(texel_directions(hm, wm) @ nmap, 0) * texel_solid_angles(hm, wm)
    white = np.einsum("hw,hwc->c", wgt, xyz_map) / math.pi

    ybar = xyz_weights(wl)[:, 1]
    res: dict[str, Any] = {}
    per_patch: dict[str, dict[str, list]] = {}
    for mode, target in (("auto", "depth16"), ("none", "depth2")):
        m, r = model[mode], refs[mode]
        lum = (m @ ybar) / (r @ ybar)
        with np.errstate(divide="ignore", invalid="ignore"):
            band = m / r
        band_mean = np.nanmean(band, 1)
        worst = band[np.arange(len(band)), np.nanargmax(np.abs(band - 1), 1)]
        de = np.asarray(delta_e00(xyz_to_lab(radiance_to_xyz(m, wl), white),
                                  xyz_to_lab(radiance_to_xyz(r, wl), white)))
        per_patch[mode] = {"lum_ratio": lum.tolist(), "band_mean_ratio": band_mean.tolist(),
                           "worst_band_ratio": worst.tolist(), "delta_e": de.tolist()}
        groups = {"all": np.ones(len(sel), bool), "share <= 2 %": ir <= IR_SPLIT,
                  "share > 2 %": ir > IR_SPLIT}
        groups.update({f"object {n}": obj == i for i, n in enumerate(names)})
        res[mode] = {"target": target, "groups": {
            g: {"lum": _stats(np.abs(lum[k] - 1)), "band_mean": _stats(np.abs(band_mean[k] - 1)),
                "worst_band": _stats(np.abs(worst[k] - 1)), "delta_e": _stats(de[k]),
                "mean_lum_ratio": float(np.mean(lum[k])) if k.any() else None}
            for g, k in groups.items()}}

    # model's own interreflection share vs the reference's
    y_auto, y_none = model["auto"] @ ybar, model["none"] @ ybar
    model_ir = (y_auto - y_none) / y_auto

    print(f"\n{a.label or a.scene}  (|ratio − 1| in %: median / p90 / max; ΔE00 likewise)")
    hdr = f"{'model vs ref':<18}{'group':<18}{'n':>4}  {'Y ratio':<20}{'band-mean':<20}" \
          f"{'worst band':<22}{'ΔE00':<18}{'mean Y ratio':>12}"
    print(hdr)
    for mode in ("auto", "none"):
        for g, s in res[mode]["groups"].items():
            if s["lum"]["n"] == 0:
                continue
            def f(d: dict, pct: bool = True) -> str:
                k = 100 if pct else 1
                return f"{k * d['median']:.2f}/{k * d['p90']:.2f}/{k * d['max']:.2f}"
            print(f"{mode + ' vs ' + res[mode]['target']:<18}{g:<18}{s['lum']['n']:>4}  "
                  f"{f(s['lum']):<20}{f(s['band_mean']):<20}{f(s['worst_band']):<22}"
                  f"{f(s['delta_e'], False):<18}{s['mean_lum_ratio']:>12.4f}")
    worst_idx = np.argsort(-np.abs(np.asarray(per_patch["auto"]["lum_ratio"]) - 1))[:8]
    print("\nlargest |Y ratio − 1| (auto vs depth 16):")
    print(f"{'patch':>6} {'object':<8} {'box x0,y0':<10} {'ref share':>9} {'model share':>11} "
          f"{'Y auto':>7} {'Y none':>7} {'ΔE auto':>7} {'n·view':>7}")
    view = origin[None] - pts
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    for k in worst_idx:
        b = np.asarray(ref.boxes)[sel[k]]
        print(f"{sel[k]:>6} {names[obj[k]]:<8} {f'{b[0]},{b[1]}':<10} {100 * ir[k]:>8.1f}% "
              f"{100 * model_ir[k]:>10.1f}% {per_patch['auto']['lum_ratio'][k]:>7.3f} "
              f"{per_patch['none']['lum_ratio'][k]:>7.3f} {per_patch['auto']['delta_e'][k]:>7.2f} "
              f"{float(np.sum(nrm[k] * view[k])):>7.2f}")

    out = {"scene": a.scene, "label": a.label, "package": pkg, "config": str(cfg),
           "mode": scene.interreflection.mode, "wavelengths": [float(wl[0]), float(wl[-1]),
                                                               int(wl.size)],
           "reference_wavelengths": [float(wl_ref[0]), float(wl_ref[-1]), int(wl_ref.size)],
           "field_scale": a.field_scale, "spot_resolution": a.spot_resolution,
           "model_seconds": times, "white_xyz": white.tolist(), "summary": res,
           "patches": {"index": sel.tolist(), "object": [names[o] for o in obj],
                       "box": np.asarray(ref.boxes)[sel].tolist(),
                       "ref_ir_share": ir.tolist(), "model_ir_share": model_ir.tolist(),
                       "aim": pts.tolist(), "normal": nrm.tolist(),
                       "field_angle_deg": field.tolist(), **{
                           f"{mode}_{k}": v for mode in per_patch
                           for k, v in per_patch[mode].items()}}}
    if a.output:
        from spectral_fit._runtime.fileio import atomic_write_text

        os.makedirs(os.path.dirname(os.path.abspath(a.output)), exist_ok=True)
        atomic_write_text(a.output, json.dumps(out, indent=1) + "\n")
        print(f"\nwrote {a.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
