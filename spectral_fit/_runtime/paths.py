"""Where the package and the repository's bundled data are on disk.

The bundled configs (``configs/``), measurements (``measurements/``) and references sit next to
the package in the repository; commands and benchmarks find them from here.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["PACKAGE_DIR", "REPO_ROOT"]

#: the ``spectral_fit`` package folder
PACKAGE_DIR = Path(__file__).resolve().parent.parent
#: the repository root (holds ``configs/`` and ``measurements/``)
REPO_ROOT = PACKAGE_DIR.parent
