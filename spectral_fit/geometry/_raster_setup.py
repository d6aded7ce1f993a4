"""The rasteriser's triangles in pixel space: homogeneous pixel coordinates of clip points, the
per-triangle setup rows (canonical edge functions, inside signs and tie rule, anchored NDC depth
planes, conservative pixel-centre boxes), coverage and depth at pixel centres, and
differentiable perspective-correct barycentrics.

Conventions (docs/conventions.md, 'Conventions'): OpenGL clip space, pixel centres at integer + 0.5,
NDC (x, y) maps to pixel coordinates ((x + 1)/2·W, (1 − y)/2·H), row 0 at the top; homogeneous
pixel coordinates are (X, Y, w) with X/w, Y/w the pixel coordinates. Float32 throughout. The
coverage rule and watertightness argument are in :mod:`spectral_fit.geometry._raster`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._runtime.backend import materialise, on_accelerator

__all__ = ["clip_to_pixel"]


def clip_to_pixel(clip: jax.Array, shape: tuple[int, int]) -> jax.Array:
    """Homogeneous pixel coordinates ``(..., 3)`` = (X, Y, w) of clip points ``(..., 4)``:
    X/w, Y/w are the pixel coordinates of our convention ((x/w + 1)/2·W, (1 − y/w)/2·H)."""
    h, w = shape
    x, y, ww = clip[..., 0], clip[..., 1], clip[..., 3]
    return jnp.stack([(x + ww) * (0.5 * w), (ww - y) * (0.5 * h), ww], axis=-1)


def _lex_less(a, b):
    """a < b lexicographically for component tuples a = (a0, a1, a2), b likewise."""
    return (a[0] < b[0]) | ((a[0] == b[0]) & ((a[1] < b[1]) | ((a[1] == b[1]) & (a[2] < b[2]))))


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _edge_setup(hv):
    """Canonical edge functions of triangles with homogeneous pixel vertices ``hv``: a list of 3
    corners, each a tuple (X, Y, w) of arrays.

    Returns ``n`` (3 edges × 3 components; edge i is opposite corner i, its edge function at
    pixel p is ``o_i · n_i · (px, py, 1)``), ``o`` (3 arrays of ±1) and the edges' vertices in
    canonical order (3 × (lo, hi), each a tuple (X, Y, w)).
    """
    ns, os_, ends = [], [], []
    for i in range(3):
        a, b = hv[(i + 1) % 3], hv[(i + 2) % 3]
        swap = _lex_less(b, a)
        lo = tuple(jnp.where(swap, bb, aa) for aa, bb in zip(a, b, strict=True))
        hi = tuple(jnp.where(swap, aa, bb) for aa, bb in zip(a, b, strict=True))
        ns.append(_cross(lo, hi))
        os_.append(jnp.where(swap, -1.0, 1.0).astype(a[0].dtype))
        ends.append((lo, hi))
    return ns, os_, ends


# columns of the per-triangle data rows (float32)
_C_EDGE = 0  # 3 edges × (X, Y, w of the canonical first vertex, then of the second)
_C_SIGN = 18  # 3 inside signs σ_i (inside: σ_i·e_i > 0)
_C_TIE = 21  # 3 values σ_i·(tie direction): the verdict where e_i == 0 exactly
_C_DEPTH = 24  # NDC depth plane (a, b, d_a, pxa, pya): z/w = d_a + a(px − pxa) + b(py − pya)
_C_VALID = 29  # 1 / 0
_C_BOX = 30  # pixel-centre index box x0, y0, nx, ny
_NCOL = 34


def _triangle_setup(clip, triangles, shape, cull):
    """Per-triangle data packed in one float32 array (T, _NCOL), computed component-wise
    (columns: see the ``_C_*`` constants)."""
    h, w = shape
    comp = [clip[:, j] for j in range(4)]
    corners = [[comp[j][triangles[:, k]] for j in range(4)] for k in range(3)]
    hv = [((c[0] + c[3]) * (0.5 * w), (c[3] - c[1]) * (0.5 * h), c[3]) for c in corners]
    # Dividing by a runtime 1.0 materialises a value: XLA:CPU does not duplicate an
    # "expensive" op (a divide) into several consumers, whereas it recomputes chains of cheap
    # ops inside every consumer kernel (the setup would run several times slower).
    one = jnp.where(clip[0, 3] == clip[0, 3], jnp.float32(1.0), jnp.float32(2.0))
    n, o, ends = _edge_setup(hv)
    # det = det[hv0; hv1; hv2], evaluated with the origin moved to the projection of the
    # corner with the largest w (a column operation: same value, no large cancelling terms).
    # Its sign decides which side of the edges is inside (and that the point seen is in
    # front of the eye), so it must be right even for edge-on slivers at a silhouette.
    wmax = jnp.maximum(jnp.maximum(corners[0][3], corners[1][3]), corners[2][3])
    anchor = [corners[k][3] == wmax for k in range(3)]
    xa = jnp.where(anchor[0], hv[0][0], jnp.where(anchor[1], hv[1][0], hv[2][0]))
    ya = jnp.where(anchor[0], hv[0][1], jnp.where(anchor[1], hv[1][1], hv[2][1]))
    inv_wa = 1.0 / jnp.where(wmax > 0, wmax, 1.0)
    pxa = jnp.where(wmax > 0, xa * inv_wa, 0.0) / one
    pya = jnp.where(wmax > 0, ya * inv_wa, 0.0) / one
    rel = [(v[0] - pxa * v[2], v[1] - pya * v[2], v[2]) for v in hv]
    c12 = _cross(rel[1], rel[2])
    det = (rel[0][0] * c12[0] + rel[0][1] * c12[1] + rel[0][2] * c12[2]) / one
    # In pixel coordinates y points down, so a front face (counter-clockwise in NDC) has det < 0.
    valid = jnp.isfinite(det) & (det != 0)
    if cull == "back":
        valid &= det < 0
    elif cull == "front":
        valid &= det > 0
    s = jnp.sign(det)
    inv_det = 1.0 / jnp.where(valid, det, 1.0)
    z = [c[2] for c in corners]
    # NDC depth z/w is affine in pixel coordinates: z/w = d_a + a·(px − pxa) + b·(py − pya),
    # anchored at the projection of the corner with the largest w (exact to rounding there);
    # the gradient comes from edge normals of the anchored coordinates (little cancellation)
    # and only acts over the distance to the anchor (a plane stored as a·px + b·py + c loses
    # ~1e−5 for edge-on triangles far from the frame's origin).
    cr = [_cross(rel[(i + 1) % 3], rel[(i + 2) % 3]) for i in range(3)]
    zc = [sum(z[i] * cr[i][k] for i in range(3)) * inv_det for k in range(2)]
    # The constant term of the depth plane from the homogeneous formula cancels badly (its
    # terms are ~X·Y of the pixel coordinates; errors ~1e-4 in NDC depth for small, distant
    # triangles). Anchor the plane at the corner with the largest w instead: z/w there is
    # exact to rounding, and the gradient's error only acts over the triangle's extent.
    za = jnp.where(anchor[0], z[0], jnp.where(anchor[1], z[1], z[2]))
    zc += [jnp.where(wmax > 0, za * inv_wa, sum(z[i] * cr[i][2] for i in range(3)) * inv_det),
           pxa, pya]
    sigma = [o[i] * s for i in range(3)]
    # tie rule: a centre exactly on an edge goes to the side the edge function takes at the
    # centre moved by +ε in x (then +ε² in y); n_i[0], n_i[1] are its x and y derivatives
    tie = [jnp.sign(sigma[i] * jnp.where(n[i][0] != 0, n[i][0], n[i][1])) for i in range(3)]
    comps = [c for lo, hi in ends for c in (*lo, *hi)] + sigma + tie + zc

    # conservative box: the polygon clipped to z >= -w
    d = [c[2] + c[3] for c in corners]
    pts, ok = [], []
    for i in range(3):
        j = (i + 1) % 3
        pts.append(hv[i])
        ok.append(d[i] >= 0)
        den = d[i] - d[j]
        t = d[i] / jnp.where(den != 0, den, 1.0)
        pts.append(tuple(hv[i][k] + t * (hv[j][k] - hv[i][k]) for k in range(3)))
        ok.append((d[i] * d[j]) < 0)
    big = jnp.float32(1e9)
    xmin = ymin = big
    xmax = ymax = -big
    bad_w = jnp.zeros_like(valid)
    any_ok = jnp.zeros_like(valid)
    for (px_, py_, pw), k in zip(pts, ok, strict=True):
        front = pw > 0
        bad_w |= k & ~front
        any_ok |= k
        inv = 1.0 / jnp.where(k & front, pw, 1.0)
        x, y = px_ * inv, py_ * inv
        xmin = jnp.minimum(xmin, jnp.where(k, x, big))
        xmax = jnp.maximum(xmax, jnp.where(k, x, -big))
        ymin = jnp.minimum(ymin, jnp.where(k, y, big))
        ymax = jnp.maximum(ymax, jnp.where(k, y, -big))
    xmin, xmax, ymin, ymax = (v / one for v in (xmin, xmax, ymin, ymax))
    full = bad_w | ~(jnp.isfinite(xmin) & jnp.isfinite(xmax) & jnp.isfinite(ymin)
                     & jnp.isfinite(ymax))
    xmin = jnp.where(full, 0.0, xmin)
    ymin = jnp.where(full, 0.0, ymin)
    xmax = jnp.where(full, w, xmax)
    ymax = jnp.where(full, h, ymax)
    valid &= any_ok
    # pixel-centre index ranges with a margin against rounding of the box
    mx = 1.0 / 64 + 1e-6 * jnp.maximum(jnp.abs(xmin), jnp.abs(xmax))
    my = 1.0 / 64 + 1e-6 * jnp.maximum(jnp.abs(ymin), jnp.abs(ymax))
    lim = jnp.float32(1 << 15)
    x0 = jnp.ceil(jnp.clip(xmin - 0.5 - mx, -1.0, lim)).astype(jnp.int32)
    x1 = jnp.floor(jnp.clip(xmax - 0.5 + mx, -2.0, lim)).astype(jnp.int32)
    y0 = jnp.ceil(jnp.clip(ymin - 0.5 - my, -1.0, lim)).astype(jnp.int32)
    y1 = jnp.floor(jnp.clip(ymax - 0.5 + my, -2.0, lim)).astype(jnp.int32)
    x0, y0 = jnp.maximum(x0, 0), jnp.maximum(y0, 0)
    x1, y1 = jnp.minimum(x1, w - 1), jnp.minimum(y1, h - 1)
    nx, ny = x1 - x0 + 1, y1 - y0 + 1
    valid &= (nx > 0) & (ny > 0)
    f32 = jnp.float32
    cols = comps + [valid.astype(f32), x0.astype(f32), y0.astype(f32), nx.astype(f32),
                    ny.astype(f32)]
    if on_accelerator():
        # the columns computed together, one thread per triangle: the GPU fused the whole
        # setup into the stack, each thread computing one (triangle, column) element, so the
        # 34 columns' shared work (corners, determinant, clipped box) ran in every column
        # and neighbouring threads took different branches
        cols = list(jax.lax.optimization_barrier(tuple(cols)))
    data = jnp.stack(cols, axis=1)
    # materialised once, instead of recomputed per gathered window (a divide by the runtime
    # 1.0 here would cost one more pass over the rows)
    return materialise(data)


def _plane(zp, px, py):
    """NDC depth at pixel coordinates from the anchored plane (a, b, d_a, pxa, pya)."""
    return zp[..., 2] + zp[..., 0] * (px - zp[..., 3]) + zp[..., 1] * (py - zp[..., 4])


def _cover(rows, px, py):
    """Coverage and depth of pixel centres (px, py) (..., S, S) for triangle rows (..., _NCOL).

    Edge functions are evaluated relative to the pixel, e = (X_lo − px·w_lo)(Y_hi − py·w_hi)
    − (Y_lo − py·w_lo)(X_hi − px·w_hi), from the edge's two vertices in canonical order: the
    two triangles sharing an edge run the identical float operations on identical operands
    (so they see bit-identical values, whatever FMA contraction the compiler applies), and
    no large terms cancel (the error is ~1e−7 of the pixel's distance to the vertices)."""
    r = rows[..., None, None, :]
    inside = None
    for i in range(3):
        c = _C_EDGE + 6 * i
        xl = r[..., c] - px * r[..., c + 2]
        yl = r[..., c + 1] - py * r[..., c + 2]
        xh = r[..., c + 3] - px * r[..., c + 5]
        yh = r[..., c + 4] - py * r[..., c + 5]
        e = xl * yh - yl * xh
        ins = jnp.where(e != 0, r[..., _C_SIGN + i] * e, r[..., _C_TIE + i]) > 0
        inside = ins if inside is None else inside & ins
    depth = _plane(r[..., _C_DEPTH:_C_DEPTH + 5], px, py)
    inside = inside & (depth >= -1.0) & (depth <= 1.0)
    return inside, depth


def _bary_at(clip, triangles, tri_id, px, py, shape):
    """Differentiable perspective-correct barycentrics (N, 3) of triangles ``tri_id (N,)``
    (−1 allowed: zeros) at pixel coordinates (px, py) (N,)."""
    hit = tri_id >= 0
    idx = triangles[jnp.where(hit, tri_id, 0)]  # (N, 3)
    hv = clip_to_pixel(clip[idx], shape)  # (N, 3, 3)
    # edge functions with the pixel moved to the origin (X − px·w, Y − py·w): no large
    # cancelling terms, so the barycentrics keep float32 precision on small triangles
    rx = hv[..., 0] - px[:, None] * hv[..., 2]
    ry = hv[..., 1] - py[:, None] * hv[..., 2]
    gam = jnp.stack([rx[:, (i + 1) % 3] * ry[:, (i + 2) % 3]
                     - ry[:, (i + 1) % 3] * rx[:, (i + 2) % 3] for i in range(3)], -1)
    tot = jnp.sum(gam, -1)
    tot = jnp.where(hit & (tot != 0), tot, 1.0)
    return jnp.where(hit[:, None], gam / tot[:, None], 0.0), idx
