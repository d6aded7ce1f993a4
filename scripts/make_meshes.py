"""Write the bundled non-convex test meshes (binary PLY, metres, per-vertex normals) to
measurements/meshes/: a ring torus, a thick-walled cup and boxes (a slab and a cube), all closed
and wound outward.

    python scripts/make_meshes.py [--out measurements/meshes]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def torus(big: float = 0.035, small: float = 0.014, nu: int = 72, nv: int = 36):
    """A ring torus about the y axis (tube radius ``small`` about a circle of radius ``big``)."""
    u = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    v = np.linspace(0, 2 * np.pi, nv, endpoint=False)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    nrm = np.stack([np.cos(vv) * np.cos(uu), np.sin(vv), np.cos(vv) * np.sin(uu)], -1)
    ring = np.stack([np.cos(uu), np.zeros_like(uu), np.sin(uu)], -1)
    pts = (big * ring + small * nrm).reshape(-1, 3)
    tris = []
    for i in range(nu):
        for j in range(nv):
            a, b = i * nv + j, ((i + 1) % nu) * nv + j
            c, d = ((i + 1) % nu) * nv + (j + 1) % nv, i * nv + (j + 1) % nv
            tris += [[a, c, b], [a, d, c]]
    return pts, np.asarray(tris), nrm.reshape(-1, 3)


def cup(outer: float = 0.03, wall: float = 0.004, height: float = 0.07, base: float = 0.006,
        lip: float = 0.002, slices: int = 72, per_segment: int = 6, glaze: bool = False):
    """A cup revolved about the y axis from its profile (outer base, outer wall, rounded lip,
    inner wall, inner floor): smooth normals within each part of the profile, split at its
    corners; the base at y = 0. ``glaze``: also each triangle's material index (1 inside:
    inner wall and floor; 0 elsewhere)."""
    inner = outer - wall
    rl = 0.5 * wall  # lip radius
    prof: list[tuple[np.ndarray, np.ndarray]] = []  # (points (n, 2) of (r, y), normals (n, 2))

    def seg(p0, p1, n):
        t = np.linspace(0.0, 1.0, per_segment + 1)[:, None]
        pts = (1 - t) * np.asarray(p0) + t * np.asarray(p1)
        prof.append((pts, np.repeat(np.asarray(n, float)[None], len(pts), axis=0)))

    seg((0.0, 0.0), (outer - lip, 0.0), (0.0, -1.0))  # outer base
    a = np.linspace(-0.5 * np.pi, 0.0, per_segment + 1)  # rounded outer foot
    prof.append((np.stack([outer - lip + lip * np.cos(a), lip + lip * np.sin(a)], -1),
                 np.stack([np.cos(a), np.sin(a)], -1)))
    seg((outer, lip), (outer, height - rl), (1.0, 0.0))  # outer wall
    a = np.linspace(0.0, np.pi, 2 * per_segment + 1)  # lip
    c = (inner + rl, height - rl)
    prof.append((np.stack([c[0] + rl * np.cos(a), c[1] + rl * np.sin(a)], -1),
                 np.stack([np.cos(a), np.sin(a)], -1)))
    seg((inner, height - rl), (inner, base), (-1.0, 0.0))  # inner wall
    seg((inner, base), (0.0, base), (0.0, 1.0))  # inner floor
    phi = np.linspace(0, 2 * np.pi, slices, endpoint=False)
    pts, nrms, tris, segment = [], [], [], []
    base_index = 0
    for s, (p, n) in enumerate(prof):
        m = len(p)
        for k in range(slices):
            cph, sph = np.cos(phi[k]), np.sin(phi[k])
            pts.append(np.stack([p[:, 0] * cph, p[:, 1], p[:, 0] * sph], -1))
            nrms.append(np.stack([n[:, 0] * cph, n[:, 1], n[:, 0] * sph], -1))
        for k in range(slices):
            k2 = (k + 1) % slices
            for i in range(m - 1):
                a0, a1 = base_index + k * m + i, base_index + k * m + i + 1
                b0, b1 = base_index + k2 * m + i, base_index + k2 * m + i + 1
                tris += [[a0, a1, b1], [a0, b1, b0]]
                segment += [s, s]
        base_index += m * slices
    pts = np.concatenate(pts)
    nrms = np.concatenate(nrms)
    nrms /= np.maximum(np.linalg.norm(nrms, axis=1, keepdims=True), 1e-12)
    tris = np.asarray(tris)
    # wound with the normals (outward), degenerate triangles at the axis dropped
    e = np.cross(pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]])
    area = np.linalg.norm(e, axis=1)
    keep = area > 1e-14
    tris, e = tris[keep], e[keep]
    flip = np.sum(e * nrms[tris].sum(axis=1), axis=1) < 0
    tris[flip] = tris[flip][:, ::-1]
    if glaze:  # the inside (inner wall and floor: profile parts 4 and 5) a material of its own
        return pts, tris, nrms, (np.asarray(segment)[keep] >= 4).astype(np.uint8)
    return pts, tris, nrms


def box(size: tuple[float, float, float], segments: int = 8):
    """A closed box of edge lengths ``size`` (x, y, z, metres) centred on the origin, its faces
    flat (four vertices of its own per face grid point, the face's normal: sharp edges), each face
    a ``segments`` × ``segments`` grid of quads (so that per-vertex quantities can vary over it)."""
    half = 0.5 * np.asarray(size, np.float64)
    t = np.linspace(-1.0, 1.0, segments + 1)
    uu, vv = np.meshgrid(t, t, indexing="ij")
    pts, nrms, tris = [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n = np.zeros(3)
            n[axis] = sign
            a, b = (axis + 1) % 3, (axis + 2) % 3
            p = np.zeros((segments + 1, segments + 1, 3))
            p[..., axis] = sign * half[axis]
            p[..., a] = uu * half[a]
            p[..., b] = vv * half[b]
            base = sum(len(q) for q in pts)
            pts.append(p.reshape(-1, 3))
            nrms.append(np.repeat(n[None], p.shape[0] * p.shape[1], axis=0))
            for i in range(segments):
                for j in range(segments):
                    k00 = base + i * (segments + 1) + j
                    k10, k01, k11 = k00 + segments + 1, k00 + 1, k00 + segments + 2
                    tris += [[k00, k10, k11], [k00, k11, k01]]
    pts, nrms, tris = np.concatenate(pts), np.concatenate(nrms), np.asarray(tris)
    e = np.cross(pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]])
    flip = np.sum(e * nrms[tris[:, 0]], axis=1) < 0
    tris[flip] = tris[flip][:, ::-1]
    return pts, tris, nrms


def write_ply(path: Path, pts, tris, nrms, material_index=None, *, comment: str) -> None:
    """Binary little-endian PLY: float32 x y z nx ny nz per vertex, uint8-counted int32 faces
    (and a uchar material_index per face when given)."""
    extra = [] if material_index is None else ["property uchar material_index"]
    header = "\n".join([
        "ply", "format binary_little_endian 1.0", f"comment {comment}",
        f"element vertex {len(pts)}", "property float x", "property float y", "property float z",
        "property float nx", "property float ny", "property float nz",
        f"element face {len(tris)}", "property list uchar int vertex_indices", *extra,
        "end_header", ""])
    vert = np.concatenate([pts, nrms], axis=1).astype("<f4")
    face = np.zeros(len(tris), dtype=[("n", "u1"), ("i", "<i4", (3,))]
                    + ([("m", "u1")] if extra else []))
    face["n"] = 3
    face["i"] = tris
    if extra:
        face["m"] = material_index
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(header.encode("ascii") + vert.tobytes() + face.tobytes())
    tmp.replace(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "measurements" / "meshes")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    write_ply(args.out / "torus.ply", *torus(),
              comment="ring torus, radii 35 mm and 14 mm, 72 x 36 (scripts/make_meshes.py)")
    write_ply(args.out / "cup.ply", *cup(),
              comment="cup, 60 mm across, 70 mm high, 4 mm wall (scripts/make_meshes.py)")
    write_ply(args.out / "cup_glazed.ply", *cup(glaze=True),
              comment="cup, 60 mm across, 70 mm high, 4 mm wall; material_index 1 inside "
                      "(inner wall and floor) (scripts/make_meshes.py)")
    write_ply(args.out / "slab.ply", *box((0.07, 0.09, 0.012)),
              comment="slab, 70 x 90 x 12 mm, flat faces (scripts/make_meshes.py)")
    write_ply(args.out / "cube.ply", *box((0.03, 0.03, 0.03)),
              comment="cube, 30 mm, flat faces (scripts/make_meshes.py)")


if __name__ == "__main__":
    main()
