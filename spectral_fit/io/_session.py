"""Spectroradiometer measurement sessions: a TOML manifest plus one spectrum file per reading.

The format is documented in ``docs/measurements.md``. :func:`load_session` reads a session
folder (or its ``session.toml``), resamples every spectrum onto the scene's wavelength grid,
subtracts the dark reading, converts units, and checks everything it can without geometry.
Every error is an :class:`~spectral_fit._runtime.errors.InputError` naming the file, the line and
the
field (e.g. ``session.toml, line 42: readings[3].object: unknown object 'blue'; the scene has
['yellow', 'red']``). Checks needing the geometry (a spot missing its object, the stated
distance) are made when the fit rasterises the spots (:func:`spectral_fit.fitting.prepare_fit`),
with the same kind of message.

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

__all__ = [
    "PARAMETERS",
    "DEFAULT_FREE",
    "KINDS",
    "RADIANCE_UNITS",
    "Reading",
    "WhiteStandard",
    "ObjectMeasurement",
    "NoiseModel",
    "Session",
    "load_session",
    "parse_session",
    "estimate_noise",
    "write_session",
]

#: Reflection-model parameters per object (docs/conventions.md), in this order everywhere.
PARAMETERS = ("alpha", "beta", "chi", "mu", "n", "gamma")
DEFAULT_FREE = ("alpha", "beta", "chi", "mu", "n")
KINDS = ("object", "interreflection")
CALIBRATION_MODES = ("white", "global", "none")

#: Radiance unit spellings → factor to W·sr⁻¹·m⁻²·nm⁻¹.
RADIANCE_UNITS: dict[str, float] = {}
for _prefix, _f in (("", 1.0), ("m", 1e-3), ("u", 1e-6), ("µ", 1e-6)):
    for _s in ("W.sr^-1.m^-2.nm^-1", "W/(sr m2 nm)", "W/sr/m2/nm", "W/(sr*m^2*nm)",
               "W sr-1 m-2 nm-1"):
        RADIANCE_UNITS[_prefix + _s] = _f
REFLECTANCE_UNITS = {"1": 1.0, "fraction": 1.0, "%": 0.01, "percent": 0.01}

_UNIT_RE = re.compile(r"^\s*#\s*units?\s*[:=]\s*(.+?)\s*$", re.IGNORECASE)


# ----------------------------------------------------------------------------- data classes


@dataclasses.dataclass(frozen=True)
class Reading:
    """One measured spot (possibly repeated).

    Attributes:
        id: unique name.
        object: the object the spot lies on (a name of the scene config).
        kind: "object" (object colour) or "interreflection".
        files: the spectrum files (repeats).
        repeats: (M, L) radiance of each repeat on the scene grid, W·sr⁻¹·m⁻²·nm⁻¹, dark
            subtracted.
        position: (3,) instrument entrance pupil, world metres.
        aim: (3,) the point aimed at, world metres.
        field_angle_deg: full angle of the measuring field.
        distance_m: measured distance to the spot (checked against the geometry) or None.
        line: line of the ``[[readings]]`` header in the manifest.
        index: position in the manifest's list.
    """

    id: str
    object: str
    kind: str
    files: tuple[Path, ...]
    repeats: np.ndarray
    position: np.ndarray
    aim: np.ndarray
    field_angle_deg: float
    distance_m: float | None
    line: int | None
    index: int

    @property
    def mean(self) -> np.ndarray:
        """(L,) mean radiance over the repeats."""
        return self.repeats.mean(axis=0)

    @property
    def field(self) -> str:
        return f"readings[{self.index}]"


@dataclasses.dataclass(frozen=True)
class WhiteStandard:
    """A diffuse reflectance standard read at the objects' position (calibration)."""

    reflectance: np.ndarray  # (L,)
    position: np.ndarray  # (3,)
    normal: np.ndarray  # (3,) unit
    instrument_position: np.ndarray  # (3,)
    repeats: np.ndarray  # (M, L) radiance, dark subtracted
    files: tuple[Path, ...]

    @property
    def mean(self) -> np.ndarray:
        return self.repeats.mean(axis=0)


