"""Pictures for people: chromaticity diagrams, PNG images. All files are written atomically.

Matplotlib runs with the non-interactive Agg backend; colour-science draws the CIE 1931
chromaticity diagram (spectral locus and the coloured background).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from .._runtime.fileio import atomic_path

__all__ = ["save_png", "chromaticity_diagram"]


def save_png(path: str | os.PathLike[str], rgb: Any) -> None:
    """Write display-encoded RGB (H, W, 3) in [0, 1] as an 8-bit PNG (or a mask (H, W))."""
    from PIL import Image

    a = np.asarray(rgb, dtype=np.float64)
    a = np.round(np.clip(a, 0.0, 1.0) * 255.0).astype(np.uint8)
    with atomic_path(path) as tmp:
        Image.fromarray(a).save(tmp, format="PNG")


def chromaticity_diagram(
    path: str | os.PathLike[str],
    points: Mapping[str, Any],
    *,
    title: str = "",
    markers: Mapping[str, str] | None = None,
    weights: Mapping[str, Any] | None = None,
) -> None:
    """CIE 1931 xy chromaticity diagram with labelled point sets.

    Args:
        points: label → (N, 2) xy coordinates.
        markers: label → matplotlib marker (default "+" / "x" / "o" in turn), as the paper's
            Fig. 11/13 mark measured (+) and rendered (×) colours.
        weights: label → (N,) marker sizes (e.g. luminance shares); default constant.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import colour.plotting
    import matplotlib.pyplot as plt

    fig, ax = colour.plotting.plot_chromaticity_diagram_CIE1931(show=False,
                                                                 title=title or " ")
    cycle = ["+", "x", "o", "s", "^"]
    for i, (label, xy) in enumerate(points.items()):
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        m = (markers or {}).get(label, cycle[i % len(cycle)])
        s = (weights or {}).get(label, 36.0)
        ax.scatter(xy[:, 0], xy[:, 1], marker=m, s=s, label=label, c="black",
                   linewidths=1.0, alpha=0.8)
    ax.set_xlim(-0.05, 0.8)
    ax.set_ylim(-0.05, 0.9)
    ax.legend(loc="upper right")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png", bbox_inches="tight")
    plt.close(fig)
