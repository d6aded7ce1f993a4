"""ΔE00 per region of our frame against a committed reference of any scene (spheres, meshes,
objects on a table), with the targets of each region.

Regions come from the reference alone (its depth-16 and depth-2 renders): object patches whose
interreflection share (Y₁₆ − Y₂)/Y₁₆ is at most 2 % (occluded parts included: the neighbour's
and the object's own occlusion of the sky is in both renders), object patches above 2 %, and,
for a scene with a table, the table patches within 2 bounding radii of an object. Patches are the
reference's (grid layout: 5×5 squares of the frame grid with a one-pixel border of the same
object; sphere layout: squares tiling the exact spheres). ΔE00 between patch means in CIELAB
against the scene white (:func:`~spectral_fit.validation.scene_white_xyz`).

Our frame: the config as it is (its interreflection mode, self-visibility on), spectral output
on the reference's bands; for a table, the surface layer's spectral radiance at the table
pixels (:func:`spectral_fit.rendering.surface_layer`). Each pixel of the reference is the
mean over its area (a box pixel filter); ours is rendered at ``samples`` × the frame's size
in each direction and averaged over each pixel's ``samples``² sub-pixels
(:func:`pixel_means`), so that a feature a few pixels wide (a cup's lip) is compared as the
same area mean and not as one point at the pixel's centre against it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from .._runtime.paths import REPO_ROOT
from ._compare import SAMPLES, check_samples, pixel_means

__all__ = ["SCENE_TARGETS", "IR_THRESHOLD", "scene_regions", "region_report", "validate_scene",
           "validate_reference", "scene_figure"]

#: interreflection share of the luminance that splits the object regions
IR_THRESHOLD = 0.02

#: ΔE00 targets per region (median, 90th percentile, max)
SCENE_TARGETS: dict[str, dict[str, float]] = {
    "objects, interreflection < 2 %": {"median": 0.3, "p90": 0.8, "max": 2.0},
    "objects, interreflection > 2 %": {"median": 0.5, "p90": 1.5, "max": 3.0},
    "table near objects": {"median": 0.5, "p90": 1.5, "max": 3.0},
}


def scene_regions(ref: Any) -> dict[str, np.ndarray]:
    """(P,) bool masks of the reference's patches per region of :data:`SCENE_TARGETS` (a
    region the scene does not have is all False)."""
    obj = np.asarray(ref.object_index) >= 0
    frac = np.asarray(ref.ir_fraction, np.float64)
    high = obj & (frac > IR_THRESHOLD)
    return {"objects, interreflection < 2 %": obj & ~high,
            "objects, interreflection > 2 %": high,
            "table near objects": (~obj) & (np.asarray(ref.labels) == "table")}


def _stats(de: np.ndarray) -> dict[str, Any]:
    if de.size == 0:
        return {"n": 0}
    return {"n": int(de.size), "median": float(np.median(de)),
            "p90": float(np.percentile(de, 90)), "max": float(de.max())}


def region_report(ref: Any, de: np.ndarray) -> dict[str, Any]:
    """Per region: ΔE00 statistics of ``de`` (P,), the targets, pass/fail per statistic, and
    the reference's own noise (median and max of its per-patch ΔE00 standard error)."""
    out: dict[str, Any] = {}
    noise = ref.noise_de if ref.noise_de is not None else np.full(ref.num_patches, np.nan)
    for name, mask in scene_regions(ref).items():
        s = _stats(np.asarray(de)[mask])
        if not s["n"]:
            continue
        t = SCENE_TARGETS[name]
        s["targets"] = dict(t)
        s["pass"] = {k: bool(s[k] <= v) for k, v in t.items()}
        s["ok"] = all(s["pass"].values())
        nz = noise[mask]
        if np.isfinite(nz).any():
            s["reference_noise_de"] = {"median": float(np.nanmedian(nz)),
                                       "max": float(np.nanmax(nz))}
        out[name] = s
    return out


