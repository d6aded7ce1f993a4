"""The fit's forward model for objects of any shape: what a mesh hides from the readings (its
own inside, a neighbour) and the light it sends them, against closed forms and against ray
casting (a second implementation of the visibility)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers.shapes import bowl, box, torus, uv_sphere, write_obj

from spectral_fit import fitting

#: bands of the test scenes (a uniform white sky of radiance 1 in each)
WL = np.arange(400.0, 701.0, 100.0)

HEADER = """
[frame]
width = 32
height = 32

[camera]
fov_y_deg = 40.0

[environment]
file = "sky.exr"

[spectral]
start_nm = 400.0
end_nm = 700.0
step_nm = 100.0

[interreflection]
mode = "{mode}"
"""

MESH_OBJECT = """
[[objects]]
name = "{name}"
shape = "mesh"
mesh = "{mesh}"
position = {position}

[objects.material]
reflectance = {rho}
beta = 0.0
chi = 0.0
"""


def _sky(folder) -> None:
    from spectral_fit.io import write_spectral_exr

    write_spectral_exr(folder / "sky.exr", WL, np.ones((64, 128, WL.size), np.float32))


def _readings(folder, mode: str, objects: str, spots: list[dict]) -> np.ndarray:
    from spectral_fit.io import load_scene

    path = folder / f"scene_{mode}.toml"
    path.write_text(HEADER.format(mode=mode) + objects)
    scene = load_scene(path)
    return fitting.simulate_readings(scene, spots, options=fitting.FitOptions(
        spot_resolution=4))


@pytest.mark.parametrize("probe_bounces", [0, 4])
def test_integrating_sphere_readings_against_the_closed_form(tmp_path, probe_bounces):
    """Spots inside an integrating sphere (radius 5 cm, 60° port, ρ = 0.7) under a uniform sky
    L0 = 1: from any inside point the port's form factor is its share of the sphere's area,
    f = (1 − cos 60°)/2, so the direct light is ρ f L0 and every bounce multiplies the last
    one's light by ρ (1 − f): the sphere's multiple-reflection series ρ f L0 Σ (ρ(1 − f))^i
    (e.g. Goebel, Appl. Opt. 6 (1967) 125), here up to the fit's bounces (one from the wall to
    the spot, ``probe_bounces`` among the probes on the wall). Before the fit modelled any
    shape, the inside saw the whole sky: ρ L0."""
    from spectral_fit.fitting import CacheOptions
    from spectral_fit.io import load_scene

    R, port, rho = 0.05, 60.0, 0.7
    f = (1.0 - math.cos(math.radians(port))) / 2.0
    write_obj(tmp_path / "port.obj", *bowl(R, 16, 32, port_deg=port))
    _sky(tmp_path)
    obj = MESH_OBJECT.format(name="sphere", mesh="port.obj", position="[0.0, 0.0, -0.2]",
                             rho=rho)
    c = np.array([0.0, 0.0, -0.2])
    spots = []
    for d in ([0.0, 0.0, -1.0], [0.4, 0.0, -1.0], [0.0, 0.6, -1.0]):
        d = np.asarray(d) / np.linalg.norm(d)
        spots.append({"object": "sphere", "aim": c + R * d, "position": np.zeros(3),
                      "field_angle_deg": 1.0})
    opts = fitting.FitOptions(spot_resolution=4, cache=CacheOptions(probe_bounces=probe_bounces))
    got = {}
    for mode in ("none", "gather"):
        path = tmp_path / f"scene_{mode}.toml"
        path.write_text(HEADER.format(mode=mode) + obj)
        got[mode] = fitting.simulate_readings(load_scene(path), spots, options=opts).mean(axis=1)
    direct = got["none"] / (rho * f)
    series = sum((rho * (1.0 - f)) ** i for i in range(probe_bounces + 2))
    bounced = got["gather"] / (rho * f * series)
    # the direction grid's resolution (0.15 rad) at the port's edge: the frame's own test
    # of this sphere allows 8 % per pixel
    assert np.all(np.abs(direct - 1.0) < 0.08), direct
    assert np.all(np.abs(bounced - 1.0) < 0.08), bounced
    assert abs(direct.mean() - 1.0) < 0.04 and abs(bounced.mean() - 1.0) < 0.04, (direct, bounced)


def test_a_neighbour_mesh_hides_the_sky_by_its_form_factor(tmp_path):
    """A black square plate (4 × 4 cm) 1 cm above a white slab (ρ = 0.5) under a uniform sky:
    a point of the slab receives ρ L0 (1 − F), F the form factor to the plate, from the
    closed form of a parallel rectangle with a corner above the point (Howell's catalogue,
    C-11: F = [A/√(1+A²) atan(B/√(1+A²)) + B/√(1+B²) atan(A/√(1+B²))]/2π, A, B the sides
    over the height), rectangles added and subtracted for points elsewhere. The black plate
    sends no light back: interreflection changes nothing."""
    a, h, rho = 0.04, 0.01, 0.5
    write_obj(tmp_path / "slab.obj", *box((0.1, 0.005, 0.1), n=3))
    write_obj(tmp_path / "plate.obj", *box((a / 2, 0.001, a / 2), n=3))
    _sky(tmp_path)
    objs = (MESH_OBJECT.format(name="slab", mesh="slab.obj", position="[0.0, -0.005, 0.0]",
                               rho=rho)
            + MESH_OBJECT.format(name="plate", mesh="plate.obj",
                                 position=f"[0.02, {h + 0.001}, 0.02]", rho=0.0))

    def corner(x: float, z: float) -> float:
        A, B = x / h, z / h
        return (A / math.sqrt(1 + A * A) * math.atan(B / math.sqrt(1 + A * A))
                + B / math.sqrt(1 + B * B) * math.atan(A / math.sqrt(1 + B * B))) / (2 * math.pi)

    # the plate spans x, z in [0, a]; the spots at x = 0, 0.01 (under it), −0.03 (beside it)
    F = np.array([corner(a, a), corner(0.01, a) + corner(0.03, a),
                  corner(0.07, a) - corner(0.03, a)])
    view = np.array([-1.0, 1.0, -1.0]) / math.sqrt(3.0)  # the plate does not hide the spots
    spots = [{"object": "slab", "aim": np.array([x, 0.0, 0.0]),
              "position": np.array([x, 0.0, 0.0]) + 0.3 * view, "field_angle_deg": 0.5}
             for x in (0.0, 0.01, -0.03)]
    got = _readings(tmp_path, "gather", objs, spots).mean(axis=1) / (rho * (1.0 - F))
    assert np.all(np.abs(got - 1.0) < 0.02), got


def test_occlusion_tables_against_ray_casting():
    """What the fit's occlusion tables say (the shadow-map test at points, the nearest of two
    meshes and a sphere along each grid direction, with the hit point) against float32 ray
    casting through a bounding volume hierarchy of the same meshes: points on a torus (its
    hole hides part of its own sky) and on a sphere beside it."""
    import jax
    import jax.numpy as jnp

    from spectral_fit.fitting._occluders import MeshOccluder, PointOcclusion
    from spectral_fit.fitting._radiance_cache import Sphere
    from spectral_fit.geometry import build_bvh, closest_hit, octahedral_directions

    tv, tt, tn = torus(0.05, 0.02, 32, 16)
    sv, st, sn = uv_sphere(0.03, 12, 24)
    sv = sv + np.array([0.1, 0.0, 0.0])
    ball = Sphere(object=2, centre=np.array([0.0, 0.08, 0.0]), radius=0.02)
    rng = np.random.default_rng(3)
    pick_t = rng.choice(len(tv), 60, replace=False)
    pick_s = rng.choice(len(sv), 30, replace=False)
    X = np.concatenate([tv[pick_t], sv[pick_s]])
    N = np.concatenate([tn[pick_t], sn[pick_s]])
    obj = np.concatenate([np.zeros(60, int), np.ones(30, int)])
    meshes = [MeshOccluder(0, tv, tt, tn, convex=False), MeshOccluder(1, sv, st, sn, convex=True)]
    R = 16
    occ = PointOcclusion(X, N, obj, spheres=[ball], meshes=meshes, resolution=R, raster_size=256)
    dirs, _ = octahedral_directions(R)
    # ray casting: both meshes in one hierarchy, from the points lifted 1e-4 m off the surface
    V = np.concatenate([tv, sv])
    T = np.concatenate([tt, st + len(tv)])
    bvh = build_bvh(V, T)
    o = np.repeat(X + 1e-4 * N, len(dirs), axis=0)
    d = np.tile(dirs, (len(X), 1))
    hit = jax.jit(jax.vmap(lambda a, b: closest_hit(bvh, a, b)))(jnp.asarray(o, jnp.float32),
                                                                   jnp.asarray(d, jnp.float32))
    t_mesh = np.where(np.asarray(hit.triangle) >= 0, np.asarray(hit.t), np.inf)
    hit_obj = np.where(np.asarray(hit.triangle) >= len(tt), 1, 0)
    # the sphere analytically
    oc = o - ball.centre
    bq = np.sum(oc * d, -1)
    disc = bq * bq - np.sum(oc * oc, -1) + ball.radius ** 2
    t_ball = np.where(disc > 0, -bq - np.sqrt(np.maximum(disc, 0)), np.inf)
    t_ball = np.where(t_ball > 0, t_ball, np.inf)
    ref = np.where(t_ball < t_mesh, 2, np.where(np.isfinite(t_mesh), hit_obj, -1))
    ref = ref.reshape(len(X), -1)
    own_convex = (obj[:, None] == 1) & (ref == 1)  # a convex mesh never hides its own sky
    ref = np.where(own_convex, -1, ref)
    up = (N @ dirs.T) > 0.15  # away from grazing directions
    # the tables: along each grid direction itself (the tap of weight 1)
    got_occ, got_pt, _ = occ.trace(np.arange(len(X))[:, None], np.broadcast_to(
        dirs[None], (len(X),) + dirs.shape).astype(np.float64))
    got = occ.occluder_object[np.maximum(got_occ, 0)]
    got = np.where(got_occ >= 0, got, -1)
    agree = (got == ref)[up]
    assert agree.mean() > 0.97, agree.mean()
    # where both hit, the hit points agree to a few shadow-map pixels
    both = up & (got >= 0) & (got == ref)
    t_ref = np.minimum(t_mesh, t_ball).reshape(len(X), -1)
    p_ref = X[:, None] + np.where(np.isfinite(t_ref), t_ref, 0.0)[..., None] * dirs[None]
    err = np.linalg.norm(got_pt - p_ref, axis=-1)[both]
    assert both.sum() > 200 and np.median(err) < 1e-3 and np.quantile(err, 0.9) < 3e-3, (
        both.sum(), np.median(err), np.quantile(err, 0.9))


@pytest.mark.parametrize("mode", ["none", "gather"])
def test_spheres_only_scenes_are_unchanged(mode, tmp_path):
    """A scene of spheres alone takes the analytic path as before: the occlusion tables are
    not built (the sphere test of the radiance cache is exact for spheres)."""
    from spectral_fit.fitting._prepare import _scene_occluders
    from spectral_fit.io import load_scene

    _sky(tmp_path)
    cfg = HEADER.format(mode=mode) + """
