"""The mixed-reality pipeline scored end to end against a ground truth.

A ground truth (``scripts/make_mr_ground_truth.py``) is a folder holding ``truth.json``, the
noise-free frames with the objects ``frame_NNN.png`` and ``masks.npz`` (per frame
``object_id`` (F, H, W) int8: object index on pixels the objects cover fully, −2 on partly
covered ones, −1 elsewhere; ``near`` (F, H, W) bool: table pixels near the objects); the
``truth.json`` names the "real" video without the objects, its true poses and the config
(paths relative to the folder).

:func:`score_mr` runs the live pipeline on the real video as ``spectral-fit live`` does (the
colour from the config's ``[colour_chart]`` in the video when it has one, markers, render,
composite) and compares each composited frame with the truth:

* colour: CIEDE2000 per pixel (colour-science), both frames decoded as sRGB, on the object
  pixels and on the table near the objects (their contact shadows included); per frame the
  median, p90 and mean, and over the frames the median and p90 of the per-frame medians;
* the same on the means of 5 × 5-pixel patches (:data:`PATCH`) lying wholly in each region
  (as ``spectral-fit validate`` scores): the path tracer's per-pixel noise in the truth, and
  the video's, mostly average out there;
* the bias: the composite's mean linear RGB over each region divided by the truth's
  (``linear_ratio``; 1 = the same level), which the per-pixel noise does not blur;
* the same against the truth written with the video's own encoder and read back
  (``codec_matched``): OpenCV's MPEG-4 round trip shifts the level (about −2.5 of 255 on the
  table) and the chart calibration carries that shift into the CG, as it should for a
  composite that must match its video; this comparison leaves the codec's share out;
* the floor: the same on the rest of the frame ("far": table, markers and chart away from the
  objects), where the pipeline passes the video's pixels through and the truth is their
  noise-free, uncompressed source: what the video's own sensor noise and compression cost;
* markers: each marker's pose (the session's detector) against the true pose, translation
  error (mm) and rotation error (degrees; the angle of R_estᵀ R_true).

The CG is composited with ``[camera] noise`` set to 0 for scoring: the grain the pipeline adds
to the CG to match the video would count as error against a noise-free truth (the video's own
noise stays in the table pixels).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from .._runtime.errors import InputError

__all__ = ["MR_TARGETS", "PATCH", "score_mr", "mr_figure", "pose_errors", "patch_delta_e00"]

#: side (px) of the square patches of the second colour figure (as ``spectral-fit validate``
#: scores 5×5-pixel patch means): the path tracer's per-pixel noise averages out over a patch
PATCH = 5

#: the targets: median over frames of the per-frame median ΔE00 on objects and on the table
#: near them, p90 over frames of the latter, marker translation (mm) and rotation (degrees)
MR_TARGETS = {"objects_median": 1.0, "near_median": 1.0, "near_p90_over_frames": 2.0,
              "translation_mm": 1.0, "rotation_deg": 0.5}


def pose_errors(r_est, t_est, r_true, t_true) -> tuple[float, float]:
    """(translation error in mm, rotation error in degrees) of an OpenCV pose (R (3, 3),
    t (3,) m) against the true one."""
    dt = 1e3 * float(np.linalg.norm(np.asarray(t_est, np.float64).reshape(3)
                                    - np.asarray(t_true, np.float64).reshape(3)))
    r = np.asarray(r_est, np.float64).T @ np.asarray(r_true, np.float64)
    c = np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)
    return dt, math.degrees(math.acos(c))


def patch_delta_e00(a: np.ndarray, b: np.ndarray, mask: np.ndarray, size: int = PATCH
                    ) -> np.ndarray:
    """CIEDE2000 (N,) between the means, in linear light, of two sRGB-encoded frames ``a``
    and ``b`` ((H, W, 3) uint8) over the ``size`` × ``size`` squares of the frame's grid that
    ``mask`` ((H, W) bool) covers entirely (D65 white, colour-science)."""
    import colour

    h, w = mask.shape
    ny, nx = h // size, w // size

    def means(img: np.ndarray) -> np.ndarray:
        lin = colour.cctf_decoding(np.asarray(img, np.float64)[:ny * size, :nx * size] / 255.0,
                                   function="sRGB")
        return lin.reshape(ny, size, nx, size, 3).mean(axis=(1, 3))

    full = mask[:ny * size, :nx * size].reshape(ny, size, nx, size).all(axis=(1, 3))
    if not full.any():
        return np.zeros(0)
    wxy = colour.RGB_COLOURSPACES["sRGB"].whitepoint

    def lab(lin: np.ndarray) -> np.ndarray:
        return colour.XYZ_to_Lab(colour.RGB_to_XYZ(lin, "sRGB"), wxy)

    return np.asarray(colour.delta_E(lab(means(a)[full]), lab(means(b)[full]),
                                     method="CIE 2000"))


def _through_codec(folder: Path, n: int, size: tuple[int, int], suffix: str,
                   fps: float | None) -> list[np.ndarray]:
    """The first ``n`` truth frames written with the video's encoder (:class:`VideoSink`, by
    the video's suffix) and read back: the truth as that codec delivers it (its level shift
    and artefacts included)."""
    import tempfile

    from ._video import VideoSink, VideoSource

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"truth{suffix or '.mp4'}"
        with VideoSink(path, fps=fps or 25.0, size=size) as sink:
            for i in range(n):
                sink.write(_truth_frame(folder, i, size))
        with VideoSource(path, field="truth video") as back:
            return [f for _, f in zip(range(n), back, strict=False)]


def _linear_ratio(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> list[float] | None:
    """(3,) mean linear RGB of sRGB frame ``a`` over ``mask`` divided by ``b``'s (a bias
    check beside the ΔE00: 1 = the same level), None for an empty mask."""
    import colour

    if not mask.any():
        return None
    la = colour.cctf_decoding(np.asarray(a, np.float64)[mask] / 255.0, function="sRGB")
    lb = colour.cctf_decoding(np.asarray(b, np.float64)[mask] / 255.0, function="sRGB")
    return (la.mean(0) / np.maximum(lb.mean(0), 1e-9)).tolist()


def _stats(v: np.ndarray) -> dict[str, float | int]:
    v = np.asarray(v, np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"n": 0}
    return {"n": int(v.size), "median": float(np.median(v)),
            "p90": float(np.percentile(v, 90)), "mean": float(v.mean()),
            "max": float(v.max())}


def _read_truth(folder: Path) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
    meta_path = folder / "truth.json"
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputError(f"cannot read ({exc.strerror or exc})", path=meta_path) from None
    except json.JSONDecodeError as exc:
        raise InputError(f"not JSON: {exc}", path=meta_path) from None
    for key in ("config", "video", "poses", "frames"):
        if key not in meta:
            raise InputError("required key is missing", path=meta_path, field=key)
    masks = folder / "masks.npz"
    try:
        with np.load(masks) as z:
            oid, near = np.asarray(z["object_id"]), np.asarray(z["near"], bool)
    except (OSError, KeyError, ValueError) as exc:
        raise InputError(f"cannot read object_id / near ({exc})", path=masks) from None
    if oid.shape != near.shape or oid.ndim != 3:
        raise InputError(f"object_id {oid.shape} and near {near.shape} must be (F, H, W)",
                         path=masks)
    return meta, oid, near


def _truth_frame(folder: Path, i: int, shape: tuple[int, int]) -> np.ndarray:
    import cv2

    p = folder / f"frame_{i:03d}.png"
    img = cv2.imread(str(p), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError("missing or not an image", path=p, field="truth frame")
    if img.shape[:2] != shape:
        raise InputError(f"is {img.shape[1]}x{img.shape[0]}, the video "
                         f"{shape[1]}x{shape[0]}", path=p, field="truth frame")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def score_mr(truth: str | Path, *, config: str | Path | None = None,
             max_frames: int | None = None, picture_frame: int | None = None,
             out: str | Path | None = None, session_options: dict[str, Any] | None = None
             ) -> dict[str, Any]:
    """Run the live pipeline on the ground truth's real video and score it (module
    docstring).

    Args:
        truth: the ground-truth folder (``truth.json``, ``frame_NNN.png``, ``masks.npz``).
        config: the scene config (default: the one ``truth.json`` names).
        max_frames: score only the first frames.
        picture_frame: frame of the side-by-side picture (default: the middle one).
        out: folder for ``mr_score.json`` and ``mr_score.png`` (nothing written when None).
        session_options: further keyword arguments of :class:`LiveSession`.

    Returns the result dict (also ``mr_score.json``): ``frames`` (per frame: ΔE00 statistics
    on ``objects`` and ``near``, marker pose errors), ``summary`` (over frames, with the
    targets), ``colour`` (the chart calibration), ``seconds``.
    """
    from ..io import load_scene
    from ._chart_video import chart_camera_model
    from ._compositing import frame_delta_e00
    from ._markers import MarkerDetector
    from ._scene_camera import scene_camera_model, scene_intrinsics
    from ._session import LiveSession
    from ._video import VideoSource

    t_start = time.perf_counter()
    folder = Path(truth)
    meta, oid, near = _read_truth(folder)
    cfg = Path(config) if config is not None else (folder / meta["config"]).resolve()
    scene = load_scene(cfg)
    scene = scene.replace(camera=dataclasses.replace(scene.camera, noise=0.0))
    video = (folder / meta["video"]).resolve()
    poses_path = (folder / meta["poses"]).resolve()
    try:
        poses = json.loads(poses_path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"cannot read the true poses ({exc})", path=poses_path) from None
    n = min(int(meta["frames"]), oid.shape[0], len(poses["frames"]))
    if max_frames is not None:
        if max_frames < 1:
            raise InputError("must be >= 1", field="--max-frames")
        n = min(n, int(max_frames))
    with VideoSource(video, field="video") as src:
        size = (src.height, src.width)
        if size != oid.shape[1:]:
            raise InputError(f"the video is {size[1]}x{size[0]}, the masks "
                             f"{oid.shape[2]}x{oid.shape[1]}", path=folder / "masks.npz")
        k, dist = scene_intrinsics(scene, size)
        chart = None
        if scene.colour_chart is not None:
            with VideoSource(video, field="video") as again:
                chart = chart_camera_model(scene, again, k=k, dist=dist, source=str(video))
            camera = chart.model
        else:
            camera = scene_camera_model(scene)
        session = LiveSession(scene, size=size, camera=camera, **(session_options or {}))
        detector = MarkerDetector(scene.markers, k, dist,
                                  expect={int(m[0]) for m in poses.get("markers", [])})
        per_frame: list[dict[str, Any]] = []
        keep: dict[str, np.ndarray] = {}
        pick = n // 2 if picture_frame is None else int(picture_frame)
        if not 0 <= pick < n:
            raise InputError(f"must be in [0, {n - 1}], got {pick}", field="--frame")
        coded = _through_codec(folder, n, size, video.suffix, src.fps)
        t_live = time.perf_counter()
        for i, frame in enumerate(src):
            if i >= n:
                break
            comp = session.process(frame)
            ref = _truth_frame(folder, i, size)
            de = frame_delta_e00(comp / 255.0, ref / 255.0, tone="srgb")
            obj = oid[i] >= 0
            far = (oid[i] == -1) & ~near[i]
            rec: dict[str, Any] = {"frame": i, "objects": _stats(de[obj]),
                                   "near": _stats(de[near[i]]), "far": _stats(de[far]),
                                   **{f"{k}_{PATCH}x{PATCH}": _stats(patch_delta_e00(
                                       comp, ref, m)) for k, m in (("objects", obj),
                                                                   ("near", near[i]),
                                                                   ("far", far))},
                                   "visible": np.asarray(session.last_poses.visible).tolist(),
                                   "markers": {}}
            dets = detector.detect(frame)
            for mid, true in poses["frames"][i]["markers"].items():
                d = dets.get(int(mid))
                if d is None:
                    rec["markers"][mid] = None
                    continue
                dt, dr = pose_errors(d.rotation, d.translation, true["R"], true["t"])
                rec["markers"][mid] = {"translation_mm": dt, "rotation_deg": dr,
                                       "distance_m": float(np.linalg.norm(true["t"]))}
            rec["linear_ratio"] = {k: _linear_ratio(comp, ref, m)
                                   for k, m in (("objects", obj), ("near", near[i]))}
            dc = frame_delta_e00(comp / 255.0, coded[i] / 255.0, tone="srgb")
            rec["codec_matched"] = {
                "objects": _stats(dc[obj]), "near": _stats(dc[near[i]]),
                **{f"{k}_{PATCH}x{PATCH}": _stats(patch_delta_e00(comp, coded[i], m))
                   for k, m in (("objects", obj), ("near", near[i]))},
                "linear_ratio": {k: _linear_ratio(comp, coded[i], m)
                                 for k, m in (("objects", obj), ("near", near[i]))}}
            per_frame.append(rec)
            if i == pick:
                keep = {"composite": comp, "truth": ref, "de": de, "objects": obj,
                        "near": near[i]}
        live_s = time.perf_counter() - t_live
    if len(per_frame) < n:
        raise InputError(f"the video has {len(per_frame)} frames, the truth {n}", path=video)
    summary = _summary(per_frame)
    result: dict[str, Any] = {
        "truth": str(folder), "config": str(cfg), "video": str(video), "frames_scored": n,
        "summary": summary, "targets": MR_TARGETS,
        "meets_targets": {
            "objects_median": summary["objects"].get("median_of_medians", math.inf)
            <= MR_TARGETS["objects_median"],
            "near_median": summary["near"].get("median_of_medians", math.inf)
            <= MR_TARGETS["near_median"],
            "near_p90_over_frames": summary["near"].get("p90_of_medians", math.inf)
            <= MR_TARGETS["near_p90_over_frames"],
            "translation_mm": summary["markers"].get("translation_mm", {}).get(
                "max", math.inf) <= MR_TARGETS["translation_mm"],
            "rotation_deg": summary["markers"].get("rotation_deg", {}).get(
                "max", math.inf) <= MR_TARGETS["rotation_deg"]},
        "meets_targets_patches": {
            f"{key}_{PATCH}x{PATCH}": summary[f"{region}_{PATCH}x{PATCH}"].get(
                stat, math.inf) <= MR_TARGETS[key]
            for key, region, stat in (("objects_median", "objects", "median_of_medians"),
                                      ("near_median", "near", "median_of_medians"),
                                      ("near_p90_over_frames", "near", "p90_of_medians"))},
        "colour": _chart_json(chart),
        "picture_frame": pick,
        "seconds": {"live": round(live_s, 2), "total": round(time.perf_counter() - t_start, 2)},
        "frames": per_frame,
    }
    if out is not None:
        from .._runtime.fileio import atomic_write_text

        dest = Path(out)
        dest.mkdir(parents=True, exist_ok=True)
        mr_figure(dest / "mr_score.png", keep, pick, per_frame[pick])
        result["picture"] = str(dest / "mr_score.png")
        atomic_write_text(dest / "mr_score.json", json.dumps(result, indent=2) + "\n")
    return result


def _summary(per_frame: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for region in ("objects", "near", "far",
                   *(f"{r}_{PATCH}x{PATCH}" for r in ("objects", "near", "far"))):
        med = np.array([f[region].get("median", np.nan) for f in per_frame])
        ok = np.isfinite(med)
        out[region] = ({"frames": int(ok.sum()), "median_of_medians": float(np.median(med[ok])),
                        "p90_of_medians": float(np.percentile(med[ok], 90)),
                        "max_of_medians": float(med[ok].max()),
                        "median_of_p90s": float(np.median(
                            [f[region]["p90"] for f in per_frame if f[region].get("n")]))}
                       if ok.any() else {"frames": 0})
    for region in ("objects", "near"):
        r = [f["linear_ratio"][region] for f in per_frame if f["linear_ratio"][region]]
        if r:
            out[region]["linear_ratio_median"] = np.median(np.asarray(r), axis=0).tolist()
    cm: dict[str, Any] = {}
    for region in ("objects", "near", f"objects_{PATCH}x{PATCH}", f"near_{PATCH}x{PATCH}"):
        med = np.array([f["codec_matched"][region].get("median", np.nan) for f in per_frame])
        ok = np.isfinite(med)
        cm[region] = ({"median_of_medians": float(np.median(med[ok])),
                       "p90_of_medians": float(np.percentile(med[ok], 90))}
                      if ok.any() else {"frames": 0})
    for region in ("objects", "near"):
        r = [f["codec_matched"]["linear_ratio"][region] for f in per_frame
             if f["codec_matched"]["linear_ratio"][region]]
        if r:
            cm[region]["linear_ratio_median"] = np.median(np.asarray(r), axis=0).tolist()
    out["codec_matched"] = cm
    dts, drs, missed = [], [], 0
    for f in per_frame:
        for v in f["markers"].values():
            if v is None:
                missed += 1
            else:
                dts.append(v["translation_mm"])
                drs.append(v["rotation_deg"])
    out["markers"] = {"detections": len(dts), "missed": missed,
                      "translation_mm": _stats(np.array(dts)),
                      "rotation_deg": _stats(np.array(drs))}
    return out


def _chart_json(chart: Any) -> dict[str, Any] | str:
    if chart is None:
        return "no [colour_chart]: the config's camera colour"
    cal = chart.calibration
    return {"frames": list(chart.frames), "patches_used": int(cal.used.sum()),
            "reproduction_delta_e00_mean": float(cal.delta_e00[cal.used].mean()),
            "reproduction_delta_e00_max": float(cal.delta_e00[cal.used].max()),
            "matrix": np.asarray(cal.matrix).tolist(),
            "white_balance": np.asarray(cal.white_balance).tolist(),
            "tone": cal.tone, "gamma": cal.gamma,
            "patch_spread_over_frames_max": float(np.max(chart.spread))}


def mr_figure(path: str | Path, keep: dict[str, np.ndarray], frame: int,
              rec: dict[str, Any], *, vmax: float = 3.0) -> None:
    """Side-by-side picture of one frame: the composite | the ground truth | the ΔE00 per
    pixel in false colour (0 … ``vmax``) on the object pixels and the table near them (the
    rest grey)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .._runtime.fileio import atomic_path

    de = np.where(keep["objects"] | keep["near"], keep["de"], np.nan)
    h, w = de.shape
    fig, axes = plt.subplots(1, 3, figsize=(3 * w / 80 + 1.0, h / 80 + 0.8))
    axes[0].imshow(keep["composite"])
    axes[0].set_title(f"live composite, frame {frame}", fontsize=8)
    axes[1].imshow(keep["truth"])
    axes[1].set_title("ground truth (path traced, noise-free)", fontsize=8)
    axes[2].imshow(keep["truth"].mean(-1), cmap="gray", vmin=0, vmax=255 * 1.6)
    cmap = plt.get_cmap("inferno").with_extremes(bad=(0, 0, 0, 0))
    im = axes[2].imshow(np.ma.masked_invalid(de), cmap=cmap, vmin=0, vmax=vmax,
                        interpolation="nearest")
    o, nr = rec["objects"], rec["near"]
    axes[2].set_title(f"ΔE00: objects median {o.get('median', float('nan')):.2f}, "
                      f"table near {nr.get('median', float('nan')):.2f}", fontsize=8)
    fig.colorbar(im, ax=axes[2], fraction=0.03, label="ΔE00")
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
