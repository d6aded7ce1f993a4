"""The fitted render's per-pixel ΔE00 uncertainty (fitting.render_uncertainty) against the
linearised propagation done independently: the frame's per-parameter Jacobian by central
finite differences of the renderer, CIELAB by colour-science, and the CIEDE2000 metric
tensor of every pixel by finite differences of colour-science's CIEDE2000."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A two-sphere scene (160 × 100) whose prepared scene and frame program the module's
    tests share (one cache folder for the module)."""
    from helpers.rendering import scene_toml as two_spheres_toml
    from helpers.rendering import symmetric_environment

    from spectral_fit.io import load_scene

    root = tmp_path_factory.mktemp("unc")
    env = symmetric_environment(root / "env.exr")
    cfg = root / "scene.toml"
    cfg.write_text(two_spheres_toml(env, stacks=12, width=160, height=100, same_colour=False,
                                    chi=0.05))
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SPECTRAL_FIT_CACHE", str(root / "cache"))
        yield load_scene(cfg)


def _result(scene):
    names = [o.name for o in scene.objects]
    params = {n: {"alpha": 0.6 + 0.1 * i, "beta": 0.4, "chi": 0.02, "mu": 0.17, "n": 1.5,
                  "gamma": 1.0} for i, n in enumerate(names)}
    free = [f"{names[0]}.alpha", f"{names[0]}.beta", f"{names[0]}.mu", f"{names[1]}.alpha",
            f"{names[1]}.n", "scale"]
    sd = {f"{names[0]}.alpha": 0.012, f"{names[0]}.beta": 0.03, f"{names[0]}.mu": 0.006,
          f"{names[1]}.alpha": 0.01, f"{names[1]}.n": 0.03}
    stderr = {n: {p: 0.0 for p in params[n]} for n in names}
    for label, v in sd.items():
        o, p = label.split(".")
        stderr[o][p] = v
    corr = np.eye(len(free))
    corr[0, 1] = corr[1, 0] = -0.8  # α–β of the first object, as fits report them
    corr[1, 2] = corr[2, 1] = 0.5
    return SimpleNamespace(params=params, stderr=stderr, free=free, correlation=corr), sd


def test_render_uncertainty_against_linearised_propagation(scene):
    """√E[ΔE00²] per pixel from 300 draws equals √trace(M J Σ Jᵀ), with J the finite-
    difference Jacobian of the pixel's CIELAB and M CIEDE2000's local metric: the median
    ratio over chromatic pixels within 8 %, 90 % of them within 25 % (Monte Carlo noise of
    an RMS of 300 draws ≈ 4 %; ΔE00 is not exactly quadratic over the draws' spread)."""
    from spectral_fit.color import delta_e00, xyz_to_lab
    from spectral_fit.fitting import render_uncertainty
    from spectral_fit.fitting._render_uncertainty import fitted_frame

    res, sd = _result(scene)
    unc = render_uncertainty(scene, res, draws=300, seed=1)
    mask = unc.mask
    assert mask.sum() > 100 and unc.varied == list(sd)
    names = [o.name for o in scene.objects]
    from spectral_fit.io import PARAMETERS

    theta = np.array([[res.params[n][p] for p in PARAMETERS] for n in names])
    base = fitted_frame(scene, theta)
    white = base["white"]
    lab0 = xyz_to_lab(base["xyz"][mask], white)
    cols = []
    for label, s in sd.items():
        o, p = label.split(".")
        i, j = names.index(o), PARAMETERS.index(p)
        h = 0.1 * s
        up, dn = theta.copy(), theta.copy()
        up[i, j] += h
        dn[i, j] -= h
        lu = xyz_to_lab(fitted_frame(scene, up, base["prep"])["xyz"][mask], white)
        ld = xyz_to_lab(fitted_frame(scene, dn, base["prep"])["xyz"][mask], white)
        cols.append((lu - ld) / (2 * h) * s)  # per unit of the normalised parameter
    jac = np.stack(cols, axis=-1)  # (N, 3, K)
    corr = np.asarray(res.correlation)[:5, :5]
    cov_lab = np.einsum("nik,kl,njl->nij", jac, corr, jac)
    # CIEDE2000's local metric M per pixel: ΔE00(lab, lab + δ)² ≈ δᵀ M δ
    e = 0.05
    basis = np.eye(3) * e
    d2 = {}
    for a in range(3):
        d2[a, a] = delta_e00(lab0, lab0 + basis[a]) ** 2
    metric = np.zeros((lab0.shape[0], 3, 3))
    for a in range(3):
        metric[:, a, a] = d2[a, a] / e ** 2
        for b in range(a + 1, 3):
            both = delta_e00(lab0, lab0 + basis[a] + basis[b]) ** 2
            metric[:, a, b] = metric[:, b, a] = (both - d2[a, a] - d2[b, b]) / (2 * e ** 2)
    linear = np.sqrt(np.einsum("nij,nji->n", metric, cov_lab))
    chroma = np.hypot(lab0[:, 1], lab0[:, 2])
    ok = (chroma > 8.0) & (linear > 0.05)
    assert ok.sum() > 100
    ratio = unc.rms[mask][ok] / linear[ok]
    assert abs(np.median(ratio) - 1.0) < 0.08, np.median(ratio)
    assert np.mean(np.abs(ratio - 1.0) < 0.25) > 0.9
    # the summary and the 95th percentile are consistent with the map
    summ = unc.summary(names)
    assert summ["all"]["pixels"] == int(mask.sum())
    assert np.all(unc.p95[mask] >= 0.0) and np.nanmedian(unc.p95) > np.nanmedian(unc.rms)


