"""The scene camera as the live session sees it: OpenCV intrinsics K (3×3, pixels) and
distortion at the video's frame size (H, W), and the video camera's colour model (a 3×3 from a
ColorChecker shot, or spectral sensitivities white-balanced on the environment).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..io import Scene
from ..lighting import white_reference
from ._compositing import CameraModel, camera_model_from_sensitivities

__all__ = ["scene_intrinsics", "scene_camera_model"]


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
