"""The stored frame programs: :func:`render_frame_cached` is
:func:`~spectral_fit.rendering.render_frame` through a compiled executable kept in memory and on
disk (``$SPECTRAL_FIT_CACHE/programs``, default ``~/.cache/spectral_fit/programs``): a hit
loads the executable without tracing. A gather-mode frame is kept as two executables (the
interreflection's senders' half, then the rest) that load, or compile, side by side on two
threads. A missing program is compiled and stored by a fresh child process (JAX's persistent
cache off there), so that what is stored does not depend on what the calling process compiled
or loaded before (see ``_program``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import os
import pickle
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .._runtime.paths import PACKAGE_DIR
from .._runtime.process import without_fastbins
from ._cache import _STATS_LOCK, CACHE_STATS, cache_root
from ._executables import _compile, _load_entry
from ._keys import _program_key

if TYPE_CHECKING:  # for annotations (imported where they are used)
    from ._prepared import Prepared

__all__ = [
    "render_frame_cached",
]


# compiled frame programs of this process, by key (jax.stages.Compiled: a flat list of arrays
# -> a dict of Frame fields)
_PROGRAMS: dict[tuple[str, str], Any] = {}


def render_frame_cached(prep: Prepared, materials: Any = None, *, model: Any = None,
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
    from ._inputs import _check_frame_inputs
    from ._materials import _mirror_flag
    from ._prepared import Frame

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
        from ._frame import render_frame
        from ._ir_stage import render_senders

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


def _split_program(prep: Prepared) -> bool:
    """Whether :func:`render_frame_cached` keeps ``prep``'s frame as two programs (the gather
    interreflection's senders' half, then the rest), loaded side by side on two threads: a
    stored executable loads in time proportional to its size and the two halves of the
    benchmark frame are about equal. ``SPECTRAL_FIT_SPLIT_PROGRAMS=0`` keeps one program."""
    if os.environ.get("SPECTRAL_FIT_SPLIT_PROGRAMS", "1") in ("0", ""):
        return False
    ir = prep.interreflection
    return ir.mode == "gather" and prep.num_objects >= 2 and ir.bounces >= 1


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
                            "from spectral_fit.rendering._program_cache import _child_main;"
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
