"""How far to believe the fitted render's colours: a per-pixel ΔE00 uncertainty map.

The fit's linearised covariance of the unknowns (standard errors × correlation, over
``result.free``) is propagated to the rendered frame by Monte Carlo: ``draws`` parameter
vectors θ_s = θ̂ + σ ⊙ (C^½ z_s), z_s ~ N(0, I), each rendered with the same compiled frame
program (the materials are its arguments: no recompile), and every covered pixel's CIEDE2000
difference (CIE 142-2001, colour-science) from the fitted frame. Per pixel the map holds the
root mean square over the draws, √E[ΔE00²] (for small errors ΔE00² is a quadratic form of
the parameters' errors, so this is the linearised propagation's answer without its
linearisation), and the 95th percentile. CIELAB is taken against the frame's display white
(Y = the exposure luminance, chromaticity the display's white point), so 1 ΔE00 is what a
viewer of the picture would call one unit.

Draws outside a parameter's physical range (α, β, μ > 0, n > 1, χ ≥ 0) are clipped to it
(an open end to a tenth of the way from it to the fitted value); a
parameter without a standard error (fixed, or not identified) does not vary.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..io import PARAMETERS, PHYSICAL_LOWER, Scene

__all__ = ["RenderUncertainty", "render_uncertainty"]


@dataclasses.dataclass(frozen=True)
class RenderUncertainty:
    """The fitted render's colour uncertainty (:func:`render_uncertainty`).

    Attributes:
        rms: (H, W) √(mean over draws of ΔE00²) per covered pixel; NaN elsewhere.
        p95: (H, W) the 95th percentile of ΔE00 over the draws; NaN elsewhere.
        rgb: (H, W, 3) the fitted frame, display-encoded [0, 1].
        mask: (H, W) bool, pixels covered by an object in the fitted frame.
        object_id: (H, W) int, object index per pixel (−1: background).
        draws: number of parameter draws.
        varied: labels ``object.parameter`` that varied (a standard error > 0).
    """

    rms: np.ndarray
    p95: np.ndarray
    rgb: np.ndarray
    mask: np.ndarray
    object_id: np.ndarray
    draws: int
    varied: list[str]

    def summary(self, names: list[str]) -> dict[str, Any]:
        """JSON-able figures: over all covered pixels and per object (``names`` in the
        scene's order), the median / 90th percentile / max of the per-pixel RMS ΔE00."""
        def stats(sel: np.ndarray) -> dict[str, float | int]:
            v = self.rms[sel]
            v = v[np.isfinite(v)]
            if v.size == 0:
                return {"pixels": 0}
            return {"pixels": int(v.size), "median": float(np.median(v)),
                    "p90": float(np.percentile(v, 90)), "max": float(v.max())}

        return {"draws": self.draws, "varied": self.varied, "all": stats(self.mask),
                "objects": {n: stats(self.object_id == i) for i, n in enumerate(names)}}


def render_uncertainty(scene: Scene, result: Any, *, draws: int = 32, seed: int = 0,
                       prep: Any = None) -> RenderUncertainty:
    """The per-pixel ΔE00 uncertainty of ``scene`` rendered with ``result``'s parameters.

    Args:
        scene: the scene config the fit was made for (its camera, frame size, objects).
        result: a :class:`~spectral_fit.fitting.FitResult` (or anything with ``params``
            {object: {parameter: value}}, ``stderr`` of the same shape, ``free`` labels
            ``object.parameter`` and their ``correlation`` (F, F)).
        draws: number of parameter draws (≥ 2).
        seed: the draws' random seed.
        prep: the scene prepared (default: :func:`~spectral_fit.rendering.prepare_cached`).

    Returns:
        :class:`RenderUncertainty`.
    """
    from .._runtime.errors import InputError
    from ..color import delta_e00

    if draws < 2:
        raise InputError(f"must be >= 2, got {draws}", field="draws")
    names = [o.name for o in scene.objects]
    theta, sd, varied = _parameters(result, names)
    corr = _correlation(result, varied)
    rng = np.random.default_rng(seed)
    w, v = np.linalg.eigh(corr)
    root = v * np.sqrt(np.clip(w, 0.0, None))  # C = root rootᵀ (C^½ up to a rotation)
    lower = np.array([[PHYSICAL_LOWER[p][0] for p in PARAMETERS]] * len(names))
    # an open end (μ = 0 is no lobe, n = 1 no interface) is not reached: a draw beyond it
    # stops a tenth of the way from it to the fitted value
    is_open = np.array([[PHYSICAL_LOWER[p][1] for p in PARAMETERS]] * len(names))
    lower = np.where(is_open, lower + 0.1 * np.maximum(theta - lower, 0.0), lower)

    fitted = fitted_frame(scene, theta, prep)
    mask = np.asarray(fitted["mask"], bool)
    lab0 = _lab(fitted, mask)
    de = np.empty((draws, int(mask.sum())))
    for s in range(draws):
        z = root @ rng.standard_normal(len(varied))
        t = theta.copy()
        for (i, j), zk in zip(varied_index(varied, names), z, strict=True):
            t[i, j] += sd[i, j] * zk
        t = np.maximum(t, lower)
        frame = fitted_frame(scene, t, fitted["prep"])
        de[s] = delta_e00(_lab(frame, mask, white=fitted["white"]), lab0)
    rms = np.full(mask.shape, np.nan)
    p95 = np.full(mask.shape, np.nan)
    rms[mask] = np.sqrt(np.mean(de ** 2, axis=0))
    p95[mask] = np.percentile(de, 95, axis=0)
    return RenderUncertainty(rms=rms, p95=p95, rgb=np.asarray(fitted["rgb"]), mask=mask,
                             object_id=np.asarray(fitted["object_id"]), draws=draws,
                             varied=varied)


def varied_index(varied: list[str], names: list[str]) -> list[tuple[int, int]]:
    """(object index, parameter index) of each ``object.parameter`` label."""
    out = []
    for label in varied:
        obj, par = label.rsplit(".", 1)
        out.append((names.index(obj), PARAMETERS.index(par)))
    return out


def _parameters(result: Any, names: list[str]) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(values (O, P), standard errors (O, P), labels of the unknowns with a standard
    error > 0, in ``result.free``'s order)."""
    theta = np.array([[float(result.params[n][p]) for p in PARAMETERS] for n in names])
    sd = np.zeros_like(theta)
    varied = []
    for label in result.free:
        if "." not in label:
            continue  # the environment's scale: not a material of the render
        obj, par = label.rsplit(".", 1)
        if obj not in names or par not in PARAMETERS:
            continue
        err = float(result.stderr[obj][par])
        if np.isfinite(err) and err > 0:
            sd[names.index(obj), PARAMETERS.index(par)] = err
            varied.append(label)
    return theta, sd, varied


def _correlation(result: Any, varied: list[str]) -> np.ndarray:
    """The correlation (K, K) of the ``varied`` unknowns from ``result.correlation`` (over
    ``result.free``); non-finite entries are taken as uncorrelated."""
    idx = [list(result.free).index(label) for label in varied]
    c = np.asarray(result.correlation, np.float64)[np.ix_(idx, idx)]
    c = np.where(np.isfinite(c), c, 0.0)
    np.fill_diagonal(c, 1.0)
    return c


def fitted_frame(scene: Scene, theta: np.ndarray, prep: Any = None) -> dict[str, Any]:
    """The frame of ``scene`` with the materials' parameters ``theta`` (O, P) (PARAMETERS'
    order): ``prep`` (default the scene prepared through the disk cache) and its compiled
    frame program run with them as arguments. Returns {prep, xyz, rgb, mask, object_id,
    white} as NumPy arrays (``white``: the display white's absolute XYZ)."""
    import jax.numpy as jnp

    from ..rendering import prepare_cached, regrow, render_frame_cached

    prep = prepare_cached(scene) if prep is None else prep
    mats = dataclasses.replace(prep.materials, **{
        p: jnp.asarray(theta[:, j], jnp.float32) for j, p in enumerate(PARAMETERS)})
    frame = regrow(prep, render_frame_cached(prep, mats), mats, False)
    return {"prep": prep, "xyz": np.asarray(frame.xyz, np.float64),
            "rgb": np.asarray(frame.rgb), "mask": np.asarray(frame.mask),
            "object_id": np.asarray(frame.object_id), "white": _display_white(prep)}


def _display_white(prep: Any) -> np.ndarray:
    """Absolute XYZ (3,) of the frame's display white: Y = the exposure luminance, the
    chromaticity of the white the display shows as white (the scene white when the frame
    adapts from it, else the display's own white point)."""
    import colour

    col = prep.colour
    xy = col.scene_white_xy if col.scene_white_xy is not None else col.display.white_xy
    return np.asarray(colour.xy_to_XYZ(np.asarray(xy, np.float64))) * float(col.exposure)


def _lab(frame: dict[str, Any], mask: np.ndarray, white: np.ndarray | None = None
         ) -> np.ndarray:
    """CIELAB (N, 3) of the ``mask``'s pixels against the display white."""
    from ..color import xyz_to_lab

    return xyz_to_lab(frame["xyz"][mask], frame["white"] if white is None else white)
