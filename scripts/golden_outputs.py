"""Golden outputs of the user-level commands, to check that a refactoring changes no result.

    python scripts/golden_outputs.py write DIR      # run everything, store the outputs in DIR
    python scripts/golden_outputs.py compare DIR  # run again, compare; exit 1 on a change

It runs the installed ``spectral-fit`` command only (never the package's modules directly), so
that the same script works before and after modules move:

* ``render`` of every config in ``configs/`` in each interreflection mode (gather, paper, none)
  and both spectral modes, at 96 x 64, as absolute CIE XYZ (EXR) and display PNG;
* ``fit`` of the bundled demo session (one start, no hold-out, no render): the fitted parameters;
* ``live`` on the first 3 frames of the sample video: the frames of the output video;
* ``bench --list``: the benchmark case names.

Frames are compared to a relative tolerance of 1e-5 of each image's peak (the compiled programs
may be scheduled differently after a move), fitted parameters to 1e-5 relative, the rest
exactly.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SIZE = "96x64"
MODES = ("gather", "paper", "none")
SPECTRAL = ("bands", "basis")


def _run(args: list[str], cwd: Path, *, may_fail: bool = False) -> str | None:
    """stdout of ``spectral-fit ARGS``; on an error exit its last line of stderr prefixed by
    'error: ' where ``may_fail`` (an error is an output too: it must stay the same)."""
    r = subprocess.run(["spectral-fit", *args], cwd=cwd, capture_output=True, text=True)
    if r.returncode != 0:
        if may_fail:
            return "error: " + r.stderr.strip().splitlines()[-1]
        sys.exit(f"spectral-fit {' '.join(args)} failed:\n{r.stderr[-3000:]}")
    return r.stdout


def _read_exr(path: Path) -> np.ndarray:
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        ch = f.channels()
        return np.stack([np.asarray(ch[k].pixels, np.float64) for k in ("X", "Y", "Z")], -1)


def _read_png(path: Path) -> np.ndarray:
    from skimage.io import imread

    return np.asarray(imread(path), np.float64)


def _video_frames(path: Path) -> np.ndarray:
    import cv2

    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        frames.append(img)
    cap.release()
    return np.asarray(frames, np.float64)


def produce(out: Path) -> dict[str, object]:
    """Run every command into ``out``; return {name: array or JSON-able value}."""
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, object] = {}
    for config in sorted((ROOT / "configs").glob("*.toml")):
        for mode in MODES:
            for spectral in SPECTRAL:
                name = f"render_{config.stem}_{mode}_{spectral}"
                exr, png = out / f"{name}.exr", out / f"{name}.png"
                out_text = _run(["render", str(config), "-o", str(png), "--xyz-exr", str(exr),
                                 "--size", SIZE, "--mode", mode, "--spectral-mode", spectral],
                                cwd=ROOT, may_fail=True)
                if out_text is not None and out_text.startswith("error: "):
                    results[name + "_error"] = out_text
                    continue
                results[name + "_xyz"] = _read_exr(exr)
                results[name + "_png"] = _read_png(png)
    fit_dir = out / "fit"
    text = _run(["fit", "configs/two_spheres.toml", "measurements/sessions/two_spheres_demo",
                 "-o", str(fit_dir), "--json", "--starts", "1", "--no-holdout", "--no-render"],
                cwd=ROOT)
    params = json.loads(text)["params"]
    results["fit_params"] = {o: {k: float(v) for k, v in p.items()} for o, p in params.items()}
    clip = out / "live.avi"
    _run(["live", "configs/live_sample.toml", "--video", "measurements/video/sample.mp4",
          "--max-frames", "3", "-o", str(clip), "--quiet"], cwd=ROOT)
    results["live_frames"] = _video_frames(clip)
    results["bench_cases"] = _run(["bench", "--list"], cwd=ROOT).split()
    return results


def _save(results: dict[str, object], folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    arrays = {k: v for k, v in results.items() if isinstance(v, np.ndarray)}
    np.savez_compressed(folder / "arrays.npz", **{k: v.astype(np.float32)
                                                  for k, v in arrays.items()})
    rest = {k: v for k, v in results.items() if not isinstance(v, np.ndarray)}
    (folder / "values.json").write_text(json.dumps(rest, indent=1, sort_keys=True) + "\n")


def _compare(results: dict[str, object], folder: Path) -> list[str]:
    problems = []
    with np.load(folder / "arrays.npz") as z:
        stored = {k: z[k] for k in z.files}
    for k in sorted(set(stored) | {k for k, v in results.items() if isinstance(v, np.ndarray)}):
        a, b = stored.get(k), results.get(k)
        if a is None or b is None:
            problems.append(f"{k}: only in {'the goldens' if b is None else 'this run'}")
            continue
        b = np.asarray(b, np.float32)
        if a.shape != b.shape:
            problems.append(f"{k}: shape {b.shape} != golden {a.shape}")
            continue
        diff = float(np.max(np.abs(a.astype(np.float64) - b))) if a.size else 0.0
        peak = float(np.max(np.abs(a))) if a.size else 0.0
        if diff > 1e-5 * max(peak, 1e-30):
            problems.append(f"{k}: max |difference| {diff:.3g} (peak {peak:.3g})")
    values = json.loads((folder / "values.json").read_text())
    for k in sorted({k for k in values if k.endswith("_error")}
                    | {k for k in results if k.endswith("_error")}):
        if values.get(k) != results.get(k):
            problems.append(f"{k}: {results.get(k)!r} != golden {values.get(k)!r}")
    if values.get("bench_cases") != results["bench_cases"]:
        problems.append(f"bench_cases: {results['bench_cases']} != {values.get('bench_cases')}")
    for obj, p in values["fit_params"].items():
        for k, v in p.items():
            got = results["fit_params"].get(obj, {}).get(k)
            if got is None or abs(got - v) > 1e-5 * max(abs(v), 1e-6):
                problems.append(f"fit_params[{obj}][{k}]: {got} != {v}")
    return problems


def main(argv: list[str]) -> int:
    if len(argv) != 2 or argv[0] not in ("write", "compare"):
        print(__doc__)
        return 2
    what, folder = argv[0], Path(argv[1])
    with tempfile.TemporaryDirectory() as tmp:
        results = produce(Path(tmp))
    if what == "write":
        if folder.exists():
            shutil.rmtree(folder)
        _save(results, folder)
        print(f"wrote {len(results)} goldens to {folder}")
        return 0
    problems = _compare(results, folder)
    for p in problems:
        print(p)
    print(f"{len(results)} outputs compared, {len(problems)} changed")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
