"""Accuracy tables of the gloss integral (docs/lighting.md): relative error of
``gloss_integral`` vs the brute-force oracle of tests/helpers/lighting.py (texel sum over the map
upsampled 4×, float64) on the two bundled maps, per μ and quality.

    python scripts/gloss_accuracy.py [--model bilinear|box] [--mus 0.05,0.1,...]
        [--qualities exact,render,fast] [--maps benchmark,room] [--ss 4] [--refine 8]

("fast": the split-sum :func:`gloss_split_sum` of the frame renderer's default quality.)

Per μ: 16 configurations with θr <= 60° (8 with the mirror direction within ~μ of the map's
brightest texel) and 8 grazing ones (θr = 65°, 70°, 75°, 80°, one on the lamp and one anywhere
each). For μ <= 0.1 the oracle sums the lobe's core ``--refine`` × finer still (adaptive
supersampling; at μ = 0.07, θr = 80° on the room map's lamp the plain 4× sum is 2.1 % off).
Printed: median and max over configurations of the worst band's relative error, for the
θr <= 60° set and for the grazing set.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from helpers.lighting import brute_gloss, configs, grazing_configs  # noqa: E402

from spectral_fit.io import read_spectral_exr  # noqa: E402
from spectral_fit.lighting import (  # noqa: E402
    EnvironmentMap,
    SplitSumMap,
    gloss_integral,
    gloss_split_sum,
    lobe_moment_table,
    rotation_y,
    texel_directions,
)

MAPS = {"benchmark": (ROOT / "measurements/benchmark/anchor_environment.exr", 180.0),
        "room": (ROOT / "measurements/environment/studio_room.exr", 0.0)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="bilinear", choices=("bilinear", "box"))
    ap.add_argument("--mus", default="0.05,0.07,0.1,0.14,0.2,0.25,0.3,0.4,0.5")
    ap.add_argument("--qualities", default="exact,render")
    ap.add_argument("--maps", default="benchmark,room")
    ap.add_argument("--ss", type=int, default=4, help="oracle supersampling")
    ap.add_argument("--refine", type=int, default=8,
                    help="oracle refinement of the lobe's core for mu <= 0.1 (1: none)")
    args = ap.parse_args()
    mus = [float(m) for m in args.mus.split(",")]
    for name in args.maps.split(","):
        path, rot_deg = MAPS[name]
        _, img = read_spectral_exr(path)
        img = np.asarray(img, np.float64)
        rot = rotation_y(rot_deg)
        env = EnvironmentMap.from_array(img, rotation_y_deg=rot_deg)
        lum = img.sum(-1)
        i, j = np.unravel_index(np.argmax(lum), lum.shape)
        lamp = rot @ texel_directions(*img.shape[:2])[i, j]
        fns = {q: jax.jit(jax.vmap(lambda n, v, m, q=q, e=env: gloss_integral(e, n, v, m, 1.5,
                                                                        quality=q),
                                   in_axes=(0, 0, None)))
               for q in args.qualities.split(",") if q != "fast"}
        if "fast" in args.qualities.split(","):
            pre = SplitSumMap.from_environment(env, img)

            @jax.jit
            def fast(n, v, m, e=env, p=pre):
                return gloss_split_sum(e, p, lobe_moment_table(m, 1.5), n, v, m, 1.5)

            fns["fast"] = fast
        print(f"\n{name} map ({args.model} oracle): μ | quality | θr <= 60°: median / max | "
              "grazing 65–80°: median / max")
        for mu in mus:
            seed = int(mu * 1000) + 7
            cfg = configs(lamp, mu, 16, seed) + grazing_configs(lamp, mu, seed + 1,
                                                               (65.0, 70.0, 75.0, 80.0))
            refine = args.refine if mu <= 0.1 and args.model == "bilinear" else 1
            ref = np.array([brute_gloss(img, n, v, mu, 1.5, rotation=rot, ss=args.ss,
                                        model=args.model, refine=refine) for n, v in cfg])
            ns = jnp.asarray(np.array([c[0] for c in cfg]), jnp.float32)
            vs = jnp.asarray(np.array([c[1] for c in cfg]), jnp.float32)
            for q, fn in fns.items():
                got = np.asarray(fn(ns, vs, jnp.float32(mu)), np.float64)
                rel = np.abs(got / ref - 1.0).max(axis=1) * 100
                a, g = rel[:16], rel[16:]
                print(f"| {mu:.2f} | {q} | {np.median(a):.2f} % / {a.max():.2f} % | "
                      f"{np.median(g):.2f} % / {g.max():.2f} % |", flush=True)


if __name__ == "__main__":
    main()
