"""``spectral-fit validate``: ΔE00 of our frames vs the committed path-traced references."""

from __future__ import annotations

import argparse
import json
import sys

HELP = "compare rendered frames with the committed path-traced references (ΔE00 per region)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("reference", nargs="?", default="benchmark",
                   help="reference name under measurements/reference (default benchmark) or "
                   "a path to a reference .npz")
    p.add_argument("--modes", default="none,paper,gather",
                   help="comma-separated interreflection modes (default none,paper,gather)")
    p.add_argument("--k", type=int, default=8,
                   help="also compare a K-coefficient basis render with bands (0: skip)")
    p.add_argument("-o", "--figure", default="validation_delta_e.png",
                   help="false-colour ΔE00 picture, .png, .pdf or .svg (default "
                   "validation_delta_e.png; the JSON goes to stdout with --json)")
    p.add_argument("--json", action="store_true", help="print the result JSON on stdout")


def run(args: argparse.Namespace) -> int:
    from ..._runtime.errors import InputError
    from ...validation import validate

    modes = tuple(m.strip() for m in args.modes.split(",") if m.strip())
    bad = [m for m in modes if m not in ("none", "paper", "gather")]
    if bad or not modes:
        raise InputError(f"modes must be among none, paper, gather; got {args.modes!r}",
                         field="--modes")
    if args.k is not None and args.k < 0:
        raise InputError(f"must be >= 0, got {args.k}", field="--k")
    res = validate(args.reference, modes=modes, basis_k=args.k or None, figure=args.figure)
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    for mode, r in res["modes"].items():
        note = "" if r["available"] else " (mode not available: rendered without interreflection)"
        for region in ("direct", "interreflection"):
            s = r[region]
            if s.get("n"):
                print(f"{mode:7s} {region:15s} n={s['n']:3d}  ΔE00 median {s['median']:.2f}  "
                      f"p90 {s['p90']:.2f}  max {s['max']:.2f}{note}")
    for key, ok in res["checks"].items():
        print(f"check {key}: {'pass' if ok else 'FAIL'}")
    print(f"figure: {res.get('figure')}", file=sys.stderr)
    return 0
