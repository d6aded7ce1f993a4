"""PCA spectral bases: the reference figures, orthonormality, and products in basis space."""

import colour
import numpy as np
import pytest

from spectral_fit._runtime.errors import InputError
from spectral_fit.color import (
    default_wavelengths,
    delta_e00,
    pca_basis,
    radiance_to_xyz,
    reflectance_to_xyz,
    training_spectra,
    wavelength_grid,
    xyz_to_lab,
)

WL10 = wavelength_grid(400, 700, 10)
CC = colour.SDS_COLOURCHECKERS["BabelColor Average"]


def _checker(wl):
    return np.stack([np.asarray(CC[k][wl]) for k in CC])


def _de_stats(wl, refl, recon, ill_name):
    ill = np.asarray(colour.SDS_ILLUMINANTS[ill_name][wl])
    white = reflectance_to_xyz(np.ones_like(wl), ill, wl)
    de = delta_e00(xyz_to_lab(reflectance_to_xyz(refl, ill, wl), white),
                   xyz_to_lab(reflectance_to_xyz(recon, ill, wl), white))
    return de.mean(), de.max()


@pytest.mark.parametrize(
    "k, ill, mean, worst",
    [(4, "D65", 1.19, 2.33), (4, "A", 1.61, 4.98), (8, "D65", 0.15, 0.56), (8, "A", 0.11, 0.36)],
)
def test_pca_oracle(k, ill, mean, worst):
    """Our measured figures (docs/conventions.md, 'Reference values'): 400–700 nm / 10 nm, CES 99 +
    rawtoaces 190, tested on the 24 BabelColor patches; margins 0.01 (mean) and 0.02 (max)."""
    B = pca_basis(k, WL10, training="reflectances", weighting="none")
    T = _checker(WL10)
    m, w = _de_stats(WL10, T, B.reconstruct(B.project(T)), ill)
    assert m == pytest.approx(mean, abs=0.01)
    assert w == pytest.approx(worst, abs=0.02)


def test_training_set_sizes():
    assert training_spectra("reflectances").shape == (289, 81)
    assert training_spectra("illuminants").shape[0] > 40


@pytest.mark.parametrize("weighting", ["visual", "none"])
def test_orthonormal_and_projection_idempotent(weighting):
    B = pca_basis(8, weighting=weighting)
    np.testing.assert_allclose(B.components * B.weights @ B.components.T, np.eye(8), atol=1e-12)
    s = _checker(default_wavelengths())
    c = B.project(s)
    np.testing.assert_allclose(B.project(B.reconstruct(c)), c, atol=1e-12)
    # a full basis reproduces any spectrum exactly
    full = pca_basis(81, weighting=weighting)
    np.testing.assert_allclose(full.reconstruct(full.project(s)), s, atol=1e-10)


def test_product_tensors_match_bandwise_product():
    wl = default_wavelengths()
    B = pca_basis(8)
    refl = _checker(wl)
    ills = np.stack([np.asarray(colour.SDS_ILLUMINANTS[n][wl]) for n in ("D65", "A", "FL2")])
    a, b = B.project(refl), B.project(ills)
    # identity checks of the two tensors against reconstruct-then-multiply (exact algebra)
    prod = np.einsum("pl,ql->pql", B.reconstruct(a), B.reconstruct(b))
    np.testing.assert_allclose(B.reconstruct(B.multiply(a[:, None], b[None])),
                               B.reconstruct(B.project(prod)), atol=1e-10)
    Q = B.product_xyz_tensor()
    np.testing.assert_allclose(np.einsum("pi,qj,ijc->pqc", a, b, Q),
                               radiance_to_xyz(prod, wl), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize(
    "k, weighting, bound_mean, bound_max",
    [(4, "visual", 1.0, 4.5), (8, "visual", 0.2, 0.7), (12, "visual", 0.07, 0.3),
     (8, "none", 0.6, 2.0)],
)
def test_basis_product_colour_error_bound(k, weighting, bound_mean, bound_max):
    """Stated bound (README table): ΔE00 of S·E computed in basis space (K×K×3 contraction)
    vs the band-wise product, 24 ColorChecker patches under D65, A and FL2 (each against its
    own white)."""
    wl = default_wavelengths()
    B = pca_basis(k, weighting=weighting)
    Q = B.product_xyz_tensor()
    des = []
    for n in ("D65", "A", "FL2"):
        e = np.asarray(colour.SDS_ILLUMINANTS[n][wl])
        e = e / radiance_to_xyz(e, wl)[1] * 100.0
        refl = _checker(wl)
        exact = radiance_to_xyz(refl * e, wl)
        basis = np.einsum("pi,j,ijc->pc", B.project(refl), B.project(e), Q)
        white = radiance_to_xyz(e, wl)
        des.append(delta_e00(xyz_to_lab(exact, white), xyz_to_lab(basis, white)))
    des = np.concatenate(des)
    assert des.mean() < bound_mean and des.max() < bound_max


def test_bad_arguments():
    with pytest.raises(InputError, match="basis size"):
        pca_basis(0)
    with pytest.raises(InputError, match="training"):
        pca_basis(4, training="nonsense")
    with pytest.raises(InputError, match="weighting"):
        pca_basis(4, weighting="nonsense")
    with pytest.raises(InputError, match="380–780"):
        pca_basis(4, wavelength_grid(360, 800, 10))


@pytest.mark.parametrize(
    "k, weighting, ill, mean, worst",
    [(4, "none", "D65", 3.10, 8.35), (8, "none", "D65", 0.33, 0.72),
     (4, "visual", "D65", 0.48, 1.28), (8, "visual", "D65", 0.09, 0.22),
     (8, "visual", "A", 0.06, 0.19), (8, "visual", "FL2", 0.10, 0.20)],
)
def test_readme_table_on_default_grid(k, weighting, ill, mean, worst):
    """The README's reconstruction table on the 81-band grid (margins 0.01 / 0.02)."""
    wl = default_wavelengths()
    B = pca_basis(k, weighting=weighting)
    T = _checker(wl)
    m, w = _de_stats(wl, T, B.reconstruct(B.project(T)), ill)
    assert m == pytest.approx(mean, abs=0.01)
    assert w == pytest.approx(worst, abs=0.02)
