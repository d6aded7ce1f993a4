"""The camera and the placement of vertices: the projection (OpenGL, from the field of view or
from OpenCV intrinsics given for the config's frame size), the lens (distortion vector, pixel
rays, the check that triangles are small enough for it), the view matrix from the config's
look-at, and points object → world → clip.

Shapes: vertices (V, 3) in m, model matrices (O, 4, 4) world-from-object, view (4, 4)
world → OpenGL eye, projection (4, 4) eye → clip, clip coordinates (V, 4).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import inverse_3x3

if TYPE_CHECKING:  # for annotations (imported where they are used)
    from ..io import Scene

__all__ = [
    "camera_clip",
]


def _projection(scene: Scene, shape: tuple[int, int]) -> np.ndarray:
    from ..geometry import intrinsics_matrix, intrinsics_to_projection, perspective

    cam = scene.camera
    h, w = shape
    if cam.intrinsics is None:
        return np.asarray(perspective(cam.fov_y_deg, w / h, cam.near, cam.far))
    i = cam.intrinsics
    sx, sy = w / scene.width, h / scene.height  # intrinsics are given for the config's size
    k = intrinsics_matrix(i["fx"] * sx, i["fy"] * sy, (i["cx"] + 0.5) * sx - 0.5,
                          (i["cy"] + 0.5) * sy - 0.5)
    return np.asarray(intrinsics_to_projection(k, w, h, cam.near, cam.far))


def _lens(scene: Scene, proj: np.ndarray, shape: tuple[int, int]
          ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """The camera's lens vector (9,), pixel rays (H·W, 3) (:mod:`spectral_fit.geometry`) and
    OpenCV intrinsics (3, 3) for the projection ``proj`` at ``shape``, or three None for a
    pinhole. The distortion coefficients act on normalised coordinates, so they hold at any
    frame size."""
    from ..geometry import is_identity, lens_parameters, pixel_rays, projection_to_intrinsics

    dist = scene.camera.distortion
    if is_identity(dist):
        return None, None, None
    path = getattr(scene, "path", None)
    lens = lens_parameters(dist, path=path)
    k = np.asarray(projection_to_intrinsics(proj, shape[1], shape[0]), np.float64)
    return lens, pixel_rays(k, lens, shape, path=path), k


#: largest midpoint error (pixels) of a triangle edge under the lens before prepare warns
LENS_EDGE_TOLERANCE_PX = 0.25


def _check_lens_tessellation(scene: Scene, k: np.ndarray, shape: tuple[int, int],
                             lens: np.ndarray, world: np.ndarray, view: np.ndarray,
                             triangles: np.ndarray, tsl: Sequence[tuple[int, int]]) -> None:
    """Warn when an object's triangles are too large for the vertex-distortion raster: an edge
    (of the configured pose, its midpoint in the frame) whose straight raster misses the
    lens's image of its midpoint by more than ``LENS_EDGE_TOLERANCE_PX``
    (:func:`~spectral_fit.geometry.edge_error_px`; ``k``: the intrinsics at ``shape``)."""
    from ..geometry import edge_error_px

    h, w = shape
    eye = world @ view[:3, :3].T.astype(np.float64) + view[:3, 3]
    for (ta, tb), obj in zip(tsl, scene.objects, strict=True):
        t = triangles[ta:tb]
        edges = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
        err, mid_px = edge_error_px(eye, edges, lens, k)
        u, v = mid_px[:, 0], mid_px[:, 1]
        front = 0.5 * (eye[edges[:, 0], 2] + eye[edges[:, 1], 2]) < -1e-9
        seen = front & (u > -0.1 * w) & (u < 1.1 * w) & (v > -0.1 * h) & (v < 1.1 * h)
        worst = float(err[seen].max()) if seen.any() else 0.0
        if worst > LENS_EDGE_TOLERANCE_PX:
            warnings.warn(
                f"{obj.name}: its triangles are large for this lens: a straight edge misses "
                f"the distorted image of its midpoint by up to {worst:.2f} px; tessellate it "
                "more finely (stacks/slices, or a denser mesh)", RuntimeWarning, stacklevel=3)


def camera_clip(projection: Any, view: Any, lens: Any, world: Any, xp: Any = jnp) -> Any:
    """Clip coordinates (V, 4) of world points (V, 3) seen by the camera: ``projection @
    view``, with the vertices distorted in eye space first when there is a ``lens``
    (:func:`~spectral_fit.geometry.distort_eye`). ``xp``: ``jax.numpy`` (traced) or ``numpy``
    (capacity planning)."""
    if lens is None:
        vp = projection @ view
        return world @ vp[:, :3].T + vp[:, 3]
    from ..geometry import distort_eye

    eye = distort_eye(world @ view[:3, :3].T + view[:3, 3], lens, xp)
    return eye @ projection[:, :3].T + projection[:, 3]


def _look_at_impl(eye, target, up):
    from ..geometry import look_at

    return look_at(eye, target, up)


_look_at_jit = jax.jit(_look_at_impl)


def _to_world(vertices: jax.Array, vertex_object: jax.Array, model: jax.Array) -> jax.Array:
    m = model[vertex_object]  # (V, 4, 4)
    return jnp.einsum("vij,vj->vi", m[:, :3, :3], vertices) + m[:, :3, 3]


def _normals_to_world(normals: jax.Array, vertex_object: jax.Array, model: jax.Array
                      ) -> jax.Array:
    nm = jnp.swapaxes(inverse_3x3(model[:, :3, :3]), 1, 2)  # inverse transpose, (O, 3, 3)
    n = jnp.einsum("vij,vj->vi", nm[vertex_object], normals)
    return n / jnp.linalg.norm(n, axis=-1, keepdims=True)
