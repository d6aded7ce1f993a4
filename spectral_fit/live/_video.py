"""Video in and out (OpenCV/FFmpeg): frames as (H, W, 3) uint8 RGB, row 0 at the top.

* :class:`VideoSource` reads a file or a camera index. A missing file, a file OpenCV cannot
  open, or one whose first frame cannot be decoded raises
  :class:`~spectral_fit._runtime.errors.InputError`
  naming the file (never a bare ``None`` frame later on).
* :class:`VideoSink` writes frames to a temporary file next to the destination and moves it into
  place when closed without error (atomic, :func:`spectral_fit._runtime.fileio.atomic_path`); an
  interrupted run leaves no half-written video. Codec by extension: ``.mp4``/``.m4v``/``.mov``
  → MPEG-4 part 2 (``mp4v``), ``.avi`` → Motion-JPEG (``MJPG``); ``.mkv`` → ``mp4v``.
* :func:`count_frames` decodes a file to the end and counts its frames (to check an output).

Requires the optional ``live`` extra (opencv-python-headless).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from .._runtime.errors import InputError

__all__ = ["VideoSource", "VideoSink", "count_frames", "read_frames"]

_FOURCC = {".mp4": "mp4v", ".m4v": "mp4v", ".mov": "mp4v", ".mkv": "mp4v", ".avi": "MJPG"}


def _cv2() -> Any:
    try:
        import cv2
    except ImportError:  # pragma: no cover - depends on the installation
        raise InputError("video input/output needs OpenCV: pip install 'spectral_fit[live]'",
                         field="video") from None
    return cv2


class VideoSource:
    """Frames from a video file (``source`` a path) or a camera (``source`` an int index).

    Attributes after opening: ``width``, ``height``, ``fps`` (0 when unknown) and
    ``frame_count`` (None for cameras or when the container does not say). The first frame is
    decoded at once, so an unreadable file fails here with a clear error.
    """

    def __init__(self, source: str | os.PathLike[str] | int, *, field: str = "--video") -> None:
        cv2 = _cv2()
        self.field = field
        self.is_camera = isinstance(source, int)
        self.path = None if self.is_camera else Path(source)  # type: ignore[arg-type]
        if self.path is not None:
            if not self.path.exists():
                raise InputError("video file not found", path=self.path, field=field)
            if not self.path.is_file():
                raise InputError("not a file", path=self.path, field=field)
            cap = cv2.VideoCapture(str(self.path), cv2.CAP_FFMPEG)
        else:
            cap = cv2.VideoCapture(int(source))  # type: ignore[arg-type]
        if not cap.isOpened():
            cap.release()
            what = f"camera {source}" if self.is_camera else "video"
            raise InputError(f"cannot open {what} (corrupt file, unsupported format or no "
                             "such device)", path=self.path, field=field)
        self._cap = cap
        ok, first = cap.read()
        if not ok or first is None or first.ndim != 3:
            cap.release()
            raise InputError("no decodable frame (corrupt or empty video)", path=self.path,
                             field=field)
        self._pending: np.ndarray | None = first
        self.height, self.width = first.shape[:2]
        self.fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        self.frame_count: int | None = n if (n > 0 and not self.is_camera) else None

    def read(self) -> np.ndarray | None:
        """Next frame (H, W, 3) uint8 RGB, or None at the end."""
        cv2 = _cv2()
        if self._pending is not None:
            bgr, self._pending = self._pending, None
        else:
            ok, bgr = self._cap.read()
            if not ok or bgr is None:
                return None
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def __iter__(self) -> Iterator[np.ndarray]:
        while (f := self.read()) is not None:
            yield f

    def close(self) -> None:
        self._cap.release()

    def __enter__(self) -> VideoSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class VideoSink:
    """Writes (H, W, 3) uint8 RGB frames to ``path`` atomically (see the module docstring).
    Use as a context manager; the file appears only when the block exits without error."""

    def __init__(self, path: str | os.PathLike[str], *, fps: float, size: tuple[int, int],
                 field: str = "--output") -> None:
        self.path = Path(path)
        self.field = field
        ext = self.path.suffix.lower()
        if ext not in _FOURCC:
            raise InputError(f"unsupported video extension {ext!r}; use one of "
                             f"{sorted(_FOURCC)}", path=self.path, field=field)
        if not (fps > 0 and np.isfinite(fps)):
            raise InputError(f"frame rate must be > 0, got {fps}", path=self.path, field=field)
        self.fps = float(fps)
        self.height, self.width = size
        self.frames = 0
        self._stack = contextlib.ExitStack()
        self._writer: Any = None

    def __enter__(self) -> VideoSink:
        cv2 = _cv2()
        tmp = self._stack.enter_context(_atomic(self.path))
        self._writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*_FOURCC[
            self.path.suffix.lower()]), self.fps, (self.width, self.height))
        if not self._writer.isOpened():
            self._stack.__exit__(RuntimeError, RuntimeError("writer"), None)
            raise InputError("cannot open a video writer for this file", path=self.path,
                             field=self.field)
        return self

    def write(self, frame: np.ndarray) -> None:
        """Append one (H, W, 3) uint8 RGB frame."""
        cv2 = _cv2()
        if frame.shape != (self.height, self.width, 3) or frame.dtype != np.uint8:
            raise InputError(f"frame must be ({self.height}, {self.width}, 3) uint8, got "
                             f"{frame.shape} {frame.dtype}", path=self.path, field=self.field)
        self._writer.write(cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2BGR))
        self.frames += 1

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        self._writer.release()
        self._stack.__exit__(exc_type, exc, tb)


@contextlib.contextmanager
def _atomic(path: Path) -> Iterator[Path]:
    from .._runtime.fileio import atomic_path

    with atomic_path(path) as tmp:
        yield tmp


def read_frames(path: str | os.PathLike[str], *, max_frames: int | None = None
                ) -> list[np.ndarray]:
    """All frames (or the first ``max_frames``) of a video file as (H, W, 3) uint8 RGB."""
    out = []
    with VideoSource(path, field="video") as src:
        for f in src:
            out.append(f)
            if max_frames is not None and len(out) >= max_frames:
                break
    return out


def count_frames(path: str | os.PathLike[str]) -> int:
    """Number of frames decoded from a video file (reads it to the end)."""
    n = 0
    with VideoSource(path, field="video") as src:
        while src.read() is not None:
            n += 1
    return n
