"""Objects made of parts with a material each: face labels of OBJ groups and PLY face
properties, the parts a config makes of one mesh (their union is the mesh, their poses the
body's, each centred on its own box), bad input, a convex mesh split into parts rendering as the
whole, and the geometric tail of an object's own light against the closed form of its series.
The comparison with the committed path-traced reference of configs/parts.toml (a cup glazed
inside beside a torus) is in tests/test_mesh_references.py."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import ANCHOR_ENV, ROOT

from spectral_fit._runtime.errors import InputError
from spectral_fit.io import face_labels, icosphere, load_mesh, load_scene, parse_scene


def _obj_text() -> str:
    # a unit square in z = 0 (two triangles, group "a"), then a triangle above it (groups "a"
    # and "b", material "m"), all in object "thing"
    return """o thing
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 0 0 1
v 1 0 1
v 0 1 1
g a
f 1 2 3 4
g a b
usemtl m
f 5 6 7
"""


def test_obj_groups_objects_and_materials_label_faces(tmp_path):
    p = tmp_path / "thing.obj"
    p.write_text(_obj_text())
    mesh, labels = load_mesh(p), face_labels(p)
    assert mesh.num_triangles == 3  # the quad as a fan of two triangles
    assert sorted(labels) == ["a", "b", "m", "thing"]
    np.testing.assert_array_equal(labels["a"], [True, True, True])
    np.testing.assert_array_equal(labels["b"], [False, False, True])
    np.testing.assert_array_equal(labels["m"], [False, False, True])
    np.testing.assert_array_equal(labels["thing"], [True, True, True])
    # the labelled triangle is the one at z = 1
    z = mesh.vertices[mesh.triangles[labels["b"]]][..., 2]
    assert np.all(z == 1.0)


def test_ply_material_index_labels_the_glazed_cups_inside():
    """scripts/make_meshes.py labels the inner wall and floor 1: checked here against the
    cup's geometry (60 mm across, 4 mm wall, floor 6 mm above the base, base at y = 0, the
    inner wall up to 68 mm, where the rounded lip begins)."""
    path = ROOT / "measurements" / "meshes" / "cup_glazed.ply"
    mesh, labels = load_mesh(path), face_labels(path)
    assert sorted(labels) == ["0", "1"]
    c = mesh.vertices[mesh.triangles].mean(axis=1).astype(np.float64)
    r = np.hypot(c[:, 0], c[:, 2])
    inside = (r < 0.026 + 1e-5) & (c[:, 1] > 0.006 - 1e-5) & (c[:, 1] < 0.068)
    np.testing.assert_array_equal(labels["1"], inside)
    np.testing.assert_array_equal(labels["0"], ~inside)
    # the same triangles as the unlabelled cup's, in the same order
    plain = load_mesh(ROOT / "measurements" / "meshes" / "cup.ply")
    np.testing.assert_array_equal(plain.triangles, mesh.triangles)


def test_ascii_ply_with_a_named_property(tmp_path):
    p = tmp_path / "two.ply"
    p.write_text("""ply
format ascii 1.0
element vertex 4
property float x
property float y
property float z
element face 2
property list uchar int vertex_indices
property int region
end_header
0 0 0
1 0 0
1 1 0
0 1 0
3 0 1 2 7
3 0 2 3 9
""")
    assert face_labels(p) == {}  # "region" is not a name the loader knows
    labels = face_labels(p, ply_property="region")
    assert sorted(labels) == ["7", "9"]
    np.testing.assert_array_equal(labels["9"], [False, True])
    with pytest.raises(InputError) as e:
        face_labels(p, ply_property="colour")
    assert e.value.field == "face.colour" and "two.ply" in str(e.value)


def _part_world_triangles(scene, names):
    out = []
    for o in scene.objects:
        if o.name in names:
            m = o.make_mesh(world=True)
            out.append(m.vertices[m.triangles])
    return np.concatenate(out)


def _sorted_rows(t):
    t = np.round(np.asarray(t, np.float64).reshape(len(t), -1), 6)
    return t[np.lexsort(t.T[::-1])]


def test_parts_config_splits_the_mesh_at_the_bodys_pose():
    scene = load_scene(ROOT / "configs" / "parts.toml")
    assert [o.name for o in scene.objects] == ["cup", "cup.glaze", "torus"]
    cup, glaze, torus = scene.objects
    assert cup.body == glaze.body == "cup" and torus.body is None
    assert glaze.faces == ("1",) and cup.faces_except == ("1",)
    assert glaze.material.mu == 0.05 and cup.material.mu == 0.25
    # the parts' triangles in the world are the whole mesh's at the table's pose
    import dataclasses

    whole = dataclasses.replace(cup, faces_except=(), part_origin=(0.0, 0.0, 0.0))
    m = whole.make_mesh(world=True)
    np.testing.assert_allclose(
        _sorted_rows(_part_world_triangles(scene, {"cup", "cup.glaze"})),
        _sorted_rows(m.vertices[m.triangles]), atol=2e-6)
    # each part's origin (the renderer's centre of the object) is its box's centre
    for o in (cup, glaze):
        v = o.make_mesh(world=True).vertices
        np.testing.assert_allclose(o.model_matrix()[:3, 3], 0.5 * (v.min(0) + v.max(0)),
                                   atol=1e-6)
        lo = o.make_mesh().vertices
        np.testing.assert_allclose(0.5 * (lo.min(0) + lo.max(0)), 0.0, atol=1e-6)
    # the glaze's box: the inner wall and floor (radius 26 mm, from 6 to 68 mm)
    np.testing.assert_allclose(glaze.part_origin, (0.0, 0.037, 0.0), atol=1e-6)
    # a marker moves the parts together (the live tracker's object-from-marker matrices)
    from spectral_fit.live._markers import MarkerTracker

    posed = scene.replace(objects=tuple(
        dataclasses.replace(o, marker=3, marker_offset=(0.01, 0.0, 0.02))
        for o in scene.objects[:2]) + scene.objects[2:])
    local = MarkerTracker(posed)._local
    for k, o in enumerate(posed.objects[:2]):
        v = o.make_mesh().vertices.astype(np.float64)
        moved = v @ local[k][:3, :3].T + local[k][:3, 3]
        ref = dataclasses.replace(o, position=(0.01, 0.0, 0.02), part_origin=(0.0, 0.0, 0.0))
        np.testing.assert_allclose(moved, (v + o.part_origin) @ ref.model_matrix()[:3, :3].T
                                   + ref.model_matrix()[:3, 3], atol=1e-7)


def _config(mesh: str, parts: str, *, extra: str = "") -> dict:
    import tomllib

    return tomllib.loads(f"""
