"""``spectral-fit calibrate``: camera intrinsics and distortion from target images."""

from __future__ import annotations

import argparse
import json
import sys

HELP = ("calibrate a camera from ChArUco/chessboard images and write intrinsics + distortion "
        "into a copy of a scene config")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("images", nargs="+", help="images of the target (any format OpenCV reads), "
                   "or one video file (every --every'th frame is used)")
    p.add_argument("--config", required=True, help="scene config (TOML) to copy the result into")
    p.add_argument("-o", "--output", default=None,
                   help="calibrated config to write (default: <config>.calibrated.toml next to "
                   "it); an existing file is kept unless --overwrite")
    p.add_argument("--overwrite", action="store_true", help="replace --output if it exists")
    p.add_argument("--target", default="charuco", choices=("charuco", "chessboard"))
    p.add_argument("--squares", default="7x5", help="squares COLSxROWS (default 7x5)")
    p.add_argument("--square-size", type=float, default=0.03, help="square side, m")
    p.add_argument("--marker-size", type=float, default=0.022, help="ChArUco marker side, m")
    p.add_argument("--dictionary", default="DICT_5X5_100", help="ChArUco marker dictionary")
    p.add_argument("--every", type=int, default=10, help="video input: use every Nth frame")
    p.add_argument("--k3", action="store_true", help="also fit k3 (default: fixed at 0)")
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")


def _squares(text: str) -> tuple[int, int]:
    from ..._runtime.errors import InputError

    try:
        c, r = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise InputError(f"use COLSxROWS, e.g. 7x5, got {text!r}", field="--squares") from None
    return c, r


def _load_images(paths: list[str], every: int) -> list:
    import cv2

    from ..._runtime.errors import InputError
    from ...live import VideoSource

    if len(paths) == 1 and paths[0].lower().endswith((".mp4", ".avi", ".mov", ".mkv", ".m4v")):
        if every < 1:
            raise InputError("must be >= 1", field="--every")
        with VideoSource(paths[0], field="images") as src:
            return [f for i, f in enumerate(src) if i % every == 0]
    out = []
    for p in paths:
        img = cv2.imread(p, cv2.IMREAD_COLOR)
        if img is None:
            raise InputError("cannot read image (missing or not an image)", path=p,
                             field="images")
        out.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
    return out


def run(args: argparse.Namespace) -> int:
    from ...live import CalibrationTarget, calibrate_images, write_calibrated_config

    target = CalibrationTarget(kind=args.target, squares=_squares(args.squares),
                               square_size=args.square_size, marker_size=args.marker_size,
                               dictionary=args.dictionary)
    images = _load_images(args.images, args.every)
    cal = calibrate_images(images, target, fix_k3=not args.k3)
    dest = write_calibrated_config(args.config, cal, args.output, overwrite=args.overwrite)
    result = {"output": str(dest), "intrinsics": cal.intrinsics(),
              "distortion": cal.dist.tolist(), "rms_px": cal.rms_px, "views": cal.views,
              "images": len(images), "image_size": list(cal.image_size)}
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        i = cal.intrinsics()
        print(f"calibrate: target found in {cal.views}/{len(images)} images; RMS "
              f"{cal.rms_px:.3f} px", file=sys.stderr)
        print(f"fx {i['fx']:.2f}  fy {i['fy']:.2f}  cx {i['cx']:.2f}  cy {i['cy']:.2f}  "
              f"dist {', '.join(f'{x:.5f}' for x in cal.dist)}")
        print(f"wrote {dest}")
    return 0
