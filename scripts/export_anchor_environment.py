"""Write the benchmark environment map (docs/benchmark.md) as a spectral EXR for benchmark.toml.

The map is made by ``make_env`` of the OpenGL anchor's ``scene.py``, an external measuring stick
that is not part of this repository; pass the folder that holds it. This script only calls it and
stores its output, so that the benchmark config and the reference renders use exactly the
anchor's pixels: 256×128, 31 bands 400–700 nm, relative radiance (sky zenith luminance 1 in the
anchor's units), forward direction −Z at the image centre (the config rotates it by 180° about
+Y). The result is committed as ``measurements/benchmark/anchor_environment.exr``, so nothing
else needs the anchor.

Usage: python scripts/export_anchor_environment.py ANCHOR_DIR [-o OUT.exr]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def load_anchor(anchor_dir: Path):
    spec = importlib.util.spec_from_file_location("anchor_scene", anchor_dir / "scene.py")
    if spec is None or spec.loader is None:
        sys.exit(f"no scene.py in {anchor_dir}")
    module = importlib.util.module_from_spec(spec)
    os.environ.setdefault("ANCHOR_OUT", str(Path(os.environ.get("TMPDIR", "/tmp")) / "anchor"))
    spec.loader.exec_module(module)
    return module


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("anchor_dir", help="folder with the anchor's scene.py")
    ap.add_argument("-o", "--output",
                    default=str(HERE.parent / "measurements" / "benchmark" /
                                "anchor_environment.exr"))
    args = ap.parse_args()
    from spectral_fit.io import write_spectral_exr

    anchor = load_anchor(Path(args.anchor_dir))
    env = np.asarray(anchor.make_env(), dtype=np.float32)  # (128, 256, 31)
    write_spectral_exr(args.output, np.asarray(anchor.WL, dtype=np.float64), env)
    print(f"wrote {args.output}: {env.shape}, {anchor.WL[0]:g}–{anchor.WL[-1]:g} nm")


if __name__ == "__main__":
    main()
