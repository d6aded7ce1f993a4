"""Rasteriser tests against independent references: a float64 brute-force rasteriser
(tests/helpers/raster_reference.py), analytic silhouettes and ray–surface intersections, finite
differences (float64, in a subprocess) and compilation counts."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import ROOT, subprocess_env
from helpers.raster import (
    MID,
    SMALL,
    camera,
    clip_of,
    count_compilations,
    coverage_sets,
    facing,
    pixel_rays,
    rasterize_padded,
    soup,
    two_spheres,
)
from helpers.raster_reference import reference_raster
from matplotlib.path import Path as MplPath
from scipy.spatial import ConvexHull

from spectral_fit import geometry as raster
from spectral_fit._runtime.errors import InputError
from spectral_fit.geometry import perspective_camera, project
from spectral_fit.io import concat_meshes, icosphere, rotate, translate, uv_sphere

# ----------------------------------------------------------------------------- scenes


def assert_matches_reference(r, clip, tris, shape, cull="none"):
    ref_id, ref_bary, ref_depth = reference_raster(clip, tris, shape, cull)
    tri_id = np.asarray(r.tri_id)
    np.testing.assert_array_equal(tri_id, ref_id)
    hit = ref_id >= 0
    # float32: nearly edge-on triangles lose a few more digits than the typical pixel
    err_b = np.abs(np.asarray(r.bary)[hit] - ref_bary[hit])
    err_d = np.abs(np.asarray(r.depth)[hit] - ref_depth[hit])
    assert err_b.max() < 5e-4 and np.quantile(err_b, 0.99) < 1e-5, err_b.max()
    assert err_d.max() < 5e-4 and np.quantile(err_d, 0.99) < 1e-5, err_d.max()
    assert np.all(np.asarray(r.depth)[~hit] == 1.0)
    assert np.all(np.asarray(r.bary)[~hit] == 0.0)
    return int(hit.sum())


def sphere_scene(centres, radii, *, subdivisions=3):
    """Icospheres (object k = triangle ids offsets[k]..offsets[k+1]) and their world vertices."""
    ms = [icosphere(r, subdivisions).transformed(translate(c)) for c, r in
          zip(centres, radii, strict=True)]
    both, offsets = concat_meshes(ms)
    return both, offsets


def ray_sphere_t(d, c, r):
    """Nearest and farthest ray parameters t (rays o = 0, directions d (..., 3)) hitting the
    sphere (c, r); inf where missed."""
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    b = d @ np.asarray(c, np.float64)
    disc = b * b - (np.dot(c, c) - r * r)
    s = np.sqrt(np.maximum(disc, 0))
    near = np.where(disc > 0, b - s, np.inf)
    far = np.where(disc > 0, b + s, np.inf)
    return near, far, disc


# ----------------------------------------------------------------------------- coverage


@pytest.mark.parametrize("seed", range(6))
def test_random_soups_match_float64_reference_exactly(seed):
    clip, tris = soup(seed)
    assert np.any(clip[:, 3] < 0), "the soup should cross the eye plane"
    r = rasterize_padded(clip, tris, SMALL)
    n = assert_matches_reference(r, clip, tris, SMALL)
    assert n > 50


@pytest.mark.parametrize("cull", ["back", "front"])
def test_culling_matches_reference(cull):
    clip, tris = soup(11)
    r = rasterize_padded(clip, tris, SMALL, cull=cull)
    assert_matches_reference(r, clip, tris, SMALL, cull)
    face = facing(clip, tris)
    ids = np.asarray(r.tri_id)
    drawn = ids[ids >= 0]
    assert np.all(face[drawn] == (1 if cull == "back" else -1))


def _grid_mesh(seed, shape):
    """A grid of vertices exactly at pixel centres (dyadic clip coordinates, w ∈ {0.5, 1, 2}),
    quads split along random diagonals: horizontal and vertical edges run through pixel
    centres, so the tie rule decides many pixels."""
    rng = np.random.default_rng(seed)
    h, w = shape
    xs = np.arange(2.5, w - 2, 3.0)  # pixel centres, every third column
    ys = np.arange(1.5, h - 1, 3.0)
    gx, gy = np.meshgrid(xs, ys)
    ww = rng.choice([0.5, 1.0, 2.0], gx.shape)
    z = rng.uniform(-0.5, 0.5, gx.shape)
    clip = np.stack([(2 * gx / w - 1) * ww, (1 - 2 * gy / h) * ww, z * ww, ww], -1)
    clip = clip.reshape(-1, 4).astype(np.float32)
    ny, nx = gx.shape
    tris = []
    for i in range(ny - 1):
        for j in range(nx - 1):
            a, b, c, d = i * nx + j, i * nx + j + 1, (i + 1) * nx + j, (i + 1) * nx + j + 1
            if rng.random() < 0.5:
                tris += [(a, c, b), (b, c, d)]
            else:
                tris += [(a, c, d), (a, d, b)]
    tris = np.asarray(tris)
    lo = np.array([xs[0], ys[0]])
    hi = np.array([xs[-1], ys[-1]])
    return clip, tris, lo, hi


@pytest.mark.parametrize("seed", [0, 1])
def test_shared_edges_through_pixel_centres_no_cracks_no_double_cover(seed):
    clip, tris, lo, hi = _grid_mesh(seed, SMALL)
    cov = coverage_sets(clip, tris, SMALL)
    count = cov.sum(0)
    h, w = SMALL
    py, px = np.mgrid[0:h, 0:w] + 0.5
    strictly_inside = (px > lo[0]) & (px < hi[0]) & (py > lo[1]) & (py < hi[1])
    outside = (px < lo[0]) | (px > hi[0]) | (py < lo[1]) | (py > hi[1])
    assert count.max() == 1  # never two triangles at one pixel centre (flat, non-overlapping)
    assert np.all(count[strictly_inside] == 1)  # no cracks, even on edges and vertices
    assert np.all(count[outside] == 0)
    r = rasterize_padded(clip, tris, SMALL)
    np.testing.assert_array_equal(np.asarray(r.tri_id) >= 0, count == 1)
    assert_matches_reference(r, clip, tris, SMALL)


def test_fan_around_a_vertex_at_a_pixel_centre():
    """Twelve triangles around a vertex exactly at a pixel centre, with edges along +x, −x and
    +y through it (dyadic coordinates: every edge function is exact in float32): the centre
    belongs to exactly the triangle containing centre + (ε, ε²)."""
    h, w = SMALL
    centre = np.array([31.5, 15.5])
    offs = np.array([(7, 0), (6, 4), (3, 6), (0, 7), (-4, 6), (-6, 3), (-7, 0), (-6, -3),
                     (-2, -7), (2, -6), (5, -5), (7, -2)], float)
    offs = offs[np.argsort(np.arctan2(offs[:, 1], offs[:, 0]))]
    pix = np.concatenate([centre[None], centre + offs])
    k = len(offs)
    ndc = np.stack([2 * pix[:, 0] / w - 1, 1 - 2 * pix[:, 1] / h], -1)
    clip = np.concatenate([ndc, np.zeros((k + 1, 1)), np.ones((k + 1, 1))], 1)
    tris = np.stack([np.zeros(k, int), 1 + np.arange(k), 1 + (np.arange(k) + 1) % k], -1)
    cov = coverage_sets(clip, tris, SMALL)
    assert cov.sum(0).max() == 1
    iy, ix = int(centre[1]), int(centre[0])
    owner = np.flatnonzero(cov[:, iy, ix])
    # pixel y points down: the triangle spanning the directions (7, 0) → (6, 4) holds (1, ε)
    want = [j for j in range(k) if tuple(offs[j]) == (7.0, 0.0)]
    np.testing.assert_array_equal(owner, want)
    r = rasterize_padded(clip, tris, SMALL)
    assert_matches_reference(r, clip, tris, SMALL)


# the icosphere (no poles, triangles of one size) in the default tier, the UV sphere in slow
@pytest.mark.parametrize("kind", ["ico", pytest.param("uv", marks=pytest.mark.slow)])
def test_closed_mesh_one_front_and_one_back_face_per_pixel(kind):
    rng = np.random.default_rng(3 if kind == "ico" else 4)
    m = icosphere(0.5, 3) if kind == "ico" else uv_sphere(0.5, 30, 40)
    model = translate((rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2), -1.6)) @ rotate(
        rng.normal(size=3), rng.uniform(0, np.pi))
    cam = camera(MID)
    clip = clip_of(cam, m.vertices, model)
    tris = m.triangles
    cov = coverage_sets(clip, tris, MID)
    face = facing(clip, tris)
    front = cov[face > 0].sum(0)
    back = cov[face < 0].sum(0)
    silhouette = (front + back) > 0
    assert silhouette.sum() > 800
    assert np.all(front[silhouette] == 1)
    assert np.all(back[silhouette] == 1)
    # the silhouette of a convex mesh is the convex hull of its projected vertices
    h, w = MID
    pix = np.stack([(clip[:, 0] / clip[:, 3] + 1) / 2 * w, (1 - clip[:, 1] / clip[:, 3]) / 2 * h],
                   -1).astype(np.float64)
    hull = MplPath(pix[ConvexHull(pix).vertices])
    py, px = np.mgrid[0:h, 0:w] + 0.5
    centres = np.stack([px.ravel(), py.ravel()], -1)
    inside = hull.contains_points(centres, radius=-1e-3).reshape(h, w)
    inside2 = hull.contains_points(centres, radius=1e-3).reshape(h, w)
    lo, hi = (inside, inside2) if inside.sum() <= inside2.sum() else (inside2, inside)
    assert np.all(silhouette[lo]) and not np.any(silhouette & ~hi)
    # the public entry points agree with the counts
    for cull, want in (("none", silhouette), ("back", front == 1), ("front", back == 1)):
        r = rasterize_padded(clip, tris, MID, cull=cull)
        np.testing.assert_array_equal(np.asarray(r.tri_id) >= 0, want)


def test_silhouette_matches_analytic_projected_sphere():
    """An off-axis sphere's silhouette is the cone of rays within asin(r/|c|) of its centre (an
    ellipse on the image): every pixel farther than the tessellation error from that boundary
    is classified correctly, and the covered area matches the analytic one."""
    c = np.array([0.35, -0.2, -1.5])
    r = 0.45
    m = icosphere(r, 4)  # 5120 triangles: more than the padded size, so use rasterize()
    cam = camera(MID)
    clip = clip_of(cam, m.vertices, translate(c))
    out = raster.rasterize(clip, m.triangles, MID)
    mask = np.asarray(out.tri_id) >= 0
    d = pixel_rays(cam, MID)
    cosang = (d @ c) / (np.linalg.norm(d, axis=-1) * np.linalg.norm(c))
    ang = np.arccos(np.clip(cosang, -1, 1))
    half = np.arcsin(r / np.linalg.norm(c))
    # inscribed polyhedron: its radius is ≥ r·cos(max edge angle / 2) everywhere
    v = m.vertices[m.triangles]
    edge = np.max(np.linalg.norm(v - np.roll(v, 1, axis=1), axis=-1)) / r
    r_in = r * np.cos(edge / 2)
    half_in = np.arcsin(r_in / np.linalg.norm(c))
    np.testing.assert_array_equal(mask[ang < half_in], True)
    np.testing.assert_array_equal(mask[ang > half], False)
    band = (ang >= half_in) & (ang <= half)
    assert band.sum() < 0.06 * mask.sum()
    # area: analytic pixel count of the ellipse vs covered pixels
    analytic = int((ang < half).sum())
    assert abs(int(mask.sum()) - analytic) <= band.sum()
    assert abs(int(mask.sum()) - analytic) / analytic < 0.02


# ----------------------------------------------------------------------------- depth order


def test_depth_order_interpenetrating_spheres():
    cs = [np.array([-0.12, 0.02, -1.4]), np.array([0.15, -0.05, -1.55])]
    rs = [0.35, 0.4]
    mesh, offsets = sphere_scene(cs, rs)
    cam = camera(MID)
    clip = clip_of(cam, mesh.vertices)
    r = rasterize_padded(clip, mesh.triangles, MID)
    ids = np.asarray(r.tri_id)
    obj = np.where(ids >= 0, np.searchsorted(offsets, ids, side="right") - 1, -1)
    d = pixel_rays(cam, MID)
    t = [ray_sphere_t(d, c, rr)[0] for c, rr in zip(cs, rs, strict=True)]
    want = np.where(np.isfinite(np.minimum(*t)), np.argmin(np.stack(t), 0), -1)
    # compare away from the intersection curve and the silhouettes (tessellation error ~1 %)
    discs = [ray_sphere_t(d, c, rr)[2] / rr**2 for c, rr in zip(cs, rs, strict=True)]
    with np.errstate(invalid="ignore"):  # inf − inf where both rays miss
        gap = np.abs(t[0] - t[1])
    sure = (np.nan_to_num(gap, nan=0.0) > 0.02)
    sure &= ((np.abs(discs[0]) > 0.05) | ~np.isfinite(t[0]))
    sure &= ((np.abs(discs[1]) > 0.05) | ~np.isfinite(t[1]))
    sure |= ~np.isfinite(t[0]) & ~np.isfinite(t[1]) & (np.minimum(*discs) < -0.05)
    assert np.sum(sure & (want == 0)) > 300 and np.sum(sure & (want == 1)) > 300
    np.testing.assert_array_equal(obj[sure], want[sure])
    # the interpenetration is real: some pixels see sphere 1 in front of sphere 0 and the
    # other way round, and depth agrees with the analytic nearest hit
    hit = (obj >= 0) & sure
    tn = np.minimum(*t)[hit]
    dn = d[hit] / np.linalg.norm(d[hit], axis=-1, keepdims=True)
    z_eye = tn * dn[:, 2]
    near, far = 0.01, 100.0
    ndc = (-(far + near) / (far - near) * z_eye - 2 * far * near / (far - near)) / -z_eye
    np.testing.assert_allclose(np.asarray(r.depth)[hit], ndc, atol=2e-4)


def test_depth_order_nested_spheres():
    """A small sphere inside a big one: hidden with no culling; with front faces culled the
    big sphere's far side is behind the small sphere, which then shows."""
    cs = [np.array([0.0, 0.0, -1.5]), np.array([0.08, 0.05, -1.45])]
    rs = [0.5, 0.2]
    mesh, offsets = sphere_scene(cs, rs)
    cam = camera(MID)
    clip = clip_of(cam, mesh.vertices)
    d = pixel_rays(cam, MID)
    _, _, disc_in = ray_sphere_t(d, cs[1], rs[1])
    _, _, disc_out = ray_sphere_t(d, cs[0], rs[0])
    for cull in ("none", "front"):
        r = rasterize_padded(clip, mesh.triangles, MID, cull=cull)
        ids = np.asarray(r.tri_id)
        obj = np.where(ids >= 0, np.searchsorted(offsets, ids, side="right") - 1, -1)
        assert np.all(obj[disc_out / rs[0] ** 2 > 0.05] >= 0)
        inner = disc_in / rs[1] ** 2 > 0.05
        assert inner.sum() > 150
        if cull == "none":
            assert np.all(obj[obj >= 0] == 0)
        else:
            assert np.all(obj[inner] == 1)
            assert np.all(obj[(disc_in / rs[1] ** 2 < -0.05) & (obj >= 0)] == 0)


