"""Markers: poses from synthetic frames at known poses, tracking (hold, mask, smoothing,
world frame), the ``[markers]`` config table."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("cv2")

from helpers.live import DIST, MARKER_SIZE, K, frame, rotation_angle_deg, scene_dict, table

from spectral_fit._runtime.errors import InputError
from spectral_fit.io import MarkerSpec, parse_scene
from spectral_fit.live import (
    MarkerDetection,
    MarkerDetector,
    MarkerTracker,
    ground_frame,
    marker_pose_in_camera,
)

EYES = [(0.0, 0.25, 0.2), (0.15, 0.2, 0.25), (-0.2, 0.3, 0.15)]


@pytest.fixture(scope="module")
def frames():
    return [frame(eye, seed=i) for i, eye in enumerate(EYES)]


def test_detected_poses_within_1deg_2mm(frames):
    det = MarkerDetector(MarkerSpec(size=MARKER_SIZE), K, DIST)
    n = 0
    for img, r, t in frames:
        found = det.detect(img)
        assert sorted(found) == [3, 7]
        for i, d in found.items():
            rt, tt = marker_pose_in_camera(table(), i, r, t)
            assert rotation_angle_deg(rt, d.rotation) < 1.0
            assert np.linalg.norm(tt - d.translation) < 2e-3
            assert d.reprojection_px < 0.3
            n += 1
    assert n == 6


def test_edge_refinement_removes_the_blur_bias_of_corner_refinement(frames):
    """OpenCV's corner refinement pulls blurred convex corners inwards (markers look farther
    away); the edge lines do not."""
    far = {}
    for refine in ("subpix", "edges"):
        det = MarkerDetector(MarkerSpec(size=MARKER_SIZE, refine=refine), K, DIST)
        dz = [d.translation[2] - marker_pose_in_camera(table(), i, r, t)[1][2]
              for img, r, t in frames for i, d in det.detect(img).items()]
        far[refine] = float(np.mean(dz))
    assert far["subpix"] > 3e-4
    assert abs(far["edges"]) < far["subpix"] / 3


def test_ignoring_distortion_is_measurably_worse(frames):
    """The distortion model matters: without it the same corners give worse poses."""
    img, r, t = frames[1]
    good = MarkerDetector(MarkerSpec(size=MARKER_SIZE), K, DIST).detect(img)
    bad = MarkerDetector(MarkerSpec(size=MARKER_SIZE), K, None).detect(img)
    err = {}
    for name, found in (("good", good), ("bad", bad)):
        err[name] = max(np.linalg.norm(marker_pose_in_camera(table(), i, r, t)[1]
                                       - d.translation) for i, d in found.items())
    assert err["bad"] > 2 * err["good"]


def test_downscaled_detection_keeps_full_resolution_accuracy(frames):
    """Detection on the frame shrunk 2× with corners refined at full resolution gives the
    poses of full-resolution detection (the 1°/2 mm test above runs at the default, 2×)."""
    full = MarkerDetector(MarkerSpec(size=MARKER_SIZE), K, DIST, downscale=1)
    half = MarkerDetector(MarkerSpec(size=MARKER_SIZE), K, DIST, downscale=2)
    for img, _r, _t in frames:
        a, b = full.detect(img), half.detect(img)
        assert sorted(a) == sorted(b) == [3, 7]
        for i in a:
            assert np.linalg.norm(a[i].translation - b[i].translation) < 2e-4
            assert rotation_angle_deg(a[i].rotation, b[i].rotation) < 0.1


def test_small_markers_with_thin_margins_keep_their_accuracy():
    """60 mm markers with a one-module white margin, 90 mm apart, seen from 0.28 m at 40–50°
    by a 90° lens (the live benchmark scene: ~50 px markers, ~5 px margins): corners refined
    at full resolution after the shrunk-frame detection stay on the black square (a fixed
    11×11 refinement window reached the margin's outer edge: 10° / 15 mm median errors)."""
    from skimage import data

    from spectral_fit.live import MarkerPlacement, camera_pose_looking_at, make_table, render_table

    k = np.array([[240.0, 0.0, 359.5], [0.0, 240.0, 239.5], [0.0, 0.0, 1.0]])
    tab = make_table(data.coffee(), [MarkerPlacement(3, -0.045, 0.0, 0.06),
                                     MarkerPlacement(7, 0.045, 0.0, 0.06)], extent=(0.9, 0.65))
    det = MarkerDetector(MarkerSpec(size=0.06), k)
    centre = np.array([0.0, 0.0375, 0.0])
    for n, (az, el) in enumerate([(-20, 45), (0, 40), (15, 50)]):
        a, e = np.radians(az), np.radians(el)
        eye = centre + 0.275 * np.array([np.cos(e) * np.sin(a), np.sin(e),
                                         np.cos(e) * np.cos(a)])
        r, t = camera_pose_looking_at(eye, centre)
        img = render_table(tab, k, None, r, t, (480, 720), blur_px=0.6, noise=1.5,
                           rng=np.random.default_rng(n))
        found = det.detect(img)
        assert sorted(found) == [3, 7]
        for i, d in found.items():
            rt, tt = marker_pose_in_camera(tab, i, r, t)
            assert rotation_angle_deg(rt, d.rotation) < 1.0
            assert np.linalg.norm(tt - d.translation) < 2e-3


def test_distant_markers_found_by_full_scan_then_tracked():
    """At ~2 m (markers ~20 px) the 2×-shrunk frame shows no marker; with the scene's ids
    expected, one full-resolution scan finds them and the next frames track them in windows
    around their last corners, without another full scan."""
    eyes = [(0.0, 1.6, 1.2), (0.02, 1.6, 1.22), (0.04, 1.62, 1.24), (0.06, 1.64, 1.24)]
    shots = [frame(eye, seed=20 + n) for n, eye in enumerate(eyes)]
    blind = MarkerDetector(MarkerSpec(size=MARKER_SIZE), K, DIST, downscale=2, track=False)
    assert blind.detect(shots[0][0]) == {}
    det = MarkerDetector(MarkerSpec(size=MARKER_SIZE), K, DIST, downscale=2, expect=(3, 7))
    full = MarkerDetector(MarkerSpec(size=MARKER_SIZE), K, DIST, downscale=1)
    for img, r, t in shots:
        found, ref = det.detect(img), full.detect(img)
        assert sorted(found) == sorted(ref) == [3, 7]
        for i, d in found.items():
            # the same pose as full-resolution detection, near the truth (20 px markers)
            np.testing.assert_allclose(d.translation, ref[i].translation, atol=1e-4)
            tt = marker_pose_in_camera(table(), i, r, t)[1]
            assert np.linalg.norm(tt - d.translation) < 0.05 * np.linalg.norm(tt)
    assert det.full_scans == 1


def test_world_marker_frame_gives_table_coordinates(frames):
    """With marker 3 as the world, the sphere on marker 7 sits at the marker's table position
    relative to marker 3 (plus its offset), whatever the camera pose."""
    scene = parse_scene(scene_dict(markers={"size": MARKER_SIZE, "world": 3}))
    det = MarkerDetector(scene.markers, K, DIST)
    m3, m7 = table().markers
    want = np.array([m7.x - m3.x, 0.03, m7.z - m3.z])
    for img, _r, _t in frames:
        poses = MarkerTracker(scene).update(det.detect(img))
        assert poses.model.shape == (2, 4, 4) and poses.model.dtype == np.float32
        assert poses.visible.tolist() == [True, True]
        np.testing.assert_allclose(poses.model[0, :3, 3], [0.0, 0.03, 0.0], atol=2e-3)
        np.testing.assert_allclose(poses.model[1, :3, 3], want, atol=3e-3)
        # world +Y (the table normal) stays +Y for both objects
        assert rotation_angle_deg(poses.model[1, :3, :3], np.eye(3)) < 1.5


def test_ground_frame_axes():
    """A marker facing the camera upright (OpenCV R = diag(1, −1, −1): its +Y up in the
    image, its +Z towards the camera) is a ground frame whose +Y points at the camera (OpenGL
    eye +Z) and whose −Z points up in the image (eye +Y)."""
    g = ground_frame(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 0.5])
    np.testing.assert_allclose(g[:3, 3], [0.0, 0.0, -0.5], atol=1e-7)
    np.testing.assert_allclose(g[:3, 1], [0.0, 0.0, 1.0], atol=1e-7)
    np.testing.assert_allclose(-g[:3, 2], [0.0, 1.0, 0.0], atol=1e-7)


