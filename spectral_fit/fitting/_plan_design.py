"""Experiment design of a measurement plan: each reading's sensitivity to the parameters, its
Fisher information in tolerance units, and the choice of K readings that minimises the worst
scaled parameter variance over a set of parameter draws (greedy, then exchange).

Shapes: B readings, P = B·d samples (d field pixels per reading), L bands, O objects,
F unknowns (free (object, parameter) pairs, then the global scale when it is fitted),
D parameter draws, N candidates. Radiance in W·sr⁻¹·m⁻²·nm⁻¹; the Fisher information of a
reading is in the unknowns scaled by their tolerances (:data:`TOLERANCES`), so its inverse's
diagonal is the variance in units of tolerance².
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..io import PARAMETERS
from ._problem import FitProblem

__all__ = [
    "TOLERANCES",
    "UNIDENTIFIED",
    "default_range",
    "draws_in_box",
    "reading_sensitivity",
    "reading_information",
    "scaled_variances",
    "plan_objective",
    "select_readings",
    "tolerances",
]

#: the precision a fit should reach per unknown: ("relative", fraction of the value) or
#: ("absolute", value); the design works in these units
TOLERANCES: dict[str, tuple[str, float]] = {
    "alpha": ("relative", 0.02),
    "beta": ("relative", 0.03),
    "chi": ("absolute", 0.01),
    "mu": ("relative", 0.03),
    "n": ("absolute", 0.02),
    "gamma": ("relative", 0.05),
    "scale": ("relative", 0.02),
}
#: a ridge on the information (tolerance⁻² units) that keeps it invertible while parameters
#: are not yet determined; a scaled variance above :data:`UNIDENTIFIED` counts as unidentified
RIDGE = 1e-8
UNIDENTIFIED = 1e6


def tolerances(values: np.ndarray, free: Sequence[tuple[int, int]], *,
               scale: np.ndarray | None = None) -> np.ndarray:
    """(D, F) tolerance of each unknown at each draw (physical units; :data:`TOLERANCES`,
    relative ones of the draw's value, at least 1e-6) for ``values`` (D, O, 6) and, when the
    scale is an unknown, ``scale`` (D,)."""
    values = np.asarray(values, np.float64)
    cols = []
    for o, k in free:
        kind, t = TOLERANCES[PARAMETERS[k]]
        cols.append(np.maximum(t * np.abs(values[:, o, k]), 1e-6) if kind == "relative"
                    else np.full(values.shape[0], t))
    if scale is not None:
        cols.append(np.maximum(TOLERANCES["scale"][1] * np.abs(np.asarray(scale)), 1e-6))
    return np.stack(cols, -1)


def _half_weights(res: int) -> tuple[np.ndarray, np.ndarray]:
    """(2, d) weights of the field's pixels for the difference of the right and left (top and
    bottom) halves of the field's mean, and (2,) the distance between the halves' centroids
    in units of the field's radius (the disc pixels of :func:`disc_pixels`, row-major)."""
    from ._spots import disc_pixels

    keep = disc_pixels(res)
    c = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    X, Y = np.meshgrid(c, -c)
    xs, ys = X.reshape(-1)[keep], Y.reshape(-1)[keep]
    w, sep = [], []
    for a in (xs, ys):
        pos, neg = a > 1e-9, a < -1e-9
        w.append(pos / max(pos.sum(), 1) - neg / max(neg.sum(), 1))
        sep.append(a[pos].mean() - a[neg].mean() if pos.any() and neg.any() else 1.0)
    return np.asarray(w), np.asarray(sep)