# ----------------------------------------------------------------------------- near plane


def _ground(y=-0.5, extent=40.0):
    v = np.array([[-extent, y, -extent], [extent, y, -extent], [extent, y, extent],
                  [-extent, y, extent]])
    return v, np.array([[0, 3, 2], [0, 2, 1]])  # facing up (+Y)


@pytest.mark.parametrize("near", [0.01, 0.8])
def test_ground_plane_crossing_the_near_plane_and_behind_the_camera(near):
    """A quad reaching behind the camera: covered exactly where the pixel ray meets the plane
    between the near and the far plane; world positions interpolate to the ray–plane point."""
    v, tris = _ground()
    cam = camera(MID, near=near, far=20.0)
    clip = clip_of(cam, v)
    assert np.any(clip[:, 3] < 0)
    r = rasterize_padded(clip, tris, MID)
    d = pixel_rays(cam, MID)
    t = -0.5 / d[..., 1]  # ray o + t d with d_z = −1: eye depth = t
    ok = (d[..., 1] < 0) & (t >= near) & (t <= 20.0)
    margin = np.abs(t - near) > 1e-3 * near
    margin &= np.abs(t - 20.0) > 1e-2
    mask = np.asarray(r.tri_id) >= 0
    np.testing.assert_array_equal(mask[margin], ok[margin])
    assert mask.sum() > 500 and (~mask).sum() > 500
    p = np.asarray(raster.interpolate(jnp.asarray(v, jnp.float32), r, tris,
                                      jnp.asarray(clip)))
    hit = mask
    q = d[hit] * t[hit][:, None]
    np.testing.assert_allclose(p[hit], q, rtol=2e-5, atol=2e-5 * np.abs(q).max())
    assert np.all(np.asarray(r.depth)[hit] >= -1) and np.all(np.asarray(r.depth)[hit] <= 1)


