"""Exceptions raised for bad input.

Every error about user input names the file (when there is one) and the field, key, channel or
line at fault, so that a user can fix it without reading a traceback from inside JAX.
"""

from __future__ import annotations

import os

__all__ = ["SpectralFitError", "InputError"]


class SpectralFitError(Exception):
    """Base class of all errors raised on purpose by spectral_fit."""


class InputError(SpectralFitError, ValueError):
    """Malformed or inconsistent user input (a file, a config key, an array argument).

    The message reads ``"<path>: <field>: <message>"`` (``path``/``field`` omitted when unknown),
    with ``line N`` appended to the path for text files.
    """

    def __init__(
        self,
        message: str,
        *,
        path: str | os.PathLike[str] | None = None,
        field: str | None = None,
        line: int | None = None,
    ) -> None:
        self.path = None if path is None else os.fspath(path)
        self.field = field
        self.line = line
        self.reason = message
        where = []
        if self.path is not None:
            where.append(self.path if line is None else f"{self.path}, line {line}")
        elif line is not None:
            where.append(f"line {line}")
        if field is not None:
            where.append(str(field))
        super().__init__(": ".join([*where, message]))
