"""Make a :class:`~spectral_fit.validation.reference.data.Reference` from a scene config (used by
``scripts/make_references.py`` and by the generator's smoke test)."""

from __future__ import annotations

import datetime as _dt
import os
from typing import Any

import numpy as np

from ..._runtime.paths import REPO_ROOT
from ...io import Scene
from .data import Reference
from .render import objects_crop, render_spectral, sphere_patches

__all__ = ["make_reference", "preview_png"]

_REPO = REPO_ROOT


def _patch_means(stack: np.ndarray, boxes: np.ndarray, crop: Any) -> np.ndarray:
    """(..., P, L) means over patch boxes of crop images (..., h, w, L)."""
    out = []
    for x0, y0, x1, y1 in boxes:
        blk = stack[..., y0 - crop.y0:y1 - crop.y0, x0 - crop.x0:x1 - crop.x0, :]
        out.append(blk.mean(axis=(-3, -2)))
    return np.stack(out, axis=-2)


def make_reference(
    scene: Scene,
    name: str,
    *,
    spp: int = 512,
    passes: int = 8,
    seed: int = 0,
    patch_size: int = 5,
    threshold: float = 0.05,
    analytic_spheres: bool = False,
    progress: Any = None,
) -> Reference:
    """Render ``scene`` at path depths 2 and 16 (``passes`` × ``spp`` samples per pixel over the
    objects' crop) and reduce it to per-patch mean spectra (see :class:`Reference`).

    Patches: ``patch_size``² pixel squares tiling each sphere (:func:`sphere_patches`). A patch
    is labelled "interreflection" when its interreflection share (Y₁₆ − Y₂)/Y₁₆ exceeds
    ``threshold`` and 3 of its standard errors.
    """
    import mitsuba as mi

    from ...color import xyz_weights

    crop = objects_crop(scene)
    pt = sphere_patches(scene, size=patch_size)
    r = render_spectral(scene, spp=spp, passes=passes, depths=(2, 16), seed=seed, crop=crop,
                        analytic_spheres=analytic_spheres, progress=progress)
    wl = r.wavelengths
    means = _patch_means(r.passes, pt["boxes"], crop)  # (2, passes, P, L)
    k = means.shape[1]

    def se(x: np.ndarray) -> np.ndarray:
        return x.std(axis=0, ddof=1) / np.sqrt(k) if k > 1 else np.full(x.shape[1:], np.nan)

    direct, total = means[0].mean(axis=0), means[1].mean(axis=0)
    w = xyz_weights(wl)
    y2, y16 = means[0] @ w[:, 1], means[1] @ w[:, 1]  # (passes, P)
    frac_p = (y16 - y2) / np.maximum(y16, 1e-30)
    frac = (y16.mean(0) - y2.mean(0)) / np.maximum(y16.mean(0), 1e-30)
    frac_se = se(frac_p)
    labels = np.where((frac > threshold) & (frac > 3.0 * np.nan_to_num(frac_se)),
                      "interreflection", "direct")
    xyz = r.mean(16) @ w
    try:
        config = os.path.relpath(scene.path, _REPO) if scene.path else ""
    except ValueError:
        config = str(scene.path)
    rel = se(means[1]) / np.maximum(np.abs(total), 1e-30)
    meta = {
        "variant": r.variant,
        "mitsuba": mi.__version__,
        "spp_per_pass": int(spp),
        "passes": int(passes),
        "spp": int(spp * passes),
        "seeds": [int(seed + p) for p in range(passes)],
        "depths": [2, 16],
        "integrator": "path (Russian roulette from depth 5, Mitsuba default), box pixel filter",
        "render_seconds": round(float(r.seconds), 1),
        "renders": int(2 * passes * -(-wl.size // 3)),
        "crop": [crop.x0, crop.y0, crop.width, crop.height],
        "frame": [scene.width, scene.height],
        "patch_size": int(patch_size),
        "threshold": float(threshold),
        "analytic_spheres": bool(analytic_spheres),
        "date": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "median_relative_noise": float(np.median(rel)),
        "p95_relative_noise": float(np.percentile(rel, 95)),
        "ir_fraction_max": float(frac.max()),
        "ir_patches": int((labels == "interreflection").sum()),
    }
    return Reference(
        name=name, config=config, wavelengths=wl, boxes=pt["boxes"],
        object_names=tuple(o.name for o in scene.objects), object_index=pt["object"],
        normals=pt["normal"], points=pt["point"], views=pt["view"],
        spectra=total, noise=se(means[1]), direct=direct, noise_direct=se(means[0]),
        ir_fraction=frac, ir_noise=frac_se, labels=labels,
        preview_xyz=xyz.astype(np.float32), metadata=meta)


def preview_png(ref: Reference, path: str | os.PathLike[str], *, boxes: bool = True) -> None:
    """Write an sRGB PNG of ``ref.preview_xyz`` (99th-percentile luminance → white; patch
    outlines: white = direct, cyan = interreflection)."""
    import colour

    from ..._runtime.fileio import atomic_path

    xyz = np.asarray(ref.preview_xyz, np.float64)
    scale = max(float(np.percentile(xyz[..., 1], 99)), 1e-30)
    with np.errstate(invalid="ignore"):
        lin = colour.XYZ_to_sRGB(xyz / scale, apply_cctf_encoding=False)
        rgb = colour.cctf_encoding(np.clip(lin, 0, 1))
    img = (np.nan_to_num(rgb) * 255 + 0.5).astype(np.uint8)
    if boxes:
        x0c, y0c = ref.metadata["crop"][:2]
        for (x0, y0, x1, y1), lab in zip(ref.boxes, ref.labels, strict=True):
            col = (0, 255, 255) if lab == "interreflection" else (255, 255, 255)
            xa, ya, xb, yb = x0 - x0c, y0 - y0c, x1 - x0c - 1, y1 - y0c - 1
            img[ya, xa:xb + 1] = col
            img[yb, xa:xb + 1] = col
            img[ya:yb + 1, xa] = col
            img[ya:yb + 1, xb] = col
    import matplotlib.image

    with atomic_path(path, suffix=".png") as tmp:
        matplotlib.image.imsave(tmp, img)
