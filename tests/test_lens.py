"""Lens distortion of the render camera (spectral_fit.geometry and the renderer's use of it),
checked against OpenCV's own implementation of the model (projectPoints, undistortPoints), a
closed-form fold radius, and an analytic sphere silhouette seen through the lens."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

pytest.importorskip("cv2")

import cv2  # noqa: E402  (after the skip: the `live` extra)
from helpers import ROOT  # noqa: E402

from spectral_fit._runtime.errors import InputError
from spectral_fit.geometry import (
    distort_eye,
    distort_normalized,
    lens_parameters,
    pixel_rays,
    undistort_normalized,
)

# one worker runs this module's tests (ONE_WORKER_MODULES in tests/conftest.py):
# the two lens frames are compiled once

GL = np.array([1.0, -1.0, -1.0])  # OpenCV camera axes <-> OpenGL eye axes
K = np.array([[210.0, 0.0, 121.0], [0.0, 205.0, 78.5], [0.0, 0.0, 1.0]])  # 240 x 160
SIZE = (160, 240)
DIST5 = np.array([-0.28, 0.09, 0.0012, -0.0008, -0.01])  # a wide-angle lens
DIST8 = np.array([-0.2, 0.05, 0.001, -0.002, 0.003, 0.05, 0.004, 0.0005])  # rational model


def _project(eye, k):
    """Pixel coordinates (N, 2), OpenCV convention, of OpenGL eye points through pinhole k."""
    cv = eye * GL
    x, y = cv[:, 0] / cv[:, 2], cv[:, 1] / cv[:, 2]
    return np.stack([k[0, 0] * x + k[0, 1] * y + k[0, 2], k[1, 1] * y + k[1, 2]], -1)


@pytest.mark.parametrize("dist", [DIST5, DIST8], ids=["5 coefficients", "8 coefficients"])
@pytest.mark.parametrize("xp", ["numpy", "jax"])
def test_distorted_vertices_project_where_opencv_projects_them(dist, xp):
    rng = np.random.default_rng(1)
    pts = rng.uniform([-0.5, -0.35, 0.4], [0.5, 0.35, 3.0], (2000, 3))  # OpenCV camera frame
    want, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, dist)
    lens = lens_parameters(dist)
    if xp == "numpy":
        got = _project(distort_eye(pts * GL, lens, np), K)
        tol = 1e-9
    else:
        import jax.numpy as jnp

        got = _project(np.asarray(distort_eye(jnp.asarray(pts * GL, jnp.float32),
                                              jnp.asarray(lens, jnp.float32)), np.float64), K)
        tol = 2e-3  # float32 eye coordinates
    assert np.abs(got - want[:, 0]).max() < tol


@pytest.mark.parametrize("dist", [DIST5, DIST8], ids=["5 coefficients", "8 coefficients"])
def test_pixel_rays_are_opencvs_undistorted_rays_of_the_pixel_centres(dist):
    lens = lens_parameters(dist)
    rays = pixel_rays(K, lens, SIZE)
    assert rays.shape == (SIZE[0] * SIZE[1], 3)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1.0, atol=1e-6)
    # forward: OpenCV projects each ray back onto its own pixel centre
    back, _ = cv2.projectPoints((rays * GL).astype(np.float64), np.zeros(3), np.zeros(3), K,
                                dist)
    v, u = np.meshgrid(np.arange(SIZE[0]), np.arange(SIZE[1]), indexing="ij")
    centres = np.stack([u.ravel(), v.ravel()], -1).astype(np.float64)
    assert np.abs(back[:, 0] - centres).max() < 1e-3
    # inverse: OpenCV's own iterative undistortion of the pixel centres
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    xy = cv2.undistortPoints(centres.reshape(-1, 1, 2), K, dist, criteria=crit).reshape(-1, 2)
    cv_rays = np.concatenate([xy, np.ones((len(xy), 1))], -1)
    cv_rays /= np.linalg.norm(cv_rays, axis=-1, keepdims=True)
    assert np.abs(rays * GL - cv_rays).max() < 1e-6


def test_fold_radius_closed_form_and_no_fold_beyond_it():
    # r (1 + k1 r²) stops growing where 1 + 3 k1 r² = 0
    k1 = -0.3
    lens = lens_parameters([k1, 0.0, 0.0, 0.0])
    assert math.sqrt(lens[8]) == pytest.approx(1.0 / math.sqrt(-3.0 * k1), abs=2e-4)
    # along any ray from the centre the distorted radius keeps growing, far past the fold
    r = np.linspace(0.0, 10.0, 5001)
    for ang in np.linspace(0.0, 2.0 * np.pi, 7):
        xd, yd = distort_normalized(r * np.cos(ang), r * np.sin(ang), lens, np)
        assert np.all(np.diff(np.hypot(xd, yd)) > 0.0)
    # inside the fold radius the model is OpenCV's (no clamp)
    x = np.linspace(-0.7, 0.7, 101)
    xd, _ = distort_normalized(x, np.zeros_like(x), lens, np)
    np.testing.assert_allclose(xd, x * (1.0 + k1 * x * x), rtol=1e-12)
    # and undistort_normalized inverts it there
    xu, yu, res = undistort_normalized(xd, np.zeros_like(xd), lens)
    np.testing.assert_allclose(xu, x, atol=1e-12)
    assert res.max() < 1e-12


@pytest.mark.parametrize("bad, words", [
    ([0.1, 0.2, 0.3], "4, 5 or 8"),
    ([float("nan"), 0.0, 0.0, 0.0], "finite"),
    ([-50.0, 0.0, 0.0, 0.0], "folds"),
])
def test_bad_lens_coefficients_name_the_field(bad, words):
    with pytest.raises(InputError, match=words) as e:
        lens_parameters(bad, path="scene.toml")
    assert "scene.toml" in str(e.value) and "camera.distortion" in str(e.value)


# --------------------------------------------------------------------------------------------
# the renderer through the lens


SPHERE = (0.06, 0.03, -0.2)


def _scene(dist, *, sphere_at=SPHERE, intrinsics=True):
    from spectral_fit.io import load_scene

    sc = load_scene(ROOT / "configs" / "benchmark.toml")
    cam = dataclasses.replace(
        sc.camera, distortion=None if dist is None else tuple(float(c) for c in dist),
        intrinsics=({"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
                    if intrinsics else None))
    obj = dataclasses.replace(sc.objects[0], position=sphere_at, stacks=48, slices=48)
    return sc.replace(camera=cam, objects=(obj,), width=SIZE[1], height=SIZE[0])


@pytest.fixture(scope="module")
def frames():
    from spectral_fit.rendering import prepare, render_frame

    out = {}
    for name, dist in (("lens", DIST5), ("pinhole", None)):
        prep = prepare(_scene(dist), mode="none")
        out[name] = (prep, render_frame(prep))
    return out


def _silhouette(dist, k=K, at=SPHERE):
    """Pixels whose ray (OpenCV's undistortion of the pixel centre) meets the sphere."""
    c = np.array(at) * GL  # OpenCV camera frame (camera at the origin)
    rad = 0.0375
    v, u = np.meshgrid(np.arange(SIZE[0]), np.arange(SIZE[1]), indexing="ij")
    pix = np.stack([u, v], -1).reshape(-1, 1, 2).astype(np.float64)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    xy = cv2.undistortPoints(pix, k, np.zeros(5) if dist is None else dist,
                             criteria=crit).reshape(*SIZE, 2)
    d = np.concatenate([xy, np.ones((*SIZE, 1))], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    alpha = np.arcsin(rad / np.linalg.norm(c))
    return np.arccos(np.clip(d @ (c / np.linalg.norm(c)), -1.0, 1.0)) < alpha


def _centroid(mask):
    ii, jj = np.nonzero(mask)
    return np.array([jj.mean(), ii.mean()])


def test_object_lands_on_its_silhouette_through_the_lens(frames):
    mask = np.asarray(frames["lens"][1].mask)
    want = _silhouette(DIST5)
    pinhole = _silhouette(None)
    shift = np.linalg.norm(_centroid(want) - _centroid(pinhole))
    assert shift > 4.0  # the lens moves the sphere by pixels here: the test can tell
    assert np.linalg.norm(_centroid(mask) - _centroid(want)) < 0.25
    assert np.sum(mask != want) <= 0.08 * want.sum()  # rim pixels of the 48 x 48 tessellation
    # the pinhole frame of the same scene misses it by the lens's shift
    pin = np.asarray(frames["pinhole"][1].mask)
    assert np.linalg.norm(_centroid(pin) - _centroid(want)) > 0.8 * shift


def test_background_is_the_environment_along_each_pixels_ray(frames):
    import jax
    import jax.numpy as jnp

    from spectral_fit.lighting import lookup

    prep, frame = frames["lens"]
    v, u = np.meshgrid(np.arange(SIZE[0]), np.arange(SIZE[1]), indexing="ij")
    pix = np.stack([u, v], -1).reshape(-1, 1, 2).astype(np.float64)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    xy = cv2.undistortPoints(pix, K, DIST5, criteria=crit).reshape(-1, 2)
    eye = np.concatenate([xy, np.ones((len(xy), 1))], -1) * GL
    world = eye @ np.asarray(prep.camera.view, np.float64)[:3, :3]  # eye → world: Rᵀ
    world /= np.linalg.norm(world, axis=-1, keepdims=True)
    env = prep.lighting.env
    want = np.asarray(jax.vmap(lambda d: lookup(env, d))(jnp.asarray(world, jnp.float32))
                      @ prep.colour.to_xyz).reshape(*SIZE, 3)
    got = np.asarray(frame.xyz)
    bg = ~np.asarray(frame.mask)
    err = np.abs(got - want)[bg] / np.abs(want[bg]).max()
    assert np.median(err) < 1e-5 and err.max() < 2e-3
    # the pinhole frame's background differs there by far more (the test can tell)
    pin = np.asarray(frames["pinhole"][1].xyz)
    assert np.median(np.abs(pin - want)[bg] / np.abs(want[bg]).max()) > 100 * np.median(err)


@pytest.mark.slow  # two more frame programs; the lens frames of the default tier are checked
# against OpenCV's projection and undistortion directly
def test_a_lens_without_distortion_renders_the_pinhole_frame():
    from spectral_fit.rendering import prepare, render_frame

    zero = prepare(_scene([0.0, 0.0, 0.0, 0.0, 0.0]), mode="none")
    assert zero.camera.lens is None and zero.camera.pixel_rays is None  # the pinhole program itself
    tiny = prepare(_scene([1e-9, 0.0, 0.0, 0.0]), mode="none")
    assert tiny.camera.lens is not None
    a, b = render_frame(zero), render_frame(tiny)
    assert np.array_equal(np.asarray(a.mask), np.asarray(b.mask))
    assert np.abs(np.asarray(a.rgb) - np.asarray(b.rgb)).max() < 1e-4


def test_a_lens_that_folds_inside_the_frame_is_an_error():
    from spectral_fit.rendering import prepare

    # the benchmark's 90° camera reaches normalised radius 1.8 at the corners; r (1 − 0.05 r²)
    # never gets there (its largest value is 1.72, at its fold radius 2.58)
    with pytest.raises(InputError, match="folds inside the frame") as e:
        prepare(_scene([-0.05, 0.0, 0.0, 0.0], intrinsics=False), mode="none")
    assert "camera.distortion" in str(e.value) and "benchmark.toml" in str(e.value)


def test_fov_camera_is_distorted_too():
    """A camera given by its field of view (no intrinsics) goes through the lens as well."""
    from spectral_fit.geometry import projection_to_intrinsics
    from spectral_fit.rendering import prepare, render_frame

    dist = np.array([-0.02, 0.0, 0.0, 0.0])
    at = (0.2, 0.1, -0.2)  # normalised (1, 0.5): the lens moves it by ~2 px
    prep = prepare(_scene(dist, intrinsics=False, sphere_at=at), mode="none")
    k = np.asarray(projection_to_intrinsics(prep.camera.projection, SIZE[1], SIZE[0]), np.float64)
    want = _silhouette(dist, k, at)
    mask = np.asarray(render_frame(prep).mask)
    assert np.linalg.norm(_centroid(mask) - _centroid(want)) < 0.25
    assert np.linalg.norm(_centroid(want) - _centroid(_silhouette(None, k, at))) > 1.0


def test_distortion_is_differentiable():
    """jax's derivative of the eye-space distortion against float64 central differences."""
    import jax
    import jax.numpy as jnp

    lens = lens_parameters(DIST8)
    rng = np.random.default_rng(4)
    pts = rng.uniform([-0.5, -0.35, -3.0], [0.5, 0.35, -0.4], (64, 3))  # OpenGL eye, in front
    pts[0] = (0.0, 0.0, -1.0)  # on the axis
    jac = jax.vmap(jax.jacfwd(lambda p: distort_eye(p[None], jnp.asarray(lens, jnp.float32))[0]))(
        jnp.asarray(pts, jnp.float32))
    h = 1e-6
    fd = np.stack([(distort_eye(pts + h * e, lens, np) - distort_eye(pts - h * e, lens, np))
                   / (2 * h) for e in np.eye(3)], -1)
    assert np.all(np.isfinite(np.asarray(jac)))
    np.testing.assert_allclose(np.asarray(jac), fd, atol=2e-4)


def test_edge_error_closed_form_and_coarse_mesh_warning():
    """The midpoint error of a straight edge under k1 alone, against its closed form; prepare
    warns for a coarsely tessellated object near the frame's edge and not for a fine one."""
    from spectral_fit.geometry import edge_error_px
    from spectral_fit.rendering import prepare

    k1 = -0.2
    lens = lens_parameters([k1, 0.0, 0.0, 0.0])
    kk = np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 50.0], [0.0, 0.0, 1.0]])
    # an edge at depth 1 from normalised x = a to x = b on the horizontal axis: the raster
    # puts its midpoint at the mean of the distorted ends, the lens at the distorted mean
    a, b = 0.2, 0.8
    pts = np.array([[a, 0.0, -1.0], [b, 0.0, -1.0]])
    d = lambda x: x * (1.0 + k1 * x * x)  # noqa: E731
    want = 100.0 * abs(0.5 * (d(a) + d(b)) - d(0.5 * (a + b)))
    err, mid = edge_error_px(pts, np.array([[0, 1]]), lens, kk)
    assert err[0] == pytest.approx(want, rel=1e-9)
    # and the lens's image of the true midpoint, in pixels
    np.testing.assert_allclose(mid[0], [50.0 + 100.0 * d(0.5 * (a + b)), 50.0], rtol=1e-12)
    import warnings

    with pytest.warns(RuntimeWarning, match="triangles are large for this lens"):
        sc = _scene(DIST5, sphere_at=(0.09, 0.05, -0.2))
        sc = sc.replace(objects=(dataclasses.replace(sc.objects[0], stacks=6, slices=6),))
        prepare(sc, mode="none")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        prepare(_scene(DIST5), mode="none")


