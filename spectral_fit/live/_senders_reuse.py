"""Reuse of the gather interreflection's senders' half across live frames: it is computed
again only when some vertex of a visible object moved more than ``ir_reuse_mm`` millimetres in
the world (bounded by the objects' bounding-box corners, metres), or visibility or the prepared
scene changed; otherwise the frame reuses it (copied to another device once).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from ._devices import put_on_device

if TYPE_CHECKING:  # for annotations (the renderer is imported where it is used)
    from ..rendering import Prepared

__all__ = ["SendersReuse"]


class SendersReuse:
    """The senders' half reuse of :class:`~spectral_fit.live.LiveSession` (its ``prep``,
    ``ir_reuse_mm``, ``devices`` and senders' state are set by the session's constructor)."""

    def _reuses_senders(self, p: Prepared) -> bool:
        """Whether frames take the senders' half from :func:`render_senders` (else the step
        computes it, or there is none)."""
        ir = p.interreflection
        return not (self.ir_reuse_mm is None or ir.mode != "gather" or p.num_objects < 2
                    or ir.bounces < 1)

    def _senders_for(self, poses: Any, inputs: Any, dev: Any = None) -> Any:
        """The gather interreflection's senders' half for these poses, on device ``dev``:
        reused when no vertex moved more than ``ir_reuse_mm`` (and visibility and the
        prepared scene are the same; copied to another device once), else computed
        (dispatched) again; None when the step computes it itself."""
        if not self._reuses_senders(self.prep):
            return None
        from ..rendering import render_senders

        dev = self.devices[0] if dev is None else dev
        model = np.asarray(poses.model, np.float64)
        visible = np.asarray(poses.visible, bool)
        key = self._senders_key
        # hidden objects neither send nor receive: only the visible ones' motion counts
        if (key is not None and key[0] is self.prep and np.array_equal(key[2], visible)
                and _max_displacement(self._corners[visible], key[1][visible],
                                      model[visible]) <= self.ir_reuse_mm * 1e-3):
            self.ir_reuses += 1
            if dev not in self._senders:
                self._senders[dev] = put_on_device(next(iter(self._senders.values())), dev)
            return self._senders[dev]
        prep = self._placed(dev)[0]
        self._senders = {dev: render_senders(prep, prep.materials, model=inputs[0],
                                             visible=inputs[2], mirror=self._mirror)}
        self._senders_key = (self.prep, model, visible)
        self.ir_updates += 1
        return self._senders[dev]


def _object_corners(prep: Prepared) -> np.ndarray:
    """(O, 8, 4) homogeneous corners of each object's bounding box in its own frame."""
    v = np.asarray(prep.mesh.vertices, np.float64)
    out = []
    for a, b in prep.mesh.object_slices:
        lo, hi = v[a:b].min(axis=0), v[a:b].max(axis=0)
        c = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                      for z in (lo[2], hi[2])])
        out.append(c)
    return np.stack(out)


def _max_displacement(corners: np.ndarray, model_a: np.ndarray, model_b: np.ndarray) -> float:
    """The largest distance (m) any point of an object's bounding box moves between the
    world-from-object matrices ``model_a`` and ``model_b`` (O, 4, 4): the displacement of an
    affine map is a convex function of the point, so its maximum over the box is at a
    corner, and it bounds every vertex's. 0 for no objects (O = 0)."""
    if len(corners) == 0:
        return 0.0
    d = np.einsum("oij,okj->oki", model_b - model_a, corners)[..., :3]
    return float(np.sqrt(np.max(np.sum(d * d, axis=-1))))
