"""Cold-start caches (spectral_fit.rendering): prepared scenes and compiled frame programs on
disk, checked against the uncached functions (bit for bit), across fresh processes, and for
invalidation when an input changes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import jax
import numpy as np
import pytest
from helpers import ANCHOR_ENV, ROOT
from helpers.rendering import scene_toml

from spectral_fit import rendering
from spectral_fit._runtime import process
from spectral_fit._runtime.errors import InputError
from spectral_fit.rendering import _executables, _keys, _program_cache


def _small_env(path: Path, scale: float = 1.0) -> Path:
    """The benchmark map averaged down to 16 × 32 texels (cheap to prepare)."""
    from spectral_fit.io import read_spectral_exr, write_spectral_exr

    wl, img = read_spectral_exr(ANCHOR_ENV)
    h, w, c = img.shape
    small = img.reshape(16, h // 16, 32, w // 32, c).mean(axis=(1, 3)) * scale
    write_spectral_exr(path, wl, small, preview=False)
    return path


@pytest.fixture(autouse=True)
def _fresh_programs(monkeypatch):
    """Each test starts without this process's in-memory programs: with several tests of one
    config on one worker, a later test's first ``render_frame_cached`` was otherwise a memory
    hit of an earlier test's program (its cache folder never consulted, its miss counts off)."""
    monkeypatch.setattr(_program_cache, "_PROGRAMS", {})


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("startup")
    env = _small_env(folder / "env.exr")
    p = folder / "scene.toml"
    p.write_text(scene_toml(env, stacks=8, width=40, height=30, same_colour=False))
    return p


def _leaves_equal(a, b) -> bool:
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    return (len(la) == len(lb) and all(
        np.array_equal(np.asarray(x), np.asarray(y)) and np.asarray(x).dtype ==
        np.asarray(y).dtype for x, y in zip(la, lb, strict=True))
        and repr(ta) == repr(tb))