def test_render_uncertainty_without_errors_is_zero(scene):
    """No standard errors: every draw is the fit itself, so the map is 0 everywhere."""
    from spectral_fit.fitting import render_uncertainty

    res, _ = _result(scene)
    for n in res.stderr:
        res.stderr[n] = {p: 0.0 for p in res.stderr[n]}
    unc = render_uncertainty(scene, res, draws=2)
    assert unc.varied == [] and np.nanmax(unc.rms) == 0.0


def test_report_picture_and_figures_kept_together(scene, tmp_path, monkeypatch):
    """The report's ``uncertainty.png`` and its figures: drawn once (the figures are the
    map's summary), then both taken from the report cache without rendering again."""
    from spectral_fit.fitting import _render_uncertainty as module
    from spectral_fit.fitting import _report as report
    from spectral_fit.fitting import render_uncertainty

    res, _ = _result(scene)
    names = [o.name for o in scene.objects]
    folder = tmp_path / "cache"
    folder.mkdir()
    first, hit = report._uncertainty(scene, res, tmp_path / "a.png", folder, "k" * 40)
    assert hit == "miss" and (tmp_path / "a.png").stat().st_size > 1000
    assert first == render_uncertainty(scene, res).summary(names)

    def fail(*a, **k):
        raise AssertionError("rendered again")

    monkeypatch.setattr(module, "render_uncertainty", fail)
    again, hit = report._uncertainty(scene, res, tmp_path / "b.png", folder, "k" * 40)
    assert hit == "hit" and again == first
    assert (tmp_path / "b.png").read_bytes() == (tmp_path / "a.png").read_bytes()
    note, _ = report._uncertainty(scene, res, tmp_path / "c.png", None, None)
    assert "rendered again" in note["note"]  # a failure is a note, not a lost report


def test_draws_beyond_an_open_bound_stay_finite(scene):
    """Standard errors far larger than the values (a lobe the readings cannot resolve: μ
    0.17 ± 1.0, n 1.5 ± 2): draws that fall below μ = 0 or n = 1 stop short of those open
    ends (μ = 0 has no lobe), so every covered pixel gets a finite ΔE00 and the summary, as
    written into fit.json, is strict JSON."""
    import json

    from spectral_fit.fitting import render_uncertainty

    res, _ = _result(scene)
    names = [o.name for o in scene.objects]
    res.stderr[names[0]]["mu"] = 1.0
    res.stderr[names[1]]["n"] = 2.0
    unc = render_uncertainty(scene, res, draws=8)
    assert np.isfinite(unc.rms[unc.mask]).all() and unc.rms[unc.mask].max() > 1.0
    json.dumps(unc.summary(names), allow_nan=False)
