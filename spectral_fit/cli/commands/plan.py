"""``spectral-fit plan CONFIG [SESSION] --budget K --out DIR``: plan the next readings."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ...fitting import Region

HELP = "plan K spectroradiometer readings that pin every parameter down (experiment design)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="scene config (TOML)")
    p.add_argument("session", nargs="?", default=None,
                   help="existing measurement session (optional): its readings count, its "
                   "fit is the centre of the parameter draws")
    p.add_argument("--budget", "-k", type=int, required=True, help="readings to plan (K)")
    p.add_argument("--out", "-o", required=True, help="output folder")
    p.add_argument("--region", default=None,
                   help="region file (TOML, docs/planning.md): where the instrument can stand "
                   "and aim; the options below override its entries")
    p.add_argument("--objects", default=None, help="objects to plan readings of (comma-separated)")
    p.add_argument("--distance", default=None,
                   help="instrument distance(s) from each object's centre, m (comma-separated)")
    p.add_argument("--elevation", default=None,
                   help="LOW,HIGH[,STEPS]: elevations in degrees around each object's centre")
    p.add_argument("--azimuth", default=None,
                   help="FIRST,LAST[,STEPS]: azimuths in degrees (0 towards +Z, 90 towards +X)")
    p.add_argument("--field-angles", default=None,
                   help="field angles to consider, degrees, from 0.2, 1, 2 (comma-separated)")
    p.add_argument("--aims-per-object", type=int, default=None,
                   help="aim points sampled over each object's surface")
    p.add_argument("--highlights", default=None,
                   help="aim points whose mirror direction lies these many degrees from the "
                   "environment's bright sources, from every position (comma-separated; "
                   "'none' for none; default 0,2,4,8)")
    p.add_argument("--noise", type=float, default=0.01,
                   help="relative noise of one reading (default 0.01)")
    p.add_argument("--aim-sigma-mm", type=float, default=1.0,
                   help="aiming error, mm (1 sigma per direction; default 1)")
    p.add_argument("--level-error", type=float, default=None,
                   help="the model's error common to a reading's bands, a fraction of it "
                   "(default: the session's [model_error.level] for object readings, else "
                   "0.005; the session's readings take their kind's stated level)")
    p.add_argument("--tilt-error", type=float, default=None,
                   help="the model's error as a tilt over a reading's bands, a fraction "
                   "(default: the session's [model_error.tilt] for object readings, else 0)")
    p.add_argument("--draws", type=int, default=8,
                   help="parameter draws the worst case is taken over (default 8)")
    p.add_argument("--spot-resolution", type=int, default=4,
                   help="pixels across each candidate's measuring field (default 4)")
    p.add_argument("--seed", type=int, default=0, help="seed of the parameter draws")
    p.add_argument("--no-picture", action="store_true", help="skip plan.png")
    p.add_argument("--json", action="store_true", help="print plan.json on stdout")


def _say(msg: str) -> None:
    print(f"plan: {msg}", file=sys.stderr, flush=True)


def _num(x: float, fmt: str = ".4g") -> str:
    return format(x, fmt) if math.isfinite(x) else "unidentified"


def _floats(text: str, option: str, counts: tuple[int, ...] | None = None) -> list[float]:
    from ..._runtime.errors import InputError

    try:
        out = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise InputError(f"must be comma-separated numbers, got {text!r}", field=option) from None
    if not out or (counts is not None and len(out) not in counts) or not all(
            math.isfinite(x) for x in out):
        raise InputError(f"expected {' or '.join(map(str, counts or ()))} numbers, got {text!r}"
                         if counts else f"expected numbers, got {text!r}", field=option)
    return out


def region_from_args(args: argparse.Namespace) -> Region:
    """The region file (or the default region) with the command-line options applied."""
    from ...fitting import Region, load_region

    region = load_region(args.region) if args.region else Region()
    kw: dict[str, object] = {}
    if args.objects:
        kw["objects"] = tuple(x.strip() for x in args.objects.split(",") if x.strip())
    if args.distance:
        kw["distances_m"] = tuple(_floats(args.distance, "--distance"))
        kw["positions"] = ()
    for opt, name in (("elevation", "elevation"), ("azimuth", "azimuth")):
        text = getattr(args, opt)
        if text:
            v = _floats(text, f"--{opt}", (2, 3))
            kw[f"{name}_deg"] = (v[0], v[1])
            if len(v) == 3:
                if v[2] != int(v[2]):
                    from ..._runtime.errors import InputError

                    raise InputError(f"STEPS must be an integer, got {v[2]}", field=f"--{opt}")
                kw[f"{name}_steps"] = int(v[2])
    if args.field_angles:
        kw["field_angles_deg"] = tuple(_floats(args.field_angles, "--field-angles"))
    if args.aims_per_object is not None:
        kw["aims_per_object"] = args.aims_per_object
    if args.highlights:
        kw["highlight_offsets_deg"] = (() if args.highlights.strip().lower() == "none"
                                       else tuple(_floats(args.highlights, "--highlights")))
    return dataclasses.replace(region, **kw).checked()


def run(args: argparse.Namespace) -> int:
    from ..._runtime.errors import InputError
    from ...fitting import plan_measurements, write_plan
    from ...io import load_scene, load_session
    from .fit import enable_compilation_cache

    if not (args.aim_sigma_mm >= 0):
        raise InputError(f"must be >= 0, got {args.aim_sigma_mm}", field="--aim-sigma-mm")
    region = region_from_args(args)
    enable_compilation_cache()
    scene = load_scene(args.config)
    session = load_session(args.session, scene=scene) if args.session else None
    try:
        res = plan_measurements(scene, session, budget=args.budget, region=region,
                                noise=args.noise, sigma_aim_m=args.aim_sigma_mm * 1e-3,
                                level_error=args.level_error, tilt_error=args.tilt_error,
                                draws=args.draws, spot_resolution=args.spot_resolution,
                                seed=args.seed, progress=_say)
    except InputError as exc:
        if exc.field in ("budget", "noise", "sigma_aim_m", "level_error", "tilt_error", "draws",
                         "spot_resolution"):
            opt = {"sigma_aim_m": "--aim-sigma-mm"}.get(exc.field,
                                                       "--" + exc.field.replace("_", "-"))
            raise InputError(exc.reason, path=exc.path, field=opt) from None
        raise
    files = write_plan(res, args.out, scene=scene, config_path=args.config,
                       picture=not args.no_picture)
    _say(f"{len(res.chosen)} readings chosen of {len(res.candidates)} candidates")
    for n, r in enumerate(res.chosen):
        _say(f"  {n + 1:2d} {r['object']:>10s}  field {r['field_angle_deg']:g} deg  position "
             f"{[round(float(x), 3) for x in r['position']]}  aim "
             f"{[round(float(x), 4) for x in r['aim']]}"
             + (f"  (highlight of source {r['highlight']['source'] + 1}, "
                f"{r['highlight']['offset_deg']:g} deg off)" if "highlight" in r else ""))
    _say(f"  {'parameter':>14s} {'tolerance':>10s} {'stderr before':>14s} "
         f"{'stderr after':>13s} {'worst/tol':>9s}")
    for j, u in enumerate(res.unknowns):
        _say(f"  {u:>14s} {res.tolerance[j]:10.4g} {_num(res.stderr_before[j]):>14s} "
             f"{_num(res.stderr_after[j]):>13s} {_num(res.worst_after[j], '.3g'):>9s}")
    _say(f"worst standard error over the draws: {_num(res.objective_before)} -> "
         f"{_num(res.objective_after)} tolerances")
    open_ = [u for u, w in zip(res.unknowns, res.worst_after, strict=True) if not math.isfinite(w)]
    if open_:
        _say(f"warning: {len(open_)} unknown(s) stay unidentified in some draw "
             f"({', '.join(open_)}); plan more readings or widen the region")
    _say("wrote " + ", ".join(files.values()))
    if args.json:
        json.dump(res.to_json(), sys.stdout, indent=2)
        print()
    return 0
