"""``spectral-fit make-env``: write the synthetic spectral environment map."""

from __future__ import annotations

import argparse
import json

HELP = "write the synthetic studio-room spectral environment map (spectral OpenEXR)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", required=True, help="output .exr path")
    p.add_argument("--width", type=int, default=256, help="map width (default 256)")
    p.add_argument("--height", type=int, default=128, help="map height (default 128)")
    p.add_argument("--supersampling", type=int, default=4,
                   help="n x n sub-samples per texel (default 4)")
    p.add_argument("--pixel-type", choices=("float", "half"), default="half",
                   help="EXR pixel type (default half: the bundled file is half to stay small)")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..._runtime.fileio import check_suffix
    from ...color import radiance_to_xyz
    from ...io import write_spectral_exr
    from ...lighting import make_environment

    check_suffix(args.output, (".exr",), "--output", "--output writes EXR")
    wl, image = make_environment(args.width, args.height, supersampling=args.supersampling)
    write_spectral_exr(args.output, wl, image, pixel_type=args.pixel_type,
                       comment="synthetic environment map made by spectral-fit make-env "
                       "from colour-science measured spectra (spectral_fit.lighting)")
    y = radiance_to_xyz(image, wl)[..., 1]
    summary = {
        "output": str(args.output),
        "width": int(image.shape[1]),
        "height": int(image.shape[0]),
        "bands": int(wl.size),
        "wavelength_range_nm": [float(wl[0]), float(wl[-1])],
        "luminance_median_cd_m2": float(np.median(y)),
        "luminance_max_cd_m2": float(y.max()),
    }
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f"wrote {args.output}: {image.shape[1]} x {image.shape[0]}, {wl.size} bands "
              f"{wl[0]:g}-{wl[-1]:g} nm, luminance median {summary['luminance_median_cd_m2']:.4g}"
              f" max {summary['luminance_max_cd_m2']:.4g} cd/m2")
    return 0
