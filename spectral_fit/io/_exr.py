"""Spectral and RGB OpenEXR images.

Spectral images use the layout of Fichet, Pacanowski & Wilkie, "An OpenEXR Layout for Spectral
Images", JCGT 10(3), 2021: one channel per wavelength, named

    <component>.<number><multiplier?><unit>

with component ``S0`` (emissive; ``S1``..``S3`` are the other Stokes components) or ``T``
(reflective/transmissive), the number written with a comma as decimal separator (EXR reserves the
dot for layers; a dot is also accepted on read), an optional SI multiplier (``Y Z E P T G M k h da
d c m u n p f a z y``; ``µ``/``μ`` are read as ``u``) and the unit ``m`` (wavelength) or ``Hz``
(frequency, converted with the speed of light). Examples: ``S0.550,000000nm``, ``S0.550nm``,
``T.0,55um``, ``S0.545,077THz``. Attributes ``spectralLayoutVersion = "1.0"`` and, for emissive
images, ``emissiveUnits = "W.m^-2.sr^-1"`` (per nm: spectral radiance W·sr⁻¹·m⁻²·nm⁻¹).

Reading (:func:`read_spectral_exr`, :func:`read_spectral_exr_ex`):

* emissive ``S0`` and reflective ``T`` images, half or float pixels (returned as float32);
* polarisation components ``S1``..``S3`` are ignored (``S0`` is the unpolarised radiance), as are
  all non-spectral channels (RGB previews, alpha, depth);
* malformed files raise :class:`~spectral_fit._runtime.errors.InputError` naming the file and the
channel:
  no spectral channel, a channel that starts like a spectral one but does not parse, bi-spectral
  channels, the same wavelength spelled twice, a regular grid with bands missing, emissive and
  reflective channels in one file (unless ``kind`` picks one), UINT or sub-sampled channels, pixel
  arrays of the wrong size, NaN/inf pixels, truncated or corrupt files, non-EXR files, missing
  files. No OpenEXR exception escapes unwrapped.

Writing (:func:`write_spectral_exr`): float32 (or half) pixels, ZIP compression, the layout's
attributes, and R, G, B preview channels in linear sRGB (colour-science's XYZ → sRGB, no chromatic
adaptation). For emissive images the preview is absolute XYZ (683 lm/W) divided by the image's
99th-percentile luminance (attribute ``previewLuminance``, cd/m²), so typical content lies in
[0, 1]; for reflective images it is the reflectance under CIE D65 (white = 1).
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import re
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Any

import numpy as np

from .._runtime.errors import InputError
from .._runtime.fileio import atomic_path
from ..color import validate_wavelengths

__all__ = [
    "SpectralImage",
    "read_channels_exr",
    "EMISSIVE_UNITS",
    "parse_channel_name",
    "channel_name",
    "read_spectral_exr",
    "read_spectral_exr_ex",
    "write_spectral_exr",
    "read_rgb_exr",
]

EMISSIVE_UNITS = "W.m^-2.sr^-1"
LAYOUT_VERSION = "1.0"
#: Speed of light in vacuum, m/s (exact, SI).
SPEED_OF_LIGHT = 299_792_458

_EXR_MAGIC = b"\x76\x2f\x31\x01"
#: Refuse images with more samples than this (guards against corrupt headers asking for huge
#: allocations): 2**31 float32 samples = 8 GiB.
MAX_SAMPLES = 2**31

_MULTIPLIERS: dict[str, int] = {
    "Y": 24, "Z": 21, "E": 18, "P": 15, "T": 12, "G": 9, "M": 6, "k": 3, "h": 2, "da": 1,
    "": 0, "d": -1, "c": -2, "m": -3, "u": -6, "n": -9, "p": -12, "f": -15, "a": -18,
    "z": -21, "y": -24,
}
_MULT_RE = "Y|Z|E|P|T|G|M|k|h|da|d|c|m|u|µ|μ|n|p|f|a|z|y"
# The layout's quantity regex (Fichet et al. 2021, §3), with '.' also allowed as decimal mark.
_QUANTITY = rf"(\d*[,.]?\d*(?:[eE][-+]?\d+)?)({_MULT_RE})?(m|Hz)"
_SPECTRAL_RE = re.compile(rf"^(S[0-3]|T)\.{_QUANTITY}$")
_BISPECTRAL_RE = re.compile(rf"^T\.{_QUANTITY}\.{_QUANTITY}$")
_PREFIX_RE = re.compile(r"^(S[0-3]|T)\.")

_KINDS = {"emissive": "S0", "reflective": "T"}


@dataclass(frozen=True)
class SpectralImage:
    """A spectral image read from disk.

    Attributes:
        wavelengths: (L,) float64, nm, strictly increasing.
        image: (H, W, L) float32; spectral radiance W·sr⁻¹·m⁻²·nm⁻¹ for emissive images,
            reflectance/transmittance (unitless) for reflective ones.
        kind: ``"emissive"`` (``S0`` channels) or ``"reflective"`` (``T`` channels).
        channels: (L,) the channel names, in wavelength order.
        attributes: the other header attributes (name -> value).
    """

    wavelengths: np.ndarray
    image: np.ndarray
    kind: str
    channels: tuple[str, ...]
    attributes: dict[str, Any]


def parse_channel_name(name: str) -> tuple[str, float] | None:
    """Parse a spectral channel name of the layout into ``(component, wavelength_nm)``.

    Returns ``None`` for names that do not match (non-spectral channels). The number is
    converted exactly (decimal arithmetic) for wavelengths; frequencies use λ = c / f.
    """
    m = _SPECTRAL_RE.match(name)
    if m is None:
        return None
    component, number, mult, unit = m.group(1), m.group(2), m.group(3) or "", m.group(4)
    number = number.replace(",", ".")
    if not any(ch.isdigit() for ch in number):
        return None
    try:
        value = Decimal(number)
    except InvalidOperation:
        return None
    if mult in ("µ", "μ"):
        mult = "u"
    scaled = value.scaleb(_MULTIPLIERS[mult])  # in m or Hz
    if unit == "m":
        nm = float(scaled.scaleb(9))
    else:
        nm = math.inf if scaled == 0 else float(Decimal(SPEED_OF_LIGHT) / scaled * Decimal(10**9))
    if not math.isfinite(nm) or nm <= 0:
        return None
    return component, nm


def channel_name(component: str, wavelength_nm: float) -> str:
    """The channel name written for a wavelength: six decimals with a comma (``550,000000``),
    more digits only when six would not represent the float exactly."""
    text = f"{wavelength_nm:.6f}"
    if float(text) != float(wavelength_nm):
        text = np.format_float_positional(float(wavelength_nm), unique=True, trim="-")
    return f"{component}.{text.replace('.', ',')}nm"


# --------------------------------------------------------------------------------------------
# reading


def _check_file(p: Path) -> None:
    try:
        with open(p, "rb") as fh:
            magic = fh.read(4)
    except FileNotFoundError:
        raise InputError("no such file", path=p) from None
    except IsADirectoryError:
        raise InputError("is a directory, not an OpenEXR file", path=p) from None
    except OSError as exc:
        raise InputError(f"cannot read ({exc.strerror or exc})", path=p) from None
    if magic != _EXR_MAGIC:
        raise InputError("not an OpenEXR file (bad magic number)", path=p)


def _open(p: Path, *, header_only: bool) -> Any:
    """Open with the OpenEXR.File API, turning every failure into InputError."""
    import OpenEXR

    out = io.StringIO()
    try:
        # the binding reports some pixel-decoding failures by printing a warning: capture it
        with contextlib.redirect_stdout(out):
            f = OpenEXR.File(str(p), separate_channels=True, header_only=header_only)
            header = f.header()
            if header_only:
                channels = {c.name: c for c in header.get("channels", [])}
            else:
                channels = f.channels()
    except Exception as exc:  # OpenEXR raises RuntimeError, ValueError, UnicodeDecodeError ...
        detail = " ".join(str(exc).split()) or type(exc).__name__
        raise InputError(f"corrupt or truncated OpenEXR file ({detail})", path=p) from None
    warning = out.getvalue().strip()
    if warning:
        raise InputError(f"corrupt or truncated OpenEXR file ({warning})", path=p)
    return f, header, channels


def _data_window(header: dict, p: Path) -> tuple[int, int]:
    try:
        lo, hi = header["dataWindow"]
        w = int(hi[0]) - int(lo[0]) + 1
        h = int(hi[1]) - int(lo[1]) + 1
    except Exception:
        raise InputError("header has no valid dataWindow", path=p, field="dataWindow") from None
    if w <= 0 or h <= 0:
        raise InputError(f"empty data window ({w} x {h})", path=p, field="dataWindow")
    return h, w


def _header_attributes(header: dict) -> dict[str, Any]:
    skip = {"channels", "dataWindow", "displayWindow", "compression", "lineOrder",
            "pixelAspectRatio", "screenWindowCenter", "screenWindowWidth", "type", "tiles"}
    return {k: v for k, v in header.items() if k not in skip}


def _classify(names: list[str], p: Path) -> dict[str, dict[float, str]]:
    """component -> {wavelength_nm: channel name}, rejecting malformed/duplicate channels."""
    comps: dict[str, dict[float, str]] = {}
    for name in names:
        if not _PREFIX_RE.match(name):
            continue  # non-spectral channel (R, G, B, A, Z, layer.R ...)
        if _BISPECTRAL_RE.match(name):
            raise InputError("bi-spectral (re-radiation) channels are not supported", path=p,
                             field=f"channel {name!r}")
        parsed = parse_channel_name(name)
        if parsed is None:
            raise InputError(
                "spectral channel name does not give a positive wavelength or frequency "
                "(expected e.g. 'S0.550,000000nm' or 'T.0,55um')", path=p,
                field=f"channel {name!r}")
        comp, nm = parsed
        grid = comps.setdefault(comp, {})
        for other_nm, other in grid.items():
            if abs(other_nm - nm) <= 1e-6 * max(1.0, nm):
                raise InputError(
                    f"duplicated wavelength {nm:g} nm (also channel {other!r})", path=p,
                    field=f"channel {name!r}")
        grid[nm] = name
    return comps


def _check_missing_bands(wl: np.ndarray, names: list[str], p: Path) -> None:
    """Reject a regular grid with a few bands missing (a non-uniform grid is otherwise fine)."""
    if wl.size < 3:
        return
    d = np.diff(wl)
    step = d.min()
    ratio = d / step
    k = np.rint(ratio)
    if not np.allclose(ratio, k, rtol=0, atol=1e-6) or np.all(k == 1):
        return
    full = int(k.sum()) + 1
    missing = full - wl.size
    if missing <= max(1, int(0.1 * full)):
        gap = int(np.argmax(k > 1))
        raise InputError(
            f"wavelength grid has a step of {step:g} nm but {missing} band(s) missing, first "
            f"between {wl[gap]:g} and {wl[gap + 1]:g} nm", path=p,
            field=f"channel after {names[gap]!r}")


def read_spectral_exr_ex(
    path: str | os.PathLike[str], *, kind: str | None = None, allow_gaps: bool = False
) -> SpectralImage:
    """Read a spectral OpenEXR image (Fichet et al. 2021 layout) with its metadata.

    Args:
        path: the file.
        kind: ``None`` (whichever of emissive ``S0`` / reflective ``T`` the file has; both is an
            error), ``"emissive"`` or ``"reflective"``.
        allow_gaps: accept a regular wavelength grid with missing bands.

    Returns:
        :class:`SpectralImage` with float32 (H, W, L) pixels (the data window) and (L,) nm.

    Raises:
        InputError naming the file and the channel for anything malformed (see module doc).
    """
    p = Path(path)
    if kind is not None and kind not in _KINDS:
        raise InputError(f"kind must be None, 'emissive' or 'reflective', got {kind!r}",
                         field="kind")
    _check_file(p)
    _, header, chans = _open(p, header_only=True)
    h, w = _data_window(header, p)
    comps = _classify(list(chans), p)
    spectral = {c: g for c, g in comps.items() if c in ("S0", "T")}
    if not spectral:
        extra = f" (only polarisation components {sorted(comps)})" if comps else ""
        raise InputError(
            "no spectral channels (expected names like 'S0.550,000000nm' or 'T.550nm')"
            + extra + f"; channels present: {sorted(chans)[:12]}", path=p, field="channels")
    if kind is None:
        if len(spectral) > 1:
            raise InputError(
                "file has both emissive (S0) and reflective (T) channels; pass kind='emissive' "
                "or kind='reflective'", path=p, field="channels")
        comp = next(iter(spectral))
    else:
        comp = _KINDS[kind]
        if comp not in spectral:
            raise InputError(f"no {kind} ({comp}.*) channels; found {sorted(spectral)}",
                             path=p, field="channels")
    grid = spectral[comp]
    wl = np.array(sorted(grid), dtype=np.float64)
    names = [grid[x] for x in wl]
    if wl.size < 2:
        raise InputError(f"only one spectral channel ({names[0]!r}); need at least 2", path=p,
                         field=f"channel {names[0]!r}")
    validate_wavelengths(wl, path=p, field=f"channels {names[0]!r}..{names[-1]!r}")
    if not allow_gaps:
        _check_missing_bands(wl, names, p)
    n_samples = h * w * len(chans)
    if n_samples > MAX_SAMPLES:
        raise InputError(f"image of {w} x {h} x {len(chans)} samples is too large", path=p,
                         field="dataWindow")
    for name in names:
        ch = chans[name]
        if (ch.xSampling, ch.ySampling) != (1, 1):
            raise InputError(f"sub-sampled channel ({ch.xSampling} x {ch.ySampling}) is not "
                             "supported", path=p, field=f"channel {name!r}")

    _, header, chans = _open(p, header_only=False)
    if _data_window(header, p) != (h, w):
        raise InputError("header changed between reads", path=p, field="dataWindow")
    image = np.empty((h, w, wl.size), dtype=np.float32)
    for i, name in enumerate(names):
        ch = chans.get(name)
        px = None if ch is None else ch.pixels
        if px is None:
            raise InputError("channel has no pixel data", path=p, field=f"channel {name!r}")
        px = np.asarray(px)
        if px.dtype not in (np.float16, np.float32):
            raise InputError(f"pixel type {px.dtype} is not HALF or FLOAT", path=p,
                             field=f"channel {name!r}")
        if px.shape != (h, w):
            raise InputError(f"pixel array has shape {px.shape}, data window is {(h, w)}",
                             path=p, field=f"channel {name!r}")
        bad = ~np.isfinite(px)
        if bad.any():
            r, c = (int(v) for v in np.argwhere(bad)[0])
            raise InputError(f"{int(bad.sum())} NaN/infinite pixel(s), first at row {r}, "
                             f"column {c} ({px[r, c]})", path=p, field=f"channel {name!r}")
        image[..., i] = px
    kind_out = "emissive" if comp == "S0" else "reflective"
    return SpectralImage(wl, image, kind_out, tuple(names), _header_attributes(header))


def read_spectral_exr(
    path: str | os.PathLike[str], *, kind: str | None = None, allow_gaps: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Read a spectral OpenEXR image (stable API).

    Returns:
        ``(wavelengths_nm (L,) float64, image (H, W, L) float32)``; see
        :func:`read_spectral_exr_ex` for the options and for the kind and attributes.
    """
    img = read_spectral_exr_ex(path, kind=kind, allow_gaps=allow_gaps)
    return img.wavelengths, img.image


