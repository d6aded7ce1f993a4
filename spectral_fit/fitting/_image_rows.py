"""Camera photographs as rows of the fit (outside ``jit``): each image is cut into square
bins of ``superpixel`` × ``superpixel`` pixels; a bin whose pixels all see one object, none
clipped and none lit noticeably by a neighbour or by its own object (the inside of a concave
one) becomes one row of the fit: its channels' mean
counts (black subtracted) and their standard errors, compared with the exposure times the
sensitivities applied to the mean model radiance of ``samples`` × ``samples`` shading samples
spread over the bin (:mod:`spectral_fit.io`'s image readings give the pixel model).

Shapes: N bins kept, S rows, Ps samples, C channels, L bands; world metres.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from ..geometry import ObjectGeometry
from ..io import ImageReading
from ._spots import cast_rays, scene_triangles

__all__ = ["ImageRows", "image_rows", "pixel_rays"]

#: bins where the neighbours' form factor (bounding spheres) exceeds this are left out: the
#: fit's interreflection term is built per spot
_NEIGHBOUR_LIMIT = 0.01
#: bins whose quadrants' means of one channel span more than this fraction of the bin's mean
#: (a highlight's flank) get superpixel/2 samples per side (one per R/B site of a mosaic)
_STEEP = 0.15


@dataclasses.dataclass(frozen=True)
class ImageRows:
    """The rows of one image: one per kept bin (a demosaiced image: every channel in one
    row), or one per kept bin and channel (a mosaic: each channel has its own samples on
    the lattice of its pixel sites).

    Attributes:
        image: index of the image in the session.
        bins: (N, 2) row and column of each kept bin.
        object: (N,) object each bin sees.
        row_bin: (S,) the bin of each row.
        measured: (S, C) mean counts per channel, black level subtracted (0 where ``mask``
            is False).
        sigma: (S, C) their standard errors (counts; 1 where ``mask`` is False).
        mask: (S, C) the channels each row carries.
        response: (C, L) exposure × sensitivity × Δλ: counts per W·sr⁻¹·m⁻²·nm⁻¹ of the
            model radiance in each band.
        pos, nrm, view: (Ps, 3) the shading samples (world), unit normals, unit directions
            to the camera: k × k per row (a mosaic's channel: on the lattice of its pixel
            sites), superpixel/2 per side in steep bins.
        sample_row, sample_weight: (Ps,) the row of each sample and its weight in the row's
            mean (1/k²).
        steep: (N,) the bins sampled superpixel/2 × superpixel/2 per row (a channel's means
            over the bin's quadrants span more than ``_STEEP`` of its mean: a highlight's
            flank).
        dropped: {reason: number of bins} of the bins over an object that were left out.
        grid: (rows, cols) of the bin grid.
    """

    image: int
    bins: np.ndarray
    object: np.ndarray
    row_bin: np.ndarray
    measured: np.ndarray
    sigma: np.ndarray
    mask: np.ndarray
    response: np.ndarray
    pos: np.ndarray
    nrm: np.ndarray
    view: np.ndarray
    sample_row: np.ndarray
    sample_weight: np.ndarray
    steep: np.ndarray
    dropped: dict[str, int]
    grid: tuple[int, int]


def pixel_rays(image: ImageReading, xy: np.ndarray) -> np.ndarray:
    """Unit world directions (N, 3) of the camera rays through pixel coordinates ``xy``
    (N, 2) (x right, y down, in pixels; pixel (i, j)'s centre at (j + 0.5, i + 0.5))."""
    from ..geometry import look_at

    H, W = image.shape
    x, y = xy[:, 0], xy[:, 1]
    if image.intrinsics is not None:
        fx, fy, cx, cy = image.intrinsics  # OpenCV: pixel centres at integers
        d = np.stack([(x - 0.5 - cx) / fx, -(y - 0.5 - cy) / fy, -np.ones_like(x)], -1)
    else:
        ty = math.tan(math.radians(image.fov_y_deg) / 2.0)
        d = np.stack([(2.0 * x / W - 1.0) * ty * W / H, (1.0 - 2.0 * y / H) * ty,
                      -np.ones_like(x)], -1)
    R = np.asarray(look_at(image.position, image.aim, image.up), np.float64)[:3, :3]
    d = d @ R  # eye → world (R is orthonormal: Rᵀ d)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _neighbour_share(x: np.ndarray, n: np.ndarray, v: np.ndarray, obj: np.ndarray,
                     spheres: Sequence[tuple[np.ndarray, float]]) -> np.ndarray:
    """(N,) the largest of: the points' form factor towards the other objects' bounding
    spheres, Σ (r/d)² cosθ, and 1 where the mirror direction passes within 0.3 rad of a
    neighbour's silhouette (its light then reaches the gloss lobe)."""
    r_dir = 2.0 * np.sum(n * v, -1, keepdims=True) * n - v
    out = np.zeros(x.shape[0])
    ff = np.zeros(x.shape[0])
    for o, (c, rad) in enumerate(spheres):
        other = obj != o
        rel = c[None] - x
        d = np.linalg.norm(rel, axis=1)
        u = rel / np.maximum(d, 1e-12)[:, None]
        cos = np.clip(np.sum(u * n, -1), 0.0, 1.0)
        ff += np.where(other, (rad / np.maximum(d, rad)) ** 2 * cos, 0.0)
        half = np.arcsin(np.clip(rad / np.maximum(d, 1e-12), 0.0, 1.0))
        ang = np.arccos(np.clip(np.sum(u * r_dir, -1), -1.0, 1.0))
        out = np.maximum(out, np.where(other & (ang < half + 0.3), 1.0, 0.0))
    return np.maximum(out, ff)


