"""Committed reference data: per-patch mean spectra rendered offline by Mitsuba.

Files: ``measurements/reference/<name>.npz`` (arrays and a JSON metadata string), written by
``scripts/make_references.py`` through :func:`make_reference` and read by :func:`load_reference`.
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..._runtime.errors import InputError
from ..._runtime.paths import REPO_ROOT

__all__ = ["Reference", "REFERENCE_DIR", "load_reference", "save_reference", "reference_path"]

#: Default folder of the committed references (the repository's measurements/reference).
REFERENCE_DIR = REPO_ROOT / "measurements" / "reference"

_ARRAYS = ("wavelengths", "boxes", "object_index", "spectra", "noise", "direct",
           "noise_direct", "ir_fraction", "ir_noise", "preview_xyz")
#: per-patch geometry of the exact spheres: only in sphere references (NaN when absent)
_SPHERE_ARRAYS = ("normals", "points", "views")


@dataclasses.dataclass(frozen=True)
class Reference:
    """Ground-truth patch spectra of one scene config (P patches, L bands).

    Two layouts (``metadata['layout']``): ``"spheres"`` (benchmark, two_spheres: patches tiling
    the exact spheres, labels at a 5 % interreflection share) and ``"grid"`` (scenes of any
    shape: the frame's 5×5 grid from column and row 1, patches whose pixels and a one-pixel
    border show one object, and for a scene with ``[[surfaces]]`` table patches within
    ``metadata['radii']`` bounding radii of an object; labels at a 2 % share).

    Attributes:
        name: reference name (file stem), e.g. ``"benchmark"``.
        config: the scene config it was rendered from (path relative to the repository root).
        wavelengths: (L,) nm, the config's grid.
        boxes: (P, 4) int32 pixel boxes x0, y0, x1, y1 (x1, y1 exclusive; row 0 on top) in the
            config's frame (width × height); the patch spectrum is the mean over these pixels.
        object_names: names of the scene's objects; ``object_index``: (P,) index into them, or
            −1 for a patch of a real surface (the table; ``labels`` "table").
        normals, points, views: (P, 3) float64, the exact sphere's unit normal and point hit by
            the camera ray through the patch centre, and the unit direction to the camera
            (NaN in the grid layout).
        spectra: (P, L) float32 mean radiance with interreflection (path depth 16),
            W·sr⁻¹·m⁻²·nm⁻¹ in the environment map's units.
        noise: (P, L) its Monte Carlo standard error (from independent passes).
        direct: (P, L) the same without interreflection (path depth 2: one bounce of the
            environment, the neighbour still occluding it); ``noise_direct`` its error (NaN for
            table patches outside the depth-2 render's window).
        ir_fraction: (P,) (Y₁₆ − Y₂)/Y₁₆, the share of the patch luminance that comes from
            interreflection; ``ir_noise``: (P,) its standard error.
        labels: (P,) "interreflection" where ``ir_fraction`` exceeds ``metadata['threshold']``
            (spheres: and 3 standard errors), else "direct"; "table" for surface patches.
        preview_xyz: (h, w, 3) float32 CIE XYZ (683 lm/W scale) of the depth-16 render over
            ``metadata['crop']`` (x0, y0, width, height), every ``metadata['preview_step']``
            (default 1) pixels (the mean of each step × step block).
        metadata: variant, spp, passes, seeds, render seconds, Mitsuba version, date, ...
        near: (P,) for a table patch the object within whose bounding radii it lies, else −1.
        noise_de: (P,) the Monte Carlo standard error of the patch colour as ΔE00 (from the
            spread of the passes; NaN when not recorded).
    """

    name: str
    config: str
    wavelengths: np.ndarray
    boxes: np.ndarray
    object_names: tuple[str, ...]
    object_index: np.ndarray
    normals: np.ndarray
    points: np.ndarray
    views: np.ndarray
    spectra: np.ndarray
    noise: np.ndarray
    direct: np.ndarray
    noise_direct: np.ndarray
    ir_fraction: np.ndarray
    ir_noise: np.ndarray
    labels: np.ndarray
    preview_xyz: np.ndarray
    metadata: dict[str, Any]
    near: np.ndarray | None = None
    noise_de: np.ndarray | None = None

    @property
    def num_patches(self) -> int:
        return int(self.boxes.shape[0])

    @property
    def interreflection(self) -> np.ndarray:
        """(P,) bool: patches labelled "interreflection"."""
        return self.labels == "interreflection"

    def patch_means(self, image: np.ndarray) -> np.ndarray:
        """Means (P, C) of a full-frame image (H, W, C) over this reference's patch boxes (use it
        on a render of the same config to compare with :attr:`spectra`)."""
        img = np.asarray(image)
        out = np.empty((self.num_patches, img.shape[-1]), np.float64)
        for i, (x0, y0, x1, y1) in enumerate(self.boxes):
            out[i] = img[y0:y1, x0:x1].reshape(-1, img.shape[-1]).mean(axis=0)
        return out

    def xyz(self, *, direct: bool = False) -> np.ndarray:
        """(P, 3) absolute CIE XYZ of the patch spectra (colorimetry.radiance_to_xyz)."""
        from ...color import radiance_to_xyz

        return np.asarray(radiance_to_xyz(self.direct if direct else self.spectra,
                                          self.wavelengths))


def reference_path(name: str | os.PathLike[str]) -> Path:
    """The file of a reference: a name (``"benchmark"``) under :data:`REFERENCE_DIR`, or a
    path to an ``.npz`` file."""
    p = Path(name)
    if p.suffix == ".npz" or p.is_file():
        return p
    return REFERENCE_DIR / f"{p.name}.npz"


def load_reference(name: str | os.PathLike[str] = "benchmark") -> Reference:
    """Load committed ground truth: ``load_reference("benchmark")`` or ``"two_spheres"`` (from
    ``measurements/reference/``), or a path to an ``.npz`` written by :func:`save_reference`.

    Usage by a validation command: render the same config (``ref.config``) with our renderer
    into a full-frame spectral image (H, W, L) on ``ref.wavelengths``, take
    ``ref.patch_means(image)`` (P, L) and compare with ``ref.spectra`` (interreflection on) or
    ``ref.direct`` (interreflection off), in units of ``ref.noise`` or as ΔE00/Δu′v′ of
    ``ref.xyz()``; split the statistics by ``ref.labels`` ("direct" / "interreflection").
    """
    p = reference_path(name)
    if not p.is_file():
        raise InputError(f"reference not found (known: "
                         f"{sorted(q.stem for q in REFERENCE_DIR.glob('*.npz'))})", path=p)
    try:
        with np.load(p, allow_pickle=False) as z:
            arrays = {k: np.asarray(z[k]) for k in z.files}
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read reference ({exc})", path=p) from None
    missing = [k for k in (*_ARRAYS, "labels", "metadata") if k not in arrays]
    if missing:
        raise InputError(f"missing arrays {missing}", path=p, field="npz")
    meta = json.loads(str(arrays["metadata"]))
    L = arrays["wavelengths"].size
    P = arrays["boxes"].shape[0]
    for k in _SPHERE_ARRAYS:
        arrays.setdefault(k, np.full((P, 3), np.nan))
    arrays.setdefault("near", np.full(P, -1))
    arrays.setdefault("noise_de", np.full(P, np.nan))
    for k in ("spectra", "noise", "direct", "noise_direct"):
        if arrays[k].shape != (P, L):
            raise InputError(f"expected shape {(P, L)}, got {arrays[k].shape}", path=p, field=k)
    return Reference(
        name=str(meta.get("name", p.stem)),
        config=str(meta.get("config", "")),
        wavelengths=arrays["wavelengths"].astype(np.float64),
        boxes=arrays["boxes"].astype(np.int64),
        object_names=tuple(meta.get("object_names", ())),
        object_index=arrays["object_index"].astype(np.int64),
        normals=arrays["normals"].astype(np.float64),
        points=arrays["points"].astype(np.float64),
        views=arrays["views"].astype(np.float64),
        spectra=arrays["spectra"].astype(np.float64),
        noise=arrays["noise"].astype(np.float64),
        direct=arrays["direct"].astype(np.float64),
        noise_direct=arrays["noise_direct"].astype(np.float64),
        ir_fraction=arrays["ir_fraction"].astype(np.float64),
        ir_noise=arrays["ir_noise"].astype(np.float64),
        labels=arrays["labels"].astype(str),
        preview_xyz=(arrays["preview_xyz"].astype(np.float32)
                     * np.float32(meta.get("preview_unit", 1.0))),
        metadata=meta,
        near=arrays["near"].astype(np.int64),
        noise_de=arrays["noise_de"].astype(np.float64),
    )


def save_reference(path: str | os.PathLike[str], ref: Reference) -> Path:
    """Write a reference as a compressed ``.npz`` (atomically); returns the path. The sphere
    geometry, ``near`` and ``noise_de`` are written only when they hold something. The grid
    layout (``metadata['layout'] == "grid"``) is compact: spectra, their errors and the
    preview as float16 (relative rounding ≤ 4.9×10⁻⁴, far below the Monte Carlo noise; the
    preview relative to the scene white's luminance, ``metadata['preview_unit']``)."""
    from ..._runtime.fileio import atomic_write_bytes

    meta = dict(ref.metadata, name=ref.name, config=ref.config,
                object_names=list(ref.object_names))
    grid = meta.get("layout") == "grid"
    spectra_dtype = np.float16 if grid else np.float32
    unit = 1.0
    if grid:  # float16 holds XYZ relative to the scene white's luminance
        unit = float(meta.get("white_xyz", [0.0, 1.0])[1]) or 1.0
        meta["preview_unit"] = unit
    arrays = {
        "wavelengths": np.asarray(ref.wavelengths, np.float32),
        "boxes": np.asarray(ref.boxes, np.int32),
        "object_index": np.asarray(ref.object_index, np.int32),
        **{k: np.asarray(getattr(ref, k), np.float64) for k in _SPHERE_ARRAYS
           if np.isfinite(getattr(ref, k)).any()},
        **{k: np.asarray(getattr(ref, k), spectra_dtype)
           for k in ("spectra", "noise", "direct", "noise_direct")},
        "ir_fraction": np.asarray(ref.ir_fraction, np.float32),
        "ir_noise": np.asarray(ref.ir_noise, np.float32),
        "labels": np.asarray(ref.labels, dtype="U16"),
        "preview_xyz": (np.asarray(ref.preview_xyz, np.float64) / unit).astype(
            np.float16 if grid else np.float32),
        "metadata": np.asarray(json.dumps(meta, sort_keys=True)),
    }
    if ref.near is not None and (np.asarray(ref.near) >= 0).any():
        arrays["near"] = np.asarray(ref.near, np.int16)
    if ref.noise_de is not None and np.isfinite(ref.noise_de).any():
        arrays["noise_de"] = np.asarray(ref.noise_de, np.float32)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    p = Path(path)
    atomic_write_bytes(p, buf.getvalue())
    return p
