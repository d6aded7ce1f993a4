"""Cold start: persistent caches for the first frame of a process.

A fresh process that renders a frame pays for three things before the first pixel: preparing the
scene (:func:`~spectral_fit.rendering.prepare`: meshes, the environment's prefiltered levels and
split-sum tables, capacity plans), tracing and lowering the frame program to XLA, and compiling
it (by far the largest of the three).
JAX's persistent compilation cache removes only the last of these: a cache hit still traces and
lowers the whole program. This module keeps all three between processes:

* :func:`enable_compilation_cache`: JAX's persistent compilation cache in a folder named for
  the library versions (:func:`library_versions_tag`) under ``$SPECTRAL_FIT_JAX_CACHE``
  (default ``~/.cache/spectral_fit/jax``), for every program;
* :func:`prepare_cached`: :func:`~spectral_fit.rendering.prepare` of a config file, stored on disk
  (``$SPECTRAL_FIT_CACHE/prepared``, default ``~/.cache/spectral_fit/prepared``);
* :func:`render_frame_cached`: :func:`~spectral_fit.rendering.render_frame` through a compiled
  executable stored on disk (``.../programs``): a hit loads the executable without tracing. A
  gather-mode frame is kept as two executables (the interreflection's senders' half, then the
  rest) that load, or compile, side by side on two threads. A missing program is compiled and
  stored by a fresh child process (JAX's persistent cache off there), so that what is stored
  does not depend on what the calling process compiled or loaded before (see ``_program``).

Every entry is keyed by a SHA-256 of everything it depends on: the text of the package's source
files, the Python version and the versions of jax, jaxlib, every installed JAX plugin (CUDA,
ROCm, TPU), equinox, optimistix, lineax, numpy and colour-science (:func:`library_versions`),
the backend and device kind, ``XLA_FLAGS`` and the JAX settings that change lowering; for a
prepared scene also the config file's bytes, the size and modification time of every file the
config names, and the options; for a program the full structure of its arguments (every static
field, every array's shape and dtype) and the compiler options. A changed input therefore misses
and recomputes; it never loads a stale entry. In particular nothing written under one
jax/jaxlib is loaded by another, JAX's own compiled programs included (their folder is named for
the versions). Set ``SPECTRAL_FIT_CACHE`` (or ``SPECTRAL_FIT_JAX_CACHE``) to an empty string to
disable a cache. Applications (the CLI, the benchmarks, the notebooks) opt in; the library never
enables a cache by itself, because JAX's setting is process-global.

Where a first frame's time goes: docs/rendering.md ("Cold start").
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import importlib.metadata
import os
import pickle
import re
import sys
import threading
import tomllib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from .._runtime.paths import PACKAGE_DIR
from .._runtime.process import WhileInside, without_fastbins

__all__ = [
    "cache_root",
    "enable_compilation_cache",
    "library_versions",
    "library_versions_tag",
    "prepare_cached",
    "render_frame_cached",
    "CACHE_STATS",
]


#: hits and misses of the two disk caches in this process (for the benchmarks and tests)
CACHE_STATS: dict[str, int] = {"prepared_hit": 0, "prepared_miss": 0, "program_hit": 0,
                               "program_miss": 0, "program_memory_hit": 0}

# entries kept per cache folder (oldest removed first)
_MAX_ENTRIES = 8
# CACHE_STATS' program counts are updated from the threads of _load_parts
_STATS_LOCK = threading.Lock()


def cache_root() -> Path | None:
    """The folder of the prepared-scene and program caches: ``$SPECTRAL_FIT_CACHE`` or
    ``~/.cache/spectral_fit``; None when the variable is set to an empty string."""
    path = os.environ.get("SPECTRAL_FIT_CACHE",
                          os.path.join(os.path.expanduser("~"), ".cache", "spectral_fit"))
    return Path(path) if path else None


def enable_compilation_cache(path: str | os.PathLike[str] | None = None, *,
                             min_compile_time_s: float = 0.0) -> str | None:
    """Turn on JAX's persistent compilation cache (process-global) and return its folder.

    Programs go to a subfolder named by :func:`library_versions_tag`, so that a program compiled
    under one jax/jaxlib (or CUDA plugin) is never loaded by another, whatever JAX's own cache
    key holds.

    Args:
        path: the cache's base folder; default ``$SPECTRAL_FIT_JAX_CACHE`` or
            ``~/.cache/spectral_fit/jax`` (an empty variable disables the cache: returns None).
        min_compile_time_s: programs that compile faster than this are not stored. The default
            0 stores every program, so that a warm process compiles nothing at all (a frame's
            few small eager programs add up to a noticeable compile otherwise).

    Returns:
        The folder in use (``<path>/<library_versions_tag()>``), or None when the cache is off.
        A folder that cannot be created (read-only home) leaves the cache off.
    """
    import jax

    if path is None:
        path = os.environ.get("SPECTRAL_FIT_JAX_CACHE",
                              os.path.join(os.path.expanduser("~"), ".cache", "spectral_fit",
                                           "jax"))
    if not path:
        return None
    path = os.path.join(os.fspath(path), library_versions_tag())
    try:
        os.makedirs(path, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", path)
        jax.config.update("jax_persistent_cache_min_compile_time_secs",
                          float(min_compile_time_s))
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    except Exception:  # a cache must never stop the application
        return None
    return path


# --------------------------------------------------------------------------------------------
# keys


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


# --------------------------------------------------------------------------------------------
# disk entries


def _read_entry(folder: Path, key: str) -> Any:
    p = folder / f"{key}.pkl"
    try:
        with open(p, "rb") as fh:
            return pickle.load(fh)
    except FileNotFoundError:
        return None
    except Exception:  # a damaged entry is recomputed (and overwritten)
        with contextlib.suppress(OSError):
            p.unlink()
        return None


def _write_entry(folder: Path, key: str, value: Any) -> None:
    from .._runtime.fileio import atomic_write_bytes

    try:
        data = pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(folder / f"{key}.pkl", data)
        entries = sorted(folder.glob("*.pkl"), key=lambda q: q.stat().st_mtime_ns)
        for old in entries[:-_MAX_ENTRIES]:
            with contextlib.suppress(OSError):
                old.unlink()
    except Exception:  # a cache that cannot be written must not stop the application
        return


# --------------------------------------------------------------------------------------------
# prepared scenes


def prepare_cached(scene: Any, *, cache_dir: str | os.PathLike[str] | None = None,
                   progress: Any = None, **options: Any) -> Any:
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
    from ._renderer import prepare

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
    text = "\n".join([_environment_digest(), digest,
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


# --------------------------------------------------------------------------------------------
# compiled frame programs


# compiled frame programs of this process, by key (jax.stages.Compiled: a flat list of arrays
# -> a dict of Frame fields)
_PROGRAMS: dict[tuple[str, str], Any] = {}


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


def render_frame_cached(prep: Any, materials: Any = None, *, model: Any = None,
                        view: Any = None, visible: Any = None, spectral: bool = False,
                        background: bool = True, mirror: bool | None = None,
                        cache_dir: str | os.PathLike[str] | None = None,
                        compiler_options: dict[str, Any] | None = None,
                        progress: Any = None) -> Any:
    """:func:`~spectral_fit.rendering.render_frame` through a compiled program kept on disk.

    The first call for a given argument structure (the :class:`Prepared` scene's static
    fields, every array's shape and dtype, ``spectral``, ``background``, the mirror switch,
    ``compiler_options``) in any process
    traces, compiles and stores the executable (``<root>/programs``); later calls, in this
    process or a new one, load it and run it without tracing. The result is the same Frame as
    ``render_frame``'s, from the same XLA program (with ``compiler_options`` None: the
    program is compiled with :func:`~spectral_fit._runtime.dispatch.cpu_compiler_options` as
    ``render_frame``'s is, and the caller's options are added to those).

    Args:
        prep, materials, model, view, visible, spectral, background, mirror: as for
            ``render_frame`` (the same checks and defaults).
        cache_dir: cache root (default :func:`cache_root`; with the cache disabled the
            program is still kept in memory for this process).
        compiler_options: XLA options of the compilation (``jax.stages.Lowered.compile``),
            e.g. ``{"xla_cpu_use_fusion_emitters": False}``, on top of
            :func:`~spectral_fit._runtime.dispatch.cpu_compiler_options`; part of the key.
        progress: called with one line of text before the program is compiled (the first
            call for this argument structure on this machine: tens of seconds), e.g.
            ``print``.

    Returns:
        :class:`~spectral_fit.rendering.Frame` (not differentiable: use ``render_frame`` for
        gradients).
    Raises:
        InputError: wrong shapes of model, view or visible (naming the field).
    """
    import jax
    import numpy as np

    from .._runtime.dispatch import requested_cpu_options
    from ._renderer import Frame, _check_frame_inputs, _mirror_flag

    if visible is None:  # a NumPy default: jnp.ones would compile a program in a new process
        visible = np.ones((prep.num_objects,), bool)
    args = (prep, *_check_frame_inputs(prep, materials, model, view, visible))
    mirror = _mirror_flag(args[1], mirror)
    leaves, treedef = jax.tree_util.tree_flatten(args)
    is_arr = [isinstance(x, jax.Array | np.ndarray) for x in leaves]
    arrays = [x for x, a in zip(leaves, is_arr, strict=True) if a]
    # keyed by the options render_frame's own program asks for, then the caller's (checked
    # against this jaxlib only when compiling: a program loaded from disk needs no compile)
    key = _program_key(treedef, leaves, spectral,
                       {**requested_cpu_options(), **(compiler_options or {})}, background,
                       mirror)
    # in memory per folder: a program kept for one cache folder is still stored in another
    mem_key = (key, str(_programs_folder(cache_dir)))
    prog = _PROGRAMS.get(mem_key)
    out = None
    if prog is not None:
        CACHE_STATS["program_memory_hit"] += 1
    else:
        from ._renderer import render_frame, render_senders

        statics = tuple(x for x, a in zip(leaves, is_arr, strict=True) if not a)

        def unflatten(arr: list[Any]) -> Any:
            it_a, it_s = iter(arr), iter(statics)
            full = [next(it_a) if a else next(it_s) for a in is_arr]
            return jax.tree_util.tree_unflatten(treedef, full)

        def fields(frame: Any) -> dict[str, Any]:
            return {f.name: getattr(frame, f.name) for f in dataclasses.fields(frame)}

        if not _split_program(prep):
            def program(arr: list[Any]) -> dict[str, Any]:
                p, mats, mod, v, vis = unflatten(arr)
                return fields(render_frame(p, mats, model=mod, view=v, visible=vis,
                                           spectral=spectral, background=background,
                                           mirror=mirror))

            parts = [(key, program, arrays)]
        else:
            n = len(arrays)

            def senders_tree(arr: list[Any]) -> Any:
                p, mats, mod, _, vis = unflatten(arr)
                return render_senders(p, mats, model=mod, visible=vis, mirror=mirror)

            def senders(arr: list[Any]) -> list[Any]:
                return jax.tree_util.tree_leaves(senders_tree(arr))

            @functools.cache
            def senders_shape() -> tuple[list[Any], Any]:  # traced only to compile
                return jax.tree_util.tree_flatten(jax.eval_shape(senders_tree, arrays))

            def pixels(arr: list[Any]) -> dict[str, Any]:
                p, mats, mod, v, vis = unflatten(arr[:n])
                snd = jax.tree_util.tree_unflatten(senders_shape()[1], arr[n:])
                return fields(render_frame(p, mats, model=mod, view=v, visible=vis,
                                           spectral=spectral, background=background,
                                           mirror=mirror, senders=snd))

            parts = [(_part_key(key, "senders"), senders, arrays),
                     (_part_key(key, "pixels"), pixels, lambda: arrays + senders_shape()[0])]
        prog, out = _program(parts, compiler_options, cache_dir, arrays, {
            "args": args, "spectral": spectral, "background": background, "mirror": mirror,
            "compiler_options": compiler_options}, progress)
        _PROGRAMS[mem_key] = prog
        if _IN_CHILD:  # compiled and stored: nothing to run
            return None
    if out is None:
        out = prog(arrays)
    return Frame(**out)


def _program(parts: list[tuple[str, Any, Any]], compiler_options: dict[str, Any] | None,
             cache_dir: str | os.PathLike[str] | None, arrays: list[Any], job: dict[str, Any],
             progress: Any = None) -> tuple[Any, Any]:
    """The frame program of ``parts`` and, when it was run here, its first output.

    Parts stored on disk are loaded. Missing parts are compiled and stored by a fresh child
    process (:func:`_compile_in_child`), then loaded: what is stored must not depend on what
    the compiling process compiled or loaded before. XLA:CPU lets a program compiled after
    others (compiled in the same process, or loaded from JAX's persistent cache) use kernels
    of those, and the stored executable then lacks them ("Function bitcast_copy_fusion.6 not
    found" when another process runs it; it ran in the compiling process, and loaded back
    there, too). A program loaded from disk is run once under a guard; one that cannot run
    is removed from disk. Whatever is still missing then (no cache folder, a child that
    failed, a removed entry) is compiled here and kept in memory only."""
    folder = _programs_folder(cache_dir)
    if _IN_CHILD:  # the child loads nothing: what it compiles must not follow other programs
        return _chain(_compile_parts(parts, compiler_options, folder)), None
    with without_fastbins():  # loading and the first run: small blocks by the million
        return _load_or_compile(parts, compiler_options, folder, arrays, job, progress)


def _load_or_compile(parts: list[tuple[str, Any, Any]],
                     compiler_options: dict[str, Any] | None, folder: Path | None,
                     arrays: list[Any], job: dict[str, Any], progress: Any = None
                     ) -> tuple[Any, Any]:
    """:func:`_program` outside the child process."""
    import jax

    compiled = _load_parts(parts, folder)
    n_hit = sum(c is not None for c in compiled)
    with _STATS_LOCK:
        CACHE_STATS["program_miss"] += len(parts) - n_hit
        CACHE_STATS["program_hit"] += n_hit
    if n_hit < len(parts) and progress is not None:
        what = "the frame program" if len(parts) == 1 else (
            f"{len(parts) - n_hit} of the frame's {len(parts)} programs")
        progress(f"compiling {what}: the first run for this scene, size and options on this "
                 "machine takes tens of seconds" + ("; stored for later runs"
                                                   if folder is not None else ""))
    if n_hit < len(parts) and folder is not None and _compile_in_child(job, folder):
        compiled = [c if c is not None else _load_entry(folder, key)
                    for c, (key, _, _) in zip(compiled, parts, strict=True)]
    from_disk = [c is not None for c in compiled]
    compiled = _compile_where(parts, compiled, [not d for d in from_disk], compiler_options)
    if not any(from_disk):
        return _chain(compiled), None
    # a program loaded from disk may still fail to run here (a kernel missing from the stored
    # executable): then its entries are removed and it is compiled here
    try:
        return _chain(compiled), jax.block_until_ready(_chain(compiled)(arrays))
    except Exception:
        for (key, _, _), d in zip(parts, from_disk, strict=True):
            if d:
                with contextlib.suppress(OSError):
                    (folder / f"{key}.pkl").unlink()  # type: ignore[operator]
        with _STATS_LOCK:  # counted as hits above, compiled after all
            CACHE_STATS["program_hit"] -= n_hit
            CACHE_STATS["program_miss"] += n_hit
        return _chain(_compile_where(parts, compiled, from_disk, compiler_options)), None


def _compile_where(parts: list[tuple[str, Any, Any]], compiled: list[Any], redo: list[bool],
                   compiler_options: dict[str, Any] | None) -> list[Any]:
    """``compiled`` with the parts marked in ``redo`` compiled here (side by side, in memory
    only)."""
    new = iter(_compile_parts([p for p, r in zip(parts, redo, strict=True) if r],
                              compiler_options, None))
    return [next(new) if r else c for c, r in zip(compiled, redo, strict=True)]


def _split_program(prep: Any) -> bool:
    """Whether :func:`render_frame_cached` keeps ``prep``'s frame as two programs (the gather
    interreflection's senders' half, then the rest), loaded side by side on two threads: a
    stored executable loads in time proportional to its size and the two halves of the
    benchmark frame are about equal. ``SPECTRAL_FIT_SPLIT_PROGRAMS=0`` keeps one program."""
    if os.environ.get("SPECTRAL_FIT_SPLIT_PROGRAMS", "1") in ("0", ""):
        return False
    return prep.ir_mode == "gather" and prep.num_objects >= 2 and prep.ir_bounces >= 1


def _part_key(key: str, part: str) -> str:
    return hashlib.sha256(f"{key}/{part}".encode()).hexdigest()[:40]


def _programs_folder(cache_dir: str | os.PathLike[str] | None) -> Path | None:
    root = Path(cache_dir) if cache_dir is not None else cache_root()
    return None if root is None else root / "programs"


def _on_threads(fn: Any, items: list[Any]) -> list[Any]:
    """``[fn(x) for x in items]``, several items on as many threads (XLA loads and compiles
    without holding the GIL; tracing takes it in turn)."""
    if len(items) <= 1:
        return [fn(x) for x in items]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(len(items)) as pool:
        return list(pool.map(fn, items))


def _load_parts(parts: list[tuple[str, Any, Any]], folder: Path | None) -> list[Any]:
    """The stored executable of each (key, fn, arrays) part, None where there is none."""
    if folder is None:
        return [None] * len(parts)
    return _on_threads(lambda part: _load_entry(folder, part[0]), parts)


def _compile_parts(parts: list[tuple[str, Any, Any]], compiler_options: dict[str, Any] | None,
                   folder: Path | None) -> list[Any]:
    """:func:`_compile` of each part, side by side (stored in ``folder`` unless None)."""
    return _on_threads(lambda part: _compile(*part, compiler_options, folder), parts)


def _chain(compiled: list[Any]) -> Any:
    """One callable (arrays -> dict of Frame fields) of the compiled parts: the whole frame,
    or the senders' half then the rest (which takes the arrays and the senders' leaves)."""
    if len(compiled) == 1:
        return compiled[0]
    senders, pixels = compiled

    def run(arrays: list[Any]) -> dict[str, Any]:
        return pixels(arrays + list(senders(arrays)))

    return run


def _custom_call_targets(compiled: Any) -> list[str] | None:
    """The custom-call targets (external kernels) of a compiled program; None if unknown."""

    try:
        return sorted(set(re.findall(r'custom_call_target="([^"]+)"', compiled.as_text())))
    except Exception:
        return None


def _prepare_custom_calls(targets: list[str] | None) -> bool:
    """Make the external kernels of a program loaded from disk callable; False when it calls
    one that this module does not know how to prepare (then the program is recompiled).

    JAX initialises the LAPACK kernels (``jnp.linalg``) lazily, while lowering a program that
    uses them; a program loaded from disk is never lowered, and calling an uninitialised
    kernel crashed the process."""
    if targets is None or any(not t.startswith("lapack_") for t in targets):
        return False
    if targets:
        try:  # a private JAX function: if it moves, programs are compiled instead of loaded
            from jax._src.lax import linalg

            linalg.initialize_lapack()
        except Exception:
            return False
    return True


def _strip_locations(lowered: Any) -> bool:
    """Drop the source locations (op names, files, lines, stack frames) from a lowered
    program before it is compiled, in place; False if this JAX does not allow it (then the
    program is compiled with them: the same executable code either way).

    XLA keeps each location as the op metadata of an HLO instruction, and a stored executable
    carries its HLO module, which a new process parses again when it loads the program: on the
    benchmark frame the locations are over a quarter of the stored bytes and a matching share
    of the load. Names in a profile of a loaded program are
    lost with them (profile :func:`~spectral_fit.rendering.render_frame` instead)."""
    try:
        from jax._src.lib.mlir import passmanager

        module = lowered.compiler_ir("stablehlo")  # the module that compile() compiles
        with module.context:
            passmanager.PassManager.parse("builtin.module(strip-debuginfo)").run(
                module.operation)
    except Exception:  # a JAX without this module or pass: keep the locations
        return False
    return True


def _cache_off() -> bool:
    import jax

    saved = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    return saved


def _cache_back(saved: bool) -> None:
    import jax

    jax.config.update("jax_enable_compilation_cache", saved)


_BYPASS = WhileInside(_cache_off, _cache_back)


def _without_persistent_cache() -> WhileInside:
    """JAX's persistent compilation cache off while any thread is inside (the setting is
    process-global: compiles on several threads restore it once, when the last one ends)."""
    return _BYPASS


def _load_entry(folder: Path, key: str) -> Any:
    """The executable stored under ``key`` in ``folder``, loaded; None if there is none, or if
    it cannot be loaded here (another jaxlib build, a kernel this module cannot prepare)."""
    from jax.experimental.serialize_executable import deserialize_and_load

    entry = _read_entry(folder, key)
    if entry is None or not _prepare_custom_calls(entry.get("custom_calls")):
        return None
    try:
        return deserialize_and_load(entry["payload"], entry["in_tree"], entry["out_tree"])
    except Exception:  # e.g. written by another jaxlib build: compiled again
        return None


def _compile(key: str, fn: Any, arrays: Any, compiler_options: dict[str, Any] | None,
             folder: Path | None) -> Any:
    """The compiled ``jax.jit(fn)`` for ``arrays`` (a list of arrays or shape structs, or a
    function returning one, called only to compile), stored in ``folder`` under ``key`` (which
    must determine the program, see :func:`_program_key`) unless ``folder`` is None. Compiled
    with :func:`~spectral_fit._runtime.dispatch.cpu_compiler_options` and ``compiler_options`` on
    top,
    bypassing JAX's persistent compilation cache (what is stored is a fresh compile)."""
    import jax
    from jax.experimental.serialize_executable import serialize

    from .._runtime.dispatch import cpu_compiler_options

    compiler_options = {**cpu_compiler_options(), **(compiler_options or {})}
    lowered = jax.jit(fn).lower(arrays() if callable(arrays) else arrays)
    _strip_locations(lowered)
    with _without_persistent_cache():
        compiled = (lowered.compile(compiler_options=compiler_options) if compiler_options
                    else lowered.compile())
    if folder is not None:
        try:
            targets = _custom_call_targets(compiled)
            if _prepare_custom_calls(targets):  # else: a kernel a new process could not call
                payload, in_tree, out_tree = serialize(compiled)
                _write_entry(folder, key, {"payload": payload, "in_tree": in_tree,
                                           "out_tree": out_tree, "custom_calls": targets})
        except Exception:  # a backend without executable serialisation: memory only
            pass
    return compiled


