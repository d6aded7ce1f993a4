"""Fit α, β, χ, μ, n (and γ) of each object to spectroradiometer readings.

Pipeline (geometry and poses are fixed while materials are fitted):

1. :func:`prepare_fit` — outside ``jit``, once per session: builds the scene's meshes and the
   environment map, rasterises every reading's measuring field from the instrument's pose (a
   square camera whose field of view is the field angle; pixels inside the inscribed disc), and
   stores a :class:`~spectral_fit.geometry.GBuffer` of the surface points seen, their
   material-independent radiance cache (:mod:`spectral_fit.fitting`: exact visible
   irradiance, mirror-direction radiance, fixed gloss nodes with their radiance, and the
   interreflection probes on the neighbours), the environment radiance of pixels that miss
   every object, the environment calibration k(λ) and the reading weights. The result is a
   :class:`FitProblem` pytree.
2. :func:`predict` — the forward model, jit-compiled, per reading b (mean over its field):

       M_b(λ) = k(λ) · B ∘ mean_p∈field(b) [ α S(λ) E(λ, N_p)/π + β ∫ L F D G/(4 cosθr) dω
                                         + χ F(n, θr) L(λ, R_p) + I_p(λ) ]

   (eq. 5 in our physical reading; I_p the light of the neighbours, eq. 6 in the gather
   reading, when the scene's interreflection mode is not "none" and every object is a
   sphere; every term is a weighted sum of cached radiances with weights from F, D, G, so
   the Jacobian is exact autodiff, interreflection included; B the instrument's band-pass,
   :func:`band_matrix`). With ``geometry = "SCI"`` reflectance, S = max(S_SCI − F(n, 8°), 0).
3. :func:`fit` — weighted least squares by Levenberg–Marquardt (:class:`CompactLM`, the
   iteration of ``optimistix.LevenbergMarquardt`` in one small compiled loop, or optimistix
   itself with ``solver="optimistix"``), several starts solved one after the other in one
   program, uncertainties from the Jacobian, a bootstrap over
   readings, identifiability warnings, the sensitivity of each reading to aiming error, and
   the hold-out prediction of interreflection readings from a fit on object-colour readings.

Parametrisation (unconstrained y → physical p): α, β, μ = exp(y); χ, γ = y² (0 is reachable);
n = 1 + exp(y); the global environment scale (calibration "global") = exp(y).

Why Levenberg–Marquardt: the problem is a small (≤ ~20 unknowns), smooth, over-determined
(readings × bands ≫ unknowns) nonlinear least-squares problem whose residuals are near zero at
the solution, which is Gauss–Newton's home ground (quadratic convergence near the optimum with
a Jacobian from ``jax.jacfwd``, cheap for few unknowns); the damping keeps it stable far from
the optimum where β and n (through F0) trade off and JᵀJ is nearly singular. Plain
Gauss–Newton diverged from poor starts in that valley; BFGS on the summed squares needed many
more residual evaluations.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from ..geometry import GBuffer, ObjectGeometry
from ..io import PARAMETERS, Session

__all__ = [
    "CompactLM",
    "SOLVERS",
    "FitProblem",
    "FitResult",
    "FitOptions",
    "prepare_fit",
    "predict",
    "residuals",
    "fit",
    "scene_geometry",
    "scene_environment",
    "to_physical",
    "to_unconstrained",
    "PARAM_INDEX",
    "fit_many",
    "simulate_readings",
    "disc_pixels",
    "band_matrix",
    "interreflection_term",
    "with_interreflection",
    "physical_from_y",
    "solve_batch",
    "make_solver",
    "y_start",
    "PARAMETERS",
]

PARAM_INDEX = {k: i for i, k in enumerate(PARAMETERS)}
_SCI_ANGLE_DEG = 8.0  # d/8° spectrophotometers: specular component reflected at 8°


# ----------------------------------------------------------------------------- scene helpers


def scene_geometry(scene: Any) -> list[ObjectGeometry]:
    """World-space meshes of the scene's objects (config order), as :class:`ObjectGeometry`."""
    out = []
    for o in scene.objects:
        mw = o.make_mesh(world=True)
        out.append(ObjectGeometry(vertices=jnp.asarray(mw.vertices, jnp.float32),
                                  normals=jnp.asarray(mw.normals, jnp.float32),
                                  triangles=jnp.asarray(mw.triangles, jnp.int32),
                                  centre=jnp.asarray(o.position, jnp.float32)))
    return out


def scene_environment(scene: Any, *, dtype: Any = jnp.float32, compress_tol: float = 1e-4
                      ) -> Any:
    """The scene's environment map on its wavelength grid (config scale and rotation applied)."""
    from ..color import resample
    from ..lighting import EnvironmentMap

    spec = scene.environment
    wl = scene.wavelengths
    from ..io import read_spectral_exr

    try:
        wl_in, img = read_spectral_exr(spec.file)
        img = resample(wl_in, np.asarray(img, np.float64), wl, path=spec.file,
                       field="environment")
    except InputError as exc:
        if "spectral" not in str(exc).lower() and "channel" not in str(exc).lower():
            raise
        from ..lighting import read_rgb_environment

        _, img = read_rgb_environment(spec.file, wl, method=spec.upsampling)
    img = np.asarray(img, np.float64) * spec.scale
    return EnvironmentMap.from_array(img, rotation_y_deg=spec.rotation_y_deg, dtype=dtype,
                                     compress_tol=compress_tol, path=str(spec.file))


# ----------------------------------------------------------------------------- parametrisation


# the unconstrained parametrisation: p = y² for these, p = offset + exp(y) for the others
_SQUARED = ("chi", "gamma")
_EXP_OFFSET = {"alpha": 0.0, "beta": 0.0, "mu": 0.0, "scale": 0.0, "n": 1.0}


def to_physical(y: Any, name: str) -> Any:
    """Unconstrained y → physical parameter (see the module docstring)."""
    if name in _SQUARED:
        return y * y
    if name in _EXP_OFFSET:
        return _EXP_OFFSET[name] + jnp.exp(y)
    raise KeyError(name)


def to_unconstrained(p: float, name: str) -> float:
    """Physical parameter → unconstrained y (inverse of :func:`to_physical`; χ, γ >= 0 map to
    √p, and 0 is moved to a small positive start so the gradient does not vanish)."""
    if name in ("alpha", "beta", "mu", "scale"):
        return math.log(max(p, 1e-6))
    if name in _SQUARED:
        return math.sqrt(max(p, 1e-4))
    if name == "n":
        return math.log(max(p - 1.0, 1e-6))
    raise KeyError(name)


# ----------------------------------------------------------------------------- the problem


class FitProblem(eqx.Module):
    """Everything the residual function needs, precomputed (a pytree; see :func:`prepare_fit`).

    Shapes: B readings, P = B·R² samples (R² pixels per reading; empty slots have object −1),
    O objects, L bands.
    """

    env: Any  # EnvironmentMap (unit scale; the calibration multiplies)
    receivers: GBuffer  # (P) the surface points seen
    cache: Any  # RadianceCache: everything material-independent of the samples
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


