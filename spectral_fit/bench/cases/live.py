"""Benchmark case ``live_paper``: the live mixed-reality loop on the bundled sample video.

Scene: ``configs/live_sample.toml``, the paper's two 75 mm spheres (UV 100×100, 19,800
triangles each; ColorChecker N Ohta yellow and red; α = β = 1, μ = 0.1, n = 1.5) on two 80 mm
ArUco markers, interreflection "gather", 31 bands (400–700 nm), 720×480, seen at 0.29–0.34 m
by the sample video's camera (fx = 560 px, a 46° vertical field of view): ~18,000–22,000
covered pixels, 2.6–3.1× the 6,944 of the paper scene (docs/benchmark.md; 90° vertical field of
view, spheres at 0.275 m). Video: ``measurements/video/sample.mp4``.

Figures:

* ``median_ms`` / ``min_ms`` / ``max_ms`` / ``compile_s``: RENDER-ONLY, the compiled step
  (render with interreflection → camera RGB → composite over the frame) at the first frame's
  poses, blocking on the result (``compile_s``: the first frame, planning and compilation).
  The session runs with its default ``ir_reuse_mm`` (0.5 mm): at fixed poses every call
  after the first reuses the interreflection's camera-independent half, and in the video
  runs below it is computed again whenever an object moved more than 0.5 mm
  (``interreflection_senders``: how often it was computed and reused);
* ``end_to_end_median_ms`` / ``end_to_end_fps``: the whole loop, one stage after the other
  (``LiveSession.run(threads=False)``): decode, detect markers, track, undistort, render,
  composite, encode (MPEG-4 into a temporary file), median frame interval over
  ``n_end_to_end`` frames after the first; ``stages_ms``: each stage's median there;
* ``end_to_end_pipelined_median_ms`` / ``_fps``: the same frames with the stages overlapped
  by threads (``run(threads=True)``, the ``live`` command's default): reader (decode, detect,
  undistort) ‖ render ‖ writer (encode); ``stages_pipelined_ms``: per stage there (stages
  running side by side share the CPU, so each may take longer than alone);
* ``non_render_ms``: sequential end-to-end minus render (what the overlap can hide);
* ``render_fps``, ``covered_pixels``, ``pixel_capacity``, ``recompiles`` (must stay 0),
  ``replans_ahead`` (buffers grown in the background; 0 on the bundled videos);
* ``benchmark_scene``: RENDER-ONLY on the benchmark's paper scene itself (its camera, poses and
  capacities, ``benchmark_scene()`` of :mod:`.frame`), the same compiled live step (render
  with interreflection → the sample camera's RGB → composite over the first video frame):
  ``median_ms``, ``min_ms``, ``render_fps``, ``compile_s``, ``covered_pixels`` (the issue's
  "benchmark scene" render-only figure, every frame computing its whole interreflection;
  the sample video's own scene is the larger one above); ``objects_static``: the same step
  reusing the interreflection's camera-independent half (objects that stay put while the
  camera moves; ``renderer.render_senders``), and ``senders_ms``: that half alone;
  ``end_to_end``: the whole loop on the benchmark scene as a live scene
  (``configs/live_benchmark.toml`` on ``measurements/video/benchmark.mp4``: the benchmark's
  camera, spheres, materials, environment and two-bounce interreflection, the spheres on
  markers, the camera 0.275 m from them looking down at 40–50°; ~7,000 covered pixels like
  the benchmark frame), the same fields as the sample video's above (``compile_s``: its first
  frame; ``covered_pixels``: its last).

``live_paper_none``: the same without interreflection (the frame program and the live stages
alone).

``live_in_flight``: two frames in flight, in a fresh process whose CPU is split into two JAX
devices (:func:`~spectral_fit._runtime.process.split_cpu_devices`; the split slows a lone frame by a
few per cent, so the other cases run without it). Frame i runs on device i mod 2, at most two
are dispatched and not yet finished; ``frame_interval_ms`` is the median over means of two
consecutive intervals between finished frames (throughput: frames in flight finish in bunches),
``one_at_a_time_ms`` the same step one frame at a time on one device of that process (latency):

* ``benchmark_scene`` / ``benchmark_scene.objects_static``: the live step on the benchmark
  scene computing its interreflection every frame / reusing the senders' half (as in
  ``live_paper``); the case's ``median_ms`` / ``min_ms`` / ``max_ms`` / ``render_fps`` are
  the static step's frame intervals (the step computing everything where there is no
  senders' half: ``--quick`` renders without interreflection);
* ``end_to_end``: :meth:`~spectral_fit.live.LiveSession.run` without threads on the sample
  video, ``in_flight`` 1 and 2 (``LiveSession(devices=both)``), frame interval as
  :meth:`~spectral_fit.live.RunStats.medians_ms` takes it;
  ``benchmark_scene.end_to_end``: the same on the benchmark video (``live_paper`` above).

CPU backend only (elsewhere the case reports ``skipped``).

``--quick``: frames at a third of the size (240×160, intrinsics scaled), interreflection
"none", K = 8 basis, 3 end-to-end frames (figures not comparable).
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from ..._runtime.paths import REPO_ROOT
from .._harness import BenchOptions, measure

__all__ = ["CASES"]

ROOT = REPO_ROOT
CONFIG = ROOT / "configs" / "live_sample.toml"
VIDEO = ROOT / "measurements" / "video" / "sample.mp4"
BENCH_CONFIG = ROOT / "configs" / "live_benchmark.toml"
BENCH_VIDEO = ROOT / "measurements" / "video" / "benchmark.mp4"


def live_paper(opts: BenchOptions) -> dict[str, Any]:
    return _live(opts)


def live_paper_none(opts: BenchOptions) -> dict[str, Any]:
    """``live_paper`` without interreflection (the frame program and the live stages alone)."""
    return _live(opts, mode="none")


def live_table(opts: BenchOptions) -> dict[str, Any]:
    """``live_paper`` with the table under the markers as a real surface (``TABLE``: the world
    marker's plane, grey ρ = 0.3): the step also puts the spheres' shadows and light into the
    video; ``surface_shadow_builds``: how often the table's textures were built (once per
    placement of the spheres; ``surface_build_ms``: one build). Compare its ``median_ms`` and
    ``end_to_end_median_ms`` with ``live_paper``'s of the same run."""
    return _live(opts, table=True)