FACING = np.diag([1.0, -1.0, -1.0])  # OpenCV pose of an upright marker facing the camera


def _det(i, t, r=None):
    r = FACING if r is None else FACING @ r
    return MarkerDetection(i, np.zeros((4, 2)), r, np.asarray(t, float), 0.0)


def test_tracker_hold_then_mask_keeps_shapes():
    scene = parse_scene(scene_dict(markers={"size": MARKER_SIZE, "hold_frames": 2}))
    tr = MarkerTracker(scene)
    p0 = tr.update({})
    assert p0.visible.tolist() == [False, False]
    p1 = tr.update({3: _det(3, [0.0, 0.0, 0.4]), 7: _det(7, [0.1, 0.0, 0.4])})
    assert p1.visible.tolist() == [True, True]
    # sphere centre: marker centre + 0.03 m along the marker normal (towards the camera)
    np.testing.assert_allclose(p1.model[0, :3, 3], [0.0, 0.0, -0.37], atol=1e-6)
    seen = []
    for _ in range(4):
        p = tr.update({7: _det(7, [0.1, 0.0, 0.4])})
        assert p.model.shape == (2, 4, 4) and p.visible.shape == (2,)
        seen.append(bool(p.visible[0]))
        np.testing.assert_allclose(p.model[0, :3, 3], [0.0, 0.0, -0.37], atol=1e-6)
    assert seen == [True, True, False, False]


