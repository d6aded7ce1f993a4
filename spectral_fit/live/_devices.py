"""The devices that render live frames: the session's choice of JAX devices (frame i on device
i mod len(devices)), the device that holds a committed array, and pytrees committed to a device.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from .._runtime.errors import InputError

__all__ = ["put_on_device"]


def _frame_devices(devices: Any) -> tuple[Any, ...]:
    """The session's rendering devices (see :class:`LiveSession` ``devices``)."""
    if devices is None:
        if jax.default_backend() == "cpu":
            return tuple(jax.devices("cpu"))
        return (jax.devices()[0],)
    if isinstance(devices, jax.Device):
        devices = (devices,)
    try:
        out = tuple(devices)
    except TypeError:
        out = ()
    if not out or not all(isinstance(d, jax.Device) for d in out):
        raise InputError(f"expected a sequence of jax devices, got {devices!r}",
                         field="devices")
    if len(set(out)) != len(out) or len({d.platform for d in out}) != 1:
        raise InputError(f"expected distinct devices of one platform, got {out!r}",
                         field="devices")
    return out


def _device_of(x: Any, devices: tuple[Any, ...]) -> Any:
    """The device that holds ``x`` when it is one of ``devices`` (a committed array), else
    the first of them."""
    if len(devices) > 1 and isinstance(x, jax.Array):
        held = x.devices()
        if len(held) == 1:
            (d,) = held
            if d in devices:
                return d
    return devices[0]


def put_on_device(tree: Any, device: Any) -> Any:
    """``tree`` with its arrays committed to ``device`` (other leaves unchanged: they are
    static parts of the compiled step)."""
    return jax.tree_util.tree_map(
        lambda x: jax.device_put(x, device) if isinstance(x, jax.Array | np.ndarray) else x,
        tree)
