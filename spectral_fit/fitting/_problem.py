"""The fit problem: everything the residuals need, precomputed once per session
(:class:`FitProblem`, a pytree), and its host-side companions (:class:`PreparedFit`).

Shapes: B readings, P = B·R² samples (R² pixels per reading; empty slots have object −1),
O objects, L bands; parameters (O, 6), columns ``PARAMETERS`` (α, β, χ, μ, n, γ).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import equinox as eqx
import jax
import numpy as np

from ..geometry import GBuffer, ObjectGeometry
from ..io import PARAMETERS, Session
from ..lighting import EnvironmentMap
from ._radiance_cache import RadianceCache

__all__ = ["FitProblem", "PreparedFit"]


class FitProblem(eqx.Module):
    """Everything the residual function needs, precomputed (a pytree; see :func:`prepare_fit`).

    Shapes: B readings, P = B·R² samples (R² pixels per reading; empty slots have object −1),
    O objects, L bands.
    """

    env: EnvironmentMap  # unit scale; the calibration multiplies
    receivers: GBuffer  # (P) the surface points seen
    cache: RadianceCache  # everything material-independent of the samples
    average: jax.Array  # (B, P) field averaging weights (rows sum to 1)
    background: jax.Array  # (B, L) mean env radiance of field pixels that miss every object
    reflectance: jax.Array  # (O, L) S(λ) as measured (SCI or SCE)
    sci: jax.Array  # (O,) 1.0 where the reflectance is SCI
    calibration: jax.Array  # (L,) k(λ)
    band: jax.Array  # (L, L) instrument band-pass (identity: none)
    measured: jax.Array  # (B, L) mean reading
    sigma: jax.Array  # (B, L) standard error of the mean reading
    values: jax.Array  # (O, 6) physical parameters (start values; fixed ones stay)
    free: tuple[tuple[int, int], ...] = eqx.field(static=True)  # (object, parameter) pairs
    fit_scale: bool = eqx.field(static=True)
    models: tuple[tuple[str, str], ...] = eqx.field(static=True)  # (distribution, geometry)/obj
    interreflection: bool = eqx.field(static=True, default=False)

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
    """Host-side companions of a :class:`FitProblem`."""

    problem: FitProblem
    session: Session
    objects: tuple[str, ...]
    geometries: list[ObjectGeometry]
    coverage: np.ndarray  # (B,) fraction of the field on the named object
    warnings: list[str]
    seconds: float
