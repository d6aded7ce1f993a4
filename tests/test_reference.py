"""The Mitsuba reference renderer (skipped without Mitsuba): furnace tests, the mirror term,
single-bounce renders vs brute-force quadrature, BSDF sampling vs eval/pdf (chi-square and
moments), the environment placement, the camera, and a smoke run of the generator."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

pytest.importorskip("mitsuba")

from helpers.reference import (  # noqa: E402
    fully_covered,
    pixel_subsamples,
    single_bounce_quadrature,
    small_scene,
    smooth_environment,
    sphere_obj,
)

from spectral_fit.validation.reference.backend import init_mitsuba  # noqa: E402

mi, dr = init_mitsuba()
JIT = mi.variant().startswith(("llvm", "cuda"))
needs_jit = pytest.mark.skipif(not JIT, reason="needs a JIT variant (scalar is too slow)")


def _env_lookup(texels: np.ndarray, rotation_y_deg: float):
    import jax
    import jax.numpy as jnp

    from spectral_fit.lighting import EnvironmentMap, GlossQuadrature, lookup

    env = EnvironmentMap.from_array(texels, rotation_y_deg=rotation_y_deg, compress_tol=0.0,
                                    quadrature=GlossQuadrature(levels=0, max_sources=0))
    f = jax.jit(jax.vmap(lambda d: lookup(env, d)))

    def run(d: np.ndarray) -> np.ndarray:
        return np.asarray(f(jnp.asarray(d, jnp.float32)), np.float64)
    return run


def _bsdf(**props):
    base = {"type": "spectral_fit_model", "alpha": 0.0, "beta": 0.0, "chi": 0.0, "mu": 0.1,
            "n": 1.5, "s0": 1.0, "s1": 1.0, "s2": 1.0}
    base.update(props)
    return base


def _sphere_scene(bsdf: dict, *, fov: float, size: int, spp: int, depth: int = 2,
                  env: float = 1.0) -> dict:
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": depth},
        "emitter": {"type": "constant", "radiance": {"type": "rgb", "value": env}},
        "sensor": {"type": "perspective", "fov": fov, "fov_axis": "y",
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0],
                                                              up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": size, "height": size,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "sphere": {"type": "sphere", "bsdf": bsdf},
    }


# ---------------------------------------------------------------------------------- furnaces


def test_white_furnace_gives_unit_radiance():
    """α = 1, S = 1, β = χ = 0 under uniform unit radiance: every sphere pixel is 1."""
    img = np.asarray(mi.render(mi.load_dict(_sphere_scene(
        _bsdf(alpha=1.0), fov=20.0, size=12, spp=1024 if JIT else 64, depth=16))))
    inner = img[3:9, 3:9]  # well inside the silhouette (radius ~ 5.8 px)
    assert abs(inner.mean() - 1.0) < (0.005 if JIT else 0.02)
    assert np.abs(inner - 1.0).max() < (0.04 if JIT else 0.2)


def test_gloss_furnace_matches_closed_form():
    """Gloss lobe alone, Beckmann m = 0.5, F = G = 1, V = N: the closed form 1 − exp(−1/m²) =
    0.981684 (Beckmann distribution integrated up to θh = 45°)."""
    img = np.asarray(mi.render(mi.load_dict(_sphere_scene(
        _bsdf(beta=1.0, mu=0.5, distribution="beckmann", unit_fg=True), fov=1.0, size=4,
        spp=4096 if JIT else 256))))
    expected = 1.0 - math.exp(-1.0 / 0.25)
    assert abs(expected - 0.981684) < 1e-6
    assert abs(img.mean() - expected) < (0.005 if JIT else 0.02)


@pytest.mark.parametrize("rotation", [0.0, 180.0])
def test_mirror_alone_is_fresnel_times_environment(rotation):
    """χ = 1 alone (delta lobe): radiance F(n, θr) · L(R), sub-pixel averaged, vs our lookup."""
    from spectral_fit.lighting import fresnel_dielectric
    from spectral_fit.validation.reference.render import camera_rays, render_spectral, sphere_hits

    centre = (0.01, -0.005, -0.3)
    scene = small_scene(objects=[sphere_obj("m", centre, alpha=0.0, chi=1.0, n=1.5)],
                        width=32, height=32, fov=16.0, rotation_y_deg=rotation)
    tex = smooth_environment()
    # the only noise is the random position inside the pixel (the delta lobe is deterministic)
    r = render_spectral(scene, spp=2048 if JIT else 64, passes=1, depths=(2,), environment=tex,
                        analytic_spheres=True)
    img = r.mean(2)
    ys, xs = np.mgrid[0:32, 0:32]
    ok = fully_covered(scene, centre, 0.0375, xs, ys)
    sx, sy = pixel_subsamples(xs[ok].astype(float), ys[ok].astype(float), 8)
    o, d = camera_rays(scene, sx, sy)
    t = sphere_hits(o, d, centre, 0.0375)
    nrm = (o + t[..., None] * d - np.asarray(centre)) / 0.0375
    v = -d
    nv = np.sum(nrm * v, -1)
    refl = 2 * nv[..., None] * nrm - v
    look = _env_lookup(tex, rotation)
    expect = (np.asarray(fresnel_dielectric(nv, 1.5), np.float64)[..., None]
              * look(refl.reshape(-1, 3)).reshape(*refl.shape)).mean(axis=1)
    got = img[ok]
    inner = nv.mean(axis=1) > 0.6
    assert inner.sum() >= 100
    rel = np.abs(got[inner] - expect[inner]) / expect[inner]
    assert np.median(rel) < (0.002 if JIT else 0.01)
    assert rel.max() < (0.015 if JIT else 0.08)


# --------------------------------------------------------------- single bounce vs quadrature


@needs_jit
@pytest.mark.parametrize("model", [
    ("gaussian", "vcavity", 0.1),
    pytest.param(("beckmann", "smith", 0.3), marks=pytest.mark.slow),
])
def test_single_bounce_sphere_matches_quadrature(model):
    """Depth-2 render of one sphere (α = 1, β = 1, S coloured) vs brute-force quadrature of the
    environment integral at 20 pixels (normal and view from the ray–sphere hit): < 1 %."""
    from spectral_fit.validation.reference.render import camera_rays, render_spectral, sphere_hits

    dist, geom, mu = model
    centre = (0.004, 0.003, -0.3)
    s = (0.2, 0.5, 0.8)
    scene = small_scene(objects=[sphere_obj("q", centre, reflectance=list(s), alpha=1.0,
                                            beta=1.0, mu=mu, n=1.5, distribution=dist,
                                            geometry=geom)],
                        width=24, height=24, fov=12.0, rotation_y_deg=180.0)
    tex = smooth_environment()
    r = render_spectral(scene, spp=8192, passes=4, depths=(2,), environment=tex,
                        analytic_spheres=True)
    img = r.mean(2)
    se = r.passes[0].std(axis=0, ddof=1) / 2.0
    ys, xs = np.mgrid[0:24, 0:24]
    ok = fully_covered(scene, centre, 0.0375, xs, ys)
    rng = np.random.default_rng(1)
    pick = rng.choice(np.flatnonzero(ok.ravel()), 20, replace=False)
    px, py = xs.ravel()[pick].astype(float), ys.ravel()[pick].astype(float)
    sx, sy = pixel_subsamples(px, py, 5)  # the box filter averages over the pixel
    o, d = camera_rays(scene, sx.ravel(), sy.ravel())
    t = sphere_hits(o, d, centre, 0.0375)
    nrm = (o + t[:, None] * d - np.asarray(centre)) / 0.0375
    quad = single_bounce_quadrature(_env_lookup(tex, 180.0), nrm, -d, alpha=1.0, s=s, beta=1.0,
                                    mu=mu, n=1.5, distribution=dist, geometry=geom)
    expect = quad.reshape(20, 25, 3).mean(axis=1)
    got = img.reshape(-1, 3)[pick]
    rel = np.abs(got - expect) / expect
    assert rel.max() < 0.01, (rel.max(), (se.reshape(-1, 3)[pick] / expect).max())


# ---------------------------------------------------------------------------- sampling


def _directions_grid(nz: int, nphi: int, sub: int):
    """Cell-centred sub-grid in (z = cosθ, φ) with its cell index and solid-angle weight."""
    z = (np.arange(nz * sub) + 0.5) / (nz * sub)
    p = 2 * np.pi * (np.arange(nphi * sub) + 0.5) / (nphi * sub)
    Z, P = np.meshgrid(z, p, indexing="ij")
    s = np.sqrt(1 - Z**2)
    d = np.stack([s * np.cos(P), s * np.sin(P), Z], -1).reshape(-1, 3)
    cell = ((np.arange(nz * sub) // sub)[:, None] * nphi
            + (np.arange(nphi * sub) // sub)[None, :]).ravel()
    dw = (1.0 / (nz * sub)) * (2 * np.pi / (nphi * sub))
    return d, cell, dw


@needs_jit
@pytest.mark.parametrize("case", [
    dict(alpha=0.6, beta=1.0, chi=0.0, mu=0.1, s0=0.3, s1=0.6, s2=0.9),
    dict(alpha=0.0, beta=1.0, chi=0.5, mu=0.3, distribution="beckmann", geometry="smith"),
    dict(alpha=1.0, beta=0.5, chi=0.3, mu=0.2),
])
def test_sampling_consistent_with_eval_and_pdf(case):
    """sample() vs pdf(): chi-square over (cosθ, φ) bins (p > 1e-3); weights vs eval/pdf; the
    mean weight vs the quadrature of eval (albedo); delta share vs its selection weight."""
    from scipy import stats

    bsdf = mi.load_dict(_bsdf(**case))
    ctx = mi.BSDFContext()
    n = 200_000
    nz, nphi = 24, 24
    d, cell, dw = _directions_grid(nz, nphi, 8)
    rng = np.random.default_rng(7)
    for theta_deg in (10.0, 50.0, 75.0):
        th = math.radians(theta_deg)
        wi = mi.Vector3f(math.sin(th), 0.0, math.cos(th))
        si = dr.zeros(mi.SurfaceInteraction3f, n)
        si.wi = wi
        u = rng.random((3, n)).astype(np.float32)
        bs, w = bsdf.sample(ctx, si, mi.Float(u[0]), mi.Point2f(u[1], u[2]))
        wo = np.asarray(bs.wo).reshape(3, -1).T if np.asarray(bs.wo).shape[0] == 3 else \
            np.asarray(bs.wo)
        w = np.asarray(w).reshape(3, -1).T if np.asarray(w).shape[0] == 3 else np.asarray(w)
        pdf_s = np.asarray(bs.pdf)
        delta = (np.asarray(bs.sampled_type) & int(mi.BSDFFlags.DeltaReflection)) > 0
        valid = pdf_s > 0
        # eval / pdf on the sample's direction (non-delta)
        si_e = dr.zeros(mi.SurfaceInteraction3f, n)
        si_e.wi = wi
        wo_v = mi.Vector3f(*[mi.Float(wo[:, k].astype(np.float32)) for k in range(3)])
        ev = np.asarray(bsdf.eval(ctx, si_e, wo_v))
        ev = ev.reshape(3, -1).T if ev.shape[0] == 3 else ev
        pd = np.asarray(bsdf.pdf(ctx, si_e, wo_v))
        sm = valid & ~delta
        assert np.allclose(pdf_s[sm], pd[sm], rtol=1e-4, atol=1e-6)
        assert np.allclose(w[sm], ev[sm] / pd[sm, None], rtol=2e-3, atol=1e-6)
        # quadrature of pdf and eval over the hemisphere
        m = d.shape[0]
        si_q = dr.zeros(mi.SurfaceInteraction3f, m)
        si_q.wi = wi
        dq = mi.Vector3f(*[mi.Float(d[:, k].astype(np.float32)) for k in range(3)])
        pq = np.asarray(bsdf.pdf(ctx, si_q, dq), np.float64)
        eq = np.asarray(bsdf.eval(ctx, si_q, dq), np.float64)
        eq = eq.reshape(3, -1).T if eq.shape[0] == 3 else eq
        p_smooth = np.bincount(cell, pq * dw, minlength=nz * nphi)
        # non-delta samples land in the upper hemisphere as often as the pdf integrates to
        assert abs(sm.mean() - p_smooth.sum()) < 0.005
        if case.get("chi", 0.0) == 0.0:
            assert not delta.any()
        # chi-square on the non-delta samples
        zc = np.clip((wo[sm, 2] * nz).astype(int), 0, nz - 1)
        pc = np.clip((np.mod(np.arctan2(wo[sm, 1], wo[sm, 0]), 2 * np.pi)
                      / (2 * np.pi) * nphi).astype(int), 0, nphi - 1)
        obs = np.bincount(zc * nphi + pc, minlength=nz * nphi).astype(float)
        exp = p_smooth * n
        big = exp > 5
        chi2 = ((obs[big] - exp[big]) ** 2 / exp[big]).sum()
        chi2 += (obs[~big].sum() - exp[~big].sum()) ** 2 / max(exp[~big].sum(), 1.0)
        pval = stats.chi2.sf(chi2, big.sum())
        assert pval > 1e-3, (theta_deg, chi2, big.sum())
        # moment: mean weight (all samples) vs ∫ eval dω + delta albedo
        albedo_q = (eq * dw).sum(axis=0)
        mirror = case.get("chi", 0.0) * float(fresnel_np(math.cos(th), case.get("n", 1.5)))
        mean_w = np.where(valid[:, None], w, 0.0).mean(axis=0)
        se = np.where(valid[:, None], w, 0.0).std(axis=0) / math.sqrt(n)
        assert np.all(np.abs(mean_w - albedo_q - mirror) < 5 * se + 0.01 * albedo_q), (
            theta_deg, mean_w, albedo_q + mirror)


def fresnel_np(c: float, n: float) -> float:
    from spectral_fit.lighting import fresnel_dielectric

    return float(fresnel_dielectric(c, n))


# ------------------------------------------------------------------ placement and camera


def test_envmap_rows_reproduce_our_lookup():
    """Mitsuba's envmap fed 2H + 1 rows of our lookup (export.mitsuba_envmap_rows) returns our
    lookup, rotation included, at random directions (relative 1e-4)."""
    from spectral_fit.lighting import rotation_y
    from spectral_fit.validation.reference.export import mitsuba_envmap_rows

    tex = smooth_environment(16, 32)
    tex[5, 7] = [40.0, 10.0, 1.0]  # a sharp texel: bilinear structure matters
    rows = mitsuba_envmap_rows(tex)
    to_world = np.eye(4)
    to_world[:3, :3] = rotation_y(180.0)
    bitmap = mi.Bitmap(np.ascontiguousarray(rows, np.float32),
                       pixel_format=mi.Bitmap.PixelFormat.RGB)
    em = mi.load_dict({"type": "envmap", "bitmap": bitmap,
                       "to_world": mi.ScalarTransform4f(to_world.tolist())})
    rng = np.random.default_rng(3)
    d = rng.normal(size=(400 if JIT else 60, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:4] = [[0, 1, 0], [0, -1, 0], [0.05, 0.998, 0.0], [0, 0, -1]]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ours = _env_lookup(tex, 180.0)(d)
    if JIT:
        si = dr.zeros(mi.SurfaceInteraction3f, d.shape[0])
        si.wi = mi.Vector3f(*[mi.Float(-d[:, k].astype(np.float32)) for k in range(3)])
        got = np.asarray(em.eval(si))
        got = got.reshape(3, -1).T if got.shape[0] == 3 else got
    else:
        got = []
        for di in d:
            si = dr.zeros(mi.SurfaceInteraction3f)
            si.wi = mi.Vector3f(*(-di))
            got.append(np.asarray(em.eval(si)))
        got = np.asarray(got)
    assert np.allclose(got, ours, rtol=1e-4, atol=1e-5)


def test_camera_and_silhouettes_match_our_conventions():
    """Black spheres left and right of the axis against a unit background: covered pixels are
    where our camera rays (row 0 on top, +x to the right) hit the spheres."""
    objs = [sphere_obj("left", (-0.045, 0.02, -0.1), alpha=0.0),
            sphere_obj("right", (0.045, 0.0, -0.1), alpha=0.0, radius=0.03)]
    _check_silhouettes(small_scene(objects=objs, width=48, height=32, fov=90.0), spp=16)


def _check_silhouettes(scene, spp: int) -> None:
    """Mitsuba's render of black spheres against a unit background is 0 on the pixels whose
    four corners see a sphere through our camera rays and 1 where none does."""
    from spectral_fit.validation.reference.render import camera_rays, render_spectral, sphere_hits

    r = render_spectral(scene, spp=spp, passes=1, depths=(2,), environment=1.0)
    img = r.mean(2)[..., 0]
    ys, xs = np.mgrid[0:scene.height, 0:scene.width]
    inside = np.zeros(xs.shape, bool)
    outside = np.ones(xs.shape, bool)
    for ob in scene.objects:
        inside |= fully_covered(scene, ob.position, ob.radius, xs, ys)
        for cx, cy in ((0, 0), (1, 0), (0, 1), (1, 1)):
            o, d = camera_rays(scene, xs + cx, ys + cy)
            outside &= ~np.isfinite(sphere_hits(o, d, ob.position, ob.radius * 1.005))
    assert inside.sum() > 40 and np.all(img[inside] < 0.02)  # meshes (uv spheres) used
    assert np.allclose(img[outside], 1.0, atol=1e-3)


def _intrinsics_scene(**kw):
    """48 × 32 frame through an OpenCV camera with its principal point off the centre."""
    scene = small_scene(width=48, height=32, **kw)
    cam = dataclasses.replace(scene.camera, intrinsics={"fx": 30.0, "fy": 30.0, "cx": 20.3,
                                                        "cy": 17.6})
    return scene.replace(camera=cam)


def _as_vec(v) -> np.ndarray:
    return np.asarray([float(np.ravel(np.asarray(v[i]))[0]) for i in range(3)])


def test_intrinsics_camera_rays_match_mitsuba_and_our_projection():
    """An intrinsics camera's sensor (fov from fy, principal point offsets): Mitsuba's rays
    through film points equal our camera rays, and our renderer's projection of points on those
    rays lands on the same pixel coordinates."""
    from spectral_fit.geometry import _camera as camera
    from spectral_fit.rendering._camera import _projection
    from spectral_fit.validation.reference.export import scene_dict
    from spectral_fit.validation.reference.render import camera_rays

    scene = _intrinsics_scene(objects=[sphere_obj("a", (0.0, 0.0, -0.3))],
                              position=(0.01, 0.02, 0.03), look_at=(0.2, -0.1, -1.0))
    d = scene_dict(scene, env_rgb=1.0, reflectances={"a": np.ones(3)}, spp=1)
    assert d["sensor"]["principal_point_offset_x"] == pytest.approx(0.5 - 20.8 / 48)
    sensor = mi.load_dict(d["sensor"])
    rng = np.random.default_rng(3)
    xs, ys = rng.uniform(0, 48, 40), rng.uniform(0, 32, 40)
    xs[:2], ys[:2] = (20.8, 0.0), (17.1, 0.0)  # the principal point; a corner
    origin, ours = camera_rays(scene, xs, ys)
    for x, y, want in zip(xs, ys, ours, strict=True):
        ray, _ = sensor.sample_ray(0.0, 0.0, mi.Point2f(float(x) / 48, float(y) / 32),
                                   mi.Point2f(0.5, 0.5))
        got = _as_vec(ray.d)
        assert np.abs(got / np.linalg.norm(got) - want).max() < 2e-5
        assert np.abs(np.cross(_as_vec(ray.o) - origin, want)).max() < 1e-6  # starts on it
    cam = scene.camera
    view = np.asarray(camera.look_at(np.asarray(cam.position, np.float32),
                                     np.asarray(cam.look_at, np.float32),
                                     np.asarray(cam.up, np.float32)), np.float64)
    proj = _projection(scene, (32, 48)).astype(np.float64)
    pts = origin + 0.5 * ours
    clip = np.concatenate([pts, np.ones((len(pts), 1))], 1) @ (proj @ view).T
    ndc = clip[:, :2] / clip[:, 3:]
    np.testing.assert_allclose((ndc[:, 0] + 1) * 24, xs, atol=1e-3)
    np.testing.assert_allclose((1 - ndc[:, 1]) * 16, ys, atol=1e-3)


def test_intrinsics_silhouettes_match_our_camera_rays():
    """Black spheres through the off-centre intrinsics camera: covered pixels are where our
    camera rays hit them (the sensor of the exported scene, rendered)."""
    objs = [sphere_obj("left", (-0.05, 0.02, -0.15), alpha=0.0),
            sphere_obj("right", (0.06, -0.01, -0.15), alpha=0.0, radius=0.03)]
    _check_silhouettes(_intrinsics_scene(objects=objs), spp=8)


def test_generator_smoke_run(tmp_path):
    """scripts/make_references.py at a tiny size: files written, loadable, consistent."""
    from helpers import load_script

    from spectral_fit.validation.reference import load_reference

    mod = load_script("make_references")
    rc = mod.main(["--only", "benchmark", "--size", "288", "192", "--bands", "500", "520", "10",
                   "--spp", "2", "--passes", "2", "--out", str(tmp_path)])
    assert rc == 0
    ref = load_reference(tmp_path / "benchmark.npz")
    assert (tmp_path / "benchmark.png").stat().st_size > 100
    assert ref.wavelengths.size == 3 and ref.num_patches > 10
    assert set(ref.object_names) == {"yellow", "red"}
    assert np.all(np.isfinite(ref.spectra)) and np.all(ref.spectra > 0)
    assert ref.metadata["spp"] == 4 and ref.metadata["passes"] == 2


def test_mesh_generator_smoke_run_and_extension(tmp_path):
    """scripts/make_references.py on flat_faces at a tiny size: files written and loadable in the
    grid layout; a second run with one more pass renders only that pass (the cached passes are
    kept bit for bit, the new one has the next seed) and the standard errors follow."""
    from helpers import load_script

    from spectral_fit.validation.reference import load_reference

    mod = load_script("make_references")
    args = ["--only", "flat_faces", "--size", "180", "120", "--bands", "500", "520", "10",
            "--spp", "2", "--out", str(tmp_path), "--cache", str(tmp_path / "cache")]
    assert mod.main([*args, "--passes", "2"]) == 0
    ref = load_reference(tmp_path / "flat_faces.npz")
    first = np.load(tmp_path / "cache" / "flat_faces.npz")["grid"]
    assert first.shape[:2] == (2, 2) and first.shape[-1] == 3
    assert ref.metadata["layout"] == "grid" and ref.metadata["seeds"] == [0, 1]
    assert ref.num_patches > 5 and set(ref.object_index) == {0, 1}
    assert np.all(np.isfinite(ref.spectra)) and np.all(ref.spectra > 0)
    assert (tmp_path / "flat_faces.png").stat().st_size > 100
    assert mod.main([*args, "--passes", "3"]) == 0
    ref3 = load_reference(tmp_path / "flat_faces.npz")
    grid = np.load(tmp_path / "cache" / "flat_faces.npz")["grid"]
    assert grid.shape[1] == 3 and np.array_equal(grid[:, :2], first)
    assert not np.array_equal(grid[:, 2], grid[:, 1])
    assert ref3.metadata["seeds"] == [0, 1, 2]
    iy, ix = (ref3.boxes[:, 1] - 1) // 5, (ref3.boxes[:, 0] - 1) // 5
    g = grid[1][:, iy, ix].astype(np.float64)  # (3 passes, P, 3 bands), depth 16
    assert np.allclose(ref3.spectra, g.mean(axis=0), rtol=2e-3)
    assert np.allclose(ref3.noise, g.std(axis=0, ddof=1) / np.sqrt(3), rtol=2e-3,
                       atol=1e-7)


# ------------------------------------------------------------------ spectroradiometer


def test_simulated_spectroradiometer_session(tmp_path):
    """Readings of the two-sphere scene (3 bands): the session folder's manifest and CSV files,
    the white standard's mean vs R·E(N)/π from our exact irradiance, noise at the stated level."""
    import json
    import tomllib

    from helpers import ROOT

    from spectral_fit.color import read_spectrum_csv
    from spectral_fit.io import load_scene
    from spectral_fit.lighting import EnvironmentMap, irradiance_exact
    from spectral_fit.validation.reference.export import environment_texels
    from spectral_fit.validation.reference.instrument import Spectroradiometer, simulate_readings

    scene = load_scene(ROOT / "configs" / "two_spheres.toml",
                       lambda d: d["spectral"].update(start_nm=540, end_nm=560, step_nm=10))
    inst = Spectroradiometer(pixels=8, repeats=4)
    white = {"position": [0.0, 0.0, -0.275], "normal": [0.0, 0.0, 1.0], "reflectance": 0.99}
    m = simulate_readings(scene, tmp_path / "sess", instrument=inst, spp=512 if JIT else 4,
                          white=white)
    man = tomllib.loads(m.read_text())
    assert man["session"]["format"] == 1 and len(man["readings"]) == 10
    assert (m.parent / man["session"]["scene"]).resolve() == (
        ROOT / "configs" / "two_spheres.toml").resolve()
    truth = json.loads((m.parent / "truth.json").read_text())
    wl = np.asarray(truth["wavelengths_nm"])
    assert wl[0] == 540 and wl[-1] == 560 and np.allclose(np.diff(wl), 1.0)
    r0 = man["readings"][0]
    reps = np.stack([read_spectrum_csv(m.parent / f)[1] for f in r0["files"]])
    mean = np.asarray(truth["readings"][r0["id"]]["mean"])
    assert reps.shape == (4, wl.size) and np.all(reps >= 0)
    rel_sd = (reps.std(axis=0, ddof=1) / mean).mean()
    assert 0.001 < rel_sd < 0.02  # 0.4 % relative + 0.2 % gain + floor
    gap = {r["id"]: r["kind"] for r in man["readings"]}
    assert gap["red_gap"] == "interreflection" and gap["red_outer"] == "object"
    # white standard: R E(N)/π, E from our exact texel-sum irradiance (nothing occludes it)
    env = EnvironmentMap.from_array(environment_texels(scene), diffuse="exact",
                                    rotation_y_deg=scene.environment.rotation_y_deg)
    e = np.asarray(irradiance_exact(env, np.array([0.0, 0.0, 1.0], np.float32)), np.float64)
    from spectral_fit.validation.reference.instrument import instrument_response

    expect = instrument_response(scene.wavelengths, 0.99 * e / math.pi, wl, 5.0)
    got = np.asarray(truth["white"]["mean"])
    assert np.allclose(got, expect, rtol=0.015 if JIT else 0.1)  # Monte Carlo noise ~0.5 %


