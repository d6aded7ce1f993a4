"""Capacity regrowth: a frame whose buffers overflowed (objects moved closer than planned) is
rendered again with the covered-pixel lists, the camera raster's windows, its cluster list or
the interreflection's pass-1 rasters grown (:func:`regrow`, :func:`ir_fallback`); and
:func:`render`, the convenience :func:`~spectral_fit.rendering.prepare` +
:func:`~spectral_fit.rendering.render_frame` that does so.
"""

from __future__ import annotations

import os
import warnings
from typing import TYPE_CHECKING, Any

import numpy as np

from ..geometry import capacity_ladder
from ._camera import _to_world, camera_clip
from ._capacities import _ir_generic_config
from ._frame import render_frame
from ._prepare import prepare
from ._prepared import Frame, Prepared

if TYPE_CHECKING:  # for annotations (imported where they are used)
    from ..geometry import RasterConfig
    from ..io import Scene

__all__ = [
    "render",
    "regrow",
    "ir_fallback",
]


def render(scene: Scene | str | os.PathLike[str], materials: Any = None, *, spectral: bool = False,
           **prepare_options: Any) -> Frame:
    """Convenience (stable API): :func:`prepare` + :func:`render_frame` with the config's
    poses. ``scene`` is a Scene or a config path; ``prepare_options`` go to :func:`prepare`
    (size, mode, spectral_mode, k, ...). When a buffer overflowed (objects moved closer than
    planned), the capacities are grown and the frame is rendered again, with a warning."""
    prep = prepare(scene, **prepare_options)
    frame = render_frame(prep, materials, spectral=spectral)
    return regrow(prep, frame, materials, spectral)


def regrow(prep: Prepared, frame: Frame, materials: Any, spectral: bool) -> Frame:
    for _ in range(4):
        pix_over = bool(frame.stats["pixel_overflow"])
        ras_over = bool(frame.stats["raster_overflow"])
        ir_cfg = ir_fallback(prep) if bool(frame.stats["interreflection_overflow"]) else None
        if not (pix_over or ras_over or ir_cfg is not None):
            return frame
        buf, cam, mesh = prep.buffers, prep.camera, prep.mesh
        changes: dict[str, Any] = {}
        if ir_cfg is not None:
            changes["ir_raster_config"] = ir_cfg
        if pix_over:
            h, w = cam.shape
            counts = np.bincount(np.asarray(frame.object_id).reshape(-1) + 1,
                                 minlength=prep.num_objects + 1)[1:]
            changes["pixel_capacity"] = tuple(
                max(c, min(h * w, capacity_ladder(1.5 * int(n) + 64, 64)))
                for c, n in zip(buf.pixel_capacity, counts, strict=True))
        if ras_over and buf.clusters is not None:
            from ..geometry import count_clusters, grown_clusters

            grown = grown_clusters(buf.clusters, count_clusters(
                buf.clusters, prep.model, cam.view, cam.projection, cull=cam.cull), 1.5)
            if grown is not buf.clusters:
                changes["clusters"] = grown
        if ras_over:
            from ..geometry import rasterize

            world = _to_world(mesh.vertices, mesh.vertex_object, prep.model)
            r = rasterize(camera_clip(cam.projection, cam.view, cam.lens, world),
                          mesh.triangles, cam.shape,
                          cull=cam.cull, config=buf.raster_config, check=False)
            changes["raster_config"] = buf.raster_config.grown(np.asarray(r.needed), 1.5)
        warnings.warn(f"render: buffers grown ({sorted(changes)}); recompiling",
                      RuntimeWarning, stacklevel=3)
        prep = prep.with_buffers(**changes)
        frame = render_frame(prep, materials, spectral=spectral)
    raise RuntimeError("render: buffers still overflow after growing them")


def ir_fallback(prep: Prepared) -> RasterConfig | None:
    """The pass-1 raster capacities after an interreflection overflow: at least the generic
    ones (:func:`_ir_generic_config`); None when they are there already (nothing to grow)."""
    cur = prep.buffers.ir_raster_config
    if cur is None:
        return None
    tris = max(tb - ta for ta, tb in prep.ir_mesh.triangle_slices)
    ir = prep.interreflection
    gen = _ir_generic_config(ir.mode, ir.texture_size, tris, ir.gather_size)
    new = cur._replace(capacities=tuple(max(a, b) for a, b in zip(
        cur.capacities, gen.capacities, strict=True)),
        block_capacity=max(cur.block_capacity, gen.block_capacity))
    return None if new == cur else new

