"""Triangle meshes: generators (UV sphere, icosphere), OBJ/PLY loaders, model matrices.

Conventions (docs/conventions.md, 'Conventions'): lengths in metres, right-handed world with +Y up.
Triangles are counter-clockwise seen from outside (their front face), so that ``(b − a) × (c − a)``
points out of a closed mesh. Model matrices are 4×4 and act on column vectors:
``p_world = M @ [p, 1]``; compose them right to left (``translate(t) @ rotate_y(a) @ scale(s)``
scales first).

Meshes hold NumPy arrays (vertices ``(V, 3)`` float32, triangles ``(T, 3)`` int32, normals
``(V, 3)`` float32 unit length, optional uvs ``(V, 2)`` float32); a :class:`Mesh` is an
``equinox.Module``, so it can be passed through ``jax.jit`` as a pytree.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import equinox as eqx
import numpy as np

from .._runtime.errors import InputError

__all__ = [
    "Mesh",
    "uv_sphere",
    "icosphere",
    "sphere_resolution",
    "sphere",
    "load_mesh",
    "load_obj",
    "load_ply",
    "face_labels",
    "load_labelled_mesh",
    "select_faces",
    "vertex_normals",
    "is_closed_outward",
    "translate",
    "scale",
    "rotate",
    "rotate_x",
    "rotate_y",
    "rotate_z",
    "transform_points",
    "transform_normals",
    "concat_meshes",
]


class Mesh(eqx.Module):
    """An indexed triangle mesh.

    Attributes:
        vertices: ``(V, 3)`` float32 positions (m, object frame).
        triangles: ``(T, 3)`` int32 vertex indices, counter-clockwise seen from the front.
        normals: ``(V, 3)`` float32 unit vertex normals.
        uvs: ``(V, 2)`` float32 texture coordinates, or None.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray | None = None

    def __init__(self, vertices, triangles, normals=None, uvs=None):
        v = np.asarray(vertices, dtype=np.float32)
        t = np.asarray(triangles)
        if v.ndim != 2 or v.shape[1] != 3:
            raise InputError(f"expected shape (V, 3), got {v.shape}", field="vertices")
        if t.ndim != 2 or t.shape[1] != 3:
            raise InputError(f"expected shape (T, 3), got {t.shape}", field="triangles")
        if t.size and not np.issubdtype(t.dtype, np.integer):
            raise InputError(f"expected integer indices, got {t.dtype}", field="triangles")
        if not np.all(np.isfinite(v)):
            raise InputError("non-finite vertex position", field="vertices")
        if t.size and (t.min() < 0 or t.max() >= len(v)):
            raise InputError(f"index out of range [0, {len(v)})", field="triangles")
        t = t.astype(np.int32)
        n = vertex_normals(v, t) if normals is None else np.asarray(normals, dtype=np.float32)
        if n.shape != v.shape:
            raise InputError(f"expected shape {v.shape}, got {n.shape}", field="normals")
        if uvs is not None:
            uvs = np.asarray(uvs, dtype=np.float32)
            if uvs.shape != (len(v), 2):
                raise InputError(f"expected shape ({len(v)}, 2), got {uvs.shape}", field="uvs")
        self.vertices = v
        self.triangles = t
        self.normals = n
        self.uvs = uvs

    @property
    def num_triangles(self) -> int:
        return int(self.triangles.shape[0])

    def transformed(self, matrix) -> Mesh:
        """This mesh with ``matrix`` (4×4, column vectors) applied to positions and normals."""
        m = np.asarray(matrix, dtype=np.float64)
        return Mesh(transform_points(m, self.vertices), self.triangles,
                    transform_normals(m, self.normals), self.uvs)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Smooth vertex normals ``(V, 3)``: area-weighted sum of the adjacent face normals."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    fn = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, t[:, k], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return (n / np.where(length > 0, length, 1.0)).astype(np.float32)


# ----------------------------------------------------------------------------- generators


