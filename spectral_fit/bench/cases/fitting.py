"""Benchmark of the fit (``fit_demo``): the bundled two-sphere session (all readings, both
kinds), 5 free parameters per sphere, 81 bands, interreflection on (inside the forward model
and its Jacobian, :mod:`spectral_fit.fitting`), one start from the config's materials;
``fit_photo``: the same solve on the bundled photograph session (one raw photograph, 41
bands, 5 free parameters per sphere); ``fit_any_shape``: on the bundled session of spots on a
cup and a torus (meshes: occlusion and interreflection from the visibility tables).

Timed: the jit-compiled Levenberg–Marquardt solve that :func:`~spectral_fit.fitting.fit` runs
per start (forward model and exact Jacobian inside), with the default compact solver
(``fit_demo``) and with ``optimistix.LevenbergMarquardt`` (``fit_demo_optimistix``);
``compile_s`` is the first call (trace + compile + run), ``compile_cpu_s`` its CPU time (all
threads; on a shared machine the CPU time is the steadier figure). The preparation
(environment prefiltering, ray casting of the measuring fields, the radiance cache with its
interreflection probes) runs once before and is reported as ``prepare_s`` / ``prepare_cpu_s``.

``fit_cli``: ``spectral-fit fit`` of the bundled session from the shell, end to end with its
report (each run a fresh ``python -m spectral_fit fit`` process): first runs, each on empty
caches (the preparation, the report's pictures, the render's scene and program, JAX's compiled
programs, all in a temporary folder), then re-runs on the caches the last first run left.
``median_ms`` / ``min_ms`` / ``max_ms`` are the re-runs' wall times, ``compile_s`` the first
runs' median; ``first_run_s`` / ``rerun_s`` (and ``*_cpu_s``, the processes' CPU time) the
medians of each, ``first_run_timing`` / ``rerun_timing`` the report's ``timing`` block of
one run of each.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import numpy as np

from .._harness import BenchOptions, measure

#: the bundled sessions besides the demo: the photograph (scripts/make_photo_session.py) and
#: the spots on a cup and a torus (scripts/make_any_shape_session.py)
SESSIONS = {name: Path(__file__).resolve().parents[3] / "measurements" / "sessions" / folder
            for name, folder in (("photo", "two_spheres_photo"),
                                 ("any_shape", "any_shape_spots"))}


@functools.lru_cache(maxsize=4)
def _prepared(quick: bool, which: str = "demo") -> tuple[Any, Any, float, float]:
    import time
    import warnings

    from ...fitting import DEMO_SESSION, FitOptions, prepare_fit
    from ...io import load_session

    session = load_session(DEMO_SESSION if which == "demo" else SESSIONS[which])
    scene = session.scene
    fo = FitOptions(spot_resolution=4 if quick else 8)
    t0, c0 = time.perf_counter(), time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prep = prepare_fit(scene, session, options=fo)
    return prep, session, time.perf_counter() - t0, time.process_time() - c0


def _fit_demo(opts: BenchOptions, solver_name: str, which: str = "demo") -> dict[str, Any]:
    import json
    import time

    import jax
    import jax.numpy as jnp

    from ...fitting import (
        PARAMETERS,
        FitOptions,
        make_solver,
        physical_from_y,
        solve_batch,
        y_start,
    )

    prep, session, prepare_s, prepare_cpu_s = _prepared(opts.quick, which)
    pr = prep.problem
    dt = pr.values.dtype
    fo = FitOptions(solver=solver_name)
    y0 = jnp.asarray(y_start(pr, np.asarray(pr.values, np.float64), 1.0)[None], dt)
    rw = jnp.asarray(prep.row_weights(fo.kinds)[None], dt)
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
    truth_path = session.path.parent / "truth.json"
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
               image_rows=prep.n_image_rows,
               bands=int(session.wavelengths.size), free_parameters=pr.n_free,
               samples=int(pr.receivers.object.shape[0]),
               iterations=int(np.asarray(res["steps"])[0]),
               converged=bool(np.asarray(res["converged"])[0]),
               interreflection=pr.interreflection, recovery_error=errs)
    return out


def fit_photo(opts: BenchOptions) -> dict[str, Any]:
    """The compact Levenberg–Marquardt solve of the bundled photograph session (one 720 × 480
    raw photograph of the two spheres and a white standard), one start."""
    return _fit_demo(opts, "compact", "photo")


def fit_any_shape(opts: BenchOptions) -> dict[str, Any]:
    """The compact Levenberg–Marquardt solve of the bundled cup-and-torus session (path-traced
    spots outside, inside the cup and the torus's hole, facing each other), one start: the
    preparation holds the meshes' visibility tables and probes (``prepare_s``)."""
    return _fit_demo(opts, "compact", "any_shape")


def fit_demo(opts: BenchOptions) -> dict[str, Any]:
    """The default (compact) Levenberg–Marquardt solve of the bundled session."""
    return _fit_demo(opts, "compact")


def fit_demo_optimistix(opts: BenchOptions) -> dict[str, Any]:
    """The same solve with ``optimistix.LevenbergMarquardt`` (for comparison)."""
    return _fit_demo(opts, "optimistix")


def _fit_process(cache: str, out: str, quick: bool) -> dict[str, Any]:
    """One ``python -m spectral_fit fit`` of the bundled session with its caches in ``cache``:
    wall and CPU seconds of the process and the report's ``timing`` block."""
    import json
    import os
    import resource
    import subprocess
    import sys
    import time

    from ..._runtime.paths import REPO_ROOT
    from ...fitting import DEMO_CONFIG, DEMO_SESSION

    env = dict(os.environ)
    env["SPECTRAL_FIT_CACHE"] = cache
    env["SPECTRAL_FIT_JAX_CACHE"] = os.path.join(cache, "jax")
    env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT), env.get("PYTHONPATH", "")])
    cmd = [sys.executable, "-m", "spectral_fit", "fit", str(DEMO_CONFIG), str(DEMO_SESSION),
           "-o", out]
    if quick:
        cmd += ["--spot-resolution", "4", "--starts", "1", "--no-render"]
    c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, capture_output=True, text=True, env=env, check=True, timeout=1200)
    wall = time.perf_counter() - t0
    c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime)
    with open(os.path.join(out, "fit.json")) as fh:
        timing = json.load(fh)["timing"]
    return {"wall_s": wall, "cpu_s": cpu, "timing": timing}


