"""Cameras and poses against closed forms, hand-built transforms and OpenCV's own projection."""

from __future__ import annotations

import math

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spectral_fit.geometry import (
    Camera,
    interreflection_camera,
    intrinsics_matrix,
    intrinsics_to_projection,
    look_at,
    opencv_pose_to_view,
    opencv_to_opengl_axes,
    perspective,
    perspective_camera,
    project,
    projection_to_intrinsics,
    relative_transform,
    view_to_opencv_pose,
)
from spectral_fit.io import rotate, translate


def _ndc(clip):
    clip = np.asarray(clip, np.float64)
    return clip[..., :3] / clip[..., 3:]


def _pixels(clip, w, h):
    n = _ndc(clip)
    return np.stack([(n[..., 0] + 1) / 2 * w, (1 - n[..., 1]) / 2 * h], -1)


def test_perspective_paper_defaults_closed_form():
    p = np.asarray(perspective(), np.float64)  # 90°, 720/480, near 0.01, far 1000
    for z, want in ((-0.01, -1.0), (-1000.0, 1.0)):
        np.testing.assert_allclose(_ndc(p @ [0, 0, z, 1])[2], want, atol=1e-5)
    # a point on the upper edge of the 90° field of view lands on NDC y = +1; aspect 1.5
    d = 2.5
    np.testing.assert_allclose(_ndc(p @ [0, d * math.tan(math.pi / 4), -d, 1])[1], 1.0,
                               rtol=1e-6)
    np.testing.assert_allclose(_ndc(p @ [1.5 * d, 0, -d, 1])[0], 1.0, rtol=1e-6)
    # configurable: 60°, square, near 0.5, far 20
    q = np.asarray(perspective(60.0, 1.0, 0.5, 20.0), np.float64)
    np.testing.assert_allclose(_ndc(q @ [0, 3 * math.tan(math.pi / 6), -3, 1])[1], 1.0,
                               rtol=1e-6)
    np.testing.assert_allclose(_ndc(q @ [0, 0, -0.5, 1])[2], -1.0, atol=1e-6)
    np.testing.assert_allclose(_ndc(q @ [0, 0, -20, 1])[2], 1.0, atol=1e-6)


def test_look_at_is_a_rigid_view_with_up_preserved():
    eye = np.array([0.3, -0.2, 1.0])
    target = np.array([-0.1, 0.4, -2.0])
    v = np.asarray(look_at(eye, target), np.float64)
    r = v[:3, :3]
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-6)
    assert np.linalg.det(r) > 0
    np.testing.assert_allclose(v @ [*eye, 1], [0, 0, 0, 1], atol=1e-6)
    dist = np.linalg.norm(target - eye)
    np.testing.assert_allclose(v @ [*target, 1], [0, 0, -dist, 1], atol=1e-5)
    # world +Y appears up (positive eye y), the eye x axis is horizontal
    up = r @ [0, 1, 0]
    assert up[1] > 0 and abs(r[0, 1]) < 1e-6
    # looking straight down: the documented fallback (image up = −Z) gives a valid rotation
    vd = np.asarray(look_at((0, 1, 0), (0, 0, 0)), np.float64)
    np.testing.assert_allclose(vd[:3, :3] @ vd[:3, :3].T, np.eye(3), atol=1e-6)
    np.testing.assert_allclose(vd[:3, :3] @ [0, 0, -1], [0, 1, 0], atol=1e-6)


def _hand_pose(axis, angle, t):
    """A marker → camera model-view matrix built by hand (float64)."""
    return translate(t) @ rotate(axis, angle)


def test_relative_transform_eqs_1_to_3_against_hand_built_matrices():
    m1 = _hand_pose((0.2, 1.0, 0.1), 0.4, (0.05, -0.02, -0.30))
    m2 = _hand_pose((1.0, 0.0, 0.3), -0.7, (-0.04, 0.01, -0.25))
    rel = np.asarray(relative_transform(m1, m2), np.float64)
    p1 = np.array([0.01, 0.02, 0.03, 1.0])
    # eq. 3: P2 = M2⁻¹ M1 P1 (both frames see the same camera-space point)
    np.testing.assert_allclose(m2 @ (rel @ p1), m1 @ p1, atol=1e-6)
    np.testing.assert_allclose(rel, np.linalg.inv(m2) @ m1, atol=1e-6)
    # a pure offset between two markers with the same orientation: P2 = P1 + (t1 − t2)
    r = rotate((0, 1, 0), 0.3)
    a = translate((0.1, 0.0, -0.3)) @ r
    b = translate((-0.05, 0.02, -0.28)) @ r
    want = translate(r[:3, :3].T @ (np.array([0.1, 0.0, -0.3]) - [-0.05, 0.02, -0.28]))
    np.testing.assert_allclose(np.asarray(relative_transform(a, b)), want, atol=1e-6)


