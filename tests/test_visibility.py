"""Self-visibility of rigid meshes (spectral_fit.geometry.self_visibility) against closed forms
and a brute-force float64 ray caster."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.interreflection import ray_mesh
from helpers.shapes import bowl, box, torus, uv_sphere

from spectral_fit._runtime.errors import InputError
from spectral_fit.geometry import (
    is_convex,
    octahedral_directions,
    octahedral_taps,
    octahedral_uv,
    self_visibility,
)

#: small grids keep the shadow maps cheap; the closed forms hold at any resolution
RES, RASTER = 16, 128


def _visible_cosine_fraction(sv, normals):
    """(V,) ∫ visible cos⁺ dω / π: the cosine-weighted share of the hemisphere each vertex sees."""
    cos = np.clip(normals @ sv.directions.T, 0.0, None)
    return (cos * sv.solid_angle * ~sv.hidden).sum(axis=1) / np.pi


def test_octahedral_grid_covers_the_sphere():
    for r in (4, 16, 24):
        d, omega = octahedral_directions(r)
        assert omega.sum() == pytest.approx(4 * np.pi, rel=1e-4)
        assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-6)
        # each texel centre's own (u, v) falls in its own texel
        u, v = octahedral_uv(d.astype(np.float64))
        col = np.floor((u + 1) / 2 * r).astype(int)
        row = np.floor((v + 1) / 2 * r).astype(int)
        assert np.array_equal(row * r + col, np.arange(r * r))
        # the bilinear taps at a texel centre put all the weight on that texel
        import jax.numpy as jnp

        idx, w = octahedral_taps(jnp.asarray(d), r)
        idx, w = np.asarray(idx), np.asarray(w)
        best = idx[np.arange(r * r), np.argmax(w, axis=1)]
        assert np.array_equal(best, np.arange(r * r))
        assert np.allclose(w.max(axis=1), 1.0, atol=1e-4)


def test_convexity():
    assert is_convex(*uv_sphere())
    assert is_convex(*box())
    assert not is_convex(*box(inward=True))
    assert not is_convex(*bowl())
    assert not is_convex(*torus())
    # a convex object hides nothing: every vertex sees its whole hemisphere
    v, t, n = uv_sphere()
    sv = self_visibility(v, t, n, resolution=RES)
    assert sv.convex and not sv.hidden.any()
    frac = _visible_cosine_fraction(sv, n)
    assert np.allclose(frac, 1.0, atol=0.02)  # the grid's own cosine quadrature


def test_inside_a_hemispherical_bowl_half_the_cosine_weighted_sky_is_seen():
    """Inside a sphere, the form factor from any point of the wall to any part of the wall is
    that part's share of the sphere's area (e.g. Siegel & Howell, Thermal Radiation Heat
    Transfer, the sphere-interior configuration): the bowl, half the sphere, takes 1/2 of every
    inside point's cosine-weighted hemisphere, wherever the point is."""
    v, t, n = bowl(0.05, 16, 32)
    sv = self_visibility(v, t, n, resolution=RES, raster_size=RASTER)
    assert not sv.convex
    inside = v[:, 2] < -1e-6  # not the rim
    frac = _visible_cosine_fraction(sv, n)[inside]
    assert abs(np.median(frac) - 0.5) < 0.015
    assert np.max(np.abs(frac - 0.5)) < 0.06  # the grid resolves the rim to ~0.2 rad
    # what it sees of itself is the bowl: every hit lands on a triangle facing the point
    hv, hk = np.nonzero(sv.hidden)
    tri = sv.hit_triangle[hv, hk]
    assert (tri >= 0).all()
    hit = np.einsum("nj,njc->nc", sv.hit_bary[hv, hk], v[t[tri]])
    assert np.allclose(np.linalg.norm(hit, axis=1), 0.05, rtol=0.01)  # on the sphere


def test_inside_a_closed_box_every_direction_is_hidden():
    """A mirror ray (any ray) from inside a closed box meets the box."""
    half = np.array([0.03, 0.02, 0.04])
    v, t, n = box(tuple(half), inward=True, n=5)
    sv = self_visibility(v, t, n, resolution=RES, raster_size=RASTER)
    cos = n @ sv.directions.T
    # directions into the box (the ones a shaded point uses) are all hidden, from the faces'
    # inner vertices and from those on the box's edges and corners alike
    inner = (np.abs(np.abs(v) - half) < 1e-9).sum(axis=1) == 1
    assert inner.sum() == 6 * 9
    assert sv.hidden[inner][cos[inner] > 0.0].all()
    # (from an edge or corner the directions into the box are those entering past every wall
    # the vertex lies on)
    on_wall = np.abs(np.abs(v) - half) < 1e-9  # (V, 3): the walls x, y, z it lies on
    inward = -np.sign(v) * on_wall  # (V, 3) sum of the inward normals' components
    into = np.all((inward[:, None, :] * sv.directions[None]) >= 0.05 * on_wall[:, None, :]
                  * np.abs(inward[:, None, :]), axis=2)
    assert sv.hidden[~inner][into[~inner]].all()


@pytest.mark.parametrize("outward", [True, False])
def test_torus_visibility_matches_brute_force_rays(outward):
    """Hidden or not, against brute-force rays; wound outward (a closed mesh: the hit is the
    first surface along the ray) the hit point is the ray's first hit too."""
    v, t, n = torus(0.05, 0.02, 32, 16)
    if not outward:
        t = t[:, ::-1].copy()
    sv = self_visibility(v, t, n, resolution=RES, raster_size=RASTER)
    rng = np.random.default_rng(3)
    picks = rng.choice(len(v), 48, replace=False)
    agree = total = near = hits = 0
    for i in picks:
        cos = sv.directions @ n[i]
        use = cos > 0.15  # off the grazing directions, where the answer hangs on a hair
        hit, dist, _ = ray_mesh(v[i] + 1e-7 * n[i], sv.directions[use].astype(np.float64),
                                v, n, t)
        agree += int(np.sum(hit == sv.hidden[i, use]))
        total += int(use.sum())
        both = hit & sv.hidden[i, use]
        k = np.nonzero(use)[0][both]
        p = np.einsum("kj,kjc->kc", sv.hit_bary[i, k], v[t[sv.hit_triangle[i, k]]])
        near += int(np.sum(np.abs(np.linalg.norm(p - v[i], axis=1) - dist[both]) < 0.004))
        hits += int(both.sum())
    assert agree / total > 0.97, agree / total
    if outward:
        assert hits > 200 and near / hits > 0.95, (near, hits)
    # the hole's inner rim is the most hidden part: about a third of its cosine-weighted sky
    frac = _visible_cosine_fraction(sv, n)
    inner = np.linalg.norm(v[:, [0, 2]], axis=1) < 0.05 - 0.019
    assert 0.5 < frac[inner].mean() < 0.8
    assert frac[~inner].min() > frac[inner].min()


def test_bad_meshes_name_the_field():
    v, t, n = bowl(0.05, 4, 8)
    with pytest.raises(InputError, match="vertices and normals"):
        self_visibility(v, t, n[:3])
    with pytest.raises(InputError, match="triangle indices"):
        self_visibility(v, t + len(v), n)
    with pytest.raises(InputError, match="non-finite"):
        self_visibility(np.where(v == v[0], np.nan, v), t, n)
    with pytest.raises(InputError, match="resolution"):
        octahedral_directions(1)
