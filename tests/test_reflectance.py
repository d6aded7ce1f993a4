"""Reflection model: the published reflectance oracles (sources in docs/conventions.md,
'Reference values'), reciprocity, validation, vmap."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spectral_fit._runtime.errors import InputError
from spectral_fit.lighting import (
    Material,
    beckmann_d,
    brdf,
    check_material,
    fresnel_dielectric,
    from_paper_params,
    gaussian_d,
    gaussian_normalisation,
    gloss_brdf,
    make_material,
    shade_point_light,
    smith_g1_beckmann,
    to_paper_params,
    vcavity_g,
)

# Unpolarised Fresnel reflectance (Rs + Rp)/2 of a dielectric, n = 1.5, from Fresnel's equations
# (closed form of Cook & Torrance 1982); checked below against the Snell-law form too.
FRESNEL_15 = {0: 0.040000, 30: 0.041523, 45: 0.050240, 60: 0.089187, 70: 0.171043,
              80: 0.387704, 85: 0.612800, 89: 0.904185}


def _f64(x):
    return np.asarray(x, dtype=np.float64)


def test_fresnel_table_and_brewster():
    """Fresnel's equations; Brewster's angle arctan(n), where Rp = 0."""
    with jax.enable_x64(True):
        for deg, want in FRESNEL_15.items():
            got = float(fresnel_dielectric(math.cos(math.radians(deg)), 1.5))
            assert got == pytest.approx(want, abs=6e-7), deg
        brewster = math.atan(1.5)
        assert math.degrees(brewster) == pytest.approx(56.31, abs=5e-3)
        assert float(fresnel_dielectric(math.cos(brewster), 1.5)) == pytest.approx(0.073964,
                                                                                    abs=6e-7)
        assert float(fresnel_dielectric(1.0, 1.49)) == pytest.approx(0.038725, abs=6e-7)
        assert float(fresnel_dielectric(0.5, 1.49)) == pytest.approx(0.087521, abs=6e-7)
        # Rs/Rp from Snell's law (independent form); at Brewster Rp = 0 so F = Rs/2
        th = np.radians(np.linspace(0.0, 89.5, 60))
        th[0] = 1e-9  # normal incidence as a limit of the Snell form
        tt = np.arcsin(np.sin(th) / 1.5)
        rs = (np.sin(th - tt) / np.sin(th + tt)) ** 2
        rp = (np.tan(th - tt) / np.tan(th + tt)) ** 2
        np.testing.assert_allclose(_f64(fresnel_dielectric(np.cos(th), 1.5)), (rs + rp) / 2,
                                   rtol=1e-10, atol=1e-14)
        # grazing and sign
        assert float(fresnel_dielectric(0.0, 1.5)) == pytest.approx(1.0, abs=1e-15)
        assert float(fresnel_dielectric(-0.5, 1.5)) == float(fresnel_dielectric(0.5, 1.5))


def test_fresnel_hemispherical_mean_and_float32():
    with jax.enable_x64(True):
        x, w = np.polynomial.legendre.leggauss(200)
        c = 0.5 * (x + 1.0)  # ∫0^1 F(c) 2c dc
        mean = float(np.sum(0.5 * w * 2.0 * c * _f64(fresnel_dielectric(c, 1.5))))
    assert mean == pytest.approx(0.091778, abs=1e-6)
    f32 = np.asarray(fresnel_dielectric(jnp.float32(0.5), jnp.float32(1.5)))
    assert f32.dtype == np.float32 and float(f32) == pytest.approx(0.089187, abs=2e-6)


def test_fresnel_keeps_the_precision_of_n():
    """A float32 cosine must not round a float64 n: central differences in n with h = 1e-7
    are then smooth (the float32 rounding of n would make them noise)."""
    with jax.enable_x64(True):
        c = jnp.float32(0.6)
        n = jnp.float64(1.5)
        assert fresnel_dielectric(c, n).dtype == jnp.float64
        assert fresnel_dielectric(c, 1.5).dtype == jnp.float32  # weak n keeps the cosine's
        h = 1e-7
        fd = float((fresnel_dielectric(c, n + h) - fresnel_dielectric(c, n - h)) / (2 * h))
        exact = float(jax.grad(lambda m: fresnel_dielectric(jnp.float64(c), m))(n))
        assert fd == pytest.approx(exact, rel=1e-6)


def test_fresnel_gradient_in_n_finite_difference():
    with jax.enable_x64(True):
        for c in (1.0, 0.7, 0.2, 0.0):
            g = float(jax.grad(lambda n: fresnel_dielectric(c, n))(1.5))  # noqa: B023
            h = 1e-6
            fd = (float(fresnel_dielectric(c, 1.5 + h)) - float(fresnel_dielectric(c, 1.5 - h))
                  ) / (2 * h)
            assert g == pytest.approx(fd, rel=1e-6, abs=1e-12)


def test_beckmann_values_and_normalisation():
    """Beckmann distribution (Beckmann & Spizzichino 1963) in the normalised microfacet form of
    Walter et al. 2007: D(0) = 1/(π m²)."""
    with jax.enable_x64(True):
        assert float(beckmann_d(1.0, 0.2)) == pytest.approx(7.957747, abs=1e-6)
        assert float(beckmann_d(math.cos(math.radians(10)), 0.2)) == pytest.approx(3.888802,
                                                                                   abs=1e-6)
        th = np.linspace(0, np.pi / 2, 200001)
        for m in (0.1, 0.2, 0.5, 1.0):
            f = _f64(beckmann_d(np.cos(th), m)) * np.cos(th) * np.sin(th) * 2 * np.pi
            assert np.trapezoid(f, th) == pytest.approx(1.0, abs=1e-6)


def test_gaussian_normalisation_values_and_integral():
    """K(μ) has no published table: the values are our quadrature (docs/conventions.md,
    'Reference values'), checked here against an independent integral of D and the small-μ limit
    1/(πμ²)."""
    with jax.enable_x64(True):
        for mu, want in ((0.1, 32.0438), (0.2, 8.17223), (0.3, 3.75412), (0.5, 1.49991)):
            assert float(gaussian_normalisation(mu)) == pytest.approx(want, abs=6e-5)
        th = np.linspace(0, np.pi / 2, 400001)
        for mu in (0.02, 0.05, 0.1, 0.37, 0.5, 1.0, 3.0):
            f = _f64(gaussian_d(np.cos(th), mu)) * np.cos(th) * np.sin(th) * 2 * np.pi
            assert np.trapezoid(f, th) == pytest.approx(1.0, abs=2e-7), mu
        # small-μ limit 1/(πμ²)
        assert float(gaussian_normalisation(1e-3)) * math.pi * 1e-6 == pytest.approx(1.0,
                                                                                     rel=1e-6)
        # smooth and differentiable in μ: derivative vs central difference
        for mu in (0.05, 0.2, 0.5, 1.3):
            g = float(jax.grad(gaussian_normalisation)(mu))
            h = 1e-6 * mu
            fd = (float(gaussian_normalisation(mu + h)) - float(gaussian_normalisation(mu - h))
                  ) / (2 * h)
            assert g == pytest.approx(fd, rel=1e-7)
        # D at θh = 0 has a finite derivative in cosθh (no arccos singularity)
        d = jax.grad(lambda c: gaussian_d(c, 0.2))(1.0)
        assert np.isfinite(float(d))


def _dirs(theta_v, theta_l, dphi):
    tv, tl, p = (math.radians(x) for x in (theta_v, theta_l, dphi))
    n = np.array([0.0, 0.0, 1.0])
    v = np.array([math.sin(tv), 0.0, math.cos(tv)])
    lv = np.array([math.sin(tl) * math.cos(p), math.sin(tl) * math.sin(p), math.cos(tl)])
    h = (v + lv) / np.linalg.norm(v + lv)
    return n, v, lv, h


def test_vcavity_values():
    """V-cavity G of Torrance & Sparrow 1967 in Blinn's 1977 closed form."""
    with jax.enable_x64(True):
        def g(tv, tl, dphi):
            n, v, lv, h = _dirs(tv, tl, dphi)
            return float(vcavity_g(n @ h, n @ v, n @ lv, v @ h))
        assert g(30, 30, 180) == pytest.approx(1.0, abs=1e-12)  # mirror configuration
        assert g(20, 70, 180) == pytest.approx(0.876743, abs=1e-6)
        assert g(30, 85, 180) == pytest.approx(0.287765, abs=1e-6)
        assert g(60, 60, 90) == pytest.approx(0.8, abs=1e-12)


