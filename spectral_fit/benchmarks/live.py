"""Benchmark case ``live_paper``: the live mixed-reality loop on the bundled sample video.

Scene: ``configs/live_sample.toml``, the paper's two 75 mm spheres (UV 100×100, 19,800
triangles each; ColorChecker N Ohta yellow and red; α = β = 1, μ = 0.1, n = 1.5) on two 80 mm
ArUco markers, interreflection "gather", 31 bands (400–700 nm), 720×480, seen at 0.3–0.35 m
(a footprint like BENCHMARK.md's paper scene). Video: ``measurements/video/sample.mp4``.

Figures:

* ``median_ms`` / ``min_ms`` / ``max_ms`` / ``compile_s``: RENDER-ONLY, the compiled step
  (render with interreflection → camera RGB → composite over the frame) at the first frame's
  poses, blocking on the result;
* ``end_to_end_median_ms`` / ``end_to_end_fps``: the whole loop per frame: decode, detect
  markers, track, undistort, render, composite, encode (MPEG-4 into a temporary file), over
  ``n_end_to_end`` consecutive frames after the first (compiling) one;
* ``end_to_end_pipelined_median_ms`` / ``_fps``: the same with frame n+1's CPU stages
  overlapping frame n's rendering (``LiveSession.submit`` / ``finish``);
* ``render_fps``, ``covered_pixels``, ``pixel_capacity``, ``recompiles`` (must stay 0).

``--quick``: frames at a third of the size (240×160, intrinsics scaled), interreflection
"none", K = 8 basis, 2 end-to-end frames (figures not comparable).
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from ..bench import BenchOptions, measure

__all__ = ["CASES"]

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "configs" / "live_sample.toml"
VIDEO = ROOT / "measurements" / "video" / "sample.mp4"


def live_paper(opts: BenchOptions) -> dict[str, Any]:
    import jax

    from ..errors import InputError
    from ..live import LiveSession
    from ..scene import load_scene
    from ..video import VideoSink, VideoSource

    if not CONFIG.is_file() or not VIDEO.is_file():
        raise InputError("live_paper needs the repository's configs/ and measurements/video/",
                         path=CONFIG if not CONFIG.is_file() else VIDEO)
    scene = load_scene(CONFIG)
    extra: dict[str, Any] = {}
    if opts.quick:
        extra = {"mode": "none", "spectral_mode": "basis", "k": 8}
    n_e2e = 2 if opts.quick else max(1, min(opts.repeats, 25))
    with VideoSource(VIDEO, field="video") as src:
        div = 3 if opts.quick else 1
        size = (src.height // div, src.width // div)

        def read():
            f = src.read()
            if f is None or div == 1:
                return f
            import cv2

            return cv2.resize(f, (size[1], size[0]), interpolation=cv2.INTER_AREA)

        first = read()
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
        with tempfile.TemporaryDirectory() as tmp:
            times = []
            with VideoSink(Path(tmp) / "out.mp4", fps=25.0, size=size) as sink:
                for _ in range(n_e2e):
                    t = time.perf_counter()
                    frame = read()
                    if frame is None:
                        break
                    sink.write(session.process(frame))
                    times.append((time.perf_counter() - t) * 1e3)
                # pipelined: frame n+1's CPU stages overlap frame n's rendering
                piped, pending, t_prev = [], None, None
                for _ in range(n_e2e + 1):
                    frame = read()
                    nxt = session.submit(frame) if frame is not None else None
                    if pending is not None:
                        sink.write(session.finish(pending))
                        now = time.perf_counter()
                        if t_prev is not None:
                            piped.append((now - t_prev) * 1e3)
                        t_prev = now
                    pending = nxt
                    if pending is None:
                        break
    jax.block_until_ready(step())
    e2e = statistics.median(times)
    out.update({
        "render_fps": 1e3 / out["median_ms"],
        "end_to_end_median_ms": e2e,
        "end_to_end_fps": 1e3 / e2e,
        "n_end_to_end": len(times),
        "end_to_end_pipelined_median_ms": statistics.median(piped) if piped else None,
        "end_to_end_pipelined_fps": 1e3 / statistics.median(piped) if piped else None,
        "covered_pixels": int(session.last_object_id.__ge__(0).sum()),
        "pixel_capacity": list(session.prep.pixel_capacity),
        "recompiles": int(session.recompiles),
        "size": [int(x) for x in session.size],
        "mode": extra.get("mode", scene.interreflection.mode),
    })
    return out


CASES = {"live_paper": live_paper}
