"""The notebooks in notebooks/ execute top to bottom (nbclient, small settings), in the default
tier (about 30 s for the three)."""

from __future__ import annotations

import pytest
from helpers import ROOT

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipywidgets")
pytest.importorskip("cv2")
pytest.importorskip("spectral_fit.rendering._frame")


class _Client(nbclient.NotebookClient):
    """nbclient's client whose wait for a cell's reply on the shell channel is sliced into 1 s
    polls: after a cell that displays widgets, a single wait with the cell's timeout often
    returned only at that timeout although the reply had arrived (jupyter/nbclient#312), which
    made the sliders' notebook take 600 s instead of 20."""

    async def async_start_new_kernel_client(self):  # noqa: ANN201 (nbclient's signature)
        from queue import Empty
        from time import monotonic

        from jupyter_core.utils import ensure_async

        kc = await super().async_start_new_kernel_client()
        channel = kc.shell_channel
        get_msg = channel.get_msg

        async def sliced(timeout: float | None = None, **kwargs):  # noqa: ANN202
            end = None if timeout is None else monotonic() + timeout
            while True:
                step = 1.0 if end is None else max(0.0, min(1.0, end - monotonic()))
                try:
                    return await ensure_async(get_msg(timeout=step, **kwargs))
                except Empty:
                    if end is not None and monotonic() >= end:
                        raise

        channel.get_msg = sliced
        return kc


def _run(name: str) -> nbformat.NotebookNode:
    nb = nbformat.read(ROOT / "notebooks" / name, as_version=4)
    client = _Client(nb, timeout=600, kernel_name="python3",
                     resources={"metadata": {"path": str(ROOT)}})
    client.execute()
    return nb


def _text(nb) -> str:
    return "\n".join(o.get("text", "") for c in nb.cells if c.cell_type == "code"
                     for o in c.get("outputs", []))


def test_render_explore_notebook():
    nb = _run("render_explore.ipynb")
    assert "recompilations caused by the sliders: 0" in _text(nb)


def test_live_mr_notebook():
    nb = _run("live_mr.ipynb")
    text = _text(nb)
    assert "frames written and read back: 6" in text
    assert "recompiles 0" in text


def test_fit_session_notebook():
    nb = _run("fit_session.ipynb")
    text = _text(nb)
    assert "report files:" in text and "fit.json" in text