def physical_from_y(problem: FitProblem, y: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(O, 6) physical parameters (fixed ones from ``problem.values``) and the global scale
    at unconstrained ``y`` (:func:`to_physical`, all free parameters in one vector op)."""
    vals = problem.values
    if problem.free:
        kinds = [PARAMETERS[k] for _, k in problem.free]
        sq = np.array([k in _SQUARED for k in kinds])
        shift = np.array([0.0 if k in _SQUARED else _EXP_OFFSET[k] for k in kinds])
        yf = y[:len(kinds)]
        p = jnp.where(sq, yf * yf, shift.astype(vals.dtype) + jnp.exp(yf))
        o_idx = np.array([o for o, _ in problem.free])
        k_idx = np.array([k for _, k in problem.free])
        vals = vals.at[o_idx, k_idx].set(p)
    scale = to_physical(y[-1], "scale") if problem.fit_scale else jnp.ones((), vals.dtype)
    return vals, scale


def _physical_from_p(problem: FitProblem, p: jax.Array) -> tuple[jax.Array, jax.Array]:
    vals = problem.values
    for j, (o, k) in enumerate(problem.free):
        vals = vals.at[o, k].set(p[j])
    scale = p[-1] if problem.fit_scale else jnp.ones((), vals.dtype)
    return vals, scale


def _reflectances(problem: FitProblem, values: jax.Array) -> jax.Array:
    """(O, L) Lambert S(λ) of the objects for physical parameters ``values (O, 6)``: the
    measured reflectance, minus the first-surface reflection F(n, 8°) where it is SCI."""
    from ..lighting import fresnel_dielectric

    cos8 = math.cos(math.radians(_SCI_ANGLE_DEG))
    f8 = fresnel_dielectric(jnp.full_like(values[:, 4], cos8), values[:, 4])  # (O,)
    s = problem.reflectance
    return jnp.where(problem.sci[:, None] > 0, jnp.maximum(s - f8[:, None], 0.0), s)


def sample_radiance(problem: FitProblem, values: jax.Array) -> jax.Array:
    """(P, L) radiance of every sample under the UNIT-scale environment, eq. (5) (+ eq. 6's
    interreflection when on), for physical parameters ``values (O, 6)``: a weighted sum of
    the cached radiances (:func:`spectral_fit.fitting.cached_radiance`)."""
    from ._radiance_cache import cached_radiance

    g = problem.receivers
    obj = jnp.maximum(g.object, 0)
    S = _reflectances(problem, values)  # (O, L)
    out, _ = cached_radiance(problem.cache, values, S, obj, problem.models,
                             interreflection=problem.interreflection)
    ok = g.valid & (problem.cache.sample_nodes.nv > 0.0)
    return jnp.where(ok[:, None], out, 0.0)


@eqx.filter_jit
def interreflection_term(problem: FitProblem, values: jax.Array) -> jax.Array:
    """(P, L) interreflection radiance (eq. 6 in the gather reading; unit environment
    scale) at the samples for physical parameters ``values (O, 6)``; zeros when off."""
    from ._radiance_cache import cached_radiance

    g = problem.receivers
    if not problem.interreflection:
        return jnp.zeros_like(problem.irradiance)
    obj = jnp.maximum(g.object, 0)
    S = _reflectances(problem, values)
    _, ir = cached_radiance(problem.cache, values, S, obj, problem.models)
    return jnp.where(g.valid[:, None], ir, 0.0)


def with_interreflection(problem: FitProblem, values: Any) -> FitProblem:
    """The problem unchanged: the interreflection term is part of the forward model (kept for
    callers written when it was a frozen term refreshed between solver rounds)."""
    del values
    return problem


def predict(problem: FitProblem, values: jax.Array, scale: Any = 1.0) -> jax.Array:
    """Predicted mean readings (B, L), W·sr⁻¹·m⁻²·nm⁻¹, for physical parameters
    ``values (O, 6)`` (columns α, β, χ, μ, n, γ) and the global environment scale: the field
    means of eq. (5) (+ eq. 6) from the radiance cache, through the band-pass, times k(λ)."""
    from ._radiance_cache import field_radiance

    obj = jnp.maximum(problem.receivers.object, 0)
    S = _reflectances(problem, values)
    mean = field_radiance(problem.cache, values, S, obj, problem.models,
                          interreflection=problem.interreflection)
    mean = (mean + problem.background) @ problem.band.T
    return problem.calibration * scale * mean


def residuals(y: jax.Array, problem: FitProblem, reading_weights: jax.Array) -> jax.Array:
    """Weighted residuals (B·L,) ((model − measured)/σ · √w_b) at unconstrained ``y``."""
    vals, scale = physical_from_y(problem, y)
    r = (predict(problem, vals, scale) - problem.measured) / problem.sigma
    return (r * jnp.sqrt(reading_weights)[:, None]).reshape(-1)


def _residuals_p(p: jax.Array, problem: FitProblem, reading_weights: jax.Array) -> jax.Array:
    vals, scale = _physical_from_p(problem, p)
    r = (predict(problem, vals, scale) - problem.measured) / problem.sigma
    return (r * jnp.sqrt(reading_weights)[:, None]).reshape(-1)


# ----------------------------------------------------------------------------- preparation


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """Options of :func:`fit` (all keyword arguments of :func:`fit` too).

    Attributes:
        spot_resolution: R, the spot camera's R×R pixels (disc inscribed).
        starts: number of starting points (the first is the session's/config's start).
        max_steps: Levenberg–Marquardt iterations per start.
        rtol, atol: optimistix LM tolerances on the unconstrained parameters.
        kinds: the reading kinds used in the fit ("object", "interreflection").
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
        solver: "compact" (default; :class:`CompactLM`, the Levenberg–Marquardt iteration of
            optimistix in one small compiled loop) or "optimistix"
            (``optimistix.LevenbergMarquardt`` with a Cholesky normal-equation solve); both
            reach the same optimum (tested), "compact" compiles in less time.

    The former options ``jacobian`` (the Jacobian is always exact forward-mode autodiff) and
    ``ir_rounds`` (the interreflection term is inside the model, no refresh rounds) were
    removed; naming them raises :class:`~spectral_fit._runtime.errors.InputError`.
    """

    spot_resolution: int = 8
    starts: int = 3
    max_steps: int = 50
    rtol: float = 1e-4
    atol: float = 1e-5
    kinds: tuple[str, ...] = ("object", "interreflection")
    interreflection: str = "auto"
    bootstrap: int = 0
    aim_step_m: float = 0.001
    holdout: bool = True
    seed: int = 0
    dtype: Any = jnp.float32
    compress_tol: float = 3e-3
    cache: Any = None
    solver: str = "compact"


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
    return opts


@dataclasses.dataclass
class Prepared:
    """Host-side companions of a :class:`FitProblem`."""

    problem: FitProblem
    session: Session
    objects: tuple[str, ...]
    geometries: list[ObjectGeometry]
    coverage: np.ndarray  # (B,) fraction of the field on the named object
    warnings: list[str]
    seconds: float


def disc_pixels(res: int) -> np.ndarray:
    """Flat indices of the R×R spot image's pixels whose centres lie inside the inscribed
    disc (the measuring field), row-major."""
    c = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    X, Y = np.meshgrid(c, -c)
    return np.flatnonzero((X ** 2 + Y ** 2 <= 1.0).reshape(-1))


def _ray_cast(origin: np.ndarray, dirs: np.ndarray, tri: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """Nearest front-facing hit of rays (N, 3) from ``origin`` with triangles (T, 3, 3)
    (counter-clockwise seen from outside): (N,) triangle index or −1, (N, 3) barycentrics."""
    v0, v1, v2 = tri[:, 0], tri[:, 1], tri[:, 2]
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(dirs[:, None, :], e2[None])  # (N, T, 3)
    det = np.einsum("ntc,tc->nt", p, e1)
    front = det > 1e-18  # ray against the outward normal e1 × e2
    inv = 1.0 / np.where(front, det, 1.0)
    s = origin[None, :] - v0  # (T, 3)
    u = np.einsum("ntc,tc->nt", p, s) * inv
    q = np.cross(s, e1)  # (T, 3)
    v = (dirs @ q.T) * inv
    t = np.einsum("tc,tc->t", q, e2)[None] * inv
    hit = front & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
    t = np.where(hit, t, np.inf)
    k = np.argmin(t, axis=1)
    n = np.arange(dirs.shape[0])
    ok = np.isfinite(t[n, k])
    uu, vv = u[n, k], v[n, k]
    bary = np.stack([1.0 - uu - vv, uu, vv], -1)
    return np.where(ok, k, -1), np.where(ok[:, None], bary, 0.0)


def _spot_samples(geoms: list[ObjectGeometry], positions: np.ndarray, aims: np.ndarray,
                  fields_deg: np.ndarray, res: int) -> dict[str, np.ndarray]:
    """Sample every reading's measuring field: the pixel rays of a square R×R camera whose
    field of view is the field angle (:func:`spectral_fit.geometry.look_at` pose, OpenGL pixel
    centres), kept inside the inscribed disc.

    The rays are intersected exactly with the triangles that can touch the field's cone (a
    cone test on each triangle's bounding sphere; typically a few dozen), in NumPy
    (Möller–Trumbore, front faces only, nearest hit). This gives the same first hits and
    perspective-correct barycentrics as rasterising the view with ``spectral_fit.geometry``
    (compared in the tests), without compiling the rasteriser for these tiny views (far
    slower than the ray casting). Returns per reading b and disc pixel k: position, normal,
    view, object (−1: the ray misses every object), ray direction.
    """
    verts = np.concatenate([np.asarray(g.vertices, np.float64) for g in geoms])
    norms = np.concatenate([np.asarray(g.normals, np.float64) for g in geoms])
    tris, tri_obj, base = [], [], 0
    for o, g in enumerate(geoms):
        t = np.asarray(g.triangles)
        tris.append(t + base)
        tri_obj.append(np.full(len(t), o, np.int32))
        base += len(np.asarray(g.vertices))
    tris = np.concatenate(tris)
    tri_obj = np.concatenate(tri_obj)
    corners = verts[tris]  # (T, 3, 3)
    centroid = corners.mean(axis=1)
    radius = np.linalg.norm(corners - centroid[:, None], axis=-1).max(axis=1)
    B = len(positions)
    sel = []
    for b in range(B):
        axis = aims[b] - positions[b]
        axis = axis / np.linalg.norm(axis)
        rel = centroid - positions[b]
        d = np.linalg.norm(rel, axis=1)
        cosang = (rel @ axis) / np.maximum(d, 1e-12)
        ang = np.arccos(np.clip(cosang, -1.0, 1.0))
        half = math.radians(fields_deg[b]) / 2.0 * math.sqrt(2.0)  # the square's corners
        grow = np.arcsin(np.clip(radius / np.maximum(d, 1e-12), 0.0, 1.0))
        sel.append(np.flatnonzero((ang <= half + grow + 1e-3) & (d > radius)))
    views = np.asarray(_look_at_many(jnp.asarray(positions, jnp.float32),
                                     jnp.asarray(aims, jnp.float32)), np.float64)
    rots = [views[b, :3, :3] for b in range(B)]
    keep = disc_pixels(res)
    c = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    X, Y = np.meshgrid(c, -c)
    xs, ys = X.reshape(-1)[keep], Y.reshape(-1)[keep]
    nd = keep.size
    tri_id = np.full((B, nd), -1, np.int64)
    bary = np.zeros((B, nd, 3))
    for b in range(B):
        t = math.tan(math.radians(fields_deg[b]) / 2.0)
        d_w = np.stack([xs * t, ys * t, -np.ones_like(xs)], -1) @ rots[b]
        d_w /= np.linalg.norm(d_w, axis=1, keepdims=True)
        if len(sel[b]):
            k, w = _ray_cast(positions[b], d_w, corners[sel[b]])
            tri_id[b] = np.where(k >= 0, k, -1)
            bary[b] = w
    out: dict[str, list[np.ndarray]] = {k: [] for k in ("pos", "nrm", "view", "obj", "ray")}
    for b in range(B):
        t = math.tan(math.radians(fields_deg[b]) / 2.0)
        d_w = np.stack([xs * t, ys * t, -np.ones_like(xs)], -1) @ rots[b]  # Rᵀ d
        d_w /= np.linalg.norm(d_w, axis=1, keepdims=True)
        hit = tri_id[b] >= 0
        gtri = sel[b][np.where(hit, tri_id[b], 0)] if len(sel[b]) else np.zeros_like(tri_id[b])
        idx = tris[gtri]
        pos = np.einsum("pk,pkc->pc", bary[b], verts[idx])
        nrm = np.einsum("pk,pkc->pc", bary[b], norms[idx])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
        vw = positions[b][None, :] - pos
        vw /= np.maximum(np.linalg.norm(vw, axis=1, keepdims=True), 1e-12)
        out["pos"].append(np.where(hit[:, None], pos, 0.0))
        out["nrm"].append(np.where(hit[:, None], nrm, np.array([0.0, 1.0, 0.0])))
        out["view"].append(np.where(hit[:, None], vw, np.array([0.0, 1.0, 0.0])))
        out["obj"].append(np.where(hit, tri_obj[gtri], -1))
        out["ray"].append(d_w)
    res_ = {k: np.stack(v) for k, v in out.items()}
    res_["xy"] = np.stack([xs, ys], -1)
    return res_


@jax.jit
def _look_at_many(eyes: jax.Array, targets: jax.Array) -> jax.Array:
    """(B, 4, 4) :func:`spectral_fit.geometry.look_at` view matrices, one compiled call (the
    eager per-reading calls cost ~25 dispatches each)."""
    from ..geometry import look_at

    return jax.vmap(look_at)(eyes, targets)


def band_matrix(wavelengths: np.ndarray, bandwidth_nm: float) -> np.ndarray:
    """(L, L) instrument band-pass on the scene grid: output band j = ∫ tri_j(λ) s(λ) dλ /
    ∫ tri_j, with tri_j a triangle of FWHM ``bandwidth_nm`` centred on λ_j and s the
    piecewise-linear spectrum through the samples (ends held); identity when the bandwidth is
    0. A spectroradiometer reports band-pass-weighted radiance; narrow lines of the
    environment (fluorescent tubes) are thereby smeared over neighbouring bands, and the model
    is passed through the same response before it is compared with the readings."""
    wl = np.asarray(wavelengths, np.float64)
    if bandwidth_nm <= 0:
        return np.eye(wl.size)
    fine = np.arange(wl[0] - bandwidth_nm, wl[-1] + bandwidth_nm + 1e-9, 0.25)
    H = np.stack([np.interp(fine, wl, e) for e in np.eye(wl.size)], -1)  # (F, L) hats
    W = np.maximum(0.0, 1.0 - np.abs(fine[None, :] - wl[:, None]) / bandwidth_nm)
    W /= W.sum(axis=1, keepdims=True)
    return W @ H


def _calibration(session: Session, env: Any, band: np.ndarray) -> np.ndarray:
    from ..lighting import irradiance_exact

    L = session.wavelengths.size
    if session.calibration != "white":
        return np.ones(L)
    w = session.white
    e = np.asarray(irradiance_exact(env, jnp.asarray(w.normal, env.texels.dtype)), np.float64)
    e = band @ e
    if np.any(e <= 0):
        raise session.error("white_standard.normal", "the environment gives no irradiance on "
                            "the white standard at some wavelengths (does the normal face away "
                            "from every light?)")
    return math.pi * w.mean / (w.reflectance * e)


def prepare_fit(scene: Any, session: Session, *, options: FitOptions | None = None,
                env: Any = None, geometries: list[ObjectGeometry] | None = None,
                check: bool = True) -> Prepared:
    """Rasterise the readings' fields and precompute everything parameter-independent.

    Raises:
        InputError: a spot misses its object (< 50 % of the field on it), a stated distance
            disagrees with the geometry, or the session's objects are not the scene's.
    """
    from .._runtime.process import single_threaded_blas

    # NumPy's OpenBLAS on one thread: on a loaded 2-core machine its busy-waiting second
    # thread costs several times the CPU of one thread (docs/fitting.md, "Speed")
    with single_threaded_blas():
        return _prepare_fit(scene, session, options=options, env=env, geometries=geometries,
                            check=check)


def _prepare_fit(scene: Any, session: Session, *, options: FitOptions | None,
                 env: Any, geometries: list[ObjectGeometry] | None, check: bool) -> Prepared:
    opts = options or FitOptions()
    t0 = time.perf_counter()
    dtype = opts.dtype
    names = tuple(o.name for o in scene.objects)
    for r in session.readings:
        if r.object not in names:
            raise session.error(f"{r.field}.object", f"unknown object {r.object!r}; the scene "
                                f"has {list(names)}")
    if env is None:
        env = scene_environment(scene, dtype=dtype, compress_tol=opts.compress_tol)
    if geometries is None:
        geometries = scene_geometry(scene)
    readings = session.readings
    if not readings:
        raise InputError("no readings to fit", path=session.path, field="readings")
    B = len(readings)
    res = int(opts.spot_resolution)
    if not 2 <= res <= 64:
        raise InputError(f"must be in [2, 64], got {res}", field="spot_resolution")
    S = _spot_samples(geometries, np.stack([r.position for r in readings]),
                      np.stack([r.aim for r in readings]),
                      np.array([r.field_angle_deg for r in readings]), res)
    nd = S["obj"].shape[1]
    warn: list[str] = []
    coverage = np.zeros(B)
    for b, r in enumerate(readings):
        on = int(np.sum(S["obj"][b] == names.index(r.object)))
        coverage[b] = on / nd
        if not check:
            continue
        if coverage[b] < 0.5:
            raise session.error(f"{r.field}.aim", f"the spot misses object {r.object!r}: only "
                                f"{100 * coverage[b]:.0f} % of the {r.field_angle_deg:g}° field "
                                "sees it")
        if coverage[b] < 0.99:
            warn.append(f"reading {r.id!r}: {100 * (1 - coverage[b]):.0f} % of the field "
                        "is off the object (modelled)")
        if r.distance_m is not None:
            centre = np.argsort(np.sum(S["xy"] ** 2, axis=1))[:4]
            ok = S["obj"][b][centre] >= 0
            if ok.any():
                d = float(np.mean(np.linalg.norm(S["pos"][b][centre][ok] - r.position, axis=1)))
                if abs(d - r.distance_m) > 0.005 + 0.02 * r.distance_m:
                    raise session.error(f"{r.field}.distance_m", f"stated {r.distance_m:g} m "
                                        f"but the geometry puts the spot at {d:.4f} m from the "
                                        "instrument")
    P = B * nd
    obj = S["obj"].reshape(P).astype(np.int32)
    recv = GBuffer(position=jnp.asarray(S["pos"].reshape(P, 3), dtype),
                   normal=jnp.asarray(S["nrm"].reshape(P, 3), dtype),
                   view=jnp.asarray(S["view"].reshape(P, 3), dtype),
                   object=jnp.asarray(obj), pixel=jnp.asarray(
                       np.tile(disc_pixels(res).astype(np.int32), B)))
    valid = obj >= 0
    rays = S["ray"].reshape(P, 3)
    L = session.wavelengths.size
    bgp = np.zeros((P, L))
    if (~valid).any():
        from ._radiance_cache import _env_lookup

        bgp[~valid] = _env_lookup(env, rays[~valid])
    avg = np.kron(np.eye(B), np.full((1, nd), 1.0 / nd))
    bg = avg @ bgp
    # material-independent radiance: irradiance, mirror direction, gloss nodes, neighbours
    from ._radiance_cache import CacheOptions, build_radiance_cache

    mode = scene.interreflection.mode if opts.interreflection == "auto" else "none"
    spheres = _scene_spheres(scene) if mode != "none" else []
    if mode != "none" and not spheres:
        warn.append("interreflection needs every object to be a sphere (uv_sphere or "
                    "icosphere); fitting without the interreflection term")
    cache = build_radiance_cache(
        env, S["pos"].reshape(P, 3), S["nrm"].reshape(P, 3), S["view"].reshape(P, 3), obj,
        np.repeat(np.arange(B), nd), average=avg, spheres=spheres,
        options=opts.cache or CacheOptions(), dtype=dtype)
    # reflectances and parameters
    O = len(names)
    refl = np.zeros((O, session.wavelengths.size))
    sci = np.zeros(O)
    vals = np.zeros((O, 6))
    models = []
    for o, ob in enumerate(scene.objects):
        m = ob.material
        om = session.objects.get(ob.name)
        refl[o] = m.reflectance if (om is None or om.reflectance is None) else om.reflectance
        sci[o] = 1.0 if (om is not None and om.geometry == "SCI") else 0.0
        for k, pname in enumerate(PARAMETERS):
            vals[o, k] = float(getattr(m, pname))
            if om is not None and pname in om.start:
                vals[o, k] = om.start[pname]
        models.append((m.distribution, m.geometry))
    measured = np.stack([r.mean for r in readings])
    nrep = np.array([r.repeats.shape[0] for r in readings], np.float64)
    sigma = session.noise.sigma(measured) / np.sqrt(nrep)[:, None]
    sigma = np.maximum(sigma, 1e-12)
    band = band_matrix(session.wavelengths, session.bandwidth_nm)
    calib = _calibration(session, env, band)
    # what is free
    measured_objs = {r.object for r in readings}
    free = []
    for o, name in enumerate(names):
        if name not in measured_objs:
            continue
        om = session.objects.get(name)
        fr = om.free if om is not None else ("alpha", "beta", "chi", "mu", "n")
        for k, pname in enumerate(PARAMETERS):
            if pname not in fr:
                continue
            if session.calibration == "global" and name == session.reference and pname == "alpha":
                continue  # the gauge: scale and this alpha are degenerate
            free.append((o, k))
    problem = FitProblem(
        env=env, receivers=recv, cache=cache, average=jnp.asarray(avg, dtype),
        background=jnp.asarray(bg, dtype), reflectance=jnp.asarray(refl, dtype),
        sci=jnp.asarray(sci, dtype), calibration=jnp.asarray(calib, dtype),
        band=jnp.asarray(band, dtype),
        measured=jnp.asarray(measured, dtype), sigma=jnp.asarray(sigma, dtype),
        values=jnp.asarray(vals, dtype), free=tuple(free),
        fit_scale=session.calibration == "global", models=tuple(models),
        interreflection=bool(spheres))
    for w in warn:
        warnings.warn(w, RuntimeWarning, stacklevel=2)
    return Prepared(problem=problem, session=session, objects=names, geometries=geometries,
                    coverage=coverage, warnings=warn, seconds=time.perf_counter() - t0)


def _scene_spheres(scene: Any) -> list[Any]:
    """The scene's objects as spheres (world centre, radius × scale) for occlusion and
    interreflection in the radiance cache; [] if any object is not a sphere."""
    from ._radiance_cache import Sphere

    out = []
    for o, ob in enumerate(scene.objects):
        if ob.shape not in ("uv_sphere", "icosphere"):
            return []
        out.append(Sphere(object=o, centre=np.asarray(ob.position, np.float64),
                          radius=float(ob.radius) * float(ob.scale)))
    return out


# ----------------------------------------------------------------------------- solver

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
        verbose: report (step, cost) per iteration through the progress callback.
    """

    rtol: float = eqx.field(static=True)
    atol: float = eqx.field(static=True)
    verbose: bool = eqx.field(static=True, default=False)


SOLVERS = ("compact", "optimistix")


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
    r = (pred - problem.measured) / problem.sigma
    return (r * jnp.sqrt(reading_weights)[:, None]).reshape(-1), pred


def _residuals_jacobian(y: jax.Array, problem: FitProblem, reading_weights: jax.Array
                        ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Weighted residuals (B·L,), their Jacobian (B·L, F) w.r.t. y (``jax.jacfwd``: the model
    evaluated once, its F tangents batched) and the predicted readings (B, L)."""
    def model(yy: jax.Array) -> tuple[jax.Array, jax.Array]:
        vals, scale = physical_from_y(problem, yy)
        p = predict(problem, vals, scale)
        return p, p

    jp, pred = jax.jacfwd(model, has_aux=True)(y)  # (B, L, F), (B, L)
    sw = jnp.sqrt(reading_weights)[:, None] / problem.sigma
    r = ((pred - problem.measured) * sw).reshape(-1)
    return r, (jp * sw[..., None]).reshape(r.shape[0], y.shape[0]), pred


def _compact_lm(problem: FitProblem, y0: jax.Array, w: jax.Array, solver: CompactLM,
                max_steps: int) -> dict[str, jax.Array]:
    """:class:`CompactLM` from ``y0`` (see there); returns the final state's y, residuals,
    Jacobian, predicted readings, step count and whether it terminated (converged)."""
    dt = y0.dtype
    F = y0.shape[0]
    tau = 1e-4  # the damping after a rejection is at least τ max (JᵀJ)_ii
    B, L = problem.measured.shape  # residuals (B·L,), Jacobian (B·L, F), predictions (B, L)
    rdt = problem.measured.dtype
    r0, j0, p0 = (jnp.zeros((B * L,), rdt), jnp.zeros((B * L, F), rdt), jnp.zeros((B, L), rdt))

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
        A = (J.T @ J).astype(dt)
        g = (J.T @ r).astype(dt)
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
                "steps": s["steps"] + 1}

    s0 = {"y": y0, "y_eval": y0, "r": r0, "J": j0, "pred": p0,
          "lam": jnp.asarray(1.0, dt), "dmax": jnp.zeros((), dt), "first": jnp.ones((), bool),
          "done": jnp.zeros((), bool), "steps": jnp.zeros((), jnp.int32)}
    return jax.lax.while_loop(cond, body, s0)


@eqx.filter_jit
def solve_batch(problem: FitProblem, y0: jax.Array, rw: jax.Array, solver: Any,
                 max_steps: int) -> dict[str, jax.Array]:
    """Solve S problems (one after the other): starts ``y0 (S, F)``, reading weights
    ``rw (S, B)``.

    Returns a dict of (S, ...) arrays: y, cost, converged, steps, the residuals, their
    Jacobian w.r.t. y (from the solver's last accepted step, so no second trace of the model
    is compiled) and the predicted readings (B, L) at y.
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
                "jacobian": s["J"], "predicted": s["pred"]}
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
def _predict_jit(problem: FitProblem, values: jax.Array, scale: jax.Array) -> jax.Array:
    return predict(problem, values, scale)


def _dp_dy(y: float, name: str) -> float:
    """Derivative of :func:`to_physical` at y."""
    if name in ("alpha", "beta", "mu", "scale", "n"):
        return math.exp(y)
    return 2.0 * y  # chi, gamma


def y_start(problem: FitProblem, values: np.ndarray, scale: float) -> np.ndarray:
    y = [to_unconstrained(float(values[o, k]), PARAMETERS[k]) for o, k in problem.free]
    if problem.fit_scale:
        y.append(to_unconstrained(scale, "scale"))
    return np.asarray(y, np.float64)


def _starts(problem: FitProblem, y0: np.ndarray, n: int, seed: int) -> np.ndarray:
    """The start and n − 1 perturbed copies (log-normal ×/÷ e^0.5 on α, β, μ, the scale; n − 1
    ×/÷ e^0.4; χ, γ: √ value ± 0.2)."""
    rng = np.random.default_rng(seed)
    out = [y0]
    kinds = [PARAMETERS[k] for _, k in problem.free] + (["scale"] if problem.fit_scale else [])
    sd = np.array([{"chi": 0.2, "gamma": 0.2, "n": 0.4}.get(k, 0.5) for k in kinds])
    for _ in range(max(0, n - 1)):
        y = y0 + sd * rng.standard_normal(y0.shape)
        y = np.array([abs(v) if k in _SQUARED else v
                      for v, k in zip(y, kinds, strict=True)])
        out.append(y)
    return np.stack(out)


# ----------------------------------------------------------------------------- results


@dataclasses.dataclass
class FitResult:
    """Outcome of :func:`fit` (stable API).

    Attributes:
        params: {object: {alpha, beta, chi, mu, n, gamma}} fitted (free) or fixed values.
        stderr: same shape: Jacobian standard errors (0 for fixed parameters), scaled by
            √(χ²/dof) when that exceeds 1 (model error larger than the instrument noise).
        status: "converged", "max_steps" (best start hit the iteration limit) or "failed".
        free: labels ``object.parameter`` of the unknowns (and ``scale``).
        correlation: (F, F) correlation matrix of the unknowns.
        relative_to: None when α, β, χ, γ are absolute (white calibration or a stated
            scale); else the parameter they are relative to (calibration "global").
        scale, scale_stderr: the fitted global environment scale (calibration "global").
        cost: ½ Σ r² at the optimum; chi2_red: Σ r² / dof.
        starts: per start: cost, converged, steps.
        bootstrap: {object: {param: std}} over bootstrap resamples of readings (or None).
        warnings: identifiability and data warnings.
        readings: per reading: id, object, kind, ΔE00, Δu′v′, xy / u′v′ measured and fitted,
            rms relative residual, aiming sensitivity.
        holdout: fit on object-colour readings only, prediction of the others (or None).
        wavelengths, measured, fitted, sigma: (L,), (B, L) ×3 spectra.
        calibration: (L,) the environment calibration k(λ) applied.
        timings: seconds of preparation, compile + first solve, steady solve, uncertainty.
    """

    params: dict[str, dict[str, float]]
    stderr: dict[str, dict[str, float]]
    status: str
    free: list[str]
    correlation: np.ndarray
    relative_to: str | None
    scale: float | None
    scale_stderr: float | None
    cost: float
    chi2_red: float
    dof: int
    starts: list[dict[str, Any]]
    bootstrap: dict[str, dict[str, float]] | None
    warnings: list[str]
    readings: list[dict[str, Any]]
    holdout: dict[str, Any] | None
    wavelengths: np.ndarray
    measured: np.ndarray
    fitted: np.ndarray
    sigma: np.ndarray
    calibration: np.ndarray
    calibration_mode: str
    timings: dict[str, float]
    iterations: int = 0
    values: np.ndarray | None = None  # (O, 6)

    def to_json(self) -> dict[str, Any]:
        """A JSON-serialisable summary (spectra excluded; see the report for those)."""
        def clean(x: Any) -> Any:
            if isinstance(x, dict):
                return {k: clean(v) for k, v in x.items()}
            if isinstance(x, list | tuple):
                return [clean(v) for v in x]
            if isinstance(x, np.ndarray):
                return clean(x.tolist())
            if isinstance(x, float | np.floating):
                return float(x) if math.isfinite(x) else None
            if isinstance(x, np.integer | np.bool_):
                return x.item()
            return x

        return clean({
            "params": self.params, "stderr": self.stderr, "status": self.status,
            "free": self.free, "correlation": self.correlation,
            "relative_to": self.relative_to, "scale": self.scale,
            "scale_stderr": self.scale_stderr, "calibration_mode": self.calibration_mode,
            "cost": self.cost, "chi2_red": self.chi2_red, "dof": self.dof,
            "iterations": self.iterations, "starts": self.starts,
            "bootstrap_std": self.bootstrap, "warnings": self.warnings,
            "readings": self.readings, "holdout": self.holdout, "timings": self.timings,
        })


def _colour_table(wl: np.ndarray, measured: np.ndarray, fitted: np.ndarray,
                  white: np.ndarray) -> list[dict[str, Any]]:
    from ..color import (
        delta_e00,
        delta_uv_prime,
        radiance_to_xyz,
        xyz_to_lab,
        xyz_to_uv_prime,
        xyz_to_xy,
    )

    xm = radiance_to_xyz(measured, wl)
    xf = radiance_to_xyz(fitted, wl)
    xw = radiance_to_xyz(white, wl)
    de = delta_e00(xyz_to_lab(xm, xw), xyz_to_lab(xf, xw))
    duv = delta_uv_prime(xm, xf)
    out = []
    for b in range(measured.shape[0]):
        out.append({
            "delta_e00": float(de[b]), "delta_uv": float(duv[b]),
            "xy_measured": xyz_to_xy(xm[b]).tolist(), "xy_fitted": xyz_to_xy(xf[b]).tolist(),
            "uv_measured": xyz_to_uv_prime(xm[b]).tolist(),
            "uv_fitted": xyz_to_uv_prime(xf[b]).tolist(),
            "Y_measured": float(xm[b, 1]), "Y_fitted": float(xf[b, 1]),
        })
    return out


def _reference_white(prep: Prepared, calib: np.ndarray, scale: float) -> np.ndarray:
    """Radiance (L,) of the scene's white for CIELAB: the white standard's reading divided by
    its reflectance, else a perfect diffuser facing the first instrument."""
    from ..lighting import irradiance_exact

    s = prep.session
    if s.white is not None:
        return s.white.mean / s.white.reflectance
    r = s.readings[0]
    n = r.position - r.aim
    n = n / np.linalg.norm(n)
    env = prep.problem.env
    e = np.asarray(irradiance_exact(env, jnp.asarray(n, env.texels.dtype)), np.float64)
    return calib * scale * e / math.pi


def _identifiability(labels: list[str], corr: np.ndarray, jtj: np.ndarray) -> list[str]:
    out = []
    F = len(labels)
    for i in range(F):
        for j in range(i + 1, F):
            c = corr[i, j]
            if np.isfinite(c) and abs(c) > 0.95:
                a, b = labels[i], labels[j]
                msg = (f"{a} and {b} are strongly correlated (r = {c:+.3f}): the readings "
                       "hardly separate them")
                oa, pa = a.rsplit(".", 1) if "." in a else ("", a)
                ob, pb = b.rsplit(".", 1) if "." in b else ("", b)
                if oa == ob and {pa, pb} == {"beta", "n"}:
                    msg += (" — β and n trade off through F0 = ((n−1)/(n+1))²; add readings "
                            "at grazing angles (θr > 60°) or fix n")
                out.append(msg)
    ev = np.linalg.eigvalsh(jtj) if F else np.array([1.0])
    if F and (ev[0] <= 0 or ev[-1] / max(ev[0], 1e-300) > 1e12):
        out.append("the normal matrix JᵀJ is (nearly) singular: some combination of the free "
                   "parameters is not determined by the readings; fix one of them")
    return out


def fit(scene: Any, session: Any, *, options: FitOptions | None = None,
        progress: Callable[[str], None] | None = None, prepared: Prepared | None = None,
        **kwargs: Any) -> FitResult:
    """Fit the reflection-model parameters of the measured objects (stable API ``fit``).

    Args:
        scene: a :class:`~spectral_fit.io.Scene` or the path of its config.
        session: a :class:`~spectral_fit.io.Session` or the path of a session.
        options: :class:`FitOptions`; keyword arguments override its fields
            (``starts=8``, ``bootstrap=50``, ``kinds=("object",)``, ...).
        progress: called with one line of text per stage and per solver iteration.
        prepared: a :func:`prepare_fit` result to reuse (benchmarks).

    Returns:
        :class:`FitResult`.
    """
    from pathlib import Path

    from ..io import load_scene, load_session

    opts = _fit_options(options, kwargs)
    if isinstance(scene, str | Path):
        scene = load_scene(scene)
    if isinstance(session, str | Path):
        session = load_session(session, scene=scene)
    say = progress or (lambda _m: None)
    t0 = time.perf_counter()
    if prepared is None:
        say(f"rasterising {len(session.readings)} measuring fields ...")
        prepared = prepare_fit(scene, session, options=opts)
    prep = prepared
    problem = prep.problem
    names = list(prep.objects)
    labels = problem.names(names)
    B = len(session.readings)
    L = session.wavelengths.size
    use = np.array([r.kind in opts.kinds for r in session.readings], np.float64)
    if use.sum() == 0:
        raise InputError(f"no readings of kinds {list(opts.kinds)}", path=session.path,
                         field="readings")
    F = problem.n_free
    if F == 0:
        raise InputError("no free parameters", path=session.path, field="objects")
    dof = int(use.sum()) * L - F
    if dof <= 0:
        raise InputError(f"{F} unknowns but only {int(use.sum()) * L} data", path=session.path,
                         field="readings")
    t_prep = time.perf_counter() - t0
    vals0 = np.asarray(problem.values, np.float64)
    scale0 = 1.0
    if problem.fit_scale:  # closed-form start for the scale from the diffuse term alone
        pr_ = {k: np.asarray(getattr(problem, k), np.float64) for k in
               ("irradiance", "reflectance", "average", "background", "measured", "calibration")}
        obj = np.maximum(np.asarray(problem.receivers.object), 0)
        diff = vals0[obj, 0:1] / math.pi * pr_["reflectance"][obj] * pr_["irradiance"]
        diff *= (np.asarray(problem.receivers.object) >= 0)[:, None]
        pred = pr_["calibration"] * (pr_["average"] @ diff + pr_["background"])
        m = use[:, None] > 0
        scale0 = float(np.sum(pred * pr_["measured"] * m) / max(np.sum(pred * pred * m),
                                                                 1e-300))
        scale0 = scale0 if scale0 > 0 and math.isfinite(scale0) else 1.0
    y0 = y_start(problem, vals0, scale0)
    starts = _starts(problem, y0, opts.starts, opts.seed)
    dt = problem.values.dtype
    solver = make_solver(opts, progress is not None)
    say(f"solving: {F} unknowns, {int(use.sum())} readings x {L} bands, {opts.starts} starts "
        f"(Levenberg-Marquardt, {opts.solver}) ...")
    if progress is not None:
        _PROGRESS.append(lambda s, c: say(f"  step {int(np.max(s)):3d}  "
                                          f"best cost {float(np.min(c)):.6g}"))
    t1 = time.perf_counter()
    try:
        out = solve_batch(problem, jnp.asarray(starts, dt),
                           jnp.asarray(np.tile(use, (len(starts), 1)), dt), solver,
                           opts.max_steps)
        out = {k: np.asarray(v) for k, v in out.items()}
    finally:
        if progress is not None:
            _PROGRESS.pop()
    t_solve = time.perf_counter() - t1
    costs = out["cost"].astype(np.float64)
    oks = out["converged"]
    steps = out["steps"]
    best = int(np.argmin(np.where(np.isfinite(costs), costs, np.inf)))
    if not np.isfinite(costs[best]):
        status = "failed"
    elif oks[best]:
        status = "converged"
    else:
        status = "max_steps"
    y = out["y"][best].astype(np.float64)
    vals, scale = physical_from_y(problem, jnp.asarray(y, dt))
    vals = np.asarray(vals, np.float64)
    scale = float(scale)
    warn = list(prep.warnings)
    agree = [i for i in range(len(costs)) if np.isfinite(costs[i])
             and costs[i] <= costs[best] * (1 + 1e-3) + 1e-9]
    if len(agree) < len(costs):
        worse = len(costs) - len(agree)
        warn.append(f"{worse} of {len(costs)} starts ended at a higher cost (local minima or "
                    "not converged); the best start is reported")
    # uncertainty: J w.r.t. the physical parameters by the chain rule ------------------------
    t2 = time.perf_counter()
    kinds = [PARAMETERS[k] for _, k in problem.free] + (["scale"] if problem.fit_scale else [])
    p_hat = np.array([vals[o, k] for o, k in problem.free] + ([scale] if problem.fit_scale
                                                             else []))
    dp_dy = np.array([_dp_dy(float(yy), kk) for yy, kk in zip(y, kinds, strict=True)])
    r = out["residual"][best].astype(np.float64)
    Jy = out["jacobian"][best].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        J = Jy / dp_dy[None, :]
    J[:, ~(np.abs(dp_dy) > 1e-12)] = 0.0
    chi2 = float(r @ r)
    chi2_red = chi2 / dof
    jtj = J.T @ J
    cov = np.linalg.pinv(jtj, rcond=1e-12, hermitian=True) * max(1.0, chi2_red)
    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(se, se)
    warn += _identifiability(labels, corr, jtj)
    for (o, k), v in zip(problem.free, p_hat, strict=False):
        pname = PARAMETERS[k]
        if pname in _SQUARED and v < 1e-4:
            warn.append(f"{names[o]}.{pname} is at its bound 0 (its standard error is "
                        "one-sided)")
    params = {nm: {p: float(vals[o, k]) for k, p in enumerate(PARAMETERS)}
              for o, nm in enumerate(names)}
    stderr = {nm: {p: 0.0 for p in PARAMETERS} for nm in names}
    for j, (o, k) in enumerate(problem.free):
        stderr[names[o]][PARAMETERS[k]] = float(se[j])
    t_unc = time.perf_counter() - t2
    fitted = out["predicted"][best].astype(np.float64)
    # colour table ---------------------------------------------------------------------------
    measured = np.asarray(problem.measured, np.float64)
    sigma = np.asarray(problem.sigma, np.float64)
    calib = np.asarray(problem.calibration, np.float64)
    wl = session.wavelengths
    white = _reference_white(prep, calib, scale)
    table = _colour_table(wl, measured, fitted, white)
    for b, rd in enumerate(session.readings):
        rel = (fitted[b] - measured[b]) / np.maximum(np.abs(measured[b]), 1e-12)
        table[b].update(id=rd.id, object=rd.object, kind=rd.kind, used=bool(use[b]),
                        repeats=int(rd.repeats.shape[0]), coverage=float(prep.coverage[b]),
                        rms_relative_residual=float(np.sqrt(np.mean(rel ** 2))),
                        chi2=float(np.sum(((fitted[b] - measured[b]) / sigma[b]) ** 2)))
    # bootstrap ---------------------------------------------------------------------------
    boot = None
    t3 = time.perf_counter()
    if opts.bootstrap > 0:
        say(f"bootstrap over readings: {opts.bootstrap} resamples ...")
        boot = _bootstrap(problem, y, use, opts, solver, names)
    t_boot = time.perf_counter() - t3
    # hold-out -----------------------------------------------------------------------------
    holdout = None
    kinds_present = {r.kind for r in session.readings if use[session.readings.index(r)] > 0}
    unused = [b for b in range(B) if use[b] == 0]
    if unused:  # readings left out of the fit are predicted by it
        held = [{k: table[b][k] for k in ("id", "object", "kind", "delta_e00", "delta_uv",
                                          "xy_measured", "xy_fitted", "Y_measured",
                                          "Y_fitted")} for b in unused]
        des = [h["delta_e00"] for h in held]
        holdout = {"fitted_on": sorted(kinds_present),
                   "predicted": sorted({session.readings[b].kind for b in unused}),
                   "params": params, "readings": held, "mean_delta_e00": float(np.mean(des)),
                   "max_delta_e00": float(np.max(des))}
    elif opts.holdout and {"object", "interreflection"} <= kinds_present:
        say("hold-out: fit on object-colour readings, predict interreflection readings ...")
        holdout = _holdout(problem, prep, y, use, opts, solver, white)
    # aiming sensitivity ------------------------------------------------------------------
    if opts.aim_step_m > 0:
        say("aiming sensitivity ...")
        sens = _aim_sensitivity(scene, prep, vals, scale, opts, white, fitted)
        for b in range(B):
            table[b]["aim_sensitivity"] = sens[b]
    steps_best = int(steps[best])
    if status != "converged":
        warn.append(f"the best start did not converge in {opts.max_steps} steps")
    return FitResult(
        params=params, stderr=stderr, status=status, free=labels, correlation=corr,
        relative_to=(f"{session.reference}.alpha" if problem.fit_scale else None),
        scale=scale if problem.fit_scale else None,
        scale_stderr=float(se[-1]) if problem.fit_scale else None,
        cost=float(costs[best]), chi2_red=chi2_red, dof=dof,
        starts=[{"cost": float(costs[i]), "converged": bool(oks[i]), "steps": int(steps[i])}
                for i in range(len(costs))],
        bootstrap=boot, warnings=warn, readings=table, holdout=holdout, wavelengths=wl,
        measured=measured, fitted=fitted, sigma=sigma, calibration=calib * scale,
        calibration_mode=session.calibration,
        timings={"prepare_s": prep.seconds if prepared is not None else t_prep,
                 "solve_s": t_solve, "uncertainty_s": t_unc, "bootstrap_s": t_boot,
                 "total_s": time.perf_counter() - t0},
        iterations=steps_best, values=vals)


def _bootstrap(problem: FitProblem, y: np.ndarray, use: np.ndarray, opts: FitOptions,
               solver: Any, names: list[str]) -> dict[str, dict[str, float]]:
    rng = np.random.default_rng(opts.seed + 1)
    idx = np.flatnonzero(use > 0)
    S = max(1, opts.starts)
    n = int(math.ceil(opts.bootstrap / S)) * S
    ws = np.zeros((n, use.size))
    for i in range(n):
        pick = rng.choice(idx, size=idx.size, replace=True)
        np.add.at(ws[i], pick, 1.0)
    dt = problem.values.dtype
    got = []
    for c in range(0, n, S):
        o = solve_batch(problem, jnp.asarray(np.tile(y, (S, 1)), dt),
                         jnp.asarray(ws[c:c + S], dt), solver, opts.max_steps)
        for yi, ci in zip(np.asarray(o["y"]), np.asarray(o["cost"]), strict=True):
            if np.isfinite(ci):
                got.append(np.asarray(physical_from_y(problem, jnp.asarray(yi, dt))[0]))
    arr = np.stack(got) if got else np.full((1,) + tuple(problem.values.shape), np.nan)
    std = arr.std(axis=0, ddof=1) if len(got) > 1 else np.full(arr.shape[1:], np.nan)
    out = {nm: {p: 0.0 for p in PARAMETERS} for nm in names}
    for o, k in problem.free:
        out[names[o]][PARAMETERS[k]] = float(std[o, k])
    out["_resamples"] = {"used": float(len(got)), "requested": float(opts.bootstrap)}
    return out


def _holdout(problem: FitProblem, prep: Prepared, y: np.ndarray, use: np.ndarray,
             opts: FitOptions, solver: Any, white: np.ndarray) -> dict[str, Any]:
    s = prep.session
    obj_only = np.array([u if r.kind == "object" else 0.0 for u, r in
                         zip(use, s.readings, strict=True)])
    dt = problem.values.dtype
    S = max(1, opts.starts)
    o = solve_batch(problem, jnp.asarray(np.tile(y, (S, 1)), dt),
                     jnp.asarray(np.tile(obj_only, (S, 1)), dt), solver, opts.max_steps)
    yh = np.asarray(o["y"])[0]
    vals, scale = physical_from_y(problem, jnp.asarray(yh, dt))
    pred = np.asarray(o["predicted"][0], np.float64)
    meas = np.asarray(problem.measured, np.float64)
    table = _colour_table(s.wavelengths, meas, pred, white)
    held = [{"id": r.id, "object": r.object, **table[b]} for b, r in enumerate(s.readings)
            if r.kind != "object" and use[b] > 0]
    names = list(prep.objects)
    v = np.asarray(vals, np.float64)
    return {
        "fitted_on": "object", "predicted": "interreflection",
        "params": {nm: {p: float(v[o, k]) for k, p in enumerate(PARAMETERS)}
                   for o, nm in enumerate(names)},
        "readings": held,
        "mean_delta_e00": float(np.mean([h["delta_e00"] for h in held])) if held else None,
        "max_delta_e00": float(np.max([h["delta_e00"] for h in held])) if held else None,
    }


def _aim_sensitivity(scene: Any, prep: Prepared, vals: np.ndarray, scale: float,
                     opts: FitOptions, white: np.ndarray, fitted: np.ndarray
                     ) -> list[dict[str, Any]]:
    """ΔE00 and relative radiance change per mm of aiming error, per reading (finite
    differences over aim shifts of ``aim_step_m`` in two directions across the axis)."""
    from ..color import delta_e00, radiance_to_xyz, xyz_to_lab

    s = prep.session
    step = opts.aim_step_m
    wl = s.wavelengths
    xw = radiance_to_xyz(white, wl)
    lab0 = xyz_to_lab(radiance_to_xyz(fitted, wl), xw)
    de = np.zeros((len(s.readings), 2))
    rel = np.zeros_like(de)
    dt = prep.problem.values.dtype
    for d in range(2):
        shifted = []
        for r in s.readings:
            ax = r.aim - r.position
            ax = ax / np.linalg.norm(ax)
            u = np.cross(ax, [0.0, 1.0, 0.0])
            if np.linalg.norm(u) < 1e-6:
                u = np.cross(ax, [1.0, 0.0, 0.0])
            u = u / np.linalg.norm(u)
            v = np.cross(ax, u)
            shifted.append(dataclasses.replace(r, aim=r.aim + step * (u if d == 0 else v)))
        ss = s.replace(readings=tuple(shifted))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                pp = prepare_fit(scene, ss, options=dataclasses.replace(
                    opts, interreflection="auto" if prep.problem.interreflection else "none"),
                    env=prep.problem.env, geometries=prep.geometries)
        except InputError:
            de[:, d] = np.nan
            rel[:, d] = np.nan
            continue
        pshift = with_interreflection(pp.problem, vals)
        pred = np.asarray(_predict_jit(pshift, jnp.asarray(vals, dt),
                                       jnp.asarray(scale, dt)), np.float64)
        lab = xyz_to_lab(radiance_to_xyz(pred, wl), xw)
        de[:, d] = delta_e00(lab0, lab)
        rel[:, d] = np.linalg.norm(pred - fitted, axis=1) / np.maximum(
            np.linalg.norm(fitted, axis=1), 1e-30)
    mm = step * 1e3
    return [{"delta_e00_per_mm": float(np.nanmax(de[b]) / mm) if np.isfinite(de[b]).any()
             else None,
             "relative_radiance_per_mm": float(np.nanmax(rel[b]) / mm)
             if np.isfinite(rel[b]).any() else None}
            for b in range(len(s.readings))]


# ----------------------------------------------------------------------------- simulation


def simulate_readings(scene: Any, spots: Sequence[dict[str, Any]], *,
                      params: dict[str, dict[str, float]] | None = None,
                      calibration: Any = None, reflectance: dict[str, Any] | None = None,
                      options: FitOptions | None = None, env: Any = None) -> np.ndarray:
    """Noiseless readings (B, L) of spots under this module's forward model (for tests and for
    sessions made before an independent reference exists).

    Args:
        spots: dicts with ``object``, ``aim``, ``position`` and optional ``field_angle_deg``,
            ``kind``.
        params: {object: {parameter: value}} overriding the scene config's materials.
        calibration: (L,) factor on the environment (the "true" room vs the map), default 1.
        reflectance: {object: (L,)} Lambert S(λ) overriding the config's (SCE).
    """
    from pathlib import Path

    from ..io import NoiseModel, Reading

    opts = options or FitOptions()
    wl = np.asarray(scene.wavelengths, np.float64)
    reads = tuple(
        Reading(id=f"s{i}", object=s["object"], kind=s.get("kind", "object"), files=(),
                repeats=np.ones((1, wl.size)), position=np.asarray(s["position"], np.float64),
                aim=np.asarray(s["aim"], np.float64),
                field_angle_deg=float(s.get("field_angle_deg", 1.0)), distance_m=None,
                line=None, index=i)
        for i, s in enumerate(spots))
    from ..io import ObjectMeasurement

    objs = {k: ObjectMeasurement(name=k, reflectance=np.asarray(v, np.float64), geometry="SCE",
                                 free=(), start={}) for k, v in (reflectance or {}).items()}
    sess = Session(path=Path("<simulated>"), scene_path=None, scene=scene, wavelengths=wl,
                   units="W.sr^-1.m^-2.nm^-1", instrument="simulated", calibration="none",
                   bandwidth_nm=0.0,
                   reference=None, white=None, dark=None,
                   noise=NoiseModel(1.0, 0.0, "default"), objects=objs, readings=reads)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prep = prepare_fit(scene, sess, options=opts, env=env)
    pr = prep.problem
    vals = np.array(pr.values, np.float64)
    for o, name in enumerate(prep.objects):
        for k, p in enumerate(PARAMETERS):
            if params and name in params and p in params[name]:
                vals[o, k] = params[name][p]
    pr = with_interreflection(pr, vals)
    if calibration is not None:
        pr = eqx.tree_at(lambda q: q.calibration, pr,
                         jnp.asarray(np.broadcast_to(calibration, wl.shape), pr.values.dtype))
    return np.asarray(_predict_jit(pr, jnp.asarray(vals, pr.values.dtype),
                                   jnp.ones((), pr.values.dtype)), np.float64)


# ----------------------------------------------------------------------------- batches


@eqx.filter_jit
def _solve_measured(problem: FitProblem, y0: jax.Array, rw: jax.Array, measured: jax.Array,
                    sigma: jax.Array, solver: Any, max_steps: int) -> dict[str, jax.Array]:
    """Like :func:`solve_batch` but each batch entry has its own readings (K, B, L) and σ."""
    def one(y0_: jax.Array, w: jax.Array, meas: jax.Array, sig: jax.Array
            ) -> dict[str, jax.Array]:
        pr = eqx.tree_at(lambda q: (q.measured, q.sigma), problem, (meas, sig))
        out = _solve_one(pr, y0_, w, solver, max_steps)
        del out["predicted"]
        return out

    return jax.vmap(one)(y0, rw, measured, sigma)


def fit_many(prepared: Prepared, measured: Any, *, sigma: Any = None,
             options: FitOptions | None = None, devices: Sequence[Any] | None = None,
             **kwargs: Any) -> dict[str, Any]:
    """Fit K sets of readings of the same spots at once (``jax.vmap``), optionally sharded
    across devices along K (``jax.sharding``; the problem is replicated).

    Args:
        prepared: :func:`prepare_fit` of the session whose spots all K sets share.
        measured: (K, B, L) mean readings; ``sigma`` (K, B, L) their standard errors (default:
            the session's).
        devices: devices to shard K over (default: all of ``jax.devices()`` when more than
            one); K is padded to a multiple of their number.

    Returns:
        dict with ``params`` (K, O, 6), ``stderr`` (K, O, 6) (Jacobian, unscaled by χ²),
        ``scale`` (K,), ``cost`` (K,), ``converged`` (K,), ``steps`` (K,), ``devices`` (the
        devices the result was computed on).
    """
    opts = _fit_options(options, kwargs)
    problem = prepared.problem
    dt = problem.values.dtype
    meas = np.asarray(measured, np.float64)
    K = meas.shape[0]
    if meas.ndim != 3 or meas.shape[1:] != tuple(problem.measured.shape):
        raise InputError(f"expected (K, {problem.measured.shape[0]}, "
                         f"{problem.measured.shape[1]}), got {meas.shape}", field="measured")
    if not np.all(np.isfinite(meas)):
        raise InputError("NaN or infinite readings", field="measured")
    sig = np.broadcast_to(np.asarray(problem.sigma if sigma is None else sigma, np.float64),
                          meas.shape)
    use = np.array([r.kind in opts.kinds for r in prepared.session.readings], np.float64)
    y0 = y_start(problem, np.asarray(problem.values, np.float64), 1.0)
    devs = list(devices) if devices is not None else jax.devices()
    nd = len(devs)
    Kp = int(math.ceil(K / nd)) * nd
    pad = lambda a: np.concatenate([a, np.repeat(a[-1:], Kp - K, 0)]) if Kp > K else a  # noqa: E731
    args = [jnp.asarray(pad(np.tile(y0, (K, 1))), dt), jnp.asarray(pad(np.tile(use, (K, 1))), dt),
            jnp.asarray(pad(meas), dt), jnp.asarray(pad(np.ascontiguousarray(sig)), dt)]
    if nd > 1:
        from jax.sharding import Mesh, NamedSharding, PartitionSpec

        mesh = Mesh(np.array(devs), ("k",))
        args = [jax.device_put(a, NamedSharding(mesh, PartitionSpec("k"))) for a in args]
    out = _solve_measured(problem, *args, make_solver(opts, False), opts.max_steps)
    used = sorted({str(d) for d in out["y"].sharding.device_set})
    out = {k: np.asarray(v)[:K] for k, v in out.items()}
    O = problem.values.shape[0]
    params = np.zeros((K, O, 6))
    stderr = np.zeros((K, O, 6))
    scales = np.ones(K)
    kinds = [PARAMETERS[k] for _, k in problem.free] + (["scale"] if problem.fit_scale else [])
    for i in range(K):
        y = out["y"][i].astype(np.float64)
        v, s = physical_from_y(problem, jnp.asarray(y, dt))
        params[i] = np.asarray(v, np.float64)
        scales[i] = float(s)
        dp = np.array([_dp_dy(float(a), k) for a, k in zip(y, kinds, strict=True)])
        with np.errstate(divide="ignore", invalid="ignore"):
            J = out["jacobian"][i].astype(np.float64) / dp[None, :]
        J[:, ~(np.abs(dp) > 1e-12)] = 0.0
        cov = np.linalg.pinv(J.T @ J, rcond=1e-12, hermitian=True)
        se = np.sqrt(np.maximum(np.diag(cov), 0.0))
        for j, (o, k) in enumerate(problem.free):
            stderr[i, o, k] = se[j]
    return {"params": params, "stderr": stderr, "scale": scales, "cost": out["cost"],
            "converged": out["converged"], "steps": out["steps"], "devices": used}
