"""Interreflection between objects: the paper's two-pass eq. (6) ("paper") and a physically
based gather ("gather"), both as radiance to ADD to the environment-only shading of eq. (5).

Both modes split into a geometry-only pass and a shading pass (nvdiffrast style), so a caller
whose geometry is fixed (the fitter) rasterises once and re-shades many times:

    geom = prepare_interreflection(objects, mode="gather")              # rasterise pass 1
    extra = interreflection_from(geom, materials, env, receivers)       # shade, (N, C)

and :func:`interreflection` is the composition. Every array has a static shape (ordered pairs
of objects, pass-1 buffers and sample lists of fixed size), so moving objects never recompiles;
everything is jit-able and differentiable w.r.t. every material parameter.

Pairs. For n objects there are P = n(n − 1) ordered pairs p = (i, j), i the object that
RECEIVES light and j the one that sends it, stored in the order p = i·(n − 1) + k with
j = k for k < i and j = k + 1 otherwise.

"paper" mode — eq. (6) of Mochizuki & Tanaka, literally:

    C(λ) = α I_d S + α T_d(λ, x, y) + {β I_gloss + χ I_mirror} E + γ T_s(λ, x, y).

Pass 1 renders object j with :func:`~spectral_fit.geometry.interreflection_camera` (at c_i,
looking at c_j, up +Y, 90° FOV, aspect 1, ``texture_size``²) into two spectral textures: T_d,
the diffuse-only radiance α_j S_j E_irr/π of j, and T_s, its specular-only radiance
β_j I_gloss + χ_j I_mirror, both shaded with the view direction towards c_i (the pass-1 eye).
Pass 2 projects the receiving fragment x through the same camera and, where the projection is
valid (in front of the eye, inside the view, and the fragment facing j: N·(c_j − x) > 0), adds
α_paper T_d + γ T_s looked up bilinearly at (x, y) (clamp to edge, texels outside j are 0). In
our scaling α_paper = α/π, γ is the material's ``gamma``. There are no bounces.

"gather" mode — our correction (docs/conventions.md). Pass 1 rasterises object j ORTHOGRAPHICALLY
along the axis c_i → c_j (so it covers the whole hemisphere of j that faces i, not only the cap seen
from c_i) at (4g)² and box-filters it into g × g surface samples y (g = ``gather_size``): area A_y,
area-weighted mean position and normal, and coverage. The shading pass then:

1. splits each sample's radiance into a view-independent part (j's diffuse α_j S_j E_irr/π,
   plus what it receives itself on later bounces) and a view-dependent part (gloss and mirror,
   :func:`_specular`: the lobe albedo times the environment prefiltered to the lobe width
   around the mirror direction, plus the bright sources exactly), the latter tabulated towards
   a 3 × 3 grid of directions spanning i's bounding sphere as seen from y;
2. gathers at each receiver x on i, per fragment (no shared projection centre), always with
   j's radiance towards x itself (view direction y → x, not towards the camera):
   - diffuse: α S_i(λ) [Σ_y F(x, y) L_y(→x) − hidden environment − hidden sources/π] with
     the point-to-patch form factor F = cos_x cos_y A_y / (π √(r⁴ + (A_y/π)²)) (the midpoint
     rule cos cos A/(π r²) to second order, bounded by cos_x cos_y at contact), L_y(→x) the
     view-independent part plus the view-dependent part interpolated bilinearly on the view
     grid; the light that j hides is a cosine-weighted quadrature of the environment over
     the receiver's directions towards j, each node's ray marched through j's pass-1 depth
     map, and the map's bright sources' sub-points marched alike. The sums run at i's
     own pass-1 samples facing j (pair (j, i)); a receiver projects onto that grid and
     interpolates the ratio of the bracket to the form factor of j's bounding sphere, times
     that form factor at the receiver (``diffuse_at="receivers"``: sums at every receiver);
   - gloss: β A(x) Σ_q w_q h_q [L_j(y_q → x) − L_env(ω_q)] over a quadrature ω_q of the
     receiver's own lobe D F G (V·H)/(N·V) (weights w_q, albedo A), each node ray marched
     through j's pass-1 depth map (hit h_q) and j's radiance at the hit read from a mip
     pyramid of the samples (view-independent part, normal) plus :func:`_specular` evaluated
     there towards x;
   - mirror: χ F(n, θr) times the same along R;
3. ``bounces`` > 1: the samples themselves receive step 2 from the other objects' samples
   before the receivers gather (Jacobi iteration of the radiosity-like exchange).

Only receivers whose tangent plane has some of j's bounding sphere above it get anything; the
sum of both modes' terms over j ≠ i is returned. Empty receiver slots (``object == −1``) get 0.

Units: radiance in the environment's unit (bands) or its basis coefficients (coefficient
mode: the S·L product goes through ``env.product_tensor``, as in ``environment.shade``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp

from ..._runtime.errors import InputError
from ...geometry import GBuffer, ObjectGeometry
from ...lighting import EnvironmentMap, Material
from ._gather import _gather_mode
from ._options import (
    _check_diffuse_at,
    _check_image_shape,
    _check_inputs,
    _check_int,
    _check_mode,
    _output_channels,
)
from ._paper import _paper_mode
from ._pass1 import IRGeometry, prepare_interreflection
from ._schedule import GLOSS_STEP

__all__ = ["interreflection_from", "interreflection"]


def interreflection_from(
    geometry: IRGeometry,
    materials: Sequence[Material],
    env: EnvironmentMap,
    receivers: GBuffer,
    *,
    mode: str | None = None,
    bounces: int = 1,
    diffuse_at: str = "samples",
    image_shape: tuple[int, int] | None = None,
    gloss_step: int = GLOSS_STEP,
    output: Any = None,
    split_sum: tuple[Any, Any] | None = None,
    own_gloss: Any = None,
) -> jax.Array:
    """Shading pass of the interreflection: radiance (N, C) to ADD to
    ``shade(materials[obj], env, normal, view)`` at every receiver (eq. 6).

    Args:
        geometry: from :func:`prepare_interreflection` (same objects, same order).
        materials: one :class:`Material` per object (bands (L,) or K coefficients, matching
            ``env``).
        env: the environment (bands, or basis coefficients with its product tensor).
        receivers: N surface samples (position m, unit normal, unit view, object index; −1 =
            empty slot → zeros).
        mode: "gather", "paper" or "none" (default: the geometry's mode).
        bounces: gather mode: number of light exchanges (1 = the neighbours' environment
            lighting only); ignored by "paper" (eq. 6 has one).
        diffuse_at: gather mode: where the diffuse transfer (form-factor sums) is evaluated:
            "samples" (default: at the receiving objects' own pass-1 samples, interpolated to
            the receivers; with ``image_shape`` corrected by the sums at every 8th row and
            column near a neighbour) or "receivers" (at every receiver; ~10× the cost on a
            frame).
        image_shape: gather mode: (H, W) of the image whose pixels the receivers are
            (``receivers.pixel`` = row·W + column): the gloss/mirror quadrature then runs at
            every ``gloss_step``-th row and column and is interpolated bilinearly between
            (receivers at silhouettes, and those that are not pixels, are evaluated
            themselves), and the diffuse transfer is summed at the receivers themselves at
            every 8th row and column that lies near a neighbour, the difference from the
            samples' interpolated light blended between them over each face. None: at every
            receiver, and the diffuse transfer from the samples alone.
        gloss_step: that subsampling step in pixels (1 = none).
        output: optional (C, D) linear map into the caller's output channels (the frame's
            channels → XYZ or camera RGB): returns ``result @ output``. Gather mode then
            works in the D channels from the receivers on (the samples' net light is
            reflected and mapped before it is interpolated, the senders' atlas before it is
            gathered from), which is cheaper than mapping the (N, C) result when D < C.
        split_sum: paper mode: (:class:`~spectral_fit.lighting.SplitSumMap` of ``env``,
            its :class:`~spectral_fit.lighting.SplitSum` settings): the pass-1 textures'
            gloss by the split sum, as the frame's quality "fast" shades (default: the
            "render" quadrature, ~100× the cost).
        own_gloss: gather mode: (N, C) (or (N, D) with ``output``) the environment's gloss
            and mirror the caller shaded at each receiver: what a neighbour hides of them is
            taken off as the hidden share of this (the lobe nodes' hidden sky over all their
            sky) instead of as the nodes' own reading of the hidden sky (which differs from the
            caller's split-sum reading at grazing angles by more than a dim band's diffuse
            light, and took such bands below zero). None: the nodes' reading.

    Returns:
        (N, C) float32, W·sr⁻¹·m⁻²·nm⁻¹ per band (or coefficients); (N, D) with ``output``.
    """
    mode = geometry.mode if mode is None else _check_mode(mode)
    n = geometry.n_objects
    _check_inputs(n, materials, env, receivers)
    bounces = _check_int(bounces, "bounces", 0, 64)
    _check_diffuse_at(diffuse_at)
    gloss_step = _check_int(gloss_step, "gloss_step", 1, 64)
    image_shape = _check_image_shape(image_shape)
    zeros = jnp.zeros((receivers.object.shape[0], _output_channels(env, output)), jnp.float32)
    if mode == "none" or n < 2 or bounces == 0:
        return zeros
    if mode != geometry.mode:
        raise InputError(f"the geometry was prepared for mode {geometry.mode!r}, not {mode!r}",
                         field="mode")
    if mode == "paper":
        out = _paper_mode(geometry, materials, env, receivers, split_sum)
        return out if output is None else out @ jnp.asarray(output, jnp.float32)
    return _gather_mode(geometry, materials, env, receivers, bounces, diffuse_at,
                        image_shape, gloss_step, output, own_gloss)


def interreflection(
    objects: Sequence[ObjectGeometry],
    materials: Sequence[Material],
    env: EnvironmentMap,
    receivers: GBuffer,
    *,
    mode: str = "gather",
    texture_size: int = 128,
    bounces: int = 1,
    image_shape: tuple[int, int] | None = None,
    gloss_step: int = GLOSS_STEP,
    output: Any = None,
) -> jax.Array:
    """Interreflection radiance (N, C) to ADD to the environment-only shading of every receiver
    sample: :func:`prepare_interreflection` then :func:`interreflection_from`.

    Modes: "paper" — eq. (6) literally (α_paper T_d + γ T_s, pass-1 textures of
    ``texture_size``² from the receiver's centre); "gather" — the neighbours' full radiance
    through the receiver's BRDF with per-fragment parallax, minus the environment they hide,
    ``bounces`` exchanges; "none" — zeros. ``image_shape``, ``gloss_step``,
    ``output``: see :func:`interreflection_from`. See the module docstring.
    """
    _check_mode(mode)
    if mode == "none":
        _check_inputs(len(objects), materials, env, receivers)
        return jnp.zeros((receivers.object.shape[0], _output_channels(env, output)),
                         jnp.float32)
    geom = prepare_interreflection(objects, mode=mode, texture_size=texture_size)
    return interreflection_from(geom, materials, env, receivers, mode=mode, bounces=bounces,
                                image_shape=image_shape, gloss_step=gloss_step, output=output)