@dataclasses.dataclass(frozen=True)
class ObjectMeasurement:
    """What the session says about one object: its measured reflectance and what to fit."""

    name: str
    reflectance: np.ndarray | None  # (L,) spectrophotometer S(λ), or None: the config's
    geometry: str  # "SCE" | "SCI"
    free: tuple[str, ...]
    start: dict[str, float]


@dataclasses.dataclass(frozen=True)
class NoiseModel:
    """σ of ONE reading: σ(λ)² = absolute² + (relative · L(λ))² (radiance units)."""

    absolute: float
    relative: float
    source: str  # "manifest", "repeats" or "default"

    def sigma(self, radiance: np.ndarray) -> np.ndarray:
        r = np.asarray(radiance, np.float64)
        return np.sqrt(self.absolute ** 2 + (self.relative * r) ** 2)


@dataclasses.dataclass(frozen=True)
class Session:
    """A loaded, validated measurement session (see ``docs/measurements.md``)."""

    path: Path  # the manifest
    scene_path: Path | None
    scene: Any  # spectral_fit.io.Scene
    wavelengths: np.ndarray
    units: str
    instrument: str
    calibration: str  # "white" | "global" | "none"
    bandwidth_nm: float  # instrument band-pass FWHM (0: none)
    reference: str | None  # "global" mode: object whose alpha is held fixed
    white: WhiteStandard | None
    dark: np.ndarray | None  # (L,) mean dark reading subtracted from everything
    noise: NoiseModel
    objects: dict[str, ObjectMeasurement]
    readings: tuple[Reading, ...]
    lines: dict[str, int] = dataclasses.field(repr=False, default_factory=dict)

    def line_of(self, field: str) -> int | None:
        """Manifest line of a dotted field (``readings[2].aim``), or of its table."""
        return _line_of(self.lines, field)

    def error(self, field: str, message: str) -> InputError:
        return InputError(message, path=self.path, field=field, line=self.line_of(field))

    @property
    def object_names(self) -> tuple[str, ...]:
        """The scene's objects in config order."""
        return tuple(o.name for o in self.scene.objects)

    def replace(self, **changes: Any) -> Session:
        return dataclasses.replace(self, **changes)

    def select(self, kinds: tuple[str, ...]) -> Session:
        """The same session with only the readings of the given kinds."""
        return self.replace(readings=tuple(r for r in self.readings if r.kind in kinds))


# ----------------------------------------------------------------------------- TOML lines


def _toml_lines(text: str) -> dict[str, int]:
    """Map dotted keys (``readings[3].aim``, ``white_standard``) to 1-based manifest lines.

    A small line scanner (tomllib keeps no positions): table headers ``[a.b]`` and array
    headers ``[[a]]`` (counted), then ``key = ...`` lines inside them.
    """
    out: dict[str, int] = {}
    prefix = ""
    counts: dict[str, int] = {}
    for i, raw in enumerate(text.splitlines(), start=1):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        m = re.match(r"^\[\[\s*([^\]]+?)\s*\]\]", s)
        if m:
            name = m.group(1).replace('"', "")
            k = counts.get(name, 0)
            counts[name] = k + 1
            prefix = f"{name}[{k}]"
            out.setdefault(prefix, i)
            continue
        m = re.match(r"^\[\s*([^\]]+?)\s*\]", s)
        if m:
            prefix = m.group(1).replace('"', "")
            out.setdefault(prefix, i)
            continue
        m = re.match(r'^("?[A-Za-z0-9_.\-]+"?)\s*=', s)
        if m:
            key = m.group(1).replace('"', "")
            out.setdefault(f"{prefix}.{key}" if prefix else key, i)
    return out


def _line_of(lines: dict[str, int], field: str) -> int | None:
    f = field
    while f:
        if f in lines:
            return lines[f]
        cut = max(f.rfind("."), f.rfind("["))
        if cut <= 0:
            break
        f = f[:cut]
    return None


