"""Render the committed references (measurements/reference/) with Mitsuba 3.

    python scripts/make_references.py                       # everything, default settings
    python scripts/make_references.py --only benchmark --spp 64 --passes 2 --out /tmp/ref
    python scripts/make_references.py --only flat_faces --cache out/reference_renders
    python scripts/make_references.py --only any_shape \
        --reuse any_shape=/tmp/asr720/mitsuba.npz           # a render of any_shape_reference.py

Sphere configs (benchmark, two_spheres): patches tiling the exact spheres
(:func:`~spectral_fit.validation.reference.make_reference`). Scenes of any shape (any_shape,
on_table, flat_faces, four_objects, parts): the frame's 5×5 patch grid, kept where a patch and a
one-pixel border around it show one object (our rasteriser's object ids, the same meshes) or,
with a ``[[surfaces]]`` table, the table within 2 bounding radii of an object
(:func:`~spectral_fit.validation.reference.make_mesh_reference`); their renders are kept in
``--cache`` (per-pass patch means of the whole grid) and reused when the config, meshes and
settings are unchanged. ``--reuse NAME=FILE`` takes the render of scripts/any_shape_reference.py
(``mitsuba.npz``) or scripts/table_reference.py (``table_mitsuba.npz``) instead, after checking
its settings against this run's.

Each config is rendered at path depths 2 and 16 with the band trick (see
spectral_fit/validation/reference/render.py) and reduced to per-patch mean spectra; writes
<name>.npz,
<name>.png (preview with patch outlines) and <name>.json (summary) per config, and the simulated
SR-3A session of two_spheres in <out>/sr3a_two_spheres (session.toml, CSV files, truth.json).
The Mitsuba variant comes from SPECTRAL_FIT_MI_VARIANT or is chosen automatically
(spectral_fit/validation/reference/backend.py). The defaults reproduce the committed files.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CONFIGS = {"benchmark": "configs/benchmark.toml", "two_spheres": "configs/two_spheres.toml"}
#: samples per pixel per pass of the committed references (8 passes each)
DEFAULT_SPP = {"benchmark": 512, "two_spheres": 256}
#: scenes of any shape: config, samples per pixel per pass and passes (the first 4 passes of
#: any_shape and on_table are those of their scripts' renders)
MESH_CONFIGS = {"any_shape": "configs/any_shape.toml", "on_table": "configs/on_table.toml",
                "flat_faces": "configs/flat_faces.toml",
                "four_objects": "configs/four_objects.toml", "parts": "configs/parts.toml",
                "sun_shadow": "configs/sun_shadow.toml"}
MESH_SPP = {"any_shape": 64, "on_table": 64, "flat_faces": 128, "four_objects": 128,
            "parts": 128, "sun_shadow": 128}
MESH_PASSES = {"any_shape": 16, "on_table": 8, "flat_faces": 8, "four_objects": 8, "parts": 8,
               "sun_shadow": 4}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", choices=[*sorted(CONFIGS), *MESH_CONFIGS, "session"],
                    action="append", help="what to make (repeatable; default: everything)")
    ap.add_argument("--spp", type=int, help="samples per pixel per pass (default: "
                    f"{DEFAULT_SPP | MESH_SPP})")
    ap.add_argument("--passes", type=int, help="independent passes (noise estimate; default 8 "
                    f"for spheres, {MESH_PASSES} for the other scenes)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", type=int, nargs=2, metavar=("W", "H"),
                    help="override the frame size (smoke runs)")
    ap.add_argument("--bands", type=float, nargs=3, metavar=("START", "END", "STEP"),
                    help="override the spectral grid (smoke runs)")
    ap.add_argument("--threshold", type=float, default=0.05)
    ap.add_argument("--out", type=Path, default=REPO / "measurements" / "reference")
    ap.add_argument("--session-spp", type=int, default=2048)
    ap.add_argument("--cache", type=Path, default=REPO / "out" / "reference_renders",
                    help="renders of the scenes of any shape (reused when unchanged)")
    ap.add_argument("--reuse", action="append", default=[], metavar="NAME=FILE",
                    help="take NAME's render from FILE (mitsuba.npz of "
                    "scripts/any_shape_reference.py or table_mitsuba.npz of "
                    "scripts/table_reference.py) when its settings match")
    ap.add_argument("--render-only", action="store_true",
                    help="scenes of any shape: fill the render cache, write nothing else")
    args = ap.parse_args(argv)
    reuse = dict(r.split("=", 1) for r in args.reuse)

    sys.path.insert(0, str(REPO))
    from spectral_fit._runtime.fileio import atomic_write_text
    from spectral_fit.io import load_scene
    from spectral_fit.validation.reference.data import save_reference
    from spectral_fit.validation.reference.generate import (
        make_mesh_reference,
        make_reference,
        preview_png,
        raster_patches,
    )

    def write(ref, out: Path, name: str) -> None:
        save_reference(out / f"{name}.npz", ref)
        preview_png(ref, out / f"{name}.png")
        summary = dict(ref.metadata, name=name, config=ref.config, patches=ref.num_patches,
                       bands=int(ref.wavelengths.size))
        atomic_write_text(out / f"{name}.json", json.dumps(summary, indent=2, sort_keys=True)
                          + "\n")
        print(json.dumps(summary, sort_keys=True), flush=True)

    def overrides(d: dict) -> None:
        if args.size:
            d.setdefault("frame", {}).update(width=args.size[0], height=args.size[1])
        if args.bands:
            d.setdefault("spectral", {}).update(start_nm=args.bands[0], end_nm=args.bands[1],
                                                step_nm=args.bands[2])

    todo = args.only or [*sorted(CONFIGS), *MESH_CONFIGS, "session"]
    for name in [n for n in todo if n in MESH_CONFIGS]:
        scene = load_scene(REPO / MESH_CONFIGS[name], overrides)
        spp, passes = args.spp or MESH_SPP[name], args.passes or MESH_PASSES[name]
        pt = raster_patches(scene)
        render = mesh_render(name, scene, pt, spp=spp, passes=passes, seed=args.seed,
                             cache=args.cache, reuse=reuse.get(name), bands=args.bands)
        if args.render_only:
            continue
        ref = make_mesh_reference(scene, name, pt, render, spp=spp, passes=passes,
                                  seed=args.seed)
        write(ref, args.out, name)
    for name in [n for n in todo if n in CONFIGS]:
        scene = load_scene(REPO / CONFIGS[name], overrides)
        ref = make_reference(scene, name, spp=args.spp or DEFAULT_SPP[name],
                             passes=args.passes or 8, seed=args.seed,
                             threshold=args.threshold,
                             progress=lambda s, n=name: print(f"[{n}] {s}", flush=True))
        write(ref, args.out, name)
    if "session" in todo:  # the simulated SR-3A session of two_spheres
        from spectral_fit.validation.reference.instrument import simulate_readings

        scene = load_scene(REPO / CONFIGS["two_spheres"], overrides)
        folder = args.out / "sr3a_two_spheres"
        white = {"position": [0.0, 0.0, -0.275], "normal": [0.0, 0.0, 1.0],
                 "reflectance": 0.99}
        m = simulate_readings(scene, folder, spp=args.session_spp, seed=args.seed, white=white,
                              progress=lambda s: print(f"[session] {s}", flush=True))
        print(f"session written: {m}", flush=True)
    return 0


def render_key(scene, spp: int, seed: int) -> str:
    """Digest of what a render's passes depend on: the config's text, its mesh files, the
    frame, bands, samples per pass and first seed (not the number of passes)."""
    import hashlib

    h = hashlib.sha256()
    h.update(Path(scene.path).read_bytes())
    for o in scene.objects:
        if o.mesh is not None:
            h.update(Path(o.mesh).read_bytes())
    h.update(json.dumps([scene.width, scene.height, scene.wavelengths.tolist(), spp,
                         seed]).encode())
    return h.hexdigest()


def _reused(scene, reuse: str, *, spp: int, seed: int, bands) -> dict:
    """A render of scripts/any_shape_reference.py or scripts/table_reference.py as
    ``render_grid``'s dict, after checking its settings against this run's."""
    import numpy as np

    from spectral_fit.color import xyz_weights
    from spectral_fit.validation.reference.patches import grid_means

    with np.load(reuse) as z:
        arrays = {k: z[k] for k in z.files}
    old = str(arrays["key"])
    text = Path(scene.path).read_text()
    if "full" in arrays:  # scripts/any_shape_reference.py: config|size|bands|spp|passes
        full = arrays["full"]  # (depths 2 and 16, passes, H, W, L)
        k = full.shape[1]
        want = f"{[scene.width, scene.height]}|{bands}|{spp}|{k}"
        if old.split("|", 1)[1] != want or seed != 0:
            raise SystemExit(f"{reuse}: settings {old!r} differ from {want!r}")
        src = Path(old.split("|", 1)[0])  # its key has the config's path, not its text
        if not src.is_file() or src.read_text() != text:
            raise SystemExit(f"{reuse}: rendered from {src}, whose text differs from "
                             f"{scene.path}'s")
        grid = np.stack([np.stack([grid_means(full[d, p]) for p in range(k)])
                         for d in (0, 1)])
        return {"grid": grid.astype(np.float32),
                "xyz16": (full[1].mean(0) @ xyz_weights(scene.wavelengths)).astype(np.float32),
                "seconds": float("nan"), "variant": "", "source": f"reused {Path(reuse).name}"}
    k = json.loads(old)  # scripts/table_reference.py: grid (depth 16, depth 2, surfaces alone)
    mine = {"text": text, "size": [scene.width, scene.height], "bands": bands, "spp": spp,
            "seed": seed, "table_size": 20.0}
    diff = sorted(f for f, v in mine.items() if k.get(f) != v)
    if diff:
        raise SystemExit(f"{reuse}: settings differ from this run's in {diff}")
    g = arrays["grid"]
    return {"grid": np.stack([g[1], g[0]]).astype(np.float32),
            "xyz16": arrays["xyz16"].astype(np.float32), "seconds": float(arrays["seconds"]),
            "variant": str(arrays["variant"]), "source": f"reused {Path(reuse).name}"}


def _render_passes(name: str, scene, pt: dict, *, spp: int, passes: int, seed: int) -> dict:
    """``passes`` new passes (seeds ``seed`` …) as ``render_grid``'s dict; a scene with
    ``[[surfaces]]`` through scripts/table_reference.py's renderer (the table as a 20 m square;
    depth 16 over the kept patches' window, depth 2 over the objects' window with 8 pixels of
    margin, as that script)."""
    import numpy as np

    from spectral_fit.validation.reference.export import Crop
    from spectral_fit.validation.reference.generate import render_grid
    from spectral_fit.validation.reference.patches import TABLE

    log = lambda s: print(f"[{name}] {s}", flush=True)  # noqa: E731
    if not getattr(scene, "surfaces", ()):
        return render_grid(scene, pt["crop"], spp=spp, passes=passes, seed=seed, progress=log)
    import dataclasses
    import importlib.util

    spec = importlib.util.spec_from_file_location("table_reference",
                                                  REPO / "scripts" / "table_reference.py")
    tr = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tr)
    surfaces = [{"name": s.name, "point": np.asarray(s.point, np.float64),
                 "normal": np.asarray(s.normal, np.float64),
                 "reflectance": np.asarray(s.reflectance, np.float64)} for s in scene.surfaces]
    obj, h, w = pt["object_id"], scene.height, scene.width
    rows, cols = np.nonzero(obj >= 0)
    x0, y0 = max(int(cols.min()) - 8, 0), max(int(rows.min()) - 8, 0)
    x1, y1 = min(int(cols.max()) + 9, w), min(int(rows.max()) + 9, h)
    keep = (pt["owner"] >= 0) | ((pt["owner"] == TABLE) & (pt["near"] >= 0))
    b = pt["boxes"][keep]
    c16 = Crop(int(b[:, 0].min()), int(b[:, 1].min()), int(b[:, 2].max() - b[:, 0].min()),
               int(b[:, 3].max() - b[:, 1].min()))
    r = tr.render_reference(dataclasses.replace(scene, surfaces=()), surfaces, spp=spp,
                            passes=passes, half=10.0, crop2=Crop(x0, y0, x1 - x0, y1 - y0),
                            seed=seed, progress=log, crop16=c16, surfaces_alone=False)
    return {"grid": np.stack([r["grid"][1], r["grid"][0]]), "xyz16": r["xyz16"],
            "seconds": r["seconds"], "variant": r["variant"]}


def mesh_render(name: str, scene, pt: dict, *, spp: int, passes: int, seed: int, cache: Path,
                reuse: str | None, bands) -> dict:
    """The scene's depth-2 and depth-16 patch grid over ``passes`` passes (``render_grid``'s
    dict plus ``source``): the passes already in ``cache`` (same key) or in ``reuse`` (after
    checking its settings), and the missing ones rendered now (seeds continuing theirs); the
    result is cached."""
    import io

    import numpy as np

    from spectral_fit._runtime.fileio import atomic_write_bytes

    key = render_key(scene, spp, seed)
    path = cache / f"{name}.npz"
    have = None
    if path.is_file():
        with np.load(path) as z:
            if str(z["key"]) == key:
                have = {k: z[k] for k in ("grid", "xyz16")} | {
                    "seconds": float(z["seconds"]), "variant": str(z["variant"]),
                    "source": str(z["source"])}
                print(f"[{name}] {have['grid'].shape[1]} passes in {path}", flush=True)
    if have is None and reuse:
        have = _reused(scene, reuse, spp=spp, seed=seed, bands=bands)
    k0 = 0 if have is None else have["grid"].shape[1]
    if k0 >= passes:
        have["grid"] = have["grid"][:, :passes]
        return have
    new = _render_passes(name, scene, pt, spp=spp, passes=passes - k0, seed=seed + k0)
    if have is None:
        out = dict(new, source="rendered by scripts/make_references.py")
    else:
        out = {"grid": np.concatenate([have["grid"], new["grid"]], axis=1),
               "xyz16": have["xyz16"],
               "seconds": have["seconds"] + new["seconds"],
               "variant": have["variant"] or f"{new['variant']} (passes {k0}-{passes - 1}; "
                                             f"passes 0-{k0 - 1} not recorded)",
               "source": f"{have['source']} (passes 0-{k0 - 1}; time not recorded) + "
                         f"passes {k0}-{passes - 1} rendered by scripts/make_references.py"
                         if not np.isfinite(have["seconds"]) else
                         f"{have['source']} (passes 0-{k0 - 1}) + passes {k0}-{passes - 1} "
                         "rendered by scripts/make_references.py"}
        if not np.isfinite(have["seconds"]):
            out["seconds"] = new["seconds"]
    buf = io.BytesIO()
    np.savez_compressed(buf, key=key, **out)
    atomic_write_bytes(path, buf.getvalue())
    return out


if __name__ == "__main__":
    sys.exit(main())