def _env(cache: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["SPECTRAL_FIT_CACHE"] = str(cache)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    return env


def test_prepare_cached_hits_and_matches_prepare(config, tmp_path):
    from spectral_fit.rendering import prepare

    before = dict(rendering.CACHE_STATS)
    said: list[str] = []
    a = rendering.prepare_cached(config, cache_dir=tmp_path, mode="none", progress=said.append)
    assert len(said) == 1 and "preparing the scene" in said[0]  # a miss says so
    b = rendering.prepare_cached(config, cache_dir=tmp_path, mode="none", progress=said.append)
    assert len(said) == 1  # a hit is quick and quiet
    assert rendering.CACHE_STATS["prepared_miss"] - before["prepared_miss"] == 1
    assert rendering.CACHE_STATS["prepared_hit"] - before["prepared_hit"] == 1
    ref = prepare(config, mode="none")
    assert _leaves_equal(a, ref) and _leaves_equal(b, ref)
    # another option value is another entry
    rendering.prepare_cached(config, cache_dir=tmp_path, mode="none", size=(20, 16))
    assert rendering.CACHE_STATS["prepared_miss"] - before["prepared_miss"] == 2
    assert len(list((tmp_path / "prepared").glob("*.pkl"))) == 2


def test_prepare_cached_invalidated_by_a_named_file(tmp_path):
    env = _small_env(tmp_path / "env.exr")
    cfg = tmp_path / "scene.toml"
    cfg.write_text(scene_toml(env, stacks=6, width=24, height=16))
    cache = tmp_path / "cache"
    a = rendering.prepare_cached(cfg, cache_dir=cache, mode="none")
    _small_env(env, scale=2.0)  # same path and size, new content and modification time
    misses = rendering.CACHE_STATS["prepared_miss"]
    b = rendering.prepare_cached(cfg, cache_dir=cache, mode="none")
    assert rendering.CACHE_STATS["prepared_miss"] == misses + 1
    np.testing.assert_allclose(np.asarray(b.lighting.env.texels),
                               2.0 * np.asarray(a.lighting.env.texels),
                               rtol=1e-6)
    # a damaged entry is recomputed, not loaded
    for p in (cache / "prepared").glob("*.pkl"):
        p.write_bytes(b"not a pickle")
    c = rendering.prepare_cached(cfg, cache_dir=cache, mode="none")
    assert rendering.CACHE_STATS["prepared_miss"] == misses + 2
    assert _leaves_equal(b, c)


def test_prepare_cached_keys_a_scene_object_by_its_values(config, tmp_path):
    """A Scene object (a config's scene changed in Python, as the live session's planning
    scene) is cached by its values: an equal scene hits and gives ``prepare``'s result bit
    for bit; a moved object, another array value or a touched named file is another entry."""
    import dataclasses

    from spectral_fit.io import load_scene
    from spectral_fit.rendering import prepare

    scene = load_scene(config)
    moved = scene.replace(objects=(dataclasses.replace(
        scene.objects[0], position=(0.01, 0.0, -0.3)), *scene.objects[1:]))
    before = dict(rendering.CACHE_STATS)

    def cached(sc: Any) -> Any:
        return rendering.prepare_cached(sc, cache_dir=tmp_path, mode="none")

    def misses() -> int:
        return rendering.CACHE_STATS["prepared_miss"] - before["prepared_miss"]

    a = cached(moved)
    b = cached(dataclasses.replace(moved))  # an equal scene, another object
    assert misses() == 1 and rendering.CACHE_STATS["prepared_hit"] - before["prepared_hit"] == 1
    assert _leaves_equal(a, prepare(moved, mode="none")) and _leaves_equal(a, b)
    assert not _leaves_equal(a, cached(scene))  # the object where the config has it
    assert misses() == 2
    o = scene.objects[1]
    tinted = scene.replace(objects=(scene.objects[0], dataclasses.replace(
        o, material=dataclasses.replace(o.material,
                                        reflectance=o.material.reflectance * 0.5))))
    cached(tinted)
    assert misses() == 3
    env = scene.environment.file
    os.utime(env, ns=(env.stat().st_atime_ns, env.stat().st_mtime_ns + 10**9))
    cached(scene)  # the same values, a newer environment file
    assert misses() == 4
    cached(scene)
    assert misses() == 4


def test_prepare_cached_bypasses_what_it_cannot_key(config, tmp_path, monkeypatch):
    from spectral_fit.io import load_scene, read_spectral_exr

    before = dict(rendering.CACHE_STATS)
    # an option that is not a plain value: an environment given as an array
    texels = read_spectral_exr(load_scene(config).environment.file)[1]
    rendering.prepare_cached(config, cache_dir=tmp_path, mode="none", environment=texels)
    monkeypatch.setenv("SPECTRAL_FIT_CACHE", "")
    assert rendering.cache_root() is None
    rendering.prepare_cached(config, mode="none")
    assert rendering.CACHE_STATS == before
    assert not (tmp_path / "prepared").exists()
    with pytest.raises(InputError) as e:
        rendering.prepare_cached(config, cache_dir=tmp_path, mode="bogus")
    assert e.value.field == "mode"


def test_program_key_ignores_numpy_print_options():
    import jax.numpy as jnp

    from spectral_fit.color import Display

    d = Display(primaries_xy=np.array([[0.64, 0.33], [0.3, 0.6], [0.15, 0.06]]),
                white_xy=np.array([0.3127, 0.329]))
    tree = (d, jnp.ones(3))
    leaves, td = jax.tree_util.tree_flatten(tree)
    k0 = _keys._program_key(td, leaves, False, None)
    with np.printoptions(legacy="1.13", precision=3):
        assert _keys._program_key(td, leaves, False, None) == k0
    assert _keys._program_key(td, leaves, True, None) != k0
    assert _keys._program_key(td, leaves, False, None, background=False) != k0
    assert _keys._program_key(td, [jnp.ones(4)], False, None) != k0


_PROGRAM = """
import json, sys
import jax
import jax.numpy as jnp
import numpy as np
from spectral_fit._runtime.dispatch import cpu_compiler_options
from spectral_fit.rendering import _executables, _program_cache, enable_compilation_cache

def fn(arr):
    (m,) = arr
    return {"inv": jnp.linalg.inv(m), "sum": jnp.sum(m)}

m = jnp.asarray(np.array([[4.0, 1.0, 0.5], [0.0, 3.0, 1.0], [1.0, 0.0, 2.0]], np.float32))
folder = _program_cache._programs_folder(sys.argv[1])
c = _executables._load_entry(folder, "k")
stats = {"program_hit": int(c is not None), "program_miss": int(c is None)}
if c is None:
    # a busy process: JAX's persistent cache in use, and the same function compiled the usual
    # way (with its source locations) before, into memory and into that cache
    enable_compilation_cache(sys.argv[2], min_compile_time_s=0)
    jax.jit(fn).lower([m]).compile(compiler_options=cpu_compiler_options() or None)
    c = _executables._compile("k", fn, [m], None, folder)
    # the cache is on again afterwards
    def after(x):
        return x * 3.0 + 1.0
    jax.jit(after).lower(m).compile()
out = c([m])
print(json.dumps({"inv": np.asarray(out["inv"]).tolist(), "stats": stats}))
"""


def test_program_loads_in_a_fresh_process(tmp_path):
    # the second process loads the executable without lowering jnp.linalg (which is what
    # initialises the LAPACK kernels): this crashed before the kernels were loaded explicitly
    script = tmp_path / "prog.py"
    script.write_text(_PROGRAM)
    outs = []
    for _ in range(2):
        r = subprocess.run([sys.executable, str(script), str(tmp_path / "cache"),
                            str(tmp_path / "jax")],
                           capture_output=True, text=True, env=_env(tmp_path / "unused"),
                           timeout=300)
        assert r.returncode == 0, r.stderr[-2000:]
        outs.append(json.loads(r.stdout.strip().splitlines()[-1]))
    assert outs[0]["stats"]["program_miss"] == 1 and outs[0]["stats"]["program_hit"] == 0
    assert outs[1]["stats"]["program_hit"] == 1 and outs[1]["stats"]["program_miss"] == 0
    m = np.array([[4.0, 1.0, 0.5], [0.0, 3.0, 1.0], [1.0, 0.0, 2.0]])
    for o in outs:
        np.testing.assert_allclose(o["inv"], np.linalg.inv(m), rtol=1e-5, atol=1e-6)
    import pickle

    entry = pickle.loads((tmp_path / "cache" / "programs" / "k.pkl").read_bytes())
    assert any(t.startswith("lapack_") for t in entry["custom_calls"])
    # stored without the source locations (op names such as "jit(fn)/jit(inv)/..." in each HLO
    # instruction's metadata) although the process had compiled the function with them before
    # (JAX hands back such an executable, from memory or from its persistent cache, unless the
    # store compiles a fresh program with that cache bypassed)
    assert b"jit(fn)/" not in entry["payload"]
    # JAX's persistent cache: the usual compile and the one after, not the stored program's
    stored = sorted(f.name.split("-")[0] for f in (tmp_path / "jax").rglob("*-cache"))
    assert stored.count("jit_fn") == 1 and "jit_after" in stored, stored


def test_strip_locations_drops_the_op_names():
    import jax.numpy as jnp

    def fn(a):
        return jnp.linalg.inv(a) + jnp.sum(a)

    lowered = jax.jit(fn).lower(jnp.eye(3))
    assert "jit(fn)/" in lowered.as_text(debug_info=True)
    assert _executables._strip_locations(lowered)
    assert "jit(fn)/" not in lowered.as_text(debug_info=True)


def test_programs_with_unknown_kernels_are_not_loaded():
    assert _executables._prepare_custom_calls([]) is True
    assert _executables._prepare_custom_calls(["lapack_sgetrf_ffi"]) is True
    assert _executables._prepare_custom_calls(["lapack_sgetrf_ffi", "ducc_fft"]) is False
    assert _executables._prepare_custom_calls(None) is False


_FRAME = """
import sys
import numpy as np
from spectral_fit import rendering
prep = rendering.prepare_cached(sys.argv[1], mode="none")
f = rendering.render_frame_cached(prep)
np.save(sys.argv[2], np.asarray(f.xyz))
print(rendering.CACHE_STATS)
"""


def _two_fresh_runs(source: str, config: Path, tmp_path: Path) -> list[Any]:
    """Run ``source`` (argv: config, output .npy) in two fresh processes one after the other,
    sharing the caches in ``tmp_path/fresh``; both must succeed. Outputs: ``xyz{i}.npy``."""
    script = tmp_path / "frame.py"
    script.write_text(textwrap.dedent(source))
    runs = [subprocess.run([sys.executable, str(script), str(config),
                            str(tmp_path / f"xyz{i}.npy")],
                           capture_output=True, text=True, env=_env(tmp_path / "fresh"),
                           timeout=900)
            for i in range(2)]
    for r in runs:
        assert r.returncode == 0, r.stderr[-2000:]
    return runs


def test_render_frame_cached_matches_render_frame(config, tmp_path):
    import jax.numpy as jnp

    from spectral_fit.rendering import render_frame

    cache = tmp_path / "cache"
    prep = rendering.prepare_cached(config, cache_dir=cache, mode="none")
    ref = render_frame(prep)
    misses = rendering.CACHE_STATS["program_miss"]
    said: list[str] = []
    got = rendering.render_frame_cached(prep, cache_dir=cache, progress=said.append)
    assert rendering.CACHE_STATS["program_miss"] == misses + 1
    assert len(said) == 1 and said[0].startswith("compiling the frame program"), said
    assert int(ref.stats["covered_pixels"]) > 20
    for name in ("xyz", "rgb", "linear_rgb", "mask", "object_id"):
        assert np.array_equal(np.asarray(getattr(got, name)), np.asarray(getattr(ref, name)))
    assert {k: float(v) for k, v in got.stats.items()} == {
        k: float(v) for k, v in ref.stats.items()}
    # a new pose reuses the program (no retrace, no recompile) and matches render_frame
    model = np.asarray(prep.model).copy()
    model[0, 0, 3] += 0.01
    mem = rendering.CACHE_STATS["program_memory_hit"]
    got2 = rendering.render_frame_cached(prep, model=model, cache_dir=cache, progress=said.append)
    ref2 = render_frame(prep, model=jnp.asarray(model))
    assert rendering.CACHE_STATS["program_memory_hit"] == mem + 1 and len(said) == 1
    assert np.array_equal(np.asarray(got2.xyz), np.asarray(ref2.xyz))
    assert not np.array_equal(np.asarray(got2.xyz), np.asarray(got.xyz))
    with pytest.raises(InputError) as e:
        rendering.render_frame_cached(prep, model=model[:1], cache_dir=cache)
    assert e.value.field == "model"


@pytest.mark.slow  # two more compiles of the frame program (one in-process, one in a child);
# the default tier loads stored programs in fresh processes in
# test_programs_stored_by_a_busy_process_load_elsewhere[none]
def test_render_frame_cached_across_folders_and_fresh_processes(config, tmp_path):
    from spectral_fit.rendering import render_frame

    prep = rendering.prepare_cached(config, cache_dir=tmp_path / "cache", mode="none")
    ref = render_frame(prep)
    rendering.render_frame_cached(prep, cache_dir=tmp_path / "cache")
    # another cache folder is consulted (and filled), not served from this one's program
    other = tmp_path / "other"
    misses = rendering.CACHE_STATS["program_miss"]
    got3 = rendering.render_frame_cached(prep, cache_dir=other)
    assert rendering.CACHE_STATS["program_miss"] == misses + 1
    assert list((other / "programs").glob("*.pkl"))
    assert np.array_equal(np.asarray(got3.xyz), np.asarray(ref.xyz))
    # a fresh process stores both entries, and the next fresh process finds them on disk and
    # renders the same frame without compiling. (The entries are written by a fresh process,
    # as `spectral-fit render` does: an executable compiled in a process that has compiled
    # many other programs before, like this test session, can reference kernels of those
    # programs and then fails to load elsewhere; render_frame_cached recompiles it then.)
    runs = _two_fresh_runs(_FRAME, config, tmp_path)
    assert "'prepared_miss': 1" in runs[0].stdout and "'program_miss': 1" in runs[0].stdout
    assert "'prepared_hit': 1" in runs[1].stdout and "'program_hit': 1" in runs[1].stdout
    assert "'program_miss': 0" in runs[1].stdout
    for i in range(2):
        assert np.array_equal(np.load(tmp_path / f"xyz{i}.npy"), np.asarray(ref.xyz))


_GATHER = """
import sys
import numpy as np
from spectral_fit import rendering
prep = rendering.prepare_cached(sys.argv[1], mode="gather")
f = rendering.render_frame_cached(prep)
np.save(sys.argv[2], np.asarray(f.xyz))
print(rendering.CACHE_STATS, prep.interreflection.mode)
"""


@pytest.mark.slow  # two fresh processes compiling a gather frame's two programs; the
# default tier stores and loads a frame program across processes (none mode) and
# checks the split frame in-process (test_ir_reuse)
def test_gather_frame_is_kept_as_two_programs(config, tmp_path):
    """A gather frame is stored as the senders' half and the rest (two entries, loaded side
    by side in a new process); the frame is the one-program frame to float rounding, and
    the loaded programs give the compiling process's frame bit for bit."""
    from spectral_fit.rendering import prepare, render_frame

    runs = _two_fresh_runs(_GATHER, config, tmp_path)
    fresh = tmp_path / "fresh"
    assert "gather" in runs[0].stdout
    assert "'program_miss': 2" in runs[0].stdout and "'program_hit': 0" in runs[0].stdout
    assert "'program_hit': 2" in runs[1].stdout and "'program_miss': 0" in runs[1].stdout
    assert len(list((fresh / "programs").glob("*.pkl"))) == 2
    a, b = np.load(tmp_path / "xyz0.npy"), np.load(tmp_path / "xyz1.npy")
    assert np.array_equal(a, b)
    prep = prepare(config, mode="gather")
    ref = np.asarray(render_frame(prep).xyz)
    assert np.abs(a - ref).max() <= 1e-5 * np.abs(ref).max()
    # the interreflection (the senders' half) matters in this frame: the test can tell
    none = prepare(config, mode="none")
    assert np.abs(np.asarray(render_frame(none).xyz) - ref).max() > 1e-3 * np.abs(ref).max()
    assert _program_cache._split_program(prep) and not _program_cache._split_program(none)


def test_single_threaded_blas_sets_and_restores_openblas_threads():
    import ctypes

    x = np.random.default_rng(0).random((300, 40))
    ref = x.T @ x  # loads NumPy's BLAS
    with open("/proc/self/maps") as fh:
        libs = sorted({line.split()[-1] for line in fh if "openblas" in line.lower()
                       and "numpy" in line})
    if not libs:
        pytest.skip("NumPy is not linked to a loadable OpenBLAS here")
    lib = ctypes.CDLL(libs[0])
    get = getattr(lib, "scipy_openblas_get_num_threads64_", None) or lib.openblas_get_num_threads
    before = get()
    with process.single_threaded_blas():
        assert get() == 1
        np.testing.assert_allclose(x.T @ x, ref, rtol=1e-12)
    assert get() == before


_ENABLE = """
import json, os, sys
import jax
from spectral_fit import rendering
a = rendering.enable_compilation_cache(sys.argv[1], min_compile_time_s=0.25)
cfg = [jax.config.jax_compilation_cache_dir,
       jax.config.jax_persistent_cache_min_compile_time_secs]
os.environ["SPECTRAL_FIT_JAX_CACHE"] = ""
b = rendering.enable_compilation_cache()
c = rendering.enable_compilation_cache(os.path.join(sys.argv[2], "sub"))
print(json.dumps({"a": a, "cfg": cfg, "b": b, "c": c, "tag": rendering.library_versions_tag()}))
"""


def test_enable_compilation_cache(tmp_path):
    # process-global JAX settings: checked in a fresh process
    blocked = tmp_path / "file"
    blocked.write_text("not a folder")
    r = subprocess.run([sys.executable, "-c", _ENABLE, str(tmp_path / "jax"), str(blocked)],
                       capture_output=True, text=True, env=_env(tmp_path), timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    # programs go to a folder of the library versions under the given one
    folder = tmp_path / "jax" / out["tag"]
    assert out["tag"].startswith(f"jax-{jax.__version__}_jaxlib-{jax.lib.__version__}_")
    assert out["a"] == str(folder) and folder.is_dir()
    assert out["cfg"] == [str(folder), 0.25]
    assert out["b"] is None  # disabled by the empty variable
    assert out["c"] is None  # a folder that cannot be created leaves the cache off


class _Dist:
    """A stand-in for an installed distribution's metadata (name and version)."""

    def __init__(self, name: str, version: str):
        self.metadata = {"Name": name}
        self.version = version


def test_caches_are_keyed_by_the_library_versions(config, tmp_path, monkeypatch):
    """A prepared scene stored under one jaxlib, or one CUDA plugin, is never loaded under
    another, and JAX's compiled programs go to another folder: installed versions are faked
    through the metadata the key reads, so that a real second install is not needed."""
    import importlib.metadata as md

    cache = tmp_path / "cache"
    real_version, real_dists = md.version, md.distributions
    base = rendering.library_versions()
    assert base["jax"] == jax.__version__ and base["jaxlib"] == jax.lib.__version__
    assert base["python"] == sys.version.split()[0]

    def stats() -> tuple[int, int]:
        return rendering.CACHE_STATS["prepared_hit"], rendering.CACHE_STATS["prepared_miss"]

    def prepare_counts() -> tuple[int, int]:
        _keys._environment_digest.cache_clear()
        h0, m0 = stats()
        rendering.prepare_cached(config, cache_dir=cache, mode="none")
        h1, m1 = stats()
        return h1 - h0, m1 - m0

    try:
        prepare_counts()  # stored (or already there)
        assert prepare_counts() == (1, 0)  # same versions: a hit
        tags = {rendering.library_versions_tag()}

        monkeypatch.setattr(md, "version",
                            lambda d: "0.0.1" if d == "jaxlib" else real_version(d))
        assert rendering.library_versions()["jaxlib"] == "0.0.1"
        assert prepare_counts() == (0, 1)  # another jaxlib: a miss, prepared again
        assert prepare_counts() == (1, 0)
        tags.add(rendering.library_versions_tag())

        monkeypatch.setattr(md, "distributions", lambda: [
            *real_dists(), _Dist("jax-cuda12-plugin", "0.0.1"), _Dist("jax_cuda12_pjrt", "0.0.1")])
        v = rendering.library_versions()
        assert v["jax-cuda12-plugin"] == "0.0.1" and v["jax-cuda12-pjrt"] == "0.0.1"
        assert prepare_counts() == (0, 1)  # a plugin installed: a miss
        tags.add(rendering.library_versions_tag())
        assert len(tags) == 3

        monkeypatch.setattr(md, "version", real_version)
        monkeypatch.setattr(md, "distributions", real_dists)
        assert prepare_counts() == (1, 0)  # back to the real set: its entry is still there
    finally:
        _keys._environment_digest.cache_clear()


@pytest.mark.slow  # the frame program compiled three times, twice in child processes
def test_stored_program_that_cannot_run_is_compiled_again(config, tmp_path, monkeypatch):
    """A program loaded from disk that fails when run (e.g. a kernel missing from the stored
    executable) is compiled again instead of failing the frame."""
    import jax.experimental.serialize_executable as se

    from spectral_fit.rendering import render_frame

    cache = tmp_path / "cache"
    prep = rendering.prepare_cached(config, cache_dir=cache, mode="none")
    rendering.render_frame_cached(prep, cache_dir=cache, background=False)  # stores the program
    _program_cache._PROGRAMS.clear()

    def broken(*args, **kwargs):
        def run(arrays):
            raise RuntimeError("NOT_FOUND: Function bitcast_copy_fusion not found")
        return run

    monkeypatch.setattr(se, "deserialize_and_load", broken)
    misses = rendering.CACHE_STATS["program_miss"]
    got = rendering.render_frame_cached(prep, cache_dir=cache, background=False)
    assert rendering.CACHE_STATS["program_miss"] == misses + 1
    ref = render_frame(prep, background=False)
    assert np.array_equal(np.asarray(got.xyz), np.asarray(ref.xyz))


_REUSE = r"""
import ctypes, json, resource, sys
from spectral_fit._runtime import process as process
applied = process.retain_freed_memory() if sys.argv[1] == "on" else None
libc = ctypes.CDLL(None)
libc.malloc.restype = ctypes.c_void_p
libc.malloc.argtypes = (ctypes.c_size_t,)
libc.free.argtypes = (ctypes.c_void_p,)
N = 96 << 20  # above any mmap threshold, as XLA's temporaries of a frame

def round_trip():  # what XLA does with a run's temporaries: malloc, write, free
    p = libc.malloc(N)
    ctypes.memset(p, 1, N)
    libc.free(p)

for _ in range(3):  # warm up: the first rounds may grow the heap
    round_trip()
r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(5):
    round_trip()
faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0) / 5
print(json.dumps({"applied": applied, "faults": faults}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_retain_freed_memory_reuses_large_blocks():
    """A 96 MB block allocated, written and freed again and again: glibc maps and unmaps it
    every time (24,576 fresh 4 kB pages, one fault each); after ``retain_freed_memory`` the
    heap keeps it and later rounds fault no page (the kernel's fault counter, in fresh
    processes)."""
    import platform

    if platform.libc_ver()[0] != "glibc":
        pytest.skip("not glibc")
    out = {}
    for mode in ("off", "on"):
        r = subprocess.run([sys.executable, "-c", _REUSE, mode], capture_output=True, text=True,
                           check=True, timeout=120)
        out[mode] = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["on"]["applied"] is True
    assert out["off"]["faults"] > 10_000  # 96 MB of fresh 4 kB pages per round (24,576)
    assert out["on"]["faults"] < 100, out


_LOAD = """
import sys
import numpy as np
from spectral_fit import rendering
rendering.enable_compilation_cache()
prep = rendering.prepare_cached(sys.argv[1], mode=sys.argv[3])
f = rendering.render_frame_cached(prep)
np.save(sys.argv[2], np.asarray(f.xyz))
print(rendering.CACHE_STATS)
"""


@pytest.mark.parametrize("mode", ["none", pytest.param("gather", marks=pytest.mark.slow)])
def test_programs_stored_by_a_busy_process_load_elsewhere(config, tmp_path, mode):
    """The programs a process stores run in a new process even when the storing process had
    compiled and loaded many programs before (this test session; or a process whose JAX
    persistent cache is warm): XLA:CPU then lets a new program use kernels of those, and the
    stored executable lacked them ("Function ... not found"). They are compiled by a fresh
    child process instead."""
    from spectral_fit.rendering import render_frame

    cache = tmp_path / "cache"
    # a warm JAX persistent cache: small programs of an earlier process, loaded here
    script = tmp_path / "load.py"
    script.write_text(textwrap.dedent(_LOAD))
    env = _env(cache)
    env["SPECTRAL_FIT_JAX_CACHE"] = str(cache / "jax")
    prep = rendering.prepare_cached(config, cache_dir=cache, mode=mode)
    ref = np.asarray(render_frame(prep).xyz)
    misses = rendering.CACHE_STATS["program_miss"]
    got = rendering.render_frame_cached(prep, cache_dir=cache)  # compiled by a child, stored
    parts = 2 if mode == "gather" else 1
    assert rendering.CACHE_STATS["program_miss"] == misses + parts
    assert len(list((cache / "programs").glob("*.pkl"))) == parts
    assert not list((cache / "programs").glob(".job-*"))  # the child's input is removed
    for i in range(2):
        r = subprocess.run([sys.executable, str(script), str(config),
                            str(tmp_path / f"xyz{i}.npy"), mode], capture_output=True,
                           text=True, env=env, timeout=900)
        assert r.returncode == 0, r.stderr[-2000:]
        assert f"'program_hit': {parts}" in r.stdout and "'program_miss': 0" in r.stdout, (
            r.stdout)
        assert np.array_equal(np.load(tmp_path / f"xyz{i}.npy"), np.asarray(got.xyz))
    tol = 0.0 if mode == "none" else 1e-5 * np.abs(ref).max()
    assert np.abs(np.asarray(got.xyz) - ref).max() <= tol


_RENDER_MODULES = r"""
import json, sys
from spectral_fit.cli import main
rc = main(["render", *sys.argv[1:]])
print(json.dumps({"rc": rc, "colour": "colour" in sys.modules}))
"""


def test_warm_cli_render_reads_no_config_and_imports_no_colour(config, tmp_path, capsys,
                                                               monkeypatch):
    """`spectral-fit render` with the config's prepared scene stored takes it from the store
    and does not parse the config, so colour-science (whose package import also loads its
    plotting and matplotlib, ~0.7 s) is not imported; the RGB EXR's colourspace still comes
    from the config; an edited config is read and checked again (its errors name the field)."""
    import OpenEXR

    from spectral_fit.cli import main

    cache = tmp_path / "cache"
    env = _env(cache)
    env["SPECTRAL_FIT_JAX_CACHE"] = ""
    cfg = tmp_path / "scene.toml"
    assert "[display]" not in config.read_text()
    cfg.write_text(config.read_text() + '\n[display]\ncolourspace = "Adobe RGB (1998)"\n')

    def render(*extra: str) -> dict:
        r = subprocess.run([sys.executable, "-c", _RENDER_MODULES, str(cfg), "-o",
                            str(tmp_path / "f.png"), "--mode", "none", *extra],
                           capture_output=True, text=True, env=env, timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
        return json.loads(r.stdout.strip().splitlines()[-1])

    assert render() == {"rc": 0, "colour": True}  # the scene prepared: the config parsed
    assert render() == {"rc": 0, "colour": False}  # stored: neither
    rgb = tmp_path / "rgb.exr"
    assert render("--rgb-exr", str(rgb)) == {"rc": 0, "colour": True}
    assert OpenEXR.File(str(rgb), header_only=True).header()["colourspace"] == \
        "Adobe RGB (1998)"
    # an edited config is another entry: read and checked again
    monkeypatch.setenv("SPECTRAL_FIT_CACHE", str(cache))
    cfg.write_text(cfg.read_text().replace("Adobe RGB (1998)", "Nonesuch RGB"))
    rc = main(["render", str(cfg), "-o", str(tmp_path / "g.png"), "--mode", "none"])
    err = capsys.readouterr().err
    assert rc == 2 and "display.colourspace" in err and "Nonesuch RGB" in err, err


@pytest.mark.slow
def test_cli_programs_stored_after_a_warm_jax_cache_are_reused(tmp_path):
    """The reproducer of the stored-program failure (before the programs were compiled by a
    child process): `spectral-fit render` of the benchmark scene, then of the same scene at
    360 x 240 twice, sharing all caches. The 360 x 240 programs used to be compiled in a
    process that had loaded programs from JAX's persistent cache; the next process could not
    run them ("Function ... not found"), compiled them again and stored them again, on every
    run. Now the third run loads them and leaves them as they are."""
    env = _env(tmp_path / "cache")
    env["SPECTRAL_FIT_JAX_CACHE"] = str(tmp_path / "cache" / "jax")
    cfg = str(ROOT / "configs" / "benchmark.toml")

    def render(*extra: str) -> None:
        r = subprocess.run([sys.executable, "-m", "spectral_fit", "render", cfg, "-o",
                            str(tmp_path / "f.png"), *extra], capture_output=True, text=True,
                           env=env, timeout=1800)
        assert r.returncode == 0, r.stderr[-2000:]

    render()
    render("--size", "360x240")
    programs = tmp_path / "cache" / "programs"
    before = {p.name: p.stat().st_mtime_ns for p in programs.glob("*.pkl")}
    assert len(before) == 4  # two programs per size
    render("--size", "360x240")
    assert {p.name: p.stat().st_mtime_ns for p in programs.glob("*.pkl")} == before


_FASTBINS = r"""
import ctypes, gc, json
from spectral_fit._runtime import process as process

class MallInfo2(ctypes.Structure):
    _fields_ = [(k, ctypes.c_size_t) for k in ("arena", "ordblks", "smblks", "hblks", "hblkhd",
                                               "usmblks", "fsmblks", "uordblks", "fordblks",
                                               "keepcost")]

libc = ctypes.CDLL(None)
libc.mallinfo2.restype = MallInfo2
libc.malloc.restype = ctypes.c_void_p
libc.malloc.argtypes = (ctypes.c_size_t,)
libc.free.argtypes = (ctypes.c_void_p,)

def freed_small_blocks():
    # 2,000 blocks of 48 bytes, every other one freed (the kept ones stop them merging):
    # glibc keeps the freed ones in its fastbins unless they are off (tcache takes 7).
    # Nothing larger may be freed between the first free and the count: a free that leaves
    # 64 KiB or more of free space in one piece (the temporary list of a slice, next to the
    # heap's top) consolidates the fastbins (malloc.c, FASTBIN_CONSOLIDATION_THRESHOLD), so
    # both halves are listed, and the collector is off, before anything is freed.
    ptrs = [libc.malloc(48) for _ in range(2000)]
    freed, kept = ptrs[::2], ptrs[1::2]
    gc.disable()
    for p in freed:
        libc.free(p)
    n = libc.mallinfo2().smblks
    gc.enable()
    for p in kept:
        libc.free(p)
    return n

before = freed_small_blocks()
with process.without_fastbins():
    with process.without_fastbins():  # nested (two loading threads): one restore, at the end
        inside = freed_small_blocks()
    still = freed_small_blocks()
after = freed_small_blocks()
print(json.dumps({"before": before, "inside": inside, "still": still, "after": after}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_fastbins_are_off_while_programs_load_and_back_after():
    """``_without_fastbins`` (around loading stored programs and their first run) turns
    glibc's fastbins off and back on when the outermost user leaves: the fastbin blocks that
    glibc's own statistics (``mallinfo2().smblks``) count after freeing many small blocks, in
    a fresh process."""
    import platform

    if platform.libc_ver()[0] != "glibc" or tuple(
            int(x) for x in platform.libc_ver()[1].split(".")[:2]) < (2, 33):
        pytest.skip("needs glibc 2.33 (mallinfo2)")
    r = subprocess.run([sys.executable, "-c", _FASTBINS], capture_output=True, text=True,
                       check=True, timeout=120)
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["before"] > 500, out  # ~993 (1,000 freed, 7 in tcache)
    assert out["inside"] == 0 and out["still"] == 0, out
    assert out["after"] > 500, out


def test_default_fastbin_limit(monkeypatch):
    """The limit restored after loading: glibc's default, 64 · sizeof(size_t) / 4 bytes
    (malloc.c, DEFAULT_MXFAST), or the process's ``glibc.malloc.mxfast`` tunable."""
    import ctypes

    monkeypatch.delenv("GLIBC_TUNABLES", raising=False)
    assert process._default_mxfast() == 64 * ctypes.sizeof(ctypes.c_size_t) // 4
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.malloc.arena_max=2:glibc.malloc.mxfast=64")
    assert process._default_mxfast() == 64
