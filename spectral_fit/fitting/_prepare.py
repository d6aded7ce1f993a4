"""Preparation of a fit, outside ``jit``, once per session (:func:`prepare_fit`).

Builds the scene's meshes and the environment map, rasterises every reading's measuring
field from the instrument's pose (a square camera whose field of view is the field angle;
pixels inside the inscribed disc), and stores a :class:`~spectral_fit.geometry.GBuffer` of
the surface points seen, their material-independent radiance cache
(:func:`~spectral_fit.fitting.build_radiance_cache`: exact visible irradiance,
mirror-direction radiance, fixed gloss nodes with their radiance, and the interreflection
probes on the neighbours), the environment radiance of pixels that miss every object, the
environment calibration k(λ), the instrument's band-pass and the reading weights. The result
is a :class:`~spectral_fit.fitting.FitProblem` pytree with its host-side companions.

Shapes: B readings, P = B·R² samples, O objects, L bands (the session's wavelengths).
"""

from __future__ import annotations

import math
import time
import warnings
from typing import Any

import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from ..geometry import GBuffer, ObjectGeometry
from ..io import PARAMETERS, Scene, Session
from ..lighting import EnvironmentMap
from ._model_error import with_model_error
from ._options import FitOptions
from ._problem import (
    FitInstrument,
    FitProblem,
    FitReadings,
    FitSurfaces,
    PreparedFit,
    row_kinds,
)
from ._radiance_cache import FieldAverage
from ._spots import _spot_samples, disc_pixels

__all__ = [
    "prepare_fit",
    "scene_geometry",
    "scene_environment",
    "band_matrix",
]


def scene_geometry(scene: Scene) -> list[ObjectGeometry]:
    """World-space meshes of the scene's objects (config order), as :class:`ObjectGeometry`."""
    out = []
    for o in scene.objects:
        mw = o.make_mesh(world=True)
        out.append(ObjectGeometry(vertices=jnp.asarray(mw.vertices, jnp.float32),
                                  normals=jnp.asarray(mw.normals, jnp.float32),
                                  triangles=jnp.asarray(mw.triangles, jnp.int32),
                                  centre=jnp.asarray(o.position, jnp.float32)))
    return out


def scene_environment(scene: Scene, *, dtype: Any = jnp.float32, compress_tol: float = 1e-4
                      ) -> EnvironmentMap:
    """The scene's environment map on its wavelength grid (config scale and rotation applied),
    as the frame's: below a ``[[surfaces]]`` plane's horizon the plane's own radiance."""
    from ..rendering import ground_surfaces, load_environment

    spec = scene.environment
    img = ground_surfaces(scene, load_environment(scene, scene.wavelengths))
    return EnvironmentMap.from_array(img, rotation_y_deg=spec.rotation_y_deg, dtype=dtype,
                                     compress_tol=compress_tol, path=str(spec.file))


def band_matrix(wavelengths: np.ndarray, bandwidth_nm: float) -> np.ndarray:
    """(L, L) instrument band-pass on the scene grid: output band j = ∫ tri_j(λ) s(λ) dλ /
    ∫ tri_j, with tri_j a triangle of FWHM ``bandwidth_nm`` centred on λ_j and s the
    piecewise-linear spectrum through the samples (ends held); identity when the bandwidth is
    0. A spectroradiometer reports band-pass-weighted radiance; narrow lines of the
    environment (fluorescent tubes) are thereby smeared over neighbouring bands, and the model
    is passed through the same response before it is compared with the readings."""
    wl = np.asarray(wavelengths, np.float64)
    if bandwidth_nm <= 0:
        return np.eye(wl.size)
    fine = np.arange(wl[0] - bandwidth_nm, wl[-1] + bandwidth_nm + 1e-9, 0.25)
    H = np.stack([np.interp(fine, wl, e) for e in np.eye(wl.size)], -1)  # (F, L) hats
    W = np.maximum(0.0, 1.0 - np.abs(fine[None, :] - wl[:, None]) / bandwidth_nm)
    W /= W.sum(axis=1, keepdims=True)
    return W @ H


def _calibration(session: Session, env: Any, band: np.ndarray) -> np.ndarray:
    from ..lighting import irradiance_exact

    L = session.wavelengths.size
    if session.calibration != "white":
        return np.ones(L)
    w = session.white
    e = np.asarray(irradiance_exact(env, jnp.asarray(w.normal, env.texels.dtype)), np.float64)
    e = band @ e
    if np.any(e <= 0):
        raise session.error("white_standard.normal", "the environment gives no irradiance on "
                            "the white standard at some wavelengths (does the normal face away "
                            "from every light?)")
    return math.pi * w.mean / (w.reflectance * e)


