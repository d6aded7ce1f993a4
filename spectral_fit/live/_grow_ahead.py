"""Background growth of a live session's buffers: a frame that fills a buffer (an object's
covered-pixel list, the raster's windows of one size or its blocks, the kept clusters) past
``grow_ahead`` starts a compile of the step with grown buffers in a background thread; the
session switches to them at the first frame after they are compiled, so no frame waits for it.
"""

from __future__ import annotations

import functools
import threading
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from ._devices import put_on_device
from ._step import live_step

if TYPE_CHECKING:  # for annotations (the renderer is imported where it is used)
    from ..rendering import Prepared

__all__ = ["GrowAhead"]


class GrowAhead:
    """The background growth of buffers of :class:`~spectral_fit.live.LiveSession` (its
    ``prep``, ``grow_ahead``, ``headroom``, ``devices`` and growth state are set by the
    session's constructor)."""

    def _grown_plan(self, stats: dict[str, Any]) -> Prepared | None:
        """``self.prep`` with every buffer that this frame filled past ``grow_ahead`` grown
        to ``headroom`` × its use, and at least to where that use is below ``grow_ahead``
        (on the capacity ladders); None when none is that full."""
        from ..geometry import grown_clusters

        p, f = self.prep, self.grow_ahead
        buf = p.buffers
        hr = max(self.headroom, 1.0 / f)
        counts = np.asarray(stats["object_counts"]).tolist()
        cfg = buf.raster_config.grown(np.asarray(stats["raster_needed"]), hr, full=f)
        h, w = p.camera.shape
        new_pix = tuple(max(c, _pixel_slots(hr * n, h * w)) if n > f * c else c
                        for c, n in zip(buf.pixel_capacity, counts, strict=True))
        clusters = grown_clusters(buf.clusters, int(stats["clusters_needed"]), hr, full=f)
        if (cfg == buf.raster_config and new_pix == tuple(buf.pixel_capacity)
                and clusters is buf.clusters):
            return None
        return p.with_buffers(raster_config=cfg, pixel_capacity=new_pix, clusters=clusters)

    def _maybe_grow(self, stats: dict[str, Any], poses: Any, background: Any) -> None:
        """Start the background compile of grown buffers when this frame (rendered with the
        current plan) filled one past ``grow_ahead``; nothing while one is under way."""
        if (self.grow_ahead is None or self._grown is not None
                or (self._grow_thread is not None and self._grow_thread.is_alive())):
            return
        grown = self._grown_plan(stats)
        if grown is None:
            return
        base = self.prep
        host = (np.asarray(poses.model), np.asarray(poses.view), np.asarray(poses.visible))
        stop = self._grow_stop = threading.Event()

        def work() -> None:
            # the grown step (and the senders' half, whose program also takes the prepared
            # scene) compiled and run once on every device, on this frame's inputs; between
            # those steps it ends early when asked to (stop_background)
            from ..rendering import render_senders

            copies: dict[Any, Any] = {}
            try:
                for dev in self.devices:
                    if stop.is_set():
                        return
                    if len(self.devices) == 1:
                        placed, cam, put = grown, self.camera, jnp.asarray
                    else:
                        placed, cam = put_on_device(grown, dev), put_on_device(self.camera, dev)
                        copies[dev] = (grown, placed, cam)
                        put = functools.partial(jax.device_put, device=dev)
                    model, view, visible = (put(x) for x in host)
                    senders = None
                    if self._reuses_senders(grown):
                        senders = render_senders(placed, placed.materials, model=model,
                                                 visible=visible, mirror=self._mirror)
                        if stop.is_set():
                            return
                    state = self._surface_state  # the same program as the frames'
                    out, _ = live_step(placed, placed.materials, model, view, visible,
                                       put(background), cam, self._mirror, senders,
                                       None if state is None else state[2])
                    if stop.is_set():
                        return
                    jax.block_until_ready(out)
            except Exception:  # e.g. out of memory: the blocking path stays in charge
                return
            if not stop.is_set():
                self._grown = (base, grown, copies)

        # not a daemon: an interpreter that exits during the compile waits for it (a daemon
        # thread stopped inside XLA's compiler aborts the process)
        self._grow_thread = threading.Thread(target=work, name="spectral_fit-grow-ahead")
        self._grow_thread.start()

    def _adopt_grown(self) -> bool:
        """Switch to the grown buffers compiled in the background (if they grew from the
        current plan; a plan re-made since then drops them). True when switched."""
        grown, self._grown = self._grown, None
        if grown is None or grown[0] is not self.prep:
            return False
        self.prep = grown[1]
        self._copies.update(grown[2])
        self.replans_ahead += 1
        return True

    @property
    def growing(self) -> bool:
        """Whether a background compile of grown buffers is under way."""
        return self._grow_thread is not None and self._grow_thread.is_alive()

    def join_background(self) -> None:
        """Wait for a background compile of grown buffers, if one is under way (the session
        switches to them at its next frame). An interpreter that exits waits for it too."""
        t = self._grow_thread
        if t is not None:
            t.join()

    def stop_background(self) -> None:
        """Ask a background compile of grown buffers, if one is under way, to stop at its
        next step (a trace, a compile or a run on one device: XLA's compiler cannot be
        interrupted) and wait for it; the session keeps its current buffers. For the end of
        a run, when no frame will use the grown ones: an interpreter that exits waits for
        the whole compile otherwise, seconds after the last frame."""
        if self._grow_stop is not None:
            self._grow_stop.set()
        self.join_background()

    def _wait_grown(self) -> bool:
        """After an overflow: wait for a background compile under way and switch to it;
        True when the session now has other buffers to render the frame with."""
        self.join_background()
        return self._adopt_grown()


def _pixel_slots(pixels: float, frame_pixels: int) -> int:
    """An object's covered-pixel capacity for ``pixels`` (headroom included): + 64, rounded
    up to a multiple of 1024, at most the frame's pixels."""
    return min(frame_pixels, 1024 * -(-int(pixels + 64) // 1024))