class _Ctx:
    """Error construction with file + line + field."""

    def __init__(self, path: Path, lines: dict[str, int]) -> None:
        self.path = path
        self.lines = lines

    def err(self, field: str, message: str) -> InputError:
        return InputError(message, path=self.path, field=field, line=_line_of(self.lines, field))

    # typed getters ---------------------------------------------------------------------------
    def table(self, parent: dict, key: str, field: str, *, required: bool = False) -> dict:
        v = parent.get(key, None)
        if v is None:
            if required:
                raise self.err(field, "missing table")
            return {}
        if not isinstance(v, dict):
            raise self.err(field, f"must be a table, got {type(v).__name__}")
        return v

    def number(self, t: dict, key: str, field: str, default: Any = None, *,
               lo: float | None = None, hi: float | None = None, lo_open: bool = False) -> Any:
        if key not in t:
            if default is None:
                raise self.err(field, "missing (required)")
            return default
        v = t[key]
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise self.err(field, f"must be a number, got {v!r}")
        v = float(v)
        if not math.isfinite(v):
            raise self.err(field, f"must be finite, got {v}")
        if lo is not None and (v < lo or (lo_open and v <= lo)):
            raise self.err(field, f"must be {'>' if lo_open else '>='} {lo:g}, got {v:g}")
        if hi is not None and v > hi:
            raise self.err(field, f"must be <= {hi:g}, got {v:g}")
        return v

    def string(self, t: dict, key: str, field: str, default: Any = None) -> Any:
        if key not in t:
            if default is None:
                raise self.err(field, "missing (required)")
            return default
        v = t[key]
        if not isinstance(v, str):
            raise self.err(field, f"must be a string, got {v!r}")
        return v

    def vector(self, t: dict, key: str, field: str, default: Any = None, *,
               unit: bool = False) -> np.ndarray:
        if key not in t:
            if default is None:
                raise self.err(field, "missing (required): a list of 3 numbers (metres)")
            return np.asarray(default, np.float64)
        v = t[key]
        if (not isinstance(v, list) or len(v) != 3
                or any(isinstance(x, bool) or not isinstance(x, int | float) for x in v)):
            raise self.err(field, f"must be a list of 3 numbers, got {v!r}")
        a = np.asarray(v, np.float64)
        if not np.all(np.isfinite(a)) or np.max(np.abs(a)) > 1e4:
            raise self.err(field, f"must be finite coordinates in metres, got {v!r}")
        if unit:
            nrm = float(np.linalg.norm(a))
            if nrm < 1e-9:
                raise self.err(field, "must be a non-zero direction")
            a = a / nrm
        return a

    def files(self, t: dict, key: str, field: str, base: Path, *,
              required: bool = True) -> list[Path]:
        v = t.get(key, None)
        if v is None:
            if required:
                raise self.err(field, "missing (required): a list of spectrum files")
            return []
        if isinstance(v, str):
            v = [v]
        if not isinstance(v, list) or not v or not all(isinstance(x, str) and x for x in v):
            raise self.err(field, f"must be a non-empty list of file names, got {v!r}")
        if len(v) > 1000:
            raise self.err(field, f"too many files ({len(v)})")
        out = []
        for j, name in enumerate(v):
            p = (base / name)
            if not p.is_file():
                raise self.err(f"{field}[{j}]", f"file not found: {p}")
            out.append(p)
        return out

    def finish(self, t: dict, allowed: tuple[str, ...], field: str) -> None:
        extra = sorted(set(t) - set(allowed))
        if extra:
            where = f"{field}.{extra[0]}" if field else extra[0]
            raise self.err(where, f"unknown key; expected one of {sorted(allowed)}")


# ----------------------------------------------------------------------------- spectra


def _file_unit(text: str) -> tuple[str | None, int | None]:
    for i, line in enumerate(text.splitlines(), start=1):
        m = _UNIT_RE.match(line)
        if m:
            return m.group(1), i
    return None, None


