"""Display output: exposure, display characterisation, clipping, tone encoding.

Pipeline, per pixel::

    XYZ (absolute, cd/m²) ──÷ exposure_luminance──▶ relative XYZ (display white has Y = 1)
      ──[optional CAT02 adaptation scene white → display white]──▶
      ──XYZ→RGB of the display (its primaries and white)──▶ target linear RGB
      ──black level b: linear = (target − b)/(1 − b)──▶ clip to [0, 1] (reported) ──▶ tone curve

*Clipping policy*: clip in linear RGB, per channel, after the black-level correction. The fraction
of pixels with any channel outside [0, 1] is reported (``out_of_gamut_fraction``), split into
pixels with a negative channel (chromaticity outside the display gamut, ``below_zero_fraction``)
and pixels brighter than display white (``overexposed_fraction``).

*Characterisation*: primaries and white chromaticities, tone curve ("srgb": IEC 61966-2-1;
"gamma": a pure power law; "linear"), black level as a fraction of white luminance, and the
white luminance in cd/m². ``fit_display_csv`` fits all of these from measured patch readings.
The black emission is assumed to have the white's chromaticity.

Everything in :func:`to_display` works on NumPy arrays and, unchanged, on JAX arrays under
``jax.jit`` (the matrices are constants).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from typing import Any, NamedTuple

import numpy as np

from .._runtime.errors import InputError

__all__ = ["Display", "DisplayImage", "to_display", "display_linear", "gamut_fractions", "encode",
           "decode", "fit_display_csv"]

TONE_CURVES = ("srgb", "gamma", "linear")


def _xp(x: Any) -> Any:
    if type(x).__module__.startswith(("jax", "jaxlib")):
        import jax.numpy as jnp

        return jnp
    return np


@dataclasses.dataclass(frozen=True, eq=False)
class Display:
    """A display characterisation.

    Attributes:
        primaries_xy: (3, 2) CIE xy of the R, G, B primaries.
        white_xy: (2,) CIE xy of the display white (R = G = B = 1).
        tone: "srgb" (IEC 61966-2-1 piecewise curve), "gamma" (v = L^(1/gamma)) or "linear".
        gamma: exponent of the "gamma" curve (display luminance ∝ drive^gamma).
        black_level: luminance at drive 0 as a fraction of white luminance, in [0, 1).
        white_luminance: luminance of display white, cd/m² (informational; exposure decides which
            scene luminance is shown as white).
        name: label for reports.
    """

    primaries_xy: np.ndarray
    white_xy: np.ndarray
    tone: str = "srgb"
    gamma: float = 2.2
    black_level: float = 0.0
    white_luminance: float = 80.0
    name: str = "sRGB"

    def __post_init__(self) -> None:
        p = np.asarray(self.primaries_xy, dtype=np.float64)
        w = np.asarray(self.white_xy, dtype=np.float64)
        if p.shape != (3, 2) or not np.all(np.isfinite(p)):
            raise InputError(f"need 3×2 finite xy values, got {p.shape}", field="primaries_xy")
        if w.shape != (2,) or not np.all(np.isfinite(w)) or w[1] <= 0:
            raise InputError("need finite xy with y > 0", field="white_xy")
        if self.tone not in TONE_CURVES:
            raise InputError(f"unknown tone curve {self.tone!r}; use one of {TONE_CURVES}",
                             field="tone")
        if not (np.isfinite(self.gamma) and 0.2 < self.gamma < 10):
            raise InputError(f"gamma {self.gamma} outside (0.2, 10)", field="gamma")
        if not (0.0 <= self.black_level < 1.0):
            raise InputError(f"black level {self.black_level} outside [0, 1)",
                             field="black_level")
        if not (np.isfinite(self.white_luminance) and self.white_luminance > 0):
            raise InputError("white luminance must be > 0 cd/m²", field="white_luminance")
        if abs(np.linalg.det(np.column_stack([p, 1 - p.sum(1)]))) < 1e-9:
            raise InputError("primaries are collinear", field="primaries_xy")
        object.__setattr__(self, "primaries_xy", p)
        object.__setattr__(self, "white_xy", w)

    @classmethod
    def srgb(cls) -> Display:
        """IEC 61966-2-1 sRGB display (primaries, D65 white, piecewise curve, 80 cd/m²)."""
        return cls.from_colourspace("sRGB")

    @classmethod
    def from_colourspace(cls, name: str, **overrides: Any) -> Display:
        """A display with the primaries and white of a colour-science RGB colourspace
        (e.g. "sRGB", "Display P3", "ITU-R BT.2020"). The tone curve is "srgb" for sRGB and
        Display P3, otherwise "gamma" 2.4 (ITU-R BT.1886 with zero black)."""
        import colour

        if name not in colour.RGB_COLOURSPACES:
            raise InputError(f"unknown colourspace {name!r}", field="colourspace")
        cs = colour.RGB_COLOURSPACES[name]
        kw: dict[str, Any] = {
            "primaries_xy": np.asarray(cs.primaries),
            "white_xy": np.asarray(cs.whitepoint),
            "tone": "srgb" if name in ("sRGB", "Display P3") else "gamma",
            "gamma": 2.4,
            "name": name,
        }
        kw.update(overrides)
        return cls(**kw)

    @property
    def rgb_to_xyz(self) -> np.ndarray:
        """(3, 3) linear RGB → relative XYZ (white Y = 1), colour.normalised_primary_matrix."""
        import colour

        return np.asarray(colour.normalised_primary_matrix(self.primaries_xy, self.white_xy))

    @property
    def xyz_to_rgb(self) -> np.ndarray:
        """(3, 3) relative XYZ → linear RGB."""
        return np.linalg.inv(self.rgb_to_xyz)


class DisplayImage(NamedTuple):
    """Result of :func:`to_display` (a pytree).

    Attributes:
        rgb: (..., 3) display-encoded drive values in [0, 1].
        linear: (..., 3) linear RGB after black-level correction, before clipping.
        out_of_gamut_fraction: fraction of (masked) pixels with any channel outside [0, 1].
        below_zero_fraction: fraction with a negative channel (outside the gamut).
        overexposed_fraction: fraction with a channel above 1 (brighter than display white).
    """

    rgb: Any
    linear: Any
    out_of_gamut_fraction: Any
    below_zero_fraction: Any
    overexposed_fraction: Any


def encode(linear: Any, display: Display | None = None) -> Any:
    """Apply the display's inverse tone curve: linear [0, 1] → drive values [0, 1].

    sRGB: IEC 61966-2-1 (v = 12.92 L for L ≤ 0.0031308, else 1.055 L^(1/2.4) − 0.055);
    on float32 JAX arrays L^(1/2.4) is :func:`_pow_5_12` (within 1.5e-7 of the exact curve).
    Inputs are clipped to [0, 1] first; the gradient is finite everywhere.
    """
    display = display or Display.srgb()
    xp = _xp(linear)
    x = xp.clip(linear, 0.0, 1.0)
    if display.tone == "linear":
        return x
    if display.tone == "gamma":
        safe = xp.maximum(x, 1e-12)
        return xp.where(x > 0, safe ** (1.0 / display.gamma), 0.0)
    safe = xp.maximum(x, 0.0031308)
    if xp is np:
        power = safe ** (1.0 / 2.4)
    elif safe.dtype == xp.float32:
        power = _pow_5_12(safe)
    else:  # float64 (JAX's x64 mode): exp(log L / 2.4), which XLA:CPU vectorises (not pow)
        power = xp.exp(xp.log(safe) / 2.4)
    return xp.where(x <= 0.0031308, 12.92 * x, 1.055 * power - 0.055)


@functools.cache
def _pow_5_12_table() -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The coefficients (monomials in t = 2m − 3) of the degree-7 Chebyshev least-squares fit
    of m^(5/12) on m ∈ [1, 2] (relative error 8e-8), and 2^(5e/12) for e = −9 … 0."""
    t = np.cos(np.pi * (np.arange(4000) + 0.5) / 4000)
    fit = np.polynomial.chebyshev.chebfit(t, ((t + 3.0) / 2.0) ** (5.0 / 12.0), 7)
    coef = tuple(float(v) for v in np.polynomial.chebyshev.cheb2poly(fit))
    return coef, tuple(2.0 ** (5.0 * e / 12.0) for e in range(-9, 1))


