"""The gather mode assembled, in two halves.

The senders' half (:func:`gather_senders`, a :class:`GatherSenders` pytree) depends on the
objects' poses, the materials and the environment, not on the camera: the samples' shading,
their mip atlases, the sample-to-sample diffuse transfer and the ``bounces`` (Jacobi
iteration of the exchange, the samples receiving from the other objects' samples). The
receivers' half (:func:`gather_receivers`) turns it into the radiance (N, C), or (N, D) in an
``output`` map's channels, to add at any receivers: the diffuse term (α S ⊙ the net light)
plus the lobe gloss and mirror; on the CPU layout with many receiver slots the valid ones are
put first and the empty slots' chunks skipped (:func:`_receive_valid_first`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..._runtime.backend import on_accelerator, prefix_chunks
from ..._runtime.errors import InputError
from ...geometry import GBuffer
from ...lighting import EnvironmentMap, Material, dot3, taps_sum
from ._atlas import _build_mips
from ._diffuse import (
    _VIEW_GRID,
    _direct_diffuse,
    _grid_views,
    _interpolate_net,
    _irradiance_at,
    _net_tables,
    _reverse_pairs,
    _sample_coverage,
    _sample_diffuse,
    _sample_diffuse_net,
    _sample_specular,
    _sees,
    _Senders,
    _view_frames,
)
from ._gloss import _hidden_source_gloss, _lobe_gather, _lobe_quadrature, _lobe_reach
from ._march import _mirror_hidden
from ._options import (
    _check_diffuse_at,
    _check_image_shape,
    _check_int,
    _check_materials,
    _check_receivers,
)
from ._pass1 import IRGeometry
from ._schedule import (
    DIFFUSE_STEP,
    GLOSS_STEP,
    _diffuse_anchors,
    _image_anchors,
    _partition,
    _pixel_slots,
)
from ._shading import _Shading, _shading, _specular, _times_reflectance

__all__ = ["GatherSenders", "gather_senders", "gather_receivers", "gather_irradiance"]


def _reflect_diffuse(sh: _Shading, net: jax.Array, obj: jax.Array) -> jax.Array:
    """α S(λ) ⊙ net (N, C) per receiver object ``obj`` (N,), in ``sh``'s output channels."""
    o = jnp.maximum(obj, 0)
    mats = sh.mats
    return sh.to_output(mats["alpha"][o][:, None]
                        * _times_reflectance(sh.env, mats["reflectance"][o], net))


def _receive(geom: IRGeometry, sh: _Shading, atlas: tuple[Any, ...],
             diffuse: jax.Array, pos: jax.Array, nrm: jax.Array, view: jax.Array,
             obj: jax.Array, *,
             grid: tuple[jax.Array, tuple[int, int], int] | None = None,
             own: jax.Array | None = None) -> jax.Array:
    """Interreflection (N, D) at receivers (pos, nrm, view (N, 3), obj (N,)) in ``sh``'s output
    channels, given their diffuse term ``diffuse`` (N, D) (α S ⊙ the net light they receive,
    :func:`_reflect_diffuse`) and the senders' mip ``atlas`` (in the output channels);
    ``own`` (N, D): the receivers' own environment gloss (:func:`_lobe_quadrature`)."""
    dif, gloss = _receive_parts(geom, sh, atlas, diffuse, pos, nrm, view, obj, grid=grid,
                                own=own)
    return dif + gloss


