"""Atomic file output.

Outputs are written to a temporary file in the destination folder and moved into place with
``os.replace``, so a reader never sees a half-written file and an interrupted run leaves the
previous file intact.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

__all__ = ["atomic_path", "atomic_write_bytes", "atomic_write_text", "check_suffix"]


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str], *, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success move it onto ``path`` atomically.

    Use it for writers that insist on a file name (OpenEXR, matplotlib, PIL). The temporary file
    keeps ``path``'s extension (or ``suffix``) so that writers that dispatch on it still work.
    On any exception the temporary file is removed and ``path`` is left untouched.
    """
    dest = Path(path)
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{dest.name}.", suffix=suffix if suffix is not None else dest.suffix,
        dir=dest.parent,
    )
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        with open(tmp_path, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp_path, 0o644)
        os.replace(tmp_path, dest)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


def read_text(path: str | os.PathLike[str], *, encoding: str = "utf-8",
              max_bytes: int | None = None, what: str = "the file") -> str:
    """A user's text file, decoded; every failure is an :class:`~spectral_fit._runtime.errors.
    InputError` naming the file (unreadable, larger than ``max_bytes`` — ``what`` names the
    expected content in that message — or not valid ``encoding``)."""
    from .errors import InputError

    p = Path(path)
    try:
        if max_bytes is not None:
            size = p.stat().st_size
            if size > max_bytes:
                raise InputError(f"file is {size} bytes; {what} is expected to be small",
                                 path=p)
        raw = p.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read ({exc.strerror or exc})", path=p) from None
    try:
        return raw.decode(encoding)
    except UnicodeDecodeError:
        raise InputError("not UTF-8 text", path=p) from None


def check_suffix(path: str | os.PathLike[str] | None, suffixes: tuple[str, ...], field: str,
                 what: str) -> None:
    """Refuse an output ``path`` whose extension (any case) is not one of ``suffixes``
    (".png", ...): the writers do not all dispatch on the name, so a PNG would land in
    ``frame.jpg``. Checked before any work; ``what`` names the output ("--output writes
    PNG"). InputError naming the file and ``field``; None passes."""
    if path is None:
        return
    suffix = Path(path).suffix.lower()
    if suffix not in suffixes:
        from .errors import InputError

        raise InputError(f"{what}: the file name must end in {' or '.join(suffixes)}, got "
                         f"{suffix or 'no extension'!r}", path=path, field=field)
