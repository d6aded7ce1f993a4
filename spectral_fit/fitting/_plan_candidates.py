"""Candidate readings of a measurement plan: the reachable region (:class:`Region`, read from a
small TOML file by :func:`load_region`) and the spots the instrument can take from it
(:func:`plan_candidates`).

A candidate is one (instrument position, aim point, field angle, object): positions on
spheres of the stated distances around each object's centre (or a stated point) at the
stated elevations and azimuths, or explicit tripod positions; aim points on the object's
surface that face the position (viewing angle below ``max_view_angle_deg``) and that the
instrument sees first (the central ray of the field, cast with the fit's ray casting, hits
the object at the aim point and not another object in front of it). World coordinates
(metres, the scene config's frame; +Y up); angles in degrees.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._runtime.errors import InputError
from ..geometry import ObjectGeometry
from ..io import Scene
from ._spots import _spot_samples

__all__ = ["Region", "load_region", "plan_candidates", "FIELD_ANGLES"]

#: the field angles a planned reading may use (an SR-3A's: 2°, 1°, 0.2°)
FIELD_ANGLES = (0.2, 1.0, 2.0)
#: an aim point counts as seen when the central ray's first hit lies this close to it (m)
_AIM_HIT_TOL_M = 5e-4


@dataclasses.dataclass(frozen=True)
class Region:
    """Where the instrument can stand and what it may aim at (world coordinates, metres,
    degrees; see ``docs/planning.md``).

    Attributes:
        objects: the objects to plan readings of (None: every object of the scene).
        distances_m: instrument distances from each object's centre (or ``centre``).
        elevation_deg: (lowest, highest) elevation above the horizontal plane through the
            centre; ``elevation_steps`` values, evenly spaced, ends included.
        azimuth_deg: (first, last) azimuth about +Y, 0 towards +Z, 90 towards +X;
            ``azimuth_steps`` values, ends included.
        centre: (3,) the point the positions are placed around (None: each object's centre).
        positions: explicit tripod positions (N, 3), used instead of the sampled ones.
        aims: {object: explicit aim points (M, 3)} used instead of that object's sampled
            ones (each must lie on the object's surface, within 1 mm).
        field_angles_deg: the field angles to consider (each one of :data:`FIELD_ANGLES`).
        aims_per_object: aim points sampled evenly over each object's surface.
        max_view_angle_deg: largest angle between the surface normal at the aim point and the
            direction to the instrument.
        highlight_offsets_deg: besides the sampled aim points, from every position the aim
            points whose mirror direction lies this many degrees from a bright source of the
            environment (0: the source's highlight itself); () for none.
        highlight_sources: how many of the environment's brightest sources (at least 10°
            apart) get highlight aim points.
        path: the region file (for error messages), or None.
    """

    objects: tuple[str, ...] | None = None
    distances_m: tuple[float, ...] = (0.3,)
    elevation_deg: tuple[float, float] = (-15.0, 45.0)
    elevation_steps: int = 3
    azimuth_deg: tuple[float, float] = (-60.0, 60.0)
    azimuth_steps: int = 5
    centre: tuple[float, float, float] | None = None
    positions: tuple[tuple[float, float, float], ...] = ()
    aims: dict[str, tuple[tuple[float, float, float], ...]] = dataclasses.field(
        default_factory=dict)
    field_angles_deg: tuple[float, ...] = (1.0, 0.2)
    aims_per_object: int = 32
    max_view_angle_deg: float = 80.0
    highlight_offsets_deg: tuple[float, ...] = (0.0, 2.0, 4.0, 8.0)
    highlight_sources: int = 2
    path: str | None = None

    def error(self, field: str, message: str) -> InputError:
        return InputError(message, path=self.path, field=field)

    def checked(self) -> Region:
        """This region after checking every field (raises :class:`InputError` naming it)."""
        if not self.distances_m and not self.positions:
            raise self.error("distances_m", "give at least one distance (or positions)")
        for d in self.distances_m:
            if not (0.01 <= d <= 100.0):
                raise self.error("distances_m", f"each distance must lie in [0.01, 100] m, got {d}")
        for name in ("elevation_deg", "azimuth_deg"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
                raise self.error(name, f"must be [lowest, highest] with lowest <= highest, got "
                                 f"{[lo, hi]}")
        if not -90.0 <= self.elevation_deg[0] <= self.elevation_deg[1] <= 90.0:
            raise self.error("elevation_deg", "must lie within [-90, 90] degrees")
        for name in ("elevation_steps", "azimuth_steps"):
            if not 1 <= getattr(self, name) <= 360:
                raise self.error(name, f"must be an integer in [1, 360], got "
                                 f"{getattr(self, name)}")
        if not self.field_angles_deg:
            raise self.error("field_angles_deg", "give at least one field angle")
        for f in self.field_angles_deg:
            if not any(abs(f - a) < 1e-9 for a in FIELD_ANGLES):
                raise self.error("field_angles_deg", f"each field angle must be one of "
                                 f"{list(FIELD_ANGLES)} degrees, got {f}")
        if not 1 <= self.aims_per_object <= 100000:
            raise self.error("aims_per_object", f"must be in [1, 100000], got "
                             f"{self.aims_per_object}")
        if not 0.0 < self.max_view_angle_deg < 90.0:
            raise self.error("max_view_angle_deg", f"must lie in (0, 90), got "
                             f"{self.max_view_angle_deg}")
        for k in self.highlight_offsets_deg:
            if not 0.0 <= k <= 45.0:
                raise self.error("highlight_offsets_deg", f"each offset must lie in [0, 45] "
                                 f"degrees, got {k}")
        if not 0 <= self.highlight_sources <= 16:
            raise self.error("highlight_sources", f"must be an integer in [0, 16], got "
                             f"{self.highlight_sources}")
        return self


def _number(data: dict[str, Any], key: str, path: Path, *, integer: bool = False) -> Any:
    v = data[key]
    wrong = isinstance(v, bool) or not isinstance(v, int | float)
    if wrong or (integer and not isinstance(v, int)) or not math.isfinite(float(v)):
        raise InputError(f"must be {'an integer' if integer else 'a number'}, got {v!r}",
                         path=path, field=key)
    return int(v) if integer else float(v)


def _numbers(v: Any, key: str, path: Path, n: int | None = None) -> tuple[float, ...]:
    if isinstance(v, int | float) and not isinstance(v, bool) and n is None:
        v = [v]
    if (not isinstance(v, list) or not all(isinstance(x, int | float) and not isinstance(x, bool)
                                           for x in v) or (n is not None and len(v) != n)
            or not all(math.isfinite(float(x)) for x in v)):
        want = f"a list of {n} numbers" if n is not None else "a list of numbers"
        raise InputError(f"must be {want}, got {v!r}", path=path, field=key)
    return tuple(float(x) for x in v)


_KEYS = ("frame", "objects", "distances_m", "elevation_deg", "elevation_steps", "azimuth_deg",
         "azimuth_steps", "centre", "positions", "aims", "field_angles_deg", "aims_per_object",
         "max_view_angle_deg", "highlight_offsets_deg", "highlight_sources")


def load_region(path: str | os.PathLike[str]) -> Region:
    """Read a region file (TOML, ``docs/planning.md``); every error names the file and the
    field.

    Raises:
        InputError: unreadable file, TOML syntax, an unknown key, a value of the wrong type
            or outside its range, ``frame`` other than "world".
    """
    p = Path(path)
    if not p.is_file():
        raise InputError("region file not found", path=p)
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not a valid TOML file: {exc}", path=p) from None
    if "region" in data and isinstance(data["region"], dict) and len(data) == 1:
        data = data["region"]
    for k in data:
        if k not in _KEYS:
            raise InputError(f"unknown key; known: {list(_KEYS)}", path=p, field=k)
    frame = data.get("frame", "world")
    if frame != "world":
        raise InputError(f"only \"world\" (the scene config's coordinates) is supported, got "
                         f"{frame!r}", path=p, field="frame")
    kw: dict[str, Any] = {"path": str(p)}
    if "objects" in data:
        v = data["objects"]
        if not isinstance(v, list) or not v or not all(isinstance(x, str) for x in v):
            raise InputError(f"must be a non-empty list of object names, got {v!r}", path=p,
                             field="objects")
        kw["objects"] = tuple(v)
    for key in ("distances_m", "field_angles_deg"):
        if key in data:
            kw[key] = _numbers(data[key], key, p)
    if "highlight_offsets_deg" in data:
        v = data["highlight_offsets_deg"]
        kw["highlight_offsets_deg"] = () if v == [] else _numbers(v, "highlight_offsets_deg", p)
    for key in ("elevation_deg", "azimuth_deg"):
        if key in data:
            kw[key] = _numbers(data[key], key, p, 2)
    if "centre" in data:
        kw["centre"] = _numbers(data["centre"], "centre", p, 3)
    if "positions" in data:
        v = data["positions"]
        if not isinstance(v, list) or not v:
            raise InputError(f"must be a non-empty list of [x, y, z], got {v!r}", path=p,
                             field="positions")
        kw["positions"] = tuple(_numbers(x, f"positions[{i}]", p, 3) for i, x in enumerate(v))
    if "aims" in data:
        v = data["aims"]
        if not isinstance(v, dict) or not v:
            raise InputError(f"must be a table {{object = [[x, y, z], ...]}}, got {v!r}",
                             path=p, field="aims")
        aims = {}
        for name, pts in v.items():
            if not isinstance(pts, list) or not pts:
                raise InputError(f"must be a non-empty list of [x, y, z], got {pts!r}", path=p,
                                 field=f"aims.{name}")
            aims[name] = tuple(_numbers(x, f"aims.{name}[{i}]", p, 3) for i, x in enumerate(pts))
        kw["aims"] = aims
    for key in ("elevation_steps", "azimuth_steps", "aims_per_object", "highlight_sources"):
        if key in data:
            kw[key] = _number(data, key, p, integer=True)
    if "max_view_angle_deg" in data:
        kw["max_view_angle_deg"] = _number(data, "max_view_angle_deg", p)
    return Region(**kw).checked()


def _centroids(geom: ObjectGeometry) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) triangle centroids of the object and (T, 3) unit normals there (the mean of
    the vertex normals)."""
    v = np.asarray(geom.vertices, np.float64)
    t = np.asarray(geom.triangles)
    nrm = np.asarray(geom.normals, np.float64)[t].mean(axis=1)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    return v[t].mean(axis=1), nrm


def _surface_points(geom: ObjectGeometry, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(n', 3) points on the object's surface and their (n', 3) unit normals, spread evenly
    over the directions from its centre (a Fibonacci set of n directions, each taking the
    triangle centroid nearest in direction; duplicates dropped). Centroids lie strictly
    inside a triangle, so the central ray of a field hits it unambiguously."""
    c = np.asarray(geom.centre, np.float64)
    cen, nrm = _centroids(geom)
    d = cen - c
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    from ..geometry import fibonacci_directions

    fib = fibonacci_directions(n)[:, [0, 2, 1]]  # the lattice's pole along +Y
    pick = np.unique(np.argmax(fib @ d.T, axis=1))
    return cen[pick], nrm[pick]


def _highlight_points(centroids: tuple[np.ndarray, np.ndarray], position: np.ndarray,
                      sources: np.ndarray, offsets: Sequence[float], cos_max: float
                      ) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """(M, 3) aim points on the object (its :func:`_centroids`), seen from ``position``, whose
    mirror direction lies
    ``offsets`` degrees from each of the (S, 3) world ``sources`` directions (M <= S·len(offsets)):
    of the triangle centroids that face the position (within the view limit) and the source,
    the one whose angle between mirror direction and source is closest to each offset, kept
    when that angle is within 1.5° of it. Also, per point, ``{"source": index, "offset_deg":
    the angle}``."""
    cen, nrm = centroids
    view = position[None] - cen
    view /= np.maximum(np.linalg.norm(view, axis=1, keepdims=True), 1e-12)
    cos_v = np.einsum("ij,ij->i", view, nrm)
    mirror = 2.0 * cos_v[:, None] * nrm - view
    out, info = [], []
    for si, s in enumerate(np.asarray(sources, np.float64)):
        ok = (cos_v >= cos_max) & (nrm @ s > 0.0)
        if not ok.any():
            continue
        ang = np.degrees(np.arccos(np.clip(mirror[ok] @ s, -1.0, 1.0)))
        pts = cen[ok]
        for k in offsets:
            i = int(np.argmin(np.abs(ang - k)))
            if abs(ang[i] - k) <= 1.5:
                out.append(pts[i])
                info.append({"source": si, "offset_deg": round(float(ang[i]), 2)})
    return np.asarray(out).reshape(-1, 3), info


def _snap_to_surface(region: Region, name: str, geom: ObjectGeometry, radius: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The region's explicit aim points of object ``name`` on its surface (M, 3) and their
    normals (M, 3): each point's surface point along the ray from outside towards the
    object's centre; an aim more than 1 mm off the surface is an error naming it."""
    from ._spots import _ray_cast

    v = np.asarray(geom.vertices, np.float64)
    nr = np.asarray(geom.normals, np.float64)
    t = np.asarray(geom.triangles)
    c = np.asarray(geom.centre, np.float64)
    pts, nrms = [], []
    for i, a in enumerate(np.asarray(region.aims[name], np.float64)):
        d = a - c
        n = float(np.linalg.norm(d))
        if n < 1e-9:
            raise region.error(f"aims.{name}[{i}]", "lies at the object's centre, not on its "
                               "surface")
        origin = c + d / n * (2.0 * radius + 0.01)
        k, bary = _ray_cast(origin, (-d / n)[None], v[t])
        hit = (bary[0] @ v[t[k[0]]]) if k[0] >= 0 else None
        off = math.inf if hit is None else float(np.linalg.norm(hit - a))
        if off > 1e-3:
            raise region.error(f"aims.{name}[{i}]", f"the aim point {a.round(4).tolist()} lies "
                               f"{1e3 * off:.1f} mm off object {name!r}'s surface (aim points "
                               "must be on the object)")
        nn = bary[0] @ nr[t[k[0]]]
        pts.append(hit)
        nrms.append(nn / np.linalg.norm(nn))
    return np.asarray(pts), np.asarray(nrms)


def _positions(region: Region, centre: np.ndarray) -> np.ndarray:
    """(N, 3) instrument positions around ``centre`` (or the region's explicit ones)."""
    if region.positions:
        return np.asarray(region.positions, np.float64)
    el = np.radians(np.linspace(*region.elevation_deg, region.elevation_steps))
    az = np.radians(np.linspace(*region.azimuth_deg, region.azimuth_steps))
    if region.elevation_steps == 1:
        el = np.radians([0.5 * sum(region.elevation_deg)])
    if region.azimuth_steps == 1:
        az = np.radians([0.5 * sum(region.azimuth_deg)])
    out = []
    for d in region.distances_m:
        for e in el:
            for a in az:
                out.append(centre + d * np.array([math.cos(e) * math.sin(a), math.sin(e),
                                                  math.cos(e) * math.cos(a)]))
    return np.asarray(out)


def plan_candidates(scene: Scene, region: Region, geometries: Sequence[ObjectGeometry], *,
                    margin_m: float = 0.0, resolution: int = 6,
                    sources: np.ndarray | None = None) -> list[dict[str, Any]]:
    """The readings the instrument can take from the region.

    Args:
        geometries: the scene's objects (:func:`~spectral_fit.fitting.scene_geometry`).
        sources: (S, 3) world directions of the environment's bright sources, brightest
            first: the region's ``highlight_sources`` first of them get highlight aim points
            (``highlight_offsets_deg``) from every position; None: none.
        margin_m: an aiming error the field must stay on its object for: the field widened
            by 2 × margin_m / distance (radians) and sampled by a ``resolution``² camera must
            see only its object (so no aim error up to ``margin_m`` moves the field over the
            object's edge).

    Returns:
        dicts with ``object``, ``position`` (3,), ``aim`` (3,), ``field_angle_deg`` and
        ``distance_m`` (position to aim point), and for highlight aim points ``highlight``
        ({``source``: index into ``sources``, ``offset_deg``}), in a deterministic order.

    Raises:
        InputError (naming the region file and field): an unknown object, a position inside
            an object, no aim point of any object visible from the region.
    """
    names = [o.name for o in scene.objects]
    wanted = region.objects or tuple(names)
    for w in wanted:
        if w not in names:
            raise region.error("objects", f"unknown object {w!r}; the scene has {names}")
    for w in region.aims:
        if w not in wanted:
            raise region.error(f"aims.{w}", f"not an object of the plan {list(wanted)}")
    centres = [np.asarray(o.position, np.float64) for o in scene.objects]
    radii = [float(np.max(np.linalg.norm(np.asarray(g.vertices, np.float64) - c, axis=1)))
             for g, c in zip(geometries, centres, strict=True)]
    cos_max = math.cos(math.radians(region.max_view_angle_deg))
    raw: list[dict[str, Any]] = []
    for name in wanted:
        o = names.index(name)
        centre = centres[o] if region.centre is None else np.asarray(region.centre)
        pos = _positions(region, centre)
        for i, p in enumerate(pos):
            for c, r in zip(centres, radii, strict=True):
                if np.linalg.norm(p - c) <= r:
                    field = "positions" if region.positions else "distances_m"
                    raise region.error(field, f"instrument position {np.round(p, 4).tolist()} "
                                       f"(#{i}) lies inside an object")
        if name in region.aims:
            pts, nrm = _snap_to_surface(region, name, geometries[o], radii[o])
        else:
            pts, nrm = _surface_points(geometries[o], region.aims_per_object)
        bright = (np.zeros((0, 3)) if sources is None or not region.highlight_offsets_deg
                  else np.asarray(sources, np.float64)[:region.highlight_sources])
        tri = _centroids(geometries[o]) if len(bright) and name not in region.aims else None
        for p in pos:
            v = p[None] - pts
            dist = np.linalg.norm(v, axis=1)
            facing = np.einsum("ij,ij->i", v, nrm) / dist >= cos_max
            for a, d in zip(pts[facing], dist[facing], strict=True):
                raw.append({"object": name, "position": p, "aim": a, "distance_m": float(d)})
            if tri is not None:
                hl, what = _highlight_points(tri, p, bright, region.highlight_offsets_deg,
                                             cos_max)
                for a, w in zip(hl, what, strict=True):
                    raw.append({"object": name, "position": p, "aim": a,
                                "distance_m": float(np.linalg.norm(p - a)), "highlight": w})
    if not raw:
        raise region.error("objects", "no aim point of any object faces an instrument position "
                           "of the region (unreachable region)")
    seen = _centre_ray_hits(geometries, raw, names)
    kept = [r for r, ok in zip(raw, seen, strict=True) if ok]
    if not kept:
        raise region.error("objects", "no candidate sees its object: every aim point is hidden "
                           "from every instrument position of the region (unreachable region)")
    out = [{**r, "field_angle_deg": float(f)} for r in kept for f in region.field_angles_deg]
    on = _field_on_object(geometries, out, names, margin_m, resolution)
    out = [c for c, ok in zip(out, on, strict=True) if ok]
    if not out:
        raise region.error("field_angles_deg", f"no candidate's field (with a {1e3 * margin_m:g} "
                           "mm aiming margin) lies wholly on its object (unreachable region)")
    return out


def _field_on_object(geometries: Sequence[ObjectGeometry], cands: list[dict[str, Any]],
                     names: list[str], margin_m: float, res: int) -> np.ndarray:
    """(N,) whether each candidate's field, widened by the aiming margin, sees only its
    object (every pixel ray of a ``res``² camera; the fit's spot ray casting)."""
    pos = np.stack([c["position"] for c in cands])
    aim = np.stack([c["aim"] for c in cands])
    d = np.array([c["distance_m"] for c in cands])
    field = np.array([c["field_angle_deg"] for c in cands]) + np.degrees(2 * margin_m / d)
    S = _spot_samples(list(geometries), pos, aim, field, res)
    obj = np.array([names.index(c["object"]) for c in cands])
    return np.all(S["obj"] == obj[:, None], axis=1)


def _centre_ray_hits(geometries: Sequence[ObjectGeometry], raw: list[dict[str, Any]],
                     names: list[str]) -> np.ndarray:
    """(N,) whether the ray from each candidate's position through its aim point first hits
    its object at the aim point (the fit's spot ray casting, with a field narrow enough that
    its 2×2 rays are the central one)."""
    pos = np.stack([r["position"] for r in raw])
    aim = np.stack([r["aim"] for r in raw])
    S = _spot_samples(list(geometries), pos, aim, np.full(len(raw), 1e-4), 2)
    obj = np.array([names.index(r["object"]) for r in raw])
    on = np.all(S["obj"] == obj[:, None], axis=1)
    near = np.all(np.linalg.norm(S["pos"] - aim[:, None], axis=-1) <= _AIM_HIT_TOL_M, axis=1)
    return on & near
