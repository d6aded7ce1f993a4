"""The committed references of scenes of any shape (measurements/reference/{any_shape, on_table,
flat_faces, four_objects, parts, sun_shadow}.npz): made from today's configs and meshes,
patches where the camera sees one object (checked with exact ray casts against the slabs, the
spheres and the table plane, not with our rasteriser), the sun's shadow of a slab where rays
cast at its exact box put it, labels reproduced from the stored spectra, noise as
recorded; the region report's arithmetic; (slow) `spectral-fit validate` of every scene against
its targets or, where a target is missed today, against today's figures as a regression bound.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
from helpers import ROOT

from spectral_fit.color import xyz_weights
from spectral_fit.io import load_scene
from spectral_fit.validation.reference import load_reference
from spectral_fit.validation.reference.render import camera_rays, sphere_hits

NAMES = ["any_shape", "on_table", "flat_faces", "four_objects", "parts", "sun_shadow"]


@pytest.fixture(scope="module", params=NAMES)
def ref(request):
    return load_reference(request.param)


def _digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_reference_is_of_todays_config_and_meshes(ref):
    """The reference was rendered from the config's scene as it is today (its parsed TOML
    without our renderer's own tables, which the path tracer does not read) and today's
    meshes; frame, bands, patch grid and objects as the config says."""
    from spectral_fit.validation.reference.generate import scene_sha256

    scene = load_scene(ROOT / ref.config)
    m = ref.metadata
    assert m["layout"] == "grid"
    assert m["scene_sha256"] == scene_sha256(ROOT / ref.config)
    assert m["meshes_sha256"] == {o.name: _digest(o.mesh) for o in scene.objects
                                  if o.mesh is not None}
    assert np.allclose(ref.wavelengths, scene.wavelengths)
    assert ref.wavelengths[0] == 400 and ref.wavelengths[-1] == 700 and ref.wavelengths.size == 31
    assert m["frame"] == [scene.width, scene.height] == [720, 480]
    assert ref.object_names == tuple(o.name for o in scene.objects)
    assert m["depths"] == [2, 16] and m["passes"] >= 4 and len(m["seeds"]) == m["passes"]
    # 5×5 squares of the frame grid from column and row 1 (one-pixel border fits)
    b = ref.boxes
    assert np.all(b[:, 2:] - b[:, :2] == 5)
    assert np.all(b[:, :2] % 5 == 1)
    assert np.all(b[:, :2] >= 1) and np.all(b[:, 2:] <= [scene.width - 1, scene.height - 1])
    assert len({tuple(x) for x in b}) == len(b)
    # every object has patches
    assert set(ref.object_index[ref.object_index >= 0]) == set(range(len(scene.objects)))


def test_labels_and_shares_follow_from_the_stored_spectra(ref):
    wy = xyz_weights(ref.wavelengths)[:, 1]
    obj = ref.object_index >= 0
    y16, y2 = ref.spectra @ wy, ref.direct @ wy
    frac = (y16 - y2) / y16
    # float16 storage: shares within 2e-3 of the full-precision ones
    assert np.allclose(frac[obj], ref.ir_fraction[obj], atol=2e-3)
    # interreflection only adds light (beyond 4 standard errors)
    assert np.all(ref.ir_fraction[obj] > -4 * ref.ir_noise[obj] - 2e-3)
    thr = ref.metadata["threshold"]
    assert thr == 0.02
    expect = np.where(~obj, "table", np.where(ref.ir_fraction > thr, "interreflection",
                                              "direct"))
    assert np.array_equal(ref.labels, expect)
    assert ref.metadata["ir_patches"] == int((ref.labels == "interreflection").sum()) > 10
    assert (ref.labels == "direct").sum() > 50
    assert np.all(ref.spectra > 0) and np.all(ref.noise[obj] > 0)


def test_noise_is_as_recorded_and_below_the_targets(ref):
    m = ref.metadata
    assert np.isclose(np.median(ref.noise_de), m["noise_de_median"], rtol=1e-3)
    # the reference's own ΔE00 noise stays below the tightest median target (0.3)
    assert m["noise_de_median"] < 0.25
    rel = ref.noise / ref.spectra
    assert np.isclose(np.median(rel), m["median_relative_noise"], rtol=2e-2)
    # the spread of the passes vs the noise expected from the sample count: the standard error
    # falls as 1/√spp; 256 spp gave 0.9 % median (any_shape), so spp·rel² is of one order
    assert 0.3 < m["spp"] * m["median_relative_noise"] ** 2 / (256 * 0.009 ** 2) < 3.0


def test_preview_agrees_with_the_patch_spectra(ref):
    """The preview (depth-16 XYZ, block means of step × step pixels) over each patch's box
    against the patch's XYZ from its spectrum (blocks straddle the patch's one-pixel border,
    which shows the same object)."""
    x0, y0, w, h = ref.metadata["crop"]
    step = ref.metadata["preview_step"]
    big = np.repeat(np.repeat(ref.preview_xyz, step, axis=0), step, axis=1)
    assert big.shape == (h, w, 3)
    sel = ref.object_index >= 0
    shifted = ref.boxes[sel] - np.array([x0, y0, x0, y0])
    y = np.array([big[b:d, a:c, 1].mean() for a, b, c, d in shifted])
    rel = y / ref.xyz()[sel, 1] - 1.0
    assert np.median(np.abs(rel)) < 0.01 and np.percentile(np.abs(rel), 90) < 0.05


def _ray_box(o, d, lo, hi):
    """Entry distance (N,) of rays o + t d (d (N, 3)) into the axis-aligned box [lo, hi]
    (inf where missed)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    tn = np.nanmax(np.minimum(t1, t2), axis=1)
    tf = np.nanmin(np.maximum(t1, t2), axis=1)
    return np.where((tf >= tn) & (tf > 0), tn, np.inf)


