"""Time the OpenGL baseline beside another implementation of the paper's pipeline, in rounds.

Each round runs, in fresh processes and alternating which goes first, ``spectral-fit bench
--gl-baseline`` (the cases ``gl_paper``, ``gl_paper_nocull``, ``gl_paper_anchor_workload``,
``gl_paper_none``) and the other implementation's command; the other's frame time is read from
the JSON file it writes (``--other-result``, the value at the dotted ``--other-key``). Prints
each round's medians and the ratios baseline / other, then the median over the rounds; ``-o``
writes everything as JSON.

Usage: python scripts/gl_beside.py --other "python /path/gl_bench.py 20" \\
           --other-result /tmp/gl_anchor/gl_results.json --other-key ir_readback_ms.median \\
           [--other-key-none noir_readback_ms.median] [--rounds 4] [--repeats 20] [-o out.json]
"""

from __future__ import annotations

import argparse
import json
import shlex
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from gl_ratio import bench

CASES = ["gl_paper", "gl_paper_nocull", "gl_paper_anchor_workload", "gl_paper_none"]


def _value(doc: dict, key: str) -> float:
    for part in key.split("."):
        doc = doc[part]
    return float(doc)  # type: ignore[arg-type]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--other", required=True, help="the other implementation's command")
    ap.add_argument("--other-result", required=True, type=Path)
    ap.add_argument("--other-key", required=True, help="its frame time with interreflection")
    ap.add_argument("--other-key-none", default=None, help="its frame time without")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("-o", "--output", default=None)
    args = ap.parse_args()
    rounds = []
    with tempfile.TemporaryDirectory(prefix="sf_beside_") as tmp:
        for k in range(args.rounds):
            res: dict = {}
            for ours in ([True, False] if k % 2 == 0 else [False, True]):
                if ours:
                    got = bench(CASES, True, args.repeats, False, Path(tmp) / f"gl_{k}.json")
                    res.update({c: got[c]["median_ms"] for c in CASES})
                else:
                    r = subprocess.run(shlex.split(args.other), capture_output=True, text=True)
                    if r.returncode:
                        sys.exit(f"{args.other} failed ({r.returncode}): {r.stderr[-500:]}")
                    doc = json.loads(args.other_result.read_text())
                    res["other"] = _value(doc, args.other_key)
                    if args.other_key_none:
                        res["other_none"] = _value(doc, args.other_key_none)
            for c in CASES[:3]:
                res[f"{c}/other"] = res[c] / res["other"]
            if "other_none" in res:
                res["gl_paper_none/other_none"] = res["gl_paper_none"] / res["other_none"]
            print(f"round {k + 1}: " + ", ".join(f"{n} {v:.3g}" for n, v in res.items()),
                  flush=True)
            rounds.append(res)
    med = {n: statistics.median(r[n] for r in rounds) for n in rounds[0]}
    print("median: " + ", ".join(f"{n} {v:.3g}" for n, v in med.items()))
    if args.output:
        Path(args.output).write_text(json.dumps({"rounds": rounds, "median": med}, indent=1))


if __name__ == "__main__":
    main()