def _stated(fraction: float | str) -> float:
    """A stated model error, 0 for "auto" (estimated later, by the fit)."""
    return 0.0 if isinstance(fraction, str) else float(fraction)


def prepare_fit(scene: Scene, session: Session, *, options: FitOptions | None = None,
                env: Any = None, geometries: list[ObjectGeometry] | None = None,
                check: bool = True) -> PreparedFit:
    """Rasterise the readings' fields and precompute everything parameter-independent.

    Raises:
        InputError: a spot misses its object (< 50 % of the field on it), a stated distance
            disagrees with the geometry, or the session's objects are not the scene's.
    """
    from .._runtime.process import single_threaded_blas

    # NumPy's OpenBLAS on one thread: on a loaded 2-core machine its busy-waiting second
    # thread costs several times the CPU of one thread (docs/fitting.md, "Speed")
    with single_threaded_blas():
        return _prepare_fit(scene, session, options=options, env=env, geometries=geometries,
                            check=check)


def _prepare_fit(scene: Scene, session: Session, *, options: FitOptions | None,
                 env: Any, geometries: list[ObjectGeometry] | None, check: bool) -> PreparedFit:
    opts = options or FitOptions()
    t0 = time.perf_counter()
    dtype = opts.dtype
    names = tuple(o.name for o in scene.objects)
    for r in session.readings:
        if r.object not in names:
            raise session.error(f"{r.field}.object", f"unknown object {r.object!r}; the scene "
                                f"has {list(names)}")
    if env is None:
        env = scene_environment(scene, dtype=dtype, compress_tol=opts.compress_tol)
    if geometries is None:
        geometries = scene_geometry(scene)
    readings = session.readings
    if not readings and not session.images:
        raise InputError("no readings to fit", path=session.path, field="readings")
    B = len(readings)
    res = int(opts.spot_resolution)
    if not 2 <= res <= 64:
        raise InputError(f"must be in [2, 64], got {res}", field="spot_resolution")
    if B:
        S = _spot_samples(geometries, np.stack([r.position for r in readings]),
                          np.stack([r.aim for r in readings]),
                          np.array([r.field_angle_deg for r in readings]), res)
    else:  # photographs only
        nd0 = disc_pixels(res).size
        S = {"obj": np.zeros((0, nd0), np.int64), "xy": np.zeros((nd0, 2)),
             **{k: np.zeros((0, nd0, 3)) for k in ("pos", "nrm", "view", "ray")}}
    nd = S["obj"].shape[1]
    warn: list[str] = []
    coverage = np.zeros(B)
    for b, r in enumerate(readings):
        on = int(np.sum(S["obj"][b] == names.index(r.object)))
        coverage[b] = on / nd
        if not check:
            continue
        if coverage[b] < 0.5:
            raise session.error(f"{r.field}.aim", f"the spot misses object {r.object!r}: only "
                                f"{100 * coverage[b]:.0f} % of the {r.field_angle_deg:g}° field "
                                "sees it")
        if coverage[b] < 0.99:
            warn.append(f"reading {r.id!r}: {100 * (1 - coverage[b]):.0f} % of the field "
                        "is off the object (modelled)")
        if r.distance_m is not None:
            centre = np.argsort(np.sum(S["xy"] ** 2, axis=1))[:4]
            ok = S["obj"][b][centre] >= 0
            if ok.any():
                d = float(np.mean(np.linalg.norm(S["pos"][b][centre][ok] - r.position, axis=1)))
                if abs(d - r.distance_m) > 0.005 + 0.02 * r.distance_m:
                    raise session.error(f"{r.field}.distance_m", f"stated {r.distance_m:g} m "
                                        f"but the geometry puts the spot at {d:.4f} m from the "
                                        "instrument")
    P = B * nd
    pos_all, nrm_all, view_all = (S[k].reshape(P, 3) for k in ("pos", "nrm", "view"))
    obj = S["obj"].reshape(P).astype(np.int32)
    pix = np.tile(disc_pixels(res).astype(np.int32), B)
    groups = np.repeat(np.arange(B), nd)
    # camera photographs: one row per kept bin, its samples after the spots'
    from ._image_rows import image_rows

    img_rows = [image_rows(im, i, geometries, names, session.wavelengths)
                for i, im in enumerate(session.images)]
    for ir in img_rows:
        im = session.images[ir.image]
        if ir.row_bin.shape[0] == 0:
            raise session.error(im.field, f"no usable {im.superpixel}-pixel bin of image "
                                f"{im.id!r} lies on an object (left out: {ir.dropped}); check "
                                "the camera pose and the objects named")
    n_img = sum(ir.row_bin.shape[0] for ir in img_rows)
    if img_rows:
        pos_all = np.concatenate([pos_all] + [ir.pos for ir in img_rows])
        nrm_all = np.concatenate([nrm_all] + [ir.nrm for ir in img_rows])
        view_all = np.concatenate([view_all] + [ir.view for ir in img_rows])
        obj = np.concatenate([obj] + [ir.object[ir.row_bin[ir.sample_row]].astype(np.int32)
                                      for ir in img_rows])
        pix = np.concatenate([pix] + [np.zeros(ir.sample_row.size, np.int32)
                                      for ir in img_rows])
        offsets = np.cumsum([B] + [ir.row_bin.size for ir in img_rows])[:-1]
        groups = np.concatenate([groups] + [o + ir.sample_row
                                            for o, ir in zip(offsets, img_rows, strict=True)])
        sample_w = np.concatenate([np.full(P, 1.0 / nd)]
                                  + [ir.sample_weight for ir in img_rows])
    else:
        sample_w = np.full(P, 1.0 / nd)
    recv = GBuffer(position=jnp.asarray(pos_all, dtype), normal=jnp.asarray(nrm_all, dtype),
                   view=jnp.asarray(view_all, dtype), object=jnp.asarray(obj),
                   pixel=jnp.asarray(pix))
    valid = obj >= 0
    rays = S["ray"].reshape(P, 3)
    L = session.wavelengths.size
    bgp = np.zeros((P, L))
    if (~valid[:P]).any():
        from ._env_sampling import _env_lookup

        bgp[~valid[:P]] = _env_lookup(env, rays[~valid[:P]])
    avg = FieldAverage(row=jnp.asarray(groups, jnp.int32), weight=jnp.asarray(sample_w, dtype),
                       rows=B + n_img)
    bg = np.zeros((B + n_img, L))
    if B:
        bg[:B] = FieldAverage(row=jnp.asarray(groups[:P], jnp.int32),
                              weight=jnp.asarray(sample_w[:P]), rows=B).apply_np(bgp)
    # material-independent radiance: irradiance, mirror direction, gloss nodes, neighbours
    from ._cache_build import build_radiance_cache
    from ._radiance_cache import CacheOptions

    mode = scene.interreflection.mode if opts.interreflection == "auto" else "none"
    spheres, meshes = _scene_occluders(scene, geometries)
    if mode == "none":
        spheres = []  # the direct light: a mesh still hides its own points' sky
    cache = build_radiance_cache(
        env, pos_all, nrm_all, view_all, obj, groups, weights=sample_w, spheres=spheres,
        meshes=meshes, interreflection=mode != "none",
        options=opts.cache or CacheOptions(), dtype=dtype, probe_groups=B)
    # reflectances and parameters
    O = len(names)
    refl = np.zeros((O, session.wavelengths.size))
    sci = np.zeros(O)
    vals = np.zeros((O, 6))
    models = []
    for o, ob in enumerate(scene.objects):
        m = ob.material
        om = session.objects.get(ob.name)
        refl[o] = m.reflectance if (om is None or om.reflectance is None) else om.reflectance
        sci[o] = 1.0 if (om is not None and om.geometry == "SCI") else 0.0
        for k, pname in enumerate(PARAMETERS):
            vals[o, k] = float(getattr(m, pname))
            if om is not None and pname in om.start:
                vals[o, k] = om.start[pname]
        models.append((m.distribution, m.geometry))
    measured = np.zeros((B + n_img, L))
    sigma = np.ones((B + n_img, L))
    if B:
        measured[:B] = np.stack([r.mean for r in readings])
        nrep = np.array([r.repeats.shape[0] for r in readings], np.float64)
        sigma[:B] = session.noise.sigma(measured[:B]) / np.sqrt(nrep)[:, None]
    C = max([ir.response.shape[0] for ir in img_rows], default=0)
    response = np.zeros((n_img, C, L))
    row = B
    for ir in img_rows:
        n, c = ir.row_bin.shape[0], ir.response.shape[0]
        measured[row:row + n, :c] = ir.measured
        sigma[row:row + n, :c] = ir.sigma
        response[row - B:row - B + n, :c] = ir.response[None] * ir.mask[:, :, None]
        row += n
    # the model's own error stated per kind, in quadrature ("auto": estimated by the fit)
    sigma = with_model_error(sigma, measured, row_kinds(session, n_img),
                             {k: _stated(v) for k, v in session.model_error.items()})
    sigma = np.maximum(sigma, 1e-12)
    kinds_rows = row_kinds(session, n_img)
    level, tilt = (np.array([float(table.get(k, 0.0)) for k in kinds_rows])
                   if any(v > 0 for v in table.values()) else None
                   for table in (session.level_error, session.tilt_error))
    band = band_matrix(session.wavelengths, session.bandwidth_nm)
    calib = _calibration(session, env, band)
    # what is free
    measured_objs = {r.object for r in readings} | {
        names[o] for ir in img_rows for o in np.unique(ir.object)}
    free = []
    for o, name in enumerate(names):
        if name not in measured_objs:
            continue
        om = session.objects.get(name)
        fr = om.free if om is not None else ("alpha", "beta", "chi", "mu", "n")
        for k, pname in enumerate(PARAMETERS):
            if pname not in fr:
                continue
            if session.calibration == "global" and name == session.reference and pname == "alpha":
                continue  # the gauge: scale and this alpha are degenerate
            free.append((o, k))
    bounds, prior = _bounds_and_priors(session, names, free, vals)
    problem = FitProblem(
        env=env, receivers=recv, cache=cache,
        readings=FitReadings(average=avg, background=jnp.asarray(bg, dtype),
                             measured=jnp.asarray(measured, dtype),
                             sigma=jnp.asarray(sigma, dtype),
                             response=jnp.asarray(response, dtype),
                             level=None if level is None else jnp.asarray(level, dtype),
                             tilt=None if tilt is None else jnp.asarray(tilt, dtype)),
        instrument=FitInstrument(calibration=jnp.asarray(calib, dtype),
                                 band=jnp.asarray(band, dtype)),
        surfaces=FitSurfaces(reflectance=jnp.asarray(refl, dtype), sci=jnp.asarray(sci, dtype),
                             models=tuple(models)),
        values=jnp.asarray(vals, dtype), free=tuple(free),
        fit_scale=session.calibration == "global",
        interreflection=mode != "none" and (bool(spheres) or bool(meshes)),
        bounds=bounds, prior=prior)
    for w in warn:
        warnings.warn(w, RuntimeWarning, stacklevel=2)
    return PreparedFit(problem=problem, session=session, objects=names, geometries=geometries,
                    coverage=coverage, warnings=warn, seconds=time.perf_counter() - t0,
                    images=img_rows)


