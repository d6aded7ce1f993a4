"""The bundled benchmark video (measurements/video/benchmark.mp4, configs/live_benchmark.toml): the
benchmark scene (docs/benchmark.md) as a live scene. Its markers give the poses it was made with,
and the spheres on them cover about as many pixels as in the benchmark frame."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("cv2")

from helpers import ROOT
from helpers.live import rotation_angle_deg

from spectral_fit.io import load_scene
from spectral_fit.live import MarkerDetector, read_frames, scene_intrinsics

CONFIG = ROOT / "configs" / "live_benchmark.toml"
VIDEO = ROOT / "measurements" / "video" / "benchmark.mp4"


@pytest.fixture(scope="module")
def bundled():
    meta = json.loads(VIDEO.with_suffix(".poses.json").read_text())
    return load_scene(CONFIG), read_frames(VIDEO), meta


def test_config_matches_the_benchmark_scene_and_the_video(bundled):
    scene, frames, meta = bundled
    bench = load_scene(ROOT / "configs" / "benchmark.toml")
    assert (scene.width, scene.height) == (bench.width, bench.height) == (720, 480)
    assert scene.camera.fov_y_deg == bench.camera.fov_y_deg == 90.0
    assert scene.interreflection == bench.interreflection
    for a, b in zip(scene.objects, bench.objects, strict=True):
        np.testing.assert_array_equal(a.material.reflectance, b.material.reflectance)
        for f in ("alpha", "beta", "chi", "mu", "n", "gamma", "distribution", "geometry"):
            assert getattr(a.material, f) == getattr(b.material, f), f
        assert (a.radius, a.stacks, a.slices) == (b.radius, b.stacks, b.slices)
    k, dist = scene_intrinsics(scene)
    np.testing.assert_allclose(k, meta["intrinsics"])
    assert dist is None and not np.any(meta["distortion"])
    assert scene.markers.size == meta["marker_size"]
    assert len(frames) == len(meta["frames"]) == 60
    assert frames[0].shape == (480, 720, 3)


def test_markers_give_the_poses_the_video_was_made_with(bundled):
    scene, frames, meta = bundled
    k, dist = scene_intrinsics(scene)
    det = MarkerDetector(scene.markers, k, dist, expect=(3, 7))
    angles, shifts = [], []
    for img, truth in zip(frames, meta["frames"], strict=True):
        found = det.detect(img)
        assert sorted(found) == [3, 7], truth["frame"]
        for i, d in found.items():
            t = truth["markers"][str(i)]
            angles.append(rotation_angle_deg(t["R"], d.rotation))
            shifts.append(np.linalg.norm(np.asarray(t["t"]) - d.translation))
    # poses at mid-shutter of a blurred, noisy, MPEG-4-coded frame of ~50 px markers
    assert np.median(angles) < 0.5 and max(angles) < 2.0
    assert max(shifts) < 2e-3


def _covered_pixels(centres_cam: np.ndarray, radius: float, k: np.ndarray) -> int:
    """Pixels (720×480) whose centre's ray hits one of the spheres (camera frame, OpenCV
    axes: +Z forward), brute force."""
    ys, xs = np.mgrid[0:480, 0:720].astype(np.float64)
    d = np.stack([(xs - k[0, 2]) / k[0, 0], (ys - k[1, 2]) / k[1, 1], np.ones_like(xs)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    hit = np.zeros(xs.shape, bool)
    for c in centres_cam:
        tc = d @ c
        hit |= (tc > 0) & (c @ c - tc * tc <= radius * radius)
    return int(hit.sum())


def test_spheres_cover_about_the_benchmark_frames_pixels(bundled):
    """docs/benchmark.md: the two spheres cover 6,944 pixels of the benchmark frame; on the video's
    camera path (0.275 m from their midpoint, looking down) they cover within 15 % of that."""
    scene, _, meta = bundled
    k, _ = scene_intrinsics(scene)
    r = 0.0375
    bench = _covered_pixels(np.array([[-0.045, 0.0, 0.275], [0.045, 0.0, 0.275]]), r, k)
    assert abs(bench - 6944) < 0.01 * 6944  # this count against docs/benchmark.md's
    world = np.array([[-0.045, r, 0.0], [0.045, r, 0.0]])  # on markers 3 and 7 (table, +Y up)
    for f in meta["frames"][::6]:
        rc, tc = np.asarray(f["camera_R"]), np.asarray(f["camera_t"])
        n = _covered_pixels(world @ rc.T + tc, r, k)
        assert abs(n - bench) < 0.15 * bench, (f["frame"], n, bench)