def _self_lit(x: np.ndarray, n: np.ndarray, v: np.ndarray, obj: np.ndarray,
              geoms: Sequence[ObjectGeometry]) -> np.ndarray:
    """(N,) whether a point of a non-convex object receives its own light: the object hides
    more than ``_NEIGHBOUR_LIMIT`` of its cosine-weighted sky, or any of its mirror
    direction's taps (the frame's visibility test on a 16² direction grid)."""
    from ..geometry import is_convex, octahedral_taps, point_visibility

    out = np.zeros(x.shape[0], bool)
    for o in np.unique(obj[obj >= 0]):
        g = geoms[int(o)]
        verts, tris, nrms = (np.asarray(a) for a in (g.vertices, g.triangles, g.normals))
        if is_convex(verts, tris, nrms):
            continue
        sel = np.flatnonzero(obj == o)
        sv = point_visibility(verts, tris, x[sel], n[sel], resolution=16)
        dirs = np.asarray(sv.directions, np.float64)
        hid = np.asarray(sv.hidden)
        cos = np.maximum(n[sel] @ dirs.T, 0.0)
        share = (hid * cos * np.asarray(sv.solid_angle)[None]).sum(axis=1) / math.pi
        r = 2.0 * np.sum(n[sel] * v[sel], -1, keepdims=True) * n[sel] - v[sel]
        idx, _ = octahedral_taps(r, 16)
        mirror = np.take_along_axis(hid, np.asarray(idx), axis=1).any(axis=1)
        out[sel] = (share > _NEIGHBOUR_LIMIT) | mirror
    return out


