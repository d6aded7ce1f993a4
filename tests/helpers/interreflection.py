"""Shared helpers of the interreflection tests (small scenes, analytic environments) and the
float64 gradient check, run in its own interpreter (``python -m helpers.interreflection
gradients``, tests/ on the import path) so that ``jax_enable_x64`` never leaks into other
tests."""

from __future__ import annotations

import json
import math
import sys

import numpy as np

R = 0.0375
CENTRES = ((-0.045, 0.0, -0.275), (0.045, 0.0, -0.275))


def sphere_objects(stacks: int = 32, centres=CENTRES, radius: float = R):
    import jax.numpy as jnp

    from spectral_fit.geometry import ObjectGeometry
    from spectral_fit.io import translate, uv_sphere

    out = []
    for c in centres:
        m = uv_sphere(radius, stacks, stacks).transformed(translate(c))
        out.append(ObjectGeometry(jnp.asarray(m.vertices), jnp.asarray(m.normals),
                                  jnp.asarray(m.triangles), jnp.asarray(c, jnp.float32)))
    return out


def linear_env_texels(a, b, height: int = 16, width: int = 32) -> np.ndarray:
    """Map (H, W, C) of L(d) = a + b·d_y per channel (map frame = world)."""
    from spectral_fit.lighting import texel_directions

    d = texel_directions(height, width)
    return np.asarray(a)[None, None, :] + d[..., 1:2] * np.asarray(b)[None, None, :]


def make_env(texels, dtype=None):
    import jax.numpy as jnp

    from spectral_fit.lighting import EnvironmentMap

    return EnvironmentMap.from_array(texels, compress_tol=0.0, dtype=dtype or jnp.float32)


def surface_points(centre, directions, radius: float = R):
    """Points on a sphere at unit ``directions`` (K, 3) from ``centre``: (positions, normals)."""
    d = np.asarray(directions, np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(centre) + radius * d, d


def gbuffer(positions, normals, views, objects, capacity: int | None = None):
    """A GBuffer of the given samples, padded with empty slots up to ``capacity``."""
    import jax.numpy as jnp

    from spectral_fit.geometry import GBuffer

    k = len(objects)
    cap = capacity or k
    pos = np.zeros((cap, 3))
    nrm = np.tile([0.0, 1.0, 0.0], (cap, 1))
    vw = nrm.copy()
    obj = np.full(cap, -1)
    pos[:k], nrm[:k], vw[:k], obj[:k] = positions, normals, views, objects
    f = jnp.float32
    return GBuffer(position=jnp.asarray(pos, f), normal=jnp.asarray(nrm, f),
                   view=jnp.asarray(vw, f), object=jnp.asarray(obj, jnp.int32),
                   pixel=jnp.full((cap,), -1, jnp.int32))


def material(*, alpha=1.0, beta=0.0, chi=0.0, mu=0.1, n=1.5, gamma=0.0, reflectance=(1, 1, 1),
             dtype=None):
    from spectral_fit.lighting import make_material

    return make_material(alpha=alpha, beta=beta, chi=chi, mu=mu, n=n, gamma=gamma,
                         reflectance=np.asarray(reflectance, np.float64), dtype=dtype)


# --------------------------------------------------------------------------------------------
# float64 gradient check (own process)


def gradient_check() -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from spectral_fit.rendering.interreflection import interreflection_from, prepare_interreflection

    f64 = jnp.float64
    objs = sphere_objects(stacks=10)
    env = make_env(linear_env_texels([1.0, 0.8, 0.6], [0.5, 0.3, -0.2], 8, 16), dtype=f64)
    dirs = np.array([[1.0, 0.0, 0.0], [1.0, 0.4, 0.1], [0.8, -0.3, 0.4], [1.0, 0.1, -0.5]])
    p0, n0 = surface_points(CENTRES[0], dirs)
    p1, n1 = surface_points(CENTRES[1], dirs * [-1, 1, 1])
    pos = np.concatenate([p0, p1])
    nrm = np.concatenate([n0, n1])
    views = -pos / np.linalg.norm(pos, axis=1, keepdims=True)
    views = np.where((np.sum(views * nrm, 1) > 0.2)[:, None], views, nrm)
    rec = gbuffer(pos, nrm, views, [0] * 4 + [1] * 4)
    mats = [material(alpha=0.9, beta=0.8, chi=0.3, mu=0.15, n=1.45, gamma=0.7,
                     reflectance=(0.8, 0.6, 0.2), dtype=f64),
            material(alpha=0.7, beta=1.1, chi=0.2, mu=0.12, n=1.55, gamma=0.4,
                     reflectance=(0.3, 0.5, 0.9), dtype=f64)]
    weights = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (8, 3)), f64)
    results = {}
    for mode, bounces in (("gather", 2), ("paper", 1)):
        geom = prepare_interreflection(objs, mode=mode, texture_size=16, gather_size=4)

        def loss(ms, geom=geom, mode=mode, bounces=bounces):
            return jnp.sum(weights * interreflection_from(geom, ms, env, rec, bounces=bounces))

        lf = jax.jit(loss)
        grad = jax.jit(jax.grad(loss))(mats)
        rows = []
        for o in range(2):
            for name in ("alpha", "beta", "chi", "mu", "n", "gamma", "reflectance"):
                leaf = getattr(mats[o], name)
                comps = [None] if leaf.ndim == 0 else list(range(leaf.shape[0]))
                for c in comps:
                    # relative step 1e-3: the O(h²) error is ~1e-7 here, while much smaller
                    # steps meet the float32 rounding of fresnel_dielectric's cos θ (the
                    # G-buffer is float32)
                    x0 = float(leaf if c is None else leaf[c])
                    eps = 1e-3 * max(abs(x0), 0.1)

                    def bump(delta, o=o, name=name, c=c, leaf=leaf, lf=lf):
                        v = leaf + delta if c is None else leaf.at[c].add(delta)
                        ms = list(mats)
                        ms[o] = type(ms[o])(**{**{k: getattr(ms[o], k) for k in (
                            "alpha", "beta", "chi", "mu", "n", "gamma", "reflectance")},
                            name: v}, distribution=ms[o].distribution,
                            geometry=ms[o].geometry)
                        return float(lf(ms))

                    fd = (bump(eps) - bump(-eps)) / (2 * eps)
                    g = getattr(grad[o], name)
                    g = float(g if c is None else g[c])
                    rows.append([o, name, c, g, fd])
        results[f"{mode}_b{bounces}"] = rows
    return results




