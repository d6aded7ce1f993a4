"""Synthetic spectral environment maps: the bundled studio room, built from measured spectra that
colour-science ships, and a simpler sky, floor and lamp map for tests, benchmarks and demos
(:func:`synthetic_environment`).

The bundled ``measurements/environment/studio_room.exr`` is made by :func:`make_environment`
(``spectral-fit make-env -o PATH``). It is SYNTHETIC: a simple analytic room, not a capture, but
every spectrum in it is real data:

* sky: CIE daylight (D series, colour's ``sd_CIE_illuminant_D_series``) at a correlated colour
  temperature of 6500 K, with the CIE standard overcast sky luminance distribution (Moon &
  Spencer 1942; CIE S 011/E:2003 sky type 1): L(θ) = L_z (1 + 2 cos θ) / 3, θ from the zenith,
  zenith luminance ``SKY_ZENITH_LUMINANCE`` = 3000 cd/m² (the sky brightens towards the zenith;
  at the horizon it is L_z / 3 = 1000 cd/m²);
* ground outside (seen below the horizon through the window): ColorChecker "foliage" lit by that
  sky, L = ρ(λ) E_h(λ) / π with the overcast sky's horizontal illuminance E_h = 7π L_z / 9;
* a tungsten lamp: colour's measured ``SDS_LIGHT_SOURCES["60 A/W (Soft White)"]`` spectrum on a
  frosted sphere of radius ``LAMP_RADIUS`` = 6 cm at ``LAMP_POSITION``, uniform luminance
  ``LAMP_LUMINANCE`` = 20 000 cd/m² (luminous intensity π r² L ≈ 226 cd, about 2 800 lm: a bright
  household bulb); it covers a few texels: the small bright source for gloss highlights;
* a fluorescent ceiling panel: colour's measured ``"F32T8/TL841 (Triphosphor)"`` spectrum on a
  0.6 m × 1.2 m Lambertian rectangle in the ceiling, luminance ``PANEL_LUMINANCE`` = 5000 cd/m²;
* walls, floor and ceiling painted with BabelColor average ColorChecker reflectances (colour's
  ``SDS_COLOURCHECKERS["BabelColor Average"]``): front wall (−Z) "moderate red", back wall (+Z)
  "bluish green", left wall (−X) "orange yellow", right wall (+X) "neutral 8 (.23 D)" with an
  open window onto the sky, ceiling "white 9.5 (.05 D)", floor a 0.5 m checkerboard of
  "neutral 6.5 (.44 D)" and "dark skin".

Geometry (metres, +Y up, the map's centre of projection at the origin, 1.2 m above the floor):
the room is the box x ∈ [−2, 2], y ∈ [−1.2, 1.6], z ∈ [−2.5, 2.5]; the window is the rectangle
z ∈ [−1, 1], y ∈ [−0.4, 1.2] of the x = 2 wall; the panel is x ∈ [−0.3, 0.3], z ∈ [0.2, 1.4] of
the ceiling y = 1.6.

Shading of the painted surfaces (Lambertian, radiance ρ E / π):
direct irradiance from the lamp as a point source of intensity I = π r² L (E = I cos θ / d²),
from the panel as a point Lambertian source at its centre (E = L A cos θ_s cos θ / d²), no
shadows (nothing occludes inside the box), plus an indirect term standing in for
interreflection: the uniform irradiance of the integrating-sphere approximation,
E_ind = Φ ρ̄ / (A (1 − ρ̄)), with Φ the lamp's and panel's total flux (4π I and π L A), A the
room's surface area and ρ̄ = 0.4. The window admits no daylight into the room in this model
(it is only seen through). The painted surfaces then range over 6–82 cd/m² (median 37 cd/m²:
a dimly lit interior), the window shows 1000–3000 cd/m² of sky and ~310 cd/m² of ground, the
panel is 5000 cd/m² and the lamp 20 000 cd/m².

Units: spectral radiance W·sr⁻¹·m⁻²·nm⁻¹; luminances use 683 lm/W and the CIE 1931 2° observer
on the output wavelength grid (so the stated luminances hold exactly on that grid).

Mapping (docs/conventions.md, 'Conventions'): texel (row k, column j) of a W × H map has its centre
at u = (j + 0.5)/W, v = (k + 0.5)/H, φ = 2πu, θ = πv and direction
d = (sin φ sin θ, cos θ, −cos φ sin θ); the forward direction −Z is at u = 0 (the left/right image
edges), +Z at the image centre. Each texel is the mean of ``supersampling``² sub-samples on a
regular grid in (u, v).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .._runtime.errors import InputError
from ..color import default_wavelengths, validate_wavelengths

__all__ = [
    "ROOM_MIN",
    "ROOM_MAX",
    "LAMP_POSITION",
    "LAMP_RADIUS",
    "LAMP_LUMINANCE",
    "LAMP_SOURCE",
    "PANEL_MIN_XZ",
    "PANEL_MAX_XZ",
    "PANEL_LUMINANCE",
    "PANEL_SOURCE",
    "WINDOW_MIN_ZY",
    "WINDOW_MAX_ZY",
    "SKY_ZENITH_LUMINANCE",
    "SKY_CCT",
    "SURFACES",
    "make_environment",
    "subsample_directions",
    "synthetic_environment",
]

ROOM_MIN = np.array([-2.0, -1.2, -2.5])
ROOM_MAX = np.array([2.0, 1.6, 2.5])
LAMP_POSITION = np.array([-1.2, 0.25, -1.5])
LAMP_RADIUS = 0.06
LAMP_LUMINANCE = 20_000.0
LAMP_SOURCE = "60 A/W (Soft White)"
PANEL_MIN_XZ = np.array([-0.3, 0.2])
PANEL_MAX_XZ = np.array([0.3, 1.4])
PANEL_LUMINANCE = 5_000.0
PANEL_SOURCE = "F32T8/TL841 (Triphosphor)"
WINDOW_MIN_ZY = np.array([-1.0, -0.4])
WINDOW_MAX_ZY = np.array([1.0, 1.2])
SKY_ZENITH_LUMINANCE = 3_000.0
SKY_CCT = 6500.0
MEAN_REFLECTANCE = 0.4
FLOOR_TILE = 0.5
GROUND = "foliage"
#: surface -> ColorChecker patch (BabelColor Average)
SURFACES: dict[str, str] = {
    "floor_a": "neutral 6.5 (.44 D)",
    "floor_b": "dark skin",
    "ceiling": "white 9.5 (.05 D)",
    "wall_-x": "orange yellow",
    "wall_+x": "neutral 8 (.23 D)",
    "wall_-z": "moderate red",
    "wall_+z": "bluish green",
}
_SURF = list(SURFACES)


def subsample_directions(width: int, height: int, du: float = 0.5, dv: float = 0.5) -> np.ndarray:
    """Unit directions (H, W, 3) at (j + du)/W, (k + dv)/H (our equirectangular mapping)."""
    u = (np.arange(width) + du) / width
    v = (np.arange(height) + dv) / height
    phi = 2.0 * np.pi * u[None, :]
    theta = np.pi * v[:, None]
    st = np.sin(theta)
    return np.stack(np.broadcast_arrays(np.sin(phi) * st, np.cos(theta), -np.cos(phi) * st), -1)


def _unit_luminance(spd: np.ndarray, wl: np.ndarray) -> np.ndarray:
    """Scale a relative spectrum to luminance 1 cd/m² (as radiance, 683 lm/W)."""
    from ..color import xyz_weights

    return spd / float(spd @ xyz_weights(wl)[:, 1])


def _spectra(wl: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """The K basis spectra (K, L) whose per-texel weights make the map, and their names."""
    import colour

    from ..color import light_source

    cc = colour.SDS_COLOURCHECKERS["BabelColor Average"]

    def refl(name: str) -> np.ndarray:
        return np.asarray(cc[name][wl], dtype=np.float64)

    xy = colour.temperature.CCT_to_xy_CIE_D(SKY_CCT)
    sky_rel = np.asarray(colour.sd_CIE_illuminant_D_series(xy)[wl], dtype=np.float64)
    sky_z = SKY_ZENITH_LUMINANCE * _unit_luminance(sky_rel, wl)
    lamp = LAMP_LUMINANCE * _unit_luminance(light_source(LAMP_SOURCE, wl), wl)
    panel = PANEL_LUMINANCE * _unit_luminance(light_source(PANEL_SOURCE, wl), wl)
    # point-source intensities (W·sr⁻¹·nm⁻¹): sphere π r² L; Lambertian panel L·A along its normal
    i_lamp = np.pi * LAMP_RADIUS**2 * lamp
    area = float(np.prod(PANEL_MAX_XZ - PANEL_MIN_XZ))
    i_panel = area * panel
    flux = 4.0 * np.pi * i_lamp + np.pi * i_panel
    size = ROOM_MAX - ROOM_MIN
    room_area = 2.0 * (size[0] * size[1] + size[1] * size[2] + size[0] * size[2])
    e_ind = flux * MEAN_REFLECTANCE / (room_area * (1.0 - MEAN_REFLECTANCE))
    rows = [lamp, panel, sky_z, refl(GROUND) * sky_z * 7.0 / 9.0]
    names = ["lamp", "panel", "sky_zenith", "ground"]
    for s in _SURF:
        rho = refl(SURFACES[s]) / np.pi
        rows += [rho * i_lamp, rho * i_panel, rho * e_ind]
        names += [f"{s}:lamp", f"{s}:panel", f"{s}:indirect"]
    return np.stack(rows), names


def _weights(d: np.ndarray) -> np.ndarray:
    """Per-direction weights (..., K) of the basis spectra of :func:`_spectra`."""
    n_k = 4 + 3 * len(_SURF)
    w = np.zeros((*d.shape[:-1], n_k))
    with np.errstate(divide="ignore", invalid="ignore"):
        t_axis = np.where(d > 0, ROOM_MAX / d, np.where(d < 0, ROOM_MIN / d, np.inf))
    axis = np.argmin(t_axis, axis=-1)
    t = np.take_along_axis(t_axis, axis[..., None], -1)[..., 0]
    x = t[..., None] * d
    positive = np.take_along_axis(d, axis[..., None], -1)[..., 0] > 0
    normal = np.zeros_like(d)
    np.put_along_axis(normal, axis[..., None], np.where(positive, -1.0, 1.0)[..., None], -1)

    # surface index
    surf = np.full(axis.shape, -1)
    surf[(axis == 0) & ~positive] = _SURF.index("wall_-x")
    surf[(axis == 0) & positive] = _SURF.index("wall_+x")
    surf[(axis == 2) & ~positive] = _SURF.index("wall_-z")
    surf[(axis == 2) & positive] = _SURF.index("wall_+z")
    surf[(axis == 1) & positive] = _SURF.index("ceiling")
    floor = (axis == 1) & ~positive
    parity = (np.floor(x[..., 0] / FLOOR_TILE) + np.floor(x[..., 2] / FLOOR_TILE)) % 2 == 0
    surf[floor & parity] = _SURF.index("floor_a")
    surf[floor & ~parity] = _SURF.index("floor_b")

    # emitters and the window replace the painted surface
    in_panel = ((axis == 1) & positive
                & (x[..., 0] >= PANEL_MIN_XZ[0]) & (x[..., 0] <= PANEL_MAX_XZ[0])
                & (x[..., 2] >= PANEL_MIN_XZ[1]) & (x[..., 2] <= PANEL_MAX_XZ[1]))
    in_window = ((axis == 0) & positive
                 & (x[..., 2] >= WINDOW_MIN_ZY[0]) & (x[..., 2] <= WINDOW_MAX_ZY[0])
                 & (x[..., 1] >= WINDOW_MIN_ZY[1]) & (x[..., 1] <= WINDOW_MAX_ZY[1]))
    # ray-sphere (lamp): |t d - p|² = r², d unit
    b = d @ LAMP_POSITION
    disc = b * b - (LAMP_POSITION @ LAMP_POSITION - LAMP_RADIUS**2)
    in_lamp = (disc >= 0) & (b > 0)

    # painted surfaces: direct lamp + panel + indirect
    to_lamp = LAMP_POSITION - x
    d_l = np.linalg.norm(to_lamp, axis=-1)
    g_lamp = np.maximum(0.0, np.sum(normal * to_lamp, -1) / d_l) / d_l**2
    centre = np.array([(PANEL_MIN_XZ[0] + PANEL_MAX_XZ[0]) / 2, ROOM_MAX[1],
                       (PANEL_MIN_XZ[1] + PANEL_MAX_XZ[1]) / 2])
    to_panel = centre - x
    d_p = np.maximum(np.linalg.norm(to_panel, axis=-1), 1e-9)
    cos_s = np.maximum(0.0, to_panel[..., 1] / d_p)  # panel normal -Y: cos = -Y . (x - c)/d
    g_panel = cos_s * np.maximum(0.0, np.sum(normal * to_panel, -1) / d_p) / d_p**2
    painted = ~(in_panel | in_window | in_lamp)
    for i in range(len(_SURF)):
        m = painted & (surf == i)
        w[..., 4 + 3 * i] = np.where(m, g_lamp, 0.0)
        w[..., 5 + 3 * i] = np.where(m, g_panel, 0.0)
        w[..., 6 + 3 * i] = m
    w[..., 0] = in_lamp
    w[..., 1] = in_panel & ~in_lamp
    outside = in_window & ~in_lamp
    w[..., 2] = np.where(outside & (d[..., 1] > 0), (1.0 + 2.0 * d[..., 1]) / 3.0, 0.0)
    w[..., 3] = outside & (d[..., 1] <= 0)
    return w


def make_environment(
    width: int = 256,
    height: int = 128,
    wavelengths: object | None = None,
    *,
    supersampling: int = 4,
) -> tuple[np.ndarray, np.ndarray]:
    """Build the synthetic studio-room environment map (see the module doc).

    Args:
        width, height: map size (equirectangular); typically width = 2 · height.
        wavelengths: (L,) nm; default 380–780 nm at 5 nm.
        supersampling: n → n × n sub-samples per texel (box filter).

    Returns:
        ``(wavelengths (L,) float64, radiance (H, W, L) float32)`` in W·sr⁻¹·m⁻²·nm⁻¹; all
        values finite and >= 0. Deterministic.
    """
    if not (isinstance(width, int | np.integer) and isinstance(height, int | np.integer)
            and width >= 2 and height >= 1):
        raise InputError(f"need integer width >= 2 and height >= 1, got {width} x {height}",
                         field="size")
    if not (isinstance(supersampling, int | np.integer) and 1 <= supersampling <= 16):
        raise InputError(f"must be an integer in 1..16, got {supersampling}",
                         field="supersampling")
    wl = default_wavelengths() if wavelengths is None else validate_wavelengths(wavelengths)
    basis, _ = _spectra(wl)
    n = int(supersampling)
    acc = np.zeros((height, width, basis.shape[0]))
    for a in range(n):
        for b in range(n):
            d = subsample_directions(width, height, (a + 0.5) / n, (b + 0.5) / n)
            acc += _weights(d)
    acc /= n * n
    image = np.maximum(acc @ basis, 0.0).astype(np.float32)
    return wl, image


def synthetic_environment(
    height: int = 64,
    width: int = 128,
    wavelengths: Any = None,
    *,
    lamp_radius_deg: float = 4.0,
    lamp_direction: tuple[float, float, float] = (0.4, 0.8, -0.45),
    lamp_luminance_ratio: float = 50.0,
    supersample: int = 4,
) -> np.ndarray:
    """A realistic spectral environment (H, W, L) in W·sr⁻¹·m⁻²·nm⁻¹ (NumPy float64).

    Sky above the horizon: CIE D65 with a brightness gradient (brighter at the horizon) and a
    bluish zenith (CIE illuminant D-series 10000 K). Floor below: a grey-brown reflectance
    (a CIE 2017 colour-evaluation sample) under D65 with a grey/red checker. A small warm lamp
    disc (CIE illuminant A) of ``lamp_radius_deg``, ``lamp_luminance_ratio`` × the sky's mean
    luminance. Texels are averaged over ``supersample``² subsamples (anti-aliased disc and
    horizon).
    """
    import colour

    from ..color import default_wavelengths, illuminant
    from ._equirect import uv_to_direction

    wl = default_wavelengths() if wavelengths is None else np.asarray(wavelengths, np.float64)
    d65 = illuminant("D65", wl) / 100.0 * 0.02  # ~ 0.02 W/(sr m² nm) at 560 nm
    cct = colour.temperature.CCT_to_xy_CIE_D(10000.0 * 1.4388 / 1.4380)
    d10k = np.asarray(colour.sd_CIE_illuminant_D_series(cct)[wl], np.float64)
    d10k = d10k / np.interp(560.0, wl, d10k) * 0.02
    lamp = illuminant("A", wl)
    lamp = lamp / np.interp(560.0, wl, lamp) * 0.02 * lamp_luminance_ratio
    from ..color import reflectances_5nm

    w5, refl = reflectances_5nm()
    floor_a = np.interp(wl, w5, refl[20])
    floor_b = np.interp(wl, w5, refl[2])

    ss = supersample
    v = (np.arange(height * ss) + 0.5) / (height * ss)
    u = (np.arange(width * ss) + 0.5) / (width * ss)
    d = uv_to_direction(u[None, :], v[:, None])
    y = d[..., 1]
    sky_w = np.clip(y, 0.0, 1.0)
    sky = ((1.0 - sky_w)[..., None] * d65 * 1.3 + sky_w[..., None] * d10k * 0.8)
    check = ((np.floor(u * 16)[None, :] + np.floor(v * 8)[:, None]) % 2)[..., None]
    floor = (0.35 * d65) * (check * floor_a + (1.0 - check) * floor_b)
    img = np.where((y > 0.0)[..., None], sky, floor)
    ld = np.asarray(lamp_direction, np.float64)
    ld = ld / np.linalg.norm(ld)
    disc = (d @ ld) > math.cos(math.radians(lamp_radius_deg))
    img = np.where(disc[..., None], lamp, img)
    return img.reshape(height, ss, width, ss, -1).mean(axis=(1, 3))
