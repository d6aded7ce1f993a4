"""Measurement planning: the design against exhaustive search, the sensitivities against finite
differences of the fit's forward model, the predicted standard errors against the scatter of
fits of noisy readings, the session template, and the errors for bad plans."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
from helpers.fitting import write_small_scene

from spectral_fit import fitting
from spectral_fit._runtime.errors import InputError
from spectral_fit.fitting._plan_design import RIDGE
from spectral_fit.io import load_scene, load_session

RES = 4  # the candidates' spot resolution in these tests
REGION = fitting.Region(aims_per_object=12, elevation_steps=2, azimuth_steps=3,
                        field_angles_deg=(1.0,))


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """The small two-sphere scene and a plan of 8 readings (1 % noise, no aiming error and no
    model level error, so the fit's own σ is the planner's); returns (config path, scene,
    plan)."""
    root = tmp_path_factory.mktemp("plan")
    cfg = write_small_scene(root)
    scene = load_scene(cfg)
    plan = fitting.plan_measurements(scene, budget=8, region=REGION, noise=0.01,
                                     sigma_aim_m=0.0, level_error=0.0, spot_resolution=RES,
                                     draws=4)
    return cfg, scene, plan


def _worst(info: np.ndarray) -> float:
    """The minimax criterion computed here: worst diagonal of the inverse information (with
    the planner's ridge) over draws and unknowns."""
    F = info.shape[-1]
    return max(float(np.max(np.diag(np.linalg.inv(m + RIDGE * np.eye(F))))) for m in info)


def test_plan_matches_exhaustive_search(small):
    """Greedy + exchange on 12 candidates, K = 3, against the best of all C(12, 3) = 220
    subsets: the plan's worst scaled variance is within 10 % of the exhaustive optimum (and
    never below it), both with and without information already there."""
    _, _, plan = small
    info = plan.information
    pick = np.linspace(0, len(info) - 1, 12).round().astype(int)
    sub = info[pick]
    for base in (None, 0.3 * info[pick[[0, 5]]].sum(axis=0)):
        b = np.zeros_like(sub[0]) if base is None else base
        chosen, obj = fitting.select_readings(sub, 3, base=base)
        assert len(set(chosen)) == 3
        assert obj == pytest.approx(_worst(b + sub[chosen].sum(axis=0)), rel=1e-9)
        best = min(_worst(b + sub[list(c)].sum(axis=0))
                   for c in itertools.combinations(range(12), 3))
        assert best * (1 - 1e-9) <= obj <= 1.1 * best, (obj, best)


def test_sensitivity_matches_finite_differences_of_the_model(small):
    """A candidate's predicted radiance equals the fit's forward model (``simulate_readings``,
    which runs ``predict``) and its Jacobian columns equal central differences of it (±1 %
    of each parameter; χ ± 0.005), within 1 % of each column's largest entry."""
    _, scene, plan = small
    cands = [plan.candidates[i] for i in (0, len(plan.candidates) // 2)]
    O = len(scene.objects)
    vals = np.array([[float(getattr(o.material, p)) for p in fitting.PARAMETERS]
                     for o in scene.objects])
    free = tuple((o, k) for o in range(O) for k in range(5))
    out = fitting.candidate_information(scene, cands, vals[None], free=free,
                                        spot_resolution=RES, sigma_aim_m=0.0)
    opts = fitting.FitOptions(spot_resolution=RES)

    def sim(v):
        params = {o.name: dict(zip(fitting.PARAMETERS, map(float, v[i]), strict=True))
                  for i, o in enumerate(scene.objects)}
        return fitting.simulate_readings(scene, cands, params=params, options=opts)

    base = sim(vals)
    np.testing.assert_allclose(out["mean"][:, 0], base, rtol=1e-4, atol=1e-6 * base.max())
    for j, (o, k) in enumerate(free):
        h = 0.005 if fitting.PARAMETERS[k] == "chi" else 0.01 * vals[o, k]
        up, dn = vals.copy(), vals.copy()
        up[o, k] += h
        dn[o, k] -= h
        fd = (sim(up) - sim(dn)) / (2 * h)
        J = out["jacobian"][:, 0, :, j]
        scale = max(np.abs(fd).max(), np.abs(J).max(), 1e-30)
        assert np.abs(J - fd).max() <= 0.01 * scale, (fitting.PARAMETERS[k], o)


def test_aim_gradient_matches_shifted_aims(small):
    """The aiming gradient (difference of the field's halves) against central differences of
    the modelled reading over ±1 mm aim shifts across the axis (as the fit's aiming
    sensitivity shifts them), on candidates whose field stays on the object under a 2 mm
    aiming error: the gradient's norm agrees within 20 % on every one (the edge of the
    object, where the two part, is what the candidates' aiming margin excludes)."""
    _, scene, _ = small
    every = fitting.plan_candidates(scene, REGION, fitting.scene_geometry(scene), margin_m=2e-3)
    cands = every[::len(every) // 8][:8]
    vals = np.array([[float(getattr(o.material, p)) for p in fitting.PARAMETERS]
                     for o in scene.objects])
    out = fitting.candidate_information(scene, cands, vals[None], free=((0, 0),),
                                        spot_resolution=RES, sigma_aim_m=0.0)
    opts = fitting.FitOptions(spot_resolution=RES)
    step = 1e-3
    fd = np.zeros((len(cands), scene.wavelengths.size, 2))
    for d in range(2):
        for sgn in (1, -1):
            moved = []
            for c in cands:
                ax = c["aim"] - c["position"]
                ax = ax / np.linalg.norm(ax)
                u = np.cross(ax, [0.0, 1.0, 0.0])
                u /= np.linalg.norm(u)
                w = u if d == 0 else np.cross(u, ax)
                moved.append({**c, "aim": c["aim"] + sgn * step * w})
            fd[..., d] += sgn * fitting.simulate_readings(scene, moved, options=opts) / (2 * step)
    g = out["aim_gradient"][:, 0]
    ratios = np.linalg.norm(g, axis=(1, 2)) / np.linalg.norm(fd, axis=(1, 2))
    assert len(cands) >= 6
    assert np.all((ratios > 1 / 1.2) & (ratios < 1.2)), ratios


def test_predicted_stderr_matches_scatter_of_fits(small, tmp_path):
    """The plan's standard errors after its 8 readings against the spread of the estimates of
    24 fits (fit_many) of those readings simulated with 1 % noise (the planner's noise model),
    within a factor 1.5 for every parameter the plan determines to better than 10 %."""
    from spectral_fit.io import write_session

    cfg, scene, plan = small
    opts = fitting.FitOptions(spot_resolution=RES)
    spots = [{k: r[k] for k in ("id", "object", "kind", "aim", "position", "field_angle_deg")}
             for r in plan.chosen]
    clean = fitting.simulate_readings(scene, spots, options=opts)
    m = write_session(tmp_path / "s", scene=str(cfg), wavelengths=scene.wavelengths,
                      readings=[{**s, "spectra": clean[b][None]} for b, s in enumerate(spots)],
                      calibration={"mode": "none"}, noise={"absolute": 1e-9, "relative": 0.01})
    session = load_session(m, scene=scene)
    prep = fitting.prepare_fit(scene, session, options=opts)
    sigma = 0.01 * np.maximum(clean, 1e-3 * clean.max(axis=1, keepdims=True))
    rng = np.random.default_rng(3)
    K = 24
    meas = clean[None] + sigma[None] * rng.standard_normal((K,) + clean.shape)
    out = fitting.fit_many(prep, meas, sigma=np.broadcast_to(sigma, meas.shape), rtol=1e-6,
                           atol=1e-7, max_steps=150)
    ok = out["converged"]
    assert ok.sum() >= K - 2
    spread = out["params"][ok].std(axis=0, ddof=1)
    names = [o.name for o in scene.objects]
    checked = 0
    for j, label in enumerate(plan.unknowns):
        obj, p = label.split(".")
        o, k = names.index(obj), fitting.PARAMETERS.index(p)
        se = plan.stderr_after[j]
        v = abs(plan.centre[obj][p])
        if not math.isfinite(se) or se / max(v, 1e-12) >= 0.1:
            continue
        checked += 1
        assert 1 / 1.5 <= se / spread[o, k] <= 1.5, (label, se, spread[o, k])
    assert checked >= 5


def test_plan_report_and_session_template(small, tmp_path):
    """plan.json, plan.png and a session template whose readings, once their spectrum files
    exist, load and prepare (aim on the object, stated distance consistent)."""
    cfg, scene, plan = small
    files = fitting.write_plan(plan, tmp_path / "out", scene=scene, config_path=cfg)
    data = json.loads((tmp_path / "out" / "plan.json").read_text())
    assert len(data["readings"]) == 8
    for u in plan.unknowns:
        assert data["parameters"][u]["stderr_before"] == "unidentified"
        assert data["parameters"][u]["stderr_after"] > 0
    assert (tmp_path / "out" / "plan.png").stat().st_size > 1000
    text = (tmp_path / "out" / "session.toml").read_text()
    assert text.count("files = []") == 8
    wl = scene.wavelengths
    rows = "\n".join(f"{w:g},0.01" for w in wl)
    for r in plan.chosen:
        (tmp_path / "out" / f"{r['id']}.csv").write_text("wavelength_nm,radiance\n" + rows)
        text = text.replace("files = []", f'files = ["{r["id"]}.csv"]', 1)
    (tmp_path / "out" / "session.toml").write_text(text)
    s = load_session(files["session"], scene=scene)
    assert [r.id for r in s.readings] == [r["id"] for r in plan.chosen]
    prep = fitting.prepare_fit(scene, s, options=fitting.FitOptions(spot_resolution=RES))
    assert np.all(prep.coverage >= 0.99)


def test_bad_plans_are_named_errors(small, tmp_path):
    cfg, scene, _ = small
    # malformed region files
    bad = tmp_path / "bad.toml"
    bad.write_text("distances_m = [0.3\n")
    with pytest.raises(InputError, match="bad.toml"):
        fitting.load_region(bad)
    bad.write_text("field_angles_deg = [0.5]\n")
    with pytest.raises(InputError, match="field_angles_deg") as e:
        fitting.load_region(bad)
    assert e.value.path == str(bad)
    bad.write_text("distance = 0.3\n")
    with pytest.raises(InputError, match="distance"):
        fitting.load_region(bad)
    bad.write_text('frame = "markers"\n')
    with pytest.raises(InputError, match="frame"):
        fitting.load_region(bad)
    # unreachable: yellow hidden behind red from a point on the line through both centres
    hidden = tmp_path / "hidden.toml"
    hidden.write_text('objects = ["yellow"]\npositions = [[0.3, 0.0, -0.275]]\n')
    with pytest.raises(InputError, match="unreachable") as e:
        fitting.plan_measurements(scene, budget=1, region=fitting.load_region(hidden))
    assert e.value.path == str(hidden)
    # an aim point off the object
    off = tmp_path / "off.toml"
    off.write_text('objects = ["yellow"]\naims = { yellow = [[-0.045, 0.0, -0.2], '
                   '[-0.045, 0.0, -0.2375]] }\n')
    with pytest.raises(InputError, match=r"aims\.yellow\[0\].*off object") as e:
        fitting.plan_measurements(scene, budget=1, region=fitting.load_region(off))
    # more readings than valid candidates
    tiny = tmp_path / "tiny.toml"
    tiny.write_text('objects = ["red"]\nelevation_steps = 1\nazimuth_steps = 1\n'
                    "aims_per_object = 16\nfield_angles_deg = [1.0]\n")
    with pytest.raises(InputError, match="budget.*only") as e:
        fitting.plan_measurements(scene, budget=50, region=fitting.load_region(tiny),
                                  spot_resolution=RES, draws=2)
    assert e.value.field == "budget"


def test_cli_plan(small, tmp_path, capsys):
    from spectral_fit.cli._main import main

    cfg, _, _ = small
    out = tmp_path / "p"
    rc = main(["plan", str(cfg), "--budget", "2", "--out", str(out), "--objects", "red",
               "--elevation", "0,30,2", "--azimuth=-30,30,2", "--aims-per-object", "8",
               "--field-angles", "1", "--draws", "2", "--highlights", "0,4", "--no-picture"])
    assert rc == 0
    err = capsys.readouterr().err
    assert "red.mu" in err and "stderr after" in err
    assert (out / "plan.json").is_file() and (out / "session.toml").is_file()
    rc = main(["plan", str(cfg), "--budget", "2", "--out", str(out), "--field-angles", "5"])
    assert rc == 2
    assert "field_angles_deg" in capsys.readouterr().err
    rc = main(["plan", str(cfg), "--budget", "2", "--out", str(out), "--highlights", "0,90"])
    assert rc == 2
    assert "highlight_offsets_deg" in capsys.readouterr().err


def test_information_woodbury_matches_direct_inverse():
    """The information with an aiming error, a level and a tilt error (Woodbury) against
    Jᵀ C⁻¹ J with the covariance C = diag(σ²) + σ_aim² G Gᵀ (+ level² m mᵀ
    + tilt² (m∘x)(m∘x)ᵀ) inverted directly."""
    rng = np.random.default_rng(0)
    D, B, L, F = 2, 3, 7, 4
    J = rng.standard_normal((D, B, L, F))
    sigma = 0.1 + rng.random((D, B, L))
    G = rng.standard_normal((D, B, L, 2))
    tol = 0.5 + rng.random((D, F))
    mean = 1.0 + rng.random((D, B, L))
    got = fitting.reading_information(J, sigma, G, tol, sigma_aim_m=0.3)
    level = fitting.reading_information(J, sigma, G, tol, sigma_aim_m=0.3, level=0.2,
                                        mean=mean)
    both = fitting.reading_information(J, sigma, G, tol, sigma_aim_m=0.3, level=0.2, tilt=0.1,
                                       mean=mean)
    x = np.linspace(-1.0, 1.0, L)
    for d in range(D):
        for b in range(B):
            C = np.diag(sigma[d, b] ** 2) + 0.09 * G[d, b] @ G[d, b].T
            Js = J[d, b] * tol[d]
            np.testing.assert_allclose(got[d, b], Js.T @ np.linalg.solve(C, Js), rtol=1e-9,
                                       atol=1e-12)
            # and with the model's level error: + level² m mᵀ
            C = C + 0.04 * np.outer(mean[d, b], mean[d, b])
            np.testing.assert_allclose(level[d, b], Js.T @ np.linalg.solve(C, Js), rtol=1e-9,
                                       atol=1e-12)
            # and a tilt: + tilt² (m∘x)(m∘x)ᵀ
            C = C + 0.01 * np.outer(mean[d, b] * x, mean[d, b] * x)
            np.testing.assert_allclose(both[d, b], Js.T @ np.linalg.solve(C, Js), rtol=1e-9,
                                       atol=1e-12)
    # a level and a tilt per reading (a session's stated errors per kind)
    lv, tv = np.array([0.2, 0.0, 0.05]), np.array([0.0, 0.1, 0.3])
    each = fitting.reading_information(J, sigma, G, tol, sigma_aim_m=0.3, level=lv, tilt=tv,
                                       mean=mean)
    for d in range(D):
        for b in range(B):
            C = (np.diag(sigma[d, b] ** 2) + 0.09 * G[d, b] @ G[d, b].T
                 + lv[b] ** 2 * np.outer(mean[d, b], mean[d, b])
                 + tv[b] ** 2 * np.outer(mean[d, b] * x, mean[d, b] * x))
            Js = J[d, b] * tol[d]
            np.testing.assert_allclose(each[d, b], Js.T @ np.linalg.solve(C, Js), rtol=1e-9,
                                       atol=1e-12)


@pytest.mark.parametrize("stated", [False, True], ids=["plain", "stated_level_tilt"])
def test_session_information_matches_the_fit(small, tmp_path, stated):
    """With a session (noiseless own-model readings of 10 spots, calibration "global": the
    scale is a nuisance unknown), the plan's standard errors before equal the fit's own
    (Jacobian) standard errors at its optimum (no aiming error; no model level error, or the
    level and tilt the session states, which the fit's generalised least squares and the
    planner's Woodbury information both take), and the plan lowers the worst one."""
    from helpers.fitting import spots, write_session

    cfg, scene, _ = small
    opts = fitting.FitOptions(spot_resolution=RES)
    clean = fitting.simulate_readings(scene, spots(), options=opts)
    session = load_session(write_session(tmp_path / "s", cfg, clean, scene.wavelengths),
                           scene=scene)
    if stated:
        session = session.replace(level_error={"object": 0.02}, tilt_error={"object": 0.01})
    res = fitting.fit(scene, session, options=opts, starts=1, holdout=False, aim_step_m=0.0)
    plan = fitting.plan_measurements(scene, session, budget=2, region=REGION,
                                     sigma_aim_m=0.0, level_error=None if stated else 0.0,
                                     draws=2, fit_options=opts)
    assert plan.settings["level_error"] == (0.02 if stated else 0.0)
    assert plan.settings["tilt_error"] == (0.01 if stated else 0.0)
    assert plan.unknowns[-1] == "scale" and "yellow.alpha" not in plan.unknowns
    for j, label in enumerate(plan.unknowns[:-1]):
        obj, p = label.split(".")
        assert plan.stderr_before[j] == pytest.approx(res.stderr[obj][p], rel=0.02), label
    assert plan.objective_after < plan.objective_before


def test_correlated_groups_are_the_connected_components():
    """Unknowns joined by |r| > 0.95 form groups through chains (a–b, b–c: one group), a
    weaker correlation joins nothing, and single unknowns are not groups."""
    free = ["y.alpha", "y.beta", "y.n", "r.beta", "r.chi", "scale"]
    c = np.eye(6)
    for i, j, r in ((1, 2, -0.97), (2, 0, 0.96), (3, 4, -0.99), (0, 5, 0.9)):
        c[i, j] = c[j, i] = r
    assert fitting.correlated_groups(free, c) == [["y.alpha", "y.beta", "y.n"],
                                                  ["r.beta", "r.chi"]]
    assert fitting.correlated_groups(free, c, threshold=0.98) == [["r.beta", "r.chi"]]


def test_cli_fit_suggests_readings(small, tmp_path, capsys):
    """``spectral-fit fit --suggest 2 --region FILE``: the fit's report names the planned
    readings (and writes the plan beside it); their predicted standard errors after are
    those of the plan from that session (the planner's own test checks them), none larger
    than now, the worst one smaller."""
    from helpers.fitting import spots, write_session

    from spectral_fit.cli._main import main

    cfg, scene, _ = small
    opts = fitting.FitOptions(spot_resolution=RES)
    clean = fitting.simulate_readings(scene, spots(), options=opts)
    sess = write_session(tmp_path / "s", cfg, clean, scene.wavelengths)
    region = tmp_path / "region.toml"
    region.write_text('frame = "world"\nelevation_steps = 2\nazimuth_steps = 3\n'
                      "aims_per_object = 12\nfield_angles_deg = [1.0]\n")
    out = tmp_path / "o"
    rc = main(["fit", str(cfg), str(sess), "-o", str(out), "--json", "--no-render",
               "--no-holdout", "--aim-step-mm", "0", "--spot-resolution", str(RES),
               "--suggest", "2", "--region", str(region)])
    cap = capsys.readouterr()
    assert rc == 0
    sug = json.loads(cap.out)["suggested"]
    assert len(sug["readings"]) == 2 and "suggest: plan_01" in cap.err
    now = np.array([v["now"] for v in sug["stderr"].values()])
    after = np.array([v["after"] for v in sug["stderr"].values()])
    assert np.all(after <= now * (1 + 1e-9)) and after.max() < now.max()
    assert (out / "suggested" / "session.toml").is_file()
    assert json.loads((out / "fit.json").read_text())["suggested"]["readings"] == sug["readings"]


def _sphere_highlight(c: np.ndarray, r: float, p: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The point of a sphere (centre c, radius r) that mirrors direction s towards p: its
    normal bisects s and the direction to p (fixed-point iteration, closed-form geometry)."""
    x = c + r * (p - c + s * np.linalg.norm(p - c)) / np.linalg.norm(p - c + s * np.linalg.norm(
        p - c))
    for _ in range(50):
        v = (p - x) / np.linalg.norm(p - x)
        h = (v + s) / np.linalg.norm(v + s)
        x = c + r * h
    return x


def test_highlight_candidates_lie_on_the_sources_mirror_points(small):
    """The region's highlight aim points against the sphere's analytic mirror point of a
    source, on the bundled scene's 100 × 100 UV spheres: the 0° aim point within 3° (at the
    centre) of the analytic point, and every aim point's mirror direction, from the sphere's
    true normal, within 2° of its offset from the source. The environment's brightest
    direction is where the map is brightest."""
    from spectral_fit.fitting._plan_candidates import _centroids, _highlight_points

    _, small_scene, _ = small
    env = fitting.scene_environment(small_scene)
    src = fitting.bright_directions(env, 2)
    assert src.shape[1] == 3 and len(src) >= 1
    from spectral_fit.lighting import lookup

    peak = float(np.asarray(env.texels).sum(-1).max())
    assert float(np.asarray(lookup(env, src[0])).sum()) >= 0.5 * peak
    s = np.array([-0.5, 0.45, -0.74])
    s /= np.linalg.norm(s)
    scene = load_scene(Path(__file__).resolve().parent.parent / "configs" / "two_spheres.toml")
    geoms = fitting.scene_geometry(scene)
    checked = 0
    for o, obj in enumerate(scene.objects):
        c = np.asarray(obj.position, np.float64)
        r = float(np.linalg.norm(np.asarray(geoms[o].vertices) - c, axis=1).mean())
        for p in (c + 0.3 * np.array([0.0, 0.2, 1.0]), c + 0.3 * np.array([-0.5, 0.5, 0.7])):
            pts, what = _highlight_points(_centroids(geoms[o]), p, s[None], (0.0, 4.0, 8.0),
                                          math.cos(math.radians(80.0)))
            assert len(pts) == 3 and [w["source"] for w in what] == [0, 0, 0]
            want = _sphere_highlight(c, r, p, s)
            got = (pts[0] - c) / np.linalg.norm(pts[0] - c)
            assert np.degrees(np.arccos(got @ (want - c) / r)) <= 3.0
            for k, x in zip((0.0, 4.0, 8.0), pts, strict=True):
                n = (x - c) / np.linalg.norm(x - c)
                v = (p - x) / np.linalg.norm(p - x)
                m = 2 * (n @ v) * n - v
                assert abs(np.degrees(np.arccos(np.clip(m @ s, -1, 1))) - k) <= 2.0
            checked += 1
    assert checked == 4
    # the candidates of a region carry them (and none without the offsets)
    region = fitting.Region(objects=("red",), aims_per_object=4, elevation_steps=1,
                            azimuth_steps=1, field_angles_deg=(1.0,))
    with_hl = fitting.plan_candidates(scene, region, geoms, sources=s[None])
    without = fitting.plan_candidates(scene, region.__class__(
        **{**region.__dict__, "highlight_offsets_deg": ()}), geoms, sources=s[None])
    assert len(with_hl) > len(without)
    assert not any("highlight" in c for c in without)
    assert {c["highlight"]["source"] for c in with_hl if "highlight" in c} == {0}
