"""Loading and validating a measurement session (format: ``docs/measurements.md``).

:func:`load_session` reads a session folder (or its ``session.toml``), resamples every spectrum
onto the scene's wavelength grid, subtracts the dark reading, converts units, and checks
everything it can without geometry. Every error is an
:class:`~spectral_fit._runtime.errors.InputError` naming the file, the line and the field (e.g.
``session.toml, line 42: readings[3].object: unknown object 'blue'; the scene has ['yellow',
'red']``). Checks needing the geometry (a spot missing its object, the stated distance) are made
when the fit rasterises the spots (:func:`spectral_fit.fitting.prepare_fit`), with the same kind
of message.

This module is plain NumPy (the data layer).
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from .._runtime.errors import InputError
from .._runtime.fileio import read_text
from ._manifest import _Ctx, _toml_lines
from ._noise import NoiseModel, estimate_noise
from ._scene import Scene
from ._session import (
    CALIBRATION_MODES,
    DATA_KINDS,
    DEFAULT_FREE,
    KINDS,
    PARAMETERS,
    PHYSICAL_LOWER,
    ObjectMeasurement,
    Reading,
    Session,
    WhiteStandard,
)
from ._spectrum_files import RADIANCE_UNITS, _read_spectra, _reflectance_value

__all__ = ["load_session", "parse_session"]


def load_session(path: str | os.PathLike[str], *, scene: Scene | None = None) -> Session:
    """Read and validate a measurement session (stable API ``load_session``).

    Args:
        path: the session folder or its ``session.toml``.
        scene: a loaded :class:`~spectral_fit.io.Scene` to use instead of the config the
            manifest names (its objects must still match the session's).

    Returns:
        :class:`Session` with every spectrum on the scene's wavelength grid, in
        W·sr⁻¹·m⁻²·nm⁻¹, dark subtracted.

    Raises:
        InputError naming file, line and field (see ``docs/measurements.md``).
    """
    p = Path(path)
    if p.is_dir():
        p = p / "session.toml"
    text = read_text(p)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        m = re.search(r"line (\d+)", str(exc))
        raise InputError(f"TOML syntax error: {exc}", path=p,
                         line=int(m.group(1)) if m else None) from None
    return parse_session(data, path=p, text=text, scene=scene)


def parse_session(data: dict[str, Any], *, path: str | os.PathLike[str], text: str = "",
                  scene: Scene | None = None) -> Session:
    """Validate a parsed manifest (a dict as from ``tomllib``); see :func:`load_session`."""
    p = Path(path)
    base = p.parent
    lines = _toml_lines(text)
    ctx = _Ctx(p, lines)
    if not isinstance(data, dict):
        raise ctx.err("<root>", "must be a table")
    ctx.finish(data, ("session", "instrument", "calibration", "white_standard", "dark", "noise",
                      "model_error", "objects", "readings", "images"), "")

    st = ctx.table(data, "session", "session", required=True)
    ctx.finish(st, ("format", "scene", "units", "instrument", "date", "notes"), "session")
    fmt = ctx.number(st, "format", "session.format", 1.0)
    if fmt != 1.0:
        raise ctx.err("session.format", f"unsupported format version {fmt:g} (this reader: 1)")
    units = ctx.string(st, "units", "session.units", "W.sr^-1.m^-2.nm^-1")
    if units not in RADIANCE_UNITS:
        raise ctx.err("session.units", f"unknown radiance unit {units!r}; use one of "
                      f"{sorted(k for k in RADIANCE_UNITS if k.startswith(('W.', 'mW.')))}")
    instrument = ctx.string(st, "instrument", "session.instrument", "")
    for k in ("date", "notes"):
        if k in st and not isinstance(st[k], str):
            raise ctx.err(f"session.{k}", "must be a string")

    scene_path = None
    if scene is None:
        sc = ctx.string(st, "scene", "session.scene")
        scene_path = base / sc
        if not scene_path.is_file():
            raise ctx.err("session.scene", f"scene config not found: {scene_path}")
        from ._scene import load_scene

        scene = load_scene(scene_path)
    else:
        if "scene" in st and isinstance(st["scene"], str):
            scene_path = base / st["scene"]
    wl = np.asarray(scene.wavelengths, np.float64)
    names = [o.name for o in scene.objects]

    it = ctx.table(data, "instrument", "instrument")
    ctx.finish(it, ("position", "field_angle_deg", "bandwidth_nm"), "instrument")
    bandwidth = ctx.number(it, "bandwidth_nm", "instrument.bandwidth_nm", 0.0, lo=0.0, hi=50.0)
    inst_pos = ctx.vector(it, "position", "instrument.position", [0.0, 0.0, 0.0])
    inst_field = ctx.number(it, "field_angle_deg", "instrument.field_angle_deg", 1.0,
                            lo=0.01, hi=20.0)

    # dark ----------------------------------------------------------------------------------
    dark = None
    dt = ctx.table(data, "dark", "dark")
    if dt:
        ctx.finish(dt, ("readings",), "dark")
        fs = ctx.files(dt, "readings", "dark.readings", base)
        dark = np.concatenate([_read_spectra(f, wl, kind="radiance", units=units,
                                             allow_negative=True) for f in fs]).mean(axis=0)

    def radiance(files: list[Path], field: str) -> np.ndarray:
        out = []
        for f in files:
            s = _read_spectra(f, wl, kind="radiance", units=units)
            out.append(s)
        arr = np.concatenate(out)
        if dark is not None:
            arr = arr - dark
        return arr

    # white standard ---------------------------------------------------------------------
    white = None
    wt = ctx.table(data, "white_standard", "white_standard")
    if wt:
        ctx.finish(wt, ("reflectance", "position", "normal", "readings", "position_instrument"),
                   "white_standard")
        if "reflectance" not in wt:
            raise ctx.err("white_standard.reflectance", "missing (required)")
        wref = _reflectance_value(ctx, wt, "reflectance", "white_standard.reflectance", base, wl)
        if np.any(wref <= 0.05):
            raise ctx.err("white_standard.reflectance",
                          f"reflectance {wref.min():g} is too low for a white standard")
        fs = ctx.files(wt, "readings", "white_standard.readings", base)
        wrep = radiance(fs, "white_standard.readings")
        if np.any(wrep.mean(axis=0) <= 0):
            raise ctx.err("white_standard.readings",
                          "the mean white reading (dark subtracted) is not positive at every "
                          "wavelength; the calibration would divide by zero")
        white = WhiteStandard(
            reflectance=wref,
            position=ctx.vector(wt, "position", "white_standard.position"),
            normal=ctx.vector(wt, "normal", "white_standard.normal", unit=True),
            instrument_position=ctx.vector(wt, "position_instrument",
                                           "white_standard.position_instrument", inst_pos),
            repeats=wrep, files=tuple(fs))

    # calibration --------------------------------------------------------------------------
    ct = ctx.table(data, "calibration", "calibration")
    ctx.finish(ct, ("mode", "reference"), "calibration")
    mode = ctx.string(ct, "mode", "calibration.mode", "white" if white is not None else "global")
    if mode not in CALIBRATION_MODES:
        raise ctx.err("calibration.mode", f"must be one of {CALIBRATION_MODES}, got {mode!r}")
    if mode == "white" and white is None:
        raise ctx.err("calibration.mode", "mode 'white' needs a [white_standard] table")
    reference = None
    if mode == "global":
        reference = ctx.string(ct, "reference", "calibration.reference", names[0])
        if reference not in names:
            raise ctx.err("calibration.reference", f"unknown object {reference!r}; the scene "
                          f"has {names}")

    # objects --------------------------------------------------------------------------------
    ot = ctx.table(data, "objects", "objects")
    objects: dict[str, ObjectMeasurement] = {}
    for name, tab in ot.items():
        f = f"objects.{name}"
        if name not in names:
            raise ctx.err(f, f"unknown object {name!r}; the scene config has {names}")
        if not isinstance(tab, dict):
            raise ctx.err(f, "must be a table")
        ctx.finish(tab, ("reflectance", "geometry", "free", "start", "bounds", "prior"), f)
        refl = None
        if "reflectance" in tab:
            refl = _reflectance_value(ctx, tab, "reflectance", f"{f}.reflectance", base, wl)
        geom = ctx.string(tab, "geometry", f"{f}.geometry", "SCE").upper()
        if geom not in ("SCE", "SCI"):
            raise ctx.err(f"{f}.geometry", f"must be 'SCE' or 'SCI', got {tab['geometry']!r}")
        free = tab.get("free", list(DEFAULT_FREE))
        if not isinstance(free, list) or not all(isinstance(x, str) for x in free):
            raise ctx.err(f"{f}.free", f"must be a list of parameter names, got {free!r}")
        bad = [x for x in free if x not in PARAMETERS]
        if bad:
            raise ctx.err(f"{f}.free", f"unknown parameter {bad[0]!r}; choose from "
                          f"{PARAMETERS}")
        if len(set(free)) != len(free):
            raise ctx.err(f"{f}.free", "repeated parameter")
        start_t = ctx.table(tab, "start", f"{f}.start")
        ctx.finish(start_t, PARAMETERS, f"{f}.start")
        start = {}
        for k in start_t:
            lo, lo_open = {"mu": (0.0, True), "n": (1.0, True)}.get(k, (0.0, False))
            start[k] = ctx.number(start_t, k, f"{f}.start.{k}", lo=lo, lo_open=lo_open,
                                  hi=10.0)
        bounds, prior = _bounds_and_prior(ctx, tab, f)
        for k, v in start.items():
            lo, hi = bounds.get(k, (None, None))
            if (lo is not None and v < lo) or (hi is not None and v > hi):
                raise ctx.err(f"{f}.start.{k}", f"{v} lies outside {f}.bounds.{k} "
                              f"[{lo}, {hi}]")
        objects[name] = ObjectMeasurement(name=name, reflectance=refl, geometry=geom,
                                          free=tuple(x for x in PARAMETERS if x in free),
                                          start=start, bounds=bounds, prior=prior)

    # readings -------------------------------------------------------------------------------
    from ._image_reading import parse_images

    images = parse_images(ctx, data, base, wl, names, lines)
    rl = data.get("readings", [] if images else None)
    if not isinstance(rl, list) or not (rl or images):
        raise ctx.err("readings", "need at least one [[readings]] or [[images]] table")
    if len(rl) > 10000:
        raise ctx.err("readings", f"too many readings ({len(rl)})")
    readings: list[Reading] = []
    seen: set[str] = set()
    for i, r in enumerate(rl):
        f = f"readings[{i}]"
        if not isinstance(r, dict):
            raise ctx.err(f, "must be a table")
        ctx.finish(r, ("id", "object", "kind", "files", "aim", "position", "field_angle_deg",
                       "distance_m"), f)
        rid = ctx.string(r, "id", f"{f}.id", f"reading_{i}")
        if rid in seen:
            raise ctx.err(f"{f}.id", f"repeated id {rid!r}")
        seen.add(rid)
        obj = ctx.string(r, "object", f"{f}.object")
        if obj not in names:
            raise ctx.err(f"{f}.object", f"unknown object {obj!r}; the scene config has {names}")
        kind = ctx.string(r, "kind", f"{f}.kind", "object")
        if kind not in KINDS:
            raise ctx.err(f"{f}.kind", f"must be one of {KINDS}, got {kind!r}")
        fs = ctx.files(r, "files", f"{f}.files", base)
        reps = radiance(fs, f"{f}.files")
        pos = ctx.vector(r, "position", f"{f}.position", inst_pos)
        aim = ctx.vector(r, "aim", f"{f}.aim")
        if np.linalg.norm(aim - pos) < 1e-3:
            raise ctx.err(f"{f}.aim", "must be at least 1 mm away from the instrument position")
        fa = ctx.number(r, "field_angle_deg", f"{f}.field_angle_deg", inst_field, lo=0.01,
                        hi=20.0)
        dist = None
        if "distance_m" in r:
            dist = ctx.number(r, "distance_m", f"{f}.distance_m", lo=0.0, lo_open=True, hi=1e3)
        readings.append(Reading(id=rid, object=obj, kind=kind, files=tuple(fs), repeats=reps,
                                position=pos, aim=aim, field_angle_deg=fa, distance_m=dist,
                                line=lines.get(f), index=i))
    means = (np.stack([r.mean for r in readings]) if readings
             else np.ones((1, wl.size)))  # images only: the spot noise model is unused
    if not np.any(means > 0):
        raise ctx.err("readings", "every reading is zero (after dark subtraction)")

    # noise ------------------------------------------------------------------------------------
    nt = ctx.table(data, "noise", "noise")
    if nt:
        ctx.finish(nt, ("absolute", "relative"), "noise")
        noise = NoiseModel(absolute=ctx.number(nt, "absolute", "noise.absolute", 0.0, lo=0.0),
                           relative=ctx.number(nt, "relative", "noise.relative", 0.0, lo=0.0,
                                               hi=10.0), source="manifest")
        if noise.absolute <= 0 and noise.relative <= 0:
            raise ctx.err("noise", "absolute and relative cannot both be 0")
    else:
        noise = estimate_noise([r.repeats for r in readings])
        if noise is None:
            noise = NoiseModel(absolute=1e-3 * float(np.max(means)), relative=0.01,
                               source="default")
    # the model's own error per reading kind: a fraction, or "auto" ------------------------
    mt = ctx.table(data, "model_error", "model_error")
    ctx.finish(mt, DATA_KINDS + ("level", "tilt"), "model_error")
    shared: dict[str, dict[str, float]] = {}
    for part in ("level", "tilt"):
        lt = ctx.table(mt, part, f"model_error.{part}")
        ctx.finish(lt, DATA_KINDS, f"model_error.{part}")
        shared[part] = {k: ctx.number(lt, k, f"model_error.{part}.{k}", lo=0.0, hi=1.0)
                        for k in DATA_KINDS if k in lt}
    model_error: dict[str, float | str] = {}
    for k in DATA_KINDS:
        if k in mt:
            if mt[k] == "auto":
                model_error[k] = "auto"
            elif isinstance(mt[k], str):
                raise ctx.err(f"model_error.{k}", f'must be a fraction or "auto", got {mt[k]!r}')
            else:
                model_error[k] = ctx.number(mt, k, f"model_error.{k}", lo=0.0, hi=1.0)
    # a floor, so that bands with a vanishing signal do not dominate
    peak = float(np.max(np.abs(means)))
    if noise.absolute < 1e-6 * peak:
        noise = dataclasses.replace(noise, absolute=1e-6 * peak)

    return Session(path=p, scene_path=scene_path, scene=scene, wavelengths=wl, units=units,
                   instrument=instrument, calibration=mode, bandwidth_nm=bandwidth,
                   reference=reference, white=white,
                   dark=dark, noise=noise, objects=objects, readings=tuple(readings),
                   lines=lines, model_error=model_error, level_error=shared["level"],
                   tilt_error=shared["tilt"],
                   images=images)



def _bounds_and_prior(ctx: Any, tab: dict, f: str
                      ) -> tuple[dict[str, tuple[float | None, float | None]],
                                 dict[str, tuple[float, float]]]:
    """``objects.<name>.bounds`` ({parameter: [lower, upper]}, either end may be the string
    "none") and ``objects.<name>.prior`` ({parameter: {mean, sigma}}: a Gaussian prior), both
    checked against the parameters' physical ranges (a prior's mean inside the bounds)."""
    bt = ctx.table(tab, "bounds", f"{f}.bounds")
    ctx.finish(bt, PARAMETERS, f"{f}.bounds")
    bounds: dict[str, tuple[float | None, float | None]] = {}
    for k, v in bt.items():
        fk = f"{f}.bounds.{k}"
        if not isinstance(v, list) or len(v) != 2:
            raise ctx.err(fk, f"must be [lower, upper] (either may be \"none\"), got {v!r}")
        ends: list[float | None] = []
        for e in v:
            if e == "none":
                ends.append(None)
            elif isinstance(e, bool) or not isinstance(e, int | float) or not math.isfinite(e):
                raise ctx.err(fk, f"each end must be a finite number or \"none\", got {e!r}")
            else:
                ends.append(float(e))
        lo, hi = ends
        plo, open_ = PHYSICAL_LOWER[k]
        for e in (lo, hi):
            if e is not None and (e < plo or (open_ and e <= plo)):
                raise ctx.err(fk, f"{k} must be {'>' if open_ else '>='} {plo}, got {e}")
        if lo is not None and hi is not None and not lo < hi:
            raise ctx.err(fk, f"lower must be below upper, got [{lo}, {hi}]")
        if lo is not None or hi is not None:
            bounds[k] = (lo, hi)
    pt = ctx.table(tab, "prior", f"{f}.prior")
    ctx.finish(pt, PARAMETERS, f"{f}.prior")
    prior: dict[str, tuple[float, float]] = {}
    for k in pt:
        fk = f"{f}.prior.{k}"
        t = ctx.table(pt, k, fk)
        ctx.finish(t, ("mean", "sigma"), fk)
        plo, open_ = PHYSICAL_LOWER[k]
        mean = ctx.number(t, "mean", f"{fk}.mean", lo=plo, lo_open=open_)
        sigma = ctx.number(t, "sigma", f"{fk}.sigma", lo=0.0, lo_open=True)
        lo, hi = bounds.get(k, (None, None))
        if (lo is not None and mean < lo) or (hi is not None and mean > hi):
            raise ctx.err(f"{fk}.mean", f"{mean} lies outside {f}.bounds.{k} [{lo}, {hi}]")
        prior[k] = (mean, sigma)
    return bounds, prior
