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
:class:`~spectral_fit.rendering.Prepared` matrix ``colour.to_xyz`` (channels → XYZ) is replaced
by channels → camera RGB (``to_spectrum @ camera.spectral_weights``), so the camera's spectral
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
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from ..io import Scene
from ._compositing import CameraModel, relight_codes
from ._devices import _device_of, _frame_devices, put_on_device
from ._frames import FramesInFlight, FrameTimings
from ._grow_ahead import GrowAhead, _pixel_slots
from ._scene_camera import scene_camera_model, scene_intrinsics
from ._senders_reuse import SendersReuse, _object_corners
from ._step import camera_output_matrix, camera_spectral_matrix, live_step

if TYPE_CHECKING:  # for annotations (the renderer is imported where it is used)
    from ..geometry import TriangleClusters
    from ..rendering import Prepared

__all__ = ["LiveSession"]

# windows of every raster size in a live plan at least: a size that the first poses do not
# use (triangles larger than 4 pixels) is planned at the ladder's floor, 16, and an object
# coming closer goes from none to some dozens of them in one frame (as on the sample video),
# too fast for growing ahead. 64 of them cost nothing measurable in a frame
_MIN_WINDOWS = 64

#: background buffers in the ring (frames queued + in flight + being written, with margin)
_RING = 6


