"""Benchmark of the fit (``fit_demo``): the bundled two-sphere session (all readings, both
kinds), 5 free parameters per sphere, 81 bands, interreflection on (inside the forward model
and its Jacobian, :mod:`spectral_fit.fitting`), one start from the config's materials.

Timed: the jit-compiled Levenberg–Marquardt solve that :func:`~spectral_fit.fitting.fit` runs
per start (forward model and exact Jacobian inside), with the default compact solver
(``fit_demo``) and with ``optimistix.LevenbergMarquardt`` (``fit_demo_optimistix``);
``compile_s`` is the first call (trace + compile + run), ``compile_cpu_s`` its CPU time (all
threads; on a shared machine the CPU time is the steadier figure). The preparation
(environment prefiltering, ray casting of the measuring fields, the radiance cache with its
interreflection probes) runs once before and is reported as ``prepare_s`` / ``prepare_cpu_s``.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from .._harness import BenchOptions, measure


@functools.lru_cache(maxsize=2)
def _prepared(quick: bool) -> tuple[Any, Any, float, float]:
    import time
    import warnings

    from ...fitting import DEMO_CONFIG, DEMO_SESSION, FitOptions, prepare_fit
    from ...io import load_scene, load_session

    scene = load_scene(DEMO_CONFIG)
    session = load_session(DEMO_SESSION, scene=scene)
    fo = FitOptions(spot_resolution=4 if quick else 8)
    t0, c0 = time.perf_counter(), time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prep = prepare_fit(scene, session, options=fo)
    return prep, session, time.perf_counter() - t0, time.process_time() - c0


def _fit_demo(opts: BenchOptions, solver_name: str) -> dict[str, Any]:
    import json
    import time

    import jax
    import jax.numpy as jnp

    from ...fitting import (
        DEMO_SESSION,
        PARAMETERS,
        FitOptions,
        make_solver,
        physical_from_y,
        solve_batch,
        y_start,
    )

    prep, session, prepare_s, prepare_cpu_s = _prepared(opts.quick)
    pr = prep.problem
    dt = pr.values.dtype
    fo = FitOptions(solver=solver_name)
    y0 = jnp.asarray(y_start(pr, np.asarray(pr.values, np.float64), 1.0)[None], dt)
    rw = jnp.ones((1, len(session.readings)), dt)
    solver = make_solver(fo, False)
    cpu: dict[str, float] = {}

    def run() -> Any:
        c = time.process_time()
        out = jax.block_until_ready(solve_batch(pr, y0, rw, solver, fo.max_steps))
        cpu.setdefault("first", time.process_time() - c)
        return out

    out = measure(run, repeats=max(3, min(opts.repeats, 10)))
    res = run()
    vals = np.asarray(physical_from_y(pr, res["y"][0])[0], np.float64)
    errs = {}
    truth_path = DEMO_SESSION / "truth.json"
    if truth_path.is_file():
        truth = json.loads(truth_path.read_text())["params"]
        for o, name in enumerate(prep.objects):
            for k, p in enumerate(PARAMETERS):
                if p in truth.get(name, {}) and p != "gamma":
                    t = truth[name][p]
                    e = vals[o, k] - t
                    errs[f"{name}.{p}"] = float(e if p in ("chi", "n") else e / t)
    out.update(solver=solver_name, compile_cpu_s=cpu["first"], prepare_s=prepare_s,
               prepare_cpu_s=prepare_cpu_s, readings=len(session.readings),
               bands=int(session.wavelengths.size), free_parameters=pr.n_free,
               samples=int(pr.receivers.object.shape[0]),
               iterations=int(np.asarray(res["steps"])[0]),
               converged=bool(np.asarray(res["converged"])[0]),
               interreflection=pr.interreflection, recovery_error=errs)
    return out


def fit_demo(opts: BenchOptions) -> dict[str, Any]:
    """The default (compact) Levenberg–Marquardt solve of the bundled session."""
    return _fit_demo(opts, "compact")


def fit_demo_optimistix(opts: BenchOptions) -> dict[str, Any]:
    """The same solve with ``optimistix.LevenbergMarquardt`` (for comparison)."""
    return _fit_demo(opts, "optimistix")


CASES = {"fit_demo": fit_demo, "fit_demo_optimistix": fit_demo_optimistix}
