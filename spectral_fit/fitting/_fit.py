"""Fit α, β, χ, μ, n (and γ) of each object to spectroradiometer readings.

Pipeline (geometry and poses are fixed while materials are fitted):

1. :func:`~spectral_fit.fitting.prepare_fit` — outside ``jit``, once per session: the
   readings' measuring fields, their material-independent radiance cache and everything
   else parameter-independent, as a :class:`~spectral_fit.fitting.FitProblem` pytree.
2. :func:`~spectral_fit.fitting.predict` — the forward model, jit-compiled: the field means
   of eq. (5) (+ eq. 6's interreflection) as weighted sums of cached radiances, through the
   instrument's band-pass, times the environment calibration k(λ).
3. :func:`fit` — weighted least squares by Levenberg–Marquardt
   (:class:`~spectral_fit.fitting.CompactLM`, the iteration of
   ``optimistix.LevenbergMarquardt`` in one small compiled loop, or optimistix itself with
   ``solver="optimistix"``), several starts solved one after the other in one program,
   uncertainties from the Jacobian, profile-likelihood intervals (option ``profile``), a
   bootstrap over readings, identifiability warnings, the
   sensitivity of each reading to aiming error, and the hold-out prediction of
   interreflection readings from a fit on object-colour readings (:class:`FitResult`).
   :func:`fit_many` fits K sets of readings of the same spots at once.

Shapes: B readings, L bands, O objects, F unknowns; parameters (O, 6), columns
``PARAMETERS``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from ..io import PARAMETERS, Scene, Session
from ..rendering import compilation_counts
from ._model import _predict_jit
from ._model_error import estimate_model_error, with_model_error
from ._options import FitOptions, _fit_options
from ._params import _SQUARED, LOWER, _dp_dy, _starts, physical_from_y, unknowns, y_start
from ._prepare_cache import aim_problems_cached, prepare_fit_cached
from ._problem import FitProblem, PreparedFit, row_kinds
from ._profile import STEPS, profile_intervals
from ._programs import stored_call
from ._solver import _PROGRESS, _solve_measured, make_solver, solve_batch

__all__ = ["FitResult", "fit", "fit_many"]


@dataclasses.dataclass
class FitResult:
    """Outcome of :func:`fit` (stable API).

    Attributes:
        params: {object: {alpha, beta, chi, mu, n, gamma}} fitted (free) or fixed values.
        stderr: same shape: standard errors (0 for fixed parameters): the Jacobian's, scaled
            by √(χ²/dof) when that exceeds 1 (model error larger than the instrument noise),
            or, where larger (``FitOptions.errors`` "robust", the default), the one from
            leaving each reading out in turn (an error shared by a reading's bands counted
            once per reading).
        status: "converged", "max_steps" (best start hit the iteration limit) or "failed".
        free: labels ``object.parameter`` of the unknowns (and ``scale``).
        correlation: (F, F) correlation matrix of the unknowns.
        relative_to: None when α, β, χ, γ are absolute (white calibration or a stated
            scale); else the parameter they are relative to (calibration "global").
        scale, scale_stderr: the fitted global environment scale (calibration "global").
        cost: ½ Σ r² at the optimum; chi2_red: Σ r² / dof.
        starts: per start: cost, converged, steps.
        bootstrap: {object: {param: std}} over bootstrap resamples of readings (or None).
        warnings: identifiability and data warnings.
        readings: per reading: id, object, kind, ΔE00, Δu′v′, xy / u′v′ measured and fitted,
            rms relative residual, aiming sensitivity.
        holdout: fit on object-colour readings only, prediction of the others (or None).
        wavelengths, measured, fitted, sigma: (L,), (B, L) ×3 spectra.
        calibration: (L,) the environment calibration k(λ) applied.
        timings: seconds of the preparation (``prepare_s``), the starts' solve with its
            compile or load (``solve_s``), the uncertainty, profile, bootstrap, hold-out and
            aiming sensitivity, ``total_s``; ``caches``: where the preparation and the
            aim-shifted problems came from ("hit", "miss", "off"; "skipped" without an aiming
            sensitivity) and the programs loaded from or compiled into JAX's persistent
            cache during the fit.
        model_error: {kind: relative error of the model} added to the readings' σ in
            quadrature (stated in the session's ``[model_error]``, or estimated there with
            "auto"; :mod:`spectral_fit.fitting._model_error`), and {"level.KIND": ℓ,
            "tilt.KIND": t} the stated errors shared by a reading's bands
            (``[model_error.level]``, ``[model_error.tilt]``).
        profile: with ``options.profile``, {label: interval} of every unknown from the
            profile likelihood (:func:`~spectral_fit.fitting._profile.profile_intervals`:
            value, lower, upper, how each end was found, the held values and their Δχ²);
            else None.
        constraints: {label: {"lower", "upper", "prior_mean", "prior_sigma"}} of the
            unknowns with a bound or a prior stated in the session (None where not stated).
        images: per camera photograph of the session: id, bins used and left out (by
            reason), χ² and the rms relative residual of its channels, and per bin its row,
            column, object, measured and fitted counts and σ (C each); ``measured``,
            ``fitted`` and ``sigma`` above hold the spot readings only.
    """

    params: dict[str, dict[str, float]]
    stderr: dict[str, dict[str, float]]
    status: str
    free: list[str]
    correlation: np.ndarray
    relative_to: str | None
    scale: float | None
    scale_stderr: float | None
    cost: float
    chi2_red: float
    dof: int
    starts: list[dict[str, Any]]
    bootstrap: dict[str, dict[str, float]] | None
    warnings: list[str]
    readings: list[dict[str, Any]]
    holdout: dict[str, Any] | None
    wavelengths: np.ndarray
    measured: np.ndarray
    fitted: np.ndarray
    sigma: np.ndarray
    calibration: np.ndarray
    calibration_mode: str
    timings: dict[str, Any]
    iterations: int = 0
    values: np.ndarray | None = None  # (O, 6)
    profile: dict[str, dict[str, Any]] | None = None
    model_error: dict[str, float] = dataclasses.field(default_factory=dict)
    constraints: dict[str, dict[str, float | None]] = dataclasses.field(default_factory=dict)
    images: list[dict[str, Any]] = dataclasses.field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        """A JSON-serialisable summary (spectra excluded; see the report for those)."""
        def clean(x: Any) -> Any:
            if isinstance(x, dict):
                return {k: clean(v) for k, v in x.items()}
            if isinstance(x, list | tuple):
                return [clean(v) for v in x]
            if isinstance(x, np.ndarray):
                return clean(x.tolist())
            if isinstance(x, float | np.floating):
                return float(x) if math.isfinite(x) else None
            if isinstance(x, np.integer | np.bool_):
                return x.item()
            return x

        return clean({
            "params": self.params, "stderr": self.stderr, "status": self.status,
            "free": self.free, "correlation": self.correlation,
            "relative_to": self.relative_to, "scale": self.scale,
            "scale_stderr": self.scale_stderr, "calibration_mode": self.calibration_mode,
            "cost": self.cost, "chi2_red": self.chi2_red, "dof": self.dof,
            "iterations": self.iterations, "starts": self.starts,
            "bootstrap_std": self.bootstrap, "warnings": self.warnings,
            "readings": self.readings, "holdout": self.holdout, "timings": self.timings,
            "profile": self.profile, "model_error": self.model_error,
            "constraints": self.constraints,
            "images": self.images,
        })


def _reading_robust_covariance(J: np.ndarray, r: np.ndarray, B: int, L: int, use: np.ndarray
                               ) -> np.ndarray | None:
    """The covariance (F, F) of the estimate with the readings as clusters, from leaving each
    reading out: (B − 1)/B · Σ_b Δ_b Δ_bᵀ, Δ_b = (JᵀJ − J_bᵀJ_b)⁺ J_bᵀ r_b the one-step change
    of the estimate without reading b (the cluster jackknife, "CR3" among the cluster-robust
    sandwich estimators; MacKinnon & White 1985, Bell & McCaffrey 2002). J, r: the weighted
    Jacobian (B·L + K, F) and residuals, priors' rows last (kept in JᵀJ). An error shared by
    a reading's bands (a level, a tilt: what a model's error at one spot looks like) then
    counts once per reading, whatever its structure, where (JᵀJ)⁻¹ counts it once per band;
    and a parameter that hangs on a few readings shows it (their residuals, which the fit
    pulls towards zero, are not taken at face value). None with fewer than F + 2
    readings."""
    F = J.shape[1]
    rows = np.flatnonzero(np.asarray(use) > 0)
    if rows.size < F + 2:
        return None
    A = J.T @ J
    Jb = J[:B * L].reshape(B, L, F)[rows]
    rb = r[:B * L].reshape(B, L)[rows]
    deltas = np.stack([np.linalg.pinv(A - Jb[i].T @ Jb[i], rcond=1e-10, hermitian=True)
                       @ (Jb[i].T @ rb[i]) for i in range(rows.size)])
    return deltas.T @ deltas * ((rows.size - 1) / rows.size)


def _colour_table(wl: np.ndarray, measured: np.ndarray, fitted: np.ndarray,
                  white: np.ndarray) -> list[dict[str, Any]]:
    from ..color import (
        delta_e00,
        delta_uv_prime,
        radiance_to_xyz,
        xyz_to_lab,
        xyz_to_uv_prime,
        xyz_to_xy,
    )

    xm = radiance_to_xyz(measured, wl)
    xf = radiance_to_xyz(fitted, wl)
    xw = radiance_to_xyz(white, wl)
    de = delta_e00(xyz_to_lab(xm, xw), xyz_to_lab(xf, xw))
    duv = delta_uv_prime(xm, xf)
    out = []
    for b in range(measured.shape[0]):
        out.append({
            "delta_e00": float(de[b]), "delta_uv": float(duv[b]),
            "xy_measured": xyz_to_xy(xm[b]).tolist(), "xy_fitted": xyz_to_xy(xf[b]).tolist(),
            "uv_measured": xyz_to_uv_prime(xm[b]).tolist(),
            "uv_fitted": xyz_to_uv_prime(xf[b]).tolist(),
            "Y_measured": float(xm[b, 1]), "Y_fitted": float(xf[b, 1]),
        })
    return out


def _reference_white(prep: PreparedFit, calib: np.ndarray, scale: float) -> np.ndarray:
    """Radiance (L,) of the scene's white for CIELAB: the white standard's reading divided by
    its reflectance, else a perfect diffuser facing the first instrument (or camera)."""
    from ..lighting import irradiance_exact

    s = prep.session
    if s.white is not None:
        return s.white.mean / s.white.reflectance
    r = s.readings[0] if s.readings else s.images[0]
    n = r.position - r.aim
    n = n / np.linalg.norm(n)
    env = prep.problem.env
    e = np.asarray(irradiance_exact(env, jnp.asarray(n, env.texels.dtype)), np.float64)
    return calib * scale * e / math.pi


def _identifiability(labels: list[str], corr: np.ndarray, jtj: np.ndarray) -> list[str]:
    out = []
    F = len(labels)
    for i in range(F):
        for j in range(i + 1, F):
            c = corr[i, j]
            if np.isfinite(c) and abs(c) > 0.95:
                a, b = labels[i], labels[j]
                msg = (f"{a} and {b} are strongly correlated (r = {c:+.3f}): the readings "
                       "hardly separate them")
                oa, pa = a.rsplit(".", 1) if "." in a else ("", a)
                ob, pb = b.rsplit(".", 1) if "." in b else ("", b)
                if oa == ob and {pa, pb} == {"beta", "n"}:
                    msg += (" — β and n trade off through F0 = ((n−1)/(n+1))²; add readings "
                            "at grazing angles (θr > 60°) or fix n")
                out.append(msg)
    ev = np.linalg.eigvalsh(jtj) if F else np.array([1.0])
    if F and (ev[0] <= 0 or ev[-1] / max(ev[0], 1e-300) > 1e12):
        out.append("the normal matrix JᵀJ is (nearly) singular: some combination of the free "
                   "parameters is not determined by the readings; fix one of them")
    return out


def fit(scene: Scene | str | os.PathLike[str], session: Session | str | os.PathLike[str], *,
        options: FitOptions | None = None,
        progress: Callable[[str], None] | None = None, prepared: PreparedFit | None = None,
        cache_dir: str | os.PathLike[str] | None = None, **kwargs: Any) -> FitResult:
    """Fit the reflection-model parameters of the measured objects (stable API ``fit``).

    Args:
        scene: a :class:`~spectral_fit.io.Scene` or the path of its config.
        session: a :class:`~spectral_fit.io.Session` or the path of a session.
        options: :class:`FitOptions`; keyword arguments override its fields
            (``starts=8``, ``bootstrap=50``, ``kinds=("object",)``, ...).
        progress: called with one line of text per stage and per solver iteration.
        prepared: a :func:`prepare_fit` result to reuse (benchmarks).
        cache_dir: keep the preparation (and the aim-shifted problems of the aiming
            sensitivity) on disk under this folder and load it from there when every input is
            unchanged (:func:`~spectral_fit.fitting.prepare_fit_cached`; the CLI passes
            ``~/.cache/spectral_fit`` or ``$SPECTRAL_FIT_CACHE``); None (default): no disk
            cache.

    Returns:
        :class:`FitResult`.
    """
    from pathlib import Path

    from ..io import load_scene, load_session

    opts = _fit_options(options, kwargs)
    if isinstance(scene, str | Path):
        scene = load_scene(scene)
    if isinstance(session, str | Path):
        session = load_session(session, scene=scene)
    say = progress or (lambda _m: None)
    t0 = time.perf_counter()
    programs0 = compilation_counts()
    if prepared is None:
        say(f"rasterising {len(session.readings)} measuring fields"
            + (f" and {len(session.images)} photograph(s)" if session.images else "") + " ...")
        prepared = prepare_fit_cached(scene, session, options=opts, cache_dir=cache_dir)
        if prepared.cached == "hit":
            say("preparation loaded from the disk cache")
    prep = prepared
    problem = prep.problem
    names = list(prep.objects)
    labels = problem.names(names)
    B = len(session.readings)  # spot readings: the first B rows; the images' bins follow
    Bt = int(problem.readings.measured.shape[0])
    L = session.wavelengths.size
    use = prep.row_weights(opts.kinds)
    if use.sum() == 0:
        raise InputError(f"no readings of kinds {list(opts.kinds)}", path=session.path,
                         field="readings")
    F = problem.n_free
    if F == 0:
        raise InputError("no free parameters", path=session.path, field="objects")
    n_data = int(np.sum(use * prep.data_per_row()))
    dof = n_data + len(problem.prior) - F  # (each prior is one datum)
    if dof <= 0:
        raise InputError(f"{F} unknowns but only {n_data} data", path=session.path,
                         field="readings")
    vals0 = np.asarray(problem.values, np.float64)
    scale0 = 1.0
    if problem.fit_scale:  # closed-form start for the scale from the diffuse term alone
        pr_ = {k: np.asarray(v, np.float64) for k, v in (
            ("irradiance", problem.irradiance), ("reflectance", problem.surfaces.reflectance),
            ("background", problem.readings.background),
            ("measured", problem.readings.measured),
            ("calibration", problem.instrument.calibration))}
        obj = np.maximum(np.asarray(problem.receivers.object), 0)
        diff = vals0[obj, 0:1] / math.pi * pr_["reflectance"][obj] * pr_["irradiance"]
        diff *= (np.asarray(problem.receivers.object) >= 0)[:, None]
        pred = pr_["calibration"] * (problem.readings.average.apply_np(diff)
                                     + pr_["background"])
        m = (use[:, None] > 0) & (np.arange(Bt) < B)[:, None]  # spot readings
        scale0 = float(np.sum(pred * pr_["measured"] * m) / max(np.sum(pred * pred * m),
                                                                 1e-300))
        scale0 = scale0 if scale0 > 0 and math.isfinite(scale0) else 1.0
    y0 = y_start(problem, vals0, scale0)
    starts = _starts(problem, y0, opts.starts, opts.seed)
    dt = problem.values.dtype
    # the compact solver records its cost per step and the lines are printed after the solve
    # (no host callback in the program: JAX's persistent cache can keep it between runs)
    live = progress is not None and opts.solver != "compact"
    solver = make_solver(opts, live)
    n_rows = int(use[B:].sum())
    n_bins = sum(ir.bins.shape[0] for ir in prep.images) if n_rows else 0
    say(f"solving: {F} unknowns, {int(use[:B].sum())} readings x {L} bands"
        + (f" + {n_bins} photograph bins ({n_rows} rows)" if n_rows else "")
        + f", {opts.starts} starts (Levenberg-Marquardt, {opts.solver}) ...")
    if live:
        _PROGRESS.append(lambda s, c: say(f"  step {int(np.max(s)):3d}  "
                                          f"best cost {float(np.min(c)):.6g}"))
    t1 = time.perf_counter()
    try:
        out = stored_call(solve_batch, problem, jnp.asarray(starts, dt),
                           jnp.asarray(np.tile(use, (len(starts), 1)), dt), solver,
                           opts.max_steps, cache_dir=cache_dir)
        out = {k: np.asarray(v) for k, v in out.items()}
    finally:
        if live:
            _PROGRESS.pop()
    t_solve = time.perf_counter() - t1
    if progress is not None and "history" in out:
        for hist, n in zip(out["history"], out["steps"], strict=True):
            for k in range(int(n)):
                say(f"  step {k:3d}  best cost {float(hist[k]):.6g}")
    costs = out["cost"].astype(np.float64)
    best = int(np.argmin(np.where(np.isfinite(costs), costs, np.inf)))
    # the starts as solved (reported, and compared for local minima)
    start_costs, start_oks, start_steps = costs, out["converged"], out["steps"]
    start_best = best
    # the model's error per reading kind: stated in the session, or estimated ("auto") from
    # the residuals and the fit solved again with it (same program: σ is data)
    reading_kinds = row_kinds(session, prep.n_image_rows)
    model_error = {k: float(v) for k, v in session.model_error.items() if not isinstance(v, str)}
    model_error.update({f"level.{k}": float(v) for k, v in session.level_error.items()})
    model_error.update({f"tilt.{k}": float(v) for k, v in session.tilt_error.items()})
    auto = sorted(k for k, v in session.model_error.items() if v == "auto")
    if auto and np.isfinite(costs[best]):
        # estimated and solved again in turn (the first solve fitted every kind with the
        # instrument's σ alone, so its residuals understate an erring kind's error): until
        # the estimates settle within 5 %, at most 6 rounds
        meas_ = np.asarray(problem.readings.measured, np.float64)
        sig0 = np.asarray(problem.readings.sigma, np.float64)
        est = {k: 0.0 for k in auto}
        for _ in range(6):
            new = estimate_model_error(out["predicted"][best] - meas_, meas_, sig0,
                                       reading_kinds, use, auto, n_free=F,
                                       data=prep.data_per_row())
            settled = all(abs(new[k] - est.get(k, 0.0)) <= 0.05 * max(new[k], 1e-12)
                          for k in new)
            est.update(new)
            sig_new = np.maximum(with_model_error(sig0, meas_, reading_kinds, est), 1e-12)
            problem = eqx.tree_at(lambda q: q.readings.sigma, problem,
                                  jnp.asarray(sig_new, dt))
            again = stored_call(solve_batch, problem,
                                jnp.asarray(np.tile(out["y"][best], (len(starts), 1)), dt),
                                jnp.asarray(np.tile(use, (len(starts), 1)), dt), solver,
                                opts.max_steps, cache_dir=cache_dir)
            out = {k: np.asarray(v) for k, v in again.items()}
            costs = out["cost"].astype(np.float64)
            best = int(np.argmin(np.where(np.isfinite(costs), costs, np.inf)))
            if settled or not np.isfinite(costs[best]):
                break
        prep = dataclasses.replace(prep, problem=problem)
        model_error.update(est)
        say("model error estimated from the residuals: " + ", ".join(
            f"{k} {100 * v:.2g} %" for k, v in est.items()))
    oks = out["converged"]
    steps = out["steps"]
    if not np.isfinite(costs[best]):
        status = "failed"
    elif oks[best]:
        status = "converged"
    else:
        status = "max_steps"
    y = out["y"][best].astype(np.float64)
    vals, scale = physical_from_y(problem, jnp.asarray(y, dt))
    vals = np.asarray(vals, np.float64)
    scale = float(scale)
    warn = list(prep.warnings)
    agree = [i for i in range(len(start_costs)) if np.isfinite(start_costs[i])
             and start_costs[i] <= start_costs[start_best] * (1 + 1e-3) + 1e-9]
    if len(agree) < len(start_costs):
        worse = len(start_costs) - len(agree)
        warn.append(f"{worse} of {len(costs)} starts ended at a higher cost (local minima or "
                    "not converged); the best start is reported")
    # uncertainty: J w.r.t. the physical parameters by the chain rule ------------------------
    t2 = time.perf_counter()
    spec = unknowns(problem)
    kinds = [k for k, _, _ in spec]
    p_hat = np.array([vals[o, k] for o, k in problem.free] + ([scale] if problem.fit_scale
                                                             else []))
    dp_dy = np.array([_dp_dy(float(yy), *sp) for yy, sp in zip(y, spec, strict=True)])
    r = out["residual"][best].astype(np.float64)
    Jy = out["jacobian"][best].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        J = Jy / dp_dy[None, :]
    J[:, ~(np.abs(dp_dy) > 1e-12)] = 0.0
    chi2 = float(r @ r)
    chi2_red = chi2 / dof
    jtj = J.T @ J
    bread = np.linalg.pinv(jtj, rcond=1e-12, hermitian=True)
    cov = bread * max(1.0, chi2_red)
    robust = (_reading_robust_covariance(J, r, Bt, L, use)
              if opts.errors == "robust" else None)
    if robust is not None:  # the larger of the two per parameter, correlations kept
        grow = np.sqrt(np.maximum(np.diag(robust), 0.0) / np.maximum(np.diag(cov), 1e-300))
        cov = cov * np.outer(np.maximum(grow, 1.0), np.maximum(grow, 1.0))
    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(se, se)
    warn += _identifiability(labels, corr, jtj)
    for (o, _), v, (pname, lo, hi) in zip(problem.free, p_hat, spec, strict=False):
        tol = 1e-3 * (hi - lo) if math.isfinite(hi) else 1e-4
        at = ([lo] if (pname in _SQUARED or math.isfinite(hi) or lo > LOWER[pname])
              and v < lo + tol else []) + ([hi] if math.isfinite(hi) and v > hi - tol else [])
        if at:
            warn.append(f"{names[o]}.{pname} is at its bound {at[0]:g} (its standard error "
                        "is one-sided)")
    params = {nm: {p: float(vals[o, k]) for k, p in enumerate(PARAMETERS)}
              for o, nm in enumerate(names)}
    stderr = {nm: {p: 0.0 for p in PARAMETERS} for nm in names}
    for j, (o, k) in enumerate(problem.free):
        stderr[names[o]][PARAMETERS[k]] = float(se[j])
    t_unc = time.perf_counter() - t2
    # profile likelihood -------------------------------------------------------------------
    profile = None
    t_prof = 0.0
    if opts.profile:
        t4 = time.perf_counter()
        say(f"profile likelihood: {len(kinds)} parameters x {2 * len(STEPS)} held fits ...")
        prof = profile_intervals(problem, y, p_hat, se, float(costs[best]), use,
                                 max(1.0, chi2_red), labels=labels, kinds=kinds,
                                 limits=[(lo, hi) for _, lo, hi in spec],
                                 rtol=opts.rtol, atol=opts.atol, max_steps=opts.max_steps,
                                 jacobian=Jy)
        profile = prof["intervals"]
        if prof["lower_cost"] is not None:
            warn.append(f"a profile fit reached a lower cost ({prof['lower_cost']:.6g}) than "
                        f"the fit ({float(costs[best]):.6g}): the fit stopped short of the best "
                        "minimum (more starts may find it)")
        for label, iv in profile.items():
            sides = [s_ for s_ in ("lower", "upper") if iv[f"{s_}_end"] == "open"]
            if sides:
                warn.append(f"{label}: the profile stays within Δχ² = {max(1.0, chi2_red):.3g} "
                            f"out to {' and '.join(sides)} end(s) of the scan "
                            f"({iv['lower']:.4g} .. {iv['upper']:.4g}): these readings do not "
                            "bound it there")
        t_prof = time.perf_counter() - t4
    fitted_all = out["predicted"][best].astype(np.float64)
    measured_all = np.asarray(problem.readings.measured, np.float64)
    sigma_all = np.asarray(problem.readings.sigma, np.float64)
    images = _image_summaries(prep, measured_all, fitted_all, sigma_all, use)
    fitted, measured, sigma = fitted_all[:B], measured_all[:B], sigma_all[:B]
    # colour table ---------------------------------------------------------------------------
    calib = np.asarray(problem.instrument.calibration, np.float64)
    wl = session.wavelengths
    white = _reference_white(prep, calib, scale)
    table = _colour_table(wl, measured, fitted, white)
    for b, rd in enumerate(session.readings):
        rel = (fitted[b] - measured[b]) / np.maximum(np.abs(measured[b]), 1e-12)
        table[b].update(id=rd.id, object=rd.object, kind=rd.kind, used=bool(use[b]),
                        repeats=int(rd.repeats.shape[0]), coverage=float(prep.coverage[b]),
                        rms_relative_residual=float(np.sqrt(np.mean(rel ** 2))),
                        chi2=float(np.sum(((fitted[b] - measured[b]) / sigma[b]) ** 2)))
    # bootstrap ---------------------------------------------------------------------------
    boot = None
    t3 = time.perf_counter()
    if opts.bootstrap > 0:
        say(f"bootstrap over readings: {opts.bootstrap} resamples ...")
        boot = _bootstrap(problem, y, use, opts, solver, names, cache_dir)
    t_boot = time.perf_counter() - t3
    t5 = time.perf_counter()
    # hold-out -----------------------------------------------------------------------------
    holdout = None
    kinds_present = {r.kind for r in session.readings if use[session.readings.index(r)] > 0}
    unused = [b for b in range(B) if use[b] == 0]
    if unused:  # readings left out of the fit are predicted by it
        held = [{k: table[b][k] for k in ("id", "object", "kind", "delta_e00", "delta_uv",
                                          "xy_measured", "xy_fitted", "Y_measured",
                                          "Y_fitted")} for b in unused]
        des = [h["delta_e00"] for h in held]
        holdout = {"fitted_on": sorted(kinds_present),
                   "predicted": sorted({session.readings[b].kind for b in unused}),
                   "params": params, "readings": held, "mean_delta_e00": float(np.mean(des)),
                   "max_delta_e00": float(np.max(des))}
    elif opts.holdout and {"object", "interreflection"} <= kinds_present:
        say("hold-out: fit on object-colour readings, predict interreflection readings ...")
        holdout = _holdout(problem, prep, y, use, opts, solver, white, cache_dir)
    t_hold = time.perf_counter() - t5
    # aiming sensitivity ------------------------------------------------------------------
    t6 = time.perf_counter()
    aim_cache = "off"
    if opts.aim_step_m > 0 and B:
        say("aiming sensitivity ...")
        sens, aim_cache = _aim_sensitivity(scene, prep, vals, scale, opts, white, fitted,
                                           cache_dir)
        for b in range(B):
            table[b]["aim_sensitivity"] = sens[b]
    t_aim = time.perf_counter() - t6
    programs = compilation_counts()
    steps_best = int(steps[best])
    if status != "converged":
        warn.append(f"the best start did not converge in {opts.max_steps} steps")
    return FitResult(
        params=params, stderr=stderr, status=status, free=labels, correlation=corr,
        relative_to=(f"{session.reference}.alpha" if problem.fit_scale else None),
        scale=scale if problem.fit_scale else None,
        scale_stderr=float(se[-1]) if problem.fit_scale else None,
        cost=float(costs[best]), chi2_red=chi2_red, dof=dof,
        starts=[{"cost": float(start_costs[i]), "converged": bool(start_oks[i]),
                 "steps": int(start_steps[i])} for i in range(len(start_costs))],
        bootstrap=boot, warnings=warn, readings=table, holdout=holdout, wavelengths=wl,
        measured=measured, fitted=fitted, sigma=sigma, calibration=calib * scale,
        calibration_mode=session.calibration,
        timings={"prepare_s": prep.seconds,
                 "solve_s": t_solve, "uncertainty_s": t_unc, "profile_s": t_prof,
                 "bootstrap_s": t_boot, "holdout_s": t_hold, "aim_sensitivity_s": t_aim,
                 "total_s": time.perf_counter() - t0,
                 "caches": {"preparation": prep.cached,
                            "aim_preparation": aim_cache if opts.aim_step_m > 0 else "skipped",
                            **{f"programs_{k}": programs[k] - programs0[k]
                               for k in programs}}},
        iterations=steps_best, values=vals, profile=profile, model_error=model_error,
        constraints=_constraints(session, names, problem, labels), images=images)


def _image_summaries(prep: PreparedFit, measured: np.ndarray, fitted: np.ndarray,
                     sigma: np.ndarray, use: np.ndarray) -> list[dict[str, Any]]:
    """Per photograph: its bins' measured and fitted counts, χ², rms relative residual."""
    out = []
    row = prep.n_spots
    for ir in prep.images:
        im = prep.session.images[ir.image]
        n, c = ir.row_bin.shape[0], ir.response.shape[0]
        m, f, sg = (a[row:row + n, :c] for a in (measured, fitted, sigma))
        u = (use[row:row + n] > 0)[:, None] & ir.mask
        rel = (f - m) / np.maximum(np.abs(m), 1e-12)
        # one entry per bin: the channels of its rows gathered
        keys, inv, ob = ir.bins, ir.row_bin, ir.object
        mb, fb, sb = (np.zeros((keys.shape[0], c)) for _ in range(3))
        for a, b_ in ((mb, m), (fb, f), (sb, sg)):
            np.add.at(a, inv, np.where(ir.mask, b_, 0.0))
        out.append({
            "id": im.id, "used": bool(u.any()), "bins": int(keys.shape[0]), "rows": n,
            "steep_bins": int(np.sum(ir.steep)), "samples": int(ir.sample_row.size),
            "grid": list(ir.grid), "superpixel": im.superpixel, "dropped": dict(ir.dropped),
            "chi2": float(np.sum(((f - m) / sg)[u] ** 2)),
            "rms_relative_residual": float(np.sqrt(np.mean(rel[u] ** 2))) if u.any() else None,
            "bin_row": keys[:, 0], "bin_col": keys[:, 1], "object": ob,
            "measured": mb, "fitted": fb, "sigma": sb})
        row += n
    return out


