"""Live mixed reality: video frames in, marker-placed spectral CG composited, frames out.

Per frame (``LiveSession.process``)::

    frame (H, W, 3) uint8 ──MarkerDetector (raw frame, K + distortion)──▶ marker poses
        ──MarkerTracker──▶ model (O, 4, 4), view (4, 4), visible (O,)      [CPU, NumPy]
    frame ──undistort onto the pinhole K (cv2.remap)──▶ background          [CPU, OpenCV]
    ──one jitted step: render_pixels (traced poses; the covered pixels only, shaded
      straight into camera RGB) → encode → written into the frame──▶ uint8 frame

Geometry: the renderer draws with the pinhole intrinsics K (``[camera] intrinsics``, or the
config's field of view when absent); each video frame is undistorted onto that same K
(:func:`spectral_fit.live.undistort_maps`), so the output video is undistorted.
With ``LiveSession(lens="distort")`` (``spectral-fit live --lens distort``) the frames are
kept as they are instead and the CG is rendered through the lens (:mod:`spectral_fit.geometry`).
Marker poses come from the raw frame with the distortion model.

Colour: the renderer's radiance channels go straight to the camera's linear RGB: the
:class:`~spectral_fit.rendering.Prepared` matrix ``to_xyz`` (channels → XYZ) is replaced by
channels → camera RGB (``to_spectrum @ camera.spectral_weights``), so the camera's spectral
sensitivities act on the full spectra at no extra cost (``Frame.xyz`` then holds camera linear
RGB). A camera model fitted from a ColorChecker shot (XYZ → RGB 3×3; the config's
``[camera_colour]``, see :func:`scene_camera_model`) uses ``to_xyz @ M.T`` instead. The
composite uses the renderer's coverage mask (see :mod:`spectral_fit.live`).

Compilation: the step is compiled once per session (poses, visibility and the background frame
are traced inputs). Buffers (raster windows, covered pixels) are planned for the objects at
``plan_distance`` in front of the camera, then on the first frame's poses. When a frame fills a
buffer past ``grow_ahead`` (objects coming closer), the session compiles larger buffers in a
background thread while the frames go on with the current ones, and switches to them once they
are compiled (``replans_ahead``): no frame waits for that compile. A frame that overflows its
buffers all the same (objects closer than planned, faster than the background compile) is
re-planned with more headroom, recompiled in place and rendered again (``recompiles``): nothing
is ever silently dropped.
"""

from __future__ import annotations

import dataclasses
import functools
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.dispatch import array_jit
from .._runtime.errors import InputError
from ..io import Scene
from ..lighting import white_reference
from ._compositing import CameraModel, camera_model_from_sensitivities, composite_pixels

__all__ = [
    "LiveSession",
    "FrameTimings",
    "RunStats",
    "scene_intrinsics",

    "scene_camera_model",
    "camera_output_matrix",
    "pipeline_pays",
    "STEP_TRACES",
    "live_step",
    "put_on_device",
]

# windows of every raster size in a live plan at least: a size that the first poses do not
# use (triangles larger than 4 pixels) is planned at the ladder's floor, 16, and an object
# coming closer goes from none to some dozens of them in one frame (as on the sample video),
# too fast for growing ahead. 64 of them cost nothing measurable in a frame
_MIN_WINDOWS = 64

#: number of times the live step has been traced (compiled), for tests and reports
STEP_TRACES = {"step": 0}


def scene_intrinsics(scene: Scene, size: tuple[int, int] | None = None
                     ) -> tuple[np.ndarray, np.ndarray | None]:
    """OpenCV K (3×3) and distortion of the scene camera for a frame of ``size`` = (H, W)
    (default the config's): ``[camera] intrinsics`` scaled to the size, or the pinhole of
    ``fov_y_deg`` (square pixels, centred); the distortion is ``[camera] distortion`` with
    either (the renderer applies it to a ``fov_y_deg`` camera too), None without one."""
    from ..geometry import perspective, projection_to_intrinsics

    h, w = size or (scene.height, scene.width)
    cam = scene.camera
    dist = None if cam.distortion is None else np.asarray(cam.distortion, np.float64)
    if cam.intrinsics is None:
        k = np.asarray(projection_to_intrinsics(perspective(cam.fov_y_deg, w / h), w, h),
                       np.float64)
        return k, dist
    i = cam.intrinsics
    sx, sy = w / scene.width, h / scene.height
    k = np.array([[i["fx"] * sx, 0.0, (i["cx"] + 0.5) * sx - 0.5],
                  [0.0, i["fy"] * sy, (i["cy"] + 0.5) * sy - 0.5], [0.0, 0.0, 1.0]])
    return k, dist


