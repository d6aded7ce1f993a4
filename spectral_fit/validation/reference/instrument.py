"""A simulated spectroradiometer (Topcon SR-3A-like) reading Mitsuba ground truth.

A reading is the mean spectral radiance over the instrument's measuring field: the cone of full
angle ``field_angle_deg`` (SR-3A: 2°, 1° or 0.2°) around the ray from the instrument's entrance
pupil ``position`` through the ``aim`` point. On an object at distance d the measured area is a
disc of diameter ≈ 2 d tan(field/2) (1° at 0.35 m: 6.1 mm). It is rendered as in the fitting
code's forward model (docs/measurements.md): a small square perspective camera whose field of
view is the field angle, the pixels inside the inscribed disc averaged with equal weights, each
pixel the radiance along its ray (path depth 16: interreflection included; depth 2 is kept to
label readings "object" or "interreflection").

Spectra: the scene's bands are rendered exactly (band trick), smoothed by the instrument's
triangular band-pass (5 nm FWHM) and interpolated to 1 nm steps over 380–780 nm (clipped to the
scene's grid). Noise, per reading and band (1σ), σ² = a² + (b L)² with b = ``noise_relative``
(repeatability) and a = ``noise_floor`` × the session's largest mean radiance, plus a gain error
per reading (``gain_sigma``, drift/aiming); independent repeats. Dark readings are pure floor
noise. The white standard (a Lambertian disc of reflectance R, objects removed) is read the same
way.

Output: a measurement session folder in the format of docs/measurements.md (``session.toml`` +
one CSV per reading repeat), plus ``truth.json`` with the noise-free means, the depth-2 means,
the materials of the config and the instrument settings.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..._runtime.errors import InputError
from ...io import Scene

__all__ = ["Spectroradiometer", "ReadingSpec", "default_spots", "render_readings",
           "simulate_readings"]


@dataclasses.dataclass(frozen=True)
class Spectroradiometer:
    """Instrument settings (SR-3A-like defaults)."""

    position: tuple[float, float, float] = (0.0, 0.05, 0.15)
    field_angle_deg: float = 1.0
    start_nm: float = 380.0
    end_nm: float = 780.0
    step_nm: float = 1.0
    bandwidth_nm: float = 5.0
    noise_relative: float = 0.004
    noise_floor: float = 5e-4
    gain_sigma: float = 0.002
    repeats: int = 3
    pixels: int = 16


@dataclasses.dataclass(frozen=True)
class ReadingSpec:
    """One measured spot: id, the object it lies on, the aim point (world, m)."""

    id: str
    object: str
    aim: tuple[float, float, float]
    position: tuple[float, float, float] | None = None
    field_angle_deg: float | None = None


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def default_spots(scene: Scene, instrument: Spectroradiometer) -> list[ReadingSpec]:
    """Five spots per sphere object: facing the instrument ("front"), 35° towards the nearest
    other object ("gap", where interreflection is strongest), 35° away from it ("outer"), 30° up
    and 30° down; each aim point lies on the sphere."""
    pos = np.asarray(instrument.position, np.float64)
    spots = []
    centres = {o.name: np.asarray(o.position, np.float64) for o in scene.objects}
    for o in scene.objects:
        if o.shape not in ("uv_sphere", "icosphere"):
            continue
        c = centres[o.name]
        r = o.radius * o.scale
        front = pos - c
        front /= np.linalg.norm(front)
        others = [v for k, v in centres.items() if k != o.name]
        side = (min(others, key=lambda v: np.linalg.norm(v - c)) - c) if others else \
            np.array([1.0, 0.0, 0.0])
        up = np.cross(front, side)
        if np.linalg.norm(up) < 1e-9:
            up = np.array([0.0, 1.0, 0.0])
        up /= np.linalg.norm(up)
        if up[1] < 0:
            up = -up
        tilt = {"front": np.eye(3), "gap": _rot(up, math.radians(35)),
                "outer": _rot(up, math.radians(-35))}
        # rotate about the horizontal axis (front × up) for up/down
        horiz = np.cross(front, up)
        tilt["up"] = _rot(horiz, math.radians(-30))
        tilt["down"] = _rot(horiz, math.radians(30))
        for name, rot in tilt.items():
            n = rot @ front
            if name == "gap" and np.dot(n, side) < 0:
                n = _rot(up, math.radians(-35)) @ front
            if name == "outer" and np.dot(n, side) > 0:
                n = _rot(up, math.radians(35)) @ front
            if name == "up" and n[1] < 0:
                n = _rot(horiz, math.radians(30)) @ front
            if name == "down" and n[1] > 0:
                n = _rot(horiz, math.radians(-30)) @ front
            spots.append(ReadingSpec(id=f"{o.name}_{name}", object=o.name,
                                     aim=tuple(float(x) for x in c + r * n)))
    return spots


def _sensor(mi: Any, position: np.ndarray, aim: np.ndarray, fov: float, pixels: int,
            spp: int) -> dict[str, Any]:
    d = aim - position
    up = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.99 * np.linalg.norm(d) else \
        np.array([0.0, 0.0, 1.0])
    return {
        "type": "perspective", "fov": float(fov), "fov_axis": "x",
        "near_clip": 1e-3, "far_clip": 1e4,
        "to_world": mi.ScalarTransform4f().look_at(origin=position.tolist(),
                                                   target=aim.tolist(), up=up.tolist()),
        "film": {"type": "hdrfilm", "width": pixels, "height": pixels,
                 "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        "sampler": {"type": "independent", "sample_count": int(spp)},
    }


def _disc_mask(pixels: int) -> np.ndarray:
    c = (np.arange(pixels) + 0.5) / pixels * 2.0 - 1.0
    return (c[:, None] ** 2 + c[None, :] ** 2) <= 1.0


def render_readings(
    scene: Scene,
    spots: list[ReadingSpec],
    instrument: Spectroradiometer,
    *,
    spp: int = 1024,
    depths: tuple[int, ...] = (2, 16),
    seed: int = 0,
    white: dict[str, Any] | None = None,
    progress: Any = None,
) -> dict[str, Any]:
    """Noise-free field-averaged radiance (D, R, L) of every spot on the scene's bands (and of
    the white standard, (D, L), when ``white`` = {position, normal, reflectance, radius} is
    given), by the band trick with Mitsuba. Returns a dict with ``readings``, ``white``,
    ``seconds``, ``variant``."""
    from .backend import current_variant, init_mitsuba
    from .bsdf import PLUGIN
    from .export import band_groups, environment_texels, mitsuba_envmap_rows, scene_dict

    mi, _ = init_mitsuba()
    wl = scene.wavelengths
    names = {o.name for o in scene.objects}
    for s in spots:
        if s.object not in names:
            raise InputError(f"unknown object {s.object!r} (scene has {sorted(names)})",
                             field=f"readings[{s.id}].object")
    t0 = time.perf_counter()
    rows = mitsuba_envmap_rows(environment_texels(scene))
    meshes = {o.name: o.make_mesh(world=True) for o in scene.objects}
    mask = _disc_mask(instrument.pixels)
    sensors = []
    for s in spots:
        pos = np.asarray(s.position or instrument.position, np.float64)
        fov = s.field_angle_deg or instrument.field_angle_deg
        sensors.append(_sensor(mi, pos, np.asarray(s.aim, np.float64), fov,
                               instrument.pixels, spp))
    integrators = {d: mi.load_dict({"type": "path", "max_depth": int(d)}) for d in depths}
    out = np.zeros((len(depths), len(spots), wl.size))
    wout = np.zeros((len(depths), wl.size)) if white else None
    wsens, wshape = None, None
    if white:
        wpos = np.asarray(white["position"], np.float64)
        wn = np.asarray(white["normal"], np.float64)
        wn /= np.linalg.norm(wn)
        wpos_i = np.asarray(white.get("position_instrument", instrument.position), np.float64)
        wsens = [_sensor(mi, wpos_i, wpos, instrument.field_angle_deg, instrument.pixels, spp)]
        refl = np.broadcast_to(np.asarray(white["reflectance"], np.float64), wl.shape)
        z = np.array([0.0, 0.0, 1.0])
        axis = np.cross(z, wn)
        ang = math.acos(float(np.clip(np.dot(z, wn), -1, 1)))
        rot = _rot(axis, ang) if np.linalg.norm(axis) > 1e-9 else (
            np.eye(3) if wn[2] > 0 else np.diag([1.0, -1.0, -1.0]))
        m = np.eye(4)
        m[:3, :3] = rot * float(white.get("radius", 0.05))
        m[:3, 3] = wpos
        wshape = (m, refl)
    for gi, idx in enumerate(band_groups(wl.size)):
        refl = {o.name: np.asarray(o.material.reflectance)[idx] for o in scene.objects}
        d = scene_dict(scene, env_rgb=rows[..., idx], reflectances=refl, spp=spp,
                       meshes=meshes, sensors=sensors)
        ms = mi.load_dict(d)
        for di, depth in enumerate(depths):
            for ri in range(len(spots)):
                img = np.asarray(mi.render(ms, sensor=ri, integrator=integrators[depth],
                                           seed=seed), np.float64)
                out[di, ri, idx] = img[mask][:, :3].mean(axis=0)
        if white:
            m, wr = wshape
            disc = {"type": "disk", "to_world": mi.ScalarTransform4f(m.tolist()),
                    "bsdf": {"type": PLUGIN, "alpha": 1.0, "beta": 0.0, "chi": 0.0,
                             "s0": float(wr[idx[0]]), "s1": float(wr[idx[1]]),
                             "s2": float(wr[idx[2]])}}
            dw = scene_dict(scene, env_rgb=rows[..., idx], reflectances=refl, spp=spp,
                            sensors=wsens, objects=False, extra_shapes={"white": disc})
            mw = mi.load_dict(dw)
            for di, depth in enumerate(depths):
                img = np.asarray(mi.render(mw, sensor=0, integrator=integrators[depth],
                                           seed=seed), np.float64)
                wout[di, idx] = img[mask][:, :3].mean(axis=0)
        if progress is not None:
            progress(f"bands {wl[idx[0]]:g}-{wl[idx[-1]]:g} nm ({gi + 1}/"
                     f"{math.ceil(wl.size / 3)}, {time.perf_counter() - t0:.1f} s)")
    return {"readings": out, "white": wout, "seconds": time.perf_counter() - t0,
            "variant": current_variant() or "", "depths": tuple(depths)}


def instrument_grid(scene: Scene, instrument: Spectroradiometer) -> np.ndarray:
    """The instrument's output wavelengths (1 nm steps by default), clipped to the scene grid."""
    wl = scene.wavelengths
    lo = max(instrument.start_nm, float(wl[0]))
    hi = min(instrument.end_nm, float(wl[-1]))
    return np.arange(lo, hi + 1e-9, instrument.step_nm)


