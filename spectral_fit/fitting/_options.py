"""Options of the fit (:class:`FitOptions`), the solvers it can choose, and the check of
keyword overrides (removed or unknown option names raise ``InputError``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax.numpy as jnp

from .._runtime.errors import InputError

__all__ = ["FitOptions", "SOLVERS"]


SOLVERS = ("compact", "optimistix")


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """Options of :func:`fit` (all keyword arguments of :func:`fit` too).

    Attributes:
        spot_resolution: R, the spot camera's R×R pixels (disc inscribed).
        starts: number of starting points (the first is the session's/config's start).
        max_steps: Levenberg–Marquardt iterations per start.
        rtol, atol: optimistix LM tolerances on the unconstrained parameters.
        kinds: the reading kinds used in the fit ("object", "interreflection", and "image":
            the bins of the session's camera photographs).
        interreflection: "auto" (the scene's mode when the interreflection module exists),
            or "none".
        bootstrap: bootstrap resamples over readings (0: skip).
        aim_step_m: aim shift for the aiming-sensitivity finite differences.
        holdout: also fit on object-colour readings only and predict the others.
        seed: random seed (starts, bootstrap).
        dtype: float32 (default) or float64 (inside ``jax.enable_x64``).
        compress_tol: the gloss lookups run in the map's own principal spectra, as many as
            keep every texel within this relative error (see ``EnvironmentMap.from_array``);
            3e-3 keeps 28 of 81 on the bundled map (far fewer channels per lookup), gloss
            error 0.07 % of peak.
        cache: node layout of the radiance cache
            (:class:`spectral_fit.fitting.CacheOptions`).
        profile: also compute profile-likelihood intervals of every free parameter
            (:mod:`spectral_fit.fitting._profile`: the fit repeated with the parameter held
            at 10 values around its estimate, then 10 around the interval's ends; one more
            compiled program).
        solver: "compact" (default; :class:`CompactLM`, the Levenberg–Marquardt iteration of
            optimistix in one small compiled loop) or "optimistix"
            (``optimistix.LevenbergMarquardt`` with a Cholesky normal-equation solve); both
            reach the same optimum (tested), "compact" compiles in less time.
        errors: "robust" (default): each standard error the larger of the linearised one,
            (JᵀJ)⁻¹ · max(1, χ²/dof), and the one from leaving each reading out in turn
            (the readings as clusters), which counts an error shared by a reading's bands
            (the model's level at a spot) once per reading instead of once per band;
            "linear": the linearised one alone.

    The former options ``jacobian`` (the Jacobian is always exact forward-mode autodiff) and
    ``ir_rounds`` (the interreflection term is inside the model, no refresh rounds) were
    removed; naming them raises :class:`~spectral_fit._runtime.errors.InputError`.
    """

    spot_resolution: int = 8
    starts: int = 3
    max_steps: int = 50
    rtol: float = 1e-4
    atol: float = 1e-5
    kinds: tuple[str, ...] = ("object", "interreflection", "image")
    interreflection: str = "auto"
    bootstrap: int = 0
    aim_step_m: float = 0.001
    holdout: bool = True
    seed: int = 0
    dtype: Any = jnp.float32
    compress_tol: float = 3e-3
    cache: Any = None
    solver: str = "compact"
    profile: bool = False
    errors: str = "robust"


_REMOVED_OPTIONS = {
    "jacobian": "the Jacobian is always exact forward-mode autodiff of the cached model",
    "ir_rounds": "the interreflection term is inside the forward model and its Jacobian, so "
                 "there are no refresh rounds",
}


def _fit_options(options: FitOptions | None, kwargs: dict[str, Any]) -> FitOptions:
    """``options`` with the keyword overrides applied; removed or unknown option names raise
    :class:`InputError` naming the option."""
    for k in kwargs:
        if k in _REMOVED_OPTIONS:
            raise InputError(f"the option {k!r} was removed: {_REMOVED_OPTIONS[k]}; drop it",
                             field=k)
        if k not in FitOptions.__dataclass_fields__:
            raise InputError(f"unknown fit option {k!r}; known: "
                             f"{sorted(FitOptions.__dataclass_fields__)}", field=k)
    opts = dataclasses.replace(options or FitOptions(), **kwargs)
    if opts.solver not in SOLVERS:
        raise InputError(f"unknown solver {opts.solver!r}; choose one of {SOLVERS}",
                         field="solver")
    if opts.errors not in ("robust", "linear"):
        raise InputError(f"must be 'robust' or 'linear', got {opts.errors!r}", field="errors")
    return opts
