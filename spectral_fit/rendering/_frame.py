"""Multipass frame renderer: scene → spectral frame → XYZ → display RGB.

Two steps, so that a live loop or a fit never recompiles:

* :func:`prepare` (Python, once per scene shape) builds everything that does not change from
  frame to frame: the meshes (object frames, concatenated), the camera projection, the
  environment (prefiltered, in bands or K basis coefficients), the display, the exposure, the
  rasteriser's window capacities and the covered-pixel capacity. It returns a
  :class:`Prepared` pytree.
* :func:`render_frame` (jit-compiled, differentiable) renders one frame from a
  :class:`Prepared` and the TRACED per-frame inputs: the materials of all objects, their model
  matrices ``(O, 4, 4)``, the camera's view matrix ``(4, 4)`` and a visibility mask ``(O,)``.
  New poses, a hidden object or new material values reuse the same compiled program.

Per frame (eq. 5 + eq. 6 of Mochizuki & Tanaka in our physical reading):

1. vertices → world (per-object model matrix) → clip; hidden objects collapse to a point, so
   their triangles are degenerate and draw nothing;
2. rasterise all objects at once (:func:`~spectral_fit.geometry.rasterize` with planned
   capacities; only the triangles of the clusters that may face the eye,
   :mod:`spectral_fit.geometry`, bit-identical to a raster of all), compact the covered
   pixels (:func:`~spectral_fit.geometry.covered_pixels`), interpolate world positions and
   normals there (a :class:`~spectral_fit.geometry.GBuffer`);
3. shade each covered pixel with its object's material under the environment
   (:func:`~spectral_fit.lighting.shade`), radiance in W·sr⁻¹·m⁻²·nm⁻¹ per band or basis
   coefficient, and add the interreflection between objects
   (``spectral_fit.rendering.interreflection.interreflection``; modes "gather", "paper", "none");
4. background = the environment seen through each pixel (no video), looked up in a precomputed
   XYZ copy of the map (exact: the lookup is linear);
5. XYZ (absolute, cd/m², 683 lm/W) → display RGB (:func:`~spectral_fit.color.to_display`:
   exposure, clipping in linear RGB with the out-of-gamut fraction reported, tone curve).

This module holds :func:`render_frame` (steps 4 and 5 after :mod:`._pixels`' steps 1–3) and
:func:`with_output`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.dispatch import array_jit
from .._runtime.errors import InputError
from ._background import _background
from ._inputs import _check_frame_inputs, _check_senders
from ._materials import _mirror_flag
from ._pixels import _pixels_impl
from ._prepared import Frame, PixelFrame, Prepared

__all__ = [
    "render_frame",
    "with_output",
]


def _scatter(values: jax.Array, px: PixelFrame, image: jax.Array) -> jax.Array:
    """Write the slots' ``values`` (N, K) into ``image`` (H, W, K)."""
    h, w, k = image.shape
    idx = jnp.where(px.valid, px.index, h * w)  # out of range: dropped
    return image.reshape(h * w, k).at[idx].set(values, mode="drop").reshape(h, w, k)


# PixelFrame.stats that are arrays (the buffers' use), not in a Frame's scalar stats
_PLAN_STATS = ("object_counts", "raster_needed", "clusters_needed")


def _render_impl(prep: Prepared, materials: Any, model: jax.Array, view: jax.Array,
                 visible: jax.Array, spectral: bool, background: bool = True,
                 mirror: bool = True, senders: Any = None) -> Frame:
    from ..color import display_linear, encode, gamut_fractions

    h, w = prep.camera.shape
    col = prep.colour
    px = _pixels_impl(prep, materials, model, view, visible, spectral, mirror, senders)
    # 4. background and XYZ
    if background:
        with jax.named_scope("background"):
            bg_xyz = _background(prep, col.env_xyz, view).reshape(h, w, 3)
    else:
        bg_xyz = jnp.zeros((h, w, 3), jnp.float32)
    spec = None
    if spectral:
        xyz_px = px.values @ col.to_xyz
        xyz = _scatter(xyz_px, px, bg_xyz)
        if background:
            env = prep.lighting.env
            hm, wm, c = env.texels.shape
            flat = jnp.concatenate([env.texels.reshape(hm * wm, c), env.poles])
            bg = (_background(prep, flat, view) @ col.to_spectrum).reshape(h, w, -1)
        else:
            bg = jnp.zeros((h, w, col.to_spectrum.shape[1]), jnp.float32)
        spec = _scatter(px.values @ col.to_spectrum, px, bg)
    else:
        xyz_px = px.values
        xyz = _scatter(xyz_px, px, bg_xyz)

    # 5. display
    with jax.named_scope("display"):
        kw = dict(exposure_luminance=col.exposure, display=col.display,
                  scene_white_xy=col.scene_white_xy)
        linear = display_linear(xyz, **kw)
        rgb = encode(linear, col.display)
        # the gamut fractions over the covered pixels' slots (N ≪ H·W) rather than the masked
        # image: four frame-wide reductions cost a noticeable share of the frame
        fractions = gamut_fractions(display_linear(xyz_px, **kw), px.valid)
    count = px.stats["covered_pixels"]
    stats = {
        "out_of_gamut_fraction": fractions[0],
        "below_zero_fraction": fractions[1],
        "overexposed_fraction": fractions[2],
        "coverage": count.astype(jnp.float32) / (h * w),
        **{k: v for k, v in px.stats.items() if k not in _PLAN_STATS},
    }
    return Frame(xyz=xyz, rgb=rgb, linear_rgb=linear, mask=px.mask,
                 object_id=px.object_id, spectral=spec, stats=stats)