[[objects]]
name = "a"
shape = "icosphere"
radius = 0.03
position = [0.0, 0.0, -0.3]

[objects.material]
reflectance = 0.5
"""
    (tmp_path / "s.toml").write_text(cfg)
    scene = load_scene(tmp_path / "s.toml")
    spheres, meshes = _scene_occluders(scene, [None])
    assert len(spheres) == 1 and meshes == []


def test_photograph_bins_a_concave_object_lights_itself_are_found():
    """A torus's outer equator faces open sky (nothing of the torus above its tangent plane)
    and the view straight out mirrors into the sky; its inner equator faces the hole, where
    the other side of the ring fills a large part of its sky: the bins there are left out of a
    fit (their light from the object itself is not in the photograph's model)."""
    from types import SimpleNamespace

    from spectral_fit.fitting._image_rows import _self_lit

    v, t, n = torus(0.05, 0.02, 48, 24)
    g = SimpleNamespace(vertices=v, triangles=t, normals=n)
    ang = np.linspace(0.0, 2 * np.pi, 12, endpoint=False)
    radial = np.stack([np.cos(ang), np.zeros_like(ang), np.sin(ang)], 1)
    outer = 0.07 * radial
    inner = 0.03 * radial
    x = np.concatenate([outer, inner])
    nrm = np.concatenate([radial, -radial])
    lit = _self_lit(x, nrm, nrm, np.zeros(len(x), int), [g])
    assert not lit[:12].any() and lit[12:].all(), lit


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["any_shape", "four_objects"])
def test_fit_model_against_the_path_traced_references(scene, tmp_path):
    """The fit's readings (interreflection on) of 60 spots aimed from the camera at patches of
    the committed Mitsuba references (depth 16; a cup beside a torus; spheres of 50 and 10 mm,
    a torus and a cube 4 mm apart), the field of equal area as the 5 × 5-pixel patch: ΔE00
    within the any-shape issue's targets for frames (patches where interreflection adds < 2 %
    of Y: 0.3 / 0.8 / 2.0 median / p90 / max; more: 0.5 / 1.5 / 3.0). Measured: any_shape
    0.12 / 0.29 / 0.73 and 0.36 / 1.43 / 2.97 (the cup's inside under its lip, 10 % dark);
    four_objects 0.13 / 0.23 / 0.65 and 0.32 / 1.33 / 1.99. Before the fit modelled any
    shape: 0.15 / 0.84 / 1.39 and 2.40 / 7.51 / 17.8 on any_shape."""
    import json

    from helpers import load_script

    out = tmp_path / "cmp.json"
    load_script("fit_model_vs_reference").main([scene, "-o", str(out)])
    groups = json.loads(out.read_text())["summary"]["auto"]["groups"]
    for name, limits in (("share <= 2 %", (0.3, 0.8, 2.0)), ("share > 2 %", (0.5, 1.5, 3.0))):
        de = groups[name]["delta_e"]
        got = (de["median"], de["p90"], de["max"])
        assert all(g <= lim for g, lim in zip(got, limits, strict=True)), (name, got)


