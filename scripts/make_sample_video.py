"""Make the bundled videos for ``spectral-fit live``: ArUco markers on a table (scikit-image's
"coffee" photograph as the table top), seen by a moving hand-held camera with motion blur,
defocus blur and sensor noise.

    python scripts/make_sample_video.py [--scene sample|benchmark] [-o OUT.mp4] [--frames N]

Scenes:

* ``sample`` (default; ``measurements/video/sample.mp4``, config ``configs/live_sample.toml``):
  two 80 mm markers 110 mm apart, a camera with lens distortion (fx = 560 px) on an arc
  0.29–0.34 m from them; the last frames pan right so that marker 7 leaves the picture (its
  sphere must disappear, not freeze).
* ``benchmark`` (``measurements/video/benchmark.mp4``, config ``configs/live_benchmark.toml``): the
  benchmark scene (docs/benchmark.md) as a live scene: its camera (720×480, 90° vertical field of
  view, no distortion) 0.275 m from the spheres' midpoint (the spheres 90 mm apart, on 60 mm
  markers), looking down at 40–50° while it moves ±20° around them; both markers stay in view, so
  every frame renders both spheres and their interreflection.

Everything is exact ray tracing of a textured plane (spectral_fit.live), so the true
camera and marker poses of every frame are known; they are written next to the video as
``<name>.poses.json`` (mid-shutter; OpenCV convention: x_cam = R x_world + t, metres;
world = table, +Y up).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SIZE = (480, 720)


@dataclasses.dataclass(frozen=True)
class VideoScene:
    """What one bundled video shows: intrinsics K (OpenCV, 720×480), distortion (k1 k2 p1 p2
    k3), markers (id, x, z in metres), their side (m), the table's extent (m) and the camera
    path ``path(n, rng)`` -> n (eye, look-at) pairs (world, m)."""

    k: np.ndarray
    dist: np.ndarray
    markers: list[tuple[int, float, float]]
    marker_size: float
    extent: tuple[float, float]
    path: Callable[[int, np.random.Generator], list[tuple[np.ndarray, np.ndarray]]]
    output: str


def sample_path(n: int, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """Eye and look-at points (world, m) of an arc around the markers with hand shake; the
    last fifth pans right until marker 7 leaves the frame."""
    out = []
    pan_start = int(0.8 * n)
    for i in range(n):
        s = i / max(n - 1, 1)
        az = math.radians(-30 + 60 * min(s / 0.8, 1.0))
        dist = 0.34 - 0.05 * math.sin(math.pi * s)
        height = 0.24 + 0.03 * math.sin(2 * math.pi * s)
        eye = np.array([dist * math.sin(az), height, dist * math.cos(az)])
        eye += rng.normal(0, 0.0015, 3)
        look = np.array([0.0, 0.0, -0.01]) + rng.normal(0, 0.001, 3)
        if i >= pan_start:
            u = (i - pan_start) / max(n - 1 - pan_start, 1)
            look[0] -= 0.3 * u * u * (3 - 2 * u)  # smoothstep pan
        out.append((eye, look))
    return out


def benchmark_path(n: int, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """Eye and look-at points (world, m): 0.275 m from the spheres' midpoint (0, 0.0375, 0),
    azimuth −20° → +20°, elevation 45° ± 5°, with hand shake."""
    centre = np.array([0.0, 0.0375, 0.0])
    out = []
    for i in range(n):
        s = i / max(n - 1, 1)
        az = math.radians(-20 + 40 * s)
        el = math.radians(45 + 5 * math.sin(2 * math.pi * s))
        d = 0.275
        eye = centre + d * np.array([math.cos(el) * math.sin(az), math.sin(el),
                                     math.cos(el) * math.cos(az)])
        out.append((eye + rng.normal(0, 0.001, 3), centre + rng.normal(0, 0.0007, 3)))
    return out


SCENES = {
    "sample": VideoScene(
        k=np.array([[560.0, 0.0, 362.0], [0.0, 556.0, 236.0], [0.0, 0.0, 1.0]]),
        dist=np.array([-0.11, 0.045, 0.0008, -0.0004, 0.0]),
        markers=[(3, -0.055, 0.0), (7, 0.055, 0.0)], marker_size=0.08, extent=(0.9, 0.65),
        path=sample_path, output="measurements/video/sample.mp4"),
    # 90° vertical field of view at 720×480: f = 240 px, centred (scene_intrinsics' pinhole)
    "benchmark": VideoScene(
        k=np.array([[240.0, 0.0, 359.5], [0.0, 240.0, 239.5], [0.0, 0.0, 1.0]]),
        dist=np.zeros(5),
        markers=[(3, -0.045, 0.0), (7, 0.045, 0.0)], marker_size=0.06, extent=(1.6, 1.2),
        path=benchmark_path, output="measurements/video/benchmark.mp4"),
}


def main(argv: list[str] | None = None) -> int:
    import cv2
    from skimage import data

    from spectral_fit.live import (
        MarkerPlacement,
        VideoSink,
        camera_pose_looking_at,
        count_frames,
        make_table,
        marker_pose_in_camera,
        render_table,
    )

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", choices=sorted(SCENES), default="sample")
    ap.add_argument("-o", "--output", default=None,
                    help="output video (default: the scene's file under measurements/video/)")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--fps", type=float, default=25.0)
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args(argv)

    sc = SCENES[args.scene]
    rng = np.random.default_rng(args.seed)
    table = make_table(data.coffee(), [MarkerPlacement(i, x, z, sc.marker_size)
                                       for i, x, z in sc.markers], extent=sc.extent)
    path = sc.path(args.frames + 1, rng)
    poses = []
    out = Path(args.output or ROOT / sc.output)
    with VideoSink(out, fps=args.fps, size=SIZE) as sink:
        for i in range(args.frames):
            # motion blur: average three instants across the shutter (half the frame interval)
            acc = np.zeros((*SIZE, 3), np.float64)
            for f in (0.0, 0.25, 0.5):
                eye = (1 - f) * path[i][0] + f * path[i + 1][0]
                look = (1 - f) * path[i][1] + f * path[i + 1][1]
                r, t = camera_pose_looking_at(eye, look)
                acc += render_table(table, sc.k, sc.dist, r, t, SIZE, blur_px=0.0, noise=0.0,
                                    supersample=2)
            img = cv2.GaussianBlur((acc / 3).astype(np.float32), (0, 0), 0.6)
            img = img + rng.normal(0, 1.5, img.shape)
            sink.write(np.clip(np.rint(img), 0, 255).astype(np.uint8))
            r, t = camera_pose_looking_at(0.75 * path[i][0] + 0.25 * path[i + 1][0],
                                          0.75 * path[i][1] + 0.25 * path[i + 1][1])
            poses.append({
                "frame": i,
                "camera_R": r.tolist(), "camera_t": t.tolist(),
                "markers": {str(m): dict(zip(("R", "t"), (a.tolist() for a in
                                                          marker_pose_in_camera(table, m, r, t)),
                                             strict=True))
                            for m, _, _ in sc.markers},
            })
    meta = {"scene": args.scene, "intrinsics": sc.k.tolist(), "distortion": sc.dist.tolist(),
            "size_hw": list(SIZE), "marker_size": sc.marker_size, "markers": sc.markers,
            "fps": args.fps,
            "note": "poses at the middle of each frame's shutter", "frames": poses}
    from spectral_fit._runtime.fileio import atomic_write_text

    atomic_write_text(out.with_suffix(".poses.json"), json.dumps(meta) + "\n")
    n = count_frames(out)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB, {n} frames)")
    return 0 if n == args.frames else 1


if __name__ == "__main__":
    raise SystemExit(main())
