"""The fit problem: everything the residuals need, precomputed once per session
(:class:`FitProblem`, a pytree), and its host-side companions (:class:`PreparedFit`).

Shapes: B readings, P = B·R² samples (R² pixels per reading; empty slots have object −1),
O objects, L bands; parameters (O, 6), columns ``PARAMETERS`` (α, β, χ, μ, n, γ).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import numpy as np

from ..geometry import GBuffer, ObjectGeometry
from ..io import PARAMETERS, Session
from ..lighting import EnvironmentMap
from ._radiance_cache import FieldAverage, RadianceCache

__all__ = ["FitProblem", "FitReadings", "FitInstrument", "FitSurfaces", "PreparedFit",
           "row_kinds"]


def row_kinds(session: Session, n_image_rows: int) -> list[str]:
    """The kind of every row of a prepared fit: the spot readings' kinds, then "image" for
    each row of the photographs' bins."""
    return [r.kind for r in session.readings] + ["image"] * n_image_rows


class FitReadings(eqx.Module):
    """The readings the model is compared with, and what each one's field averages.

    Attributes:
        average: :class:`~spectral_fit.fitting.FieldAverage`, each reading's field mean of
            its samples (weights sum to 1 per reading).
        background: (B, L) mean environment radiance (unit-scale map, W·sr⁻¹·m⁻²·nm⁻¹) of
            the field pixels that miss every object.
        measured: (B, L) mean reading (W·sr⁻¹·m⁻²·nm⁻¹).
        sigma: (B, L) standard error of the mean reading (W·sr⁻¹·m⁻²·nm⁻¹).
        response: (S, C, L) the last S rows are bins of camera photographs: row B − S + i
            holds C channel counts in its first C columns (the rest 0, σ 1), modelled as
            ``response[i] @ (k(λ) · mean radiance)`` (exposure × sensitivity × Δλ); S = 0
            without photographs.
        level, tilt: (B,) the model's error shared by all bands of a row, 1σ as fractions of
            its measured radiance: a level, and a tilt from −1 at the first band to +1 at the
            last (``[model_error.level]``, ``[model_error.tilt]``; 0: none): the rows are
            weighted by the covariance diag(σ²) + ℓ² m mᵀ + t² (m∘x)(m∘x)ᵀ
            (:func:`~spectral_fit.fitting.whiten_correlated`); None: none anywhere.
    """

    average: FieldAverage
    background: jax.Array
    measured: jax.Array
    sigma: jax.Array
    response: jax.Array
    level: jax.Array | None = None
    tilt: jax.Array | None = None


class FitInstrument(eqx.Module):
    """What lies between the modelled radiance and a reading.

    Attributes:
        calibration: (L,) environment calibration k(λ) (dimensionless; ones without a white
            standard): the model is k(λ) times the radiance under the unit-scale map.
        band: (L, L) the spectroradiometer's band-pass (identity: none; see
            :func:`~spectral_fit.fitting.band_matrix`).
    """

    calibration: jax.Array
    band: jax.Array


class FitSurfaces(eqx.Module):
    """The objects' surfaces as far as they are not fitted.

    Attributes:
        reflectance: (O, L) reflectance S(λ) as measured (SCI or SCE), in [0, 1].
        sci: (O,) 1.0 where the reflectance is SCI (specular included), else 0.0.
        models: static (distribution, geometry) of each object's reflection model.
    """

    reflectance: jax.Array
    sci: jax.Array
    models: tuple[tuple[str, str], ...] = eqx.field(static=True)