def test_smith_g1_limits_and_integral_form():
    with jax.enable_x64(True):
        assert float(smith_g1_beckmann(1.0, 0.3)) == pytest.approx(1.0, abs=1e-12)
        assert float(smith_g1_beckmann(0.0, 0.3)) == 0.0
        # Λ(a) = (1/a) ∫_a^∞ (x − a) e^{−x²}/√π dx ... equivalently the closed form; check the
        # closed form against direct numerical integration of Smith's integral
        for cos_t, m in ((0.3, 0.3), (0.6, 0.5), (0.1, 0.2)):
            a = cos_t / (m * math.sqrt(1 - cos_t**2))
            x = np.linspace(a, a + 12, 400001)
            lam = np.trapezoid((x - a) * np.exp(-x * x), x) / (a * math.sqrt(math.pi))
            assert float(smith_g1_beckmann(cos_t, m)) == pytest.approx(1 / (1 + lam), rel=1e-8)


def _mat(**kw):
    base = dict(alpha=0.7, beta=0.9, chi=0.3, mu=0.2, n=1.5, gamma=0.0,
                reflectance=np.linspace(0.1, 0.9, 5))
    base.update(kw)
    return make_material(**base, dtype=jnp.asarray(0.0).dtype)  # float64 under enable_x64