def instrument_response(wl: np.ndarray, spectra: np.ndarray, out_wl: np.ndarray,
                        bandwidth_nm: float) -> np.ndarray:
    """Spectra (..., L) on ``wl`` seen through a triangular band-pass of FWHM ``bandwidth_nm``
    centred on each output wavelength (the band-pass integrated against the piecewise-linear
    spectrum on a 0.25 nm grid; edges held)."""
    fine = np.arange(wl[0] - bandwidth_nm, wl[-1] + bandwidth_nm + 1e-9, 0.25)
    flat = np.asarray(spectra, np.float64).reshape(-1, wl.size)
    f = np.stack([np.interp(fine, wl, row) for row in flat])
    out = np.empty((flat.shape[0], out_wl.size))
    for j, c in enumerate(out_wl):
        w = np.maximum(0.0, 1.0 - np.abs(fine - c) / bandwidth_nm)
        out[:, j] = f @ w / w.sum()
    return out.reshape(*np.shape(spectra)[:-1], out_wl.size)


def simulate_readings(
    scene: Scene,
    folder: str | os.PathLike[str],
    *,
    instrument: Spectroradiometer | None = None,
    spots: list[ReadingSpec] | None = None,
    spp: int = 1024,
    seed: int = 0,
    white: dict[str, Any] | None = None,
    dark: bool = True,
    ir_threshold: float = 0.05,
    scene_ref: str | None = None,
    progress: Any = None,
) -> Path:
    """Render the spots, add instrument noise and write a measurement session folder
    (docs/measurements.md) with ``truth.json``; returns the manifest's path.

    Args:
        instrument: settings (default :class:`Spectroradiometer`()).
        spots: readings to take (default :func:`default_spots`).
        white: optional white standard {position, normal, reflectance (number), radius}.
        dark: also write two dark readings.
        ir_threshold: a reading is of kind "interreflection" when the depth-16 vs depth-2
            luminance difference exceeds this share.
        scene_ref: the scene path as written into the manifest (default: relative to folder).
    """
    from ...color import xyz_weights

    inst = instrument or Spectroradiometer()
    spots = spots if spots is not None else default_spots(scene, inst)
    if not spots:
        raise InputError("no spots to read", field="spots")
    res = render_readings(scene, spots, inst, spp=spp, seed=seed, white=white,
                          progress=progress)
    wl = scene.wavelengths
    owl = instrument_grid(scene, inst)
    means = instrument_response(wl, res["readings"], owl, inst.bandwidth_nm)  # (2, R, L')
    total, direct = means[1], means[0]
    wy = xyz_weights(wl)[:, 1]
    y16, y2 = res["readings"][1] @ wy, res["readings"][0] @ wy
    ir = (y16 - y2) / np.maximum(y16, 1e-30)
    rng = np.random.default_rng(seed + 12345)
    peak = float(total.max())
    floor = inst.noise_floor * peak

    def noisy(mean: np.ndarray) -> np.ndarray:
        reps = []
        for _ in range(inst.repeats):
            sig = np.sqrt(floor**2 + (inst.noise_relative * mean) ** 2)
            gain = 1.0 + inst.gain_sigma * rng.standard_normal()
            reps.append(np.maximum(gain * mean + sig * rng.standard_normal(mean.shape), 0.0))
        return np.stack(reps)

    folder = Path(folder)
    if scene_ref is not None:
        scene_path = scene_ref
    else:
        scene_path = os.path.relpath(scene.path, folder) if scene.path else ""
    readings = []
    for i, s in enumerate(spots):
        pos = np.asarray(s.position or inst.position, np.float64)
        r = {"id": s.id, "object": s.object,
             "kind": "interreflection" if ir[i] > ir_threshold else "object",
             "aim": list(s.aim), "spectra": noisy(total[i]),
             "distance_m": round(float(np.linalg.norm(np.asarray(s.aim) - pos)), 4)}
        if s.position is not None:
            r["position"] = list(s.position)
        if s.field_angle_deg is not None:
            r["field_angle_deg"] = s.field_angle_deg
        readings.append(r)
    white_out = None
    if white:
        wmean = instrument_response(wl, res["white"][1], owl, inst.bandwidth_nm)
        white_out = {"reflectance": float(white["reflectance"]),
                     "position": list(white["position"]), "normal": list(white["normal"]),
                     "spectra": noisy(wmean)}
    dark_out = (rng.standard_normal((2, owl.size)) * floor) if dark else None
    instrument_tbl = {"position": list(inst.position),
                      "field_angle_deg": inst.field_angle_deg}
    notes = (f"Simulated SR-3A-like readings of Mitsuba ground truth ({res['variant']}, "
             f"{spp} spp, path depth 16); see truth.json")
    manifest = _write_session(folder, scene=scene_path, wavelengths=owl, readings=readings,
                              instrument=instrument_tbl, white=white_out, dark=dark_out,
                              notes=notes)
    truth = {
        "scene": scene_path,
        "variant": res["variant"],
        "spp": spp,
        "seed": seed,
        "render_seconds": round(res["seconds"], 1),
        "instrument": dataclasses.asdict(inst),
        "noise_floor_abs": floor,
        "wavelengths_nm": owl.tolist(),
        "materials": {o.name: {k: getattr(o.material, k) for k in
                               ("alpha", "beta", "chi", "mu", "n", "distribution", "geometry")}
                      | {"reflectance": o.material.reflectance_source}
                      for o in scene.objects},
        "readings": {s.id: {"object": s.object, "aim": list(s.aim),
                            "ir_fraction": float(ir[i]),
                            "mean": total[i].tolist(), "mean_direct": direct[i].tolist()}
                     for i, s in enumerate(spots)},
    }
    if white:
        truth["white"] = {"mean": instrument_response(
            wl, res["white"][1], owl, inst.bandwidth_nm).tolist()}
    from ..._runtime.fileio import atomic_write_text

    atomic_write_text(folder / "truth.json", json.dumps(_rounded(truth), indent=1) + "\n")
    return manifest


