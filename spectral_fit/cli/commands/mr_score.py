"""``spectral-fit mr-score``: the live pipeline scored end to end against a ground truth."""

from __future__ import annotations

import argparse
import json
import sys

HELP = ("run the live pipeline on a ground truth's real video and score it against the "
        "path-traced frames (ΔE00 on the objects and the table near them, marker poses)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("truth", nargs="?", default="measurements/video/room_truth",
                   help="ground-truth folder (truth.json, frame_NNN.png, masks.npz; default "
                   "measurements/video/room_truth, made by scripts/make_mr_ground_truth.py)")
    p.add_argument("--config", default=None,
                   help="scene config (default: the one truth.json names)")
    p.add_argument("--max-frames", type=int, default=None, help="score the first N frames")
    p.add_argument("--frame", type=int, default=None,
                   help="frame of the side-by-side picture (default: the middle one)")
    p.add_argument("-o", "--out", default="out/mr_score",
                   help="folder for mr_score.json and mr_score.png (default out/mr_score)")
    p.add_argument("--json", action="store_true", help="print the result JSON on stdout")


def run(args: argparse.Namespace) -> int:
    from ...rendering import enable_compilation_cache

    enable_compilation_cache(min_compile_time_s=1.0)
    from ...live import score_mr

    res = score_mr(args.truth, config=args.config, max_frames=args.max_frames,
                   picture_frame=args.frame, out=args.out)
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    s = res["summary"]
    from ...live import PATCH

    p = f"_{PATCH}x{PATCH}"
    for region, label in (("objects", "objects"), ("near", "table near the objects"),
                          ("far", "rest of the frame (the video's own noise and compression)"),
                          ("objects" + p, f"objects, {PATCH}×{PATCH} patch means"),
                          ("near" + p, f"table near the objects, {PATCH}×{PATCH} patch means"),
                          ("far" + p, f"rest of the frame, {PATCH}×{PATCH} patch means")):
        r = s[region]
        if r.get("frames"):
            print(f"ΔE00 {label}: per-frame median, over {r['frames']} frames: median "
                  f"{r['median_of_medians']:.2f}, p90 {r['p90_of_medians']:.2f}, max "
                  f"{r['max_of_medians']:.2f}")
    for region in ("objects", "near"):
        lr = s[region].get("linear_ratio_median")
        if lr:
            print(f"mean linear RGB composite / truth, {region} (median over frames): "
                  + ", ".join(f"{x:.3f}" for x in lr))
    cm = s["codec_matched"]
    for region in ("objects", "near"):
        a, b = cm[region], cm[f"{region}{p}"]
        if "median_of_medians" in a:
            print(f"against the truth through the video's codec, {region}: per pixel "
                  f"{a['median_of_medians']:.2f} (p90 over frames {a['p90_of_medians']:.2f}), "
                  f"{PATCH}×{PATCH} patches {b['median_of_medians']:.2f} "
                  f"({b['p90_of_medians']:.2f}); linear ratio "
                  + ", ".join(f"{x:.3f}" for x in a.get("linear_ratio_median", [])))
    m = s["markers"]
    if m["detections"]:
        t, r = m["translation_mm"], m["rotation_deg"]
        print(f"marker poses ({m['detections']} detections, {m['missed']} missed): "
              f"translation median {t['median']:.2f} mm, max {t['max']:.2f} mm; rotation "
              f"median {r['median']:.2f}°, max {r['max']:.2f}°")
    for key, ok in res["meets_targets"].items():
        print(f"target {key} <= {res['targets'][key]:g}: {'met' if ok else 'NOT met'}")
    for key, ok in res["meets_targets_patches"].items():
        print(f"target {key} <= {res['targets'][key.removesuffix(p)]:g}: "
              f"{'met' if ok else 'NOT met'}")
    print(f"wrote {args.out}/mr_score.json, {res.get('picture')}", file=sys.stderr)
    return 0
