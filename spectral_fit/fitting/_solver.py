"""The fit's least-squares solvers: :class:`CompactLM` (default) and
``optimistix.LevenbergMarquardt``, batches of starts (:func:`solve_batch`) and of reading sets.

Why Levenberg–Marquardt: the problem is a small (≤ ~20 unknowns), smooth, over-determined
(readings × bands ≫ unknowns) nonlinear least-squares problem whose residuals are near zero at
the solution, which is Gauss–Newton's home ground (quadratic convergence near the optimum with
a Jacobian from ``jax.jacfwd``, cheap for few unknowns); the damping keeps it stable far from
the optimum where β and n (through F0) trade off and JᵀJ is nearly singular. Plain
Gauss–Newton diverged from poor starts in that valley; BFGS on the summed squares needed many
more residual evaluations.

Shapes: S starts, F unknowns y, B readings, L bands; residuals (B·L,), Jacobian (B·L, F).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._model import predict, reading_residuals, whiten_correlated
from ._options import FitOptions
from ._params import physical_from_y, prior_residuals
from ._problem import FitProblem

__all__ = ["CompactLM", "make_solver", "solve_batch", "solve_frozen"]


_PROGRESS: list[Callable[[np.ndarray, np.ndarray], None]] = []


def _emit(step: Any, loss: Any) -> None:
    if _PROGRESS:
        _PROGRESS[-1](np.asarray(step), np.asarray(loss))


def _verbose(**kwargs: Any) -> None:
    jax.debug.callback(_emit, kwargs["num_steps"][1], kwargs["loss_last_accepted_step"][1])


class CompactLM(eqx.Module):
    """Levenberg–Marquardt as one ``lax.while_loop`` over an explicit forward-mode Jacobian
    (the fit's default solver).

    The iteration of ``optimistix.LevenbergMarquardt`` with two changes: every damped step
    solves (JᵀJ + λI) δ = −Jᵀr by Cholesky of the F×F normal matrix; a step is accepted when
    the actual reduction of ½|r|² is more than 0.01 of the Gauss–Newton model's prediction;
    λ starts at 1 and is divided by 3.5 after a step predicted within 1 % (optimistix's
    classical trust region), and after a rejection it becomes max(4λ, τ max (JᵀJ)_ii) with
    τ = 1e-4, where optimistix multiplies by 4 (the bundled session's first Gauss–Newton steps
    overshoot: optimistix spent 5 rejections climbing from λ = 1). Termination: optimistix's
    Cauchy test on accepted steps (|Δy| < atol + rtol |y| and |Δr| < atol + rtol |r|
    elementwise), or, after a rejection, a next step already below the tolerance on y (the
    round-off floor; optimistix kept shrinking the step for ~10 more evaluations). What gets
    compiled is small: the residuals and their Jacobian come from one ``jax.jacfwd`` of the
    forward model (10 tangents through the cache's custom JVP), where optimistix linearises
    the model and transposes the linearisation for Jᵀr and JᵀJ.

    Attributes:
        rtol, atol: termination tolerances on y and on the residuals.
        verbose: report (step, cost) per iteration through a host callback while solving
            (a program with a host callback is never stored by JAX's persistent
            compilation cache; :func:`~spectral_fit.fitting.fit` leaves it off and prints
            the solve's ``history`` instead).
    """

    rtol: float = eqx.field(static=True)
    atol: float = eqx.field(static=True)
    verbose: bool = eqx.field(static=True, default=False)


def make_solver(opts: FitOptions, progress: bool) -> Any:
    """The solver named by ``opts.solver``: :class:`CompactLM` ("compact", default) or
    ``optimistix.LevenbergMarquardt`` ("optimistix") whose damped steps solve the normal
    equations (JᵀJ + λI) δ = −Jᵀr by Cholesky (``lineax.Normal(lineax.Cholesky())``): with ~10
    unknowns and ~1500 residuals this is a 10×10 factorisation per step, where the default
    QR of the materialised (B·L + F) × F augmented operator makes each iteration several
    times slower (same optimum).
    Forming JᵀJ squares the condition number; the damping keeps it positive definite, and
    the float64 exact-recovery test still reaches 1e-6."""
    if opts.solver == "compact":  # opts come from _fit_options, which checked the name
        return CompactLM(rtol=opts.rtol, atol=opts.atol, verbose=progress)
    import lineax as lx
    import optimistix as optx

    return optx.LevenbergMarquardt(rtol=opts.rtol, atol=opts.atol,
                                   linear_solver=lx.Normal(lx.Cholesky()),
                                   verbose=_verbose if progress else False)


def _residuals_aux(y: jax.Array, problem: FitProblem, reading_weights: jax.Array
                   ) -> tuple[jax.Array, jax.Array]:
    vals, scale = physical_from_y(problem, y)
    pred = predict(problem, vals, scale)
    r = reading_residuals(pred, problem, reading_weights).reshape(-1)
    return jnp.concatenate([r, prior_residuals(problem, y)]), pred


def _residuals_jacobian(y: jax.Array, problem: FitProblem, reading_weights: jax.Array
                        ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Weighted residuals (B·L + K,) (the readings', then the K priors' rows), their
    Jacobian (B·L + K, F) w.r.t. y (``jax.jacfwd``: the model evaluated once, its F tangents
    batched) and the predicted readings (B, L)."""
    def model(yy: jax.Array) -> tuple[tuple[jax.Array, jax.Array], jax.Array]:
        vals, scale = physical_from_y(problem, yy)
        p = predict(problem, vals, scale)
        return (p, prior_residuals(problem, yy)), p

    (jp, jq), pred = jax.jacfwd(model, has_aux=True)(y)  # (B, L, F), (K, F); (B, L)
    rd = problem.readings
    r = reading_residuals(pred, problem, reading_weights).reshape(-1)
    J = (whiten_correlated(jp / rd.sigma[..., None], rd, pred)
         * jnp.sqrt(reading_weights)[:, None, None]).reshape(r.shape[0], y.shape[0])
    return (jnp.concatenate([r, prior_residuals(problem, y)]), jnp.concatenate([J, jq]),
            pred)


def _compact_lm(problem: FitProblem, y0: jax.Array, w: jax.Array, solver: CompactLM,
                max_steps: int, frozen: jax.Array | None = None) -> dict[str, jax.Array]:
    """:class:`CompactLM` from ``y0`` (see there); returns the final state's y, residuals,
    Jacobian, predicted readings, step count, whether it terminated (converged) and the
    cost ½|r|² after each step (``history`` (max_steps,), NaN beyond the last step).
    ``frozen`` (F,) bool: unknowns held at their start value (their rows and columns of the
    normal equations replaced by the identity's, their gradient by 0: every step leaves them
    where they are), for profile likelihoods."""
    dt = y0.dtype
    F = y0.shape[0]
    tau = 1e-4  # the damping after a rejection is at least τ max (JᵀJ)_ii
    # residuals (B·L + K,), Jacobian (B·L + K, F), predictions (B, L)
    B, L = problem.readings.measured.shape
    rdt = problem.readings.measured.dtype
    R = B * L + len(problem.prior)
    r0, j0, p0 = (jnp.zeros((R,), rdt), jnp.zeros((R, F), rdt), jnp.zeros((B, L), rdt))

    def cond(s: dict[str, jax.Array]) -> jax.Array:
        return jnp.logical_not(s["done"]) & (s["steps"] < max_steps)

    def body(s: dict[str, jax.Array]) -> dict[str, jax.Array]:
        r_e, j_e, p_e = _residuals_jacobian(s["y_eval"], problem, w)
        r, J = s["r"], s["J"]
        dy = s["y_eval"] - s["y"]
        rtr = jnp.sum(r * r)
        predicted = 0.5 * (jnp.sum((J @ dy + r) ** 2) - rtr)  # < 0: the model's reduction
        actual = 0.5 * (jnp.sum(r_e * r_e) - rtr)
        first = s["first"]
        neg = predicted < 0
        rho = jnp.where(neg, actual / jnp.where(neg, predicted, -1.0), -1.0)
        accept = first | (jnp.isfinite(actual) & (rho > 0.01))
        # the damping: ÷3.5 after a step the quadratic model predicted within 1 % (ρ > 0.99,
        # optimistix's rule); after a rejected step ×4, and at least τ max (JᵀJ)_ii of the
        # start (optimistix: ×4 only)
        lam = jnp.where(accept, s["lam"] * jnp.where(rho > 0.99, 1.0 / 3.5, 1.0),
                        jnp.maximum(s["lam"] * 4.0, tau * s["dmax"]))
        y_ok = jnp.max(jnp.abs(dy) / (solver.atol + solver.rtol * jnp.abs(s["y_eval"]))) < 1
        r_ok = jnp.max(jnp.abs(r_e - r) / (solver.atol + solver.rtol * jnp.abs(r_e))) < 1
        y = jnp.where(accept, s["y_eval"], s["y"])
        r = jnp.where(accept, r_e, r)
        J = jnp.where(accept, j_e, J)
        pred = jnp.where(accept, p_e, s["pred"])
        if solver.verbose:
            jax.debug.callback(_emit, s["steps"], 0.5 * jnp.sum(r * r))
        history = s["history"].at[s["steps"]].set(0.5 * jnp.sum(r * r).astype(rdt))
        A = (J.T @ J).astype(dt)
        g = (J.T @ r).astype(dt)
        if frozen is not None:
            keep = jnp.logical_not(frozen)
            A = (jnp.where(keep[:, None] & keep[None, :], A, 0.0)
                 + jnp.diag(jnp.where(keep, 0.0, 1.0).astype(dt)))
            g = jnp.where(keep, g, 0.0)
        dmax = jnp.where(first, jnp.max(jnp.diag(A)), s["dmax"])
        eye = jnp.eye(F, dtype=dt)
        chol = jax.scipy.linalg.cho_factor(A + lam * eye, lower=True)
        delta = jax.scipy.linalg.cho_solve(chol, g)
        # after a rejected step the next one is below the tolerance on y (the damping grew
        # at the round-off floor, e.g. of a zero-residual problem): nothing left to resolve
        small = (jnp.logical_not(accept)
                 & (jnp.max(jnp.abs(delta) / (solver.atol + solver.rtol * jnp.abs(y))) < 1))
        return {"y": y, "y_eval": y - delta, "r": r, "J": J, "pred": pred, "lam": lam,
                "dmax": dmax, "first": jnp.zeros((), bool),
                "done": (accept & jnp.logical_not(first) & y_ok & r_ok) | small,
                "steps": s["steps"] + 1, "history": history}

    s0 = {"y": y0, "y_eval": y0, "r": r0, "J": j0, "pred": p0,
          "lam": jnp.asarray(1.0, dt), "dmax": jnp.zeros((), dt), "first": jnp.ones((), bool),
          "done": jnp.zeros((), bool), "steps": jnp.zeros((), jnp.int32),
          "history": jnp.full((max_steps,), jnp.nan, rdt)}
    return jax.lax.while_loop(cond, body, s0)


@eqx.filter_jit
def solve_batch(problem: FitProblem, y0: jax.Array, rw: jax.Array, solver: Any,
                 max_steps: int) -> dict[str, jax.Array]:
    """Solve S problems (one after the other): starts ``y0 (S, F)``, reading weights
    ``rw (S, B)``.

    Returns a dict of (S, ...) arrays: y, cost, converged, steps, the residuals, their
    Jacobian w.r.t. y (from the solver's last accepted step, so no second trace of the model
    is compiled), the predicted readings (B, L) at y and, with :class:`CompactLM`, the cost
    after each step (``history`` (S, max_steps), NaN beyond a start's last step: the
    progress lines are printed from it after the solve, so the compiled program has no host
    callback and JAX's persistent compilation cache can store it).
    """
    def one(args: tuple[jax.Array, jax.Array]) -> dict[str, jax.Array]:
        return _solve_one(problem, args[0], args[1], solver, max_steps)

    # one start after the other (``lax.map``): each solve stops at its own convergence and
    # runs the unbatched model, whose per-point contractions are plain batched matrix
    # products (vmapped, they become much slower general dot products on the CPU)
    return jax.lax.map(one, (y0, rw))


def _solve_one(problem: FitProblem, y0: jax.Array, w: jax.Array, solver: Any,
               max_steps: int) -> dict[str, jax.Array]:
    """One least-squares solve from start ``y0`` with reading weights ``w`` (unbatched):
    y, cost, converged, steps, residuals, their Jacobian at the last accepted step and the
    predicted readings."""
    if isinstance(solver, CompactLM):
        s = _compact_lm(problem, y0, w, solver, max_steps)
        r = s["r"]
        cost = 0.5 * jnp.sum(r * r)
        fin = jnp.isfinite(cost)
        return {"y": s["y"], "cost": jnp.where(fin, cost, jnp.inf),
                "converged": s["done"] & fin, "steps": s["steps"], "residual": r,
                "jacobian": s["J"], "predicted": s["pred"], "history": s["history"]}
    import optimistix as optx

    sol = optx.least_squares(lambda y, ww: _residuals_aux(y, problem, ww), solver, y0,
                             args=w, has_aux=True, max_steps=max_steps, throw=False)
    info = sol.state.f_info
    r = info.residual
    cost = 0.5 * jnp.sum(r * r)
    ok = (sol.result == optx.RESULTS.successful) & jnp.isfinite(cost)
    return {"y": sol.value, "cost": jnp.where(jnp.isfinite(cost), cost, jnp.inf),
            "converged": ok, "steps": sol.stats["num_steps"], "residual": r,
            "jacobian": info.jac.as_matrix(), "predicted": sol.aux}


@eqx.filter_jit
def solve_frozen(problem: FitProblem, y0: jax.Array, rw: jax.Array, frozen: jax.Array,
                 solver: CompactLM, max_steps: int) -> dict[str, jax.Array]:
    """Solve S problems one after the other (``lax.map``), each with some unknowns held at
    their start: starts ``y0 (S, F)``, reading weights ``rw (S, B)``, ``frozen (S, F)`` bool.
    Returns (S, ...) arrays: y, cost (½ Σ r², +inf when not finite), converged, steps."""
    def one(args: tuple[jax.Array, jax.Array, jax.Array]) -> dict[str, jax.Array]:
        s = _compact_lm(problem, args[0], args[1], solver, max_steps, frozen=args[2])
        cost = 0.5 * jnp.sum(s["r"] * s["r"])
        fin = jnp.isfinite(cost)
        return {"y": s["y"], "cost": jnp.where(fin, cost, jnp.inf),
                "converged": s["done"] & fin, "steps": s["steps"]}

    return jax.lax.map(one, (y0, rw, frozen))


@eqx.filter_jit
def _solve_measured(problem: FitProblem, y0: jax.Array, rw: jax.Array, measured: jax.Array,
                    sigma: jax.Array, solver: Any, max_steps: int) -> dict[str, jax.Array]:
    """Like :func:`solve_batch` but each batch entry has its own readings (K, B, L) and σ."""
    def one(y0_: jax.Array, w: jax.Array, meas: jax.Array, sig: jax.Array
            ) -> dict[str, jax.Array]:
        pr = eqx.tree_at(lambda q: (q.readings.measured, q.readings.sigma), problem,
                         (meas, sig))
        out = _solve_one(pr, y0_, w, solver, max_steps)
        del out["predicted"]
        return out

    return jax.vmap(one)(y0, rw, measured, sigma)