def read_rgb_exr(path: str | os.PathLike[str]) -> np.ndarray:
    """Read the R, G, B channels of an OpenEXR image as (H, W, 3) float32 (linear values as
    stored; the file's colourspace is not interpreted). Alpha and other channels are ignored.

    Raises InputError naming the file and channel for missing channels, UINT or sub-sampled
    data, NaN/inf pixels and corrupt files.
    """
    p = Path(path)
    _check_file(p)
    _, header, chans = _open(p, header_only=True)
    h, w = _data_window(header, p)
    missing = [c for c in "RGB" if c not in chans]
    if missing:
        raise InputError(f"no channel(s) {missing}; channels present: {sorted(chans)[:12]}",
                         path=p, field="channels")
    if h * w * len(chans) > MAX_SAMPLES:
        raise InputError(f"image of {w} x {h} x {len(chans)} samples is too large", path=p,
                         field="dataWindow")
    _, header, chans = _open(p, header_only=False)
    out = np.empty((h, w, 3), dtype=np.float32)
    for i, name in enumerate("RGB"):
        ch = chans.get(name)
        px = None if ch is None else ch.pixels
        if px is None or (ch.xSampling, ch.ySampling) != (1, 1):
            raise InputError("missing or sub-sampled channel", path=p, field=f"channel {name!r}")
        px = np.asarray(px)
        if px.dtype not in (np.float16, np.float32) or px.shape != (h, w):
            raise InputError(f"pixels of type {px.dtype} and shape {px.shape}; need HALF/FLOAT "
                             f"{(h, w)}", path=p, field=f"channel {name!r}")
        bad = ~np.isfinite(px)
        if bad.any():
            r, c = (int(v) for v in np.argwhere(bad)[0])
            raise InputError(f"NaN/infinite pixel at row {r}, column {c}", path=p,
                             field=f"channel {name!r}")
        out[..., i] = px
    return out


