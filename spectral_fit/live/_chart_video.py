"""The camera's colour from a ColorChecker lying in the video (the config's ``[colour_chart]``).

The chart lies on the table at a known place relative to a marker (:class:`~spectral_fit.io.
ColourChartSpec`): its centre and size in that marker's ground frame (+Y = the marker's
normal, −Z = its top edge; metres). In each frame where that marker is found, the chart's four
outer patch corners are projected through the marker's pose (with the camera's distortion);
a frame is used when all four lie inside it, the chart faces the camera and every patch is at
least ``min_patch_px`` across. The patches are sampled there (:func:`sample_chart`: the central
half of each cell) in the first ``frames`` such frames among the first ``search_frames``, their
encoded values averaged over those frames, and the 3×3 (XYZ → linear frame RGB) fitted by
:func:`calibrate_colour_samples` against the patches' XYZ under the scene's light
(:func:`chart_xyz`: the chart's reflectances, lying on the table, facing +Y).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable

import numpy as np

from .._runtime.errors import InputError
from ..io import ColourChartSpec, Scene
from ._compositing import (
    CameraModel,
    ChartCalibration,
    calibrate_colour_samples,
    chart_xyz,
    sample_chart,
)
from ._synthetic_video import MARKER_AXES

__all__ = ["chart_corners_world", "chart_corners_in_frame", "VideoChart", "chart_camera_model"]


def chart_corners_world(spec: ColourChartSpec) -> np.ndarray:
    """(4, 3) the chart's outer patch corners in its marker's ground frame (m), in the order
    top-left (patch 1), top-right, bottom-right, bottom-left."""
    w, h = spec.size
    local = np.array([[-w / 2, 0.0, -h / 2], [w / 2, 0.0, -h / 2], [w / 2, 0.0, h / 2],
                      [-w / 2, 0.0, h / 2]])
    a = math.radians(spec.rotation_deg)
    ry = np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0],
                   [-math.sin(a), 0.0, math.cos(a)]])
    return local @ ry.T + np.asarray(spec.centre, np.float64)


def chart_corners_in_frame(spec: ColourChartSpec, rotation, translation, k, dist, size
                           ) -> np.ndarray | None:
    """(4, 2) pixel corners (OpenCV convention, with the distortion ``dist``) of the chart
    placed by its marker at OpenCV pose (``rotation`` (3, 3), ``translation`` (3,) m;
    x_cam = R x_marker + t), or None when a corner falls outside the (H, W) frame ``size``
    or the chart faces away from the camera."""
    import cv2

    r = np.asarray(rotation, np.float64) @ MARKER_AXES.T   # camera from ground frame
    t = np.asarray(translation, np.float64).reshape(3)
    pts = chart_corners_world(spec)
    cam = pts @ r.T + t
    if np.any(cam[:, 2] <= 0) or (r[:, 1] @ cam.mean(0)) >= 0:
        return None
    rvec, _ = cv2.Rodrigues(r)
    px, _ = cv2.projectPoints(pts, rvec, t, np.asarray(k, np.float64),
                              None if dist is None else np.asarray(dist, np.float64))
    px = px.reshape(4, 2)
    h, w = size
    if np.any(px < 1.0) or np.any(px[:, 0] > w - 2.0) or np.any(px[:, 1] > h - 2.0):
        return None
    return px


def _smallest_patch_px(corners: np.ndarray) -> float:
    """Shortest side (px) of a patch cell of a 6 × 4 chart with these outer corners."""
    sides = np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)
    return float(min(sides[0] / 6, sides[2] / 6, sides[1] / 4, sides[3] / 4))


@dataclasses.dataclass(frozen=True, eq=False)
class VideoChart:
    """Result of :func:`chart_camera_model`: ``model`` (the :class:`CameraModel`, with the
    scene's blur and noise), ``calibration`` (:class:`ChartCalibration`), ``frames`` (indices
    of the frames sampled), ``corners`` ((n, 4, 2) the chart's corners there, px),
    ``spread`` ((24, 3) standard deviation of the encoded patch values over those frames)."""

    model: CameraModel
    calibration: ChartCalibration
    frames: tuple[int, ...]
    corners: np.ndarray
    spread: np.ndarray


def chart_camera_model(scene: Scene, frames: Iterable[np.ndarray], *, k=None, dist=None,
                       source: str = "video") -> VideoChart:
    """Fit the video camera's colour from the chart of ``scene.colour_chart`` in ``frames``
    ((H, W, 3) uint8 RGB, read from the start; at most ``search_frames`` are read).

    ``k`` (3×3) and ``dist``: the camera's OpenCV intrinsics and distortion at the frames'
    size (default: :func:`scene_intrinsics` at the config's ``[frame]`` size).

    Raises:
        InputError: no ``[colour_chart]`` or ``[markers]``, or the chart was not seen whole
            and large enough in any frame searched (naming the config and ``source``).
    """
    from ._markers import MarkerDetector
    from ._scene_camera import scene_intrinsics

    spec = scene.colour_chart
    if spec is None or scene.markers is None:
        raise InputError("needs [markers] and [colour_chart]", path=scene.path,
                         field="colour_chart")
    if k is None:
        k, dist = scene_intrinsics(scene)
    detector = None
    samples, used, corners = [], [], []
    size = None
    for i, frame in enumerate(frames):
        if i >= spec.search_frames or len(samples) >= spec.frames:
            break
        if detector is None:
            size = frame.shape[:2]
            detector = MarkerDetector(scene.markers, k, dist, expect={spec.marker})
        det = detector.detect(frame).get(spec.marker)
        if det is None:
            continue
        c = chart_corners_in_frame(spec, det.rotation, det.translation, k, dist, size)
        if c is None or _smallest_patch_px(c) < spec.min_patch_px:
            continue
        samples.append(sample_chart(frame, c) / 255.0)
        used.append(i)
        corners.append(c)
    if not samples:
        raise InputError(f"the chart was not seen whole (patches of at least "
                         f"{spec.min_patch_px:g} px, marker {spec.marker} found) in the first "
                         f"{spec.search_frames} frames of {source}", path=scene.path,
                         field="colour_chart")
    s = np.stack(samples)
    xyz, white = chart_xyz(scene, chart=spec.chart)
    cal = calibrate_colour_samples(s.mean(0), xyz, white, tone=spec.tone, gamma=spec.gamma)
    model = dataclasses.replace(cal.model, blur_px=float(scene.camera.blur_px),
                                noise=float(scene.camera.noise))
    return VideoChart(model=model, calibration=cal, frames=tuple(used),
                      corners=np.stack(corners), spread=s.std(0))