def scene_camera_model(scene: Scene, *, sensitivities: str | None = None,
                       white_level: float = 0.85) -> CameraModel:
    """The video camera's colour model for ``scene``: its ``[camera_colour]`` table (a 3×3
    from a ColorChecker shot, ``spectral-fit calibrate-colour``) unless ``sensitivities`` is
    given; otherwise measured spectral sensitivities (default "Nikon 5100 (NPL)") white-
    balanced on the environment's white reference (:func:`white_reference`) shown at linear
    level ``white_level``. The config's ``[camera] blur_px`` and ``noise`` go with it (the
    blur and noise given to the composited CG)."""
    from ..rendering import load_environment
    from ._compositing import camera_model_from_spec

    if sensitivities is None and scene.camera_colour is not None:
        model = camera_model_from_spec(scene.camera_colour, scene.wavelengths)
    else:
        env = load_environment(scene, scene.wavelengths)
        model = camera_model_from_sensitivities(
            sensitivities or "Nikon 5100 (NPL)", scene.wavelengths, white_reference(env),
            white_level=white_level)
    return dataclasses.replace(model, blur_px=float(scene.camera.blur_px),
                               noise=float(scene.camera.noise))


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


#: background buffers in the ring (frames queued + in flight + being written, with margin)
_RING = 6
_QUEUE = 2


def camera_output_matrix(prep: Any, camera: CameraModel) -> np.ndarray:
    """(C, 3) map from ``prep``'s radiance channels to the video camera's linear RGB: through
    the camera's spectral sensitivities (a model with them) or through XYZ and its 3 × 3
    (for :func:`~spectral_fit.rendering.with_output`)."""
    if camera.has_spectral:
        return np.asarray(prep.to_spectrum) @ np.asarray(camera.spectral_weights)
    return np.asarray(prep.to_xyz) @ np.asarray(camera.xyz_matrix).T


def _step_impl(prep: Any, materials: Any, model: jax.Array, view: jax.Array,
               visible: jax.Array, background: jax.Array, camera: CameraModel,
               mirror: bool = True, senders: Any = None
               ) -> tuple[jax.Array, dict[str, jax.Array]]:
    from ..rendering import render_pixels

    STEP_TRACES["step"] += 1
    # only the covered pixels are shaded (in the camera's linear RGB: prep's output matrix),
    # encoded and written into the video frame: no environment background, no full-frame
    # display encoding, no decoding of the video
    px = render_pixels(prep, materials, model=model, view=view, visible=visible,
                       mirror=mirror, senders=senders)
    out = composite_pixels(background, px.values, px.index, px.valid, camera)
    stats = {"covered_pixels": px.stats["covered_pixels"],
             "overflow": px.stats["pixel_overflow"] | px.stats["raster_overflow"],
             "interreflection_overflow": px.stats["interreflection_overflow"],
             "object_counts": px.stats["object_counts"],
             "raster_needed": px.stats["raster_needed"],
             "clusters_needed": px.stats["clusters_needed"],
             "object_id": px.object_id}
    return out, stats


live_step = array_jit(_step_impl)


def pipeline_pays() -> bool:
    """Whether :meth:`LiveSession.run` overlaps its stages with threads by default: only when
    the compiled step runs on an accelerator (GPU, TPU). On the CPU backend XLA already spreads
    the step's parallel loops over every core; a reader thread beside it preempts one of the
    step's workers and each loop then waits for that one (on 2 cores the threaded loop is
    slower than the sequential one), so the stages run one after the other there. Follows
    :func:`spectral_fit._runtime.backend.on_accelerator`."""
    from .._runtime.backend import on_accelerator

    return on_accelerator()


