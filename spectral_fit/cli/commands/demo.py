"""``spectral-fit demo``: the main job on the bundled data, end to end."""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

from ..._runtime.paths import REPO_ROOT

HELP = "run the demo on the bundled data (environment, render, fit) and write pictures + JSON"

ROOT = REPO_ROOT
ENVIRONMENT = ROOT / "measurements" / "environment" / "studio_room.exr"
CONFIG = ROOT / "configs" / "two_spheres.toml"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--output", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--json", action="store_true", help="print the summary JSON on stdout")
    p.add_argument("--skip-fit", action="store_true", help="render only (no fit)")


def _say(msg: str) -> None:
    print(f"demo: {msg}", file=sys.stderr, flush=True)


def environment_step(out: Path) -> dict:
    """Show the bundled spectral environment: a display image and the chromaticities of its
    texels on the CIE 1931 diagram."""
    import numpy as np

    from ...color import chromaticity_diagram, radiance_to_xyz, save_png, to_display, xyz_to_xy
    from ...io import read_spectral_exr

    wl, img = read_spectral_exr(ENVIRONMENT)
    xyz = radiance_to_xyz(img.astype(np.float64), wl)
    y = xyz[..., 1]
    exposure = float(np.exp(np.mean(np.log(np.maximum(y, 1e-9)))) / 0.18)
    disp = to_display(xyz, exposure_luminance=exposure)
    save_png(out / "environment.png", disp.rgb)
    xy = xyz_to_xy(xyz.reshape(-1, 3))
    chromaticity_diagram(out / "environment_chromaticity.png", {"environment texels": xy[::7]},
                         title="Bundled environment: texel chromaticities", markers={
                             "environment texels": "."})
    return {
        "file": str(ENVIRONMENT),
        "size": [int(img.shape[1]), int(img.shape[0])],
        "bands": int(wl.size),
        "luminance_cd_m2": {"median": float(np.median(y)), "max": float(y.max())},
        "exposure_luminance": exposure,
        "out_of_gamut_fraction": float(disp.out_of_gamut_fraction),
        "pictures": ["environment.png", "environment_chromaticity.png"],
    }


def render_step(out: Path) -> dict:
    """Render the bundled two-sphere scene (the paper's setup, interreflection in the config's
    mode): display PNG, spectral EXR and coverage mask."""
    import jax

    from ...io import load_scene
    from ...rendering import prepare_cached, regrow, render_frame_cached, write_frame

    scene = load_scene(CONFIG)
    t0 = time.perf_counter()
    # as `spectral-fit render`: the prepared scene and the compiled frame program are kept on
    # disk, so a second demo loads them (docs/rendering.md "Cold start")
    prep = prepare_cached(CONFIG, progress=_say)
    frame = jax.block_until_ready(render_frame_cached(prep, spectral=True, progress=_say))
    frame = regrow(prep, frame, None, True)
    first = time.perf_counter() - t0
    again = []  # steady state: the median of a few frames after the first (the benchmark's
    # `spectral-fit bench` gives compile and steady-state times with more repeats)
    for _ in range(5):
        t1 = time.perf_counter()
        jax.block_until_ready(render_frame_cached(prep, spectral=True))
        again.append(time.perf_counter() - t1)
    files = write_frame(frame, png=out / "frame.png", exr=out / "frame.exr",
                        mask_png=out / "frame_mask.png", wavelengths=prep.colour.wavelengths,
                        colourspace=scene.display.colourspace)
    stats = {k: (v.item() if hasattr(v, "item") else v) for k, v in frame.stats.items()}
    h, w = prep.camera.shape
    return {
        "config": str(CONFIG),
        "size": [w, h],
        "interreflection": prep.interreflection.mode,
        "spectral_mode": prep.colour.spectral_mode,
        "channels": int(prep.channels),
        "first_frame_s": first,
        "frame_ms": statistics.median(again) * 1e3,
        "frame_ms_repeats": len(again),
        "coverage": float(stats["coverage"]),
        "out_of_gamut_fraction": float(stats.get("out_of_gamut_fraction", float("nan"))),
        "pictures": [Path(f).name for f in files],
    }


def fit_step(out: Path) -> dict:
    """Fit the bundled spectroradiometer session (readings simulated by the Mitsuba reference
    renderer) and write its report (JSON, chromaticity diagram, spectra, residuals)."""
    from ...fitting import run_demo_fit

    def progress(msg: object) -> None:
        _say(f"fit: {msg}")

    return run_demo_fit(out, progress=progress, render=False)


def run(args: argparse.Namespace) -> int:
    from ..._runtime.fileio import atomic_write_text
    from ...rendering import enable_compilation_cache

    # JAX's persistent compilation cache, as render / live / fit use: a second demo loads the
    # frame and fit programs instead of compiling them (docs/rendering.md "Cold start")
    enable_compilation_cache(min_compile_time_s=1.0)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    summary: dict = {"output": str(out)}
    t0 = time.perf_counter()
    _say("environment map ...")
    summary["environment"] = environment_step(out)
    _say("rendering configs/two_spheres.toml ...")
    summary["render"] = render_step(out)
    r = summary["render"]
    _say(f"frame {r['frame_ms']:.0f} ms (median of {r['frame_ms_repeats']}) after a first "
         f"frame of {r['first_frame_s']:.1f} s")
    if not args.skip_fit:
        _say("fitting the bundled session measurements/sessions/two_spheres_demo ...")
        summary["fit"] = fit_step(out / "fit")
    summary["seconds"] = time.perf_counter() - t0
    text = json.dumps(summary, indent=2)
    atomic_write_text(out / "summary.json", text + "\n")
    if args.json:
        print(text)
    else:
        _say(f"done in {summary['seconds']:.1f} s; pictures and summary.json in {out}/")
    return 0