def test_helmholtz_reciprocity_and_gloss_formula():
    rng = np.random.default_rng(3)
    with jax.enable_x64(True):
        for dist in ("gaussian", "beckmann"):
            for geom in ("vcavity", "smith"):
                m = _mat(distribution=dist, geometry=geom)
                for _ in range(20):
                    n = rng.normal(size=3)
                    n /= np.linalg.norm(n)
                    v, lv = rng.normal(size=3), rng.normal(size=3)
                    v, lv = v / np.linalg.norm(v), lv / np.linalg.norm(lv)
                    v, lv = (v if v @ n > 0 else -v), (lv if lv @ n > 0 else -lv)
                    a = _f64(brdf(m, n, v, lv))
                    b = _f64(brdf(m, n, lv, v))
                    np.testing.assert_allclose(a, b, rtol=1e-12)
        # gloss formula written out independently (Gaussian, V-cavity)
        m = _mat()
        n, v, lv, h = _dirs(25, 40, 160)
        th = math.acos(n @ h)
        K = 8.17223  # K(μ = 0.2), by quadrature (docs/conventions.md, 'Reference values')
        D = K * math.exp(-((th / 0.2) ** 2))
        G = min(1, 2 * (n @ h) * (n @ v) / (v @ h), 2 * (n @ h) * (n @ lv) / (v @ h))
        c = v @ h
        g = math.sqrt(1.5**2 + c * c - 1)
        F = 0.5 * ((g - c) / (g + c)) ** 2 * (1 + ((c * (g + c) - 1) / (c * (g - c) + 1)) ** 2)
        want = F * D * G / (4 * (n @ v) * (n @ lv))
        assert float(gloss_brdf(m, n, v, lv)) == pytest.approx(want, rel=2e-6)
        # point light: radiance = f·E·cosθi
        E = np.linspace(1.0, 2.0, 5)
        got = _f64(shade_point_light(m, n, v, lv, E))
        np.testing.assert_allclose(got, _f64(brdf(m, n, v, lv)) * E * (n @ lv), rtol=1e-12)


