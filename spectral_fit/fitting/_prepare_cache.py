"""The fit's preparation kept on disk: :func:`prepare_fit_cached` is
:func:`~spectral_fit.fitting.prepare_fit` with its result stored under
``<cache_dir>/fit_prepared`` (the CLI passes :func:`~spectral_fit.rendering.cache_root`:
``$SPECTRAL_FIT_CACHE``, default ``~/.cache/spectral_fit``), and
:func:`aim_problems_cached` does the same for the aim-shifted problems of the aiming
sensitivity.

An entry's key is a SHA-256 of everything the preparation depends on:

* the package's source files, the library versions, backend, device, ``XLA_FLAGS`` and the
  JAX settings that change results (the rendering caches' ``environment_digest``);
* :data:`FIT_PREPARED_LAYOUT` (the layout of what is stored);
* the scene and the session as deterministic text of every field (arrays by dtype, shape and
  a SHA-256 of their bytes: every reading, repeat, dark, white and reflectance value; every
  file they name by resolved path, size and modification time: the config, the manifest,
  the environment map);
* the options the preparation reads (:data:`PREPARE_FIELDS` of
  :class:`~spectral_fit.fitting.FitOptions`; the solver's options are not part of it);
* for the aim-shifted problems also the aim step.

A changed input therefore misses and prepares again; it never loads a stale entry. Entries are
pickled and written atomically (``_runtime.fileio``); a damaged entry is prepared again and
overwritten; a cache that cannot be written does not stop the fit. Inputs that cannot be
written as such text (e.g. a scene holding a Python object) are prepared without the cache.
Bad inputs raise as :func:`prepare_fit` does and are never stored.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from ..io import Scene, Session
    from ._options import FitOptions
    from ._problem import FitProblem, PreparedFit

__all__ = ["FIT_PREPARED_LAYOUT", "PREPARE_FIELDS", "FIT_CACHE_STATS", "prepare_fit_cached",
           "aim_problems_cached", "fit_prepare_key"]

#: layout number of the stored entries (raised whenever what is stored changes shape)
FIT_PREPARED_LAYOUT = 3

#: the :class:`FitOptions` fields that :func:`prepare_fit` reads (the key's options)
PREPARE_FIELDS = ("spot_resolution", "interreflection", "dtype", "compress_tol", "cache")

#: hits and misses of the fit's preparation cache in this process
FIT_CACHE_STATS: dict[str, int] = {"prepared_hit": 0, "prepared_miss": 0, "aim_hit": 0,
                                   "aim_miss": 0}


def _options_text(opts: FitOptions) -> str | None:
    from ..rendering import plain_repr

    parts = []
    for name in PREPARE_FIELDS:
        v = getattr(opts, name)
        text = np.dtype(v).name if name == "dtype" else plain_repr(v)
        if text is None:
            return None
        parts.append(f"{name}={text}")
    return ";".join(parts)


def fit_prepare_key(scene: Scene, session: Session, opts: FitOptions, *extra: str
                    ) -> str | None:
    """The cache key (40 hex digits) of the preparation of ``scene`` and ``session`` with
    ``opts`` (and ``extra`` texts), or None when an input has no deterministic text."""
    from ..rendering import environment_digest, scene_text

    scene_part = scene_text(scene)
    session_part = scene_text(session)
    options_part = _options_text(opts)
    if scene_part is None or session_part is None or options_part is None:
        return None
    h = hashlib.sha256()
    for part in (environment_digest(), f"fit_layout={FIT_PREPARED_LAYOUT}", scene_part,
                 session_part, options_part, *extra):
        h.update(part.encode())
        h.update(b"\0")
    return h.hexdigest()[:40]


def _folder(cache_dir: str | os.PathLike[str] | None) -> Path | None:
    return None if cache_dir is None else Path(cache_dir) / "fit_prepared"


def prepare_fit_cached(scene: Scene, session: Session, *, options: FitOptions | None = None,
                       cache_dir: str | os.PathLike[str] | None = None) -> PreparedFit:
    """:func:`~spectral_fit.fitting.prepare_fit` with a disk cache of its result.

    Args:
        scene, session: as for ``prepare_fit``.
        options: :class:`~spectral_fit.fitting.FitOptions` (only :data:`PREPARE_FIELDS` are
            read, and keyed).
        cache_dir: the cache's root folder (entries in ``<cache_dir>/fit_prepared``); None
            prepares without a cache.

    Returns:
        The :class:`~spectral_fit.fitting.PreparedFit`, equal to ``prepare_fit``'s (a hit is
        unpickled, not recomputed: the same arrays). Its ``cached`` is "hit", "miss" or
        "off", its ``seconds`` the time this call took. A hit warns as the preparation did.

    Raises:
        InputError: as ``prepare_fit`` (bad inputs are never stored).
    """
    from ..rendering import read_cache_entry, write_cache_entry
    from ._options import FitOptions
    from ._prepare import prepare_fit

    opts = options or FitOptions()
    t0 = time.perf_counter()
    folder = _folder(cache_dir)
    key = None if folder is None else fit_prepare_key(scene, session, opts, "prepared")
    if key is None:
        return dataclasses.replace(prepare_fit(scene, session, options=opts), cached="off")
    hit = read_cache_entry(folder, key)
    if hit is not None:
        FIT_CACHE_STATS["prepared_hit"] += 1
        for w in hit.warnings:
            warnings.warn(w, RuntimeWarning, stacklevel=2)
        return dataclasses.replace(hit, session=session, cached="hit",
                                   seconds=time.perf_counter() - t0)
    FIT_CACHE_STATS["prepared_miss"] += 1
    prep = prepare_fit(scene, session, options=opts)
    # the session is the caller's (equal by the key); stored without it
    write_cache_entry(folder, key, dataclasses.replace(prep, session=None))
    return dataclasses.replace(prep, cached="miss", seconds=time.perf_counter() - t0)


def aim_problems_cached(scene: Scene, prep: PreparedFit, opts: FitOptions, shifted: list[Any],
                        *, cache_dir: str | os.PathLike[str] | None = None
                        ) -> tuple[list[FitProblem | None], str]:
    """The problems of the aim-shifted sessions ``shifted`` (each the prepared session with
    every reading's aim moved), prepared with the scene's map and meshes of ``prep``; None
    for a shifted session whose spots miss their objects. Kept on disk under ``cache_dir``
    like :func:`prepare_fit_cached` (stored without the map, which is ``prep``'s), keyed by
    the shifted sessions themselves.

    Returns:
        (problems, "hit" | "miss" | "off").
    """
    import equinox as eqx

    from .._runtime.errors import InputError
    from ..rendering import read_cache_entry, write_cache_entry
    from ._prepare import prepare_fit

    folder = _folder(cache_dir)
    key = None
    if folder is not None:
        texts = []
        for ss in shifted:
            k = fit_prepare_key(scene, ss, opts, "aim")
            if k is None:
                texts = None
                break
            texts.append(k)
        if texts is not None:
            key = hashlib.sha256("\n".join(texts).encode()).hexdigest()[:40]
    env = prep.problem.env
    if key is not None:
        hit = read_cache_entry(folder, key)
        if isinstance(hit, list) and len(hit) == len(shifted):
            FIT_CACHE_STATS["aim_hit"] += 1
            return [None if p is None else eqx.tree_at(lambda q: q.env, p, env,
                                                       is_leaf=lambda x: x is None)
                    for p in hit], "hit"
    out: list[FitProblem | None] = []
    for ss in shifted:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                pp = prepare_fit(scene, ss, options=opts, env=env, geometries=prep.geometries)
            out.append(pp.problem)
        except InputError:
            out.append(None)
    if key is None:
        return out, "off"
    FIT_CACHE_STATS["aim_miss"] += 1
    write_cache_entry(folder, key, [None if p is None else eqx.tree_at(lambda q: q.env, p, None)
                               for p in out])
    return out, "miss"
