"""Video in/out: frame counts read back, clear errors for missing/corrupt video, atomicity."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("cv2")

from spectral_fit._runtime.errors import InputError
from spectral_fit.live import VideoSink, VideoSource, count_frames, read_frames


def _ramp(i, shape=(48, 64)):
    f = np.zeros((*shape, 3), np.uint8)
    f[..., 0] = 20 * i
    f[..., 1] = np.arange(shape[1], dtype=np.uint8)[None, :] * 3
    f[..., 2] = 200 - 10 * i
    return f


@pytest.mark.parametrize("ext", [".mp4", ".avi"])
def test_written_video_reads_back_complete(tmp_path, ext):
    path = tmp_path / f"out{ext}"
    with VideoSink(path, fps=24.0, size=(48, 64)) as sink:
        for i in range(9):
            sink.write(_ramp(i))
    assert sink.frames == 9
    assert count_frames(path) == 9
    src = VideoSource(path)
    assert (src.width, src.height) == (64, 48)
    assert src.fps == pytest.approx(24.0, rel=1e-3)
    frames = read_frames(path)
    src.close()
    assert len(frames) == 9
    # lossy codecs: the mean colour of each frame survives, in RGB order (not BGR)
    for i, f in enumerate(frames):
        np.testing.assert_allclose(f.reshape(-1, 3).mean(0), _ramp(i).reshape(-1, 3).mean(0),
                                   atol=4.0)
    assert [p.name for p in tmp_path.iterdir()] == [f"out{ext}"]


def test_missing_video_names_the_file(tmp_path):
    with pytest.raises(InputError, match="video file not found") as e:
        VideoSource(tmp_path / "nope.mp4")
    assert "nope.mp4" in str(e.value) and e.value.field == "--video"


@pytest.mark.parametrize("content", [b"", np.random.default_rng(5).bytes(4096),
                                     b"\x00\x00\x00\x18ftypmp42" * 50],
                         ids=["empty", "random", "truncated-mp4-header"])
def test_corrupt_video_is_a_clear_error(tmp_path, content):
    p = tmp_path / "bad.mp4"
    p.write_bytes(content)
    with pytest.raises(InputError, match="corrupt") as e:
        VideoSource(p)
    assert str(e.value).startswith(str(p))


def test_truncated_video_is_an_error_or_shorter(tmp_path):
    """A cut file either fails to open with a clear error (AVI: index lost) or yields the
    frames that decode; never a raw OpenCV exception or a None frame."""
    good = tmp_path / "good.avi"
    with VideoSink(good, fps=10.0, size=(48, 64)) as sink:
        for i in range(10):
            sink.write(_ramp(i))
    data = good.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: len(data) // 2])
    try:
        n = count_frames(cut)
    except InputError as e:
        assert str(e).startswith(str(cut)) and "corrupt" in str(e)
    else:
        assert 1 <= n < 10


def test_interrupted_write_leaves_no_file(tmp_path):
    path = tmp_path / "out.mp4"
    with pytest.raises(KeyError), VideoSink(path, fps=24.0, size=(48, 64)) as sink:
        sink.write(_ramp(0))
        raise KeyError("interrupted")
    assert list(tmp_path.iterdir()) == []


def test_sink_rejects_bad_input(tmp_path):
    with pytest.raises(InputError, match="extension"):
        VideoSink(tmp_path / "x.gif", fps=24.0, size=(8, 8))
    with pytest.raises(InputError, match="frame rate"):
        VideoSink(tmp_path / "x.mp4", fps=0.0, size=(8, 8))
    with pytest.raises(InputError, match=r"\(48, 64, 3\) uint8"), \
            VideoSink(tmp_path / "x.mp4", fps=24.0, size=(48, 64)) as sink:
        sink.write(np.zeros((48, 64, 3), np.float32))


def test_missing_camera_is_a_clear_error():
    with pytest.raises(InputError, match="cannot open camera 97") as e:
        VideoSource(97, field="--camera")
    assert e.value.field == "--camera"
