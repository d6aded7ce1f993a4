"""The gather interreflection's camera-independent half computed once and reused: the split
frame equals the frame that computes it itself, and the live session reuses it only while the
objects stay within its tolerance."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("spectral_fit.rendering._frame")

import jax.numpy as jnp

from spectral_fit._runtime.errors import InputError

# one worker runs this module's tests (ONE_WORKER_MODULES in tests/conftest.py):
# the gather scene's programs are compiled once


def _views():
    from spectral_fit.geometry import look_at

    up = jnp.array([0.0, 1.0, 0.0])
    target = jnp.array([0.0, 0.0, -0.275])
    return [look_at(jnp.array(e), target, up) for e in
            ([0.0, 0.0, 0.0], [0.05, 0.03, -0.02], [-0.06, 0.08, -0.05])]


@pytest.fixture(scope="module")
def prep():
    from spectral_fit.bench.cases.frame import benchmark_scene
    from spectral_fit.rendering import prepare

    return prepare(benchmark_scene(quick=True), size=(96, 64), mode="gather")


def test_split_frame_equals_the_frame_that_computes_its_senders(prep):
    """render_pixels(senders=render_senders(...)) against render_pixels alone, for three
    camera views of one object state (one senders' computation), and for moved objects; the
    interreflection is a visible part of those pixels (so the comparison can fail)."""
    from spectral_fit._runtime.dispatch import array_jit
    from spectral_fit.rendering import TRACE_COUNT, render_pixels, render_senders

    both = jnp.array([True, True])
    # ``visible`` is always passed as an argument: a default would be a constant of the
    # program, and the call that hides an object would compile another one
    run = array_jit(lambda p, model, view, senders, visible: render_pixels(
        p, model=model, view=view, visible=visible, senders=senders, mirror=False))

    def pixels(p, model, view, senders, visible=both):
        return run(p, model, view, senders, visible)

    senders = render_senders(prep, mirror=False)
    n0 = TRACE_COUNT["ir_senders"]
    for view in _views():
        a = pixels(prep, prep.model, view, None).values
        b = pixels(prep, prep.model, view, senders).values
        peak = float(jnp.abs(a).max())
        assert float(jnp.abs(a - b).max()) <= 1e-6 * peak
    # the neighbour 1 km away: the interreflection is a visible part of those pixels
    view = prep.camera.view
    far = pixels(prep, prep.model.at[1, 1, 3].add(-1e3), view, None)
    full = pixels(prep, prep.model, view, None)
    a = full.values
    assert float(jnp.abs(a - far.values).max()) > 1e-3 * float(jnp.abs(a).max())
    # a hidden neighbour (its marker lost) neither lights nor shadows object 0: its pixels
    # are those of the neighbour 1 km away (physically ~1e-9 of the radiance there), finite
    # (the collapsed geometry of a hidden object once made the form factors NaN), and the
    # hidden object covers no pixel
    hidden = pixels(prep, prep.model, view, None, jnp.array([True, False]))
    _same_pixels_of_object_0(hidden, far)
    assert not np.any(np.asarray(hidden.object_id) == 1)
    # another object state: the senders of that state, same compiled programs
    model = prep.model.at[1, 0, 3].add(0.01)
    s2 = render_senders(prep, model=model, mirror=False)
    a = pixels(prep, model, view, None).values
    b = pixels(prep, model, view, s2).values
    c = pixels(prep, model, view, senders).values  # stale senders: differs
    peak = float(jnp.abs(a).max())
    assert float(jnp.abs(a - b).max()) <= 1e-6 * peak
    assert float(jnp.abs(a - c).max()) > 1e-4 * peak
    assert TRACE_COUNT["ir_senders"] == n0


def _same_pixels_of_object_0(got, ref) -> None:
    """The values of ``got``'s object-0 pixels equal ``ref``'s at the same pixels (to 1e-5
    of their peak) and are finite."""
    def on0(f):
        index, valid = np.asarray(f.index), np.asarray(f.valid)
        keep = valid & (np.asarray(f.object_id).reshape(-1)[index] == 0)
        pix = index[keep]
        order = np.argsort(pix)
        return pix[order], np.asarray(f.values)[keep][order]

    pg, vg = on0(got)
    pr, vr = on0(ref)
    np.testing.assert_array_equal(pg, pr)
    assert pg.size > 50 and np.isfinite(vg).all()
    assert np.abs(vg - vr).max() < 1e-5 * np.abs(vr).max()


@pytest.mark.slow  # the split frame's test above runs the same senders' path in the default tier
def test_render_frame_with_senders_equals_the_frame(prep):
    """render_frame(senders=...) (a turntable or camera path over objects that stay put)
    against render_frame alone, two camera views of one senders' state; without the
    interreflection the frame differs visibly (so the comparison can fail)."""
    from spectral_fit.rendering import render_frame, render_senders

    senders = render_senders(prep, mirror=False)
    for view in _views()[1:]:
        a = render_frame(prep, view=view, mirror=False).xyz
        b = render_frame(prep, view=view, mirror=False, senders=senders).xyz
        peak = float(jnp.abs(a).max())
        assert float(jnp.abs(a - b).max()) <= 1e-6 * peak
    vis = jnp.array([True, False])  # the neighbour hidden: no interreflection on object 0
    lone = render_frame(prep, visible=vis, mirror=False)
    full = render_frame(prep, mirror=False, senders=senders)
    on0 = np.asarray(lone.object_id) == 0
    assert float(jnp.abs(full.xyz - lone.xyz)[on0].max()) > 1e-3 * float(jnp.abs(full.xyz).max())


def test_senders_need_gather_mode():
    from spectral_fit.bench.cases.frame import benchmark_scene
    from spectral_fit.rendering import prepare, render_frame, render_pixels, render_senders

    p = prepare(benchmark_scene(quick=True), size=(48, 32), mode="none")
    with pytest.raises(InputError, match="gather"):
        render_senders(p)
    with pytest.raises(InputError, match="senders"):
        render_pixels(p, senders=object())
    with pytest.raises(InputError, match="senders"):
        render_frame(p, senders=object())
    import dataclasses

    p0 = dataclasses.replace(p, interreflection=dataclasses.replace(
        p.interreflection, mode="gather", bounces=0))  # bounces = 0: nothing to send
    with pytest.raises(InputError, match="0 bounces"):
        render_senders(p0)


def test_max_displacement_is_the_largest_vertex_displacement():
    """The bounding-box corner bound against the displacement of every vertex of a mesh,
    brute force, for random rigid motions and a scaled one."""
    from spectral_fit.io import rotate, uv_sphere
    from spectral_fit.live._senders_reuse import _max_displacement

    sph = uv_sphere(0.03, 16, 16)
    v = np.c_[sph.vertices, np.ones(len(sph.vertices))]
    lo, hi = sph.vertices.min(0), sph.vertices.max(0)
    corners = np.array([[[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                         for z in (lo[2], hi[2])]])
    rng = np.random.default_rng(3)
    for k in range(20):
        a = rotate(rng.normal(size=3), rng.uniform(0, 6.3))
        a[:3, 3] = rng.normal(size=3) * 0.1
        b = rotate(rng.normal(size=3), rng.uniform(0, 0.01)) @ a
        b[:3, 3] += rng.normal(size=3) * 1e-3
        if k == 0:
            b[:3, :3] *= 1.01
        brute = np.sqrt((((v @ (b - a).T)[:, :3]) ** 2).sum(-1)).max()
        bound = _max_displacement(corners, a[None], b[None])
        assert brute <= bound + 1e-12
        # and it is not loose by more than the box's corners beyond the sphere (√3)
        assert bound <= np.sqrt(3) * brute + 1e-12
    assert _max_displacement(corners[:0], a[None][:0], b[None][:0]) == 0.0  # none visible


@pytest.mark.slow  # two live steps in gather mode and the senders' program compiled
def test_live_session_reuses_senders_while_objects_stay_put():
    """A session with reuse against one without (``ir_reuse_mm=None``: every step computes
    it): the same frames (within one 8-bit level) for a moving camera; the senders' half is
    computed once for objects that stay put, again after a move beyond the tolerance or a
    visibility change, and nothing recompiles."""
    import dataclasses

    from helpers.live import scene_dict

    from spectral_fit.io import parse_scene
    from spectral_fit.live import STEP_TRACES, LiveSession, Poses
    from spectral_fit.rendering import TRACE_COUNT

    d = scene_dict(markers={"size": 0.08}, width=120, height=80, intrinsics=False)
    for o in d["objects"]:
        o["stacks"] = o["slices"] = 16
    d["interreflection"] = {"mode": "gather"}
    scene = parse_scene(d)
    fused = LiveSession(scene, size=(80, 120), ir_reuse_mm=None)
    reuse = LiveSession(scene, size=(80, 120), ir_reuse_mm=0.5)
    base = np.array(fused.prep.model, np.float64)
    base[0, :3, 3] = (-0.04, 0.0, -0.3)
    base[1, :3, 3] = (0.04, 0.0, -0.3)
    views = [np.asarray(v, np.float64) for v in _views()]
    bg = np.full((80, 120, 3), 90, np.uint8)
    vis = np.array([True, True])

    def frame(s, model, view, visible=vis):
        p = Poses(model.astype(np.float32), view.astype(np.float32), visible)
        out, _ = s.render(p, bg)
        return np.asarray(out).astype(int)

    for v in views:  # the camera moves, the objects stay
        np.testing.assert_allclose(frame(reuse, base, v), frame(fused, base, v), atol=1)
    assert (reuse.ir_updates, reuse.ir_reuses) == (1, 2)
    traces = (STEP_TRACES["step"], TRACE_COUNT["ir_senders"])
    small = base.copy()
    small[1, 0, 3] += 0.3e-3  # within 0.5 mm: reused
    frame(reuse, small, views[1])
    assert (reuse.ir_updates, reuse.ir_reuses) == (1, 3)
    big = base.copy()
    big[1, 0, 3] += 2e-3  # beyond: computed again, and the frame is the fused one's
    np.testing.assert_allclose(frame(reuse, big, views[1]), frame(fused, big, views[1]),
                               atol=1)
    assert (reuse.ir_updates, reuse.ir_reuses) == (2, 3)
    hidden = np.array([True, False])
    np.testing.assert_allclose(frame(reuse, big, views[0], hidden),
                               frame(fused, big, views[0], hidden), atol=1)
    assert (reuse.ir_updates, reuse.ir_reuses) == (3, 3)
    moved = big.copy()
    moved[1, 0, 3] += 5e-3  # the hidden object moved (a held pose's noise): reused
    frame(reuse, moved, views[2], hidden)
    assert (reuse.ir_updates, reuse.ir_reuses) == (3, 4)
    assert (STEP_TRACES["step"], TRACE_COUNT["ir_senders"]) == traces
    with pytest.raises(InputError, match="ir_reuse_mm"):
        LiveSession(dataclasses.replace(scene), size=(80, 120), ir_reuse_mm=-1.0)


def test_live_command_reuse_option():
    """``--ir-reuse-mm``: millimetres >= 0 or 'off'; anything else is refused by name."""
    import argparse

    from spectral_fit.cli.commands.live import _reuse_mm, add_arguments

    assert _reuse_mm("0.5") == 0.5 and _reuse_mm("0") == 0.0 and _reuse_mm("OFF") is None
    for bad in ("-1", "nan", "inf", "half"):
        with pytest.raises(argparse.ArgumentTypeError, match="'off'"):
            _reuse_mm(bad)
    p = argparse.ArgumentParser()
    add_arguments(p)
    assert p.parse_args(["c.toml", "--video", "v.mp4"]).ir_reuse_mm == 0.5
    assert p.parse_args(["c.toml", "--video", "v.mp4", "--ir-reuse-mm", "off"]).ir_reuse_mm \
        is None
