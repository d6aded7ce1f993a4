"""Lazy exports for the subpackages' ``__init__`` modules (PEP 562).

A package lists its public names and the private module that defines each; the module is
imported on the first use of one of its names, so importing a package (or one of its
modules) never imports the rest of it. This keeps ``import spectral_fit.<package>`` cheap and
lets the command-line tools start without colour-science, matplotlib or OpenCV when they do
not need them.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable
from typing import Any


def lazy_exports(package: str, exports: dict[str, str]
                 ) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for ``package`` whose public names are ``exports``.

    Args:
        package: the package's ``__name__``.
        exports: public name -> name of the module of ``package`` that defines it.
    """

    def __getattr__(name: str) -> Any:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{module}"), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted({*vars(sys.modules[package]), *exports})

    return __getattr__, __dir__
