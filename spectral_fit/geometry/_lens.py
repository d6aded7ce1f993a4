"""Lens distortion of the render camera: OpenCV's model, applied to the rendered image itself.

The camera projects a point of OpenCV camera coordinates (X, Y, Z) (OpenCV axes: +Y down,
+Z forward; OpenGL eye coordinates are (X, −Y, −Z),
:func:`~spectral_fit.geometry.opencv_to_opengl_axes`) to normalised coordinates
(x, y) = (X/Z, Y/Z), distorts them and maps them to pixels with the intrinsics K (OpenCV,
"Camera Calibration and 3D Reconstruction", ``projectPoints``):

    r² = x² + y²,   f(r²) = (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)
    x_d = x f + 2 p1 x y + p2 (r² + 2 x²)
    y_d = y f + p1 (r² + 2 y²) + 2 p2 x y
    (u, v) = (fx x_d + s y_d + cx, fy y_d + cy)

Coefficients come in OpenCV's order (k1, k2, p1, p2[, k3[, k4, k5, k6]]). A polynomial lens
model holds only out to some radius: past the first radius where r·f(r²) stops growing, it
folds the image back towards the centre. :func:`lens_parameters` finds that radius
(``r_max``) once; beyond it :func:`distort_normalized` continues the lens radially linearly
(the distortion of the point scaled back to ``r_max``, scaled out again), so geometry far
outside the frame never folds back into it.

The renderer uses it in two places (both precomputed per camera, both exact at the pixel
centres):

* geometry: every vertex is distorted in eye space (:func:`distort_eye`: its depth kept, its
  normalised coordinates distorted) before rasterisation, the way a vertex shader would;
  triangle edges stay straight in the distorted image, which for triangles a few pixels across
  is well within a pixel (the benchmark spheres' triangles are ~1 px);
* rays: the background and every per-pixel direction use the undistorted ray of each pixel
  centre (:func:`pixel_rays`, Newton's method on the model in float64; a pixel whose
  iteration does not converge, i.e. the model folds inside the frame, is an error).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._runtime.errors import InputError

__all__ = ["distort_eye", "distort_normalized", "edge_error_px", "is_identity",
           "lens_parameters", "pixel_rays", "undistort_normalized"]

#: the radius (normalised coordinates, tan of the angle off axis) searched for the fold
#: (tan 87°)
_R_SCAN = 19.0
_NEWTON_STEPS = 30


def _radial(r2: Any, k1: Any, k2: Any, k3: Any, k4: Any, k5: Any, k6: Any
            ) -> tuple[Any, Any]:
    """The radial factor f(r²) of the model (module docstring) and its derivative df/d(r²),
    elementwise (any array type; an unused derivative costs nothing under ``jit``)."""
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    dden = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
    return num / den, (dnum * den - num * dden) / (den * den)


def is_identity(coefficients: Any) -> bool:
    """Whether ``coefficients`` (None or a sequence) describe no distortion at all."""
    return coefficients is None or not any(float(c) != 0.0 for c in coefficients)


def lens_parameters(coefficients: Any, *, field: str = "camera.distortion",
                    path: Any = None) -> np.ndarray:
    """The renderer's lens vector (9,) float64: (k1, k2, p1, p2, k3, k4, k5, k6, r_max²).

    Args:
        coefficients: 4, 5 or 8 numbers in OpenCV's order (k1, k2, p1, p2[, k3[, k4, k5,
            k6]]); missing ones are 0.
        field, path: named in errors.

    Returns:
        The 8 coefficients and the square of ``r_max``, the first radius (normalised
        coordinates) where the radial map r → r·f(r²) stops increasing (or tan 87°).
    Raises:
        InputError: not 4, 5 or 8 finite numbers; a lens that folds within 0.1 of the axis
            (tan 5.7°: no real camera).
    """
    c = np.asarray(coefficients, np.float64).reshape(-1)
    if c.size not in (4, 5, 8):
        raise InputError(f"must be 4, 5 or 8 numbers (OpenCV order), got {c.size}",
                         field=field, path=path)
    if not np.all(np.isfinite(c)):
        raise InputError("must be finite numbers", field=field, path=path)
    full = np.zeros(8)
    full[:c.size] = c
    k1, k2, _, _, k3, k4, k5, k6 = full
    r = np.linspace(0.0, _R_SCAN, 190_001)
    r2 = r * r
    den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    with np.errstate(divide="ignore", invalid="ignore"):
        f, df = _radial(r2, k1, k2, k3, k4, k5, k6)
        slope = f + 2.0 * r2 * df  # d(r f)/dr
    bad = ~((slope > 0.0) & (f > 0.0) & (den > 0.0))
    r_max = _R_SCAN if not bad.any() else float(r[max(int(np.argmax(bad)) - 1, 0)])
    if r_max < 0.1:
        raise InputError(f"this lens model folds the image {r_max:.3g} from the axis "
                         "(normalised radius): not a usable camera", field=field, path=path)
    return np.concatenate([full, [r_max * r_max]])


def distort_normalized(x: Any, y: Any, lens: Any, xp: Any = None) -> tuple[Any, Any]:
    """OpenCV distortion of normalised coordinates (module docstring), extended linearly
    past ``r_max``.

    Args:
        x, y: (...) normalised OpenCV coordinates X/Z, Y/Z.
        lens: (9,) from :func:`lens_parameters`.
        xp: array module (``jax.numpy``, the default, or ``numpy``); differentiable in JAX.

    Returns:
        (x_d, y_d), each shaped like ``x``.
    """
    if xp is None:
        import jax.numpy as xp
    k1, k2, p1, p2, k3, k4, k5, k6, rmax2 = (lens[i] for i in range(9))
    r2 = x * x + y * y
    far = r2 > rmax2
    s = xp.where(far, xp.sqrt(rmax2 / xp.where(far, r2, 1.0)), 1.0)  # back onto r_max
    xc, yc = x * s, y * s
    r2c = xp.where(far, rmax2, r2)
    f, _ = _radial(r2c, k1, k2, k3, k4, k5, k6)
    xd = xc * f + 2.0 * p1 * xc * yc + p2 * (r2c + 2.0 * xc * xc)
    yd = yc * f + p1 * (r2c + 2.0 * yc * yc) + 2.0 * p2 * xc * yc
    return xd / s, yd / s


def distort_eye(points: Any, lens: Any, xp: Any = None) -> Any:
    """Points (N, 3) in OpenGL eye coordinates moved to where the lens images them: the same
    depth z, the normalised coordinates distorted (:func:`distort_normalized`). A projection
    of the result is OpenCV's ``projectPoints`` with the same K and coefficients. Points at or
    behind the eye plane (z ≥ −1e-9) are left as they are (clipping removes them).

    Args:
        points: (N, 3) eye coordinates (m).
        lens: (9,) from :func:`lens_parameters`.
        xp: array module (default ``jax.numpy``).
    Returns:
        (N, 3) eye coordinates.
    """
    if xp is None:
        import jax.numpy as xp
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    front = z < -1e-9
    depth = xp.where(front, -z, 1.0)  # OpenCV Z
    xd, yd = distort_normalized(x / depth, -y / depth, lens, xp)
    moved = xp.stack([xd * depth, -yd * depth, z], axis=-1)
    return xp.where(front[:, None], moved, points)


def undistort_normalized(xd: np.ndarray, yd: np.ndarray, lens: np.ndarray,
                         *, steps: int = _NEWTON_STEPS) -> tuple[np.ndarray, np.ndarray,
                                                                  np.ndarray]:
    """Inverse of :func:`distort_normalized` inside ``r_max``, by Newton's method (float64,
    the analytic Jacobian of the model), started from the distorted point.

    Returns:
        (x, y, residual): the undistorted coordinates and, per point, the distance in
        normalised units between the distortion of (x, y) and (x_d, y_d).
    """
    k1, k2, p1, p2, k3, k4, k5, k6, rmax2 = (float(v) for v in lens)
    xd = np.asarray(xd, np.float64)
    yd = np.asarray(yd, np.float64)
    x, y = xd.copy(), yd.copy()
    for _ in range(steps):
        r2 = np.minimum(x * x + y * y, rmax2)
        f, df = _radial(r2, k1, k2, k3, k4, k5, k6)
        ex = x * f + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
        ey = y * f + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
        a = f + 2.0 * x * x * df + 2.0 * p1 * y + 6.0 * p2 * x
        b = 2.0 * x * y * df + 2.0 * p1 * x + 2.0 * p2 * y
        d = f + 2.0 * y * y * df + 6.0 * p1 * y + 2.0 * p2 * x
        det = a * d - b * b
        det = np.where(np.abs(det) > 1e-12, det, 1e-12)
        x = x - (d * ex - b * ey) / det
        y = y - (a * ey - b * ex) / det
    gx, gy = distort_normalized(x, y, lens, np)
    return x, y, np.hypot(gx - xd, gy - yd)


def pixel_rays(k: Any, lens: np.ndarray, shape: tuple[int, int], *,
               field: str = "camera.distortion", path: Any = None) -> np.ndarray:
    """Unit ray directions (H·W, 3) in OpenGL eye coordinates through every pixel centre of an
    image seen through the lens: pixel (row i, column j) has OpenCV coordinates (u, v) =
    (j, i) (ours has centres at integer + 0.5), undistorted with
    :func:`undistort_normalized`.

    Args:
        k: (3, 3) OpenCV intrinsics at this image size (skew allowed).
        lens: (9,) from :func:`lens_parameters`.
        shape: (H, W).
    Raises:
        InputError: the model does not reach a pixel centre (its inverse does not converge to
            1e-9 there: the lens folds inside the frame).
    """
    k = np.asarray(k, np.float64)
    h, w = shape
    v, u = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64),
                       indexing="ij")
    yd = (v - k[1, 2]) / k[1, 1]
    xd = (u - k[0, 2] - k[0, 1] * yd) / k[0, 0]
    x, y, res = undistort_normalized(xd.ravel(), yd.ravel(), lens)
    inside = x * x + y * y <= lens[8] * (1.0 + 1e-9)
    if not np.all((res < 1e-9) & inside):
        bad = int(np.argmax(~((res < 1e-9) & inside)))
        raise InputError(f"the lens model does not reach pixel (row {bad // w}, column "
                         f"{bad % w}) of the {w}x{h} frame: it folds inside the frame",
                         field=field, path=path)
    rays = np.stack([x, -y, -np.ones_like(x)], axis=-1)  # OpenCV (x, y, 1) in OpenGL axes
    return (rays / np.linalg.norm(rays, axis=-1, keepdims=True)).astype(np.float32)


def edge_error_px(points: np.ndarray, edges: np.ndarray, lens: np.ndarray,
                  k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How far (pixels) the straight-edged raster of distorted vertices puts the midpoint of
    each edge from where the lens images it: per edge (a, b) of ``points`` (V, 3, OpenGL eye
    coordinates), the distance between the projection of the midpoint of the distorted
    endpoints (what the rasteriser interpolates) and the distorted projection of the true
    midpoint. The bound of :func:`distort_eye`'s approximation inside a triangle; it grows
    with the square of the triangle's size. Edges with an end at or behind the eye plane
    give 0.

    Args:
        points: (V, 3) eye coordinates; edges: (E, 2) vertex indices; lens: (9,); k: (3, 3)
            intrinsics.
    Returns:
        (E,) float64 pixels, and (E, 2) the pixel coordinates (OpenCV convention) where the
        lens images each true midpoint.
    """
    p = np.asarray(points, np.float64)
    e = np.asarray(edges)
    front = (p[e[:, 0], 2] < -1e-6) & (p[e[:, 1], 2] < -1e-6)

    def pix(q: np.ndarray) -> np.ndarray:
        z = np.where(q[:, 2] < -1e-9, -q[:, 2], 1.0)
        x, y = q[:, 0] / z, -q[:, 1] / z
        return np.stack([k[0, 0] * x + k[0, 1] * y + k[0, 2], k[1, 1] * y + k[1, 2]], -1)

    moved = distort_eye(p, lens, np)  # each vertex once
    lin = pix(0.5 * (moved[e[:, 0]] + moved[e[:, 1]]))
    true = pix(distort_eye(0.5 * (p[e[:, 0]] + p[e[:, 1]]), lens, np))
    return np.where(front, np.linalg.norm(lin - true, axis=-1), 0.0), true
