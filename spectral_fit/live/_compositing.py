"""Colour-matched compositing: CG spectra → the video camera's encoded RGB → over the frame.

The CG must look as the camera would have seen it. A :class:`CameraModel` is the whole chain
from scene light to the video frame's linear RGB, folded into ONE linear map, followed by the
frame's tone curve:

    spectral radiance (…, L) ──@ spectral_weights (L, 3)──▶ linear frame RGB ──tone──▶ [0, 1]
    absolute XYZ (…, 3)      ──@ xyz_matrix.T (3, 3)──────▶ linear frame RGB ──tone──▶ [0, 1]

where, for a camera with spectral sensitivities s(λ) (L, 3):

    spectral_weights = s(λ)·Δλ · diag(exposure · white_balance) · colour_matrixᵀ

* raw camera RGB = ∫ L(λ) s(λ) dλ (Riemann sum on the scene grid);
* white balance: per-channel gains that make the scene's white (the radiance of a white
  reference) neutral, raw(white) · wb = (1, 1, 1);
* exposure: that white is shown at linear level ``white_level``;
* colour matrix (3×3): white-balanced camera RGB → the frame's linear RGB primaries (sRGB),
  least squares over the 24 ColorChecker patches under the scene's white, targets adapted to
  the output white (CAT02), the usual camera characterisation (ISO 17321-1 style);
* tone curve: the frame's encoding (sRGB by default), :func:`spectral_fit.color.encode`.

Two ways to get a model:

1. :func:`camera_model_from_sensitivities`: measured spectral sensitivities (colour-science's
   ``MSDS_CAMERA_SENSITIVITIES``, e.g. "Nikon 5100 (NPL)", or an (L, 3) array). Spectral
   renders go through ``spectral_weights``; XYZ renders through the best 3×3 from XYZ
   (``xyz_matrix``, fitted on the same patches: exact only for a Luther camera).
2. :func:`camera_model_from_colorchecker`: a 3×3 fitted from a ColorChecker in the video
   itself: the patches' CG XYZ (rendered or computed under the scene light) against their
   decoded frame RGB (:func:`sample_chart`). It absorbs exposure, white balance and matrix.

3. :func:`camera_model_from_spec`: the ``[camera_colour]`` table of a scene config, written
   by ``spectral-fit calibrate-colour`` (:func:`calibrate_colour` + :func:`write_colour_config`):
   ``linear = diag(white_balance) · matrix · XYZ``, where ``matrix`` maps the scene's white to
   equal channels and ``white_balance`` holds the per-channel gains (exposure included);
   optionally the tone curve's exponent fitted on the chart's six neutral patches.

Compositing (:func:`composite`) mixes in LINEAR light with the renderer's coverage (0..1):
``out = encode(cov · cg + (1 − cov) · decode(frame))``; pixels without coverage are the frame's
own values exactly (no round trip through the curve).

Everything after the model is built runs under ``jax.jit`` (float32).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.backend import materialise
from .._runtime.errors import InputError

__all__ = [
    "CameraModel",
    "camera_sensitivities",
    "camera_model_from_sensitivities",
    "camera_model_from_colorchecker",
    "colorchecker_reflectances",
    "fit_colour_matrix",
    "sample_chart",
    "encode_frame",
    "decode_frame",
    "composite",
    "composite_pixels",
    "relight",
    "relight_codes",
    "camera_model_from_spec",
    "chart_xyz",
    "ChartCalibration",
    "calibrate_colour",
    "calibrate_colour_samples",
    "frame_delta_e00",
    "colour_config_text",
    "write_colour_config",
]


class CameraModel(eqx.Module):
    """Scene light → the frame's linear RGB (see the module docstring), then ``tone``.

    Attributes:
        spectral_weights: (L, 3) radiance (W·sr⁻¹·m⁻²·nm⁻¹) → linear frame RGB, or NaN-free
            zeros when the model came from XYZ only (``has_spectral`` False).
        xyz_matrix: (3, 3) absolute XYZ (cd/m²) → linear frame RGB (``rgb = xyz @ M.T``).
        wavelengths: (L,) nm grid of ``spectral_weights``.
        tone: "srgb", "gamma" or "linear" (static).
        gamma: exponent of the "gamma" curve (static).
        has_spectral: whether ``spectral_weights`` is meaningful (static).
        blur_px: the camera's blur, a Gaussian of this σ in pixels, given to the composited
            CG in linear light (static; 0: sharp CG).
        noise: the camera's noise, σ in 8-bit levels of the encoded frame, added to the
            composited CG in proportion to its coverage (static; 0: none).
    """

    spectral_weights: jax.Array
    xyz_matrix: jax.Array
    wavelengths: jax.Array
    tone: str = eqx.field(static=True, default="srgb")
    gamma: float = eqx.field(static=True, default=2.2)
    has_spectral: bool = eqx.field(static=True, default=True)
    blur_px: float = eqx.field(static=True, default=0.0)
    noise: float = eqx.field(static=True, default=0.0)

    def linear_from_spectra(self, radiance: jax.Array) -> jax.Array:
        """(…, L) spectral radiance → (…, 3) linear frame RGB."""
        if not self.has_spectral:
            raise InputError("this camera model has no spectral weights (fitted from XYZ)",
                             field="camera")
        return radiance @ self.spectral_weights

    def linear_from_xyz(self, xyz: jax.Array) -> jax.Array:
        """(…, 3) absolute XYZ → (…, 3) linear frame RGB."""
        return xyz @ self.xyz_matrix.T


def _display(tone: str, gamma: float):
    from ..color import Display

    return Display.from_colourspace("sRGB", tone=tone, gamma=gamma)


def encode_frame(linear, model: CameraModel):
    """Linear frame RGB (…, 3) → encoded [0, 1] with the model's tone curve (clipped)."""
    from ..color import encode

    return encode(linear, _display(model.tone, model.gamma))


