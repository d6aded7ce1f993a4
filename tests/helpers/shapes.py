"""Small triangle meshes with known geometry for the visibility and any-shape tests:
(vertices (V, 3), triangles (T, 3), normals (V, 3)) in metres, float64 / int64."""

from __future__ import annotations

import numpy as np


def _grid_triangles(nu: int, nv: int, wrap_u: bool, wrap_v: bool) -> np.ndarray:
    """Two triangles per cell of an nu × nv vertex grid (index u·nv + v), wrapping as asked."""
    tris = []
    cu = nu if wrap_u else nu - 1
    cv = nv if wrap_v else nv - 1
    for i in range(cu):
        for j in range(cv):
            a = i * nv + j
            b = ((i + 1) % nu) * nv + j
            c = ((i + 1) % nu) * nv + (j + 1) % nv
            d = i * nv + (j + 1) % nv
            tris += [[a, b, c], [a, c, d]]
    return np.asarray(tris, np.int64)


def torus(big: float = 0.05, small: float = 0.02, nu: int = 48, nv: int = 24):
    """A ring torus about the y axis (tube radius ``small`` about a circle of radius ``big``),
    wound outward: the bundled mesh's generator (scripts/make_meshes.py) at these sizes."""
    from . import load_script

    return load_script("make_meshes").torus(big, small, nu, nv)


def bowl(radius: float = 0.05, stacks: int = 24, slices: int = 48, *,
         port_deg: float = 90.0):
    """The inside of a sphere with a circular port (an integrating sphere): the sphere of
    ``radius`` about the origin less the cap of half-angle ``port_deg`` about +z (90: a
    hemispherical bowl open at z = 0), normals towards the centre; the bottom (−z) is one
    vertex. From any inside point the port's form factor is the cap's share of the sphere's
    area, (1 − cos port)/2."""
    top = np.pi - np.radians(port_deg)  # polar angle from the bottom where the port begins
    pts = [[0.0, 0.0, -radius]]
    for i in range(1, stacks + 1):
        th = top * i / stacks  # from the bottom
        for j in range(slices):
            ph = 2 * np.pi * j / slices
            pts.append([radius * np.sin(th) * np.cos(ph), radius * np.sin(th) * np.sin(ph),
                        -radius * np.cos(th)])
    pts = np.asarray(pts)
    tris = [[0, 1 + (j + 1) % slices, 1 + j] for j in range(slices)]
    for i in range(stacks - 1):
        for j in range(slices):
            a = 1 + i * slices + j
            b = 1 + i * slices + (j + 1) % slices
            c = b + slices
            d = a + slices
            tris += [[a, b, c], [a, c, d]]
    tris = np.asarray(tris, np.int64)[:, ::-1]  # wound towards the centre
    return pts, tris.copy(), -pts / radius


def box(half=(0.03, 0.03, 0.03), inward: bool = False, n: int = 4):
    """An axis-aligned box's six faces, each an n × n grid of its own vertices (flat normals),
    outward (or towards the inside with ``inward``)."""
    h = np.asarray(half, float)
    pts, tris, nrms = [], [], []
    g = np.linspace(-1.0, 1.0, n)
    for axis in range(3):
        for sign in (-1.0, 1.0):
            a1, a2 = [k for k in range(3) if k != axis]
            uu, vv = np.meshgrid(g, g, indexing="ij")
            p = np.zeros((n, n, 3))
            p[..., axis] = sign * h[axis]
            p[..., a1] = uu * h[a1]
            p[..., a2] = vv * h[a2]
            base = len(pts) and sum(len(x) for x in pts)
            t = _grid_triangles(n, n, False, False) + base
            nm = np.zeros(3)
            nm[axis] = -sign if inward else sign
            e1 = np.zeros(3)
            e1[a1] = 1.0
            e2 = np.zeros(3)
            e2[a2] = 1.0
            if np.dot(np.cross(e1, e2), nm) < 0:
                t = t[:, ::-1]
            pts.append(p.reshape(-1, 3))
            tris.append(t)
            nrms.append(np.repeat(nm[None], n * n, axis=0))
    return np.concatenate(pts), np.concatenate(tris), np.concatenate(nrms)


def uv_sphere(radius: float = 0.04, stacks: int = 16, slices: int = 32):
    """A closed UV sphere about the origin, outward normals."""
    th = np.linspace(0, np.pi, stacks + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, slices, endpoint=False)
    tt, pp = np.meshgrid(th, ph, indexing="ij")
    nrm = np.stack([np.sin(tt) * np.cos(pp), np.cos(tt), np.sin(tt) * np.sin(pp)], -1)
    nrm = np.concatenate([[[0, 1.0, 0]], nrm.reshape(-1, 3), [[0, -1.0, 0]]])
    s = slices
    tris = [[0, 1 + (j + 1) % s, 1 + j] for j in range(s)]
    tris += [[1 + i * s + j, 1 + i * s + (j + 1) % s, 1 + (i + 1) * s + (j + 1) % s]
             for i in range(stacks - 2) for j in range(s)]
    tris += [[1 + i * s + j, 1 + (i + 1) * s + (j + 1) % s, 1 + (i + 1) * s + j]
             for i in range(stacks - 2) for j in range(s)]
    last = len(nrm) - 1
    base = 1 + (stacks - 2) * s
    tris += [[last, base + j, base + (j + 1) % s] for j in range(s)]
    tris = np.asarray(tris, np.int64)
    a, b, c = (nrm[tris[:, i]] for i in range(3))
    flip = np.sum(np.cross(b - a, c - a) * (a + b + c), axis=1) < 0
    tris[flip] = tris[flip][:, ::-1]
    return radius * nrm, tris, nrm


def write_obj(path, vertices, triangles, normals) -> None:
    """A Wavefront OBJ with per-vertex normals (1-based indices)."""
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in vertices]
    lines += [f"vn {x:.9g} {y:.9g} {z:.9g}" for x, y, z in normals]
    lines += [f"f {a + 1}//{a + 1} {b + 1}//{b + 1} {c + 1}//{c + 1}" for a, b, c in triangles]
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def quad(origin, edge_a, edge_b, na: int, nb: int):
    """A flat rectangle origin + s·edge_a + t·edge_b (s, t in [0, 1]) as na × nb cells of two
    triangles, wound and normalled towards edge_a × edge_b."""
    origin, edge_a, edge_b = (np.asarray(x, np.float64) for x in (origin, edge_a, edge_b))
    a, b = np.meshgrid(np.linspace(0, 1, na + 1), np.linspace(0, 1, nb + 1), indexing="ij")
    v = origin + a.reshape(-1, 1) * edge_a + b.reshape(-1, 1) * edge_b
    i = np.arange(len(v)).reshape(na + 1, nb + 1)
    t = np.concatenate([np.stack([i[:-1, :-1], i[1:, :-1], i[1:, 1:]], -1).reshape(-1, 3),
                        np.stack([i[:-1, :-1], i[1:, 1:], i[:-1, 1:]], -1).reshape(-1, 3)])
    normal = np.cross(edge_a, edge_b)
    normal /= np.linalg.norm(normal)
    return v, t, np.broadcast_to(normal, v.shape).copy()
