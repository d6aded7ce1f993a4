"""Benchmark cases ``raster_paper`` and ``raster_closeup`` (docs/benchmark.md).

720×480, 90° vertical FOV, near 0.01, far 1000, camera at the origin looking down −Z; two UV
spheres of radius 0.0375 m (100 stacks × 100 slices, 19,800 triangles each) centred at
(∓0.045, 0, z) with z = −0.275 (paper) or −0.100 (close-up). Times the jitted rasteriser on
precomputed clip coordinates (visibility + barycentrics + depth), no culling, with capacities
planned on the pose (headroom 1.5). Extra figures: ``covered_pixels``, ``first_call_s`` (the
public ``rasterize`` in a fresh cache: plan + compile + run), ``lower_s`` / ``xla_compile_s``
(the compile split into tracing + lowering and XLA) and ``compile_cpu_s`` (CPU seconds of
both, robust to other processes' load; these three not with ``--quick``), the ladder,
capacities and the windows/blocks each pose needed.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from .._harness import BenchOptions, measure

__all__ = ["CASES", "scene_clip"]


def scene_clip(z: float, *, quick: bool = False):
    """Clip coordinates (V, 4), triangles (T, 3) and (H, W) of the benchmark scene."""
    import jax.numpy as jnp

    from ...geometry import perspective_camera, project
    from ...io import concat_meshes, translate, uv_sphere

    n = 20 if quick else 100
    h, w = (120, 180) if quick else (480, 720)
    s = uv_sphere(0.0375, n, n)
    both, _ = concat_meshes([s.transformed(translate((-0.045, 0.0, z))),
                             s.transformed(translate((0.045, 0.0, z)))])
    cam = perspective_camera((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), fov_y_deg=90.0, aspect=w / h,
                             near=0.01, far=1000.0)
    return project(cam, both.vertices), jnp.asarray(both.triangles), (h, w)


def _compile_split(clip, tris, shape, cfg) -> dict[str, float]:
    """The compile alone, split into tracing + lowering and XLA's compilation, with the CPU
    seconds this process spent on both (all its threads): on a shared machine the wall time
    also counts the other processes' load, the CPU time does not."""
    import jax

    from ...geometry import raster_jit

    jax.clear_caches()
    t0, c0 = time.perf_counter(), time.process_time()
    lowered = jax.jit(lambda c, t: raster_jit(c, t, shape=shape, cull="none",
                                               config=cfg)).lower(clip, tris)
    t1 = time.perf_counter()
    lowered.compile()
    t2, c2 = time.perf_counter(), time.process_time()
    return {"lower_s": t1 - t0, "xla_compile_s": t2 - t1, "compile_cpu_s": c2 - c0}


def _case(z: float, opts: BenchOptions) -> dict[str, Any]:
    import jax

    from ...geometry import clear_plans, plan_config, raster_jit, rasterize

    clip, tris, shape = scene_clip(z, quick=opts.quick)
    # first call of the public entry point in a fresh cache: plan (NumPy, no compile)
    # + compile + one run: the latency a user sees once per (T, frame size, cull)
    jax.clear_caches()
    clear_plans()
    t0 = time.perf_counter()
    jax.block_until_ready(rasterize(clip, tris, shape))
    first_call_s = time.perf_counter() - t0
    cfg = plan_config(clip, tris, shape)  # capacities sized up front (not timed)
    jax.clear_caches()
    fn = jax.jit(lambda c, t: raster_jit(c, t, shape=shape, cull="none", config=cfg))
    out = measure(fn, clip, tris, repeats=opts.repeats)
    r = fn(clip, tris)
    if not opts.quick:  # (one more compile: left out of the quick smoke run)
        out.update(_compile_split(clip, tris, shape, cfg))
    out["first_call_s"] = first_call_s
    out["covered_pixels"] = int(np.sum(np.asarray(r.tri_id) >= 0))
    out["triangles"] = int(tris.shape[0])
    out["frame"] = list(shape)
    out["tile_sizes"] = list(cfg.tile_sizes)
    out["capacities"] = [*cfg.capacities, cfg.block_capacity]
    out["needed"] = np.asarray(r.needed).tolist()
    out["overflow"] = bool(r.overflow)
    return out


def raster_paper(opts: BenchOptions) -> dict[str, Any]:
    return _case(-0.275, opts)


def raster_closeup(opts: BenchOptions) -> dict[str, Any]:
    return _case(-0.100, opts)


CASES = {"raster_paper": raster_paper, "raster_closeup": raster_closeup}