def test_lambert_energy():
    """α = 1 white Lambert: ∫ f cosθi dω = 1 (directional albedo), by quadrature."""
    with jax.enable_x64(True):
        m = _mat(alpha=1.0, beta=0.0, chi=0.0, reflectance=np.ones(5))
        th = np.linspace(0, np.pi / 2, 2001)
        n = np.array([0.0, 0.0, 1.0])
        v = np.array([0.3, 0.0, math.sqrt(1 - 0.09)])
        light = np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], -1)
        vals = np.asarray(jax.jit(jax.vmap(lambda lv: brdf(m, n, v, lv)[0]))(light))
        albedo = np.trapezoid(vals * np.cos(th) * np.sin(th), th) * 2 * np.pi
        assert albedo == pytest.approx(1.0, abs=1e-6)


def test_paper_scaling_round_trip():
    ours = dict(alpha=0.6, beta=0.8, chi=0.1, mu=0.2, n=1.5, gamma=0.3)
    paper = to_paper_params(ours)
    assert paper["alpha"] == pytest.approx(0.6 / math.pi)
    assert paper["beta"] == pytest.approx(0.2)
    assert paper["chi"] == 0.1 and paper["mu"] == 0.2 and paper["n"] == 1.5
    back = from_paper_params(paper)
    for k, v in ours.items():
        assert back[k] == pytest.approx(v)
    m = _mat()
    assert float(to_paper_params(m)["beta"]) == pytest.approx(0.9 / 4)


def test_vmap_over_pixels_and_materials_equals_loop():
    rng = np.random.default_rng(5)
    ns = rng.normal(size=(6, 3))
    ns /= np.linalg.norm(ns, axis=1, keepdims=True)
    vs = ns + 0.5 * rng.normal(size=(6, 3))
    vs /= np.linalg.norm(vs, axis=1, keepdims=True)
    ls = ns + 0.7 * rng.normal(size=(6, 3))
    ls /= np.linalg.norm(ls, axis=1, keepdims=True)
    E = np.linspace(0.5, 1.5, 5)
    f = jax.jit(jax.vmap(jax.vmap(shade_point_light, in_axes=(None, 0, 0, 0, None)),
                         in_axes=(0, None, None, None, None)))
    with jax.enable_x64(True):
        stacked = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[
            _mat(mu=mu, n=n) for mu, n in ((0.1, 1.4), (0.3, 1.6))])
        got = _f64(f(stacked, ns, vs, ls, E))
        for i, (mu, n) in enumerate(((0.1, 1.4), (0.3, 1.6))):
            m = _mat(mu=mu, n=n)
            for j in range(6):
                np.testing.assert_allclose(got[i, j], _f64(shade_point_light(m, ns[j], vs[j],
                                                                              ls[j], E)),
                                           rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("bad, field", [
    (dict(mu=0.0), "mu"), (dict(mu=-0.1), "mu"), (dict(n=1.0), "n"), (dict(n=0.8), "n"),
    (dict(alpha=float("nan")), "alpha"), (dict(beta=-1.0), "beta"),
    (dict(reflectance=np.array([0.1, np.nan, 0.3, 0.4, 0.5])), "reflectance"),
    (dict(distribution="ggx"), "distribution"), (dict(geometry="x"), "geometry"),
])
def test_bad_material_rejected(bad, field):
    with pytest.raises(InputError) as e:
        _mat(**bad)
    assert e.value.field == field


def test_bad_material_shapes():
    with pytest.raises(InputError, match="channels"):
        make_material(reflectance=np.ones(5), channels=81)
    m = Material(alpha=jnp.ones(2), beta=jnp.ones(3), chi=jnp.ones(2), mu=jnp.ones(2),
                 n=jnp.full(2, 1.5), gamma=jnp.zeros(2), reflectance=jnp.ones((2, 4)))
    with pytest.raises(InputError) as e:
        check_material(m)
    assert e.value.field == "beta"
    with pytest.raises(InputError):
        make_material(reflectance="abc")