def _our_patches(ref: Any, scene: Any, samples: int = SAMPLES
                 ) -> tuple[np.ndarray, np.ndarray, Any]:
    """Our patch spectra (P, L) over the reference's boxes (each pixel the mean of
    ``samples``² sub-pixels), our display frame (H·samples, W·samples, 3), and the prepared
    scene."""
    import jax

    from ..rendering import prepare, render_frame

    prep = prepare(scene, size=(scene.width * samples, scene.height * samples))
    frame = jax.block_until_ready(render_frame(prep, spectral=True))
    ours = ref.patch_means(pixel_means(frame.spectral, samples))
    table = np.asarray(ref.object_index) < 0
    if table.any():
        from ..rendering import surface_layer

        wl = scene.wavelengths
        layer = jax.block_until_ready(surface_layer(prep, out=np.eye(wl.size, dtype=np.float32)))
        ours[table] = ref.patch_means(pixel_means(layer.radiance, samples))[table]
    return ours, np.asarray(frame.rgb), prep


def validate_scene(reference: str | os.PathLike[str], *,
                   figure: str | os.PathLike[str] | None = None,
                   samples: int = SAMPLES) -> dict[str, Any]:
    """ΔE00 of our frame of the reference's config against the reference's depth-16 patch
    means, per region (:func:`region_report`), per object, and for the table; our pixels
    the means of ``samples``² sub-pixels (1: the pixel centres alone).

    Returns a JSON-able dict ``{"reference", "config", "layout", "mode", "patches",
    "regions": {region: {n, median, p90, max, targets, pass, ok, reference_noise_de}},
    "per_object": {name: stats}, "ok", "figure", "delta_e": (P,) per patch}``; ``figure``
    writes the false-colour ΔE00 picture (:func:`scene_figure`; PNG, PDF or SVG, its name
    checked first).
    """
    from .._runtime.errors import InputError
    from .._runtime.fileio import check_suffix
    from ..color import radiance_to_xyz, xyz_weights
    from ..rendering import load_environment
    from ._compare import FIGURE_FORMATS, delta_e_patches, reference_scene, scene_white_xyz

    check_suffix(figure, FIGURE_FORMATS, "figure", "the ΔE00 figure is a picture")
    ref, cfg, scene = reference_scene(reference)
    wl = scene.wavelengths
    frame_size = tuple(ref.metadata.get("frame", (scene.width, scene.height)))
    if frame_size != (scene.width, scene.height):
        raise InputError(f"the reference's frame {frame_size} differs from its config's",
                         path=cfg, field="frame")
    samples = check_samples(samples)
    ours, _, prep = _our_patches(ref, scene, samples)
    env = load_environment(scene, wl)
    white = scene_white_xyz(np.asarray(env) @ xyz_weights(wl), scene.environment.rotation_y_deg,
                            np.asarray(prep.camera.view)[2, :3])
    de = delta_e_patches(radiance_to_xyz(ours, wl), ref.xyz(), white)
    regions = region_report(ref, de)
    obj = np.asarray(ref.object_index)
    out: dict[str, Any] = {
        "reference": ref.name, "config": str(ref.config),
        "layout": ref.metadata.get("layout", "spheres"),
        "mode": scene.interreflection.mode, "patches": int(ref.num_patches),
        "reference_spp": ref.metadata.get("spp"), "samples": samples,
        "white_xyz": white.tolist(),
        "regions": regions,
        "per_object": {n: _stats(de[obj == i]) for i, n in enumerate(ref.object_names)},
        "ok": all(r["ok"] for r in regions.values()),
    }
    if figure is not None:
        scene_figure(figure, ref, de)
        out["figure"] = str(figure)
    out["delta_e"] = [round(float(d), 4) for d in de]
    return out


