"""Benchmark cases of the interreflection passes on the benchmark scene (docs/benchmark.md).

Two UV spheres of radius 0.0375 m (100 × 100, 19,800 triangles each) at (∓0.045, 0, −0.275)
(``ir_*_paper``) or z = −0.100 (``ir_gather_closeup``), the anchor's environment
(``measurements/benchmark/anchor_environment.exr``, 31 bands, rotated 180° about +Y), yellow
and red ColorChecker N Ohta diffuse spectra, α = β = 1, χ = 0, μ = 0.1, n = 1.5, γ = 1. The
receivers are the covered pixels of the 720×480 camera view (90° vertical FOV), as the frame
renderer passes them. Each case times the jitted ``interreflection`` (pass-1 raster + shading
pass, what a frame with moving objects pays) and, where marked ``_shade``, only
``interreflection_from`` on a prepared geometry (what the fitter pays per iteration);
``_receivers``: the diffuse transfer summed at every receiver (``diffuse_at="receivers"``)
instead of at the objects' own samples. The receivers are passed as the pixels of the camera
image (``image_shape``), as the renderer does (gloss quadrature subsampled).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..._runtime.paths import REPO_ROOT
from .._harness import BenchOptions, measure

__all__ = ["CASES", "benchmark_scene"]

_ENV = REPO_ROOT / "measurements" / "benchmark" / \
    "anchor_environment.exr"


def benchmark_scene(z: float = -0.275, *, stacks: int = 100, shape: tuple[int, int] = (480, 720),
                    capacity: int = 8192, k: int | None = None, env_path: Any = None,
                    wavelengths: Any = None, diffuse: str = "sh") -> dict[str, Any]:
    """The benchmark scene as interreflection inputs.

    Returns a dict with ``objects`` (2 :class:`ObjectGeometry`), ``materials``, ``env``
    (:class:`EnvironmentMap`, bands or K coefficients), ``receivers`` (:class:`GBuffer` of the
    camera's covered pixels, ``capacity`` slots), ``base`` (the environment-only shading of
    the receivers, (N, C)), ``wavelengths``, ``shape``, ``basis`` (or None), ``pixels``.
    """
    import colour
    import jax
    import jax.numpy as jnp

    from ...color import pca_basis
    from ...geometry import (
        GBuffer,
        ObjectGeometry,
        covered_pixels,
        interpolate_pixels,
        perspective_camera,
        project,
        rasterize,
    )
    from ...io import concat_meshes, read_spectral_exr, translate, uv_sphere
    from ...lighting import EnvironmentMap, make_material, shade_points
    from ...rendering import plan_capacities

    wl, img = read_spectral_exr(env_path or _ENV)
    if wavelengths is not None:
        from ...color import resample

        img = resample(wl, img, np.asarray(wavelengths, np.float64))
        wl = np.asarray(wavelengths, np.float64)
    basis = None
    if k is None:
        env = EnvironmentMap.from_array(img, rotation_y_deg=180.0, diffuse=diffuse)
    else:
        basis = pca_basis(int(k), wl)
        env = EnvironmentMap.from_array(basis.project(img), rotation_y_deg=180.0,
                                        product_tensor=basis.product_tensor, diffuse=diffuse)
    centres = [(-0.045, 0.0, z), (0.045, 0.0, z)]
    sph = uv_sphere(0.0375, stacks, stacks)
    meshes = [sph.transformed(translate(c)) for c in centres]
    objects = [ObjectGeometry(jnp.asarray(m.vertices), jnp.asarray(m.normals),
                              jnp.asarray(m.triangles), jnp.asarray(c, jnp.float32))
               for m, c in zip(meshes, centres, strict=True)]
    ohta = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    materials = []
    for name in ("yellow", "red"):
        sd = ohta[name]
        s = np.interp(wl, sd.wavelengths, sd.values)
        if basis is not None:
            s = basis.project(s)
        materials.append(make_material(alpha=1.0, beta=1.0, chi=0.0, mu=0.1, n=1.5, gamma=1.0,
                                       reflectance=s))
    h, w = shape
    both, offs = concat_meshes(meshes)
    cam = perspective_camera((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), fov_y_deg=90.0, aspect=w / h)
    clip = project(cam, both.vertices)
    # back faces culled: with cull="none" the rasteriser returned the far side of the spheres
    # at ~9 % of the covered pixels of this frame (605 of 6,933)
    # window capacities planned for this view (the default sizing overflowed and was grown)
    cfg, _ = plan_capacities(np.asarray(clip), np.asarray(both.triangles), shape)
    ras = rasterize(clip, both.triangles, shape, cull="back", config=cfg)
    pix = covered_pixels(ras, capacity)
    pos = interpolate_pixels(both.vertices, pix, both.triangles, clip)
    nrm = interpolate_pixels(both.normals, pix, both.triangles, clip)
    nrm = nrm / jnp.maximum(jnp.linalg.norm(nrm, axis=-1, keepdims=True), 1e-12)
    view = -pos / jnp.maximum(jnp.linalg.norm(pos, axis=-1, keepdims=True), 1e-12)
    obj = jnp.where(pix.valid, jnp.where(pix.tri_id >= int(offs[1]), 1, 0), -1).astype(
        jnp.int32)
    receivers = GBuffer(position=pos, normal=nrm, view=view, object=obj,
                        pixel=jnp.where(pix.valid, pix.index, -1))

    def base_fn(mats, e, r):
        out = jnp.zeros((r.object.shape[0], e.channels), jnp.float32)
        for o, m in enumerate(mats):
            # in batches (lax.map): the exact-quality shading vmapped over all 8,192 slots
            # asked XLA for 25.8 GB of temporaries
            v = shade_points(m, e, r.normal, r.view)
            out = jnp.where((r.object == o)[:, None], v, out)
        return out

    base = jax.jit(base_fn)(materials, env, receivers)
    return dict(objects=objects, materials=materials, env=env, receivers=receivers, base=base,
                wavelengths=wl, shape=shape, basis=basis, pixels=int(pix.count))


def _case(opts: BenchOptions, *, mode: str, z: float = -0.275, k: int | None = None,
          bands: int = 31, bounces: int = 1, shade_only: bool = False,
          diffuse_at: str = "samples") -> dict[str, Any]:
    import jax

    from ...rendering.interreflection import (
        interreflection,
        interreflection_from,
        prepare_interreflection,
    )

    wl = None if bands == 31 else np.linspace(400.0, 700.0, bands)
    if opts.quick:
        sc = benchmark_scene(z, stacks=20, shape=(120, 180), capacity=2048, k=k,
                             wavelengths=wl)
    else:
        # capacity: the close-up covers ~66k pixels
        sc = benchmark_scene(z, k=k, wavelengths=wl, capacity=8192 if z < -0.2 else 81920)
    objs, mats, env, rec = sc["objects"], sc["materials"], sc["env"], sc["receivers"]
    if shade_only:
        geom = prepare_interreflection(objs, mode=mode)
        fn = jax.jit(lambda g, m, e, r: interreflection_from(g, m, e, r, bounces=bounces,
                                                              diffuse_at=diffuse_at,
                                                              image_shape=sc["shape"]))
        out = measure(fn, geom, mats, env, rec, repeats=opts.repeats)
    else:
        fn = jax.jit(lambda o, m, e, r: interreflection(o, m, e, r, mode=mode,
                                                         bounces=bounces,
                                                         image_shape=sc["shape"]))
        out = measure(fn, objs, mats, env, rec, repeats=opts.repeats)
    out.update(receivers=sc["pixels"], channels=int(env.channels), mode=mode, bounces=bounces,
               diffuse_at=diffuse_at)
    return out


CASES = {
    "ir_gather_paper": lambda o: _case(o, mode="gather"),
    "ir_gather_b2_paper": lambda o: _case(o, mode="gather", bounces=2),
    "ir_gather_paper_81": lambda o: _case(o, mode="gather", bands=81),
    "ir_gather_paper_k8": lambda o: _case(o, mode="gather", k=8),
    "ir_gather_shade_paper": lambda o: _case(o, mode="gather", shade_only=True),
    "ir_gather_b2_shade_paper": lambda o: _case(o, mode="gather", bounces=2, shade_only=True),
    "ir_gather_b2_shade_receivers_paper": lambda o: _case(o, mode="gather", bounces=2,
                                                          shade_only=True,
                                                          diffuse_at="receivers"),
    "ir_gather_closeup": lambda o: _case(o, mode="gather", z=-0.100),
    "ir_paper_paper": lambda o: _case(o, mode="paper"),
}
