"""Where the compiled programs run, and the work layout that follows from it.

The same JAX code runs on the CPU and on accelerators (GPU, TPU), but a few layout choices that
make it fast on one make it slow on the other:

* **CPU** (XLA:CPU): large batches are split into chunks of a few thousand points run by a
  ``lax.map`` loop, and chunks with nothing to do are skipped by ``lax.cond``: the chunk's
  intermediates stay in cache and the cost follows the number of covered pixels.
* **Accelerator**: every iteration of a device loop and every ``lax.cond`` costs a round trip
  to the host for its predicate and a few kernel launches, which on a frame of ~2 ms is what
  dominates; there the batches run whole (or in a few very large chunks), all at once.

The choice is read when a function is traced (not when it runs), from the default backend; the
environment variable ``SPECTRAL_FIT_LAYOUT`` overrides it (``auto``, the default; ``cpu``;
``accelerator``) for benchmarking one layout against the other on the same device. Both layouts
compute the same values (tests/test_backend.py).
"""

from __future__ import annotations

import os

__all__ = ["LAYOUT_VARIABLE", "on_accelerator"]

#: environment variable that overrides the layout: "auto" (default), "cpu", "accelerator"
LAYOUT_VARIABLE = "SPECTRAL_FIT_LAYOUT"


def on_accelerator() -> bool:
    """Whether the accelerator layout applies: the default JAX backend is not the CPU, unless
    ``SPECTRAL_FIT_LAYOUT`` says ``cpu`` or ``accelerator``. Read at trace time.

    Raises:
        InputError: ``SPECTRAL_FIT_LAYOUT`` holds another value.
    """
    value = os.environ.get(LAYOUT_VARIABLE, "auto").strip().lower()
    if value == "cpu":
        return False
    if value == "accelerator":
        return True
    if value not in ("", "auto"):
        from .errors import InputError

        raise InputError(f"expected 'auto', 'cpu' or 'accelerator', got {value!r}",
                         field=LAYOUT_VARIABLE)
    import jax

    return jax.default_backend() != "cpu"
