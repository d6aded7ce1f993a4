"""Noiseless readings of spots simulated with the fit's own forward model (for tests and
for sessions made before an independent reference exists); readings (B, L) in
W·sr⁻¹·m⁻²·nm⁻¹ on the scene's wavelengths. Raw camera photographs rendered by the frame
renderer (a second implementation of the model) with a camera's sensitivities, mosaic and
noise.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..io import PARAMETERS, Scene, Session
from ._model import _predict_jit
from ._options import FitOptions
from ._prepare import prepare_fit

__all__ = ["simulate_readings", "simulate_photograph"]


def simulate_readings(scene: Scene, spots: Sequence[dict[str, Any]], *,
                      params: dict[str, dict[str, float]] | None = None,
                      calibration: Any = None, reflectance: dict[str, Any] | None = None,
                      options: FitOptions | None = None, env: Any = None) -> np.ndarray:
    """Noiseless readings (B, L) of spots under this module's forward model (for tests and for
    sessions made before an independent reference exists).

    Args:
        spots: dicts with ``object``, ``aim``, ``position`` and optional ``field_angle_deg``,
            ``kind``.
        params: {object: {parameter: value}} overriding the scene config's materials.
        calibration: (L,) factor on the environment (the "true" room vs the map), default 1.
        reflectance: {object: (L,)} Lambert S(λ) overriding the config's (SCE).
    """
    from pathlib import Path

    from ..io import NoiseModel, Reading

    opts = options or FitOptions()
    wl = np.asarray(scene.wavelengths, np.float64)
    reads = tuple(
        Reading(id=f"s{i}", object=s["object"], kind=s.get("kind", "object"), files=(),
                repeats=np.ones((1, wl.size)), position=np.asarray(s["position"], np.float64),
                aim=np.asarray(s["aim"], np.float64),
                field_angle_deg=float(s.get("field_angle_deg", 1.0)), distance_m=None,
                line=None, index=i)
        for i, s in enumerate(spots))
    from ..io import ObjectMeasurement

    objs = {k: ObjectMeasurement(name=k, reflectance=np.asarray(v, np.float64), geometry="SCE",
                                 free=(), start={}) for k, v in (reflectance or {}).items()}
    sess = Session(path=Path("<simulated>"), scene_path=None, scene=scene, wavelengths=wl,
                   units="W.sr^-1.m^-2.nm^-1", instrument="simulated", calibration="none",
                   bandwidth_nm=0.0,
                   reference=None, white=None, dark=None,
                   noise=NoiseModel(1.0, 0.0, "default"), objects=objs, readings=reads)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prep = prepare_fit(scene, sess, options=opts, env=env)
    pr = prep.problem
    vals = np.array(pr.values, np.float64)
    for o, name in enumerate(prep.objects):
        for k, p in enumerate(PARAMETERS):
            if params and name in params and p in params[name]:
                vals[o, k] = params[name][p]
    if calibration is not None:
        pr = eqx.tree_at(lambda q: q.instrument.calibration, pr,
                         jnp.asarray(np.broadcast_to(calibration, wl.shape), pr.values.dtype))
    return np.asarray(_predict_jit(pr, jnp.asarray(vals, pr.values.dtype),
                                   jnp.ones((), pr.values.dtype)), np.float64)


def simulate_photograph(scene: Scene, *, position: Any, aim: Any, up: Any = (0.0, 1.0, 0.0),
                        fov_y_deg: float = 40.0, size: tuple[int, int] = (720, 480),
                        sensitivities: Any, exposure_s: float,
                        params: dict[str, dict[str, float]] | None = None,
                        calibration: Any = None, mosaic: str = "RGGB",
                        black_level: float = 64.0, white_level: float = 4095.0,
                        read_noise: float = 2.0, gain: float = 0.0, relative_noise: float = 0.0,
                        seed: int = 0, quality: str = "render",
                        render_options: dict[str, Any] | None = None) -> dict[str, np.ndarray]:
    """A raw photograph of ``scene`` rendered by the frame renderer (not the fit's model):
    spectral radiance (H, W, L) at the camera pose, counts t Σ_λ s_c L Δλ (+ black), a Bayer
    mosaic (or every channel with ``mosaic="none"``), Gaussian noise of σ² = read² + gain ·
    signal + (relative · signal)², rounded to integer counts and clipped at the white level.

    Args:
        position, aim, up: the camera's pose (world metres); ``fov_y_deg`` its vertical field
            of view; ``size`` (W, H) pixels.
        sensitivities: (C, L) counts · s⁻¹ per (W·sr⁻¹·m⁻²·nm⁻¹ · nm) on the scene's grid.
        params: {object: {parameter: value}} overriding the config's materials.
        calibration: (L,) factor on the environment (the "true" room vs the map), default 1.
        quality, render_options: the frame renderer's gloss quality and further keyword
            arguments of :func:`spectral_fit.rendering.prepare` (e.g. ``diffuse="exact"``).

    Returns:
        dict with ``raw`` (H, W) or (H, W, C) counts, ``clean`` (same, noise-free, unclipped)
        and ``object_id`` (H, W) (−1: background).
    """
    import dataclasses

    from ..color import integration_weights
    from ..rendering import prepare, render_frame

    W, H = int(size[0]), int(size[1])
    objs = []
    for o in scene.objects:
        p = (params or {}).get(o.name, {})
        objs.append(dataclasses.replace(o, material=dataclasses.replace(o.material, **p)))
    cam = dataclasses.replace(scene.camera, position=tuple(map(float, position)),
                              look_at=tuple(map(float, aim)), up=tuple(map(float, up)),
                              fov_y_deg=float(fov_y_deg), intrinsics=None, distortion=None)
    sc = dataclasses.replace(scene, objects=tuple(objs), camera=cam, width=W, height=H)
    prep = prepare(sc, quality=quality, **(render_options or {}))
    fr = render_frame(prep, spectral=True)
    L_img = np.asarray(fr.spectral, np.float64)  # (H, W, L)
    wl = np.asarray(scene.wavelengths, np.float64)
    if calibration is not None:
        L_img = L_img * np.broadcast_to(np.asarray(calibration, np.float64), wl.shape)
    dl = integration_weights(wl)
    s = np.asarray(sensitivities, np.float64)
    clean = exposure_s * np.einsum("hwl,cl->hwc", L_img, s * dl[None, :])
    if mosaic != "none":
        tile = np.array(["RGB".index(c) for c in mosaic]).reshape(2, 2)
        chan = np.tile(tile, (H // 2 + 1, W // 2 + 1))[:H, :W]
        clean = np.take_along_axis(clean, chan[..., None], axis=-1)[..., 0]
    rng = np.random.default_rng(seed)
    sig = np.sqrt(read_noise ** 2 + gain * np.maximum(clean, 0.0)
                  + (relative_noise * clean) ** 2)
    raw = np.clip(np.round(black_level + clean + sig * rng.standard_normal(clean.shape)),
                  0.0, white_level)
    return {"raw": raw, "clean": clean + black_level,
            "object_id": np.asarray(fr.object_id)}
