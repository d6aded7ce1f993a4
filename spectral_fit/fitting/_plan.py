"""Measurement planning (:func:`plan_measurements`): which K spectroradiometer readings to take
next so that every free parameter is determined to its tolerance, robustly over the range
the parameters may lie in (``docs/planning.md``).

Candidates come from the reachable region (:mod:`._plan_candidates`); each one's Fisher
information is computed through the fit's own forward model at D parameter draws
(:mod:`._plan_design`), and K of them are chosen to minimise the worst scaled variance over
the draws. With a session, its readings (and priors) are information already there and its
fit is the centre of the draws.

Shapes: N candidates, D draws, F unknowns (free (object, parameter) pairs, then the scale when
the session's calibration fits one), O objects, L bands.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from .._runtime.errors import InputError
from ..io import DEFAULT_FREE, PARAMETERS, Scene, Session
from ._options import FitOptions
from ._plan_candidates import Region, plan_candidates
from ._plan_design import (
    UNIDENTIFIED,
    default_range,
    draws_in_box,
    scaled_variances,
    select_readings,
    stderr_from_information,
    tolerances,
)
from ._plan_information import candidate_information, session_information

__all__ = ["PlanResult", "bright_directions", "plan_measurements"]

#: a candidate is kept when at least this fraction of its field lies on its object
_MIN_COVERAGE = 0.99


@dataclasses.dataclass
class PlanResult:
    """A measurement plan.

    Attributes:
        chosen: the planned readings (dicts: ``id``, ``object``, ``kind``, ``aim``,
            ``position``, ``field_angle_deg``, ``distance_m``, ``candidate`` index).
        candidates: every valid candidate (same keys, no ``id``).
        unknowns: labels of the F unknowns (``object.parameter``, ``scale``).
        tolerance: (F,) tolerances at the centre (physical units).
        stderr_before, stderr_after: (F,) predicted standard errors at the centre (physical
            units; inf: unidentified) with the existing readings only / with the plan added.
        worst_before, worst_after: (F,) the largest standard error over the draws, in
            tolerances.
        objective_before, objective_after: the worst scaled standard error (tolerances) over
            draws and unknowns (√ of the design criterion).
        draws: (D, F) the parameter draws (physical; the centre first).
        information: (N, D, F, F) each candidate's Fisher information (tolerance units).
        base_information: (D, F, F) the information already there (readings, priors).
        mask: (F,) the unknowns the criterion looks at (all but the scale).
        centre: {object: {parameter: value}} the centre of the draws.
        settings: the plan's options (noise, aiming error, draws, ...).
        timings: seconds per stage.
    """

    chosen: list[dict[str, Any]]
    candidates: list[dict[str, Any]]
    unknowns: list[str]
    tolerance: np.ndarray
    stderr_before: np.ndarray
    stderr_after: np.ndarray
    worst_before: np.ndarray
    worst_after: np.ndarray
    objective_before: float
    objective_after: float
    draws: np.ndarray
    information: np.ndarray
    base_information: np.ndarray
    mask: np.ndarray
    centre: dict[str, dict[str, float]]
    settings: dict[str, Any]
    timings: dict[str, float]

    def to_json(self) -> dict[str, Any]:
        """The plan as JSON-ready data (``plan.json``); "unidentified" where a standard
        error is infinite."""

        def se(x: float) -> float | str:
            return float(x) if math.isfinite(x) else "unidentified"

        def vec(v: Any) -> list[float]:
            return [float(x) for x in np.asarray(v)]

        return {
            "readings": [{k: (vec(v) if isinstance(v, np.ndarray) else v) for k, v in r.items()}
                         for r in self.chosen],
            "parameters": {
                u: {"tolerance": float(self.tolerance[j]),
                    "stderr_before": se(self.stderr_before[j]),
                    "stderr_after": se(self.stderr_after[j]),
                    "worst_before_tolerances": se(self.worst_before[j]),
                    "worst_after_tolerances": se(self.worst_after[j])}
                for j, u in enumerate(self.unknowns)},
            "objective": {"worst_stderr_tolerances_before": se(self.objective_before),
                          "worst_stderr_tolerances_after": se(self.objective_after)},
            "centre": self.centre,
            "draws": {u: vec(self.draws[:, j]) for j, u in enumerate(self.unknowns)},
            "candidates": len(self.candidates),
            "settings": self.settings,
            "timings": self.timings,
        }


def _unknowns(scene: Scene, session: Session | None, region: Region, free_params: tuple[str, ...],
              session_free: tuple[tuple[int, int], ...]) -> tuple[tuple[int, int], ...]:
    """The free (object, parameter) pairs: the session's, and those of every object of the
    region (its session entry's free parameters, else ``free_params``)."""
    names = [o.name for o in scene.objects]
    out = set(session_free)
    for name in region.objects or names:
        if name not in names:
            continue
        om = session.objects.get(name) if session is not None else None
        fr = om.free if om is not None else free_params
        o = names.index(name)
        for k, p in enumerate(PARAMETERS):
            if p in fr and not (session is not None and session.calibration == "global"
                                and name == session.reference and p == "alpha"):
                out.add((o, k))
    return tuple(sorted(out))


def plan_measurements(scene: Scene, session: Session | None = None, *, budget: int,
                      region: Region | None = None, noise: float = 0.01,
                      sigma_aim_m: float = 1e-3, level_error: float | None = None,
                      tilt_error: float | None = None, draws: int = 8,
                      spot_resolution: int = 4,
                      free: tuple[str, ...] = DEFAULT_FREE, seed: int = 0, chunk: int = 256,
                      fit_options: FitOptions | None = None,
                      progress: Callable[[str], None] | None = None) -> PlanResult:
    """Plan ``budget`` readings that minimise the worst scaled parameter variance.

    Args:
        scene: the loaded scene config.
        session: existing readings (optional): their information is there already, their fit
            is the centre of the parameter draws (else the config's materials), and its
            bounds, priors and standard errors narrow the draws' ranges.
        budget: K, the number of readings to plan.
        region: where the instrument can stand and aim (default :class:`Region`()).
        noise: relative noise of one planned reading (0.01: 1 %).
        sigma_aim_m: aiming error (metres, 1σ per direction across the measuring axis).
        level_error: the model's error common to a reading's bands, a fraction of the reading,
            in every reading's information, planned and measured: a plan does not lean on one
            reading's level. Default (None): what the session states for object readings
            (``[model_error.level]``), else 0.005 (the renderer against the path-traced
            reference at object spots, docs/fitting.md). The session's readings of a kind
            it states a level for take that level.
        tilt_error: the model's error as a tilt over a reading's bands (a fraction, from −1
            at the first band to +1 at the last; the fit's ``[model_error.tilt]``), in every
            reading's information like the level. Default (None): what the session states
            for object readings, else 0 (none).
        draws: D, parameter draws the criterion takes its worst case over (the centre and a
            Latin hypercube of the ranges).
        spot_resolution: R of the candidates' fields (R×R camera, disc pixels).
        free: the parameters fitted on objects the session does not list.

    Returns:
        :class:`PlanResult`.

    Raises:
        InputError: a bad region (see :func:`plan_candidates`), no valid candidate, a budget
            larger than the number of valid candidates or below 1, bad options.
    """
    from ._prepare import scene_environment, scene_geometry

    say = progress or (lambda _m: None)
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    region = (region or Region()).checked()
    if not isinstance(budget, int) or budget < 1:
        raise InputError(f"must be an integer >= 1, got {budget!r}", field="budget")
    if level_error is None:
        level_error = session.level_error.get("object", 0.005) if session else 0.005
    if tilt_error is None:
        tilt_error = session.tilt_error.get("object", 0.0) if session else 0.0
    for name, v, lo, hi in (("noise", noise, 1e-6, 1.0), ("sigma_aim_m", sigma_aim_m, 0.0, 0.1),
                            ("level_error", level_error, 0.0, 0.5),
                            ("tilt_error", tilt_error, 0.0, 0.5)):
        if not (lo <= v <= hi):
            raise InputError(f"must lie in [{lo:g}, {hi:g}], got {v}", field=name)
    if not 1 <= draws <= 64:
        raise InputError(f"must be in [1, 64], got {draws}", field="draws")
    if not 2 <= spot_resolution <= 16:
        raise InputError(f"must be in [2, 16], got {spot_resolution}", field="spot_resolution")
    bad = [p for p in free if p not in PARAMETERS]
    if bad or not free:
        raise InputError(f"unknown parameter(s) {bad}; choose from {list(PARAMETERS)}",
                         field="free")
    names = [o.name for o in scene.objects]
    geoms = scene_geometry(scene)
    fo = fit_options or FitOptions()
    say("preparing the environment ...")
    env = scene_environment(scene, compress_tol=fo.compress_tol)
    timings["environment_s"] = time.perf_counter() - t0

    # the centre, the existing readings and what is free --------------------------------
    t1 = time.perf_counter()
    prep_s, values0, scale0, stderr0 = _centre(scene, session, fo, env, geoms, say)
    fit_scale = prep_s is not None and prep_s.problem.fit_scale
    timings["session_fit_s"] = time.perf_counter() - t1
    unknowns = _unknowns(scene, session, region, tuple(free),
                         prep_s.problem.free if prep_s is not None else ())
    labels = [f"{names[o]}.{PARAMETERS[k]}" for o, k in unknowns] + (["scale"] if fit_scale
                                                                    else [])
    F = len(labels)
    mask = np.array([True] * len(unknowns) + [False] * int(fit_scale))

    # the draws --------------------------------------------------------------------------
    centre = np.array([values0[o, k] for o, k in unknowns] + ([scale0] if fit_scale else []))
    lower, upper = _ranges(session, names, unknowns, centre, stderr0, fit_scale)
    y = draws_in_box(centre, lower, upper, n=draws, seed=seed)
    values, scale = _draw_values(values0, unknowns, y, fit_scale)
    tol = tolerances(values, unknowns, scale=scale if fit_scale else None)

    # the candidates ----------------------------------------------------------------------
    t1 = time.perf_counter()
    say("casting the candidates' central rays ...")
    sources = bright_directions(env, region.highlight_sources)
    cands = plan_candidates(scene, region, geoms, margin_m=2.0 * sigma_aim_m, sources=sources)
    _check_budget(budget, len(cands), region)
    say(f"{len(cands)} candidates; their sensitivities at {draws} parameter draws ...")
    info = candidate_information(scene, cands, values, free=unknowns, fit_scale=fit_scale,
                                 scale=scale, noise=noise, sigma_aim_m=sigma_aim_m,
                                 level=level_error, tilt=tilt_error,
                                 spot_resolution=spot_resolution,
                                 session=session, env=env,
                                 geometries=geoms, chunk=chunk, progress=say)
    ok = info["coverage"] >= _MIN_COVERAGE
    if not ok.any():
        raise region.error("objects", f"no candidate's {region.field_angles_deg} degree field "
                           "lies on its object (unreachable region)")
    cands = [c for c, k in zip(cands, ok, strict=True) if k]
    cinfo = info["information"][ok]
    timings["candidates_s"] = time.perf_counter() - t1
    _check_budget(budget, len(cands), region)

    # the information already there ---------------------------------------------------------
    base = np.zeros((draws, F, F))
    if prep_s is not None and prep_s.n_image_rows == 0:
        base = base + session_information(prep_s, values, scale=scale, unknowns=unknowns,
                                          fit_scale=fit_scale, tol=tol, sigma_aim_m=sigma_aim_m,
                                          resolution=fo.spot_resolution, level=level_error,
                                          tilt=tilt_error)

    # the choice ------------------------------------------------------------------------------
    t1 = time.perf_counter()
    say(f"choosing {budget} of {len(cands)} readings ...")
    idx, obj = select_readings(cinfo, budget, base=base, mask=mask, progress=say)
    timings["selection_s"] = time.perf_counter() - t1
    after = base + cinfo[idx].sum(axis=0)
    before_v = scaled_variances(base)
    after_v = scaled_variances(after)

    def worst(v: np.ndarray) -> np.ndarray:
        w = np.sqrt(np.max(v, axis=0))
        return np.where(np.max(v, axis=0) >= UNIDENTIFIED, math.inf, w)

    obj_before = float(np.max(worst(before_v)[mask]))
    chosen = _chosen_readings(cands, idx)
    timings["total_s"] = time.perf_counter() - t0
    return PlanResult(
        chosen=chosen, candidates=cands, unknowns=labels, tolerance=tol[0],
        stderr_before=stderr_from_information(base[0], tol[0]),
        stderr_after=stderr_from_information(after[0], tol[0]),
        worst_before=worst(before_v), worst_after=worst(after_v),
        objective_before=obj_before, objective_after=math.sqrt(obj) if obj < UNIDENTIFIED
        else math.inf,
        draws=y, information=cinfo, base_information=base, mask=mask,
        centre={names[o]: {p: float(values0[o, k]) for k, p in enumerate(PARAMETERS)}
                for o in sorted({o for o, _ in unknowns})},
        settings={"budget": budget, "noise": noise, "sigma_aim_m": sigma_aim_m,
                  "level_error": level_error, "tilt_error": tilt_error,
                  "draws": draws, "spot_resolution": spot_resolution, "seed": seed,
                  "session": None if session is None else str(session.path),
                  "region": region.path, "interreflection": "none (object readings)",
                  "bright_sources": [[round(float(x), 6) for x in d] for d in sources]},
        timings=timings)


def bright_directions(env: Any, count: int, *, separation_deg: float = 10.0,
                      contrast: float = 4.0) -> np.ndarray:
    """(S, 3) world directions of the environment's ``count`` brightest sources (S <= count),
    brightest first, where a highlight tells the gloss apart from the mirror.

    The map's texels (radiance summed over its channels) in order of radiance: each pick is
    the brightest texel more than ``separation_deg`` from every earlier pick and at least
    ``contrast`` times the map's median radiance (a uniform map has none); its direction is
    the radiance-weighted mean of the texels within ``separation_deg`` that reach half its
    radiance (a lamp's core)."""
    from ..lighting import texel_directions

    if count <= 0:
        return np.zeros((0, 3))
    tex = np.asarray(env.texels, np.float64)
    L = tex.sum(axis=-1).ravel()
    d = texel_directions(*tex.shape[:2]).reshape(-1, 3) @ np.asarray(env.rotation,
                                                                       np.float64).T
    floor = contrast * float(np.median(L))
    cos_sep = math.cos(math.radians(separation_deg))
    out: list[np.ndarray] = []
    for i in np.argsort(-L):
        if L[i] < floor or len(out) == count:
            break
        if any(float(d[i] @ q) >= cos_sep for q in out):
            continue
        core = (d @ d[i] >= cos_sep) & (L >= 0.5 * L[i])
        m = (L[core, None] * d[core]).sum(axis=0)
        out.append(m / np.linalg.norm(m))
    return np.asarray(out).reshape(-1, 3)


def _centre(scene: Scene, session: Session | None, fo: FitOptions, env: Any, geoms: Any,
            say: Callable[[str], None]) -> tuple[Any, np.ndarray, float, Any]:
    """(the session's PreparedFit or None, (O, 6) centre values, centre scale, the session
    fit's standard errors or None): the session's fit (one start), else the config's
    materials."""
    from ._fit import fit
    from ._prepare import prepare_fit

    values0 = np.array([[float(getattr(o.material, p)) for p in PARAMETERS]
                        for o in scene.objects])
    if session is None:
        return None, values0, 1.0, None
    say(f"fitting the session's {len(session.readings)} readings ...")
    prep = prepare_fit(scene, session, options=fo, env=env, geometries=geoms)
    res = fit(scene, session, options=dataclasses.replace(fo, starts=1, holdout=False,
                                                           aim_step_m=0.0, bootstrap=0),
              prepared=prep)
    values = np.asarray(res.values, np.float64)
    if res.status == "failed" or not np.all(np.isfinite(values)):
        raise InputError("the fit of the session's readings failed, so it cannot centre the "
                         "plan; check the session with `spectral-fit fit`", path=session.path,
                         field="readings")
    say(f"session fit: {res.status}, chi2/dof {res.chi2_red:.3g}")
    if session.images:  # the plan counts the information of the session's spots only
        say("the session's photographs centre the plan; its information counts the spots only")
        if session.readings:
            prep = prepare_fit(scene, session.replace(images=()), options=fo, env=env,
                               geometries=geoms)
    return prep, values, float(res.scale) if res.scale is not None else 1.0, res.stderr


def _draw_values(values0: np.ndarray, unknowns: tuple[tuple[int, int], ...], y: np.ndarray,
                 fit_scale: bool) -> tuple[np.ndarray, np.ndarray]:
    """(D, O, 6) parameters and (D,) scales of the draws ``y`` (D, F) of the unknowns."""
    values = np.repeat(values0[None], y.shape[0], 0)
    for j, (o, k) in enumerate(unknowns):
        values[:, o, k] = y[:, j]
    return values, (y[:, -1] if fit_scale else np.ones(y.shape[0]))


def _chosen_readings(cands: list[dict[str, Any]], idx: list[int]) -> list[dict[str, Any]]:
    """The chosen candidates as planned readings (ids ``plan_NN_object``)."""
    out = []
    for n, c in enumerate(idx):
        r = cands[c]
        out.append({"id": f"plan_{n + 1:02d}_{r['object']}", "object": r["object"],
                    "kind": "object", "aim": np.asarray(r["aim"]),
                    "position": np.asarray(r["position"]),
                    "field_angle_deg": float(r["field_angle_deg"]),
                    "distance_m": float(r["distance_m"]), "candidate": int(c)})
        if "highlight" in r:
            out[-1]["highlight"] = dict(r["highlight"])
    return out


def _check_budget(budget: int, n: int, region: Region) -> None:
    if budget > n:
        raise InputError(f"{budget} readings asked for but the region gives only {n} valid "
                         "candidates; widen the region or lower the budget", path=region.path,
                         field="budget")


def _ranges(session: Session | None, names: list[str], unknowns: tuple[tuple[int, int], ...],
            centre: np.ndarray, stderr: dict[str, dict[str, float]] | None, fit_scale: bool
            ) -> tuple[np.ndarray, np.ndarray]:
    """(F,) lower and upper ends of the draws: the default range around the centre
    (:func:`default_range`), narrowed to ± 3 standard errors of the session's fit where it
    determined the parameter, to ± 2σ of a stated prior, and to the stated bounds."""
    lo, hi = [], []
    keys = [(names[o], PARAMETERS[k]) for o, k in unknowns] + ([("", "scale")] if fit_scale
                                                               else [])
    for j, (name, p) in enumerate(keys):
        a, b = default_range(p, float(centre[j]))
        if stderr is not None and p != "scale":
            s = stderr.get(name, {}).get(p)
            if s is not None and math.isfinite(s) and s > 0:
                a, b = max(a, centre[j] - 3 * s), min(b, centre[j] + 3 * s)
        om = session.objects.get(name) if session is not None else None
        if om is not None:
            if p in om.prior:
                m, sd = om.prior[p]
                a, b = max(a, m - 2 * sd), min(b, m + 2 * sd)
            bl, bu = om.bounds.get(p, (None, None))
            a = a if bl is None else max(a, bl)
            b = b if bu is None else min(b, bu)
        if not a < b:
            a = b = float(centre[j])
        lo.append(a)
        hi.append(b)
    return np.asarray(lo), np.asarray(hi)
