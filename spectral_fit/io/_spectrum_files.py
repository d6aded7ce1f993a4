"""Spectrum files of a measurement session: radiance and reflectance units (a file may declare
its own, ``# unit: ...``), files read and resampled onto the scene's wavelength grid (L,) as
(M, L) W·sr⁻¹·m⁻²·nm⁻¹ or reflectance fractions, and reflectance values given as a number or a
file.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .._runtime.errors import InputError
from .._runtime.fileio import read_text
from ._manifest import _Ctx

__all__ = ["RADIANCE_UNITS"]

#: Radiance unit spellings → factor to W·sr⁻¹·m⁻²·nm⁻¹.
RADIANCE_UNITS: dict[str, float] = {}
for _prefix, _f in (("", 1.0), ("m", 1e-3), ("u", 1e-6), ("µ", 1e-6)):
    for _s in ("W.sr^-1.m^-2.nm^-1", "W/(sr m2 nm)", "W/sr/m2/nm", "W/(sr*m^2*nm)",
               "W sr-1 m-2 nm-1"):
        RADIANCE_UNITS[_prefix + _s] = _f
REFLECTANCE_UNITS = {"1": 1.0, "fraction": 1.0, "%": 0.01, "percent": 0.01}

_UNIT_RE = re.compile(r"^\s*#\s*units?\s*[:=]\s*(.+?)\s*$", re.IGNORECASE)


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
