"""Fit reports: JSON, pictures, fitted materials (JSON and a Mitsuba 3 scene snippet).

:func:`write_report` writes into one folder (every file atomically):

- ``fit.json`` — parameters ± standard errors, profile-likelihood intervals, correlations,
  bootstrap spread, warnings, per
  reading ΔE00 / Δu′v′ / xy / u′v′ measured and fitted, the hold-out prediction, timings, and
  the spectra (measured, fitted, σ) on the scene's grid;
- ``materials.json`` — the fitted materials (our physical scaling and the paper's), with S(λ);
- ``materials_mitsuba.xml`` — the materials as ``spectral_fit_model`` BSDFs (the reference
  renderer's plugin, ``spectral_fit.validation.reference``);
- ``chromaticity.png`` — CIE 1931 xy diagram, measured (+) and rendered (×) colours of every
  reading, as the paper's Fig. 11/13;
- ``spectra.png`` — measured (points, ±2σ) and fitted spectra per reading;
- ``residuals.png`` — normalised residuals (fitted − measured)/σ per reading and band;
- ``profile.png`` — with the profile likelihood (``FitOptions.profile``,
  ``spectral-fit fit --profile``): each parameter's profile Δχ², its interval and the
  linearised parabola;
- ``image_<id>.png`` — per camera photograph of the session: its bins as measured and as
  fitted (camera counts, the same scale) and the normalised residual of each bin;
- ``render.png`` — the scene rendered with the fitted materials, when the frame renderer is
  available;
- ``uncertainty.png`` — beside it, the per-pixel ΔE00 uncertainty of that render from the
  fit's covariance (:func:`~spectral_fit.fitting.render_uncertainty`; its figures in
  ``fit.json``'s ``render_uncertainty``).

:func:`run_demo_fit` fits the bundled session and writes its report (used by
``spectral-fit demo``).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .._runtime.fileio import atomic_path, atomic_write_bytes, atomic_write_text
from .._runtime.paths import REPO_ROOT
from ..io import PARAMETERS, Scene, Session
from ._fit import FitResult

__all__ = ["write_report", "materials_json", "mitsuba_snippet", "run_demo_fit",
           "DEMO_SESSION", "DEMO_CONFIG", "recovery_table"]

ROOT = REPO_ROOT
DEMO_CONFIG = ROOT / "configs" / "two_spheres.toml"
DEMO_SESSION = ROOT / "measurements" / "sessions" / "two_spheres_demo"


def materials_json(result: FitResult, scene: Scene) -> dict[str, Any]:
    """Fitted materials: parameters (our physical scaling and the paper's), standard
    errors, S(λ), the microfacet model."""
    from ..lighting import to_paper_params

    out: dict[str, Any] = {"scaling": "physical, docs/conventions.md (alpha = 1: ideal Lambertian "
                           "of albedo S; "
                           "beta = 1: energy-normalised microfacet lobe)",
                           "relative_to": result.relative_to,
                           "wavelengths_nm": [float(w) for w in result.wavelengths],
                           "objects": {}}
    for o in scene.objects:
        p = result.params[o.name]
        out["objects"][o.name] = {
            "params": p, "stderr": result.stderr[o.name],
            "paper_params": to_paper_params(dict(p)),
            "distribution": o.material.distribution, "geometry": o.material.geometry,
            "reflectance": [float(x) for x in o.material.reflectance],
        }
    return out


def mitsuba_snippet(result: FitResult, scene: Scene, reflectance: dict[str, Any] | None = None
                    ) -> str:
    """Mitsuba 3 XML: one ``spectral_fit_model`` BSDF per object (the reference renderer's
    plugin; register it with ``spectral_fit.validation.reference``). ``s0, s1, s2`` carry S(λ) at
    three
    bands: the reference renders ⌈L/3⌉ band triples; the default triple here is S averaged
    over 400–500, 500–600 and 600–700 nm (an RGB-like preview)."""
    wl = np.asarray(result.wavelengths)
    lines = ["<!-- fitted materials (spectral_fit fit); plugin spectral_fit_model from",
             "     spectral_fit.validation.reference; s0..s2 = S(lambda) band means 400-500,",
             "     500-600, 600-700 nm; full S(lambda) in materials.json -->"]
    for o in scene.objects:
        p = result.params[o.name]
        s = np.asarray((reflectance or {}).get(o.name, o.material.reflectance), np.float64)
        bands = [float(np.mean(s[(wl >= a) & (wl < b)])) if np.any((wl >= a) & (wl < b))
                 else float(np.mean(s)) for a, b in ((400, 500), (500, 600), (600, 700))]
        lines.append(f'<bsdf type="spectral_fit_model" id="{o.name}">')
        for k in ("alpha", "beta", "chi", "mu", "n"):
            lines.append(f'    <float name="{k}" value="{p[k]:.6g}"/>')
        for i, v in enumerate(bands):
            lines.append(f'    <float name="s{i}" value="{v:.6g}"/>')
        lines.append(f'    <string name="distribution" value="{o.material.distribution}"/>')
        lines.append(f'    <string name="geometry" value="{o.material.geometry}"/>')
        lines.append("</bsdf>")
    return "\n".join(lines) + "\n"


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> None:
    plt = _plt()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png", bbox_inches="tight")
    plt.close(fig)


def _spectra_plot(result: FitResult, path: Path) -> None:
    plt = _plt()
    B = result.measured.shape[0]
    cols = min(5, B)
    rows = int(math.ceil(B / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.5 * rows), squeeze=False)
    wl = result.wavelengths
    for b in range(rows * cols):
        ax = axes[b // cols][b % cols]
        if b >= B:
            ax.axis("off")
            continue
        r = result.readings[b]
        ax.errorbar(wl, result.measured[b], yerr=2 * result.sigma[b], fmt=".", ms=2,
                    lw=0.5, color="0.3", label="measured")
        ax.plot(wl, result.fitted[b], "-", color="C3", lw=1.2, label="fitted")
        ax.set_title(f"{r['id']} ({r['kind'][:6]}) ΔE00 {r['delta_e00']:.2f}", fontsize=8)
        ax.tick_params(labelsize=7)
        if b == 0:
            ax.legend(fontsize=7)
    fig.supxlabel("wavelength (nm)")
    fig.supylabel("radiance (W sr⁻¹ m⁻² nm⁻¹)")
    _save(fig, path)


def _residual_plot(result: FitResult, path: Path) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 3.5))
    z = (result.fitted - result.measured) / result.sigma
    for b, r in enumerate(result.readings):
        ax.plot(result.wavelengths, z[b], lw=0.8, label=r["id"],
                ls="-" if r["kind"] == "object" else "--")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("(fitted − measured) / σ")
    ax.legend(fontsize=6, ncol=2)
    ax.set_title(f"normalised residuals (χ²/dof = {result.chi2_red:.2f})")
    _save(fig, path)


def _image_plot(im: dict[str, Any], path: Path) -> None:
    """Measured and fitted bins of one photograph (channels as RGB, one scale: the 99th
    percentile of the measured counts) and the mean normalised residual of each bin, cropped
    to the bins used."""
    plt = _plt()
    r, c = np.asarray(im["bin_row"]), np.asarray(im["bin_col"])
    m, f, sg = (np.asarray(im[k], np.float64) for k in ("measured", "fitted", "sigma"))
    if r.size == 0:
        return
    r0, c0 = max(int(r.min()) - 1, 0), max(int(c.min()) - 1, 0)
    rows, cols = int(r.max()) + 2 - r0, int(c.max()) + 2 - c0
    r, c = r - r0, c - c0
    C = m.shape[1]
    top = max(float(np.percentile(m, 99)), 1e-30)
    pics = []
    for a in (m, f):
        img = np.zeros((rows, cols, 3))
        img[r, c] = (a / top)[:, [0, min(1, C - 1), min(2, C - 1)]]
        pics.append(np.clip(img, 0.0, 1.0) ** (1 / 2.2))
    z = np.full((rows, cols), np.nan)
    z[r, c] = np.mean((f - m) / sg, axis=1)
    lim = max(float(np.nanpercentile(np.abs(z), 98)), 1e-6)
    w = 4.2
    fig, axes = plt.subplots(1, 3, figsize=(3 * w + 1.0, w * rows / cols + 0.9),
                             layout="constrained")
    for ax, pic, title in zip(axes[:2], pics, ("measured", "fitted"), strict=True):
        ax.imshow(pic, interpolation="nearest")
        ax.set_title(f"{im['id']}: {title}, {im['superpixel']}-pixel bins", fontsize=9)
        ax.axis("off")
    h = axes[2].imshow(z, cmap="RdBu_r", vmin=-lim, vmax=lim, interpolation="nearest")
    axes[2].set_title(f"(fitted - measured)/σ, mean of channels\nrms relative "
                      f"{100 * (im['rms_relative_residual'] or 0):.2g} %", fontsize=9)
    axes[2].axis("off")
    fig.colorbar(h, ax=axes[2], fraction=0.04)
    _save(fig, path)


def _profile_plot(result: FitResult, path: Path) -> None:
    """One panel per free parameter: the profile's Δχ² (in units of max(1, χ²/dof)) at the
    held values, the interval's ends, and the parabola of the linearised standard error."""
    plt = _plt()
    prof = result.profile or {}
    labels = list(prof)
    cols = min(5, len(labels))
    rows = int(math.ceil(len(labels) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.0 * cols, 2.6 * rows), squeeze=False)
    fig.subplots_adjust(hspace=0.45, wspace=0.3)
    se = {f"{o}.{k}": v for o, d in result.stderr.items() for k, v in d.items()}
    if result.scale_stderr is not None:
        se["scale"] = result.scale_stderr
    for i in range(rows * cols):
        ax = axes[i // cols][i % cols]
        if i >= len(labels):
            ax.axis("off")
            continue
        iv = prof[labels[i]]
        x = np.asarray(iv["held"], np.float64)
        z = np.asarray(iv["delta_chi2"], np.float64)
        ok = np.isfinite(x) & np.isfinite(z)
        ax.plot(np.r_[x[ok], iv["value"]], np.r_[z[ok], 0.0], ".", color="C0", ms=5,
                label="profile")
        s_ = se.get(labels[i], 0.0)
        if s_ > 0:
            xx = np.linspace(np.nanmin(x), np.nanmax(x), 100)
            ax.plot(xx, ((xx - iv["value"]) / s_) ** 2, "--", color="0.5", lw=0.8,
                    label="linearised")
        ax.axhline(1.0, color="k", lw=0.5)
        for end in ("lower", "upper"):
            ax.axvline(iv[end], color="C3", lw=0.8, ls="-" if iv[f"{end}_end"] == "profile"
                       else ":")
        ax.set_ylim(0, 9)
        # the held values up to Δχ² = 9 (3σ) and the interval's ends, with a margin
        near = x[ok & (z <= 9.0)]
        span = np.r_[near, iv["lower"], iv["upper"], iv["value"]]
        pad = 0.15 * max(np.ptp(span), 1e-12)
        ax.set_xlim(span.min() - pad, span.max() + pad)
        ax.set_title(labels[i], fontsize=8)
        ax.tick_params(labelsize=7)
        if i == 0:
            ax.legend(fontsize=6)
    fig.supylabel("Δχ² / max(1, χ²/dof)")
    fig.suptitle("profile likelihood: interval ends (red) where Δχ² = 1; dotted: open or at a "
                 "bound", fontsize=9)
    _save(fig, path)


def _render(scene: Scene, result: FitResult, path: Path) -> str | None:
    """Render the fitted scene when the frame renderer exists; returns a note otherwise."""
    try:
        from ..rendering import regrow  # noqa: F401  (the frame renderer is in this build)
    except ImportError:
        return "frame renderer not available in this build"
    try:
        # the config's scene prepared (and kept on disk: nothing in it depends on the
        # materials' parameters) and its frame program run with the fitted parameters as
        # arguments, so a later report loads both instead of preparing and compiling again;
        # the picture is renderer.render of the fitted scene (tests/test_fitting.py)
        from ..color import save_png
        from ._render_uncertainty import fitted_frame

        theta = np.array([[float(result.params[o.name][k]) for k in PARAMETERS]
                          for o in scene.objects])
        save_png(path, fitted_frame(scene, theta)["rgb"])
        return None
    except Exception as exc:  # a failed picture must not lose the fit's report
        return f"render failed: {type(exc).__name__}: {exc}"


def _uncertainty(scene: Scene, result: FitResult, path: Path, folder: Path | None,
                 key: str | None) -> tuple[dict[str, Any], str]:
    """``uncertainty.png`` (the fitted render beside its per-pixel RMS ΔE00 from the fit's
    covariance) and its figures (:meth:`RenderUncertainty.summary`), kept beside the cached
    picture as ``<key>.json``; ({"note": ...}, hit) when it could not be drawn."""
    figures: dict[str, Any] = {}
    side = None if folder is None or key is None else folder / f"{key[:40]}.json"
    if side is not None:
        with contextlib.suppress(OSError, ValueError):
            figures = json.loads(side.read_text())

    def draw(p: Path) -> str | None:
        try:
            from ._render_uncertainty import render_uncertainty

            unc = render_uncertainty(scene, result)
            figures.clear()
            figures.update(unc.summary([o.name for o in scene.objects]))
            _uncertainty_plot(unc, figures, p)
            return None
        except Exception as exc:  # a failed picture must not lose the fit's report
            return f"uncertainty failed: {type(exc).__name__}: {exc}"

    note, hit = _cached_picture(folder, key, path, draw)
    if note is None and hit == "hit" and not figures:  # a kept picture without its figures
        note, hit = draw(path), "miss"
    if note is not None:
        return {"note": note}, hit
    if side is not None and hit != "hit":
        with contextlib.suppress(OSError):
            atomic_write_text(side, json.dumps(figures) + "\n")
    return figures, hit


def _uncertainty_plot(unc: Any, figures: dict[str, Any], path: Path) -> None:
    """The fitted render and its RMS ΔE00 map side by side, cropped to the objects."""
    plt = _plt()
    h, w = unc.mask.shape
    rows, cols = np.nonzero(unc.mask) if unc.mask.any() else ([0, h - 1], [0, w - 1])
    pad = max(4, int(0.15 * max(np.ptp(rows), np.ptp(cols))))
    y0, y1 = max(0, int(np.min(rows)) - pad), min(h, int(np.max(rows)) + pad + 1)
    x0, x1 = max(0, int(np.min(cols)) - pad), min(w, int(np.max(cols)) + pad + 1)
    crop = (slice(y0, y1), slice(x0, x1))
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2), layout="constrained")
    axes[0].imshow(np.clip(unc.rgb[crop], 0.0, 1.0), interpolation="nearest")
    axes[0].set_title("fitted render", fontsize=9)
    rms = np.where(unc.mask, unc.rms, np.nan)[crop]
    vmax = max(float(np.nanpercentile(rms, 99)), 0.1) if unc.mask.any() else 1.0
    im = axes[1].imshow(rms, cmap="magma", vmin=0.0, vmax=vmax, interpolation="nearest")
    a = figures.get("all", {})
    axes[1].set_title(f"ΔE00 uncertainty (RMS, {unc.draws} draws)\n"
                      f"median {a.get('median', float('nan')):.3f}, "
                      f"p90 {a.get('p90', float('nan')):.3f}, "
                      f"max {a.get('max', float('nan')):.3f}", fontsize=9)
    fig.colorbar(im, ax=list(axes), shrink=0.8, label="ΔE00")
    for ax in axes:
        ax.set_axis_off()
    _save(fig, path)


