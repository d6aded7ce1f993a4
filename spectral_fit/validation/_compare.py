"""Validation of rendered frames against the committed path-traced references.

For each interreflection mode, render the reference's scene config at its frame size with our
renderer (spectral output; each pixel the mean of ``SAMPLES``² sub-pixels, as the reference's
pixels are area means: a box pixel filter), take the mean spectrum over each reference patch
(5×5 pixels on the spheres), convert both to CIE XYZ and CIELAB against the scene white, and
report ΔE00 statistics per region: "direct" patches (interreflection below 5 % of the
luminance in the reference) and "interreflection" patches (the rest). The reference's
interreflection-on spectra (path depth 16) are the target of every mode; "none" is
additionally compared with the reference's single-bounce spectra (depth 2), which checks the
direct shading alone.

Scene white (docs/conventions.md, 'Colorimetry and display'): a perfect white Lambertian facing the
camera under the environment (the same white the display exposure uses).

Targets (issue): direct regions median ≤ 0.5, 90th percentile ≤ 1.0; interreflection regions
in gather mode median ≤ 0.5, 90th percentile ≤ 1.5; K = 8 basis vs bands: max ≤ 0.5.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from .._runtime.paths import REPO_ROOT

__all__ = ["TARGETS", "SAMPLES", "scene_white_xyz", "delta_e_patches", "pixel_means",
           "check_samples", "validate", "delta_e_figure"]

ROOT = REPO_ROOT

TARGETS = {
    "direct": {"median": 0.5, "p90": 1.0},
    "interreflection_gather": {"median": 0.5, "p90": 1.5},
    "basis_vs_bands_max": 0.5,
}


def scene_white_xyz(xyz_map: np.ndarray, rotation_y_deg: float, normal: Any) -> np.ndarray:
    """Absolute XYZ (3,) of a perfect white Lambertian with world normal ``normal`` under an
    environment whose texels have XYZ ``xyz_map`` (Hm, Wm, 3): Σ XYZ max(0, N·ω) Δω / π."""
    from ..lighting import rotation_y, texel_directions, texel_solid_angles

    h, w, _ = xyz_map.shape
    n = np.asarray(normal, np.float64)
    n_map = rotation_y(rotation_y_deg).T @ (n / np.linalg.norm(n))
    wgt = np.maximum(texel_directions(h, w) @ n_map, 0.0) * texel_solid_angles(h, w)
    return np.einsum("hw,hwc->c", wgt, xyz_map) / math.pi


def reference_scene(reference: str | os.PathLike[str]) -> tuple[Any, Path, Any]:
    """(the committed reference, its config's path, the config's scene), the reference's
    wavelengths checked against the config's."""
    from .._runtime.errors import InputError
    from ..io import load_scene
    from .reference import load_reference

    ref = load_reference(reference)
    cfg = ROOT / ref.config if not os.path.isabs(ref.config) else Path(ref.config)
    scene = load_scene(cfg)
    wl = scene.wavelengths
    if wl.size != ref.wavelengths.size or not np.allclose(wl, ref.wavelengths):
        raise InputError("the reference's wavelengths differ from its config's", path=cfg,
                         field="spectral")
    return ref, cfg, scene


#: sub-pixels per side of each pixel of our frames (the references' pixels are area means)
SAMPLES = 2


def check_samples(samples: Any, *, field: str = "samples") -> int:
    """``samples`` as an int, or :class:`~spectral_fit.InputError` naming ``field`` unless it
    is an integer from 1 to 4 (sub-pixels per side of each of our pixels)."""
    from .._runtime.errors import InputError

    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or not (
            1 <= int(samples) <= 4):
        raise InputError(f"must be an integer from 1 to 4, got {samples!r}", field=field)
    return int(samples)


def pixel_means(image: Any, samples: int) -> np.ndarray:
    """The area mean of each pixel (H, W, C) of an image rendered at ``samples`` × its size in
    each direction (H·samples, W·samples, C): the box pixel filter of the reference."""
    img = np.asarray(image, np.float64)
    h, w = img.shape[0] // samples, img.shape[1] // samples
    if img.shape[:2] != (h * samples, w * samples):
        raise ValueError(f"image {img.shape[:2]} is not {samples} × a frame's size")
    return img.reshape(h, samples, w, samples, *img.shape[2:]).mean(axis=(1, 3))


