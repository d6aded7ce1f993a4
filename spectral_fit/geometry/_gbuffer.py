"""Pytrees passed between the rasteriser, the shading and the interreflection passes.

* :class:`ObjectGeometry` — one object's triangle mesh in WORLD space plus its centre (the
  interreflection passes place their cameras at object centres).
* :class:`GBuffer` — a fixed-capacity list of surface samples to shade (deferred shading): the
  covered pixels of a camera view, the texels of an interreflection pass, or the measured spots
  of a spectroradiometer session. Unused slots have ``object == -1`` and must be ignored.

Shapes are static (capacities are fixed up front), so new poses never recompile.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

__all__ = ["ObjectGeometry", "GBuffer"]


class ObjectGeometry(eqx.Module):
    """One object's mesh in world space.

    Attributes:
        vertices: (V, 3) float32 world positions, metres.
        normals: (V, 3) float32 unit vertex normals (world).
        triangles: (T, 3) int32 vertex indices, counter-clockwise seen from outside.
        centre: (3,) float32 world position of the object's centre (the model-frame origin).
    """

    vertices: jax.Array
    normals: jax.Array
    triangles: jax.Array
    centre: jax.Array


class GBuffer(eqx.Module):
    """Surface samples to shade, N slots (N static).

    Attributes:
        position: (N, 3) world position of the surface point, metres.
        normal: (N, 3) unit shading normal (world), facing outwards.
        view: (N, 3) unit direction from the point towards the observer (camera or instrument).
        object: (N,) int32 index of the object the point lies on; −1 for an empty slot.
        pixel: (N,) int32 flat pixel index (row · W + column) in the view that produced the
            sample, or −1 when the samples do not come from an image.
    """

    position: jax.Array
    normal: jax.Array
    view: jax.Array
    object: jax.Array
    pixel: jax.Array

    @property
    def valid(self) -> jax.Array:
        """(N,) bool: slots that hold a sample."""
        return self.object >= 0

    @property
    def size(self) -> int:
        return int(self.object.shape[0])

    @classmethod
    def empty(cls, n: int) -> GBuffer:
        z3 = jnp.zeros((n, 3), jnp.float32)
        up = z3.at[:, 1].set(1.0)
        neg = jnp.full((n,), -1, jnp.int32)
        return cls(position=z3, normal=up, view=up, object=neg, pixel=neg)
