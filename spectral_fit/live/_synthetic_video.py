"""Synthetic camera frames of a textured table with fiducial markers (test data, sample video).

A flat table (the plane world y = 0, +Y up) carries a texture: a photograph with
ArUco markers pasted on it at known places. A pinhole camera with OpenCV intrinsics ``K`` and
distortion (k1, k2, p1, p2[, k3]) looks at it from a known pose; every output pixel is traced:
its distorted pixel coordinate is undistorted (``cv2.undistortPoints``, exact every 4 pixels and
bilinear in between, ~1e-3 px), the ray is intersected with the plane, and the texture is
sampled bilinearly (``supersample``² rays per pixel are averaged). Optional Gaussian blur
(σ in pixels) and Gaussian noise (σ in 8-bit levels) follow. Because the geometry is exact,
the marker poses are known to float precision.

Frames: (H, W, 3) uint8 RGB, row 0 at the top. OpenCV pixel convention inside (pixel (0, 0)'s
centre at (0, 0)); our pixel-centre convention (+0.5) is applied where projections meet OpenGL
(:func:`spectral_fit.geometry.intrinsics_to_projection`).

Marker frame (OpenCV ArUco): origin at the square's centre, +X to the right of the printed
marker, +Y towards its top edge, +Z out of the paper. On the table the marker's top points to
world −Z and its +Z to world +Y, i.e. ``world_from_marker = translate(c) · A`` with
``A (x, y, z) = (x, z, −y)`` (:data:`MARKER_AXES`).

Requires the optional ``live`` extra (opencv-python-headless).
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = [
    "MARKER_AXES",
    "Table",
    "MarkerPlacement",
    "make_table",
    "render_table",
    "camera_pose_looking_at",
    "marker_pose_in_camera",
]

#: rotation taking the OpenCV marker frame to the table's Y-up frame: (x, y, z) -> (x, z, -y)
MARKER_AXES = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


@dataclasses.dataclass(frozen=True)
class MarkerPlacement:
    """A marker lying on the table: ``marker_id`` of ``dictionary``, its square's centre at
    world (x, 0, z) (metres) and side ``size`` (metres, black square only)."""

    marker_id: int
    x: float
    z: float
    size: float


@dataclasses.dataclass(frozen=True, eq=False)
class Table:
    """A textured table top: ``texture`` (h, w, 3) uint8 covering world x in
    [x0, x0 + w·pitch], z in [z0, z0 + h·pitch] (texture row grows with +z)."""

    texture: np.ndarray
    x0: float
    z0: float
    pitch: float
    markers: tuple[MarkerPlacement, ...]
    background: tuple[int, int, int] = (40, 40, 48)


def make_table(background: np.ndarray, markers: list[MarkerPlacement], *,
               dictionary: str = "DICT_5X5_100", extent: tuple[float, float] = (0.8, 0.6),
               pitch: float = 0.0005, border_bits: float = 1.0) -> Table:
    """Table of ``extent`` = (width along x, depth along z) metres centred on the origin, with
    ``background`` (any size, uint8 RGB) stretched over it and ``markers`` pasted on top (each
    with a white quiet zone of ``border_bits`` marker cells). ``pitch``: metres per texel."""
    import cv2

    w = round(extent[0] / pitch)
    h = round(extent[1] / pitch)
    tex = cv2.resize(np.ascontiguousarray(background[..., :3]), (w, h),
                     interpolation=cv2.INTER_CUBIC)
    x0, z0 = -extent[0] / 2, -extent[1] / 2
    dic = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    cells = dic.markerSize + 2
    for m in markers:
        side = round(m.size / pitch)
        img = cv2.aruco.generateImageMarker(dic, m.marker_id, cells * 64)
        img = cv2.resize(img, (side, side), interpolation=cv2.INTER_AREA)
        pad = round(border_bits * side / cells)
        img = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
        c0 = round((m.x - x0) / pitch - img.shape[1] / 2)
        r0 = round((m.z - z0) / pitch - img.shape[0] / 2)
        if c0 < 0 or r0 < 0 or c0 + img.shape[1] > w or r0 + img.shape[0] > h:
            raise ValueError(f"marker {m.marker_id} does not fit on the table")
        tex[r0:r0 + img.shape[0], c0:c0 + img.shape[1]] = img[..., None]
    return Table(texture=tex, x0=x0, z0=z0, pitch=pitch, markers=tuple(markers))


def camera_pose_looking_at(eye, target, up=(0.0, 1.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV pose (R (3, 3), t (3,)), x_cam = R x_world + t, of a camera at ``eye`` looking
    at ``target`` with ``up`` up in the image (through :func:`spectral_fit.geometry.look_at`)."""
    from ..geometry import look_at, view_to_opencv_pose

    r, t = view_to_opencv_pose(look_at(eye, target, up))
    return np.asarray(r, np.float64), np.asarray(t, np.float64)


