"""The committed Mitsuba references (measurements/reference/*.npz), without Mitsuba: geometry
consistent with the configs, statistics self-consistent, the preview consistent with the patch
spectra, and (slow) the direct light of patches that cannot see the neighbour vs our own
environment shading."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import ANCHOR_ENV, ROOT

from spectral_fit._runtime.errors import InputError
from spectral_fit.color import xyz_weights
from spectral_fit.io import load_scene
from spectral_fit.validation.reference import load_reference
from spectral_fit.validation.reference.render import sphere_patches

NAMES = ["benchmark", "two_spheres"]


@pytest.fixture(scope="module", params=NAMES)
def ref(request):
    return load_reference(request.param)


def test_shapes_and_geometry_match_the_config(ref):
    scene = load_scene(ROOT / ref.config)
    assert np.allclose(ref.wavelengths, scene.wavelengths)
    assert ref.object_names == tuple(o.name for o in scene.objects)
    assert ref.metadata["frame"] == [scene.width, scene.height]
    pt = sphere_patches(scene, size=ref.metadata["patch_size"])
    assert np.array_equal(pt["boxes"], ref.boxes)
    assert np.array_equal(pt["object"], ref.object_index)
    assert np.allclose(pt["normal"], ref.normals, atol=1e-9)
    P, L = ref.num_patches, ref.wavelengths.size
    assert P >= 100
    for a in (ref.spectra, ref.noise, ref.direct, ref.noise_direct):
        assert a.shape == (P, L) and np.all(np.isfinite(a))
    # every patch lies inside the preview crop
    x0, y0, w, h = ref.metadata["crop"]
    assert ref.preview_xyz.shape == (h, w, 3)
    assert np.all(ref.boxes[:, :2] >= (x0, y0)) and np.all(ref.boxes[:, 2:] <= (x0 + w, y0 + h))


def test_noise_is_small_and_positive(ref):
    assert np.all(ref.spectra > 0) and np.all(ref.direct > 0)
    assert np.all(ref.noise > 0) and np.all(ref.noise_direct > 0)
    rel = ref.noise / ref.spectra
    assert np.median(rel) < 0.01
    assert np.isclose(np.median(rel), ref.metadata["median_relative_noise"], rtol=1e-3)


def test_interreflection_fraction_and_labels_are_consistent(ref):
    wy = xyz_weights(ref.wavelengths)[:, 1]
    y16, y2 = ref.spectra @ wy, ref.direct @ wy
    frac = (y16 - y2) / y16
    assert np.allclose(frac, ref.ir_fraction, atol=2e-5)
    # interreflection only adds light (beyond 4 standard errors of the difference)
    assert np.all(frac > -4 * ref.ir_noise - 1e-4)
    thr = ref.metadata["threshold"]
    expect = (ref.ir_fraction > thr) & (ref.ir_fraction > 3 * ref.ir_noise)
    assert np.array_equal(ref.interreflection, expect)
    assert set(np.unique(ref.labels)) <= {"direct", "interreflection"}
    assert 3 <= ref.interreflection.sum() < ref.num_patches // 2
    # interreflection-dominated patches face the neighbour (normal towards its centre)
    scene = load_scene(ROOT / ref.config)
    pos = np.array([o.position for o in scene.objects])
    other = pos[1 - ref.object_index]
    towards = np.sum(ref.normals * (other - ref.points), axis=1) > 0
    assert np.all(towards[ref.interreflection])


def test_preview_matches_patch_spectra(ref):
    x0, y0 = ref.metadata["crop"][:2]
    shifted = ref.boxes - np.array([x0, y0, x0, y0])
    means = np.stack([ref.preview_xyz[b:d, a:c].reshape(-1, 3).mean(axis=0)
                      for a, b, c, d in shifted])
    assert np.allclose(means, ref.xyz(), rtol=2e-4)


def test_patch_means_helper_and_errors(tmp_path):
    ref = load_reference("benchmark")
    w, h = ref.metadata["frame"]
    img = np.zeros((h, w, 2))
    x0, y0, x1, y1 = ref.boxes[0]
    img[y0:y1, x0:x1, 0] = 2.0
    img[y0, x0, 1] = 25.0
    m = ref.patch_means(img)
    assert np.allclose(m[0], [2.0, 1.0]) and np.allclose(m[1:], 0.0)
    with pytest.raises(InputError, match="reference not found"):
        load_reference("no_such_reference")
    bad = tmp_path / "bad.npz"
    np.savez(bad, wavelengths=np.zeros(3))
    with pytest.raises(InputError, match="missing arrays"):
        load_reference(bad)


@pytest.mark.slow
def test_direct_light_matches_our_shading_where_the_neighbour_is_hidden():
    """Patches whose tangent plane hides the other sphere: Mitsuba's depth-2 spectra vs our
    eq. (5) shading (exact irradiance, gloss quadrature) averaged over the 25 pixel centres."""
    import jax.numpy as jnp

    from spectral_fit.lighting import EnvironmentMap, make_material, shade_points
    from spectral_fit.validation.reference.export import environment_texels
    from spectral_fit.validation.reference.render import camera_rays, sphere_hits

    ref = load_reference("benchmark")
    scene = load_scene(ROOT / ref.config)
    env = EnvironmentMap.from_array(environment_texels(scene), diffuse="exact",
                                    rotation_y_deg=scene.environment.rotation_y_deg)
    ys, xs = np.mgrid[0:5, 0:5] + 0.5
    ours = np.zeros_like(ref.direct)
    hidden = np.zeros(ref.num_patches, bool)
    for oi, ob in enumerate(scene.objects):
        m = ob.material
        mat = make_material(alpha=m.alpha, beta=m.beta, chi=m.chi, mu=m.mu, n=m.n,
                            reflectance=m.reflectance, distribution=m.distribution,
                            geometry=m.geometry)
        sel = np.flatnonzero(ref.object_index == oi)
        other = scene.objects[1 - oi]
        hidden[sel] = (np.sum((np.asarray(other.position) - ref.points[sel])
                              * ref.normals[sel], axis=1) < -other.radius)
        sel = sel[hidden[sel]]
        px = ref.boxes[sel, 0, None] + xs.ravel()[None]
        py = ref.boxes[sel, 1, None] + ys.ravel()[None]
        o, d = camera_rays(scene, px, py)
        t = sphere_hits(o, d, ob.position, ob.radius)
        nrm = (o + t[..., None] * d - np.asarray(ob.position)) / ob.radius
        rad = shade_points(mat, env, jnp.asarray(nrm.reshape(-1, 3), jnp.float32),
                           jnp.asarray(-d.reshape(-1, 3), jnp.float32))
        ours[sel] = np.asarray(rad).reshape(len(sel), 25, -1).mean(axis=1)
    assert hidden.sum() >= 40
    wy = xyz_weights(ref.wavelengths)[:, 1]
    rel = (ours[hidden] @ wy - ref.direct[hidden] @ wy) / (ref.direct[hidden] @ wy)
    assert np.median(np.abs(rel)) < 0.005
    assert np.abs(rel).max() < 0.015
    assert abs(rel.mean()) < 0.002


def test_environment_export_reads_spectral_and_rgb_maps(tmp_path):
    """environment_texels: the benchmark's spectral map on the config grid (scale applied), and
    an RGB map lifted to the scene's bands; an object without reflectance gets the 0.5 default."""
    import OpenEXR

    from spectral_fit.io import parse_scene, read_spectral_exr
    from spectral_fit.validation.reference.export import environment_texels

    scene = load_scene(ROOT / "configs" / "benchmark.toml",
                       lambda d: d["environment"].update(scale=2.0))
    wl, img = read_spectral_exr(ANCHOR_ENV)
    assert np.allclose(environment_texels(scene), 2.0 * img)
    p = tmp_path / "rgb.exr"
    rgb = np.full((8, 16, 3), 0.5, np.float32)
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"RGB": rgb}).write(str(p))
    sc = parse_scene({"environment": {"file": str(p)}, "objects": [{"name": "a"}]})
    assert np.allclose(sc.objects[0].material.reflectance, 0.5)
    tex = environment_texels(sc)
    assert tex.shape == (8, 16, sc.wavelengths.size) and np.all(tex > 0)
    assert np.allclose(tex, tex[0, 0])  # a uniform grey map stays uniform