class FitProblem(eqx.Module):
    """Everything the residual function needs, precomputed (a pytree; see :func:`prepare_fit`).

    Shapes: B readings, P = B·R² samples (R² pixels per reading; empty slots have object −1),
    O objects, L bands.

    Attributes:
        env: the :class:`~spectral_fit.lighting.EnvironmentMap` at unit scale (the
            calibration multiplies).
        receivers: (P) :class:`~spectral_fit.geometry.GBuffer` of the surface points seen.
        cache: :class:`~spectral_fit.fitting.RadianceCache`, everything material-independent
            of the samples.
        readings: :class:`FitReadings` (field weights, background, means, their errors).
        instrument: :class:`FitInstrument` (calibration k(λ), band-pass).
        surfaces: :class:`FitSurfaces` (reflectances, SCI flags, reflection models).
        values: (O, 6) physical parameters, columns ``PARAMETERS`` (start values; fixed ones
            stay).
        free: static (object, parameter) pairs that are fitted.
        fit_scale: static, whether a global scale is fitted too.
        interreflection: static, whether the model adds the interreflection term.
        bounds: static (lower, upper) of each free parameter (upper = inf: none), from the
            session's ``bounds`` and the physical limits; () = the physical limits.
        prior: static Gaussian priors (index into ``free``, mean, σ), from the session's
            ``prior``: rows (p − mean)/σ appended to the residuals.
    """

    env: EnvironmentMap
    receivers: GBuffer
    cache: RadianceCache
    readings: FitReadings
    instrument: FitInstrument
    surfaces: FitSurfaces
    values: jax.Array
    free: tuple[tuple[int, int], ...] = eqx.field(static=True)
    fit_scale: bool = eqx.field(static=True)
    interreflection: bool = eqx.field(static=True, default=False)
    bounds: tuple[tuple[float, float], ...] = eqx.field(static=True, default=())
    prior: tuple[tuple[int, float, float], ...] = eqx.field(static=True, default=())

    @property
    def irradiance(self) -> jax.Array:
        """(P, L) E(λ, N) of the environment visible from each sample (exact texel sum)."""
        return self.cache.irradiance

    @property
    def mirror_env(self) -> jax.Array:
        """(P, L) environment radiance along the mirror direction R (0 where hidden)."""
        return self.cache.mirror

    @property
    def n_free(self) -> int:
        return len(self.free) + int(self.fit_scale)

    def names(self, objects: Sequence[str]) -> list[str]:
        """Labels of the unknowns, ``object.parameter`` (and ``scale``)."""
        out = [f"{objects[o]}.{PARAMETERS[k]}" for o, k in self.free]
        return out + (["scale"] if self.fit_scale else [])


@dataclasses.dataclass
class PreparedFit:
    """Host-side companions of a :class:`FitProblem`.

    ``seconds`` is the time the preparation took (or its load from the disk cache);
    ``cached`` says where it came from: "off" (prepared, no disk cache), "miss" (prepared and
    stored) or "hit" (loaded; :func:`~spectral_fit.fitting.prepare_fit_cached`).
    """

    problem: FitProblem
    session: Session
    objects: tuple[str, ...]
    geometries: list[ObjectGeometry]
    coverage: np.ndarray  # (B,) fraction of the field on the named object
    warnings: list[str]
    seconds: float
    cached: str = "off"
    #: the photographs' kept bins (rows after the spot readings), one entry per image
    images: list[Any] = dataclasses.field(default_factory=list)

    @property
    def n_spots(self) -> int:
        """Rows of spot readings (the first rows; the photographs' bins follow)."""
        return int(self.problem.readings.measured.shape[0]) - self.n_image_rows

    @property
    def n_image_rows(self) -> int:
        return int(self.problem.readings.response.shape[0])

    def row_weights(self, kinds: Sequence[str]) -> np.ndarray:
        """(B,) 1.0 for every row (spot reading or image bin) whose kind is in ``kinds``."""
        k = row_kinds(self.session, self.n_image_rows)
        return np.array([x in kinds for x in k], np.float64)

    def data_per_row(self) -> np.ndarray:
        """(B,) data each row holds: L bands for a spot, its channels for an image row."""
        B, L = self.problem.readings.measured.shape
        out = np.full(B, L)
        resp = np.asarray(self.problem.readings.response)
        out[self.n_spots:] = np.sum(np.abs(resp).sum(axis=-1) > 0, axis=-1)
        return out