def _read_spectra(path: Path, wl: np.ndarray, *, kind: str, units: str,
                  allow_negative: bool = False) -> np.ndarray:
    """Read a spectrum file → (M, L) on the grid ``wl``, converted to W·sr⁻¹·m⁻²·nm⁻¹ (or a
    reflectance fraction). ``kind``: "radiance" or "reflectance"."""
    from ..color import parse_spectrum_text, resample

    text = read_text(path, encoding="utf-8-sig", max_bytes=16 * 1024 * 1024,
                     what="a spectrum")
    unit, uline = _file_unit(text)
    if kind == "radiance":
        factor = RADIANCE_UNITS[units]
        if unit is not None:
            if unit not in RADIANCE_UNITS:
                raise InputError(f"unit {unit!r} is not a spectral radiance unit (expected "
                                 f"{units!r})", path=path, line=uline, field="unit")
            if unit != units and RADIANCE_UNITS[unit] != factor:
                raise InputError(f"unit mismatch: the file says {unit!r}, the session says "
                                 f"{units!r}", path=path, line=uline, field="unit")
            factor = RADIANCE_UNITS[unit]
    else:
        factor = 1.0
        if unit is not None:
            if unit not in REFLECTANCE_UNITS:
                raise InputError(f"unit {unit!r} is not a reflectance unit (expected one of "
                                 f"{sorted(REFLECTANCE_UNITS)})", path=path, line=uline,
                                 field="unit")
            factor = REFLECTANCE_UNITS[unit]
    w, v = parse_spectrum_text(text, path=path, allow_negative=allow_negative)
    v = np.atleast_2d(v)
    if v.shape[0] > 1000:
        raise InputError(f"too many value columns ({v.shape[0]})", path=path)
    out = resample(w, v, wl, path=path, field=f"{kind} spectrum") * factor
    if not np.all(np.isfinite(out)) or np.max(np.abs(out)) > 1e12:
        raise InputError("values out of range after unit conversion", path=path)
    return out


def _reflectance_value(ctx: _Ctx, t: dict, key: str, field: str, base: Path,
                       wl: np.ndarray) -> np.ndarray:
    v = t[key]
    if isinstance(v, bool):
        raise ctx.err(field, f"must be a number in [0, 1] or a spectrum file, got {v!r}")
    if isinstance(v, int | float):
        x = ctx.number(t, key, field, lo=0.0, hi=1.0, lo_open=True)
        return np.full(wl.shape, x)
    if isinstance(v, str):
        p = base / v
        if not p.is_file():
            raise ctx.err(field, f"file not found: {p}")
        s = _read_spectra(p, wl, kind="reflectance", units="1")
        if s.shape[0] != 1:
            raise InputError(f"expected one reflectance column, found {s.shape[0]}", path=p)
        s = s[0]
        if np.any(s > 1.5):
            raise InputError(f"reflectance {s.max():g} > 1.5: give a fraction or declare "
                             "'# unit: %'", path=p, field="reflectance")
        return s
    raise ctx.err(field, f"must be a number in [0, 1] or a spectrum file, got {v!r}")


def estimate_noise(groups: list[np.ndarray], *, floor_abs: float = 1e-9) -> NoiseModel | None:
    """Fit σ² = a² + (b L)² to the sample variances of repeated readings.

    Args:
        groups: arrays (M_i, L) of repeats of the same spot (groups with M_i < 2 are ignored).

    Returns:
        the noise of ONE reading, or None when no spot was repeated. Linear least squares of
        s²(λ) on [1, mean(λ)²] over all bands of all repeated spots, with both coefficients
        constrained >= 0 (non-negative least squares on two unknowns).
    """
    rows, rhs, dof = [], [], []
    for g in groups:
        g = np.asarray(g, np.float64)
        if g.ndim != 2 or g.shape[0] < 2:
            continue
        m = g.mean(axis=0)
        s2 = g.var(axis=0, ddof=1)
        rows.append(np.stack([np.ones_like(m), m * m], -1))
        rhs.append(s2)
        dof.append(np.full(m.shape, g.shape[0] - 1.0))
    if not rows:
        return None
    A = np.concatenate(rows)
    y = np.concatenate(rhs)
    w = np.concatenate(dof)
    # weight by dof / expected variance (iterate once: variance of s² ∝ σ⁴ / dof)
    coef = np.array([np.mean(y), 0.0])
    for _ in range(3):
        pred = np.maximum(A @ coef, 1e-30)
        sw = np.sqrt(w) / pred
        coef = _nnls2(A * sw[:, None], y * sw)
    a2, b2 = coef
    return NoiseModel(absolute=float(math.sqrt(max(a2, floor_abs ** 2))),
                      relative=float(math.sqrt(max(b2, 0.0))), source="repeats")


