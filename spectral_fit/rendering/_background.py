"""The frame's background: the environment seen through each pixel centre (no video), looked up
bilinearly in a table laid out as the map's texels + 2 pole rows (e.g. the precomputed
absolute XYZ copy of the map: exact, the lookup is linear). A pinhole camera's rays are affine
in the pixel coordinates and evaluated by components; through a lens the pixels' own rays are
looked up.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._runtime.backend import materialise_each
from ..geometry import eye_position, inverse_4x4
from ._prepared import Prepared


def _background(prep: Prepared, flat: jax.Array, view: jax.Array) -> jax.Array:
    """The environment seen through each pixel centre: bilinear lookups (H·W, C') of a table
    laid out as the map's texels + 2 pole rows (e.g. ``prep.colour.env_xyz``). Per pixel the
    map-frame ray direction is an affine function of the pixel coordinates (one 3 × 3 matrix
    for the frame: inverse projection, camera rotation and map rotation), evaluated by
    components (:func:`_pinhole_ray_components`, not normalised); (u, v) as
    :func:`~spectral_fit.lighting.fast_direction_to_uv`'s; the lookup from the table laid
    out with a pole row above and below and a wrapped column
    (:func:`~spectral_fit.lighting.padded_bilinear`, bit-identical to the general one).
    Through a lens (``prep.camera.pixel_rays``) each pixel's ray is looked up instead
    (rotated into the map frame)."""
    from ..lighting import fast_direction_to_uv, padded_bilinear, padded_table, uv_of

    env = prep.lighting.env
    rays = prep.camera.pixel_rays
    hm, wm = env.texels.shape[:2]
    if rays is not None:  # through the lens: the pixel centres' own rays
        # eye → world is view[:3, :3]ᵀ (a rotation), then the map's rotation
        m = view[:3, :3] @ env.rotation
        r = [rays[:, i] for i in range(3)]
        dmap = jnp.stack([r[0] * m[0, j] + r[1] * m[1, j] + r[2] * m[2, j] for j in range(3)],
                         axis=-1)
        u, v = materialise_each(*fast_direction_to_uv(dmap))
    else:  # (u, v) straight from the rays' components, written once as two planes
        u, v = materialise_each(*(c.reshape(-1) for c in uv_of(
            *_pinhole_ray_components(prep, view, env.rotation))))
    return padded_bilinear(padded_table(flat, hm, wm), u, v, hm, wm)


def _pinhole_ray_components(prep: Prepared, view: jax.Array, rot: jax.Array
                            ) -> list[jax.Array]:
    """The map-frame rays of the pixel centres of ``prep``'s pinhole camera as three (H, W)
    components, not normalised (the (u, v) of a direction do not depend on its length; about
    unit length near the image centre); ``rot``: the map's rotation (see :func:`_background`).

    A far-plane point of NDC (x, y, 1, 1) minus the eye, as a function of the pixel's NDC
    (x, y), is linear in (x, y) after the perspective division by w = inv[3] · (x, y, 1, 1),
    and w does not depend on (x, y) for a projection whose last row is (0, 0, −1, 0) (any
    OpenGL pinhole, intrinsics included): one 3 × 3 map from (x, y, 1) to the direction. The
    components are evaluated inside the (u, v) kernel (no (H, W, 3) stack and normalisation
    written out first, which is slower; display RGB within 9e-6)."""
    h, w = prep.camera.shape
    inv = inverse_4x4(prep.camera.projection @ view)
    eye = eye_position(view)
    wrow = inv[3]
    cols = [inv[:3, 0], inv[:3, 1], inv[:3, 2] + inv[:3, 3]]
    wx, wy, w1 = wrow[0], wrow[1], wrow[2] + wrow[3]
    # d(x, y) = (x c0 + y c1 + c2) / den − eye with den = x wx + y wy + w1 (> 0: a constant
    # w1 for an OpenGL pinhole); times den (> 0, so the direction is unchanged):
    # d ∝ x (c0 − eye wx) + y (c1 − eye wy) + (c2 − eye w1), then rotated into the map frame
    a = [(cols[0][i] - eye[i] * wx) for i in range(3)]
    b = [(cols[1][i] - eye[i] * wy) for i in range(3)]
    c = [(cols[2][i] - eye[i] * w1) for i in range(3)]
    am, bm, cm = ([v[0] * rot[0, j] + v[1] * rot[1, j] + v[2] * rot[2, j] for j in range(3)]
                  for v in (a, b, c))
    # scaled to ~unit length at the centre ray (the uv's pole guard assumes unit-ish rays)
    s = jax.lax.rsqrt(cm[0] * cm[0] + cm[1] * cm[1] + cm[2] * cm[2]) * jnp.sign(w1)
    xs = 2.0 * (jnp.arange(w, dtype=jnp.float32) + 0.5) / w - 1.0
    ys = 1.0 - 2.0 * (jnp.arange(h, dtype=jnp.float32) + 0.5) / h
    x, y = xs[None, :], ys[:, None]
    return [x * (am[j] * s) + y * (bm[j] * s) + cm[j] * s for j in range(3)]


