"""The fit's standard errors under a model error it does not know (fitting.coverage_study,
FitOptions.errors): the robust (reading-clustered sandwich) errors against the actual scatter
of the estimates over repeated simulated sessions, and the binomial interval the study reports
against closed forms."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.fitting import TRUE, small_session

from spectral_fit import fitting

RES = 6


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """The small session with α, β, μ of each sphere free (6 unknowns, 10 readings: the
    readings' clusters outnumber them)."""
    return small_session(tmp_path_factory.mktemp("cov"), resolution=RES,
                         objects={n: {"free": ["alpha", "beta", "mu"]} for n in TRUE})


def _truths(scene, prep, k: int) -> np.ndarray:
    """(k, O, P) copies of the small session's true parameters (TRUE over the start values)."""
    from spectral_fit.io import PARAMETERS

    truth = np.asarray(prep.problem.values, np.float64).copy()
    for o, obj in enumerate(scene.objects):
        for j, p in enumerate(PARAMETERS):
            if p in TRUE[obj.name]:
                truth[o, j] = TRUE[obj.name][p]
    return np.repeat(truth[None], k, axis=0)


def test_robust_errors_match_the_scatter_under_a_level_error(small):
    """60 sessions of the same truth, each reading off by a level (2 %) and a tilt (1 %) over
    its bands that the model does not know, 0.3 % noise per band: per parameter, the spread
    of the 60 estimates against the median reported standard error. The linearised errors
    count the level once per band and are several times too small (spread / error 1.9-3.3
    here, > 2 for most parameters); the robust ones (the readings left out in turn) count
    it once per reading and cover the spread: 0.27-1.01 here, asserted below 1.2 for every
    parameter (the spread of 60 draws is uncertain by ~9 %) and above 0.2 (with 10 readings
    for 6 unknowns leaving one out is conservative: the μ that hang on the two glossy
    readings get errors up to 3.7 times their spread)."""
    scene, session, prep, env, clean = small
    truths = _truths(scene, prep, 60)
    ratios = {}
    for errors in ("robust", "linear"):
        opts = fitting.FitOptions(spot_resolution=RES, starts=1, holdout=False, aim_step_m=0.0,
                                  errors=errors)
        st = fitting.coverage_study(scene, session, truths=truths, seed=5, noise=0.003,
                                    level=0.02, tilt=0.01, options=opts)
        assert all(s == "converged" for s in st.status)
        spread = np.std(st.estimate - st.truth, axis=0, ddof=1)
        ratios[errors] = spread / np.median(st.stderr, axis=0)
    assert np.all(ratios["robust"] < 1.2) and np.all(ratios["robust"] > 0.2), ratios
    assert np.mean(ratios["linear"] > 2.0) >= 0.7, ratios["linear"]


def test_stated_level_error_gives_errors_that_match_the_scatter(small):
    """The same kind of study with a pure level error (2 % per reading, no tilt) that the
    session states for both of its kinds (``[model_error.level]``, object and interreflection
    0.02): the fit weights each reading by
    diag(σ²) + ℓ² m mᵀ (generalised least squares), so its plain linearised errors match
    the spread of 60 estimates (within a factor 1.5 each way: the spread of 60 draws is
    uncertain by ~9 %), and its estimates scatter less than those of the fit that weights
    the bands as independent (the efficient estimator; asserted no more than 10 % above for
    every parameter, and below on average)."""
    scene, session, prep, env, clean = small
    truths = _truths(scene, prep, 60)
    opts = fitting.FitOptions(spot_resolution=RES, starts=1, holdout=False, aim_step_m=0.0,
                              errors="linear")
    spread = {}
    for name, sess in (("gls", session.replace(level_error={"object": 0.02,
                                                          "interreflection": 0.02})),
                       ("ols", session)):
        st = fitting.coverage_study(scene, sess, truths=truths, seed=9, noise=0.003,
                                    level=0.02, tilt=0.0, options=opts)
        assert all(s == "converged" for s in st.status)
        spread[name] = np.std(st.estimate - st.truth, axis=0, ddof=1)
        if name == "gls":
            ratio = spread[name] / np.median(st.stderr, axis=0)
            assert np.all((ratio > 1 / 1.5) & (ratio < 1.5)), ratio
    assert np.all(spread["gls"] <= 1.1 * spread["ols"]), spread
    assert np.mean(spread["gls"] / spread["ols"]) < 1.0, spread


def test_level_whitening_is_the_generalised_least_squares_cost():
    """|whiten_levels(z)|² per row against zᵀ (D^-½ C D^-½)⁻¹ z with C = diag(σ²) + ℓ² m mᵀ
    inverted directly, for residuals and (column by column) a Jacobian; rows with ℓ = 0 are
    unchanged."""
    import jax.numpy as jnp

    rng = np.random.default_rng(4)
    B, L, F = 5, 12, 3
    m = rng.uniform(0.1, 2.0, (B, L))
    sig = 0.01 * m + 1e-3
    lvl = np.array([0.0, 0.005, 0.02, 0.1, 1.0])
    z = rng.standard_normal((B, L))
    J = rng.standard_normal((B, L, F))

    class R:
        measured, sigma, level = (jnp.asarray(x) for x in (m, sig, lvl))

    wz = np.asarray(fitting.whiten_levels(jnp.asarray(z), R))
    wJ = np.asarray(fitting.whiten_levels(jnp.asarray(J), R))
    for b in range(B):
        C = np.diag(sig[b] ** 2) + lvl[b] ** 2 * np.outer(m[b], m[b])
        Cw = C / np.outer(sig[b], sig[b])
        want = z[b] @ np.linalg.solve(Cw, z[b])
        assert float(wz[b] @ wz[b]) == pytest.approx(want, rel=1e-5)
        assert np.allclose(wJ[b].T @ wJ[b], J[b].T @ np.linalg.solve(Cw, J[b]), rtol=1e-4,
                           atol=1e-5)
    assert np.array_equal(wz[0], z[0].astype(wz.dtype))


def test_clopper_pearson_against_closed_forms():
    """The exact binomial interval: with no failures its upper end solves (1 − p)ⁿ = α/2, with
    no successes the same mirrored; 5 of 10 gives 0.1871 .. 0.8129 (Clopper & Pearson 1934,
    as tabulated, e.g. in NIST/SEMATECH e-Handbook §7.2.4.1)."""
    lo, hi = fitting.clopper_pearson(0, 10)
    assert lo == 0.0 and hi == pytest.approx(1 - 0.025 ** (1 / 10), rel=1e-9)
    lo, hi = fitting.clopper_pearson(20, 20)
    assert hi == 1.0 and lo == pytest.approx(0.025 ** (1 / 20), rel=1e-9)
    lo, hi = fitting.clopper_pearson(5, 10)
    assert (lo, hi) == (pytest.approx(0.1871, abs=1e-4), pytest.approx(0.8129, abs=1e-4))
