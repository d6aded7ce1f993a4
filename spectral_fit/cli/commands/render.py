"""``spectral-fit render CONFIG``: render a scene config to PNG / EXR files."""

from __future__ import annotations

import argparse
import json
import sys
import time

HELP = "render a scene config (TOML) to a PNG and optional spectral/XYZ/RGB EXR files"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="scene config (TOML), e.g. configs/two_spheres.toml")
    p.add_argument("-o", "--output", default="frame.png",
                   help="display-encoded PNG (default frame.png)")
    p.add_argument("--exr", help="spectral OpenEXR of the frame (radiance per band)")
    p.add_argument("--xyz-exr", help="OpenEXR with absolute CIE XYZ (X, Y, Z channels)")
    p.add_argument("--rgb-exr", help="OpenEXR with the display's linear RGB (unclipped)")
    p.add_argument("--mask", help="coverage mask PNG (255 = object)")
    p.add_argument("--composite", help="PNG of the objects over --background")
    p.add_argument("--background", help="background picture (PNG/JPEG, frame size)")
    p.add_argument("--size", help="frame size WxH (default: the config's)")
    p.add_argument("--mode", choices=("paper", "gather", "none"),
                   help="interreflection mode (default: the config's)")
    p.add_argument("--spectral-mode", choices=("bands", "basis"),
                   help="spectral representation (default: the config's)")
    p.add_argument("--k", type=int, help="basis size in basis mode (default: the config's)")
    p.add_argument("--json", action="store_true", help="print the summary JSON on stdout")


def parse_size(text: str | None) -> tuple[int, int] | None:
    """'720x480' → (720, 480); InputError naming --size otherwise."""
    from ..._runtime.errors import InputError

    if text is None:
        return None
    parts = text.lower().replace("×", "x").split("x")
    try:
        w, h = (int(s) for s in parts)
    except ValueError:
        raise InputError(f"expected WxH (e.g. 720x480), got {text!r}", field="--size") from None
    if not (0 < w <= 16384 and 0 < h <= 16384):
        raise InputError(f"W and H must be in 1..16384, got {text!r}", field="--size")
    return w, h


#: the output options and the extension their file format needs
_OUTPUT_SUFFIX = {"--output": ".png", "--mask": ".png", "--composite": ".png", "--exr": ".exr",
                  "--xyz-exr": ".exr", "--rgb-exr": ".exr"}


def _check_output_names(args: argparse.Namespace) -> None:
    """Refuse an output file whose extension is not its format's (a PNG written into
    ``frame.jpg``, an EXR into ``frame.png``) before anything is rendered."""
    from ..._runtime.fileio import check_suffix

    for option, suffix in _OUTPUT_SUFFIX.items():
        check_suffix(getattr(args, option[2:].replace("-", "_")), (suffix,), option,
                     f"{option} writes {suffix[1:].upper()}")


def _say(msg: str) -> None:
    """Progress of the long first-run steps, on stderr (stdout keeps the summary)."""
    print(f"render: {msg}", file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    from ..._runtime.errors import InputError

    size = parse_size(args.size)
    _check_output_names(args)
    if args.composite and not args.background:
        raise InputError("--composite needs --background", field="--composite")
    t0 = time.perf_counter()
    import jax

    from ...io import load_scene
    from ...rendering import (
        enable_compilation_cache,
        prepare_cached,
        render_frame_cached,
        write_frame,
    )

    t_import = time.perf_counter() - t0
    enable_compilation_cache(min_compile_time_s=1.0)  # docs/rendering.md "Cold start"
    # the config is read (and checked, errors naming its file and field) by prepare_cached,
    # unless its prepared scene is stored: that skips the scene's parsing, and with it
    # colour-science's import (slow: its package imports its plotting and matplotlib)
    t1 = time.perf_counter()
    prep = prepare_cached(args.config, size=size, mode=args.mode,
                          spectral_mode=args.spectral_mode, k=args.k, progress=_say)
    t_prep = time.perf_counter() - t1
    t2 = time.perf_counter()
    frame = jax.block_until_ready(render_frame_cached(prep, spectral=bool(args.exr),
                                                      progress=_say))
    t_first = time.perf_counter() - t2
    t3 = time.perf_counter()
    jax.block_until_ready(render_frame_cached(prep, spectral=bool(args.exr)))
    t_frame = time.perf_counter() - t3
    from ...rendering import regrow

    frame = regrow(prep, frame, None, bool(args.exr))
    ratio = None
    if prep.surfaces:  # the table drawn in the frame, and its change over a background
        from ...rendering import draw_surfaces, surface_layer, surface_ratio

        layer = surface_layer(prep, prep.surfaces)
        ratio = surface_ratio(prep, layer, frame.mask)
        frame = draw_surfaces(prep, frame, layer)
    written = write_frame(frame, png=args.output, exr=args.exr, xyz_exr=args.xyz_exr,
                          rgb_exr=args.rgb_exr, mask_png=args.mask,
                          composite_png=args.composite, background=args.background,
                          surface_ratio=ratio,
                          wavelengths=prep.colour.wavelengths,
                          colourspace=(load_scene(args.config).display.colourspace
                                       if args.rgb_exr else "sRGB"))
    stats = {k: (v.item() if hasattr(v, "item") else v) for k, v in frame.stats.items()}
    h, w = prep.camera.shape
    summary = {
        "config": str(args.config),
        "size": [w, h],
        "mode": prep.interreflection.mode,
        "spectral_mode": prep.colour.spectral_mode,
        "channels": prep.channels,
        "import_s": t_import,
        "prepare_s": t_prep,
        "first_frame_s": t_first,
        "frame_ms": t_frame * 1e3,
        "exposure_luminance": float(prep.colour.exposure),
        **stats,
        "files": written,
    }
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f"rendered {w}x{h} ({prep.interreflection.mode}, {prep.colour.spectral_mode}, "
              f"{prep.channels} channels): frame {t_frame * 1e3:.1f} ms (first {t_first:.2f} s, "
              f"prepare {t_prep:.2f} s); coverage {100 * stats['coverage']:.2f} % "
              f"({stats['covered_pixels']} px); out of gamut "
              f"{100 * stats['out_of_gamut_fraction']:.1f} % of object pixels; wrote "
              f"{', '.join(written)}", file=sys.stdout)
    return 0