_render_jit = array_jit(_render_impl)


def render_frame(prep: Prepared, materials: Any = None, *, model: Any = None, view: Any = None,
                 visible: Any = None, spectral: bool = False, background: bool = True,
                 mirror: bool | None = None, senders: Any = None) -> Frame:
    """Render one frame (jit-compiled once per :class:`Prepared` shape; differentiable).

    Args:
        prep: from :func:`prepare`.
        materials: a stacked :class:`~spectral_fit.lighting.Material` (leading axis O) or a
            sequence of O Materials (reflectance in bands, or K coefficients in basis mode);
            default the config's. Traced: new values never recompile, except χ going from
            all zero to not (see ``mirror``).
        model: (O, 4, 4) world-from-object matrices (default the config's poses). Traced.
        view: (4, 4) world → OpenGL eye view matrix (default the config's camera). Traced.
        visible: (O,) bool per-object visibility (default all visible). Traced.
        spectral: also return the spectral radiance (H, W, L) (a separate compilation; the
            default frame never forms per-pixel spectra: it shades straight into XYZ).
        background: False: uncovered pixels are black (0) instead of the environment seen
            through them (for callers that replace them, e.g. by a video frame; a separate
            compilation).
        mirror: whether the frame is compiled with the perfect-mirror term (χ). Default
            (None): :func:`mirror_needed`: without it only when every χ is a concrete 0 (the
            paper's plastics; not under ``jax.grad``/``vmap``/``jit``, where χ is traced),
            which leaves out the neighbours' mirror radiance the interreflection would
            otherwise carry in every channel (a tenth of the frame); the first χ
            that is not 0 then compiles the frame with it. True: always with it (e.g. a slider
            for χ that should never recompile). False: every χ taken as 0 (refused when a
            concrete χ is not 0).
        senders: gather mode: the interreflection's camera-independent half from
            :func:`render_senders` for the same ``prep``, materials, mirror switch, ``model``
            and ``visible`` (the caller keeps them consistent), used instead of the frame's
            own pass 1: camera paths around objects that stay put compute it once (a separate
            compilation; the frame equals the one that computes it, to float rounding).

    Returns:
        :class:`Frame`. Gradients flow to every material parameter of every object (and to
        the model/view matrices through shading, not through visibility).
    """
    mats, model, view, visible = _check_frame_inputs(prep, materials, model, view, visible)
    _check_senders(prep, senders)
    return _render_jit(prep, mats, model, view, visible, bool(spectral), bool(background),
                       _mirror_flag(mats, mirror), senders)


def with_output(prep: Prepared, matrix: Any) -> Prepared:
    """``prep`` with its radiance-channels → output map replaced by ``matrix`` (C, 3) (e.g.
    channels → a video camera's linear RGB): :attr:`Frame.xyz` (and the background table, and
    the mirror lookups that the frame does in the output space) are then in that space."""
    m = np.asarray(matrix, np.float64)
    if m.shape != (prep.channels, 3) or not np.all(np.isfinite(m)):
        raise InputError(f"expected a finite ({prep.channels}, 3) matrix, got {m.shape}",
                         field="matrix")
    env = prep.lighting.env
    hm, wm, c = env.texels.shape
    flat = np.concatenate([np.asarray(env.texels, np.float64).reshape(hm * wm, c),
                           np.asarray(env.poles, np.float64)])
    colour = dataclasses.replace(prep.colour, to_xyz=jnp.asarray(m, jnp.float32),
                                 env_xyz=jnp.asarray(flat @ m, jnp.float32))
    return dataclasses.replace(prep, colour=colour)
