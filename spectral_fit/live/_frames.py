"""Frames in flight in a live session: a frame's CPU stages and the dispatch of its step
(``submit``), waiting for it with re-planning on overflow (``finish``), and streams of frames
(``run``: reader/render/writer threads, or several frames submitted before the oldest is
finished), with per-stage timings in seconds.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

import jax
import numpy as np

from .._runtime.errors import InputError

if TYPE_CHECKING:  # for annotations (the renderer is imported where it is used)
    from ..rendering import Prepared

__all__ = ["FrameTimings", "FramesInFlight", "RunStats", "pipeline_pays"]


@dataclasses.dataclass
class FrameTimings:
    """Seconds spent per stage of the last frame (``detect`` includes tracking)."""

    detect: float = 0.0
    undistort: float = 0.0
    render: float = 0.0
    total: float = 0.0


@dataclasses.dataclass
class RunStats:
    """Per-frame seconds of each stage of :meth:`LiveSession.run` (lists in frame order).

    ``decode``, ``detect`` (+ tracking), ``undistort`` (+ upload) run on the reader thread,
    ``render`` (the compiled step, dispatch to ready) on the calling thread, ``encode`` (the
    ``write`` callback) on the writer thread; ``interval`` is the time between consecutive
    finished frames (the end-to-end frame time; its first entry is the first frame's
    latency, compilation included); ``recompiled`` flags frames that re-planned buffers;
    ``in_flight``: frames the run kept submitted (with more than one, frames finish in
    bunches and the intervals alternate short and long, so :meth:`medians_ms` takes the
    interval's median over means of ``in_flight`` consecutive intervals).
    """

    decode: list[float] = dataclasses.field(default_factory=list)
    detect: list[float] = dataclasses.field(default_factory=list)
    undistort: list[float] = dataclasses.field(default_factory=list)
    render: list[float] = dataclasses.field(default_factory=list)
    encode: list[float] = dataclasses.field(default_factory=list)
    interval: list[float] = dataclasses.field(default_factory=list)
    recompiled: list[bool] = dataclasses.field(default_factory=list)
    visible: list[np.ndarray] = dataclasses.field(default_factory=list)
    in_flight: int = 1

    @property
    def frames(self) -> int:
        return len(self.interval)

    def medians_ms(self) -> dict[str, float | None]:
        """Steady-state medians (ms) per stage: frames after the first, without re-plans."""
        import statistics

        keep = [i for i in range(1, self.frames) if not self.recompiled[i]]
        out: dict[str, float | None] = {}
        for name in ("decode", "detect", "undistort", "render", "encode"):
            vals = [getattr(self, name)[i] for i in keep if i < len(getattr(self, name))]
            out[name] = statistics.median(vals) * 1e3 if vals else None
        k = max(1, self.in_flight)
        windows = [sum(self.interval[i - k + 1:i + 1]) / k for i in keep if i >= k]
        if not windows:  # fewer frames than a window
            windows = [self.interval[i] for i in keep]
        out["interval"] = statistics.median(windows) * 1e3 if windows else None
        return out


_QUEUE = 2


def pipeline_pays() -> bool:
    """Whether :meth:`LiveSession.run` overlaps its stages with threads by default: only when
    the compiled step runs on an accelerator (GPU, TPU). On the CPU backend XLA already spreads
    the step's parallel loops over every core; a reader thread beside it preempts one of the
    step's workers and each loop then waits for that one (on 2 cores the threaded loop is
    slower than the sequential one), so the stages run one after the other there. Follows
    :func:`spectral_fit._runtime.backend.on_accelerator`."""
    from .._runtime.backend import on_accelerator

    return on_accelerator()


@dataclasses.dataclass
class _Pending:
    """A submitted frame (see :meth:`LiveSession.submit`)."""

    poses: Any
    background: np.ndarray
    out: Any
    stats: dict[str, Any]
    times: tuple[float, float, float]
    prep: Prepared | None = None  # the session's prepared scene when it was dispatched


class FramesInFlight:
    """The per-frame entry points of :class:`~spectral_fit.live.LiveSession` (its CPU stages,
    dispatch, re-planning and buffers are the session's own)."""

    def submit(self, frame: np.ndarray) -> _Pending:
        """CPU stages of one frame (detect, track, undistort) and the DISPATCH of its compiled
        step, which runs asynchronously: call :meth:`finish` on the result later. Submitting
        frame n+1 before finishing frame n overlaps the CPU stages with the device (a GPU),
        and with several :attr:`devices` (frame n+1 goes to the next one) the two frames'
        steps with each other; :meth:`run` does either (threads, or frames in flight)."""
        (poses, inputs), bg, times = self._cpu_stages(frame)
        out, stats = self._dispatch(poses, inputs, bg)
        return _Pending(poses, bg, out, stats, times, self.prep)

    def finish(self, pending: _Pending) -> np.ndarray:
        """Wait for a submitted frame; re-plans, recompiles and re-renders it when its buffers
        overflowed. Returns (H, W, 3) uint8 RGB. ``timings.render`` is dispatch → ready (with
        frames in flight it includes the overlapped CPU work of the next frame)."""
        poses, bg, out, stats = pending.poses, pending.background, pending.out, pending.stats
        t0, t1, t2 = pending.times
        out = jax.block_until_ready(out)
        from ..rendering import ir_fallback

        planned = pending.prep
        for _ in range(3):
            # the pass-1 rasters' planned capacities overflowed: their generic ones, once
            ir = bool(stats["interreflection_overflow"]) and (
                planned is not self.prep or ir_fallback(self.prep) is not None)
            if not (bool(stats["overflow"]) or ir):
                break
            if (planned is None or planned is self.prep) and not (
                    bool(stats["overflow"]) and not ir and self._wait_grown()):
                if bool(stats["overflow"]):
                    self.headroom *= 1.5
                self._replan(poses, self.headroom, interreflection=ir)
                self.recompiles += 1
            # else: re-planned since this frame was dispatched (a frame in flight before it
            # overflowed): rendered again with that plan before growing it further
            planned = self.prep
            out, stats = self.render(poses, bg)
            out = jax.block_until_ready(out)
        if bool(stats["overflow"]):
            raise RuntimeError("live: render buffers still overflow after re-planning")
        if planned is None or planned is self.prep:
            self._maybe_grow(stats, poses, bg)
        t3 = time.perf_counter()
        self.timings = FrameTimings(detect=t1 - t0, undistort=t2 - t1, render=t3 - t2,
                                    total=t3 - t0)
        self.frames += 1
        self.last_poses = poses
        self.last_object_id = stats["object_id"]
        return np.asarray(out)

    def process(self, frame: np.ndarray) -> np.ndarray:
        """Composite one video frame (H, W, 3) uint8 RGB; returns (H, W, 3) uint8 RGB."""
        return self.finish(self.submit(frame))

    def run(self, frames: Iterable[np.ndarray], write: Callable[[np.ndarray], Any] | None = None,
            *, threads: bool | None = None, max_frames: int | None = None,
            on_frame: Callable[[int, RunStats], Any] | None = None,
            in_flight: int | None = None) -> RunStats:
        """Composite a stream of frames; returns per-stage timings (:class:`RunStats`).

        Args:
            frames: (H, W, 3) uint8 RGB frames (e.g. a :class:`~spectral_fit.live.VideoSource`;
                its decoding is timed as ``decode``).
            write: called with each composited frame, in order (e.g. ``VideoSink.write``).
            threads: overlap the stages: a reader thread decodes, detects, tracks, undistorts
                and uploads frame n+1 (and further, up to 2 queued) while this thread renders
                frame n, and a writer thread encodes frame n−1. OpenCV and JAX release the
                Python lock while they work, so the stages run in parallel. False: one stage
                after the other (each stage's own cost, for comparisons). None (default):
                :func:`pipeline_pays` (threads when the step runs on an accelerator).
            max_frames: stop after this many frames.
            on_frame: called after each rendered frame with (index, stats so far).
            in_flight: without threads, how many frames are submitted before the oldest is
                finished (:meth:`submit` / :meth:`finish`): frame n+1's decoding, detection
                and dispatch (to the next of :attr:`devices`) run while frame n renders.
                Default: ``len(devices)``; 1 is one stage after the other. With threads, 1.
                ``render`` times are then dispatch → ready of each frame (its latency, which
                includes the other frames in flight); ``interval`` is the throughput.

        The output frames are identical either way (tracking stays in frame order on the
        reader thread; the compiled step is the same).
        """
        import queue
        import threading

        stats = RunStats()
        if threads is None:
            threads = pipeline_pays()
        limit = None if max_frames is None else int(max_frames)
        done = object()

        def produce(put: Callable[[Any], Any], stop: threading.Event | None) -> None:
            it = iter(frames)
            n = 0
            while limit is None or n < limit:
                if stop is not None and stop.is_set():
                    return
                t = time.perf_counter()
                frame = next(it, None)
                if frame is None:
                    break
                t_dec = time.perf_counter() - t
                item = self._cpu_stages(frame)
                put((t_dec, *item))
                n += 1
            put(done)

        def start(item: Any) -> tuple[Any, _Pending]:
            _, (poses, inputs), bg, _ = item
            t3 = time.perf_counter()
            out, st = self._dispatch(poses, inputs, bg)
            return item, _Pending(poses, bg, out, st, (t3, t3, t3), self.prep)

        def complete(started: tuple[Any, _Pending]) -> np.ndarray:
            item, pending = started
            t_dec, (poses, _), _, (t0, t1, t2) = item
            before = self.recompiles
            img = self.finish(pending)
            stats.decode.append(t_dec)
            stats.detect.append(t1 - t0)
            stats.undistort.append(t2 - t1)
            stats.render.append(time.perf_counter() - pending.times[0])
            stats.recompiled.append(self.recompiles != before)
            stats.visible.append(np.asarray(poses.visible).copy())
            return img

        def render_one(item: Any) -> np.ndarray:
            return complete(start(item))

        def emit(img: np.ndarray, put_out: Callable[[Any], Any]) -> None:
            nonlocal t_prev
            put_out(img)
            now = time.perf_counter()
            stats.interval.append(now - t_prev)
            t_prev = now
            if on_frame is not None:
                on_frame(stats.frames - 1, stats)

        def encode(img: np.ndarray) -> None:
            t = time.perf_counter()
            if write is not None:
                write(img)
            stats.encode.append(time.perf_counter() - t)

        t_prev = time.perf_counter()
        if not threads:
            depth = len(self.devices) if in_flight is None else int(in_flight)
            if depth < 1:
                raise InputError(f"must be >= 1, got {in_flight!r}", field="in_flight")
            stats.in_flight = depth
            started: list[tuple[Any, _Pending]] = []

            def step(item: Any) -> None:
                if item is not done:
                    started.append(start(item))
                while started and (len(started) >= depth or item is done):
                    emit(complete(started.pop(0)), encode)

            produce(step, None)
            return stats

        q_in: queue.Queue[Any] = queue.Queue(maxsize=_QUEUE)
        q_out: queue.Queue[Any] = queue.Queue(maxsize=_QUEUE)
        stop = threading.Event()
        errors: list[BaseException] = []

        def put_in(item: Any) -> None:
            while not stop.is_set():
                try:
                    q_in.put(item, timeout=0.1)
                    return
                except queue.Full:
                    continue

        def reader() -> None:
            try:
                produce(put_in, stop)
            except BaseException as exc:  # noqa: BLE001 - re-raised on the calling thread
                errors.append(exc)
                put_in(done)

        def writer() -> None:
            while True:
                img = q_out.get()
                if img is done:
                    return
                if errors:
                    continue  # drain: the run is failing, write nothing more
                try:
                    encode(img)
                except BaseException as exc:  # noqa: BLE001 - re-raised on the calling thread
                    errors.append(exc)
                    stop.set()

        threads_ = [threading.Thread(target=reader, name="live-reader", daemon=True),
                    threading.Thread(target=writer, name="live-writer", daemon=True)]
        for th in threads_:
            th.start()
        try:
            while not errors:
                try:
                    item = q_in.get(timeout=0.1)
                except queue.Empty:
                    continue
                if item is done:
                    break
                emit(render_one(item), q_out.put)
        finally:
            stop.set()
            q_out.put(done)
            for th in threads_:
                th.join()
        if errors:
            raise errors[0]
        return stats
