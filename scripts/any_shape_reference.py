"""Compare frames of a scene with non-convex objects (default configs/any_shape.toml) with the
Mitsuba path tracer rendering our whole model as one BSDF, per 5×5-pixel patch.

    python scripts/any_shape_reference.py --size 360 240 --spp 64 --passes 4 --out /tmp/any_ref

Patches: 5×5 squares of the frame grid whose pixels, and a one-pixel border around them, all
show one object in our raster. Regions from the reference alone: the interreflection share
(Y₁₆ − Y₂)/Y₁₆ of its depth-16 and depth-2 renders below or above 2 %. Our frames: modes
"none" and "gather", with and without the objects' self-visibility. Writes
``<out>/any_shape.json`` (ΔE00 statistics per frame and region), ``<out>/any_shape_de.png``
(false-colour ΔE00 per patch) and keeps the path-traced patch means in ``<out>/mitsuba.npz``
(reused by a later run with the same settings; ``--fresh`` renders again).
"""

from __future__ import annotations

import argparse
import json
import sys
import types
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, default=REPO / "configs" / "any_shape.toml")
    ap.add_argument("--size", type=int, nargs=2, default=(360, 240), metavar=("W", "H"))
    ap.add_argument("--bands", type=float, nargs=3, metavar=("START", "END", "STEP"))
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--passes", type=int, default=4)
    ap.add_argument("--threshold", type=float, default=0.02)
    ap.add_argument("--out", type=Path, default=Path("out/any_shape_reference"))
    ap.add_argument("--fresh", action="store_true")
    args = ap.parse_args(argv)

    sys.path.insert(0, str(REPO))
    import jax

    from spectral_fit._runtime.fileio import atomic_write_text
    from spectral_fit.color import radiance_to_xyz, xyz_weights
    from spectral_fit.io import load_scene
    from spectral_fit.rendering import load_environment, prepare, render_frame
    from spectral_fit.validation import delta_e_figure, delta_e_patches, scene_white_xyz

    def overrides(d: dict) -> None:
        d.setdefault("frame", {}).update(width=args.size[0], height=args.size[1])
        if args.bands:
            d.setdefault("spectral", {}).update(start_nm=args.bands[0], end_nm=args.bands[1],
                                                step_nm=args.bands[2])

    scene = load_scene(args.config, overrides)
    wl = scene.wavelengths
    args.out.mkdir(parents=True, exist_ok=True)

    variants = {"none": dict(mode="none"), "gather": dict(mode="gather"),
                "none, no self-visibility": dict(mode="none", occlusion=False),
                "gather, no self-visibility": dict(mode="gather", occlusion=False)}
    spectra, rgbs, obj = {}, {}, None
    view = None
    for name, kw in variants.items():
        prep = prepare(scene, **kw)
        f = jax.block_until_ready(render_frame(prep, spectral=True))
        spectra[name] = np.asarray(f.spectral, np.float64)
        rgbs[name] = np.asarray(f.rgb)
        obj = np.asarray(f.object_id) if obj is None else obj
        view = np.asarray(prep.camera.view)
        print(f"[ours] {name}", flush=True)

    # patches: 5×5 grid squares inside one object, with a one-pixel border of the same object
    h, w = obj.shape
    boxes, owner = [], []
    for y in range(1, h - 6, 5):
        for x in range(1, w - 6, 5):
            win = obj[y - 1:y + 6, x - 1:x + 6]
            if win.min() >= 0 and win.min() == win.max():
                boxes.append((x, y, x + 5, y + 5))
                owner.append(int(win[0, 0]))
    boxes = np.asarray(boxes, np.int32)
    rows, cols = np.nonzero(obj >= 0)
    x0, y0 = max(int(cols.min()) - 4, 0), max(int(rows.min()) - 4, 0)
    x1, y1 = min(int(cols.max()) + 5, w), min(int(rows.max()) + 5, h)

    cache = args.out / "mitsuba.npz"
    key = f"{args.config.resolve()}|{args.size}|{args.bands}|{args.spp}|{args.passes}"
    if cache.exists() and not args.fresh and str(np.load(cache)["key"]) == key:
        full = np.load(cache)["full"]
        print("[mitsuba] reused", cache, flush=True)
    else:
        from spectral_fit.validation.reference import render_spectral
        from spectral_fit.validation.reference.export import Crop

        r = render_spectral(scene, spp=args.spp, passes=args.passes, depths=(2, 16),
                            crop=Crop(x0, y0, x1 - x0, y1 - y0),
                            progress=lambda s: print(f"[mitsuba] {s}", flush=True))
        full = np.zeros((2, r.passes.shape[1], h, w, wl.size), np.float32)
        full[:, :, y0:y1, x0:x1] = r.passes
        np.savez_compressed(cache, full=full, key=key)

    def patch_means(img: np.ndarray) -> np.ndarray:
        return np.stack([img[b[1]:b[3], b[0]:b[2]].reshape(-1, img.shape[-1]).mean(0)
                         for b in boxes])

    ref16 = patch_means(full[1].mean(0))
    ref2 = patch_means(full[0].mean(0))
    wy = xyz_weights(wl)[:, 1]
    share = (ref16 @ wy - ref2 @ wy) / np.maximum(ref16 @ wy, 1e-30)
    high = share > args.threshold
    env = load_environment(scene, wl)
    white = scene_white_xyz(env @ xyz_weights(wl), scene.environment.rotation_y_deg, view[2, :3])
    xyz_ref = radiance_to_xyz(ref16, wl)

    def stats(d: np.ndarray) -> dict:
        if d.size == 0:
            return {"n": 0}
        return {"n": int(d.size), "median": float(np.median(d)),
                "p90": float(np.percentile(d, 90)), "max": float(d.max())}

    out = {"config": str(args.config), "size": list(args.size), "spp": args.spp,
           "passes": args.passes, "patches": int(len(boxes)),
           "interreflection_patches": int(high.sum()), "threshold": args.threshold,
           "frames": {}}
    de_by = {}
    for name, spec in spectra.items():
        de = delta_e_patches(radiance_to_xyz(patch_means(spec), wl), xyz_ref, white)
        de_by[name] = de
        out["frames"][name] = {"interreflection < 2 %": stats(de[~high]),
                               "interreflection > 2 %": stats(de[high]),
                               "per object": {o.name: stats(de[np.asarray(owner) == i])
                                              for i, o in enumerate(scene.objects)}}
        if name.startswith("none"):  # the direct term alone, against the depth-2 render
            de2 = delta_e_patches(radiance_to_xyz(patch_means(spec), wl),
                                  radiance_to_xyz(ref2, wl), white)
            out["frames"][name]["vs single bounce"] = stats(de2)
            de_by[name + " vs single bounce"] = de2
    atomic_write_text(args.out / "any_shape.json", json.dumps(out, indent=2) + "\n")
    np.savez_compressed(args.out / "patches.npz", boxes=boxes, owner=np.asarray(owner),
                        share=share, ref16=ref16, ref2=ref2,
                        **{f"de_{k}": v for k, v in de_by.items()},
                        **{f"ours_{k}": patch_means(v) for k, v in spectra.items()})
    de_by = {k: v for k, v in de_by.items() if k in rgbs}
    ref_view = types.SimpleNamespace(boxes=boxes, labels=np.where(high, "interreflection",
                                                                  "direct"),
                                     metadata={"crop": (x0, y0, x1 - x0, y1 - y0)})
    delta_e_figure(args.out / "any_shape_de.png", ref_view, rgbs, de_by)
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
