"""Fiducial markers: ArUco detection, marker poses, objects attached to markers.

The modern counterpart of the paper's NyARToolkit ID markers (80 mm): OpenCV ArUco / AprilTag
dictionaries, chosen with the scene's ``[markers]`` table (:class:`spectral_fit.io.MarkerSpec`).

Pipeline per frame::

    frame (H, W, 3) uint8 ──ArucoDetector──▶ corners (4, 2) px per id (distorted image)
        ──solvePnP (IPPE_SQUARE, then Levenberg–Marquardt; K and distortion)──▶ (R, t) per id
        ──MarkerTracker──▶ model (O, 4, 4) world-from-object, view (4, 4), visible (O,) bool

Frames (see also :mod:`spectral_fit.live`):

* OpenCV marker frame: origin at the black square's centre, +X right, +Y towards the marker's
  top edge, +Z out of the paper; corners in the order top-left, top-right, bottom-right,
  bottom-left at (∓s/2, ±s/2, 0). (R, t): x_cam = R·x_marker + t, metres.
* Marker "ground" frame (used for offsets): the same origin with +Y = the marker's normal and
  −Z = its top edge, so that a marker lying on a table has the world's Y-up axes.
  ``marker_offset = [0, r, 0]`` puts a sphere of radius r ON the marker.
* The OpenCV → OpenGL axis change happens only in :func:`spectral_fit.geometry.opencv_pose_to_view`.

Object placement: an object with ``marker = id`` sits at
``eye_from_object = eye_from_ground(id) · T(marker_offset) · Rz·Ry·Rx(rotation_deg) · scale``
(its ``position`` is ignored); objects without a marker keep their config placement in world
coordinates. The world frame is the ``[markers] world`` marker's ground frame when one is named
(so the environment map stays fixed to the table while the camera moves), otherwise the scene
camera's configured frame (a static camera). ``model = view⁻¹ · eye_from_object``.

A lost marker: the object keeps its last pose for ``hold_frames`` frames, then ``visible`` turns
False (the renderer masks it out). Array shapes never change, so nothing recompiles. With
``smoothing = s`` the reported pose is ``s · previous + (1 − s) · measured`` (translation
linearly; rotation blended and projected back onto SO(3)); a marker that reappears after being
masked starts afresh.

Requires the optional ``live`` extra (opencv-python-headless).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from .._runtime.errors import InputError
from ..io import MarkerSpec, Scene

__all__ = [
    "MarkerDetection",
    "MarkerDetector",
    "MarkerTracker",
    "Poses",
    "aruco_dictionary",
    "marker_object_points",
    "estimate_marker_pose",
    "refine_corners_by_edges",
    "ground_frame",
]

#: OpenCV marker frame -> ground frame (x, y, z) -> (x, z, -y); see the module docstring
_GROUND_FROM_MARKER = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _cv2() -> Any:
    try:
        import cv2
    except ImportError:  # pragma: no cover - depends on the installation
        raise InputError("marker tracking needs OpenCV: pip install 'spectral_fit[live]'",
                         field="markers") from None
    return cv2


def aruco_dictionary(name: str) -> Any:
    """OpenCV predefined dictionary ``name`` (e.g. "DICT_5X5_100")."""
    cv2 = _cv2()
    code = getattr(cv2.aruco, name, None)
    if not name.startswith("DICT_") or code is None:
        raise InputError(f"unknown marker dictionary {name!r}", field="markers.dictionary")
    return cv2.aruco.getPredefinedDictionary(code)


def marker_object_points(size: float) -> np.ndarray:
    """(4, 3) corners of a square marker of side ``size`` (m) in its OpenCV frame, in
    ArUco order (top-left, top-right, bottom-right, bottom-left)."""
    h = size / 2
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


@dataclasses.dataclass(frozen=True, eq=False)
class MarkerDetection:
    """One detected marker: ``corners`` (4, 2) distorted pixel coordinates (OpenCV: pixel
    (0, 0)'s centre at (0, 0)), pose ``rotation`` (3, 3) and ``translation`` (3,) m with
    x_cam = R·x_marker + t, and the RMS corner reprojection error in pixels."""

    marker_id: int
    corners: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    reprojection_px: float


def estimate_marker_pose(corners, size: float, k, dist=None
                         ) -> tuple[np.ndarray, np.ndarray, float]:
    """Pose (R (3, 3), t (3,), RMS reprojection error px) of a square marker of side ``size``
    (m) from its four image corners (4, 2) (ArUco order), intrinsics ``k`` (3×3) and OpenCV
    distortion ``dist``: IPPE for squares (picks the better of the two planar solutions), then
    Levenberg–Marquardt refinement."""
    cv2 = _cv2()
    obj = marker_object_points(size)
    img = np.asarray(corners, np.float64).reshape(4, 1, 2)
    k = np.asarray(k, np.float64)
    d = np.zeros(5) if dist is None else np.asarray(dist, np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, k, d, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    if not ok:
        raise InputError("solvePnP failed for a marker", field="markers")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, k, d, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, k, d)
    err = float(np.sqrt(np.mean(np.sum((proj.reshape(4, 2) - img.reshape(4, 2)) ** 2, -1))))
    r, _ = cv2.Rodrigues(rvec)
    return r, tvec.reshape(3), err


def refine_corners_by_edges(grey: np.ndarray, corners, k, dist=None, *, samples: int = 24,
                            half_width: float = 4.0, levels: np.ndarray | None = None
                            ) -> np.ndarray:
    """Corners (4, 2) in NORMALISED undistorted coordinates (x/z, y/z) from the marker's four
    outer edges: along each side, the black-to-white crossing at half contrast of a profile
    across the edge (unbiased for a symmetric blur, unlike corner-based refinement, which pulls
    blurred convex corners inwards), undistorted, fitted with a straight line (total least
    squares); adjacent lines intersect at the corners.

    ``grey``: (H, W) image; ``corners``: (4, 2) approximate pixel corners (ArUco order);
    ``levels``: (256,) what each grey level of a uint8 ``grey`` stands for (e.g. linear light
    × 255, to find the crossings in linear light), None: the levels themselves.
    """
    cv2 = _cv2()
    c = np.asarray(corners, np.float64).reshape(4, 2)
    centre = c.mean(0)
    ts = np.linspace(0.15, 0.85, samples)
    offs = np.linspace(-half_width, half_width, int(4 * half_width) + 1)
    a, b = c, np.roll(c, -1, axis=0)  # edge e runs from corner e to corner e + 1
    d = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    n = np.stack([-d[:, 1], d[:, 0]], 1)
    flip = np.sum(n * ((a + b) / 2 - centre), axis=1) < 0
    n[flip] = -n[flip]  # outward normals: profiles go from black (inside) to white
    base = a[:, None] + ts[None, :, None] * (b - a)[:, None]  # (4, S, 2)
    pts = base[:, :, None, :] + offs[None, None, :, None] * n[:, None, None, :]  # (4, S, P, 2)
    # sample a float copy of the marker's neighbourhood only (sub-level precision)
    gh, gw = grey.shape[:2]
    x0, y0 = (max(0, min(int(np.floor(pts[..., i].min())) - 2, lim - 1))
              for i, lim in ((0, gw), (1, gh)))
    x1, y1 = (max(int(np.ceil(pts[..., i].max())) + 3, v + 1)
              for i, v in ((0, x0), (1, y0)))
    g = (np.asarray(grey[y0:y1, x0:x1], np.float32) if levels is None else
         np.asarray(levels, np.float32)[grey[y0:y1, x0:x1]])
    flat = (pts.reshape(4 * samples, offs.size, 2) - [x0, y0]).astype(np.float32)
    prof = cv2.remap(g, flat[..., 0], flat[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    prof = prof.reshape(4, samples, offs.size)
    lo = prof[..., :3].mean(-1)
    hi = prof[..., -3:].mean(-1)
    level = (lo + hi) / 2
    above = prof >= level[..., None]
    rise = above[..., 1:] & ~above[..., :-1]
    ok = ((hi - lo) > 20.0) & (rise.sum(-1) == 1)  # one clean black-to-white crossing
    j = np.argmax(rise, axis=-1)
    p0 = np.take_along_axis(prof, j[..., None], -1)[..., 0]
    p1 = np.take_along_axis(prof, j[..., None] + 1, -1)[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        f = (level - p0) / (p1 - p0)
    off = offs[j] + f * (offs[1] - offs[0])
    edge_pts = base + off[..., None] * n[:, None, :]  # (4, S, 2)
    if np.any(ok.sum(1) < 4):
        raise ValueError("edge refinement failed")
    kk = np.asarray(k, np.float64)
    dd = np.zeros(5) if dist is None else np.asarray(dist, np.float64)
    und = cv2.undistortPoints(edge_pts[ok].reshape(-1, 1, 2), kk, dd).reshape(-1, 2)
    which = np.nonzero(ok)[0]
    lines = []
    for e in range(4):
        q = und[which == e]
        m = q.mean(0)
        _, _, vt = np.linalg.svd(q - m)
        normal = vt[1]
        lines.append(np.array([normal[0], normal[1], -normal @ m]))  # a x + b y + c = 0
    out = []
    for e in range(4):
        p = np.cross(lines[(e - 1) % 4], lines[e])  # corner e lies on edges e-1 and e
        out.append(p[:2] / p[2])
    return np.asarray(out)


class MarkerDetector:
    """ArUco detection and per-marker pose for one camera.

    Args:
        spec: the scene's :class:`~spectral_fit.io.MarkerSpec`.
        k: intrinsics (3×3, OpenCV).
        dist: distortion coefficients (OpenCV order) or None. Detection runs on the raw
            (distorted) frame; the poses account for the distortion.
        downscale: detect the markers' squares on the frame shrunk by this integer factor
            (``cv2.INTER_AREA``; ~5× cheaper at 2), then refine every corner on the
            full-resolution frame (``cv2.cornerSubPix``, then the edge lines when
            ``spec.refine == "edges"``), so the poses keep full-resolution accuracy. None
            (default): 2 for frames whose shorter side is at least 400 px, else 1, and 1 with
            ``refine = "none"``. Refinements "contour" and "apriltag" (done inside OpenCV's
            detector) always detect at 1.
        track: markers found in the previous frame but missed by the downscaled detection
            are searched again at full resolution in a window around their last corners
            (small or distant markers), so downscaling loses no marker that full resolution
            finds frame to frame.
        expect: ids the caller needs (e.g. the scene's markers). While one of them is neither
            found nor tracked, the whole frame is also searched at full resolution, once every
            ``rescan`` frames (markers too small for the shrunk frame are picked up there, and
            then tracked).
        rescan: see ``expect``.
    """

    def __init__(self, spec: MarkerSpec, k, dist=None, *, downscale: int | None = None,
                 track: bool = True, expect=None, rescan: int = 8) -> None:
        cv2 = _cv2()
        self.spec = spec
        self.k = np.asarray(k, np.float64)
        self.dist = None if dist is None else np.asarray(dist, np.float64)
        if downscale is not None and (int(downscale) != downscale or downscale < 1):
            raise InputError(f"must be a positive integer, got {downscale!r}",
                             field="downscale")
        self.downscale = None if downscale is None else int(downscale)
        self.track = bool(track)
        self.expect = frozenset(int(i) for i in (expect or ()))
        self.rescan = max(1, int(rescan))
        self._since_scan = self.rescan  # the first frame with a missing id is scanned
        self.full_scans = 0  # full-resolution scans so far (for tests and reports)
        self._last: dict[int, np.ndarray] = {}
        self._grey: np.ndarray | None = None
        self._small: np.ndarray | None = None
        self._levels = _linear_levels(getattr(spec, "tone", "none"), getattr(spec, "gamma", 2.2))
        method = {
            "none": cv2.aruco.CORNER_REFINE_NONE, "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
            "edges": cv2.aruco.CORNER_REFINE_SUBPIX,
            "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
            "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG}[spec.refine]
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = method
        dic = aruco_dictionary(spec.dictionary)
        self._cells = int(dic.markerSize) + 2  # modules across a marker, black border included
        self._detector = cv2.aruco.ArucoDetector(dic, params)
        coarse = cv2.aruco.DetectorParameters()  # corners refined at full resolution instead
        coarse.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
        self._coarse = cv2.aruco.ArucoDetector(dic, coarse)

    def _scale(self, shape: tuple[int, ...]) -> int:
        if self.spec.refine in ("contour", "apriltag"):
            return 1
        if self.downscale is not None:
            return self.downscale
        if self.spec.refine == "none":  # nothing would recover full-resolution corners
            return 1
        return 2 if min(shape[:2]) >= 400 else 1

    def _pose(self, grey: np.ndarray, c: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """(R, t, corners (4, 2) px, RMS reprojection px) of one marker."""
        if self.spec.refine == "edges":
            cv2 = _cv2()
            try:
                norm = refine_corners_by_edges(grey, c, self.k, self.dist,
                                               levels=self._levels)
            except ValueError:
                pass
            else:
                d = np.zeros(5) if self.dist is None else self.dist
                px, _ = cv2.projectPoints(np.concatenate([norm, np.ones((4, 1))], 1),
                                          np.zeros(3), np.zeros(3), self.k, d)
                px = px.reshape(4, 2)
                if np.all(np.isfinite(px)) and np.max(np.abs(px - c)) < 3.0:
                    r, t, err = estimate_marker_pose(px, self.spec.size, self.k, self.dist)
                    return r, t, px, err
        r, t, err = estimate_marker_pose(c, self.spec.size, self.k, self.dist)
        return r, t, c, err

    def _subpix(self, grey: np.ndarray, c: np.ndarray) -> np.ndarray:
        """Corners refined on the full-resolution frame (OpenCV's SUBPIX settings, window
        scaled to the marker's module as OpenCV's ``relativeCornerRefinmentWinSize`` does:
        a fixed 11×11 window reaches past a small marker's white margin and pulls the
        corner outwards)."""
        if self.spec.refine == "none":
            return c
        cv2 = _cv2()
        perimeter = float(np.sum(np.linalg.norm(c - np.roll(c, 1, axis=0), axis=1)))
        module = perimeter / (4 * self._cells)  # px per marker cell
        win = int(max(1, min(5, round(0.3 * module))))
        pts = np.ascontiguousarray(c, np.float32).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_MAX_ITER | cv2.TERM_CRITERIA_EPS, 30, 0.1)
        cv2.cornerSubPix(grey, pts, (win, win), (-1, -1), crit)
        return pts.reshape(4, 2).astype(np.float64)

    def _candidates(self, grey: np.ndarray) -> list[tuple[int, np.ndarray]]:
        """(id, corners (4, 2) full-resolution px) of every marker square found."""
        cv2 = _cv2()
        s = self._scale(grey.shape)
        out: list[tuple[int, np.ndarray]] = []
        if s == 1:
            corners, ids, _ = self._detector.detectMarkers(grey)
            if ids is not None:
                out = [(int(i), c.reshape(4, 2).astype(np.float64))
                       for c, i in zip(corners, ids.reshape(-1), strict=True)]
            return out
        h, w = grey.shape
        size = (w // s, h // s)
        if self._small is None or self._small.shape != (size[1], size[0]):
            self._small = np.empty((size[1], size[0]), np.uint8)
        cv2.resize(grey[: size[1] * s, : size[0] * s], size, dst=self._small,
                   interpolation=cv2.INTER_AREA)
        corners, ids, _ = self._coarse.detectMarkers(self._small)
        # a small pixel i covers full pixels s·i … s·i + s − 1: centre s·i + (s − 1)/2
        if ids is not None:
            out = [(int(i), self._subpix(grey, c.reshape(4, 2).astype(np.float64) * s
                                         + (s - 1) / 2))
                   for c, i in zip(corners, ids.reshape(-1), strict=True)]
        found = {i for i, _ in out}
        if self.track:
            for i, prev in self._last.items():
                if i not in found:
                    out.extend(self._search(grey, i, prev))
            found = {i for i, _ in out}
        self._since_scan += 1
        if self.expect - found and self._since_scan >= self.rescan:
            self._since_scan = 0
            self.full_scans += 1
            corners, ids, _ = self._detector.detectMarkers(grey)
            if ids is not None:
                out.extend((int(i), c.reshape(4, 2).astype(np.float64))
                           for c, i in zip(corners, ids.reshape(-1), strict=True)
                           if int(i) not in found)
        return out

    def _search(self, grey: np.ndarray, marker_id: int, prev: np.ndarray
                ) -> list[tuple[int, np.ndarray]]:
        """Full-resolution detection of ``marker_id`` in a window around its last corners."""
        h, w = grey.shape
        lo, hi = prev.min(0), prev.max(0)
        pad = np.maximum(0.5 * (hi - lo), 24.0)
        x0, y0 = np.maximum(np.floor(lo - pad), 0).astype(int)
        x1, y1 = np.minimum(np.ceil(hi + pad), [w, h]).astype(int)
        if x1 - x0 < 16 or y1 - y0 < 16:
            return []
        corners, ids, _ = self._detector.detectMarkers(grey[y0:y1, x0:x1])
        if ids is None:
            return []
        return [(marker_id, c.reshape(4, 2).astype(np.float64) + [x0, y0])
                for c, i in zip(corners, ids.reshape(-1), strict=True) if int(i) == marker_id]

    def detect(self, frame: np.ndarray) -> dict[int, MarkerDetection]:
        """Markers in ``frame`` ((H, W, 3) RGB or (H, W) grey, uint8), by id. A marker seen
        twice keeps the detection with the larger image area."""
        cv2 = _cv2()
        if frame.ndim == 2:
            grey = frame
        else:
            if self._grey is None or self._grey.shape != frame.shape[:2]:
                self._grey = np.empty(frame.shape[:2], np.uint8)
            grey = cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY, dst=self._grey)
        best: dict[int, np.ndarray] = {}
        for i, c in self._candidates(grey):
            if i in best and cv2.contourArea(c.astype(np.float32)) <= cv2.contourArea(
                    best[i].astype(np.float32)):
                continue
            best[i] = c
        out: dict[int, MarkerDetection] = {}
        for i, c in best.items():
            r, t, c, err = self._pose(grey, c)
            out[i] = MarkerDetection(i, c, r, t, err)
        self._last = {i: d.corners for i, d in out.items()}
        return out


def _linear_levels(tone: str, gamma: float) -> np.ndarray | None:
    """(256,) linear light × 255 of each 8-bit level under the tone curve ``tone`` ("srgb"
    or "gamma"), None for "none"."""
    v = np.arange(256) / 255.0
    if tone == "none":
        return None
    if tone == "srgb":
        lin = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
    elif tone == "gamma":
        lin = v ** float(gamma)
    else:
        raise InputError(f"must be 'none', 'srgb' or 'gamma', got {tone!r}",
                         field="markers.tone")
    return (255.0 * lin).astype(np.float32)


def ground_frame(rotation, translation) -> np.ndarray:
    """OpenGL eye-from-ground matrix (4×4) of a marker at OpenCV pose (R, t): the marker's
    ground frame (+Y = marker normal, −Z = its top edge) in OpenGL eye coordinates."""
    from ..geometry import opencv_pose_to_view

    r = np.asarray(rotation, np.float64) @ _GROUND_FROM_MARKER.T
    return np.asarray(opencv_pose_to_view(r, translation), np.float64)


class Poses:
    """What the renderer needs each frame: ``model`` (O, 4, 4) float32 world-from-object,
    ``view`` (4, 4) float32 world → OpenGL eye, ``visible`` (O,) bool. Shapes never change."""

    __slots__ = ("model", "view", "visible")

    def __init__(self, model: np.ndarray, view: np.ndarray, visible: np.ndarray) -> None:
        self.model = model
        self.view = view
        self.visible = visible


def _blend_rigid(prev: np.ndarray, new: np.ndarray, s: float) -> np.ndarray:
    """s·prev + (1 − s)·new for rigid 4×4 transforms; rotation projected onto SO(3)."""
    m = s * prev + (1.0 - s) * new
    u, _, vt = np.linalg.svd(m[:3, :3])
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    out = np.eye(4)
    out[:3, :3] = r
    out[:3, 3] = m[:3, 3]
    return out


class MarkerTracker:
    """Turns per-frame marker detections into object poses for the renderer (see the module
    docstring for frames, holding and smoothing).

    Args:
        scene: the scene (its objects' ``marker``/``marker_offset``; its ``[markers]`` table).
        spec: overrides ``scene.markers``.
    """

    def __init__(self, scene: Scene, spec: MarkerSpec | None = None) -> None:
        from ..geometry import look_at

        self.spec = spec or scene.markers or MarkerSpec()
        cam = scene.camera
        self._static_view = np.asarray(look_at(cam.position, cam.look_at, cam.up), np.float64)
        self._view = self._static_view.copy()
        self.marker_ids = [o.marker for o in scene.objects]
        self._local = np.stack([
            dataclasses.replace(o, position=o.marker_offset).model_matrix()
            if o.marker is not None else o.model_matrix() for o in scene.objects])
        o = len(scene.objects)
        self._eye_from_object = np.stack([self._view @ m for m in self._local])
        self._visible = np.array([m is None for m in self.marker_ids])
        self._ground: dict[int, np.ndarray] = {}
        self._missing: dict[int, int] = {}
        self.frames = 0
        assert self._eye_from_object.shape == (o, 4, 4)

    def _track(self, detections: dict[int, MarkerDetection]) -> None:
        s = self.spec.smoothing
        for i, d in detections.items():
            g = ground_frame(d.rotation, d.translation)
            fresh = self._missing.get(i, 0) > self.spec.hold_frames or i not in self._ground
            self._ground[i] = g if fresh or s == 0 else _blend_rigid(self._ground[i], g, s)
            self._missing[i] = 0
        for i in self._ground:
            if i not in detections:
                self._missing[i] = self._missing.get(i, 0) + 1

    def _alive(self, i: int | None) -> bool:
        return i is not None and i in self._ground and self._missing[i] <= self.spec.hold_frames

    def update(self, detections: dict[int, MarkerDetection]) -> Poses:
        """Poses after this frame's ``detections`` (from :meth:`MarkerDetector.detect`)."""
        self.frames += 1
        self._track(detections)
        w = self.spec.world
        if self._alive(w):
            self._view = self._ground[w]  # type: ignore[index]
        for j, mid in enumerate(self.marker_ids):
            if mid is None:
                self._eye_from_object[j] = self._view @ self._local[j]
                continue
            alive = self._alive(mid)
            self._visible[j] = alive
            if alive:
                self._eye_from_object[j] = self._ground[mid] @ self._local[j]
        model = np.linalg.solve(self._view[None], self._eye_from_object)
        return Poses(model.astype(np.float32), self._view.astype(np.float32),
                     self._visible.copy())
