"""Camera photographs as readings of a measurement session (``[[images]]``): a raw Bayer
mosaic or a linear (demosaiced) image in camera counts, the camera's spectral sensitivities,
its exposure, black and white levels, noise model and pose.

A pixel of channel c records (docs/measurements.md, "Images")

    v_c = black + t · Σ_λ s_c(λ) L(λ) Δλ  (+ noise),   clipped at the white level,

with t the exposure (s), s_c the sensitivity in counts per second per W·sr⁻¹·m⁻²·nm⁻¹ per nm
on the scene's wavelength grid (Δλ its step, nm; trapezoid weights on an uneven grid) and L
the spectral radiance reaching the pixel. Noise: σ² = read² + gain · (v − black) (read noise
in counts, gain in counts per photo-electron).

This module is plain NumPy (the data layer): it loads and checks the files and says what
each pixel is; the fit turns pixels into readings (:mod:`spectral_fit.fitting`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from .._runtime.errors import InputError
from .._runtime.fileio import read_text
from ._manifest import _Ctx

__all__ = ["ImageReading", "MOSAICS", "load_image_pixels", "load_sensitivities"]

#: Bayer layouts (the 2 × 2 tile read row by row) and "none": every pixel has every channel
MOSAICS = ("RGGB", "BGGR", "GRBG", "GBRG", "none")
_MAX_PIXELS = 64_000_000


@dataclasses.dataclass(frozen=True)
class ImageReading:
    """One camera photograph used as a reading (see the module docstring).

    Attributes:
        id: unique name.
        file: the image file.
        pixels: (H, W) raw mosaic or (H, W, C) linear image, in counts (float64, black level
            not subtracted).
        mosaic: one of :data:`MOSAICS`.
        sensitivities: (C, L) s_c(λ) on the scene's grid, counts · s⁻¹ per
            (W·sr⁻¹·m⁻²·nm⁻¹ · nm); channels in the order R, G, B of the mosaic (from a file,
            or estimated from a chart shot).
        exposure_s: t, seconds.
        black_level, white_level: counts; a pixel at or above
            ``black + saturation · (white − black)`` is clipped (left out).
        saturation: see ``white_level``.
        read_noise: counts (σ of a dark pixel).
        gain: counts per photo-electron (shot-noise variance = gain × signal).
        superpixel: side in pixels of the square bins the fit compares (even for a mosaic).
        samples: shading samples per bin side (samples² per bin).
        objects: the objects whose pixels enter the fit (empty: every object).
        position, aim, up: (3,) camera pose, world metres (OpenGL look-at).
        fov_y_deg: vertical field of view, or None when ``intrinsics`` are given.
        intrinsics: (4,) fx, fy, cx, cy in pixels (OpenCV: pixel (0, 0)'s centre at 0), or
            None.
        line: line of the ``[[images]]`` header in the manifest; index: its position.
    """

    id: str
    file: Path
    pixels: np.ndarray
    mosaic: str
    sensitivities: np.ndarray
    exposure_s: float
    black_level: float
    white_level: float
    saturation: float
    read_noise: float
    gain: float
    superpixel: int
    samples: int
    objects: tuple[str, ...]
    position: np.ndarray
    aim: np.ndarray
    up: np.ndarray
    fov_y_deg: float | None
    intrinsics: np.ndarray | None
    line: int | None
    index: int

    @property
    def field(self) -> str:
        return f"images[{self.index}]"

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) pixels."""
        return int(self.pixels.shape[0]), int(self.pixels.shape[1])

    @property
    def channels(self) -> int:
        return int(self.sensitivities.shape[0])

    def channel_of_pixel(self) -> np.ndarray:
        """(H, W) channel index of every pixel of a mosaic (R 0, G 1, B 2); −1 without one."""
        H, W = self.shape
        if self.mosaic == "none":
            return np.full((H, W), -1, np.int64)
        tile = np.array(["RGB".index(c) for c in self.mosaic]).reshape(2, 2)
        return np.tile(tile, (H // 2 + 1, W // 2 + 1))[:H, :W]

    def clip_level(self) -> float:
        """Counts at and above which a pixel is clipped."""
        return self.black_level + self.saturation * (self.white_level - self.black_level)


def load_image_pixels(path: Path, mosaic: str, channels: int) -> np.ndarray:
    """Read an image file: ``.npy`` (2-D mosaic or (H, W, C)), ``.exr`` (R, G, B; linear),
    or 16-bit ``.png``/``.tif``/``.tiff`` → float64 counts. Raises :class:`InputError`
    naming the file for a wrong shape, NaN or negative counts."""
    suf = path.suffix.lower()
    try:
        if suf == ".npy":
            arr = np.load(path, allow_pickle=False)
        elif suf == ".exr":
            from ._exr import read_rgb_exr

            arr = read_rgb_exr(path)
        elif suf in (".png", ".tif", ".tiff"):
            import skimage.io

            arr = skimage.io.imread(path)
        else:
            raise InputError(f"unknown image format {suf!r}; use .npy, .exr, .png or .tif",
                             path=path, field="file")
    except InputError:
        raise
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read the image: {e}", path=path, field="file") from None
    arr = np.asarray(arr)
    if arr.dtype.kind not in "uif":
        raise InputError(f"pixels must be numbers, got dtype {arr.dtype}", path=path,
                         field="pixels")
    arr = arr.astype(np.float64)
    if mosaic != "none":
        if arr.ndim != 2:
            raise InputError(f"a {mosaic} mosaic must be one channel (H, W), got shape "
                             f"{arr.shape}", path=path, field="pixels")
        if arr.shape[0] % 2 or arr.shape[1] % 2:
            raise InputError(f"a mosaic needs an even width and height, got {arr.shape}",
                             path=path, field="pixels")
    elif arr.ndim != 3 or arr.shape[2] != channels:
        raise InputError(f"a demosaiced image must be (H, W, {channels}) for {channels} "
                         f"sensitivity channels, got shape {arr.shape}", path=path,
                         field="pixels")
    if arr.shape[0] < 8 or arr.shape[1] < 8 or arr.size > _MAX_PIXELS:
        raise InputError(f"image size {arr.shape} out of range", path=path, field="pixels")
    if not np.all(np.isfinite(arr)):
        raise InputError("NaN or infinite pixels", path=path, field="pixels")
    if np.any(arr < 0):
        raise InputError("negative counts (give the raw values, black level included)",
                         path=path, field="pixels")
    return arr


def load_sensitivities(path: Path, wl: np.ndarray) -> np.ndarray:
    """A camera's spectral sensitivities: a spectrum file with one column per channel (R, G, B
    for a mosaic) → (C, L) on the grid ``wl``, counts · s⁻¹ per (W·sr⁻¹·m⁻²·nm⁻¹ · nm)."""
    from ..color import parse_spectrum_text, resample

    text = read_text(path, encoding="utf-8-sig", max_bytes=4 * 1024 * 1024,
                     what="camera sensitivities")
    try:
        w, v = parse_spectrum_text(text, path=path)
    except InputError as e:
        raise InputError(e.reason, path=path, line=e.line,
                         field=e.field or "sensitivities") from None
    v = np.atleast_2d(v)
    if not 1 <= v.shape[0] <= 8:
        raise InputError(f"expected 1 to 8 channel columns, found {v.shape[0]}", path=path,
                         field="sensitivities")
    out = resample(w, v, wl, path=path, field="sensitivities")
    if not np.all(np.isfinite(out)) or np.any(out < 0):
        raise InputError("sensitivities must be finite and non-negative", path=path,
                         field="sensitivities")
    if np.any(out.max(axis=1) <= 0):
        raise InputError("a channel's sensitivity is zero at every wavelength of the scene",
                         path=path, field="sensitivities")
    return out


def _read_counts(path: Path) -> np.ndarray:
    """A chart's mean counts: CSV rows ``patch, R, G, B`` (a header line and ``#`` comments
    allowed) → (N, C), black subtracted by the user."""
    text = read_text(path, encoding="utf-8-sig", max_bytes=1024 * 1024, what="chart counts")
    rows = []
    for i, line in enumerate(text.splitlines(), start=1):
        t = line.strip()
        if not t or t.startswith("#"):
            continue
        parts = [x.strip() for x in t.replace(";", ",").split(",")]
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            if not rows:
                continue  # the header
            raise InputError(f"not a number in {parts!r}", path=path, line=i,
                             field="chart_counts") from None
        if len(vals) < 2 or (rows and len(vals) != len(rows[0])) or not all(
                np.isfinite(vals)):
            raise InputError("each row: patch, then one finite count per channel", path=path,
                             line=i, field="chart_counts")
        rows.append(vals)
    if not rows:
        raise InputError("no rows", path=path, field="chart_counts")
    return np.asarray(rows)[:, 1:]


def _chart_sensitivities(ctx: _Ctx, t: dict[str, Any], f: str, base: Path,
                         wl: np.ndarray) -> np.ndarray:
    """Sensitivities estimated from a chart shot (``{chart_counts, chart_radiance,
    exposure_s}``; :func:`spectral_fit.color.estimate_camera_sensitivities`)."""
    from ..color import estimate_camera_sensitivities
    from ._spectrum_files import _read_spectra

    ctx.finish(t, ("chart_counts", "chart_radiance", "exposure_s"), f)
    paths = {}
    for k in ("chart_counts", "chart_radiance"):
        p = base / ctx.string(t, k, f"{f}.{k}")
        if not p.is_file():
            raise ctx.err(f"{f}.{k}", f"file not found: {p}")
        paths[k] = p
    counts = _read_counts(paths["chart_counts"])  # (N, C)
    rad = _read_spectra(paths["chart_radiance"], wl, kind="radiance",
                        units="W.sr^-1.m^-2.nm^-1")  # (N, L)
    if rad.shape[0] != counts.shape[0]:
        raise InputError(f"{counts.shape[0]} patches' counts but {rad.shape[0]} radiance "
                         "columns", path=paths["chart_radiance"], field="chart_radiance")
    try:
        return estimate_camera_sensitivities(
            counts, rad, wl, ctx.number(t, "exposure_s", f"{f}.exposure_s", lo=0.0,
                                        lo_open=True))
    except InputError as e:
        raise ctx.err(f, e.reason) from None


def parse_images(ctx: _Ctx, data: dict[str, Any], base: Path, wl: np.ndarray,
                 names: list[str], lines: dict[str, int]) -> tuple[ImageReading, ...]:
    """The manifest's ``[[images]]`` tables, checked (errors name the file and field)."""
    il = data.get("images", [])
    if not isinstance(il, list):
        raise ctx.err("images", "must be an array of tables ([[images]])")
    out: list[ImageReading] = []
    seen: set[str] = set()
    for i, t in enumerate(il):
        f = f"images[{i}]"
        if not isinstance(t, dict):
            raise ctx.err(f, "must be a table")
        ctx.finish(t, ("id", "file", "mosaic", "sensitivities", "exposure_s", "black_level",
                       "white_level", "saturation", "read_noise", "gain", "superpixel",
                       "samples", "objects", "camera"), f)
        iid = ctx.string(t, "id", f"{f}.id", f"image_{i}")
        if iid in seen:
            raise ctx.err(f"{f}.id", f"repeated id {iid!r}")
        seen.add(iid)
        mosaic = ctx.string(t, "mosaic", f"{f}.mosaic", "RGGB")
        if mosaic not in MOSAICS:
            raise ctx.err(f"{f}.mosaic", f"must be one of {MOSAICS}, got {mosaic!r}")
        if isinstance(t.get("sensitivities"), dict):
            sens = _chart_sensitivities(ctx, t["sensitivities"], f"{f}.sensitivities", base, wl)
        else:
            sp = base / ctx.string(t, "sensitivities", f"{f}.sensitivities")
            if not sp.is_file():
                raise ctx.err(f"{f}.sensitivities", f"file not found: {sp}")
            sens = load_sensitivities(sp, wl)
        if mosaic != "none" and sens.shape[0] != 3:
            raise ctx.err(f"{f}.sensitivities", f"a {mosaic} mosaic needs 3 channel columns "
                          f"(R, G, B), the file has {sens.shape[0]}")
        ip = base / ctx.string(t, "file", f"{f}.file")
        if not ip.is_file():
            raise ctx.err(f"{f}.file", f"file not found: {ip}")
        pixels = load_image_pixels(ip, mosaic, sens.shape[0])
        white = ctx.number(t, "white_level", f"{f}.white_level", float(pixels.max()),
                           lo=0.0, lo_open=True)
        black = ctx.number(t, "black_level", f"{f}.black_level", 0.0, lo=0.0)
        if black >= white:
            raise ctx.err(f"{f}.black_level", f"{black:g} must be below the white level "
                          f"{white:g}")
        sp_px = int(ctx.number(t, "superpixel", f"{f}.superpixel", 8.0, lo=1.0, hi=256.0))
        if mosaic != "none" and sp_px % 2:
            raise ctx.err(f"{f}.superpixel", f"must be even for a mosaic, got {sp_px}")
        objs = t.get("objects", [])
        if not isinstance(objs, list) or not all(isinstance(x, str) for x in objs):
            raise ctx.err(f"{f}.objects", f"must be a list of object names, got {objs!r}")
        bad = [x for x in objs if x not in names]
        if bad:
            raise ctx.err(f"{f}.objects", f"unknown object {bad[0]!r}; the scene has {names}")
        cam = ctx.table(t, "camera", f"{f}.camera", required=True)
        ctx.finish(cam, ("position", "aim", "up", "fov_y_deg", "intrinsics"), f"{f}.camera")
        pos = ctx.vector(cam, "position", f"{f}.camera.position")
        aim = ctx.vector(cam, "aim", f"{f}.camera.aim")
        if np.linalg.norm(aim - pos) < 1e-3:
            raise ctx.err(f"{f}.camera.aim", "must be at least 1 mm from the camera position")
        up = ctx.vector(cam, "up", f"{f}.camera.up", [0.0, 1.0, 0.0], unit=True)
        fov = intr = None
        if ("fov_y_deg" in cam) == ("intrinsics" in cam):
            raise ctx.err(f"{f}.camera", "give exactly one of fov_y_deg and intrinsics")
        if "fov_y_deg" in cam:
            fov = ctx.number(cam, "fov_y_deg", f"{f}.camera.fov_y_deg", lo=0.1, hi=170.0)
        else:
            v = cam["intrinsics"]
            if (not isinstance(v, list) or len(v) != 4
                    or any(isinstance(x, bool) or not isinstance(x, int | float) for x in v)):
                raise ctx.err(f"{f}.camera.intrinsics", f"must be [fx, fy, cx, cy] in pixels, "
                              f"got {v!r}")
            intr = np.asarray(v, np.float64)
            if not np.all(np.isfinite(intr)) or intr[0] <= 0 or intr[1] <= 0:
                raise ctx.err(f"{f}.camera.intrinsics", f"fx, fy must be positive, got {v!r}")
        out.append(ImageReading(
            id=iid, file=ip, pixels=pixels, mosaic=mosaic, sensitivities=sens,
            exposure_s=ctx.number(t, "exposure_s", f"{f}.exposure_s", lo=0.0, lo_open=True),
            black_level=black, white_level=white,
            saturation=ctx.number(t, "saturation", f"{f}.saturation", 0.98, lo=0.1, hi=1.0),
            read_noise=ctx.number(t, "read_noise", f"{f}.read_noise", 1.0, lo=0.0),
            gain=ctx.number(t, "gain", f"{f}.gain", 0.0, lo=0.0),
            superpixel=sp_px,
            samples=int(ctx.number(t, "samples", f"{f}.samples", 1.0, lo=1.0, hi=8.0)),
            objects=tuple(objs), position=pos, aim=aim, up=up, fov_y_deg=fov, intrinsics=intr,
            line=lines.get(f), index=i))
    return tuple(out)
