"""Make the bundled sample video for ``spectral-fit live``: two 80 mm ArUco markers on a table
(scikit-image's "coffee" photograph as the table top), seen by a moving hand-held camera with
lens distortion, motion blur, defocus blur and sensor noise.

    python scripts/make_sample_video.py [-o measurements/video/sample.mp4] [--frames 60]

Everything is exact ray tracing of a textured plane (spectral_fit.synthetic_video), so the true
camera and marker poses of every frame are known; they are written next to the video as
``<name>.poses.json`` (mid-shutter; OpenCV convention: x_cam = R x_world + t, metres;
world = table, +Y up).
The matching scene config is ``configs/live_sample.toml`` (same intrinsics, distortion and
markers). The last frames pan right so that marker 7 leaves the picture (its sphere must
disappear, not freeze).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

#: camera of the sample video (OpenCV intrinsics for 720×480, k1 k2 p1 p2 k3)
K = np.array([[560.0, 0.0, 362.0], [0.0, 556.0, 236.0], [0.0, 0.0, 1.0]])
DIST = np.array([-0.11, 0.045, 0.0008, -0.0004, 0.0])
SIZE = (480, 720)
MARKERS = [(3, -0.055, 0.0), (7, 0.055, 0.0)]  # id, x, z (m); 80 mm squares
MARKER_SIZE = 0.08


def camera_path(n: int, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
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


def main(argv: list[str] | None = None) -> int:
    import cv2
    from skimage import data

    from spectral_fit.synthetic_video import (
        MarkerPlacement,
        camera_pose_looking_at,
        make_table,
        marker_pose_in_camera,
        render_table,
    )
    from spectral_fit.video import VideoSink, count_frames

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", default=str(ROOT / "measurements/video/sample.mp4"))
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--fps", type=float, default=25.0)
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    table = make_table(data.coffee(), [MarkerPlacement(i, x, z, MARKER_SIZE)
                                       for i, x, z in MARKERS], extent=(0.9, 0.65))
    path = camera_path(args.frames + 1, rng)
    poses = []
    out = Path(args.output)
    with VideoSink(out, fps=args.fps, size=SIZE) as sink:
        for i in range(args.frames):
            # motion blur: average three instants across the shutter (half the frame interval)
            acc = np.zeros((*SIZE, 3), np.float64)
            for f in (0.0, 0.25, 0.5):
                eye = (1 - f) * path[i][0] + f * path[i + 1][0]
                look = (1 - f) * path[i][1] + f * path[i + 1][1]
                r, t = camera_pose_looking_at(eye, look)
                acc += render_table(table, K, DIST, r, t, SIZE, blur_px=0.0, noise=0.0,
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
                            for m, _, _ in MARKERS},
            })
    meta = {"intrinsics": K.tolist(), "distortion": DIST.tolist(), "size_hw": list(SIZE),
            "marker_size": MARKER_SIZE, "markers": MARKERS, "fps": args.fps,
            "note": "poses at the middle of each frame's shutter", "frames": poses}
    from spectral_fit.fileio import atomic_write_text

    atomic_write_text(out.with_suffix(".poses.json"), json.dumps(meta) + "\n")
    n = count_frames(out)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB, {n} frames)")
    return 0 if n == args.frames else 1


if __name__ == "__main__":
    raise SystemExit(main())
