"""Benchmark of the fit (``fit_demo``): the bundled two-sphere session (all readings, both
kinds), 5 free parameters per sphere, 81 bands, interreflection on (inside the forward model
and its Jacobian, :mod:`spectral_fit.radiance_cache`), one start from the config's materials.

Timed: the jit-compiled optimistix Levenberg–Marquardt solve that :func:`~spectral_fit.fitting.fit`
runs per start (forward model and exact Jacobian inside); ``compile_s`` is the first call
(trace + compile + run). The preparation (environment prefiltering, ray casting of the
measuring fields, the radiance cache with its interreflection probes) runs once before and is
reported as ``prepare_s``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..bench import BenchOptions, measure


def fit_demo(opts: BenchOptions) -> dict[str, Any]:
    import json
    import time
    import warnings

    import jax.numpy as jnp

    from ..fitting import (
        PARAMETERS,
        FitOptions,
        _physical_from_y,
        _solve_batch,
        _solver,
        _y_start,
        prepare_fit,
    )
    from ..report import DEMO_CONFIG, DEMO_SESSION
    from ..scene import load_scene
    from ..session import load_session

    scene = load_scene(DEMO_CONFIG)
    session = load_session(DEMO_SESSION, scene=scene)
    fo = FitOptions(spot_resolution=4 if opts.quick else 8)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prep = prepare_fit(scene, session, options=fo)
    prepare_s = time.perf_counter() - t0
    pr = prep.problem
    dt = pr.values.dtype
    y0 = jnp.asarray(_y_start(pr, np.asarray(pr.values, np.float64), 1.0)[None], dt)
    rw = jnp.ones((1, len(session.readings)), dt)
    solver = _solver(fo, False)

    def run() -> Any:
        return _solve_batch(pr, y0, rw, solver, fo.max_steps)

    out = measure(run, repeats=max(3, min(opts.repeats, 10)))
    res = run()
    vals = np.asarray(_physical_from_y(pr, res["y"][0])[0], np.float64)
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
    out.update(prepare_s=prepare_s, readings=len(session.readings),
               bands=int(session.wavelengths.size), free_parameters=pr.n_free,
               samples=int(pr.receivers.object.shape[0]),
               iterations=int(np.asarray(res["steps"])[0]),
               converged=bool(np.asarray(res["converged"])[0]),
               interreflection=pr.interreflection, recovery_error=errs)
    return out


CASES = {"fit_demo": fit_demo}
