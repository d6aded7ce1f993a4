"""The ``spectral-fit`` subcommands, one module each."""

from __future__ import annotations


def check_suffix(name: str | None, suffix: str, option: str) -> None:
    """Refuse an output file ``name`` whose extension is not ``suffix`` (".png", ".exr"): the
    writers do not dispatch on the name, so a PNG would land in ``frame.jpg``. Checked before
    any work; InputError naming the file and the command-line ``option``."""
    from pathlib import Path

    from ..errors import InputError

    if name is not None and Path(name).suffix.lower() != suffix:
        raise InputError(f"{option} writes {suffix[1:].upper()}: the file name must end in "
                         f"{suffix}", path=name, field=option)
