"""Do the fit's intervals cover the truth? A coverage study on simulated sessions.

Each simulated session keeps a measured session's spots (their fields are rasterised once:
:func:`~spectral_fit.fitting.prepare_fit`) and draws
- true parameters, uniformly over each one's range (the planner's:
  :func:`~spectral_fit.fitting.default_range` around the start, inside the session's
  bounds and ± 2σ of its priors);
- readings from this package's forward model at those parameters, times a **model error**
  the fit does not know: per reading a smooth spectral factor 1 + a + c·(λ − λ̄)/(λ_max −
  λ̄), a and c normal with standard deviations ``level`` and ``tilt`` (what a renderer's
  error looks like at one spot: mostly a level, correlated over the bands), then
- the instrument's noise: ``noise`` × the reading, independent per band.

It is then fitted as a user would (:func:`~spectral_fit.fitting.fit`, with the session's
``[model_error]`` or the one given), and each parameter's interval p̂ ± z·σ̂ (z = 1.96: 95 %)
is checked against the truth. Coverage per parameter and pooled, with the Clopper–Pearson
95 % confidence interval of a binomial proportion; interval widths beside the recovery
tolerances (:data:`~spectral_fit.fitting.TOLERANCES`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from ..io import PARAMETERS, Scene, Session

__all__ = ["CoverageStudy", "coverage_study", "clopper_pearson"]

#: z of a two-sided 95 % normal interval
Z95 = 1.959963984540054


@dataclasses.dataclass(frozen=True)
class CoverageStudy:
    """Result of :func:`coverage_study`.

    Attributes:
        labels: the unknowns ``object.parameter`` (F).
        truth, estimate, stderr: (K, F) per simulated session.
        status: (K,) the fits' status.
        model_error: (K,) the model error per kind the fit used (stated or estimated).
        options: the study's settings.
    """

    labels: list[str]
    truth: np.ndarray
    estimate: np.ndarray
    stderr: np.ndarray
    status: list[str]
    model_error: list[dict[str, float]]
    options: dict[str, Any]

    def covered(self, z: float = Z95) -> np.ndarray:
        """(K, F) bool: the truth inside p̂ ± z σ̂."""
        return np.abs(self.estimate - self.truth) <= z * self.stderr

    def table(self, tolerances: Mapping[str, tuple[str, float]] | None = None
              ) -> dict[str, Any]:
        """Coverage of the 95 % intervals per parameter kind and pooled: hits, n, the
        proportion and its Clopper–Pearson 95 % interval; the median full width 2 z σ̂ and,
        with ``tolerances`` ({parameter: ("relative" | "absolute", value)}, e.g.
        :data:`~spectral_fit.fitting.TOLERANCES`), that width in tolerances."""
        ok = self.covered()
        good = np.array([s != "failed" for s in self.status])
        kinds = [label.rsplit(".", 1)[1] for label in self.labels]
        rows: dict[str, Any] = {}
        for kind in dict.fromkeys(kinds):
            cols = [j for j, k in enumerate(kinds) if k == kind]
            rows[kind] = self._row(ok[good][:, cols], self.truth[good][:, cols],
                                   self.stderr[good][:, cols],
                                   None if tolerances is None else tolerances.get(kind))
        rows["pooled"] = self._row(ok[good], self.truth[good], self.stderr[good], None)
        return rows

    @staticmethod
    def _row(ok: np.ndarray, truth: np.ndarray, se: np.ndarray,
             tol: tuple[str, float] | None) -> dict[str, Any]:
        k, n = int(ok.sum()), int(ok.size)
        lo, hi = clopper_pearson(k, n)
        width = 2.0 * Z95 * se
        row = {"covered": k, "n": n, "coverage": k / n if n else math.nan,
               "ci95": [lo, hi], "median_width": float(np.median(width)) if n else math.nan}
        if tol is not None and n:
            kind, value = tol
            scale = value * np.abs(truth) if kind == "relative" else value
            row["median_width_in_tolerances"] = float(np.median(width / scale))
        return row


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """The exact (Clopper–Pearson) ``level`` confidence interval of a binomial proportion
    with ``k`` successes in ``n`` trials (from the beta distribution's quantiles)."""
    from scipy.stats import beta

    if n == 0:
        return math.nan, math.nan
    a = 1.0 - level
    lo = 0.0 if k == 0 else float(beta.ppf(a / 2, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a / 2, k + 1, n - k))
    return lo, hi


def coverage_study(scene: Scene, session: Session, *, sessions: int = 200, seed: int = 0,
                   noise: float = 0.01, level: float = 0.01, tilt: float = 0.005,
                   model_error: Mapping[str, float | str] | None = None,
                   truths: np.ndarray | None = None, options: Any = None,
                   progress: Callable[[str], None] | None = None) -> CoverageStudy:
    """Simulate ``sessions`` sessions on ``session``'s spots and fit each (see the module
    docstring).

    Args:
        scene, session: the scene and a session whose spots (positions, aims, fields,
            kinds, white standard) the simulated sessions share; its readings' values are
            replaced.
        sessions: number of simulated sessions K.
        seed: random seed of the truths, the model errors and the noise.
        noise: the instrument's noise, a fraction of each reading per band (1σ).
        level, tilt: the injected model error's standard deviations (fractions).
        model_error: the session's ``[model_error]`` for the fits (default: the session's
            own; ``{"object": "auto", ...}`` estimates it per kind).
        truths: (K, O, P) true parameters instead of drawn ones (P = len(PARAMETERS)).
        options: :class:`~spectral_fit.fitting.FitOptions` of the fits (default: one start,
            no hold-out, no aiming sensitivity: the intervals are what is studied).
        progress: called with a line per simulated session.

    Returns:
        :class:`CoverageStudy`.
    """
    import equinox as eqx
    import jax.numpy as jnp

    from ._fit import fit
    from ._model import _predict_jit
    from ._options import FitOptions
    from ._plan import _ranges
    from ._prepare import prepare_fit

    opts = options or FitOptions(starts=1, holdout=False, aim_step_m=0.0)
    rng = np.random.default_rng(seed)
    sess = session if model_error is None else session.replace(model_error=dict(model_error))
    prepared = prepare_fit(scene, sess, options=opts)
    problem = prepared.problem
    names = list(prepared.objects)
    labels = problem.names(names)
    free = list(problem.free)
    base = np.asarray(problem.values, np.float64)
    if truths is None:  # the planner's ranges around the start (no fit to narrow them)
        lower, upper = _ranges(sess, names, tuple(free),
                               np.array([base[o, k] for o, k in free]), None, False)
        truths = np.repeat(base[None], sessions, axis=0)
        for j, (o, k) in enumerate(free):
            truths[:, o, k] = rng.uniform(lower[j], upper[j], sessions)
    truths = np.asarray(truths, np.float64)
    wl = np.asarray(sess.wavelengths, np.float64)
    mid = 0.5 * (wl[0] + wl[-1])
    x = (wl - mid) / max(wl[-1] - mid, 1e-9)
    dt = problem.values.dtype
    est, se, true, status, merr = [], [], [], [], []
    for i in range(truths.shape[0]):
        clean = np.asarray(_predict_jit(problem, jnp.asarray(truths[i], dt), jnp.asarray(1.0, dt)),
                           np.float64)
        a = rng.normal(0.0, level, (clean.shape[0], 1))
        c = rng.normal(0.0, tilt, (clean.shape[0], 1))
        meas = clean * (1.0 + a + c * x[None, :])
        sigma = noise * np.abs(meas) + 1e-12
        meas = meas + sigma * rng.standard_normal(meas.shape)
        pr = eqx.tree_at(lambda q: (q.readings.measured, q.readings.sigma), problem,
                         (jnp.asarray(meas, dt), jnp.asarray(sigma, dt)))
        res = fit(scene, sess, options=opts, prepared=dataclasses.replace(prepared, problem=pr))
        est.append([res.params[names[o]][PARAMETERS[k]] for o, k in free])
        se.append([res.stderr[names[o]][PARAMETERS[k]] for o, k in free])
        true.append([truths[i, o, k] for o, k in free])
        status.append(res.status)
        merr.append(dict(res.model_error))
        if progress is not None:
            hits = np.abs(np.array(est[-1]) - true[-1]) <= Z95 * np.array(se[-1])
            progress(f"session {i + 1}/{truths.shape[0]}: {res.status}, "
                     f"{int(hits.sum())}/{len(hits)} intervals cover the truth")
    return CoverageStudy(labels=labels[:len(free)],
                         truth=np.array(true), estimate=np.array(est), stderr=np.array(se),
                         status=status, model_error=merr,
                         options={"sessions": int(truths.shape[0]), "seed": seed,
                                  "noise": noise, "level": level, "tilt": tilt,
                                  "model_error": dict(sess.model_error),
                                  "level_error": dict(sess.level_error),
                                  "tilt_error": dict(sess.tilt_error)})
