"""Ray casting through the bounding volume hierarchy (spectral_fit.geometry.build_bvh,
closest_hit, occluded) against a brute-force float64 Möller–Trumbore over every triangle
(helpers.interreflection.ray_mesh), on a closed sphere, a self-occluding torus and an open
triangle soup."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers.interreflection import ray_mesh

from spectral_fit._runtime.errors import InputError
from spectral_fit.geometry import build_bvh, closest_hit, occluded


def _torus(big: float = 0.05, small: float = 0.02, nu: int = 24, nv: int = 12):
    """A torus around +Z (genus 1: rays through the hole, rays that meet it twice)."""
    u, v = np.meshgrid(np.arange(nu) * 2 * np.pi / nu, np.arange(nv) * 2 * np.pi / nv,
                       indexing="ij")
    ring = big + small * np.cos(v)
    pos = np.stack([ring * np.cos(u), ring * np.sin(u), small * np.sin(v)], -1).reshape(-1, 3)
    idx = np.arange(nu * nv).reshape(nu, nv)
    a, b = idx, np.roll(idx, -1, 0)
    c, d = np.roll(idx, -1, 1), np.roll(b, -1, 1)
    tris = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3),
                           np.stack([a, d, c], -1).reshape(-1, 3)])
    return pos, tris


def _soup(n: int = 300, seed: int = 5):
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-0.1, 0.1, (n, 1, 3))
    pos = (centres + rng.normal(0.0, 0.02, (n, 3, 3))).reshape(-1, 3)
    return pos, np.arange(3 * n).reshape(n, 3)


def _meshes():
    from spectral_fit.io import uv_sphere

    sph = uv_sphere(0.04, 24, 24)
    return {"sphere": (np.asarray(sph.vertices), np.asarray(sph.triangles)),
            "torus": _torus(), "soup": _soup()}


def _rays(seed: int, n: int = 600):
    """Origins on a 0.3 m shell and inside the objects' region, aimed at random points near the
    middle (many hits, some misses, rays from inside the torus tube and the sphere)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    outside = 0.3 * d / np.linalg.norm(d, axis=1, keepdims=True)
    inside = rng.uniform(-0.06, 0.06, (n, 3))
    origin = np.where((np.arange(n) % 3 == 0)[:, None], inside, outside)
    target = rng.uniform(-0.08, 0.08, (n, 3))
    return origin, target - origin


@pytest.fixture(scope="module")
def trace():
    hits = jax.jit(jax.vmap(lambda b, o, d: closest_hit(b, o, d), in_axes=(None, 0, 0)))
    any_hit = jax.jit(jax.vmap(lambda b, o, d, t: occluded(b, o, d, t),
                               in_axes=(None, 0, 0, 0)))
    return hits, any_hit


@pytest.mark.parametrize("name", ["sphere", "torus", "soup"])
def test_closest_hit_and_occlusion_match_brute_force(name, trace):
    hits, any_hit = trace
    v, tris = _meshes()[name]
    bvh = build_bvh(v, tris)
    for seed in range(2):
        origin, direction = _rays(seed + 10 * len(tris))
        got = hits(bvh, jnp.asarray(origin, jnp.float32), jnp.asarray(direction, jnp.float32))
        ref_hit = np.zeros(len(origin), bool)
        ref_t = np.full(len(origin), np.inf)
        for k in range(len(origin)):  # ray_mesh casts from one origin
            h, t, _ = ray_mesh(origin[k], direction[k][None], v, v * 0 + 1.0, tris)
            ref_hit[k], ref_t[k] = h[0], t[0]
        hit = np.asarray(got.hit)
        # rays grazing an edge may fall either way in float32: a handful at most
        assert (hit != ref_hit).sum() <= max(2, len(hit) // 200), name
        both = hit & ref_hit
        assert both.sum() > len(hit) // 4  # the comparison sees many hits
        np.testing.assert_allclose(np.asarray(got.t)[both], ref_t[both], rtol=1e-4, atol=1e-6)
        assert np.all(np.isinf(np.asarray(got.t)[~hit])) and np.all(
            np.asarray(got.triangle)[~hit] == -1)
        # the hit point from the returned triangle and barycentrics is the point at t
        tri = np.asarray(got.triangle)[both]
        u, w = np.asarray(got.u)[both], np.asarray(got.v)[both]
        p = ((1 - u - w)[:, None] * v[tris[tri, 0]] + u[:, None] * v[tris[tri, 1]]
             + w[:, None] * v[tris[tri, 2]])
        q = origin[both] + np.asarray(got.t)[both][:, None] * direction[both]
        assert np.abs(p - q).max() < 1e-5
        # occluded: true on a segment past the nearest hit, false on one short of it
        sure = both & (ref_t > 1e-3)
        far = any_hit(bvh, jnp.asarray(origin[sure], jnp.float32),
                      jnp.asarray(direction[sure], jnp.float32),
                      jnp.asarray(ref_t[sure] * 1.01, jnp.float32))
        near = any_hit(bvh, jnp.asarray(origin[sure], jnp.float32),
                       jnp.asarray(direction[sure], jnp.float32),
                       jnp.asarray(ref_t[sure] * 0.99, jnp.float32))
        assert np.all(np.asarray(far)) and not np.any(np.asarray(near))


def test_hierarchy_covers_every_triangle_once_within_nested_boxes():
    v, tris = _torus()
    bvh = build_bvh(v, tris, leaf_size=3)
    lo, hi = np.asarray(bvh.lo), np.asarray(bvh.hi)
    first, count, escape = (np.asarray(a) for a in (bvh.first, bvh.count, bvh.escape))
    m = len(lo)
    assert m <= 2 * len(tris) - 1 and escape[0] == m
    seen = []
    for i in range(m):
        if count[i]:
            assert 1 <= count[i] <= 3
            ids = np.asarray(bvh.triangle)[first[i]:first[i] + count[i]]
            seen.extend(ids.tolist())
            corners = v[tris[ids]].reshape(-1, 3)
            assert np.all(corners >= lo[i] - 1e-7) and np.all(corners <= hi[i] + 1e-7)
        else:  # an inner node: its children's boxes lie inside its own
            left = i + 1
            right = escape[left]
            for c in (left, right):
                assert np.all(lo[c] >= lo[i] - 1e-7) and np.all(hi[c] <= hi[i] + 1e-7)
            assert escape[right] == escape[i]
    assert sorted(seen) == list(range(len(tris)))


def test_bad_meshes_name_the_field():
    v, tris = _torus()
    with pytest.raises(InputError, match="vertices"):
        build_bvh(v[:, :2], tris)
    with pytest.raises(InputError, match="vertices"):
        build_bvh(np.where(np.arange(len(v))[:, None] == 3, np.nan, v), tris)
    with pytest.raises(InputError, match="triangles"):
        build_bvh(v, tris + len(v))
    with pytest.raises(InputError, match="triangles"):
        build_bvh(v, tris[:0])
    with pytest.raises(InputError, match="leaf_size"):
        build_bvh(v, tris, leaf_size=9)