def _pow_5_12(x: Any) -> Any:
    """x^(5/12) = x^(1/2.4) of float32 JAX x ∈ [2^-9, 1] (the sRGB encoding's range,
    x ≥ 0.0031308): x = m·2^e from the float's bits, m^(5/12) by a degree-7 polynomial
    (:func:`_pow_5_12_table`), 2^(5e/12) from a table of the 10 exponents (a chain of
    selects); within 1.5e-7 of the exact sRGB encoding, as exp(log x / 2.4) is, and ≤ 1 as
    x^(5/12) is (the polynomial rounds up to 1 + 1e-7 next to x = 1). On XLA:CPU exp and log
    cost about twice as much over a frame's values.
    Differentiable: d/dx = (5/12)·x^(5/12)/x."""
    return _pow_5_12_fn()(x)


@functools.cache
def _pow_5_12_fn() -> Any:
    import jax

    f = jax.custom_jvp(_pow_5_12_impl)

    @f.defjvp
    def _jvp(primals: Any, tangents: Any) -> Any:
        (x,), (dx,) = primals, tangents
        y = _pow_5_12_impl(x)
        return y, dx * (5.0 / 12.0) * y / x

    return f


def _pow_5_12_impl(x: Any) -> Any:
    import jax
    import jax.numpy as jnp

    coef, powers = _pow_5_12_table()
    bits = jax.lax.bitcast_convert_type(x, jnp.int32)
    e = (bits >> 23) - 127
    m = jax.lax.bitcast_convert_type((bits & 0x7FFFFF) | 0x3F800000, jnp.float32)
    t = 2.0 * m - 3.0
    poly = jnp.float32(coef[-1])
    for a in coef[-2::-1]:
        poly = poly * t + jnp.float32(a)
    scale = jnp.full(x.shape, jnp.float32(powers[0]))
    for k in range(1, len(powers)):
        scale = jnp.where(e == k - 9, jnp.float32(powers[k]), scale)
    return jnp.minimum(scale * poly, 1.0)