def is_closed_outward(vertices, triangles) -> bool:
    """Whether a triangle mesh is closed by its indices and consistently wound outward: every
    directed edge (a, b) occurs once and its reverse (b, a) once (a closed, oriented 2-manifold;
    vertices duplicated along a seam count as an opening), and the enclosed signed volume
    Σ v0 · (v1 × v2) / 6 is positive (counter-clockwise seen from outside). A camera outside
    such a mesh sees only its front faces, so back faces can be culled without changing a
    pixel."""
    v = np.asarray(vertices, np.float64)
    t = np.asarray(triangles, np.int64)
    if t.ndim != 2 or t.shape[0] == 0 or t.shape[1] != 3:
        return False
    n = int(t.max()) + 1
    a = np.concatenate([t[:, 0], t[:, 1], t[:, 2]])
    b = np.concatenate([t[:, 1], t[:, 2], t[:, 0]])
    key, rev = a * n + b, b * n + a
    if np.unique(key).size != key.size or not np.all(np.isin(rev, key)):
        return False
    p0, p1, p2 = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    return bool(np.sum(p0 * np.cross(p1, p2)) > 0.0)


def uv_sphere(radius: float = 1.0, stacks: int = 100, slices: int = 100, *,
              with_uvs: bool = False) -> Mesh:
    """UV sphere centred at the origin, poles on ±Y, poles closed with triangle fans.

    ``2·slices·(stacks − 2) + 2·slices`` triangles (100 × 100 → 19,800: the paper's spheres).
    Without uvs the mesh is closed by indices ((stacks − 1)·slices + 2 vertices). With uvs
    (u = φ/2π along the slices, v = θ/π from the north pole) the seam column and the poles are
    duplicated with bit-identical positions.
    """
    stacks, slices = int(stacks), int(slices)
    if stacks < 2:
        raise InputError(f"must be >= 2, got {stacks}", field="stacks")
    if slices < 3:
        raise InputError(f"must be >= 3, got {slices}", field="slices")
    if not radius > 0:
        raise InputError(f"must be > 0, got {radius}", field="radius")
    theta = np.pi * np.arange(1, stacks) / stacks  # ring polar angles
    ncol = slices + 1 if with_uvs else slices
    phi = 2 * np.pi * np.arange(ncol) / slices
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    # φ measured from +Z toward +X: direction (sinθ sinφ, cosθ, sinθ cosφ)
    ring = np.stack([st * np.sin(phi), np.broadcast_to(ct, (stacks - 1, ncol)),
                     st * np.cos(phi)], -1)
    if with_uvs:
        ring[:, slices] = ring[:, 0]
    ring = ring.reshape(-1, 3)
    npole = slices if with_uvs else 1
    north = np.tile([[0.0, 1.0, 0.0]], (npole, 1))
    south = np.tile([[0.0, -1.0, 0.0]], (npole, 1))
    dirs = np.concatenate([north, ring, south])
    first = npole  # index of ring 0, column 0
    south0 = npole + (stacks - 1) * ncol

    def rv(i, j):  # ring i (0-based), column j
        return first + i * ncol + (j if with_uvs else j % slices)

    j = np.arange(slices)
    npi = j if with_uvs else np.zeros_like(j)
    spi = south0 + (j if with_uvs else np.zeros_like(j))
    tris = [np.stack([npi, rv(0, j), rv(0, j + 1)], -1)]
    for i in range(stacks - 2):
        a, b, c, d = rv(i, j), rv(i, j + 1), rv(i + 1, j), rv(i + 1, j + 1)
        tris.append(np.stack([a, c, d], -1))
        tris.append(np.stack([a, d, b], -1))
    tris.append(np.stack([spi, rv(stacks - 2, j + 1), rv(stacks - 2, j)], -1))
    tri = np.concatenate(tris).astype(np.int32)
    uvs = None
    if with_uvs:
        u_ring = np.broadcast_to(np.arange(ncol) / slices, (stacks - 1, ncol))
        v_ring = np.broadcast_to(np.arange(1, stacks)[:, None] / stacks, (stacks - 1, ncol))
        uvs = np.concatenate([
            np.stack([(j + 0.5) / slices, np.zeros(slices)], -1),
            np.stack([u_ring.ravel(), v_ring.ravel()], -1),
            np.stack([(j + 0.5) / slices, np.ones(slices)], -1),
        ])
    return Mesh((dirs * radius).astype(np.float32), tri, dirs.astype(np.float32), uvs)