def _corner_rays(scene, boxes):
    """Rays through the centre and the four corners of each patch's one-pixel border."""
    pts = [(0.5 * (boxes[:, 0] + boxes[:, 2]), 0.5 * (boxes[:, 1] + boxes[:, 3]))]
    for cx, cy in ((0, 1), (2, 1), (0, 3), (2, 3)):
        pts.append((boxes[:, cx] + (-0.5 if cx == 0 else 0.5),
                    boxes[:, cy] + (-0.5 if cy == 1 else 0.5)))
    return [camera_rays(scene, x, y) for x, y in pts]


def test_flat_faces_patches_see_their_slab_first():
    """Exact ray casts against the two slabs (axis-aligned boxes, no rotation): the rays
    through each patch's centre and the corners of its border meet the patch's slab first."""
    ref = load_reference("flat_faces")
    scene = load_scene(ROOT / ref.config)
    half = np.array([0.035, 0.045, 0.006])
    for o in scene.objects:
        assert o.rotation_deg == (0.0, 0.0, 0.0) and o.scale == 1.0
    # the slabs' large faces are parallel and 4 mm apart, overlapping
    zb, zf = scene.objects[0].position[2], scene.objects[1].position[2]
    assert (zf - half[2]) - (zb + half[2]) == pytest.approx(0.004, abs=1e-9)
    for o_ray, d in _corner_rays(scene, ref.boxes):
        t = np.stack([_ray_box(o_ray, d, np.asarray(o.position) - half,
                               np.asarray(o.position) + half) for o in scene.objects])
        assert np.all(np.isfinite(t.min(axis=0)))
        assert np.array_equal(t.argmin(axis=0), ref.object_index)


