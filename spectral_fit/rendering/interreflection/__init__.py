"""Light exchanged between virtual objects: the paper's eq. (6) and the gather mode.

Public names are imported lazily from the private modules below on first use.
"""

from __future__ import annotations

from ..._runtime.lazy import lazy_exports

#: public name -> private module of this package that defines it
_EXPORTS: dict[str, str] = {
    "GatherSenders": "_gather",
    "IRGeometry": "_pass1",
    "MODES": "_options",
    "gather_irradiance": "_gather",
    "gather_receivers": "_gather",
    "gather_senders": "_gather",
    "interreflection": "_transport",
    "interreflection_from": "_transport",
    "pair_list": "_pass1",
    "pass1_config": "_pass1",
    "plan_gather_pass1": "_pass1",
    "prepare_interreflection": "_pass1",
    "without_pairs": "_pass1",
}

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)
