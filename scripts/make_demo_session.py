"""Make the bundled demo session measurements/sessions/two_spheres_demo/ (configs/two_spheres.toml).

Simulated Topcon SR-3A-style readings of the two spheres: 10 spots (5 per sphere: facing the
instrument, the ceiling panel's highlight, a grazing view, the lamp's grazing highlight, and one
interreflection spot on the side facing the other sphere), 3 repeats each, a white standard
(reflectance 0.98) between the spheres, dark readings, and the spheres' spectrophotometer
reflectances (yellow SCE, red SCI).

The "real room" is the bundled map times a smooth calibration error k(λ) (the map is 15 % too
dark and tilted in colour), which the white standard calibrates away. Noise of one reading:
σ² = (2e-6)² + (0.003 · L)² W·sr⁻¹·m⁻²·nm⁻¹, plus a dark offset of 3e-6 (subtracted by the loader).

Readings are rendered by spectral_fit's own forward model (``fitting.simulate_readings``) at a
finer field sampling (spot_resolution 16) than the fit uses (8), with the interreflection term
when that module is present; they are therefore NOT independent of the fitted model.

    python scripts/make_demo_session.py [OUTDIR]
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from spectral_fit.fitting import FitOptions, scene_environment, simulate_readings  # noqa: E402
from spectral_fit.reflectance import fresnel_dielectric  # noqa: E402
from spectral_fit.scene import load_scene  # noqa: E402
from spectral_fit.session import write_session  # noqa: E402

CONFIG = ROOT / "configs" / "two_spheres.toml"
OUT = ROOT / "measurements" / "sessions" / "two_spheres_demo"

TRUE = {
    "yellow": {"alpha": 0.92, "beta": 0.85, "chi": 0.05, "mu": 0.12, "n": 1.50, "gamma": 1.0},
    "red": {"alpha": 0.88, "beta": 1.10, "chi": 0.02, "mu": 0.08, "n": 1.55, "gamma": 1.0},
}
NOISE_ABS = 2e-6
NOISE_REL = 0.003
DARK = 3e-6
REPEATS = 3
RADIUS = 0.0375
CENTRES = {"yellow": np.array([-0.045, 0.0, -0.275]), "red": np.array([0.045, 0.0, -0.275])}
LAMP = np.array([-1.2, 0.25, -1.5])
PANEL = np.array([0.0, 1.6, 0.8])


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def spots() -> list[dict]:
    out = []
    for name, c in CENTRES.items():
        side = -1.0 if name == "yellow" else 1.0  # outward x direction
        inst0 = np.array([0.0, 0.0, 0.0])
        # 1: facing the instrument at the origin
        v = _unit(inst0 - c)
        out.append({"id": f"{name}_front", "object": name, "kind": "object", "N": v, "V": v})
        # 2: the ceiling panel's highlight seen from the origin
        L = _unit(PANEL - c)
        out.append({"id": f"{name}_panel_highlight", "object": name, "kind": "object",
                    "N": _unit(v + L), "V": v})
        # 3: a grazing view (θr ≈ 60°) from above and outside
        V = _unit([side * 0.5, 0.55, 1.0])
        N = _unit(_unit([side * 0.2, 1.0, 0.6]))
        out.append({"id": f"{name}_grazing", "object": name, "kind": "object", "N": N, "V": V})
        # 4: the lamp's highlight (the lamp is behind-left): seen from the front-left
        Ll = _unit(LAMP - c)
        V = _unit([-0.6 + 0.3 * side, 0.1, 1.0])
        out.append({"id": f"{name}_lamp_highlight", "object": name, "kind": "object",
                    "N": _unit(Ll + V), "V": V})
        # 5: interreflection: the side facing the other sphere, seen from the front
        N = _unit([-side * 0.8, 0.05, 0.6])
        V = _unit([-side * 0.15, 0.05, 1.0])
        out.append({"id": f"{name}_gap", "object": name, "kind": "interreflection",
                    "N": N, "V": V})
    for s in out:
        c = CENTRES[s["object"]]
        s["aim"] = c + RADIUS * s["N"]
        s["position"] = s["aim"] + 0.30 * s["V"]
        s["field_angle_deg"] = 1.0
        cos_r = float(np.dot(s["N"], s["V"]))
        assert cos_r > 0.2, (s["id"], cos_r)
    return out


def calibration_error(wl: np.ndarray) -> np.ndarray:
    return 1.15 * (1.0 + 0.10 * (wl - 580.0) / 200.0)


def main(out: Path = OUT) -> None:
    scene = load_scene(CONFIG)
    wl = scene.wavelengths
    rng = np.random.default_rng(20261126)
    env = scene_environment(scene, compress_tol=3e-3)
    sp = spots()
    k = calibration_error(wl)
    clean = simulate_readings(scene, sp, params=TRUE, calibration=k, env=env,
                              options=FitOptions(spot_resolution=16))
    # white standard: Lambertian, reflectance 0.98, between the spheres facing the origin
    from spectral_fit.environment import irradiance_exact

    w_pos = np.array([0.0, 0.0, -0.275])
    w_n = _unit(-w_pos)
    e = np.asarray(irradiance_exact(env, w_n.astype(np.float32)), np.float64)
    white_clean = k * 0.98 * e / math.pi

    def noisy(x: np.ndarray, m: int) -> np.ndarray:
        sig = np.sqrt(NOISE_ABS ** 2 + (NOISE_REL * x) ** 2)
        return x[None] + DARK + sig[None] * rng.standard_normal((m,) + x.shape)

    readings = []
    for s, x in zip(sp, clean, strict=True):
        readings.append({"id": s["id"], "object": s["object"], "kind": s["kind"],
                         "aim": s["aim"], "position": s["position"],
                         "field_angle_deg": s["field_angle_deg"],
                         "spectra": np.maximum(noisy(x, REPEATS), 0.0)})
    cos8 = math.cos(math.radians(8.0))
    red_sci = scene.objects[1].material.reflectance + float(
        fresnel_dielectric(cos8, TRUE["red"]["n"]))
    write_session(
        out, scene="../../../configs/two_spheres.toml", wavelengths=wl, readings=readings,
        instrument={"position": [0.0, 0.0, 0.0], "field_angle_deg": 1.0},
        white={"reflectance": 0.98, "position": w_pos, "normal": w_n,
               "spectra": noisy(white_clean, REPEATS)},
        dark=DARK + NOISE_ABS * rng.standard_normal((2, wl.size)),
        objects={"yellow": {"reflectance": scene.objects[0].material.reflectance,
                            "geometry": "SCE"},
                 "red": {"reflectance": red_sci, "geometry": "SCI"}},
        notes="simulated with spectral_fit's own forward model (scripts/make_demo_session.py); "
              "true parameters in truth.json")
    truth = {"params": TRUE, "noise": {"absolute": NOISE_ABS, "relative": NOISE_REL,
                                       "dark_offset": DARK, "repeats": REPEATS},
             "calibration_error": "1.15 * (1 + 0.10 * (wavelength_nm - 580) / 200)",
             "generator": "spectral_fit.fitting.simulate_readings, spot_resolution 16",
             "independent": False}
    (out / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else OUT)