[environment]
file = "{ANCHOR_ENV.as_posix()}"
rotation_y_deg = 180.0

[spectral]
start_nm = 400.0
end_nm = 700.0
step_nm = 10.0

[[objects]]
name = "thing"
shape = "mesh"
mesh = "{mesh}"
{extra}
{parts}
""")


@pytest.mark.parametrize("parts, field, words", [
    ('[[objects.parts]]\nname = "lid"\n', "objects[0].parts[0].faces", "labels no face"),
    ('[[objects.parts]]\nname = "x"\nfaces = ["a"]\n[[objects.parts]]\nname = "y"\n'
     'faces = ["b"]\n', "objects[0].parts[1].faces", "overlap"),
    ('[[objects.parts]]\nname = "x"\nfaces = []\n', "objects[0].parts[0].faces", "list"),
    ('parts = 3\n', "objects[0].parts", "array of tables"),
])
def test_bad_parts_name_the_file_and_the_key(tmp_path, parts, field, words):
    p = tmp_path / "thing.obj"
    p.write_text(_obj_text())
    with pytest.raises(InputError) as e:
        parse_scene(_config(p.as_posix(), parts), path=tmp_path / "scene.toml")
    assert e.value.field == field and words in str(e.value), str(e.value)
    assert "scene.toml" in str(e.value)


def test_parts_need_a_mesh_with_labels(tmp_path):
    p = tmp_path / "plain.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                 "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                 "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    with pytest.raises(InputError) as e:
        parse_scene(_config(p.as_posix(), '[[objects.parts]]\nname = "x"\n'),
                    path=tmp_path / "scene.toml")
    assert e.value.field == "objects[0].parts" and "names no sets of faces" in str(e.value)
    o = tmp_path / "thing.obj"
    o.write_text(_obj_text())
    with pytest.raises(InputError) as e:
        parse_scene(_config(o.as_posix(), '[[objects.parts]]\nname = "a"\n',
                            extra='part_property = "material_index"'),
                    path=tmp_path / "scene.toml")
    assert e.value.field == "objects[0].part_property"


def _split_sphere_scene(tmp_path, split: bool, mode: str = "gather"):
    """A 40 mm icosphere (as an OBJ; split: its faces above y = 0 group "top", the rest
    "bottom", each part the same material) beside a red sphere, 64 × 48."""
    m = icosphere(0.02, 2)
    c = m.vertices[m.triangles].mean(axis=1)
    top = c[:, 1] > 0
    lines = [f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in m.vertices]
    lines += [f"vn {x:.7f} {y:.7f} {z:.7f}" for x, y, z in m.normals]
    for name, sel in (("top", top), ("bottom", ~top)):
        lines.append(f"g {name}")
        lines += ["f " + " ".join(f"{i + 1}//{i + 1}" for i in t) for t in m.triangles[sel]]
    p = tmp_path / "ball.obj"
    p.write_text("\n".join(lines) + "\n")
    material = """reflectance = "colourchecker:ColorChecker N Ohta/yellow"