#: ``live_table``'s surface: the world marker's plane (the table), a mid-grey reflectance
TABLE = {"name": "table", "point": [0.0, 0.0, 0.0], "normal": [0.0, 1.0, 0.0],
         "reflectance": 0.3}


def _live(opts: BenchOptions, mode: str | None = None, *, table: bool = False
          ) -> dict[str, Any]:
    import jax

    from ..._runtime.errors import InputError
    from ...io import load_scene
    from ...live import LiveSession, VideoSource

    for path in (CONFIG, VIDEO, BENCH_CONFIG, BENCH_VIDEO):
        if not path.is_file():
            raise InputError("live_paper needs the repository's configs/ and "
                             "measurements/video/", path=path)
    scene = load_scene(CONFIG)
    if table:
        import tomllib

        from ...io import parse_scene

        data = tomllib.loads(CONFIG.read_text())
        data["surfaces"] = [TABLE]
        scene = parse_scene(data, path=CONFIG)
    extra: dict[str, Any] = {} if mode is None else {"mode": mode}
    if opts.quick:
        extra = {"mode": "none", "spectral_mode": "basis", "k": 8}
    n_e2e = 3 if opts.quick else max(2, min(opts.repeats, 12))
    with VideoSource(VIDEO, field="video") as src:
        div = 3 if opts.quick else 1
        size = (src.height // div, src.width // div)
        stream = _frames(src, size)
        first = next(stream)
        session = LiveSession(scene, size=size, **extra)
        t0 = time.perf_counter()
        session.process(first)  # plans buffers on the first poses, compiles
        first_frame_s = time.perf_counter() - t0
        poses = session.last_poses
        bg = session.undistort(first)

        def step():
            return session.render(poses, bg)[0]

        out = measure(step, repeats=opts.repeats)
        out["compile_s"] = first_frame_s  # the first frame: planning + compilation + render
        if table:
            t0 = time.perf_counter()
            jax.block_until_ready(session.surface_textures_for(poses, rebuild=True))
            out["surface_build_ms"] = (time.perf_counter() - t0) * 1e3
        else:
            out["benchmark_scene"] = _benchmark_scene_step(session, bg, quick=opts.quick,
                                                           repeats=3 if opts.quick else 20)
        out.update(_end_to_end(session, stream, n_e2e))
        if table:
            out["surface_shadow_builds"] = int(session.surface_builds)
        else:
            out["benchmark_scene"]["end_to_end"] = _benchmark_video(size, n_e2e, extra)
    jax.block_until_ready(step())
    out.update({
        "render_fps": 1e3 / out["median_ms"],
        "covered_pixels": _covered_pixels(session),
        "pixel_capacity": list(session.prep.buffers.pixel_capacity),
        "size": [int(x) for x in session.size],
        "mode": extra.get("mode", scene.interreflection.mode),
    })
    return out


def _end_to_end(session: Any, stream: Any, n: int) -> dict[str, Any]:
    """The live loop on ``n`` + 1 frames of ``stream`` one stage after the other, then on the
    next ``n`` + 1 with the stages overlapped by threads (``run(threads=...)``, one frame in
    flight); medians over every frame after the first (which also waits for the pipeline to
    fill). Frames are encoded as MPEG-4 into a temporary file."""
    from ...live import VideoSink

    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for threads in (False, True):
            with VideoSink(Path(tmp) / f"out{int(threads)}.mp4", fps=25.0,
                           size=session.size) as sink:
                runs[threads] = session.run(stream, sink.write, threads=threads,
                                            max_frames=n + 1, in_flight=1)

    def stage_medians(st) -> dict[str, float | None]:
        vals = {}
        for name in ("decode", "detect", "undistort", "render", "encode", "interval"):
            xs = getattr(st, name)[1:]
            vals[name] = statistics.median(xs) * 1e3 if xs else None
        return vals

    seq, piped = stage_medians(runs[False]), stage_medians(runs[True])
    e2e, e2e_p = seq.pop("interval"), piped.pop("interval")
    return {
        "end_to_end_median_ms": e2e,
        "end_to_end_fps": 1e3 / e2e if e2e else None,
        "n_end_to_end": runs[False].frames - 1,
        "stages_ms": seq,
        "non_render_ms": e2e - seq["render"] if e2e and seq["render"] else None,
        "end_to_end_pipelined_median_ms": e2e_p,
        "end_to_end_pipelined_fps": 1e3 / e2e_p if e2e_p else None,
        "stages_pipelined_ms": piped,
        "recompiles": int(session.recompiles),
        "replans_ahead": int(session.replans_ahead),
        "interreflection_senders": {"computed": int(session.ir_updates),
                                    "reused": int(session.ir_reuses),
                                    "reuse_mm": session.ir_reuse_mm},
    }


def _benchmark_video(size: tuple[int, int], n: int, extra: dict[str, Any]) -> dict[str, Any]:
    """``_end_to_end`` (``n`` frames) on the benchmark scene as a live scene
    (``configs/live_benchmark.toml`` on ``measurements/video/benchmark.mp4``, frames resized to
    ``size`` (H, W) when needed; session options ``extra``), after a first frame that plans and
    compiles (``compile_s``); ``covered_pixels``: the last frame's."""
    from ...io import load_scene
    from ...live import LiveSession, VideoSource

    with VideoSource(BENCH_VIDEO, field="video") as src:
        stream = _frames(src, size)
        session = LiveSession(load_scene(BENCH_CONFIG), size=size, **extra)
        t0 = time.perf_counter()
        session.process(next(stream))
        out: dict[str, Any] = {"compile_s": time.perf_counter() - t0}
        out.update(_end_to_end(session, stream, n))
    out["covered_pixels"] = _covered_pixels(session)
    out["pixel_capacity"] = list(session.prep.buffers.pixel_capacity)
    return out


def _covered_pixels(session: Any) -> int:
    """Pixels covered by an object in ``session``'s last frame."""
    return int((session.last_object_id >= 0).sum())


def _frames(src: Any, size: tuple[int, int]) -> Any:
    """The frames of ``src`` (a :class:`~spectral_fit.live.VideoSource`), resized to
    ``size`` (H, W) when they are not that size already."""
    while (f := src.read()) is not None:
        if f.shape[:2] != tuple(size):
            import cv2

            f = cv2.resize(f, (size[1], size[0]), interpolation=cv2.INTER_AREA)
        yield f


def _benchmark_scene_inputs(session: Any, background: Any, *, quick: bool = False
                            ) -> tuple[Any, ...]:
    """(prep, materials, model, view, visible, background, camera, mirror): the live step's
    arguments for the benchmark's paper scene at the session's frame size, in its camera RGB
    and with its renderer options, composited over ``background``. ``quick``: 20×20
    spheres."""
    import jax.numpy as jnp

    from ...live import camera_output_matrix
    from ...rendering import all_visible, mirror_needed, prepare, with_output
    from .frame import benchmark_scene

    h, w = session.size
    prep = prepare(benchmark_scene(quick=quick), size=(w, h), **session._options)
    prep = with_output(prep, camera_output_matrix(prep, session.camera))
    return (prep, prep.materials, prep.model, prep.camera.view, all_visible(prep.num_objects),
            jnp.asarray(background), session.camera, mirror_needed(prep.materials))


def _benchmark_scene_step(session: Any, background: Any, *, quick: bool = False,
                          repeats: int = 20) -> dict[str, Any]:
    """The compiled live step on the benchmark's paper scene (camera, poses, capacities
    planned for it) at the video's frame size (720×480, the scene's own, for the sample
    video), composited over ``background`` (an undistorted video frame), in the session's
    camera RGB and with its renderer options. ``quick``: 20×20 spheres."""
    import jax

    from ...live import live_step

    prep, *args = _benchmark_scene_inputs(session, background, quick=quick)

    def step():
        return live_step(prep, *args)

    out = measure(lambda: step()[0], repeats=repeats)
    stats = jax.block_until_ready(step())[1]
    if prep.interreflection.mode == "gather":
        # objects that stay put (a camera moving around them): the interreflection's
        # camera-independent half computed once (LiveSession's reuse), the step per frame
        from ...rendering import render_senders

        def senders():
            return render_senders(prep, args[0], model=args[1], visible=args[3],
                                  mirror=args[6])

        state = jax.block_until_ready(senders())
        reuse = measure(lambda: live_step(prep, *args, state)[0], repeats=repeats)
        out["objects_static"] = {"median_ms": reuse["median_ms"], "min_ms": reuse["min_ms"],
                                 "render_fps": 1e3 / reuse["median_ms"],
                                 "compile_s": reuse["compile_s"]}
        out["senders_ms"] = measure(senders, repeats=repeats)["median_ms"]
    out.update(render_fps=1e3 / out["median_ms"],
               covered_pixels=int(stats["covered_pixels"]),
               overflow=bool(stats["overflow"]),
               pixel_capacity=list(prep.buffers.pixel_capacity),
               mode=prep.interreflection.mode)
    return out


def live_stages(opts: BenchOptions) -> dict[str, Any]:
    """Case ``live_stages``: the live loop WITHOUT the renderer, per 720×480 frame of the sample
    video: marker detection + tracking + poses, undistortion + upload, the compiled camera-RGB
    composite (a fixed CG image and bool mask covering 10 % of the frame) with its transfers,
    and MPEG-4 encoding; ``median_ms`` is the chain, ``stages_ms`` each stage's median. These
    are the stages :meth:`LiveSession.run` overlaps with rendering. ``--quick``: 240×160."""
    import cv2
    import jax
    import jax.numpy as jnp
    import numpy as np

    from ...io import load_scene
    from ...live import LiveSession, VideoSink, read_frames

    scene = load_scene(CONFIG)
    frames = read_frames(VIDEO, max_frames=48)
    size = frames[0].shape[:2]
    if opts.quick:
        size = (size[0] // 3, size[1] // 3)
        frames = [cv2.resize(f, (size[1], size[0]), interpolation=cv2.INTER_AREA)
                  for f in frames[:6]]
    session = LiveSession.__new__(LiveSession)  # the CPU parts only: no renderer preparation
    session._init_cpu(scene, size)
    from ...live import scene_camera_model

    camera = scene_camera_model(scene)
    rng = np.random.default_rng(0)
    cg = jnp.asarray(rng.random((*size, 3), dtype=np.float32))
    mask = np.zeros(size, bool)
    h, w = size
    mask[int(0.35 * h):int(0.65 * h), int(0.33 * w):int(0.67 * w)] = True
    mask = jnp.asarray(mask)
    from ...live import composite

    comp = jax.jit(lambda bg, c, m: composite(bg, c, m, camera))
    times: dict[str, list[float]] = {k: [] for k in ("detect", "undistort", "composite",
                                                     "encode")}
    state = {"i": 0}
    with tempfile.TemporaryDirectory() as tmp, VideoSink(Path(tmp) / "s.mp4", fps=25.0,
                                                         size=size) as sink:
        def chain():
            f = frames[state["i"] % len(frames)]
            state["i"] += 1
            t0 = time.perf_counter()
            (_poses, _inputs), bg, _ = session._cpu_stages(f)
            t1 = time.perf_counter()
            out = np.asarray(jax.block_until_ready(comp(bg, cg, mask)))
            t2 = time.perf_counter()
            sink.write(out)
            t3 = time.perf_counter()
            times["detect"].append(session._last_detect)
            times["undistort"].append(t1 - t0 - session._last_detect)
            times["composite"].append(t2 - t1)
            times["encode"].append(t3 - t2)
            return out

        out = measure(chain, repeats=opts.repeats)
    out["stages_ms"] = {k: statistics.median(v[1:]) * 1e3 for k, v in times.items()}
    out["size"] = [int(x) for x in size]
    return out


_IN_FLIGHT = r"""
import json, sys
from spectral_fit._runtime import process as process
from spectral_fit.rendering import _cache as startup
process.retain_freed_memory()
assert process.split_cpu_devices(2) == 2
from spectral_fit.bench.cases.live import _in_flight_figures
print(json.dumps(_in_flight_figures(sys.argv[1] == "quick", int(sys.argv[2]))))
"""


def live_in_flight(opts: BenchOptions) -> dict[str, Any]:
    import json
    import os
    import subprocess
    import sys

    import jax

    if jax.default_backend() != "cpu":
        return {"skipped": "CPU backend only (frames in flight on a split CPU)"}
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    r = subprocess.run([sys.executable, "-c", _IN_FLIGHT, "quick" if opts.quick else "full",
                        str(opts.repeats)], capture_output=True, text=True, env=env,
                       timeout=1800)
    if r.returncode != 0:
        raise RuntimeError(f"live_in_flight: the measuring process failed:\n{r.stderr[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def _stream(calls: list[Any], frames: int) -> list[float]:
    """Dispatch ``frames`` calls, call i with ``calls[i % len(calls)]``, keeping at most
    ``len(calls)`` unfinished; returns the frame intervals (s): means of ``len(calls)``
    consecutive intervals between finished frames (frames in flight finish in bunches, so
    single intervals alternate short and long)."""
    import jax

    pending: list[Any] = []
    done = [time.perf_counter()]
    for i in range(frames):
        pending.append(calls[i % len(calls)]())
        if len(pending) == len(calls):
            jax.block_until_ready(pending.pop(0))
            done.append(time.perf_counter())
    for p in pending:
        jax.block_until_ready(p)
        done.append(time.perf_counter())
    k = len(calls)
    return [(done[i + k] - done[i]) / k for i in range(1, len(done) - k)]


def _in_flight_figures(quick: bool, repeats: int) -> dict[str, Any]:
    """The figures of ``live_in_flight`` (run in a process with two CPU devices)."""
    import jax
    import jax.numpy as jnp

    from ...io import load_scene
    from ...live import LiveSession, live_step, put_on_device
    from ...rendering import render_senders

    devs = jax.devices("cpu")[:2]
    scene = load_scene(CONFIG)
    extra: dict[str, Any] = {}
    size = (480, 720)
    if quick:
        extra = {"mode": "none", "spectral_mode": "basis", "k": 8}
        size = (160, 240)
    n = max(2, repeats) + 2  # frames per stream: n - 2 windows of two
    session = LiveSession(scene, size=size, devices=devs, **extra)
    args = _benchmark_scene_inputs(session, jnp.zeros((*size, 3), jnp.uint8), quick=quick)
    prep = args[0]

    def figures(full: tuple[Any, ...]) -> dict[str, Any]:
        on = [put_on_device(full, d) for d in devs]
        calls = [lambda a=a: live_step(*a)[0] for a in on]
        t0 = time.perf_counter()
        jax.block_until_ready(calls[0]())
        t1 = time.perf_counter()
        jax.block_until_ready(calls[1]())
        t2 = time.perf_counter()
        one = _stream(calls[:1], n)
        two = _stream(calls, n)
        iv = statistics.median(two) * 1e3
        return {"frame_interval_ms": iv, "median_ms": iv, "min_ms": min(two) * 1e3,
                "max_ms": max(two) * 1e3, "render_fps": 1e3 / iv,
                "one_at_a_time_ms": statistics.median(one) * 1e3,
                "compile_s": t2 - t0, "compile_s_per_device": [t1 - t0, t2 - t1],
                "n": len(two)}

    bench = figures(args)
    bench["mode"] = prep.interreflection.mode
    headline = bench
    if prep.interreflection.mode == "gather":
        state = render_senders(prep, args[1], model=args[2], visible=args[4], mirror=args[7])
        headline = bench["objects_static"] = figures((*args, state))
    res: dict[str, Any] = {k: headline[k] for k in ("median_ms", "min_ms", "max_ms", "n",
                                                    "render_fps")}
    res.update(compile_s=bench["compile_s"], devices=[str(d) for d in devs],
               benchmark_scene=bench)
    res["end_to_end"] = _in_flight_e2e(session, VIDEO, size, quick)
    bench_session = LiveSession(load_scene(BENCH_CONFIG), size=size, devices=devs, **extra)
    res["benchmark_scene"]["end_to_end"] = _in_flight_e2e(bench_session, BENCH_VIDEO, size,
                                                          quick)
    return res


def _in_flight_e2e(session: Any, video: Path, size: tuple[int, int], quick: bool
                   ) -> dict[str, Any]:
    """:meth:`~spectral_fit.live.LiveSession.run` without threads on ``video`` with
    ``in_flight`` 1 and 2, after 4 frames that compile the step on both devices."""
    from ...live import VideoSink, VideoSource

    e2e: dict[str, Any] = {}
    with VideoSource(video, field="video") as src, tempfile.TemporaryDirectory() as tmp:
        stream = _frames(src, size)
        with VideoSink(Path(tmp) / "o.mp4", fps=25.0, size=size) as sink:
            session.run(stream, sink.write, threads=False, max_frames=4)  # compile both
            for depth in (1, 2):
                st = session.run(stream, sink.write, threads=False, in_flight=depth,
                                 max_frames=(3 if quick else 12) + depth)
                med = st.medians_ms()  # frame interval: median over windows of `depth`
                e2e[f"in_flight_{depth}"] = {"median_ms": med["interval"],
                                             "fps": 1e3 / med["interval"],
                                             "render_latency_ms": med["render"],
                                             "stages_ms": {k: med[k] for k in (
                                                 "decode", "detect", "undistort",
                                                 "encode")}}
    e2e["recompiles"] = int(session.recompiles)
    e2e["replans_ahead"] = int(session.replans_ahead)
    e2e["interreflection_senders"] = {"computed": int(session.ir_updates),
                                      "reused": int(session.ir_reuses)}
    e2e["covered_pixels"] = _covered_pixels(session)
    return e2e


CASES = {"live_paper": live_paper, "live_paper_none": live_paper_none, "live_table": live_table,
         "live_stages": live_stages, "live_in_flight": live_in_flight}
