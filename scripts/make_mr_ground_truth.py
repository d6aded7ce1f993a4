"""End-to-end ground truth for mixed reality: a path-traced "real" video of a table with printed
ArUco markers and a ColorChecker, seen through a camera pipeline that is not ours, made twice
(without and with the virtual objects), plus the noise-free version of the latter for scoring.

    python scripts/make_mr_ground_truth.py [--config configs/live_room.toml] [--frames 24]
        [--size 360 240] [--spp 16] [--spp-near 256] [--out measurements/video]
        [--cache out/mr_cache] [--seed 0]

Scene (world = marker 3's ground frame: the table is the plane y = 0, +Y up, −Z = the top
edge of marker 3): the config's ``[markers] size`` (80 mm) markers 3 at (0, 0, 0) and 7 at
(MARKER7_X, 0, 0), printed black ("black 2" of colour-science's BabelColor ColorChecker) on
white ("white 9.5") with a one-cell white margin, and the config's ``[colour_chart]`` (24
BabelColor patches on a black surround) lying on a table of the config's ``[[surfaces]]``
reflectance. The objects are the config's ``[[objects]]`` (exact spheres here) resting on
their markers, with our whole reflection model as one Mitsuba BSDF
(:mod:`spectral_fit.validation.reference`). Environment: the config's ``[environment]``.

Light (Mitsuba 3, depth 16, band trick: three bands per rgb render). The table is a 20 m
textured rectangle (the texture's border colour beyond the printed area). Without the objects
a Lambertian plane under an environment at infinity has the closed form ρ(x) E_up/π, computed
here per pixel over 4 × 4 sub-pixel rays (``A``). With them, a control variate: the path
tracer renders the frame with and without the objects with the same random numbers
(``M_with``, ``M_without``), and the truth is ``M_with + (1 − cov)·(A − M_without)`` with cov
the objects' pixel coverage: where the objects change nothing the two renders take the same
paths and the table is exactly ``A``; near the objects only the light they change is left to
chance. The window around the objects and the table within ``--radii`` + 0.5 bounding radii of them
is rendered with ``--spp-near`` samples, the rest with ``--spp``. Each frame's Mitsuba
results are cached in ``--cache`` (keyed by every setting).

Camera pipeline (not the renderer's camera model; :data:`PIPELINE`): the spectral radiance
through colour-science's Nikon 5100 (NPL) sensitivities, exposure and per-channel white-balance
gains that drift over the clip, vignetting, an RGGB Bayer mosaic, sensor noise (shot + read,
12-bit), OpenCV's bilinear demosaicing, a 3×3 colour matrix (ColorChecker under D65), a
gamma-2.2 tone curve, 8 bits. Outputs in ``--out``:

* ``room.mp4``: the "real" video (no objects), MPEG-4 Part 2 (``mp4v``: the H.264 encoder is
  not available in the installed OpenCV build), ``room.poses.json`` (true camera and marker
  poses, OpenCV convention, as ``sample.poses.json``);
* ``room_objects.mp4``: the same with the objects (noise and compression);
* ``room_truth/frame_NNN.png``: the frames with the objects, same pipeline and drift, no sensor
  noise, no compression (lossless), ``room_truth/masks.npz``: per frame ``object_id`` (H, W)
  int8 (object index where a pixel is fully covered, −1 elsewhere, −2 on partly covered
  pixels), ``near`` (H, W) bool (table pixels, no object, whose table point lies within
  ``--radii`` bounding radii of an object's centre projected onto the table),
  ``room_truth/truth.json`` (settings, pipeline parameters, times, the reference's measured
  noise).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

import table_reference as tr  # noqa: E402  (the table's building blocks)

#: marker 7's centre on the table (world x, m); marker 3 is the world origin
MARKER7_X = 0.12
#: the printed table's extent (m, along x and z) and texel pitch (m)
TABLE_EXTENT = (0.6, 0.5)
TABLE_PITCH = 0.0005
#: surround between the chart's patches (m)
CHART_GAP = 0.003
CHART_SET = "BabelColor Average"
PAPER = "white 9.5 (.05 D)"
INK = "black 2 (1.5 D)"

#: the camera pipeline (see the module docstring); s = frame / (frames − 1)
PIPELINE: dict[str, Any] = {
    "sensitivities": "Nikon 5100 (NPL)",
    "white_raw_green": 0.72,          # raw green level of the white paper at frame 0
    "exposure_drift": "1 + 0.06 s + 0.02 sin(2π s)",
    "white_balance_drift": "R gain × (1 + 0.03 s), B gain × (1 − 0.03 s)",
    "vignetting": "1 − 0.12 r², r = distance from the centre / half diagonal",
    "bayer": "RGGB",
    "noise": "σ² = 0.0015² + 6e-5 · raw (raw full scale 1), then 12-bit quantisation",
    "demosaic": "cv2.COLOR_BayerRGGB2RGB (bilinear), 16-bit",
    "colour_matrix": "3×3 white-balanced camera RGB → linear sRGB, least squares on the 24 "
                     "BabelColor patches under D65, rows summing to 1",
    "tone": "gamma 2.2 (encoded = linear^(1/2.2)), 8 bits",
    "codec": "mp4v (MPEG-4 Part 2) through cv2.VideoWriter",
}


# --------------------------------------------------------------------------------------------
# the scene


@dataclasses.dataclass(frozen=True)
class Setup:
    """Everything a frame needs: the scene (config), wavelengths (L,), reflectances (L,) of
    table / paper / ink, the chart's (24, L), its corners (4, 3) world (TL, TR, BR, BL), the
    printed table's label textures, the objects' centres (O, 3) and radii (O,)."""

    scene: Any
    wl: np.ndarray
    table: np.ndarray
    paper: np.ndarray
    ink: np.ndarray
    chart: np.ndarray
    chart_corners: np.ndarray
    marker_table: Any
    w_base: np.ndarray
    w_paper: np.ndarray
    chart_index: np.ndarray
    centres: np.ndarray
    radii: np.ndarray


def setup(config: Path) -> Setup:
    """Read ``config`` and print the table (labels per texel)."""
    from spectral_fit.io import load_scene
    from spectral_fit.live import (
        MarkerPlacement,
        chart_corners_world,
        colorchecker_reflectances,
        make_table,
    )

    scene = load_scene(config)
    _, _, surfaces = tr.read_config(config, None, None)
    wl = scene.wavelengths
    spec = scene.colour_chart
    if spec is None or scene.markers is None:
        raise SystemExit(f"{config}: needs [markers] and [colour_chart]")
    refl = colorchecker_reflectances(wl, chart=CHART_SET)
    names = list(__import__("colour").SDS_COLOURCHECKERS[CHART_SET])
    paper, ink = refl[names.index(PAPER)], refl[names.index(INK)]
    size = scene.markers.size
    markers = [MarkerPlacement(3, 0.0, 0.0, size), MarkerPlacement(7, MARKER7_X, 0.0, size)]
    # labels through two prints: on black and on white background (paper value v where a
    # marker is, 0 / 255 elsewhere)
    bg0 = make_table(np.zeros((8, 8, 3), np.uint8), markers, extent=TABLE_EXTENT,
                     pitch=TABLE_PITCH, dictionary=scene.markers.dictionary)
    bg1 = make_table(np.full((8, 8, 3), 255, np.uint8), markers, extent=TABLE_EXTENT,
                     pitch=TABLE_PITCH, dictionary=scene.markers.dictionary)
    v0 = bg0.texture[..., 0].astype(np.float64) / 255.0
    v1 = bg1.texture[..., 0].astype(np.float64) / 255.0
    w_base = v1 - v0                    # 1 on the table, 0 on a printed marker sheet
    w_paper = v0                        # paper share of the printed sheet (ink = 1 − it)
    # the chart: patch index per texel (−2 = surround, −1 = none)
    corners = chart_corners_world(spec)  # (4, 3) TL TR BR BL, the marker's ground frame
    ny, nx = bg0.texture.shape[:2]
    xs = bg0.x0 + (np.arange(nx) + 0.5) * TABLE_PITCH
    zs = bg0.z0 + (np.arange(ny) + 0.5) * TABLE_PITCH
    px, pz = np.meshgrid(xs, zs)
    o = corners[0]
    ex, ey = corners[1] - corners[0], corners[3] - corners[0]
    rel = np.stack([px - o[0], pz - o[2]], -1)
    a = np.array([[ex[0], ey[0]], [ex[2], ey[2]]])
    uv = rel @ np.linalg.inv(a).T   # (u, v) in [0, 1] across the chart's patch area
    cols, rows = 6, 4
    u, v = uv[..., 0] * cols, uv[..., 1] * rows
    mu, mv = CHART_GAP / np.linalg.norm(ex) * cols, CHART_GAP / np.linalg.norm(ey) * rows
    inside = (u >= -mu) & (u <= cols + mu) & (v >= -mv) & (v <= rows + mv)
    ci = np.full((ny, nx), -1, np.int16)
    ci[inside] = -2
    cell_w, cell_h = np.linalg.norm(ex) / cols, np.linalg.norm(ey) / rows
    fu, fv = u - np.floor(u), v - np.floor(v)
    gu, gv = 0.5 * CHART_GAP / cell_w, 0.5 * CHART_GAP / cell_h
    patch = (inside & (u >= 0) & (u < cols) & (v >= 0) & (v < rows) & (fu > gu) & (fu < 1 - gu)
             & (fv > gv) & (fv < 1 - gv))
    ci[patch] = (np.floor(v[patch]) * cols + np.floor(u[patch])).astype(np.int16)
    if np.any(ci[[0, -1], :] != -1) or np.any(ci[:, [0, -1]] != -1):
        raise SystemExit("the chart does not fit on the printed table")
    w_base = np.where(ci != -1, 0.0, w_base)
    cs, rs = [], []
    for ob in scene.objects:
        mx = 0.0 if ob.marker == 3 else MARKER7_X
        cs.append(np.array([mx, 0.0, 0.0]) + np.asarray(ob.marker_offset))
        rs.append(float(ob.radius * ob.scale))
    return Setup(scene=scene, wl=wl, table=np.asarray(surfaces[0]["reflectance"]), paper=paper,
                 ink=ink, chart=refl, chart_corners=corners, marker_table=bg0, w_base=w_base,
                 w_paper=w_paper, chart_index=ci, centres=np.asarray(cs), radii=np.asarray(rs))


def texture(st: Setup, idx: np.ndarray) -> np.ndarray:
    """(ny, nx, len(idx)) reflectance of the printed table in the bands ``idx``."""
    base = st.w_base[..., None] * st.table[idx]
    sheet = (1.0 - st.w_base)[..., None] * (st.w_paper[..., None] * st.paper[idx]
                                            + (1.0 - st.w_paper)[..., None] * st.ink[idx])
    out = base + sheet
    ci = st.chart_index
    out[ci == -2] = st.ink[idx]
    for k in range(24):
        out[ci == k] = st.chart[k, idx]
    return out.astype(np.float32)


def texture_at(st: Setup, x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Bilinear reflectance (..., L) of the printed table at world (x, z) (clamped at its
    border, as the renderer's texture)."""
    t = st.marker_table
    ny, nx = st.w_base.shape
    fx = np.clip((x - t.x0) / TABLE_PITCH - 0.5, 0, nx - 1)
    fz = np.clip((z - t.z0) / TABLE_PITCH - 0.5, 0, ny - 1)
    x0 = np.minimum(np.floor(fx).astype(int), nx - 2)
    z0 = np.minimum(np.floor(fz).astype(int), ny - 2)
    ax, az = (fx - x0)[..., None], (fz - z0)[..., None]
    tex = _full_texture(st)
    return ((1 - az) * ((1 - ax) * tex[z0, x0] + ax * tex[z0, x0 + 1])
            + az * ((1 - ax) * tex[z0 + 1, x0] + ax * tex[z0 + 1, x0 + 1]))