def icosphere(radius: float = 1.0, subdivisions: int = 3) -> Mesh:
    """Icosphere: an icosahedron subdivided ``subdivisions`` times (20·4^s triangles, closed,
    10·4^s + 2 vertices), vertices on the sphere of ``radius``."""
    subdivisions = int(subdivisions)
    if subdivisions < 0:
        raise InputError(f"must be >= 0, got {subdivisions}", field="subdivisions")
    if not radius > 0:
        raise InputError(f"must be > 0, got {radius}", field="radius")
    g = (1 + math.sqrt(5)) / 2
    v = np.array([[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g],
                  [0, -1, -g], [0, 1, -g], [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]],
                 dtype=np.float64)
    t = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                  [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                  [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                  [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        edges = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
        key = np.sort(edges, axis=1)
        uniq, inv = np.unique(key, axis=0, return_inverse=True)
        mid = v[uniq[:, 0]] + v[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = len(v) + inv.reshape(3, -1)  # midpoints of edges 01, 12, 20
        v = np.concatenate([v, mid])
        a, b, c = t[:, 0], t[:, 1], t[:, 2]
        t = np.concatenate([np.stack([a, m[0], m[2]], -1), np.stack([b, m[1], m[0]], -1),
                            np.stack([c, m[2], m[1]], -1), np.stack([m[0], m[1], m[2]], -1)])
    return Mesh((v * radius).astype(np.float32), t.astype(np.int32), v.astype(np.float32))


def sphere_resolution(triangle_count: int, kind: str = "uv") -> tuple[int, int] | int:
    """Sizes giving a sphere with about ``triangle_count`` triangles.

    ``kind="uv"``: ``(stacks, slices)`` with stacks = slices = n, 2n(n − 1) triangles, n rounded
    to the nearest count. ``kind="ico"``: subdivisions s, 20·4^s triangles, s rounded in log.
    """
    if not triangle_count >= 8:
        raise InputError(f"must be >= 8, got {triangle_count}", field="triangle_count")
    if kind == "uv":
        n = (1 + math.sqrt(1 + 2 * triangle_count)) / 2
        cands = [max(3, math.floor(n)), max(3, math.ceil(n))]
        n = min(cands, key=lambda k: abs(2 * k * (k - 1) - triangle_count))
        return n, n
    if kind == "ico":
        return max(0, round(math.log(triangle_count / 20) / math.log(4)))
    raise InputError(f"unknown kind {kind!r} (uv, ico)", field="kind")


def sphere(radius: float, triangle_count: int, kind: str = "uv") -> Mesh:
    """A sphere with about ``triangle_count`` triangles (see :func:`sphere_resolution`)."""
    res = sphere_resolution(triangle_count, kind)
    return uv_sphere(radius, *res) if kind == "uv" else icosphere(radius, res)


def concat_meshes(meshes: list[Mesh]) -> tuple[Mesh, np.ndarray]:
    """Concatenate meshes into one; returns the mesh and ``(len(meshes) + 1,)`` triangle offsets
    (triangle ids ``offsets[k] ≤ id < offsets[k + 1]`` belong to mesh k)."""
    if not meshes:
        raise InputError("no meshes", field="meshes")
    vs, ts, ns, offs = [], [], [], [0]
    base = 0
    for m in meshes:
        vs.append(m.vertices)
        ts.append(m.triangles + base)
        ns.append(m.normals)
        base += len(m.vertices)
        offs.append(offs[-1] + len(m.triangles))
    uvs = None
    if all(m.uvs is not None for m in meshes):
        uvs = np.concatenate([m.uvs for m in meshes])
    return Mesh(np.concatenate(vs), np.concatenate(ts), np.concatenate(ns), uvs), np.array(
        offs, dtype=np.int32)


# ----------------------------------------------------------------------------- loaders


def load_mesh(path: str | os.PathLike[str]) -> Mesh:
    """Load an OBJ or PLY file (by extension)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".obj":
        return load_obj(path)
    if suffix == ".ply":
        return load_ply(path)
    raise InputError(f"unknown mesh format {suffix!r} (.obj, .ply)", path=path)


def _finish(path, positions, corners, normals, uvs, corner_lines) -> Mesh:
    """Build a Mesh from per-corner (position, uv, normal) index triples."""
    if not corners:
        raise InputError("no faces", path=path, field="f")
    keys = np.asarray(corners, dtype=np.int64)  # (N, 3): v, vt, vn (−1 = absent)
    for col, name in ((1, "texture coordinate"), (2, "normal")):
        have = keys[:, col] >= 0
        if have.any() and not have.all():
            bad = int(np.argmin(have))
            raise InputError(f"face corner without a {name} while other corners have one",
                             path=path, line=corner_lines[bad], field="f")
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    verts = np.asarray(positions, dtype=np.float64).reshape(-1, 3)[uniq[:, 0]]
    tris = inv.reshape(-1, 3)
    n = None
    if uniq[0, 2] >= 0:
        n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)[uniq[:, 2]]
        length = np.linalg.norm(n, axis=1, keepdims=True)
        n = n / np.where(length > 0, length, 1.0)
    uv = None
    if uniq[0, 1] >= 0:
        uv = np.asarray(uvs, dtype=np.float64).reshape(-1, 2)[uniq[:, 1]]
    if not np.all(np.isfinite(verts)):
        raise InputError("non-finite vertex position", path=path, field="v")
    return Mesh(verts, tris, n, uv)


def load_obj(path: str | os.PathLike[str]) -> Mesh:
    """Load a Wavefront OBJ: ``v`` (x y z [w]), ``vt`` (u [v]), ``vn``, ``f`` (``v``, ``v/vt``,
    ``v//vn``, ``v/vt/vn``; negative indices relative to the end). Polygons are triangulated as
    fans from their first corner. Other statements (o, g, s, usemtl, mtllib, l, p) are ignored
    here (the names of o, g and usemtl label the faces: :func:`face_labels`).
    Vertices are split where a position is used with different uvs/normals.

    Raises:
        InputError: naming the file, line and statement for malformed lines or bad indices.
    """
    return _read_obj(path)[0]


def _read_obj(path: str | os.PathLike[str]) -> tuple[Mesh, dict[str, np.ndarray]]:
    """:func:`load_obj`'s mesh and its face labels (name → (T,) bool over its triangles)."""
    positions: list[float] = []
    normals: list[float] = []
    uvs: list[float] = []
    corners: list[tuple[int, int, int]] = []
    corner_lines: list[int] = []
    # the names in force (g's names, o's, usemtl's), and each triangle's set of them
    groups: tuple[str, ...] = ()
    obj_name: tuple[str, ...] = ()
    material: tuple[str, ...] = ()
    states: dict[frozenset[str], int] = {}
    tri_state: list[int] = []
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", path=path) from None
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        tok = line.split()
        kind = tok[0]
        if kind in ("v", "vn", "vt"):
            want = {"v": (3, 4), "vn": (3, 3), "vt": (1, 3)}[kind]
            if not want[0] <= len(tok) - 1 <= want[1] and not (kind == "v" and len(tok) == 7):
                raise InputError(f"expected {want[0]} numbers, got {len(tok) - 1}", path=path,
                                 line=lineno, field=kind)
            try:
                vals = [float(x) for x in tok[1:]]
            except ValueError:
                raise InputError(f"not a number in {line!r}", path=path, line=lineno,
                                 field=kind) from None
            if not all(math.isfinite(x) for x in vals):
                raise InputError(f"non-finite value in {line!r}", path=path, line=lineno,
                                 field=kind)
            if kind == "v":
                w = vals[3] if len(vals) == 4 else 1.0
                if len(vals) == 4 and w == 0:
                    raise InputError("w = 0", path=path, line=lineno, field=kind)
                positions.extend(x / w for x in vals[:3])
            elif kind == "vn":
                normals.extend(vals)
            else:
                uvs.extend((vals + [0.0])[:2])
        elif kind == "f":
            if len(tok) < 4:
                raise InputError(f"a face needs at least 3 corners, got {len(tok) - 1}",
                                 path=path, line=lineno, field="f")
            face = []
            for c in tok[1:]:
                parts = c.split("/")
                if len(parts) > 3 or parts[0] == "":
                    raise InputError(f"malformed corner {c!r}", path=path, line=lineno,
                                     field="f")
                idx = []
                for k, (p, count) in enumerate(zip(
                        parts + [""] * (3 - len(parts)),
                        (len(positions) // 3, len(uvs) // 2, len(normals) // 3), strict=True)):
                    if p == "":
                        idx.append(-1)
                        continue
                    try:
                        i = int(p)
                    except ValueError:
                        raise InputError(f"malformed index {p!r} in corner {c!r}", path=path,
                                         line=lineno, field="f") from None
                    i = i - 1 if i > 0 else count + i
                    if not 0 <= i < count:
                        what = ("v", "vt", "vn")[k]
                        raise InputError(f"{what} index {p} out of range (1..{count})",
                                         path=path, line=lineno, field="f")
                    idx.append(i)
                face.append(tuple(idx))
            state = states.setdefault(frozenset(groups + obj_name + material), len(states))
            for k in range(1, len(face) - 1):
                corners.extend((face[0], face[k], face[k + 1]))
                corner_lines.extend((lineno,) * 3)
                tri_state.append(state)
        elif kind == "g":
            groups = tuple(tok[1:])
        elif kind == "o":
            obj_name = tuple(tok[1:2])
        elif kind == "usemtl":
            material = tuple(tok[1:2])
        elif kind in ("s", "mtllib", "l", "p", "vp", "cstype"):
            continue
        else:
            raise InputError(f"unknown statement {kind!r}", path=path, line=lineno, field=kind)
    mesh = _finish(path, positions, corners, normals, uvs, corner_lines)
    code = np.asarray(tri_state, np.int64)
    labels: dict[str, np.ndarray] = {}
    for names, k in states.items():
        for name in names:
            labels[name] = labels.get(name, np.zeros(code.shape, bool)) | (code == k)
    return mesh, labels


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_UV_NAMES = (("u", "v"), ("s", "t"), ("texture_u", "texture_v"), ("texture_s", "texture_t"))


def load_ply(path: str | os.PathLike[str]) -> Mesh:
    """Load a PLY mesh (``ascii 1.0``, ``binary_little_endian 1.0`` or ``binary_big_endian``):
    element ``vertex`` with x, y, z and optionally nx, ny, nz and u, v (or s, t / texture_u,
    texture_v); element ``face`` with a list property ``vertex_indices`` (or ``vertex_index``).
    Polygons are triangulated as fans. Other elements and properties are skipped here (the
    face's scalar properties label the faces: :func:`face_labels`).

    Raises:
        InputError: naming the file and the header line or element/field at fault.
    """
    return _read_ply(path)[0]


def _read_ply(path: str | os.PathLike[str]) -> tuple[Mesh, dict[str, np.ndarray]]:
    """:func:`load_ply`'s mesh and the face element's scalar properties, one value per
    triangle (property name → (T,) array)."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", path=path) from None
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise InputError("not a PLY file (missing 'ply' magic or 'end_header')", path=path,
                         line=1)
    nl = data.find(b"\n", end)
    body = data[nl + 1:] if nl >= 0 else b""
    header = data[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[dict] = []
    for lineno, line in enumerate(header, 1):
        tok = line.split()
        if not tok or tok[0] in ("ply", "comment", "obj_info"):
            continue
        if tok[0] == "format":
            if len(tok) != 3 or tok[1] not in ("ascii", "binary_little_endian",
                                               "binary_big_endian"):
                raise InputError(f"unsupported format {' '.join(tok[1:])!r}", path=path,
                                 line=lineno, field="format")
            fmt = tok[1]
        elif tok[0] == "element":
            if len(tok) != 3 or not re.fullmatch(r"\d+", tok[2]):
                raise InputError(f"malformed element line {line!r}", path=path, line=lineno,
                                 field="element")
            elements.append({"name": tok[1], "count": int(tok[2]), "props": [],
                             "line": lineno})
        elif tok[0] == "property":
            if not elements:
                raise InputError("property before any element", path=path, line=lineno,
                                 field="property")
            if len(tok) == 5 and tok[1] == "list":
                if tok[2] not in _PLY_TYPES or tok[3] not in _PLY_TYPES:
                    raise InputError(f"unknown type in {line!r}", path=path, line=lineno,
                                     field="property")
                elements[-1]["props"].append((tok[4], _PLY_TYPES[tok[2]], _PLY_TYPES[tok[3]]))
            elif len(tok) == 3 and tok[1] in _PLY_TYPES:
                elements[-1]["props"].append((tok[2], _PLY_TYPES[tok[1]], None))
            else:
                raise InputError(f"malformed property line {line!r}", path=path, line=lineno,
                                 field="property")
        else:
            raise InputError(f"unknown header keyword {tok[0]!r}", path=path, line=lineno,
                             field="header")
    if fmt is None:
        raise InputError("missing format line", path=path, field="format")
    values: dict[str, dict[str, object]] = {}
    if fmt == "ascii":
        lines = body.decode("ascii", errors="replace").splitlines()
        pos = 0
        body_line0 = len(header) + 1
        for el in elements:
            rows = []
            for k in range(el["count"]):
                while pos < len(lines) and not lines[pos].strip():
                    pos += 1
                if pos >= len(lines):
                    raise InputError(f"file ends in element {el['name']!r} {k}", path=path,
                                     line=body_line0 + pos + 1, field=el["name"])
                tok = lines[pos].split()
                lno = body_line0 + pos + 1
                pos += 1
                row: list = []
                i = 0
                try:
                    for _name, t, item in el["props"]:
                        if item is None:
                            row.append(float(tok[i]) if t[0] == "f" else int(tok[i]))
                            i += 1
                        else:
                            n = int(tok[i])
                            row.append([int(x) if item[0] != "f" else float(x)
                                        for x in tok[i + 1:i + 1 + n]])
                            if len(row[-1]) != n:
                                raise IndexError
                            i += 1 + n
                except (ValueError, IndexError):
                    raise InputError(f"malformed {el['name']} {k}: {lines[pos - 1]!r}",
                                     path=path, line=lno, field=el["name"]) from None
                if i != len(tok):
                    raise InputError(f"{len(tok) - i} extra value(s) in {el['name']} {k}",
                                     path=path, line=lno, field=el["name"])
                rows.append(row)
            values[el["name"]] = {p[0]: [r[j] for r in rows] for j, p in enumerate(el["props"])}
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        off = 0
        for el in elements:
            props = el["props"]
            if all(item is None for _, _, item in props):
                dt = np.dtype([(name, order + t) for name, t, _ in props])
                nbytes = dt.itemsize * el["count"]
                if off + nbytes > len(body):
                    raise InputError(f"file ends inside element {el['name']!r}", path=path,
                                     field=el["name"])
                arr = np.frombuffer(body, dtype=dt, count=el["count"], offset=off)
                off += nbytes
                values[el["name"]] = {name: arr[name] for name, _, _ in props}
                continue
            cols: dict[str, list] = {name: [] for name, _, _ in props}
            for k in range(el["count"]):
                for name, t, item in props:
                    ct = np.dtype(order + t)
                    if off + ct.itemsize > len(body):
                        raise InputError(f"file ends inside {el['name']} {k}", path=path,
                                         field=f"{el['name']}.{name}")
                    v = np.frombuffer(body, ct, 1, off)[0]
                    off += ct.itemsize
                    if item is not None:
                        it = np.dtype(order + item)
                        n = int(v)
                        if off + n * it.itemsize > len(body):
                            raise InputError(f"file ends inside {el['name']} {k}", path=path,
                                             field=f"{el['name']}.{name}")
                        v = np.frombuffer(body, it, n, off)
                        off += n * it.itemsize
                    cols[name].append(v)
            values[el["name"]] = cols
    if "vertex" not in values:
        raise InputError("no 'vertex' element", path=path, field="vertex")
    vtx = values["vertex"]
    for c in ("x", "y", "z"):
        if c not in vtx:
            raise InputError(f"vertex element lacks property {c!r}", path=path,
                             field=f"vertex.{c}")
    positions = np.stack([np.asarray(vtx[c], dtype=np.float64) for c in "xyz"], -1)
    if not np.all(np.isfinite(positions)):
        bad = int(np.argmin(np.all(np.isfinite(positions), axis=1)))
        raise InputError(f"non-finite position in vertex {bad}", path=path, field="vertex.x")
    normals = None
    if all(c in vtx for c in ("nx", "ny", "nz")):
        normals = np.stack([np.asarray(vtx[c], dtype=np.float64) for c in ("nx", "ny", "nz")],
                           -1)
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = normals / np.where(length > 0, length, 1.0)
    uv = None
    for a, b in _UV_NAMES:
        if a in vtx and b in vtx:
            uv = np.stack([np.asarray(vtx[a], np.float64), np.asarray(vtx[b], np.float64)], -1)
            break
    face = values.get("face")
    if face is None:
        raise InputError("no 'face' element", path=path, field="face")
    key = "vertex_indices" if "vertex_indices" in face else "vertex_index"
    if key not in face:
        raise InputError("face element lacks a 'vertex_indices' list", path=path,
                         field="face.vertex_indices")
    tris = []
    tri_face: list[int] = []
    nv = len(positions)
    for k, poly in enumerate(face[key]):
        poly = np.asarray(poly, dtype=np.int64)
        if poly.ndim != 1 or len(poly) < 3:
            raise InputError(f"face {k} has {poly.size} vertices (need >= 3)", path=path,
                             field="face.vertex_indices")
        if poly.min() < 0 or poly.max() >= nv:
            raise InputError(f"face {k} index out of range [0, {nv})", path=path,
                             field="face.vertex_indices")
        for i in range(1, len(poly) - 1):
            tris.append((poly[0], poly[i], poly[i + 1]))
            tri_face.append(k)
    if not tris:
        raise InputError("no faces", path=path, field="face")
    scalars = {name: np.asarray(face[name])[np.asarray(tri_face)]
               for name, _t, item in next(e for e in elements if e["name"] == "face")["props"]
               if item is None}
    return Mesh(positions, np.asarray(tris, dtype=np.int64), normals, uv), scalars


#: the PLY face properties that name a face's part, tried in this order
PLY_PART_PROPERTIES = ("material_index", "material", "part", "label", "segment", "group")


def face_labels(path: str | os.PathLike[str], *,
                ply_property: str | None = None) -> dict[str, np.ndarray]:
    """The named sets of faces of a mesh file, for objects made of parts with a material each.

    OBJ: every name of ``g`` (a face belongs to each group in force), ``o`` and ``usemtl``
    labels the faces that follow it. PLY: the values of an integer property of the ``face``
    element, as decimal strings (``ply_property``, default the first present of
    :data:`PLY_PART_PROPERTIES`).

    Returns:
        name → ``(T,)`` bool mask over the triangles of :func:`load_mesh` of the same file
        (polygons triangulated as there); empty when the file names no sets.

    Raises:
        InputError: the file is malformed, or ``ply_property`` is not an integer property of
            its faces (naming the file and ``face.<property>``).
    """
    return load_labelled_mesh(path, ply_property=ply_property)[1]


def load_labelled_mesh(path: str | os.PathLike[str], *, ply_property: str | None = None
                       ) -> tuple[Mesh, dict[str, np.ndarray]]:
    """:func:`load_mesh` and :func:`face_labels` of one file, read once."""
    suffix = Path(path).suffix.lower()
    if suffix == ".obj":
        return _read_obj(path)
    if suffix != ".ply":
        raise InputError(f"unknown mesh format {suffix!r} (.obj, .ply)", path=path)
    mesh, scalars = _read_ply(path)
    if ply_property is None:
        ply_property = next((n for n in PLY_PART_PROPERTIES if n in scalars), None)
        if ply_property is None:
            return mesh, {}
    values = scalars.get(ply_property)
    if values is None:
        raise InputError(f"the faces have no scalar property {ply_property!r} (they have "
                         f"{sorted(scalars)})", path=path, field=f"face.{ply_property}")
    values = np.asarray(values)
    if not (np.issubdtype(values.dtype, np.integer)
            or (np.issubdtype(values.dtype, np.floating) and np.all(values == np.round(values)))):
        raise InputError(f"face property {ply_property!r} must hold integers", path=path,
                         field=f"face.{ply_property}")
    values = values.astype(np.int64)
    return mesh, {str(v): values == v for v in np.unique(values)}


def select_faces(mesh: Mesh, mask: np.ndarray) -> Mesh:
    """The triangles of ``mesh`` where ``mask`` ((T,) bool) holds, with the vertices they use
    (positions, normals and uvs unchanged, so a part's shading matches the whole's).

    Raises:
        InputError: ``mask`` has the wrong shape or selects no triangle."""
    mask = np.asarray(mask, bool)
    if mask.shape != (mesh.num_triangles,):
        raise InputError(f"expected shape ({mesh.num_triangles},), got {mask.shape}",
                         field="mask")
    if not mask.any():
        raise InputError("selects no triangle", field="mask")
    tris = mesh.triangles[mask]
    used, inv = np.unique(tris, return_inverse=True)
    return Mesh(mesh.vertices[used], inv.reshape(tris.shape), mesh.normals[used],
                None if mesh.uvs is None else mesh.uvs[used])


# ----------------------------------------------------------------------------- model matrices


def translate(t) -> np.ndarray:
    """4×4 translation by ``t`` (3,) (m)."""
    m = np.eye(4)
    m[:3, 3] = np.asarray(t, dtype=np.float64)
    return m


def scale(s) -> np.ndarray:
    """4×4 scale by a scalar or per-axis ``(3,)`` factors."""
    s = np.broadcast_to(np.asarray(s, dtype=np.float64), (3,))
    return np.diag([*s, 1.0])


def rotate(axis, angle_rad: float) -> np.ndarray:
    """4×4 right-handed rotation by ``angle_rad`` about ``axis`` (3,) (Rodrigues' formula)."""
    a = np.asarray(axis, dtype=np.float64)
    n = np.linalg.norm(a)
    if not n > 0:
        raise InputError("rotation axis has zero length", field="axis")
    x, y, z = a / n
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    k = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    m = np.eye(4)
    m[:3, :3] = np.eye(3) + s * k + (1 - c) * (k @ k)
    return m


def rotate_x(angle_rad: float) -> np.ndarray:
    return rotate((1.0, 0.0, 0.0), angle_rad)


def rotate_y(angle_rad: float) -> np.ndarray:
    return rotate((0.0, 1.0, 0.0), angle_rad)


def rotate_z(angle_rad: float) -> np.ndarray:
    return rotate((0.0, 0.0, 1.0), angle_rad)


def transform_points(matrix, points) -> np.ndarray:
    """``(matrix @ [p, 1])[:3] / w`` for points ``(..., 3)``."""
    m = np.asarray(matrix, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64)
    h = p @ m[:3, :3].T + m[:3, 3]
    w = p @ m[3, :3] + m[3, 3]
    return h / w[..., None]


def transform_normals(matrix, normals) -> np.ndarray:
    """Normals ``(..., 3)`` through the inverse transpose of the upper 3×3, renormalised."""
    m = np.linalg.inv(np.asarray(matrix, dtype=np.float64)[:3, :3]).T
    n = np.asarray(normals, dtype=np.float64) @ m.T
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    return n / np.where(length > 0, length, 1.0)