class LiveSession:
    """A compiled live mixed-reality pipeline for one scene and frame size.

    After :meth:`process`: ``last_poses`` (:class:`~spectral_fit.live.Poses`),
    ``last_object_id`` ((H, W) int32 object per pixel, −1 = video), ``timings``
    (:class:`FrameTimings`), ``frames``, ``recompiles`` (compiles a frame waited for),
    ``replans_ahead`` (buffers grown in the background).

    Args:
        scene: the scene (objects with ``marker`` ids; ``[markers]``; camera intrinsics).
        size: (H, W) of the video frames. With ``[camera] intrinsics`` (calibrated at the
            ``[frame]`` size) the frames may be a uniform resize of that size (the intrinsics
            are scaled; pixel centres stay at +0.5); another aspect ratio is an error.
        camera: the video camera's colour model (default: :func:`scene_camera_model`).
        sensitivities: colour-science camera name for the default model (overrides the
            config's ``[camera_colour]``).
        white_level: linear level of the white reference in a sensitivities model.
        mode, spectral_mode, k: renderer options (interreflection mode, bands/basis).
        plan_distance: distance (m) in front of the camera at which buffers are planned.
        headroom: capacity headroom over the planned poses.
        grow_ahead: a frame whose use of a buffer (an object's covered-pixel list, the
            raster's windows of one size or its blocks) passes this fraction of it starts a
            background compile of the step with that buffer ``headroom`` × its use; the
            session switches to it at the first frame after it is compiled (counted in
            ``replans_ahead``). None: buffers grow only when a frame overflows (a compile that
            the frame waits for).
        detect_downscale: marker detection on the frame shrunk by this factor, corners
            refined at full resolution (:class:`~spectral_fit.live.MarkerDetector`; None:
            2 for frames of 400 px and more).
        ir_reuse_mm: gather interreflection: the senders' half (pass 1, the senders'
            shading, transfer and bounces: :func:`~spectral_fit.rendering.render_senders`;
            it does not depend on the camera) is computed again only when some vertex of a
            visible object moved more than this many millimetres in the world (or an object's
            visibility changed) since it was last computed; otherwise the frame reuses it
            (a camera moving around objects that stay put). 0: reused only for identical
            poses. None: every frame computes it inside the step (one program). Counted in
            ``ir_updates`` and ``ir_reuses``.
        devices: the JAX devices that render the frames, in turn (frame i on device
            i mod len(devices)), each with its own copy of the prepared scene and its own
            compiled step; :meth:`run` keeps that many frames in flight. Default: every CPU
            device when the default backend is the CPU (one, unless the process split it:
            :func:`~spectral_fit._runtime.process.split_cpu_devices`), else the first accelerator.
            Frames are the same on every device (same program, same inputs).
        lens: with a distorting lens (``[camera] distortion``), "undistort" (default): each
            video frame is resampled onto the pinhole K and the CG is rendered with that K, so
            the output is undistorted; "distort": the video frames are kept as they are (no
            resampling) and the CG is rendered through the lens itself
            (:mod:`spectral_fit.geometry`), so the output keeps the camera's geometry.
    """

    def __init__(self, scene: Scene, *, size: tuple[int, int] | None = None,
                 camera: CameraModel | None = None,
                 sensitivities: str | None = None, white_level: float = 0.85,
                 mode: str | None = None, spectral_mode: str | None = None,
                 k: int | None = None, plan_distance: float = 0.35,
                 headroom: float = 1.6, detect_downscale: int | None = None,
                 ir_reuse_mm: float | None = 0.5, devices: Any = None,
                 grow_ahead: float | None = 0.8, lens: str = "undistort") -> None:
        if lens not in ("undistort", "distort"):
            raise InputError(f"must be 'undistort' or 'distort', got {lens!r}", field="lens")
        self.lens = lens
        self.devices = _frame_devices(devices)
        self._device_turn = 0
        self._copies: dict[Any, tuple[Any, Any, Any]] = {}
        self._init_cpu(scene, size, detect_downscale=detect_downscale)
        scene = self.scene
        if camera is None:
            camera = scene_camera_model(scene, sensitivities=sensitivities,
                                        white_level=white_level)
        self.camera = camera
        self._options = {"mode": mode, "spectral_mode": spectral_mode, "k": k}
        self.plan_distance = float(plan_distance)
        self.headroom = float(headroom)
        self.recompiles = 0
        self.frames = 0
        if grow_ahead is not None and not (0.0 < grow_ahead <= 1.0):
            raise InputError(f"must be in (0, 1] or None, got {grow_ahead!r}",
                             field="grow_ahead")
        self.grow_ahead = None if grow_ahead is None else float(grow_ahead)
        self.replans_ahead = 0
        self._grow_thread: threading.Thread | None = None
        self._grow_stop: threading.Event | None = None  # asks that thread to end early
        # (the prepared scene it grew from, the grown one, its copies per device), once compiled
        self._grown: tuple[Any, Any, dict[Any, Any]] | None = None
        self._planned = False
        self.timings = FrameTimings()
        self.prep = self._prepare(self.headroom)
        # compiled without the mirror term when every χ of the scene is 0 (exact; see
        # renderer.mirror_needed): the materials are the scene's for the whole session
        from ..rendering import mirror_needed

        self._mirror = mirror_needed(self.prep.materials)
        if ir_reuse_mm is not None and not (np.isfinite(ir_reuse_mm) and ir_reuse_mm >= 0):
            raise InputError(f"must be a number >= 0 or None, got {ir_reuse_mm!r}",
                             field="ir_reuse_mm")
        self.ir_reuse_mm = None if ir_reuse_mm is None else float(ir_reuse_mm)
        self.ir_updates = 0
        self.ir_reuses = 0
        self._senders: dict[Any, Any] = {}  # device -> the current senders' half there
        self._senders_key: Any = None
        self._corners = _object_corners(self.prep)

    # ------------------------------------------------------------------ preparation

    def _init_cpu(self, scene: Scene, size: tuple[int, int] | None, *,
                  detect_downscale: int | None = None) -> None:
        """The CPU side: intrinsics at the frame size, marker detector and tracker,
        undistortion maps, frame buffers (``self.scene``, ``self.size``, ...)."""
        from ._markers import MarkerDetector, MarkerTracker

        h, w = size or (scene.height, scene.width)
        if scene.camera.intrinsics is not None and abs(
                (w / h) / (scene.width / scene.height) - 1) > 0.01:
            raise InputError(f"the video is {w}x{h} but the camera was calibrated at "
                             f"{scene.width}x{scene.height} ([frame] and [camera] "
                             "intrinsics), another aspect ratio; recalibrate", path=scene.path,
                             field="frame")
        if not any(o.marker is not None for o in scene.objects):
            raise InputError("no object has a marker id: nothing to place", path=scene.path,
                             field="objects")
        self.k, self.dist = scene_intrinsics(scene, (h, w))
        if scene.camera.intrinsics is not None:
            i = {"fx": self.k[0, 0], "fy": self.k[1, 1], "cx": self.k[0, 2], "cy": self.k[1, 2]}
            scene = scene.replace(camera=dataclasses.replace(scene.camera, intrinsics=i))
        scene = scene.replace(width=w, height=h)
        self.scene = scene
        self.size = (h, w)
        spec = scene.markers or _default_markers()
        expect = {o.marker for o in scene.objects if o.marker is not None}
        if spec.world is not None:
            expect.add(spec.world)
        self.detector = MarkerDetector(spec, self.k, self.dist, expect=expect,
                                       downscale=detect_downscale)
        self.tracker = MarkerTracker(scene)
        self._maps = None
        self._ring = [np.empty((h, w, 3), np.uint8) for _ in range(_RING)]
        self._ring_next = 0
        self._last_detect = 0.0
        if self.dist is not None and np.any(self.dist != 0) and self.lens == "undistort":
            from ._calibration import undistort_maps

            self._maps = undistort_maps(self.k, self.dist, (h, w))

    def _planning_scene(self) -> Scene:
        """The scene with marker-attached objects side by side at ``plan_distance`` in front
        of the configured camera (their screen footprint sizes the buffers)."""
        objs = []
        x = 0.0
        cam = self.scene.camera
        fwd = np.subtract(cam.look_at, cam.position)
        fwd = fwd / np.linalg.norm(fwd)
        right = np.cross(fwd, cam.up)
        right = right / np.linalg.norm(right)
        for o in self.scene.objects:
            if o.marker is None:
                objs.append(o)
                continue
            r = o.radius * o.scale
            pos = np.asarray(cam.position) + self.plan_distance * fwd + (x + r) * right
            x += 2.2 * r
            objs.append(dataclasses.replace(o, position=tuple(float(v) for v in pos)))
        # "undistort": the render is an ideal pinhole, the frames are undistorted instead;
        # "distort": the render goes through the lens the markers were detected with
        dist = (None if self.lens == "undistort" or self.dist is None
                else tuple(float(c) for c in self.dist))
        camera = dataclasses.replace(cam, distortion=dist)
        return self.scene.replace(objects=tuple(objs), camera=camera)

    def _replan(self, poses: Any, headroom: float, *, interreflection: bool = False) -> bool:
        """Grow the buffers to fit ``poses`` (× ``headroom``), and the interreflection's
        pass-1 rasters to their generic capacities after they overflowed; True when they
        changed (the next render recompiles)."""
        from ..geometry import RasterConfig
        from ..rendering import camera_clip, ir_fallback, plan_capacities

        p = self.prep
        ir_cfg = ir_fallback(p) if interreflection else None
        if ir_cfg is not None:
            p = self.prep = dataclasses.replace(p, ir_raster_config=ir_cfg)
        v = np.asarray(p.vertices, np.float64)
        m = np.asarray(poses.model, np.float64)[np.asarray(p.vertex_object)]
        world = np.einsum("vij,vj->vi", m[:, :3, :3], v) + m[:, :3, 3]
        clip = camera_clip(np.asarray(p.projection, np.float64),
                            np.asarray(poses.view, np.float64),
                            None if p.lens is None else np.asarray(p.lens, np.float64), world,
                            np)
        cfg, _ = plan_capacities(clip, np.asarray(p.triangles), p.shape, headroom=headroom,
                                 cull=p.cull)
        old = p.raster_config
        cfg = RasterConfig(old.tile_sizes, tuple(max(a, b, _MIN_WINDOWS) for a, b in zip(
            cfg.capacities, old.capacities, strict=True)),
            max(cfg.block_capacity, old.block_capacity))
        h, w = p.shape
        tris = np.asarray(p.triangles)
        caps = []
        for (ta, tb), c in zip(p.triangle_slices, p.pixel_capacity, strict=True):
            _, bound = plan_capacities(clip, tris[ta:tb], p.shape, headroom=headroom,
                                       cull=p.cull)
            caps.append(max(c, _pixel_slots(headroom * bound, h * w)))
        cap = tuple(caps)
        clusters = _planned_clusters(p, poses, headroom)
        if cfg == old and cap == p.pixel_capacity and clusters is p.clusters:
            return ir_cfg is not None
        self.prep = dataclasses.replace(p, raster_config=cfg, pixel_capacity=cap,
                                        clusters=clusters)
        return True

    def _prepare(self, headroom: float) -> Any:
        from ..rendering import prepare_cached, with_output

        h, w = self.size
        # kept on disk (startup's cache; SPECTRAL_FIT_CACHE="" turns it off): a session of
        # the same config, camera and options starts from the stored prepared scene
        prep = prepare_cached(self._planning_scene(), size=(w, h), headroom=headroom,
                              **self._options)
        return with_output(prep, camera_output_matrix(prep, self.camera))

    # ------------------------------------------------------------------ growing ahead

    def _grown_plan(self, stats: dict[str, Any]) -> Any:
        """``self.prep`` with every buffer that this frame filled past ``grow_ahead`` grown
        to ``headroom`` × its use, and at least to where that use is below ``grow_ahead``
        (on the capacity ladders); None when none is that full."""
        from ..geometry import grown_clusters

        p, f = self.prep, self.grow_ahead
        hr = max(self.headroom, 1.0 / f)
        counts = np.asarray(stats["object_counts"]).tolist()
        cfg = p.raster_config.grown(np.asarray(stats["raster_needed"]), hr, full=f)
        h, w = p.shape
        new_pix = tuple(max(c, _pixel_slots(hr * n, h * w)) if n > f * c else c
                        for c, n in zip(p.pixel_capacity, counts, strict=True))
        clusters = grown_clusters(p.clusters, int(stats["clusters_needed"]), hr, full=f)
        if (cfg == p.raster_config and new_pix == tuple(p.pixel_capacity)
                and clusters is p.clusters):
            return None
        return dataclasses.replace(p, raster_config=cfg, pixel_capacity=new_pix,
                                   clusters=clusters)

    def _maybe_grow(self, stats: dict[str, Any], poses: Any, background: Any) -> None:
        """Start the background compile of grown buffers when this frame (rendered with the
        current plan) filled one past ``grow_ahead``; nothing while one is under way."""
        if (self.grow_ahead is None or self._grown is not None
                or (self._grow_thread is not None and self._grow_thread.is_alive())):
            return
        grown = self._grown_plan(stats)
        if grown is None:
            return
        base = self.prep
        host = (np.asarray(poses.model), np.asarray(poses.view), np.asarray(poses.visible))
        stop = self._grow_stop = threading.Event()

        def work() -> None:
            # the grown step (and the senders' half, whose program also takes the prepared
            # scene) compiled and run once on every device, on this frame's inputs; between
            # those steps it ends early when asked to (stop_background)
            from ..rendering import render_senders

            copies: dict[Any, Any] = {}
            try:
                for dev in self.devices:
                    if stop.is_set():
                        return
                    if len(self.devices) == 1:
                        placed, cam, put = grown, self.camera, jnp.asarray
                    else:
                        placed, cam = put_on_device(grown, dev), put_on_device(self.camera, dev)
                        copies[dev] = (grown, placed, cam)
                        put = functools.partial(jax.device_put, device=dev)
                    model, view, visible = (put(x) for x in host)
                    senders = None
                    if self._reuses_senders(grown):
                        senders = render_senders(placed, placed.materials, model=model,
                                                 visible=visible, mirror=self._mirror)
                        if stop.is_set():
                            return
                    out, _ = live_step(placed, placed.materials, model, view, visible,
                                   put(background), cam, self._mirror, senders)
                    if stop.is_set():
                        return
                    jax.block_until_ready(out)
            except Exception:  # e.g. out of memory: the blocking path stays in charge
                return
            if not stop.is_set():
                self._grown = (base, grown, copies)

        # not a daemon: an interpreter that exits during the compile waits for it (a daemon
        # thread stopped inside XLA's compiler aborts the process)
        self._grow_thread = threading.Thread(target=work, name="spectral_fit-grow-ahead")
        self._grow_thread.start()

    def _adopt_grown(self) -> bool:
        """Switch to the grown buffers compiled in the background (if they grew from the
        current plan; a plan re-made since then drops them). True when switched."""
        grown, self._grown = self._grown, None
        if grown is None or grown[0] is not self.prep:
            return False
        self.prep = grown[1]
        self._copies.update(grown[2])
        self.replans_ahead += 1
        return True

    @property
    def growing(self) -> bool:
        """Whether a background compile of grown buffers is under way."""
        return self._grow_thread is not None and self._grow_thread.is_alive()

    def join_background(self) -> None:
        """Wait for a background compile of grown buffers, if one is under way (the session
        switches to them at its next frame). An interpreter that exits waits for it too."""
        t = self._grow_thread
        if t is not None:
            t.join()

    def stop_background(self) -> None:
        """Ask a background compile of grown buffers, if one is under way, to stop at its
        next step (a trace, a compile or a run on one device: XLA's compiler cannot be
        interrupted) and wait for it; the session keeps its current buffers. For the end of
        a run, when no frame will use the grown ones: an interpreter that exits waits for
        the whole compile otherwise, seconds after the last frame."""
        if self._grow_stop is not None:
            self._grow_stop.set()
        self.join_background()

    def _wait_grown(self) -> bool:
        """After an overflow: wait for a background compile under way and switch to it;
        True when the session now has other buffers to render the frame with."""
        self.join_background()
        return self._adopt_grown()

    # ------------------------------------------------------------------ per frame

    def undistort(self, frame: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """The frame resampled onto the pinhole intrinsics (identity without distortion or
        with ``lens="distort"``), into ``out`` when given ((H, W, 3) uint8)."""
        if self._maps is None:
            if out is None:
                return frame
            np.copyto(out, frame)
            return out
        import cv2

        return cv2.remap(frame, self._maps[0], self._maps[1], cv2.INTER_LINEAR, dst=out)

    def render(self, poses: Any, background: Any) -> tuple[jax.Array, dict[str, Any]]:
        """Dispatch the compiled step (asynchronous; block on the result to time it), on
        the device that holds ``background`` (a committed ``jax.Array``), else the first
        of :attr:`devices`."""
        dev = _device_of(background, self.devices)
        if len(self.devices) == 1:
            bg, put = jnp.asarray(background), jnp.asarray
        else:
            bg = jax.device_put(background, dev)
            put = functools.partial(jax.device_put, device=dev)
        inputs = (put(poses.model), put(poses.view), put(poses.visible))
        return self._dispatch(poses, inputs, bg, plan=False)

    def _placed(self, dev: Any) -> tuple[Any, CameraModel]:
        """The prepared scene and camera model on device ``dev`` (copied once per prepared
        scene; with one device the session's own, uncommitted)."""
        if len(self.devices) == 1:
            return self.prep, self.camera
        c = self._copies.get(dev)
        if c is None or c[0] is not self.prep:
            c = (self.prep, put_on_device(self.prep, dev), put_on_device(self.camera, dev))
            self._copies[dev] = c
        return c[1], c[2]

    def _reuses_senders(self, p: Any) -> bool:
        """Whether frames take the senders' half from :func:`render_senders` (else the step
        computes it, or there is none)."""
        return not (self.ir_reuse_mm is None or p.ir_mode != "gather" or p.num_objects < 2
                    or p.ir_bounces < 1)

    def _senders_for(self, poses: Any, inputs: Any, dev: Any = None) -> Any:
        """The gather interreflection's senders' half for these poses, on device ``dev``:
        reused when no vertex moved more than ``ir_reuse_mm`` (and visibility and the
        prepared scene are the same; copied to another device once), else computed
        (dispatched) again; None when the step computes it itself."""
        if not self._reuses_senders(self.prep):
            return None
        from ..rendering import render_senders

        dev = self.devices[0] if dev is None else dev
        model = np.asarray(poses.model, np.float64)
        visible = np.asarray(poses.visible, bool)
        key = self._senders_key
        # hidden objects neither send nor receive: only the visible ones' motion counts
        if (key is not None and key[0] is self.prep and np.array_equal(key[2], visible)
                and _max_displacement(self._corners[visible], key[1][visible],
                                      model[visible]) <= self.ir_reuse_mm * 1e-3):
            self.ir_reuses += 1
            if dev not in self._senders:
                self._senders[dev] = put_on_device(next(iter(self._senders.values())), dev)
            return self._senders[dev]
        prep = self._placed(dev)[0]
        self._senders = {dev: render_senders(prep, prep.materials, model=inputs[0],
                                             visible=inputs[2], mirror=self._mirror)}
        self._senders_key = (self.prep, model, visible)
        self.ir_updates += 1
        return self._senders[dev]

    def _check(self, frame: np.ndarray) -> None:
        if frame.shape != (*self.size, 3) or frame.dtype != np.uint8:
            raise InputError(f"frame must be {(*self.size, 3)} uint8, got {frame.shape} "
                             f"{frame.dtype}", field="frame")

    def _cpu_stages(self, frame: np.ndarray) -> tuple[Any, Any, tuple[float, float, float]]:
        """Detect + track, then undistort into the next ring buffer and upload it (to the
        next of :attr:`devices` in turn)."""
        self._check(frame)
        t0 = time.perf_counter()
        poses = self.tracker.update(self.detector.detect(frame))
        t1 = time.perf_counter()
        self._last_detect = t1 - t0
        buf = self._ring[self._ring_next]
        self._ring_next = (self._ring_next + 1) % len(self._ring)
        if len(self.devices) == 1:
            put = jax.device_put
        else:
            put = functools.partial(jax.device_put,
                                    device=self.devices[self._device_turn % len(self.devices)])
            self._device_turn += 1
        bg = put(self.undistort(frame, out=buf))
        inputs = (put(poses.model), put(poses.view), put(poses.visible))
        t2 = time.perf_counter()
        return (poses, inputs), bg, (t0, t1, t2)

    def _dispatch(self, poses: Any, inputs: Any, bg: Any, *, plan: bool = True
                  ) -> tuple[Any, Any]:
        """The compiled step on the device that holds ``bg`` (asynchronous)."""
        if plan and not self._planned and poses.visible.any():
            self._replan(poses, self.headroom)  # size the buffers on the first real poses
            self._planned = True
        if self._grown is not None:
            self._adopt_grown()
        dev = _device_of(bg, self.devices)
        prep, camera = self._placed(dev)
        return live_step(prep, prep.materials, *inputs, bg, camera, self._mirror,
                     self._senders_for(poses, inputs, dev))

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
@dataclasses.dataclass
class _Pending:
    """A submitted frame (see :meth:`LiveSession.submit`)."""

    poses: Any
    background: np.ndarray
    out: Any
    stats: dict[str, Any]
    times: tuple[float, float, float]
    prep: Any = None  # the session's prepared scene when it was dispatched


def _object_corners(prep: Any) -> np.ndarray:
    """(O, 8, 4) homogeneous corners of each object's bounding box in its own frame."""
    v = np.asarray(prep.vertices, np.float64)
    out = []
    for a, b in prep.object_slices:
        lo, hi = v[a:b].min(axis=0), v[a:b].max(axis=0)
        c = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                      for z in (lo[2], hi[2])])
        out.append(c)
    return np.stack(out)


