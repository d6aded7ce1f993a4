"""``spectral-fit view``: show a spectral (or RGB) OpenEXR image as a display PNG."""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

HELP = "convert a spectral or RGB OpenEXR image to an sRGB display PNG and print its statistics"

#: Default exposure: Reinhard et al. (2002) photographic key. The log-average luminance maps to
#: KEY of display white, i.e. exposure_luminance = log-average / KEY.
KEY = 0.18


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", help="spectral OpenEXR (Fichet 2021 layout) or RGB OpenEXR")
    p.add_argument("-o", "--output", required=True, help="output PNG path")
    p.add_argument("--exposure", type=float, default=None,
                   help="scene luminance (cd/m2 for absolute spectral images) shown as display "
                   "white; default: log-average luminance / 0.18 (Reinhard's key value)")
    p.add_argument("--kind", choices=("emissive", "reflective"), default=None,
                   help="which spectral channels to use when a file has both")
    p.add_argument("--json", action="store_true", help="print the statistics as JSON on stdout")


def _stats(y: Any) -> dict:
    import numpy as np

    return {
        "min": float(y.min()), "median": float(np.median(y)), "mean": float(y.mean()),
        "p99": float(np.percentile(y, 99.0)), "max": float(y.max()),
    }


def run(args: argparse.Namespace) -> int:
    import numpy as np
    from PIL import Image

    from ..._runtime.errors import InputError
    from ..._runtime.fileio import atomic_path, check_suffix
    from ...color import illuminant, radiance_to_xyz, reflectance_to_xyz, to_display
    from ...io import read_rgb_exr, read_spectral_exr_ex

    check_suffix(args.output, (".png",), "--output", "--output writes PNG")
    info: dict = {"file": str(args.file)}
    try:
        img = read_spectral_exr_ex(args.file, kind=args.kind)
    except InputError as exc:
        if "no spectral channels" not in str(exc):
            raise
        import colour

        rgb = read_rgb_exr(args.file).astype(np.float64)
        xyz = np.asarray(colour.RGB_to_XYZ(rgb, "sRGB", chromatic_adaptation_transform=None))
        info.update(kind="rgb", units="relative (linear sRGB)")
    else:
        wl = img.wavelengths
        if img.kind == "emissive":
            xyz = radiance_to_xyz(img.image, wl)
            units = "cd/m2"
        else:
            xyz = reflectance_to_xyz(img.image, illuminant("D65", wl), wl) / 100.0
            units = "relative (reflectance under D65, white = 1)"
        info.update(kind=img.kind, units=units, bands=int(wl.size),
                    wavelength_range_nm=[float(wl[0]), float(wl[-1])])
    h, w = xyz.shape[:2]
    y = xyz[..., 1]
    info.update(width=int(w), height=int(h), luminance=_stats(y))
    if args.exposure is not None:
        if not (math.isfinite(args.exposure) and args.exposure > 0):
            raise InputError(f"must be finite and > 0, got {args.exposure}", field="--exposure")
        exposure = float(args.exposure)
    else:
        floor = max(float(y.max()) * 1e-6, 1e-12)
        log_avg = float(np.exp(np.mean(np.log(np.maximum(y, floor)))))
        exposure = log_avg / KEY if log_avg > 0 else 1.0
    out = to_display(xyz, exposure_luminance=exposure)
    info.update(exposure_luminance=exposure,
                out_of_gamut_fraction=float(out.out_of_gamut_fraction),
                output=str(args.output))
    pixels = np.clip(np.rint(np.asarray(out.rgb) * 255.0), 0, 255).astype(np.uint8)
    with atomic_path(args.output, suffix=".png") as tmp:
        Image.fromarray(pixels, mode="RGB").save(tmp, format="PNG")
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        lum = info["luminance"]
        rng = info.get("wavelength_range_nm")
        print(f"{args.file}: {w} x {h}, {info['kind']}"
              + (f", {info['bands']} bands {rng[0]:g}-{rng[1]:g} nm" if rng else ""))
        print(f"luminance ({info['units']}): min {lum['min']:.4g}  median {lum['median']:.4g}  "
              f"mean {lum['mean']:.4g}  p99 {lum['p99']:.4g}  max {lum['max']:.4g}")
        print(f"exposure {exposure:.4g} -> display white; out of gamut "
              f"{info['out_of_gamut_fraction']:.3%}; wrote {args.output}")
    return 0
