"""configs/on_table.toml and the patch bookkeeping of scripts/table_reference.py (no Mitsuba, no
rendering)."""

from __future__ import annotations

import importlib.util
import tomllib

import numpy as np
import pytest

from spectral_fit._runtime.paths import REPO_ROOT

CONFIG = REPO_ROOT / "configs" / "on_table.toml"


@pytest.fixture(scope="module")
def tr():
    spec = importlib.util.spec_from_file_location(
        "table_reference", REPO_ROOT / "scripts" / "table_reference.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_on_table_objects_rest_on_the_plane(tr):
    scene, _, surfaces = tr.read_config(CONFIG, None, None)
    assert (scene.width, scene.height) == (720, 480)
    assert scene.interreflection.mode == "gather" and scene.interreflection.bounces == 2
    (table,) = surfaces
    n, p0 = table["normal"], table["point"]
    assert np.allclose(n, [0.0, 1.0, 0.0])
    assert 0.2 < table["reflectance"].mean() < 0.6
    assert [o.name for o in scene.objects] == ["yellow", "red", "cup"]
    for o in scene.objects:
        v = np.asarray(o.make_mesh(world=True).vertices, np.float64)
        height = (v - p0) @ n
        assert height.min() == pytest.approx(0.0, abs=2e-4), o.name  # touches the table
        if o.shape == "uv_sphere":
            assert (np.asarray(o.position) - p0) @ n == pytest.approx(o.radius)
    # the camera looks down at the table at 30–45° elevation
    cam = scene.camera
    d = np.asarray(cam.look_at) - np.asarray(cam.position)
    elev = np.degrees(np.arcsin(-(d @ n) / np.linalg.norm(d)))
    assert 30.0 <= elev <= 45.0
    # the same file without its surfaces is a plain objects-only config
    data = tomllib.loads(CONFIG.read_text())
    assert data["surfaces"][0]["shape"] == "plane"


def test_label_patches(tr):
    h, w = 18, 24
    obj = np.full((h, w), -1, np.int32)
    obj[0:12, 0:12] = 0   # object 0 over the top-left
    obj[0:7, 17:24] = 1   # object 1 at the top right
    surface = np.ones((h, w), bool)
    surface[:, 12:15] = False  # a strip of environment
    surface &= obj < 0
    boxes, owner, obj_of = tr.label_patches(obj, surface)
    ys, xs = tr.patch_grid(h, w)
    assert (ys.tolist(), xs.tolist()) == ([1, 6, 11], [1, 6, 11, 16])
    assert len(boxes) == 12 and (boxes[:, 2:] - boxes[:, :2] == 5).all()
    lab = {tuple(b[:2]): (int(o), int(k)) for b, o, k in zip(boxes, owner, obj_of, strict=True)}
    for x, y in ((1, 1), (6, 1), (1, 6), (6, 6)):
        assert lab[(x, y)] == (0, 0)             # object 0 with its whole border
    assert lab[(1, 11)] == (tr.MIXED, 0)         # object row 11, then table
    assert lab[(6, 11)] == (tr.MIXED, 0)
    assert lab[(16, 1)] == (tr.MIXED, 1)
    assert lab[(16, 6)] == (tr.MIXED, 1)
    assert lab[(16, 11)] == (tr.TABLE, -1)       # table with its whole border
    for y in (1, 6, 11):
        assert lab[(11, y)] == (tr.OTHER, -1)    # the environment strip
    # a patch of table with its whole border on the table
    obj2 = np.full((h, w), -1, np.int32)
    b2, o2, _ = tr.label_patches(obj2, np.ones((h, w), bool))
    assert (o2 == tr.TABLE).all()
    # grid means are the boxes' means
    img = np.random.default_rng(0).random((h, w, 2))
    gm = tr.grid_means(img).reshape(-1, 2)
    want = np.stack([img[y0:y1, x0:x1].mean((0, 1)) for x0, y0, x1, y1 in b2])
    assert np.allclose(gm, want)


def test_plane_geometry(tr):
    fr = tr.plane_frame([0.0, 0.0, 2.0])
    assert np.allclose(np.cross(fr[0], fr[1]), fr[2]) and np.allclose(fr @ fr.T, np.eye(3))
    o = np.array([0.0, 1.0, 0.0])
    d = np.array([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0], [0.6, -0.8, 0.0], [0.99, -0.141, 0.0]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    hit = tr.plane_hits(o, d, [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], half_size=5.0)
    assert np.allclose(hit[0], 0.0) and np.isnan(hit[1]).all()
    assert np.allclose(hit[2], [0.75, 0.0, 0.0]) and np.isnan(hit[3]).all()  # 7 m: outside
    centres = np.array([[0.0, 0.0375, 0.0], [1.0, 0.1, 0.0]])
    near = tr.near_object(np.array([[0.07, 0.0, 0.0], [0.08, 0.0, 0.0], [1.15, 0.0, 0.0],
                                    [np.nan] * 3]), centres, np.array([0.0375, 0.1]),
                          [0.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    assert near.tolist() == [0, -1, 1, -1]
    c, r = tr.bounding_sphere(np.array([[-1.0, 0.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 1.0]]))
    assert np.allclose(c, [0.0, 1.0, 0.5]) and r == pytest.approx(np.sqrt(2.25))
