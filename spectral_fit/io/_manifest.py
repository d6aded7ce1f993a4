"""Reading a session manifest's TOML with positions: dotted keys (``readings[3].aim``) mapped
to 1-based manifest lines, and typed getters (tables, numbers, strings, 3-vectors in metres,
spectrum file lists, allowed keys) whose errors are
:class:`~spectral_fit._runtime.errors.InputError` naming the file, the line and the field.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from .._runtime.errors import InputError


def _toml_lines(text: str) -> dict[str, int]:
    """Map dotted keys (``readings[3].aim``, ``white_standard``) to 1-based manifest lines.

    A small line scanner (tomllib keeps no positions): table headers ``[a.b]`` and array
    headers ``[[a]]`` (counted), then ``key = ...`` lines inside them.
    """
    out: dict[str, int] = {}
    prefix = ""
    counts: dict[str, int] = {}
    for i, raw in enumerate(text.splitlines(), start=1):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        m = re.match(r"^\[\[\s*([^\]]+?)\s*\]\]", s)
        if m:
            name = m.group(1).replace('"', "")
            k = counts.get(name, 0)
            counts[name] = k + 1
            prefix = f"{name}[{k}]"
            out.setdefault(prefix, i)
            continue
        m = re.match(r"^\[\s*([^\]]+?)\s*\]", s)
        if m:
            prefix = m.group(1).replace('"', "")
            out.setdefault(prefix, i)
            continue
        m = re.match(r'^("?[A-Za-z0-9_.\-]+"?)\s*=', s)
        if m:
            key = m.group(1).replace('"', "")
            out.setdefault(f"{prefix}.{key}" if prefix else key, i)
    return out


def _line_of(lines: dict[str, int], field: str) -> int | None:
    f = field
    while f:
        if f in lines:
            return lines[f]
        cut = max(f.rfind("."), f.rfind("["))
        if cut <= 0:
            break
        f = f[:cut]
    return None


class _Ctx:
    """Error construction with file + line + field."""

    def __init__(self, path: Path, lines: dict[str, int]) -> None:
        self.path = path
        self.lines = lines

    def err(self, field: str, message: str) -> InputError:
        return InputError(message, path=self.path, field=field, line=_line_of(self.lines, field))

    # typed getters ---------------------------------------------------------------------------
    def table(self, parent: dict, key: str, field: str, *, required: bool = False) -> dict:
        v = parent.get(key, None)
        if v is None:
            if required:
                raise self.err(field, "missing table")
            return {}
        if not isinstance(v, dict):
            raise self.err(field, f"must be a table, got {type(v).__name__}")
        return v

    def number(self, t: dict, key: str, field: str, default: Any = None, *,
               lo: float | None = None, hi: float | None = None, lo_open: bool = False) -> Any:
        if key not in t:
            if default is None:
                raise self.err(field, "missing (required)")
            return default
        v = t[key]
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise self.err(field, f"must be a number, got {v!r}")
        v = float(v)
        if not math.isfinite(v):
            raise self.err(field, f"must be finite, got {v}")
        if lo is not None and (v < lo or (lo_open and v <= lo)):
            raise self.err(field, f"must be {'>' if lo_open else '>='} {lo:g}, got {v:g}")
        if hi is not None and v > hi:
            raise self.err(field, f"must be <= {hi:g}, got {v:g}")
        return v

    def string(self, t: dict, key: str, field: str, default: Any = None) -> Any:
        if key not in t:
            if default is None:
                raise self.err(field, "missing (required)")
            return default
        v = t[key]
        if not isinstance(v, str):
            raise self.err(field, f"must be a string, got {v!r}")
        return v

    def vector(self, t: dict, key: str, field: str, default: Any = None, *,
               unit: bool = False) -> np.ndarray:
        if key not in t:
            if default is None:
                raise self.err(field, "missing (required): a list of 3 numbers (metres)")
            return np.asarray(default, np.float64)
        v = t[key]
        if (not isinstance(v, list) or len(v) != 3
                or any(isinstance(x, bool) or not isinstance(x, int | float) for x in v)):
            raise self.err(field, f"must be a list of 3 numbers, got {v!r}")
        a = np.asarray(v, np.float64)
        if not np.all(np.isfinite(a)) or np.max(np.abs(a)) > 1e4:
            raise self.err(field, f"must be finite coordinates in metres, got {v!r}")
        if unit:
            nrm = float(np.linalg.norm(a))
            if nrm < 1e-9:
                raise self.err(field, "must be a non-zero direction")
            a = a / nrm
        return a

    def files(self, t: dict, key: str, field: str, base: Path, *,
              required: bool = True) -> list[Path]:
        v = t.get(key, None)
        if v is None:
            if required:
                raise self.err(field, "missing (required): a list of spectrum files")
            return []
        if isinstance(v, str):
            v = [v]
        if not isinstance(v, list) or not v or not all(isinstance(x, str) and x for x in v):
            raise self.err(field, f"must be a non-empty list of file names, got {v!r}")
        if len(v) > 1000:
            raise self.err(field, f"too many files ({len(v)})")
        out = []
        for j, name in enumerate(v):
            p = (base / name)
            if not p.is_file():
                raise self.err(f"{field}[{j}]", f"file not found: {p}")
            out.append(p)
        return out

    def finish(self, t: dict, allowed: tuple[str, ...], field: str) -> None:
        extra = sorted(set(t) - set(allowed))
        if extra:
            where = f"{field}.{extra[0]}" if field else extra[0]
            raise self.err(where, f"unknown key; expected one of {sorted(allowed)}")