def _cup_wall(o, d, base, radius, height):
    """Distance (N,) along rays o + t d (d (N, 3)) to the outside of an upright open cylinder
    (axis +y from ``base``), inf where they miss it, and the hit's outward normal (N, 3)."""
    rel = o - base
    a = d[:, 0] ** 2 + d[:, 2] ** 2
    b = 2.0 * (rel[0] * d[:, 0] + rel[2] * d[:, 2])
    c = rel[0] ** 2 + rel[2] ** 2 - radius ** 2
    disc = b * b - 4.0 * a * c
    t = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a), np.inf)
    y = rel[1] + t * d[:, 1]
    t = np.where((t > 0) & (y >= 0.0) & (y <= height), t, np.inf)
    hit = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    n = hit - base
    n[:, 1] = 0.0
    return t, n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def test_sun_shadow_reference_shows_the_slab_s_shadow_where_rays_say():
    """sun_shadow: rays cast from the cup's patches towards the map's sun (its brightest
    texel's direction) against the slab's exact (rotated) box split the cup's patches facing
    the sun into lit and shadowed ones, both present; in the path-traced reference (depth 2,
    the direct light) the lit ones are several times brighter: the reference holds the box's
    shadow of the sun, with its edge across the cup, where the geometry puts it."""
    from spectral_fit.io import read_spectral_exr

    ref = load_reference("sun_shadow")
    scene = load_scene(ROOT / ref.config)
    cup, slab = scene.objects
    assert cup.rotation_deg == (0.0, 0.0, 0.0) and slab.rotation_deg[0] == slab.rotation_deg[2] == 0
    wl, img = read_spectral_exr(ROOT / "measurements" / "environment" / "sunny.exr")
    lum = img @ xyz_weights(wl)[:, 1]
    r, c = np.unravel_index(np.argmax(lum), lum.shape)
    th, ph = (r + 0.5) / lum.shape[0] * np.pi, (c + 0.5) / lum.shape[1] * 2 * np.pi
    sun = np.array([np.sin(ph) * np.sin(th), np.cos(th), -np.cos(ph) * np.sin(th)])
    yaw = np.radians(slab.rotation_deg[1])
    rot = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    half = np.array([0.035, 0.045, 0.006])
    base = np.asarray(cup.position)
    on_cup = ref.object_index == 0
    lit = np.ones(ref.num_patches, bool)
    shade = np.ones(ref.num_patches, bool)
    for o_ray, d in _corner_rays(scene, ref.boxes):
        t, n = _cup_wall(np.asarray(o_ray), d, base, 0.03, 0.065)
        p = np.asarray(o_ray) + np.where(np.isfinite(t), t, 0.0)[:, None] * d
        facing = np.isfinite(t) & (n @ sun > 0.3)
        q = (p - np.asarray(slab.position)) @ rot  # the slab's frame
        blocked = np.isfinite(_ray_box(q, np.tile(sun @ rot, (len(q), 1)), -half, half))
        lit &= facing & ~blocked
        shade &= facing & blocked
    lit &= on_cup
    shade &= on_cup
    assert lit.sum() >= 5 and shade.sum() >= 5, (lit.sum(), shade.sum())
    y2 = ref.direct @ xyz_weights(ref.wavelengths)[:, 1]
    assert np.median(y2[lit]) > 3.0 * np.median(y2[shade]), (np.median(y2[lit]),
                                                            np.median(y2[shade]))


def test_four_objects_sizes_and_sphere_patches():
    """Radii differing by ≥ 4× (bounding radii of all four); the small sphere 4 mm from the
    large one; patches of the two spheres meet their exact sphere (ray cast) before the
    other's."""
    from spectral_fit.validation.reference.patches import object_spheres

    ref = load_reference("four_objects")
    scene = load_scene(ROOT / ref.config)
    centres, radii = object_spheres(scene)
    assert radii.max() / radii.min() >= 4.0
    assert [o.shape for o in scene.objects] == ["uv_sphere", "uv_sphere", "mesh", "mesh"]
    big, small = scene.objects[:2]
    gap = np.linalg.norm(np.subtract(big.position, small.position)) - big.radius - small.radius
    assert gap == pytest.approx(0.004, abs=2e-4)
    sel = ref.object_index <= 1
    for o_ray, d in _corner_rays(scene, ref.boxes[sel]):
        t = np.stack([sphere_hits(o_ray, d, s.position, s.radius) for s in (big, small)])
        first = t.argmin(axis=0)
        assert np.all(np.isfinite(t.min(axis=0)))
        assert np.array_equal(first, ref.object_index[sel])
    # the small sphere's patches facing the large one gather > 2 % interreflection
    small_ir = ref.ir_fraction[ref.object_index == 1]
    assert small_ir.size >= 10 and small_ir.max() > 0.1


