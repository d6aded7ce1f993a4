"""What the scene hides from the radiance caches' points, for objects of any shape (host side,
NumPy, outside ``jit``; no gradient: visibility is a constant of the geometry).

Two kinds of occluder:

- :class:`~spectral_fit.fitting.Sphere` (uv_sphere and icosphere objects): rays are cast
  analytically; a sphere never hides anything from its own points (convex).
- :class:`MeshOccluder` (mesh objects): the frame's self-visibility test
  (:func:`~spectral_fit.geometry.point_visibility`: the mesh rasterised orthographically along
  each of K = R² octahedral directions, each point tested against the front-most surface over
  it) applied to the caches' points themselves, in the world. A non-convex mesh hides parts
  of the sky from its own points (a cup's inside); every mesh hides what lies behind it from
  the other objects' points.

:class:`PointOcclusion` holds, for a fixed set of P points, the nearest occluder along each of
the K directions with its hit point and normal; any direction is answered from its four
bilinear taps in the octahedral grid: a fraction hidden (for the environment's texels in the
irradiance sum) or a yes/no (a gloss node, the mirror direction, a bright source: hidden when
at least half the taps' weight is). The hit is the hidden tap's of largest weight. Resolution
is the grid's: ~0.15 rad at R = 24, the frame's default.

Shapes: P points, K directions, (..., 3) world vectors; distances in metres.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from ._cache_geometry import _ray_spheres, _unit
from ._radiance_cache import Sphere

__all__ = ["MeshOccluder", "PointOcclusion"]

#: directions traced per step (bounds the temporary arrays)
_CHUNK = 1 << 17


@dataclasses.dataclass(frozen=True)
class MeshOccluder:
    """An object given by its triangle mesh in the world.

    Attributes:
        object: the object's index.
        vertices: (V, 3) world positions (m).
        triangles: (T, 3) int vertex indices.
        normals: (V, 3) unit world vertex normals.
        convex: the mesh hides nothing from its own points (its self-test is skipped).
    """

    object: int
    vertices: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray
    convex: bool


class PointOcclusion:
    """The scene's occluders as seen from P fixed points (see the module docstring).

    Args:
        points, normals: (P, 3) world positions and unit surface normals.
        objects: (P,) object of each point (−1: none; such points are tested like others).
        spheres: analytic occluders.
        meshes: mesh occluders.
        own_only: meshes hide only their own object's points (the direct light of mode
            "none": a neighbour neither hides nor lights).
        resolution: R of the octahedral grid of the mesh tests.
        raster_size: side of each direction's shadow map (pixels over a mesh's bounding
            sphere).
    """

    def __init__(self, points: np.ndarray, normals: np.ndarray, objects: np.ndarray, *,
                 spheres: Sequence[Sphere] = (), meshes: Sequence[MeshOccluder] = (),
                 own_only: bool = False, resolution: int = 24, raster_size: int = 192):
        from ..geometry import point_visibility

        self.points = np.asarray(points, np.float64).reshape(-1, 3)
        self.objects = np.asarray(objects, np.int64).reshape(-1)
        self.spheres = list(spheres)
        self.meshes = list(meshes)
        self.resolution = int(resolution)
        self._map: np.ndarray | None = None
        P = self.points.shape[0]
        ns = len(self.spheres)
        self.occluder_object = np.array([s.object for s in self.spheres]
                                        + [m.object for m in self.meshes], np.int64)
        K = self.resolution ** 2
        self.occ = np.full((P, K), -1, np.int32)
        self.t = np.full((P, K), np.inf, np.float32)
        self.hit = np.zeros((P, K, 3), np.float32)
        self.hit_normal = np.zeros((P, K, 3), np.float32)
        if not self.meshes or P == 0:
            return
        N = _unit(np.asarray(normals, np.float64).reshape(-1, 3))
        for j, m in enumerate(self.meshes):
            test = (self.objects == m.object) if own_only else np.ones(P, bool)
            if m.convex:
                test &= self.objects != m.object
            rows = np.flatnonzero(test)
            if rows.size == 0:
                continue
            sv = point_visibility(m.vertices, m.triangles, self.points[rows], N[rows],
                                  resolution=self.resolution, raster_size=raster_size)
            r_, k_ = np.nonzero(np.asarray(sv.hidden))
            tri = np.asarray(m.triangles)[np.asarray(sv.hit_triangle)[r_, k_]]  # (n, 3)
            bary = np.asarray(sv.hit_bary, np.float64)[r_, k_][..., None]  # (n, 3, 1)
            pt = np.sum(bary * np.asarray(m.vertices, np.float64)[tri], axis=1)
            nr = _unit(np.sum(bary * np.asarray(m.normals, np.float64)[tri], axis=1))
            rr = rows[r_]
            t = np.linalg.norm(pt - self.points[rr], axis=-1)
            closer = t < self.t[rr, k_]
            r_, k_, rr, pt, nr, t = (a[closer] for a in (r_, k_, rr, pt, nr, t))
            self.occ[rr, k_] = ns + j
            self.t[rr, k_] = t
            self.hit[rr, k_] = pt
            self.hit_normal[rr, k_] = nr

    @property
    def has_meshes(self) -> bool:
        return bool(self.meshes)

    def rows_at(self, rows: np.ndarray) -> PointOcclusion:
        """A view of these tables whose point i is this one's point ``rows[i]``."""
        view = copy.copy(self)
        rows = np.asarray(rows, np.int64)
        view._map = rows if self._map is None else self._map[rows]
        return view

    def _mapped(self, rows: Any) -> np.ndarray:
        rows = np.asarray(rows)
        return rows if self._map is None else self._map[rows]

    def taps(self, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The octahedral grid's bilinear taps (..., 4) and weights of directions (..., 3)."""
        from ..geometry import octahedral_taps

        idx, w = octahedral_taps(np.asarray(dirs, np.float64), self.resolution)
        return np.asarray(idx), np.asarray(w)

    def _mesh_taps(self, rows: np.ndarray, idx: np.ndarray, w: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Hidden fraction, and the dominant hidden tap's occluder (−1 if none), hit point and
        normal (..., 3), of the directions with taps ``idx``, ``w`` (..., 4) from points
        ``rows`` (broadcast against ``idx[..., 0]``)."""
        r = np.asarray(rows)[..., None]
        occ = self.occ[r, idx]  # (..., 4)
        hid = occ >= 0
        frac = np.sum(np.where(hid, w, 0.0), axis=-1)
        best = np.argmax(np.where(hid, w, -1.0), axis=-1)[..., None]
        k = np.take_along_axis(np.broadcast_to(idx, occ.shape), best, axis=-1)[..., 0]
        rr = np.asarray(rows)
        o = np.where(frac > 0.0, self.occ[rr, k], -1)
        return (frac, o, self.hit[rr, k].astype(np.float64),
                self.hit_normal[rr, k].astype(np.float64))

    def trace(self, rows: Any, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The occluder (index into spheres then meshes; −1: none) along directions ``dirs``
        (..., 3) from points ``rows`` (broadcast against ``dirs[..., 0]``), its hit point and
        unit normal (..., 3). A mesh counts when at least half the taps' weight is hidden."""
        shape = dirs.shape[:-1]
        rows = self._mapped(np.broadcast_to(np.asarray(rows), shape).reshape(-1))
        flat = np.asarray(dirs, np.float64).reshape(-1, 3)
        occ = np.full(rows.shape, -1, np.int64)
        pt = np.zeros(flat.shape)
        nr = np.zeros(flat.shape)
        for a in range(0, rows.size, _CHUNK):
            sl = slice(a, a + _CHUNK)
            occ[sl], pt[sl], nr[sl] = self._trace(rows[sl], flat[sl])
        return occ.reshape(shape), pt.reshape(dirs.shape), nr.reshape(dirs.shape)

    def _trace(self, rows: np.ndarray, dirs: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        X = self.points[rows]
        occ = np.full(dirs.shape[:-1], -1, np.int64)
        t = np.full(dirs.shape[:-1], np.inf)
        pt = np.zeros(dirs.shape)
        nr = np.zeros(dirs.shape)
        if self.spheres:
            k, ts = _ray_spheres(X, dirs, self.spheres, self.objects[rows])
            hit = k >= 0
            occ = np.where(hit, k, -1)
            t = np.where(hit, ts, np.inf)
            p = X + np.where(hit, ts, 0.0)[..., None] * dirs
            c = np.stack([s.centre for s in self.spheres])[np.maximum(k, 0)]
            pt = np.where(hit[..., None], p, 0.0)
            nr = np.where(hit[..., None], _unit(p - c), 0.0)
        if self.meshes:
            frac, o, p, n = self._mesh_taps(rows, *self.taps(dirs))
            tm = np.linalg.norm(p - X, axis=-1)
            use = (frac >= 0.5) & (o >= 0) & (tm < t)
            occ = np.where(use, o, occ)
            pt = np.where(use[..., None], p, pt)
            nr = np.where(use[..., None], n, nr)
        return occ, pt, nr

    def hidden_share(self, rows: np.ndarray, idx: np.ndarray, w: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Fraction of each direction (taps ``idx``, ``w`` (..., 4) from :meth:`taps`) from
        points ``rows`` (broadcast against ``idx[..., 0]``) that the MESHES hide (bilinear in
        the grid), the dominant occluder (−1: none) and its hit point (..., 3)."""
        frac, o, p, _ = self._mesh_taps(self._mapped(rows), idx, w)
        return frac, o, p
