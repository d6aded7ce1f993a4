"""The end-to-end mixed-reality ground truth (scripts/make_mr_ground_truth.py,
measurements/video/room*): the camera's colour from the chart in the video ([colour_chart]),
markers found in linear light ([markers] tone), and the live pipeline scored against the
path-traced frames (spectral_fit.live.score_mr)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cv2")

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "configs" / "live_room.toml"
TRUTH = REPO / "measurements" / "video" / "room_truth"


def _scene():
    from spectral_fit.io import load_scene

    return load_scene(CONFIG)


def _look(eye, target):
    from spectral_fit.live import camera_pose_looking_at

    return camera_pose_looking_at(np.asarray(eye, float), np.asarray(target, float))


def _chart_frame(scene, m: np.ndarray, gamma: float, eye, target):
    """A frame of the table with marker 3 and the config's chart painted in the colours a
    camera with linear map ``m`` (XYZ → linear RGB) and a gamma curve gives the patches'
    XYZ (chart_xyz), seen from ``eye``; returns (frame, K)."""
    from spectral_fit.live import (
        MarkerPlacement,
        chart_corners_world,
        chart_xyz,
        make_table,
        render_table,
        scene_intrinsics,
    )

    spec = scene.colour_chart
    xyz, _ = chart_xyz(scene, chart=spec.chart)
    lin = np.clip(xyz @ m.T, 0, 1)
    enc = np.rint(255 * lin ** (1 / gamma)).astype(np.uint8)   # (24, 3)
    pitch, extent = 0.0005, (0.5, 0.5)
    nx, nz = round(extent[0] / pitch), round(extent[1] / pitch)
    bg = np.full((nz, nx, 3), 150, np.uint8)
    c = chart_corners_world(spec)   # TL TR BR BL
    x0, z0 = -extent[0] / 2, -extent[1] / 2
    xs = x0 + (np.arange(nx) + 0.5) * pitch
    zs = z0 + (np.arange(nz) + 0.5) * pitch
    # this chart is axis-aligned (rotation 0): columns along +x, rows along +z
    u = (xs - c[0, 0]) / (c[1, 0] - c[0, 0]) * 6
    v = (zs - c[0, 2]) / (c[3, 2] - c[0, 2]) * 4
    for r in range(4):
        for k in range(6):
            cols = (u >= k + 0.06) & (u < k + 0.94)
            rows = (v >= r + 0.06) & (v < r + 0.94)
            bg[np.ix_(rows, cols)] = enc[r * 6 + k]
    table = make_table(bg, [MarkerPlacement(3, 0.0, 0.0, scene.markers.size)], extent=extent,
                       pitch=pitch)
    k, dist = scene_intrinsics(scene)
    r, t = _look(eye, target)
    frame = render_table(table, k, dist, r, t, (scene.height, scene.width), supersample=3)
    return frame, k


def test_chart_in_frame_recovers_camera():
    """[colour_chart]: a synthetic frame whose chart was painted through a known camera
    (3×3 from XYZ, gamma 2.2) gives that camera back, found through marker 3 alone."""
    from spectral_fit.live import chart_camera_model

    scene = _scene()
    spec = scene.colour_chart
    xyz_white = np.asarray(__import__("spectral_fit.live", fromlist=["chart_xyz"])
                           .chart_xyz(scene)[1])
    # a camera: sRGB-like primaries, white (the room's white reference) at linear 0.8
    m0 = np.array([[3.1, -1.5, -0.5], [-0.95, 1.9, 0.05], [0.05, -0.2, 1.05]])
    m = m0 * (0.8 / (m0 @ xyz_white))[:, None]
    frame, k = _chart_frame(scene, m, 2.2, eye=(0.06, 0.33, 0.30), target=(0.06, 0.0, 0.08))
    res = chart_camera_model(scene, [frame, frame], k=k, dist=None)
    assert res.frames == (0, 1)
    fitted = np.asarray(res.model.xyz_matrix, np.float64)
    rel = np.abs(fitted - m).max() / np.abs(m).max()
    assert rel < 0.02, (fitted, m)
    # the white reference comes out at the camera's level, neutral, within 1.5 %
    w = fitted @ xyz_white
    assert np.allclose(w, 0.8, rtol=0.015), w
    # the chart's corners are where the true marker pose puts them
    from spectral_fit.live import chart_corners_in_frame

    r, t = _look((0.06, 0.33, 0.30), (0.06, 0.0, 0.08))
    from spectral_fit.live import MARKER_AXES

    true = chart_corners_in_frame(spec, r @ MARKER_AXES, t, k, None, frame.shape[:2])
    # (within 2 px: 140 mm from a 50-px marker, its pose's small rotation error is amplified)
    assert np.abs(res.corners[0] - true).max() < 2.0


def test_chart_not_seen_names_the_config():
    from spectral_fit import InputError
    from spectral_fit.live import chart_camera_model

    scene = _scene()
    blank = np.full((scene.height, scene.width, 3), 128, np.uint8)
    with pytest.raises(InputError) as e:
        chart_camera_model(scene, [blank] * 3, source="clip.mp4")
    assert "colour_chart" in str(e.value) and "live_room.toml" in str(e.value)
    assert "clip.mp4" in str(e.value)


@pytest.mark.parametrize("bad, field", [
    ({"colour_chart": {"marker": 3, "size": [0.1, -0.1]}}, "colour_chart.size"),
    ({"colour_chart": {"marker": 3, "chart": "no such chart"}}, "colour_chart.chart"),
    ({"colour_chart": {"marker": 300}}, "colour_chart.marker"),
    ({"colour_chart": {"marker": 3, "tone": "log"}}, "colour_chart.tone"),
    ({"colour_chart": {"marker": 3, "frame": 2}}, "colour_chart.frame"),
    ({"markers": {"tone": "log"}}, "markers.tone"),
])
def test_colour_chart_config_errors(bad, field):
    import tomllib

    from spectral_fit import InputError
    from spectral_fit.io import parse_scene

    data = tomllib.loads(CONFIG.read_text())
    for table, values in bad.items():
        data[table] = {**data[table], **values} if table == "markers" else values
    with pytest.raises(InputError) as e:
        parse_scene(data, path=CONFIG)
    assert field in str(e.value) and "live_room.toml" in str(e.value)


def test_chart_needs_markers():
    import tomllib

    from spectral_fit import InputError
    from spectral_fit.io import parse_scene

    data = tomllib.loads(CONFIG.read_text())
    del data["markers"]
    for o in data["objects"]:
        o.pop("marker")
        o.pop("marker_offset")
    with pytest.raises(InputError, match="colour_chart"):
        parse_scene(data, path=CONFIG)


def test_edges_in_linear_light_remove_the_tone_curve_bias():
    """A camera integrates light linearly over a pixel, then applies its tone curve: the
    encoded half level lies on the dark side of an edge, the black square shrinks and the
    marker looks farther away. [markers] tone = "gamma" finds the crossings in linear light.
    True poses: the exact ray-traced table."""
    from spectral_fit.live import (
        MarkerDetector,
        MarkerPlacement,
        make_table,
        marker_pose_in_camera,
        render_table,
        scene_intrinsics,
    )

    scene = _scene()
    k, _ = scene_intrinsics(scene)
    table = make_table(np.full((8, 8, 3), 200, np.uint8),
                       [MarkerPlacement(3, 0.0, 0.0, 0.08)], extent=(0.4, 0.4))
    errs = {"none": [], "gamma": []}
    for eye in ((0.05, 0.35, 0.25), (-0.1, 0.3, 0.3), (0.12, 0.4, 0.2)):
        r, t = _look(eye, (0.0, 0.0, 0.0))
        lin = render_table(table, k, None, r, t, (scene.height, scene.width),
                           supersample=4).astype(np.float64)   # linear light, area-averaged
        frame = np.rint(255 * (lin / 255) ** (1 / 2.2)).astype(np.uint8)
        _, t_true = marker_pose_in_camera(table, 3, r, t)
        for tone in errs:
            spec = dataclasses.replace(scene.markers, tone=tone, gamma=2.2)
            d = MarkerDetector(spec, k, None, expect={3}).detect(frame)[3]
            errs[tone].append(1e3 * np.linalg.norm(d.translation.reshape(3) - t_true))
    assert max(errs["gamma"]) < 0.6, errs
    assert np.mean(errs["none"]) > 2.0 * np.mean(errs["gamma"]), errs


def test_pose_errors_closed_form():
    from spectral_fit.live import pose_errors

    a = math.radians(0.7)
    r = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    dt, dr = pose_errors(r, [0.001, 0.0, 0.3], np.eye(3), [0.0, 0.0, 0.3])
    assert dt == pytest.approx(1.0, abs=1e-9)
    assert dr == pytest.approx(0.7, abs=1e-6)


def _check(res, limits):
    s = res["summary"]
    got = {"objects": s["objects"]["median_of_medians"], "near": s["near"]["median_of_medians"],
           "near_p90": s["near"]["p90_of_medians"],
           "objects_5x5": s["objects_5x5"]["median_of_medians"],
           "near_5x5": s["near_5x5"]["median_of_medians"],
           "near_5x5_p90": s["near_5x5"]["p90_of_medians"],
           "translation_mm": s["markers"]["translation_mm"]["max"],
           "rotation_deg": s["markers"]["rotation_deg"]["max"]}
    for key, lim in limits.items():
        assert got[key] <= lim, (key, got)
    assert s["markers"]["missed"] == 0
    # the bias (measured, full clip: objects 0.961 0.945 0.837, table near 0.967 0.968 0.954
    # of the truth's mean linear RGB), against the direct mean over the masks of one frame
    for region, lo in (("objects", 0.78), ("near", 0.92)):
        lr = np.asarray(s[region]["linear_ratio_median"])
        assert np.all((lr > lo) & (lr < 1.05)), (region, lr)
    return got


# The targets (spectral_fit.live.MR_TARGETS: ΔE00 1.0 on objects and near table, p90
# over frames 2.0; 1 mm / 0.5°) are NOT met on this clip; these limits hold the measured
# figures (full clip: per pixel objects 2.81, near 6.58 (p90 over frames 7.38); 5×5 patches
# objects 2.10, near 3.20 (p90 3.36); against the truth through the video's codec objects
# 2.20 / 1.59, near 4.06 / 2.04; poses max 2.46 mm / 0.85°, docs/live.md "End-to-end ground
# truth", with what limits them) with a margin, so that a regression shows.
SHORT_LIMITS = {"objects": 3.3, "near": 8.5, "near_p90": 9.0, "objects_5x5": 2.6,
                "near_5x5": 3.8, "near_5x5_p90": 4.0, "translation_mm": 2.5,
                "rotation_deg": 0.6}
FULL_LIMITS = {"objects": 3.3, "near": 7.5, "near_p90": 8.0, "objects_5x5": 2.6,
               "near_5x5": 3.7, "near_5x5_p90": 3.8, "translation_mm": 3.0,
               "rotation_deg": 1.0}


@pytest.mark.skipif(not (TRUTH / "truth.json").exists(), reason="no ground truth")
def test_mr_score_short_clip(tmp_path):
    """The live pipeline on the first frames of the path-traced video (colour calibrated from
    the chart in the video itself) against the noise-free path-traced frames."""
    from spectral_fit.live import score_mr

    res = score_mr(TRUTH, max_frames=3, out=tmp_path)
    assert res["frames_scored"] == 3
    assert res["colour"]["frames"][0] == 0
    _check(res, SHORT_LIMITS)
    # away from the objects the composite is the video's own pixels: their level is the
    # truth's once the truth goes through the same encoder (OpenCV's MPEG-4 round trip lowers
    # it by ~3 %, the codec's share, which codec_matched leaves out)
    import colour
    import cv2

    from spectral_fit.live import VideoSink, VideoSource

    masks = np.load(TRUTH / "masks.npz")
    truth = [cv2.imread(str(TRUTH / f"frame_{i:03d}.png"))[..., ::-1] for i in range(3)]
    with VideoSink(tmp_path / "t.mp4", fps=12, size=truth[0].shape[:2]) as sink:
        for f in truth:
            sink.write(np.ascontiguousarray(f))
    with VideoSource(tmp_path / "t.mp4") as src:
        coded = next(iter(src))
    with VideoSource(REPO / "measurements" / "video" / "room.mp4") as src:
        first = next(iter(src))
    far = (masks["object_id"][0] == -1) & ~masks["near"][0]

    def level(x):
        return colour.cctf_decoding(x[far] / 255.0, function="sRGB").mean(0)

    np.testing.assert_allclose(level(first) / level(coded), 1.0, atol=0.015)  # 1.001-1.010
    assert np.all(level(coded) / level(truth[0]) < 0.99)
    cm = res["summary"]["codec_matched"]
    assert cm["objects"]["median_of_medians"] < res["summary"]["objects"]["median_of_medians"]
    saved = json.loads((tmp_path / "mr_score.json").read_text())
    assert saved["summary"] == json.loads(json.dumps(res["summary"]))
    assert (tmp_path / "mr_score.png").stat().st_size > 10_000


@pytest.mark.slow
@pytest.mark.skipif(not (TRUTH / "truth.json").exists(), reason="no ground truth")
def test_mr_score_full_clip(tmp_path):
    from spectral_fit.live import score_mr

    res = score_mr(TRUTH, out=tmp_path)
    assert res["frames_scored"] == json.loads((TRUTH / "truth.json").read_text())["frames"]
    _check(res, FULL_LIMITS)
