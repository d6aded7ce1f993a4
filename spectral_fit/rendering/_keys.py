"""Cache keys: SHA-256 digests of everything a cached entry depends on, so that a changed input
misses and recomputes and never loads a stale entry: the text of the package's source files,
the library versions (:func:`library_versions`, and :func:`library_versions_tag` naming a
folder for them), the backend, device kind, ``XLA_FLAGS`` and the JAX settings that change
lowering; a config file's bytes with the size and modification time of every file it names;
option values and scenes as deterministic text; and a frame program's argument structure
(every static field, every array's shape and dtype) with its compiler options
(:func:`_program_key`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import importlib.metadata
import os
import sys
import tomllib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from .._runtime.paths import PACKAGE_DIR

__all__ = [
    "distribution_version",
    "environment_digest",
    "library_versions",
    "library_versions_tag",
    "plain_repr",
    "program_key",
    "scene_text",
]


@functools.cache
def _source_digest() -> str:
    """SHA-256 of every file of the package (relative path and bytes), computed once."""
    h = hashlib.sha256()
    for p in sorted(PACKAGE_DIR.rglob("*")):
        if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc":
            h.update(str(p.relative_to(PACKAGE_DIR)).encode())
            h.update(b"\0")
            h.update(p.read_bytes())
            h.update(b"\0")
    return h.hexdigest()


def _version(dist: str) -> str:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return "-"


# the distributions whose versions change what is prepared, lowered or compiled
_KEY_DISTRIBUTIONS = ("jax", "jaxlib", "equinox", "optimistix", "lineax", "numpy",
                      "colour-science")


# JAX's backend plugins: their versions change the compiled programs of their device
_PLUGIN_PREFIXES = ("jax-cuda", "jax_cuda", "jax-rocm", "jax_rocm", "libtpu")


def library_versions() -> dict[str, str]:
    """The versions the on-disk caches are keyed by: ``{"python": ..., "jax": ..., ...}``.

    Python, jax, jaxlib, equinox, optimistix, lineax, numpy, colour-science (``"-"`` where not
    installed) and every installed JAX backend plugin (``jax-cuda12-plugin``,
    ``jax-cuda12-pjrt``, ROCm and TPU likewise), sorted by name. Read from the installed
    distributions' metadata on each call.
    """
    out = {"python": sys.version.split()[0]}
    out.update({d: _version(d) for d in _KEY_DISTRIBUTIONS})
    plugins = {}
    for dist in importlib.metadata.distributions():
        name = (dist.metadata["Name"] or "").lower()
        if name.startswith(_PLUGIN_PREFIXES):
            plugins[name.replace("_", "-")] = dist.version
    out.update(sorted(plugins.items()))
    return out


def library_versions_tag() -> str:
    """A folder name for :func:`library_versions`: ``jax-<v>_jaxlib-<v>_<hash>``, the hash
    (12 hex digits of SHA-256) over all of them, plugins and Python included."""
    v = library_versions()
    digest = hashlib.sha256(
        "\n".join(f"{k}={x}" for k, x in v.items()).encode()).hexdigest()[:12]
    return f"jax-{v['jax']}_jaxlib-{v['jaxlib']}_{digest}"


@functools.cache
def _environment_digest() -> str:
    """The package sources, library versions, backend and the settings that change lowering."""
    import jax

    from .._runtime.backend import on_accelerator

    dev = jax.devices()[0]
    parts = [
        _source_digest(),
        *(f"{d}={v}" for d, v in library_versions().items()),
        f"backend={jax.default_backend()}", f"device={dev.platform}:{dev.device_kind}",
        f"devices={jax.device_count()}",
        f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')}",
        f"accelerator_layout={on_accelerator()}",
        f"x64={jax.config.jax_enable_x64}",
        f"matmul={jax.config.jax_default_matmul_precision}",
    ]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def _strings(tree: Any) -> Iterable[str]:
    if isinstance(tree, str):
        yield tree
    elif isinstance(tree, dict):
        for v in tree.values():
            yield from _strings(v)
    elif isinstance(tree, list | tuple):
        for v in tree:
            yield from _strings(v)


def _config_digest(path: Path) -> str | None:
    """Config bytes plus (path, size, mtime) of every existing file any of its strings names
    (absolute, or relative to the config's folder or the working folder); None when the file
    cannot be read or parsed (then :func:`prepare` reports the error itself)."""
    try:
        raw = path.read_bytes()
        doc = tomllib.loads(raw.decode("utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return None
    h = hashlib.sha256(raw)
    h.update(str(path.resolve()).encode())
    seen = set()
    for s in _strings(doc):
        if not s or len(s) > 4096 or "\0" in s:
            continue
        p = Path(s).expanduser()
        for cand in ([p] if p.is_absolute() else [path.parent / p, Path.cwd() / p]):
            with contextlib.suppress(OSError):
                if cand.is_file():
                    key = _file_stamp(cand)
                    if key not in seen:
                        seen.add(key)
                        h.update(key.encode())
    return h.hexdigest()


def _file_stamp(path: Path) -> str:
    """A file's resolved path, size and modification time (ns), as the cache keys name a
    file; OSError when it cannot be read."""
    st = path.stat()
    return f"{path.resolve()}|{st.st_size}|{st.st_mtime_ns}"


_PLAIN = (type(None), bool, int, float, str)


def _plain_repr(value: Any) -> str | None:
    """A deterministic text of a plain option value (scalars, tuples/lists of them, frozen
    dataclasses of them); None for anything else (arrays, objects): then no caching."""
    return _value_text(value, rich=False)


def _scene_text(value: Any) -> str | None:
    """A deterministic text of a :class:`~spectral_fit.io.Scene` (or any part of one):
    plain values as :func:`_plain_repr`, arrays by dtype, shape and a SHA-256 of their bytes,
    dicts by sorted key, and every file path with the resolved path, size and modification
    time of the file it names (as :func:`_config_digest` does for a config's files); None
    when any part is something else (then no caching)."""
    return _value_text(value, rich=True)


def _value_text(value: Any, *, rich: bool) -> str | None:
    """:func:`_plain_repr` (``rich`` False) or :func:`_scene_text` (True)."""
    import numpy as np

    if isinstance(value, _PLAIN):
        return repr(value)
    if rich and isinstance(value, Path):
        try:
            return "file:" + _file_stamp(value)
        except OSError:
            return f"file:{value}|missing"
    if rich and isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        if a.dtype.hasobject:
            return None
        return f"array:{a.dtype.str}:{a.shape}:{hashlib.sha256(a.tobytes()).hexdigest()}"
    if rich and isinstance(value, dict):
        pairs = [(_value_text(k, rich=True), _value_text(v, rich=True))
                 for k, v in value.items()]
        if any(k is None or v is None for k, v in pairs):
            return None
        return "{" + ",".join(sorted(f"{k}:{v}" for k, v in pairs)) + "}"
    if isinstance(value, list | tuple):
        items = [_value_text(v, rich=rich) for v in value]
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        items = [_value_text(getattr(value, f.name), rich=rich)
                 for f in dataclasses.fields(value)]
    else:
        return None
    if any(i is None for i in items):
        return None
    text = ",".join(items)  # type: ignore[arg-type]
    return (f"({text})" if isinstance(value, list | tuple)
            else f"{type(value).__qualname__}({text})")


def _program_key(treedef: Any, leaves: list[Any], spectral: bool,
                 compiler_options: dict[str, Any] | None, background: bool = True,
                 mirror: bool = True) -> str:
    import jax
    import numpy as np

    # static fields are written with repr: numpy's print options (which other libraries change
    # on import) are pinned so that the text does not depend on what was imported before
    with np.printoptions(precision=8, threshold=sys.maxsize, edgeitems=3, linewidth=75,
                         suppress=False, nanstr="nan", infstr="inf", sign="-",
                         floatmode="unique", legacy=False):
        parts = [_environment_digest(), repr(treedef), f"spectral={bool(spectral)}",
                 f"background={bool(background)}", f"mirror={bool(mirror)}",
                 f"options={sorted((compiler_options or {}).items())!r}"]
        for x in leaves:
            if isinstance(x, jax.Array | np.ndarray):
                parts.append(f"{tuple(x.shape)}:{x.dtype}:{getattr(x, 'weak_type', False)}")
            else:
                parts.append("static:" + repr(x))
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:40]


# the keys' parts as the other layers' disk caches use them (the fit's preparation, programs
# and report pictures): the same texts, so one change of code or libraries misses them all
#: every value of a scene (or part of one), files by path, size and modification time
scene_text = _scene_text
#: plain values only (None for anything else)
plain_repr = _plain_repr
#: the package's sources, library versions, backend and numerics flags
environment_digest = _environment_digest
#: an installed distribution's version ("-" when absent)
distribution_version = _version
#: a compiled program's key: its arguments' structure, static values, shapes and dtypes
program_key = _program_key