# --------------------------------------------------------------------------------------------
# brute-force single bounce (float64 quadrature over the receiver's hemisphere, rays cast
# against the neighbour's triangle mesh)


def _frame(a):
    t = np.cross(a, [0.0, 1.0, 0.0] if abs(a[1]) < 0.9 else [1.0, 0.0, 0.0])
    t /= np.linalg.norm(t)
    return t, np.cross(a, t)


def ray_mesh(origin, dirs, vertices, normals, triangles, chunk: int = 256):
    """Nearest hits of rays (origin (3,), dirs (K, 3)) on a triangle mesh (Möller–Trumbore,
    float64): (hit (K,) bool, distance (K,), interpolated unit normal (K, 3))."""
    v = np.asarray(vertices, np.float64)
    nv = np.asarray(normals, np.float64)
    tri = np.asarray(triangles)
    p0, p1, p2 = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
    e1, e2 = p1 - p0, p2 - p0
    s = origin - p0  # (T, 3)
    q = np.cross(s, e1)  # (T, 3)
    hit = np.zeros(len(dirs), bool)
    dist = np.full(len(dirs), np.inf)
    nrm = np.zeros((len(dirs), 3))
    for a in range(0, len(dirs), chunk):
        d = dirs[a:a + chunk]
        pv = np.cross(d[:, None, :], e2[None])  # (K, T, 3)
        det = np.sum(pv * e1[None], -1)
        inv = 1.0 / np.where(np.abs(det) > 1e-18, det, 1e-18)
        u = np.sum(pv * s[None], -1) * inv
        w = (d @ q.T) * inv
        t = np.sum(e2 * q, -1)[None] * inv
        ok = (np.abs(det) > 1e-18) & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 1e-9)
        t = np.where(ok, t, np.inf)
        k = np.argmin(t, axis=1)
        tk = t[np.arange(len(d)), k]
        h = np.isfinite(tk)
        uk, wk = u[np.arange(len(d)), k], w[np.arange(len(d)), k]
        n = ((1 - uk - wk)[:, None] * nv[tri[k, 0]] + uk[:, None] * nv[tri[k, 1]]
             + wk[:, None] * nv[tri[k, 2]])
        hit[a:a + chunk], dist[a:a + chunk] = h, tk
        nrm[a:a + chunk] = n / np.linalg.norm(n, axis=1, keepdims=True)
    return hit, dist, nrm


_PAD = 4096
_BF_EVAL = []


def _bf_eval(mat_j, receiver, env, dirs, normals, n, v):
    """Jitted (once) neighbour radiance towards the receiver, environment along the rays and the
    receiver's gloss BRDF, for padded ray lists."""
    if not _BF_EVAL:
        import jax

        from spectral_fit.lighting import gloss_brdf, lookup, shade

        def f(mj, mi, e, d, ny, nn, vv):
            lj = jax.vmap(lambda a, b: shade(mj, e, a, b))(ny, -d)
            le = jax.vmap(lambda a: lookup(e, a))(d)
            g = jax.vmap(lambda a: gloss_brdf(mi, nn, vv, a))(d)
            return lj, le, g

        _BF_EVAL.append(jax.jit(f))
    return _BF_EVAL[0](mat_j, receiver, env, dirs, normals, n, v)


