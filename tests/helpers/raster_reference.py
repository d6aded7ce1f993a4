"""Independent float64 NumPy reference rasteriser for the tests (brute force, small frames).

Definition implemented: a pixel centre p = (x + 0.5, y + 0.5) is covered by triangle t when the
perspective-correct barycentrics of the point of t's plane seen through p are all positive and
its NDC depth z/w lies in [−1, 1]. Barycentrics come from a direct 3×3 solve in clip space
(x − u·w = 0, y − v·w = 0, Σβ = 1), not from edge functions. A centre exactly on an edge
(a barycentric that is 0 up to float64 rounding, |β| < 1e-11) is decided by moving the centre
by +ε in x (then +ε² in y).
The visible triangle has the smallest depth; ties go to the smaller id.
"""

from __future__ import annotations

import numpy as np


def reference_raster(clip, triangles, shape, cull="none"):
    """(tri_id (H, W) int, bary (H, W, 3), depth (H, W)) in float64."""
    h, w = shape
    clip = np.asarray(clip, dtype=np.float64)
    tris = np.asarray(triangles)
    ys, xs = np.mgrid[0:h, 0:w]
    px = (xs + 0.5).ravel()
    py = (ys + 0.5).ravel()
    # pixel centre in NDC
    u = 2 * px / w - 1
    v = 1 - 2 * py / h
    best = np.full(h * w, np.inf)
    best_id = np.full(h * w, -1)
    best_bary = np.zeros((h * w, 3))
    for t, (a, b, c) in enumerate(tris):
        cv = clip[[a, b, c]]  # (3, 4)
        # rows: Σβ(x − u w) = 0, Σβ(y − v w) = 0, Σβ = 1
        m = np.stack([cv[None, :, 0] - u[:, None] * cv[None, :, 3],
                      cv[None, :, 1] - v[:, None] * cv[None, :, 3],
                      np.ones((len(u), 3))], axis=1)  # (N, 3, 3)
        det = np.linalg.det(m)
        ok = np.abs(det) > 0
        beta = np.zeros((len(u), 3))
        rhs = np.array([0.0, 0.0, 1.0])
        beta[ok] = np.linalg.solve(m[ok], np.broadcast_to(rhs, (ok.sum(), 3))[..., None])[..., 0]
        # derivatives of β along +x (pixel units), then +y, for the tie rule (finite, exact
        # enough in float64 for the dyadic test inputs that produce exact zeros)
        keyed = beta.copy()
        for dx, dy in ((1e-7, 0.0), (0.0, 1e-7)):
            # a barycentric that is zero in exact arithmetic comes out of the float64 solve
            # as rounding noise (~1e-16); genuine values this small do not occur in the tests
            zero = np.abs(keyed) < 1e-11
            if not zero.any():
                break
            uu = 2 * (px + dx) / w - 1
            vv = 1 - 2 * (py + dy) / h
            m2 = np.stack([cv[None, :, 0] - uu[:, None] * cv[None, :, 3],
                           cv[None, :, 1] - vv[:, None] * cv[None, :, 3],
                           np.ones((len(u), 3))], axis=1)
            ok2 = np.abs(np.linalg.det(m2)) > 0
            b2 = np.zeros_like(beta)
            b2[ok2] = np.linalg.solve(m2[ok2], np.broadcast_to(rhs, (ok2.sum(), 3))[..., None])[
                ..., 0]
            keyed = np.where(zero, b2, keyed)
        inside = ok & np.all(keyed > 0, axis=1)
        pw = beta @ cv[:, 3]
        pz = beta @ cv[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = pz / pw
        inside &= (pw > 0) & (depth >= -1) & (depth <= 1)
        # facing: signed NDC area for triangles in front; in general the clip-space triple
        # product of (x, y, w) (positive = counter-clockwise = front)
        tri_det = np.linalg.det(cv[:, [0, 1, 3]])
        if cull == "back" and not tri_det > 0:
            continue
        if cull == "front" and not tri_det < 0:
            continue
        better = inside & ((depth < best) | ((depth == best) & (best_id > t)))
        best[better] = depth[better]
        best_id[better] = t
        best_bary[better] = beta[better]
    depth = np.where(best_id >= 0, best, 1.0)
    return best_id.reshape(h, w), best_bary.reshape(h, w, 3), depth.reshape(h, w)
