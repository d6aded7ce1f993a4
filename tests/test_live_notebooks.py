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


def _run(name: str) -> nbformat.NotebookNode:
    nb = nbformat.read(ROOT / "notebooks" / name, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
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