def _max_displacement(corners: np.ndarray, model_a: np.ndarray, model_b: np.ndarray) -> float:
    """The largest distance (m) any point of an object's bounding box moves between the
    world-from-object matrices ``model_a`` and ``model_b`` (O, 4, 4): the displacement of an
    affine map is a convex function of the point, so its maximum over the box is at a
    corner, and it bounds every vertex's. 0 for no objects (O = 0)."""
    if len(corners) == 0:
        return 0.0
    d = np.einsum("oij,okj->oki", model_b - model_a, corners)[..., :3]
    return float(np.sqrt(np.max(np.sum(d * d, axis=-1))))


def _frame_devices(devices: Any) -> tuple[Any, ...]:
    """The session's rendering devices (see :class:`LiveSession` ``devices``)."""
    if devices is None:
        if jax.default_backend() == "cpu":
            return tuple(jax.devices("cpu"))
        return (jax.devices()[0],)
    if isinstance(devices, jax.Device):
        devices = (devices,)
    try:
        out = tuple(devices)
    except TypeError:
        out = ()
    if not out or not all(isinstance(d, jax.Device) for d in out):
        raise InputError(f"expected a sequence of jax devices, got {devices!r}",
                         field="devices")
    if len(set(out)) != len(out) or len({d.platform for d in out}) != 1:
        raise InputError(f"expected distinct devices of one platform, got {out!r}",
                         field="devices")
    return out


