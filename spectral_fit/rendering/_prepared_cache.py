"""The prepared-scene cache: :func:`prepare_cached` is :func:`~spectral_fit.rendering.prepare` of
a config file or a :class:`~spectral_fit.io.Scene` with its result stored on disk
(``$SPECTRAL_FIT_CACHE/prepared``, default ``~/.cache/spectral_fit/prepared``), keyed by the
config's bytes and the files it names (or the scene's values), the options, the environment
(``_keys``) and the layout of :class:`~spectral_fit.rendering.Prepared`; a hit is unpickled,
identical to what ``prepare`` returned.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ._cache import CACHE_STATS, _read_entry, _write_entry, cache_root
from ._keys import _config_digest, _environment_digest, _plain_repr, _scene_text

if TYPE_CHECKING:  # for annotations (imported where they are used)
    from ..io import Scene
    from ._prepared import Prepared

__all__ = [
    "prepare_cached",
]


def prepare_cached(scene: Scene | str | os.PathLike[str], *,
                   cache_dir: str | os.PathLike[str] | None = None, progress: Any = None,
                   **options: Any) -> Prepared:
    """:func:`~spectral_fit.rendering.prepare` with a disk cache of its result.

    Args:
        scene: path to a scene config (TOML), keyed by its bytes and the size and
            modification time of every file it names; or a
            :class:`~spectral_fit.io.Scene` object (e.g. a config's scene changed in
            Python, as the live session's planning scene), keyed by every field's value
            (arrays by their bytes) and the same of every file it names. An option that is
            not a plain value (e.g. an ``environment`` array) is prepared without the
            cache.
        cache_dir: cache root (default :func:`cache_root`); entries go to ``<root>/prepared``.
        progress: called with one line of text when the scene is prepared rather than
            loaded (seconds of work), e.g. ``print``.
        **options: passed to ``prepare`` (size, mode, spectral_mode, k, ...).

    Returns:
        The :class:`~spectral_fit.rendering.Prepared` scene, identical to ``prepare``'s (the
        stored arrays are float32 as prepared; pickled, not recomputed).
    Raises:
        InputError: as ``prepare`` (bad configs and options are never cached).
    """
    from ._prepare import prepare
    from ._prepared import PREPARED_LAYOUT

    root = Path(cache_dir) if cache_dir is not None else cache_root()
    texts = {k: _plain_repr(v) for k, v in options.items()}
    digest = None
    if root is not None and isinstance(scene, str | os.PathLike):
        digest = _config_digest(Path(scene))
    elif root is not None and dataclasses.is_dataclass(scene) and not isinstance(scene, type):
        text = _scene_text(scene)
        digest = None if text is None else hashlib.sha256(text.encode()).hexdigest()
    say = progress or (lambda _m: None)
    if digest is None or any(t is None for t in texts.values()):
        say(_PREPARING)
        return prepare(scene, **options)
    text = "\n".join([_environment_digest(), f"layout={PREPARED_LAYOUT}", digest,
                      *(f"{k}={texts[k]}" for k in sorted(texts))])
    key = hashlib.sha256(text.encode()).hexdigest()[:40]
    folder = root / "prepared"
    hit = _read_entry(folder, key)
    if hit is not None:
        CACHE_STATS["prepared_hit"] += 1
        return hit
    CACHE_STATS["prepared_miss"] += 1
    say(_PREPARING + "; stored for later runs")
    prep = prepare(scene, **options)
    _write_entry(folder, key, prep)
    return prep


_PREPARING = ("preparing the scene (environment levels, split-sum tables, irradiance map, "
              "capacity plans)")