def test_on_table_patches_lie_near_their_object():
    """Table patches: the ray through the centre meets the plane y = 0 within 2 bounding radii
    of the object named by ``near`` (its centre dropped onto the plane), and in front of every
    sphere; the table's light makes most object patches > 2 %."""
    from spectral_fit.validation.reference.patches import object_spheres

    ref = load_reference("on_table")
    scene = load_scene(ROOT / ref.config)
    table = ref.object_index < 0
    assert table.sum() > 100 and np.all(ref.near[table] >= 0) and np.all(ref.near[~table] == -1)
    b = ref.boxes[table]
    o, d = camera_rays(scene, 0.5 * (b[:, 0] + b[:, 2]), 0.5 * (b[:, 1] + b[:, 3]))
    t = -o[1] / d[:, 1]
    p = o + t[:, None] * d
    assert np.all(t > 0) and np.allclose(p[:, 1], 0.0, atol=1e-12)
    centres, radii = object_spheres(scene)
    k = ref.near[table]
    dist = np.linalg.norm((p - centres[k])[:, [0, 2]], axis=1) / radii[k]
    assert np.all(dist <= 2.0 + 1e-9)
    for s in scene.objects[:2]:
        assert np.all(t < sphere_hits(o, d, s.position, s.radius))
    obj = ~table
    assert np.mean(ref.ir_fraction[obj] > 0.02) > 0.5


def test_region_report_arithmetic():
    """Statistics and pass/fail against hand-computed values on a synthetic reference."""
    from types import SimpleNamespace

    from spectral_fit.validation import SCENE_TARGETS, region_report

    n = 21
    labels = np.array(["direct"] * 10 + ["interreflection"] * 10 + ["table"])
    ref = SimpleNamespace(object_index=np.array([0] * 20 + [-1]), labels=labels,
                          ir_fraction=np.array([0.01] * 10 + [0.05] * 10 + [np.nan]),
                          noise_de=np.full(n, 0.1), num_patches=n)
    de = np.concatenate([np.arange(10) * 0.1, np.arange(10) * 0.5, [4.0]])
    r = region_report(ref, de)
    low = r["objects, interreflection < 2 %"]
    # 0.0 … 0.9: median 0.45, p90 0.81 (linear interpolation), max 0.9
    assert (low["n"], low["median"], low["p90"], low["max"]) == pytest.approx((10, 0.45, 0.81,
                                                                                0.9))
    assert low["pass"] == {"median": False, "p90": False, "max": True} and not low["ok"]
    high = r["objects, interreflection > 2 %"]
    assert (high["median"], high["max"]) == pytest.approx((2.25, 4.5))
    tab = r["table near objects"]
    assert tab["n"] == 1 and tab["max"] == 4.0 and tab["pass"]["median"] is False
    assert low["targets"] == SCENE_TARGETS["objects, interreflection < 2 %"]
    assert low["reference_noise_de"]["median"] == pytest.approx(0.1)


