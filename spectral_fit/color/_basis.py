"""Linear spectral bases (PCA) and products of spectra in basis space.

A basis is K spectra ``B (K, L)``, orthonormal under a weighted inner product
``<f, g> = Σ_l w_l f_l g_l`` (``B diag(w) Bᵀ = I``). A spectrum ``s (..., L)`` is represented by
coefficients ``c = (s·w) @ Bᵀ (..., K)`` (the weighted least-squares projection) and reconstructed
as ``c @ B``. With ``weighting="none"`` (w = 1) this is plain PCA. The default ``"visual"``
weighting, w = (x̄ + ȳ + z̄)/max + 0.01 from the CIE 1931 CMFs, spends the K components where the
eye looks: on the 81-band grid it cuts the ΔE00 of 8-coefficient products roughly fourfold
(README table), while the 0.01 floor keeps the spectra sane outside the visible range.

The basis is NOT mean-centred, so the representation is linear:
sums, scalings and filtering of spectra commute with projection, which is what lets the renderer
integrate lighting coefficient by coefficient.

Only the product ``S(λ)·E(λ)`` of two spectra needs more: its coefficients are
``c_k = Σ_ij a_i b_j T[i, j, k]`` with ``T = product_tensor()`` (K×K×K), and its XYZ is
``Σ_ij a_i b_j Q[i, j, :]`` with ``Q = product_xyz_tensor()`` (K×K×3): the projection skipped.

Training data (colour-science): reflectances of the CIE 2017 colour-fidelity-index 99 colour
evaluation samples (CIE 224:2017) and the 190 patches of the rawtoaces training set; emitters from
colour's CIE illuminants and measured light sources (each normalised to unit norm).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from .._runtime.errors import InputError
from ._colorimetry import xyz_weights
from ._spectra import default_wavelengths, validate_wavelengths

__all__ = [
    "SpectralBasis",
    "training_spectra",
    "pca_basis",
    "visual_weights",
    "reflectances_5nm",
]

TRAINING_SETS = ("reflectances", "illuminants", "reflectances+illuminants")


@functools.lru_cache(maxsize=4)
def reflectances_5nm() -> tuple[np.ndarray, np.ndarray]:
    import colour
    from colour.characterisation import read_training_data_rawtoaces_v1
    from colour.quality.cfi2017 import load_TCS_CIE2017

    wl = np.arange(380.0, 781.0, 5.0)
    ces = np.asarray(load_TCS_CIE2017(colour.SpectralShape(380, 780, 5))[wl]).T
    raw = np.asarray(read_training_data_rawtoaces_v1()[wl]).T
    return wl, np.concatenate([ces, raw])


@functools.lru_cache(maxsize=4)
def _emitters_5nm() -> tuple[np.ndarray, np.ndarray]:
    import colour

    wl = np.arange(380.0, 781.0, 5.0)
    rows = []
    for table in (colour.SDS_ILLUMINANTS, colour.SDS_LIGHT_SOURCES):
        for sd in table.values():
            if sd.wavelengths[0] > 380.0 or sd.wavelengths[-1] < 780.0:
                continue  # partial measurements would need invented values
            v = np.asarray(sd[wl], dtype=np.float64)
            if np.all(np.isfinite(v)) and v.max() > 0:
                rows.append(v / np.linalg.norm(v))
    return wl, np.stack(rows)


def training_spectra(kind: str = "reflectances", wavelengths: object | None = None) -> np.ndarray:
    """Training spectra (M, L) on ``wavelengths`` (default grid; must lie within 380–780 nm)."""
    wl = default_wavelengths() if wavelengths is None else validate_wavelengths(wavelengths)
    if wl[0] < 380.0 - 1e-9 or wl[-1] > 780.0 + 1e-9:
        raise InputError(f"training data cover 380–780 nm, grid is {wl[0]:g}–{wl[-1]:g} nm",
                         field="wavelengths")
    if kind not in TRAINING_SETS:
        raise InputError(f"unknown training set {kind!r}; choose one of {TRAINING_SETS}",
                         field="training")
    parts = []
    if "reflectances" in kind:
        parts.append(reflectances_5nm())
    if "illuminants" in kind:
        parts.append(_emitters_5nm())
    rows = [np.stack([np.interp(wl, w5, r) for r in data]) for w5, data in parts]
    return np.concatenate(rows)


@dataclasses.dataclass(frozen=True, eq=False)
class SpectralBasis:
    """K orthonormal basis spectra on a wavelength grid.

    Attributes:
        wavelengths: (L,) nm.
        components: (K, L), rows orthonormal under the weights:
            ``components @ diag(weights) @ components.T == I``.
        singular_values: (K,) of the weighted training matrix (for reporting explained energy).
        weights: (L,) inner-product weights (ones for plain PCA).
    """

    wavelengths: np.ndarray
    components: np.ndarray
    singular_values: np.ndarray
    weights: np.ndarray

    @property
    def k(self) -> int:
        return int(self.components.shape[0])

    def project(self, spectra: object) -> np.ndarray:
        """Coefficients (..., K) of spectra (..., L) (orthogonal projection). Works on JAX arrays
        too (the components are a constant)."""
        return (spectra * self.weights) @ self.components.T  # type: ignore[operator]

    def reconstruct(self, coefficients: object) -> np.ndarray:
        """Spectra (..., L) from coefficients (..., K)."""
        return coefficients @ self.components  # type: ignore[operator]

    @functools.cached_property
    def product_tensor(self) -> np.ndarray:
        """T (K, K, K): coefficients of the band-wise product of two spectra,
        ``c = einsum('...i,...j,ijk->...k', a, b, T)`` (the projection of B_i·B_j onto B_k)."""
        B = self.components
        return np.einsum("il,jl,kl,l->ijk", B, B, B, self.weights)

    def product_xyz_tensor(self, *, scale: float = 683.0, observer: str | None = None
                           ) -> np.ndarray:
        """Q (K, K, 3): XYZ of the band-wise product straight from the two coefficient vectors,
        ``XYZ = einsum('...i,...j,ijc->...c', a, b, Q)``, with :func:`xyz_weights` scaling."""
        kw = {} if observer is None else {"observer": observer}
        W = xyz_weights(self.wavelengths, scale=scale, **kw)
        B = self.components
        return np.einsum("il,jl,lc->ijc", B, B, W)

    def multiply(self, a: object, b: object) -> np.ndarray:
        """Coefficients (..., K) of the product of two spectra given by coefficients (..., K)."""
        return np.einsum("...i,...j,ijk->...k", a, b, self.product_tensor)


def visual_weights(wavelengths: object | None = None, *, floor: float = 0.01) -> np.ndarray:
    """Inner-product weights (L,): (x̄ + ȳ + z̄) / max + ``floor`` (CIE 1931 2° CMFs)."""
    from ._colorimetry import cmfs

    c = cmfs(wavelengths).sum(axis=1)
    return c / c.max() + floor


def pca_basis(
    k: int,
    wavelengths: object | None = None,
    *,
    training: str = "reflectances",
    weighting: str = "visual",
) -> SpectralBasis:
    """Uncentred (weighted) PCA basis of size ``k`` from colour-science's bundled spectra.

    Args:
        k: number of components, 1..L.
        wavelengths: grid (default 380–780 nm / 5 nm); must lie within 380–780 nm.
        training: ``"reflectances"`` (CIE 2017 CES 99 + rawtoaces 190; the default: with visual
            weighting it also represents products with light sources best), ``"illuminants"``
            (CIE illuminants and measured light sources, unit-normalised), or both.
        weighting: ``"visual"`` (see module docstring) or ``"none"`` (plain PCA, as the
            reference values of docs/conventions.md use).
    """
    wl = default_wavelengths() if wavelengths is None else validate_wavelengths(wavelengths)
    if not isinstance(k, int | np.integer) or k < 1 or k > wl.size:
        raise InputError(f"basis size must be an integer in 1..{wl.size}, got {k!r}", field="k")
    if weighting == "visual":
        w = visual_weights(wl)
    elif weighting == "none":
        w = np.ones_like(wl)
    else:
        raise InputError(f"unknown weighting {weighting!r}; use 'visual' or 'none'",
                         field="weighting")
    X = training_spectra(training, wl)
    sw = np.sqrt(w)
    _, s, vt = np.linalg.svd(X * sw, full_matrices=False)
    comps = vt[: int(k)] / sw
    # sign convention: each component has a positive sum, so bases are reproducible
    comps = comps * np.where(comps.sum(axis=1, keepdims=True) < 0, -1.0, 1.0)
    return SpectralBasis(wavelengths=wl, components=comps, singular_values=s[: int(k)],
                         weights=w)
