"""Light exchanged between virtual objects: the paper's eq. (6) and the gather mode.

Public names are imported lazily from the private modules below on first use.
"""

from __future__ import annotations

from ..._runtime.lazy import lazy_exports

#: public name -> private module of this package that defines it
_EXPORTS: dict[str, str] = {
    "GatherSenders": "_transport",
    "IRGeometry": "_transport",
    "MODES": "_transport",
    "gather_receivers": "_transport",
    "gather_senders": "_transport",
    "interreflection": "_transport",
    "interreflection_from": "_transport",
    "pair_list": "_transport",
    "pass1_config": "_transport",
    "plan_gather_pass1": "_transport",
    "prepare_interreflection": "_transport",
}

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)