def _device_of(x: Any, devices: tuple[Any, ...]) -> Any:
    """The device that holds ``x`` when it is one of ``devices`` (a committed array), else
    the first of them."""
    if len(devices) > 1 and isinstance(x, jax.Array):
        held = x.devices()
        if len(held) == 1:
            (d,) = held
            if d in devices:
                return d
    return devices[0]


def _planned_clusters(prep: Any, poses: Any, headroom: float) -> Any:
    """``prep.clusters`` with its kept list grown to ``headroom`` × the clusters kept at
    ``poses`` (never shrunk; the same object when unchanged, None without clusters)."""
    from ..geometry import count_clusters, sized

    cl = prep.clusters
    if cl is None:
        return None
    n = count_clusters(cl, np.asarray(poses.model), np.asarray(poses.view),
                       np.asarray(prep.projection), cull=prep.cull)
    return sized(cl, headroom * n + 4, at_least=cl.capacity)


def _pixel_slots(pixels: float, frame_pixels: int) -> int:
    """An object's covered-pixel capacity for ``pixels`` (headroom included): + 64, rounded
    up to a multiple of 1024, at most the frame's pixels."""
    return min(frame_pixels, 1024 * -(-int(pixels + 64) // 1024))


def put_on_device(tree: Any, device: Any) -> Any:
    """``tree`` with its arrays committed to ``device`` (other leaves unchanged: they are
    static parts of the compiled step)."""
    return jax.tree_util.tree_map(
        lambda x: jax.device_put(x, device) if isinstance(x, jax.Array | np.ndarray) else x,
        tree)


def _default_markers():
    from ..io import MarkerSpec

    return MarkerSpec()
