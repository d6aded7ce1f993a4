"""Host-side (NumPy, float64) geometry of the radiance caches: unit vectors, tangent frames
along the view, ray casts against spheres and directions spread over a spherical cap.

Shapes: vectors (..., 3) in world space; distances in metres.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ._radiance_cache import Sphere


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def _view_frames(N: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tangent T along V's projection on the tangent plane (any tangent if V ∥ N), B = N × T."""
    p = V - np.sum(N * V, -1, keepdims=True) * N
    alt = np.where(np.abs(N[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]),
                   np.array([[0.0, 1.0, 0.0]]))
    alt = alt - np.sum(N * alt, -1, keepdims=True) * N
    ok = np.sum(p * p, -1, keepdims=True) > 1e-18
    T = _unit(np.where(ok, p, alt))
    return T, np.cross(N, T)


def _ray_spheres(origins: np.ndarray, dirs: np.ndarray, spheres: Sequence[Sphere],
                 skip: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest sphere hit of rays (..., 3): (…,) index into ``spheres`` or −1 and distance t.
    Spheres whose object equals ``skip`` (broadcast against the rays) are ignored."""
    best = np.full(dirs.shape[:-1], np.inf)
    idx = np.full(dirs.shape[:-1], -1, np.int64)
    for i, s in enumerate(spheres):
        oc = origins - s.centre
        b = np.sum(oc * dirs, -1)
        c = np.sum(oc * oc, -1) - s.radius ** 2
        disc = b * b - c
        t = -b - np.sqrt(np.maximum(disc, 0.0))
        hit = (disc > 0.0) & (t > 1e-7) & (skip != s.object)
        closer = hit & (t < best)
        best = np.where(closer, t, best)
        idx = np.where(closer, i, idx)
    return idx, best


def _fibonacci_cap(axis: np.ndarray, half: float, n: int) -> np.ndarray:
    """n unit directions spread evenly over the spherical cap of half-angle ``half``."""
    i = np.arange(n) + 0.5
    c = 1.0 - (1.0 - math.cos(half)) * i / n
    s = np.sqrt(np.maximum(1.0 - c * c, 0.0))
    ang = i * math.pi * (3.0 - math.sqrt(5.0))
    t, b = _view_frames(axis[None], axis[None] * 0 + np.array([[0.3, 0.5, 0.81]]))
    t, b = t[0], b[0]
    return _unit(c[:, None] * axis + s[:, None] * (np.cos(ang)[:, None] * t
                                                    + np.sin(ang)[:, None] * b))