def test_interreflection_camera_looks_from_centre_i_at_centre_j():
    ci = np.array([-0.045, 0.0, -0.275])
    cj = np.array([0.045, 0.0, -0.275])
    cam = interreflection_camera(ci, cj)
    clip = np.asarray(project(cam, np.stack([cj, cj + [0, 0.01, 0]])), np.float64)
    np.testing.assert_allclose(_ndc(clip[0])[:2], [0, 0], atol=1e-6)
    assert _ndc(clip[1])[1] > 0  # world up is up
    # 90° field of view: a point at 45° off the axis lands on the edge
    d = np.linalg.norm(cj - ci)
    edge = ci + (cj - ci) + np.array([0, d, 0])
    np.testing.assert_allclose(_ndc(project(cam, edge[None]))[0, 1], 1.0, rtol=1e-5)
    # object j's vertices through lookAt(c_i, c_j)·(world-from-j)
    model = translate(cj)
    np.testing.assert_allclose(np.asarray(project(cam, np.zeros((1, 3)), model)), clip[:1],
                               atol=1e-6)


def test_opencv_to_opengl_axis_flip_round_trips():
    f = np.asarray(opencv_to_opengl_axes(), np.float64)
    np.testing.assert_allclose(f @ f, np.eye(4))
    rvec = np.array([0.3, -0.5, 0.2])
    r, _ = cv2.Rodrigues(rvec)
    t = np.array([0.02, -0.01, 0.4])
    view = opencv_pose_to_view(r, t)
    r2, t2 = view_to_opencv_pose(view)
    np.testing.assert_allclose(np.asarray(r2), r, atol=1e-6)
    np.testing.assert_allclose(np.asarray(t2), t, atol=1e-6)
    v = np.asarray(view, np.float64)
    np.testing.assert_allclose(np.asarray(opencv_pose_to_view(*view_to_opencv_pose(v))), v,
                               atol=1e-6)
    # a point in front of the OpenCV camera (Z > 0) is in front of the OpenGL one (z < 0),
    # above the image centre in OpenCV (Y < 0) is above in OpenGL (y > 0)
    x_world = np.linalg.solve(r, np.array([0.0, -0.05, 0.3]) - t)
    e = v @ [*x_world, 1]
    assert e[2] < 0 and e[1] > 0


def test_intrinsics_projection_matches_cv2_project_points():
    w, h = 720, 480
    # (cv2.projectPoints ignores a skew term; skew is checked by hand below)
    k = np.asarray(intrinsics_matrix(600.0, 610.0, 355.2, 243.7), np.float64)
    proj = intrinsics_to_projection(k, w, h, near=0.01, far=100.0)
    rvec = np.array([0.1, 0.2, -0.05])
    r, _ = cv2.Rodrigues(rvec)
    t = np.array([0.01, 0.02, 0.5])
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.1, 0.1, (20, 3))
    uv, _ = cv2.projectPoints(pts, rvec, t, k, None)
    cam = Camera(opencv_pose_to_view(r, t), proj)
    ours = _pixels(project(cam, pts), w, h)
    # OpenCV's pixel (0, 0) centre is our (0.5, 0.5)
    np.testing.assert_allclose(ours, uv[:, 0, :] + 0.5, atol=2e-3)
    ks = np.asarray(intrinsics_matrix(600.0, 610.0, 355.2, 243.7, skew=3.0), np.float64)
    cams = Camera(opencv_pose_to_view(r, t), intrinsics_to_projection(ks, w, h))
    xc = pts @ r.T + t
    want = np.stack([600 * xc[:, 0] / xc[:, 2] + 3.0 * xc[:, 1] / xc[:, 2] + 355.2,
                     610 * xc[:, 1] / xc[:, 2] + 243.7], -1)
    np.testing.assert_allclose(_pixels(project(cams, pts), w, h), want + 0.5, atol=2e-3)
    # depth: near → −1, far → +1 along the optical axis
    cam0 = Camera(opencv_pose_to_view(np.eye(3), np.zeros(3)), proj)
    z = _ndc(project(cam0, np.array([[0, 0, 0.01], [0, 0, 100.0]])))[:, 2]
    np.testing.assert_allclose(z, [-1, 1], atol=1e-4)


