"""Lens distortion, one convention end to end: frames are undistorted onto the calibrated
pinhole K and the CG is rendered with that K. Synthetic frames through a strongly distorting
lens: with the calibrated distortion in the config the composited sphere lands on its
analytic (pinhole) silhouette in the output; with the distortion left out it misses the
sphere's true place in the frame by several pixels."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("cv2")
pytest.importorskip("spectral_fit.rendering._frame")

from helpers.live import K, scene_dict, table

from spectral_fit._runtime.errors import InputError
from spectral_fit.io import parse_scene
from spectral_fit.live import camera_pose_looking_at, marker_pose_in_camera, render_table

S = 3  # 240×160 frames
SIZE = (160, 240)
KS = np.array([[K[0, 0] / S, 0, (K[0, 2] + 0.5) / S - 0.5],
               [0, K[1, 1] / S, (K[1, 2] + 0.5) / S - 0.5], [0, 0, 1.0]])
DIST = np.array([-0.25, 0.08, 0.001, -0.0005, 0.0])  # a wide-angle lens
R = 0.03
EYE, TARGET = (0.0, 0.3, 0.25), (-0.1, 0.0, -0.1)  # marker 7 near the right edge


def _scene(distortion):
    d = scene_dict(markers={"size": 0.08}, width=SIZE[1], height=SIZE[0])
    d["camera"]["intrinsics"] = {"fx": KS[0, 0], "fy": KS[1, 1], "cx": KS[0, 2],
                                 "cy": KS[1, 2]}
    if distortion is None:
        del d["camera"]["distortion"]
    else:
        d["camera"]["distortion"] = [float(x) for x in distortion]
    for o in d["objects"]:
        o["stacks"] = o["slices"] = 24
    d["interreflection"] = {"mode": "none"}
    return parse_scene(d)


def _sphere_masks(r, t, marker_id):
    """Pixels (OpenCV centres) whose ray passes within the sphere's angular radius, for the
    ideal pinhole K (the undistorted output) and for the distorting lens (the raw frame)."""
    import cv2

    rm, tm = marker_pose_in_camera(table(), marker_id, r, t)
    c = rm @ np.array([0.0, 0.0, R]) + tm
    c = c / np.linalg.norm(c)
    alpha = np.arcsin(R / np.linalg.norm(rm @ np.array([0.0, 0.0, R]) + tm))
    jj, ii = np.meshgrid(np.arange(SIZE[1], dtype=np.float64),
                         np.arange(SIZE[0], dtype=np.float64))
    pix = np.stack([jj, ii], -1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 60, 1e-12)
    out = []
    for dist in (np.zeros(5), DIST):
        xy = cv2.undistortPoints(pix, KS, dist, criteria=crit).reshape(SIZE[0], SIZE[1], 2)
        d = np.concatenate([xy, np.ones((*SIZE, 1))], -1)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        ang = np.arccos(np.clip(d @ c, -1.0, 1.0))
        out.append((ang < alpha, np.abs(ang - alpha) * KS[0, 0]))
    return out


def _centroid(mask):
    ii, jj = np.nonzero(mask)
    return np.array([jj.mean(), ii.mean()])


@pytest.fixture(scope="module")
def shot():
    r, t = camera_pose_looking_at(EYE, TARGET)
    img = render_table(table(), KS, DIST, r, t, SIZE, blur_px=0.5, noise=1.5,
                       rng=np.random.default_rng(5))
    return img, r, t


def test_undistorted_frames_put_the_sphere_on_its_silhouette(shot):
    from spectral_fit.live import LiveSession, MarkerDetector, MarkerTracker

    img, r, t = shot
    (pin, pin_d), (raw, _) = _sphere_masks(r, t, 7)
    # the lens moves this sphere by several pixels: the two analytic silhouettes differ
    assert np.linalg.norm(_centroid(pin) - _centroid(raw)) > 3.0

    good = LiveSession(_scene(DIST), size=SIZE)
    out = good.process(img)
    assert good.last_poses.visible.tolist() == [True, True]
    got = np.asarray(good.last_object_id) == 1
    iou = (got & pin).sum() / (got | pin).sum()
    assert iou > 0.95
    assert np.all(pin_d[got != pin] < 1.0)  # disagreements only at the rim
    assert np.linalg.norm(_centroid(got) - _centroid(pin)) < 0.5
    # the output is the undistorted frame (pinhole geometry) outside the CG
    oid = np.asarray(good.last_object_id)
    np.testing.assert_array_equal(out[oid < 0], good.undistort(img)[oid < 0])

    # without the distortion model the frame stays raw (the sphere truly is at `raw`) and the
    # marker pose comes from a pinhole: the sphere's pinhole silhouette at that pose (what
    # the renderer draws, as checked above) misses `raw` by pixels
    scene = _scene(None)
    poses = MarkerTracker(scene).update(MarkerDetector(scene.markers, KS, None).detect(img))
    centre_eye = (poses.view.astype(np.float64) @ poses.model[1].astype(np.float64))[:3, 3]
    c = centre_eye * np.array([1.0, -1.0, -1.0])  # OpenGL eye -> OpenCV camera
    jj, ii = np.meshgrid(np.arange(SIZE[1], dtype=np.float64),
                         np.arange(SIZE[0], dtype=np.float64))
    d = np.stack([jj, ii, np.ones_like(jj)], -1) @ np.linalg.inv(KS).T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    ang = np.arccos(np.clip(d @ (c / np.linalg.norm(c)), -1.0, 1.0))
    drawn = ang < np.arcsin(R / np.linalg.norm(c))
    assert (drawn & raw).sum() / (drawn | raw).sum() < 0.85
    assert np.linalg.norm(_centroid(drawn) - _centroid(raw)) > 2.0


@pytest.mark.slow
def test_without_the_distortion_model_the_composite_misses(shot):
    """The same as the last part above, through a whole live session (a second compile)."""
    from spectral_fit.live import LiveSession

    img, r, t = shot
    _, (raw, _) = _sphere_masks(r, t, 7)
    bad = LiveSession(_scene(None), size=SIZE)
    out = bad.process(img)
    assert bad.last_poses.visible.tolist() == [True, True]
    oid = np.asarray(bad.last_object_id)
    np.testing.assert_array_equal(out[oid < 0], img[oid < 0])  # the raw frame
    got = oid == 1
    assert (got & raw).sum() / (got | raw).sum() < 0.85
    assert np.linalg.norm(_centroid(got) - _centroid(raw)) > 2.0


def test_rendering_through_the_lens_keeps_the_raw_frame(shot):
    """lens="distort": the video frame is not resampled, and the CG lands on the sphere's
    silhouette in the raw frame (through the lens), not on its pinhole one."""
    from spectral_fit.live import LiveSession

    img, r, t = shot
    (pin, _), (raw, raw_d) = _sphere_masks(r, t, 7)
    sess = LiveSession(_scene(DIST), size=SIZE, lens="distort")
    assert sess.prep.camera.lens is not None
    out = sess.process(img)
    assert sess.last_poses.visible.tolist() == [True, True]
    oid = np.asarray(sess.last_object_id)
    np.testing.assert_array_equal(out[oid < 0], img[oid < 0])  # the raw frame itself
    got = oid == 1
    assert (got & raw).sum() / (got | raw).sum() > 0.95
    assert np.all(raw_d[got != raw] < 1.0)  # disagreements only at the rim
    assert np.linalg.norm(_centroid(got) - _centroid(raw)) < 0.5
    assert np.linalg.norm(_centroid(got) - _centroid(pin)) > 2.5
    with pytest.raises(InputError, match="lens"):
        LiveSession(_scene(DIST), size=SIZE, lens="fisheye")