def test_triangles_entirely_behind_the_camera_draw_nothing():
    cam = camera(SMALL)
    v = np.array([[-1.0, -1.0, 0.5], [1.0, -1.0, 0.5], [0.0, 1.0, 0.5],  # behind the eye
                  [-1.0, -1.0, 0.005], [1.0, -1.0, 0.005], [0.0, 1.0, 0.005]])  # before near
    tris = np.array([[0, 1, 2], [0, 2, 1], [3, 4, 5], [3, 5, 4]])
    r = rasterize_padded(clip_of(cam, v), tris, SMALL)
    assert not np.any(np.asarray(r.tri_id) >= 0)


def test_barycentrics_reproduce_ray_plane_intersection():
    cs = [np.array([-0.12, 0.02, -1.4]), np.array([0.15, -0.05, -1.55])]
    mesh, _ = sphere_scene(cs, [0.35, 0.4], subdivisions=2)
    cam = camera(MID)
    clip = clip_of(cam, mesh.vertices)
    r = rasterize_padded(clip, mesh.triangles, MID)
    ids = np.asarray(r.tri_id)
    hit = ids >= 0
    d = pixel_rays(cam, MID)[hit]
    v = mesh.vertices.astype(np.float64)[mesh.triangles[ids[hit]]]  # (N, 3, 3)
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    q = d * (np.sum(n * v[:, 0], -1) / np.sum(n * d, -1))[:, None]
    for p in (raster.interpolate(mesh.vertices, r, mesh.triangles),  # stored barycentrics
              raster.interpolate(mesh.vertices, r, mesh.triangles, jnp.asarray(clip))):
        np.testing.assert_allclose(np.asarray(p)[hit], q, atol=2e-6)
    b = np.asarray(r.bary)[hit]
    assert np.all(b >= -1e-6) and np.allclose(b.sum(-1), 1, atol=1e-6)


