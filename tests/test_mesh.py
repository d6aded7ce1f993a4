"""Mesh generators, loaders and model matrices, checked against closed forms (counts, volume,
normals of a sphere) and hand-written files."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from spectral_fit._runtime.errors import InputError
from spectral_fit.io import (
    Mesh,
    concat_meshes,
    icosphere,
    is_closed_outward,
    load_mesh,
    load_obj,
    load_ply,
    rotate,
    rotate_x,
    rotate_y,
    rotate_z,
    scale,
    sphere,
    sphere_resolution,
    transform_normals,
    transform_points,
    translate,
    uv_sphere,
    vertex_normals,
)


def _edge_use(tris):
    """Directed edge → count; a closed, consistently oriented mesh uses every directed edge
    once and its reverse once."""
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    fwd = {tuple(x) for x in e.tolist()}
    assert len(fwd) == len(e), "a directed edge is used twice"
    return fwd


def _check_closed_sphere(m: Mesh, r: float, *, radial_normals=True, min_volume=0.97):
    fwd = _edge_use(m.triangles)
    assert all((b, a) in fwd for a, b in fwd), "open or inconsistently oriented"
    v = m.vertices.astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), r, rtol=1e-6)
    # outward (counter-clockwise seen from outside): face normals point away from the centre
    a, b, c = (v[m.triangles[:, k]] for k in range(3))
    fn = np.cross(b - a, c - a)
    assert np.all(np.sum(fn * (a + b + c), axis=1) > 0)
    # smooth normals = radial directions
    if radial_normals:
        np.testing.assert_allclose(m.normals, v / r, atol=2e-6)
    else:  # area-weighted face normals: close to radial on a fine sphere
        assert np.all(np.sum(m.normals * v / r, axis=1) > 0.99)
    # enclosed volume (divergence theorem) → 4/3 π r³ from below
    vol = np.sum(np.einsum("ij,ij->i", a, np.cross(b, c))) / 6
    assert min_volume * (4 / 3) * math.pi * r**3 < vol < (4 / 3) * math.pi * r**3
    return vol


@pytest.mark.parametrize("stacks, slices", [(100, 100), (3, 3), (7, 12)])
def test_uv_sphere_counts_normals_closed(stacks, slices):
    m = uv_sphere(0.0375, stacks, slices)
    assert m.num_triangles == 2 * slices * (stacks - 2) + 2 * slices
    assert len(m.vertices) == (stacks - 1) * slices + 2
    if (stacks, slices) == (100, 100):
        assert m.num_triangles == 19_800  # the paper's spheres
        _check_closed_sphere(m, 0.0375)
    else:
        _edge_use(m.triangles)


def test_uv_sphere_with_uvs_duplicates_the_seam_with_identical_positions():
    m = uv_sphere(1.0, 10, 16, with_uvs=True)
    assert m.num_triangles == 2 * 16 * 8 + 2 * 16
    assert m.uvs.shape == (len(m.vertices), 2)
    assert m.uvs.min() >= 0 and m.uvs.max() <= 1
    # welding bit-identical positions gives the closed mesh
    uniq, inv = np.unique(m.vertices, axis=0, return_inverse=True)
    welded = Mesh(uniq, inv.reshape(-1)[m.triangles])
    _check_closed_sphere(welded, 1.0, radial_normals=False, min_volume=0.9)
    # u = φ/2π with φ measured from +Z toward +X; v = θ/π from the north pole (+Y)
    ring = (m.uvs[:, 1] > 0) & (m.uvs[:, 1] < 1) & (m.uvs[:, 0] < 1)
    v = m.vertices[ring]
    phi = np.mod(np.arctan2(v[:, 0], v[:, 2]), 2 * np.pi)
    np.testing.assert_allclose(m.uvs[ring, 0], phi / (2 * np.pi), atol=1e-6)
    np.testing.assert_allclose(m.uvs[ring, 1], np.arccos(np.clip(v[:, 1], -1, 1)) / np.pi,
                               atol=1e-6)


@pytest.mark.parametrize("s", [0, 1, 3])
def test_icosphere_counts_normals_closed(s):
    m = icosphere(0.5, s)
    assert m.num_triangles == 20 * 4**s
    assert len(m.vertices) == 10 * 4**s + 2
    vol = _check_closed_sphere(m, 0.5, min_volume=0.85) if s else None
    if s == 0:  # the icosahedron's exact volume
        _edge_use(m.triangles)
        a = 0.5 / math.sin(2 * math.pi / 5)  # edge of an icosahedron of circumradius 0.5
        v = m.vertices.astype(np.float64)
        edge = np.linalg.norm(v[m.triangles[:, 0]] - v[m.triangles[:, 1]], axis=1)
        np.testing.assert_allclose(edge, a, rtol=1e-6)
    if s == 3:
        assert vol > 0.99 * (4 / 3) * math.pi * 0.125


def test_sphere_with_requested_triangle_count():
    assert sphere_resolution(19_800) == (100, 100)
    assert sphere_resolution(20 * 4**4, "ico") == 4
    for target in (500, 5000, 20000):
        m = sphere(1.0, target)
        assert abs(m.num_triangles - target) / target < 0.05
        mi = sphere(1.0, target, "ico")
        assert 0.5 * target <= mi.num_triangles <= 2 * target
    with pytest.raises(InputError, match="kind"):
        sphere(1.0, 100, "cube")


def test_vertex_normals_of_a_tetrahedron_corner():
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    t = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    n = vertex_normals(v, t)
    # corner 0 touches three faces of area 1/2 with normals −x, −y, −z
    np.testing.assert_allclose(n[0], -np.ones(3) / math.sqrt(3), atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, atol=1e-6)


def test_model_matrices_against_hand_built_transforms():
    p = np.array([[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(transform_points(translate((1, -2, 0.5)), p), [[2, 0, 3.5]])
    np.testing.assert_allclose(transform_points(scale((2, 3, 4)), p), [[2, 6, 12]])
    # right-handed: +90° about Y takes +X to −Z, about X takes +Y to +Z, about Z takes +X to +Y
    np.testing.assert_allclose(transform_points(rotate_y(math.pi / 2), [[1, 0, 0]]),
                               [[0, 0, -1]], atol=1e-12)
    np.testing.assert_allclose(transform_points(rotate_x(math.pi / 2), [[0, 1, 0]]),
                               [[0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(transform_points(rotate_z(math.pi / 2), [[1, 0, 0]]),
                               [[0, 1, 0]], atol=1e-12)
    r = rotate((1, 1, 1), 2 * math.pi / 3)  # cyclic permutation x → y → z
    np.testing.assert_allclose(transform_points(r, p), [[3, 1, 2]], atol=1e-12)
    # composition order: translate @ scale scales first
    np.testing.assert_allclose(transform_points(translate((1, 0, 0)) @ scale(2), p), [[3, 4, 6]])
    # normals under a non-uniform scale stay perpendicular to transformed tangents
    m = scale((1, 4, 1)) @ rotate((0.3, 1, -0.2), 0.7)
    n = np.array([[1.0, 1.0, 0.0]]) / math.sqrt(2)
    t = np.array([[1.0, -1.0, 0.3]])
    tn = transform_points(m, t) - transform_points(m, np.zeros((1, 3)))
    nn = transform_normals(m, n)
    assert abs(float(np.sum(nn * tn))) < 1e-12
    np.testing.assert_allclose(np.linalg.norm(nn), 1)
    with pytest.raises(InputError, match="axis"):
        rotate((0, 0, 0), 1.0)


def test_transformed_mesh_and_concat_offsets():
    s = icosphere(1.0, 1)
    moved = s.transformed(translate((0, 0, -3)) @ scale(0.5))
    np.testing.assert_allclose(np.linalg.norm(moved.vertices - [0, 0, -3], axis=1), 0.5,
                               rtol=1e-6)
    np.testing.assert_allclose(moved.normals, s.normals, atol=1e-6)
    both, offs = concat_meshes([s, moved])
    assert offs.tolist() == [0, 80, 160]
    np.testing.assert_array_equal(both.triangles[80:], s.triangles + len(s.vertices))
    np.testing.assert_allclose(both.vertices[both.triangles[80:]], moved.vertices[s.triangles])
    with pytest.raises(InputError, match="meshes"):
        concat_meshes([])


def test_mesh_rejects_bad_arrays():
    v = np.zeros((3, 3))
    with pytest.raises(InputError, match="vertices"):
        Mesh(np.zeros((3, 2)), [[0, 1, 2]])
    with pytest.raises(InputError, match="vertices"):
        Mesh(np.array([[0, 0, np.nan], [1, 0, 0], [0, 1, 0]]), [[0, 1, 2]])
    with pytest.raises(InputError, match="triangles"):
        Mesh(v, [[0, 1, 3]])
    with pytest.raises(InputError, match="triangles"):
        Mesh(v, [[0.0, 1.0, 2.0]])
    with pytest.raises(InputError, match="normals"):
        Mesh(v, [[0, 1, 2]], normals=np.zeros((2, 3)))
    with pytest.raises(InputError, match="uvs"):
        Mesh(v, [[0, 1, 2]], uvs=np.zeros((3, 3)))


# ----------------------------------------------------------------------------- files


def _corner_positions(m):
    return m.vertices[m.triangles].astype(np.float64)


def test_obj_round_trip_and_features(tmp_path):
    s = uv_sphere(0.5, 6, 8, with_uvs=True)
    lines = ["# test", "o ball", "mtllib none.mtl"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in s.vertices]
    lines += [f"vt {u:.9g} {v:.9g}" for u, v in s.uvs]
    lines += [f"vn {x:.9g} {y:.9g} {z:.9g}" for x, y, z in s.normals]
    lines += ["s 1", "usemtl red"]
    lines += ["f " + " ".join(f"{i + 1}/{i + 1}/{i + 1}" for i in t) for t in s.triangles]
    p = tmp_path / "ball.obj"
    p.write_text("\n".join(lines) + "\n")
    m = load_mesh(p)
    np.testing.assert_allclose(_corner_positions(m), _corner_positions(s), atol=1e-7)
    np.testing.assert_allclose(m.uvs[m.triangles], s.uvs[s.triangles], atol=1e-7)
    np.testing.assert_allclose(m.normals[m.triangles], s.normals[s.triangles], atol=1e-6)
    # a quad with negative indices and v//vn corners, fan-triangulated; w divides
    q = tmp_path / "quad.obj"
    q.write_text("v 0 0 0\nv 2 0 0 2\nv 1 1 0\nv 0 1 0\nvn 0 0 1\n"
                 "f -4//1 -3//1 -2//1 -1//1\n")
    m = load_obj(q)
    assert m.num_triangles == 2 and m.uvs is None
    np.testing.assert_allclose(_corner_positions(m),
                               [[[0, 0, 0], [1, 0, 0], [1, 1, 0]],
                                [[0, 0, 0], [1, 1, 0], [0, 1, 0]]])
    np.testing.assert_allclose(m.normals, np.tile([0, 0, 1], (len(m.vertices), 1)))
    # without normals: smooth normals are computed
    f = tmp_path / "flat.obj"
    f.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    np.testing.assert_allclose(load_obj(f).normals, np.tile([0, 0, 1], (3, 1)), atol=1e-7)


@pytest.mark.parametrize("text, line, field", [
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", 4, "f"),
    ("v 0 0 zero\n", 1, "v"),
    ("v 0 0\n", 1, "v"),
    ("v 0 0 0\nv 1 0 0\nf 1 2\n", 3, "f"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nbogus 1\n", 4, "bogus"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2 3\n", 5, "f"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/x 2 3\n", 4, "f"),
    ("v 0 0 nan\n", 1, "v"),
    ("v 0 0 0\n", None, "f"),
])
def test_malformed_obj_names_file_line_and_field(tmp_path, text, line, field):
    p = tmp_path / "bad.obj"
    p.write_text(text)
    with pytest.raises(InputError) as e:
        load_obj(p)
    assert e.value.path == str(p) and e.value.field == field and e.value.line == line
    assert str(p) in str(e.value)


def _ply_header(fmt, nv, nf, extra=""):
    return (f"ply\nformat {fmt} 1.0\ncomment test\nelement vertex {nv}\nproperty float x\n"
            f"property float y\nproperty float z\nproperty float nx\nproperty float ny\n"
            f"property float nz\nproperty float u\nproperty float v\n{extra}"
            f"element face {nf}\nproperty list uchar int vertex_indices\nend_header\n")


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_round_trip(tmp_path, fmt):
    s = uv_sphere(0.5, 5, 7, with_uvs=True)
    rows = np.concatenate([s.vertices, s.normals, s.uvs], 1).astype(np.float32)
    p = tmp_path / f"ball_{fmt}.ply"
    head = _ply_header(fmt, len(rows), s.num_triangles).encode()
    if fmt == "ascii":
        body = "".join(" ".join(f"{x:.9g}" for x in r) + "\n" for r in rows)
        body += "".join("3 " + " ".join(str(i) for i in t) + "\n" for t in s.triangles)
        p.write_bytes(head + body.encode())
    else:
        o = "<" if fmt.endswith("little_endian") else ">"
        body = b"".join(struct.pack(o + "8f", *r) for r in rows)
        body += b"".join(struct.pack(o + "B3i", 3, *t) for t in s.triangles.tolist())
        p.write_bytes(head + body)
    m = load_mesh(p)
    np.testing.assert_allclose(_corner_positions(m), _corner_positions(s), atol=1e-7)
    np.testing.assert_allclose(m.uvs[m.triangles], s.uvs[s.triangles], atol=1e-7)
    np.testing.assert_allclose(m.normals[m.triangles], s.normals[s.triangles], atol=1e-6)


@pytest.mark.parametrize("case, field", [
    ("magic", None), ("format", "format"), ("index", "face.vertex_indices"),
    ("truncated", "vertex"), ("no_x", "vertex.x"), ("nan", "vertex.x"),
    ("short_face", "face.vertex_indices"), ("truncated_binary", "vertex"),
])
def test_malformed_ply_names_file_and_field(tmp_path, case, field):
    head = _ply_header("ascii", 3, 1)
    verts = "0 0 0 0 0 1 0 0\n1 0 0 0 0 1 0 0\n0 1 0 0 0 1 0 0\n"
    face = "3 0 1 2\n"
    if case == "magic":
        data = "PLY\n" + head[4:] + verts + face
    elif case == "format":
        data = head.replace("ascii", "utf8") + verts + face
    elif case == "index":
        data = head + verts + "3 0 1 3\n"
    elif case == "truncated":
        data = head + verts[: verts.rindex("0 1 0")]
    elif case == "no_x":
        data = head.replace("property float x\n", "property float q\n") + verts + face
    elif case == "nan":
        data = head + verts.replace("1 0 0 0", "nan 0 0 0", 1) + face
    elif case == "short_face":
        data = head + verts + "2 0 1\n"
    else:
        data = _ply_header("binary_little_endian", 3, 1) + "\0" * 40
    p = tmp_path / "bad.ply"
    p.write_bytes(data.encode())
    with pytest.raises(InputError) as e:
        load_ply(p)
    assert e.value.path == str(p) and str(p) in str(e.value)
    if field is not None:
        assert e.value.field == field


def test_unknown_extension_and_missing_file(tmp_path):
    with pytest.raises(InputError, match="format"):
        load_mesh(tmp_path / "x.stl")
    with pytest.raises(InputError, match="cannot read"):
        load_mesh(tmp_path / "missing.obj")


def test_is_closed_outward():
    """Closed, consistently and outwardly wound meshes (the spheres, moved and rotated) pass;
    an opening (one triangle removed, or the seam of a UV sphere with uvs), inward winding, a
    single flipped triangle and a duplicated face do not."""
    for m in (uv_sphere(0.0375, 100, 100), uv_sphere(1.0, 3, 3), icosphere(2.0, 2)):
        moved = transform_points(translate((0.3, -2.0, 5.0)) @ rotate((1, 2, 3), 0.7),
                                 m.vertices)
        assert is_closed_outward(m.vertices, m.triangles)
        assert is_closed_outward(moved, m.triangles)
        assert not is_closed_outward(m.vertices, m.triangles[:, ::-1])  # inward
        assert not is_closed_outward(m.vertices, m.triangles[1:])  # an opening
        flip = m.triangles.copy()
        flip[0] = flip[0, ::-1]
        assert not is_closed_outward(m.vertices, flip)
        assert not is_closed_outward(m.vertices, np.concatenate([m.triangles, m.triangles[:1]]))
    seam = uv_sphere(1.0, 8, 8, with_uvs=True)
    assert not is_closed_outward(seam.vertices, seam.triangles)
    assert not is_closed_outward(np.zeros((3, 3)), np.zeros((0, 3), np.int32))