def _receive_parts(geom: IRGeometry, sh: _Shading, atlas: tuple[jax.Array, ...],
                   diffuse: jax.Array, pos: jax.Array, nrm: jax.Array, view: jax.Array,
                   obj: jax.Array, *,
                   grid: tuple[jax.Array, tuple[int, int], int] | None = None,
                   own: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
    """:func:`_receive` in two parts (N, D): the diffuse term and the gloss and mirror, each 0
    where the receiver gets no interreflection."""
    # gloss and mirror: quadrature of the receiver's lobe, each node ray against the senders
    gloss = _lobe_gather(geom, atlas, sh, pos, nrm, view, obj, grid, own)
    gloss, ok = _less_hidden_sources(geom, sh, gloss, pos, nrm, view, obj)
    return (jnp.where(ok[:, None], diffuse, 0.0), jnp.where(ok[:, None], gloss, 0.0))


def _less_hidden_sources(geom: IRGeometry, sh: _Shading, out: jax.Array, pos: jax.Array,
                         nrm: jax.Array, view: jax.Array, obj: jax.Array
                         ) -> tuple[jax.Array, jax.Array]:
    """``out`` (N, D) less the environment's gloss that the neighbours hide
    (:func:`_hidden_source_gloss`), and (N,) whether each receiver gets interreflection at
    all (it sees a neighbour and faces its view)."""
    hsrc = _hidden_source_gloss(sh, geom, obj, pos, nrm, view)
    if hsrc is not None:
        out = out - hsrc
    return out, _sees(geom, pos, nrm, obj) & (dot3(nrm, view) > 0.0)


class GatherSenders(eqx.Module):
    """The camera-independent half of the gather interreflection of one scene state
    (:func:`gather_senders`): pass-1 geometry, the senders' samples with their radiance after
    all the bounces, their mip atlases and the diffuse net light at the samples. A pytree of
    arrays; :func:`gather_receivers` turns it into the light at any receivers. It depends on
    the objects' poses, the materials and the environment, not on the camera.

    Attributes:
        geometry: :class:`IRGeometry` (gather mode).
        senders: the senders' samples as the last gather saw them.
        atlas: (radiance (P, A, C), normal·coverage and coverage (P, A, 4), and after a
            bounce (the change of the samples' gloss towards their receivers (P, A, C), the
            share of it each view of the grid shows (P, A, 9)), each times coverage, else
            None) mip atlases.
        net: (P, M, C) diffuse net light at the samples, or None (``diffuse_at`` =
            "receivers" with one bounce).
    """

    geometry: IRGeometry
    senders: _Senders
    atlas: tuple[Any, ...]
    net: jax.Array | None


def gather_senders(geometry: IRGeometry, materials: Sequence[Material], env: EnvironmentMap,
                   *, bounces: int = 1, diffuse_at: str = "samples") -> GatherSenders:
    """The senders' side of :func:`interreflection_from` in gather mode (pass-1 shading, mip
    atlases, the sample-to-sample transfer and the bounces): everything that does not depend
    on the receivers, so a caller whose objects and materials did not change (a camera
    moving around static objects) computes it once and calls :func:`gather_receivers` per
    frame. ``gather_receivers(gather_senders(g, m, e), m, e, r)`` equals
    ``interreflection_from(g, m, e, r)`` exactly."""
    if geometry.mode != "gather":
        raise InputError(f"needs a gather-mode geometry, got {geometry.mode!r}", field="mode")
    _check_materials(geometry.n_objects, materials, env)
    bounces = _check_int(bounces, "bounces", 1, 64)
    _check_diffuse_at(diffuse_at)
    return _gather_senders(geometry, materials, env, bounces, diffuse_at)


def _gather_senders(geom: IRGeometry, materials: Sequence[Material], env: EnvironmentMap,
                    bounces: int, diffuse_at: str) -> GatherSenders:
    pairs = geom.pairs
    senders = [j for _, j in pairs]
    p_count, m_count = geom.s_area.shape
    sh = _shading(materials, env)
    live = geom.s_area > 0
    frames = _view_frames(geom)
    with jax.named_scope("ir_sample_shading"):
        spec, mirror = _sample_specular(geom, sh, frames)
        irr = _irradiance_at(env, geom.s_nrm)  # (P, M, C): the samples' diffuse light
        l0 = jnp.where(live[..., None], _sample_diffuse(geom, sh, irr), 0.0)
    cov = geom.s_cov[..., None]
    with jax.named_scope("ir_atlas"):  # geometry alone: once, not per bounce
        geo_atlas = _build_mips(jnp.concatenate([geom.s_nrm * cov, cov], -1),
                                geom.gather_size)

    def senders_with(lum: jax.Array, bounced: tuple[jax.Array, jax.Array] | None = None
                     ) -> tuple[_Senders, tuple[jax.Array, ...]]:
        """The senders with view-independent radiance ``lum`` (P, M, C) and, after a bounce,
        its change of their gloss towards their receivers (``geom.s_view``) (P, M, C) with the
        share of it each view of the grid shows (P, M, 9): in bands the views' radiance then
        stays non-negative (the change may cancel at most the view's own radiance)."""
        view_part, view_atlas = mirror, None
        if bounced is not None:
            change, shown = bounced
            dview = change[:, :, None] * shown[..., None]  # (P, M, 9, C)
            if toward is not None:
                dview = jnp.maximum(dview, -toward - lum[:, :, None])
            view_part = dview if mirror is None else mirror + dview
            with jax.named_scope("ir_atlas"):  # two atlases: each tap sum consumed whole
                view_atlas = (_build_mips(change * cov, geom.gather_size),
                              _build_mips(shown * cov, geom.gather_size))
        snd = _Senders(pos=geom.s_pos, nrm=geom.s_nrm, area=geom.s_area, frames=frames,
                       lum=lum, spec=spec, mirror=view_part)
        with jax.named_scope("ir_atlas"):
            atlas = (_build_mips(lum * cov, geom.gather_size), geo_atlas, view_atlas)
        return snd, atlas

    toward = None  # the senders' gloss towards their view grids, where it bounds
    shown = None  # which views of the grid the bounce's change of gloss reaches
    if bounces > 1:
        # the environment's gloss and mirror each sample shows towards its grid's views
        g_all = spec @ env.spectral_basis + (0.0 if mirror is None else mirror)  # (P, M, 9, C)
        if env.product_tensor is None:  # bands (a basis's may be negative)
            toward = jax.lax.stop_gradient(jnp.maximum(g_all, 0.0))
        # the grid's views and the one the bounce's change is found towards (the sample's
        # view of the nearest point of its receiver's bounding sphere)
        views = jnp.concatenate([_grid_views(geom, frames), geom.s_view[:, :, None]], 2)
        mu = sh.mats["mu"][jnp.asarray(senders, jnp.int32)][:, None, None]
        cos_v = jnp.maximum(jnp.sum(views * geom.s_nrm[:, :, None], -1), 0.05)
        hid = _mirror_hidden(geom, views, math.sqrt(2.0) * mu * jnp.sqrt(cos_v))
        # the gloss each view shows of the environment (summed over the channels)
        g_ref, m_ref = _specular(sh, jnp.repeat(jnp.asarray(senders, jnp.int32), m_count),
                                 geom.s_nrm.reshape(-1, 3), geom.s_view.reshape(-1, 3))
        g_ref = g_ref @ env.spectral_basis + (0.0 if m_ref is None else m_ref)
        g_all = jnp.concatenate([g_all, g_ref.reshape(p_count, m_count, 1, -1)], 2)
        hidden = hid * jnp.sum(jnp.maximum(g_all, 0.0), -1)  # (P, M, 10)
        # each view's hidden gloss against that of the bounce's view, at most all of it
        shown = jnp.where(hid[..., -1:] > 0.05, jnp.clip(
            hidden[..., :-1] / jnp.maximum(hidden[..., -1:], 1e-30), 0.0, 1.0), 1.0)
        shown = jax.lax.stop_gradient(shown)
    lum = l0
    snd, atlas = senders_with(lum)
    s_obj = jnp.where(live.reshape(-1), jnp.asarray(np.repeat(senders, m_count), jnp.int32),
                      -1)
    s_pos, s_nrm = geom.s_pos.reshape(-1, 3), geom.s_nrm.reshape(-1, 3)
    net = cover = None
    for b in range(bounces):
        if diffuse_at == "samples" or b < bounces - 1:
            with jax.named_scope("ir_sample_transfer"):
                if cover is None:  # geometry and environment alone: once, not per bounce
                    cover = _sample_coverage(geom, env, irr)
                net = _sample_diffuse_net(geom, snd, env, cover)
        if b == bounces - 1:
            break
        with jax.named_scope("ir_sample_bounce"):
            dif, gloss = _receive_parts(
                geom, sh, atlas, _reflect_diffuse(sh, net.reshape(-1, net.shape[-1]), s_obj),
                s_pos, s_nrm, geom.s_view.reshape(-1, 3), s_obj)
        lum = l0 + jnp.where(live[..., None], dif.reshape(l0.shape), 0.0)
        if toward is not None:  # towards the receiver's centre, never below zero
            lum = jnp.maximum(lum, -toward[:, :, len(_VIEW_GRID) ** 2 // 2])
        # the bounce's change of a sample's gloss (the environment its neighbour hides in the
        # lobe, less the neighbour's light there), found towards its receiver, is carried
        # towards each view of its grid in the share of the gloss a neighbour hides there: a
        # view that grazes past the neighbour (a slab's face seen from beside the other slab)
        # keeps its open gloss
        change = jnp.where(live[..., None], gloss.reshape(l0.shape), 0.0)
        snd, atlas = senders_with(lum, (change, shown))
    return GatherSenders(geometry=geom, senders=snd, atlas=atlas,
                         net=net if diffuse_at == "samples" else None)


def gather_receivers(state: GatherSenders, materials: Sequence[Material], env: EnvironmentMap,
                     receivers: GBuffer, *, image_shape: tuple[int, int] | None = None,
                     gloss_step: int = GLOSS_STEP, output: Any = None,
                     own_gloss: Any = None) -> jax.Array:
    """The receivers' side of the gather interreflection: radiance (N, C) (or (N, D) with
    ``output``) to add at ``receivers``, from :func:`gather_senders`'s state of the same
    objects, ``materials`` and ``env`` (options as :func:`interreflection_from`; the
    diffuse transfer is evaluated where the state was made for)."""
    geom = state.geometry
    _check_materials(geom.n_objects, materials, env)
    _check_receivers(receivers)
    gloss_step = _check_int(gloss_step, "gloss_step", 1, 64)
    image_shape = _check_image_shape(image_shape)
    diffuse_at = "samples" if state.net is not None else "receivers"
    return _gather_receivers(state, materials, env, receivers, diffuse_at, image_shape,
                             gloss_step, output, own_gloss)


def _gather_receivers(state: GatherSenders, materials: Sequence[Material],
                      env: EnvironmentMap, receivers: GBuffer, diffuse_at: str,
                      image_shape: tuple[int, int] | None, gloss_step: int,
                      output: jax.Array | None, own: Any = None) -> jax.Array:
    geom, snd, atlas, net = state.geometry, state.senders, state.atlas, state.net
    senders = [j for _, j in geom.pairs]
    sh = _shading(materials, env)
    pos, nrm, obj = receivers.position, receivers.normal, receivers.object
    # the receivers' terms in the output channels: the diffuse net light of each pair's
    # samples reflected by their object (α S ⊙ net, then the output map) before it is
    # interpolated, the senders' atlas mapped before it is gathered from (all linear)
    sh = dataclasses.replace(sh, output=None if output is None else jnp.asarray(output,
                                                                              jnp.float32))
    if output is not None:
        view_atlas = atlas[2]
        if view_atlas is not None:  # the change of gloss mapped, the views' shares kept
            view_atlas = (view_atlas[0] @ sh.output, view_atlas[1])
        atlas = (atlas[0] @ sh.output, atlas[1], view_atlas)
    grid = None if image_shape is None or gloss_step < 2 else (receivers.pixel, image_shape,
                                                                gloss_step)
    # pixels of one image: the samples' interpolated light corrected at screen-space anchors
    image = None if image_shape is None or diffuse_at != "samples" else (
        receivers.pixel, image_shape, snd, env)
    tables = None
    with jax.named_scope("ir_receiver_diffuse"):
        if diffuse_at == "samples":
            refl = sh.diffuse_matrices()[jnp.asarray(senders, jnp.int32)]  # (P, C, D)
            tables = _net_tables(geom, jnp.einsum("pmc,pcd->pmd", net, refl))
            diffuse = None
        else:
            diffuse = _reflect_diffuse(sh, _direct_diffuse(geom, snd, env, pos, nrm, obj),
                                       obj)
    if own is not None:
        own = jnp.asarray(own, jnp.float32)
        if own.shape != (pos.shape[0], sh.channels):
            raise InputError(f"expected shape {(pos.shape[0], sh.channels)}, got {own.shape}",
                             field="own_gloss")
    if not on_accelerator() and pos.shape[0] > _RECEIVER_CHUNK:
        return _receive_valid_first(geom, sh, atlas, tables, diffuse, pos, nrm,
                                    receivers.view, obj, grid, own, image)
    if diffuse is None:
        with jax.named_scope("ir_receiver_diffuse"):
            diffuse = _interpolate_net(geom, net, pos, nrm, obj, tables=tables)
            if image is not None:
                diffuse = _anchored_diffuse(geom, sh, diffuse, pos, nrm, obj, *image)
    with jax.named_scope("ir_receiver_gloss"):
        return _receive(geom, sh, atlas, diffuse, pos, nrm, receivers.view, obj, grid=grid,
                        own=own)


def gather_irradiance(state: GatherSenders, positions: jax.Array, normals: jax.Array,
                      objects: jax.Array) -> jax.Array | None:
    """The change (N, C) of the irradiance at points on the objects that the other objects
    make (their light, less the environment they hide), in the environment's channels:
    π × the diffuse net light of ``state``'s samples (kept as ΔE/π, what α S(λ) turns into
    radiance), interpolated as the frame's receivers get it.

    Args:
        state: :func:`gather_senders` of the objects (diffuse transfer at the samples).
        positions, normals: (N, 3) world points on the objects and their unit normals.
        objects: (N,) int the object each point lies on.

    Returns:
        (N, C), 0 where a point faces no neighbour; None when ``state`` holds no samples'
        net light (``diffuse_at`` = "receivers" with one bounce).
    """
    if state.net is None:
        return None
    pos = jnp.asarray(positions, jnp.float32)
    nrm = jnp.asarray(normals, jnp.float32)
    obj = jnp.asarray(objects, jnp.int32)
    # the samples' net light is kept as ΔE/π (what α S(λ) turns into radiance)
    return math.pi * _interpolate_net(state.geometry, state.net, pos, nrm, obj)


#: the diffuse anchors are evaluated where a neighbour's samples come nearer than this many
#: of the receiving object's sample spacings (seen along the receiver's normal): farther
#: away the sky the neighbour hides changes slowly between the samples
_ANCHOR_NEAR = 2.0
#: the spacings of :data:`_ANCHOR_NEAR` are those of a g × g grid with g at most this: the
#: interpolation's error beside a neighbour follows distances (the sky it hides), not the
#: grid, and finer grids (``gather_size`` 32) would otherwise leave receivers 20 mm from a
#: slab uncorrected (5 % too dark in the red on the back slab of ``configs/flat_faces.toml``)
_ANCHOR_GRID = 16
#: anchors per chunk of their per-receiver sums (chunks past the anchors near a neighbour
#: are skipped; a few dozen of them is a common count)
_ANCHOR_CHUNK = 32


def _near_neighbour(geom: IRGeometry, pos: jax.Array, nrm: jax.Array, obj: jax.Array
                    ) -> jax.Array:
    """(N,) bool: receivers (pos, unit nrm (N, 3), obj (N,), −1 = none) that lie within
    ``_ANCHOR_NEAR`` sample spacings of a neighbour's samples, plus half the neighbour's
    spacing. The spacing of the receiving object's samples that face the neighbour (the
    pair's g × g window, 2·extent/g a side) is stretched by 1/|n·a| on a face the pair's axis
    a meets obliquely (at most 5×): there they are far apart, and the sky a close neighbour
    hides changes between them."""
    k_per = geom.n_objects - 1
    g = min(geom.gather_size, _ANCHOR_GRID)
    rev = jnp.asarray(_reverse_pairs(geom.n_objects))
    o = jnp.maximum(obj, 0)
    live = geom.s_area > 0
    near = jnp.zeros(obj.shape, bool)
    for k in range(k_per):
        pair = o * k_per + k  # (i, j): samples on the neighbour j
        q = rev[pair]  # (j, i): the samples on i facing j
        # by components (a sum over a last axis of 3 runs as a slow loop on XLA:CPU)
        d = [geom.s_pos[..., c][pair] - pos[:, None, c] for c in range(3)]  # 3 × (N, M)
        d2 = jnp.where(live[pair], d[0] * d[0] + d[1] * d[1] + d[2] * d[2], jnp.inf)
        dmin = jnp.sqrt(jnp.min(d2, -1))
        cos_a = jnp.maximum(jnp.abs(dot3(nrm, geom.frame[q][:, 2])), 0.2)
        reach = _ANCHOR_NEAR * (2.0 * geom.extent[q] / g) / cos_a + geom.extent[pair] / g
        near = near | (dmin < reach)
    return near & (obj >= 0)


def _anchored_diffuse(geom: IRGeometry, sh: _Shading, base: jax.Array, pos: jax.Array,
                      nrm: jax.Array, obj: jax.Array, pixel: jax.Array,
                      shape: tuple[int, int], snd: _Senders, env: EnvironmentMap
                      ) -> jax.Array:
    """The diffuse term (N, D) of receivers that are pixels of one image (``pixel`` (N,),
    ``shape`` (H, W)): ``base`` (N, D), the samples' net light interpolated to them
    (:func:`_interpolate_net`, reflected: α S ⊙ net in ``sh``'s output channels), corrected
    by the difference between the transfer summed at the receiver itself
    (:func:`_direct_diffuse`: the neighbours' samples' form factors and the environment
    they hide, marched from the receiver) and that interpolation. The difference is
    evaluated at screen-space anchors every ``DIFFUSE_STEP``-th row and column that lie near
    a neighbour (:func:`_near_neighbour`; at most ⌈H/step⌉·⌈W/step⌉ of them, a fixed
    shape) and blended between them (:func:`_diffuse_anchors`). The samples lie where the
    pass-1 raster along each pair's axis puts them: on a face that axis meets obliquely they
    are centimetres apart, and the sky a neighbour a few millimetres away hides changes
    within that distance."""
    n = obj.shape[0]
    evaluate, idx, wts = _diffuse_anchors(pixel, obj, shape, DIFFUSE_STEP, pos, nrm)
    cap = min(n, -(-shape[0] // DIFFUSE_STEP) * -(-shape[1] // DIFFUSE_STEP))
    _, order = _partition(evaluate)
    sel = order[:cap]  # the anchors first (each is a distinct pixel: at most cap of them)
    a_pos, a_nrm = pos[sel], nrm[sel]
    a_obj = jnp.where(evaluate[sel], obj[sel], -1)
    a_obj = jnp.where(_near_neighbour(geom, a_pos, a_nrm, a_obj), a_obj, -1)
    own = _reflect_diffuse(sh, _direct_diffuse(geom, snd, env, a_pos, a_nrm, a_obj,
                                               chunk=_ANCHOR_CHUNK), a_obj)
    corr = jnp.zeros_like(base).at[sel].set(jnp.where((a_obj >= 0)[:, None],
                                                      own - base[sel], 0.0))
    return base + jnp.where(evaluate[:, None], corr, taps_sum(corr, idx, wts))


#: CPU layout: receivers per chunk of the per-receiver terms of :func:`_receive_valid_first`
_RECEIVER_CHUNK = 4096


def _receive_valid_first(geom: IRGeometry, sh: _Shading, atlas: tuple[Any, ...],
                         tables: tuple[jax.Array, ...] | None,
                         diffuse: jax.Array | None, pos: jax.Array, nrm: jax.Array,
                         view: jax.Array, obj: jax.Array,
                         grid: tuple[jax.Array, tuple[int, int], int] | None,
                         own: jax.Array | None = None, image: tuple[Any, ...] | None = None
                         ) -> jax.Array:
    """:func:`_receive` (N, D) for many receivers on the CPU layout, at a cost that follows
    the number of valid receivers (obj >= 0) rather than N: a renderer's receivers are
    fixed-capacity slot lists, of which the covered pixels fill ~55–60 % (the capacities'
    headroom). The valid receivers are put first (a stable partition), their per-receiver
    terms (the interpolated diffuse net light, ``tables`` from :func:`_net_tables`, or the
    given ``diffuse`` (N, D); the hidden sources; the lobe's reach; the image anchors) run in
    chunks of ``_RECEIVER_CHUNK`` with the chunks past them skipped, the lobe quadrature runs
    on the active ones as in :func:`_lobe_gather`, and the result goes back to the slots'
    order. Equal to :func:`_receive` (the same arithmetic per receiver). ``image`` = (pixel
    (N,), image shape, senders, environment): the interpolated diffuse light corrected at
    screen-space anchors (:func:`_anchored_diffuse`)."""
    valid = obj >= 0
    rank, order = _partition(valid)
    count = jnp.sum(valid.astype(jnp.int32))
    pos, nrm, view, obj = pos[order], nrm[order], view[order], obj[order]
    if diffuse is not None:
        diffuse = diffuse[order]
    if own is not None:
        own = own[order]
    if image is not None and diffuse is None:
        with jax.named_scope("ir_receiver_diffuse"):
            base = prefix_chunks(
                lambda x, nn, ob: _interpolate_net(geom, None, x, nn, ob, tables=tables),
                count, [pos, nrm, obj], size=_RECEIVER_CHUNK)
            diffuse = _anchored_diffuse(geom, sh, base, pos, nrm, obj, image[0][order],
                                        *image[1:])
    step = 0
    at = None
    pixel = jnp.full(obj.shape, -1, jnp.int32)
    if grid is not None:
        pixel, shape, step = grid[0][order], grid[1], grid[2]
        refl_all = 2.0 * dot3(nrm, view)[:, None] * nrm - view
        at = (_pixel_slots(pixel, obj, shape), pos, refl_all, obj)
    mu = sh.mats["mu"]

    def terms(x: jax.Array, nn: jax.Array, vv: jax.Array, ob: jax.Array, px: jax.Array,
              *dif: jax.Array) -> tuple[jax.Array, ...]:
        with jax.named_scope("ir_receiver_diffuse"):
            base = dif[0] if dif else _interpolate_net(geom, None, x, nn, ob, tables=tables)
        with jax.named_scope("ir_receiver_gloss"):
            base, ok = _less_hidden_sources(geom, sh, base, x, nn, vv, ob)
            active, gap, refl = _lobe_reach(geom, sh, x, nn, vv, ob)
            if at is None:
                return base, ok, active
            itself, a_idx, a_w = _image_anchors(px, ob, shape, step, x, refl, gap,
                                                math.sqrt(2.0) * mu[jnp.maximum(ob, 0)], at=at)
            return base, ok, active & itself, itself, a_idx, a_w

    extra = [] if diffuse is None else [diffuse]
    out = prefix_chunks(terms, count, [pos, nrm, view, obj, pixel, *extra],
                        size=_RECEIVER_CHUNK)
    base, ok, active = out[:3]
    with jax.named_scope("ir_receiver_gloss"):
        res = _lobe_quadrature(geom, atlas, sh, pos, nrm, view, obj, active, own)
        if at is not None:
            itself, a_idx, a_w = out[3:]
            res = jnp.where(itself[:, None], res, taps_sum(res, a_idx, a_w))
        return jnp.where(ok[:, None], base + res, 0.0)[rank]


def _gather_mode(geom: IRGeometry, materials: Sequence[Material], env: EnvironmentMap,
                 receivers: GBuffer, bounces: int, diffuse_at: str = "samples",
                 image_shape: tuple[int, int] | None = None, gloss_step: int = 1,
                 output: jax.Array | None = None, own: Any = None) -> jax.Array:
    state = _gather_senders(geom, materials, env, bounces, diffuse_at)
    return _gather_receivers(state, materials, env, receivers, diffuse_at, image_shape,
                             gloss_step, output, own)
