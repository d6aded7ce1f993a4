"""Writing a measurement session folder in the documented format (``docs/measurements.md``):
the TOML manifest and one CSV spectrum file per reading, repeat, dark reading and reflectance
(wavelength in nm, then one value column per spectrum, with a ``# unit:`` line).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["toml_value", "write_session"]


def toml_value(v: Any) -> str:
    """``v`` (bool, int, float, str, dict, list / tuple / array of these) as a TOML value."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | np.integer):
        return str(int(v))
    if isinstance(v, float | np.floating):
        return repr(float(v))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, list | tuple | np.ndarray):
        return "[" + ", ".join(toml_value(x) for x in list(np.asarray(v).tolist()
                                                          if isinstance(v, np.ndarray) else v)
                               ) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _spectrum_text(wl: np.ndarray, values: np.ndarray, unit: str, comment: str = "") -> str:
    values = np.atleast_2d(np.asarray(values, np.float64))
    head = [f"# {line}" for line in comment.splitlines() if line] + [f"# unit: {unit}"]
    cols = ["wavelength_nm"] + (["value"] if values.shape[0] == 1 else
                                [f"value_{k + 1}" for k in range(values.shape[0])])
    rows = [",".join(cols)]
    for j, w in enumerate(wl):
        rows.append(",".join([f"{w:g}"] + [f"{v:.12g}" for v in values[:, j]]))
    return "\n".join(head + rows) + "\n"