def decode_frame(encoded, model: CameraModel):
    """Encoded [0, 1] (…, 3) → linear frame RGB (inverse tone curve)."""
    from ..color import decode

    return decode(encoded, _display(model.tone, model.gamma))


def camera_sensitivities(name: str, wavelengths) -> np.ndarray:
    """(L, 3) spectral sensitivities of camera ``name`` from colour-science's
    ``MSDS_CAMERA_SENSITIVITIES``, resampled onto ``wavelengths`` (nm), zero outside the
    measured range."""
    import colour

    if name not in colour.MSDS_CAMERA_SENSITIVITIES:
        raise InputError(f"unknown camera {name!r}; known: "
                         f"{sorted(colour.MSDS_CAMERA_SENSITIVITIES)}", field="camera")
    msds = colour.MSDS_CAMERA_SENSITIVITIES[name]
    wl = np.asarray(wavelengths, np.float64)
    src = np.asarray(msds.wavelengths)
    vals = np.asarray(msds.values, np.float64)
    return np.stack([np.interp(wl, src, vals[:, c], left=0.0, right=0.0) for c in range(3)], -1)


def colorchecker_reflectances(wavelengths, *, chart: str = "BabelColor Average") -> np.ndarray:
    """(24, L) reflectances of colour-science's ColorChecker ``chart`` (row-major, patch 1 =
    dark skin … 24 = black) on ``wavelengths`` (nm)."""
    import colour

    from ..color import resample

    sds = colour.SDS_COLOURCHECKERS[chart]
    wl = np.asarray(wavelengths, np.float64)
    return np.stack([resample(sd.wavelengths, sd.values, wl, field=f"chart {chart}",
                              margin_nm=40.0) for sd in sds.values()])


