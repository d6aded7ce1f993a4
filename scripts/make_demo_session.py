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
from spectral_fit.io import (  # noqa: E402
    load_scene,
    write_session,  # noqa: E402
)
from spectral_fit.lighting import fresnel_dielectric  # noqa: E402

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


def _tilt(n: np.ndarray, towards: np.ndarray, deg: float) -> np.ndarray:
    """n rotated by ``deg`` towards the direction ``towards``."""
    t = towards - np.dot(towards, n) * n
    t = t / np.linalg.norm(t)
    a = math.radians(deg)
    return _unit(math.cos(a) * n + math.sin(a) * t)


def spots() -> list[dict]:
    """Nine spots per sphere: facing the instrument; the ceiling panel's highlight and two
    spots 4° and 8° (of normal) off it (the lobe's width: μ); two grazing views (θr ≈ 60°,
    75°: n through the Fresnel rise); the lamp's highlight and a spot 3° off it (a small
    source: mirror χ vs gloss β); one spot facing the other sphere (interreflection).
    Grazing and lamp spots use the 0.2° field, the others 1°."""
    out = []
    for name, c in CENTRES.items():
        side = -1.0 if name == "yellow" else 1.0  # outward x direction
        v0 = _unit(-c)  # towards the origin
        up = np.array([0.0, 1.0, 0.0])
        out.append({"id": f"{name}_front", "object": name, "kind": "object", "N": v0, "V": v0})
        L = _unit(PANEL - c)
        nh = _unit(v0 + L)
        for k, deg in enumerate((0.0, 4.0, 8.0)):
            n = nh if deg == 0 else _tilt(nh, v0, deg)
            out.append({"id": f"{name}_panel_{k}", "object": name, "kind": "object",
                        "N": n, "V": v0})
        for k, (vv, th) in enumerate((([side * 0.5, 0.55, 1.0], 60.0),
                                      ([side * 1.0, 0.2, 0.3], 75.0))):
            V = _unit(vv)
            N = _tilt(V, up if k == 0 else np.array([0.0, -1.0, 0.0]), th)
            out.append({"id": f"{name}_grazing_{k}", "object": name, "kind": "object",
                        "N": N, "V": V})
        Ll = _unit(LAMP - c)
        V = _unit([-0.6 + 0.3 * side, 0.1, 1.0])
        nl = _unit(Ll + V)
        for k, deg in enumerate((0.0, 3.0)):
            n = nl if deg == 0 else _tilt(nl, V, deg)
            out.append({"id": f"{name}_lamp_{k}", "object": name, "kind": "object",
                        "N": n, "V": V})
        N = _unit([-side * 0.8, 0.05, 0.6])
        V = _unit([-side * 0.15, 0.05, 1.0])
        out.append({"id": f"{name}_gap", "object": name, "kind": "interreflection",
                    "N": N, "V": V})
    for s in out:
        c = CENTRES[s["object"]]
        s["aim"] = c + RADIUS * s["N"]
        s["position"] = s["aim"] + 0.30 * s["V"]
        # the 0.2° field (SR-3A) where the footprint must stay small: grazing views (the
        # footprint stretches by 1/cos θr) and the lamp's reflection (a 3.6° source)
        s["field_angle_deg"] = 0.2 if ("grazing" in s["id"] or "lamp" in s["id"]) else 1.0
        cos_r = float(np.dot(s["N"], s["V"]))
        assert cos_r > 0.2, (s["id"], cos_r)
    return out


def calibration_error(wl: np.ndarray) -> np.ndarray:
    return 1.15 * (1.0 + 0.10 * (wl - 580.0) / 200.0)


def main_reference(out: Path = OUT, spp: int = 512) -> None:
    """The bundled session: the same spots and true parameters rendered by the independent
    Mitsuba reference (spectral_fit.validation.reference: our whole model as one BSDF, path depth
    16,
    band trick) and read by its simulated SR-3A (1 nm output, 5 nm band-pass, repeatability
    0.4 %, floor 5e-4 of the peak, gain jitter 0.2 %, 3 repeats)."""
    import dataclasses

    from spectral_fit.validation.reference.instrument import ReadingSpec, Spectroradiometer
    from spectral_fit.validation.reference.instrument import simulate_readings as sim

    scene = load_scene(CONFIG)
    objs = []
    for o in scene.objects:
        m = dataclasses.replace(o.material, **TRUE[o.name])
        objs.append(dataclasses.replace(o, material=m))
    truth_scene = scene.replace(objects=tuple(objs))
    sp = [ReadingSpec(id=s["id"], object=s["object"], aim=tuple(map(float, s["aim"])),
                      position=tuple(map(float, s["position"])),
                      field_angle_deg=s["field_angle_deg"]) for s in spots()]
    w_pos = [0.0, 0.0, -0.275]
    white = {"position": w_pos, "normal": [0.0, 0.0, 1.0], "reflectance": 0.98,
             "radius": 0.02}
    manifest = sim(truth_scene, out, instrument=Spectroradiometer(), spots=sp, spp=spp,
                   white=white, scene_ref="../../../configs/two_spheres.toml",
                   progress=print)
    text = manifest.read_text()
    for s_ in spots():  # kinds by geometry: the spots facing the neighbour
        if s_["kind"] == "interreflection":
            i = text.index(f'id = "{s_["id"]}"')
            j = text.index("kind = ", i)
            k = text.index("\n", j)
            text = text[:j] + 'kind = "interreflection"' + text[k:]
    text = text.replace("field_angle_deg = 1.0\n", "field_angle_deg = 1.0\nbandwidth_nm = 5.0\n", 1)
    manifest.write_text(text)
    truth = json.loads((out / "truth.json").read_text())
    truth["params"] = TRUE
    truth["independent"] = True
    truth["generator"] = ("scripts/make_demo_session.py ("
                          "spectral_fit.validation.reference.instrument."
                          f"simulate_readings, {spp} spp, path depth 16)")
    (out / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
    print(f"wrote {out}")


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
    from spectral_fit.lighting import irradiance_exact

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
    args = sys.argv[1:]
    own = "--own-model" in args
    args = [a for a in args if a != "--own-model"]
    dest = Path(args[0]) if args else OUT
    (main if own else main_reference)(dest)