def delta_e_patches(xyz: np.ndarray, xyz_ref: np.ndarray, white: np.ndarray) -> np.ndarray:
    """ΔE00 (P,) between patch colours (P, 3) and reference colours (P, 3) (absolute XYZ),
    CIELAB against ``white`` (3,)."""
    from ..color import delta_e00, xyz_to_lab

    return np.asarray(delta_e00(xyz_to_lab(xyz, white), xyz_to_lab(xyz_ref, white)))


def _stats(de: np.ndarray) -> dict[str, float]:
    if de.size == 0:
        return {"n": 0}
    return {"n": int(de.size), "median": float(np.median(de)),
            "p90": float(np.percentile(de, 90)), "max": float(de.max()),
            "mean": float(de.mean())}


#: picture formats of the ΔE00 figure (by the file's extension)
FIGURE_FORMATS = (".png", ".pdf", ".svg")


def validate(
    reference: str | os.PathLike[str] = "benchmark",
    *,
    modes: tuple[str, ...] = ("none", "paper", "gather"),
    basis_k: int | None = 8,
    figure: str | os.PathLike[str] | None = None,
    samples: int = SAMPLES,
) -> dict[str, Any]:
    """ΔE00 of our frames vs a committed reference, per mode and region (see module doc);
    each pixel of ours the mean of ``samples``² sub-pixels (the reference's pixels are area
    means; 1: the pixel centres; the basis-vs-bands comparison, ours against ours, at 1).

    Returns a JSON-able dict: ``{"reference", "config", "white_xyz", "patches",
    "modes": {mode: {"interreflection": stats, "direct": stats, "all": stats, "available"}},
    "none_vs_single_bounce": {...}, "basis_k8_vs_bands": {...}, "targets", "checks",
    "delta_e": {mode: (P,) per patch}}``;
    ``figure`` writes a false-colour ΔE00 picture (one panel per mode; PNG, PDF or SVG by
    its extension, checked before anything is rendered).
    """
    import warnings

    import jax

    from .._runtime.fileio import check_suffix
    from ..color import radiance_to_xyz, xyz_weights
    from ..rendering import prepare, render_frame

    # the picture is written last: its name is checked before any frame is rendered
    check_suffix(figure, FIGURE_FORMATS, "figure", "the ΔE00 figure is a picture")
    samples = check_samples(samples)
    ref, cfg, scene = reference_scene(reference)
    wl = scene.wavelengths
    size = tuple(ref.metadata.get("frame", (scene.width, scene.height)))
    fine = (size[0] * samples, size[1] * samples)
    xyz_ref = ref.xyz()
    xyz_ref_direct = ref.xyz(direct=True)
    ir = ref.interreflection
    out: dict[str, Any] = {"reference": ref.name, "config": str(ref.config),
                           "samples": samples,
                           "patches": {"all": ref.num_patches, "interreflection": int(ir.sum()),
                                       "direct": int((~ir).sum())},
                           "modes": {}, "targets": TARGETS}
    white = None
    frames: dict[str, np.ndarray] = {}
    de_by_mode: dict[str, np.ndarray] = {}
    for mode in modes:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            prep = prepare(scene, size=fine, mode=mode)
            frame = jax.block_until_ready(render_frame(prep, spectral=True))
        unavailable = any("not available" in str(w.message) for w in caught)
        if white is None:
            from ..lighting import rotation_y  # noqa: F401  (white from the same env)
            from ..rendering import load_environment

            env = load_environment(scene, wl)
            white = scene_white_xyz(env @ xyz_weights(wl), scene.environment.rotation_y_deg,
                                    np.asarray(prep.camera.view)[2, :3])
            out["white_xyz"] = white.tolist()
        spec = pixel_means(frame.spectral, samples)
        xyz = radiance_to_xyz(ref.patch_means(spec), wl)
        de = delta_e_patches(xyz, xyz_ref, white)
        de_by_mode[mode] = de
        frames[mode] = pixel_means(frame.rgb, samples)
        out["modes"][mode] = {"available": not unavailable, "all": _stats(de),
                              "direct": _stats(de[~ir]), "interreflection": _stats(de[ir])}
        if mode == "none":
            de1 = delta_e_patches(xyz, xyz_ref_direct, white)
            out["none_vs_single_bounce"] = {"all": _stats(de1), "direct": _stats(de1[~ir]),
                                            "interreflection": _stats(de1[ir])}
    if basis_k:
        mode = modes[-1]
        prep_b = prepare(scene, size=size, mode=mode, spectral_mode="basis", k=basis_k)
        fb = render_frame(prep_b, spectral=True)
        xyz_b = radiance_to_xyz(ref.patch_means(np.asarray(fb.spectral, np.float64)), wl)
        prep_f = prepare(scene, size=size, mode=mode)
        ff = render_frame(prep_f, spectral=True)
        xyz_f = radiance_to_xyz(ref.patch_means(np.asarray(ff.spectral, np.float64)), wl)
        out[f"basis_k{basis_k}_vs_bands"] = {"mode": mode,
                                             **_stats(delta_e_patches(xyz_b, xyz_f, white))}
    out["checks"] = _checks(out, basis_k)
    out["delta_e"] = {m: [round(float(d), 4) for d in de] for m, de in de_by_mode.items()}
    if figure is not None:
        delta_e_figure(figure, ref, frames, de_by_mode)
        out["figure"] = str(figure)
    return out


