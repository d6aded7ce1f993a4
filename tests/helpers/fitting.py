"""Shared helpers of the fitting tests: a small two-sphere scene and session writers."""

from __future__ import annotations

from pathlib import Path

import numpy as np

SMALL_CONFIG = """
[frame]
width = 64
height = 48

[camera]
fov_y_deg = 60.0

[environment]
file = "env.exr"

[spectral]
start_nm = 400.0
end_nm = 700.0
step_nm = 20.0

[interreflection]
mode = "none"

[[objects]]
name = "yellow"
shape = "icosphere"
radius = 0.0375
subdivisions = 4
position = [-0.045, 0.0, -0.275]

[objects.material]
reflectance = "colourchecker:ColorChecker N Ohta/yellow"
alpha = 1.0
beta = 1.0
chi = 0.05
mu = 0.15
n = 1.5

[[objects]]
name = "red"
shape = "icosphere"
radius = 0.0375
subdivisions = 4
position = [0.045, 0.0, -0.275]

[objects.material]
reflectance = "colourchecker:ColorChecker N Ohta/red"
alpha = 1.0
beta = 1.0
chi = 0.05
mu = 0.15
n = 1.5
"""

TRUE = {
    "yellow": {"alpha": 0.9, "beta": 0.8, "chi": 0.06, "mu": 0.12, "n": 1.52},
    "red": {"alpha": 0.85, "beta": 1.1, "chi": 0.03, "mu": 0.18, "n": 1.45},
}

CENTRES = {"yellow": np.array([-0.045, 0.0, -0.275]), "red": np.array([0.045, 0.0, -0.275])}
RADIUS = 0.0375


def assert_recovered(params: dict, *, rel: float, chi_abs: float) -> None:
    """Every parameter of :data:`TRUE` within ``rel`` × its true value in ``params``
    ({object: {param: value}}), χ within ``chi_abs`` (absolute: its true value is small)."""
    for obj, tp in TRUE.items():
        for p, v in tp.items():
            got = params[obj][p]
            tol = rel * abs(v) if p != "chi" else chi_abs
            assert abs(got - v) <= tol, (obj, p, got, v)


def write_small_scene(folder: Path, *, env_size: tuple[int, int] = (16, 32)) -> Path:
    """Write the small scene (two icospheres, a 16×32 synthetic environment, 16 bands)."""
    from spectral_fit.color import wavelength_grid
    from spectral_fit.io import write_spectral_exr
    from spectral_fit.lighting import synthetic_environment

    folder.mkdir(parents=True, exist_ok=True)
    wl = wavelength_grid(400.0, 700.0, 20.0)
    img = synthetic_environment(env_size[0], env_size[1], wl, lamp_radius_deg=12.0,
                                lamp_luminance_ratio=8.0, supersample=2)
    write_spectral_exr(folder / "env.exr", wl, img.astype(np.float32))
    (folder / "scene.toml").write_text(SMALL_CONFIG)
    return folder / "scene.toml"


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def spots(distance: float = 0.3) -> list[dict]:
    """Five spots per sphere at several viewing angles (all seen from outside, unoccluded)."""
    out = []
    for name, c in CENTRES.items():
        side = -1.0 if name == "yellow" else 1.0
        for k, (nrm, view) in enumerate([
            ([0.0, 0.0, 1.0], [0.0, 0.0, 1.0]),
            ([side * 0.3, 0.5, 1.0], [0.0, 0.1, 1.0]),
            ([side * 0.9, 0.3, 0.6], [side * 0.2, 0.2, 1.0]),
            ([side * 0.2, 1.0, 0.5], [side * 0.3, 1.0, 0.9]),
            ([side * 0.5, -0.3, 1.0], [-side * 0.4, -0.2, 1.0]),
        ]):
            n, v = _unit(nrm), _unit(view)
            aim = c + RADIUS * n
            out.append({"id": f"{name}_{k}", "object": name,
                        "kind": "interreflection" if k == 4 else "object",
                        "aim": aim, "position": aim + distance * v, "field_angle_deg": 1.0})
    return out


def write_session(folder: Path, scene_path: Path, readings: np.ndarray, wl: np.ndarray, *,
                  spot_list: list[dict] | None = None, repeats: np.ndarray | None = None,
                  white: dict | None = None, noise: dict | None = None,
                  objects: dict | None = None) -> Path:
    """A session of the given spot readings (B, L) (or repeats (B, M, L))."""
    from spectral_fit.io import write_session as ws

    sp = spot_list or spots()
    rl = []
    for b, s in enumerate(sp):
        spec = repeats[b] if repeats is not None else readings[b][None]
        rl.append({**{k: s[k] for k in ("id", "object", "kind", "aim", "position",
                                        "field_angle_deg")}, "spectra": spec})
    rel = Path(*([".."] * 1)) / scene_path.name if scene_path.parent == folder.parent else None
    scene_ref = str(rel) if rel is not None else str(scene_path)
    return ws(folder, scene=scene_ref, wavelengths=wl, readings=rl,
              white=white, noise=noise or {"absolute": 1e-7, "relative": 0.003},
              objects=objects)


def k_true(wl):
    """The small session's true calibration k(λ) of the map (a 20 % brighter room, tilted)."""
    return 1.2 * (1.0 + 0.1 * (wl - 550.0) / 150.0)


def small_session(root: Path, *, resolution: int = 6, objects: dict | None = None):
    """The small scene (:func:`write_small_scene`) and noiseless own-model readings of
    :func:`spots` at :data:`TRUE` under a mis-scaled map, with a white standard that
    calibrates it, written into ``root`` (``objects``: the session's per-object entries, as
    :func:`write_session`); returns (scene, session, prepared fit, environment,
    clean readings (B, L))."""
    import math

    import jax.numpy as jnp

    from spectral_fit import fitting
    from spectral_fit.io import load_scene, load_session
    from spectral_fit.lighting import irradiance_exact

    cfg = write_small_scene(root)
    scene = load_scene(cfg)
    wl = scene.wavelengths
    env = fitting.scene_environment(scene, compress_tol=3e-3)
    opts = fitting.FitOptions(spot_resolution=resolution)
    clean = fitting.simulate_readings(scene, spots(), params=TRUE, calibration=k_true(wl),
                                      env=env, options=opts)
    n_w = np.array([0.0, 0.0, 1.0])
    e = np.asarray(irradiance_exact(env, jnp.asarray(n_w, jnp.float32)), np.float64)
    white = {"reflectance": 0.98, "position": [0.0, 0.0, -0.275], "normal": n_w,
             "spectra": (k_true(wl) * 0.98 * e / math.pi)[None]}
    m = write_session(root / "sess", cfg, clean, wl, white=white, objects=objects)
    session = load_session(m, scene=scene)
    prep = fitting.prepare_fit(scene, session, options=opts, env=env)
    return scene, session, prep, env, clean