def _rounded(x: Any) -> Any:
    """JSON-ready copy with floats at 6 significant digits (compact truth files)."""
    if isinstance(x, float):
        return float(f"{x:.6g}")
    if isinstance(x, list | tuple):
        return [_rounded(v) for v in x]
    if isinstance(x, dict):
        return {k: _rounded(v) for k, v in x.items()}
    return x


def _write_session(folder: Path, **kw: Any) -> Path:
    """Write through ``spectral_fit.io.write_session`` when the package has it; else the
    same documented layout (docs/measurements.md) by the minimal writer below."""
    try:
        from ...io import write_session  # type: ignore[attr-defined]
    except ImportError:
        write_session = _minimal_write_session
    return write_session(folder, **kw)


def _spectrum_text(wl: np.ndarray, values: np.ndarray, unit: str, comment: str) -> str:
    head = [f"# {comment}", f"# unit: {unit}", "wavelength_nm,value"]
    return "\n".join(head + [f"{w:g},{v:.8g}" for w, v in zip(wl, values, strict=True)]) + "\n"


def _toml(v: Any) -> str:
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    return repr(float(v)) if isinstance(v, float) else str(v)


def _minimal_write_session(folder: Path, *, scene: str, wavelengths: np.ndarray,
                           readings: list[dict], instrument: dict, white: dict | None,
                           dark: np.ndarray | None, notes: str,
                           units: str = "W.sr^-1.m^-2.nm^-1") -> Path:
    from ..._runtime.fileio import atomic_write_text

    out = ["# Spectroradiometer session (format: docs/measurements.md)", "", "[session]",
           "format = 1", f"scene = {_toml(scene)}", f"units = {_toml(units)}",
           f"notes = {_toml(notes)}", "", "[instrument]"]
    out += [f"{k} = {_toml(v)}" for k, v in instrument.items()]
    if dark is not None:
        names = []
        for k, row in enumerate(dark):
            names.append(f"dark/dark_{k + 1}.csv")
            atomic_write_text(folder / names[-1], _spectrum_text(wavelengths, row, units,
                                                                 "dark reading"))
        out += ["", "[dark]", f"readings = {_toml(names)}"]
    if white:
        names = []
        for k, row in enumerate(white["spectra"]):
            names.append(f"white/white_{k + 1}.csv")
            atomic_write_text(folder / names[-1], _spectrum_text(wavelengths, row, units,
                                                                 "white standard"))
        out += ["", "[white_standard]", f"reflectance = {_toml(white['reflectance'])}",
                f"position = {_toml(white['position'])}", f"normal = {_toml(white['normal'])}",
                f"readings = {_toml(names)}"]
    for r in readings:
        files = []
        for k, row in enumerate(r["spectra"]):
            files.append(f"readings/{r['id']}_{k + 1}.csv")
            atomic_write_text(folder / files[-1], _spectrum_text(wavelengths, row, units,
                                                                 f"reading {r['id']}"))
        out += ["", "[[readings]]", f"id = {_toml(r['id'])}", f"object = {_toml(r['object'])}",
                f"kind = {_toml(r['kind'])}", f"files = {_toml(files)}",
                f"aim = {_toml([round(float(x), 6) for x in r['aim']])}"]
        for k in ("position", "field_angle_deg", "distance_m"):
            if k in r:
                out.append(f"{k} = {_toml(r[k])}")
    manifest = folder / "session.toml"
    atomic_write_text(manifest, "\n".join(out) + "\n")
    return manifest
