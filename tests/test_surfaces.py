"""Real surfaces (a table under the objects) against closed forms: the plane's radiance in the
objects' environment, a sphere's form factor from the plane under a uniform sky, the hard
shadow of a sphere under one small bright source, a white furnace, gradients, and the
differential composite."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spectral_fit._runtime.errors import InputError
from spectral_fit.io import parse_scene, write_spectral_exr
from spectral_fit.lighting import ground_plane, upper_irradiance
from spectral_fit.rendering import prepare, surface_layer, surface_texels

WL = np.arange(400.0, 701.0, 100.0)
R = 0.05

#: the frame, camera, environment and bands of the test scenes
HEADER = """
[frame]
width = 96
height = 64

[camera]
fov_y_deg = 60.0
position = [0.0, 0.35, 0.45]
look_at = [0.0, 0.0, 0.0]

[environment]
file = "{env}"

[spectral]
start_nm = 400.0
end_nm = 700.0
step_nm = 100.0
"""

CONFIG = HEADER + """
[interreflection]
mode = "none"

[[objects]]
name = "ball"
shape = "icosphere"
subdivisions = 4
radius = {r}
position = [0.0, {h}, 0.0]

[objects.material]
reflectance = {rho_obj}
alpha = {alpha}
beta = 0.0
chi = 0.0

