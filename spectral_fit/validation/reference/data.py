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

_ARRAYS = ("wavelengths", "boxes", "object_index", "normals", "points", "views", "spectra",
           "noise", "direct", "noise_direct", "ir_fraction", "ir_noise", "preview_xyz")


@dataclasses.dataclass(frozen=True)
class Reference:
    """Ground-truth patch spectra of one scene config (P patches, L bands).

    Attributes:
        name: reference name (file stem), e.g. ``"benchmark"``.
        config: the scene config it was rendered from (path relative to the repository root).
        wavelengths: (L,) nm, the config's grid.
        boxes: (P, 4) int32 pixel boxes x0, y0, x1, y1 (x1, y1 exclusive; row 0 on top) in the
            config's frame (width × height); the patch spectrum is the mean over these pixels.
        object_names: names of the scene's objects; ``object_index``: (P,) index into them.
        normals, points, views: (P, 3) float64, the exact sphere's unit normal and point hit by
            the camera ray through the patch centre, and the unit direction to the camera.
        spectra: (P, L) float32 mean radiance with interreflection (path depth 16),
            W·sr⁻¹·m⁻²·nm⁻¹ in the environment map's units.
        noise: (P, L) its Monte Carlo standard error (from independent passes).
        direct: (P, L) the same without interreflection (path depth 2: one bounce of the
            environment, the neighbour still occluding it); ``noise_direct`` its error.
        ir_fraction: (P,) (Y₁₆ − Y₂)/Y₁₆, the share of the patch luminance that comes from
            interreflection; ``ir_noise``: (P,) its standard error.
        labels: (P,) "interreflection" where ``ir_fraction`` exceeds ``metadata['threshold']``
            (and 3 standard errors), else "direct".
        preview_xyz: (h, w, 3) float32 CIE XYZ (683 lm/W scale) of the depth-16 render over
            ``metadata['crop']`` (x0, y0, width, height).
        metadata: variant, spp, passes, seeds, render seconds, Mitsuba version, date, ...
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
        preview_xyz=arrays["preview_xyz"].astype(np.float32),
        metadata=meta,
    )


def save_reference(path: str | os.PathLike[str], ref: Reference) -> Path:
    """Write a reference as a compressed ``.npz`` (atomically); returns the path."""
    from ..._runtime.fileio import atomic_write_bytes

    meta = dict(ref.metadata, name=ref.name, config=ref.config,
                object_names=list(ref.object_names))
    arrays = {
        "wavelengths": np.asarray(ref.wavelengths, np.float32),
        "boxes": np.asarray(ref.boxes, np.int32),
        "object_index": np.asarray(ref.object_index, np.int32),
        "normals": np.asarray(ref.normals, np.float64),
        "points": np.asarray(ref.points, np.float64),
        "views": np.asarray(ref.views, np.float64),
        "spectra": np.asarray(ref.spectra, np.float32),
        "noise": np.asarray(ref.noise, np.float32),
        "direct": np.asarray(ref.direct, np.float32),
        "noise_direct": np.asarray(ref.noise_direct, np.float32),
        "ir_fraction": np.asarray(ref.ir_fraction, np.float32),
        "ir_noise": np.asarray(ref.ir_noise, np.float32),
        "labels": np.asarray(ref.labels, dtype="U16"),
        "preview_xyz": np.asarray(ref.preview_xyz, np.float32),
        "metadata": np.asarray(json.dumps(meta, sort_keys=True)),
    }
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    p = Path(path)
    atomic_write_bytes(p, buf.getvalue())
    return p