def marker_pose_in_camera(table: Table, marker_id: int, r_cam: np.ndarray, t_cam: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
    """True OpenCV pose (R, t) of marker ``marker_id`` (camera from marker frame)."""
    (m,) = [m for m in table.markers if m.marker_id == marker_id]
    r = r_cam @ MARKER_AXES
    t = r_cam @ np.array([m.x, 0.0, m.z]) + t_cam
    return r, t


def _undistorted_grid(k: np.ndarray, dist: np.ndarray, h: int, w: int, s: int,
                      step: int = 4) -> np.ndarray:
    """Normalised undistorted coordinates (h·s, w·s, 2) of the supersampled pixel centres:
    exact (``cv2.undistortPoints``) on a grid every ``step`` output pixels, bilinear in
    between (the map is smooth: interpolation error ~1e-3 px for typical lenses)."""
    import cv2

    gj = np.arange(0, w + step, step, dtype=np.float64) - 0.5
    gi = np.arange(0, h + step, step, dtype=np.float64) - 0.5
    jj, ii = np.meshgrid(gj, gi)
    pts = np.stack([jj, ii], -1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 60, 1e-12)
    coarse = cv2.undistortPoints(pts, k, dist, criteria=crit).reshape(gi.size, gj.size, 2)
    fj = ((np.arange(w * s) + 0.5) / s - 0.5 - gj[0]) / step
    fi = ((np.arange(h * s) + 0.5) / s - 0.5 - gi[0]) / step
    mj, mi = np.meshgrid(fj.astype(np.float32), fi.astype(np.float32))
    return np.stack([cv2.remap(coarse[..., c].astype(np.float32), mj, mi, cv2.INTER_LINEAR)
                     for c in range(2)], -1).astype(np.float64)


def render_table(table: Table, k: np.ndarray, dist, r_cam: np.ndarray, t_cam: np.ndarray,
                 size: tuple[int, int], *, blur_px: float = 0.0, noise: float = 0.0,
                 supersample: int = 2, rng: np.random.Generator | None = None) -> np.ndarray:
    """Frame (H, W, 3) uint8 of ``table`` seen by a camera with intrinsics ``k`` (3×3),
    distortion ``dist`` (OpenCV order, or None) at pose x_cam = r_cam·x_world + t_cam.
    ``size`` = (H, W)."""
    import cv2

    h, w = size
    s = int(supersample)
    und = _undistorted_grid(np.asarray(k, np.float64),
                            np.zeros(5) if dist is None else np.asarray(dist, np.float64),
                            h, w, s).reshape(-1, 2)
    x, y = und[:, 0].astype(np.float32), und[:, 1].astype(np.float32)
    rw = np.asarray(r_cam, np.float64).T  # world-from-camera rotation
    centre = -rw @ np.asarray(t_cam, np.float64)
    ray = [np.float32(rw[c, 0]) * x + np.float32(rw[c, 1]) * y + np.float32(rw[c, 2])
           for c in range(3)]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.float32(-centre[1]) / ray[1]
    lam = np.where(np.isfinite(lam) & (lam > 0), lam, np.float32(np.nan))
    col = ((np.float32(centre[0] - table.x0) + lam * ray[0]) / np.float32(table.pitch)
           - np.float32(0.5))
    row = ((np.float32(centre[2] - table.z0) + lam * ray[2]) / np.float32(table.pitch)
           - np.float32(0.5))
    col = np.nan_to_num(col, nan=-1e6).reshape(h * s, w * s)
    row = np.nan_to_num(row, nan=-1e6).reshape(h * s, w * s)
    img = cv2.remap(table.texture, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                    borderValue=table.background)
    img = img.astype(np.float32)
    if s > 1:
        img = img.reshape(h, s, w, s, 3).mean(axis=(1, 3))
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    if noise > 0:
        rng = rng or np.random.default_rng(0)
        img = img + rng.normal(0.0, noise, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