def fit_colour_matrix(source, target, *, weights=None) -> np.ndarray:
    """3×3 ``M`` minimising Σ w‖target − source·Mᵀ‖² (source, target (N, 3); N ≥ 3)."""
    a = np.asarray(source, np.float64)
    b = np.asarray(target, np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape != b.shape or a.shape[0] < 3:
        raise InputError(f"need matching (N>=3, 3) arrays, got {a.shape} and {b.shape}",
                         field="colour matrix")
    if weights is not None:
        w = np.sqrt(np.asarray(weights, np.float64))[:, None]
        a, b = a * w, b * w
    m, *_ = np.linalg.lstsq(a, b, rcond=None)
    return m.T


def _srgb_targets(xyz_rel: np.ndarray, white_xyz: np.ndarray) -> np.ndarray:
    """Linear sRGB of relative XYZ, adapted (CAT02) from ``white_xyz`` to D65."""
    import colour

    d65 = colour.xy_to_XYZ(colour.RGB_COLOURSPACES["sRGB"].whitepoint)
    cat = colour.adaptation.matrix_chromatic_adaptation_VonKries(
        white_xyz / white_xyz[1], d65, transform="CAT02")
    from ..color import Display

    return (xyz_rel @ np.asarray(cat).T) @ Display.srgb().xyz_to_rgb.T


def camera_model_from_sensitivities(sensitivities, wavelengths, white, *,
                                    white_level: float = 0.85, tone: str = "srgb",
                                    gamma: float = 2.2) -> CameraModel:
    """Camera model from spectral sensitivities.

    Args:
        sensitivities: a colour-science camera name or an (L, 3) array on ``wavelengths``.
        wavelengths: (L,) nm, the render's grid.
        white: (L,) spectral radiance of the scene's white reference (e.g. a white Lambertian
            under the environment); it becomes neutral at linear level ``white_level``.
        white_level: linear frame value of the white reference (exposure).
        tone, gamma: the frame's tone curve.
    """
    from ..color import integration_weights, xyz_weights

    wl = np.asarray(wavelengths, np.float64)
    s = (camera_sensitivities(sensitivities, wl) if isinstance(sensitivities, str)
         else np.asarray(sensitivities, np.float64))
    if s.shape != (wl.size, 3):
        raise InputError(f"sensitivities must be ({wl.size}, 3), got {s.shape}", field="camera")
    white = np.asarray(white, np.float64).reshape(-1)
    if white.shape != wl.shape or not np.all(np.isfinite(white)) or white.max() <= 0:
        raise InputError("white reference must be a positive (L,) spectrum", field="white")
    sw = s * integration_weights(wl)[:, None]
    raw_white = white @ sw
    if np.any(raw_white <= 0):
        raise InputError("the white reference gives no signal in some camera channel",
                         field="white")
    wb = 1.0 / raw_white
    refl = colorchecker_reflectances(wl)
    patches = refl * white  # (24, L) radiance of the patches under the white's light
    cam = (patches @ sw) * wb
    xyzw = xyz_weights(wl)
    white_xyz = white @ xyzw
    target = _srgb_targets((patches @ xyzw) / white_xyz[1], white_xyz)
    c = fit_colour_matrix(cam, target)
    c = c / (c @ np.ones(3))[:, None]  # keep white neutral exactly: C·(1,1,1) = (1,1,1)
    weights = sw @ np.diag(wb * white_level) @ c.T
    xyz_m = fit_colour_matrix(patches @ xyzw, patches @ weights)
    return CameraModel(jnp.asarray(weights, jnp.float32), jnp.asarray(xyz_m, jnp.float32),
                       jnp.asarray(wl, jnp.float32), tone=tone, gamma=gamma, has_spectral=True)


def camera_model_from_colorchecker(xyz, frame_rgb, *, tone: str = "srgb", gamma: float = 2.2,
                                   wavelengths=None) -> CameraModel:
    """Camera model fitted from a ColorChecker shot.

    Args:
        xyz: (N, 3) absolute XYZ of the patches as the renderer would produce them (the chart's
            reflectances under the scene's light).
        frame_rgb: (N, 3) the same patches' encoded values in the video frame, in [0, 1]
            (e.g. from :func:`sample_chart` / 255). Clipped patches (any channel ≥ 0.98 or
            ≤ 0.02) are left out of the fit.
        tone, gamma: the frame's tone curve (to linearise ``frame_rgb``).
    """
    xyz = np.asarray(xyz, np.float64)
    enc = np.asarray(frame_rgb, np.float64)
    probe = CameraModel(jnp.zeros((1, 3)), jnp.eye(3), jnp.zeros(1), tone=tone, gamma=gamma,
                        has_spectral=False)
    lin = np.asarray(decode_frame(enc, probe), np.float64)
    ok = np.all((enc < 0.98) & (enc > 0.02), axis=1)
    if ok.sum() < 3:
        raise InputError("fewer than 3 unclipped patches in the chart", field="chart")
    m = fit_colour_matrix(xyz[ok], lin[ok])
    wl = np.zeros(1) if wavelengths is None else np.asarray(wavelengths)
    return CameraModel(jnp.zeros((wl.size, 3), jnp.float32), jnp.asarray(m, jnp.float32),
                       jnp.asarray(wl, jnp.float32), tone=tone, gamma=gamma, has_spectral=False)


def sample_chart(image: np.ndarray, corners, *, rows: int = 4, cols: int = 6,
                 patch_fraction: float = 0.5) -> np.ndarray:
    """Mean values (rows·cols, C) of a chart's patches, row-major.

    ``corners`` (4, 2): pixel coordinates (x, y; OpenCV convention) of the chart's outer
    corners in the order top-left, top-right, bottom-right, bottom-left (patch 1 at top-left).
    Each patch is averaged over the central ``patch_fraction`` of its cell, mapped through
    the chart's homography (so perspective views work).
    """
    import cv2

    img = np.asarray(image)
    src = np.array([[0, 0], [cols, 0], [cols, rows], [0, rows]], np.float64)
    h = cv2.getPerspectiveTransform(src.astype(np.float32),
                                    np.asarray(corners, np.float32).reshape(4, 2))
    out = []
    n = 9
    g = (np.arange(n) + 0.5) / n - 0.5
    gu, gv = np.meshgrid(g * patch_fraction, g * patch_fraction)
    for r in range(rows):
        for c in range(cols):
            pts = np.stack([c + 0.5 + gu.ravel(), r + 0.5 + gv.ravel()], -1)
            xy = cv2.perspectiveTransform(pts.reshape(-1, 1, 2), h).reshape(-1, 2)
            vals = cv2.remap(img.astype(np.float32), xy[:, 0:1].astype(np.float32),
                             xy[:, 1:2].astype(np.float32), cv2.INTER_LINEAR)
            out.append(vals.reshape(-1, img.shape[-1] if img.ndim == 3 else 1).mean(0))
    return np.stack(out)


def composite(frame, cg_linear, coverage, model: CameraModel) -> jax.Array:
    """Composite CG over a video frame in linear light.

    Args:
        frame: (H, W, 3) uint8 encoded video frame.
        cg_linear: (H, W, 3) float linear frame RGB of the CG (from ``model.linear_from_*``).
        coverage: (H, W) CG coverage in [0, 1], or a bool mask.
        model: the camera model (its tone curve).

    Returns (H, W, 3) uint8; uncovered pixels equal ``frame`` exactly. A bool mask (the
    renderer's coverage, no partial pixels) needs no decoding of the frame: covered pixels are
    ``encode(cg)``; partial coverage decodes the frame through a 256-entry table of the inverse
    tone curve (exact for uint8 input) and mixes ``cov · cg + (1 − cov) · frame`` linearly.
    With the model's ``blur_px`` or ``noise`` the CG gets the camera's blur and noise as in
    :func:`composite_pixels` (pixels the blurred CG does not reach keep their bytes).
    """
    fr = jnp.asarray(frame, jnp.uint8)
    cov = jnp.asarray(coverage)
    cg = jnp.clip(cg_linear, 0.0, 1.0)
    if model.blur_px > 0 or model.noise > 0:
        a = jnp.clip(cov.astype(jnp.float32), 0.0, 1.0)[..., None]
        noise = _frame_noise(fr, fr.shape) * (a > 0) if model.noise > 0 else None
        return _as_seen(fr, jnp.concatenate([cg * a, a], axis=-1), model, noise)
    if cov.dtype == jnp.bool_:
        enc = jnp.round(encode_frame(cg, model) * 255.0).astype(jnp.uint8)
        return jnp.where(cov[..., None], enc, fr)
    cov = jnp.clip(cov.astype(jnp.float32), 0.0, 1.0)[..., None]
    lut = decode_frame(jnp.arange(256, dtype=jnp.float32) / 255.0, model)
    mixed = cov * cg + (1.0 - cov) * lut[fr.astype(jnp.int32)]
    enc = jnp.round(encode_frame(mixed, model) * 255.0).astype(jnp.uint8)
    return jnp.where(cov > 0, enc, fr)


#: the ratio steps of :func:`relight_codes`: ratios in [0, RELIGHT_MAX] at 1 / RELIGHT_STEPS
RELIGHT_STEPS = 1024
RELIGHT_MAX = 4


def relight_codes(model: CameraModel) -> jax.Array:
    """(256, RELIGHT_MAX · RELIGHT_STEPS + 1) uint8: the code of a pixel of code c whose
    linear light is multiplied by the ratio q / RELIGHT_STEPS, through the model's tone
    curve (decoded, multiplied, encoded, rounded). The column of ratio 1 is the identity
    (c → c), so a pixel whose ratio rounds to 1 keeps its byte. Depends on the tone curve
    only: a live session builds it once per camera model (1 M curve evaluations)."""
    lin = decode_frame(jnp.arange(256, dtype=jnp.float32) / 255.0, model)
    r = jnp.arange(RELIGHT_MAX * RELIGHT_STEPS + 1, dtype=jnp.float32) / RELIGHT_STEPS
    codes = jnp.round(encode_frame(lin[:, None] * r[None, :], model) * 255.0)
    return codes.astype(jnp.uint8).at[:, RELIGHT_STEPS].set(jnp.arange(256, dtype=jnp.uint8))


def relight(frame, ratio, model: CameraModel, *, codes: jax.Array | None = None
            ) -> jax.Array:
    """The objects' shadows and light on a real surface, put into the video frame: each
    pixel's linear light (through the model's tone curve) times ``ratio`` (H, W, 3) (the
    surface's radiance with / without the objects in the frame's linear RGB,
    :func:`spectral_fit.rendering.surface_ratio`), encoded again. The ratio is rounded to
    steps of 1/1024 (≤ 0.05 % of the light, below an 8-bit code) and the result read from
    ``codes`` (:func:`relight_codes`, built here when not given): no tone curve per pixel.
    Pixels whose ratio rounds to 1 keep their bytes, so a frame without objects comes back
    bit for bit. A pixel with a clipped channel (255) holds at least the clip level's light:
    it is darkened from that level where the objects shade it (a lower bound of its true
    value, and the same as its unclipped neighbours get: no speckle on white paper), never
    brightened (its true light is unknown)."""
    fr = jnp.asarray(frame, jnp.uint8)
    r = jnp.asarray(ratio, jnp.float32)
    table = relight_codes(model) if codes is None else codes
    clipped = jnp.any(fr == 255, axis=-1, keepdims=True)
    r = jnp.where(clipped, jnp.minimum(r, 1.0), r)
    q = jnp.round(jnp.clip(r, 0.0, float(RELIGHT_MAX)) * RELIGHT_STEPS).astype(jnp.int32)
    flat = fr.astype(jnp.int32) * (RELIGHT_MAX * RELIGHT_STEPS + 1) + q
    return table.reshape(-1).at[flat].get(mode="promise_in_bounds")


def composite_pixels(frame, cg_linear, index, valid, model: CameraModel) -> jax.Array:
    """Composite a list of covered pixels over a video frame (the renderer's
    :class:`~spectral_fit.rendering.PixelFrame`): each valid slot's CG colour, encoded with the
    model's tone curve, replaces its pixel; every other pixel is the frame's own value.
    Identical to :func:`composite` with the bool coverage mask of those pixels, but only the
    N listed pixels are encoded (no full-frame CG image).

    Args:
        frame: (H, W, 3) uint8 encoded video frame.
        cg_linear: (N, 3) float linear frame RGB of the CG per slot.
        index: (N,) int flat pixel index y·W + x per slot.
        valid: (N,) bool, slots that hold a covered pixel.
        model: the camera model (its tone curve).

    Returns (H, W, 3) uint8.
    """
    fr = jnp.asarray(frame, jnp.uint8)
    h, w, _ = fr.shape
    cg = jnp.clip(jnp.asarray(cg_linear), 0.0, 1.0)
    idx = jnp.where(jnp.asarray(valid), jnp.asarray(index), h * w)  # out of range: dropped
    if model.blur_px > 0 or model.noise > 0:
        return _composite_as_seen(fr, cg, idx, model)
    enc = jnp.round(encode_frame(cg, model) * 255.0).astype(jnp.uint8)
    return fr.reshape(h * w, 3).at[idx].set(enc, mode="drop").reshape(h, w, 3)


def _composite_as_seen(frame: jax.Array, cg: jax.Array, index: jax.Array,
                       model: CameraModel) -> jax.Array:
    """:func:`composite_pixels` with the camera's blur and noise given to the CG (see
    :func:`_as_seen`); the noise is drawn for the slots only (a frame's worth of draws would
    cost more than the rest of the composite)."""
    h, w, _ = frame.shape
    rgba = jnp.concatenate([cg, jnp.ones((cg.shape[0], 1), cg.dtype)], axis=1)
    layer = jnp.zeros((h * w, 4), jnp.float32).at[index].set(rgba, mode="drop")
    noise = None
    if model.noise > 0:
        draws = _frame_noise(frame, (index.shape[0], 3))
        noise = jnp.zeros((h * w, 3), jnp.float32).at[index].set(draws, mode="drop")
        noise = noise.reshape(h, w, 3)
    return _as_seen(frame, layer.reshape(h, w, 4), model, noise)


def _as_seen(frame: jax.Array, layer: jax.Array, model: CameraModel,
             noise: jax.Array | None) -> jax.Array:
    """The CG layer (H, W, 4: linear CG premultiplied by its coverage, then the coverage)
    given the camera's blur and noise and composited over the frame: the layer blurred with a
    Gaussian of σ = ``model.blur_px`` (zero outside the frame), composited over the decoded
    video frame (``frame·(1 − a) + cg``), encoded, and given ``model.noise`` levels times the
    blurred coverage a of the standard normal ``noise`` (H, W, 3) (drawn for the covered
    pixels: the blurred rim outside them keeps the video's own noise, in proportion 1 − a).
    Pixels the CG does not reach (a < 1/512) keep their bytes."""
    if model.blur_px > 0:
        # computed once (XLA otherwise fuses the blur into each of its consumers)
        layer = materialise(gaussian_blur(layer, model.blur_px), cut=True)
    cover = layer[..., 3:]
    # the frame decoded through a (256, 3) table: indexed by (code, channel), XLA:CPU gathers
    # it in the composite's own loop (a (256,) table indexed by the (H, W, 3) codes becomes a
    # separate gather that doubles the composite's cost)
    codes = jnp.broadcast_to(jnp.arange(256, dtype=jnp.float32)[:, None] / 255.0, (256, 3))
    table = decode_frame(codes, model)
    linear = table[frame.astype(jnp.int32), jnp.arange(3)] * (1.0 - cover) + layer[..., :3]
    enc = encode_frame(jnp.clip(linear, 0.0, 1.0), model) * 255.0
    if noise is not None:
        enc = enc + (model.noise * cover) * noise
    out = jnp.clip(jnp.round(enc), 0.0, 255.0).astype(jnp.uint8)
    return jnp.where(cover > 1.0 / 512.0, out, frame)


def gaussian_blur(image: jax.Array, sigma: float) -> jax.Array:
    """(H, W, C) image blurred by a Gaussian of σ = ``sigma`` pixels (static), separably,
    over ±⌈3σ⌉ taps with normalised weights, zero outside the image."""
    r = max(1, math.ceil(3.0 * sigma))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k = (k / k.sum()).astype(np.float32)
    h, w = image.shape[:2]
    out = jnp.pad(image, ((r, r), (0, 0), (0, 0)))
    out = sum(float(k[i]) * out[i:i + h] for i in range(2 * r + 1))
    out = jnp.pad(out, ((0, 0), (r, r), (0, 0)))
    return sum(float(k[i]) * out[:, i:i + w] for i in range(2 * r + 1))


def _frame_noise(frame: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """Standard normal draws of ``shape`` for a frame, seeded by the frame's content (another
    frame, other noise; the same frame, the same noise: renders stay reproducible)."""
    sample = frame[::7, ::5].reshape(-1).astype(jnp.uint32)
    weights = jnp.arange(sample.size, dtype=jnp.uint32) * jnp.uint32(2654435761) + 1
    seed = jnp.sum(sample * weights)  # wraps around: a hash of the sampled bytes
    key = jax.random.key(seed)
    return jax.random.normal(key, shape, jnp.float32)


# --------------------------------------------------------------------------------------------
# the camera model of a scene config ([camera_colour]) and its calibration from a chart shot


def camera_model_from_spec(spec, wavelengths=None) -> CameraModel:
    """:class:`CameraModel` of a :class:`~spectral_fit.io.CameraColourSpec`:
    ``xyz_matrix = diag(white_balance) · matrix`` (XYZ route only)."""
    m = np.diag(np.asarray(spec.white_balance, np.float64)) @ np.asarray(spec.matrix,
                                                                          np.float64)
    wl = np.zeros(1) if wavelengths is None else np.asarray(wavelengths, np.float64)
    return CameraModel(jnp.zeros((wl.size, 3), jnp.float32), jnp.asarray(m, jnp.float32),
                       jnp.asarray(wl, jnp.float32), tone=spec.tone, gamma=float(spec.gamma),
                       has_spectral=False)


def chart_xyz(scene, *, chart: str = "BabelColor Average") -> tuple[np.ndarray, np.ndarray]:
    """(24, 3) absolute XYZ (cd/m²) of a ColorChecker lying on the table (facing world +Y)
    under the scene's environment, as the renderer would compute them (reflectance ×
    :func:`spectral_fit.lighting.white_reference`, CIE 1931 2° at 683 lm/W), and the (3,) XYZ of
    that light's white."""
    from ..color import xyz_weights
    from ..lighting import white_reference
    from ..rendering import load_environment

    wl = scene.wavelengths
    white = white_reference(load_environment(scene, wl))
    w = xyz_weights(wl)
    return (colorchecker_reflectances(wl, chart=chart) * white) @ w, white @ w


def frame_delta_e00(a, b, *, tone: str = "srgb", gamma: float = 2.2) -> np.ndarray:
    """CIEDE2000 between encoded frame colours ``a`` and ``b`` ((…, 3) in [0, 1]), both
    decoded with the tone curve and read as linear sRGB (D65 white)."""
    import colour

    probe = CameraModel(jnp.zeros((1, 3)), jnp.eye(3), jnp.zeros(1), tone=tone, gamma=gamma,
                        has_spectral=False)
    wxy = colour.RGB_COLOURSPACES["sRGB"].whitepoint

    def lab(x):
        lin = np.asarray(decode_frame(jnp.asarray(np.asarray(x, np.float32)), probe),
                         np.float64)
        return colour.XYZ_to_Lab(colour.RGB_to_XYZ(lin, "sRGB"), wxy)

    return np.asarray(colour.delta_E(lab(a), lab(b), method="CIE 2000"))


def _fit_gamma(xyz: np.ndarray, enc: np.ndarray) -> float:
    """Exponent γ of enc = (k·Y)^(1/γ) from the chart's neutral patches (19–24): a line
    through (log Y, log enc), channels averaged; unclipped patches only."""
    y = xyz[18:24, 1]
    e = np.asarray(enc, np.float64)[18:24].mean(1)
    ok = (e > 0.02) & (e < 0.98) & (y > 0)
    if ok.sum() < 3:
        raise InputError("fewer than 3 unclipped neutral patches to fit the tone curve",
                         field="--tone")
    slope = np.polyfit(np.log(y[ok]), np.log(e[ok]), 1)[0]
    if not slope > 0:
        raise InputError("the neutral patches do not get brighter with luminance",
                         field="--tone")
    return float(1.0 / slope)


@dataclasses.dataclass(frozen=True, eq=False)
class ChartCalibration:
    """Result of :func:`calibrate_colour`.

    Attributes:
        matrix: (3, 3) XYZ → white-balanced linear frame RGB (the scene's white → equal
            channels, at its luminance Y).
        white_balance: (3,) per-channel gains; the full map is ``diag(wb) · matrix``.
        tone, gamma: the frame's tone curve ("gamma" with a fitted exponent for ``fit``).
        model: the :class:`CameraModel`.
        xyz: (24, 3) the patches' XYZ; frame_rgb: (24, 3) their sampled encoded values.
        used: (24,) bool, patches in the fit (unclipped, not held out).
        delta_e00: (24,) ΔE00 between each patch's predicted and sampled frame colour.
    """

    matrix: np.ndarray
    white_balance: np.ndarray
    tone: str
    gamma: float
    model: CameraModel
    xyz: np.ndarray
    frame_rgb: np.ndarray
    used: np.ndarray
    delta_e00: np.ndarray


def calibrate_colour(image: np.ndarray, corners, xyz, white_xyz, *, tone: str = "srgb",
                     gamma: float = 2.2, hold_out=()) -> ChartCalibration:
    """Fit the video camera's colour model from a ColorChecker in a frame.

    Args:
        image: (H, W, 3) uint8 RGB frame showing the chart.
        corners: (4, 2) pixel coordinates (x, y; OpenCV convention) of the chart's outer
            patch corners, top-left, top-right, bottom-right, bottom-left (patch 1, dark
            skin, at the top-left; see :func:`sample_chart`).
        xyz: (24, 3) absolute XYZ of the patches under the scene's light (:func:`chart_xyz`).
        white_xyz: (3,) XYZ of that light's white (for the white-balance decomposition).
        tone: "srgb", "gamma" (exponent ``gamma``), "linear", or "fit" (a "gamma" curve whose
            exponent is fitted on the neutral patches).
        hold_out: patch indices (0-based) left out of the fit (to validate it).
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise InputError(f"need an (H, W, 3) uint8 image, got {img.shape} {img.dtype}",
                         field="image")
    c = np.asarray(corners, np.float64)
    if c.shape != (4, 2) or not np.all(np.isfinite(c)):
        raise InputError(f"need 4 (x, y) corners, got shape {c.shape}", field="--corners")
    h, w = img.shape[:2]
    if np.any(c < 0) or np.any(c[:, 0] > w) or np.any(c[:, 1] > h):
        raise InputError(f"corners must lie inside the {w}x{h} image", field="--corners")
    return calibrate_colour_samples(sample_chart(img, c) / 255.0, xyz, white_xyz, tone=tone,
                                    gamma=gamma, hold_out=hold_out)


def calibrate_colour_samples(enc, xyz, white_xyz, *, tone: str = "srgb", gamma: float = 2.2,
                             hold_out=()) -> ChartCalibration:
    """:func:`calibrate_colour` from the chart's sampled patches: ``enc`` (24, 3) encoded
    frame values in [0, 1] (e.g. :func:`sample_chart` / 255, or a mean over frames), ``xyz``
    (24, 3) their absolute XYZ under the scene's light, ``white_xyz`` (3,) that light's
    white."""
    if tone not in ("srgb", "gamma", "linear", "fit"):
        raise InputError(f"unknown tone curve {tone!r}", field="--tone")
    xyz = np.asarray(xyz, np.float64)
    enc = np.asarray(enc, np.float64)
    if enc.shape != (24, 3) or xyz.shape != (24, 3):
        raise InputError(f"need (24, 3) patch values and XYZ, got {enc.shape} and {xyz.shape}",
                         field="chart")
    white_xyz = np.asarray(white_xyz, np.float64)
    if tone == "fit":
        tone, gamma = "gamma", _fit_gamma(xyz, enc)
    keep = np.ones(24, bool)
    keep[list(hold_out)] = False
    fitted = camera_model_from_colorchecker(xyz[keep], enc[keep], tone=tone, gamma=gamma)
    full = np.asarray(fitted.xyz_matrix, np.float64)
    ok = np.all((enc < 0.98) & (enc > 0.02), axis=1) & keep
    wrgb = full @ np.asarray(white_xyz, np.float64)
    if np.any(wrgb <= 0):
        raise InputError("the fitted camera sees the scene's white with a non-positive "
                         "channel; check the corners (patch 1 = dark skin at the top-left)",
                         field="--corners")
    wb = wrgb / white_xyz[1]
    matrix = full / wb[:, None]
    pred = np.asarray(encode_frame(fitted.linear_from_xyz(jnp.asarray(xyz, jnp.float32)),
                                   fitted), np.float64)
    de = frame_delta_e00(pred, enc, tone=tone, gamma=gamma)
    return ChartCalibration(matrix=matrix, white_balance=wb, tone=tone, gamma=float(gamma),
                            model=fitted, xyz=xyz, frame_rgb=enc, used=ok, delta_e00=de)


def _colour_lines(cal: ChartCalibration, note: str) -> list[str]:
    rows = ", ".join("[" + ", ".join(f"{x:.9g}" for x in r) + "]" for r in cal.matrix)
    used = cal.delta_e00[cal.used]
    return [
        f"# calibrated: {note}; {int(cal.used.sum())} patches, ΔE00 mean "
        f"{used.mean():.2f} max {used.max():.2f}",
        f"matrix = [{rows}]",
        "white_balance = [" + ", ".join(f"{x:.9g}" for x in cal.white_balance) + "]",
        f'tone = "{cal.tone}"',
        f"gamma = {cal.gamma:.6g}",
    ]


def colour_config_text(text: str, cal: ChartCalibration, note: str = "ColorChecker") -> str:
    """The config ``text`` with its ``[camera_colour]`` table replaced by (or, when missing,
    appended with) the calibration; every other line is kept."""
    import re

    header = re.compile(r"^\s*\[\[?\s*([A-Za-z0-9_.\"' -]+?)\s*\]\]?\s*(#.*)?$")
    out: list[str] = []
    skipping = False
    for line in text.splitlines():
        m = header.match(line)
        if m:
            skipping = m.group(1).strip() == "camera_colour"
            if skipping:
                continue
        if not skipping:
            out.append(line)
    while out and not out[-1].strip():
        out.pop()
    out += ["", "[camera_colour]", *_colour_lines(cal, note)]
    return "\n".join(out) + "\n"


def write_colour_config(config, cal: ChartCalibration, output=None, *,
                        overwrite: bool = False, note: str = "ColorChecker"):
    """Write ``config`` with ``[camera_colour]`` from ``cal`` into ``output`` (default
    ``<name>.colour.toml`` next to it), atomically, validated before it is written; an
    existing file is kept unless ``overwrite``. Returns the path."""
    import tomllib
    from pathlib import Path

    from .._runtime.fileio import atomic_write_text, read_text
    from ..io import parse_scene

    src = Path(config)
    text = read_text(src)
    dest = Path(output) if output is not None else src.with_name(src.stem + ".colour.toml")
    if dest.exists() and not overwrite:
        raise InputError("exists; pass --overwrite to replace it", path=dest, field="--output")
    if dest.resolve().parent != src.resolve().parent:
        raise InputError("write the new config next to the original (relative paths in it "
                         "stay valid)", path=dest, field="--output")
    new = colour_config_text(text, cal, note)
    try:
        parse_scene(tomllib.loads(new), path=src)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"could not insert the colour calibration: {exc}", path=src) from None
    atomic_write_text(dest, new)
    return dest
