"""Do the fit's 95 % intervals cover the truth? Simulated sessions on the bundled session's spots
(configs/two_spheres.toml + measurements/sessions/two_spheres_demo), truths drawn over the
default ranges, this package's forward model times a model error the fit does not know (per
reading a level and a tilt over the bands), 1 % noise per band; each session fitted with the
robust standard errors (the default) and with the linearised ones alone.

    python scripts/coverage_study.py --sessions 200 --out out/coverage
    python scripts/coverage_study.py --sessions 0 --path-traced 20 --spp 64 --out out/coverage_pt
    python scripts/coverage_study.py --sessions 200 --state-model-error --out out/coverage_stated

``--state-model-error``: the simulated sessions state the injected error's size
(``[model_error.level]`` = --level and ``[model_error.tilt]`` = --tilt for every kind), so
the fit weights each reading by diag(σ²) + ℓ² m mᵀ + t² (m∘x)(m∘x)ᵀ.

``--path-traced N``: also N sessions rendered by the Mitsuba reference (our whole model as one
BSDF, path depth 16, read by its simulated spectroradiometer: 0.4 % repeatability, 5 nm
band-pass, gain jitter; the same spots, truths drawn over the same ranges), each fitted with
both kinds of error; their coverage is reported apart (``path_traced`` in the JSON). The
sessions are kept under ``<out>/sessions/`` and reused by a later run.

Writes ``<out>/coverage.json`` (the table per parameter for both kinds of error: coverage,
its Clopper–Pearson 95 % interval, median interval width, also in recovery tolerances; every
session's truth, estimate and standard errors) and ``<out>/coverage.png`` (coverage per
parameter with its interval, and the normalised errors (p̂ − p)/σ̂ against a standard normal).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=200)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--noise", type=float, default=0.01, help="noise per band (fraction)")
    ap.add_argument("--level", type=float, default=0.01, help="model error: level (1σ)")
    ap.add_argument("--tilt", type=float, default=0.005, help="model error: tilt (1σ)")
    ap.add_argument("--state-model-error", action="store_true",
                    help="the sessions state the level and tilt ([model_error.level], .tilt)")
    ap.add_argument("--path-traced", type=int, default=0, metavar="N",
                    help="also N sessions path-traced with Mitsuba (the 'validate' extra)")
    ap.add_argument("--spp", type=int, default=64, help="samples per pixel of those")
    ap.add_argument("--out", type=Path, default=Path("out/coverage"))
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    from spectral_fit import fitting
    from spectral_fit._runtime.fileio import atomic_path, atomic_write_text
    from spectral_fit.io import load_scene, load_session

    scene = load_scene(fitting.DEMO_CONFIG)
    session = load_session(fitting.DEMO_SESSION, scene=scene)
    if args.state_model_error:
        kinds = ("object", "interreflection")
        session = session.replace(level_error={k: args.level for k in kinds},
                                  tilt_error={k: args.tilt for k in kinds})
    out: dict = {"config": str(fitting.DEMO_CONFIG.relative_to(REPO)),
                 "session": str(fitting.DEMO_SESSION.relative_to(REPO)), "studies": {}}
    studies = {}
    for errors in ("robust", "linear") if args.sessions else ():
        t0 = time.perf_counter()
        opts = fitting.FitOptions(starts=1, holdout=False, aim_step_m=0.0, errors=errors)
        st = fitting.coverage_study(scene, session, sessions=args.sessions, seed=args.seed,
                                    noise=args.noise, level=args.level, tilt=args.tilt,
                                    options=opts,
                                    progress=lambda m: print(m, file=sys.stderr, flush=True))
        studies[errors] = st
        out["studies"][errors] = {
            "table": st.table(fitting.TOLERANCES), "seconds": time.perf_counter() - t0,
            "options": st.options, "labels": st.labels, "status": st.status,
            "truth": st.truth.tolist(), "estimate": st.estimate.tolist(),
            "stderr": st.stderr.tolist()}
        for kind, row in out["studies"][errors]["table"].items():
            print(f"{errors:6s} {kind:6s} coverage {row['coverage']:.3f} "
                  f"[{row['ci95'][0]:.3f}, {row['ci95'][1]:.3f}]  n {row['n']}  "
                  f"median width {row['median_width']:.4g}"
                  + (f" = {row['median_width_in_tolerances']:.2f} tolerances"
                     if "median_width_in_tolerances" in row else ""))
    args.out.mkdir(parents=True, exist_ok=True)
    if args.path_traced:
        out["path_traced"] = _path_traced(scene, session, args)
    atomic_write_text(args.out / "coverage.json", json.dumps(out, indent=1) + "\n")
    if studies:
        _figure(studies, args.out / "coverage.png", atomic_path)
    pictures = f" and {args.out / 'coverage.png'}" if studies else ""
    print(f"wrote {args.out / 'coverage.json'}{pictures}")
    return 0


def _path_traced(scene, session, args) -> dict:
    """N sessions of the bundled session's spots path-traced at truths drawn over the default
    ranges (kept in ``<out>/sessions/<i>``), fitted with both kinds of error."""
    import dataclasses

    from spectral_fit import fitting
    from spectral_fit.fitting import default_range
    from spectral_fit.io import PARAMETERS, load_session
    from spectral_fit.validation.reference.instrument import ReadingSpec, Spectroradiometer
    from spectral_fit.validation.reference.instrument import simulate_readings as sim

    rng = np.random.default_rng(args.seed + 1000)
    start = {o.name: dict(session.objects[o.name].start) if o.name in session.objects else {}
             for o in scene.objects}
    kinds = {r.id: r.kind for r in session.readings}
    specs = [ReadingSpec(id=r.id, object=r.object, aim=tuple(map(float, r.aim)),
                         position=tuple(map(float, r.position)),
                         field_angle_deg=float(r.field_angle_deg)) for r in session.readings]
    free = [(o.name, p) for o in scene.objects for p in ("alpha", "beta", "chi", "mu", "n")]
    white = {"position": [0.0, 0.0, -0.275], "normal": [0.0, 0.0, 1.0], "reflectance": 0.98,
             "radius": 0.02}
    rows: dict[str, list] = {"robust": [], "linear": []}
    truths = []
    for i in range(args.path_traced):
        truth = {}
        for o in scene.objects:
            vals = {p: float(start[o.name].get(p, getattr(o.material, p))) for p in PARAMETERS}
            for name, p in free:
                if name == o.name:
                    lo, hi = default_range(p, vals[p])
                    vals[p] = float(rng.uniform(lo, hi))
            truth[o.name] = vals
        truths.append(truth)
        folder = args.out / "sessions" / f"{i:03d}"
        manifest = folder / "session.toml"
        done = folder / "truth.json"
        if not (done.is_file() and json.loads(done.read_text()).get("params") == truth):
            objs = tuple(dataclasses.replace(o, material=dataclasses.replace(
                o.material, **truth[o.name])) for o in scene.objects)
            manifest = sim(scene.replace(objects=objs), folder, instrument=Spectroradiometer(),
                           spots=specs, spp=args.spp, seed=args.seed + i, white=white,
                           scene_ref=str(scene.path), progress=None)
            meta = json.loads(done.read_text())
            meta["params"] = truth
            done.write_text(json.dumps(meta, indent=1) + "\n")
        sess = load_session(manifest, scene=scene)
        sess = sess.replace(readings=tuple(dataclasses.replace(r, kind=kinds[r.id])
                                           for r in sess.readings))
        for errors in rows:
            res = fitting.fit(scene, sess, starts=1, holdout=False, aim_step_m=0.0,
                              errors=errors)
            rows[errors].append([(res.params[n][p] - truth[n][p]) / max(res.stderr[n][p], 1e-300)
                                 for n, p in free])
        print(f"path-traced session {i + 1}/{args.path_traced}: robust |z| max "
              f"{np.max(np.abs(rows['robust'][-1])):.2f}", file=sys.stderr, flush=True)
    out: dict = {"spp": args.spp, "labels": [f"{n}.{p}" for n, p in free], "truths": truths}
    for errors, zs in rows.items():
        z = np.array(zs)
        ok = np.abs(z) <= 1.959963984540054
        lo, hi = fitting.clopper_pearson(int(ok.sum()), ok.size)
        out[errors] = {"coverage": float(ok.mean()), "ci95": [lo, hi], "n": int(ok.size),
                       "per_parameter": {p: float(ok[:, [j for j, (_, q) in enumerate(free)
                                                          if q == p]].mean())
                                         for p in ("alpha", "beta", "chi", "mu", "n")},
                       "z": z.tolist()}
        print(f"path-traced {errors:6s} pooled coverage {ok.mean():.3f} [{lo:.3f}, {hi:.3f}] "
              f"n {ok.size}")
    return out


def _figure(studies: dict, path: Path, atomic_path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.stats import norm

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4), layout="constrained")
    for i, (errors, st) in enumerate(studies.items()):
        table = st.table()
        kinds = list(table)
        x = np.arange(len(kinds)) + (i - 0.5) * 0.25
        cov = np.array([table[k]["coverage"] for k in kinds])
        lo = np.array([table[k]["ci95"][0] for k in kinds])
        hi = np.array([table[k]["ci95"][1] for k in kinds])
        ax.errorbar(x, cov, yerr=[cov - lo, hi - cov], fmt="o", capsize=3, label=errors)
        ax.set_xticks(np.arange(len(kinds)), kinds)
        z = ((st.estimate - st.truth) / np.maximum(st.stderr, 1e-300)).ravel()
        bx.hist(np.clip(z, -8, 8), bins=np.linspace(-8, 8, 65), density=True,
                histtype="step", label=f"{errors} standard errors")
    ax.axhline(0.95, color="k", lw=0.8, ls="--")
    ax.set_ylim(0, 1.02)
    ax.set_ylabel("coverage of the 95 % intervals")
    ax.set_title("coverage per parameter (Clopper–Pearson 95 % bars)", fontsize=9)
    ax.legend(fontsize=8)
    zz = np.linspace(-8, 8, 400)
    bx.plot(zz, norm.pdf(zz), "k--", lw=0.8, label="standard normal")
    bx.set_xlabel("(estimate − truth) / standard error")
    bx.set_title("normalised errors, all parameters (clipped at ±8)", fontsize=9)
    bx.legend(fontsize=8)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
