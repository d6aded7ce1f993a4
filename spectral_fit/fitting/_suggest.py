"""The readings that would separate what a fit could not: correlated groups of unknowns, and a
plan of the next readings from the fitted session (``spectral-fit fit --suggest K``)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ..io import Scene, Session

__all__ = ["correlated_groups", "suggest_readings"]


def correlated_groups(free: list[str], correlation: np.ndarray, *, threshold: float = 0.95
                      ) -> list[list[str]]:
    """The groups of unknowns (labels of ``free``) joined by correlations |r| > ``threshold``
    (connected components of that graph), each of two or more, in ``free``'s order."""
    c = np.asarray(correlation, np.float64)
    n = len(free)
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(n):
        for j in range(i + 1, n):
            if np.isfinite(c[i, j]) and abs(c[i, j]) > threshold:
                parent[root(i)] = root(j)
    groups: dict[int, list[str]] = {}
    for i in range(n):
        groups.setdefault(root(i), []).append(free[i])
    return [g for g in groups.values() if len(g) > 1]


def suggest_readings(scene: Scene, session: Session, result: Any, *, budget: int,
                     region: Any = None, fit_options: Any = None,
                     progress: Callable[[str], None] | None = None, **plan_options: Any
                     ) -> tuple[dict[str, Any], Any]:
    """Plan ``budget`` more readings from the fitted ``session``
    (:func:`~spectral_fit.fitting.plan_measurements`, its fit the centre of the draws) and say
    what they do for the groups of unknowns the fit ``result`` could not separate.

    Returns:
        ({"groups": the correlated groups, "readings": the planned readings (id, object,
        position, aim, field angle), "stderr": {label: {"now", "after"}} of every unknown
        the plan predicts (the plan's own linearised errors before and after)}, the
        :class:`~spectral_fit.fitting.PlanResult`).
    """
    from ._plan import plan_measurements

    groups = correlated_groups(list(result.free), result.correlation)
    plan = plan_measurements(scene, session, budget=budget, region=region,
                             fit_options=fit_options, progress=progress, **plan_options)
    stderr = {label: {"now": float(b), "after": float(a)}
              for label, b, a in zip(plan.unknowns, plan.stderr_before, plan.stderr_after,
                                     strict=True)}
    readings = [{"id": r["id"], "object": r["object"],
                 "position": [float(x) for x in r["position"]],
                 "aim": [float(x) for x in r["aim"]],
                 "field_angle_deg": float(r["field_angle_deg"])} for r in plan.chosen]
    return {"groups": groups, "readings": readings, "stderr": stderr}, plan