# --------------------------------------------------------------------------------------------
# writing


def _preview_rgb(wl: np.ndarray, image: np.ndarray, kind: str) -> tuple[np.ndarray, float]:
    """Linear sRGB preview (H, W, 3) float32 and the luminance mapped to 1 (emissive)."""
    import colour

    from ..color import illuminant, xyz_weights

    if kind == "emissive":
        xyz = image.astype(np.float64) @ xyz_weights(wl)
        y99 = float(np.percentile(xyz[..., 1], 99.0))
        scale = y99 if y99 > 0 else 1.0
        xyz = xyz / scale
    else:
        e = illuminant("D65", wl)
        W = xyz_weights(wl, scale=1.0)
        k = 1.0 / (e @ W[:, 1])
        xyz = k * (image.astype(np.float64) * e) @ W
        scale = 1.0
    rgb = colour.XYZ_to_RGB(xyz, "sRGB", chromatic_adaptation_transform=None)
    return np.asarray(rgb, dtype=np.float32), scale


def write_spectral_exr(
    path: str | os.PathLike[str],
    wavelengths_nm: object,
    image: object,
    *,
    spectral_kind: str = "emissive",
    pixel_type: str = "float",
    preview: bool = True,
    **attributes: Any,
) -> None:
    """Write a spectral OpenEXR image in the Fichet et al. (2021) layout, atomically (stable API).

    Args:
        path: destination (``.exr``).
        wavelengths_nm: (L,) nm, strictly increasing.
        image: (H, W, L) spectral radiance (W·sr⁻¹·m⁻²·nm⁻¹) for ``spectral_kind="emissive"``
            (channels ``S0.<λ>nm``), reflectance for ``"reflective"`` (channels ``T.<λ>nm``).
            All values finite.
        pixel_type: ``"float"`` (float32, the default) or ``"half"``.
        preview: add linear-sRGB R, G, B preview channels (see module doc).
        **attributes: extra header attributes (str, int, float or small numeric arrays).

    Raises:
        InputError for a wrong shape, non-finite values, bad wavelengths or unwritable file.
    """
    import OpenEXR

    if spectral_kind not in _KINDS:
        raise InputError(f"must be 'emissive' or 'reflective', got {spectral_kind!r}",
                         field="spectral_kind")
    dtypes = {"float": np.float32, "half": np.float16}
    if pixel_type not in dtypes:
        raise InputError(f"must be 'float' or 'half', got {pixel_type!r}", field="pixel_type")
    wl = validate_wavelengths(wavelengths_nm, field="wavelengths_nm")
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[-1] != wl.size or img.shape[0] < 1 or img.shape[1] < 1:
        raise InputError(f"need shape (H, W, {wl.size}), got {img.shape}", field="image")
    try:
        img = img.astype(np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"not numeric ({exc})", field="image") from None
    bad = ~np.isfinite(img)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise InputError(f"NaN or infinite value at (row, column, band) {idx}", field="image")
    dt = dtypes[pixel_type]
    if dt == np.float16 and np.abs(img).max() > 65504.0:
        raise InputError("values exceed the half-float range (65504); use pixel_type='float'",
                         field="image")
    kind = spectral_kind
    comp = _KINDS[kind]
    names = [channel_name(comp, x) for x in wl]
    if len(set(names)) != len(names):
        raise InputError("two wavelengths give the same channel name", field="wavelengths_nm")
    channels: dict[str, np.ndarray] = {
        n: np.ascontiguousarray(img[..., i].astype(dt)) for i, n in enumerate(names)}
    header: dict[str, Any] = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "spectralLayoutVersion": LAYOUT_VERSION,
    }
    if kind == "emissive":
        header["emissiveUnits"] = EMISSIVE_UNITS
    if preview:
        rgb, scale = _preview_rgb(wl, img, kind)
        for i, n in enumerate("RGB"):
            channels[n] = np.ascontiguousarray(rgb[..., i].astype(dt))
        if kind == "emissive":
            header["previewLuminance"] = float(scale)
    for key, value in attributes.items():
        if key in ("channels", "dataWindow", "displayWindow", "compression", "type"):
            raise InputError("reserved OpenEXR attribute name", field=key)
        header[key] = value
    with atomic_path(path) as tmp:
        try:
            OpenEXR.File(header, channels).write(str(tmp))
        except Exception as exc:
            raise InputError(f"OpenEXR could not write the file ({exc})", path=path) from None


def read_channels_exr(path: str | os.PathLike[str], names: str) -> np.ndarray:
    """Read the single-letter channels ``names`` (e.g. "XYZ") of an OpenEXR as (H, W, len)."""
    _, _, chans = _open(Path(path), header_only=False)
    missing = [c for c in names if c not in chans]
    if missing:
        raise InputError(f"no channel(s) {missing}", path=path, field="channels")
    return np.stack([np.asarray(chans[c].pixels, np.float32) for c in names], -1)