@eqx.filter_jit
def _sensitivity(problem: FitProblem, values: jax.Array, scale: jax.Array,
                 free: tuple[tuple[int, int], ...], fit_scale: bool, halves: jax.Array
                 ) -> tuple[jax.Array, jax.Array, jax.Array]:
    from ._cache_model import cached_radiance
    from ._model import _reflectances

    g = problem.receivers
    B = problem.readings.average.rows
    obj = jnp.maximum(g.object, 0)
    o_idx = np.array([o for o, _ in free], np.int32)
    k_idx = np.array([k for _, k in free], np.int32)
    inst = problem.instrument

    def samples(vals: jax.Array) -> jax.Array:
        S = _reflectances(problem, vals)
        rad, _ = cached_radiance(problem.cache, vals, S, obj, problem.surfaces.models,
                                 interreflection=problem.interreflection)
        return jnp.where(g.valid[:, None], rad, 0.0).reshape(B, -1, rad.shape[-1])

    def mean(p: jax.Array, vals: jax.Array, s: jax.Array) -> jax.Array:
        vals = vals.at[o_idx, k_idx].set(p[:len(free)])
        if fit_scale:
            s = p[-1]
        m = samples(vals).mean(axis=1) + problem.readings.background
        return inst.calibration * s * (m @ inst.band.T)

    def one(vals: jax.Array, s: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        p = vals[o_idx, k_idx]
        if fit_scale:
            p = jnp.concatenate([p, s[None]])
        m = mean(p, vals, s)
        J = jax.jacfwd(mean)(p, vals, s)  # (B, L, F)
        dif = jnp.einsum("hd,bdl->bhl", halves, samples(vals)) @ inst.band.T
        return m, J, inst.calibration * s * dif

    return jax.lax.map(lambda a: one(*a), (values, scale))


def reading_sensitivity(problem: FitProblem, values: np.ndarray, *,
                        free: Sequence[tuple[int, int]], fit_scale: bool = False,
                        scale: np.ndarray | None = None, aim_distances: np.ndarray,
                        field_angles_deg: np.ndarray, spot_resolution: int
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each reading's predicted mean radiance, its Jacobian and its aiming gradient, at each
    parameter draw, through the fit's forward model (the radiance cache of ``problem``).

    Args:
        problem: a prepared problem whose readings are the ones to assess.
        values: (D, O, 6) physical parameters of each draw.
        free: the (object, parameter) pairs to differentiate by (the unknowns, in order).
        fit_scale: whether the global environment scale is an unknown too (the last one).
        scale: (D,) the global scale of each draw (default 1).
        aim_distances: (B,) instrument to aim point (m).
        field_angles_deg: (B,) full field angles.
        spot_resolution: R of the prepared fields (R×R camera, disc pixels).

    Returns:
        mean (D, B, L) radiance; J (D, B, L, F) ∂mean/∂unknown (physical units);
        grad (D, B, L, 2) ∂mean/∂aim shift (per metre across the measuring axis, in the
        field's two image directions): the difference of the means of the field's two
        halves over the distance between their centroids at the aim point (the same pixel
        samples, so a reading on a highlight's edge has a large gradient).
    """
    D = np.asarray(values).shape[0]
    dt = problem.values.dtype
    s = np.ones(D) if scale is None else np.asarray(scale, np.float64)
    w, sep = _half_weights(spot_resolution)
    m, J, dif = _sensitivity(problem, jnp.asarray(values, dt), jnp.asarray(s, dt),
                             tuple((int(o), int(k)) for o, k in free), bool(fit_scale),
                             jnp.asarray(w, dt))
    radius = np.asarray(aim_distances) * np.tan(np.radians(np.asarray(field_angles_deg)) / 2)
    step = sep[None, :] * radius[:, None]  # (B, 2) metres between the halves' centroids
    grad = np.asarray(dif, np.float64) / step[None, :, :, None]
    return (np.asarray(m, np.float64), np.asarray(J, np.float64),
            np.moveaxis(grad, 2, 3))


def reading_information(J: np.ndarray, sigma: np.ndarray, grad: np.ndarray, tol: np.ndarray,
                        *, sigma_aim_m: float, level: float | np.ndarray = 0.0,
                        tilt: float | np.ndarray = 0.0,
                        mean: np.ndarray | None = None) -> np.ndarray:
    """(D, B, F, F) Fisher information of each reading in tolerance units.

    The reading's error covariance is diag(σ²) + σ_aim² (g_u g_uᵀ + g_v g_vᵀ) + level² m mᵀ:
    independent noise per band, an aiming error of σ_aim in each direction across the axis,
    which moves every band together (g the aiming gradient), and the model's error common to
    the reading's bands, a fraction ``level`` of its radiance m, and a ``tilt`` t² (m∘x)(m∘x)ᵀ
    with x from −1 at the first band to +1 at the last (the fit's ``[model_error.level]``,
    ``[model_error.tilt]``: docs/measurements.md); its inverse by the Woodbury identity.

    Args:
        J: (D, B, L, F) Jacobian (physical units); sigma: (D, B, L) or (B, L) noise of the
            mean reading; grad: (D, B, L, 2) aiming gradient (per metre); tol: (D, F)
            tolerances; sigma_aim_m: aiming error (m, 1σ per direction); level, tilt: the
            model's level and tilt errors (fractions), one for every reading or (B,) one per
            reading; mean: (D, B, L) or (B, L) the readings' radiance (needed when ``level``
            or ``tilt`` > 0).
    """
    sig = np.broadcast_to(sigma, J.shape[:3])
    B = J.shape[1]
    lev = np.broadcast_to(np.asarray(level, np.float64), (B,))[None, :, None]
    til = np.broadcast_to(np.asarray(tilt, np.float64), (B,))[None, :, None]
    Jt = J * tol[:, None, None, :] / sig[..., None]  # whitened, tolerance units
    cols = []
    if sigma_aim_m > 0:
        cols.append(grad * sigma_aim_m / sig[..., None])  # (D, B, L, 2)
    if (np.any(lev > 0) or np.any(til > 0)) and mean is None:
        raise ValueError("a level or tilt error needs the readings' radiance (mean)")
    if np.any(lev > 0):
        cols.append((lev * np.broadcast_to(mean, J.shape[:3]) / sig)[..., None])
    if np.any(til > 0):
        x = np.linspace(-1.0, 1.0, J.shape[2])
        cols.append((til * np.broadcast_to(mean, J.shape[:3]) * x / sig)[..., None])
    info = np.einsum("dblf,dblg->dbfg", Jt, Jt)
    if cols:
        G = np.concatenate(cols, axis=-1)  # (D, B, L, H)
        GJ = np.einsum("dblh,dblf->dbhf", G, Jt)  # (D, B, H, F)
        core = np.eye(G.shape[-1]) + np.einsum("dblh,dblk->dbhk", G, G)
        info = info - np.einsum("dbhf,dbhk,dbkg->dbfg", GJ, np.linalg.inv(core), GJ)
    return 0.5 * (info + np.swapaxes(info, -1, -2))


def scaled_variances(info: np.ndarray) -> np.ndarray:
    """(..., F) diagonal of the inverse of ``info`` (..., F, F) + :data:`RIDGE` I: each
    unknown's variance in tolerance² units (≥ :data:`UNIDENTIFIED`: not determined)."""
    F = info.shape[-1]
    M = info + RIDGE * np.eye(F)
    try:
        return np.diagonal(np.linalg.inv(M), axis1=-2, axis2=-1).copy()
    except np.linalg.LinAlgError:
        return np.diagonal(np.linalg.pinv(M, hermitian=True), axis1=-2, axis2=-1).copy()


def plan_objective(info: np.ndarray, *, mask: np.ndarray | None = None) -> float:
    """The design criterion: the worst scaled variance over the draws and the unknowns
    named by ``mask`` (F,) (default all) of the total information ``info`` (D, F, F)."""
    v = scaled_variances(info)
    return float(np.max(v if mask is None else v[..., np.asarray(mask, bool)]))


def _soft(v: np.ndarray, p: float = 8.0) -> np.ndarray:
    """log of the p-power mean of the variances over draws and unknowns (last two axes): a
    smooth stand-in for the worst one that still counts every unidentified unknown."""
    lv = np.log(np.maximum(v, 1e-300)) * p
    m = lv.max(axis=(-2, -1), keepdims=True)
    return (m[..., 0, 0] + np.log(np.exp(lv - m).sum(axis=(-2, -1)))) / p


def _scores(base: np.ndarray, cand: np.ndarray, mask: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """(N,) worst and smooth criterion after adding each candidate's information to
    ``base`` (D, F, F); ``cand`` (N, D, F, F)."""
    v = scaled_variances(base[None] + cand)[..., mask]
    return v.max(axis=(-2, -1)), _soft(v)


def select_readings(candidates: np.ndarray, budget: int, *, base: np.ndarray | None = None,
                    mask: np.ndarray | None = None, max_passes: int = 20, starts: int | None = None,
                    progress: Callable[[str], None] | None = None) -> tuple[list[int], float]:
    """Choose ``budget`` of N candidates (without repeats) minimising :func:`plan_objective`
    of ``base`` + the chosen informations.

    Greedy (each step adds the candidate with the lowest smooth criterion, a p-power mean
    of the scaled variances, which also rewards identifying a parameter while others are
    still undetermined), then exchange passes (swap a chosen reading for any other while
    the worst scaled variance drops, ties broken by the smooth criterion) until none helps;
    from ``starts`` first readings (the best ``starts`` by the smooth criterion), keeping the
    best result: one greedy path can end in a local optimum of single exchanges far from the
    best (when the budget leaves parameters nearly undetermined, a parameter may need two
    particular readings at once).

    Args:
        candidates: (N, D, F, F) each candidate's information (tolerance units).
        base: (D, F, F) information already there (existing readings, priors); default 0.
        mask: (F,) unknowns the criterion looks at (default all; e.g. not the scale).
        starts: first readings to start the greedy from (at least 1; default every
            candidate when there are at most 64, else 1).

    Returns:
        the chosen indices (in the order chosen) and the criterion's value.
    """
    N, D, F, _ = candidates.shape
    if not 1 <= budget <= N:
        from .._runtime.errors import InputError

        raise InputError(f"must be in [1, {N}] (the number of candidates), got {budget}",
                         field="budget")
    base = np.zeros((D, F, F)) if base is None else np.asarray(base, np.float64)
    mask = np.ones(F, bool) if mask is None else np.asarray(mask, bool)
    say = progress or (lambda _m: None)
    _, soft0 = _scores(base, candidates, mask)
    n_starts = (N if N <= 64 else 1) if starts is None else max(1, int(starts))
    firsts = [int(c) for c in np.argsort(soft0, kind="stable")[:n_starts]]
    best_key, best_chosen = None, None
    for k, first in enumerate(firsts):
        key, chosen = _greedy_exchange(candidates, budget, base, mask, first, max_passes,
                                       say if k == 0 else (lambda _m: None))
        if best_key is None or key < best_key:
            best_key, best_chosen = key, chosen
        if len(firsts) > 1:
            say(f"start {k + 1}/{len(firsts)}: worst scaled variance {key[0]:.4g}")
    assert best_chosen is not None
    total = base + candidates[best_chosen].sum(axis=0)
    return best_chosen, plan_objective(total, mask=mask)


def _greedy_exchange(candidates: np.ndarray, budget: int, base: np.ndarray, mask: np.ndarray,
                     first: int, max_passes: int, say: Callable[[str], None]
                     ) -> tuple[tuple[float, float], list[int]]:
    """One greedy path from ``first`` and its exchange passes: ((worst, smooth), chosen)."""
    chosen = [first]
    total = base + candidates[first]
    say(f"greedy 1/{budget}: candidate {first}")
    for step in range(1, budget):
        _, soft = _scores(total, candidates, mask)
        soft[chosen] = np.inf
        c = int(np.argmin(soft))
        chosen.append(c)
        total = total + candidates[c]
        say(f"greedy {step + 1}/{budget}: candidate {c}")
    best = (plan_objective(total, mask=mask), float(_soft(scaled_variances(total)[..., mask])))
    for npass in range(max_passes):
        improved = False
        for i in range(budget):
            rest = total - candidates[chosen[i]]
            worst, soft = _scores(rest, candidates, mask)
            worst[chosen] = np.inf
            soft[chosen] = np.inf
            order = np.lexsort((soft, worst))
            c = int(order[0])
            key = (float(worst[c]), float(soft[c]))
            if key[0] < best[0] * (1 - 1e-9) or (key[0] <= best[0] and key[1] < best[1] - 1e-9):
                chosen[i] = c
                total = rest + candidates[c]
                best = key
                improved = True
        say(f"exchange pass {npass + 1}: worst scaled variance {best[0]:.4g}")
        if not improved:
            break
    return best, chosen


def draws_in_box(centre: np.ndarray, lower: np.ndarray, upper: np.ndarray, *, n: int,
                 seed: int = 0) -> np.ndarray:
    """(n, F) parameter draws spanning the box [lower, upper] (F,): the centre first, then a
    Latin hypercube of n − 1 points (each unknown's range cut into n − 1 strata, one draw in
    each, shuffled independently per unknown)."""
    rng = np.random.default_rng(seed)
    F = centre.size
    out = [np.asarray(centre, np.float64)]
    if n > 1:
        u = (np.stack([rng.permutation(n - 1) for _ in range(F)], -1)
             + rng.random((n - 1, F))) / (n - 1)
        out += list(lower + u * (upper - lower))
    return np.stack(out)


def default_range(name: str, centre: float) -> tuple[float, float]:
    """The range a parameter is assumed to lie in without a session that says otherwise
    (``docs/planning.md``): α ×/÷ 1.25, β, μ, γ, scale ×/÷ 1.5, χ ± 0.05 (≥ 0), n ± 0.1
    (> 1)."""
    if name == "alpha":
        return centre / 1.25, centre * 1.25
    if name in ("beta", "mu", "gamma", "scale"):
        return centre / 1.5, centre * 1.5
    if name == "chi":
        return max(0.0, centre - 0.05), centre + 0.05
    if name == "n":
        return max(1.0 + 1e-3, centre - 0.1), centre + 0.1
    raise KeyError(name)


def stderr_from_information(info: np.ndarray, tol: np.ndarray) -> np.ndarray:
    """(..., F) standard errors in physical units (inf where unidentified) from the
    information ``info`` (..., F, F) in tolerance units and the tolerances (..., F)."""
    v = scaled_variances(info)
    se = np.sqrt(np.maximum(v, 0.0)) * tol
    return np.where(v >= UNIDENTIFIED, math.inf, se)
