"""Wavelength grids, resampling of measured spectra, and spectrum files.

Conventions (docs/conventions.md, 'Conventions'): wavelengths in nm, default grid 380–780 nm at 5 nm
(81 samples). Spectra are arrays whose LAST axis runs over wavelength, shape ``(..., L)``. This
module is plain NumPy: it is the data layer, used before anything is handed to JAX.
"""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path

import numpy as np

from .._runtime.errors import InputError

__all__ = [
    "DEFAULT_START_NM",
    "DEFAULT_END_NM",
    "DEFAULT_STEP_NM",
    "EXTRAPOLATION_MARGIN_NM",
    "wavelength_grid",
    "default_wavelengths",
    "validate_wavelengths",
    "validate_spectrum",
    "resample",
    "read_spectrum_csv",
    "colour_sd",
    "parse_spectrum_text",
]

DEFAULT_START_NM = 380.0
DEFAULT_END_NM = 780.0
DEFAULT_STEP_NM = 5.0
#: How far (nm) a target grid may reach beyond the measured range; inside this margin the end
#: value is held constant, beyond it :func:`resample` refuses.
EXTRAPOLATION_MARGIN_NM = 5.0


def wavelength_grid(
    start: float = DEFAULT_START_NM, end: float = DEFAULT_END_NM, step: float = DEFAULT_STEP_NM
) -> np.ndarray:
    """Uniform wavelength grid ``start, start + step, ..., end`` in nm, float64, shape (L,).

    ``end`` is included when ``(end - start)`` is a multiple of ``step`` (to 1e-9 nm).
    """
    if not (math.isfinite(start) and math.isfinite(end) and math.isfinite(step)):
        raise InputError("start, end and step must be finite", field="wavelengths")
    if step <= 0 or end <= start:
        raise InputError(
            f"need start < end and step > 0, got start={start}, end={end}, step={step}",
            field="wavelengths",
        )
    n = int(math.floor((end - start) / step + 1e-9)) + 1
    return start + step * np.arange(n, dtype=np.float64)


def default_wavelengths() -> np.ndarray:
    """The default grid: 380–780 nm at 5 nm, shape (81,)."""
    return wavelength_grid()


def validate_wavelengths(
    wavelengths: object, *, path: str | os.PathLike[str] | None = None, field: str = "wavelengths"
) -> np.ndarray:
    """Return ``wavelengths`` as float64 (L,), checking it is finite, strictly increasing, in nm.

    Raises :class:`InputError` naming ``path`` and ``field`` otherwise.
    """
    try:
        wl = np.asarray(wavelengths, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"not numeric ({exc})", path=path, field=field) from None
    if wl.ndim != 1 or wl.size < 2:
        raise InputError(
            f"need a 1-D array of at least 2 wavelengths, got shape {wl.shape}", path=path,
            field=field,
        )
    if not np.all(np.isfinite(wl)):
        raise InputError("contains NaN or infinite values", path=path, field=field)
    if np.any(np.diff(wl) <= 0):
        k = int(np.argmax(np.diff(wl) <= 0))
        raise InputError(
            f"wavelengths must increase strictly; {wl[k]:g} nm is followed by {wl[k + 1]:g} nm",
            path=path, field=field,
        )
    if wl[0] < 100.0 or wl[-1] > 10000.0:
        raise InputError(
            f"range {wl[0]:g}–{wl[-1]:g} does not look like nanometres", path=path, field=field
        )
    return wl


def validate_spectrum(
    values: object,
    n_wavelengths: int,
    *,
    path: str | os.PathLike[str] | None = None,
    field: str = "values",
    allow_negative: bool = True,
) -> np.ndarray:
    """Return ``values`` as float64 (..., L) with L == ``n_wavelengths``, all finite.

    ``allow_negative=False`` also rejects negative entries (radiance, reflectance).
    """
    try:
        v = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"not numeric ({exc})", path=path, field=field) from None
    if v.ndim == 0 or v.shape[-1] != n_wavelengths:
        raise InputError(
            f"last axis must have {n_wavelengths} samples (one per wavelength), got shape "
            f"{v.shape}", path=path, field=field,
        )
    bad = ~np.isfinite(v)
    if bad.any():
        idx = np.argwhere(bad)[0]
        raise InputError(f"NaN or infinite value at index {tuple(int(i) for i in idx)}",
                         path=path, field=field)
    if not allow_negative and (v < 0).any():
        idx = np.argwhere(v < 0)[0]
        raise InputError(f"negative value {v[tuple(idx)]:g} at index "
                         f"{tuple(int(i) for i in idx)}", path=path, field=field)
    return v


