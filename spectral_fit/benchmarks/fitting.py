"""Benchmark of the fit (``fit_demo``): the bundled two-sphere session (all readings, both
kinds), 5 free parameters per sphere, 81 bands, interreflection on (the scene's gather mode),
one start.

Timed: what :func:`~spectral_fit.fitting.fit` does per start — ``ir_rounds`` rounds of (the
interreflection term at the current estimate, then the jit-compiled optimistix
Levenberg–Marquardt solve with the forward model and its Jacobian inside); ``compile_s`` is
the first call (traces + compiles + run). The preparation (environment prefiltering, ray
casting of the measuring fields, exact irradiance, the interreflection geometry pass) runs once
before and is reported as ``prepare_s``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..bench import BenchOptions, measure


def fit_demo(opts: BenchOptions) -> dict[str, Any]:
    import time
    import warnings

    import jax.numpy as jnp

    from ..fitting import (
        FitOptions,
        _physical_from_y,
        _solve_batch,
        _solver,
        _y_start,
        prepare_fit,
        with_interreflection,
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

    rounds = fo.ir_rounds if pr.ir_apply is not None else 1

    def run() -> Any:
        p, y, out = pr, y0, None
        for r in range(rounds):
            if r:
                p = with_interreflection(p, _physical_from_y(p, out["y"][0])[0])
            out = _solve_batch(p, y, rw, solver, fo.max_steps)
            y = out["y"]
        return out

    out = measure(run, repeats=max(3, min(opts.repeats, 5)))
    res = run()
    out.update(prepare_s=prepare_s, readings=len(session.readings),
               bands=int(session.wavelengths.size), free_parameters=pr.n_free,
               samples=int(pr.receivers.object.shape[0]),
               iterations=int(np.asarray(res["steps"])[0]),
               converged=bool(np.asarray(res["converged"])[0]),
               interreflection=pr.ir_apply is not None, ir_rounds=rounds)
    return out


CASES = {"fit_demo": fit_demo}