def test_pixel_means_are_the_area_means_of_the_sub_pixels():
    """The box filter validate puts on our frame (the references' pixels are area means): a
    checkerboard of sub-pixels averages to its mean in every pixel; a linear ramp sampled at
    the sub-pixel centres averages to the ramp at the pixel's centre (closed form of the
    area mean of a linear function); a frame that is not s × a size, and samples outside
    1..4, are refused naming the field."""
    from spectral_fit import InputError
    from spectral_fit.validation import check_samples, pixel_means

    s, h, w = 3, 4, 5
    yy, xx = np.mgrid[0:h * s, 0:w * s]
    board = ((yy + xx) % 2).astype(float)[..., None] * [1.0, 2.0]
    got = pixel_means(board, s)
    assert got.shape == (h, w, 2)
    # s odd: each pixel holds (s² ± 1)/2 ones; mean 0.5 ± 1/(2 s²)
    assert np.all(np.abs(got[..., 0] - 0.5) <= 0.5 / s**2 + 1e-12)
    ramp = 0.3 * (xx + 0.5) / s - 0.7 * (yy + 0.5) / s + 2.0  # in pixel units
    cy, cx = np.mgrid[0:h, 0:w] + 0.5
    np.testing.assert_allclose(pixel_means(ramp, s), 0.3 * cx - 0.7 * cy + 2.0, atol=1e-12)
    with pytest.raises(ValueError, match="2"):
        pixel_means(np.zeros((5, 4, 3)), 2)
    assert check_samples(2) == 2
    for bad in (0, 5, 1.5, True):
        with pytest.raises(InputError, match="samples"):
            check_samples(bad)


def test_cli_validate_refuses_samples_outside_the_range(capsys):
    """`spectral-fit validate --samples 0` exits 2 naming the option, before rendering."""
    from spectral_fit.cli import main

    assert main(["validate", "any_shape", "--samples", "0"]) == 2
    err = capsys.readouterr().err
    assert "--samples" in err and "Traceback" not in err


# --------------------------------------------------------------------------------------------
# slow: `spectral-fit validate` of every committed scene

#: ΔE00 (median, p90, max) measured on the committed references where a target is missed
#: (docs/reference.md, "Scenes of any shape"); the regression bound is 1.1 × today + 0.05 for
#: those statistics, the target for every other one
MISSED = {
    "on_table": {"objects, interreflection > 2 %": (0.15, 0.75, 4.21)},
    "flat_faces": {"objects, interreflection > 2 %": (0.60, 1.23, 2.76)},
    "parts": {"objects, interreflection > 2 %": (0.29, 1.58, 1.90)},
    "sun_shadow": {"objects, interreflection < 2 %": (0.29, 1.26, 12.42),
                   "objects, interreflection > 2 %": (1.68, 6.99, 27.56)},
}


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES + ["benchmark", "two_spheres"])
def test_validate_every_scene(name, tmp_path):
    """`spectral-fit validate <name> --json -o picture` (2 × 2 samples per pixel): each
    region's median, p90 and max within its target where met today, else within 1.1 × today's
    figure + 0.05 (MISSED): on_table objects > 2 % max 4.21 (the cup's inside under its lip);
    flat_faces > 2 % median 0.60 (at the config's gather_size = 32; the back slab's face
    above and beside the front slab and the front slab's side face, 3–10 % off); parts > 2 %
    p90 1.58 (the glaze inside the cup 5 % too dark: its own glossy light); sun_shadow, the
    cup: every figure but the < 2 % median (a band under its rim facing the sun up to 2.2×
    too bright, the wall where the sun grazes it 20–27 % too dark). Met today: every
    other figure, all of benchmark's, two_spheres', any_shape's and four_objects' (the sphere
    references in gather, their regions split at 2 %). The picture is written where asked."""
    import subprocess
    import sys

    from helpers import subprocess_env

    fig = tmp_path / f"{name}.png"
    cmd = [sys.executable, "-m", "spectral_fit", "validate", name, "--json", "-o", str(fig)]
    if name in ("benchmark", "two_spheres"):
        cmd += ["--modes", "gather", "--k", "0"]
    out = subprocess.run(cmd, capture_output=True, text=True, env=subprocess_env(),
                         cwd=tmp_path, timeout=1800)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout)
    regions = {k: v for k, v in res["regions"].items() if k != "mode"}
    assert len(regions) >= 2
    missed = MISSED.get(name, {})
    for region, s in regions.items():
        for i, (stat, target) in enumerate(s["targets"].items()):
            today = missed.get(region, (0.0, 0.0, 0.0))[i]
            bound = 1.1 * today + 0.05 if today > target else target
            assert s[stat] <= bound, (name, region, stat, s[stat], bound)
    assert fig.is_file() and fig.stat().st_size > 10_000