def _nnls2(A: np.ndarray, y: np.ndarray) -> np.ndarray:
    best, best_r = np.zeros(2), float(np.sum(y * y))
    cands = []
    sol, *_ = np.linalg.lstsq(A, y, rcond=None)
    cands.append(sol)
    for j in range(2):
        c = np.zeros(2)
        d = float(A[:, j] @ A[:, j])
        if d > 0:
            c[j] = float(A[:, j] @ y) / d
        cands.append(c)
    for c in cands:
        if np.all(c >= 0):
            r = float(np.sum((A @ c - y) ** 2))
            if r < best_r:
                best, best_r = c, r
    return best


# ----------------------------------------------------------------------------- loader


def load_session(path: str | os.PathLike[str], *, scene: Any = None) -> Session:
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
                  scene: Any = None) -> Session:
    """Validate a parsed manifest (a dict as from ``tomllib``); see :func:`load_session`."""
    p = Path(path)
    base = p.parent
    lines = _toml_lines(text)
    ctx = _Ctx(p, lines)
    if not isinstance(data, dict):
        raise ctx.err("<root>", "must be a table")
    ctx.finish(data, ("session", "instrument", "calibration", "white_standard", "dark", "noise",
                      "objects", "readings"), "")

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
        ctx.finish(tab, ("reflectance", "geometry", "free", "start"), f)
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
        objects[name] = ObjectMeasurement(name=name, reflectance=refl, geometry=geom,
                                          free=tuple(x for x in PARAMETERS if x in free),
                                          start=start)

    # readings -------------------------------------------------------------------------------
    rl = data.get("readings", None)
    if not isinstance(rl, list) or not rl:
        raise ctx.err("readings", "need at least one [[readings]] table")
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
    means = np.stack([r.mean for r in readings])
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
    # a floor, so that bands with a vanishing signal do not dominate
    peak = float(np.max(np.abs(means)))
    if noise.absolute < 1e-6 * peak:
        noise = dataclasses.replace(noise, absolute=1e-6 * peak)

    return Session(path=p, scene_path=scene_path, scene=scene, wavelengths=wl, units=units,
                   instrument=instrument, calibration=mode, bandwidth_nm=bandwidth,
                   reference=reference, white=white,
                   dark=dark, noise=noise, objects=objects, readings=tuple(readings),
                   lines=lines)


# ----------------------------------------------------------------------------- writer


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | np.integer):
        return str(int(v))
    if isinstance(v, float | np.floating):
        return repr(float(v))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, list | tuple | np.ndarray):
        return "[" + ", ".join(_toml_value(x) for x in list(np.asarray(v).tolist()
                                                          if isinstance(v, np.ndarray) else v)
                               ) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _spectrum_text(wl: np.ndarray, values: np.ndarray, unit: str, comment: str = "") -> str:
    values = np.atleast_2d(np.asarray(values, np.float64))
    head = [f"# {line}" for line in comment.splitlines() if line] + [f"# unit: {unit}"]
    cols = ["wavelength_nm"] + (["value"] if values.shape[0] == 1 else
                                [f"value_{k + 1}" for k in range(values.shape[0])])
    rows = [",".join(cols)]
    for j, w in enumerate(wl):
        rows.append(",".join([f"{w:g}"] + [f"{v:.12g}" for v in values[:, j]]))
    return "\n".join(head + rows) + "\n"


