"""``spectral-fit validate``: ΔE00 of our frames vs the committed path-traced references."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

HELP = "compare rendered frames with the committed path-traced references (ΔE00 per region)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("reference", nargs="?", default="benchmark",
                   help="reference name under measurements/reference (default benchmark; "
                   "benchmark, two_spheres, any_shape, on_table, flat_faces, four_objects, "
                   "parts, sun_shadow) or a path to a reference .npz")
    p.add_argument("--all", action="store_true",
                   help="every committed reference, one after the other")
    p.add_argument("--modes", default="none,paper,gather",
                   help="sphere references: comma-separated interreflection modes (default "
                   "none,paper,gather)")
    p.add_argument("--k", type=int, default=8,
                   help="sphere references: also compare a K-coefficient basis render with "
                   "bands (0: skip)")
    p.add_argument("--samples", type=int, default=2,
                   help="sub-pixels per side of each of our pixels, averaged: the references' "
                   "pixels are area means (default 2; 1: pixel centres only)")
    p.add_argument("-o", "--figure", default=None,
                   help="false-colour ΔE00 picture of one reference, .png, .pdf or .svg "
                   "(default <output>/<name>_delta_e.png; the JSON goes to stdout with --json)")
    p.add_argument("--output", default="out/validate",
                   help="folder of the pictures (default out/validate)")
    p.add_argument("--json", action="store_true", help="print the result JSON on stdout")


def _print_regions(regions: dict[str, Any], head: str) -> None:
    for region, s in regions.items():
        if not isinstance(s, dict) or not s.get("n"):
            continue
        t, ok = s["targets"], s["pass"]
        cells = "  ".join(f"{k} {s[k]:.2f} (≤ {t[k]:g} {'pass' if ok[k] else 'FAIL'})"
                          for k in ("median", "p90", "max"))
        noise = s.get("reference_noise_de", {}).get("median")
        extra = f"  [reference noise {noise:.2f}]" if noise is not None else ""
        print(f"{head:14s} {region:32s} n={s['n']:4d}  {cells}{extra}")


def _one(name: str, args: argparse.Namespace, modes: tuple[str, ...]) -> dict[str, Any]:
    from ...validation import validate_reference
    from ...validation.reference import load_reference

    ref = load_reference(name)
    figure = args.figure if args.figure and not args.all else str(
        Path(args.output) / f"{ref.name}_delta_e.png")
    res = validate_reference(name, modes=modes, basis_k=args.k or None, figure=figure,
                             samples=args.samples)
    if "modes" not in res:  # a scene of any shape
        if not args.json:
            _print_regions(res["regions"], ref.name)
            print(f"{ref.name:14s} all targets: {'pass' if res['ok'] else 'FAIL'}")
        return res
    if not args.json:
        for mode, r in res["modes"].items():
            note = "" if r["available"] else " (mode not available: rendered without " \
                "interreflection)"
            for region in ("direct", "interreflection"):
                s = r[region]
                if s.get("n"):
                    print(f"{mode:7s} {region:15s} n={s['n']:3d}  ΔE00 median "
                          f"{s['median']:.2f}  p90 {s['p90']:.2f}  max {s['max']:.2f}{note}")
        for key, ok in res["checks"].items():
            print(f"check {key}: {'pass' if ok else 'FAIL'}")
        if "regions" in res:
            regions = {k: v for k, v in res["regions"].items() if k != "mode"}
            _print_regions(regions, ref.name)
    return res


def run(args: argparse.Namespace) -> int:
    from ..._runtime.errors import InputError
    from ..._runtime.fileio import check_suffix
    from ...validation import FIGURE_FORMATS, check_samples
    from ...validation.reference import REFERENCE_DIR

    modes = tuple(m.strip() for m in args.modes.split(",") if m.strip())
    bad = [m for m in modes if m not in ("none", "paper", "gather")]
    if bad or not modes:
        raise InputError(f"modes must be among none, paper, gather; got {args.modes!r}",
                         field="--modes")
    if args.k is not None and args.k < 0:
        raise InputError(f"must be >= 0, got {args.k}", field="--k")
    check_suffix(args.figure, FIGURE_FORMATS, "figure", "the ΔE00 figure is a picture")
    check_samples(args.samples, field="--samples")
    names = sorted(p.stem for p in REFERENCE_DIR.glob("*.npz")) if args.all else [
        args.reference]
    results = {}
    for name in names:
        res = _one(name, args, modes)
        results[res["reference"]] = res
        if not args.json:
            print(f"figure: {res.get('figure')}", file=sys.stderr)
    if args.json:
        print(json.dumps(results if args.all else results[next(iter(results))], indent=2))
    return 0
