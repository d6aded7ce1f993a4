"""``spectral-fit bench``: run the benchmarks and write JSON."""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import sys
from pathlib import Path
from typing import Any

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
    p.add_argument("--save", action="store_true",
                   help="also write the results to benchmarks/results/<date>-<machine>.json in "
                   "the repository (the files README's table is made from)")
    p.add_argument("--table", nargs="+", metavar="RESULTS", default=None,
                   help="print a Markdown table of saved result files (one column each) "
                   "and exit")
    p.add_argument("--gl-baseline", action="store_true",
                   help="run the OpenGL baseline's cases instead (the paper's two-pass pipeline "
                   "on Mesa's EGL; needs the 'gl' extra; docs/benchmark.md)")


def run(args: argparse.Namespace) -> int:
    from ..._runtime.errors import InputError
    from ..._runtime.fileio import atomic_write_text
    from ...bench import BenchOptions, discover_cases, run_benchmarks

    if args.table:
        print(results_table([_read_results(f) for f in args.table]))
        return 0
    gl_cases = None
    if args.gl_baseline:
        from ...bench.cases.gl_baseline import GL_CASES

        gl_cases = GL_CASES
    if args.list:
        print("\n".join(sorted(gl_cases if gl_cases is not None else discover_cases())))
        return 0
    if args.repeats < 1:
        raise InputError("must be at least 1", field="--repeats")
    names = [n.strip() for n in args.cases.split(",") if n.strip()] if args.cases else None
    gl_meta: dict[str, str] = {}
    if gl_cases is not None:  # fail at once (one line) without moderngl or EGL
        from ...bench.cases.gl_baseline import gl_info

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
        "cpu": cpu_name(),
        "cores": os.cpu_count(),
        "date": datetime.date.today().isoformat(),
        "repeats": args.repeats,
        "quick": args.quick,
        **gl_meta,
    }
    text = json.dumps(results, indent=2, sort_keys=True)
    if args.output:
        atomic_write_text(args.output, text + "\n")
    if args.save:
        saved = results_path(results["_meta"])
        saved.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(saved, json.dumps(merged_results(saved, results), indent=2,
                                            sort_keys=True) + "\n")
        print(f"bench: wrote {saved}", file=sys.stderr)
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


def cpu_name() -> str:
    """The processor's model name (Linux: /proc/cpuinfo), else ``platform.processor()``."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def results_path(meta: dict[str, Any]) -> Path:
    """``benchmarks/results/<date>-<machine>.json`` in the repository; the machine named by
    its processor, core count and, off the CPU, the first device."""
    from ..._runtime.paths import REPO_ROOT

    name = f"{meta['cpu']} {meta['cores']}c"
    if meta.get("backend", "cpu") != "cpu":
        name += " " + str(meta["devices"][0])
    slug = re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")
    return REPO_ROOT / "benchmarks" / "results" / f"{meta['date']}-{slug}.json"


def _read_results(path: str) -> dict[str, Any]:
    from ..._runtime.errors import InputError

    try:
        data = json.loads(Path(path).read_text())
    except OSError as exc:
        raise InputError(f"cannot read ({exc.strerror or exc})", path=path) from None
    except json.JSONDecodeError as exc:
        raise InputError(f"not JSON: {exc.msg}", path=path, line=exc.lineno) from None
    if not isinstance(data, dict) or not isinstance(data.get("_meta"), dict):
        raise InputError("not a bench result (no '_meta' object)", path=path, field="_meta")
    return data


def merged_results(path: Path, results: dict[str, Any]) -> dict[str, Any]:
    """``results`` merged into the results file of the same date and machine at ``path`` (a
    run of some cases, e.g. the OpenGL baseline's, adds to that day's file; a case run again
    replaces its entry; ``_meta`` keeps both runs' keys, this run's winning)."""
    if not path.exists():
        return results
    old = _read_results(str(path))
    return {**old, **results, "_meta": {**old["_meta"], **results["_meta"]}}


#: speed ratios the table adds when a run has both cases: (slower case, faster case)
TABLE_RATIOS = (("gl_paper", "frame_paper"), ("gl_paper", "frame_paper_b1"),
                ("gl_paper_none", "frame_paper_none"), ("gl_paper_anchor_workload", "frame_paper"),
                ("frame_any_shape", "frame_paper"))


def _cell(v: dict[str, Any]) -> str:
    if "first_frame_after_import_cold_s" in v:  # cold_start_s: a fresh process's first frame
        return (f"{v['first_frame_after_import_cold_s']:.3g} s cold, "
                f"{v['first_frame_after_import_warm_s']:.3g} s with warm caches")
    return f"{v['median_ms']:.3g} ms (compile {v['compile_s']:.3g} s)"


def results_table(runs: list[dict[str, Any]]) -> str:
    """A Markdown table: one row per case, one column per run (median ms; compile s; the
    cold start as first frame after import, cold and with warm caches), then the speed ratios
    of ``TABLE_RATIOS`` that some run has both cases of (median / median)."""
    cases = sorted({k for r in runs for k, v in r.items()
                    if not k.startswith("_") and isinstance(v, dict) and "median_ms" in v})
    head = ["case"] + [f"{r['_meta'].get('date', '?')}, {r['_meta'].get('cpu', '?')} "
                       f"({r['_meta'].get('cores', '?')} cores, {r['_meta'].get('backend', '?')})"
                       for r in runs]
    rows = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for c in cases:
        cells = [f"`{c}`"]
        for r in runs:
            v = r.get(c)
            cells.append("—" if not isinstance(v, dict) else _cell(v))
        rows.append("| " + " | ".join(cells) + " |")
    for slow, fast in TABLE_RATIOS:
        cells = [f"`{slow}` / `{fast}`"]
        for r in runs:
            a, b = r.get(slow), r.get(fast)
            ok = isinstance(a, dict) and isinstance(b, dict)
            cells.append(f"{a['median_ms'] / b['median_ms']:.2f}×" if ok else "—")
        if any(c != "—" for c in cells[1:]):
            rows.append("| " + " | ".join(cells) + " |")
    return "\n".join(rows)
