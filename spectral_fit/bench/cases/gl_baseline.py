"""Benchmark cases of the OpenGL baseline: ``spectral-fit bench --gl-baseline`` (docs/benchmark.md).

The paper's two-pass pipeline in OpenGL (:mod:`spectral_fit.bench.cases.gl`) on the benchmark
scene (``configs/benchmark.toml``) in the paper's eq. (6): the speed baseline of the frame cases
(``frame_paper`` …, :mod:`spectral_fit.bench.cases.frame`). Its inputs are the JAX renderer's
precomputation (``prepare(scene, mode="paper")``; not timed, reported as ``prepare_s``); the
textures, buffers and programs are made once (``setup_s``). Then, as the frame cases:
``compile_s`` is the first frame (llvmpipe compiles the shaders' machine code at the first draw;
Mesa keeps it in its disk cache, so a second process starts faster), and after two untimed
frames ``median_ms`` / ``min_ms`` / ``max_ms`` of ``n`` frames.

* ``gl_paper``: the full frame with interreflection (pass 1 for both pairs, pass 2, the image
  read back as 8-bit RGB); ``finish_ms``: the same frame waited for with ``glFinish`` instead
  of read back;
* ``gl_paper_none``: without interreflection (no pass 1);
* ``gl_paper_nocull``: ``gl_paper`` with face culling off (every triangle drawn, the depth
  test keeps the nearest; the same image): the OpenGL state of the anchor the project measured
  against before this baseline;
* ``gl_paper_anchor_workload``: ``gl_paper`` doing the work of the external OpenGL
  implementation of the same pipeline that the project measured against before this baseline
  (the same equations, more work per frame): face culling off, 60° pass-1 views (the sender
  covers ~3× the texels), the mip chains of the pass-1 targets built every frame, and pass 2's
  texture lookups on every object fragment. Its image is ``gl_paper``'s up to the pass-1
  texture resolution; its time is what ``gl_paper``'s would be with that implementation's
  workload;
* ``gl_first_frame``: fresh processes (import, EGL context, setup, first frame read back) with
  Mesa's shader cache in a temporary folder: cold (empty cache) and warm (second process).

These cases need the ``gl`` extra (moderngl) and Mesa's EGL; they are not among the default
``spectral-fit bench`` cases. ``--quick`` renders 180×120 with 20 × 20 spheres.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from .._harness import WARMUP, BenchOptions

__all__ = ["GL_CASES", "check_available", "gl_info"]

_ROOT = Path(__file__).resolve().parents[2]
#: the EGL context of this process's cases (made once)
_CONTEXT: list[Any] = []
#: the prepared benchmark scene of this process's cases, by ``quick``
_PREPARED: dict[bool, Any] = {}
#: the baseline inputs of this process's cases, by ``quick`` and pass-1 field of view
_MADE: dict[tuple[bool, float], dict[str, Any]] = {}
#: ``gl_paper_anchor_workload``'s pass-1 field of view (degrees)
ANCHOR_PASS1_FOV_DEG = 60.0


def check_available() -> dict[str, str]:
    """Make (and keep) an EGL context; returns its renderer and version strings.

    Raises:
        GLUnavailable: moderngl or EGL missing (one-line message).
    """
    from .gl import create_context

    if not _CONTEXT:
        _CONTEXT.append(create_context())
    ctx = _CONTEXT[0]
    return {"gl_renderer": str(ctx.info.get("GL_RENDERER", "?")),
            "gl_version": str(ctx.info.get("GL_VERSION", "?"))}


def gl_info() -> dict[str, str]:
    """Renderer, version and moderngl version, for the bench JSON's ``_meta``."""
    info = check_available()
    import moderngl

    return {**info, "moderngl": str(moderngl.__version__)}


def _inputs(opts: BenchOptions, pass1_fov_deg: float = 90.0) -> dict[str, Any]:
    """The benchmark scene prepared in paper mode (once per ``quick``) and its baseline inputs
    for a pass-1 field of view (cached)."""
    if (opts.quick, pass1_fov_deg) in _MADE:
        return _MADE[opts.quick, pass1_fov_deg]
    from ...rendering import prepare
    from .frame import benchmark_scene
    from .gl import baseline_inputs

    check_available()
    t0 = time.perf_counter()
    if opts.quick not in _PREPARED:
        _PREPARED[opts.quick] = prepare(benchmark_scene(quick=opts.quick),
                                        size=(180, 120) if opts.quick else None, mode="paper")
    inputs = baseline_inputs(_PREPARED[opts.quick], pass1_fov_deg=pass1_fov_deg)
    made = {"inputs": inputs, "prepare_s": time.perf_counter() - t0}
    _MADE[opts.quick, pass1_fov_deg] = made
    return made