def test_instrument_band_pass_closed_forms():
    from spectral_fit.validation.reference.instrument import instrument_response

    wl = np.arange(380.0, 781.0, 5.0)
    out_wl = np.arange(400.0, 760.0, 1.0)
    const = instrument_response(wl, np.full(wl.size, 2.5), out_wl, 5.0)
    assert np.allclose(const, 2.5)
    lin = instrument_response(wl, 0.01 * wl, out_wl, 5.0)  # symmetric slit keeps lines
    assert np.allclose(lin, 0.01 * out_wl, rtol=1e-9)
    spike = np.zeros(wl.size)
    spike[wl == 550] = 1.0  # a 5 nm-wide triangle (piecewise linear) through a 5 nm slit
    out = instrument_response(wl, spike, out_wl, 5.0)
    assert np.isclose(out[out_wl == 550][0], 2.0 / 3.0, atol=2e-3)  # ∫ tri² / ∫ tri


def test_bad_input_is_a_clear_error(tmp_path):
    from spectral_fit._runtime.errors import InputError
    from spectral_fit.validation.reference.export import scene_dict
    from spectral_fit.validation.reference.render import render_spectral

    other = "scalar_rgb" if JIT else "llvm_ad_rgb"
    with pytest.raises(InputError, match="SPECTRAL_FIT_MI_VARIANT"):
        init_mitsuba(other)
    scene = small_scene(objects=[sphere_obj("a", (0, 0, -0.3))])
    for bad, field in (({"intrinsics": {"fx": 10.0, "fy": 12.0, "cx": 16.0, "cy": 16.0}},
                        "camera.intrinsics"),
                       ({"distortion": (0.1, 0.0, 0.0, 0.0, 0.0)}, "camera.distortion")):
        cam = dataclasses.replace(scene.camera, **bad)
        with pytest.raises(InputError) as e:
            scene_dict(scene.replace(camera=cam), env_rgb=1.0, reflectances={"a": np.ones(3)},
                       spp=1)
        assert e.value.field == field and e.value.path == str(scene.path)
    with pytest.raises(InputError, match="environment"):
        render_spectral(scene, spp=1, environment=np.ones((4, 8, 5)))
