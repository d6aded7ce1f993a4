"""Speed ratio of the JAX frame to the OpenGL baseline, measured side by side (docs/benchmark.md).

Runs ROUNDS rounds of two fresh ``spectral-fit bench`` processes, alternating which goes first:
the OpenGL baseline's cases (``--gl-baseline``: gl_paper, gl_paper_none) and the JAX frame cases
(frame_paper, frame_paper_b1, frame_paper_none). Prints each round's medians and the ratios
baseline / JAX of the round, then the median over the rounds; ``-o`` writes everything as JSON.

Usage: python scripts/gl_ratio.py [--rounds 3] [--repeats 20] [--quick] [-o ratios.json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from spectral_fit.cli.commands.bench import TABLE_RATIOS

ROOT = Path(__file__).resolve().parents[1]
GL = ["gl_paper", "gl_paper_none"]
JAX = ["frame_paper", "frame_paper_b1", "frame_paper_none"]
#: (baseline case, JAX case) of each ratio: README table's ratios of the cases run here
RATIOS = [(a, b) for a, b in TABLE_RATIOS if a in GL and b in JAX]


def bench(cases: list[str], gl: bool, repeats: int, quick: bool, out: Path) -> dict:
    cmd = [sys.executable, "-m", "spectral_fit", "bench", "--cases", ",".join(cases),
           "--repeats", str(repeats), "-o", str(out)]
    if gl:
        cmd.append("--gl-baseline")
    if quick:
        cmd.append("--quick")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    r = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if r.returncode:
        sys.exit(r.stderr.strip().splitlines()[-1] if r.stderr.strip() else
                 f"{' '.join(cmd)} failed ({r.returncode})")
    return json.loads(out.read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--quick", action="store_true", help="small frames (the harness only)")
    ap.add_argument("-o", "--output", default=None)
    args = ap.parse_args()
    rounds = []
    with tempfile.TemporaryDirectory(prefix="sf_ratio_") as tmp:
        for k in range(args.rounds):
            order = [True, False] if k % 2 == 0 else [False, True]
            res: dict = {}
            for gl in order:
                out = Path(tmp) / f"{'gl' if gl else 'jax'}_{k}.json"
                res.update(bench(GL if gl else JAX, gl, args.repeats, args.quick, out))
            meds = {c: res[c]["median_ms"] for c in GL + JAX}
            ratios = {f"{a}/{b}": meds[a] / meds[b] for a, b in RATIOS}
            rounds.append({"median_ms": meds, "ratios": ratios,
                           "gl_renderer": res["_meta"].get("gl_renderer")})
            print(f"round {k + 1}: " + ", ".join(f"{c} {m:.1f} ms" for c, m in meds.items()),
                  flush=True)
            print("         " + ", ".join(f"{r} {v:.2f}×" for r, v in ratios.items()),
                  flush=True)
    summary = {r: statistics.median(x["ratios"][r] for x in rounds) for r in rounds[0]["ratios"]}
    print("median over rounds: " + ", ".join(f"{r} {v:.2f}×" for r, v in summary.items()))
    if args.output:
        Path(args.output).write_text(json.dumps({"rounds": rounds, "median_ratios": summary},
                                                indent=2) + "\n")


if __name__ == "__main__":
    main()