def _checks(out: dict[str, Any], basis_k: int | None) -> dict[str, bool]:
    checks = {}
    t = TARGETS
    for mode, r in out["modes"].items():
        d = r["direct"]
        if mode != "none" and d.get("n"):
            checks[f"{mode}_direct"] = (d["median"] <= t["direct"]["median"]
                                        and d["p90"] <= t["direct"]["p90"])
    g = out["modes"].get("gather", {}).get("interreflection")
    if g and g.get("n"):
        checks["gather_interreflection"] = (
            g["median"] <= t["interreflection_gather"]["median"]
            and g["p90"] <= t["interreflection_gather"]["p90"])
    b = out.get(f"basis_k{basis_k}_vs_bands")
    if b:
        checks["basis_vs_bands"] = b["max"] <= t["basis_vs_bands_max"]
    return checks


def delta_e_figure(path: str | os.PathLike[str], ref: Any, frames: dict[str, np.ndarray],
                   de_by_mode: dict[str, np.ndarray], *, vmax: float = 3.0) -> None:
    """False-colour ΔE00 picture: per mode, the crop around the objects in grey with each
    reference patch filled by its ΔE00 (0 … ``vmax``, colour bar), interreflection patches
    outlined in white."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    from .._runtime.fileio import atomic_path

    x0, y0, cw, ch = ref.metadata.get("crop", (0, 0, frames[next(iter(frames))].shape[1],
                                                frames[next(iter(frames))].shape[0]))
    pad = 6
    xa, ya = max(0, x0 - pad), max(0, y0 - pad)
    xb, yb = x0 + cw + pad, y0 + ch + pad
    n = len(frames)
    fig, axes = plt.subplots(n, 2, figsize=(11, 2.9 * n), squeeze=False)
    cmap = plt.get_cmap("inferno")
    for row, (mode, rgb) in enumerate(frames.items()):
        crop = rgb[ya:yb, xa:xb]
        axes[row, 0].imshow(crop, extent=(xa, xa + crop.shape[1], ya + crop.shape[0], ya))
        axes[row, 0].set_title(f"{mode}: our frame")
        grey = crop.mean(axis=-1)
        ax = axes[row, 1]
        ax.imshow(grey, cmap="gray", vmin=0, vmax=1,
                  extent=(xa, xa + crop.shape[1], ya + crop.shape[0], ya))
        de = de_by_mode[mode]
        for (bx0, by0, bx1, by1), d, lab in zip(ref.boxes, de, ref.labels, strict=True):
            ax.add_patch(Rectangle((bx0, by0), bx1 - bx0, by1 - by0,
                                   facecolor=cmap(min(d / vmax, 1.0)),
                                   edgecolor="white" if lab == "interreflection" else "none",
                                   linewidth=0.8))
        ax.set_title(f"{mode}: ΔE00 per 5×5 patch (median {np.median(de):.2f}, "
                     f"max {de.max():.2f}; white outline = interreflection)", fontsize=9)
        sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, vmax))
        fig.colorbar(sm, ax=ax, fraction=0.03, label="ΔE00")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
