"""The frame's interreflection stage (``spectral_fit.rendering.interreflection``): the objects as
its pass 1 sees them (the pass-1 meshes placed by the model matrices, hidden objects moved out
of the scene), the transport added to the covered pixels in the output channels, and the
gather mode's camera-independent senders' half on its own (:func:`render_senders`, compiled
once per :class:`~spectral_fit.rendering.Prepared`).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from .._runtime.dispatch import array_jit
from .._runtime.errors import InputError
from ..geometry import GBuffer, ObjectGeometry
from ..lighting import Material
from ._camera import _normals_to_world, _to_world
from ._inputs import _check_frame_inputs
from ._materials import _as_stacked, _mirror_flag, _without_mirror
from ._prepared import TRACE_COUNT, Prepared

__all__ = [
    "render_senders",
]


def _interreflection(prep: Prepared, geoms: list[ObjectGeometry], mats: list[Material],
                     gb: GBuffer, to_out: jax.Array | None,
                     own_gloss: jax.Array | None = None) -> tuple[jax.Array | None, jax.Array]:
    """Interreflection radiance (N, D) to add, in the output channels of ``to_out`` (C, D)
    (the C channels when ``to_out`` is None; None when off), and the pass-1 overflow flag;
    ``own_gloss`` (N, D): the receivers' own environment gloss (gather mode)."""
    no = jnp.zeros((), bool)
    ir, lit = prep.interreflection, prep.lighting
    if ir.mode == "none" or len(geoms) < 2:
        return None, no
    from .interreflection._transport import interreflection_from
    geom = _ir_pass1(prep, geoms)
    # paper mode's pass-1 textures shaded as the frame is: by the split sum in quality "fast"
    split = ((lit.split_map, lit.split_settings)
             if ir.mode == "paper" and lit.split_map is not None else None)
    extra = interreflection_from(geom, mats, lit.env, gb, mode=ir.mode, bounces=ir.bounces,
                                 image_shape=prep.camera.shape, output=to_out,
                                 split_sum=split, own_gloss=own_gloss)
    return extra, jnp.asarray(geom.overflow, bool)


def _ir_pass1(prep: Prepared, geoms: list[ObjectGeometry]) -> Any:
    """The interreflection's pass 1 (geometry only) of the objects, with ``prep``'s mode,
    texture size and planned raster capacities."""
    from .interreflection._pass1 import prepare_interreflection, without_pairs

    with jax.named_scope("ir_pass1"):
        geom = prepare_interreflection(geoms, mode=prep.interreflection.mode,
                                       texture_size=prep.interreflection.texture_size,
                                       gather_size=prep.interreflection.gather_size,
                                       raster_config=prep.buffers.ir_raster_config)
        return without_pairs(geom, prep.interreflection.bodies)


def _ir_geometries(prep: Prepared, model: jax.Array, visible: jax.Array
                   ) -> list[ObjectGeometry]:
    """The objects as the interreflection sees them (its pass-1 meshes, placed by ``model``):
    a hidden object intact (no degenerate triangles, which gave NaN) but 1 km below the
    scene: its light and shadow on the others are ~1e-9 of a neighbour's."""
    centres = model[:, :3, 3]
    away = jnp.where(visible, 0.0, 1e3)[:, None] * jnp.array([0.0, -1.0, 0.0], jnp.float32)
    mesh = prep.ir_mesh
    world_ir = (_to_world(mesh.vertices, mesh.vertex_object, model)
                + away[mesh.vertex_object])
    wnorm = _normals_to_world(mesh.normals, mesh.vertex_object, model)
    return [ObjectGeometry(vertices=world_ir[a:b], normals=wnorm[a:b],
                           triangles=mesh.triangles[ta:tb] - a, centre=centres[i] + away[i])
            for i, ((a, b), (ta, tb)) in enumerate(zip(mesh.object_slices,
                                                       mesh.triangle_slices, strict=True))]


def _senders_impl(prep: Prepared, materials: Any, model: jax.Array, visible: jax.Array,
                  mirror: bool = True) -> Any:
    from .interreflection._gather import gather_senders

    TRACE_COUNT["ir_senders"] += 1
    mats = _as_stacked(materials, prep.num_objects)
    if not mirror:
        mats = _without_mirror(mats)
    model = jnp.asarray(model, jnp.float32)
    visible = jnp.asarray(visible, bool)
    geom = _ir_pass1(prep, _ir_geometries(prep, model, visible))
    return gather_senders(geom, mats, prep.lighting.env, bounces=prep.interreflection.bounces)


_senders_jit = array_jit(_senders_impl)


def render_senders(prep: Prepared, materials: Any = None, *, model: Any = None,
                   visible: Any = None, mirror: bool | None = None) -> Any:
    """The camera-independent half of a gather-mode frame's interreflection (pass 1, the
    senders' shading, atlases, transfer and bounces;
    :class:`~spectral_fit.rendering.interreflection.GatherSenders`), for the objects at ``model`` /
    ``visible`` (defaults as :func:`render_frame`; traced, compiled once per ``prep``).
    Pass it to :func:`render_pixels` (``senders=``) for any number of camera views of that
    same object state: the result equals the frame that computes it itself. Its
    ``geometry.overflow`` is the pass-1 overflow flag. ``mirror``: as for
    :func:`render_frame`, and the same for the frames that use it."""
    ir = prep.interreflection
    if ir.mode != "gather" or prep.num_objects < 2 or ir.bounces < 1:
        raise InputError("needs a gather-mode interreflection of at least two objects and "
                         f"one bounce, got mode {ir.mode!r} with {prep.num_objects} "
                         f"objects and {ir.bounces} bounces", field="interreflection.mode")
    mats, model, _, visible = _check_frame_inputs(prep, materials, model, None, visible)
    return _senders_jit(prep, mats, model, visible, _mirror_flag(mats, mirror))
