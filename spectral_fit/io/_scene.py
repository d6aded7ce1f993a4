"""Scene configuration files (TOML) → validated :class:`Scene` descriptions.

A scene config says what to render: frame size, camera, environment map, display, spectral mode,
objects with their materials, and the interreflection mode. This module only reads and checks
the file (data layer); turning a :class:`Scene` into meshes, cameras and JAX pytrees is the
renderer's job. Relative paths in a config are relative to the config file's folder.

Every error is an :class:`~spectral_fit._runtime.errors.InputError` naming the file and the key,
e.g.
``configs/two_spheres.toml: objects[1].material.mu: must be > 0, got -0.1``.

Schema (all lengths in metres, angles in degrees; defaults in brackets)::

    [frame]            width [720], height [480]
    [camera]           fov_y_deg [90], near [0.01], far [1000],
                       position [[0,0,0]], look_at [[0,0,-1]], up [[0,1,0]]
                       intrinsics = {fx, fy, cx, cy}  (optional; replaces fov_y_deg, pixels)
                       distortion = [k1, k2, p1, p2, k3]  (optional, OpenCV model; 4, 5
                         or 8 numbers; the renderer draws through it: spectral_fit.geometry)
                       blur_px [0], noise [0]  (live compositing: the video camera's blur,
                       Gaussian σ in pixels, and noise, σ in 8-bit levels, given to the CG)
    [environment]      file (spectral or RGB OpenEXR; required), scale [1.0],
                       rotation_y_deg [0]  (180 for maps with −Z at the image centre),
                       upsampling ["mallett2019"]  (RGB maps only),
                       compress_tol [1e-4] (relative error per texel of the map's principal
                       spectra, 0 = keep every band; 1e-3 makes frames under a noisy measured
                       map faster at a small spectral cost: docs/lighting.md)
    [display]          colourspace ["sRGB"] or characterisation = "patches.csv",
                       exposure_luminance ["auto" or cd/m²], scene_white_xy (optional [x, y])
    [spectral]         start_nm [380], end_nm [780], step_nm [5],
                       mode ["bands" | "basis"], k [8]
    [interreflection]  mode ["gather" | "paper" | "none"], bounces [1], texture_size [256],
                       gather_size [16] (samples per side of each sender in gather mode, a
                       power of two: 32 for faces a few mm apart, at ~4x the transfer's cost;
                       docs/interreflection.md),
                       tail ["none" | "geometric"] (a concave object's light on itself after
                       ``bounces`` steps: "geometric" adds the rest of the series from the
                       ratio of its last two steps, for bounces >= 3; docs/any_shape.md)
    [[objects]]        name (unique), shape ["uv_sphere" | "icosphere" | "mesh"],
                       radius, stacks [100], slices [100], subdivisions [5], mesh (file),
                       position [[0,0,0]], rotation_deg [[0,0,0]] (XYZ Euler), scale [1.0],
                       marker (optional int id), marker_offset [[0,0,0]]
      [objects.material] reflectance (number, CSV file, or "colourchecker:<set>/<patch>"),
                       alpha [1], beta [1], chi [0], mu [0.1], n [1.5], gamma [1],
                       distribution ["gaussian" | "beckmann"], geometry ["vcavity" | "smith"]
                       (a mesh with parts: the material of the faces no part takes)
      part_property    (mesh objects with parts, PLY only) the integer face property that
                       labels the parts [the first of material_index, material, part, label,
                       segment, group]
      [[objects.parts]] (mesh objects) a part with a material of its own, an object named
                       "<name>.<part name>" at the table's pose (docs/any_shape.md, "Parts"):
                       name, faces [[name]] (labels of the mesh file: OBJ g, o or usemtl
                       names, PLY property values), [objects.parts.material] (as above)
    [[surfaces]]       (optional) real surfaces that are not drawn but take part in the light
                       transport (docs/surfaces.md): name (unique), shape ["plane"],
                       point [[0,0,0]] (a point of the plane, world, m), normal [[0,1,0]]
                       (world; the objects' side), reflectance (as a material's, [0.5]),
                       margin [3.0] (the shaded region around the objects, in bounding radii),
                       resolution [128] (texels across that region)
    [markers]          (optional; live mixed reality, see spectral_fit/live/_markers.py)
                       dictionary ["DICT_5X5_100"] (an OpenCV ArUco/AprilTag dictionary),
                       size [0.08] (side of the black square, m), world (optional marker id
                       whose frame is the world: marker plane = ground, +Y up), smoothing [0]
                       (exponential pose smoothing in [0, 1)), hold_frames [0] (frames a lost
                       marker's object stays at its last pose before it is masked out),
                       refine ["edges" | "subpix" | "contour" | "apriltag" | "none"],
                       tone ["none" | "srgb" | "gamma"] (the frames' tone curve: "edges"
                       finds the half-contrast crossing in linear light), gamma [2.2]
    [camera_colour]    (optional; live compositing, from ``spectral-fit calibrate-colour``)
                       matrix (3×3 rows: absolute XYZ → white-balanced linear frame RGB),
                       white_balance [[1, 1, 1]] (per-channel gains after the matrix),
                       tone ["srgb" | "gamma" | "linear"], gamma [2.2]
    [colour_chart]     (optional; live compositing: a ColorChecker lying in the video, placed
                       relative to a marker, from which the live session fits the camera's
                       colour) marker (id), centre [[0,0,0]] (the chart's centre in that
                       marker's ground frame, m: +Y its normal, −Z its top edge), size
                       [[0.12, 0.08]] (width × height of the patch area, m: 6 × 4 patches),
                       rotation_deg [0] (about the ground frame's +Y; 0: patch 1, dark skin,
                       at the −X, −Z corner), chart ["BabelColor Average"] (colour-science's
                       reflectances), frames [8] (frames averaged), search_frames [300]
                       (frames looked through from the start), min_patch_px [6] (smallest
                       patch side in pixels to use a frame), tone ["srgb" | "gamma" |
                       "linear" | "fit"], gamma [2.2]
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from .._runtime.errors import InputError

__all__ = [
    "Scene",
    "CameraSpec",
    "EnvironmentSpec",
    "DisplaySpec",
    "SpectralSpec",
    "InterreflectionSpec",
    "ObjectSpec",
    "MaterialSpec",
    "MarkerSpec",
    "SurfaceSpec",
    "CameraColourSpec",
    "ColourChartSpec",
    "MARKER_DICTIONARIES",
    "load_scene",
    "parse_scene",
    "MAX_BLUR_PX",
    "MAX_NOISE",
]

_MISSING = object()


#: largest coordinate (m) of a camera or object position, look-at point, up vector or marker
#: offset: far beyond any scene of this renderer, and products of two such stay finite in
#: float32
MAX_COORD_M = 1e6
# bounds of [camera] blur_px (σ, pixels) and noise (σ, 8-bit levels)
MAX_BLUR_PX = 20.0
MAX_NOISE = 64.0


@dataclasses.dataclass(frozen=True)
class CameraSpec:
    """Pinhole camera (OpenGL convention: looks down −Z of its frame, +Y up)."""

    fov_y_deg: float = 90.0
    near: float = 0.01
    far: float = 1000.0
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    look_at: tuple[float, float, float] = (0.0, 0.0, -1.0)
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    intrinsics: dict[str, float] | None = None  # fx, fy, cx, cy in pixels
    distortion: tuple[float, ...] | None = None  # k1, k2, p1, p2, k3
    blur_px: float = 0.0  # the video's blur (Gaussian σ, pixels), given to composited CG
    noise: float = 0.0  # the video's noise (σ, 8-bit levels), given to composited CG


@dataclasses.dataclass(frozen=True)
class EnvironmentSpec:
    file: Path
    scale: float = 1.0
    rotation_y_deg: float = 0.0
    upsampling: str = "mallett2019"
    #: relative error per texel allowed when the prefiltered maps are kept in the map's own
    #: principal spectra (:meth:`~spectral_fit.lighting.EnvironmentMap.from_array`)
    compress_tol: float = 1e-4


@dataclasses.dataclass(frozen=True)
class DisplaySpec:
    colourspace: str = "sRGB"
    characterisation: Path | None = None
    exposure_luminance: float | str = "auto"
    scene_white_xy: tuple[float, float] | None = None


@dataclasses.dataclass(frozen=True)
class SpectralSpec:
    start_nm: float = 380.0
    end_nm: float = 780.0
    step_nm: float = 5.0
    mode: str = "bands"
    k: int = 8

    def wavelengths(self) -> np.ndarray:
        from ..color import wavelength_grid

        return wavelength_grid(self.start_nm, self.end_nm, self.step_nm)


@dataclasses.dataclass(frozen=True)
class InterreflectionSpec:
    mode: str = "gather"
    bounces: int = 1
    texture_size: int = 256
    gather_size: int = 16
    tail: str = "none"


@dataclasses.dataclass(frozen=True)
class MaterialSpec:
    """Material parameters in our physical scaling (not the paper's)."""

    reflectance: np.ndarray  # (L,) on the scene grid
    reflectance_source: str
    alpha: float = 1.0
    beta: float = 1.0
    chi: float = 0.0
    mu: float = 0.1
    n: float = 1.5
    gamma: float = 1.0
    distribution: str = "gaussian"
    geometry: str = "vcavity"


@dataclasses.dataclass(frozen=True)
class ObjectSpec:
    name: str
    shape: str
    material: MaterialSpec
    radius: float = 0.0375
    stacks: int = 100
    slices: int = 100
    subdivisions: int = 5
    mesh: Path | None = None
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: float = 1.0
    marker: int | None = None
    marker_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: a part of a mesh object with several materials: the name of the ``[[objects]]`` table
    #: it comes from (its pose and marker are that table's), else None
    body: str | None = None
    #: the face labels of the mesh file this object takes (:func:`~spectral_fit.io.face_labels`;
    #: None: every face), and those it leaves to other parts
    faces: tuple[str, ...] | None = None
    faces_except: tuple[str, ...] = ()
    #: the PLY face property whose values are the labels (None: the first known one)
    face_property: str | None = None
    #: a part's origin: the point of the mesh file (its frame, m, before ``scale``) at the
    #: centre of the part's bounding box, so that the parts of one body have centres of their
    #: own (the interreflection and the occlusion between objects are built on each object's
    #: origin); (0, 0, 0) for a whole object
    part_origin: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def model_matrix(self) -> np.ndarray:
        """4×4 world-from-object matrix: translate · Rz · Ry · Rx · scale · translate(part
        origin) (column vectors)."""
        rx, ry, rz = (math.radians(a) for a in self.rotation_deg)

        def rot(axis: int, a: float) -> np.ndarray:
            c, s = math.cos(a), math.sin(a)
            i, j = [(1, 2), (2, 0), (0, 1)][axis]
            m = np.eye(3)
            m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
            return m

        m = np.eye(4)
        m[:3, :3] = rot(2, rz) @ rot(1, ry) @ rot(0, rx) * self.scale
        m[:3, 3] = np.asarray(self.position) + m[:3, :3] @ np.asarray(self.part_origin)
        return m

    def make_mesh(self, *, world: bool = False) -> Any:
        """The object's :class:`~spectral_fit.io.Mesh`: its UV sphere, icosphere or mesh
        file in the object's own frame (metres), or moved into the world by
        :meth:`model_matrix` (``world=True``)."""
        from ._mesh import (
            icosphere,
            load_labelled_mesh,
            load_mesh,
            select_faces,
            translate,
            uv_sphere,
        )

        if self.shape == "uv_sphere":
            m = uv_sphere(self.radius, self.stacks, self.slices)
        elif self.shape == "icosphere":
            m = icosphere(self.radius, self.subdivisions)
        elif self.faces is None and not self.faces_except:
            m = load_mesh(self.mesh)
        else:
            m, labels = load_labelled_mesh(self.mesh, ply_property=self.face_property)
            m = select_faces(m, self.face_mask(labels))
        if any(self.part_origin):
            m = m.transformed(translate(-np.asarray(self.part_origin)))
        return m.transformed(self.model_matrix()) if world else m

    def face_mask(self, labels: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """``(T,)`` bool over the triangles of the whole mesh file: those this object takes
        (a part: its labels; the rest of a body: every face no part takes). ``labels``: the
        file's :func:`~spectral_fit.io.face_labels` (read from it when None)."""
        from ._mesh import face_labels

        if labels is None:
            labels = face_labels(self.mesh, ply_property=self.face_property)
        some = next(iter(labels.values()))
        take = (np.ones(some.shape, bool) if self.faces is None
                else np.any([labels[k] for k in self.faces], axis=0))
        for k in self.faces_except:
            take &= ~labels[k]
        return take


#: OpenCV's predefined marker dictionaries and how many ids each holds
MARKER_DICTIONARIES: dict[str, int] = {
    **{f"DICT_{b}X{b}_{n}": n for b in (4, 5, 6, 7) for n in (50, 100, 250, 1000)},
    "DICT_ARUCO_ORIGINAL": 1024,
    "DICT_APRILTAG_16h5": 30,
    "DICT_APRILTAG_25h9": 35,
    "DICT_APRILTAG_36h10": 2320,
    "DICT_APRILTAG_36h11": 587,
    "DICT_ARUCO_MIP_36h12": 250,
}


@dataclasses.dataclass(frozen=True)
class MarkerSpec:
    """Fiducial markers of a live session (the ``[markers]`` table).

    Attributes:
        dictionary: OpenCV dictionary name (a key of :data:`MARKER_DICTIONARIES`).
        size: side of the marker's black square in metres (the paper's markers: 0.08).
        world: id of the marker whose frame is the world frame (its plane is the ground,
            world +Y its normal), or None: the world is the camera's frame.
        smoothing: exponential smoothing weight of the previous pose, in [0, 1) (0 = none).
        hold_frames: frames an object keeps its last pose after its marker is lost.
        refine: corner refinement: "edges" (sub-pixel edge lines, unbiased under blur; the
            default), or OpenCV's "subpix", "contour", "apriltag", "none".
        tone: the frames' tone curve as the "edges" refinement reads them: "none" (default:
            the half-contrast crossing of the encoded grey levels), "srgb" or "gamma" (with
            ``gamma``): the crossing in linear light. A camera blurs in linear light (its
            pixels integrate light); after a tone curve the encoded half level lies on the
            dark side of the edge, so the black square looks smaller and farther away.
        gamma: exponent of ``tone = "gamma"``.
    """

    dictionary: str = "DICT_5X5_100"
    size: float = 0.08
    world: int | None = None
    smoothing: float = 0.0
    hold_frames: int = 0
    refine: str = "edges"
    tone: str = "none"
    gamma: float = 2.2


@dataclasses.dataclass(frozen=True)
class SurfaceSpec:
    """A real surface of the scene (a ``[[surfaces]]`` table): an infinite plane that is not
    drawn but hides the environment below it, receives the objects' shadows and light and
    reflects its own light onto them (Lambertian).

    Attributes:
        name: unique name.
        shape: "plane".
        point: (3,) a point of the plane, world frame (m).
        normal: (3,) unit normal, world frame, pointing to the objects' side.
        reflectance: (L,) spectral reflectance on the scene's wavelengths, in [0, 1].
        reflectance_source: where it came from (for reports).
        margin: half-side of the shaded region beyond the objects' footprints, in units of
            their largest bounding radius.
        resolution: texels across the shaded region (per side).
    """

    name: str
    shape: str
    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    reflectance: np.ndarray
    reflectance_source: str
    margin: float = 3.0
    resolution: int = 128


@dataclasses.dataclass(frozen=True)
class CameraColourSpec:
    """The video camera's colour model of a live session (the ``[camera_colour]`` table), a
    3×3 fitted from a ColorChecker shot: linear frame RGB = diag(white_balance) · matrix · XYZ
    (XYZ absolute, cd/m²), then the frame's tone curve (see :mod:`spectral_fit.live`).

    Attributes:
        matrix: 3×3 rows, absolute XYZ → white-balanced linear RGB (the scene's white maps to
            equal channels).
        white_balance: per-channel gains (exposure included).
        tone: "srgb", "gamma" or "linear"; gamma: exponent of "gamma".
    """

    matrix: tuple[tuple[float, float, float], ...]
    white_balance: tuple[float, float, float] = (1.0, 1.0, 1.0)
    tone: str = "srgb"
    gamma: float = 2.2


@dataclasses.dataclass(frozen=True)
class ColourChartSpec:
    """A ColorChecker lying in the video (the ``[colour_chart]`` table): the live session finds
    it through a tracked marker and fits the camera's colour from it
    (:func:`spectral_fit.live.chart_camera_model`).

    Attributes:
        marker: id of the marker the chart is placed against.
        centre: (3,) the chart's centre in that marker's ground frame (m; +Y = the marker's
            normal, −Z = its top edge).
        size: (width, height) of the chart's patch area (m): its 6 columns run along the
            ground frame's +X and its 4 rows along +Z before ``rotation_deg``.
        rotation_deg: rotation about the ground frame's +Y (degrees, counter-clockwise seen
            from above); at 0 patch 1 (dark skin) is at the −X, −Z corner.
        chart: colour-science ColorChecker reflectances (``SDS_COLOURCHECKERS`` key).
        frames: frames whose patch samples are averaged.
        search_frames: frames looked through from the start of the video.
        min_patch_px: a frame is used when every patch is at least this many pixels across.
        tone: the frame's tone curve ("fit": a gamma curve fitted on the neutral patches);
            gamma: its exponent for "gamma".
    """

    marker: int
    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)
    size: tuple[float, float] = (0.12, 0.08)
    rotation_deg: float = 0.0
    chart: str = "BabelColor Average"
    frames: int = 8
    search_frames: int = 300
    min_patch_px: float = 6.0
    tone: str = "srgb"
    gamma: float = 2.2


@dataclasses.dataclass(frozen=True)
class Scene:
    """A validated scene description (see the module docstring for the file format)."""

    path: Path | None
    width: int
    height: int
    camera: CameraSpec
    environment: EnvironmentSpec
    display: DisplaySpec
    spectral: SpectralSpec
    interreflection: InterreflectionSpec
    objects: tuple[ObjectSpec, ...]
    markers: MarkerSpec | None = None
    camera_colour: CameraColourSpec | None = None
    surfaces: tuple[SurfaceSpec, ...] = ()
    colour_chart: ColourChartSpec | None = None

    @property
    def wavelengths(self) -> np.ndarray:
        return self.spectral.wavelengths()

    def replace(self, **changes: Any) -> Scene:
        return dataclasses.replace(self, **changes)


# ----------------------------------------------------------------------------- validation


class _Reader:
    """Typed access to one table of the config, with errors naming file and key."""

    def __init__(self, table: Any, prefix: str, path: Path | None) -> None:
        self.path = path
        self.prefix = prefix
        if not isinstance(table, dict):
            raise InputError(f"must be a table, got {type(table).__name__}", path=path,
                             field=prefix or "<root>")
        self.table = table
        self.used: set[str] = set()

    def key(self, k: str) -> str:
        return f"{self.prefix}.{k}" if self.prefix else k

    def err(self, k: str, msg: str) -> InputError:
        return InputError(msg, path=self.path, field=self.key(k))

    def raw(self, k: str, default: Any = _MISSING) -> Any:
        self.used.add(k)
        if k not in self.table:
            if default is _MISSING:
                raise self.err(k, "required key is missing")
            return default
        return self.table[k]

    def number(self, k: str, default: Any = _MISSING, *, lo: float | None = None,
               hi: float | None = None, lo_open: bool = False) -> float:
        v = self.raw(k, default)
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise self.err(k, f"must be a number, got {v!r}")
        v = float(v)
        if not math.isfinite(v):
            raise self.err(k, f"must be finite, got {v}")
        if lo is not None and (v <= lo if lo_open else v < lo):
            raise self.err(k, f"must be {'>' if lo_open else '>='} {lo:g}, got {v:g}")
        if hi is not None and v > hi:
            raise self.err(k, f"must be <= {hi:g}, got {v:g}")
        return v

    def integer(self, k: str, default: Any = _MISSING, *, lo: int | None = None,
                hi: int | None = None) -> int:
        v = self.raw(k, default)
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.err(k, f"must be an integer, got {v!r}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise self.err(k, f"must be in [{lo}, {hi}], got {v}")
        return int(v)

    def choice(self, k: str, options: tuple[str, ...], default: Any = _MISSING) -> str:
        v = self.raw(k, default)
        if not isinstance(v, str) or v not in options:
            raise self.err(k, f"must be one of {list(options)}, got {v!r}")
        return v

    def string(self, k: str, default: Any = _MISSING) -> str:
        v = self.raw(k, default)
        if not isinstance(v, str) or not v:
            raise self.err(k, f"must be a non-empty string, got {v!r}")
        return v

    def vector(self, k: str, n: int, default: Any = _MISSING, *,
               bound: float | None = None) -> tuple[float, ...]:
        """``n`` finite numbers; ``bound``: each within ±bound."""
        v = self.raw(k, default)
        if (not isinstance(v, list | tuple) or len(v) != n
                or not all(isinstance(x, int | float) and not isinstance(x, bool) for x in v)):
            raise self.err(k, f"must be a list of {n} numbers, got {v!r}")
        if not all(math.isfinite(float(x)) for x in v):
            raise self.err(k, f"must be finite, got {v!r}")
        if bound is not None and any(abs(float(x)) > bound for x in v):
            raise self.err(k, f"each component must be within ±{bound:g} (metres: the "
                              f"renderer computes in float32), got {v!r}")
        return tuple(float(x) for x in v)

    def file(self, k: str, default: Any = _MISSING, *, must_exist: bool = True) -> Path | None:
        v = self.raw(k, default)
        if v is None:
            return None
        if not isinstance(v, str) or not v or "\x00" in v:
            raise self.err(k, f"must be a file path, got {v!r}")
        base = self.path.parent if self.path is not None else Path.cwd()
        p = (base / v).resolve() if not os.path.isabs(v) else Path(v)
        if must_exist and not p.is_file():
            raise self.err(k, f"file not found: {p}")
        return p

    def sub(self, k: str, *, required: bool = False) -> _Reader:
        v = self.raw(k, _MISSING if required else {})
        return _Reader(v, self.key(k), self.path)

    def finish(self) -> None:
        unknown = sorted(set(self.table) - self.used)
        if unknown:
            raise self.err(unknown[0], f"unknown key (known: {sorted(self.used)})")


def _reflectance(r: _Reader, wl: np.ndarray) -> tuple[np.ndarray, str]:
    v = r.raw("reflectance", 0.5)
    if isinstance(v, int | float) and not isinstance(v, bool):
        x = r.number("reflectance", v, lo=0.0, hi=1.0)
        return np.full(wl.shape, x), f"constant {x:g}"
    if isinstance(v, list):
        vals = r.vector("reflectance", wl.size)
        arr = np.asarray(vals)
        if (arr < 0).any() or (arr > 1.5).any():
            raise r.err("reflectance", "values must lie in [0, 1.5]")
        return arr, "inline list"
    if not isinstance(v, str) or not v:
        raise r.err("reflectance", f"must be a number, a list, a CSV file or "
                    f"'colourchecker:<set>/<patch>', got {v!r}")
    if v.startswith("colourchecker:"):
        import colour

        name = v.split(":", 1)[1]
        if "/" not in name:
            raise r.err("reflectance", "use 'colourchecker:<set>/<patch>'")
        cset, patch = name.split("/", 1)
        if cset not in colour.SDS_COLOURCHECKERS:
            raise r.err("reflectance", f"unknown ColorChecker set {cset!r}; known: "
                        f"{sorted(colour.SDS_COLOURCHECKERS)}")
        if patch not in colour.SDS_COLOURCHECKERS[cset]:
            raise r.err("reflectance", f"unknown patch {patch!r} in {cset!r}")
        sd = colour.SDS_COLOURCHECKERS[cset][patch]
        from ..color import resample

        return resample(sd.wavelengths, sd.values, wl, field=r.key("reflectance"),
                        margin_nm=40.0), v
    p = r.file("reflectance")
    from ..color import read_spectrum_csv, resample

    wl_in, values = read_spectrum_csv(p)  # type: ignore[arg-type]
    if values.ndim != 1:
        values = values.mean(axis=0)
    refl = resample(wl_in, values, wl, path=p, field="reflectance")
    if (refl > 1.5).any():
        raise InputError("reflectance above 1.5: is this a percentage? use 0..1", path=p,
                         field="reflectance")
    return refl, str(p)


def _material(r: _Reader, wl: np.ndarray) -> MaterialSpec:
    refl, src = _reflectance(r, wl)
    m = MaterialSpec(
        reflectance=refl,
        reflectance_source=src,
        alpha=r.number("alpha", 1.0, lo=0.0),
        beta=r.number("beta", 1.0, lo=0.0),
        chi=r.number("chi", 0.0, lo=0.0),
        mu=r.number("mu", 0.1, lo=0.0, lo_open=True, hi=1.5),
        n=r.number("n", 1.5, lo=1.0, lo_open=True, hi=4.0),
        gamma=r.number("gamma", 1.0, lo=0.0),
        distribution=r.choice("distribution", ("gaussian", "beckmann"), "gaussian"),
        geometry=r.choice("geometry", ("vcavity", "smith"), "vcavity"),
    )
    r.finish()
    return m


def _objects(r: _Reader, wl: np.ndarray) -> list[ObjectSpec]:
    """One ``[[objects]]`` table: its object, or for a mesh with ``[[objects.parts]]`` one
    object per part (named ``<name>.<part>``) and one for the faces no part takes (named
    ``<name>``, left out when every face is in a part), all at the table's pose."""
    obj = _object(r, wl)
    parts = r.raw("parts", None)
    if parts is None:
        r.finish()
        return [obj]
    if obj.shape != "mesh":
        raise r.err("parts", "only a mesh object (shape = \"mesh\") has parts")
    if not isinstance(parts, list) or not parts:
        raise r.err("parts", "must be a non-empty array of tables ([[objects.parts]])")
    prop = r.raw("part_property", None)
    if prop is not None:
        prop = r.string("part_property")
        if obj.mesh is not None and obj.mesh.suffix.lower() != ".ply":
            raise r.err("part_property", "only PLY files have face properties")
    r.finish()
    from ._mesh import load_labelled_mesh

    whole, labels = load_labelled_mesh(obj.mesh, ply_property=prop)  # type: ignore[arg-type]
    if not labels:
        raise r.err("parts", f"{obj.mesh} names no sets of faces (OBJ: g, o or usemtl; PLY: "
                    "an integer face property such as material_index)")
    out: list[ObjectSpec] = []
    owner = np.full(next(iter(labels.values())).shape, -1)
    taken: list[str] = []
    for j, t in enumerate(parts):
        pr = _Reader(t, r.key(f"parts[{j}]"), r.path)
        part = pr.string("name")
        faces = pr.raw("faces", [part])
        if isinstance(faces, str | int) and not isinstance(faces, bool):
            faces = [faces]
        if (not isinstance(faces, list) or not faces
                or not all(isinstance(f, str | int) and not isinstance(f, bool) for f in faces)):
            raise pr.err("faces", f"must be a list of face labels (names or integers), got "
                         f"{faces!r}")
        faces = [str(f) for f in faces]
        missing = [f for f in faces if f not in labels]
        if missing:
            known = sorted(labels)
            raise pr.err("faces", f"{missing[0]!r} labels no face of {obj.mesh.name} (its "  # type: ignore[union-attr]
                         f"labels: {known[:20]}{' ...' if len(known) > 20 else ''})")
        mask = np.any([labels[f] for f in faces], axis=0)
        clash = np.unique(owner[mask & (owner >= 0)])
        if clash.size:
            raise pr.err("faces", f"faces {faces} overlap those of part "
                         f"{parts[int(clash[0])].get('name')!r}")
        owner[mask] = j
        taken.extend(faces)
        out.append(dataclasses.replace(
            obj, name=f"{obj.name}.{part}", material=_material(pr.sub("material"), wl),
            body=obj.name, faces=tuple(faces), face_property=prop))
        pr.finish()
    if (owner < 0).any():  # the faces no part takes keep the table's own material
        out.insert(0, dataclasses.replace(obj, body=obj.name, faces_except=tuple(taken),
                                          face_property=prop))
    # each part's origin at its bounding box's centre
    for k, o in enumerate(out):
        v = whole.vertices[np.unique(whole.triangles[o.face_mask(labels)])]
        centre = 0.5 * (v.min(axis=0) + v.max(axis=0)).astype(np.float64)
        out[k] = dataclasses.replace(o, part_origin=tuple(float(x) for x in centre))
    return out


def _object(r: _Reader, wl: np.ndarray) -> ObjectSpec:
    name = r.string("name")
    shape = r.choice("shape", ("uv_sphere", "icosphere", "mesh"), "uv_sphere")
    kw: dict[str, Any] = {}
    if shape == "mesh":
        kw["mesh"] = r.file("mesh")
    else:
        kw["radius"] = r.number("radius", 0.0375, lo=0.0, lo_open=True)
    if shape == "uv_sphere":
        kw["stacks"] = r.integer("stacks", 100, lo=3, hi=2000)
        kw["slices"] = r.integer("slices", 100, lo=3, hi=2000)
    if shape == "icosphere":
        kw["subdivisions"] = r.integer("subdivisions", 5, lo=0, hi=8)
    marker = r.raw("marker", None)
    if marker is not None:
        marker = r.integer("marker", lo=0, hi=100000)
    obj = ObjectSpec(
        name=name,
        shape=shape,
        material=_material(r.sub("material"), wl),
        position=r.vector("position", 3, [0.0, 0.0, 0.0],  # type: ignore[arg-type]
                          bound=MAX_COORD_M),
        rotation_deg=r.vector("rotation_deg", 3, [0.0, 0.0, 0.0]),  # type: ignore[arg-type]
        scale=r.number("scale", 1.0, lo=0.0, lo_open=True),
        marker=marker,
        marker_offset=r.vector("marker_offset", 3, [0.0, 0.0, 0.0],  # type: ignore[arg-type]
                               bound=MAX_COORD_M),
        **kw,
    )
    return obj


def _surface(r: _Reader, wl: np.ndarray) -> SurfaceSpec:
    name = r.string("name")
    shape = r.choice("shape", ("plane",), "plane")
    refl, src = _reflectance(r, wl)
    if (refl > 1.0).any():
        raise r.err("reflectance", "a real surface reflects at most all the light (≤ 1)")
    normal = np.asarray(r.vector("normal", 3, [0.0, 1.0, 0.0]), np.float64)
    length = float(np.linalg.norm(normal))
    if length < 1e-9:
        raise r.err("normal", "must not be zero")
    s = SurfaceSpec(
        name=name, shape=shape,
        point=tuple(r.vector("point", 3, [0.0, 0.0, 0.0],  # type: ignore[arg-type]
                             bound=MAX_COORD_M)),
        normal=tuple(float(x) for x in normal / length),  # type: ignore[arg-type]
        reflectance=refl, reflectance_source=src,
        margin=r.number("margin", 3.0, lo=0.5, hi=50.0),
        resolution=r.integer("resolution", 128, lo=8, hi=2048),
    )
    r.finish()
    return s


def parse_scene(data: dict[str, Any], *, path: str | os.PathLike[str] | None = None) -> Scene:
    """Validate a parsed config (a dict as from ``tomllib``) into a :class:`Scene`."""
    p = None if path is None else Path(path)
    root = _Reader(data, "", p)

    fr = root.sub("frame")
    width = fr.integer("width", 720, lo=1, hi=16384)
    height = fr.integer("height", 480, lo=1, hi=16384)
    fr.finish()

    cr = root.sub("camera")
    intr = cr.raw("intrinsics", None)
    intrinsics = None
    if intr is not None:
        ir = cr.sub("intrinsics")
        intrinsics = {k: ir.number(k, lo=0.0, lo_open=k in ("fx", "fy"))
                      for k in ("fx", "fy", "cx", "cy")}
        ir.finish()
    dist = cr.raw("distortion", None)
    distortion = None
    if dist is not None:
        if not isinstance(dist, list) or len(dist) not in (4, 5, 8):
            raise cr.err("distortion", "must be a list of 4, 5 or 8 numbers (OpenCV order)")
        distortion = cr.vector("distortion", len(dist))
    camera = CameraSpec(
        fov_y_deg=cr.number("fov_y_deg", 90.0, lo=1.0, hi=179.0),
        near=cr.number("near", 0.01, lo=0.0, lo_open=True),
        far=cr.number("far", 1000.0, lo=0.0, lo_open=True),
        position=cr.vector("position", 3, [0.0, 0.0, 0.0],  # type: ignore[arg-type]
                           bound=MAX_COORD_M),
        look_at=cr.vector("look_at", 3, [0.0, 0.0, -1.0],  # type: ignore[arg-type]
                          bound=MAX_COORD_M),
        up=cr.vector("up", 3, [0.0, 1.0, 0.0],  # type: ignore[arg-type]
                     bound=MAX_COORD_M),
        intrinsics=intrinsics,
        distortion=distortion,
        blur_px=cr.number("blur_px", 0.0, lo=0.0, hi=MAX_BLUR_PX),
        noise=cr.number("noise", 0.0, lo=0.0, hi=MAX_NOISE),
    )
    if camera.far <= camera.near:
        raise cr.err("far", f"must be greater than near ({camera.near:g})")
    fwd = np.subtract(camera.look_at, camera.position)
    if np.linalg.norm(fwd) < 1e-12:
        raise cr.err("look_at", "must differ from position")
    if np.linalg.norm(np.cross(fwd, camera.up)) < 1e-9 * np.linalg.norm(fwd):
        raise cr.err("up", "must not be parallel to the viewing direction")
    cr.finish()

    er = root.sub("environment", required=True)
    environment = EnvironmentSpec(
        file=er.file("file"),  # type: ignore[arg-type]
        scale=er.number("scale", 1.0, lo=0.0, lo_open=True),
        rotation_y_deg=er.number("rotation_y_deg", 0.0, lo=-360.0, hi=360.0),
        upsampling=er.choice("upsampling", ("mallett2019", "jakob2019"), "mallett2019"),
        compress_tol=er.number("compress_tol", 1e-4, lo=0.0, hi=0.1),
    )
    er.finish()

    dr = root.sub("display")
    exp = dr.raw("exposure_luminance", "auto")
    if exp != "auto":
        exp = dr.number("exposure_luminance", lo=0.0, lo_open=True)
    swxy = dr.raw("scene_white_xy", None)
    import colour  # validated against colour's registry of RGB colourspaces

    cs = dr.string("colourspace", "sRGB")
    if cs not in colour.RGB_COLOURSPACES:
        raise dr.err("colourspace", f"unknown RGB colourspace {cs!r}")
    display = DisplaySpec(
        colourspace=cs,
        characterisation=dr.file("characterisation", None),
        exposure_luminance=exp,
        scene_white_xy=None if swxy is None else dr.vector("scene_white_xy", 2),  # type: ignore[arg-type]
    )
    dr.finish()

    sr = root.sub("spectral")
    spectral = SpectralSpec(
        start_nm=sr.number("start_nm", 380.0, lo=360.0, hi=830.0),
        end_nm=sr.number("end_nm", 780.0, lo=360.0, hi=830.0),
        step_nm=sr.number("step_nm", 5.0, lo=0.5, hi=100.0),
        mode=sr.choice("mode", ("bands", "basis"), "bands"),
        k=sr.integer("k", 8, lo=1, hi=64),
    )
    if spectral.end_nm <= spectral.start_nm:
        raise sr.err("end_nm", f"must exceed start_nm ({spectral.start_nm:g})")
    sr.finish()
    wl = spectral.wavelengths()
    if wl.size < 3:
        raise sr.err("step_nm", "the grid must have at least 3 wavelengths")
    if spectral.mode == "basis" and spectral.k > wl.size:
        raise sr.err("k", f"must not exceed the number of wavelengths ({wl.size})")

    ir_ = root.sub("interreflection")
    inter = InterreflectionSpec(
        mode=ir_.choice("mode", ("gather", "paper", "none"), "gather"),
        bounces=ir_.integer("bounces", 1, lo=0, hi=16),
        texture_size=ir_.integer("texture_size", 256, lo=8, hi=4096),
        gather_size=ir_.integer("gather_size", 16, lo=4, hi=64),
        tail=ir_.choice("tail", ("none", "geometric"), "none"),
    )
    if inter.gather_size & (inter.gather_size - 1):
        raise ir_.err("gather_size", f"must be a power of two (4, 8, 16, 32 or 64), got "
                                     f"{inter.gather_size}")
    ir_.finish()

    objs = root.raw("objects", [])
    if not isinstance(objs, list) or not objs:
        raise root.err("objects", "need at least one [[objects]] table")
    groups = [_objects(_Reader(t, f"objects[{i}]", p), wl) for i, t in enumerate(objs)]
    objects = tuple(o for g in groups for o in g)
    tables = [i for i, g in enumerate(groups) for _ in g]  # each object's [[objects]] table
    names = [o.name for o in objects]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise root.err("objects", f"object names must be unique; repeated: {sorted(dup)}")
    surf = root.raw("surfaces", [])
    if not isinstance(surf, list):
        raise root.err("surfaces", "must be an array of tables ([[surfaces]])")
    surfaces = tuple(_surface(_Reader(t, f"surfaces[{i}]", p), wl) for i, t in enumerate(surf))
    snames = [t.name for t in surfaces]
    if len(set(snames)) != len(snames):
        raise root.err("surfaces", f"surface names must be unique: {snames}")
    markers = _markers(root, objects, tables) if "markers" in data else None
    camera_colour = _camera_colour(root) if "camera_colour" in data else None
    colour_chart = _colour_chart(root, markers) if "colour_chart" in data else None
    root.finish()
    return Scene(path=p, width=width, height=height, camera=camera, environment=environment,
                 display=display, spectral=spectral, interreflection=inter, objects=objects,
                 markers=markers, camera_colour=camera_colour, surfaces=surfaces,
                 colour_chart=colour_chart)


def _colour_chart(root: _Reader, markers: MarkerSpec | None) -> ColourChartSpec:
    """The ``[colour_chart]`` table; needs ``[markers]`` (its marker id in the dictionary)."""
    import colour

    cr = root.sub("colour_chart")
    if markers is None:
        raise cr.err("marker", "a chart placed by a marker needs a [markers] table")
    n_ids = MARKER_DICTIONARIES[markers.dictionary]
    size = cr.vector("size", 2, [0.12, 0.08], bound=MAX_COORD_M)
    if min(size) <= 0:
        raise cr.err("size", f"width and height must be > 0, got {list(size)}")
    chart = cr.string("chart", "BabelColor Average")
    if chart not in colour.SDS_COLOURCHECKERS:
        raise cr.err("chart", f"unknown chart {chart!r}; known: "
                              f"{sorted(colour.SDS_COLOURCHECKERS)}")
    spec = ColourChartSpec(
        marker=cr.integer("marker", lo=0, hi=n_ids - 1),
        centre=cr.vector("centre", 3, [0.0, 0.0, 0.0], bound=MAX_COORD_M),  # type: ignore[arg-type]
        size=size,  # type: ignore[arg-type]
        rotation_deg=cr.number("rotation_deg", 0.0, lo=-360.0, hi=360.0),
        chart=chart,
        frames=cr.integer("frames", 8, lo=1, hi=10000),
        search_frames=cr.integer("search_frames", 300, lo=1, hi=1000000),
        min_patch_px=cr.number("min_patch_px", 6.0, lo=1.0, hi=1000.0),
        tone=cr.choice("tone", ("srgb", "gamma", "linear", "fit"), "srgb"),
        gamma=cr.number("gamma", 2.2, lo=0.1, hi=10.0),
    )
    cr.finish()
    return spec


def _camera_colour(root: _Reader) -> CameraColourSpec:
    """The ``[camera_colour]`` table."""
    cr = root.sub("camera_colour")
    m = cr.raw("matrix")
    if not isinstance(m, list) or len(m) != 3:
        raise cr.err("matrix", f"must be 3 rows of 3 numbers, got {m!r}")
    rows = []
    for i, row in enumerate(m):
        if (not isinstance(row, list) or len(row) != 3 or not all(
                isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
                for x in row)):
            raise cr.err("matrix", f"row {i} must be 3 finite numbers, got {row!r}")
        rows.append(tuple(float(x) for x in row))
    if abs(np.linalg.det(np.asarray(rows))) < 1e-12:
        raise cr.err("matrix", "is singular")
    wb = cr.vector("white_balance", 3, [1.0, 1.0, 1.0])
    if min(wb) <= 0:
        raise cr.err("white_balance", f"gains must be > 0, got {list(wb)}")
    spec = CameraColourSpec(
        matrix=tuple(rows), white_balance=wb,  # type: ignore[arg-type]
        tone=cr.choice("tone", ("srgb", "gamma", "linear"), "srgb"),
        gamma=cr.number("gamma", 2.2, lo=0.1, hi=10.0),
    )
    cr.finish()
    return spec


def _markers(root: _Reader, objects: tuple[ObjectSpec, ...], tables: list[int]) -> MarkerSpec:
    """The ``[markers]`` table; object marker ids must exist in the dictionary."""
    mr = root.sub("markers")
    dictionary = mr.choice("dictionary", tuple(MARKER_DICTIONARIES), "DICT_5X5_100")
    n_ids = MARKER_DICTIONARIES[dictionary]
    world = mr.raw("world", None)
    if world is not None:
        world = mr.integer("world", lo=0, hi=n_ids - 1)
    spec = MarkerSpec(
        dictionary=dictionary,
        size=mr.number("size", 0.08, lo=0.0, lo_open=True, hi=10.0),
        world=world,
        smoothing=mr.number("smoothing", 0.0, lo=0.0, hi=0.99),
        hold_frames=mr.integer("hold_frames", 0, lo=0, hi=10000),
        refine=mr.choice("refine", ("edges", "subpix", "contour", "apriltag", "none"), "edges"),
        tone=mr.choice("tone", ("none", "srgb", "gamma"), "none"),
        gamma=mr.number("gamma", 2.2, lo=0.1, hi=10.0),
    )
    mr.finish()
    for i, o in zip(tables, objects, strict=True):
        if o.marker is not None and o.marker >= n_ids:
            raise root.err(f"objects[{i}].marker", f"id {o.marker} is not in {dictionary} "
                           f"(ids 0..{n_ids - 1})")
    return spec


def load_scene(path: str | os.PathLike[str],
               overrides: Callable[[dict[str, Any]], None] | None = None) -> Scene:
    """Read and validate a TOML scene config (stable API ``load_scene``).

    ``overrides``, if given, may edit the parsed dict before validation (used by the CLI's
    ``--size``/``--mode`` options).
    """
    from .._runtime.fileio import read_text

    p = Path(path)
    text = read_text(p)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"TOML syntax error: {exc}", path=p) from None
    if overrides is not None:
        overrides(data)
    return parse_scene(data, path=p)