[[surfaces]]
name = "table"
reflectance = {rho}
resolution = 64
margin = 2.0
"""


def _scene(folder, env: np.ndarray, *, h: float, alpha: float, rho: float = 1.0,
           rho_obj: float = 1.0):
    write_spectral_exr(folder / "sky.exr", WL, env.astype(np.float32))
    path = folder / "scene.toml"
    path.write_text(CONFIG.format(env="sky.exr", r=R, h=h, alpha=alpha, rho=rho,
                                  rho_obj=rho_obj))
    return path


def _texel_centres(st) -> np.ndarray:
    """World positions (T², 3) of the transfer's texel centres (the module's convention)."""
    t = st.resolution
    col, row = np.meshgrid(np.arange(t), np.arange(t))
    u = (col.reshape(-1) + 0.5) * 2.0 / t - 1.0
    v = 1.0 - (row.reshape(-1) + 0.5) * 2.0 / t
    axes = np.asarray(st.axes, np.float64)
    half = float(st.half)
    return np.asarray(st.origin, np.float64) + half * (u[:, None] * axes[0]
                                                       + v[:, None] * axes[1])


def test_ground_plane_closed_form():
    """Uniform sky L0 over a plane of reflectance ρ: E_up = π L0, and every direction below
    the horizon shows ρ L0; half-split texels on the horizon by area."""
    h, w = 16, 32
    sky = np.full((h, w, 3), 2.0)
    e_up = upper_irradiance(sky, [0.0, 1.0, 0.0])
    np.testing.assert_allclose(e_up, 2.0 * math.pi, rtol=1e-3)
    grounded, plane = ground_plane(sky, [0.0, 1.0, 0.0], [0.2, 0.5, 1.0])
    np.testing.assert_allclose(plane, [0.4, 1.0, 2.0], rtol=1e-3)
    np.testing.assert_allclose(grounded[: h // 2], 2.0)
    np.testing.assert_allclose(grounded[h // 2:], np.broadcast_to(plane, (h // 2, w, 3)),
                               rtol=1e-3)
    # a tilted plane: the lower side's share follows the normal
    tilted, _ = ground_plane(sky, [math.sin(0.3), math.cos(0.3), 0.0], 0.0)
    from spectral_fit.lighting import texel_solid_angles

    sa = texel_solid_angles(h, w)
    dark = 1.0 - (tilted[..., 0] / 2.0)  # share of each texel below
    np.testing.assert_allclose((dark * sa).sum(), 2.0 * math.pi, rtol=2e-3)


def test_objects_see_the_plane(tmp_path):
    """A white plane (ρ = 1) under a uniform sky makes the objects' environment uniform: the
    map the renderer prepares from equals the sky everywhere; ρ = 0.25 darkens the lower half
    to 0.25 L0."""
    from spectral_fit.io import load_scene
    from spectral_fit.rendering import ground_surfaces, load_environment

    sky = np.ones((16, 32, WL.size))
    for rho, lower in ((1.0, 1.0), (0.25, 0.25)):
        scene = load_scene(_scene(tmp_path, sky, h=R, alpha=1.0, rho=rho))
        tex = ground_surfaces(scene, load_environment(scene, scene.wavelengths))
        np.testing.assert_allclose(tex[:8], 1.0, rtol=1e-5)
        np.testing.assert_allclose(tex[8:], lower, rtol=2e-3)


def test_sphere_form_factor_from_plane(tmp_path):
    """A black sphere (radius r, centre at height h) over a plane under a uniform sky L0: the
    plane's irradiance is π L0 (1 − F) with F = r² h / d³, the sphere's form factor from a
    point at distance d from its centre (a sphere wholly above the point's horizon: its
    cosine-weighted solid angle is π sin²θ cosφ = π r² h / d³; Howell's catalogue of
    configuration factors, C-56)."""
    h = 2.0 * R
    prep = prepare(_scene(tmp_path, np.ones((32, 64, WL.size)), h=h, alpha=0.0),
                   occlusion=False)
    st = prep.surfaces[0]
    e = np.asarray(surface_texels(prep, st, None, prep.model))[:, 0]
    x = _texel_centres(st)
    d = np.linalg.norm(x - np.array([0.0, h, 0.0]), axis=1)
    expect = math.pi * (1.0 - R * R * h / d ** 3)
    err = (e - expect) / math.pi
    assert np.median(np.abs(err)) < 0.005
    assert np.abs(err).max() < 0.03
    # right under the sphere: F = (r/h)² = 0.25
    centre = np.argmin(np.linalg.norm(x[:, [0, 2]], axis=1))
    assert abs(e[centre] / math.pi - 0.75) < 0.02


def _source_sky() -> tuple[np.ndarray, np.ndarray]:
    """A dim sky (1e-3) with one bright texel at elevation ~40°: the map and the texel's
    direction (world frame, rotation 0)."""
    from spectral_fit.lighting import texel_directions

    sky = np.full((64, 128, WL.size), 1e-3)
    row, col = 16, 40
    sky[row, col] = 2000.0
    return sky, texel_directions(64, 128)[row, col]


def test_hard_shadow_of_a_sphere(tmp_path):
    """A black sphere under one small bright source (its texel's four sub-points): each texel
    of the plane loses the share of the source's flux whose sub-points' rays hit the sphere
    (ray–sphere intersection, analytic), to within the texel grid's edge."""
    h = 1.5 * R
    sky, _ = _source_sky()
    prep = prepare(_scene(tmp_path, sky, h=h, alpha=0.0), occlusion=False)
    env = prep.lighting.env
    sub = np.asarray(env.source_dirs, np.float64).reshape(-1, 3) @ np.asarray(
        env.rotation, np.float64).T
    flux = np.asarray(env.source_flux_full, np.float64)[0, 0] / 4.0
    assert sub.shape == (4, 3)
    st = prep.surfaces[0]
    e = np.asarray(surface_texels(prep, st, None, prep.model))[:, 0]
    x = _texel_centres(st)
    c = np.array([0.0, h, 0.0])
    hidden = np.zeros(len(x))
    near_edge = np.zeros(len(x), bool)
    texel = 2.0 * float(st.half) / st.resolution
    for s in sub:
        oc = c - x
        along = oc @ s
        miss = np.sqrt(np.maximum(np.sum(oc * oc, 1) - along ** 2, 0.0))
        hidden += ((miss < R) & (along > 0)) * flux * s[1]
        near_edge |= np.abs(miss - R) < 1.5 * texel
    drop = float(np.asarray(st.upper)[0]) - e
    total = flux * sub[:, 1].sum()
    assert hidden.max() > 0.99 * total  # the shadow is in the region
    ok = ~near_edge
    np.testing.assert_allclose(drop[ok], hidden[ok], atol=0.02 * total)
    # the shadow's area (sum of the lost flux) within 5 % of the analytic one
    assert abs(drop.sum() - hidden.sum()) < 0.05 * hidden.sum()


def test_white_furnace(tmp_path):
    """A white Lambertian sphere on a white plane under a uniform sky: everything is lit by
    L0 from every direction, so the plane's irradiance stays π L0 wherever the sphere is."""
    prep = prepare(_scene(tmp_path, np.ones((32, 64, WL.size)), h=R, alpha=1.0, rho=1.0,
                          rho_obj=1.0), occlusion=False)
    st = prep.surfaces[0]
    e = np.asarray(surface_texels(prep, st, None, prep.model))
    np.testing.assert_allclose(e / math.pi, 1.0, atol=0.02)


#: one diffuse icosphere of the two-sphere scene
BALL = """
[[objects]]
name = "{name}"
shape = "icosphere"
subdivisions = 4
radius = {r}
position = [{x}, {h}, 0.0]

[objects.material]
reflectance = 1.0
alpha = {alpha}
beta = 0.0
chi = 0.0
"""

TWO = HEADER + """
[interreflection]
mode = "gather"
bounces = 1
{balls}
[[surfaces]]
name = "table"
reflectance = 0.0
resolution = 64
margin = 1.0
"""


def _cosine_directions(n_t: int, n_p: int, normals: np.ndarray) -> np.ndarray:
    """(N, n_t·n_p, 3) directions over the hemisphere of each of ``normals`` (N, 3), each
    carrying π/(n_t·n_p) of projected solid angle (a product rule in sin²θ and φ)."""
    t = (np.arange(n_t) + 0.5) / n_t
    phi = (np.arange(n_p) + 0.5) / n_p * 2.0 * math.pi
    s, p = np.meshgrid(np.sqrt(t), phi, indexing="ij")
    local = np.stack([s * np.cos(p), s * np.sin(p), np.sqrt(1.0 - s * s)], -1).reshape(-1, 3)
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    a = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    t1 = np.cross(a, n)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    frames = np.stack([t1, np.cross(n, t1), n], axis=1)  # (N, 3, 3)
    return np.einsum("kj,nji->nki", local, frames)


def _ray_sphere(o: np.ndarray, d: np.ndarray, c: np.ndarray, r: float):
    """(hit, distance) of rays from points ``o`` (..., 3) along ``d`` (..., 3)."""
    oc = c - o
    b = np.sum(d * oc, -1)
    disc = b * b - (np.sum(oc * oc, -1) - r * r)
    return (disc > 0) & (b > 0), b - np.sqrt(np.maximum(disc, 0.0))


def test_neighbours_light_towards_the_plane(tmp_path):
    """A black and a white diffuse sphere side by side over a black plane under a uniform sky
    L0 = 1: the black one hides part of the white one's sky, so the white one's side facing
    it, and the plane under the gap that sees that side, are darker. Against a float64
    quadrature with exact ray–sphere tests: what the black sphere takes from the white one's
    vertices (``neighbour_irradiance``), and what that changes of the plane's irradiance
    between them (texels, with the term against without)."""
    from spectral_fit.rendering import neighbour_irradiance

    r, h, xa, xb = R, 1.1 * R, -0.065, 0.065
    write_spectral_exr(tmp_path / "sky.exr", WL, np.ones((32, 64, WL.size), np.float32))
    balls = "".join(BALL.format(name=n, r=r, x=x, h=h, alpha=al)
                    for n, x, al in (("black", xa, 0.0), ("white", xb, 1.0)))
    (tmp_path / "scene.toml").write_text(TWO.format(env="sky.exr", balls=balls))
    prep = prepare(tmp_path / "scene.toml", occlusion=False)
    a, b = np.array([xa, h, 0.0]), np.array([xb, h, 0.0])

    def lost(y: np.ndarray, n: np.ndarray) -> np.ndarray:
        """(N,) the sky irradiance the black sphere takes from points y with normals n."""
        d = _cosine_directions(16, 32, n)  # (N, K, 3)
        hit, _ = _ray_sphere(y[:, None], d, a, r)
        return -math.pi / d.shape[1] * np.sum(hit & (d[..., 1] > 0), axis=1)

    # the white sphere's vertices facing the black one
    nb = neighbour_irradiance(prep)
    mesh = prep.ir_mesh
    white = np.where(np.asarray(mesh.vertex_object) == 1)[0]
    v = np.asarray(mesh.vertices, np.float64)[white] + b  # object frame: centred at 0
    n = np.asarray(mesh.normals, np.float64)[white]
    facing = np.where(n[:, 0] < -0.3)[0][::5]
    got = np.asarray(nb, np.float64)[white[facing], 0]
    want = lost(v[facing], n[facing])
    assert want.min() < -0.3  # a large effect: up to 1/5 of the sky
    np.testing.assert_allclose(got, want, atol=0.03 * math.pi)
    # the plane between them (its irradiance with and without the neighbours' term)
    st = prep.surfaces[0]
    with_nb = np.asarray(surface_texels(prep, st, None, prep.model, neighbours=nb))[:, 0]
    # (zeros rather than None: the same compiled program)
    without = np.asarray(surface_texels(prep, st, None, prep.model,
                                        neighbours=np.zeros_like(nb)))[:, 0]
    x = _texel_centres(st)
    pick = np.where((np.abs(x[:, 0]) < 0.02) & (np.abs(x[:, 2]) < 0.05))[0][::4]
    up = _cosine_directions(60, 120, np.array([0.0, 1.0, 0.0]))[0]
    want_t = []
    for p in x[pick]:
        ha, ta = _ray_sphere(p, up, a, r)
        hb, tb = _ray_sphere(p, up, b, r)
        on_b = hb & ~(ha & (ta < tb))
        y = p + up[on_b] * tb[on_b, None]
        # the white sphere's radiance changes by α ΔE/π at each point the plane sees
        want_t.append(math.pi / len(up) * np.sum(lost(y, (y - b) / r)) / math.pi)
    want_t = np.array(want_t)
    got_t = with_nb[pick] - without[pick]
    assert want_t.min() < -0.04  # 2–4 % of the plane's irradiance there
    np.testing.assert_allclose(got_t, want_t, rtol=0.15, atol=0.004)


def test_gradient_against_finite_differences(tmp_path):
    """∂(plane radiance)/∂α of the object, through the layer, against a central difference."""
    import jax
    import jax.numpy as jnp

    from spectral_fit.lighting import Material

    sky, _ = _source_sky()
    sky = sky + 0.5
    prep = prepare(_scene(tmp_path, sky, h=R, alpha=0.6, rho=0.5, rho_obj=0.8),
                   occlusion=False)
    st = prep.surfaces

    def total(a):
        m = prep.materials
        mats = Material(**{**{f: getattr(m, f) for f in m.__dataclass_fields__},
                           "alpha": jnp.reshape(a, m.alpha.shape)})
        lay = surface_layer(prep, st, mats)
        return jnp.sum(lay.radiance[..., 1])

    # one program gives the gradient and the values of the differences (op by op, the
    # layer's few hundred operations each compiled apart cost more than the whole program)
    value_and_grad = jax.jit(jax.value_and_grad(total))
    a0 = 0.6
    g = float(value_and_grad(jnp.float32(a0))[1])
    eps = 0.05
    fd = (float(value_and_grad(jnp.float32(a0 + eps))[0])
          - float(value_and_grad(jnp.float32(a0 - eps))[0])) / (2 * eps)
    assert g > 0
    assert abs(g - fd) < 1e-3 * abs(fd) + 1e-6


def test_layer_sees_the_plane_through_the_camera(tmp_path):
    """The layer's pixels: every pixel whose ray goes down meets the plane (the camera looks
    down at it), and far from the sphere the radiance equals the plane's without objects."""
    prep = prepare(_scene(tmp_path, np.ones((32, 64, WL.size)), h=R, alpha=0.0, rho=0.5),
                   occlusion=False)
    tex = np.asarray(prep.lighting.env.texels)  # prepared under the plane: ρ L0 below
    np.testing.assert_allclose(tex[16:], 0.5, rtol=2e-3)
    lay = surface_layer(prep, prep.surfaces)
    mask = np.asarray(lay.mask)
    assert mask.mean() > 0.9
    rad, base = np.asarray(lay.radiance), np.asarray(lay.base)
    ratio = rad[..., 1] / np.where(mask, base[..., 1], 1.0)
    assert ratio[mask].min() < 0.6  # the contact shadow
    assert np.isclose(np.median(ratio[mask]), 1.0, atol=1e-3)
    # base = ρ π L0 / π = ρ in XYZ-weighted units: Y = 683 ∫ ȳ ρ L0 dλ on the grid
    from spectral_fit.color import xyz_weights

    y = float((0.5 * xyz_weights(WL))[:, 1].sum())
    np.testing.assert_allclose(base[mask][:, 1], y, rtol=1e-4)


def test_config_errors(tmp_path):
    data = {
        "environment": {"file": str(tmp_path / "sky.exr")},
        "objects": [{"name": "a"}],
        "surfaces": [{"name": "t", "normal": [0.0, 0.0, 0.0]}],
    }
    write_spectral_exr(tmp_path / "sky.exr", WL, np.ones((8, 16, WL.size), np.float32))
    with pytest.raises(InputError, match=r"surfaces\[0\]\.normal"):
        parse_scene(data, path=tmp_path / "x.toml")
    data["surfaces"] = [{"name": "t", "reflectance": 1.2}]
    with pytest.raises(InputError, match=r"surfaces\[0\]\.reflectance"):
        parse_scene(data, path=tmp_path / "x.toml")
    data["surfaces"] = [{"name": "t", "colour": 1}]
    with pytest.raises(InputError, match=r"surfaces\[0\]\.colour"):
        parse_scene(data, path=tmp_path / "x.toml")


def test_live_relight(tmp_path):
    """The live step's differential composite: a ratio of 1 gives the frame back bit for bit
    (a frame without objects); in the shadow each pixel's linear value is the frame's times
    the ratio (to the 8-bit quantisation); a clipped pixel is only darkened. With the
    table's reflectance 20 % off in the config, the ratio form stays closer to the truth than
    an added difference would (the hidden sky cancels in it; only the light the table sends
    back to the object, and from it to the table, scales with ρ)."""
    import jax.numpy as jnp

    from spectral_fit.io import load_scene
    from spectral_fit.live import camera_spectral_matrix, decode_frame, encode_frame, relight
    from spectral_fit.live._scene_camera import scene_camera_model
    from spectral_fit.rendering import (
        surface_ratio,
        surface_ratio_lookup,
        surface_ratio_textures,
        surface_textures,
    )

    sky, _ = _source_sky()
    sky = sky + 0.2
    ratios, layers = [], []
    for rho in (0.5, 0.6):  # the truth, and the table's reflectance 20 % off
        path = _scene(tmp_path, sky, h=R, alpha=0.7, rho=rho)
        prep = prepare(path, occlusion=False)
        camera = scene_camera_model(load_scene(path))
        tex = surface_textures(prep, prep.surfaces, out=camera_spectral_matrix(prep, camera))
        layer = surface_layer(prep, textures=tex)
        layers.append((np.asarray(layer.radiance), np.asarray(layer.base)))
        ratios.append(np.asarray(surface_ratio(prep, layer, channels="linear")))
        # the live step's form: the ratio per texel, read per pixel, equals the ratio of the
        # per-pixel lookups (the plane's base is one value per channel), 1 where it is 1
        looked = np.asarray(surface_ratio_lookup(prep, surface_ratio_textures(tex)))
        np.testing.assert_allclose(looked, ratios[-1], rtol=2e-6, atol=2e-7)
        np.testing.assert_array_equal(looked[ratios[-1] == 1.0], 1.0)
    (true_with, true_base), (off_with, off_base) = layers
    m = true_base[..., 1] > 0
    err_ratio = np.abs(true_base * ratios[1] - true_with)[m] / true_base[m]
    err_added = np.abs(true_base + (off_with - off_base) - true_with)[m] / true_base[m]
    assert err_ratio.max() < 0.6 * err_added.max()
    ratio = ratios[0]
    assert ratio.min() < 0.7
    rng = np.random.default_rng(3)
    frame = rng.integers(20, 240, size=(*ratio.shape[:2], 3), dtype=np.uint8)
    frame[0, 0] = 255
    same = np.asarray(relight(frame, np.ones_like(ratio), camera))
    np.testing.assert_array_equal(same, frame)
    out = np.asarray(relight(frame, ratio, camera))
    lin_in = np.asarray(decode_frame(jnp.asarray(frame / 255.0), camera))
    lin_out = np.asarray(decode_frame(jnp.asarray(out / 255.0), camera))
    shade = ratio.min(axis=-1) < 0.9
    assert shade.sum() > 20
    # the 8-bit step of the curve, relative, at these levels: < 2 %
    np.testing.assert_allclose(lin_out[shade], (lin_in * ratio)[shade], rtol=0.03,
                               atol=2e-3)
    # the code table against the curve evaluated per pixel (decode, times the ratio,
    # encode, round): at most one code apart (the ratio's 1/1024 steps), mostly equal
    exact = np.round(np.asarray(encode_frame(jnp.asarray(lin_in * ratio), camera)) * 255.0)
    diff = np.abs(out.astype(int) - exact.astype(int))
    assert diff.max() <= 1 and (diff == 0).mean() > 0.99
    untouched = np.all(ratio == 1.0, axis=-1)
    np.testing.assert_array_equal(out[untouched], frame[untouched])
    clipped = frame.copy()
    clipped[shade] = 255
    lit = np.asarray(relight(clipped, np.maximum(ratio, 1.0) * 1.1, camera))
    np.testing.assert_array_equal(lit[shade], 255)  # never brightened past what is known


def _change(field, half=0.2, cells=16, split=4):
    """A TableChange over the square [−half, half]² of the plane y = 0 (t1 = +x, t2 = −z as
    the module builds them for a +Y normal) with the fine change ``field`` (T, T, 1)."""
    from spectral_fit.rendering import TableChange
    from spectral_fit.rendering._surfaces import _plane_axes

    axes = _plane_axes(np.array([0.0, 1.0, 0.0]))
    return TableChange.from_fine(field, origin=np.zeros(3), axes=axes, half=half,
                                 spheres=np.zeros((1, 4)), cells=cells, split=split), axes


def test_table_change_seen_from_above():
    """What a point sees of the table's change: a uniform change ΔL over the square region,
    seen from heights h above its centre by a point facing down, gives π ΔL F with F the
    square's form factor from a point on its axis (four corner rectangles, Howell's
    catalogue C-11); the mirrored change is the field at the mirror ray's hit point."""
    half = 0.2
    ch, axes = _change(np.full((64, 64, 1), -0.3), half=half)
    for h in (0.03, 0.08, 0.2):
        a = b = half / h
        corner = (a / np.sqrt(1 + a * a) * np.arctan(b / np.sqrt(1 + a * a))
                  + b / np.sqrt(1 + b * b) * np.arctan(a / np.sqrt(1 + b * b))) / (2 * np.pi)
        want = np.pi * (-0.3) * 4 * corner
        got = float(ch.diffuse(np.array([[0.0, h, 0.0]], np.float32),
                               np.array([[0.0, -1.0, 0.0]], np.float32))[0, 0])
        assert abs(got - want) < 0.02 * abs(want), (h, got, want)
    # a field linear in the plane's u: the mirror ray from (0.05, 0.1, 0) seen from above at
    # 45° meets the plane at x = 0.15, u = 0.15/half
    t = 64
    col = (np.arange(t) + 0.5) * 2.0 / t - 1.0
    field = np.broadcast_to(col[None, :, None], (t, t, 1)).copy()
    ch, axes = _change(field, half=half)
    p = np.array([[0.05, 0.1, 0.0]], np.float32)
    n = np.array([[0.0, 1.0, 0.0]], np.float32)
    v = np.array([[-1.0, 1.0, 0.0]], np.float32) / np.sqrt(2.0)
    hit_x = 0.05 + 0.1  # reflected direction (1, −1, 0)/√2 from height 0.1
    want = (np.array([hit_x, 0.0, 0.0]) @ axes[0]) / half
    got = float(ch.mirrored(p, n, v)[0, 0])
    assert abs(got - want) < 0.02
    assert float(ch.mirrored(p, n, np.array([[1.0, 0.0, 0.0]], np.float32))[0, 0]) == 0.0


@pytest.mark.parametrize(("radius", "height", "offset"),
                         [(0.01, 0.005, 0.0), (0.015, 0.004, 0.03), (0.01, 0.02, -0.05)])
def test_table_change_next_to_a_contact_shadow(radius, height, offset):
    """A contact shadow much smaller than the coarse cells (ΔL = −1 over a disc of 1–1.5 cm
    in a 40 cm region of 16 × 16 cells), seen from a few millimetres above it by a point
    facing down: against the sum of ΔL cos² / d² over the field's texels (the exact integral
    of the texelised disc). The near-field cells around the point's foot carry it (within
    15 %); the coarse cells alone spread it over 2.5 cm and gave 3–40 % of it."""
    from spectral_fit.rendering._surfaces import _plane_axes

    half, t = 0.2, 256
    axes = _plane_axes(np.array([0.0, 1.0, 0.0]))
    col, row = np.meshgrid(np.arange(t), np.arange(t))
    u = (col + 0.5) * 2.0 / t - 1.0
    v = 1.0 - (row + 0.5) * 2.0 / t
    world = half * (u[..., None] * axes[0] + v[..., None] * axes[1])
    foot = np.array([offset, 0.0, 0.0])
    d2 = np.sum((world - foot) ** 2, -1)
    field = np.where(d2 < radius ** 2, -1.0, 0.0)[..., None]
    want = float(np.sum(field[..., 0] * height ** 2 / (d2 + height ** 2) ** 2)
                 * (2.0 * half / t) ** 2)
    point = np.array([[offset, height, 0.0]], np.float32)
    down = np.array([[0.0, -1.0, 0.0]], np.float32)
    ch, _ = _change(field, half=half)
    got = float(ch.diffuse(point, down)[0, 0])
    assert got == pytest.approx(want, rel=0.15)
    coarse, _ = _change(field, half=half, split=1)
    assert abs(float(coarse.diffuse(point, down)[0, 0])) < 0.5 * abs(want)
