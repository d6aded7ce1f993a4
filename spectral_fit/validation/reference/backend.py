"""Mitsuba 3 set-up: variant choice and the LLVM library for the JIT variants.

The reference renderer needs the optional extra ``validate`` (``pip install
spectral_fit[validate]``, i.e. ``mitsuba>=3.5``). Variant choice, in order:

1. the environment variable ``SPECTRAL_FIT_MI_VARIANT`` (e.g. ``llvm_ad_rgb``, ``scalar_rgb``,
   ``cuda_ad_rgb``), used as given;
2. ``llvm_ad_rgb`` when an LLVM shared library of version >= 16 is found (Dr.Jit's LLVM backend
   crashed with Debian 12's default LLVM 15; Debian's ``libllvm19`` works); the library is
   handed to Dr.Jit through ``DRJIT_LIBLLVM_PATH`` unless that is already set;
3. ``scalar_rgb`` otherwise (no extra library; the Python BSDF then runs once per ray, far
   slower, which only suits tests at tiny sizes).

Only rgb variants are used: the band trick carries three spectral bands per render.
"""

from __future__ import annotations

import glob
import os
import re
from types import ModuleType
from typing import Any

from ..._runtime.errors import InputError

__all__ = ["VARIANT_ENV", "find_llvm", "mitsuba_available", "init_mitsuba", "current_variant"]

VARIANT_ENV = "SPECTRAL_FIT_MI_VARIANT"
_RGB_VARIANTS = ("llvm_ad_rgb", "scalar_rgb", "cuda_ad_rgb")
_LLVM_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.*",
    "/usr/lib/x86_64-linux-gnu/libLLVM-*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM.so.*",
    "/usr/lib/aarch64-linux-gnu/libLLVM-*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
)


def find_llvm(min_major: int = 16) -> str | None:
    """Path of the newest LLVM shared library of major version >= ``min_major``, or None."""
    best: tuple[int, str] | None = None
    for pattern in _LLVM_GLOBS:
        for path in glob.glob(pattern):
            m = re.search(r"libLLVM(?:-|\.so\.)(\d+)", os.path.basename(path))
            if m is None:
                continue
            major = int(m.group(1))
            if major >= min_major and (best is None or major > best[0]):
                best = (major, path)
    return None if best is None else best[1]


def mitsuba_available() -> bool:
    """True when ``import mitsuba`` would succeed (does not import it)."""
    import importlib.util

    return importlib.util.find_spec("mitsuba") is not None


_STATE: dict[str, Any] = {}


def init_mitsuba(variant: str | None = None) -> tuple[ModuleType, ModuleType]:
    """Import Mitsuba 3 and Dr.Jit, select an rgb variant (see the module docstring) and register
    the BSDF of our model; returns ``(mi, dr)``. The first call fixes the variant for the process
    (a later call asking for another one raises :class:`InputError`)."""
    if _STATE:
        if variant is not None and variant != _STATE["variant"]:
            raise InputError(f"Mitsuba already runs variant {_STATE['variant']!r} in this "
                             f"process; cannot switch to {variant!r}", field=VARIANT_ENV)
        return _STATE["mi"], _STATE["dr"]
    if not mitsuba_available():
        raise InputError("the reference renderer needs Mitsuba 3: pip install "
                         "'spectral_fit[validate]'", field="mitsuba")
    chosen = variant or os.environ.get(VARIANT_ENV) or None
    if chosen is None:
        llvm = os.environ.get("DRJIT_LIBLLVM_PATH") or find_llvm()
        if llvm is not None:
            os.environ.setdefault("DRJIT_LIBLLVM_PATH", llvm)
            chosen = "llvm_ad_rgb"
        else:
            chosen = "scalar_rgb"
    elif chosen.startswith("llvm") and "DRJIT_LIBLLVM_PATH" not in os.environ:
        llvm = find_llvm()
        if llvm is not None:
            os.environ["DRJIT_LIBLLVM_PATH"] = llvm
    if chosen not in _RGB_VARIANTS:
        raise InputError(f"must be one of {list(_RGB_VARIANTS)} (the band trick needs an rgb "
                         f"variant), got {chosen!r}", field=VARIANT_ENV)
    import drjit as dr
    import mitsuba as mi

    if chosen not in mi.variants():
        raise InputError(f"variant {chosen!r} is not in this Mitsuba build "
                         f"({mi.variants()})", field=VARIANT_ENV)
    mi.set_variant(chosen)
    from .bsdf import register_bsdf

    register_bsdf(mi, dr)
    _STATE.update(mi=mi, dr=dr, variant=chosen)
    return mi, dr


def current_variant() -> str | None:
    """The variant chosen by :func:`init_mitsuba`, or None before the first call."""
    return _STATE.get("variant")
