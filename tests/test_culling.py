"""Cluster culling before the camera raster (spectral_fit.geometry): the raster of the kept
clusters' triangles equals the raster of every triangle, bit for bit, over poses that stress the
orientation identity (eye near the surface, inside an object, objects behind the eye or across
the near plane, mirrored models, off-centre and flipped projections, non-convex meshes)."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from spectral_fit import geometry as raster
from spectral_fit.geometry import (
    CLUSTER_SIZE,
    MARGIN,
    build_clusters,
    cluster_rows,
    count_clusters,
    grown_clusters,
    intrinsics_to_projection,
    look_at,
    perspective,
    spatial_order,
    visible_clusters,
    worst_direction_count,
)
from spectral_fit.io import Mesh, concat_meshes, icosphere, is_closed_outward, uv_sphere

SHAPE = (48, 64)


def _bumpy(radius: float, seed: int) -> Mesh:
    """A closed, outward-wound, non-convex mesh: a uv sphere with radial bumps."""
    m = uv_sphere(radius, 48, 64)
    v = np.asarray(m.vertices, np.float64)
    d = v / np.linalg.norm(v, axis=1, keepdims=True)
    rng = np.random.default_rng(seed)
    k = rng.normal(size=(6, 3))
    bump = 1.0 + 0.35 * np.sum(np.sin(3.0 * d @ k.T), axis=1) / 6.0
    return dataclasses.replace(m, vertices=(v * bump[:, None]).astype(np.float32))


def _scene():
    meshes = [uv_sphere(0.5, 40, 56), icosphere(0.4, 4), _bumpy(0.45, 1)]
    for m in meshes:
        assert is_closed_outward(m.vertices, m.triangles)
    both, offs = concat_meshes(meshes)
    slices = [(int(a), int(b)) for a, b in zip(offs[:-1], offs[1:], strict=True)]
    nv = np.cumsum([0] + [len(m.vertices) for m in meshes])
    vobj = np.repeat(np.arange(len(meshes)), np.diff(nv))
    v = np.asarray(both.vertices, np.float64)
    tris = np.asarray(both.triangles)[spatial_order(v, both.triangles, slices)]
    return v, tris, slices, vobj


def _rot(axis, angle):
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def _model(rot, pos, scale=(1.0, 1.0, 1.0)):
    m = np.eye(4)
    m[:3, :3] = rot @ np.diag(scale)
    m[:3, 3] = pos
    return m


def _poses():
    """(name, model (3, 4, 4), view, projection)."""
    rng = np.random.default_rng(7)
    persp = np.asarray(perspective(70.0, SHAPE[1] / SHAPE[0], 0.05, 50.0), np.float64)
    k = np.array([[60.0, 0.0, 20.0], [0.0, 55.0, 30.0], [0.0, 0.0, 1.0]])  # off-centre
    intr = np.asarray(intrinsics_to_projection(k, SHAPE[1], SHAPE[0], 0.05, 50.0), np.float64)
    flipped = persp @ np.diag([-1.0, 1.0, 1.0, 1.0])  # a mirror-image camera
    out = []
    for n in range(6):
        models = np.stack([_model(_rot(rng.normal(size=3), rng.uniform(0, 6.3)), p)
                           for p in ((-1.2, 0, 0), (0.2, 0.1, 0.3), (1.3, -0.1, -0.2))])
        eye = rng.normal(size=3)
        eye = eye / np.linalg.norm(eye) * (2.5 + 2 * n)
        out.append((f"around{n}", models, np.asarray(look_at(eye, np.zeros(3)), np.float64),
                    persp))
    base = np.stack([_model(np.eye(3), p) for p in ((-1.2, 0, 0), (0.2, 0.1, 0.3),
                                                    (1.3, -0.1, -0.2))])
    close = np.asarray(look_at((0.2, 0.1, 1.0), (0.2, 0.1, 0.3)), np.float64)  # 0.2 off
    out.append(("close", base, close, persp))
    inside = np.asarray(look_at((0.2, 0.1, 0.3), (1.3, 0.0, 0.0)), np.float64)
    out.append(("eye_inside_an_object", base, inside, persp))
    across = np.asarray(look_at((0.0, 0.0, 0.2), (0.0, 0.0, -5.0)), np.float64)
    out.append(("objects_behind_and_across_the_near_plane", base, across, persp))
    mirrored = base.copy()
    mirrored[1] = _model(np.eye(3), (0.2, 0.1, 0.3), (-1.0, 1.0, 1.0))
    mirrored[2] = _model(_rot((1, 1, 0), 0.7), (1.3, -0.1, -0.2), (1.5, 0.7, 1.0))
    side = np.asarray(look_at((0.5, 1.0, 4.0), (0.0, 0.0, 0.0)), np.float64)
    out.append(("mirrored_and_scaled_models", mirrored, side, persp))
    out.append(("intrinsics_off_centre", base, side, intr))
    out.append(("mirror_image_projection", base, side, flipped))
    return out


def _clip(v, vobj, models, view, proj):
    world = np.einsum("vij,vj->vi", models[vobj][:, :3, :3], v) + models[vobj][:, :3, 3]
    return ((world @ view[:3, :3].T + view[:3, 3]) @ proj[:, :3].T + proj[:, 3]).astype(
        np.float32)


def _row_ids(cl, slices):
    """(C + 1, S) original triangle id of every cluster row (−1: padding)."""
    s = cl.size
    ids = np.full((cl.num_clusters + 1, s), -1, np.int64)
    for (ta, tb), (ca, cb) in zip(slices, cl.cluster_slices, strict=True):
        flat = np.full((cb - ca) * s, -1, np.int64)
        flat[:tb - ta] = np.arange(ta, tb)
        ids[ca:cb] = flat.reshape(cb - ca, s)
    return ids


# slow: the default tier checks the kept clusters end to end (frames with and without them,
# below: identical for three object states)
@pytest.mark.slow
@pytest.mark.parametrize("cull", ["back", "front"])
def test_kept_clusters_raster_equals_the_full_raster(cull):
    v, tris, slices, vobj = _scene()
    cl = build_clusters(v, tris, slices)
    ids = _row_ids(cl, slices)
    cfg = raster.RasterConfig(raster.TILE_SIZES, (4096, 4096, 256), 64)
    n_culled = []
    for name, models, view, proj in _poses():
        clip = _clip(v, vobj, models, view, proj)
        full = raster.rasterize(clip, tris, SHAPE, cull=cull, config=cfg)
        index, count = visible_clusters(cl, jnp.asarray(models, jnp.float32),
                                        jnp.asarray(view, jnp.float32),
                                        jnp.asarray(proj, jnp.float32),
                                        jnp.ones((3,), bool), cull=cull)
        assert int(count) <= cl.capacity
        rows, obj = cluster_rows(cl, index)
        part = raster.rasterize(clip, rows, SHAPE, cull=cull, config=cfg)
        tid = np.asarray(part.tri_id)
        mapped = np.where(tid >= 0, ids[np.asarray(index)].reshape(-1)[np.maximum(tid, 0)], -1)
        np.testing.assert_array_equal(mapped, np.asarray(full.tri_id), err_msg=name)
        np.testing.assert_array_equal(np.asarray(part.bary), np.asarray(full.bary),
                                      err_msg=name)
        np.testing.assert_array_equal(np.asarray(part.depth), np.asarray(full.depth),
                                      err_msg=name)
        # the rows' objects
        o = np.asarray(obj)[np.maximum(tid, 0)]
        np.testing.assert_array_equal(np.where(tid >= 0, o, -1),
                                      np.where(tid >= 0, vobj[tris[np.maximum(
                                          np.asarray(full.tri_id), 0), 0]], -1))
        # NumPy's count (capacity planning) is the traced one
        assert count_clusters(cl, models, view, proj, cull=cull) == int(count), name
        n_culled.append((name, cl.num_clusters - int(count)))
    culled = dict(n_culled)
    # the test has teeth: clusters are dropped in the ordinary views, and from inside an
    # object (every one of its triangles faces away) that object's clusters go too
    assert all(culled[f"around{n}"] > 0.25 * cl.num_clusters for n in range(6)), culled
    assert culled["eye_inside_an_object"] > 0


def test_grazing_triangles_keep_their_cluster():
    """A triangle seen almost edge-on (its plane 0.1 % of the distance from the eye: the
    raster may still draw it) keeps its cluster; one well behind its plane does not."""
    q = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # normal +z
    cl = build_clusters(q, np.array([[0, 1, 2]]), [(0, 1)])
    proj = jnp.asarray(perspective(60.0, 1.0, 0.01, 100.0))
    eye_m = jnp.eye(4)[None]

    def kept(eye):
        view = look_at(jnp.asarray(eye, jnp.float32), jnp.asarray((0.3, 0.3, 0.0)))
        return int(visible_clusters(cl, eye_m, view, proj, jnp.ones((1,), bool))[1])

    d = 10.0
    assert kept((0.3, 0.3 + d, 0.001 * d)) == 1  # in front, grazing
    assert kept((0.3, 0.3 + d, -0.001 * d)) == 1  # behind, grazing: within the margin
    assert kept((0.3, 0.3 + d, -3 * MARGIN * (d + 1.0))) == 0  # clearly behind
    assert kept((0.3, 0.3, 5.0)) == 1


def test_hidden_objects_and_padding():
    v, tris, slices, vobj = _scene()
    cl = build_clusters(v, tris, slices)
    # every object's run padded to whole clusters; the padding never kept
    for (ta, tb), (ca, cb) in zip(slices, cl.cluster_slices, strict=True):
        assert cb - ca == -(-(tb - ta) // CLUSTER_SIZE)
    name, models, view, proj = _poses()[0]
    args = (jnp.asarray(models, jnp.float32), jnp.asarray(view, jnp.float32),
            jnp.asarray(proj, jnp.float32))
    idx_all, n_all = visible_clusters(cl, *args, jnp.ones((3,), bool))
    idx_one, n_one = visible_clusters(cl, *args, jnp.asarray([True, False, True]))
    kept_all = set(np.asarray(idx_all)[:int(n_all)].tolist())
    kept_one = set(np.asarray(idx_one)[:int(n_one)].tolist())
    ca, cb = cl.cluster_slices[1]
    assert kept_one == {c for c in kept_all if not ca <= c < cb}
    # unused slots read the degenerate cluster
    assert np.all(np.asarray(idx_one)[int(n_one):] == cl.num_clusters)
    rows, obj = cluster_rows(cl, idx_one)
    dead = np.asarray(rows).reshape(-1, CLUSTER_SIZE, 3)[int(n_one):]
    assert np.all(dead == 0) and np.all(np.asarray(obj).reshape(-1, CLUSTER_SIZE)[
        int(n_one):] == -1)


def test_overflowing_list_is_reported_and_grown():
    v, tris, slices, vobj = _scene()
    cl = dataclasses.replace(build_clusters(v, tris, slices), capacity=8)
    name, models, view, proj = _poses()[0]
    _, count = visible_clusters(cl, jnp.asarray(models, jnp.float32),
                                jnp.asarray(view, jnp.float32), jnp.asarray(proj, jnp.float32),
                                jnp.ones((3,), bool))
    assert int(count) > cl.capacity
    grown = grown_clusters(cl, int(count), 1.25)
    assert grown.capacity >= 1.25 * int(count) or grown.capacity == cl.num_clusters
    assert grown_clusters(grown, int(count), 1.25) is grown  # fits: unchanged
    # ahead of an overflow (80 % full)
    assert grown_clusters(grown, int(0.9 * grown.capacity), 1.5, full=0.8).capacity > \
        grown.capacity or grown.capacity == cl.num_clusters


def test_spatial_order_and_the_directional_bound():
    v, tris, slices, vobj = _scene()
    perm = spatial_order(v, tris, slices)
    assert sorted(perm.tolist()) == list(range(len(tris)))
    for ta, tb in slices:  # each object's triangles stay in its range
        assert perm[ta:tb].min() == ta and perm[ta:tb].max() == tb - 1
    cl = build_clusters(v, tris, slices)
    worst = worst_direction_count(cl)
    # far eyes (nearly orthographic views of the objects) never keep more than the bound
    rng = np.random.default_rng(3)
    proj = np.asarray(perspective(1.0, 1.0, 1.0, 1e6), np.float64)
    models = np.stack([_model(_rot(rng.normal(size=3), rng.uniform(0, 6.3)), p)
                       for p in ((-1.2, 0, 0), (0.2, 0.1, 0.3), (1.3, -0.1, -0.2))])
    counts = []
    for _ in range(20):
        d = rng.normal(size=3)
        view = np.asarray(look_at(1e4 * d / np.linalg.norm(d), np.zeros(3)), np.float64)
        counts.append(count_clusters(cl, models, view, proj))
    assert max(counts) <= worst < cl.num_clusters
    # spatial order pays: far fewer clusters straddle the silhouette than in mesh order
    plain = build_clusters(v, np.asarray(concat_meshes(
        [uv_sphere(0.5, 40, 56), icosphere(0.4, 4), _bumpy(0.45, 1)])[0].triangles), slices)
    assert worst_direction_count(plain) > worst


def test_frames_with_and_without_clusters_are_identical():
    from spectral_fit.bench.cases.frame import benchmark_scene
    from spectral_fit.rendering import prepare, render_frame

    prep = prepare(benchmark_scene(z=-0.275), mode="none", size=(96, 64))
    cl = prep.buffers.clusters
    assert cl is not None and prep.camera.cull == "back"
    assert cl.capacity < cl.num_clusters
    plain = prep.with_buffers(clusters=None)
    model = np.asarray(prep.model).copy()
    model[0, :3, 3] += (0.01, 0.005, 0.0)
    for kw in ({}, {"model": model}, {"visible": np.array([True, False])}):
        a = render_frame(prep, **kw)
        b = render_frame(plain, **kw)
        for f in ("xyz", "rgb", "mask", "object_id"):
            np.testing.assert_array_equal(np.asarray(getattr(a, f)),
                                          np.asarray(getattr(b, f)), err_msg=f"{f} {kw}")
        assert not bool(a.stats["raster_overflow"])