def image_rows(image: ImageReading, index: int, geoms: Sequence[ObjectGeometry],
               objects: Sequence[str], wavelengths: np.ndarray) -> ImageRows:
    """The bins of ``image`` that enter the fit (see the module docstring).

    Args:
        image: the photograph.
        index: its index in the session.
        geoms: world meshes of the scene's objects (config order), named ``objects``.
        wavelengths: (L,) the scene's grid (nm).
    """
    H, W = image.shape
    s, k = image.superpixel, image.samples
    rows, cols = H // s, W // s
    from ..geometry import build_bvh

    verts, norms, tris, tri_obj = scene_triangles(list(geoms))
    bvh = build_bvh(verts, tris)
    spheres = []
    for g in geoms:
        v = np.asarray(g.vertices, np.float64)
        c = 0.5 * (v.min(axis=0) + v.max(axis=0))
        spheres.append((c, float(np.linalg.norm(v - c, axis=1).max())))
    eye = np.asarray(image.position, np.float64)
    # bins whose centre ray passes near an object's bounding sphere
    ii, jj = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    ii, jj = ii.reshape(-1), jj.reshape(-1)
    centre = np.stack([(jj + 0.5) * s, (ii + 0.5) * s], -1).astype(np.float64)
    dc = pixel_rays(image, centre)
    foot = s * 2.0 * math.tan(math.radians(image.fov_y_deg or 60.0) / 2.0) / H \
        if image.intrinsics is None else s / float(min(image.intrinsics[:2]))
    near = np.zeros(ii.size, bool)
    for c, rad in spheres:
        rel = c - eye
        t = rel @ dc.T
        dist = np.linalg.norm(rel[None] - t[:, None] * dc, axis=1)
        near |= (t > 0) & (dist <= rad + foot * max(float(np.linalg.norm(rel)), rad) * 1.5)
    ii, jj = ii[near], jj[near]
    nb = ii.size
    # rays: the bin's 4 corner pixels, then k × k samples per sample set: one set per
    # channel of a mosaic, on the lattice of its pixel sites (the midpoint rule over blocks
    # of sites: R and B sit half a pixel either side of a 2 × 2 tile's centre), one set for
    # a demosaiced image
    C = image.channels
    off_c = np.array([[0.5, 0.5], [s - 0.5, 0.5], [0.5, s - 0.5], [s - 0.5, s - 0.5]])
    if image.mosaic == "none":
        shifts = np.zeros((1, 2))
    else:
        chan2 = image.channel_of_pixel()[:2, :2]
        shifts = np.stack([np.argwhere(chan2 == c)[:, ::-1].mean(axis=0) - 0.5
                           for c in range(C)])  # (x, y) of each channel's site centroid
    sets = shifts.shape[0]

    def sample_offsets(q: int) -> np.ndarray:
        """(sets · q², 2) pixel offsets in a bin of q × q samples per set, row-major."""
        g = (np.arange(q) + 0.5) / q * s
        gx, gy = np.meshgrid(g, g)
        grid = np.stack([gx.reshape(-1), gy.reshape(-1)], -1)
        return (grid[None] + shifts[:, None]).reshape(-1, 2)

    offs = np.concatenate([off_c, sample_offsets(k)])
    xy = (np.stack([jj * s, ii * s], -1)[:, None, :] + offs[None]).reshape(-1, 2)
    d = pixel_rays(image, xy)
    obj, pos, nrm = cast_rays(bvh, eye, d, verts, norms, tris, tri_obj)
    m = offs.shape[0]
    obj, pos, nrm = obj.reshape(nb, m), pos.reshape(nb, m, 3), nrm.reshape(nb, m, 3)
    d = d.reshape(nb, m, 3)
    allowed = ([objects.index(o) for o in image.objects] if image.objects
               else list(range(len(objects))))
    on_obj = (obj >= 0).any(axis=1)
    one = (obj == obj[:, :1]).all(axis=1) & (obj[:, 0] >= 0)
    ok = one & np.isin(obj[:, 0], allowed)
    dropped = {"edge": int(np.sum(on_obj & ~one)),
               "other_object": int(np.sum(one & ~ok))}
    # pixels: clipped bins out
    px = image.pixels
    blocks = px[:rows * s, :cols * s].reshape(rows, s, cols, s, *px.shape[2:])
    blocks = np.moveaxis(blocks, 2, 1)[ii, jj]  # (nb, s, s[, C])
    clipped = (blocks >= image.clip_level()).reshape(nb, -1).any(axis=1)
    dropped["clipped"] = int(np.sum(ok & clipped))
    ok &= ~clipped
    # shading samples; bins a neighbour lights noticeably are left out
    sp, sn = pos[:, 4:], nrm[:, 4:]
    sv = -d[:, 4:]
    share = _neighbour_share(sp.reshape(-1, 3), sn.reshape(-1, 3), sv.reshape(-1, 3),
                             np.repeat(obj[:, 0], sp.shape[1]), spheres).reshape(nb, -1)
    lit = share.max(axis=1) > _NEIGHBOUR_LIMIT
    dropped["neighbour"] = int(np.sum(ok & lit))
    ok &= ~lit
    # and bins a concave object lights itself (a cup's inside): the light an object sends
    # itself enters the fit through probes made per spot
    own = np.zeros(nb, bool)
    own[ok] = _self_lit(sp[ok, 0], sn[ok, 0], sv[ok, 0], obj[ok, 0], geoms)
    dropped["self"] = int(np.sum(own))
    ok &= ~own
    ok &= np.sum(sn * sv, -1).min(axis=1) > 0.0
    vals = blocks[ok] - image.black_level
    if image.mosaic == "none":
        per = vals.reshape(vals.shape[0], -1, C)
        n_c = np.full((vals.shape[0], C), per.shape[1], np.float64)
        mean = per.mean(axis=1)
    else:
        chan = image.channel_of_pixel()[:s, :s]
        flat = vals.reshape(vals.shape[0], -1)
        mean = np.stack([flat[:, chan.reshape(-1) == c].mean(axis=1) for c in range(C)], -1)
        n_c = np.stack([np.full(flat.shape[0], float(np.sum(chan == c))) for c in range(C)],
                       -1)
    var = image.read_noise ** 2 + image.gain * np.maximum(mean, 0.0)
    sigma = np.sqrt(np.maximum(var, 1e-12) / n_c)
    from ..color import integration_weights

    dl = integration_weights(wavelengths)
    response = image.exposure_s * image.sensitivities * dl[None, :]
    bins = np.stack([ii[ok], jj[ok]], -1)
    n = bins.shape[0]
    # steepness: the spread of each channel's means over the bin's four quadrants (a
    # gradient across the bin; the means damp the pixels' noise)
    h = s // 2
    corners = [(a, b) for a in (0, h) for b in (0, h)]
    if image.mosaic == "none":
        qm = np.stack([vals[:, a:a + h, b:b + h].reshape(n, -1, C).mean(axis=1)
                       for a, b in corners], 1)  # (n, 4, C)
        span = (qm.max(axis=1) - qm.min(axis=1)) / np.maximum(mean, 1e-12)
    elif h >= 2:  # each quadrant with its own sites (an odd half-width shifts the pattern)
        qm = np.stack([np.stack([vals[:, a:a + h, b:b + h][:, chan[a:a + h, b:b + h] == c]
                                 .mean(axis=1) for c in range(C)], -1)
                       for a, b in corners], 1)
        span = (qm.max(axis=1) - qm.min(axis=1)) / np.maximum(mean, 1e-12)
    else:  # 2-pixel bins: no quadrant holds every channel
        span = np.zeros_like(mean)
    steep = np.any(span > _STEEP, axis=1) & (mean.min(axis=1) > 10.0 * image.read_noise)
    k_hi = max(k, s // 2)
    # the samples, flat: each belongs to one row (a bin's channel) with weight 1/k_b²
    sp, sn, sv = sp[ok], sn[ok], sv[ok]
    kk = k * k
    base_row = np.repeat(np.arange(n) * sets, sets * kk) + np.tile(
        np.repeat(np.arange(sets), kk), n)
    keep = ~np.repeat(steep, sets * kk)
    pos_f, nrm_f, view_f = (a.reshape(-1, 3)[keep] for a in (sp, sn, sv))
    row_f, w_f = base_row[keep], np.full(int(keep.sum()), 1.0 / kk)
    if steep.any() and k_hi > k:
        offs_h = sample_offsets(k_hi)
        sb = np.flatnonzero(steep)
        xy_h = (np.stack([bins[sb, 1] * s, bins[sb, 0] * s], -1)[:, None, :]
                + offs_h[None]).reshape(-1, 2)
        dh = pixel_rays(image, xy_h)
        oh, ph, nh = cast_rays(bvh, eye, dh, verts, norms, tris, tri_obj)
        m_h = offs_h.shape[0]
        front = (np.sum(nh * -dh, -1) > 0.0).reshape(sb.size, m_h)
        same = (oh.reshape(sb.size, m_h) == obj[ok][sb, :1]).all(axis=1) & front.all(axis=1)
        good = np.repeat(same, m_h)
        hh = k_hi * k_hi
        row_h = np.repeat(sb * sets, sets * hh) + np.tile(np.repeat(np.arange(sets), hh),
                                                          sb.size)
        # a steep bin whose finer samples leave its object keeps its k × k samples
        back = np.isin(base_row // sets, sb[~same])
        pos_f = np.concatenate([pos_f, ph[good], sp.reshape(-1, 3)[back]])
        nrm_f = np.concatenate([nrm_f, nh[good], sn.reshape(-1, 3)[back]])
        view_f = np.concatenate([view_f, -dh[good], sv.reshape(-1, 3)[back]])
        row_f = np.concatenate([row_f, row_h[good], base_row[back]])
        w_f = np.concatenate([w_f, np.full(int(good.sum()), 1.0 / hh),
                              np.full(int(back.sum()), 1.0 / kk)])
        steep[sb[~same]] = False
    order = np.argsort(row_f, kind="stable")
    if sets == 1:  # every channel in one row
        mask = np.ones((n, C), bool)
        meas, sig = mean, sigma
        row_bin = np.arange(n)
    else:  # a mosaic: one row per bin and channel, the mean of its own sample set
        mask = np.tile(np.eye(C, dtype=bool), (n, 1))
        meas = np.where(mask, np.repeat(mean, C, axis=0), 0.0)
        sig = np.where(mask, np.repeat(sigma, C, axis=0), 1.0)
        row_bin = np.repeat(np.arange(n), sets)
    return ImageRows(image=index, bins=bins, object=obj[ok, 0], row_bin=row_bin,
                     measured=meas, sigma=sig, mask=mask, response=response,
                     pos=pos_f[order], nrm=nrm_f[order], view=view_f[order],
                     sample_row=row_f[order], sample_weight=w_f[order], steep=steep,
                     dropped=dropped, grid=(rows, cols))