def test_intrinsics_projection_round_trips():
    w, h = 640, 400
    k = np.asarray(intrinsics_matrix(500.0, 505.0, 321.0, 198.5, 0.25), np.float64)
    p = intrinsics_to_projection(k, w, h)
    np.testing.assert_allclose(np.asarray(projection_to_intrinsics(p, w, h)), k, rtol=1e-5,
                               atol=1e-4)
    # perspective() → K → projection reproduces it; fy = (H/2) / tan(fov/2)
    q = perspective(90.0, w / h, 0.01, 1000.0)
    kq = np.asarray(projection_to_intrinsics(q, w, h), np.float64)
    np.testing.assert_allclose(kq[1, 1], h / 2 / math.tan(math.pi / 4), rtol=1e-6)
    np.testing.assert_allclose(kq[0, 0], kq[1, 1], rtol=1e-6)
    np.testing.assert_allclose(kq[:2, 2], [w / 2 - 0.5, h / 2 - 0.5], atol=1e-4)
    np.testing.assert_allclose(np.asarray(intrinsics_to_projection(kq, w, h, 0.01, 1000.0)),
                               np.asarray(q), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("shape", [(480, 720), (100, 100)])
def test_perspective_camera_pixel_of_a_known_direction(shape):
    h, w = shape
    cam = perspective_camera((0, 0, 0), (0, 0, -1), fov_y_deg=90.0, aspect=w / h)
    # the ray through the centre of pixel (row 0, column 0) points at tan(45°) up, scaled
    px, py = 0.5, 0.5
    x = (2 * px / w - 1) * (w / h)
    y = 1 - 2 * py / h
    clip = project(cam, np.array([[x * 2.0, y * 2.0, -2.0]]))
    np.testing.assert_allclose(_pixels(clip, w, h)[0], [px, py], atol=1e-3)


def test_closed_form_inverses_match_numpy():
    """inverse_3x3 / inverse_4x4 (closed forms, no LAPACK) against float64 numpy.linalg.inv on
    random well-conditioned matrices and on a projection·view product; eye_position against
    the eye given to look_at; gradients against jnp.linalg.inv's."""
    from spectral_fit.geometry import eye_position, inverse_3x3, inverse_4x4

    rng = np.random.default_rng(3)
    m4 = (rng.normal(size=(40, 4, 4)) + 3 * np.eye(4)).astype(np.float32)
    ref4 = np.linalg.inv(m4.astype(np.float64))
    assert np.abs(np.asarray(inverse_4x4(m4)) - ref4).max() < 2e-5 * np.abs(ref4).max()
    m3 = (rng.normal(size=(40, 3, 3)) + 2 * np.eye(3)).astype(np.float32)
    ref3 = np.linalg.inv(m3.astype(np.float64))
    assert np.abs(np.asarray(inverse_3x3(m3)) - ref3).max() < 2e-5 * np.abs(ref3).max()
    eye = np.array([0.12, -0.05, 0.31], np.float32)
    view = look_at(eye, np.array([0.0, 0.0, -0.3], np.float32))
    np.testing.assert_allclose(np.asarray(eye_position(view)), eye, atol=2e-6)
    pv = np.asarray(perspective(75.0, 1.5, 0.01, 100.0) @ view, np.float64)
    np.testing.assert_allclose(np.asarray(inverse_4x4(pv)) @ pv, np.eye(4), atol=1e-5)
    g_closed = jax.grad(lambda a: inverse_4x4(a)[1, 2])(jnp.asarray(m4[0]))
    g_lapack = jax.grad(lambda a: jnp.linalg.inv(a)[1, 2])(jnp.asarray(m4[0]))
    np.testing.assert_allclose(np.asarray(g_closed), np.asarray(g_lapack), rtol=1e-4, atol=1e-6)
