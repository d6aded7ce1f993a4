"""Benchmark case ``reference_render`` (needs the optional extra ``validate``: Mitsuba 3).

One band-triple render of the benchmark scene's objects crop (docs/benchmark.md, spheres at 0.275 m)
with our whole model as one Mitsuba BSDF, path depth 16, 64 samples per pixel (4 in quick mode).
``compile_s`` is the first render (scene load + Mitsuba's kernel compilation), ``median_ms`` a
steady render. Extra figures: paths per second and the projected time of a full 31-band,
two-depth, 2048-spp reference (as committed: 11 band triples × 2 depths × 8 passes × 256 spp).
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np

from ..._runtime.paths import REPO_ROOT
from .._harness import BenchOptions, measure

__all__ = ["CASES"]

_CONFIG = REPO_ROOT / "configs" / "benchmark.toml"


def reference_render(opts: BenchOptions) -> dict[str, Any]:
    from ...validation.reference.backend import mitsuba_available

    if not mitsuba_available():
        return {"skipped": "Mitsuba 3 is not installed (pip install 'spectral_fit[validate]')"}
    from ...io import load_scene
    from ...validation.reference.backend import current_variant, init_mitsuba
    from ...validation.reference.export import environment_texels, mitsuba_envmap_rows, scene_dict
    from ...validation.reference.render import objects_crop

    mi, _ = init_mitsuba()
    scene = load_scene(_CONFIG)
    spp = 4 if opts.quick else 64
    crop = objects_crop(scene)
    rows = mitsuba_envmap_rows(environment_texels(scene))
    idx = np.arange(3)
    meshes = {o.name: o.make_mesh(world=True) for o in scene.objects}
    refl = {o.name: np.asarray(o.material.reflectance)[idx] for o in scene.objects}
    seeds = itertools.count()
    state: dict[str, Any] = {}

    def render() -> np.ndarray:
        if "scene" not in state:
            state["scene"] = mi.load_dict(scene_dict(
                scene, env_rgb=rows[..., idx], reflectances=refl, spp=spp, crop=crop,
                meshes=meshes))
        return np.asarray(mi.render(state["scene"], seed=next(seeds), spp=spp))

    out: dict[str, Any] = measure(render, repeats=min(opts.repeats, 5))
    paths = crop.width * crop.height * spp
    out.update(variant=current_variant(), spp=spp, pixels=crop.width * crop.height,
               paths_per_s=paths / (out["median_ms"] / 1e3),
               full_reference_estimate_s=out["median_ms"] / 1e3 * 11 * 2 * 8 * 256 / spp)
    return out


CASES = {"reference_render": reference_render}