def write_session(
    folder: str | os.PathLike[str],
    *,
    scene: str,
    wavelengths: Any,
    readings: list[dict[str, Any]],
    instrument: dict[str, Any] | None = None,
    white: dict[str, Any] | None = None,
    dark: Any = None,
    objects: dict[str, dict[str, Any]] | None = None,
    calibration: dict[str, Any] | None = None,
    noise: dict[str, float] | None = None,
    notes: str = "",
    units: str = "W.sr^-1.m^-2.nm^-1",
) -> Path:
    """Write a session folder in the documented format (``docs/measurements.md``).

    Args:
        scene: the scene config's path as written into the manifest (relative to ``folder``).
        wavelengths: (L,) grid of every spectrum given here.
        readings: dicts with ``id``, ``object``, ``aim`` (3,), ``spectra`` (M, L) radiance (one
            file per repeat), and optional ``kind``, ``position``, ``field_angle_deg``,
            ``distance_m``.
        instrument: optional ``position`` and ``field_angle_deg`` defaults.
        white: optional ``reflectance`` (number or (L,)), ``position``, ``normal``,
            ``spectra`` (M, L).
        dark: optional (M, L) dark readings.
        objects: optional per object ``reflectance`` (L,), ``geometry``, ``free``, ``start``.

    Returns:
        the manifest's path. Files are written atomically.
    """
    from .._runtime.fileio import atomic_write_text

    root = Path(folder)
    wl = np.asarray(wavelengths, np.float64)
    out = ["# Spectroradiometer session (format: docs/measurements.md)", "", "[session]",
           "format = 1", f"scene = {_toml_value(scene)}", f"units = {_toml_value(units)}"]
    if notes:
        out.append(f"notes = {_toml_value(notes)}")
    if instrument:
        out += ["", "[instrument]"] + [f"{k} = {_toml_value(v)}" for k, v in instrument.items()]
    if calibration:
        out += ["", "[calibration]"] + [f"{k} = {_toml_value(v)}"
                                        for k, v in calibration.items()]
    if noise:
        out += ["", "[noise]"] + [f"{k} = {_toml_value(v)}" for k, v in noise.items()]
    if dark is not None:
        d = np.atleast_2d(dark)
        names = []
        for k, row in enumerate(d):
            name = f"dark/dark_{k + 1}.csv"
            atomic_write_text(root / name, _spectrum_text(wl, row, units, "dark reading"))
            names.append(name)
        out += ["", "[dark]", f"readings = {_toml_value(names)}"]
    if white:
        out += ["", "[white_standard]"]
        refl = white["reflectance"]
        if np.ndim(refl) == 0:
            out.append(f"reflectance = {_toml_value(float(refl))}")
        else:
            atomic_write_text(root / "white" / "reflectance.csv",
                              _spectrum_text(wl, refl, "1", "white standard reflectance"))
            out.append('reflectance = "white/reflectance.csv"')
        out.append(f"position = {_toml_value(list(map(float, white['position'])))}")
        out.append(f"normal = {_toml_value(list(map(float, white['normal'])))}")
        names = []
        for k, row in enumerate(np.atleast_2d(white["spectra"])):
            name = f"white/white_{k + 1}.csv"
            atomic_write_text(root / name, _spectrum_text(wl, row, units, "white standard"))
            names.append(name)
        out.append(f"readings = {_toml_value(names)}")
    for name, spec in (objects or {}).items():
        out += ["", f"[objects.{name}]"]
        for k, v in spec.items():
            if k == "reflectance":
                fn = f"reflectance/{name}.csv"
                atomic_write_text(root / fn, _spectrum_text(
                    wl, v, "1", f"{name}: spectrophotometer reflectance "
                    f"({spec.get('geometry', 'SCE')})"))
                out.append(f'reflectance = "{fn}"')
            else:
                out.append(f"{k} = {_toml_value(v)}")
    for r in readings:
        out += ["", "[[readings]]"]
        files = []
        for k, row in enumerate(np.atleast_2d(r["spectra"])):
            fn = f"readings/{r['id']}_{k + 1}.csv"
            atomic_write_text(root / fn, _spectrum_text(wl, row, units, f"reading {r['id']}"))
            files.append(fn)
        for k in ("id", "object", "kind"):
            if k in r:
                out.append(f"{k} = {_toml_value(r[k])}")
        out.append(f"files = {_toml_value(files)}")
        for k in ("aim", "position"):
            if k in r:
                out.append(f"{k} = {_toml_value([float(x) for x in r[k]])}")
        for k in ("field_angle_deg", "distance_m"):
            if k in r:
                out.append(f"{k} = {_toml_value(float(r[k]))}")
    manifest = root / "session.toml"
    atomic_write_text(manifest, "\n".join(out) + "\n")
    return manifest
