"""Material-independent radiance caches for fitting (eqs. 5 and 6).

Geometry, poses and the environment are fixed while materials are fitted, so everything that
does not depend on (α, β, χ, μ, n) is computed once, here, and the model for any parameters is
a weighted sum of cached radiances with weights built from the reflection model's own F, D, G
(:mod:`spectral_fit.lighting`).

Gloss (eq. 5's β term) at a shading point with normal N and view V:

    ∫ L(ω) F(n, θd) D(μ, θh) G / (4 cosθr) dω  =  ∫ D(μ, θh) F(n, V·H) G (V·H)/(N·V) L(l(H)) dω_H

(dω = 4 (V·H) dω_H, l(H) = 2 (V·H) H − V). The half vectors H are sampled on a FIXED,
μ-independent set of nodes: rings around N at θh_j = θ0 q^j (geometric spacing, the trapezoid
rule in log θh, which integrates a Gaussian lobe of any width μ >> θ0 to high accuracy) with the
geometric tail below θ0 folded into the first ring, and on each ring M azimuths from V's
azimuth: equally spaced on fully visible rings, Gauss–Legendre over the visible arc
(N·l(H) > 0) otherwise. Each node's radiance L_k is looked up ONCE from the environment's
prefiltered residual map (:class:`~spectral_fit.lighting.EnvironmentMap`, its own principal
spectra) at a prefilter std matched to the node's footprint in reflected directions (limited
near the horizon); the map's bright source texels are kept as explicit directions with their
exact flux (by default 16 equal-weight points of each one's footprint in the bilinear map;
``CacheOptions.sources="gauss"`` takes the product Gauss points the environment module's exact
gloss sums). Then

    gloss(μ, n) = Σ_k D(μ, θh_k) F(n, (V·H)_k) G_k c_k L_k + Σ_s D F G /(4 N·V) Φ_s,

c_k = Δω_H,k (V·H)_k/(N·V): smooth in μ and n, so its derivatives are exact autodiff.

Interreflection (eq. 6 in the "gather" reading): every node direction, the mirror
direction and every environment texel of the irradiance sum is ray-cast once against the OTHER
objects (spheres, analytically). Directions that hit a neighbour take the neighbour's outgoing
radiance instead of the environment: for each reading and neighbour a fixed set of probes
(directions from the spot's centre spread over the neighbour's silhouette) holds the hit point,
its normal and the direction back to the spot, with their own gloss nodes (the samples'
layout, stored after the samples' in one :class:`GlossNodes`, so one evaluation of the node
weights serves samples, probes and the sample nodes that hit a neighbour),
visible-environment irradiance and mirror radiance, so the neighbour's radiance
α' S' E'/π + β' gloss'(μ', n') + χ' F L' is a function of the neighbour's parameters and its
derivative is in the Jacobian. A hit takes the radiance of the nearest probe (one bounce: the
neighbour is lit by the environment it sees, the receiver's own light is not fed back).

Shapes: P shading points, J rings, M azimuths, S source sub-points, r environment channels
(principal spectra), L bands, Q probes.

This module holds the caches' options and pytrees (:class:`CacheOptions`, :class:`Sphere`,
:class:`GlossNodes`, :class:`RadianceCache`); the gloss nodes are built by
:func:`~spectral_fit.fitting.build_gloss_nodes`, the whole cache by
:func:`~spectral_fit.fitting.build_radiance_cache`, and the model for given parameters is
evaluated by :func:`~spectral_fit.fitting.cached_radiance` and
:func:`~spectral_fit.fitting.field_radiance`.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "CacheOptions",
    "FieldAverage",
    "GlossNodes",
    "RadianceCache",
    "Sphere",
]


@dataclasses.dataclass(frozen=True)
class CacheOptions:
    """Node layout of the caches (static).

    Attributes:
        theta0: smallest ring's θh (radians); the lobe mass inside is folded into it.
        ring_ratio: q, ratio of consecutive ring angles (trapezoid step log q in log θh).
        azimuths: M, nodes per ring.
        prefilter: a node's prefilter std = this × √(its solid angle in reflected directions).
        horizon_ratio: a node's prefilter std is at most this × its elevation above the
            surface's horizon (no light from behind the surface is blurred in).
        subsamples: s; a node's radiance is the mean of s × s sub-samples over its cell
            (1: one prefiltered lookup per node). 3 lowers the median gloss error at wide
            lobes by ~40 % (docs/fitting.md) for 9× the lookups in the preparation.
        probes: probes per reading and neighbour (interreflection); their gloss nodes have
            the samples' layout (one array, one evaluation of the node weights).
        sources: each bright source texel of the map as 16 equal-weight points of its
            footprint in the bilinear map ("tent", default) or the environment module's
            product Gauss rule over that footprint ("gauss", 64 points, what its exact gloss
            sums; the bundled session's red β then comes out at +2.8 % instead of +1.8 %).
        visibility: R of the octahedral direction grid (R² directions) in which mesh objects
            are tested against the samples and the probes (the frame's default, ~0.15 rad
            apart); the probes on meshes are the first hits of the grid's directions from
            each spot's most central sample.
        probe_bounces: Jacobi steps of the probes' light among themselves (diffuse: what a
            probe's hidden directions meet is the nearest probe of its reading there): the
            second and later bounces inside a concave object or among three or more.
    """

    theta0: float = 0.003
    ring_ratio: float = 1.35
    azimuths: int = 16
    prefilter: float = 0.35
    horizon_ratio: float = 0.2
    subsamples: int = 1
    probes: int = 64
    sources: str = "tent"
    visibility: int = 24
    probe_bounces: int = 4


@dataclasses.dataclass(frozen=True)
class Sphere:
    """An occluder: object index, world centre (3,) and radius (metres)."""

    object: int
    centre: np.ndarray
    radius: float


class FieldAverage(eqx.Module):
    """The readings' field means as weights of their samples (a pytree): every sample belongs
    to at most one reading (a spot's field, or one channel of a photograph's bin), so the mean
    of reading b is Σ_{p: row_p = b} weight_p x_p (a segment sum; the dense (B, P) matrix
    would hold P numbers per row where a photograph has thousands of rows).

    Attributes:
        row: (P,) int32 the reading of each sample (any valid row where its weight is 0).
        weight: (P,) its weight in that reading's mean (0: in none).
        rows: static B, the number of readings.
    """

    row: jax.Array
    weight: jax.Array
    rows: int = eqx.field(static=True)

    @property
    def shape(self) -> tuple[int, int]:
        """(B, P), the shape of the equivalent dense matrix."""
        return self.rows, int(self.weight.shape[0])

    def apply(self, x: jax.Array) -> jax.Array:
        """(B, ...) field means of per-sample values ``x`` (P, ...) (JAX)."""
        w = self.weight.reshape((-1,) + (1,) * (x.ndim - 1))
        return jax.ops.segment_sum(w * x, self.row, num_segments=self.rows)

    def apply_np(self, x: np.ndarray) -> np.ndarray:
        """As :meth:`apply`, in NumPy float64."""
        x = np.asarray(x, np.float64)
        out = np.zeros((self.rows,) + x.shape[1:])
        w = np.asarray(self.weight, np.float64).reshape((-1,) + (1,) * (x.ndim - 1))
        np.add.at(out, np.asarray(self.row), w * x)
        return out

    def dense(self) -> np.ndarray:
        """The (B, P) averaging matrix (NumPy; for small problems and checks)."""
        out = np.zeros(self.shape)
        out[np.asarray(self.row), np.arange(self.shape[1])] = np.asarray(self.weight)
        return out


class GlossNodes(eqx.Module):
    """Gloss quadrature nodes of P shading points with their cached radiance (a pytree).

    Attributes:
        cos_h: (J,) cosθh of the rings.
        vh, nl: (P, J, M) V·H and N·l(H) per node.
        nv: (P,) N·V.
        base: (P, J, M) Δω_H (V·H)/(N·V) (0 for invisible nodes).
        radiance: (P, J, M, r) environment radiance at l(H) in the map's principal spectra
            (0 where a neighbour hides the environment).
        src_nh, src_vh, src_nl: (P, S) cosines of the source sub-points' half vectors.
        src_base: (P, S) 1/(4 N·V), 0 where the source is below the horizon or hidden.
        src_flux: (S, r) excess flux of the source sub-points.
    """

    cos_h: jax.Array
    vh: jax.Array
    nl: jax.Array
    nv: jax.Array
    base: jax.Array
    radiance: jax.Array
    src_nh: jax.Array
    src_vh: jax.Array
    src_nl: jax.Array
    src_base: jax.Array
    src_flux: jax.Array


class RadianceCache(eqx.Module):
    """Everything material-independent of the fit's field samples (a pytree).

    Attributes:
        nodes: :class:`GlossNodes` of the P samples followed by the Q probes (one node
            layout; ``sample_nodes`` and ``probe_nodes`` are the two parts).
        irradiance: (P, L) E(λ, N) of the visible environment (exact texel sum, texels hidden
            by a neighbour left out).
        mirror: (P, L) environment radiance along R (0 if a neighbour hides it).
        spectral_basis: (r, L) the map's principal spectra.
        probe_object: (Q,) object of each probe (Q may be 0).
        probe_irradiance, probe_mirror: (Q, L) as ``irradiance``/``mirror`` at the probes.
        mirror_probe: (P,) probe seen along R, −1 for none.
        diffuse_probe: (P, Q) cosine-weighted solid angle of each probe's share of the
            hemisphere hidden by neighbours (irradiance from neighbours = this @ radiance).
        hit_sample, hit_probe: (H,) sample and probe of every gloss node that hits a neighbour.
        hit_node: (H,) that node's flat index in the sample's J·M nodes.
        average: :class:`FieldAverage`, the readings' field means (weight 0 for samples on no
            object or facing away).
        probe_group: (Q,) the reading each probe belongs to.
        probe_diffuse: (O, Q) ``average @ diffuse_probe`` per receiving object, summed over
            each probe's reading (every reading only sees its own probes).
        hit_average: (H,) the averaging weight of each hit's sample (the gloss hits are
            summed straight into field means).
        transfer_row, transfer_col, transfer_weight: (E,) probe → probe diffuse transfer:
            probe ``row`` receives irradiance ``weight`` × the radiance of probe ``col``
            (cos·Δω of its directions that meet the object there).
        probe_bounces: static, Jacobi steps of that transfer (0: the probes are lit by the
            environment alone).
    """

    nodes: GlossNodes
    irradiance: jax.Array
    mirror: jax.Array
    spectral_basis: jax.Array
    probe_object: jax.Array
    probe_irradiance: jax.Array
    probe_mirror: jax.Array
    mirror_probe: jax.Array
    diffuse_probe: jax.Array
    hit_sample: jax.Array
    hit_probe: jax.Array
    hit_node: jax.Array
    average: FieldAverage
    probe_group: jax.Array
    probe_diffuse: jax.Array
    hit_average: jax.Array
    transfer_row: jax.Array
    transfer_col: jax.Array
    transfer_weight: jax.Array
    probe_bounces: int = eqx.field(static=True, default=0)

    @property
    def n_probes(self) -> int:
        return int(self.probe_object.shape[0])

    @property
    def sample_nodes(self) -> GlossNodes:
        """:class:`GlossNodes` of the P samples (the first P points of ``nodes``)."""
        return _node_rows(self.nodes, 0, int(self.irradiance.shape[0]))

    @property
    def probe_nodes(self) -> GlossNodes:
        """:class:`GlossNodes` of the Q probes (hit point, normal, direction back)."""
        P = int(self.irradiance.shape[0])
        return _node_rows(self.nodes, P, P + self.n_probes)


_SHARED_NODE_FIELDS = ("cos_h", "src_flux")


def _node_rows(nodes: GlossNodes, start: int, stop: int) -> GlossNodes:
    """The points start:stop of ``nodes`` (the ring angles and source fluxes are shared)."""
    return GlossNodes(**{f.name: getattr(nodes, f.name) if f.name in _SHARED_NODE_FIELDS
                         else getattr(nodes, f.name)[start:stop]
                         for f in dataclasses.fields(nodes)})


def _concat_nodes(a: GlossNodes, b: GlossNodes) -> GlossNodes:
    """The points of ``a`` followed by those of ``b`` (same layout, same map)."""
    return GlossNodes(**{f.name: getattr(a, f.name) if f.name in _SHARED_NODE_FIELDS
                         else jnp.concatenate([getattr(a, f.name), getattr(b, f.name)])
                         for f in dataclasses.fields(a)})
