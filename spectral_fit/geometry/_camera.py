"""Cameras and poses: OpenGL perspective, look-at, intrinsics, OpenCV poses, marker frames.

Conventions (docs/conventions.md, 'Conventions'): right-handed world, +Y up; the OpenGL eye frame
looks down −Z with +Y up; clip space −w ≤ x, y, z ≤ w; NDC (x, y) maps to pixel coordinates
((x + 1)/2·W, (1 − y)/2·H) with pixel centres at integer + 0.5 and row 0 at the top; NDC depth z/w
runs from −1 (near) to +1 (far). Matrices are 4×4 acting on column vectors (``p_eye = V @ [p, 1]``).

OpenCV cameras (+X right, +Y down, +Z forward; pixel (0, 0)'s centre at coordinate (0, 0))
meet OpenGL in exactly one place, :func:`opencv_to_opengl_axes`; intrinsics and poses both go
through it.

All functions are written in ``jax.numpy`` (jit-able, differentiable).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

__all__ = [
    "Camera",
    "perspective",
    "look_at",
    "opencv_to_opengl_axes",
    "intrinsics_matrix",
    "intrinsics_to_projection",
    "projection_to_intrinsics",
    "opencv_pose_to_view",
    "view_to_opencv_pose",
    "relative_transform",
    "interreflection_camera",
    "project",
    "perspective_camera",
    "inverse_3x3",
    "inverse_4x4",
    "eye_position",
]


def perspective(fov_y_deg: float = 90.0, aspect: float = 720 / 480, near: float = 0.01,
                far: float = 1000.0) -> jax.Array:
    """OpenGL perspective projection (gluPerspective): vertical field of view in degrees,
    aspect = width/height, near/far clip distances (m). Maps eye z = −near to NDC −1 and
    z = −far to +1."""
    f = 1.0 / jnp.tan(jnp.deg2rad(jnp.asarray(fov_y_deg, jnp.float32)) / 2)
    n, fa = near, far
    return jnp.array([
        [f / aspect, 0.0, 0.0, 0.0],
        [0.0, f, 0.0, 0.0],
        [0.0, 0.0, (fa + n) / (n - fa), 2 * fa * n / (n - fa)],
        [0.0, 0.0, -1.0, 0.0],
    ], dtype=jnp.float32)


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> jax.Array:
    """View matrix (world → OpenGL eye) of a camera at ``eye`` looking at ``target``, with
    ``up`` (default world +Y) appearing up in the image (gluLookAt).

    Degenerate cases: when the look direction is (nearly) parallel to ``up``, the camera is
    treated as pitched from the default camera by ±90°: image up becomes +Z when looking along
    +Y and −Z when looking along −Y (for up = +Y; in general ``up`` rotated likewise). When
    ``target`` is ``eye`` (two parts of one mesh with one centre), the camera looks along −Z.
    """
    eye = jnp.asarray(eye, jnp.float32)
    target = jnp.asarray(target, jnp.float32)
    up = jnp.asarray(up, jnp.float32)
    f = target - eye
    fn = jnp.linalg.norm(f)
    f = jnp.where(fn > 0.0, f / jnp.where(fn > 0.0, fn, 1.0), jnp.array([0.0, 0.0, -1.0]))
    upn = up / jnp.linalg.norm(up)
    s = jnp.cross(f, upn)
    sn = jnp.linalg.norm(s)
    # fallback "up" for a look direction along ±up: the default camera's backward axis, signed
    alt = jnp.where(jnp.abs(upn[2]) < 0.9, jnp.array([0.0, 0.0, 1.0]), jnp.array([1.0, 0.0, 0.0]))
    alt = alt * jnp.sign(jnp.dot(f, upn) + 1e-30)
    s_alt = jnp.cross(f, alt)
    degenerate = sn < 1e-6
    s = jnp.where(degenerate, s_alt / jnp.linalg.norm(s_alt), s / jnp.where(degenerate, 1.0, sn))
    u = jnp.cross(s, f)
    rot = jnp.stack([s, u, -f])
    return jnp.concatenate([
        jnp.concatenate([rot, -(rot @ eye)[:, None]], axis=1),
        jnp.array([[0.0, 0.0, 0.0, 1.0]], jnp.float32),
    ])


def opencv_to_opengl_axes() -> jax.Array:
    """The ONE place where OpenCV camera axes (+Y down, +Z forward) meet OpenGL's (+Y up, −Z
    forward): diag(1, −1, −1, 1), its own inverse. ``p_gl = F @ p_cv``."""
    return jnp.diag(jnp.array([1.0, -1.0, -1.0, 1.0], jnp.float32))


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float, skew: float = 0.0
                      ) -> jax.Array:
    """OpenCV camera matrix K (3×3): u = fx·X/Z + skew·Y/Z + cx, v = fy·Y/Z + cy (pixels,
    pixel (0, 0)'s centre at (0, 0))."""
    return jnp.array([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], jnp.float32)


def intrinsics_to_projection(k, width: int, height: int, near: float = 0.01,
                             far: float = 1000.0) -> jax.Array:
    """OpenGL projection (4×4, acting on OpenGL eye coordinates) equivalent to OpenCV
    intrinsics ``k`` (3×3) for a ``width`` × ``height`` image.

    A point whose OpenCV projection is (u, v) lands on our pixel coordinates (u + 0.5, v + 0.5)
    (our pixel centres are at integer + 0.5), so the pixel whose centre OpenCV calls (i, j)
    is our pixel (row j, column i). Depth as :func:`perspective` (near → −1, far → +1).
    """
    k = jnp.asarray(k, jnp.float32)
    fx, s, cx = k[0, 0], k[0, 1], k[0, 2]
    fy, cy = k[1, 1], k[1, 2]
    w, h = float(width), float(height)
    # OpenCV camera coordinates (X, Y, Z) -> clip, with w_clip = Z:
    # x_ndc = 2(u + 0.5)/W − 1, y_ndc = 1 − 2(v + 0.5)/H
    zero = jnp.zeros((), jnp.float32)
    p_cv = jnp.stack([
        jnp.stack([2 * fx / w, 2 * s / w, 2 * (cx + 0.5) / w - 1, zero]),
        jnp.stack([zero, -2 * fy / h, 1 - 2 * (cy + 0.5) / h, zero]),
        jnp.stack([zero, zero, jnp.asarray((far + near) / (far - near), jnp.float32),
                   jnp.asarray(-2 * far * near / (far - near), jnp.float32)]),
        jnp.stack([zero, zero, jnp.ones((), jnp.float32), zero]),
    ])
    return p_cv @ opencv_to_opengl_axes()


def projection_to_intrinsics(projection, width: int, height: int) -> jax.Array:
    """Inverse of :func:`intrinsics_to_projection`: OpenCV K (3×3) of a perspective projection
    (OpenGL, acting on eye coordinates) for a ``width`` × ``height`` image."""
    p_cv = jnp.asarray(projection, jnp.float32) @ opencv_to_opengl_axes()
    w, h = float(width), float(height)
    fx = p_cv[0, 0] * w / 2
    s = p_cv[0, 1] * w / 2
    cx = (p_cv[0, 2] + 1) * w / 2 - 0.5
    fy = -p_cv[1, 1] * h / 2
    cy = (1 - p_cv[1, 2]) * h / 2 - 0.5
    return jnp.stack([jnp.stack([fx, s, cx]), jnp.stack([0.0 * fx, fy, cy]),
                      jnp.array([0.0, 0.0, 1.0], jnp.float32)])


def opencv_pose_to_view(r, t) -> jax.Array:
    """OpenGL view matrix (world → eye) of an OpenCV pose: x_cam = R x_world + t (R (3, 3),
    t (3,), e.g. from cv2.solvePnP / an ArUco marker, with 'world' = the marker frame)."""
    r = jnp.asarray(r, jnp.float32)
    t = jnp.asarray(t, jnp.float32).reshape(3)
    rt = jnp.concatenate([jnp.concatenate([r, t[:, None]], 1),
                          jnp.array([[0.0, 0.0, 0.0, 1.0]], jnp.float32)])
    return opencv_to_opengl_axes() @ rt


def view_to_opencv_pose(view) -> tuple[jax.Array, jax.Array]:
    """Inverse of :func:`opencv_pose_to_view`: (R (3, 3), t (3,))."""
    rt = opencv_to_opengl_axes() @ jnp.asarray(view, jnp.float32)
    return rt[:3, :3], rt[:3, 3]


def inverse_3x3(m) -> jax.Array:
    """Inverse of 3×3 matrices (..., 3, 3) by the adjugate over the determinant, in closed
    form: elementwise arithmetic that XLA fuses into one kernel (no LAPACK call, cheap to
    compile, differentiable). For the well-conditioned rotation/scale blocks of model and view
    matrices; a singular matrix gives inf/NaN."""
    m = jnp.asarray(m)
    a, b, c = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    d, e, f = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    g, h, i = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    c00, c01, c02 = e * i - f * h, f * g - d * i, d * h - e * g  # cofactors of row 0
    det = a * c00 + b * c01 + c * c02
    adj = jnp.stack([
        jnp.stack([c00, c * h - b * i, b * f - c * e], -1),
        jnp.stack([c01, a * i - c * g, c * d - a * f], -1),
        jnp.stack([c02, b * g - a * h, a * e - b * d], -1),
    ], -2)
    return adj / det[..., None, None]


def inverse_4x4(m) -> jax.Array:
    """Inverse of 4×4 matrices (..., 4, 4) in closed form (Laplace expansion by the 2×2 minors
    of the top and bottom row pairs); like :func:`inverse_3x3`, fused elementwise arithmetic
    instead of a LAPACK call. Used for projection·view products (clip → world)."""
    m = jnp.asarray(m)
    a = [[m[..., r, k] for k in range(4)] for r in range(4)]
    # 2×2 minors of rows 0-1 (s) and rows 2-3 (c), columns (0,1) (0,2) (0,3) (1,2) (1,3) (2,3)
    pairs = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
    s = [a[0][p] * a[1][q] - a[1][p] * a[0][q] for p, q in pairs]
    c = [a[2][p] * a[3][q] - a[3][p] * a[2][q] for p, q in pairs]
    det = s[0] * c[5] - s[1] * c[4] + s[2] * c[3] + s[3] * c[2] - s[4] * c[1] + s[5] * c[0]
    r0 = [a[1][1] * c[5] - a[1][2] * c[4] + a[1][3] * c[3],
          -a[0][1] * c[5] + a[0][2] * c[4] - a[0][3] * c[3],
          a[3][1] * s[5] - a[3][2] * s[4] + a[3][3] * s[3],
          -a[2][1] * s[5] + a[2][2] * s[4] - a[2][3] * s[3]]
    r1 = [-a[1][0] * c[5] + a[1][2] * c[2] - a[1][3] * c[1],
          a[0][0] * c[5] - a[0][2] * c[2] + a[0][3] * c[1],
          -a[3][0] * s[5] + a[3][2] * s[2] - a[3][3] * s[1],
          a[2][0] * s[5] - a[2][2] * s[2] + a[2][3] * s[1]]
    r2 = [a[1][0] * c[4] - a[1][1] * c[2] + a[1][3] * c[0],
          -a[0][0] * c[4] + a[0][1] * c[2] - a[0][3] * c[0],
          a[3][0] * s[4] - a[3][1] * s[2] + a[3][3] * s[0],
          -a[2][0] * s[4] + a[2][1] * s[2] - a[2][3] * s[0]]
    r3 = [-a[1][0] * c[3] + a[1][1] * c[1] - a[1][2] * c[0],
          a[0][0] * c[3] - a[0][1] * c[1] + a[0][2] * c[0],
          -a[3][0] * s[3] + a[3][1] * s[1] - a[3][2] * s[0],
          a[2][0] * s[3] - a[2][1] * s[1] + a[2][2] * s[0]]
    adj = jnp.stack([jnp.stack(r, -1) for r in (r0, r1, r2, r3)], -2)
    return adj / det[..., None, None]


def eye_position(view) -> jax.Array:
    """World position (..., 3) of the eye of an affine view matrix (..., 4, 4) (world → eye,
    last row (0, 0, 0, 1)): −A⁻¹ t for view = [A t; 0 1]."""
    view = jnp.asarray(view)
    return -jnp.einsum("...ij,...j->...i", inverse_3x3(view[..., :3, :3]), view[..., :3, 3])


def relative_transform(m1, m2) -> jax.Array:
    """Paper eqs. 1–3: with M1, M2 the model-view matrices of markers 1 and 2 (marker frame →
    camera), a point P1 in marker 1's frame has coordinates P2 = M2⁻¹ M1 P1 in marker 2's
    frame. Returns M2⁻¹ M1 (4×4)."""
    return jnp.linalg.solve(jnp.asarray(m2, jnp.float32), jnp.asarray(m1, jnp.float32))


class Camera(eqx.Module):
    """A view matrix (world → OpenGL eye, 4×4) and a projection (eye → clip, 4×4)."""

    view: jax.Array
    projection: jax.Array

    @property
    def view_projection(self) -> jax.Array:
        return self.projection @ self.view


def perspective_camera(eye, target, *, fov_y_deg: float = 90.0, aspect: float = 720 / 480,
                       near: float = 0.01, far: float = 1000.0, up=(0.0, 1.0, 0.0)) -> Camera:
    """Camera at ``eye`` looking at ``target`` with :func:`perspective` (paper defaults)."""
    return Camera(look_at(eye, target, up), perspective(fov_y_deg, aspect, near, far))


def interreflection_camera(center_i, center_j, *, aspect: float = 1.0, fov_y_deg: float = 90.0,
                           near: float = 0.01, far: float = 1000.0) -> Camera:
    """The interreflection pass's camera (paper eqs. 1–3): at object i's centre,
    looking at object j's centre, up = world +Y (with :func:`look_at`'s fallback when the two
    centres are vertically aligned), 90° vertical FOV, aspect of the target texture, near 0.01,
    far 1000. Object j's vertices go through ``projection @ view @ world_from_j``."""
    return perspective_camera(center_i, center_j, fov_y_deg=fov_y_deg, aspect=aspect, near=near,
                              far=far)


def project(camera: Camera, points, model=None) -> jax.Array:
    """Clip coordinates ``(N, 4)`` of points ``(N, 3)`` (object frame when ``model`` (4×4) is
    given, else world): ``P @ V @ M @ [p, 1]``."""
    p = jnp.asarray(points, jnp.float32)
    m = camera.view_projection
    if model is not None:
        m = m @ jnp.asarray(model, jnp.float32)
    return p @ m[:, :3].T + m[:, 3]
