"""``spectral-fit live``: marker-placed spectral CG composited onto a video."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

HELP = ("mixed reality: place the scene's objects on ArUco markers in a video (file or "
        "camera), render them spectrally and composite them colour-matched")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="scene config (TOML) with [markers] and objects' marker ids")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--video", help="input video file")
    src.add_argument("--camera", type=int, help="camera index (e.g. 0) instead of a file")
    p.add_argument("-o", "--output", default=None, help="output video (.mp4 or .avi)")
    p.add_argument("--max-frames", type=int, default=None, help="stop after N frames")
    p.add_argument("--mode", choices=("gather", "paper", "none"), default=None,
                   help="interreflection mode (default: the config's)")
    p.add_argument("--spectral-mode", choices=("bands", "basis"), default=None)
    p.add_argument("--k", type=int, default=None, help="basis size for --spectral-mode basis")
    p.add_argument("--sensitivities", default=None,
                   help="camera spectral sensitivities (colour-science name) for colour "
                   "matching (default: fitted from the config's [colour_chart] in the video, "
                   "else the config's [camera_colour] from 'spectral-fit calibrate-colour', "
                   "else 'Nikon 5100 (NPL)')")
    p.add_argument("--white-level", type=float, default=0.85,
                   help="linear frame level of a white sheet on the table (exposure)")
    p.add_argument("--blur-px", type=float, default=None, metavar="SIGMA",
                   help="the video's blur given to the CG: a Gaussian of SIGMA pixels "
                   "(default: the config's [camera] blur_px, 0 = sharp CG)")
    p.add_argument("--noise", type=float, default=None, metavar="LEVELS",
                   help="the video's noise given to the CG: σ in 8-bit levels (default: the "
                   "config's [camera] noise, 0 = none)")
    p.add_argument("--lens", choices=("undistort", "distort"), default="undistort",
                   help="with [camera] distortion: undistort the video frames onto the "
                        "pinhole (default), or keep them and render the CG through the lens")
    p.add_argument("--fps", type=float, default=None,
                   help="output frame rate (default: the input's, or 25)")
    p.add_argument("--pipeline", action=argparse.BooleanOptionalAction, default=None,
                   help="overlap the stages with threads (decode, detection and undistortion "
                   "of frame n+1 and encoding of frame n-1 run while frame n renders); "
                   "--no-pipeline runs them one after the other; default: threads on a GPU, "
                   "one after the other on the CPU backend (there the render already uses "
                   "every core and threads beside it slow it down)")
    p.add_argument("--ir-reuse-mm", type=_reuse_mm, default=0.5, metavar="MM|off",
                   help="gather interreflection: compute its camera-independent half again "
                   "only when an object moved more than MM millimetres (default 0.5; 0: only "
                   "for identical poses; off: every frame)")
    p.add_argument("--cpu-devices", type=int, default=None, metavar="N",
                   help="on the CPU backend, split the CPU into N JAX devices and keep N "
                   "frames in flight (frame i renders on device i mod N while frame i+1 is "
                   "decoded and detected): more frames per second, each device compiling its "
                   "own step on the first run (later runs load them from the cache); default "
                   "2 on a machine with 2 or more cores (1 with --pipeline), 1 turns it off "
                   "(docs/live.md 'Frames in flight')")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _reuse_mm(text: str) -> float | None:
    if text.strip().lower() == "off":
        return None
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not (v >= 0 and v < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a number >= 0 or 'off', got {text!r}")
    return v


def _bar(i: int, n: int | None, render_ms: float, e2e_fps: float, in_flight: int = 1) -> str:
    """One progress line. With one frame in flight the render readout is its rate; with
    several each frame's render time includes the others', so it is shown as a latency."""
    if n:
        done = int(30 * i / n)
        head = f"[{'#' * done}{'.' * (30 - done)}] {i}/{n}"
    else:
        head = f"frame {i}"
    if in_flight == 1:
        render = f"render {1e3 / render_ms if render_ms else 0.0:6.1f} fps"
    else:
        render = f"render latency {render_ms:6.1f} ms ({in_flight} in flight)"
    return f"\rlive: {head}  {render}  end-to-end {e2e_fps:6.1f} fps"


def run(args: argparse.Namespace) -> int:
    from ..._runtime.errors import InputError
    from ..._runtime.process import split_cpu_devices
    from ...rendering import enable_compilation_cache

    cpu_devices = args.cpu_devices
    if cpu_devices is None:  # threads keep one frame in flight: a second device only compiles
        cpu_devices = 2 if (os.cpu_count() or 1) >= 2 and not args.pipeline else 1
    if cpu_devices < 1:
        raise InputError("must be >= 1", field="--cpu-devices")
    if cpu_devices > 1:
        split_cpu_devices(cpu_devices)  # before anything starts JAX's backend
    enable_compilation_cache(min_compile_time_s=1.0)  # a second run loads the programs

    from ...io import MAX_BLUR_PX, MAX_NOISE, load_scene
    from ...live import LiveSession, VideoSink, VideoSource, count_frames, pipeline_pays

    if args.max_frames is not None and args.max_frames < 1:
        raise InputError("must be >= 1", field="--max-frames")
    if not 0 < args.white_level <= 1:
        raise InputError("must be in (0, 1]", field="--white-level")
    for name, v, hi in (("--blur-px", args.blur_px, MAX_BLUR_PX),
                        ("--noise", args.noise, MAX_NOISE)):
        if v is not None and not 0 <= v <= hi:
            raise InputError(f"must be in [0, {hi:g}], got {v:g}", field=name)
    scene = load_scene(args.config)
    if args.blur_px is not None or args.noise is not None:
        cam = scene.camera
        scene = scene.replace(camera=dataclasses.replace(
            cam, blur_px=cam.blur_px if args.blur_px is None else args.blur_px,
            noise=cam.noise if args.noise is None else args.noise))
    pipeline = pipeline_pays() if args.pipeline is None else bool(args.pipeline)
    t_start = time.perf_counter()
    source = VideoSource(args.camera if args.camera is not None else args.video,
                         field="--camera" if args.camera is not None else "--video")
    chart = None
    if scene.colour_chart is not None and args.sensitivities is None:
        # the camera's colour from the chart in the video's first frames (a file is read
        # once more from its start; a camera's first frames are spent on it)
        chart = _chart_model(scene, args, source)
    with source:
        session = LiveSession(scene, size=(source.height, source.width), mode=args.mode,
                              spectral_mode=args.spectral_mode, k=args.k,
                              sensitivities=args.sensitivities, white_level=args.white_level,
                              ir_reuse_mm=args.ir_reuse_mm, lens=args.lens,
                              camera=None if chart is None else chart.model)
        in_flight = 1 if pipeline else len(session.devices)  # LiveSession.run's choice
        fps_out = args.fps or (source.fps if source.fps and source.fps > 0 else 25.0)
        total = source.frame_count
        if args.max_frames is not None:
            total = min(total, args.max_frames) if total else args.max_frames
        sink = (VideoSink(args.output, fps=fps_out, size=(source.height, source.width))
                if args.output else None)

        def progress(i: int, st) -> None:
            if args.quiet:
                return
            med = st.medians_ms() if i > 0 else {}
            ef = 1e3 / med["interval"] if med.get("interval") else 0.0
            print(_bar(i + 1, total, med.get("render") or 0.0, ef, in_flight),
                  end="", file=sys.stderr, flush=True)

        ctx = sink if sink is not None else _Null()
        t_run = time.perf_counter()
        try:
            with ctx:
                stats = session.run(source, sink.write if sink is not None else None,
                                    threads=pipeline, max_frames=args.max_frames,
                                    on_frame=progress)
        finally:
            # no frame will come: a compile of grown buffers still under way is stopped
            # early rather than finished (the interpreter would wait for the whole of it)
            session.stop_background()
        if not args.quiet:
            print(file=sys.stderr)
    n = stats.frames
    first_s = (t_run - t_start) + stats.interval[0] if n else None
    lost = [sum(int(not v[j]) for v in stats.visible) for j in range(len(scene.objects))]
    med = stats.medians_ms()
    if n == 0:
        raise InputError("no frames read", field="--video")
    written = count_frames(args.output) if args.output else None
    summary = {
        "frames": n,
        "first_frame_s": first_s,
        "render_median_ms": med["render"],
        "end_to_end_median_ms": med["interval"],
        "render_fps": (1e3 / med["render"] if med["render"] and in_flight == 1 else None),
        "in_flight": in_flight,
        "end_to_end_fps": 1e3 / med["interval"] if med["interval"] else None,
        "stage_median_ms": {k: v for k, v in med.items() if k != "interval"},
        "recompiles": session.recompiles,
        "replans_ahead": session.replans_ahead,
        "interreflection_senders": {"computed": session.ir_updates,
                                    "reused": session.ir_reuses,
                                    "reuse_mm": session.ir_reuse_mm},
        "surface_shadow_builds": session.surface_builds,
        "frames_masked": {o.name: c for o, c in zip(scene.objects, lost, strict=True)},
        "output": args.output,
        "output_frames": written,
        "pixel_capacity": session.prep.buffers.pixel_capacity,
        "pipeline": pipeline,
        "devices": [str(d) for d in session.devices],
        "cg_blur_px": session.camera.blur_px,
        "cg_noise": session.camera.noise,
        "colour": (_chart_note(chart) if chart is not None else
                   "sensitivities " + (args.sensitivities or "Nikon 5100 (NPL)")
                   if args.sensitivities or scene.camera_colour is None
                   else "[camera_colour]"),
    }
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        def f(x: float | None, fmt: str) -> str:
            return "n/a" if x is None else format(x, fmt)

        render = (f"render {f(summary['render_median_ms'], '.1f')} ms "
                  f"({f(summary['render_fps'], '.1f')} fps)" if in_flight == 1 else
                  f"render latency {f(summary['render_median_ms'], '.1f')} ms "
                  f"({in_flight} frames in flight)")
        print(f"live: {n} frames; first frame (compile) {f(first_s, '.1f')} s; {render}; "
              f"end-to-end {f(summary['end_to_end_median_ms'], '.1f')} ms "
              f"({f(summary['end_to_end_fps'], '.1f')} fps); recompiles {session.recompiles}, "
              f"buffers grown ahead {session.replans_ahead}")
        if args.output:
            print(f"wrote {args.output} ({written} frames)")
    if args.output and written != n:
        raise InputError(f"wrote {n} frames but {written} read back", path=args.output,
                         field="--output")
    return 0


def _chart_model(scene, args: argparse.Namespace, source):
    """The colour model fitted from the config's ``[colour_chart]`` in the video."""
    from ...live import VideoSource, chart_camera_model, scene_intrinsics

    k, dist = scene_intrinsics(scene, (source.height, source.width))
    if args.camera is not None:
        return chart_camera_model(scene, source, k=k, dist=dist, source=f"camera {args.camera}")
    with VideoSource(args.video, field="--video") as again:
        chart = chart_camera_model(scene, again, k=k, dist=dist, source=str(args.video))
    if not args.quiet:
        print(f"live: {_chart_note(chart)}", file=sys.stderr)
    return chart


def _chart_note(chart) -> str:
    cal = chart.calibration
    de = cal.delta_e00[cal.used]
    return (f"[colour_chart] in {len(chart.frames)} frames (first {chart.frames[0]}), "
            f"{int(cal.used.sum())} patches, reproduction ΔE00 mean {de.mean():.2f} "
            f"max {de.max():.2f}")


class _Null:
    def __enter__(self) -> _Null:
        return self

    def __exit__(self, *exc: object) -> None:
        return None
