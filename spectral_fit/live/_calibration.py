"""Camera calibration from images of a ChArUco board or a chessboard (OpenCV).

Result: OpenCV intrinsics K (fx, fy, cx, cy in pixels; pixel (0, 0)'s centre at (0, 0)) and
distortion (k1, k2, p1, p2, k3), written into a scene config's ``[camera]`` table as
``intrinsics = {fx, fy, cx, cy}`` and ``distortion = [k1, k2, p1, p2, k3]``
(:func:`write_calibrated_config`). The renderer works with the ideal pinhole K (via
:func:`spectral_fit.geometry.intrinsics_to_projection`, which adds our +0.5 pixel-centre offset);
the live pipeline UNDISTORTS each video frame onto that same K (:func:`undistort_maps`) and
composites there, so render and frame share one pinhole geometry. Marker poses are estimated on
the raw frame with the distortion model (no resampling before detection).

Targets (:class:`CalibrationTarget`):

* ``charuco``: ``squares`` = (columns, rows) of squares, ``square_size`` and ``marker_size`` in
  metres, an ArUco ``dictionary``; partial views work (each corner has an id).
* ``chessboard``: ``squares`` = (columns, rows) of squares (inner corners = squares − 1);
  the whole board must be visible.

Requires the optional ``live`` extra (opencv-python-headless).
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._runtime.errors import InputError

__all__ = [
    "CalibrationTarget",
    "Calibration",
    "detect_target",
    "calibrate_camera",
    "calibrate_images",
    "target_image",
    "undistort_maps",
    "write_calibrated_config",
]


def _cv2() -> Any:
    try:
        import cv2
    except ImportError:  # pragma: no cover - depends on the installation
        raise InputError("calibration needs OpenCV: pip install 'spectral_fit[live]'",
                         field="calibrate") from None
    return cv2


@dataclasses.dataclass(frozen=True)
class CalibrationTarget:
    """A planar calibration target (see the module docstring). Lengths in metres."""

    kind: str = "charuco"
    squares: tuple[int, int] = (7, 5)
    square_size: float = 0.03
    marker_size: float = 0.022
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self) -> None:
        if self.kind not in ("charuco", "chessboard"):
            raise InputError(f"unknown target {self.kind!r}; use 'charuco' or 'chessboard'",
                             field="--target")
        if len(self.squares) != 2 or min(self.squares) < 3:
            raise InputError(f"need at least 3×3 squares, got {self.squares}", field="--squares")
        if not self.square_size > 0:
            raise InputError("must be > 0", field="--square-size")
        if self.kind == "charuco" and not 0 < self.marker_size < self.square_size:
            raise InputError("must be > 0 and smaller than the square", field="--marker-size")

    def board(self) -> Any:
        """The OpenCV ``CharucoBoard`` (charuco targets only)."""
        cv2 = _cv2()
        from ._markers import aruco_dictionary

        return cv2.aruco.CharucoBoard(tuple(self.squares), self.square_size, self.marker_size,
                                      aruco_dictionary(self.dictionary))


def target_image(target: CalibrationTarget, pixels_per_square: int = 80) -> np.ndarray:
    """Printable (H, W) uint8 image of the target (no margin; add a white border to print)."""
    cv2 = _cv2()
    cols, rows = target.squares
    size = (cols * pixels_per_square, rows * pixels_per_square)
    if target.kind == "charuco":
        return target.board().generateImage(size, marginSize=0, borderBits=1)
    yy, xx = np.mgrid[0:size[1], 0:size[0]] // pixels_per_square
    img = np.where((xx + yy) % 2 == 0, 0, 255).astype(np.uint8)
    return cv2.resize(img, size, interpolation=cv2.INTER_NEAREST)


def detect_target(image: np.ndarray, target: CalibrationTarget
                  ) -> tuple[np.ndarray, np.ndarray] | None:
    """Target corners in one image: (object points (N, 3) m, image points (N, 2) px), or
    None when fewer than 6 corners are found."""
    cv2 = _cv2()
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if target.kind == "charuco":
        board = target.board()
        det = cv2.aruco.CharucoDetector(board)
        ch_corners, ch_ids, _, _ = det.detectBoard(grey)
        if ch_ids is None or len(ch_ids) < 6:
            return None
        obj = board.getChessboardCorners()[ch_ids.reshape(-1)]
        return obj.astype(np.float64), ch_corners.reshape(-1, 2).astype(np.float64)
    pattern = (target.squares[0] - 1, target.squares[1] - 1)
    ok, corners = cv2.findChessboardCornersSB(grey, pattern, flags=cv2.CALIB_CB_ACCURACY)
    if not ok:
        return None
    gx, gy = np.meshgrid(np.arange(pattern[0]), np.arange(pattern[1]))
    obj = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], -1) * target.square_size
    return obj.astype(np.float64), corners.reshape(-1, 2).astype(np.float64)


@dataclasses.dataclass(frozen=True, eq=False)
class Calibration:
    """Calibration result: ``k`` (3, 3) OpenCV intrinsics (px), ``dist`` (5,) k1, k2, p1, p2,
    k3, ``rms_px`` RMS reprojection error, ``image_size`` (H, W), ``views`` used and the
    indices of the images where the target was found (``used``)."""

    k: np.ndarray
    dist: np.ndarray
    rms_px: float
    image_size: tuple[int, int]
    views: int
    used: tuple[int, ...]

    def intrinsics(self) -> dict[str, float]:
        return {"fx": float(self.k[0, 0]), "fy": float(self.k[1, 1]),
                "cx": float(self.k[0, 2]), "cy": float(self.k[1, 2])}


def calibrate_camera(views: Sequence[tuple[np.ndarray, np.ndarray]], image_size: tuple[int, int],
                     *, fix_k3: bool = True, used: Sequence[int] | None = None) -> Calibration:
    """Calibrate from per-view (object points (N, 3), image points (N, 2)) correspondences
    (``cv2.calibrateCamera``, zero skew; k3 fixed at 0 unless ``fix_k3`` is False)."""
    cv2 = _cv2()
    if len(views) < 3:
        raise InputError(f"need the target in at least 3 images, found it in {len(views)}",
                         field="images")
    obj = [np.asarray(o, np.float32).reshape(-1, 3) for o, _ in views]
    img = [np.asarray(i, np.float32).reshape(-1, 1, 2) for _, i in views]
    h, w = image_size
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, k, dist, _, _ = cv2.calibrateCamera(obj, img, (w, h), None, None, flags=flags,
                                             criteria=crit)
    d = np.zeros(5)
    d[: min(5, dist.size)] = dist.reshape(-1)[:5]
    return Calibration(np.asarray(k, np.float64), d, float(rms), (h, w), len(views),
                       tuple(used if used is not None else range(len(views))))


def calibrate_images(images: Sequence[np.ndarray], target: CalibrationTarget, *,
                     fix_k3: bool = True) -> Calibration:
    """Detect ``target`` in each image (same size, RGB or grey uint8) and calibrate."""
    if not images:
        raise InputError("no images", field="images")
    size = images[0].shape[:2]
    views, used = [], []
    for i, im in enumerate(images):
        if im.shape[:2] != size:
            raise InputError(f"image {i} is {im.shape[:2]}, the first is {size}",
                             field="images")
        found = detect_target(im, target)
        if found is not None:
            views.append(found)
            used.append(i)
    return calibrate_camera(views, size, fix_k3=fix_k3, used=used)


def undistort_maps(k, dist, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps (fixed point) that undistort an (H, W) frame onto the SAME pinhole
    intrinsics ``k`` (no rescaling), the live pipeline's one geometric convention."""
    cv2 = _cv2()
    h, w = size
    k = np.asarray(k, np.float64)
    return cv2.initUndistortRectifyMap(k, np.asarray(dist, np.float64), None, k, (w, h),
                                       cv2.CV_16SC2)