def test_committed_sr3a_session_is_consistent_with_its_truth():
    """measurements/reference/sr3a_two_spheres: manifest and files in the documented format;
    repeats scatter about the noise-free truth at the stated noise; kinds follow the truth."""
    import json
    import tomllib

    from spectral_fit.color import read_spectrum_csv

    folder = ROOT / "measurements" / "reference" / "sr3a_two_spheres"
    man = tomllib.loads((folder / "session.toml").read_text())
    truth = json.loads((folder / "truth.json").read_text())
    assert (folder / man["session"]["scene"]).resolve() == (
        ROOT / "configs" / "two_spheres.toml").resolve()
    assert man["session"]["format"] == 1 and man["session"]["units"] == "W.sr^-1.m^-2.nm^-1"
    wl = np.asarray(truth["wavelengths_nm"])
    assert wl[0] == 380 and wl[-1] == 780 and wl.size == 401
    inst = truth["instrument"]
    floor = truth["noise_floor_abs"]
    z_all = []
    for r in man["readings"]:
        t = truth["readings"][r["id"]]
        mean = np.asarray(t["mean"])
        reps = []
        for f in r["files"]:
            wl_f, v = read_spectrum_csv(folder / f)
            assert np.allclose(wl_f, wl)
            reps.append(v)
        reps = np.stack(reps)
        assert reps.shape[0] == inst["repeats"]
        sigma = np.sqrt(floor**2 + (inst["noise_relative"] * mean) ** 2
                        + (inst["gain_sigma"] * mean) ** 2)
        z_all.append((reps - mean) / sigma)
        assert r["kind"] == ("interreflection" if t["ir_fraction"] > 0.05 else "object")
        assert np.isclose(r["distance_m"], np.linalg.norm(
            np.asarray(r["aim"]) - np.asarray(man["instrument"]["position"])), atol=1e-3)
    z = np.concatenate([x.ravel() for x in z_all])
    assert 0.8 < z.std() < 1.2 and abs(z.mean()) < 0.2
    assert sum(r["kind"] == "interreflection" for r in man["readings"]) >= 1
    white = np.stack([read_spectrum_csv(folder / f)[1]
                      for f in man["white_standard"]["readings"]])
    wmean = np.asarray(truth["white"]["mean"])
    wsig = np.sqrt(floor**2 + ((inst["noise_relative"] + inst["gain_sigma"]) * wmean) ** 2)
    assert np.all(np.abs(white.mean(axis=0) - wmean) < 5 * wsig / np.sqrt(white.shape[0]))