def test_lens_benchmark_scene_rays_are_opencvs():
    """``spectral-fit bench``'s ``frame_paper_lens`` scene: the benchmark camera (720 × 480,
    90° vertical field of view) with the bundled webcam's distortion, which must not fold
    inside the frame: every pixel centre's ray projects back onto that centre through
    OpenCV's model (checked on a sparse grid)."""
    from spectral_fit.bench.cases.frame import LENS, benchmark_scene
    from spectral_fit.live import scene_intrinsics

    scene = benchmark_scene(distortion=LENS, quick=True)
    assert scene.camera.distortion == LENS and scene.camera.intrinsics is None
    h, w = scene.height, scene.width
    k = np.asarray(scene_intrinsics(scene, (h, w))[0], np.float64)
    rays = pixel_rays(k, lens_parameters(np.asarray(LENS)), (h, w)).reshape(h, w, 3)
    v, u = np.mgrid[0:h:37, 0:w:53]
    back, _ = cv2.projectPoints((rays[v.ravel(), u.ravel()] * GL).astype(np.float64),
                                np.zeros(3), np.zeros(3), k, np.asarray(LENS))
    centres = np.stack([u.ravel(), v.ravel()], -1).astype(np.float64)
    assert np.abs(back[:, 0] - centres).max() < 1e-3
    # the lens matters at this size: the frame's corner moves by more than 10 px
    corner = np.array([[[0.0, 0.0]]])
    und = cv2.undistortPoints(corner, k, np.asarray(LENS), P=k).reshape(2)
    assert np.linalg.norm(und - corner.reshape(2)) > 10.0