def decode(drive: Any, display: Display | None = None) -> Any:
    """The display's tone curve: drive values [0, 1] → linear light [0, 1] (inverse of encode)."""
    display = display or Display.srgb()
    xp = _xp(drive)
    v = xp.clip(drive, 0.0, 1.0)
    if display.tone == "linear":
        return v
    if display.tone == "gamma":
        return v**display.gamma
    safe = xp.maximum(v, 0.04045)
    return xp.where(v <= 0.04045, v / 12.92, ((safe + 0.055) / 1.055) ** 2.4)


def _adaptation_matrix(scene_white_xy: Any, display: Display) -> np.ndarray:
    import colour

    src = colour.xy_to_XYZ(np.asarray(scene_white_xy, np.float64))
    dst = colour.xy_to_XYZ(display.white_xy)
    return np.asarray(colour.adaptation.matrix_chromatic_adaptation_VonKries(
        src, dst, transform="CAT02"))


def display_linear(
    xyz: Any,
    *,
    exposure_luminance: float | Any,
    display: Display | None = None,
    scene_white_xy: Any | None = None,
) -> Any:
    """XYZ (..., 3) → the display's linear RGB (..., 3) after the black-level correction,
    before clipping: the first half of :func:`to_display` (same arguments)."""
    display = display or Display.srgb()
    xp = _xp(xyz)
    M = display.xyz_to_rgb
    if scene_white_xy is not None:
        M = M @ _adaptation_matrix(scene_white_xy, display)
    b = display.black_level
    # ((xyz / exposure) @ M.T − b) / (1 − b) with the scale folded into the 3 × 3 matrix (one
    # pass over the image instead of a division pass before the product), by components (a
    # (..., 3) @ (3, 3) product is a slow loop on XLA:CPU)
    dtype = getattr(xyz, "dtype", np.float64)
    Mt = xp.asarray(M.T, dtype=dtype) * (1.0 / (exposure_luminance * (1.0 - b)))
    target = xyz[..., 0:1] * Mt[0] + xyz[..., 1:2] * Mt[1] + xyz[..., 2:3] * Mt[2]
    return target - b / (1.0 - b) if b else target


def gamut_fractions(linear: Any, mask: Any | None = None, *, tol: float = 1e-4
                    ) -> tuple[Any, Any, Any]:
    """Fractions of (masked) pixels of linear RGB (..., 3) outside [0, 1]: (any channel
    outside, a channel < −tol, a channel > 1 + tol); ``mask`` (...,) bool (default all).
    The last three fields of :class:`DisplayImage`."""
    xp = _xp(linear)
    below = xp.any(linear < -tol, axis=-1)
    above = xp.any(linear > 1.0 + tol, axis=-1)
    oog = below | above
    if mask is None:
        return tuple(xp.mean(v.astype(xp.float32)) for v in (oog, below, above))
    m = xp.asarray(mask).astype(xp.float32)
    n = xp.maximum(m.sum(), 1.0)
    return tuple((v.astype(xp.float32) * m).sum() / n for v in (oog, below, above))


def to_display(
    xyz: Any,
    *,
    exposure_luminance: float | Any,
    display: Display | None = None,
    scene_white_xy: Any | None = None,
    mask: Any | None = None,
    tol: float = 1e-4,
) -> DisplayImage:
    """Map XYZ (..., 3) to display-encoded RGB.

    Args:
        xyz: (..., 3) XYZ, absolute (cd/m²) or relative; ``exposure_luminance`` in the same units.
        exposure_luminance: scene luminance shown as display white (Y → 1).
        display: characterisation (default sRGB).
        scene_white_xy: if given, colours are adapted from this white to the display white with
            the CAT02 von Kries transform (CIE 159:2004); by default colorimetric (no adaptation).
        mask: optional (...,) boolean; the gamut fractions count masked pixels only.
        tol: tolerance for counting a channel as outside [0, 1].

    Works under ``jax.jit`` when ``xyz`` is a JAX array. :func:`display_linear`,
    :func:`gamut_fractions` and :func:`encode` are its three steps.
    """
    display = display or Display.srgb()
    linear = display_linear(xyz, exposure_luminance=exposure_luminance, display=display,
                            scene_white_xy=scene_white_xy)
    return DisplayImage(encode(linear, display), linear, *gamut_fractions(linear, mask, tol=tol))


