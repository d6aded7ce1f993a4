"""Make the bundled photograph session measurements/sessions/two_spheres_photo/: one simulated
720 × 480 raw photograph of the two spheres (a glossy yellow, μ = 0.07) plus a white-standard
reading, both path-traced with the reference renderer (Mitsuba, one BSDF = the whole model,
path depth 16), so that the session is independent of the fit's forward model.

The camera: Nikon D5100 spectral sensitivities (colour-science's NPL measurement) scaled to
counts, an RGGB mosaic, 12-bit counts (black 64, white 4095), exposure chosen so that the
brightest highlight clips, read noise 2 counts and shot noise (0.15 counts per electron:
1 % at 1500 counts); the white standard: 3 repeats, 0.3 % noise, on the scene's grid. The
true materials are in truth.json; the scene config (configs/two_spheres_photo.toml) holds
other values, which the fit starts from.

    python scripts/make_photo_session.py [--spp N] [--size W H] [--out DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from spectral_fit.color import integration_weights  # noqa: E402
from spectral_fit.io import load_scene, write_session  # noqa: E402

CONFIG = ROOT / "configs" / "two_spheres_photo.toml"
OUT = ROOT / "measurements" / "sessions" / "two_spheres_photo"
TRUE = {
    "yellow": {"alpha": 0.92, "beta": 0.85, "chi": 0.03, "mu": 0.07, "n": 1.50},
    "red": {"alpha": 0.88, "beta": 1.10, "chi": 0.0, "mu": 0.09, "n": 1.55},
}
CAMERA = {"position": [0.0, 0.06, 0.05], "aim": [0.0, 0.0, -0.275], "fov_y_deg": 20.0}
WHITE = {"position": [0.0, 0.0, -0.275], "normal": [0.0, 0.0, 1.0], "reflectance": 0.98}
BLACK, WHITE_LEVEL, READ, GAIN = 64.0, 4095.0, 2.0, 0.15


def camera_sensitivities(wl: np.ndarray) -> np.ndarray:
    """(3, L) Nikon D5100 sensitivities (colour-science, NPL), peak 1, on ``wl``."""
    import colour

    cam = colour.MSDS_CAMERA_SENSITIVITIES["Nikon 5100 (NPL)"]
    s = np.stack([np.interp(wl, cam.wavelengths, cam.values[:, c], left=0.0, right=0.0)
                  for c in range(3)])
    return s / s.max()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--size", type=int, nargs=2, default=(720, 480))
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    from spectral_fit.validation.reference.instrument import Spectroradiometer, render_readings
    from spectral_fit.validation.reference.render import objects_crop, render_spectral

    scene = load_scene(CONFIG)
    W, H = args.size
    wl = np.asarray(scene.wavelengths, np.float64)
    objs = tuple(dataclasses.replace(o, material=dataclasses.replace(o.material,
                                                                     **TRUE[o.name]))
                 for o in scene.objects)
    cam = dataclasses.replace(scene.camera, position=tuple(CAMERA["position"]),
                              look_at=tuple(CAMERA["aim"]), fov_y_deg=CAMERA["fov_y_deg"])
    truth = dataclasses.replace(scene, objects=objs, camera=cam, width=W, height=H)
    t0 = time.perf_counter()
    crop = objects_crop(truth, margin=8)
    r = render_spectral(truth, spp=args.spp, passes=1, depths=(16,), crop=crop,
                        progress=print)
    radiance = np.zeros((H, W, wl.size))
    radiance[crop.y0:crop.y0 + crop.height, crop.x0:crop.x0 + crop.width] = \
        r.passes[0, 0].astype(np.float64)
    print(f"photograph rendered in {time.perf_counter() - t0:.0f} s")
    w = render_readings(truth, [], Spectroradiometer(), spp=args.spp * 4, depths=(16,),
                        white={**WHITE, "radius": 0.03}, progress=print)
    white = w["white"][0]
    # the camera
    sens = camera_sensitivities(wl)
    dl = integration_weights(wl)
    signal = np.einsum("hwl,cl->hwc", radiance, sens * dl[None, :])
    peak = float(np.percentile(signal[..., 1], 99.95))
    scale = 1.4 * (WHITE_LEVEL - BLACK) / max(peak, 1e-30)  # the top highlights clip
    exposure = 0.01
    sens_counts = sens * scale / exposure
    tile = np.array([[0, 1], [1, 2]])
    chan = np.tile(tile, (H // 2, W // 2))
    clean = np.take_along_axis(signal * scale, chan[..., None], axis=-1)[..., 0]
    rng = np.random.default_rng(7)
    sig = np.sqrt(READ ** 2 + GAIN * np.maximum(clean, 0.0))
    raw = np.clip(np.round(BLACK + clean + sig * rng.standard_normal(clean.shape)), 0,
                  WHITE_LEVEL).astype(np.uint16)
    print(f"clipped pixels: {int(np.sum(raw >= WHITE_LEVEL))}")
    whites = white[None] * (1.0 + 0.003 * rng.standard_normal((3, wl.size)))
    out = args.out
    write_session(
        out, scene=os.path.relpath(CONFIG, out.resolve()), wavelengths=wl,
        readings=[], calibration={"mode": "white"},
        white={"reflectance": WHITE["reflectance"], "position": WHITE["position"],
               "normal": WHITE["normal"], "spectra": whites},
        notes=f"A simulated raw photograph and a white standard, path-traced (Mitsuba "
              f"{r.variant}, {args.spp} spp, depth 16); truth in truth.json",
        images=[{"id": "photo", "pixels": raw, "format": "png", "sensitivities": sens_counts,
                 "exposure_s": exposure, "mosaic": "RGGB", "black_level": BLACK,
                 "white_level": WHITE_LEVEL, "read_noise": READ, "gain": GAIN,
                 "camera": CAMERA}])
    (out / "truth.json").write_text(json.dumps(
        {"params": TRUE, "camera": CAMERA, "spp": args.spp, "size": [W, H],
         "seconds": time.perf_counter() - t0, "variant": r.variant}, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