def brute_force_single_bounce(x, n, v, receiver, neighbour, centre, radius, env, *,
                              cone=(40, 64), lobe=(40, 48), lobe_angle: float = 0.8):
    """Radiance (C,) that ONE bounce off the neighbour adds at receiver point x (normal n,
    view v), float64 quadrature: Σ f_x(ω) [L_j(y(ω) → x) − L_env(ω)] cosθ dω over the rays
    that hit the neighbour's mesh, L_j = ``shade`` of the neighbour at the hit (interpolated
    normal, view towards x). The diffuse lobe is integrated over a grid uniform in solid angle
    on the cone of the neighbour's bounding sphere, the gloss lobe over a polar grid around
    the mirror direction. ``neighbour``: (ObjectGeometry, Material); ``receiver``: Material.
    Returns (diffuse part, gloss part), each (C,)."""
    import jax.numpy as jnp

    geo, mat_j = neighbour
    x, n, v = (np.asarray(a, np.float64) for a in (x, n, v))
    c = np.asarray(centre, np.float64)
    dc = np.linalg.norm(c - x)
    a = (c - x) / dc
    cmax = math.sqrt(max(1.0 - (1.02 * radius / dc) ** 2, 0.0))
    na, nphi = cone
    u = cmax + (1 - cmax) * (np.arange(na) + 0.5) / na
    ph = 2 * np.pi * (np.arange(nphi) + 0.5) / nphi
    t1, t2 = _frame(a)
    U, PH = np.meshgrid(u, ph, indexing="ij")
    sn = np.sqrt(1 - U ** 2)
    w_cone = (U[..., None] * a + sn[..., None] * (np.cos(PH)[..., None] * t1
                                                 + np.sin(PH)[..., None] * t2)).reshape(-1, 3)
    dw_cone = np.full(len(w_cone), (1 - cmax) * 2 * np.pi / (na * nphi))
    r = 2 * (n @ v) * n - v
    q1, q2 = _frame(r)
    npsi, nph2 = lobe
    psi = lobe_angle * (np.arange(npsi) + 0.5) / npsi
    ph2 = 2 * np.pi * (np.arange(nph2) + 0.5) / nph2
    PS, PH2 = np.meshgrid(psi, ph2, indexing="ij")
    w_lobe = (np.cos(PS)[..., None] * r + np.sin(PS)[..., None] * (
        np.cos(PH2)[..., None] * q1 + np.sin(PH2)[..., None] * q2)).reshape(-1, 3)
    dw_lobe = (np.sin(PS) * (lobe_angle / npsi) * (2 * np.pi / nph2)).reshape(-1)
    rays, weights, parts = [], [], []
    for dirs, dw, part in ((w_cone, dw_cone, 0), (w_lobe, dw_lobe, 1)):
        cos = dirs @ n
        keep = cos > 0
        hit, _, ny = ray_mesh(x, dirs[keep], geo.vertices, geo.normals, geo.triangles)
        rays.append(np.concatenate([dirs[keep][hit], ny[hit]], 1))
        weights.append(dw[keep][hit])
        parts.append(np.full(int(hit.sum()), part))
    rays, dw, part = np.concatenate(rays), np.concatenate(weights), np.concatenate(parts)
    k = len(rays)
    size = max(_PAD, -(-k // _PAD) * _PAD)
    pad = np.tile([[0.0, 0.0, 1.0, 0.0, 0.0, 1.0]], (size - k, 1))
    arr = jnp.asarray(np.concatenate([rays, pad]), jnp.float32)
    # _PAD rays per call: one compilation for every call, and bounded memory (the vmapped
    # shading of 4,096 rays holds ~2.6 GB of intermediates; all of the fine test's rays in
    # one call made its process peak at 15.8 GB, in calls of _PAD at 3.6 GB)
    nj, vj = jnp.asarray(n, jnp.float32), jnp.asarray(v, jnp.float32)
    evals = [_bf_eval(mat_j, receiver, env, arr[a:a + _PAD, :3], arr[a:a + _PAD, 3:], nj, vj)
             for a in range(0, size, _PAD)]
    lj, le, g = (np.concatenate([np.asarray(e_[i], np.float64) for e_ in evals])[:k]
                 for i in range(3))
    dirs = rays[:, :3]
    cos = dirs @ n
    diffuse = (float(receiver.alpha) / math.pi) * np.asarray(receiver.reflectance,
                                                               np.float64)[None] * cos[:, None]
    gloss = (float(receiver.beta) * g * cos)[:, None]
    out = []
    for p_, f in ((0, diffuse), (1, gloss)):
        sel = part == p_
        out.append((f[sel] * (lj[sel] - le[sel]) * dw[sel, None]).sum(0))
    return out[0], out[1]


if __name__ == "__main__":
    if sys.argv[1:] == ["gradients"]:
        print(json.dumps(gradient_check()))
    else:  # pragma: no cover
        raise SystemExit(f"usage: {sys.argv[0]} gradients")

_ = math