mu = 0.1
chi = 0.02
"""
    parts = "" if not split else "".join(
        f'[[objects.parts]]\nname = "{n}"\n[objects.parts.material]\n{material}\n'
        for n in ("top", "bottom"))
    import tomllib

    data = tomllib.loads(f"""
[frame]
width = 64
height = 48

[camera]
fov_y_deg = 30.0
position = [0.0, 0.03, 0.0]
look_at = [0.0, 0.0, -0.2]

[environment]
file = "{ANCHOR_ENV.as_posix()}"
rotation_y_deg = 180.0

[spectral]
start_nm = 400.0
end_nm = 700.0
step_nm = 50.0

[interreflection]
mode = "{mode}"
bounces = 2

[[objects]]
name = "ball"
shape = "mesh"
mesh = "{p.as_posix()}"
position = [-0.022, 0.0, -0.2]
rotation_deg = [10.0, 30.0, 0.0]

[objects.material]
{material}
{parts}
[[objects]]
name = "red"
shape = "icosphere"
radius = 0.018
subdivisions = 3
position = [0.022, -0.002, -0.205]

[objects.material]
reflectance = "colourchecker:ColorChecker N Ohta/red"
""")
    return parse_scene(data, path=tmp_path / "scene.toml")


@pytest.mark.parametrize("mode", ["none", pytest.param("gather", marks=pytest.mark.slow)])
def test_a_convex_mesh_split_into_parts_renders_as_the_whole(tmp_path, mode):
    """Two parts with the same material are the same surface: the frame matches the unsplit
    object's (the parts' origins are their own, their self-visibility their own triangles';
    a convex surface hides nothing of itself, and its parts exchange no light)."""
    from spectral_fit.rendering import prepare, render_frame, scene_materials

    frames = []
    for split in (False, True):
        scene = _split_sphere_scene(tmp_path, split, mode)
        assert len(scene.objects) == (3 if split else 2)
        prep = prepare(scene, mode=mode)
        fr = render_frame(prep, scene_materials(scene))
        frames.append((np.asarray(fr.xyz, np.float64), np.asarray(fr.object_id)))
    (xa, ida), (xb, idb) = frames
    obj_a, obj_b = ida >= 0, idb >= 0
    assert np.array_equal(obj_a, obj_b) and obj_a.sum() > 200
    assert np.all(np.isfinite(xb))
    # the red neighbour is the last object in both
    assert np.array_equal(ida == 1, idb == 2)
    y_a, y_b = xa[..., 1][obj_a], xb[..., 1][obj_b]
    rel = np.abs(y_b / y_a - 1.0)
    assert np.median(rel) < 2e-3 and np.percentile(rel, 99) < 0.02, (
        np.median(rel), np.percentile(rel, 99), rel.max())


def test_geometric_tail_matches_the_series_closed_form():
    """x = Σ_k M^k b = (I − M)^-1 b for a non-negative M of spectral radius 0.85 (the sums of
    a white cup's inside): four steps and the tail against the solve, per channel."""
    from spectral_fit.rendering._occlusion import _series_rest

    rng = np.random.default_rng(3)
    P = 40
    base = rng.random((P, P))
    xs, exact = [], []
    for rho in (0.85, 0.6, 0.3):
        m = base / np.abs(np.linalg.eigvals(base)).max() * rho
        b = rng.random(P)
        exact.append(np.linalg.solve(np.eye(P) - m, b))
        x, steps = b.copy(), []
        for _ in range(3):  # bounces = 4: three Jacobi steps after b
            new = b + m @ x
            steps.append(new - x)
            x = new
        xs.append((x, steps))
    x4 = np.stack([x for x, _ in xs], 1)
    prev = np.stack([s[-2] for _, s in xs], 1)
    last = np.stack([s[-1] for _, s in xs], 1)
    exact = np.stack(exact, 1)
    done = x4 + np.asarray(_series_rest(prev, last, per_channel=True))
    err_trunc = np.abs(x4 / exact - 1).max(axis=0)
    err_tail = np.abs(done / exact - 1).max(axis=0)
    assert err_trunc[0] > 0.3  # four steps miss a third of the bright channel's light
    assert np.all(err_tail < 0.01), err_tail
    # basis mode: one ratio for all channels (their norms)
    one = x4[:, :1] + np.asarray(_series_rest(prev[:, :1], last[:, :1], per_channel=False))
    assert np.abs(one[:, 0] / exact[:, 0] - 1).max() < 0.01


def test_look_at_a_point_from_itself_is_the_default_camera():
    """Two parts whose boxes share a centre (a hollow ball's inner and outer surface) put a
    pass-1 camera at its own target: finite, looking along −Z (their pair is emptied)."""
    from spectral_fit.geometry import look_at

    v = np.asarray(look_at([0.1, 0.2, 0.3], [0.1, 0.2, 0.3]))
    np.testing.assert_allclose(v[:3, :3], np.eye(3), atol=1e-7)
    np.testing.assert_allclose(v[:3, 3], [-0.1, -0.2, -0.3], atol=1e-7)
