"""Noiseless readings of spots simulated with the fit's own forward model (for tests and
for sessions made before an independent reference exists); readings (B, L) in
W·sr⁻¹·m⁻²·nm⁻¹ on the scene's wavelengths.
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

__all__ = ["simulate_readings"]


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
