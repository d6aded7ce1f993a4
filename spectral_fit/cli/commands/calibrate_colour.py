"""``spectral-fit calibrate-colour``: the video camera's colour model from a ColorChecker shot."""

from __future__ import annotations

import argparse
import json
import sys

HELP = ("fit the video camera's colour model (3x3 matrix, white balance, tone curve) from a "
        "ColorChecker in a frame and write it into a copy of a scene config ([camera_colour])")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("image", help="frame showing the chart (an image file, or a video with "
                   "--frame)")
    p.add_argument("--config", required=True, help="scene config (TOML) whose environment "
                   "lights the chart (the chart lies on the table, facing world +Y)")
    p.add_argument("--corners", required=True,
                   help="the chart's outer patch corners in pixels, top-left, top-right, "
                   "bottom-right, bottom-left (dark skin at the top-left): "
                   "'x1,y1 x2,y2 x3,y3 x4,y4'")
    p.add_argument("--frame", type=int, default=0, help="video input: frame index (from 0)")
    p.add_argument("--chart", default="BabelColor Average",
                   help="colour-science ColorChecker reflectances (default: BabelColor "
                   "Average)")
    p.add_argument("--tone", default="srgb", choices=("srgb", "gamma", "linear", "fit"),
                   help="the frame's tone curve; 'fit': a gamma curve fitted on the neutral "
                   "patches")
    p.add_argument("--gamma", type=float, default=2.2, help="exponent for --tone gamma")
    p.add_argument("-o", "--output", default=None,
                   help="config to write (default: <config>.colour.toml next to it)")
    p.add_argument("--overwrite", action="store_true", help="replace --output if it exists")
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")


def _corners(text: str):
    import numpy as np

    from ..._runtime.errors import InputError

    try:
        vals = [float(x) for x in text.replace(",", " ").replace(";", " ").split()]
    except ValueError:
        raise InputError(f"use 'x1,y1 x2,y2 x3,y3 x4,y4', got {text!r}",
                         field="--corners") from None
    if len(vals) != 8:
        raise InputError(f"need 4 corners (8 numbers), got {len(vals)} numbers",
                         field="--corners")
    return np.asarray(vals).reshape(4, 2)


def _image(path: str, frame: int):
    import cv2

    from ..._runtime.errors import InputError
    from ...live import VideoSource

    if path.lower().endswith((".mp4", ".avi", ".mov", ".mkv", ".m4v")):
        if frame < 0:
            raise InputError("must be >= 0", field="--frame")
        with VideoSource(path, field="image") as src:
            for i, f in enumerate(src):
                if i == frame:
                    return f
        raise InputError(f"the video has no frame {frame}", path=path, field="--frame")
    img = cv2.imread(path, cv2.IMREAD_COLOR)
    if img is None:
        raise InputError("cannot read image (missing or not an image)", path=path,
                         field="image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def run(args: argparse.Namespace) -> int:
    import colour

    from ..._runtime.errors import InputError
    from ...io import load_scene
    from ...live import calibrate_colour, chart_xyz, write_colour_config

    if args.chart not in colour.SDS_COLOURCHECKERS:
        raise InputError(f"unknown chart {args.chart!r}; known: "
                         f"{sorted(colour.SDS_COLOURCHECKERS)}", field="--chart")
    if not 0.1 <= args.gamma <= 10:
        raise InputError("must be in [0.1, 10]", field="--gamma")
    corners = _corners(args.corners)
    scene = load_scene(args.config)
    image = _image(args.image, args.frame)
    xyz, white = chart_xyz(scene, chart=args.chart)
    cal = calibrate_colour(image, corners, xyz, white, tone=args.tone, gamma=args.gamma)
    dest = write_colour_config(args.config, cal, args.output, overwrite=args.overwrite,
                               note=f"{args.chart}, {args.image}")
    de = cal.delta_e00[cal.used]
    result = {"output": str(dest), "matrix": cal.matrix.tolist(),
              "white_balance": cal.white_balance.tolist(), "tone": cal.tone,
              "gamma": cal.gamma, "patches_used": int(cal.used.sum()),
              "delta_e00_mean": float(de.mean()), "delta_e00_max": float(de.max()),
              "delta_e00": cal.delta_e00.tolist()}
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(f"calibrate-colour: {int(cal.used.sum())}/24 patches; reproduction ΔE00 mean "
              f"{de.mean():.2f}, max {de.max():.2f}; tone {cal.tone}"
              + (f" (gamma {cal.gamma:.3f})" if cal.tone == "gamma" else ""),
              file=sys.stderr)
        print(f"wrote {dest}")
    return 0