_TABLE = re.compile(r"^\s*\[\[?\s*([A-Za-z0-9_.\"' -]+?)\s*\]\]?\s*(#.*)?$")


def _camera_lines(cal: Calibration) -> list[str]:
    i = cal.intrinsics()
    d = ", ".join(f"{x:.9g}" for x in cal.dist)
    return [
        f"# calibrated: {cal.views} views, RMS reprojection {cal.rms_px:.3f} px, "
        f"image {cal.image_size[1]}x{cal.image_size[0]}",
        f"intrinsics = {{ fx = {i['fx']:.6f}, fy = {i['fy']:.6f}, cx = {i['cx']:.6f}, "
        f"cy = {i['cy']:.6f} }}",
        f"distortion = [{d}]",
    ]


def calibrated_config_text(text: str, cal: Calibration) -> str:
    """The config ``text`` with ``[camera]`` ``intrinsics``/``distortion`` set from ``cal``
    (existing one-line keys replaced, other lines and comments kept; a ``[camera]`` table is
    added when missing). ``[frame]`` width/height must match the calibrated image size."""
    lines = text.splitlines()
    out: list[str] = []
    table = None
    inserted = False
    key = re.compile(r"^\s*(intrinsics|distortion)\s*=")
    for line in lines:
        m = _TABLE.match(line)
        if m:
            table = m.group(1).strip()
            out.append(line)
            if table == "camera" and not line.lstrip().startswith("[["):
                out.extend(_camera_lines(cal))
                inserted = True
            continue
        if table == "camera" and key.match(line):
            if line.count("[") != line.count("]") or line.count("{") != line.count("}"):
                raise InputError("multi-line intrinsics/distortion values are not supported; "
                                 "put them on one line", field="camera")
            continue
        if table == "camera" and line.strip().startswith("# calibrated:"):
            continue
        out.append(line)
    if not inserted:
        out.extend(["", "[camera]", *_camera_lines(cal)])
    return "\n".join(out) + "\n"


def write_calibrated_config(config: str | os.PathLike[str], cal: Calibration,
                            output: str | os.PathLike[str] | None = None, *,
                            overwrite: bool = False) -> Path:
    """Write ``config`` with the calibration into ``output`` (default: ``<name>.calibrated.toml``
    next to it) atomically. Refuses to replace an existing file unless ``overwrite``; the
    result is validated with :func:`spectral_fit.io.parse_scene` before it is written, and
    its ``[frame]`` size must equal the calibrated image size."""
    import tomllib

    from .._runtime.fileio import atomic_write_text
    from ..io import parse_scene

    src = Path(config)
    try:
        text = src.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"cannot read ({exc.strerror or exc})", path=src) from None
    dest = Path(output) if output is not None else src.with_name(src.stem + ".calibrated.toml")
    if dest.exists() and not overwrite:
        raise InputError("exists; pass --overwrite to replace it", path=dest, field="--output")
    new = calibrated_config_text(text, cal)
    try:
        data = tomllib.loads(new)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"could not insert the calibration: {exc}", path=src) from None
    scene = parse_scene(data, path=src)  # relative paths resolve against the source's folder
    if (scene.height, scene.width) != tuple(cal.image_size):
        raise InputError(f"[frame] is {scene.width}x{scene.height} but the images are "
                         f"{cal.image_size[1]}x{cal.image_size[0]}", path=src, field="frame")
    if dest.resolve().parent != src.resolve().parent:
        raise InputError("write the calibrated config next to the original (relative paths "
                         "in it stay valid)", path=dest, field="--output")
    atomic_write_text(dest, new)
    return dest
