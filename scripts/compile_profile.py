"""Sum the JAX compile events of a test run (``SPECTRAL_FIT_TEST_COMPILE_LOG=FOLDER python -m
pytest ...``, see tests/conftest.py): where the tests' compile time goes.

Usage: python scripts/compile_profile.py FOLDER [--top N]

Prints, per test and per function name, the seconds spent tracing, lowering and compiling
(XLA backend compiles; loads from JAX's persistent cache counted apart), largest first. A
function compiled by many tests is a candidate for a shared fixture or one frame size.
"""

from __future__ import annotations

import argparse
import collections
from pathlib import Path

EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "compile",
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--top", type=int, default=25)
    args = ap.parse_args()
    by_test: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    by_fun: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    tests_of_fun: dict[str, set[str]] = collections.defaultdict(set)
    for f in sorted(args.folder.glob("*.tsv")):
        pending_hit: dict[str, float] = {}
        for line in f.read_text(encoding="utf-8").splitlines():
            parts = line.split("\t")
            if len(parts) != 4:
                continue
            test, event, fun, sec = parts[0], parts[1], parts[2], float(parts[3])
            test = test or "(collection / fixtures outside a test)"
            if event == "/jax/compilation_cache/cache_retrieval_time_sec":
                pending_hit[test] = sec
                continue
            kind = EVENTS.get(event)
            if kind is None:
                continue
            if kind == "compile" and test in pending_hit:
                kind = "cache load"
                del pending_hit[test]
            by_test[test][kind] += sec
            by_test[test][kind + " n"] += 1
            by_fun[fun][kind] += sec
            by_fun[fun][kind + " n"] += 1
            if kind == "compile" and sec > 1.0:
                tests_of_fun[fun].add(test)
    total = collections.Counter()
    for c in by_test.values():
        total.update(c)
    print("total: " + ", ".join(f"{k} {total[k]:.0f} s ({total[k + ' n']})"
                                for k in ("trace", "lower", "compile", "cache load")))

    def table(title: str, rows: dict[str, collections.Counter], extra=None) -> None:
        print(f"\n{title}")
        order = sorted(rows, key=lambda k: -(rows[k]["trace"] + rows[k]["lower"]
                                             + rows[k]["compile"]))
        for k in order[:args.top]:
            c = rows[k]
            s = c["trace"] + c["lower"] + c["compile"]
            note = extra(k) if extra else ""
            print(f"{s:7.1f} s  compile {c['compile']:6.1f} ({c['compile n']:4d})  lower "
                  f"{c['lower']:5.1f}  trace {c['trace']:5.1f}  load {c['cache load']:4.1f}  "
                  f"{k}{note}")

    table("by test", by_test)
    table("by function", by_fun,
          lambda k: f"  [{len(tests_of_fun[k])} tests compile it > 1 s]" if tests_of_fun[k]
          else "")


if __name__ == "__main__":
    main()