def validate_reference(reference: str | os.PathLike[str], *,
                       modes: tuple[str, ...] = ("none", "paper", "gather"),
                       basis_k: int | None = 8,
                       figure: str | os.PathLike[str] | None = None,
                       samples: int = SAMPLES) -> dict[str, Any]:
    """Any committed reference: a grid-layout one through :func:`validate_scene`; a sphere
    one (benchmark, two_spheres) through :func:`~spectral_fit.validation.validate` (its
    figures unchanged) with ``"regions"`` added: :func:`region_report` of the config's
    interreflection mode (``"regions"["mode"]``) when that mode is among ``modes``. Our
    pixels are the means of ``samples``² sub-pixels in both."""
    from ..io import load_scene
    from ._compare import validate
    from .reference import load_reference

    ref = load_reference(reference)
    if ref.metadata.get("layout", "spheres") == "grid":
        return validate_scene(reference, figure=figure, samples=samples)
    res = validate(reference, modes=modes, basis_k=basis_k, figure=figure, samples=samples)
    cfg = REPO_ROOT / ref.config if not os.path.isabs(ref.config) else Path(ref.config)
    mode = load_scene(cfg).interreflection.mode
    if mode in res["delta_e"]:
        res["regions"] = {"mode": mode,
                          **region_report(ref, np.asarray(res["delta_e"][mode]))}
    return res


def scene_figure(path: str | os.PathLike[str], ref: Any, de: np.ndarray, *,
                 vmax: float = 3.0) -> None:
    """False-colour ΔE00 picture: the reference (depth 16, sRGB, 99th-percentile luminance →
    white) with its regions outlined (white: objects < 2 %, cyan: > 2 %, orange: table), and
    each patch filled with its ΔE00 (0 … ``vmax``) over the reference in grey."""
    import matplotlib

    matplotlib.use("Agg")
    import colour
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    from .._runtime.fileio import atomic_path

    xyz = np.asarray(ref.preview_xyz, np.float64)
    scale = max(float(np.percentile(xyz[..., 1], 99)), 1e-30)
    with np.errstate(invalid="ignore"):
        lin = colour.XYZ_to_sRGB(xyz / scale, apply_cctf_encoding=False)
        rgb = np.nan_to_num(colour.cctf_encoding(np.clip(lin, 0, 1)))
    x0, y0, cw, ch = ref.metadata.get("crop", (0, 0, rgb.shape[1], rgb.shape[0]))
    ext = (x0, x0 + cw, y0 + ch, y0)
    masks = scene_regions(ref)
    edge = np.full(ref.num_patches, "white", dtype=object)
    edge[masks["objects, interreflection > 2 %"]] = "cyan"
    edge[masks["table near objects"]] = "orange"
    aspect = ch / max(cw, 1)
    fig, axes = plt.subplots(1, 2, figsize=(12, 6.0 * aspect + 1.0), squeeze=False)
    axes[0, 0].imshow(rgb, extent=ext)
    for (bx0, by0, bx1, by1), e in zip(ref.boxes, edge, strict=True):
        axes[0, 0].add_patch(Rectangle((bx0, by0), bx1 - bx0, by1 - by0, facecolor="none",
                                       edgecolor=e, linewidth=0.3))
    axes[0, 0].set_title(f"{ref.name}: reference, depth 16; patches: objects < 2 % "
                         "white, > 2 % cyan, table orange", fontsize=8)
    ax = axes[0, 1]
    ax.imshow(rgb.mean(axis=-1), cmap="gray", vmin=0, vmax=1.5, extent=ext)
    cmap = plt.get_cmap("inferno")
    for (bx0, by0, bx1, by1), d in zip(ref.boxes, de, strict=True):
        ax.add_patch(Rectangle((bx0, by0), bx1 - bx0, by1 - by0,
                               facecolor=cmap(min(float(d) / vmax, 1.0)), edgecolor="none"))
    for m in masks.values():
        if m.any():
            worst = int(np.flatnonzero(m)[np.argmax(np.asarray(de)[m])])
            bx0, by0, bx1, by1 = ref.boxes[worst]
            ax.add_patch(Rectangle((bx0 - 2, by0 - 2), bx1 - bx0 + 4, by1 - by0 + 4,
                                   facecolor="none", edgecolor=edge[worst], linewidth=1.2))
    ax.set_title(f"ΔE00 per 5×5 patch (median {np.median(de):.2f}, max {np.max(de):.2f}); "
                 "worst of each region boxed", fontsize=8)
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, vmax))
    fig.colorbar(sm, ax=ax, fraction=0.03, label="ΔE00")
    for a in axes.ravel():
        a.set_xlim(ext[0], ext[1])
        a.set_ylim(ext[2], ext[3])
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