# pictures kept per cache folder (oldest removed first)
_MAX_PICTURES = 48


def _picture_digest(*parts: str) -> str:
    """SHA-256 over the package sources, library versions and backend (the rendering
    caches' environment digest), matplotlib's and Pillow's versions and ``parts``."""
    from ..rendering import distribution_version, environment_digest

    h = hashlib.sha256()
    for part in (environment_digest(), f"matplotlib={distribution_version('matplotlib')}",
                 f"pillow={distribution_version('pillow')}", *parts):
        h.update(part.encode())
        h.update(b"\0")
    return h.hexdigest()


def _cached_picture(folder: Path | None, key: str | None, path: Path,
                    draw: Callable[[Path], str | None]) -> tuple[str | None, str]:
    """Write the picture ``path`` by ``draw`` (returns None, or a note when it could not draw),
    or copy it from ``folder/<key>.png`` where an earlier report drew it from the same data.
    Returns (the note, "hit" | "miss" | "off")."""
    if folder is None or key is None:
        return draw(path), "off"
    entry = folder / f"{key[:40]}.png"
    with contextlib.suppress(OSError):
        data = entry.read_bytes()
        if data.startswith(b"\x89PNG\r\n\x1a\n"):
            atomic_write_bytes(path, data)
            return None, "hit"
    note = draw(path)
    if note is None:
        with contextlib.suppress(OSError):  # a cache that cannot be written is skipped
            atomic_write_bytes(entry, path.read_bytes())
            kept = sorted(folder.glob("*.png"), key=lambda q: q.stat().st_mtime_ns)
            for old in kept[:-_MAX_PICTURES]:
                with contextlib.suppress(OSError):
                    old.unlink()
    return note, "miss"


