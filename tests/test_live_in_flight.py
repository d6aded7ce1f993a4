"""Frames in flight on a CPU split into two JAX devices: the live session renders frame i on
device i mod 2, its run loop keeps two frames submitted, and the pictures are those of a
session on one device. The two-device checks run in a fresh process (the split must happen
before JAX starts its backend)."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest

pytest.importorskip("cv2")
pytest.importorskip("spectral_fit.rendering._frame")

from helpers import ROOT, subprocess_env

from spectral_fit._runtime.errors import InputError

_TWO = textwrap.dedent("""
    import json, sys
    from spectral_fit._runtime import process as process
    from spectral_fit.rendering import _cache as startup
    assert process.split_cpu_devices(2) == 2
    import jax, numpy as np
    from helpers.live import SMALL_SIZE as SIZE, small_frame as _frame, small_scene as _scene
    from skimage import data
    from spectral_fit.live import LiveSession, STEP_TRACES
    from spectral_fit.live import MarkerPlacement, make_table

    mode, reuse = sys.argv[1], float(sys.argv[2])
    devs = jax.devices()
    assert len(devs) == 2 and process.split_cpu_devices(3) == 2  # too late: unchanged
    table = make_table(data.coffee(), [MarkerPlacement(3, -0.06, 0.0, 0.08),
                                       MarkerPlacement(7, 0.07, 0.02, 0.08)])
    eyes = [(0.0, 0.3, 0.25), (0.0, 0.3, 0.25), (0.05, 0.3, 0.24), (0.05, 0.3, 0.24),
            (-0.05, 0.31, 0.25)]
    frames = [_frame(table, e, seed=40 + i)[0] for i, e in enumerate(eyes)]
    one = LiveSession(_scene(hold_frames=0), size=SIZE, mode=mode, devices=devs[:1],
                      ir_reuse_mm=reuse)
    want = [one.process(f) for f in frames]
    # default devices: both
    two = LiveSession(_scene(hold_frames=0), size=SIZE, mode=mode, ir_reuse_mm=reuse)
    got = []
    st = two.run(iter(frames), got.append, threads=False)
    traced = STEP_TRACES["step"]
    recompiles = two.recompiles
    updates = [one.ir_updates, two.ir_updates]
    reuses = [one.ir_reuses, two.ir_reuses]
    # submitted frames alternate between the devices
    pend = [two.submit(f) for f in frames[:2]]
    on = [sorted(str(d) for d in p.out.devices()) for p in pend]
    again = [two.finish(p) for p in pend]
    retraced = STEP_TRACES["step"] != traced
    # buffers too small for both frames in flight: the first to finish re-plans (one
    # recompilation), the second is rendered again with that plan, not re-planned again
    two.prep = two.prep.with_buffers(pixel_capacity=(64,) * two.prep.num_objects)
    before = two.recompiles
    pend = [two.submit(f) for f in frames[2:4]]
    grown = [two.finish(p) for p in pend]
    print(json.dumps({
        "devices": [str(d) for d in two.devices], "on": on,
        "equal": [bool(np.array_equal(a, b)) for a, b in zip(got, want)],
        "max_diff": max(int(np.abs(a.astype(int) - b.astype(int)).max())
                        for a, b in zip(got, want)),
        "again_equal": [bool(np.array_equal(a, b)) for a, b in zip(again, want[:2])],
        "grown_equal": [bool(np.array_equal(a, b)) for a, b in zip(grown, want[2:4])],
        "replans": two.recompiles - before,
        "covered": [int((b != one.undistort(f)).any(axis=-1).sum())
                    for f, b in zip(frames, want)],
        "frames": st.frames, "recompiles": recompiles,
        "retraced": retraced,
        "updates": updates, "reuses": reuses}))
""")


def _two_devices(mode: str, reuse_mm: float = 0.5) -> dict:
    out = subprocess.run([sys.executable, "-c", _TWO, mode, str(reuse_mm)],
                         capture_output=True,
                         text=True, timeout=900,
                         env=subprocess_env())
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def _check(got: dict) -> None:
    assert len(got["devices"]) == 2
    assert got["on"][0] != got["on"][1]  # frame n and n + 1 on different devices
    assert got["frames"] == 5 and got["recompiles"] == 0 and not got["retraced"]
    # the same program on either device: the pictures of the one-device session
    assert all(got["equal"]), got["max_diff"]
    assert all(got["again_equal"])
    assert all(got["grown_equal"]) and got["replans"] == 1
    assert min(got["covered"]) > 500  # the spheres are in the pictures (the test can fail)


@pytest.mark.slow  # two CPU devices in a child process, each compiling the live step
def test_two_devices_render_the_one_device_frames():
    """Without interreflection: frames alternate between the devices, two in flight, and
    equal the one-device session's frames exactly; no retrace after the first frames."""
    _check(_two_devices("none"))


@pytest.mark.slow  # four gather-mode programs compiled (~3 min on a slow 2-core machine)
def test_two_devices_share_the_interreflection_senders():
    """Gather mode: the senders' half computed on one device is copied to the other (not
    computed again) while the objects stay within the tolerance, and the frames equal the
    one-device session's."""
    got = _two_devices("gather", reuse_mm=20.0)  # the markers' pose noise stays within it
    _check(got)
    # without a world marker the objects sit in the camera's frame and move whenever the
    # camera does: computed for frames 0, 2, 4 (device 0) and reused for frames 1 and 3 (same
    # eye; device 1, a copy), whose pictures equal the one-device session's (checked above)
    assert got["updates"] == [3, 3] and got["reuses"] == [2, 2], got


def test_live_command_checks_cpu_devices(tmp_path, capsys):
    from spectral_fit.cli import main

    video = ROOT / "measurements" / "video" / "sample.mp4"
    assert main(["live", str(ROOT / "configs" / "live_sample.toml"), "--video", str(video),
                 "--cpu-devices", "0"]) == 2
    assert "--cpu-devices" in capsys.readouterr().err


def test_devices_argument_is_checked():
    import jax

    from spectral_fit.live._devices import _frame_devices

    assert _frame_devices(None) == tuple(jax.devices())
    assert _frame_devices(jax.devices()[0]) == (jax.devices()[0],)
    for bad in ([], ["cpu:0"], 3, [jax.devices()[0]] * 2):
        with pytest.raises(InputError, match="devices"):
            _frame_devices(bad)


def test_split_after_start_changes_nothing():
    import jax

    from spectral_fit._runtime import process

    jax.numpy.zeros(1)  # the backend is running
    assert process.split_cpu_devices(2) == len(jax.devices("cpu"))
    with pytest.raises(InputError, match=">= 1"):
        process.split_cpu_devices(0)


def test_in_flight_must_be_positive():
    from spectral_fit.live import LiveSession

    s = LiveSession.__new__(LiveSession)
    s.devices = (None,)
    with pytest.raises(InputError, match="in_flight"):
        s.run(iter([np.zeros((2, 2, 3), np.uint8)]), in_flight=0, threads=False)