_TEX: dict[int, np.ndarray] = {}


def _full_texture(st: Setup) -> np.ndarray:
    if id(st) not in _TEX:
        _TEX[id(st)] = texture(st, np.arange(st.wl.size))
    return _TEX[id(st)]


def table_rectangle(mi: Any, st: Setup, idx: np.ndarray) -> dict[str, Any]:
    """The table: :func:`table_reference.rectangle` (20 m) with the printed texture in the
    bands ``idx``. The rectangle's (u, v) run along its local axes (plane_frame rows t1 = +Z,
    t2 = +X for the normal +Y); ``to_uv`` maps them onto the texture (columns along x, rows
    along z; clamped beyond it)."""
    surface = {"point": np.zeros(3), "normal": np.array([0.0, 1.0, 0.0])}
    half = 10.0
    d = tr.rectangle(mi, surface, np.zeros(3), half)
    tex = texture(st, idx)
    t = st.marker_table
    ny, nx = tex.shape[:2]
    wx, wz = nx * TABLE_PITCH, ny * TABLE_PITCH
    fr = tr.plane_frame(surface["normal"])
    assert np.allclose(fr[0], [0, 0, 1]) and np.allclose(fr[1], [1, 0, 0])
    m = [[0.0, 2 * half / wx, 0.0, (-half - t.x0) / wx],
         [2 * half / wz, 0.0, 0.0, (-half - t.z0) / wz],
         [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
    d["bsdf"]["reflectance"] = {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(tex)),
                                "raw": True, "filter_type": "bilinear", "wrap_mode": "clamp",
                                "to_uv": mi.ScalarTransform4f(m)}
    return d


# --------------------------------------------------------------------------------------------
# the camera path


def camera_path(n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Eye and look-at points (world, m) of n frames: from high above the chart and markers
    round to the right and down towards the objects (the chart leaves the picture), with
    hand shake."""
    rng = np.random.default_rng(seed)
    out = []
    mid = np.array([0.5 * MARKER7_X, 0.0, 0.0])
    for i in range(n):
        s = i / max(n - 1, 1)
        az = math.radians(-20.0 + 45.0 * s)
        el = math.radians(58.0 - 18.0 * s)
        d = 0.43 - 0.08 * s
        look = mid + np.array([0.0, 0.015 * s, 0.075 * (1.0 - s) ** 1.5])
        eye = look + d * np.array([math.cos(el) * math.sin(az), math.sin(el),
                                   math.cos(el) * math.cos(az)])
        out.append((eye + rng.normal(0, 0.001, 3), look + rng.normal(0, 0.0007, 3)))
    return out


def scene_key(sc: Any) -> str:
    """Digest of what the path tracer sees of the config (objects, materials, environment,
    bands, markers, chart, table, camera intrinsics): comments and live-only settings may
    change without rendering again."""
    parts = [sc.width, sc.height, sc.camera.intrinsics, sc.environment.file.name,
             sc.environment.rotation_y_deg, sc.environment.scale, sc.spectral, sc.markers.size,
             sc.markers.dictionary, sc.colour_chart.centre, sc.colour_chart.size,
             sc.colour_chart.rotation_deg, sc.colour_chart.chart,
             np.asarray(sc.surfaces[0].reflectance).round(6).tolist()]
    for o in sc.objects:
        m = o.material
        parts += [o.name, o.shape, o.radius, o.scale, o.marker, o.marker_offset, m.alpha, m.beta,
                  m.chi, m.mu, m.n, m.distribution, m.geometry,
                  np.asarray(m.reflectance).round(6).tolist()]
    return hashlib.sha256(repr(parts).encode()).hexdigest()


def frame_scene(st: Setup, eye: np.ndarray, look: np.ndarray) -> Any:
    """The config's scene seen from ``eye`` towards ``look``, objects at their true places."""
    sc = st.scene
    cam = dataclasses.replace(sc.camera, position=tuple(map(float, eye)),
                              look_at=tuple(map(float, look)), up=(0.0, 1.0, 0.0))
    objs = tuple(dataclasses.replace(o, position=tuple(map(float, c)), marker=None)
                 for o, c in zip(sc.objects, st.centres, strict=True))
    return sc.replace(camera=cam, objects=objs)


# --------------------------------------------------------------------------------------------
# pixel geometry (closed forms)


def sub_rays(scene: Any, n: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Origin (3,) and directions (H, W, n·n, 3) of n × n stratified rays per pixel."""
    from spectral_fit.validation.reference.render import camera_rays

    h, w = scene.height, scene.width
    o = (np.arange(n) + 0.5) / n
    oy, ox = np.meshgrid(o, o, indexing="ij")
    ys, xs = np.mgrid[0:h, 0:w]
    x = xs[..., None] + ox.reshape(-1)
    y = ys[..., None] + oy.reshape(-1)
    return camera_rays(scene, x, y)


def coverage(st: Setup, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(O, H, W) share of each pixel's sub-rays whose first hit is object k (exact spheres)."""
    from spectral_fit.validation.reference.render import sphere_hits

    t = np.stack([sphere_hits(origin, dirs, c, r) for c, r in zip(st.centres, st.radii,
                                                                   strict=True)])
    first = np.argmin(t, axis=0)
    hit = np.isfinite(t.min(axis=0))
    return np.stack([(hit & (first == k)).mean(-1) for k in range(len(st.radii))])


def analytic_table(st: Setup, origin: np.ndarray, dirs: np.ndarray, e_up: np.ndarray
                   ) -> np.ndarray:
    """(H, W, L) the table without objects: ρ(x) E_up/π averaged over the sub-rays (sky
    where a ray misses the plane: not in these views)."""
    p = tr.plane_hits(origin, dirs, [0, 0, 0], [0, 1, 0], 10.0)
    if not np.isfinite(p).all():
        raise SystemExit("a camera ray misses the table")
    refl = texture_at(st, p[..., 0], p[..., 2])   # (H, W, S, L)
    return refl.mean(axis=2) * (e_up / math.pi)


def near_mask(st: Setup, origin: np.ndarray, dirs_c: np.ndarray, k: float) -> np.ndarray:
    """(H, W) pixels whose centre ray meets the table within ``k`` bounding radii of an
    object's centre projected onto it."""
    p = tr.plane_hits(origin, dirs_c, [0, 0, 0], [0, 1, 0], 10.0)
    h, w = p.shape[:2]
    near = tr.near_object(p.reshape(-1, 3), st.centres, st.radii, [0, 0, 0], [0, 1, 0], k)
    return near.reshape(h, w) >= 0


# --------------------------------------------------------------------------------------------
# the path tracer


def render_frame_mitsuba(st: Setup, scene: Any, *, spp: int, spp_near: int, crop: Any,
                         seed: int) -> dict[str, np.ndarray]:
    """``with`` / ``without`` (H, W, L): the frame with and without the objects, same random
    numbers; inside ``crop`` (:class:`Crop`) with ``spp_near`` samples, elsewhere ``spp``."""
    from spectral_fit.validation.reference.backend import init_mitsuba
    from spectral_fit.validation.reference.export import (
        band_groups,
        environment_texels,
        mitsuba_envmap_rows,
        scene_dict,
    )

    mi, _ = init_mitsuba()
    wl = st.wl
    h, w = scene.height, scene.width
    rows = mitsuba_envmap_rows(environment_texels(scene))
    out = {k: np.zeros((h, w, wl.size), np.float32) for k in ("with", "without")}
    for idx in band_groups(wl.size):
        table = table_rectangle(mi, st, idx)
        refl = {o.name: np.asarray(o.material.reflectance)[idx] for o in scene.objects}
        for key, objects in (("with", True), ("without", False)):
            for c, n in ((None, spp), *(((crop, spp_near),) if crop is not None else ())):
                d = tr_scene(scene, rows[..., idx], refl, n, table, objects, c, scene_dict)
                img = np.asarray(mi.render(mi.load_dict(d), seed=seed, spp=n),
                                 np.float32)[..., :3]
                if c is None:
                    out[key][..., idx] = img
                else:
                    out[key][c.y0:c.y0 + c.height, c.x0:c.x0 + c.width, idx] = img
    return out


def tr_scene(scene: Any, rows: np.ndarray, refl: dict, spp: int, table: dict, objects: bool,
             crop: Any, scene_dict: Any) -> dict:
    return scene_dict(scene, env_rgb=rows, reflectances=refl, spp=spp, max_depth=16,
                      crop=crop, analytic_spheres=True, objects=objects,
                      extra_shapes={"table": dict(table)})


def mitsuba_cached(st: Setup, scene: Any, cache: Path, **kw: Any) -> dict[str, Any]:
    """:func:`render_frame_mitsuba` through the cache file ``cache`` (its name carries a
    digest of every setting)."""
    from spectral_fit._runtime.fileio import atomic_path

    if cache.exists():
        with np.load(cache) as z:
            return {k: z[k] for k in ("with", "without", "seconds")}
    t0 = time.perf_counter()
    m = render_frame_mitsuba(st, scene, **kw)
    m["seconds"] = np.float64(time.perf_counter() - t0)
    with atomic_path(cache) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **m)
    return m


def truth_frame(*, st: Setup, scene: Any, cov: np.ndarray, a: np.ndarray, crop: Any,
                spp: int, spp_near: int, key: dict, cache: Path, seed: int
                ) -> tuple[np.ndarray, float]:
    """The frame with the objects (H, W, L), ``M_with + (1 − cov)·(A − M_without)``, and the
    path tracer's seconds."""
    text = json.dumps({**key, "seed_frame": seed})
    path = Path(f"{cache}_{hashlib.sha256(text.encode()).hexdigest()[:16]}.npz")
    m = mitsuba_cached(st, scene, path, spp=spp, spp_near=spp_near, crop=crop, seed=seed)
    free = (1.0 - cov.sum(0))[..., None]
    return m["with"] + free * (a - m["without"]), float(m["seconds"])


# --------------------------------------------------------------------------------------------
# the camera pipeline


class Pipeline:
    """The video camera (:data:`PIPELINE`): spectral radiance (H, W, L) → 8-bit sRGB-like
    frames, frame ``i`` of ``n``."""

    def __init__(self, wl: np.ndarray, e_up: np.ndarray, paper: np.ndarray, n: int,
                 size: tuple[int, int]) -> None:
        import colour

        from spectral_fit.color import integration_weights
        from spectral_fit.live import camera_sensitivities

        self.n = n
        s = camera_sensitivities(PIPELINE["sensitivities"], wl)
        self.sw = s * integration_weights(wl)[:, None]           # (L, 3)
        white = paper * e_up / math.pi
        raw_white = white @ self.sw
        self.k0 = PIPELINE["white_raw_green"] / raw_white[1]      # exposure at frame 0
        self.wb0 = raw_white[1] / raw_white                        # white balance at frame 0
        # factory colour matrix: the 24 patches under D65, white-balanced camera → linear sRGB
        d65 = colour.SDS_ILLUMINANTS["D65"]
        e = np.interp(wl, d65.wavelengths, d65.values)
        refl = np.stack([np.interp(wl, sd.wavelengths, sd.values)
                         for sd in colour.SDS_COLOURCHECKERS[CHART_SET].values()])
        cam = (refl * e) @ self.sw
        cam = cam / (e @ self.sw)
        cmf = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
        xbar = np.stack([np.interp(wl, cmf.wavelengths, cmf.values[:, c]) for c in range(3)],
                        -1)
        xyz = (refl * e) @ xbar / (e @ xbar[:, 1])
        target = colour.XYZ_to_RGB(xyz, "sRGB", apply_cctf_encoding=False)
        m, *_ = np.linalg.lstsq(cam, target, rcond=None)
        c = m.T
        self.matrix = c / c.sum(axis=1, keepdims=True)
        h, w = size
        yy, xx = np.mgrid[0:h, 0:w]
        r2 = ((xx + 0.5 - w / 2) ** 2 + (yy + 0.5 - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
        self.vignette = 1.0 - 0.12 * r2

    def drift(self, i: int) -> tuple[float, np.ndarray]:
        """Exposure and white-balance gains (3,) of frame ``i``."""
        s = i / max(self.n - 1, 1)
        k = self.k0 * (1.0 + 0.06 * s + 0.02 * math.sin(2 * math.pi * s))
        wb = self.wb0 * np.array([1.0 + 0.03 * s, 1.0, 1.0 - 0.03 * s])
        return k, wb

    def __call__(self, radiance: np.ndarray, i: int, rng: np.random.Generator | None
                 ) -> np.ndarray:
        import cv2

        k, wb = self.drift(i)
        raw = (radiance.astype(np.float64) @ self.sw) * k * self.vignette[..., None]
        h, w = raw.shape[:2]
        bayer = np.empty((h, w))
        bayer[0::2, 0::2] = raw[0::2, 0::2, 0]
        bayer[0::2, 1::2] = raw[0::2, 1::2, 1]
        bayer[1::2, 0::2] = raw[1::2, 0::2, 1]
        bayer[1::2, 1::2] = raw[1::2, 1::2, 2]
        if rng is not None:
            sigma = np.sqrt(0.0015 ** 2 + 6e-5 * np.maximum(bayer, 0.0))
            bayer = bayer + rng.normal(0.0, 1.0, bayer.shape) * sigma
        q = np.clip(np.rint(bayer * 4095.0), 0, 4095).astype(np.uint16) * 16
        rgb = cv2.cvtColor(q, cv2.COLOR_BayerRGGB2RGB).astype(np.float64) / (4095.0 * 16)
        lin = np.clip((rgb * wb) @ self.matrix.T, 0.0, 1.0)
        return np.clip(np.rint(255.0 * lin ** (1 / 2.2)), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, default=REPO / "configs" / "live_room.toml")
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--size", type=int, nargs=2, default=None, metavar=("W", "H"),
                    help="frame size (default: the config's; intrinsics scale with it)")
    ap.add_argument("--spp", type=int, default=16, help="samples per pixel away from the "
                    "objects (the control variate makes that table exact)")
    ap.add_argument("--spp-near", type=int, default=256,
                    help="samples per pixel in the window of the objects and the table near them")
    ap.add_argument("--radii", type=float, default=2.0)
    ap.add_argument("--fps", type=float, default=12.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=REPO / "measurements" / "video")
    ap.add_argument("--name", default="room")
    ap.add_argument("--cache", type=Path, default=REPO / "out" / "mr_cache")
    ap.add_argument("--noise-check", type=int, nargs="*", default=[],
                    help="frames rendered a second time with another seed to measure the "
                    "reference's noise (ΔE00 between the two noise-free frames)")
    args = ap.parse_args(argv)

    import cv2

    from spectral_fit._runtime.fileio import atomic_path, atomic_write_text
    from spectral_fit.live import (
        PATCH,
        VideoSink,
        camera_pose_looking_at,
        count_frames,
        frame_delta_e00,
        marker_pose_in_camera,
        patch_delta_e00,
    )
    from spectral_fit.rendering import load_environment
    from spectral_fit.validation.reference.export import Crop

    st = setup(args.config)
    sc = st.scene
    if args.size:
        w, h = args.size
        i = sc.camera.intrinsics
        sx, sy = w / sc.width, h / sc.height
        cam = dataclasses.replace(sc.camera, intrinsics={
            "fx": i["fx"] * sx, "fy": i["fy"] * sy, "cx": (i["cx"] + 0.5) * sx - 0.5,
            "cy": (i["cy"] + 0.5) * sy - 0.5})
        sc = sc.replace(width=w, height=h, camera=cam)
        st = dataclasses.replace(st, scene=sc)
    h, w = sc.height, sc.width
    env = load_environment(sc, st.wl)
    e_up = tr.plane_irradiance(np.asarray(env, np.float64), sc.environment.rotation_y_deg,
                               [0, 1, 0])
    pipe = Pipeline(st.wl, e_up, st.paper, args.frames, (h, w))
    path = camera_path(args.frames, args.seed + 11)
    args.cache.mkdir(parents=True, exist_ok=True)
    truth_dir = args.out / f"{args.name}_truth"
    truth_dir.mkdir(parents=True, exist_ok=True)
    key_base = {"scene": scene_key(sc), "size": [w, h], "spp": args.spp,
                "spp_near": args.spp_near, "radii": args.radii, "frames": args.frames,
                "seed": args.seed, "marker7": MARKER7_X, "extent": TABLE_EXTENT,
                "pitch": TABLE_PITCH, "gap": CHART_GAP, "version": 1}
    poses, ids, nears, seconds, noise = [], [], [], 0.0, {}
    real = VideoSink(args.out / f"{args.name}.mp4", fps=args.fps, size=(h, w))
    withv = VideoSink(args.out / f"{args.name}_objects.mp4", fps=args.fps, size=(h, w))
    t_all = time.perf_counter()
    with real, withv:
        for fi, (eye, look) in enumerate(path):
            scene = frame_scene(st, eye, look)
            origin, dirs = sub_rays(scene)
            cov = coverage(st, origin, dirs)                # (O, H, W)
            a = analytic_table(st, origin, dirs, e_up)      # (H, W, L)
            from spectral_fit.validation.reference.render import camera_rays

            yc, xc = np.mgrid[0:h, 0:w] + 0.5
            _, dc = camera_rays(scene, xc, yc)
            near = near_mask(st, origin, dc, args.radii) & (cov.sum(0) == 0)
            # the window: the objects and the table near them, 4 px of margin
            win = (cov.sum(0) > 0) | near_mask(st, origin, dc, args.radii + 0.5)
            crop = None
            if win.any():
                rr, cc = np.nonzero(win)
                x0, y0 = max(int(cc.min()) - 4, 0), max(int(rr.min()) - 4, 0)
                x1, y1 = min(int(cc.max()) + 5, w), min(int(rr.max()) + 5, h)
                crop = Crop(x0, y0, x1 - x0, y1 - y0)

            common = {"st": st, "scene": scene, "cov": cov, "a": a, "crop": crop,
                      "spp": args.spp, "spp_near": args.spp_near,
                      "key": {**key_base, "frame": fi, "eye": eye.tolist(),
                              "look": look.tolist()},
                      "cache": args.cache / f"{args.name}_{fi:03d}"}
            g, dt = truth_frame(seed=args.seed * 1000 + fi, **common)
            seconds += dt
            if fi in args.noise_check:
                g2, dt2 = truth_frame(seed=args.seed * 1000 + fi + 500, **common)
                seconds += dt2
                f1, f2 = pipe(g, fi, None), pipe(g2, fi, None)
                de = frame_delta_e00(f1 / 255.0, f2 / 255.0, tone="gamma", gamma=2.2)
                obj = cov.max(0) >= 1.0
                pobj, pnear = (patch_delta_e00(f1, f2, m) for m in (obj, near))
                noise[str(fi)] = {"objects_median": float(np.median(de[obj])),
                                  "objects_p90": float(np.percentile(de[obj], 90)),
                                  "near_median": float(np.median(de[near])),
                                  "near_p90": float(np.percentile(de[near], 90)),
                                  f"objects_{PATCH}x{PATCH}_median": float(np.median(pobj)),
                                  f"objects_{PATCH}x{PATCH}_p90": float(np.percentile(pobj, 90)),
                                  f"near_{PATCH}x{PATCH}_median": float(np.median(pnear)),
                                  f"near_{PATCH}x{PATCH}_p90": float(np.percentile(pnear, 90)),
                                  "note": "ΔE00 between two independent references of the "
                                          "frame (the noise of one is about 1/√2 of it)"}
            real.write(pipe(a, fi, np.random.default_rng([args.seed, fi, 1])))
            withv.write(pipe(g, fi, np.random.default_rng([args.seed, fi, 1])))
            clean = pipe(g, fi, None)
            with atomic_path(truth_dir / f"frame_{fi:03d}.png") as tmp:
                cv2.imwrite(str(tmp), cv2.cvtColor(clean, cv2.COLOR_RGB2BGR),
                            [cv2.IMWRITE_PNG_COMPRESSION, 9])
            oid = np.full((h, w), -1, np.int8)
            for k in range(cov.shape[0]):
                oid[cov[k] >= 1.0] = k
            oid[(cov.sum(0) > 0) & (cov.max(0) < 1.0)] = -2
            ids.append(oid)
            nears.append(near)
            r, t = camera_pose_looking_at(eye, look)
            poses.append({"frame": fi, "camera_R": r.tolist(), "camera_t": t.tolist(),
                          "markers": {str(m.marker_id): dict(zip(("R", "t"), (
                              x.tolist() for x in marker_pose_in_camera(st.marker_table,
                                                                        m.marker_id, r, t)),
                              strict=True)) for m in st.marker_table.markers}})
            print(f"[mr] frame {fi + 1}/{args.frames}: {dt:.0f} s (crop {crop})", flush=True)
    with atomic_path(truth_dir / "masks.npz") as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, object_id=np.stack(ids), near=np.stack(nears))
    i = sc.camera.intrinsics
    k = np.array([[i["fx"], 0, i["cx"]], [0, i["fy"], i["cy"]], [0, 0, 1.0]])
    meta = {"scene": args.name, "intrinsics": k.tolist(), "distortion": [0.0] * 5,
            "size_hw": [h, w], "marker_size": sc.markers.size,
            "markers": [[m.marker_id, m.x, m.z] for m in st.marker_table.markers],
            "fps": args.fps, "note": "poses of each frame (no motion blur)", "frames": poses}
    atomic_write_text(args.out / f"{args.name}.poses.json", json.dumps(meta) + "\n")
    info = {"config": os.path.relpath(args.config.resolve(), truth_dir.resolve()),
            "video": f"../{args.name}.mp4", "video_with_objects": f"../{args.name}_objects.mp4",
            "poses": f"../{args.name}.poses.json", "frames": args.frames, "size": [w, h],
            "spp": args.spp, "spp_near": args.spp_near, "max_depth": 16,
            "radii": args.radii, "seed": args.seed, "fps": args.fps,
            "mitsuba_seconds": round(seconds, 1),
            "wall_seconds": round(time.perf_counter() - t_all, 1),
            "table": {"extent_m": TABLE_EXTENT, "pitch_m": TABLE_PITCH,
                      "markers": [[m.marker_id, m.x, m.z] for m in st.marker_table.markers],
                      "marker_size_m": sc.markers.size, "paper": f"{CHART_SET}/{PAPER}",
                      "ink": f"{CHART_SET}/{INK}", "chart": CHART_SET,
                      "chart_corners_world": st.chart_corners.tolist()},
            "objects": [{"name": o.name, "centre": c.tolist(), "radius": r}
                        for o, c, r in zip(sc.objects, st.centres, st.radii, strict=True)],
            "pipeline": PIPELINE, "colour_matrix": pipe.matrix.tolist(),
            "reference_noise": noise}
    atomic_write_text(truth_dir / "truth.json", json.dumps(info, indent=2) + "\n")
    n1 = count_frames(args.out / f"{args.name}.mp4")
    print(f"[mr] wrote {args.out}/{args.name}.mp4 ({n1} frames), {args.name}_objects.mp4, "
          f"{truth_dir}; Mitsuba {seconds:.0f} s", flush=True)
    return 0 if n1 == args.frames else 1


if __name__ == "__main__":
    raise SystemExit(main())