class LiveSession(FramesInFlight, GrowAhead, SendersReuse):
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
        # the real surfaces' shadows and light: built for the tracked placement of the
        # objects, rebuilt when one moves more than surface_reuse_mm / _deg relative to them
        self.surface_reuse_mm = 3.0
        self.surface_reuse_deg = 1.0
        self.surface_builds = 0
        self._surface_state: tuple[Any, Any, Any] | None = None  # (visible, model, textures)
        self._surface_next: tuple[Any, Any, Any, Any] | None = None  # a background build
        self._surface_thread: threading.Thread | None = None

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
            p = self.prep = p.with_buffers(ir_raster_config=ir_cfg)
        mesh, cam, buf = p.mesh, p.camera, p.buffers
        v = np.asarray(mesh.vertices, np.float64)
        m = np.asarray(poses.model, np.float64)[np.asarray(mesh.vertex_object)]
        world = np.einsum("vij,vj->vi", m[:, :3, :3], v) + m[:, :3, 3]
        clip = camera_clip(np.asarray(cam.projection, np.float64),
                            np.asarray(poses.view, np.float64),
                            None if cam.lens is None else np.asarray(cam.lens, np.float64),
                            world, np)
        tris = np.asarray(mesh.triangles)
        cfg, _ = plan_capacities(clip, tris, cam.shape, headroom=headroom, cull=cam.cull)
        old = buf.raster_config
        cfg = RasterConfig(old.tile_sizes, tuple(max(a, b, _MIN_WINDOWS) for a, b in zip(
            cfg.capacities, old.capacities, strict=True)),
            max(cfg.block_capacity, old.block_capacity))
        h, w = cam.shape
        caps = []
        for (ta, tb), c in zip(mesh.triangle_slices, buf.pixel_capacity, strict=True):
            _, bound = plan_capacities(clip, tris[ta:tb], cam.shape, headroom=headroom,
                                       cull=cam.cull)
            caps.append(max(c, _pixel_slots(headroom * bound, h * w)))
        cap = tuple(caps)
        clusters = _planned_clusters(p, poses, headroom)
        if cfg == old and cap == buf.pixel_capacity and clusters is buf.clusters:
            return ir_cfg is not None
        self.prep = p.with_buffers(raster_config=cfg, pixel_capacity=cap, clusters=clusters)
        return True

    def _prepare(self, headroom: float) -> Prepared:
        from ..rendering import prepare_cached, with_output

        h, w = self.size
        # kept on disk (startup's cache; SPECTRAL_FIT_CACHE="" turns it off): a session of
        # the same config, camera and options starts from the stored prepared scene
        # the planes' shadows are built from the tracked poses (_surfaces_for), not from
        # the planning scene's stand-in placement
        prep = prepare_cached(self._planning_scene(), size=(w, h), headroom=headroom,
                              surfaces=False, **self._options)
        return with_output(prep, camera_output_matrix(prep, self.camera))

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

    def _placed(self, dev: Any) -> tuple[Prepared, CameraModel]:
        """The prepared scene and camera model on device ``dev`` (copied once per prepared
        scene; with one device the session's own, uncommitted)."""
        if len(self.devices) == 1:
            return self.prep, self.camera
        c = self._copies.get(dev)
        if c is None or c[0] is not self.prep:
            c = (self.prep, put_on_device(self.prep, dev), put_on_device(self.camera, dev))
            self._copies[dev] = c
        return c[1], c[2]

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
        textures = self.surface_textures_for(poses)  # may renew self.prep's table change
        prep, camera = self._placed(dev)
        return live_step(prep, prep.materials, *inputs, bg, camera, self._mirror,
                         self._senders_for(poses, inputs, dev), textures)

    def surface_textures_for(self, poses: Any, *, rebuild: bool = False) -> Any:
        """What the step relights the video with for the visible objects at ``poses``: the
        ``[[surfaces]]`` planes' ratio textures (camera channels) and the camera's
        :func:`relight_codes`. Built when an object appears or vanishes (at once: a shadow must not
        outlive its object); when one moves more than ``surface_reuse_mm`` /
        ``surface_reuse_deg``, built again in a background thread while the frames keep the
        last ones (a build takes a second or more on a CPU; the step's program stays the
        same while the texture shapes hold). None without surfaces or visible objects.
        ``rebuild``: build them now even if the objects stayed."""
        if not self.scene.surfaces:
            return None
        vis = np.asarray(poses.visible, bool)
        if not vis.any():
            return None
        model = np.asarray(poses.model, np.float64)
        if self._surface_next is not None:  # a background build finished
            self._adopt_surfaces(self._surface_next)
            self._surface_next = None
        st = self._surface_state
        if st is None or rebuild or not np.array_equal(st[0], vis):
            self._adopt_surfaces(self._build_surfaces(vis, model))
            return self._surface_state[2]
        moved = np.linalg.norm(model[vis, :3, 3] - st[1][vis, :3, 3], axis=1).max()
        rot = np.einsum("oij,oik->ojk", model[vis, :3, :3], st[1][vis, :3, :3])
        cos = np.clip((np.trace(rot, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
        turned = np.degrees(np.arccos(cos)).max()
        if moved * 1e3 > self.surface_reuse_mm or turned > self.surface_reuse_deg:
            t = self._surface_thread
            if t is None or not t.is_alive():
                def work(v: np.ndarray = vis, m: np.ndarray = model) -> None:
                    self._surface_next = self._build_surfaces(v, m)

                # not a daemon (as the grow-ahead thread: XLA must not be stopped mid-call)
                self._surface_thread = threading.Thread(target=work,
                                                        name="spectral_fit-surfaces")
                self._surface_thread.start()
        return st[2]

    def _build_surfaces(self, vis: np.ndarray, model: np.ndarray
                        ) -> tuple[Any, Any, Any, Any]:
        """(visible, model, what the step relights the video with (the planes' ratio
        textures in the camera's linear RGB and :func:`relight_codes`), what the objects see
        of the planes' change)."""
        from ..rendering import (
            neighbour_irradiance,
            surface_ratio_textures,
            surface_textures,
            surface_transfer,
            table_changes,
        )

        prep = self.prep
        transfers = surface_transfer(self.scene.surfaces, prep.lighting.env, prep.ir_mesh,
                                     model, visible=vis)
        near = neighbour_irradiance(prep, prep.materials, model=jnp.asarray(model, jnp.float32),
                                    visible=jnp.asarray(vis, bool))
        textures = surface_textures(prep, transfers, prep.materials, model=model,
                                    out=camera_spectral_matrix(prep, self.camera),
                                    neighbours=near)
        relit = (surface_ratio_textures(textures), relight_codes(self.camera))
        changes = table_changes(prep, transfers, prep.materials, model, neighbours=near)
        self.surface_builds += 1
        return vis, model, jax.block_until_ready(relit), jax.block_until_ready(changes)

    def _adopt_surfaces(self, built: tuple[Any, Any, Any, Any]) -> None:
        """Use a build: its textures for the frames, its change in the prepared scene (the
        objects' pixels see it; same shapes from one build to the next: no recompile)."""
        import dataclasses

        self._surface_state = built[:3]
        self.prep = dataclasses.replace(self.prep, surface_changes=built[3])


def _planned_clusters(prep: Prepared, poses: Any, headroom: float
                      ) -> TriangleClusters | None:
    """``prep.buffers.clusters`` with its kept list grown to ``headroom`` × the clusters kept
    at ``poses`` (never shrunk; the same object when unchanged, None without clusters)."""
    from ..geometry import count_clusters, sized

    cl = prep.buffers.clusters
    if cl is None:
        return None
    n = count_clusters(cl, np.asarray(poses.model), np.asarray(poses.view),
                       np.asarray(prep.camera.projection), cull=prep.camera.cull)
    return sized(cl, headroom * n + 4, at_least=cl.capacity)


def _default_markers():
    from ..io import MarkerSpec

    return MarkerSpec()