@pytest.mark.slow
def test_bundled_any_shape_session_recovery():
    """The bundled session of 23 path-traced spots on a cup and a torus (meshes; readings
    inside the cup and the torus's hole and on the sides facing each other; independent of
    the fit's model: scripts/make_any_shape_session.py), fitted with the model error the
    session asks the fit to estimate for its interreflection readings. The cup (μ = 0.06)
    within every tolerance of docs/fitting.md (α 2 %, β 3 %, χ 0.01, μ 3 %, n 0.02); the
    torus, whose gloss is weak in every reading (β, χ, μ correlated, |r| ≥ 0.98), within them
    for α, χ and μ and within 10 % / 0.04 for β and n (measured −6.4 %, +0.026)."""
    import json
    import warnings
    from pathlib import Path

    from spectral_fit.io import load_session

    folder = Path(__file__).resolve().parents[1] / "measurements" / "sessions" / "any_shape_spots"
    truth = json.loads((folder / "truth.json").read_text())["params"]
    session = load_session(folder)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = fitting.fit(session.scene, session, holdout=False, aim_step_m=0.0)
    assert res.status == "converged"
    for name, t in truth.items():
        p = res.params[name]
        beta_tol, n_tol = (0.03, 0.02) if name == "cup" else (0.10, 0.04)
        assert p["alpha"] == pytest.approx(t["alpha"], rel=0.02), name
        assert p["beta"] == pytest.approx(t["beta"], rel=beta_tol), name
        assert abs(p["chi"] - t["chi"]) <= 0.01, name
        assert p["mu"] == pytest.approx(t["mu"], rel=0.03), name
        assert p["n"] == pytest.approx(t["n"], abs=n_tol), name