def _bounds_and_priors(session: Session, names: list[str], free: list[tuple[int, int]],
                       vals: np.ndarray) -> tuple[tuple[Any, ...], tuple[Any, ...]]:
    """The free parameters' (lower, upper) limits (stated bounds, else the physical ones;
    upper inf: none) and Gaussian priors (index into ``free``, mean, σ) from the session's
    objects; start values ``vals`` (O, 6) outside a stated bound are moved onto it (in
    place). () for either when the session states none."""
    from ._params import LOWER

    bounds, prior, stated = [], [], False
    for j, (o, k) in enumerate(free):
        pname = PARAMETERS[k]
        om = session.objects.get(names[o])
        lo, hi = (om.bounds.get(pname, (None, None)) if om is not None else (None, None))
        stated |= lo is not None or hi is not None
        lo = LOWER[pname] if lo is None else lo
        hi = math.inf if hi is None else hi
        vals[o, k] = min(max(vals[o, k], lo), hi)
        bounds.append((float(lo), float(hi)))
        if om is not None and pname in om.prior:
            m, sd = om.prior[pname]
            prior.append((j, float(m), float(sd)))
    return (tuple(bounds) if stated else ()), tuple(prior)


def _scene_occluders(scene: Scene, geometries: Any) -> tuple[list[Any], list[Any]]:
    """The scene's objects as occluders of the radiance cache: uv_sphere and icosphere
    objects as spheres (world centre, radius × scale: exact, analytic), mesh objects as their
    world meshes (the frame's visibility test; convex ones hide nothing from themselves)."""
    from ..geometry import is_convex
    from ._occluders import MeshOccluder
    from ._radiance_cache import Sphere

    spheres, meshes = [], []
    for o, ob in enumerate(scene.objects):
        if ob.shape in ("uv_sphere", "icosphere"):
            spheres.append(Sphere(object=o, centre=np.asarray(ob.position, np.float64),
                                  radius=float(ob.radius) * float(ob.scale)))
            continue
        g = geometries[o]
        v, t, n = (np.asarray(a) for a in (g.vertices, g.triangles, g.normals))
        meshes.append(MeshOccluder(object=o, vertices=v, triangles=t, normals=n,
                                   convex=is_convex(v, t, n)))
    return spheres, meshes
