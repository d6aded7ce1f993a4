"""Shared helpers of the interreflection tests (small scenes, analytic environments) and the
float64 gradient check, run in its own interpreter (``python tests/_interreflection_util.py``)
so that ``jax_enable_x64`` never leaks into other tests."""

from __future__ import annotations

import json
import math
import sys

import numpy as np

R = 0.0375
CENTRES = ((-0.045, 0.0, -0.275), (0.045, 0.0, -0.275))


def sphere_objects(stacks: int = 32, centres=CENTRES, radius: float = R):
    import jax.numpy as jnp

    from spectral_fit.gbuffer import ObjectGeometry
    from spectral_fit.mesh import translate, uv_sphere

    out = []
    for c in centres:
        m = uv_sphere(radius, stacks, stacks).transformed(translate(c))
        out.append(ObjectGeometry(jnp.asarray(m.vertices), jnp.asarray(m.normals),
                                  jnp.asarray(m.triangles), jnp.asarray(c, jnp.float32)))
    return out


def linear_env_texels(a, b, height: int = 16, width: int = 32) -> np.ndarray:
    """Map (H, W, C) of L(d) = a + b·d_y per channel (map frame = world)."""
    from spectral_fit.environment import texel_directions

    d = texel_directions(height, width)
    return np.asarray(a)[None, None, :] + d[..., 1:2] * np.asarray(b)[None, None, :]


def make_env(texels, dtype=None):
    import jax.numpy as jnp

    from spectral_fit.environment import EnvironmentMap

    return EnvironmentMap.from_array(texels, compress_tol=0.0, dtype=dtype or jnp.float32)


def surface_points(centre, directions, radius: float = R):
    """Points on a sphere at unit ``directions`` (K, 3) from ``centre``: (positions, normals)."""
    d = np.asarray(directions, np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(centre) + radius * d, d


def gbuffer(positions, normals, views, objects, capacity: int | None = None):
    """A GBuffer of the given samples, padded with empty slots up to ``capacity``."""
    import jax.numpy as jnp

    from spectral_fit.gbuffer import GBuffer

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
    from spectral_fit.reflectance import make_material

    return make_material(alpha=alpha, beta=beta, chi=chi, mu=mu, n=n, gamma=gamma,
                         reflectance=np.asarray(reflectance, np.float64), dtype=dtype)


# --------------------------------------------------------------------------------------------
# float64 gradient check (own process)


def gradient_check() -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from spectral_fit.interreflection import interreflection_from, prepare_interreflection

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


if __name__ == "__main__":
    if sys.argv[1:] == ["gradients"]:
        print(json.dumps(gradient_check()))
    else:  # pragma: no cover
        raise SystemExit(f"usage: {sys.argv[0]} gradients")

_ = math
