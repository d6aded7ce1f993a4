"""The scene's environment as a frame uses it: the map read from the config's file as spectral
radiance (Hm, Wm, L) in W·sr⁻¹·m⁻²·nm⁻¹ on the scene's bands (:func:`load_environment`), and the
paper's irradiance map I_d over normal directions, the diffuse term's look-up table
(:func:`irradiance_table`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .._runtime.errors import InputError

if TYPE_CHECKING:  # for annotations (imported where they are used)
    from ..io import Scene

__all__ = [
    "ground_surfaces",
    "load_environment",
]


def load_environment(scene: Scene, wavelengths: np.ndarray) -> np.ndarray:
    """The scene's environment map as spectral radiance (Hm, Wm, L) on ``wavelengths`` (nm),
    times the config's ``scale``: a spectral OpenEXR is resampled (linear), an RGB one is lifted
    with the config's upsampling method."""
    from ..color import resample
    from ..io import read_spectral_exr
    from ..lighting import read_rgb_environment

    spec = scene.environment
    try:
        wl_in, img = read_spectral_exr(spec.file)
    except InputError as exc:
        try:
            _, img = read_rgb_environment(spec.file, wavelengths, method=spec.upsampling)
        except InputError:
            raise exc from None
        return np.asarray(img, np.float64) * spec.scale
    if not (wl_in.size == wavelengths.size and np.allclose(wl_in, wavelengths)):
        img = resample(wl_in, img, wavelengths, path=spec.file, field="environment.file")
    return np.asarray(img, np.float64) * spec.scale


def irradiance_table(texels: np.ndarray, shape: tuple[int, int] = (32, 64),
                     source_texels: int = 64 * 128) -> np.ndarray:
    """The paper's irradiance map I_d: irradiance E(N) = Σ L(ω) max(0, N·ω) Δω (C channels,
    bands or basis coefficients; exact texel sum with exact texel solid angles) at the texel
    centres of an (Hl, Wl) equirectangular grid of normals in the MAP frame, then the two
    pole values. Returns (Hl·Wl + 2, C). The map is first averaged down (solid-angle weighted)
    to at most ``source_texels`` texels, which keeps every source's flux."""
    from ..lighting import texel_directions, texel_solid_angles, uv_to_direction

    img = np.asarray(texels, np.float64)
    h, w, c = img.shape
    f = 1
    while (h // (2 * f)) * (w // (2 * f)) >= source_texels and h % (2 * f) == 0 \
            and w % (2 * f) == 0:
        f *= 2
    sa = texel_solid_angles(h, w)
    if f > 1:
        wsum = sa.reshape(h // f, f, w // f, f).sum(axis=(1, 3))
        img = (img * sa[..., None]).reshape(h // f, f, w // f, f, c).sum(axis=(1, 3))
        img = img / wsum[..., None]
        h, w = h // f, w // f
        sa = texel_solid_angles(h, w)
    src = texel_directions(h, w).reshape(-1, 3)
    rad = img.reshape(-1, c) * sa.reshape(-1, 1)
    hl, wl = shape
    normals = np.concatenate([texel_directions(hl, wl).reshape(-1, 3),
                              uv_to_direction(0.0, 0.0)[None], uv_to_direction(0.0, 1.0)[None]])
    return np.maximum(normals @ src.T, 0.0) @ rad


def ground_surfaces(scene: Scene, texels: np.ndarray) -> np.ndarray:
    """The environment (Hm, Wm, L) as the objects see it above the scene's ``[[surfaces]]``
    planes: every direction below a plane's horizon shows that plane's uniform radiance
    ρ E_up/π (:func:`~spectral_fit.lighting.ground_plane`; the planes in config order). A
    scene without surfaces returns ``texels`` unchanged."""
    from ..lighting import ground_plane, rotation_y

    img = np.asarray(texels)
    rot = rotation_y(scene.environment.rotation_y_deg)  # world from map
    for s in scene.surfaces:
        img, _ = ground_plane(img, rot.T @ np.asarray(s.normal, np.float64), s.reflectance)
    return img