# ----------------------------------------------------------------------------- gradients

_FD_SCRIPT = textwrap.dedent("""
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp, numpy as np
    from helpers.raster import MID, camera
    from spectral_fit import geometry as raster
    from spectral_fit.geometry import project
    from spectral_fit.io import icosphere, translate

    m = icosphere(0.4, 1).transformed(translate((0.05, -0.03, -1.3)))
    cam = camera(MID)
    verts = jnp.asarray(m.vertices, jnp.float64)
    tris = jnp.asarray(m.triangles)
    clip = project(cam, verts).astype(jnp.float64)
    r = raster.rasterize(clip, tris, MID)
    px = raster.covered_pixels(r, MID[0] * MID[1])
    rng = np.random.default_rng(0)
    attr = jnp.asarray(rng.normal(size=(len(m.vertices), 3)))
    wimg = jnp.asarray(rng.normal(size=MID + (3,)))
    wpix = jnp.asarray(rng.normal(size=(MID[0] * MID[1], 3)))
    cam64 = jax.tree.map(lambda a: a.astype(jnp.float64), cam)

    def clip_of(v):
        m = cam64.view_projection
        return v @ m[:, :3].T + m[:, 3]

    @jax.jit
    def f_img(a, v):
        return jnp.sum(wimg * raster.interpolate(a, r, tris, clip_of(v)))

    @jax.jit
    def f_pix(a, v):
        return jnp.sum(wpix * raster.interpolate_pixels(a, px, tris, clip_of(v)))

    out = {}
    for name, f in (("image", f_img), ("pixels", f_pix)):
        ga, gv = jax.jit(jax.grad(f, argnums=(0, 1)))(attr, verts)
        for arg, g, x in (("attributes", ga, attr), ("positions", gv, verts)):
            res = []
            for k in range(4):
                dx = jnp.asarray(rng.normal(size=x.shape))
                h = 1e-6 if arg == "positions" else 1.0
                if arg == "attributes":
                    fp, fm = f(attr + h * dx, verts), f(attr - h * dx, verts)
                else:
                    fp, fm = f(attr, verts + h * dx), f(attr, verts - h * dx)
                res.append([float((fp - fm) / (2 * h)), float(jnp.sum(g * dx))])
            out[name + "/" + arg] = res
    out["dtype"] = str(raster.interpolate(attr, r, tris, clip_of(verts)).dtype)
    out["covered"] = int(px.count)
    print(json.dumps(out))
""")


