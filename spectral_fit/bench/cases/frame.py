"""Benchmark cases of whole frames (docs/benchmark.md "paper" scene, ``configs/benchmark.toml``).

Every case prepares the scene once (not timed; reported as ``prepare_s``), then times the
jit-compiled :func:`~spectral_fit.rendering.render_frame` (visibility, G-buffer, shading of the
covered pixels, interreflection, background, XYZ, display encoding): ``compile_s`` is the first
call, ``median_ms`` the steady state.

* ``frame_paper``: 720×480, 31 bands (400–700 nm, the anchor's), gather interreflection with
  the config's 2 bounces; ``frame_paper_b1``: one bounce, the anchor's work (eq. 6's two passes
  carry one bounce; gather's interreflection regions ΔE00 median 0.25, p90 0.86 against the
  path tracer, 0.23 / 0.32 with 2 bounces); ``frame_paper_none`` / ``frame_paper_paper``:
  without interreflection / eq. (6) literally;
* ``frame_paper_81``: 81 bands (400–700 nm at 3.75 nm); ``frame_paper_k8``: K = 8 basis;
* ``frame_paper_lens``: the same frame through a distorting lens (``LENS``: the vertices
  distorted, each pixel's background ray from the lens's inverse; docs/rendering.md "Lens
  distortion");
* ``frame_closeup``: the spheres at z = −0.100 m (~19 % coverage), gather;
  ``frame_closeup_none``: the same without interreflection;
* ``frame_any_shape``: ``configs/any_shape.toml`` (a cup and a torus, ~5,000 triangles each,
  ~9,600 covered pixels, the benchmark's camera, environment and 31 bands), gather: the general
  path with both objects' self-visibility (``prepare_s`` includes its precomputation);
  ``frame_any_shape_plain``: the same scene prepared with ``occlusion=False``;
* ``frame_table``: ``configs/on_table.toml`` (the spheres and a cup on a table plane): the
  frame, the table's layer and one placement's precomputation (:func:`frame_table`);
* ``cold_start_s``: fresh Python processes (import + prepare + compile + first frame of the
  paper scene) with caches in a temporary folder: first run (cold caches) and second run (warm
  caches), for the cached path of :mod:`spectral_fit.rendering` (the headline figures) and for
  plain ``prepare`` + ``render_frame`` with JAX's persistent cache only; import time reported
  separately, CPU times beside wall times. The processes keep freed memory as the
  ``spectral-fit`` command does (:func:`~spectral_fit._runtime.process.retain_freed_memory`).

``--quick`` (harness smoke test) renders one small configuration for every frame case and runs
two fresh processes (cold, warm) of the cached path for the cold start.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import tempfile
from typing import Any

from ..._runtime.paths import REPO_ROOT
from .._harness import BenchOptions, measure

ROOT = REPO_ROOT
CONFIG = ROOT / "configs" / "benchmark.toml"
ANY_SHAPE = ROOT / "configs" / "any_shape.toml"
ON_TABLE = ROOT / "configs" / "on_table.toml"

__all__ = ["CASES", "benchmark_scene"]


#: ``frame_paper_lens``' camera distortion (OpenCV k1, k2, p1, p2, k3): the bundled
#: ``configs/live_sample.toml`` camera's, a typical webcam's barrel distortion
LENS = (-0.11, 0.045, 0.0008, -0.0004, 0.0)


def benchmark_scene(*, z: float = -0.275, quick: bool = False, step_nm: float | None = None,
                    distortion: tuple[float, ...] | None = None, bounces: int | None = None):
    """The benchmark Scene with sphere centres at depth ``z`` (m); quick: 20×20 spheres;
    ``distortion``: the camera's lens (OpenCV coefficients) instead of a pinhole;
    ``bounces``: the interreflection's bounces instead of the config's (2)."""
    from ...io import load_scene

    scene = load_scene(CONFIG)
    objs = []
    for o in scene.objects:
        kw: dict[str, Any] = {"position": (o.position[0], o.position[1], z)}
        if quick:
            kw.update(stacks=20, slices=20)
        objs.append(dataclasses.replace(o, **kw))
    changes: dict[str, Any] = {"objects": tuple(objs)}
    if distortion is not None:
        changes["camera"] = dataclasses.replace(scene.camera, distortion=tuple(distortion))
    if bounces is not None:
        changes["interreflection"] = dataclasses.replace(scene.interreflection,
                                                         bounces=int(bounces))
    if step_nm is not None:
        from ...color import resample

        spectral = dataclasses.replace(scene.spectral, step_nm=step_nm)
        wl = spectral.wavelengths()
        objs = [dataclasses.replace(o, material=dataclasses.replace(
            o.material, reflectance=resample(scene.wavelengths, o.material.reflectance, wl)))
            for o in changes["objects"]]
        changes.update(spectral=spectral, objects=tuple(objs))
    return scene.replace(**changes)


def _case(opts: BenchOptions, *, mode: str = "gather", z: float = -0.275,
          step_nm: float | None = None, spectral_mode: str | None = None,
          k: int | None = None, distortion: tuple[float, ...] | None = None,
          bounces: int | None = None) -> dict[str, Any]:
    import time

    import jax

    from ...rendering import prepare, render_frame

    if opts.quick:  # harness smoke test: one small configuration shared by the variants
        mode, z, step_nm, spectral_mode, k = "none", -0.275, None, None, None
        distortion = bounces = None
    scene = benchmark_scene(z=z, quick=opts.quick, step_nm=step_nm, distortion=distortion,
                            bounces=bounces)
    size = (180, 120) if opts.quick else None
    if not opts.quick:
        jax.clear_caches()
    t0 = time.perf_counter()
    prep = prepare(scene, size=size, mode=mode, spectral_mode=spectral_mode, k=k)
    prepare_s = time.perf_counter() - t0
    out = measure(lambda: render_frame(prep).rgb, repeats=opts.repeats)
    f = render_frame(prep)
    out.update(prepare_s=prepare_s, mode=mode, channels=prep.channels,
               size=[prep.camera.shape[1], prep.camera.shape[0]],
               covered_pixels=int(f.stats["covered_pixels"]),
               pixel_capacity=prep.buffers.pixel_capacity,
               overflow=bool(f.stats["pixel_overflow"] | f.stats["raster_overflow"]
                             | f.stats["interreflection_overflow"]))
    return out


_COLD = r"""
import json, os, sys, time
def cpu():  # this process and its finished children (render_frame_cached's compiling child)
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system
t0, c0 = time.perf_counter(), cpu()
import jax
from spectral_fit._runtime import process as process
from spectral_fit.rendering import (CACHE_STATS, enable_compilation_cache, prepare,
                                    prepare_cached, render_frame, render_frame_cached)
