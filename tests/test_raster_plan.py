"""Capacity planning (NumPy, no compilation) against the rasteriser's own counts: the windows
per ladder size it reports in ``Raster.needed`` and the blocks and pixels it covers."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.raster import MID, SMALL, camera, clip_of, rasterize_padded, soup, two_spheres

from spectral_fit import geometry as raster
from spectral_fit._runtime.errors import InputError
from spectral_fit.io import translate
from spectral_fit.rendering import plan_capacities


def _check(clip, tris, shape, cull="none"):
    counts = raster.plan_counts(clip, tris, shape, cull=cull)
    r = rasterize_padded(clip, tris, shape, cull=cull)
    needed = np.asarray(r.needed)
    # the same window counting as the rasteriser (its float32 setup pass)
    assert list(counts.windows) == needed[:-1].tolist()
    # the blocks touched by the boxes bound the blocks with a visible triangle, the pixels
    # in the boxes bound the covered pixels
    covered = int(np.sum(np.asarray(r.tri_id) >= 0))
    assert needed[-1] <= counts.blocks and covered <= counts.pixels
    return counts, covered


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("cull", ["none", "back", "front"])
def test_plan_counts_equal_the_rasterisers_counts_on_soups(seed, cull):
    clip, tris = soup(seed)  # crossing the eye, near and far planes
    counts, covered = _check(clip, tris, SMALL, cull)
    assert covered > 20 and sum(counts.windows) > 20


def test_plan_counts_near_plane_crossing_meshes():
    mesh = two_spheres(-2.0)
    cam = camera(MID, near=0.5)
    for z in (0.0, 1.3, 1.6):  # in front, cut by the near plane, around the eye
        clip = clip_of(cam, mesh.vertices, translate((0.0, 0.0, z)))
        _check(clip, mesh.triangles, MID)


def test_plan_config_sizes_from_counts_and_renderer_shares_it():
    mesh = two_spheres(-2.0)
    clip = clip_of(camera(MID), mesh.vertices)
    counts = raster.plan_counts(clip, mesh.triangles, MID)
    cfg = raster.plan_config(clip, mesh.triangles, MID, headroom=1.5)
    for cap, n in zip(cfg.capacities, counts.windows, strict=True):
        assert 1.5 * n + 16 <= cap <= 1.25 * (1.5 * n + 16)  # the quarter-octave ladder
    assert 1.5 * counts.blocks + 16 <= cfg.block_capacity
    # several poses: the worst of each count
    near = clip_of(camera(MID), mesh.vertices, translate((0.0, 0.0, 1.0)))
    both = raster.plan_config(np.stack([clip, near]), mesh.triangles, MID, headroom=1.0)
    c2 = raster.plan_counts(near, mesh.triangles, MID)
    want = [raster.capacity_ladder(max(a, b) + 16) for a, b in zip(counts.windows, c2.windows,
                                                           strict=True)]
    assert list(both.capacities) == want
    rcfg, pixels = plan_capacities(clip, mesh.triangles, MID, headroom=1.5)
    assert rcfg == cfg and pixels == counts.pixels
    with pytest.raises(InputError, match="tile_sizes"):
        raster.RasterConfig.from_counts(counts, tile_sizes=(1, 8))
