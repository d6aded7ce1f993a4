"""Environment shading of a frame's covered pixels (eq. 5 of Mochizuki & Tanaka in our physical
reading): the G-buffer samples, laid out object by object, each object's slice shaded with its
material under the environment. Qualities "render" and "exact" shade in the C radiance
channels (W·sr⁻¹·m⁻²·nm⁻¹ per band or basis coefficient), (N, C); quality "fast" (the split
sum) shades straight into the K output channels, (N, K), in chunks of slots that skip the
chunks past each object's covered count.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.backend import as_chunks, materialise, on_accelerator
from ..geometry import GBuffer
from ..lighting import Material
from ._materials import mirror_needed
from ._prepared import Prepared


def _shade_samples(mats: list[Material], env: Any, gb: GBuffer, batch: int,
                   lut: jax.Array | None = None, quality: str = "render",
                   capacities: tuple[int, ...] | None = None, split_map: Any = None,
                   split_settings: Any = None, spec_vis: jax.Array | None = None
                   ) -> jax.Array:
    """Environment shading (eq. 5) of the G-buffer samples, (N, C): the samples are laid out
    object by object (``capacities[o]`` slots for object o), and each object's slice is shaded
    with its material by :func:`~spectral_fit.lighting.shade_points`. With an irradiance map
    ``lut`` (:func:`irradiance_table`), the diffuse term α S I_d(N)/π takes its irradiance from
    the map (the gloss and mirror terms come from ``env`` as always). ``spec_vis`` (N,): the
    gloss and mirror terms scaled by it (the visibility of the mirror direction, from the
    objects' self-occlusion; None: 1); the object's own light reflected instead is
    :func:`own_reflection_out`'s."""
    import dataclasses

    from ..lighting import shade_points

    if capacities is None:
        capacities = (gb.object.shape[0],)
        mats = mats[:1]
    if quality == "fast":
        return _shade_fast(mats, env, gb, lut, capacities, split_map, split_settings)
    table = None if lut is None else _lut_env(env, lut)
    out = []
    extra = () if spec_vis is None else (spec_vis,)
    for m, cap, (nrm, v, *sv) in zip(mats, capacities, _object_slices(gb, capacities, *extra),
                                     strict=True):
        bs = max(1, min(batch, cap))
        if table is None and not sv:
            out.append(shade_points(m, env, nrm, v, batch_size=bs, quality=quality))
            continue
        spec = shade_points(dataclasses.replace(m, alpha=jnp.zeros_like(m.alpha)), env, nrm, v,
                            batch_size=bs, quality=quality)
        if sv:
            spec = spec * sv[0][:, None]
        if table is None:
            diffuse = shade_points(dataclasses.replace(m, beta=jnp.zeros_like(m.beta),
                                                       chi=jnp.zeros_like(m.chi)),
                                   env, nrm, v, batch_size=bs, quality=quality)
            out.append(spec + diffuse)
            continue
        e = jax.vmap(lambda d: _lookup(table, d))(nrm)
        se = _filtered_irradiance(m, env, e)
        front = jnp.sum(nrm * v, axis=-1, keepdims=True) > 0.0
        out.append(spec + jnp.where(front, m.alpha / math.pi, 0.0) * se)
    return jnp.concatenate(out)


def _object_slices(gb: GBuffer, capacities: tuple[int, ...], *extra: jax.Array):
    """Yield each object's (normals, views, *extras), normals and views (capacity, 3), from the
    G-buffer whose samples are laid out object after object with the given capacities, and
    the same slices of each ``extra`` array (N, ...)."""
    start = 0
    for cap in capacities:
        yield (gb.normal[start:start + cap], gb.view[start:start + cap],
               *(x[start:start + cap] for x in extra))
        start += cap


def own_reflection_out(mats: list[Material], gb: GBuffer, capacities: tuple[int, ...],
                       seen: jax.Array) -> jax.Array:
    """The object's own light in its gloss lobe and mirror direction (N, K), every object's
    slice of the G-buffer: :func:`lobe_albedo` times ``seen`` (N, K), the object's diffuse
    radiance over the hidden share of the mirror direction
    (:func:`~spectral_fit.rendering._occlusion.own_reflection`); for the qualities that
    shade in the radiance channels ("render", "exact": their lobe albedo from the split
    sum's moment table, as quality "fast" uses)."""
    from ..lighting import lobe_moment_table

    out = []
    for m, (nrm, v, sn) in zip(mats, _object_slices(gb, capacities, seen), strict=True):
        moments = lobe_moment_table(m.mu, m.n, distribution=m.distribution, geometry=m.geometry)
        nv = jnp.sum(nrm * v, axis=-1, keepdims=True)
        own = lobe_albedo(m, moments, nv, mirror=mirror_needed([m])) * sn
        out.append(jnp.where(nv > 0.0, own, 0.0))
    return jnp.concatenate(out)


def lobe_albedo(m: Material, moments: jax.Array, nv: jax.Array, *, mirror: bool) -> jax.Array:
    """β A(θr) + χ F(θr) (N, 1): how much of a uniform radiance around the mirror direction
    the gloss and mirror reflect at cosθr = ``nv`` (N, 1); A the lobe's albedo from
    ``moments`` (:func:`~spectral_fit.lighting.lobe_moment_table`), the mirror term only
    with ``mirror``."""
    from ..lighting import fresnel_dielectric, split_sum_albedo

    f = m.beta * split_sum_albedo(moments, nv[:, 0])[:, None]
    if mirror:
        f = f + m.chi * fresnel_dielectric(jnp.clip(nv, 0.0, 1.0), m.n)
    return f


def specular_at(m: Material, env: Any, normals: jax.Array, views: jax.Array, *,
                quality: str, split_map: Any = None, split_settings: Any = None,
                moments: jax.Array | None = None, batch_size: int = 32) -> jax.Array:
    """The gloss and mirror terms of eq. (5), β gloss + χ F L(R), at points of one material
    (normals, views (N, 3) world, unit) in the radiance channels (N, C); 0 where N·V ≤ 0.
    Quality "fast": the split sum (``split_map``, ``split_settings``; the material's
    :func:`~spectral_fit.lighting.lobe_moment_table` ``moments``, computed when None) and
    one mirror lookup, as the frame's pixels; else
    :func:`~spectral_fit.lighting.shade_points` with α = 0."""
    import dataclasses

    from ..lighting import lobe_moment_table, shade_points

    if quality != "fast":
        spec = shade_points(dataclasses.replace(m, alpha=jnp.zeros_like(m.alpha)), env,
                            normals, views, batch_size=batch_size, quality=quality)
        nv = jnp.sum(normals * views, axis=-1, keepdims=True)
        return jnp.where(nv > 0.0, spec, 0.0)
    if moments is None:
        moments = lobe_moment_table(m.mu, m.n, settings=split_settings,
                                    distribution=m.distribution, geometry=m.geometry)
    spec, nv = _gloss_and_mirror(env, split_map, env if mirror_needed([m]) else None, moments,
                                 normals, views, m, split_settings)
    return jnp.where(nv > 0.0, spec, 0.0)


def _irradiance_at(env: Any, table: Any, normals: jax.Array) -> jax.Array:
    """Irradiance (N, C) of world ``normals`` (N, 3): looked up in the irradiance map ``table``
    (:func:`_lut_env` of the frame's map), or the environment's own (SH or exact) without."""
    from ..lighting import fast_lookup, irradiance

    if table is None:
        return jax.vmap(lambda d: irradiance(env, d))(normals)
    return fast_lookup(table, normals)


def _filtered_irradiance(m: Material, env: Any, e: jax.Array) -> jax.Array:
    """S(λ)·E (N, C): the irradiance ``e`` (N, C) filtered by the material's reflectance, per band
    or through the basis product tensor when the map is in K coefficients."""
    if env.product_tensor is None:
        return m.reflectance * e
    return jnp.einsum("i,nj,ijk->nk", m.reflectance, e, env.product_tensor)


def _gloss_and_mirror(env_gloss: Any, split_map: Any, env_mirror: Any, moments: jax.Array,
                      nrm: jax.Array, v: jax.Array, m: Material, settings: Any
                      ) -> tuple[jax.Array, jax.Array]:
    """Quality "fast" gloss and mirror of eq. (5) at points nrm, v (N, 3), β gloss + χ F L(R)
    (N, C): the split-sum gloss per unit β looked up in ``env_gloss``'s channels, F(n, N·V)
    times the mirror radiance along R from ``env_mirror`` (None: no mirror term); and N·V
    (N, 1)."""
    from ..lighting import fast_lookup, fresnel_dielectric, gloss_split_sum

    gloss = gloss_split_sum(env_gloss, split_map, moments, nrm, v, m.mu, m.n,
                            settings=settings, distribution=m.distribution,
                            geometry=m.geometry)
    nv = (nrm[:, 0] * v[:, 0] + nrm[:, 1] * v[:, 1] + nrm[:, 2] * v[:, 2])[:, None]
    refl = 2.0 * nv * nrm - v
    # per-point factors computed once (not inside each of the C channels' expressions)
    fac = materialise(jnp.concatenate([fresnel_dielectric(nv, m.n), nv], axis=-1))
    spec = m.beta * gloss
    if env_mirror is not None:
        spec = spec + m.chi * (fac[:, 0:1] * fast_lookup(env_mirror, refl))
    return spec, fac[:, 1:2]


def _shade_fast(mats: list[Material], env: Any, gb: GBuffer, lut: jax.Array | None,
                capacities: tuple[int, ...], split_map: Any, settings: Any) -> jax.Array:
    """Quality "fast" of :func:`_shade_samples`: eq. (5) with the split-sum gloss
    (:func:`~spectral_fit.lighting.gloss_split_sum`; one moment table per object), the
    mirror by one lookup along R and the diffuse irradiance from the irradiance map ``lut``
    (or ``env``), all points of an object at once (few lookups per point: no batching)."""
    from ..lighting import lobe_moment_table

    table = None if lut is None else _lut_env(env, lut)
    out = []
    for m, (nrm, v) in zip(mats, _object_slices(gb, capacities), strict=True):
        kw = dict(distribution=m.distribution, geometry=m.geometry)
        moments = lobe_moment_table(m.mu, m.n, settings=settings, **kw)
        spec, nv = _gloss_and_mirror(env, split_map, env if mirror_needed([m]) else None,
                                     moments, nrm, v, m, settings)
        se = _filtered_irradiance(m, env, _irradiance_at(env, table, nrm))
        out.append(jnp.where(nv > 0.0, (m.alpha / math.pi) * se + spec, 0.0))
    return jnp.concatenate(out)


def _lut_env(env: Any, flat: jax.Array, shape: tuple[int, int] | None = None) -> Any:
    """``env`` with its texels/poles replaced by a table laid out as texels + 2 pole rows
    (same rotation), for :func:`~spectral_fit.lighting.lookup`."""
    c = flat.shape[-1]
    if shape is None:
        n = flat.shape[0] - 2
        h = int(round(math.sqrt(n / 2)))
        shape = (h, n // h)
    return eqx.tree_at(lambda e: (e.texels, e.poles), env,
                       (flat[:-2].reshape(shape[0], shape[1], c), flat[-2:]))


def _lookup(table: Any, direction: jax.Array) -> jax.Array:
    from ..lighting import lookup

    return lookup(table, direction)


#: largest shading chunk with the accelerator layout (slots)
_ACCEL_CHUNK = 65536


def _chunk_size(capacity: int) -> int:
    """Slots per shading chunk: chunks beyond the covered-pixel count are skipped, so the
    shading cost follows the count (to within one chunk), not the planned capacity; chunks of
    a few thousand points also keep the gloss's intermediates in cache (about twice as fast
    on the close-up as one batch of all slots). With the accelerator layout
    (:mod:`spectral_fit._runtime.backend`) the chunks are as large as the capacity, up to 65,536
    slots."""
    if on_accelerator():
        return min(capacity, _ACCEL_CHUNK)
    if capacity >= 32768:
        return 4096
    if capacity >= 4096:
        return 2048
    return capacity


def _chunked(fn: Any, counts: Sequence[jax.Array], out_channels: int,
             arrays: Sequence[tuple[jax.Array, ...]]) -> list[jax.Array]:
    """``fn(o, *chunk)`` (B, K) over consecutive chunks of segment o's (cap_o, …) ``arrays[o]``
    for every segment o (one traced body for all segments: o is a traced int32), skipping
    (zeros) the chunks that start at or after ``counts[o]`` (the valid slots come first).
    With the accelerator layout all chunks run at once (``vmap``, nothing skipped): a device
    loop and a conditional per chunk cost more there than the skipped work.
    Returns the (cap_o, K) results per segment."""
    caps = [a[0].shape[0] for a in arrays]
    b = min(_chunk_size(c) for c in caps)
    nchunks = [-(-c // b) for c in caps]
    if sum(nchunks) == 1:
        return [fn(jnp.int32(0), *arrays[0])]
    padded = [as_chunks(seg, b) for seg in arrays]
    chunks = [jnp.concatenate(parts) for parts in zip(*padded, strict=True)]
    seg_of = jnp.asarray(np.repeat(np.arange(len(caps)), nchunks), jnp.int32)
    first = jnp.asarray(np.concatenate([np.arange(nc) * b for nc in nchunks]), jnp.int32)
    count = jnp.stack([jnp.asarray(c, jnp.int32) for c in counts])
    dtype = jnp.float32

    def body(x: tuple[jax.Array, ...]) -> jax.Array:
        o, start, *chunk = x
        return jax.lax.cond(start < count[o], lambda *c: fn(o, *c).astype(dtype),
                            lambda *c: jnp.zeros((b, out_channels), dtype), *chunk)

    if on_accelerator():
        out = jax.vmap(lambda o, *c: fn(o, *c).astype(dtype))(seg_of, *chunks)
    else:
        out = jax.lax.map(body, (seg_of, first, *chunks))
    res, at = [], 0
    for cap, nc in zip(caps, nchunks, strict=True):
        res.append(out[at:at + nc].reshape(nc * b, out_channels)[:cap])
        at += nc
    return res


def _shade_out(prep: Prepared, mats: list[Material], gb: GBuffer, counts: list[jax.Array],
               to_out: jax.Array, mirror_table: jax.Array,
               spec_vis: jax.Array | None = None,
               spec_seen: jax.Array | None = None, *,
               with_gloss: bool = False) -> Any:
    """Environment shading (eq. 5, quality "fast") of the G-buffer samples straight into the output
    channels (N, K) (``with_gloss``: and, as a second (N, K) array, the part of it that is the
    environment's gloss and mirror, after the object's own visibility and before its own
    reflected light: what a neighbour can hide of it): ``to_out`` (C, K) maps radiance channels
    to them. The gloss and mirror depend on λ only through the environment, so they are looked
    up in K channels (the split-sum levels' principal spectra times ``to_out``; ``mirror_table``
    = the map's texels + 2 pole rows times ``to_out``); the diffuse term α S(λ) I_d(N)/π is one
    lookup of a per-object table (the irradiance map filtered by S(λ), times α/π, times
    ``to_out``, built per frame: 2,050 rows). In chunks of slots, chunks past each object's
    covered count skipped; the objects whose materials share a distribution and geometry share
    one traced shading body (their per-object tables and parameters selected by object), which
    halves the compilation of a two-object frame. ``spec_vis`` (N,), ``spec_seen`` (N, K): the
    gloss and mirror scaled by the first, the object's own light reflected from the second (see
    :func:`_shade_samples`)."""
    from ..lighting import fast_lookup, lobe_moment_table

    env = prep.lighting.env
    settings = prep.lighting.split_settings
    k_out = int(to_out.shape[1])
    env_g = eqx.tree_at(lambda e: e.spectral_basis, env, env.spectral_basis @ to_out)
    mirror_env = _lut_env(env, mirror_table, env.texels.shape[:2])
    lut = prep.lighting.irradiance_lut
    extra = tuple(x for x in (spec_vis, spec_seen) if x is not None)
    slices = list(_object_slices(gb, prep.buffers.pixel_capacity, *extra))
    groups: dict[tuple[str, str], list[int]] = {}
    for i, m in enumerate(mats):
        groups.setdefault((m.distribution, m.geometry), []).append(i)
    out: list[Any] = [None] * len(mats)
    for (dist, geom), members in groups.items():
        kw = dict(distribution=dist, geometry=geom)
        group = [mats[i] for i in members]
        stacked = jax.tree.map(lambda *xs: jnp.stack([jnp.asarray(x, jnp.float32)
                                                      for x in xs]), *group)
        moments = jax.vmap(functools.partial(lobe_moment_table, settings=settings, **kw))(
            stacked.mu, stacked.n)  # (O, size, 4), one compiled table for the group
        group_mirror = mirror_env if mirror_needed(group) else None
        dflat = None
        if lut is not None:
            dflat = jnp.stack([(m.alpha / math.pi) * _filtered_irradiance(m, env, lut) @ to_out
                               for m in group])

        def shade(o: jax.Array, nn: jax.Array, vv: jax.Array, sv: Any = None,
                  seen: Any = None, stacked: Material = stacked, moments: jax.Array = moments,
                  dflat: Any = dflat, group_mirror: Any = group_mirror) -> jax.Array:
            m = jax.tree.map(lambda x: x[o], stacked)
            spec, nv = _gloss_and_mirror(env_g, prep.lighting.split_map, group_mirror,
                                         moments[o], nn, vv, m, settings)
            if dflat is None:
                diffuse = (m.alpha / math.pi) * _filtered_irradiance(
                    m, env, _irradiance_at(env, None, nn)) @ to_out
            else:
                diffuse = fast_lookup(_lut_env(env, dflat[o]), nn)
            if sv is not None:
                spec = spec * sv[:, None]
            env_spec = spec
            if seen is not None:
                spec = spec + lobe_albedo(m, moments[o], nv,
                                          mirror=group_mirror is not None) * seen
            res = diffuse + spec
            if with_gloss:
                res = jnp.concatenate([res, env_spec], axis=-1)
            return jnp.where(nv > 0.0, res, 0.0)

        res = _chunked(shade, [counts[i] for i in members], 2 * k_out if with_gloss else k_out,
                       [slices[i] for i in members])
        for i, r in zip(members, res, strict=True):
            out[i] = r
    res = jnp.concatenate(out)
    return (res[:, :k_out], res[:, k_out:]) if with_gloss else res
