"""Outputs of a measurement plan (:func:`write_plan`): a session template with the planned
readings (``session.toml``, ``files = []`` to fill in), ``plan.json`` and ``plan.png`` (where to
stand and aim: top and side views). Every file is written atomically.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..io import Scene, toml_value
from ._plan import PlanResult

__all__ = ["write_plan", "plan_session_toml"]


def plan_session_toml(result: PlanResult, *, scene_ref: str, units: str = "W.sr^-1.m^-2.nm^-1"
                      ) -> str:
    """The manifest of a session of the planned readings (``docs/measurements.md``), each
    with ``files = []``: once every reading's spectrum files are listed, the session loader
    reads it. ``scene_ref``: the scene config's path relative to the manifest's folder."""
    out = ["# Planned readings (docs/planning.md). Take each reading, export its spectra and list",
           "# them in its `files`; add [white_standard] and [dark] as in docs/measurements.md.",
           "", "[session]", "format = 1", f"scene = {toml_value(scene_ref)}",
           f"units = {toml_value(units)}",
           f"notes = {toml_value(f'{len(result.chosen)} planned readings')}"]
    for r in result.chosen:
        out += ["", "[[readings]]", f"id = {toml_value(r['id'])}",
                f"object = {toml_value(r['object'])}", f"kind = {toml_value(r['kind'])}",
                "files = []",
                f"aim = {toml_value([round(float(x), 6) for x in r['aim']])}",
                f"position = {toml_value([round(float(x), 6) for x in r['position']])}",
                f"field_angle_deg = {toml_value(float(r['field_angle_deg']))}",
                f"distance_m = {toml_value(round(float(r['distance_m']), 4))}"]
    return "\n".join(out) + "\n"


def _picture(result: PlanResult, scene: Scene, path: Path) -> None:
    """Top (x–z) and side (z–y) views: objects as circles, instrument positions numbered
    (``h``: a highlight reading), aim lines to the aim points, and arrows towards the
    environment's bright sources whose highlights were candidates."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .._runtime.fileio import atomic_path
    from ._prepare import scene_geometry

    geoms = scene_geometry(scene)
    colours = {o.name: f"C{i}" for i, o in enumerate(scene.objects)}
    fig, axes = plt.subplots(1, 2, figsize=(12, 6))
    for ax, (a, b), title in ((axes[0], (0, 2), "top view (x, z)"),
                              (axes[1], (2, 1), "side view (z, y)")):
        for o, g in zip(scene.objects, geoms, strict=True):
            c = np.asarray(o.position, np.float64)
            r = float(np.max(np.linalg.norm(np.asarray(g.vertices, np.float64) - c, axis=1)))
            ax.add_patch(plt.Circle((c[a], c[b]), r, fill=False, color=colours[o.name], lw=2))
            ax.annotate(o.name, (c[a], c[b]), ha="center", va="center",
                        color=colours[o.name], fontsize=9)
        labels: dict[tuple[float, float], list[str]] = {}
        for n, rd in enumerate(result.chosen):
            p, t = np.asarray(rd["position"]), np.asarray(rd["aim"])
            col = colours.get(rd["object"], "k")
            ax.plot([p[a], t[a]], [p[b], t[b]], "-", color=col, lw=0.8, alpha=0.8)
            ax.plot(p[a], p[b], "^", color=col, ms=7)
            ax.plot(t[a], t[b], "o", color=col, ms=3)
            labels.setdefault((round(p[a], 3), round(p[b], 3)), []).append(
                f"{n + 1}h" if "highlight" in rd else str(n + 1))
        centre = np.mean([np.asarray(o.position, np.float64) for o in scene.objects], axis=0)
        span = max(np.ptp([np.asarray(r["position"], np.float64)[[a, b]] for r in result.chosen]
                          + [centre[[a, b]]], axis=0).max(), 0.05)
        for si, d in enumerate(result.settings.get("bright_sources", [])):
            d = np.asarray(d, np.float64)
            tip = (centre[a] + 0.45 * span * d[a], centre[b] + 0.45 * span * d[b])
            ax.annotate("", xy=tip, xytext=(centre[a], centre[b]),
                        arrowprops={"arrowstyle": "->", "color": "0.5", "lw": 1.0})
            ax.text(tip[0], tip[1], f" source {si + 1}", fontsize=8, color="0.35",
                    ha="left", va="center")
            ax.plot([tip[0]], [tip[1]], alpha=0.0)  # in the autoscaled limits
        for (u, v), text in labels.items():  # readings from one place share a label
            ax.annotate(",".join(text), (u, v), textcoords="offset points", xytext=(4, 4),
                        fontsize=9)
        ax.set_xlabel(["x", "y", "z"][a] + " (m)")
        ax.set_ylabel(["x", "y", "z"][b] + " (m)")
        ax.set_title(title)
        ax.set_aspect("equal")
        ax.autoscale_view()
        ax.grid(alpha=0.3)
    fig.suptitle(f"{len(result.chosen)} planned readings (triangle: instrument, dot: aim point, "
                 f"h: on a bright source's highlight); worst standard error "
                 f"{result.objective_after:.3g} tolerances")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


def write_plan(result: PlanResult, folder: str | os.PathLike[str], *, scene: Scene,
               config_path: str | os.PathLike[str], picture: bool = True) -> dict[str, str]:
    """Write ``session.toml`` (the planned readings), ``plan.json`` and ``plan.png`` into
    ``folder`` (created; each file atomically). Returns {what: path}."""
    from .._runtime.fileio import atomic_write_text

    root = Path(folder)
    root.mkdir(parents=True, exist_ok=True)
    ref = os.path.relpath(Path(config_path).resolve(), root.resolve())
    out = {"session": str(root / "session.toml"), "plan": str(root / "plan.json")}
    atomic_write_text(out["session"], plan_session_toml(result, scene_ref=ref))
    atomic_write_text(out["plan"], json.dumps(result.to_json(), indent=2) + "\n")
    if picture:
        out["picture"] = str(root / "plan.png")
        _picture(result, scene, Path(out["picture"]))
    return out
