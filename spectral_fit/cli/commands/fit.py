"""``spectral-fit fit CONFIG SESSION -o OUTDIR``: fit materials to spectroradiometer readings."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

HELP = "fit alpha, beta, chi, mu, n (gamma) of the scene's objects to a measurement session"

#: run as a program, the command ends its process without the interpreter's teardown (its
#: report files are written atomically and synced before it returns; see ``cli._main``)
FAST_EXIT = True


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="scene config (TOML)")
    p.add_argument("session", help="measurement session folder or its session.toml")
    p.add_argument("-o", "--output", required=True, help="output folder of the report")
    p.add_argument("--json", action="store_true", help="print the result JSON on stdout")
    p.add_argument("--starts", type=int, default=3, help="starting points (default 3)")
    p.add_argument("--bootstrap", type=int, default=0,
                   help="bootstrap resamples over readings (default 0: off)")
    p.add_argument("--kinds", default="object,interreflection,image",
                   help="reading kinds to fit (comma-separated: object, interreflection, "
                        "image = the session's photographs; default all)")
    p.add_argument("--spot-resolution", type=int, default=8,
                   help="pixels across each measuring field (default 8)")
    p.add_argument("--max-steps", type=int, default=50, help="iterations per start")
    p.add_argument("--no-holdout", action="store_true",
                   help="skip the hold-out prediction of interreflection readings")
    p.add_argument("--aim-step-mm", type=float, default=0.5,
                   help="aim shift for the aiming sensitivity (0: skip; default 0.5 mm)")
    p.add_argument("--no-render", action="store_true", help="skip the render of the fit")
    p.add_argument("--profile", action="store_true",
                   help="also compute profile-likelihood intervals (the fit repeated with each "
                   "parameter held at 20 values around its estimate and its interval's ends; "
                   "about 2 s per parameter on 2 CPU cores for 18 readings of 81 bands)")
    p.add_argument("--suggest", type=int, default=0, metavar="K",
                   help="also plan K more readings from the fitted session (spectral-fit "
                   "plan's design) and name what they separate: fit.json 'suggested', the "
                   "plan in OUTPUT/suggested/")
    p.add_argument("--region", default=None, metavar="FILE",
                   help="with --suggest: where the instrument can stand and aim (a plan "
                   "region file; default: plan's default region)")
    p.add_argument("--errors", choices=("robust", "linear"), default="robust",
                   help="robust (default): each standard error the larger of the linearised "
                   "one and the one from leaving each reading out (an error shared by a "
                   "reading's bands counted once per reading); linear: the linearised one")
    p.add_argument("--interreflection", choices=("auto", "none"), default="auto",
                   help="auto: the scene config's interreflection mode; none: fit without "
                   "the interreflection term")


def _suggest(args: argparse.Namespace, scene: Any, session: Any, res: Any) -> dict:
    """``--suggest K``: plan K readings from the fitted session, write the plan into
    OUTPUT/suggested/ and say what they separate."""
    from pathlib import Path

    from ...fitting import FitOptions, load_region, suggest_readings, write_plan

    region = load_region(args.region) if args.region else None
    block, plan = suggest_readings(scene, session, res, budget=args.suggest, region=region,
                                   fit_options=FitOptions(spot_resolution=args.spot_resolution),
                                   progress=lambda m: _say(f"suggest: {m}"))
    files = write_plan(plan, Path(args.output) / "suggested", scene=scene,
                       config_path=args.config)
    block["files"] = files
    for group in block["groups"] or [list(block["stderr"])]:
        _say("suggest: " + ", ".join(
            f"{label} ± {block['stderr'][label]['now']:.2g} → {block['stderr'][label]['after']:.2g}"
            for label in group if label in block["stderr"]))
    for r in block["readings"]:
        _say(f"suggest: {r['id']}: stand at {_xyz(r['position'])}, aim at {_xyz(r['aim'])}, "
             f"field {r['field_angle_deg']:g}°")
    return block


def _xyz(v: list[float]) -> str:
    return "(" + ", ".join(f"{x:.3f}" for x in v) + ") m"


def _say(msg: str) -> None:
    print(f"fit: {msg}", file=sys.stderr, flush=True)


def enable_compilation_cache() -> str | None:
    """Keep XLA's compiled programs between runs (compiling the fit's solver is most of its
    first call): ``$SPECTRAL_FIT_JAX_CACHE`` or
    ``~/.cache/spectral_fit/jax``; set the variable to an empty string to disable.
    Every program is kept, however quickly it compiled (a second run compiles nothing).
    Applications (this CLI) opt in; the library never does."""
    from ...rendering import enable_compilation_cache as enable

    return enable(min_compile_time_s=0.0)


def run(args: argparse.Namespace) -> int:
    import time

    from ..._runtime.errors import InputError
    from ...fitting import fit, write_report
    from ...io import DATA_KINDS, load_scene, load_session
    from ...rendering import cache_root
    from .._main import STARTED

    kinds = tuple(k.strip() for k in args.kinds.split(",") if k.strip())
    bad = [k for k in kinds if k not in DATA_KINDS]
    if bad or not kinds:
        raise InputError(f"unknown kind(s) {bad}; choose from {DATA_KINDS}", field="--kinds")
    for name, v, lo in (("--starts", args.starts, 1), ("--spot-resolution",
                        args.spot_resolution, 2), ("--max-steps", args.max_steps, 1),
                        ("--bootstrap", args.bootstrap, 0)):
        if v < lo:
            raise InputError(f"must be >= {lo}, got {v}", field=name)
    if not (args.aim_step_mm >= 0):
        raise InputError(f"must be >= 0, got {args.aim_step_mm}", field="--aim-step-mm")
    enable_compilation_cache()
    t_load = time.perf_counter()
    scene = load_scene(args.config)
    session = load_session(args.session, scene=scene)
    before = {"startup_s": t_load - STARTED, "load_s": time.perf_counter() - t_load}
    _say(f"{len(session.readings)} readings of {sorted({r.object for r in session.readings})}"
         + (f", {len(session.images)} photograph(s)" if session.images else "")
         + f", calibration {session.calibration}, noise {session.noise.source}")
    res = fit(scene, session, progress=_say, starts=args.starts, bootstrap=args.bootstrap,
              kinds=kinds, spot_resolution=args.spot_resolution, max_steps=args.max_steps,
              holdout=not args.no_holdout, aim_step_m=args.aim_step_mm * 1e-3,
              interreflection=args.interreflection, profile=args.profile, errors=args.errors,
              cache_dir=cache_root())
    extra = {}
    if args.suggest:
        extra["suggested"] = _suggest(args, scene, session, res)
    summary = write_report(res, args.output, scene=scene, session=session,
                           render=not args.no_render, cache_dir=cache_root(), timing=before,
                           started=STARTED, extra=extra)
    for w in res.warnings:
        _say(f"warning: {w}")
    _say(f"{res.status} after {res.iterations} iterations; chi2/dof {res.chi2_red:.3g}")
    for im in res.images:
        _say(f"  photograph {im['id']}: {im['bins']} bins of {im['superpixel']} px fitted "
             f"(left out: {', '.join(f'{k} {v}' for k, v in im['dropped'].items())}); rms "
             f"relative residual {100 * (im['rms_relative_residual'] or 0):.2g} %")
    for obj, p in res.params.items():
        se = res.stderr[obj]
        _say(f"  {obj}: " + ", ".join(f"{k} {v:.4g} ± {se[k]:.2g}" for k, v in p.items()))
        for k in p:
            iv = (res.profile or {}).get(f"{obj}.{k}")
            if iv is not None:
                ends = ["" if iv[f"{e}_end"] == "profile" else
                        (" (bound)" if iv[f"{e}_end"] == "bound" else " (open)")
                        for e in ("lower", "upper")]
                _say(f"    {k} profile interval {iv['lower']:.4g}{ends[0]} .. "
                     f"{iv['upper']:.4g}{ends[1]}")
    _say(f"report in {args.output}/ ({', '.join(summary['files'])})")
    tm = summary["timing"]
    hit = {k: v for k, v in tm["caches"].items() if not k.startswith("programs_")}
    _say(f"time: {tm['total_s']:.1f} s (start-up {tm['startup_s']:.1f}, preparation "
         f"{tm['preparation_s']:.1f}, compile + solve {tm['compile_and_solve_s']:.1f}, "
         f"report {tm['report_s']:.1f}); caches: "
         + ", ".join(f"{k} {v}" for k, v in hit.items())
         + f"; programs loaded {tm['caches'].get('programs_loaded', 0)}, compiled "
         f"{tm['caches'].get('programs_compiled', 0)}")
    if args.json:
        slim = {k: v for k, v in summary.items() if k != "spectra"}
        print(json.dumps(slim, indent=2))
    return 0 if res.status != "failed" else 1
