"""Writing rendered frames: spectral EXR, XYZ EXR, display-RGB EXR, PNG, coverage mask, and a
composite over a background picture. Every file is written atomically (``fileio``).

Files (all optional, chosen by :func:`write_frame`'s arguments):

* spectral OpenEXR (Fichet et al. 2021 layout, ``S0.<λ>nm`` channels, W·sr⁻¹·m⁻²·nm⁻¹, with
  linear-sRGB preview channels) of ``Frame.spectral`` (render with ``spectral=True``);
* XYZ OpenEXR: channels X, Y, Z, absolute CIE XYZ (Y in cd/m²), float32;
* display-RGB OpenEXR: channels R, G, B, the display's LINEAR RGB (exposure applied, display
  white = 1, before clipping: values outside [0, 1] are the out-of-gamut colours), float32;
* PNG: display-encoded RGB (8 bit);
* mask PNG: 255 where an object covers the pixel, 0 elsewhere;
* composite PNG: the frame's object pixels over a background picture (PNG/JPEG, display
  encoded, same size as the frame), e.g. a video frame.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from .._runtime.errors import InputError
from .._runtime.fileio import atomic_path

__all__ = ["write_frame", "write_xyz_exr", "write_rgb_exr", "composite", "read_background"]


def _write_exr(path: str | os.PathLike[str], image: np.ndarray, names: str,
               attributes: dict[str, Any]) -> None:
    import OpenEXR

    img = np.asarray(image, np.float32)
    if img.ndim != 3 or img.shape[-1] != len(names):
        raise InputError(f"need shape (H, W, {len(names)}), got {img.shape}", field="image")
    if not np.all(np.isfinite(img)):
        raise InputError("NaN or infinite value", field="image")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              **attributes}
    channels = {n: np.ascontiguousarray(img[..., i]) for i, n in enumerate(names)}
    with atomic_path(path) as tmp:
        try:
            OpenEXR.File(header, channels).write(str(tmp))
        except Exception as exc:
            raise InputError(f"OpenEXR could not write the file ({exc})", path=path) from None


def write_xyz_exr(path: str | os.PathLike[str], xyz: Any) -> None:
    """Write absolute CIE XYZ (H, W, 3) (Y in cd/m²) as an OpenEXR with channels X, Y, Z."""
    _write_exr(path, np.asarray(xyz), "XYZ", {"xyzUnits": "cd.m^-2 (Y)"})


def write_rgb_exr(path: str | os.PathLike[str], linear_rgb: Any, *, colourspace: str = "sRGB"
                  ) -> None:
    """Write linear display RGB (H, W, 3) (display white = 1, unclipped) as channels R, G, B."""
    _write_exr(path, np.asarray(linear_rgb), "RGB", {"colourspace": colourspace,
                                                      "rgbEncoding": "linear"})


def read_background(path: str | os.PathLike[str], shape: tuple[int, int]) -> np.ndarray:
    """A background picture (PNG/JPEG, display-encoded) as RGB (H, W, 3) in [0, 1]; it must
    have the frame's size ``shape`` = (H, W)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            a = np.asarray(im.convert("RGB"), np.float64) / 255.0
    except (OSError, UnidentifiedImageError) as exc:
        raise InputError(f"cannot read the picture ({exc})", path=path,
                         field="background") from None
    if a.shape[:2] != tuple(shape):
        raise InputError(f"picture is {a.shape[1]}×{a.shape[0]}, the frame "
                         f"{shape[1]}×{shape[0]}", path=path, field="background")
    return a


def composite(rgb: Any, mask: Any, background: Any, ratio: Any = None,
              display: Any = None) -> np.ndarray:
    """Object pixels of ``rgb`` (H, W, 3) where ``mask`` (H, W), ``background`` (H, W, 3)
    elsewhere (all display-encoded). With ``ratio`` (H, W, 3), the change the objects make
    on the real surfaces in linear display RGB (:func:`~spectral_fit.rendering.surface_ratio`,
    1 where none): the background's pixels are decoded with ``display``'s curve (sRGB by
    default), multiplied and encoded again; pixels with a ratio of exactly 1 keep their
    values, and a pixel with a clipped channel is only darkened (as
    :func:`spectral_fit.live.relight`)."""
    m = np.asarray(mask, bool)[..., None]
    bg = np.asarray(background, np.float64)
    if ratio is not None:
        from ..color import decode, encode

        r = np.asarray(ratio, np.float64)
        r = np.where(np.any(bg >= 1.0, axis=-1, keepdims=True), np.minimum(r, 1.0), r)
        keep = np.all(r == 1.0, axis=-1, keepdims=True)
        lit = np.clip(encode(decode(bg, display) * r, display), 0.0, 1.0)
        bg = np.where(keep, bg, lit)
    return np.where(m, np.asarray(rgb, np.float64), bg)


def write_frame(
    frame: Any,
    *,
    png: str | os.PathLike[str] | None = None,
    exr: str | os.PathLike[str] | None = None,
    xyz_exr: str | os.PathLike[str] | None = None,
    rgb_exr: str | os.PathLike[str] | None = None,
    mask_png: str | os.PathLike[str] | None = None,
    composite_png: str | os.PathLike[str] | None = None,
    background: str | os.PathLike[str] | None = None,
    surface_ratio: Any = None,
    wavelengths: Any = None,
    colourspace: str = "sRGB",
) -> list[str]:
    """Write the chosen files of a :class:`~spectral_fit.rendering.Frame`; returns their paths.

    ``exr`` needs ``frame.spectral`` and ``wavelengths`` (L,); ``composite_png`` needs
    ``background`` (a picture of the frame's size); ``surface_ratio`` (H, W, 3) the
    objects' shadows and light on the real surfaces, applied to the background
    (:func:`composite`).
    """
    from ..color import save_png
    from ..io import write_spectral_exr

    written = []
    if png is not None:
        save_png(png, np.asarray(frame.rgb))
        written.append(str(png))
    if exr is not None:
        if frame.spectral is None or wavelengths is None:
            raise InputError("the spectral EXR needs a frame rendered with spectral=True and "
                             "its wavelengths", field="exr")
        write_spectral_exr(exr, np.asarray(wavelengths), np.asarray(frame.spectral))
        written.append(str(exr))
    if xyz_exr is not None:
        write_xyz_exr(xyz_exr, frame.xyz)
        written.append(str(xyz_exr))
    if rgb_exr is not None:
        write_rgb_exr(rgb_exr, frame.linear_rgb, colourspace=colourspace)
        written.append(str(rgb_exr))
    if mask_png is not None:
        save_png(mask_png, np.asarray(frame.mask, np.float64))
        written.append(str(mask_png))
    if composite_png is not None:
        if background is None:
            raise InputError("a composite needs a background picture", field="background")
        bg = read_background(background, tuple(np.shape(frame.mask)))
        save_png(composite_png, composite(frame.rgb, frame.mask, bg, surface_ratio))
        written.append(str(composite_png))
    return written