def resample(
    wavelengths_in: object,
    values_in: object,
    wavelengths_out: object | None = None,
    *,
    margin_nm: float = EXTRAPOLATION_MARGIN_NM,
    method: str = "linear",
    path: str | os.PathLike[str] | None = None,
    field: str = "spectrum",
) -> np.ndarray:
    """Resample spectra measured at ``wavelengths_in`` onto ``wavelengths_out``.

    Args:
        wavelengths_in: (Lin,) nm, strictly increasing, any spacing.
        values_in: (..., Lin) spectra.
        wavelengths_out: (Lout,) nm; default :func:`default_wavelengths`.
        margin_nm: the target grid may extend at most this far outside the measured range; the
            nearest measured value is held there. Further out the call fails, because inventing
            spectra the instrument did not see would bias every fit.
        method: ``"linear"`` (piecewise linear: no overshoot, keeps non-negative data non-negative;
            the default) or ``"colour"`` (colour-science's default interpolator: Sprague (1880)
            for uniformly spaced input, cubic spline otherwise).

    Returns:
        (..., Lout) float64.
    """
    wl_in = validate_wavelengths(wavelengths_in, path=path, field=f"{field} wavelengths")
    v = validate_spectrum(values_in, wl_in.size, path=path, field=field)
    wl_out = default_wavelengths() if wavelengths_out is None else validate_wavelengths(
        wavelengths_out, field="target wavelengths")
    lo, hi = wl_in[0] - margin_nm, wl_in[-1] + margin_nm
    if wl_out[0] < lo - 1e-9 or wl_out[-1] > hi + 1e-9:
        raise InputError(
            f"measured range {wl_in[0]:g}–{wl_in[-1]:g} nm does not cover the grid "
            f"{wl_out[0]:g}–{wl_out[-1]:g} nm (extrapolation allowed up to {margin_nm:g} nm)",
            path=path, field=field,
        )
    flat = v.reshape(-1, wl_in.size)
    if method == "linear":
        out = np.stack([np.interp(wl_out, wl_in, row) for row in flat])
    elif method == "colour":
        import colour

        inside = np.clip(wl_out, wl_in[0], wl_in[-1])
        out = np.stack(
            [colour.SpectralDistribution(dict(zip(wl_in, row, strict=True)))[inside]
             for row in flat]
        )
    else:
        raise InputError(f"unknown method {method!r}; use 'linear' or 'colour'", field="method")
    return out.reshape(*v.shape[:-1], wl_out.size)


_MAX_SPECTRUM_BYTES = 64 * 1024 * 1024


def read_spectrum_csv(
    path: str | os.PathLike[str],
    *,
    allow_negative: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Read a spectrum exported by an instrument as delimited text.

    Format: one row per wavelength; first column wavelength in nm, then one or more value columns
    (repeated readings). Delimiter comma, semicolon, tab or spaces. An optional header row of
    names and ``#`` comment lines are skipped.

    Returns:
        ``(wavelengths (L,), values (L,) or (M, L))``: one row per value column when there are
        several.

    Raises:
        InputError naming the file, the line and the column for any malformed content
        (non-numeric cell, ragged rows, NaN, negative values unless ``allow_negative``,
        non-increasing wavelengths, fewer than 2 rows).
    """
    from .._runtime.fileio import read_text

    p = Path(path)
    text = read_text(p, encoding="utf-8-sig", max_bytes=_MAX_SPECTRUM_BYTES, what="a spectrum")
    return parse_spectrum_text(text, path=p, allow_negative=allow_negative)


def _split(line: str) -> list[str]:
    for delim in (",", ";", "\t"):
        if delim in line:
            return [c.strip() for c in next(csv.reader(io.StringIO(line), delimiter=delim))]
    return line.split()


def parse_spectrum_text(
    text: str, *, path: str | os.PathLike[str] | None = None, allow_negative: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Parse the text of a spectrum file (see :func:`read_spectrum_csv`)."""
    rows: list[tuple[int, list[float]]] = []
    header_seen = False
    ncols = None
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        cells = _split(s)
        if any(c == "" for c in cells):
            raise InputError("empty cell", path=path, line=lineno)
        try:
            vals = [float(c) for c in cells]
        except ValueError:
            if not rows and not header_seen:
                header_seen = True
                continue
            bad = next(i for i, c in enumerate(cells) if not _is_float(c))
            raise InputError(f"column {bad + 1}: not a number: {cells[bad]!r}", path=path,
                             line=lineno) from None
        if len(vals) < 2:
            raise InputError("need a wavelength and at least one value per row", path=path,
                             line=lineno)
        if ncols is None:
            ncols = len(vals)
        elif len(vals) != ncols:
            raise InputError(f"expected {ncols} columns, found {len(vals)}", path=path,
                             line=lineno)
        for j, x in enumerate(vals):
            if not math.isfinite(x):
                raise InputError(f"column {j + 1}: {cells[j]!r} is not a finite number",
                                 path=path, line=lineno)
            if j > 0 and x < 0 and not allow_negative:
                raise InputError(f"column {j + 1}: negative value {x:g}", path=path, line=lineno)
        if rows and vals[0] <= rows[-1][1][0]:
            raise InputError(
                f"wavelength {vals[0]:g} nm does not increase (previous {rows[-1][1][0]:g} nm)",
                path=path, line=lineno,
            )
        rows.append((lineno, vals))
    if len(rows) < 2:
        raise InputError("need at least 2 rows of (wavelength, value)", path=path)
    data = np.array([r for _, r in rows], dtype=np.float64)
    wl = validate_wavelengths(data[:, 0], path=path, field="wavelength column")
    values = data[:, 1:].T
    return wl, values[0] if values.shape[0] == 1 else values


def _is_float(c: str) -> bool:
    try:
        float(c)
    except ValueError:
        return False
    return True


def colour_sd(sd: object, wavelengths: np.ndarray | None = None) -> np.ndarray:
    """Sample a colour-science spectral distribution (or multi-distribution) on a grid.

    Uses colour's own interpolation; outside the distribution's range, colour's default
    extrapolation (constant) applies. Returns (L,) or (L, M) float64.
    """
    wl = default_wavelengths() if wavelengths is None else np.asarray(wavelengths, np.float64)
    return np.asarray(sd[wl], dtype=np.float64)  # type: ignore[index]