t1, c1 = time.perf_counter(), cpu()
process.retain_freed_memory()  # as the spectral-fit command does for every subcommand
enable_compilation_cache(sys.argv[3])
size = None if sys.argv[2] == "full" else (180, 120)
if sys.argv[4] == "cached":
    prep = prepare_cached(sys.argv[1], size=size)
else:
    prep = prepare(sys.argv[1], size=size)
t2, c2 = time.perf_counter(), cpu()
if sys.argv[4] == "cached":
    jax.block_until_ready(render_frame_cached(prep).rgb)
else:
    jax.block_until_ready(render_frame(prep).rgb)
t3, c3 = time.perf_counter(), cpu()
print(json.dumps({"import_s": t1 - t0, "prepare_s": t2 - t1, "first_frame_s": t3 - t2,
                  "total_s": t3 - t0, "import_cpu_s": c1 - c0, "prepare_cpu_s": c2 - c1,
                  "first_frame_cpu_s": c3 - c2, "caches": CACHE_STATS}))
"""


def _fresh_process(cache: str, quick: bool, path: str) -> dict[str, Any]:
    """One fresh process: import, prepare, first frame; ``path`` "plain" (prepare +
    render_frame, JAX's persistent cache in ``cache``/jax) or "cached" (spectral_fit.rendering's
    prepared-scene and program caches in ``cache`` as well)."""
    env = dict(os.environ)
    env["SPECTRAL_FIT_CACHE"] = cache
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    r = subprocess.run([sys.executable, "-c", _COLD, str(CONFIG), "quick" if quick else "full",
                        os.path.join(cache, "jax"), path],
                       capture_output=True, text=True, env=env, check=True, timeout=900)
    out = json.loads(r.stdout.strip().splitlines()[-1])
    out["first_frame_after_import_s"] = out["prepare_s"] + out["first_frame_s"]
    out["first_frame_after_import_cpu_s"] = out["prepare_cpu_s"] + out["first_frame_cpu_s"]
    return out


def cold_start_s(opts: BenchOptions) -> dict[str, Any]:
    """Fresh processes rendering the paper scene's first frame: cold then warm caches, for the
    cached path (``spectral_fit.rendering``: prepared scene, compiled program and JAX's
    persistent cache, as the CLI uses) and the plain path (``prepare`` + ``render_frame`` with
    JAX's persistent cache only: a warm cache still traces and lowers the frame)."""
    runs: dict[str, dict[str, Any]] = {}
    for path in ("cached", "plain"):
        with tempfile.TemporaryDirectory(prefix="sf_cache_") as cache:
            runs[f"{path}_cold"] = _fresh_process(cache, opts.quick, path)
            runs[f"{path}_warm"] = _fresh_process(cache, opts.quick, path)
        if opts.quick:
            break
    cold, warm = runs["cached_cold"], runs["cached_warm"]
    out: dict[str, Any] = {
        "median_ms": cold["total_s"] * 1e3, "min_ms": cold["total_s"] * 1e3,
        "max_ms": cold["total_s"] * 1e3, "compile_s": cold["first_frame_s"], "n": 1,
        "import_s": warm["import_s"],
        "first_frame_after_import_cold_s": cold["first_frame_after_import_s"],
        "first_frame_after_import_warm_s": warm["first_frame_after_import_s"],
        "first_frame_after_import_cold_cpu_s": cold["first_frame_after_import_cpu_s"],
        "first_frame_after_import_warm_cpu_s": warm["first_frame_after_import_cpu_s"],
    }
    for name, r in runs.items():
        out[name] = r
    return out


def _any_shape_case(opts: BenchOptions, *, occlusion: bool) -> dict[str, Any]:
    import time

    import jax

    from ...rendering import prepare, render_frame

    if not opts.quick:
        jax.clear_caches()
    size = (180, 120) if opts.quick else None
    t0 = time.perf_counter()
    prep = prepare(ANY_SHAPE, size=size, mode="none" if opts.quick else "gather",
                   occlusion=occlusion, occlusion_resolution=8 if opts.quick else 24)
    prepare_s = time.perf_counter() - t0
    out = measure(lambda: render_frame(prep).rgb, repeats=opts.repeats)
    f = render_frame(prep)
    out.update(prepare_s=prepare_s, occlusion=occlusion,
               size=[prep.camera.shape[1], prep.camera.shape[0]],
               covered_pixels=int(f.stats["covered_pixels"]),
               triangles=int(prep.mesh.triangles.shape[0]))
    return out


def frame_any_shape(opts: BenchOptions) -> dict[str, Any]:
    return _any_shape_case(opts, occlusion=True)


def frame_any_shape_plain(opts: BenchOptions) -> dict[str, Any]:
    return _any_shape_case(opts, occlusion=False)


def frame_table(opts: BenchOptions) -> dict[str, Any]:
    """``configs/on_table.toml`` (the benchmark's spheres and a cup on a table plane): the
    frame (``median_ms``, ``compile_s``), the table's layer with the objects' shadows and
    light drawn into it (``surface_ms`` / ``surface_compile_s``: textures from the materials
    and the per-pixel lookup, jit-compiled), and one placement's precomputation
    (``surface_build_ms``: the projected rasters and the hits, median of 3)."""
    import time

    import jax

    from ...io import load_scene
    from ...rendering import prepare, render_frame, surface_layer, surface_transfer

    if not opts.quick:
        jax.clear_caches()
    size = (180, 120) if opts.quick else None
    t0 = time.perf_counter()
    prep = prepare(ON_TABLE, size=size, mode="none" if opts.quick else "gather",
                   occlusion_resolution=8 if opts.quick else 24)
    prepare_s = time.perf_counter() - t0
    out = measure(lambda: render_frame(prep).rgb, repeats=opts.repeats)
    import equinox as eqx

    layer = eqx.filter_jit(lambda p: surface_layer(p).radiance)
    lay = measure(lambda: layer(prep), repeats=opts.repeats)
    scene = load_scene(ON_TABLE)
    builds = []
    for _ in range(1 if opts.quick else 3):
        t0 = time.perf_counter()
        jax.block_until_ready(surface_transfer(scene.surfaces, prep.lighting.env,
                                               prep.ir_mesh, prep.model))
        builds.append((time.perf_counter() - t0) * 1e3)
    st = prep.surfaces[0]
    out.update(prepare_s=prepare_s, surface_ms=lay["median_ms"],
               surface_compile_s=lay["compile_s"], surface_build_ms=sorted(builds)[
                   len(builds) // 2], surface_texels=st.resolution ** 2,
               surface_hits=int(st.hit_texel.shape[0]),
               size=[prep.camera.shape[1], prep.camera.shape[0]])
    return out


def frame_paper(opts: BenchOptions) -> dict[str, Any]:
    return _case(opts, mode="gather")


def frame_paper_b1(opts: BenchOptions) -> dict[str, Any]:
    return _case(opts, mode="gather", bounces=1)


def frame_paper_none(opts: BenchOptions) -> dict[str, Any]:
    return _case(opts, mode="none")


def frame_paper_paper(opts: BenchOptions) -> dict[str, Any]:
    return _case(opts, mode="paper")


def frame_paper_81(opts: BenchOptions) -> dict[str, Any]:
    return _case(opts, mode="gather", step_nm=3.75)


def frame_paper_k8(opts: BenchOptions) -> dict[str, Any]:
    return _case(opts, mode="gather", spectral_mode="basis", k=8)


def frame_paper_lens(opts: BenchOptions) -> dict[str, Any]:
    return _case(opts, mode="gather", distortion=LENS)


def frame_closeup(opts: BenchOptions) -> dict[str, Any]:
    return _case(opts, mode="gather", z=-0.100)


def frame_closeup_none(opts: BenchOptions) -> dict[str, Any]:
    return _case(opts, mode="none", z=-0.100)


CASES = {
    "frame_paper": frame_paper,
    "frame_paper_b1": frame_paper_b1,
    "frame_paper_none": frame_paper_none,
    "frame_paper_paper": frame_paper_paper,
    "frame_paper_81": frame_paper_81,
    "frame_paper_k8": frame_paper_k8,
    "frame_paper_lens": frame_paper_lens,
    "frame_closeup": frame_closeup,
    "frame_closeup_none": frame_closeup_none,
    "frame_any_shape": frame_any_shape,
    "frame_any_shape_plain": frame_any_shape_plain,
    "frame_table": frame_table,
    "cold_start_s": cold_start_s,
}