def _constraints(session: Session, names: list[str], problem: FitProblem,
                 labels: list[str]) -> dict[str, dict[str, float | None]]:
    """The bounds and priors the session states for the unknowns, by label."""
    out: dict[str, dict[str, float | None]] = {}
    for label, (o, k) in zip(labels, problem.free, strict=False):
        om = session.objects.get(names[o])
        if om is None:
            continue
        lo, hi = om.bounds.get(PARAMETERS[k], (None, None))
        mean, sd = om.prior.get(PARAMETERS[k], (None, None))
        if lo is not None or hi is not None or mean is not None:
            out[label] = {"lower": lo, "upper": hi, "prior_mean": mean, "prior_sigma": sd}
    return out


def _bootstrap(problem: FitProblem, y: np.ndarray, use: np.ndarray, opts: FitOptions,
               solver: Any, names: list[str], cache_dir: str | os.PathLike[str] | None = None
               ) -> dict[str, dict[str, float]]:
    rng = np.random.default_rng(opts.seed + 1)
    idx = np.flatnonzero(use > 0)
    S = max(1, opts.starts)
    n = int(math.ceil(opts.bootstrap / S)) * S
    ws = np.zeros((n, use.size))
    for i in range(n):
        pick = rng.choice(idx, size=idx.size, replace=True)
        np.add.at(ws[i], pick, 1.0)
    dt = problem.values.dtype
    got = []
    for c in range(0, n, S):
        o = stored_call(solve_batch, problem, jnp.asarray(np.tile(y, (S, 1)), dt),
                        jnp.asarray(ws[c:c + S], dt), solver, opts.max_steps,
                        cache_dir=cache_dir)
        for yi, ci in zip(np.asarray(o["y"]), np.asarray(o["cost"]), strict=True):
            if np.isfinite(ci):
                got.append(np.asarray(physical_from_y(problem, jnp.asarray(yi, dt))[0]))
    arr = np.stack(got) if got else np.full((1,) + tuple(problem.values.shape), np.nan)
    std = arr.std(axis=0, ddof=1) if len(got) > 1 else np.full(arr.shape[1:], np.nan)
    out = {nm: {p: 0.0 for p in PARAMETERS} for nm in names}
    for o, k in problem.free:
        out[names[o]][PARAMETERS[k]] = float(std[o, k])
    out["_resamples"] = {"used": float(len(got)), "requested": float(opts.bootstrap)}
    return out