def fit_cli(opts: BenchOptions) -> dict[str, Any]:
    """``spectral-fit fit`` of the bundled session end to end, first runs on empty caches and
    re-runs on warm ones (fresh processes; see the module docstring)."""
    import os
    import statistics
    import tempfile

    n_first = 1 if opts.quick else max(1, min(opts.repeats, 2))
    n_again = 2 if opts.quick else max(3, min(opts.repeats, 5))
    first, again = [], []
    with tempfile.TemporaryDirectory(prefix="sf_fit_cli_") as tmp:
        for i in range(n_first):
            cache = os.path.join(tmp, f"cache{i}")
            first.append(_fit_process(cache, os.path.join(tmp, f"first{i}"), opts.quick))
        for i in range(n_again):
            again.append(_fit_process(cache, os.path.join(tmp, f"again{i}"), opts.quick))
    walls = [r["wall_s"] for r in again]
    med = statistics.median
    return {
        "median_ms": med(walls) * 1e3, "min_ms": min(walls) * 1e3, "max_ms": max(walls) * 1e3,
        "compile_s": med([r["wall_s"] for r in first]), "n": len(walls),
        "first_run_s": med([r["wall_s"] for r in first]),
        "first_run_cpu_s": med([r["cpu_s"] for r in first]),
        "rerun_s": med(walls), "rerun_cpu_s": med([r["cpu_s"] for r in again]),
        "first_runs": len(first), "first_run_timing": first[-1]["timing"],
        "rerun_timing": again[-1]["timing"],
    }


CASES = {"fit_demo": fit_demo, "fit_demo_optimistix": fit_demo_optimistix, "fit_cli": fit_cli,
         "fit_photo": fit_photo, "fit_any_shape": fit_any_shape}