# --------------------------------------------------------------------------------------------
# compiling in a fresh process

# True in the child process of _compile_in_child (it compiles and stores, and runs nothing)
_IN_CHILD = False


def _compile_in_child(job: dict[str, Any], folder: Path) -> bool:
    """Compile and store the frame program of ``job`` (render_frame_cached's checked
    arguments) in a fresh Python process with JAX's persistent cache off, so that the stored
    executables reference only their own kernels; True when it succeeded. The child imports
    this same package (its source digest, hence the keys, are this process's)."""
    import subprocess
    import tempfile
    import warnings

    from .._runtime.fileio import atomic_write_bytes

    try:
        folder.mkdir(parents=True, exist_ok=True)
        # not "*.pkl": the job file must not count among the entries that _write_entry keeps
        fd, name = tempfile.mkstemp(prefix=".job-", suffix=".job", dir=folder)
        os.close(fd)
    except OSError:
        return False
    job_path = Path(name)
    try:
        atomic_write_bytes(job_path, pickle.dumps({**job, "folder": str(folder)},
                                                  protocol=pickle.HIGHEST_PROTOCOL))
        env = dict(os.environ)
        env["SPECTRAL_FIT_JAX_CACHE"] = ""
        env["JAX_ENABLE_COMPILATION_CACHE"] = "false"
        env["PYTHONPATH"] = os.pathsep.join(
            [str(PACKAGE_DIR.parent)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
        r = subprocess.run([sys.executable, "-c",
                            "from spectral_fit.rendering._cache import _child_main;"
                            " _child_main()", str(job_path)],
                           env=env, capture_output=True, text=True)
    except Exception as exc:  # pickling the arguments, starting Python, ...
        warnings.warn(f"render_frame_cached: the program is compiled in this process ({exc})",
                      RuntimeWarning, stacklevel=4)
        return False
    finally:
        with contextlib.suppress(OSError):
            job_path.unlink()
    if r.returncode != 0:
        tail = (r.stderr or "").strip().splitlines()[-1:] or ["no message"]
        warnings.warn("render_frame_cached: compiling in a fresh process failed "
                      f"(exit {r.returncode}: {tail[0][:300]}); compiled in this process",
                      RuntimeWarning, stacklevel=4)
        return False
    return True


def _child_main() -> None:
    """Entry point of :func:`_compile_in_child`'s process: argv[1] is the job file."""
    global _IN_CHILD
    import jax

    _IN_CHILD = True
    jax.config.update("jax_enable_compilation_cache", False)
    with open(sys.argv[1], "rb") as fh:
        job = pickle.load(fh)
    prep, mats, model, view, visible = job["args"]
    render_frame_cached(prep, mats, model=model, view=view, visible=visible,
                        spectral=job["spectral"], background=job["background"],
                        mirror=job["mirror"], cache_dir=Path(job["folder"]).parent,
                        compiler_options=job["compiler_options"])