def _npy_bytes(a: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def write_session(
    folder: str | os.PathLike[str],
    *,
    scene: str,
    wavelengths: Any,
    readings: list[dict[str, Any]],
    instrument: dict[str, Any] | None = None,
    white: dict[str, Any] | None = None,
    dark: Any = None,
    objects: dict[str, dict[str, Any]] | None = None,
    calibration: dict[str, Any] | None = None,
    noise: dict[str, float] | None = None,
    model_error: dict[str, float | str] | None = None,
    level_error: dict[str, float] | None = None,
    tilt_error: dict[str, float] | None = None,
    notes: str = "",
    units: str = "W.sr^-1.m^-2.nm^-1",
    images: list[dict[str, Any]] | None = None,
) -> Path:
    """Write a session folder in the documented format (``docs/measurements.md``).

    Args:
        scene: the scene config's path as written into the manifest (relative to ``folder``).
        wavelengths: (L,) grid of every spectrum given here.
        readings: dicts with ``id``, ``object``, ``aim`` (3,), ``spectra`` (M, L) radiance (one
            file per repeat), and optional ``kind``, ``position``, ``field_angle_deg``,
            ``distance_m``.
        instrument: optional ``position`` and ``field_angle_deg`` defaults.
        white: optional ``reflectance`` (number or (L,)), ``position``, ``normal``,
            ``spectra`` (M, L).
        dark: optional (M, L) dark readings.
        objects: optional per object ``reflectance`` (L,), ``geometry``, ``free``, ``start``.
        model_error: optional ``{kind: relative error of the model, or "auto"}`` (estimated
            by the fit).
        level_error: optional ``{kind: the model's error common to a reading's bands}``, a
            fraction of the reading (``[model_error.level]``); ``tilt_error`` the same for a
            tilt over the bands (``[model_error.tilt]``).
        images: camera photographs: dicts with ``id``, ``pixels`` (H, W) mosaic or (H, W, C)
            counts (written as ``images/<id>.npy``, or a 16-bit ``.png`` with ``format =
            "png"``), ``sensitivities`` (C, L) (written as a
            CSV on ``wavelengths``), ``camera`` ({position, aim, up?, fov_y_deg |
            intrinsics}) and the optional keys of an ``[[images]]`` table (``mosaic``,
            ``exposure_s``, ``black_level``, ``white_level``, ``saturation``,
            ``read_noise``, ``gain``, ``superpixel``, ``samples``, ``objects``).

    Returns:
        the manifest's path. Files are written atomically.
    """
    from .._runtime.fileio import atomic_write_bytes, atomic_write_text

    root = Path(folder)
    wl = np.asarray(wavelengths, np.float64)
    out = ["# Spectroradiometer session (format: docs/measurements.md)", "", "[session]",
           "format = 1", f"scene = {toml_value(scene)}", f"units = {toml_value(units)}"]
    if notes:
        out.append(f"notes = {toml_value(notes)}")
    if instrument:
        out += ["", "[instrument]"] + [f"{k} = {toml_value(v)}" for k, v in instrument.items()]
    if calibration:
        out += ["", "[calibration]"] + [f"{k} = {toml_value(v)}"
                                        for k, v in calibration.items()]
    if noise:
        out += ["", "[noise]"] + [f"{k} = {toml_value(v)}" for k, v in noise.items()]
    if model_error:
        out += ["", "[model_error]"] + [f"{k} = {toml_value(v)}"
                                        for k, v in model_error.items()]
    for part, table in (("level", level_error), ("tilt", tilt_error)):
        if table:
            out += ["", f"[model_error.{part}]"] + [f"{k} = {toml_value(v)}"
                                                     for k, v in table.items()]
    if dark is not None:
        d = np.atleast_2d(dark)
        names = []
        for k, row in enumerate(d):
            name = f"dark/dark_{k + 1}.csv"
            atomic_write_text(root / name, _spectrum_text(wl, row, units, "dark reading"))
            names.append(name)
        out += ["", "[dark]", f"readings = {toml_value(names)}"]
    if white:
        out += ["", "[white_standard]"]
        refl = white["reflectance"]
        if np.ndim(refl) == 0:
            out.append(f"reflectance = {toml_value(float(refl))}")
        else:
            atomic_write_text(root / "white" / "reflectance.csv",
                              _spectrum_text(wl, refl, "1", "white standard reflectance"))
            out.append('reflectance = "white/reflectance.csv"')
        out.append(f"position = {toml_value(list(map(float, white['position'])))}")
        out.append(f"normal = {toml_value(list(map(float, white['normal'])))}")
        names = []
        for k, row in enumerate(np.atleast_2d(white["spectra"])):
            name = f"white/white_{k + 1}.csv"
            atomic_write_text(root / name, _spectrum_text(wl, row, units, "white standard"))
            names.append(name)
        out.append(f"readings = {toml_value(names)}")
    for name, spec in (objects or {}).items():
        out += ["", f"[objects.{name}]"]
        for k, v in spec.items():
            if k == "reflectance":
                fn = f"reflectance/{name}.csv"
                atomic_write_text(root / fn, _spectrum_text(
                    wl, v, "1", f"{name}: spectrophotometer reflectance "
                    f"({spec.get('geometry', 'SCE')})"))
                out.append(f'reflectance = "{fn}"')
            else:
                out.append(f"{k} = {toml_value(v)}")
    for r in readings:
        out += ["", "[[readings]]"]
        files = []
        for k, row in enumerate(np.atleast_2d(r["spectra"])):
            fn = f"readings/{r['id']}_{k + 1}.csv"
            atomic_write_text(root / fn, _spectrum_text(wl, row, units, f"reading {r['id']}"))
            files.append(fn)
        for k in ("id", "object", "kind"):
            if k in r:
                out.append(f"{k} = {toml_value(r[k])}")
        out.append(f"files = {toml_value(files)}")
        for k in ("aim", "position"):
            if k in r:
                out.append(f"{k} = {toml_value([float(x) for x in r[k]])}")
        for k in ("field_angle_deg", "distance_m"):
            if k in r:
                out.append(f"{k} = {toml_value(float(r[k]))}")
    for im in images or []:
        iid = im["id"]
        out += ["", "[[images]]", f"id = {toml_value(iid)}"]
        px = np.asarray(im["pixels"])
        if im.get("format", "npy") == "png":  # 16-bit PNG (integer counts up to 65535)
            import skimage.io

            from .._runtime.fileio import atomic_path

            fn = f"images/{iid}.png"
            with atomic_path(root / fn, suffix=".png") as tmp:
                skimage.io.imsave(tmp, px.astype(np.uint16), check_contrast=False)
        else:
            fn = f"images/{iid}.npy"
            atomic_write_bytes(root / fn, _npy_bytes(px))
        out.append(f"file = {toml_value(fn)}")
        sn = f"images/{iid}_sensitivities.csv"
        atomic_write_text(root / sn, _spectrum_text(
            wl, im["sensitivities"], "counts/s per W.sr^-1.m^-2.nm^-1 per nm",
            f"camera sensitivities of image {iid} (R, G, B)"))
        out.append(f"sensitivities = {toml_value(sn)}")
        for k in ("mosaic", "exposure_s", "black_level", "white_level", "saturation",
                  "read_noise", "gain", "superpixel", "samples", "objects"):
            if k in im:
                out.append(f"{k} = {toml_value(im[k])}")
        cam = {k: (list(map(float, v)) if k != "fov_y_deg" else float(v))
               for k, v in im["camera"].items()}
        out.append(f"camera = {toml_value(cam)}")
    manifest = root / "session.toml"
    atomic_write_text(manifest, "\n".join(out) + "\n")
    return manifest
