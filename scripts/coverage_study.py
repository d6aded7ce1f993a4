"""Do the fit's 95 % intervals cover the truth? Simulated sessions on the bundled session's spots
(configs/two_spheres.toml + measurements/sessions/two_spheres_demo), truths drawn over the
default ranges, this package's forward model times a model error the fit does not know (per
reading a level and a tilt over the bands), 1 % noise per band; each session fitted with the
robust standard errors (the default) and with the linearised ones alone.

    python scripts/coverage_study.py --sessions 200 --out out/coverage

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
    ap.add_argument("--out", type=Path, default=Path("out/coverage"))
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    from spectral_fit import fitting
    from spectral_fit._runtime.fileio import atomic_path, atomic_write_text
    from spectral_fit.io import load_scene, load_session

    scene = load_scene(fitting.DEMO_CONFIG)
    session = load_session(fitting.DEMO_SESSION, scene=scene)
    out: dict = {"config": str(fitting.DEMO_CONFIG.relative_to(REPO)),
                 "session": str(fitting.DEMO_SESSION.relative_to(REPO)), "studies": {}}
    studies = {}
    for errors in ("robust", "linear"):
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
    atomic_write_text(args.out / "coverage.json", json.dumps(out, indent=1) + "\n")
    _figure(studies, args.out / "coverage.png", atomic_path)
    print(f"wrote {args.out / 'coverage.json'} and {args.out / 'coverage.png'}")
    return 0


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
