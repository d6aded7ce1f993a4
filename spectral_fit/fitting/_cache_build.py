"""Building the :class:`~spectral_fit.fitting.RadianceCache` of field samples, outside
``jit``: gloss nodes, exact visible irradiance, mirror radiance, and the interreflection
probes on the neighbours with the hits that refer to them.

Shapes: P field samples, B readings, Q probes, H gloss hits, C environment channels (bands),
O objects; positions in metres.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np

from ._cache_geometry import _fibonacci_cap, _ray_spheres, _unit
from ._env_sampling import _env_lookup, _texel_table
from ._gloss_nodes import build_gloss_nodes
from ._occluders import MeshOccluder, PointOcclusion
from ._radiance_cache import CacheOptions, FieldAverage, RadianceCache, Sphere, _concat_nodes
from ._spots import cast_rays, scene_triangles

__all__ = ["build_radiance_cache"]


def _coarse_texels(env: Any, dirs: np.ndarray, sa: np.ndarray, tex: np.ndarray,
                   spacing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The texel table merged into blocks of f × f texels (f the largest power of two that
    divides the map's sides and keeps a texel's height below ``spacing`` radians): solid
    angles summed, radiance averaged by solid angle (the flux kept), directions the
    solid-angle-weighted mean."""
    h, w = env.texels.shape[:2]
    f = 1
    while h % (2 * f) == 0 and w % (2 * f) == 0 and 2 * f * math.pi / h <= spacing:
        f *= 2
    if f == 1:
        return dirs, sa, tex
    c = tex.shape[1]
    blk = lambda a, k: a.reshape(h // f, f, w // f, f, k).sum(axis=(1, 3)).reshape(-1, k)  # noqa: E731
    s_ = blk(sa[:, None], 1)[:, 0]
    t_ = blk(sa[:, None] * tex, c) / np.maximum(s_, 1e-300)[:, None]
    d_ = _unit(blk(sa[:, None] * dirs, 3))
    return d_, s_, t_


def _silhouette_cone(s: Sphere, X: np.ndarray, objects: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cone sphere ``s`` fills as seen from points X (n, 3): unit axis towards its centre
    (n, 3), cosine of the half-angle asin(radius/distance) (n,), and whether it hides
    anything from each point (n,) (not its own object's, not from inside it)."""
    rel = s.centre[None] - X
    dist = np.linalg.norm(rel, axis=1)
    axis = rel / np.maximum(dist, 1e-300)[:, None]
    cos_half = np.sqrt(np.maximum(1.0 - (s.radius / np.maximum(dist, 1e-300)) ** 2, 0.0))
    return axis, cos_half, (objects != s.object) & (dist > s.radius)


def _visible_irradiance(env: Any, X: np.ndarray, N: np.ndarray, objects: np.ndarray,
                        spheres: Sequence[Sphere], chunk: int = 64, *,
                        occlusion: PointOcclusion | None = None,
                        rows: np.ndarray | None = None
                        ) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray, np.ndarray,
                                                          np.ndarray]]]:
    """Exact texel-sum irradiance (P, C) of the environment visible from each point, and per
    chunk the hidden texels: (point index, cos·Δω, hit occluder, hit point).

    A texel direction is hidden by a sphere when it lies inside the sphere's silhouette cone
    from the point (angle to the centre <= asin(radius/distance)); by the meshes of
    ``occlusion`` (whose point ``rows[i]`` is ``X[i]``) in the fraction its bilinear taps in
    the occlusion's direction grid say; computed in float32."""
    dirs, sa, tex = _texel_table(env)
    taps = None
    if occlusion is not None and occlusion.has_meshes:
        # what the meshes hide is summed over a coarser table (texels about half the
        # direction grid's spacing: the grid resolves no finer)
        c_dirs, c_sa, c_tex = _coarse_texels(env, dirs, sa, tex, 2.0 * math.pi / (
            4.0 * occlusion.resolution))
        taps = occlusion.taps(c_dirs)
        c_d32 = c_dirs.astype(np.float32)
        c_sa32 = c_sa.astype(np.float32)
        c_tex32 = c_tex.astype(np.float32)
    d32 = dirs.astype(np.float32)
    tex32 = tex.astype(np.float32)
    P = X.shape[0]
    E = np.zeros((P, tex.shape[1]))
    hidden = []
    for a in range(0, P, chunk):
        sl = slice(a, min(P, a + chunk))
        w = np.maximum(N[sl].astype(np.float32) @ d32.T, 0.0) * sa[None].astype(np.float32)
        cones = [_silhouette_cone(s, X[sl], objects[sl]) for s in spheres]
        for si, (s, (axis, cos_half, use)) in enumerate(zip(spheres, cones, strict=True)):
            if not use.any():
                continue
            inside = (axis.astype(np.float32) @ d32.T >= cos_half[:, None]) & use[:, None]
            pi, ti = np.nonzero(inside & (w > 0.0))
            if pi.size:
                hw = w[pi, ti].astype(np.float64)
                w[pi, ti] = 0.0
                o = X[sl][pi]
                oc = o - s.centre
                bq = np.sum(oc * dirs[ti], -1)
                t = -bq - np.sqrt(np.maximum(bq * bq - np.sum(oc * oc, -1) + s.radius ** 2,
                                             0.0))
                hidden.append((pi + a, hw, np.full(pi.size, si), o + t[:, None] * dirs[ti]))
        E[sl] = w @ tex32
        if taps is not None:
            frac, occ, hp = occlusion.hidden_share(  # type: ignore[union-attr]
                rows[sl][:, None], taps[0][None], taps[1][None])  # type: ignore[index]
            wc = np.maximum(N[sl].astype(np.float32) @ c_d32.T, 0.0) * c_sa32[None]
            pi, ti = np.nonzero((frac > 0.0) & (wc > 0.0))
            for axis, cos_half, use in cones:  # what a sphere hides is its own (above)
                behind = use[pi] & (np.sum(axis[pi] * c_dirs[ti], -1) >= cos_half[pi])
                pi, ti = pi[~behind], ti[~behind]
            if pi.size:
                hw = (wc[pi, ti] * frac[pi, ti]).astype(np.float64)
                np.subtract.at(E[sl], pi, hw[:, None] * c_tex32[ti])
                hidden.append((pi + a, hw, occ[pi, ti], hp[pi, ti]))
    return E, hidden


