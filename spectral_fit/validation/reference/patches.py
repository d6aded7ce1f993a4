"""Patches of the frame's 5×5 grid labelled by what they show (one object, a real surface, or
neither), and the plane and bounding-sphere geometry that places surface patches near an object.

Used by ``scripts/table_reference.py`` and by the mesh-scene references
(:func:`~spectral_fit.validation.reference.generate.make_mesh_reference`). NumPy only.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["TABLE", "MIXED", "OTHER", "PATCH", "patch_grid", "grid_means", "label_patches",
           "plane_frame", "plane_hits", "bounding_sphere", "near_object", "object_spheres"]

#: owners of patches that show a surface, a surface and one object, anything else
TABLE, MIXED, OTHER = -1, -2, -3
#: patch side (pixels)
PATCH = 5


def patch_grid(h: int, w: int, size: int = PATCH) -> tuple[np.ndarray, np.ndarray]:
    """Top-left corners (rows, columns) of the frame grid's patches: 1, 1 + size, … so that a
    one-pixel border fits around each."""
    return np.arange(1, h - size, size), np.arange(1, w - size, size)


def grid_means(img: np.ndarray, size: int = PATCH) -> np.ndarray:
    """Means (ny, nx, C) of ``img`` (H, W, C) over the grid's patches (:func:`patch_grid`)."""
    ys, xs = patch_grid(img.shape[0], img.shape[1], size)
    blk = img[1:1 + ys.size * size, 1:1 + xs.size * size]
    return blk.reshape(ys.size, size, xs.size, size, -1).mean(axis=(1, 3))


def label_patches(obj: np.ndarray, surface: np.ndarray, size: int = PATCH
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Label the grid's patches from per-pixel object ids ``obj`` (H, W) int (−1 = none) and
    ``surface`` (H, W) bool (a surface is seen and no object covers the pixel).

    Returns ``boxes`` (P, 4) x0, y0, x1, y1 (exclusive) of every grid patch (row-major),
    ``owner`` (P,) object index, TABLE, MIXED or OTHER (module docstring) and ``obj_of`` (P,)
    the object of an object or mixed patch (−1 otherwise).
    """
    h, w = obj.shape
    ys, xs = patch_grid(h, w, size)
    boxes, owner, obj_of = [], [], []
    for y in ys:
        for x in xs:
            win = obj[y - 1:y + size + 1, x - 1:x + size + 1]
            swin = surface[y - 1:y + size + 1, x - 1:x + size + 1]
            inner = win[1:-1, 1:-1]
            sin = swin[1:-1, 1:-1]
            o, k = OTHER, -1
            ids = np.unique(win[win >= 0])
            if win.min() >= 0 and ids.size == 1:
                o = k = int(ids[0])
            elif swin.all():
                o = TABLE
            elif (ids.size == 1 and ((win >= 0) | swin).all() and sin.any()
                  and (inner >= 0).any()):
                o, k = MIXED, int(ids[0])
            boxes.append((x, y, x + size, y + size))
            owner.append(o)
            obj_of.append(k)
    return (np.asarray(boxes, np.int32).reshape(-1, 4), np.asarray(owner, np.int32),
            np.asarray(obj_of, np.int32))


def plane_frame(normal: Any) -> np.ndarray:
    """(3, 3) rows t1, t2, n: a right-handed frame (t1 × t2 = n) of the plane with ``normal``."""
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t2 = a - (a @ n) * n
    t2 /= np.linalg.norm(t2)
    return np.stack([np.cross(t2, n), t2, n])


def plane_hits(origin: np.ndarray, dirs: np.ndarray, point: Any, normal: Any,
               half_size: float) -> np.ndarray:
    """World points (..., 3) where rays ``origin + t dirs`` meet the square of side
    2·``half_size`` about ``point`` in the plane (front side, t > 0); NaN where they miss."""
    fr = plane_frame(normal)
    p0 = np.asarray(point, np.float64)
    dn = dirs @ fr[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((p0 - origin) @ fr[2]) / dn
    hit = origin + t[..., None] * dirs
    local = (hit - p0) @ fr[:2].T
    ok = (dn < 0) & (t > 0) & (np.abs(local) <= half_size).all(-1)
    return np.where(ok[..., None], hit, np.nan)


def bounding_sphere(vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre (the middle of the bounding box) and radius (its farthest vertex) of points
    (N, 3)."""
    v = np.asarray(vertices, np.float64)
    c = 0.5 * (v.min(0) + v.max(0))
    return c, float(np.linalg.norm(v - c, axis=1).max())


def near_object(points: np.ndarray, centres: np.ndarray, radii: np.ndarray, point: Any,
                normal: Any, k: float = 2.0) -> np.ndarray:
    """(P,) index of the object whose centre, projected onto the plane, lies within k bounding
    radii of each surface point (P, 3) (the closest in radii when several do), −1 for none or
    for NaN points."""
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    proj = centres - ((centres - np.asarray(point, np.float64)) @ n)[:, None] * n
    d = np.linalg.norm(points[:, None, :] - proj[None], axis=-1) / radii[None]  # (P, O)
    d = np.where(np.isfinite(d), d, np.inf)
    if d.shape[1] == 0:
        return np.full(len(points), -1, np.int32)
    return np.where(d.min(axis=1) <= k, d.argmin(axis=1), -1).astype(np.int32)


def object_spheres(scene: Any) -> tuple[np.ndarray, np.ndarray]:
    """Centres (O, 3) and bounding radii (O,) of the scene's objects, world frame."""
    cs, rs = [], []
    for o in scene.objects:
        if o.shape in ("uv_sphere", "icosphere"):
            cs.append(np.asarray(o.position, np.float64))
            rs.append(float(o.radius * o.scale))
        else:
            c, r = bounding_sphere(np.asarray(o.make_mesh(world=True).vertices))
            cs.append(c)
            rs.append(r)
    return np.asarray(cs).reshape(-1, 3), np.asarray(rs)