def test_interpolate_gradients_match_finite_differences_float64():
    """d/d(attributes) and d/d(vertex positions, through the camera) of interpolated
    attributes, against central differences in float64 (own process: the x64 switch is
    global)."""
    env = subprocess_env(JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", _FD_SCRIPT], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["dtype"] == "float64" and out["covered"] > 1000
    for key in ("image/attributes", "image/positions", "pixels/attributes",
                "pixels/positions"):
        fd, ad = np.array(out[key]).T
        assert np.all(np.abs(ad) > 1e-3), key
        np.testing.assert_allclose(ad, fd, rtol=1e-6, err_msg=key)


def test_interpolate_is_linear_in_attributes_with_barycentric_weights():
    clip, tris = soup(5, behind=False)
    r = rasterize_padded(clip, tris, SMALL)
    attr = jnp.asarray(np.random.default_rng(0).normal(size=(len(clip), 2)), jnp.float32)
    w = jnp.asarray(np.random.default_rng(1).normal(size=SMALL + (2,)), jnp.float32)
    g = jax.grad(lambda a: jnp.sum(w * raster.interpolate(a, r, tris, jnp.asarray(clip))))(attr)
    # closed form: dL/da_v = Σ_pixels bary_k(pixel) w(pixel) over the corners k that are v
    ids = np.asarray(r.tri_id)
    want = np.zeros((len(clip), 2))
    bary = np.asarray(r.bary)
    for y, x in zip(*np.nonzero(ids >= 0), strict=True):
        for k in range(3):
            want[tris[ids[y, x], k]] += bary[y, x, k] * np.asarray(w)[y, x]
    np.testing.assert_allclose(np.asarray(g), want, atol=1e-4)


# ----------------------------------------------------------------------------- pixel lists


def test_covered_pixels_list_and_scatter_round_trip():
    clip, tris = soup(2)
    r = rasterize_padded(clip, tris, SMALL)
    ids = np.asarray(r.tri_id)
    n = int((ids >= 0).sum())
    h, w = SMALL
    pl = raster.covered_pixels(r, h * w)
    assert int(pl.count) == n and not bool(pl.overflow)
    np.testing.assert_array_equal(np.asarray(pl.index)[:n], np.flatnonzero(ids >= 0))
    np.testing.assert_array_equal(np.asarray(pl.tri_id)[:n], ids[ids >= 0])
    assert np.all(np.asarray(pl.tri_id)[n:] == -1)
    attr = np.random.default_rng(0).normal(size=(len(clip), 3)).astype(np.float32)
    full = np.asarray(raster.interpolate(attr, r, tris, jnp.asarray(clip)))
    vals = raster.interpolate_pixels(attr, pl, tris, jnp.asarray(clip))
    img = np.asarray(raster.scatter_pixels(vals, pl, -7.0))
    np.testing.assert_allclose(img[ids >= 0], full[ids >= 0], rtol=1e-6, atol=1e-6)
    assert np.all(img[ids < 0] == -7.0)
    small = raster.covered_pixels(r, n - 5)  # too small: reported, never silent
    assert bool(small.overflow) and int(small.count) == n


@pytest.mark.parametrize("n", [1, 31, 32, 33, 1000, 345_600])
def test_compact_flags_matches_flatnonzero(n):
    """compact_flags (bit-packed select) against NumPy's flatnonzero: densities from empty to
    full, lengths around the 32-bit word, capacities below, at and above the count; one
    jitted program per shape, every density through it."""
    rng = np.random.default_rng(n)
    for cap in sorted({1, max(1, n // 7), n + 5}):
        f = jax.jit(lambda m, cap=cap: raster.compact_flags(m, cap))
        for density in (0.0, 0.01, 0.3, 0.97, 1.0):
            flags = rng.random(n) < density
            if density == 0.3 and n >= 64:  # runs that span whole words
                flags[n // 3: n // 3 + 70] = True
            index, count = (np.asarray(x) for x in f(jnp.asarray(flags)))
            ref = np.flatnonzero(flags)
            assert int(count) == ref.size, (n, cap, density)
            k = min(cap, ref.size)
            np.testing.assert_array_equal(index[:k], ref[:k])
            assert np.all(index[k:] == 0)


# ----------------------------------------------------------------------------- buffers


def test_moving_objects_does_not_recompile():
    mesh = two_spheres(-2.0)
    cam = camera(MID)
    clip0 = clip_of(cam, mesh.vertices)
    raster.rasterize(clip0, mesh.triangles, MID)  # plans capacities with headroom, compiles
    rng = np.random.default_rng(0)
    centre = np.array([0.0, 0.05, -2.1])  # rotate the pair about its own centre
    moves = [translate(centre + rng.uniform(-0.1, 0.1, 3)) @ rotate(rng.normal(size=3),
                                                                    rng.uniform(0, 3))
             @ translate(-centre) for _ in range(6)]
    # warm up the small eager ops (projection) outside the counted region
    clips = [jnp.asarray(clip_of(cam, mesh.vertices, mv)) for mv in moves]
    tris = jnp.asarray(mesh.triangles)
    with count_compilations() as seen, warnings.catch_warnings():
        warnings.simplefilter("error")
        outs = [raster.rasterize(c, tris, MID) for c in clips]
        jax.block_until_ready(outs)
    assert seen == []
    assert all(int(np.sum(np.asarray(o.tri_id) >= 0)) > 200 for o in outs)  # still in view
    # the results are right (vs a fresh rasterisation with fixed, generous buffers)
    for c, o in zip(clips[:2], outs[:2], strict=True):
        ref = rasterize_padded(np.asarray(c), mesh.triangles, MID)
        np.testing.assert_array_equal(np.asarray(o.tri_id), np.asarray(ref.tri_id))


def test_overflow_is_detected_reported_and_recovered():
    mesh = two_spheres(-4.0)
    cam = camera(MID)
    far_clip = clip_of(cam, mesh.vertices)
    near_clip = clip_of(cam, mesh.vertices, translate((0.0, 0.0, 3.0)))
    cfg = raster.plan_config(far_clip, mesh.triangles, MID, headroom=1.0)
    # inside a jit the flag and the counts come back to the caller
    out = jax.jit(lambda c: raster.rasterize(c, mesh.triangles, MID, config=cfg))(near_clip)
    caps = np.asarray([*cfg.capacities, cfg.block_capacity])
    assert bool(out.overflow)
    assert np.any(np.asarray(out.needed) > caps)
    out2 = out  # flagged and incomplete
    # default: warns, grows the buffers once and returns the complete result
    with pytest.warns(RuntimeWarning, match="capacities grown"):
        out3 = raster.rasterize(near_clip, mesh.triangles, MID, config=cfg)
    assert not bool(out3.overflow)
    ref = rasterize_padded(near_clip, mesh.triangles, MID)
    np.testing.assert_array_equal(np.asarray(out3.tri_id), np.asarray(ref.tri_id))
    assert (np.asarray(out2.tri_id) >= 0).sum() < (np.asarray(ref.tri_id) >= 0).sum()


def test_batch_equals_single_views():
    mesh = two_spheres(-2.0)
    cams = [camera(MID), perspective_camera((0.3, 0.2, 0.5), (0.0, 0.0, -2.0),
                                            fov_y_deg=60.0, aspect=MID[1] / MID[0],
                                            near=0.01, far=100.0)]
    clips = np.stack([clip_of(c, mesh.vertices) for c in cams])
    rb = raster.rasterize_batch(clips, mesh.triangles, MID)
    assert rb.tri_id.shape == (2,) + MID and rb.bary.shape == (2,) + MID + (3,)
    for k in range(2):
        ref = rasterize_padded(clips[k], mesh.triangles, MID)
        # another compiled program: float rounding (FMA contraction) may differ, which can
        # only move pixels within ~1e-6 px of an edge or at a depth tie
        same = np.asarray(rb.tri_id[k]) == np.asarray(ref.tri_id)
        assert (~same).sum() <= 2, np.argwhere(~same)
        np.testing.assert_allclose(np.asarray(rb.depth[k])[same], np.asarray(ref.depth)[same],
                                   atol=2e-6)


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("case, field", [
    ("clip_shape", "clip_xyzw"), ("clip_dtype", "clip_xyzw"), ("clip_nan", "clip_xyzw"),
    ("tris_shape", "triangles"), ("tris_dtype", "triangles"), ("tris_range", "triangles"),
    ("tris_negative", "triangles"), ("tris_empty", "triangles"), ("shape", "shape"),
    ("cull", "cull"),
])
def test_bad_input_raises_input_error_naming_the_field(case, field):
    clip, tris = soup(0, 4)
    kwargs = {}
    shape = SMALL
    if case == "clip_shape":
        clip = clip[:, :3]
    elif case == "clip_dtype":
        clip = (clip * 100).astype(np.int32)
    elif case == "clip_nan":
        clip = clip.copy()
        clip[2, 1] = np.nan
    elif case == "tris_shape":
        tris = tris.reshape(-1)
    elif case == "tris_dtype":
        tris = tris.astype(np.float32)
    elif case == "tris_range":
        tris = tris.copy()
        tris[1, 2] = len(clip)
    elif case == "tris_negative":
        tris = tris.copy()
        tris[0, 0] = -1
    elif case == "tris_empty":
        tris = tris[:0]
    elif case == "shape":
        shape = (0, 32)
    elif case == "cull":
        kwargs["cull"] = "sideways"
    with pytest.raises(InputError) as e:
        raster.rasterize(clip, tris, shape, **kwargs)
    assert e.value.field == field and field in str(e.value)


def test_interpolate_bad_input():
    clip, tris = soup(0, 4)
    r = rasterize_padded(clip, tris, SMALL)
    with pytest.raises(InputError, match="attributes"):
        raster.interpolate(np.ones((len(clip) - 1, 2), np.float32), r, tris, clip)
    with pytest.raises(InputError, match="clip_xyzw"):
        raster.interpolate(np.ones((len(clip), 2), np.float32), r, tris, clip[:, :3])
    with pytest.raises(InputError, match="capacity"):
        raster.covered_pixels(r, 0)


def test_project_matches_camera_matrices():
    cam = camera(SMALL)
    pts = np.random.default_rng(0).normal(size=(5, 3))
    model = translate((0.1, 0.2, -3.0))
    want = (np.asarray(cam.projection, np.float64) @ np.asarray(cam.view, np.float64) @ model
            @ np.concatenate([pts, np.ones((5, 1))], 1).T).T
    np.testing.assert_allclose(np.asarray(project(cam, pts, model)), want, rtol=1e-5,
                               atol=1e-5)


@pytest.mark.slow
def test_benchmark_scene_is_watertight_at_full_size():
    """The paper's scene (720×480, two 19,800-triangle UV spheres at 0.275 m: sub-pixel and
    edge-on triangles at pixel coordinates in the hundreds): the front faces and the back
    faces of the closed spheres cover exactly the same pixels (a crack or a wrongly oriented
    sliver shows up as a difference), and so does the unculled frame."""
    from spectral_fit.bench.cases.raster import scene_clip

    clip, tris, shape = scene_clip(-0.275)
    masks = {cull: np.asarray(raster.rasterize(clip, tris, shape, cull=cull).tri_id) >= 0
             for cull in ("back", "front")}
    np.testing.assert_array_equal(masks["back"], masks["front"])
    # silhouettes vs the analytic discs: two spheres of radius 0.0375 at distance 0.2787
    cam = perspective_camera((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), fov_y_deg=90.0,
                             aspect=shape[1] / shape[0], near=0.01, far=1000.0)
    d = pixel_rays(cam, shape)
    inside = np.zeros(shape, bool)
    for cx in (-0.045, 0.045):
        _, _, disc = ray_sphere_t(d, np.array([cx, 0.0, -0.275]), 0.0375)
        inside |= disc > 0
    assert abs(int(masks["back"].sum()) - int(inside.sum())) < 0.01 * inside.sum()
