"""Shared helpers of the renderer tests: a small two-sphere scene under a mirror-symmetric
environment (the benchmark map averaged with its mirror image u → 1 − u)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from helpers import ANCHOR_ENV

SIZE = (128, 96)  # W, H of the test frames
RADIUS = 0.0375
CENTRES = ((-0.045, 0.0, -0.275), (0.045, 0.0, -0.275))


def symmetric_environment(path: Path) -> Path:
    """Write the mirror-symmetric benchmark environment (31 bands) to ``path``."""
    from spectral_fit.io import read_spectral_exr, write_spectral_exr

    wl, img = read_spectral_exr(ANCHOR_ENV)
    sym = 0.5 * (img + img[:, ::-1])
    write_spectral_exr(path, wl, sym, preview=False)
    return path


def scene_toml(env: Path, *, mode: str = "none", stacks: int = 32, chi: float = 0.0,
               width: int = SIZE[0], height: int = SIZE[1], same_colour: bool = True,
               extra: str = "") -> str:
    """A two-sphere config (paper geometry, coarser meshes, 31 bands 400–700 nm)."""
    colours = ("yellow", "yellow") if same_colour else ("yellow", "red")
    objs = []
    for name, c, colour in zip(("left", "right"), CENTRES, colours, strict=True):
        objs.append(f"""
[[objects]]
name = "{name}"
shape = "uv_sphere"
radius = {RADIUS}
stacks = {stacks}
slices = {stacks}
position = [{c[0]}, {c[1]}, {c[2]}]

[objects.material]
reflectance = "colourchecker:ColorChecker N Ohta/{colour}"
alpha = 1.0
beta = 1.0
chi = {chi}
mu = 0.2
n = 1.5
gamma = 1.0
""")
    return f"""
[frame]
width = {width}
height = {height}

[camera]
fov_y_deg = 90.0

[environment]
file = "{env.as_posix()}"
rotation_y_deg = 180.0

[spectral]
start_nm = 400.0
end_nm = 700.0
step_nm = 10.0

[interreflection]
mode = "{mode}"
texture_size = 64
{extra}
""" + "".join(objs)


def write_scene(folder: Path, **kw) -> Path:
    env = folder / "env_sym.exr"
    if not env.exists():
        symmetric_environment(env)
    p = folder / f"scene_{kw.get('mode', 'none')}.toml"
    p.write_text(scene_toml(env, **kw))
    return p


def ray_directions(projection: np.ndarray, view: np.ndarray, rows, cols, shape):
    """World unit directions of the rays through pixel centres (rows, cols)."""
    h, w = shape
    x = 2 * (np.asarray(cols) + 0.5) / w - 1
    y = 1 - 2 * (np.asarray(rows) + 0.5) / h
    inv = np.linalg.inv(np.asarray(projection, np.float64) @ np.asarray(view, np.float64))
    p = np.stack([x, y, np.ones_like(x), np.ones_like(x)], -1) @ inv.T
    p = p[:, :3] / p[:, 3:]
    eye = np.linalg.inv(np.asarray(view, np.float64))[:3, 3]
    d = p - eye
    return eye, d / np.linalg.norm(d, axis=1, keepdims=True)
