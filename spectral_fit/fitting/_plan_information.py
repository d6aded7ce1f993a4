"""The information of readings for a measurement plan: the candidates prepared as the fit
prepares readings (:func:`prepare_candidates`), their Fisher information at each parameter
draw (:func:`candidate_information`), and the information of an existing session's readings
and priors.

Shapes: N candidates, D draws, F unknowns, O objects, L bands; radiance in W·sr⁻¹·m⁻²·nm⁻¹,
information in the unknowns scaled by their tolerances.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..io import Scene, Session
from ._options import FitOptions
from ._plan_design import reading_information, reading_sensitivity, tolerances

__all__ = ["prepare_candidates", "candidate_information", "session_information"]


def _session_for(scene: Scene, base: Session | None, spots: list[dict[str, Any]]) -> Session:
    """A session whose readings are ``spots`` (placeholder spectra), with the calibration,
    white standard and objects of ``base`` (or none)."""
    from ..io import NoiseModel, Reading

    wl = np.asarray(scene.wavelengths, np.float64)
    reads = tuple(
        Reading(id=f"candidate_{i}", object=s["object"], kind="object", files=(),
                repeats=np.ones((1, wl.size)), position=np.asarray(s["position"], np.float64),
                aim=np.asarray(s["aim"], np.float64), field_angle_deg=float(s["field_angle_deg"]),
                distance_m=None, line=None, index=i) for i, s in enumerate(spots))
    if base is not None:
        return base.replace(readings=reads)
    return Session(path=Path("<plan>"), scene_path=None, scene=scene, wavelengths=wl,
                   units="W.sr^-1.m^-2.nm^-1", instrument="planned", calibration="none",
                   bandwidth_nm=0.0, reference=None, white=None, dark=None,
                   noise=NoiseModel(1.0, 0.0, "default"), objects={}, readings=reads)


def prepare_candidates(scene: Scene, candidates: list[dict[str, Any]], *,
                       session: Session | None = None, spot_resolution: int = 4,
                       env: Any = None, geometries: Any = None, chunk: int = 256,
                       progress: Callable[[str], None] | None = None) -> list[Any]:
    """The candidates prepared as the fit prepares readings (fields ray-cast at
    ``spot_resolution``, radiance cache built; without the interreflection term), in chunks of
    ``chunk`` (the last one padded with copies of its last candidate, so that one compiled
    program serves every chunk). Returns one :class:`PreparedFit` per chunk."""
    from ._prepare import prepare_fit, scene_environment, scene_geometry

    say = progress or (lambda _m: None)
    if env is None:
        env = scene_environment(scene, compress_tol=FitOptions().compress_tol)
    if geometries is None:
        geometries = scene_geometry(scene)
    opts = FitOptions(spot_resolution=spot_resolution, interreflection="none")
    N = len(candidates)
    size = min(chunk, N)
    out = []
    for start in range(0, N, size):
        part = candidates[start:start + size]
        part = part + [part[-1]] * (size - len(part))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out.append(prepare_fit(scene, _session_for(scene, session, part), options=opts,
                                   env=env, geometries=geometries, check=False))
        say(f"prepared candidates {min(start + size, N)}/{N}")
    return out


def candidate_information(scene: Scene, candidates: list[dict[str, Any]], values: np.ndarray,
                          *, free: tuple[tuple[int, int], ...], fit_scale: bool = False,
                          scale: np.ndarray | None = None, noise: float = 0.01,
                          sigma_aim_m: float = 1e-3, level: float = 0.0, tilt: float = 0.0,
                          spot_resolution: int = 4,
                          session: Session | None = None, env: Any = None,
                          geometries: Any = None, chunk: int = 256,
                          prepared: list[Any] | None = None,
                          progress: Callable[[str], None] | None = None
                          ) -> dict[str, np.ndarray]:
    """Fisher information of each candidate reading at each parameter draw, through the fit's
    forward model (:func:`reading_sensitivity`, :func:`reading_information`).

    Args:
        candidates: dicts with ``object``, ``position``, ``aim``, ``field_angle_deg``,
            ``distance_m``.
        values: (D, O, 6) physical parameters of each draw; ``scale`` (D,) the global scale.
        noise: relative noise of a reading (σ = noise × max(L, 1e-3 × its peak band)).
        sigma_aim_m: aiming error (m, 1σ per direction across the axis).
        level: the model's error common to a reading's bands (a fraction of it); tilt: its
            tilt over the bands (a fraction, from −1 at the first band to +1 at the last).
        prepared: :func:`prepare_candidates` of these candidates (default: prepared here).

    Returns:
        ``information`` (N, D, F, F) in tolerance units, ``coverage`` (N,) fraction of the
        field on the object, ``mean`` (N, D, L) radiance, ``jacobian`` (N, D, L, F),
        ``aim_gradient`` (N, D, L, 2) (per metre).
    """
    say = progress or (lambda _m: None)
    if prepared is None:
        prepared = prepare_candidates(scene, candidates, session=session,
                                      spot_resolution=spot_resolution, env=env,
                                      geometries=geometries, chunk=chunk, progress=say)
    N = len(candidates)
    size = len(prepared[0].session.readings)
    tol = tolerances(values, free, scale=scale if fit_scale else None)
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("information", "coverage", "mean",
                                                          "jacobian", "aim_gradient")}
    for c, prep in enumerate(prepared):
        start = c * size
        n = min(size, N - start)
        reads = prep.session.readings
        m, J, g = reading_sensitivity(
            prep.problem, values, free=free, fit_scale=fit_scale, scale=scale,
            aim_distances=np.array([np.linalg.norm(r.aim - r.position) for r in reads]),
            field_angles_deg=np.array([r.field_angle_deg for r in reads]),
            spot_resolution=spot_resolution)
        peak = m.max(axis=-1, keepdims=True)
        sigma = noise * np.maximum(m, 1e-3 * np.maximum(peak, 1e-30))
        info = reading_information(J, sigma, g, tol, sigma_aim_m=sigma_aim_m, level=level,
                                   tilt=tilt, mean=m)
        parts["information"].append(np.swapaxes(info, 0, 1)[:n])
        parts["coverage"].append(prep.coverage[:n])
        parts["mean"].append(np.swapaxes(m, 0, 1)[:n])
        parts["jacobian"].append(np.swapaxes(J, 0, 1)[:n])
        parts["aim_gradient"].append(np.swapaxes(g, 0, 1)[:n])
        say(f"sensitivity of candidates {start + n}/{N}")
    return {k: np.concatenate(v) for k, v in parts.items()}


def session_information(prep: Any, values: np.ndarray, *, scale: np.ndarray,
                        unknowns: tuple[tuple[int, int], ...], fit_scale: bool,
                        tol: np.ndarray, sigma_aim_m: float, resolution: int,
                        level: float = 0.0, tilt: float = 0.0) -> np.ndarray:
    """(D, F, F) information of the session's readings (their standard errors, the same
    aiming error, the model's level and tilt errors) and of its priors, in tolerance units.

    Where the session states a level (``[model_error.level]``), its readings take the level
    stated for their kind (0 for a kind it leaves out), as the fit weights them; where it
    states none, every reading takes ``level``. The same for the tilt."""
    pr = prep.problem
    s = prep.session
    level, tilt = (np.array([table.get(r.kind, 0.0) for r in s.readings], np.float64)
                   if any(v > 0 for v in table.values()) else default
                   for table, default in ((s.level_error, level), (s.tilt_error, tilt)))
    dist = np.array([np.linalg.norm(r.aim - r.position) for r in s.readings])
    fields = np.array([r.field_angle_deg for r in s.readings])
    m, J, g = reading_sensitivity(pr, values, free=unknowns, fit_scale=fit_scale, scale=scale,
                                  aim_distances=dist, field_angles_deg=fields,
                                  spot_resolution=resolution)
    info = reading_information(J, np.asarray(pr.readings.sigma, np.float64), g, tol,
                               sigma_aim_m=sigma_aim_m, level=level, tilt=tilt,
                               mean=m).sum(axis=1)
    for j, _, sd in pr.prior:
        jj = unknowns.index(pr.free[j])
        info[:, jj, jj] += (tol[:, jj] / sd) ** 2
    return info