def _facing(n: np.ndarray, p: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Unit normals (N, 3) turned to face ``origin`` (an open mesh is two-sided: a probe
    faces the spot it lights)."""
    n = _unit(np.asarray(n, np.float64))
    return np.where((np.sum(n * (origin - p), -1) < 0.0)[:, None], -n, n)


def _first_hits(scene: tuple[Any, ...], origin: np.ndarray, dirs: np.ndarray,
                spheres: Sequence[Sphere], n_spheres: int, *, skip: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The first occluder (index: spheres, then meshes; −1 none) along rays (N, 3) from
    ``origin``, its hit point and normal: the meshes through their hierarchy (``scene``: bvh,
    vertices, normals, triangles, each triangle's occluder), the spheres analytically (the
    sphere of object ``skip`` ignored)."""
    bvh, verts, norms, tris, tri_occ = scene
    # two-sided: an open mesh's back is a surface too (a closed one's is never met from
    # outside)
    k, p, n = cast_rays(bvh, origin, dirs, verts, norms, tris, tri_occ, chunk=512,
                        two_sided=True)
    t = np.where(k >= 0, np.linalg.norm(p - origin, axis=1), np.inf)
    if n_spheres:
        ks, ts = _ray_spheres(np.broadcast_to(origin, dirs.shape), dirs, spheres,
                              np.array(skip))
        nearer = (ks >= 0) & (ts < t)
        k = np.where(nearer, -1, k)  # a sphere in front: its probes are its own
    return k, p, n


def build_radiance_cache(env: Any, positions: np.ndarray, normals: np.ndarray,
                         views: np.ndarray, objects: np.ndarray, groups: np.ndarray, *,
                         weights: np.ndarray | None = None, spheres: Sequence[Sphere] = (),
                         meshes: Sequence[MeshOccluder] = (), interreflection: bool = True,
                         options: CacheOptions | None = None, dtype: Any = jnp.float32,
                         probe_groups: int | None = None) -> RadianceCache:
    """Precompute the :class:`RadianceCache` of P field samples (outside ``jit``).

    Args:
        env: :class:`~spectral_fit.lighting.EnvironmentMap` (bands).
        positions, normals, views: (P, 3) world samples (invalid ones: any values).
        objects: (P,) object per sample, −1 for none.
        groups: (P,) reading of each sample (probes are made per reading and neighbour).
        weights: (P,) each sample's weight in its reading's field mean (default: the mean of
            each group's samples).
        spheres: the sphere objects for occlusion and interreflection (analytic).
        meshes: the mesh objects for occlusion and interreflection (:class:`MeshOccluder`:
            the frame's shadow-map visibility at the samples and probes, a non-convex mesh
            hiding parts of its own points' sky and lighting them).
        interreflection: False: no probes, and the meshes hide only their own object's
            points (the direct light, as the frame's mode "none"); the spheres given are
            occluders either way.
        probe_groups: only groups below this get probes (None: every group); the others are
            occluded by the neighbours but receive no light from them.
    """
    opts = options or CacheOptions()
    X = np.asarray(positions, np.float64)
    N = _unit(np.asarray(normals, np.float64))
    V = _unit(np.asarray(views, np.float64))
    obj = np.asarray(objects, np.int64)
    grp = np.asarray(groups, np.int64)
    valid = obj >= 0
    P = X.shape[0]
    C = env.texels.shape[-1]
    if meshes and interreflection:
        from ..geometry import build_bvh, octahedral_directions

        verts, norms, tris, tri_mesh = scene_triangles(list(meshes))
        scene_bvh = (build_bvh(verts, tris), verts, norms, tris, tri_mesh + len(spheres))
        grid = octahedral_directions(opts.visibility)[0].astype(np.float64)
        size = float(np.ptp(verts, axis=0).max())
        lift = 1e-4 * size
    # probes: per reading and neighbour, directions from the spot centre over its silhouette
    occ_object = np.array([sp.object for sp in spheres] + [m.object for m in meshes], np.int64)
    probe_dirs, probe_pts, probe_sph, probe_grp, probe_orig = [], [], [], [], []
    probe_nrm: list[np.ndarray] = []
    if interreflection and (spheres or meshes):
        for b in np.unique(grp[valid]):
            if probe_groups is not None and b >= probe_groups:
                break
            sel = valid & (grp == b)
            xb = X[sel].mean(axis=0)
            ob = int(np.bincount(obj[sel]).argmax())
            for si, s in enumerate(spheres):
                if s.object == ob:
                    continue
                d = np.linalg.norm(s.centre - xb)
                if d <= s.radius:
                    continue
                half = math.asin(s.radius / d) * 0.999
                u = _fibonacci_cap((s.centre - xb) / d, half, opts.probes)
                k, t = _ray_spheres(np.broadcast_to(xb, u.shape), u, [s], np.array(-1))
                u, t = u[k >= 0], t[k >= 0]
                probe_dirs.append(u)
                probe_pts.append(xb + t[:, None] * u)
                probe_sph.append(np.full(u.shape[0], si))
                probe_grp.append(np.full(u.shape[0], b))
                probe_orig.append(np.broadcast_to(xb, u.shape))
                probe_nrm.append(_unit(probe_pts[-1] - s.centre))
            if meshes:
                # the meshes (the spot's own object too, where it hides its sky): what the
                # spot's most central sample sees of them along the upper half of the
                # direction grid (ray casting, first hits), at most ``probes`` per mesh,
                # spread by taking every k-th
                cand = np.flatnonzero(sel)
                rb = cand[np.argmin(np.linalg.norm(X[cand] - xb, axis=1))]
                hk, hp, hn = _first_hits(scene_bvh, X[rb] + lift * N[rb], grid[grid @ N[rb] > 0],
                                         spheres, len(spheres), skip=ob)
                for j in range(len(meshes)):
                    ks = np.flatnonzero(hk == len(spheres) + j)
                    if ks.size == 0:
                        continue
                    ks = ks[np.unique(np.linspace(0, ks.size - 1, min(ks.size, opts.probes)
                                                  ).round().astype(int))]
                    probe_dirs.append(_unit(hp[ks] - xb))
                    probe_pts.append(hp[ks])
                    probe_sph.append(np.full(ks.size, len(spheres) + j))
                    probe_grp.append(np.full(ks.size, b))
                    probe_orig.append(np.broadcast_to(X[rb], hp[ks].shape))
                    probe_nrm.append(hn[ks])
    occ = None
    if meshes:
        # every sample and probe gets a row (invalid samples at a valid one's place: unused)
        first = int(np.argmax(valid)) if valid.any() else 0
        Xs = np.where(valid[:, None], X, X[first] if P else 0.0)
        Ns = np.where(valid[:, None], N, N[first] if P else [0.0, 1.0, 0.0])
        pts0 = np.concatenate([Xs] + probe_pts) if probe_pts else Xs
        nrm0 = np.concatenate([Ns] + [_facing(n, p, o) for n, p, o in zip(
            probe_nrm, probe_pts, probe_orig, strict=True)]) if probe_pts else Ns
        obj0 = np.concatenate([obj] + [occ_object[k] for k in probe_sph]) if probe_pts else obj
        occ = PointOcclusion(pts0, nrm0, obj0, spheres=spheres, meshes=meshes,
                             own_only=not interreflection, resolution=opts.visibility)
    nodes, hits = build_gloss_nodes(
        env, X, N, V, objects=obj, spheres=spheres if spheres else (), occlusion=occ,
        theta0=opts.theta0,
        ring_ratio=opts.ring_ratio, azimuths=opts.azimuths, prefilter=opts.prefilter,
        horizon_ratio=opts.horizon_ratio, subsamples=opts.subsamples, sources=opts.sources,
        dtype=dtype)
    nv = np.sum(N * V, -1)
    R = _unit(2.0 * nv[:, None] * N - V)
    irr = np.zeros((P, C))
    mir = np.zeros((P, C))
    iv = np.flatnonzero(valid)
    E, hidden = _visible_irradiance(env, X[iv], N[iv], obj[iv], spheres, occlusion=occ,
                                    rows=iv)
    irr[iv] = E
    mk = np.full(P, -1)
    mpt = np.zeros((P, 3))
    if occ is not None:
        mk[iv], mpt[iv], _ = occ.trace(iv, R[iv])
    elif spheres:
        mk[iv], mt = _ray_spheres(X[iv], R[iv], spheres, obj[iv])
        mpt[iv] = X[iv] + np.where(mk[iv] >= 0, mt, 0.0)[:, None] * R[iv]
    mvis = valid & (mk < 0)
    mir[mvis] = _env_lookup(env, R[mvis])
    Q = int(sum(u.shape[0] for u in probe_dirs))
    if Q:
        pd = np.concatenate(probe_dirs)
        pp = np.concatenate(probe_pts)
        ps = np.concatenate(probe_sph)
        pg = np.concatenate(probe_grp)
        po = np.concatenate(probe_orig)
        pn = np.concatenate(probe_nrm)
        centre_of = {int(b): X[valid & (grp == b)].mean(axis=0) for b in np.unique(pg)}

        def nearest(sample: np.ndarray, sph: np.ndarray, pts: np.ndarray) -> np.ndarray:
            """Nearest probe (by direction from the spot centre) of each hit; −1 if none."""
            return nearest_in(grp[sample], sph, pts)

        def nearest_in(g: np.ndarray, sph: np.ndarray, pts: np.ndarray) -> np.ndarray:
            """The same for hits of readings ``g``."""
            out = np.full(g.shape[0], -1)
            for b in np.unique(g):
                for si in np.unique(sph):
                    m = (g == b) & (sph == si)
                    cand = np.flatnonzero((pg == b) & (ps == si))
                    if not m.any() or cand.size == 0:
                        continue
                    u = _unit(pts[m] - centre_of[int(b)])
                    out[np.flatnonzero(m)] = cand[np.argmax(u @ pd[cand].T, axis=1)]
            return out

        # diffuse: hidden texels → probes
        dpr = np.zeros((P, Q))
        for pi, hw, hk, pts in hidden:
            pi = iv[pi]
            q = nearest(pi, hk, pts)
            ok = q >= 0
            np.add.at(dpr, (pi[ok], q[ok]), hw[ok])
        # mirror
        mprobe = np.full(P, -1)
        mh = np.flatnonzero(valid & (mk >= 0))
        if mh.size:
            mprobe[mh] = nearest(mh, mk[mh], mpt[mh])
        # gloss hits
        J, M = nodes.vh.shape[1], nodes.vh.shape[2]
        hs = hits["node"] // (J * M)
        hq = nearest(hs, hits["sphere"], hits["point"])
        keep = hq >= 0
        hn = hits["node"][keep]
        hs, hq = hs[keep], hq[keep]
        hnode = hn % (J * M)
        # keep the probes something refers to
        used = (dpr.sum(axis=0) > 0.0)
        used[mprobe[mprobe >= 0]] = True
        used[hq] = True
        new = np.cumsum(used) - 1
        Q = int(used.sum())
        dpr = dpr[:, used]
        mprobe = np.where(mprobe >= 0, new[np.maximum(mprobe, 0)], -1)
        hq = new[hq]
        pd, pp, ps, pg, po = pd[used], pp[used], ps[used], pg[used], po[used]
        pobj = occ_object[ps]
        pV = _unit(po - pp)
        pN = _facing(pn[used], pp, po)
        pocc = occ.rows_at(P + np.flatnonzero(used)) if occ is not None else None
        pnodes, _ = build_gloss_nodes(
            env, pp, pN, pV, objects=pobj, spheres=spheres, occlusion=pocc,
            theta0=opts.theta0, ring_ratio=opts.ring_ratio, azimuths=opts.azimuths,
            prefilter=opts.prefilter, horizon_ratio=opts.horizon_ratio, sources=opts.sources,
            dtype=dtype)
        pE, phidden = _visible_irradiance(env, pp, pN, pobj, spheres, occlusion=pocc,
                                          rows=np.arange(Q))
        # probe → probe: what a probe's hidden directions meet, as the nearest probe of the
        # same reading there (the second and later bounces, diffuse)
        tr = np.zeros((Q, Q))
        for qi, hw, hk, pts in phidden:
            qq = nearest_in(pg[qi], hk, pts)
            ok = qq >= 0
            np.add.at(tr, (qi[ok], qq[ok]), hw[ok])
        t_row, t_col = np.nonzero(tr)
        t_w = tr[t_row, t_col]
        pnv = np.sum(pN * pV, -1)
        pR = _unit(2.0 * pnv[:, None] * pN - pV)
        if pocc is not None:
            k, _, _ = pocc.trace(np.arange(Q), pR)
        else:
            k, _ = _ray_spheres(pp, pR, spheres, pobj)
        pM = np.zeros((Q, C))
        pM[k < 0] = _env_lookup(env, pR[k < 0])
    else:
        pobj = np.zeros(0, np.int64)
        pnodes, _ = build_gloss_nodes(env, np.zeros((0, 3)), np.zeros((0, 3)) + [0, 1, 0],
                                      np.zeros((0, 3)) + [0, 1, 0], objects=pobj,
                                      theta0=opts.theta0, ring_ratio=opts.ring_ratio,
                                      azimuths=opts.azimuths, sources=opts.sources,
                                      dtype=dtype)
        pE = pM = np.zeros((0, C))
        pg = np.zeros(0, np.int64)
        dpr = np.zeros((P, 0))
        mprobe = np.full(P, -1)
        hs = hq = np.zeros(0, np.int64)
        hnode = np.zeros(0, np.int64)
        t_row = t_col = np.zeros(0, np.int64)
        t_w = np.zeros(0)
    mprobe = np.where(mprobe >= 0, mprobe, Q)  # index Q: a zero row
    nb = int(grp.max()) + 1 if grp.size else 0
    if weights is None:
        count = np.bincount(np.maximum(grp, 0), minlength=nb)
        weights = 1.0 / np.maximum(count[np.maximum(grp, 0)], 1)
    w = np.asarray(weights, np.float64) * (valid & (nv > 0.0) & (grp >= 0))
    O = int(max([obj.max() + 1 if obj.size else 0] + [s.object + 1 for s in spheres]
                + [m.object + 1 for m in meshes]))
    fdq = np.zeros((O, Q))
    if Q:  # each probe's share of its own reading's mean, per receiving object
        same = grp[:, None] == pg[None, :]  # (P, Q)
        for o in range(O):
            fdq[o] = np.sum((w * (obj == o))[:, None] * dpr * same, axis=0)
    h_avg = w[hs] if hs.size else np.zeros(0)
    f = lambda a: jnp.asarray(a, dtype)  # noqa: E731
    return RadianceCache(
        nodes=_concat_nodes(nodes, pnodes), irradiance=f(irr), mirror=f(mir),
        spectral_basis=f(np.asarray(env.spectral_basis, np.float64)),
        probe_object=jnp.asarray(pobj, jnp.int32),
        probe_irradiance=f(pE), probe_mirror=f(pM), mirror_probe=jnp.asarray(mprobe, jnp.int32),
        diffuse_probe=f(dpr), hit_sample=jnp.asarray(hs, jnp.int32),
        hit_probe=jnp.asarray(hq, jnp.int32), hit_node=jnp.asarray(hnode, jnp.int32),
        average=FieldAverage(row=jnp.asarray(np.maximum(grp, 0), jnp.int32), weight=f(w),
                             rows=nb),
        probe_group=jnp.asarray(pg, jnp.int32), probe_diffuse=f(fdq),
        hit_average=f(h_avg), transfer_row=jnp.asarray(t_row, jnp.int32),
        transfer_col=jnp.asarray(t_col, jnp.int32), transfer_weight=f(t_w),
        probe_bounces=opts.probe_bounces)
