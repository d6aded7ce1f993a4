"""The materials of a frame: the config's materials (one per object, reflectance on the
scene's band grid or in K basis coefficients), stacked (leading axis O) or as a list of
per-object materials, and the frame's static mirror switch (:func:`mirror_needed`: whether the
perfect-mirror term χ is compiled into the frame at all).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from ..lighting import Material

if TYPE_CHECKING:  # for annotations (imported where they are used)
    from ..io import Scene

__all__ = [
    "scene_materials",
    "mirror_needed",
]


def scene_materials(scene: Scene, *, basis: Any = None) -> list[Material]:
    """The config's materials (one per object), reflectance on the scene's band grid or
    projected on ``basis`` (a :class:`~spectral_fit.color.SpectralBasis`)."""
    from ..lighting import make_material

    out = []
    for obj in scene.objects:
        m = obj.material
        refl = np.asarray(m.reflectance, np.float64)
        if basis is not None:
            refl = basis.project(refl)
        out.append(make_material(alpha=m.alpha, beta=m.beta, chi=m.chi, mu=m.mu, n=m.n,
                                 gamma=m.gamma, reflectance=refl, distribution=m.distribution,
                                 geometry=m.geometry))
    return out


def _stack(materials: Sequence[Material]) -> Material:
    first = materials[0]
    return Material(**{f: jnp.stack([jnp.asarray(getattr(m, f), jnp.float32)
                                     for m in materials])
                       for f in ("alpha", "beta", "chi", "mu", "n", "gamma", "reflectance")},
                    distribution=first.distribution, geometry=first.geometry)


def _as_stacked(materials: Any, n_objects: int) -> list[Material]:
    """Materials → a list of per-object Materials (accepts a stacked Material or a sequence)."""
    if isinstance(materials, Material):
        a = jnp.asarray(materials.alpha)
        if a.ndim == 0:
            if n_objects != 1:
                raise InputError(f"one material given for {n_objects} objects",
                                 field="materials")
            return [materials]
        if a.shape[0] != n_objects:
            raise InputError(f"{a.shape[0]} materials for {n_objects} objects",
                             field="materials")
        return [jax.tree.map(lambda x, i=i: x[i], materials) for i in range(n_objects)]
    mats = list(materials)
    if len(mats) != n_objects:
        raise InputError(f"{len(mats)} materials for {n_objects} objects", field="materials")
    return mats


def mirror_needed(materials: Any) -> bool:
    """Whether a frame of ``materials`` needs the perfect-mirror term (χ) at all: False only
    when every χ is a concrete 0 (not traced: under ``jax.grad``, ``vmap`` or a caller's
    ``jit`` it is True). The frame is then compiled without the mirror: the direct term's
    lookup along R and, the larger part, the neighbours' mirror radiance that the
    interreflection would otherwise carry in every channel (the paper's plastics have χ = 0).
    Exact: a term multiplied by a concrete 0 is left out, nothing else changes."""
    for x in _chi_leaves(materials):
        if isinstance(x, jax.core.Tracer):
            return True
        if not _all_zero(x):
            return True
    return False


#: the last device arrays :func:`_all_zero` read, with the answer (weak references): the frame's
#: default materials are the same arrays every frame, and reading them is a device → host copy
_ZERO_MEMO: list[tuple[Any, bool]] = []


def _all_zero(x: Any) -> bool:
    """Whether every element of the concrete array ``x`` is 0 (NaN is not)."""
    import weakref

    if not isinstance(x, jax.Array):
        return bool(np.all(np.asarray(x) == 0.0))
    for ref, answer in _ZERO_MEMO:
        if ref() is x:
            return answer
    answer = bool(np.all(np.asarray(x) == 0.0))
    _ZERO_MEMO.insert(0, (weakref.ref(x), answer))
    del _ZERO_MEMO[4:]
    return answer


def _chi_leaves(materials: Any) -> list[Any]:
    """χ of a stacked Material or of each Material of a sequence."""
    return [materials.chi] if isinstance(materials, Material) else [m.chi for m in materials]


def _without_mirror(mats: list[Material]) -> list[Material]:
    """The materials with χ a concrete 0 (see :func:`mirror_needed`): the shading and the
    interreflection then leave the mirror term out at trace time."""
    return [eqx.tree_at(lambda m: m.chi, m, np.zeros(np.shape(m.chi), np.float32))
            for m in mats]


def _mirror_flag(mats: Any, mirror: bool | None) -> bool:
    """The static mirror switch of a frame: ``mirror`` when given (False with a concrete χ
    that is not 0 is refused: it would drop light silently), else :func:`mirror_needed`."""
    needed = mirror_needed(mats)
    if mirror is None:
        return needed
    if not mirror and needed and not _traced_chi(mats):
        raise InputError("mirror=False but a material has χ != 0 (its mirror term would be "
                         "dropped)", field="materials.chi")
    return bool(mirror)


def _traced_chi(mats: Any) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in _chi_leaves(mats))
