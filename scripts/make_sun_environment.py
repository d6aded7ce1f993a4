"""Write the bundled sunny environment map, ``measurements/environment/sunny.exr``: a sky
with a small sun that carries most of the light, for scenes where a bright source casts the
shadow of one object on another (``configs/sun_shadow.toml``).

    python scripts/make_sun_environment.py [--out measurements/environment/sunny.exr]

The map is :func:`spectral_fit.lighting.synthetic_environment` (CIE D65 / 10,000 K sky over a
checkered floor; its "lamp" disc of CIE illuminant A made a sun here): 128 × 256 texels, 31
bands 400–700 nm, the disc 1.5° in radius, 20° above the horizon, 3000 × the sky's mean
luminance (on a face turned to it, twice the light of the whole sky), 4 × 4 sub-samples per
texel. Deterministic; half-float pixels.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
#: the sun's direction (map frame: +Y up), 20° above the horizon
ELEVATION_DEG = 20.0
AZIMUTH = np.array([-0.62469505, 0.0, -0.78086881])  # horizontal, towards −X and −Z


def sun_direction() -> tuple[float, float, float]:
    e = math.radians(ELEVATION_DEG)
    d = math.cos(e) * AZIMUTH + math.sin(e) * np.array([0.0, 1.0, 0.0])
    return tuple(float(x) for x in d)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path,
                    default=REPO / "measurements" / "environment" / "sunny.exr")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    from spectral_fit.io import write_spectral_exr
    from spectral_fit.lighting import synthetic_environment

    wl = np.arange(400.0, 701.0, 10.0)
    img = synthetic_environment(128, 256, wl, lamp_radius_deg=1.5,
                                lamp_direction=sun_direction(), lamp_luminance_ratio=3000.0)
    write_spectral_exr(args.out, wl, img, pixel_type="half")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