def write_report(result: FitResult, out_dir: str | os.PathLike[str], *, scene: Scene,
                 session: Session | None = None, render: bool = True,
                 cache_dir: str | os.PathLike[str] | None = None,
                 timing: Mapping[str, float] | None = None,
                 started: float | None = None,
                 extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Write the report files (see the module docstring); returns the JSON summary.

    Args:
        result, scene, session: the fit, its scene and session.
        out_dir: the report's folder (created).
        render: also write ``render.png`` (the scene with the fitted materials).
        cache_dir: keep the pictures under ``<cache_dir>/fit_report``, keyed by the data they
            show (every value of the summary but its timings; for ``render.png`` the scene and
            the fitted parameters) with the package sources and the library versions; a later
            report of the same data copies them instead of drawing again. None: no cache.
        timing: seconds of stages before the fit (e.g. ``startup_s``, ``load_s``), put into
            the summary's ``timing`` block.
        started: ``time.perf_counter()`` when the work began (the command's start): the
            block's ``total_s`` is measured from it; default the fit's and the report's
            seconds.
        extra: further blocks for ``fit.json`` (e.g. ``suggested``: the readings that would
            separate what the fit could not, :func:`~spectral_fit.fitting.suggest_readings`).
    """
    t_report = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = result.to_json()
    summary["scene"] = str(getattr(scene, "path", ""))
    if session is not None:
        summary["session"] = str(session.path)
    summary["spectra"] = {
        "wavelengths_nm": result.wavelengths.tolist(),
        "measured": result.measured.tolist(), "fitted": result.fitted.tolist(),
        "sigma": result.sigma.tolist(), "calibration": result.calibration.tolist(),
    }
    pictures = ["chromaticity.png", "spectra.png", "residuals.png"] if result.readings else []
    folder = None if cache_dir is None else Path(cache_dir) / "fit_report"
    data_digest = None
    if folder is not None:  # what the pictures show: everything but the timings
        shown = {k: v for k, v in summary.items() if k not in ("timings", "scene", "session")}
        data_digest = _picture_digest(json.dumps(shown, sort_keys=True, allow_nan=True))

    def key(name: str) -> str | None:
        return None if data_digest is None else _picture_digest(data_digest, name)

    def chromaticity(path: Path) -> None:
        from ..color import chromaticity_diagram

        xy_m = np.array([r["xy_measured"] for r in result.readings])
        xy_f = np.array([r["xy_fitted"] for r in result.readings])
        chromaticity_diagram(path, {"measured": xy_m, "rendered (fit)": xy_f},
                             markers={"measured": "+", "rendered (fit)": "x"},
                             title="Spectroradiometer spots: measured (+) vs fitted render (×)")

    drawers: list[tuple[str, Callable[[Path], None]]] = [
        ("chromaticity.png", chromaticity),
        ("spectra.png", lambda p: _spectra_plot(result, p)),
        ("residuals.png", lambda p: _residual_plot(result, p))] if result.readings else []
    for im in result.images:
        name = f"image_{im['id']}.png"
        drawers.append((name, lambda p, im=im: _image_plot(im, p)))
        pictures.append(name)
    if result.profile:
        drawers.append(("profile.png", lambda p: _profile_plot(result, p)))
        pictures.append("profile.png")
    hits = []
    for name, draw in drawers:
        hits.append(_cached_picture(folder, key(name), out / name,
                                    lambda p, d=draw: d(p))[1])
    if render:
        from ..rendering import scene_text

        scene_part = scene_text(scene) if folder is not None else None
        render_key = None if scene_part is None else _picture_digest(
            "render.png", scene_part, json.dumps(result.params, sort_keys=True))
        note, hit = _cached_picture(folder, render_key, out / "render.png",
                                    lambda p: _render(scene, result, p))
        hits.append(hit)
        if note is None:
            pictures.append("render.png")
            unc_key = None if render_key is None else _picture_digest(
                "uncertainty.png", render_key, json.dumps(
                    [result.stderr, result.free, np.asarray(result.correlation).tolist()],
                    sort_keys=True, allow_nan=True))
            figures, hit = _uncertainty(scene, result, out / "uncertainty.png", folder, unc_key)
            hits.append(hit)
            if "note" in figures:
                summary["render_uncertainty_note"] = figures["note"]
            else:
                pictures.append("uncertainty.png")
                summary["render_uncertainty"] = figures
        else:
            summary["render_note"] = note
    summary.update(extra or {})
    summary["pictures"] = pictures
    atomic_write_text(out / "materials.json", json.dumps(
        _json_ready(materials_json(result, scene)), indent=2, allow_nan=False) + "\n")
    atomic_write_text(out / "materials_mitsuba.xml", mitsuba_snippet(result, scene))
    summary["files"] = pictures + ["fit.json", "materials.json", "materials_mitsuba.xml"]
    summary["timing"] = _timing_block(result, timing, started, time.perf_counter() - t_report,
                                      hits)
    atomic_write_text(out / "fit.json", json.dumps(_json_ready(summary), indent=2,
                                                   allow_nan=False) + "\n")
    return summary


def _json_ready(x: Any) -> Any:
    """``x`` with every non-finite float (NaN, ±inf: an undefined standard error, an empty
    statistic) as None, so the file is strict JSON."""
    if isinstance(x, dict):
        return {k: _json_ready(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_ready(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, np.ndarray):
        return _json_ready(x.tolist())
    if isinstance(x, np.integer):
        return int(x)
    return x


def _timing_block(result: FitResult, before: Mapping[str, float] | None,
                  started: float | None, report_s: float, pictures: list[str]
                  ) -> dict[str, Any]:
    """The report's ``timing``: seconds per stage and where the disk caches were hit."""
    t = result.timings
    caches = dict(t.get("caches", {}))
    caches["pictures"] = ("off" if not pictures or all(h == "off" for h in pictures) else
                          "hit" if all(h == "hit" for h in pictures) else
                          "miss" if all(h != "hit" for h in pictures) else "partial")
    out: dict[str, Any] = {k: float(v) for k, v in (before or {}).items()}
    out.update({
        "preparation_s": float(t.get("prepare_s", 0.0)),
        "compile_and_solve_s": float(t.get("solve_s", 0.0)),
        "holdout_s": float(t.get("holdout_s", 0.0)),
        "aim_sensitivity_s": float(t.get("aim_sensitivity_s", 0.0)),
        "fit_s": float(t.get("total_s", 0.0)),
        "report_s": float(report_s),
    })
    out["total_s"] = (time.perf_counter() - started if started is not None
                      else out["fit_s"] + out["report_s"])
    used = [v for k, v in caches.items() if not k.startswith("programs_")]
    out["warm"] = (all(v in ("hit", "skipped") for v in used)
                   and caches.get("programs_compiled", 0) == 0)
    out["caches"] = caches
    return out


def recovery_table(result: FitResult, truth: dict[str, dict[str, float]]) -> list[dict]:
    """Rows object/parameter/true/fitted/stderr/error for a session with known parameters."""
    rows = []
    for obj, tp in truth.items():
        for p in PARAMETERS:
            if p not in tp or obj not in result.params:
                continue
            got = result.params[obj][p]
            rows.append({"object": obj, "param": p, "true": tp[p], "fitted": got,
                         "stderr": result.stderr[obj][p], "error": got - tp[p]})
    return rows


def run_demo_fit(out_dir: str | os.PathLike[str], *, progress: Any = None,
                 render: bool = False) -> dict[str, Any]:
    """Fit the bundled session (configs/two_spheres.toml + measurements/sessions/
    two_spheres_demo) and write its report into ``out_dir``; returns a summary with the
    recovered-parameter table against the session's stated truth."""
    from ..io import load_scene, load_session
    from ._fit import fit

    t0 = time.perf_counter()
    scene = load_scene(DEMO_CONFIG)
    session = load_session(DEMO_SESSION, scene=scene)
    # All readings, interreflection readings included, with the interreflection term inside
    # the forward model (spectral_fit.fitting); the report's hold-out fits the
    # object-colour readings alone and predicts the interreflection readings.
    res = fit(scene, session, progress=progress, aim_step_m=0.0)
    summary = write_report(res, out_dir, scene=scene, session=session, render=render)
    truth_path = DEMO_SESSION / "truth.json"
    table = None
    if truth_path.is_file():
        truth = json.loads(truth_path.read_text())
        table = recovery_table(res, truth.get("params") or truth.get("materials", {}))
    return {"output": str(out_dir), "status": res.status, "params": res.params,
            "stderr": res.stderr, "recovery": table, "warnings": res.warnings,
            "mean_delta_e00": float(np.mean([r["delta_e00"] for r in res.readings])),
            "holdout": summary.get("holdout"), "pictures": summary["pictures"],
            "seconds": time.perf_counter() - t0, "timings": res.timings}
