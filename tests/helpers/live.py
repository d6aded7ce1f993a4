"""Shared fixtures of the live tests: a synthetic table with two markers and a known camera."""

from __future__ import annotations

import functools

import numpy as np

from helpers import ANCHOR_ENV

#: intrinsics (OpenCV) and distortion (k1, k2, p1, p2, k3) of the synthetic camera, 720×480
K = np.array([[520.0, 0.0, 355.0], [0.0, 515.0, 243.0], [0.0, 0.0, 1.0]])
DIST = np.array([-0.12, 0.05, 0.001, -0.0005, 0.0])
SIZE = (480, 720)
MARKER_SIZE = 0.08


@functools.lru_cache(maxsize=1)
def table():
    from skimage import data

    from spectral_fit.live import MarkerPlacement, make_table

    return make_table(data.coffee(), [MarkerPlacement(3, -0.06, 0.0, MARKER_SIZE),
                                      MarkerPlacement(7, 0.07, 0.02, MARKER_SIZE)])


def frame(eye, target=(0.0, 0.0, 0.0), *, blur_px=0.8, noise=2.0, seed=0, dist=DIST, k=K):
    """(image, R, t) of the table seen from ``eye`` (world, m)."""
    from spectral_fit.live import camera_pose_looking_at, render_table

    r, t = camera_pose_looking_at(eye, target)
    img = render_table(table(), k, dist, r, t, SIZE, blur_px=blur_px, noise=noise,
                       rng=np.random.default_rng(seed))
    return img, r, t


def rotation_angle_deg(ra, rb) -> float:
    c = (np.trace(np.asarray(ra).T @ np.asarray(rb)) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def scene_dict(*, markers=None, objects=None, width=720, height=480, intrinsics=True):
    """A small scene config (dict) with the synthetic camera and two marker-attached spheres."""
    cam = {}
    if intrinsics:
        cam["intrinsics"] = {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]),
                             "cy": float(K[1, 2])}
        cam["distortion"] = [float(x) for x in DIST]
    d = {
        "frame": {"width": width, "height": height},
        "camera": cam,
        "environment": {"file": str(ANCHOR_ENV), "rotation_y_deg": 180.0},
        "spectral": {"start_nm": 400.0, "end_nm": 700.0, "step_nm": 10.0},
        "objects": objects if objects is not None else [
            {"name": "yellow", "radius": 0.03, "stacks": 24, "slices": 24, "marker": 3,
             "marker_offset": [0.0, 0.03, 0.0],
             "material": {"reflectance": "colourchecker:ColorChecker N Ohta/yellow"}},
            {"name": "red", "radius": 0.03, "stacks": 24, "slices": 24, "marker": 7,
             "marker_offset": [0.0, 0.03, 0.0],
             "material": {"reflectance": "colourchecker:ColorChecker N Ohta/red"}},
        ],
    }
    if markers is not False:
        d["markers"] = markers or {"dictionary": "DICT_5X5_100", "size": MARKER_SIZE}
    return d


#: the live pipeline tests' frames: 1/3 of the 720×480 test camera (240×160), and its intrinsics
S = 3
SMALL_SIZE = (160, 240)
KS = np.array([[K[0, 0] / S, 0, (K[0, 2] + 0.5) / S - 0.5],
               [0, K[1, 1] / S, (K[1, 2] + 0.5) / S - 0.5], [0, 0, 1.0]])


def small_scene(tmp_path=None, **markers):
    """The live scene of :func:`scene_dict` at :data:`SMALL_SIZE` (intrinsics :data:`KS`, 32-stack
    spheres, no interreflection); ``markers``: overrides of the markers table."""
    from spectral_fit.io import parse_scene

    d = scene_dict(markers={"size": 0.08, **markers}, width=SMALL_SIZE[1], height=SMALL_SIZE[0])
    d["camera"]["intrinsics"] = {"fx": KS[0, 0], "fy": KS[1, 1], "cx": KS[0, 2],
                                 "cy": KS[1, 2]}
    for o in d["objects"]:
        o["stacks"] = o["slices"] = 32
    d["interreflection"] = {"mode": "none"}
    return parse_scene(d, path=None if tmp_path is None else tmp_path / "live.toml")


def small_frame(table, eye, seed=0):
    """(image, R, t) of ``table`` seen from ``eye`` at :data:`SMALL_SIZE` (camera :data:`KS`)."""
    from spectral_fit.live import camera_pose_looking_at, render_table

    r, t = camera_pose_looking_at(eye, (0.0, 0.0, 0.0))
    img = render_table(table, KS, DIST, r, t, SMALL_SIZE, blur_px=0.5, noise=1.5,
                       rng=np.random.default_rng(seed))
    return img, r, t