def fit_display_csv(path: str | os.PathLike[str], *, name: str | None = None) -> Display:
    """Fit a display characterisation from measured patches.

    CSV with a header naming columns ``R, G, B, X, Y, Z`` (drive values in [0, 1]; XYZ in cd/m²,
    as a colorimeter reads the screen). At least 8 rows including black (0, 0, 0), and ideally
    ramps of each primary. Model (a gain-offset-gamma display with one gamma for all channels)::

        XYZ = M · (drive ** gamma) + XYZ_black

    For a fixed gamma the model is linear in M and XYZ_black (least squares); gamma is found by a
    bounded 1-D search (golden section) on the residual. Primaries = xy of M's columns, white = xy
    of M·1, black level = Y_black / Y(white), white luminance = Y of M·1 + Y_black.

    Raises InputError naming the file, line and column for malformed rows.
    """
    import csv

    p = os.fspath(path)
    try:
        with open(p, newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        raise InputError(f"cannot read ({exc.strerror or exc})", path=p) from None
    rows = [(i + 1, r) for i, r in enumerate(rows) if r and not r[0].lstrip().startswith("#")]
    if not rows:
        raise InputError("empty file", path=p)
    header = [c.strip().upper() for c in rows[0][1]]
    need = ["R", "G", "B", "X", "Y", "Z"]
    missing = [c for c in need if c not in header]
    if missing:
        raise InputError(f"header must name columns {need}; missing {missing}", path=p,
                         line=rows[0][0])
    idx = [header.index(c) for c in need]
    data = []
    for lineno, r in rows[1:]:
        if len(r) != len(header):
            raise InputError(f"expected {len(header)} cells, found {len(r)}", path=p, line=lineno)
        vals = []
        for c, j in zip(need, idx, strict=True):
            try:
                v = float(r[j])
            except ValueError:
                raise InputError(f"not a number: {r[j]!r}", path=p, line=lineno,
                                 field=c) from None
            if not np.isfinite(v):
                raise InputError("not finite", path=p, line=lineno, field=c)
            if c in "RGB" and not (0.0 <= v <= 1.0):
                raise InputError(f"drive value {v} outside [0, 1]", path=p, line=lineno, field=c)
            if c in "XYZ" and v < 0:
                raise InputError(f"negative tristimulus value {v}", path=p, line=lineno, field=c)
            vals.append(v)
        data.append(vals)
    d = np.asarray(data)
    if d.shape[0] < 8:
        raise InputError(f"need at least 8 patches, found {d.shape[0]}", path=p)
    rgb, xyz = d[:, :3], d[:, 3:]

    def solve(gamma: float) -> tuple[float, np.ndarray]:
        A = np.column_stack([rgb**gamma, np.ones(len(rgb))])
        coef, *_ = np.linalg.lstsq(A, xyz, rcond=None)
        return float(np.sum((A @ coef - xyz) ** 2)), coef

    lo, hi = 1.0, 3.5
    g = (np.sqrt(5) - 1) / 2
    a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    fa, fb = solve(a)[0], solve(b)[0]
    for _ in range(60):
        if fa < fb:
            hi, b, fb = b, a, fa
            a = hi - g * (hi - lo)
            fa = solve(a)[0]
        else:
            lo, a, fa = a, b, fb
            b = lo + g * (hi - lo)
            fb = solve(b)[0]
    gamma = (lo + hi) / 2
    _, coef = solve(gamma)
    M, black = coef[:3].T, coef[3]
    if np.linalg.matrix_rank(M) < 3:
        raise InputError("patches do not determine three primaries (need R, G, B ramps)", path=p)
    white = M @ np.ones(3)
    xy = lambda v: v[:2] / v.sum()  # noqa: E731
    return Display(
        primaries_xy=np.stack([xy(M[:, i]) for i in range(3)]),
        white_xy=xy(white),
        tone="gamma",
        gamma=float(gamma),
        black_level=float(max(black[1], 0.0) / (white[1] + max(black[1], 0.0))),
        white_luminance=float(white[1] + max(black[1], 0.0)),
        name=name or os.path.basename(p),
    )
