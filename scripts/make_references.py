"""Render the committed references (measurements/reference/) with Mitsuba 3.

    python scripts/make_references.py                       # both configs, default settings
    python scripts/make_references.py --only benchmark --spp 64 --passes 2 --out /tmp/ref

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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", choices=[*sorted(CONFIGS), "session"], action="append",
                    help="what to make (repeatable; default: everything)")
    ap.add_argument("--spp", type=int, help="samples per pixel per pass (default: "
                    f"{DEFAULT_SPP})")
    ap.add_argument("--passes", type=int, default=8, help="independent passes (noise estimate)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", type=int, nargs=2, metavar=("W", "H"),
                    help="override the frame size (smoke runs)")
    ap.add_argument("--bands", type=float, nargs=3, metavar=("START", "END", "STEP"),
                    help="override the spectral grid (smoke runs)")
    ap.add_argument("--threshold", type=float, default=0.05)
    ap.add_argument("--out", type=Path, default=REPO / "measurements" / "reference")
    ap.add_argument("--session-spp", type=int, default=2048)
    args = ap.parse_args(argv)

    sys.path.insert(0, str(REPO))
    from spectral_fit._runtime.fileio import atomic_write_text
    from spectral_fit.io import load_scene
    from spectral_fit.validation.reference.data import save_reference
    from spectral_fit.validation.reference.generate import make_reference, preview_png

    def overrides(d: dict) -> None:
        if args.size:
            d.setdefault("frame", {}).update(width=args.size[0], height=args.size[1])
        if args.bands:
            d.setdefault("spectral", {}).update(start_nm=args.bands[0], end_nm=args.bands[1],
                                                step_nm=args.bands[2])

    todo = args.only or [*sorted(CONFIGS), "session"]
    for name in [n for n in todo if n in CONFIGS]:
        scene = load_scene(REPO / CONFIGS[name], overrides)
        ref = make_reference(scene, name, spp=args.spp or DEFAULT_SPP[name],
                             passes=args.passes, seed=args.seed,
                             threshold=args.threshold,
                             progress=lambda s, n=name: print(f"[{n}] {s}", flush=True))
        out = args.out
        save_reference(out / f"{name}.npz", ref)
        preview_png(ref, out / f"{name}.png")
        summary = dict(ref.metadata, name=name, config=ref.config, patches=ref.num_patches,
                       bands=int(ref.wavelengths.size))
        atomic_write_text(out / f"{name}.json", json.dumps(summary, indent=2, sort_keys=True)
                          + "\n")
        print(json.dumps(summary, sort_keys=True), flush=True)
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


if __name__ == "__main__":
    sys.exit(main())
