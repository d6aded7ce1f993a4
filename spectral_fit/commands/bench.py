"""``spectral-fit bench``: run the benchmarks and write JSON."""

from __future__ import annotations

import argparse
import json
import platform
import sys

HELP = "run the speed benchmarks (compile and steady-state time, medians) and write JSON"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cases", default=None,
                   help="comma-separated case names (default: all); --list shows them")
    p.add_argument("--list", action="store_true", help="list the cases and exit")
    p.add_argument("--repeats", type=int, default=20, help="timed calls per case (default 20)")
    p.add_argument("--quick", action="store_true",
                   help="small inputs, to check the harness (figures not comparable)")
    p.add_argument("-o", "--output", default=None, help="also write the JSON to this file")
    p.add_argument("--json", action="store_true", help="print the JSON object on stdout")
    p.add_argument("--gl-baseline", action="store_true",
                   help="run the OpenGL baseline's cases instead (the paper's two-pass pipeline "
                   "on Mesa's EGL; needs the 'gl' extra; docs/benchmark.md)")


def run(args: argparse.Namespace) -> int:
    from ..bench import BenchOptions, discover_cases, run_benchmarks
    from ..errors import InputError
    from ..fileio import atomic_write_text

    gl_cases = None
    if args.gl_baseline:
        from ..benchmarks.gl_baseline import GL_CASES

        gl_cases = GL_CASES
    if args.list:
        print("\n".join(sorted(gl_cases if gl_cases is not None else discover_cases())))
        return 0
    if args.repeats < 1:
        raise InputError("must be at least 1", field="--repeats")
    names = [n.strip() for n in args.cases.split(",") if n.strip()] if args.cases else None
    gl_meta: dict[str, str] = {}
    if gl_cases is not None:  # fail at once (one line) without moderngl or EGL
        from ..benchmarks.gl_baseline import gl_info

        gl_meta = gl_info()

    def progress(name: str) -> None:
        print(f"bench: {name} ...", file=sys.stderr, flush=True)

    results = run_benchmarks(names, BenchOptions(repeats=args.repeats, quick=args.quick),
                             progress, cases=gl_cases)
    import jax

    results["_meta"] = {
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        "jax": jax.__version__,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "repeats": args.repeats,
        "quick": args.quick,
        **gl_meta,
    }
    text = json.dumps(results, indent=2, sort_keys=True)
    if args.output:
        atomic_write_text(args.output, text + "\n")
    if args.json:
        print(text)
    else:
        for name, r in results.items():
            if name.startswith("_") or not isinstance(r, dict):
                continue
            if "median_ms" in r:
                print(f"{name:24s} median {r['median_ms']:9.3f} ms  "
                      f"compile {r['compile_s']:7.3f} s  (n={r['n']})")
            else:
                print(f"{name:24s} {r}")
    return 0