def _holdout(problem: FitProblem, prep: PreparedFit, y: np.ndarray, use: np.ndarray,
             opts: FitOptions, solver: Any, white: np.ndarray,
             cache_dir: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    s = prep.session
    obj_only = use * prep.row_weights(("object", "image"))
    dt = problem.values.dtype
    # one solve from the fit's optimum; the batch has the fit's size (the same compiled
    # program), its other rows weigh no reading and stop within a few steps
    S = max(1, opts.starts)
    rw = np.zeros((S, obj_only.size))
    rw[0] = obj_only
    o = stored_call(solve_batch, problem, jnp.asarray(np.tile(y, (S, 1)), dt),
                    jnp.asarray(rw, dt), solver, opts.max_steps, cache_dir=cache_dir)
    yh = np.asarray(o["y"])[0]
    vals, scale = physical_from_y(problem, jnp.asarray(yh, dt))
    pred = np.asarray(o["predicted"][0], np.float64)
    meas = np.asarray(problem.readings.measured, np.float64)
    table = _colour_table(s.wavelengths, meas, pred, white)
    held = [{"id": r.id, "object": r.object, **table[b]} for b, r in enumerate(s.readings)
            if r.kind != "object" and use[b] > 0]
    names = list(prep.objects)
    v = np.asarray(vals, np.float64)
    return {
        "fitted_on": "object", "predicted": "interreflection",
        "params": {nm: {p: float(v[o, k]) for k, p in enumerate(PARAMETERS)}
                   for o, nm in enumerate(names)},
        "readings": held,
        "mean_delta_e00": float(np.mean([h["delta_e00"] for h in held])) if held else None,
        "max_delta_e00": float(np.max([h["delta_e00"] for h in held])) if held else None,
    }


def _aim_sensitivity(scene: Scene, prep: PreparedFit, vals: np.ndarray, scale: float,
                     opts: FitOptions, white: np.ndarray, fitted: np.ndarray,
                     cache_dir: str | os.PathLike[str] | None = None
                     ) -> tuple[list[dict[str, Any]], str]:
    """ΔE00 and relative radiance change per mm of aiming error, per reading (finite
    differences over aim shifts of ``aim_step_m`` in two directions across the axis), and
    whether the shifted problems came from the disk cache ("hit", "miss", "off")."""
    from ..color import delta_e00, radiance_to_xyz, xyz_to_lab

    s = prep.session
    step = opts.aim_step_m
    wl = s.wavelengths
    xw = radiance_to_xyz(white, wl)
    lab0 = xyz_to_lab(radiance_to_xyz(fitted, wl), xw)
    de = np.zeros((len(s.readings), 2))
    rel = np.zeros_like(de)
    dt = prep.problem.values.dtype
    sessions = []
    for d in range(2):
        shifted = []
        for r in s.readings:
            ax = r.aim - r.position
            ax = ax / np.linalg.norm(ax)
            u = np.cross(ax, [0.0, 1.0, 0.0])
            if np.linalg.norm(u) < 1e-6:
                u = np.cross(ax, [1.0, 0.0, 0.0])
            u = u / np.linalg.norm(u)
            v = np.cross(ax, u)
            shifted.append(dataclasses.replace(r, aim=r.aim + step * (u if d == 0 else v)))
        sessions.append(s.replace(readings=tuple(shifted), images=()))
    problems, cached = aim_problems_cached(
        scene, prep, dataclasses.replace(
            opts, interreflection="auto" if prep.problem.interreflection else "none"),
        sessions, cache_dir=cache_dir)
    for d, pp in enumerate(problems):
        if pp is None:
            de[:, d] = np.nan
            rel[:, d] = np.nan
            continue
        pred = np.asarray(stored_call(_predict_jit, pp, jnp.asarray(vals, dt),
                                      jnp.asarray(scale, dt), cache_dir=cache_dir), np.float64)
        lab = xyz_to_lab(radiance_to_xyz(pred, wl), xw)
        de[:, d] = delta_e00(lab0, lab)
        rel[:, d] = np.linalg.norm(pred - fitted, axis=1) / np.maximum(
            np.linalg.norm(fitted, axis=1), 1e-30)
    mm = step * 1e3
    return [{"delta_e00_per_mm": float(np.nanmax(de[b]) / mm) if np.isfinite(de[b]).any()
             else None,
             "relative_radiance_per_mm": float(np.nanmax(rel[b]) / mm)
             if np.isfinite(rel[b]).any() else None}
            for b in range(len(s.readings))], cached


def fit_many(prepared: PreparedFit, measured: Any, *, sigma: Any = None,
             options: FitOptions | None = None, devices: Sequence[Any] | None = None,
             **kwargs: Any) -> dict[str, Any]:
    """Fit K sets of readings of the same spots at once (``jax.vmap``), optionally sharded
    across devices along K (``jax.sharding``; the problem is replicated).

    Args:
        prepared: :func:`prepare_fit` of the session whose spots all K sets share.
        measured: (K, B, L) mean readings; ``sigma`` (K, B, L) their standard errors (default:
            the session's).
        devices: devices to shard K over (default: all of ``jax.devices()`` when more than
            one); K is padded to a multiple of their number.

    Returns:
        dict with ``params`` (K, O, 6), ``stderr`` (K, O, 6) (Jacobian, unscaled by χ²),
        ``scale`` (K,), ``cost`` (K,), ``converged`` (K,), ``steps`` (K,), ``devices`` (the
        devices the result was computed on).
    """
    opts = _fit_options(options, kwargs)
    problem = prepared.problem
    dt = problem.values.dtype
    meas = np.asarray(measured, np.float64)
    K = meas.shape[0]
    shape = tuple(problem.readings.measured.shape)
    if meas.ndim != 3 or meas.shape[1:] != shape:
        raise InputError(f"expected (K, {shape[0]}, {shape[1]}), got {meas.shape}",
                         field="measured")
    if not np.all(np.isfinite(meas)):
        raise InputError("NaN or infinite readings", field="measured")
    sig = np.broadcast_to(np.asarray(problem.readings.sigma if sigma is None else sigma,
                                     np.float64), meas.shape)
    use = prepared.row_weights(opts.kinds)
    y0 = y_start(problem, np.asarray(problem.values, np.float64), 1.0)
    devs = list(devices) if devices is not None else jax.devices()
    nd = len(devs)
    Kp = int(math.ceil(K / nd)) * nd
    pad = lambda a: np.concatenate([a, np.repeat(a[-1:], Kp - K, 0)]) if Kp > K else a  # noqa: E731
    args = [jnp.asarray(pad(np.tile(y0, (K, 1))), dt), jnp.asarray(pad(np.tile(use, (K, 1))), dt),
            jnp.asarray(pad(meas), dt), jnp.asarray(pad(np.ascontiguousarray(sig)), dt)]
    if nd > 1:
        from jax.sharding import Mesh, NamedSharding, PartitionSpec

        mesh = Mesh(np.array(devs), ("k",))
        args = [jax.device_put(a, NamedSharding(mesh, PartitionSpec("k"))) for a in args]
    out = _solve_measured(problem, *args, make_solver(opts, False), opts.max_steps)
    used = sorted({str(d) for d in out["y"].sharding.device_set})
    out = {k: np.asarray(v)[:K] for k, v in out.items()}
    O = problem.values.shape[0]
    params = np.zeros((K, O, 6))
    stderr = np.zeros((K, O, 6))
    scales = np.ones(K)
    spec = unknowns(problem)
    for i in range(K):
        y = out["y"][i].astype(np.float64)
        v, s = physical_from_y(problem, jnp.asarray(y, dt))
        params[i] = np.asarray(v, np.float64)
        scales[i] = float(s)
        dp = np.array([_dp_dy(float(a), *sp) for a, sp in zip(y, spec, strict=True)])
        with np.errstate(divide="ignore", invalid="ignore"):
            J = out["jacobian"][i].astype(np.float64) / dp[None, :]
        J[:, ~(np.abs(dp) > 1e-12)] = 0.0
        cov = np.linalg.pinv(J.T @ J, rcond=1e-12, hermitian=True)
        se = np.sqrt(np.maximum(np.diag(cov), 0.0))
        for j, (o, k) in enumerate(problem.free):
            stderr[i, o, k] = se[j]
    return {"params": params, "stderr": stderr, "scale": scales, "cost": out["cost"],
            "converged": out["converged"], "steps": out["steps"], "devices": used}
