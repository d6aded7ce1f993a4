"""Helpers shared by the reference-renderer tests (Mitsuba scenes built directly, small scenes,
smooth analytic environment maps, brute-force quadrature)."""

from __future__ import annotations

import math

import numpy as np

from helpers import ANCHOR_ENV, ROOT
from spectral_fit.io import parse_scene


def small_scene(*, objects: list[dict], width: int = 32, height: int = 32, fov: float = 20.0,
                rotation_y_deg: float = 0.0, bands: tuple[float, float, float] = (500, 520, 10),
                position=(0.0, 0.0, 0.0), look_at=(0.0, 0.0, -1.0)):
    """A Scene with the given objects (dicts of the config schema), 3 bands by default."""
    data = {
        "frame": {"width": width, "height": height},
        "camera": {"fov_y_deg": fov, "position": list(position), "look_at": list(look_at)},
        "environment": {"file": str(ANCHOR_ENV), "rotation_y_deg": rotation_y_deg},
        "spectral": {"start_nm": bands[0], "end_nm": bands[1], "step_nm": bands[2]},
        "objects": objects,
    }
    return parse_scene(data, path=ROOT / "configs" / "test.toml")


def sphere_obj(name: str, position, radius: float = 0.0375, **material) -> dict:
    mat = {"reflectance": 0.5, "alpha": 1.0, "beta": 0.0, "chi": 0.0}
    mat.update(material)
    return {"name": name, "shape": "uv_sphere", "radius": radius, "position": list(position),
            "material": mat}


def smooth_environment(h: int = 32, w: int = 64) -> np.ndarray:
    """A smooth positive 3-band map (h, w, 3) in the map frame: a gradient plus a soft lobe."""
    from spectral_fit.lighting import texel_directions

    d = texel_directions(h, w)
    s = np.array([0.4, 0.6, -0.7])
    s /= np.linalg.norm(s)
    lobe = np.maximum(d @ s, 0.0) ** 6
    base = np.stack([0.6 + 0.3 * d[..., 1], 0.5 + 0.2 * d[..., 0], 0.4 - 0.2 * d[..., 2]], -1)
    return (base + lobe[..., None] * np.array([3.0, 2.0, 1.0])).astype(np.float32)


def pixel_subsamples(x: np.ndarray, y: np.ndarray, k: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """(N, k²) sub-pixel positions of pixels with top-left corners (x, y)."""
    o = (np.arange(k) + 0.5) / k
    ox, oy = np.meshgrid(o, o)
    return x[:, None] + ox.ravel()[None], y[:, None] + oy.ravel()[None]


def fully_covered(scene, centre, radius, xs, ys) -> np.ndarray:
    """Pixels (top-left corners xs, ys) whose four corners all see the sphere."""
    from spectral_fit.validation.reference.render import camera_rays, sphere_hits

    ok = np.ones(np.shape(xs), bool)
    for cx, cy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        o, d = camera_rays(scene, xs + cx, ys + cy)
        ok &= np.isfinite(sphere_hits(o, d, centre, radius * 0.995))
    return ok


def gl(n: int, a: float, b: float) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (b - a) * x + 0.5 * (b + a), 0.5 * (b - a) * w


def frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tangent vectors (N, 3) × 2 orthonormal to unit normals (N, 3)."""
    a = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t = np.cross(n, a)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return t, np.cross(n, t)


def single_bounce_quadrature(env_lookup, normals, views, *, alpha, s, beta, mu, n,
                             distribution, geometry, n_theta: int = 48, n_phi: int = 96
                             ) -> np.ndarray:
    """Brute-force ∫ L(ω) f(V, ω) cosθ dω (N, 3) for unit normals/views (N, 3): the diffuse part
    in (cosθ, φ) about N, the gloss part in half-vector angles about N (dω = 4 V·H dω_h).
    ``env_lookup``: (M, 3) world directions -> (M, 3) radiance."""
    from spectral_fit.lighting import fresnel_dielectric, microfacet_d, microfacet_g

    N = normals.shape[0]
    t, b = frame(normals)
    out = np.zeros((N, 3))
    # diffuse: ∫ L cosθ dω = ∫∫ L cosθ d(cosθ) dφ
    c, wc = gl(n_theta, 0.0, 1.0)
    p, wp = gl(n_phi, 0.0, 2 * math.pi)
    C, P = np.meshgrid(c, p, indexing="ij")
    W = np.outer(wc, wp)
    st = np.sqrt(1 - C**2)
    dirs = (st * np.cos(P))[None, ..., None] * t[:, None, None] + (st * np.sin(P))[
        None, ..., None] * b[:, None, None] + C[None, ..., None] * normals[:, None, None]
    L = env_lookup(dirs.reshape(-1, 3)).reshape(N, n_theta, n_phi, 3)
    out += alpha * np.asarray(s)[None] / math.pi * np.einsum("ijkc,jk->ic", L, W * C)
    # gloss in half-vector space
    tmax = min(math.pi / 2, 7 * mu) if distribution == "gaussian" else math.pi / 2 * 0.999
    th, wt = gl(n_theta * 2, 0.0, tmax)
    TH, P2 = np.meshgrid(th, p, indexing="ij")
    W2 = np.outer(wt, wp) * np.sin(TH)
    h = (np.sin(TH) * np.cos(P2))[None, ..., None] * t[:, None, None] + (
        np.sin(TH) * np.sin(P2))[None, ..., None] * b[:, None, None] + np.cos(TH)[
        None, ..., None] * normals[:, None, None]
    v = views[:, None, None, :]
    vh = np.sum(v * h, -1)
    wi = 2 * vh[..., None] * h - v
    nl = np.sum(wi * normals[:, None, None], -1)
    nv = np.sum(views * normals, -1)[:, None, None]
    nh = np.cos(TH)[None]
    F = np.asarray(fresnel_dielectric(vh, n), np.float64)
    D = np.asarray(microfacet_d(np.broadcast_to(nh, vh.shape), mu, distribution), np.float64)
    G = np.asarray(microfacet_g(np.broadcast_to(nh, vh.shape), np.broadcast_to(nv, vh.shape),
                                nl, vh, mu, geometry), np.float64)
    ok = (nl > 0) & (vh > 0)
    integrand = np.where(ok, F * D * G / (4 * nv) * 4 * vh, 0.0)
    L2 = env_lookup(wi.reshape(-1, 3)).reshape(*wi.shape[:3], 3)
    out += beta * np.einsum("ijkc,ijk,jk->ic", L2, integrand, W2)
    return out
