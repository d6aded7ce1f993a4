"""``spectral-fit demo``: the main job on the bundled data, end to end."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

HELP = "run the demo on the bundled data (environment, render, fit) and write pictures + JSON"

ROOT = Path(__file__).resolve().parent.parent.parent
ENVIRONMENT = ROOT / "measurements" / "environment" / "studio_room.exr"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--json", action="store_true", help="print the summary JSON on stdout")


def _say(msg: str) -> None:
    print(f"demo: {msg}", file=sys.stderr, flush=True)


def environment_step(out: Path) -> dict:
    """Show the bundled spectral environment: a display image and the chromaticities of its
    texels on the CIE 1931 diagram."""
    import numpy as np

    from ..colorimetry import radiance_to_xyz, xyz_to_xy
    from ..display import to_display
    from ..exr import read_spectral_exr
    from ..plots import chromaticity_diagram, save_png

    wl, img = read_spectral_exr(ENVIRONMENT)
    xyz = radiance_to_xyz(img.astype(np.float64), wl)
    y = xyz[..., 1]
    exposure = float(np.exp(np.mean(np.log(np.maximum(y, 1e-9)))) / 0.18)
    disp = to_display(xyz, exposure_luminance=exposure)
    save_png(out / "environment.png", disp.rgb)
    xy = xyz_to_xy(xyz.reshape(-1, 3))
    chromaticity_diagram(out / "environment_chromaticity.png", {"environment texels": xy[::7]},
                         title="Bundled environment: texel chromaticities", markers={
                             "environment texels": "."})
    return {
        "file": str(ENVIRONMENT),
        "size": [int(img.shape[1]), int(img.shape[0])],
        "bands": int(wl.size),
        "luminance_cd_m2": {"median": float(np.median(y)), "max": float(y.max())},
        "exposure_luminance": exposure,
        "out_of_gamut_fraction": float(disp.out_of_gamut_fraction),
        "pictures": ["environment.png", "environment_chromaticity.png"],
    }


def run(args: argparse.Namespace) -> int:
    from ..fileio import atomic_write_text

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    summary: dict = {"output": str(out)}
    t0 = time.perf_counter()
    _say("environment map ...")
    summary["environment"] = environment_step(out)
    summary["seconds"] = time.perf_counter() - t0
    text = json.dumps(summary, indent=2)
    atomic_write_text(out / "summary.json", text + "\n")
    if args.json:
        print(text)
    else:
        _say(f"done in {summary['seconds']:.1f} s; pictures and summary.json in {out}/")
    return 0
