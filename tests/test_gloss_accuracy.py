"""Gloss integral vs brute force on the benchmark's bundled spectral map; the exact spherical
prefilter; behaviour below μ = 0.05; Beckmann and Smith options."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import STUDIO_ROOM
from helpers.lighting import brute_gloss, configs, grazing_configs, unit

from spectral_fit.lighting import (
    EnvironmentMap,
    gloss_integral,
    lookup,
    rotation_y,
    synthetic_environment,
    texel_directions,
    texel_solid_angles,
)
from spectral_fit.lighting._prefilter import _sphere_blur


def test_sphere_blur_is_the_direct_spherical_gaussian_sum():
    rng = np.random.default_rng(0)
    img = rng.uniform(0.0, 1.0, size=(12, 24, 2))
    img[2, 5] = 30.0  # a bright texel near the pole
    d = texel_directions(12, 24).reshape(-1, 3)
    sa = texel_solid_angles(12, 24).reshape(-1)
    for sigma in (0.15, 0.6):
        ang = np.arccos(np.clip(d @ d.T, -1, 1))
        w = np.exp(-0.5 * (ang / sigma) ** 2) * sa[None, :]
        want = (w @ img.reshape(-1, 2)) / w.sum(axis=1, keepdims=True)
        np.testing.assert_allclose(_sphere_blur(img, sigma).reshape(-1, 2), want, rtol=1e-10)


_JITTED = {}


def _gloss_fn(env, quality):
    """One compiled, point-vmapped gloss per (map, quality): μ is traced."""
    key = (id(env), quality)
    if key not in _JITTED:
        _JITTED[key] = (env, jax.jit(jax.vmap(
            lambda n, v, m: gloss_integral(env, n, v, m, 1.5, quality=quality),
            in_axes=(0, 0, None))))
    return _JITTED[key][1]


def _relative_errors(env, img, mu, cfg, quality, rotation, refine=1):
    """Worst band's relative error (per configuration) vs the brute-force oracle on the map
    upsampled 4× bilinearly (the map as the library's lookup defines it), with the lobe's
    core ``refine``× finer still (test_oracle_converges)."""
    ns = jnp.asarray(np.array([c[0] for c in cfg]), jnp.float32)
    vs = jnp.asarray(np.array([c[1] for c in cfg]), jnp.float32)
    got = np.asarray(_gloss_fn(env, quality)(ns, vs, jnp.float32(mu)), np.float64)
    ref = np.array([brute_gloss(img, n, v, mu, 1.5, rotation=rotation, ss=4, refine=refine)
                    for n, v in cfg])
    return np.abs(got / ref - 1.0).max(axis=1)


def _refine(mu):
    """The oracle's refinement for lobes narrower than a few texels at grazing views (at
    μ = 0.07, θr = 80° on the room map's lamp the plain 4× sum is 2.1 % off)."""
    return 8 if mu <= 0.1 else 1


def _grid(lamp, mu, seed, k=8, grazing=(70.0, 80.0)):
    """k configurations with θr <= 60° (half with the lobe on the lamp's edge), then two per
    grazing angle."""
    return configs(lamp, mu, k, seed) + grazing_configs(lamp, mu, seed + 1, grazing)


@pytest.mark.parametrize("mu", [0.05, 0.1, 0.2, 0.3, 0.5])
def test_gloss_exact_vs_brute_force_bundled_map(anchor_lighting, mu):
    """The issue's bound: < 1 % (every band) for μ in [0.05, 0.5], θr <= 60°. Grazing views
    (70°, 80°): measured up to 1.7 % (μ = 0.2, in the blend with the texel sum;
    docs/lighting.md has the full tables): bounded at 2 %."""
    img, env, lamp = anchor_lighting
    rel = _relative_errors(env, img, mu, _grid(lamp, mu, int(mu * 1000) + 1), "exact",
                           rotation_y(180.0))
    print(f"exact mu={mu}: median {np.median(rel):.4f} max {rel.max():.4f}")
    assert rel[:8].max() < 0.01 and rel[8:].max() < 0.02, rel


@pytest.mark.slow
@pytest.mark.parametrize("mu", [0.05, 0.07, 0.1, 0.14, 0.2, 0.25, 0.3, 0.4, 0.5])
def test_gloss_exact_vs_brute_force_dense(anchor_lighting, mu):
    """A denser grid on the benchmark map (16 configurations with θr <= 60° and 8 grazing ones
    up to 80° per μ; the grid of scripts/gloss_accuracy.py), the oracle refined for
    μ <= 0.1. Measured worst: 0.35 % (θr <= 60°), 0.66 % (grazing, μ = 0.14)."""
    img, env, lamp = anchor_lighting
    cfg = _grid(lamp, mu, int(mu * 1000) + 7, k=16, grazing=(65.0, 70.0, 75.0, 80.0))
    rel = _relative_errors(env, img, mu, cfg, "exact", rotation_y(180.0), refine=_refine(mu))
    assert rel[:16].max() < 0.01 and rel[16:].max() < 0.01, rel


@pytest.fixture(scope="module")
def room():
    """The bundled room map (2° lamp of 8 source texels, a window and a ceiling panel with
    sharp edges): (img, EnvironmentMap, world direction of its brightest texel)."""
    from spectral_fit.io import read_spectral_exr

    _, img = read_spectral_exr(STUDIO_ROOM)
    img = np.asarray(img, np.float64)
    lum = img.sum(-1)
    i, j = np.unravel_index(np.argmax(lum), lum.shape)
    return img, EnvironmentMap.from_array(img), texel_directions(*img.shape[:2])[i, j]


def test_gloss_exact_vs_brute_force_room_map_grazing(room):
    """μ = 0.14 on the room map up to θr = 80°: the polar lobe rule was 6.8 % off at 75°
    (aliasing along the plane of incidence and one across-narrowing for the whole lobe);
    measured now <= 0.68 % on the dense grid."""
    img, env, lamp = room
    mu = 0.14
    rel = _relative_errors(env, img, mu, _grid(lamp, mu, int(mu * 1000) + 7, k=2,
                                               grazing=(75.0, 80.0)), "exact", np.eye(3))
    print(f"room exact mu={mu}: median {np.median(rel):.4f} max {rel.max():.4f}")
    assert rel.max() < 0.01, rel


@pytest.mark.slow
@pytest.mark.parametrize("mu", [0.05, 0.07, 0.1, 0.14, 0.2, 0.25, 0.3, 0.4, 0.5])
def test_gloss_exact_vs_brute_force_room_dense(room, mu):
    """The room map on the grid of scripts/gloss_accuracy.py (16 configurations with
    θr <= 60°, 8 from 65° to 80°), the oracle refined for μ <= 0.1. Measured worst: 0.67 %
    (μ = 0.14, θr = 80°; docs/lighting.md)."""
    img, env, lamp = room
    cfg = _grid(lamp, mu, int(mu * 1000) + 7, k=16, grazing=(65.0, 70.0, 75.0, 80.0))
    rel = _relative_errors(env, img, mu, cfg, "exact", np.eye(3), refine=_refine(mu))
    assert rel[:16].max() < 0.01 and rel[16:].max() < 0.01, rel


def test_gloss_exact_vs_brute_force_room_narrow(room):
    """μ = 0.07 on the room map, the dense grid's hardest configurations: θr = 45° with the
    window's edge in the lobe's tail (was 1.42 % in the 380–390 nm bands with the prefilter
    at r = 0.2 and 24 columns across; measured now 0.54 %) and the grazing ones on the lamp
    and anywhere up to 80° (against the refined oracle; measured <= 0.44 %)."""
    img, env, lamp = room
    mu = 0.07
    cfg = _grid(lamp, mu, int(mu * 1000) + 7, k=16, grazing=(65.0, 70.0, 75.0, 80.0))
    pick = [10, 11, 20, 21, 22, 23]
    rel = _relative_errors(env, img, mu, [cfg[i] for i in pick], "exact", np.eye(3),
                           refine=_refine(mu))
    print(f"room exact mu={mu}: {np.round(rel * 100, 2)} %")
    assert rel.max() < 0.01, rel


def _oracle_cases(room):
    """μ = 0.07 on the room map: θr = 80° on the 2° lamp (the lobe 0.7 texel across) and
    θr = 45° next to the window: (img, mu, [(n, v), (n, v)])."""
    img, _, lamp = room
    mu = 0.07
    cfg = _grid(lamp, mu, int(mu * 1000) + 7, k=16, grazing=(65.0, 70.0, 75.0, 80.0))
    return img, mu, [cfg[22], cfg[11]]


def test_oracle_converges(room):
    """The oracle's refinement (the lobe's core summed 4·k× finer) converges: at 80° on the
    lamp the plain 4× sum is 2.1 % off the 32× core, the 8× core 0.5 %, the 16× core 0.1 %;
    at 45° all of them agree to 0.1 %."""
    img, mu, cases = _oracle_cases(room)
    for (n, v), plain in zip(cases, (0.015, 0.0), strict=True):
        ref = brute_gloss(img, n, v, mu, 1.5, ss=4, refine=8)
        rel = {k: np.abs(brute_gloss(img, n, v, mu, 1.5, ss=4, refine=k) / ref - 1).max()
               for k in (1, 2, 4)}
        print({k: f"{100 * x:.3f} %" for k, x in rel.items()})
        assert plain <= rel[1] < 0.03 and rel[2] < 0.007 and rel[4] < 0.002, rel


@pytest.mark.slow
def test_oracle_refined_is_the_fine_sum(room):
    """The refined oracle (4×, the lobe's core 32×) against the plain sum at 16× over the
    whole map (no refinement): measured 0.12 % at 80° on the lamp (where the plain 4× is
    2.1 % off), 0.01 % at 45°."""
    img, mu, cases = _oracle_cases(room)
    for n, v in cases:
        ref = brute_gloss(img, n, v, mu, 1.5, ss=4, refine=8)
        fine = brute_gloss(img, n, v, mu, 1.5, ss=16)
        assert np.abs(fine / ref - 1).max() < 0.002


@pytest.mark.parametrize("mu", [0.1, 0.3])
def test_gloss_render_vs_brute_force_bundled_map(anchor_lighting, mu):
    img, env, lamp = anchor_lighting
    rel = _relative_errors(env, img, mu, configs(lamp, mu, 8, int(mu * 1000) + 2), "render",
                           rotation_y(180.0))
    print(f"render mu={mu}: median {np.median(rel):.4f} max {rel.max():.4f}")
    assert np.median(rel) < 0.02 and rel.max() < 0.1, rel


def test_oracle_bilinear_model_is_the_library_lookup():
    """The oracle's own bilinear upsampling (tests/helpers/lighting.py) reproduces the library's
    lookup at the fine texel centres, poles and seam included: both define the same map."""
    from helpers.lighting import bilinear_taps

    rng = np.random.default_rng(1)
    img = rng.uniform(0.0, 1.0, size=(6, 12, 2))
    env = EnvironmentMap.from_array(img)
    idx, wt = bilinear_taps(6, 12, 3)
    flat = np.concatenate([img.reshape(-1, 2), img[0].mean(0)[None], img[-1].mean(0)[None]])
    want = np.einsum("fk,fkc->fc", wt, flat[idx])
    d = jnp.asarray(texel_directions(18, 36).reshape(-1, 3), jnp.float32)
    got = np.asarray(jax.vmap(lambda x: lookup(env, x))(d))
    np.testing.assert_allclose(got, want, atol=2e-6)


def test_below_mu_005_tends_to_albedo_times_map(anchor_lighting):
    """Below μ = 0.05 the same quadrature runs on the (bilinear) map itself: as μ → 0 the
    gloss tends to A(θr)·L(R), A the lobe albedo, i.e. F(θr)·L(R) (a Fresnel mirror) — the
    map resolves nothing finer than its texels. Continuous through 0.05."""
    from helpers.lighting import fresnel

    img, env, lamp = anchor_lighting
    g = jax.jit(lambda n, v, m: gloss_integral(env, n, v, m, 1.5))
    for n, v in configs(lamp, 0.02, 6, seed=5)[1::2]:  # away from the lamp's edge
        N, V = jnp.asarray(n, jnp.float32), jnp.asarray(v, jnp.float32)
        r = 2 * (n @ v) * n - v
        mirror = np.asarray(lookup(env, jnp.asarray(r, jnp.float32)))
        tiny = np.asarray(g(N, V, jnp.float32(0.004)))
        np.testing.assert_allclose(tiny, fresnel(n @ v, 1.5) * mirror, rtol=0.02)
        a, b = (np.asarray(g(N, V, jnp.float32(m))) for m in (0.0499, 0.0501))
        np.testing.assert_allclose(a, b, rtol=5e-3)


@pytest.mark.parametrize("distribution, geometry", [("beckmann", "vcavity"),
                                                    ("gaussian", "smith"),
                                                    ("beckmann", "smith")])
def test_gloss_options_vs_brute_force(distribution, geometry):
    wl = np.array([450.0, 550.0, 650.0])
    img = synthetic_environment(32, 64, wl, lamp_radius_deg=10.0, lamp_luminance_ratio=10.0)
    env = EnvironmentMap.from_array(img)
    lamp = unit([0.4, 0.8, -0.45])
    f = jax.jit(jax.vmap(lambda n, v, m: gloss_integral(env, n, v, m, 1.5,
                                                        distribution=distribution,
                                                        geometry=geometry),
                         in_axes=(0, 0, None)))
    for mu in (0.1, 0.3):
        cfg = configs(lamp, mu, 6, seed=3)
        ns = jnp.asarray(np.array([c[0] for c in cfg]), jnp.float32)
        vs = jnp.asarray(np.array([c[1] for c in cfg]), jnp.float32)
        got = np.asarray(f(ns, vs, jnp.float32(mu)), np.float64)
        ref = np.array([brute_gloss(img, n, v, mu, 1.5, ss=4, distribution=distribution,
                                    geometry=geometry) for n, v in cfg])
        rel = np.abs(got / ref - 1).max(axis=1)
        assert np.median(rel) < 0.01 and rel.max() < 0.03, (mu, rel)


def test_uniform_map_all_options_match_brute_force():
    """Uniform map: only the lobe albedo and the node placement matter."""
    img = np.ones((16, 32, 1))
    env = EnvironmentMap.from_array(img)
    cfg = configs(unit([0, 1, 0]), 0.2, 4, seed=9, theta_max_deg=75)
    ns = jnp.asarray(np.array([c[0] for c in cfg]), jnp.float32)
    vs = jnp.asarray(np.array([c[1] for c in cfg]), jnp.float32)
    for distribution in ("gaussian", "beckmann"):
        for geometry in ("vcavity", "smith"):
            qualities = (("exact", "render") if (distribution, geometry) == ("gaussian", "vcavity")
                         else ("exact",))
            for quality in qualities:
                f = jax.jit(jax.vmap(lambda n, v, m: gloss_integral(
                    env, n, v, m, 1.5, distribution=distribution,  # noqa: B023
                    geometry=geometry, quality=quality), in_axes=(0, 0, None)))  # noqa: B023
                for mu in (0.03, 0.2, 0.5):
                    got = np.asarray(f(ns, vs, jnp.float32(mu)))[:, 0]
                    ref = np.array([brute_gloss(np.ones((64, 128, 1)), n, v, mu, 1.5, ss=2,
                                                distribution=distribution,
                                                geometry=geometry)[0] for n, v in cfg])
                    np.testing.assert_allclose(got, ref, rtol=1e-2,
                                               err_msg=f"{distribution} {geometry} {mu}")


def test_unknown_quality_rejected(anchor_lighting):
    from spectral_fit._runtime.errors import InputError

    _, env, _ = anchor_lighting
    with pytest.raises(InputError) as e:
        gloss_integral(env, jnp.array([0.0, 1.0, 0.0]), jnp.array([0.0, 1.0, 0.0]), 0.1, 1.5,
                       quality="fast")
    assert e.value.field == "quality"


def test_unknown_node_rule_rejected():
    from spectral_fit._runtime.errors import InputError
    from spectral_fit.lighting import GlossQuadrature

    with pytest.raises(InputError) as e:
        EnvironmentMap.from_array(np.ones((8, 16, 1)), quadrature=GlossQuadrature(nodes="x"))
    assert e.value.field == "quadrature.nodes"
    with pytest.raises(InputError) as e:
        EnvironmentMap.from_array(np.ones((8, 16, 1)),
                                  quadrature=GlossQuadrature(source_subpoints=2))
    assert e.value.field == "quadrature.source_subpoints"
    with pytest.raises(InputError) as e:
        EnvironmentMap.from_array(np.ones((8, 16, 1)), quadrature=GlossQuadrature(tent_points=0))
    assert e.value.field == "quadrature.tent_points"
    with pytest.raises(InputError) as e:
        EnvironmentMap.from_array(np.ones((8, 16, 1)),
                                  quadrature=GlossQuadrature(texel_sum_from=0.3,
                                                             texel_sum_full=0.2))
    assert e.value.field == "quadrature.texel_sum_from"


def test_shade_points_batches_equal_vmap():
    from spectral_fit.lighting import make_material, shade, shade_points

    wl = np.array([450.0, 550.0, 650.0])
    env = EnvironmentMap.from_array(synthetic_environment(16, 32, wl))
    cfg = configs(unit([0.4, 0.8, -0.45]), 0.2, 7, seed=4)
    ns = jnp.asarray(np.array([c[0] for c in cfg]), jnp.float32)
    vs = jnp.asarray(np.array([c[1] for c in cfg]), jnp.float32)
    m = make_material(alpha=0.7, beta=1.0, chi=0.3, mu=0.2, n=1.5,
                      reflectance=np.array([0.2, 0.5, 0.7]))
    for quality in ("render",):  # the batching does not depend on the quadrature
        want = np.asarray(jax.jit(jax.vmap(lambda a, b, q=quality: shade(
            m, env, a, b, quality=q)))(ns, vs))
        got = np.asarray(jax.jit(lambda a, b, q=quality: shade_points(
            m, env, a, b, batch_size=3, quality=q))(ns, vs))
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-9)
