"""Benchmark of measurement planning (``planning``): the bundled two-sphere scene, 2,000
candidate readings (``quick``: 256), 10 unknowns (α, β, χ, μ, n of both spheres), 8 parameter
draws, K = 10 readings chosen.

Timed: each candidate's Jacobian (all 81 bands, ``jax.jacfwd`` through the fit's radiance
cache, one compiled program for every chunk of 256 candidates and every draw), its aiming
gradient and Fisher information, and the greedy + exchange choice
(:func:`~spectral_fit.fitting.candidate_information`,
:func:`~spectral_fit.fitting.select_readings`). ``compile_s`` is the first call (trace +
compile + run: the cold figure), ``median_ms`` the steady state (warm). The preparation
before (the candidates' central rays and aiming margins, their fields ray-cast and their
radiance caches, NumPy) is reported as ``prepare_s``; it does not depend on the parameters.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from .._harness import BenchOptions, measure


def planning(opts: BenchOptions) -> dict[str, Any]:
    """Sensitivities and the choice of 10 of 2,000 candidates at 8 parameter draws."""
    import warnings

    from ...fitting import (
        DEMO_CONFIG,
        PARAMETERS,
        Region,
        candidate_information,
        default_range,
        draws_in_box,
        plan_candidates,
        prepare_candidates,
        scene_environment,
        scene_geometry,
        select_readings,
    )
    from ...io import load_scene

    n_cand = 256 if opts.quick else 2000
    scene = load_scene(DEMO_CONFIG)
    t0, c0 = time.perf_counter(), time.process_time()
    env = scene_environment(scene, compress_tol=3e-3)
    geoms = scene_geometry(scene)
    region = Region(elevation_steps=5, azimuth_steps=9, aims_per_object=48)
    cands = plan_candidates(scene, region, geoms, margin_m=2e-3)
    distinct = min(len(cands), n_cand)
    cands = (cands * (n_cand // len(cands) + 1))[:n_cand]  # (repeated if the region gives fewer)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        preps = prepare_candidates(scene, cands, spot_resolution=4, env=env, geometries=geoms)
    prepare_s, prepare_cpu_s = time.perf_counter() - t0, time.process_time() - c0
    O = len(scene.objects)
    free = tuple((o, k) for o in range(O) for k in range(5))
    vals0 = np.array([[float(getattr(o.material, p)) for p in PARAMETERS]
                      for o in scene.objects])
    centre = np.array([vals0[o, k] for o, k in free])
    rng = [default_range(PARAMETERS[k], vals0[o, k]) for o, k in free]
    y = draws_in_box(centre, np.array([a for a, _ in rng]), np.array([b for _, b in rng]),
                     n=8, seed=0)
    values = np.repeat(vals0[None], 8, 0)
    for j, (o, k) in enumerate(free):
        values[:, o, k] = y[:, j]
    cpu: dict[str, float] = {}
    chosen: dict[str, Any] = {}

    def run() -> Any:
        c = time.process_time()
        info = candidate_information(scene, cands, values, free=free, spot_resolution=4,
                                     prepared=preps)
        idx, obj = select_readings(info["information"], 10)
        cpu.setdefault("first", time.process_time() - c)
        chosen.update(idx=idx, objective=obj)
        return obj

    out = measure(run, repeats=max(3, min(opts.repeats, 5)))
    out.update(candidates=len(cands), distinct_candidates=distinct, unknowns=len(free), draws=8,
               budget=10,
               bands=int(scene.wavelengths.size), chunks=len(preps),
               compile_cpu_s=cpu["first"], prepare_s=prepare_s, prepare_cpu_s=prepare_cpu_s,
               worst_stderr_tolerances=float(np.sqrt(chosen["objective"])),
               targets={"cold_s": 60.0, "warm_s": 10.0})
    return out


CASES = {"planning": planning}