def test_tracker_smoothing_is_exponential():
    scene = parse_scene(scene_dict(markers={"size": MARKER_SIZE, "smoothing": 0.5}))
    tr = MarkerTracker(scene)
    tr.update({3: _det(3, [0.0, 0.0, 0.4])})
    p = tr.update({3: _det(3, [0.02, 0.0, 0.4])})
    np.testing.assert_allclose(p.model[0, :3, 3], [0.01, 0.0, -0.37], atol=1e-6)
    # rotation: halfway between 0 and 20 degrees about the marker normal -> 10 degrees
    c, s = np.cos(np.radians(20)), np.sin(np.radians(20))
    rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    tr2 = MarkerTracker(scene)
    p1 = tr2.update({3: _det(3, [0.0, 0.0, 0.4])})
    p2 = tr2.update({3: _det(3, [0.0, 0.0, 0.4], rz)})
    assert abs(rotation_angle_deg(p2.model[0, :3, :3], p1.model[0, :3, :3]) - 10.0) < 1e-3


@pytest.mark.parametrize(("markers", "key"), [
    ({"dictionary": "DICT_9X9_50"}, "markers.dictionary"),
    ({"size": -0.08}, "markers.size"),
    ({"smoothing": 1.0}, "markers.smoothing"),
    ({"world": 100}, "markers.world"),
    ({"sizes": 0.08}, "markers.sizes"),
    ({"dictionary": "DICT_4X4_50", "hold_frames": 1}, "objects[1].marker"),
])
def test_markers_table_errors_name_the_key(markers, key):
    d = scene_dict(markers=markers)
    if key == "objects[1].marker":
        d["objects"][1]["marker"] = 50
    with pytest.raises(InputError) as e:
        parse_scene(d, path="live.toml")
    assert e.value.field == key
    assert str(e.value).startswith("live.toml: " + key)


def test_markers_table_defaults_and_absence():
    assert parse_scene(scene_dict(markers=False)).markers is None
    m = parse_scene(scene_dict(markers={})).markers
    assert m == MarkerSpec()