def _baseline(opts: BenchOptions, *, workload: str = "lean", cull: str | None = None
              ) -> tuple[Any, dict[str, Any]]:
    from .gl import GLBaseline

    if workload == "anchor":
        made = _inputs(opts, ANCHOR_PASS1_FOV_DEG)
        return GLBaseline(made["inputs"], ctx=_CONTEXT[0], cull="none", pass1_mipmaps=True,
                          interreflection_everywhere=True), made
    made = _inputs(opts)
    return GLBaseline(made["inputs"], ctx=_CONTEXT[0], cull=cull), made


def _time_frames(fn: Any, repeats: int) -> dict[str, Any]:
    """``compile_s``: the first call; then WARMUP untimed calls and ``repeats`` timed ones."""
    t0 = time.perf_counter()
    fn()
    first = time.perf_counter() - t0
    for _ in range(WARMUP):
        fn()
    times = []
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return {"median_ms": statistics.median(times), "min_ms": min(times), "max_ms": max(times),
            "compile_s": first, "n": len(times)}


def _case(opts: BenchOptions, *, interreflection: bool, cull: str | None = None,
          workload: str = "lean") -> dict[str, Any]:
    gl, made = _baseline(opts, workload=workload, cull=cull)
    inp = gl.inputs
    out = _time_frames(lambda: gl.render(interreflection), opts.repeats)
    if interreflection:
        fin = _time_frames(lambda: gl.render(interreflection, readback=False), opts.repeats)
        out["finish_ms"] = fin["median_ms"]
    _, obj = gl.render_xyz(interreflection)
    out.update(prepare_s=made["prepare_s"], setup_s=gl.setup_s,
               first_frame_ms=out["compile_s"] * 1e3, size=[inp.shape[1], inp.shape[0]],
               bands=inp.channels, texture_size=inp.texture_size, cull=gl.cull,
               pass1_mipmaps=gl.pass1_mipmaps,
               interreflection_everywhere=gl.interreflection_everywhere,
               interreflection=interreflection, covered_pixels=int((obj >= 0).sum()),
               triangles=int(sum(len(t) for t in inp.triangles)), **gl.info)
    return out


_FIRST = r"""
import json, sys, time
t0 = time.perf_counter()
from spectral_fit.bench.cases.gl import BaselineInputs, GLBaseline, create_context
inputs = BaselineInputs.load(sys.argv[1])
t1 = time.perf_counter()
ctx = create_context()
t2 = time.perf_counter()
gl = GLBaseline(inputs, ctx=ctx)
t3 = time.perf_counter()
gl.render(True)
t4 = time.perf_counter()
print(json.dumps({"import_load_s": t1 - t0, "context_s": t2 - t1, "setup_s": t3 - t2,
                  "first_frame_s": t4 - t3, "total_s": t4 - t1}))
"""


def _fresh(inputs_path: str, cache: str) -> dict[str, Any]:
    env = dict(os.environ)
    env["MESA_SHADER_CACHE_DIR"] = cache  # Mesa ≥ 21
    env["MESA_GLSL_CACHE_DIR"] = cache  # older Mesa
    env.pop("MESA_SHADER_CACHE_DISABLE", None)
    env["PYTHONPATH"] = os.pathsep.join([str(_ROOT), env.get("PYTHONPATH", "")])
    r = subprocess.run([sys.executable, "-c", _FIRST, inputs_path], capture_output=True,
                       text=True, env=env, check=True, timeout=600)
    return json.loads(r.stdout.strip().splitlines()[-1])


def gl_first_frame(opts: BenchOptions) -> dict[str, Any]:
    """Fresh processes: EGL context, setup and first frame (read back), Mesa's shader cache
    cold (an empty temporary folder) then warm (the same folder)."""
    made = _inputs(opts)
    with tempfile.TemporaryDirectory(prefix="sf_gl_") as tmp:
        path = os.path.join(tmp, "inputs.npz")
        made["inputs"].save(path)
        cache = os.path.join(tmp, "mesa_cache")
        os.makedirs(cache)
        cold = _fresh(path, cache)
        warm = _fresh(path, cache)
    ms = cold["total_s"] * 1e3
    return {"median_ms": ms, "min_ms": ms, "max_ms": ms, "compile_s": cold["first_frame_s"],
            "n": 1, "first_frame_cold_s": cold["first_frame_s"],
            "first_frame_warm_s": warm["first_frame_s"],
            "context_setup_first_frame_cold_s": cold["total_s"],
            "context_setup_first_frame_warm_s": warm["total_s"], "cold": cold, "warm": warm}


GL_CASES = {
    "gl_paper": lambda o: _case(o, interreflection=True),
    "gl_paper_none": lambda o: _case(o, interreflection=False),
    "gl_paper_nocull": lambda o: _case(o, interreflection=True, cull="none"),
    "gl_paper_anchor_workload": lambda o: _case(o, interreflection=True, workload="anchor"),
    "gl_first_frame": gl_first_frame,
}
