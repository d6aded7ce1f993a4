"""The live step: puts the objects' shadows and light on the real surfaces into the (H, W, 3)
uint8 background frame (``[[surfaces]]``, as a ratio of the table's radiance with / without
them), renders the covered pixels of the traced poses (shaded straight into the video camera's
linear RGB), encodes them and writes them into it, with the buffer statistics the session
re-plans from. Two jitted programs, dispatched one after the other without waiting: the
relight of the frame, then the objects' pixels.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import jax
import numpy as np

from .._runtime.dispatch import array_jit
from ._compositing import CameraModel, composite_pixels, relight

if TYPE_CHECKING:  # for annotations (the renderer is imported where it is used)
    from ..lighting import Material
    from ..rendering import Prepared

__all__ = ["STEP_TRACES", "camera_output_matrix", "camera_spectral_matrix", "live_step"]

#: number of times the live step's programs have been traced (compiled), for tests and
#: reports: "step" the objects' pixels, "relight" the surfaces' change put into the frame
STEP_TRACES = {"step": 0, "relight": 0}


def camera_output_matrix(prep: Prepared, camera: CameraModel) -> np.ndarray:
    """(C, 3) map from ``prep``'s radiance channels to the video camera's linear RGB: through
    the camera's spectral sensitivities (a model with them) or through XYZ and its 3 × 3
    (for :func:`~spectral_fit.rendering.with_output`)."""
    if camera.has_spectral:
        return np.asarray(prep.colour.to_spectrum) @ np.asarray(camera.spectral_weights)
    return np.asarray(prep.colour.to_xyz) @ np.asarray(camera.xyz_matrix).T


def camera_spectral_matrix(prep: Prepared, camera: CameraModel) -> np.ndarray:
    """(L, 3) map from spectral radiance on ``prep``'s wavelengths to the video camera's
    linear RGB (its spectral weights, or XYZ and its 3 × 3)."""
    if camera.has_spectral:
        return np.asarray(camera.spectral_weights)
    from ..color import xyz_weights

    return xyz_weights(np.asarray(prep.colour.wavelengths)) @ np.asarray(camera.xyz_matrix).T


def _relight_impl(prep: Prepared, view: jax.Array, background: jax.Array,
                  camera: CameraModel, surfaces: Any) -> jax.Array:
    from ..rendering import surface_ratio_lookup

    STEP_TRACES["relight"] += 1
    textures, codes = surfaces
    return relight(background, surface_ratio_lookup(prep, textures, view=view), camera,
                   codes=codes)


def _step_impl(prep: Prepared, materials: Material, model: jax.Array, view: jax.Array,
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


_relight_program = array_jit(_relight_impl)
_step_program = array_jit(_step_impl)


def live_step(prep: Prepared, materials: Material, model: jax.Array, view: jax.Array,
              visible: jax.Array, background: jax.Array, camera: CameraModel,
              mirror: bool = True, senders: Any = None, surfaces: Any = None
              ) -> tuple[jax.Array, dict[str, jax.Array]]:
    """One live frame (asynchronous: block on the result to time it).

    Args:
        prep: the prepared scene (its camera at the video's size).
        materials: the objects' materials.
        model: (M, 4, 4) object → world poses; view: (4, 4) world → eye; visible: (M,) bool
            (a hidden object neither renders nor lights).
        background: (H, W, 3) uint8 video frame, undistorted.
        camera: the video camera's colour model (tone curve, matrices, blur, noise).
        mirror: whether the frames shade the mirror term.
        senders: the interreflection's senders reused from another call
            (:func:`~spectral_fit.rendering.render_senders`), or None.
        surfaces: (ratio textures, relight codes) of the ``[[surfaces]]``
            (:func:`~spectral_fit.rendering.surface_ratio_textures`, :func:`relight_codes`),
            or None.

    Returns:
        ((H, W, 3) uint8 composite, statistics for re-planning the buffers).

    The relight is its own program, dispatched first: inside the pixels' program XLA:CPU
    fuses it into the composite's scatter, and the same work took about 3 ms more at
    720×480 than on its own.
    """
    if surfaces is not None:  # the objects' shadows and light on the real table, first
        background = _relight_program(prep, view, background, camera, surfaces)
    return _step_program(prep, materials, model, view, visible, background, camera, mirror,
                         senders)
