"""The seed notebook (docs/notebook.ipynb) runs every cell in a Jupyter kernel, as a user would.

At the test size (``FASTSDF_EXAMPLE_SMALL=1``, read by the notebook's hidden first cell: at
most 50 particles and 3 frames per animation) it takes well under a minute; the docs build runs
it at the seed's own sizes.
"""

import base64
import os
import re

import numpy as np
import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NOTEBOOK = os.path.join(REPO, "docs", "notebook.ipynb")


def _text(cell):
    return "".join(
        o.get("text", "") + o.get("data", {}).get("text/plain", "") for o in cell.outputs
    )


def _video_frames(cell, path):
    """The frames of the MP4 that the cell's HTML output embeds, as (h, w, 3) arrays."""
    import imageio_ffmpeg

    (html,) = [o["data"]["text/html"] for o in cell.outputs if "text/html" in o.get("data", {})]
    assert "<video" in html
    path.write_bytes(base64.b64decode(re.search(r"base64,([A-Za-z0-9+/=\s]+)\"", html).group(1)))
    reader = imageio_ffmpeg.read_frames(str(path))
    w, h = next(reader)["size"]
    return [np.frombuffer(f, np.uint8).reshape(h, w, 3) for f in reader]


@pytest.mark.slow
def test_notebook_runs_every_cell(tmp_path, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("ipykernel")
    pytest.importorskip("imageio_ffmpeg")
    monkeypatch.setenv("FASTSDF_EXAMPLE_SMALL", "1")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([REPO, os.environ.get("PYTHONPATH", "")]))
    nb = nbformat.read(NOTEBOOK, as_version=4)
    sources = [c.source for c in nb.cells if c.cell_type == "code"]
    nbclient.NotebookClient(
        nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    ).execute()
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert [c.source for c in code] == sources
    # In [2] and In [3]: the seed's numbers (scalars for scalar coordinates, where the seed
    # printed one-element arrays), and the circle's expression
    circle = next(c for c in code if "c = circle()" in c.source)
    assert _text(circle) == "(np.float64(-1.0), np.float64(0.0), np.float64(140.4213562373095))"
    assert "(length(x, y) - 1)" in _text(next(c for c in code if c.source == "c.f"))
    # every figure cell shows its figure
    figures = [c for c in code if "sdf.plot_sdf(fig" in c.source and "HTML(" not in c.source]
    assert len(figures) == 7
    for cell in figures:
        assert any("image/png" in o.get("data", {}) for o in cell.outputs), cell.source
    # every animation is an inline video whose particles move from its first frame to its last
    animations = [c for c in code if "HTML(run_animation" in c.source]
    assert len(animations) == 4
    for cell in animations:
        frames = _video_frames(cell, tmp_path / "video.mp4")
        assert len(frames) == 3, cell.source
        moved = np.abs(frames[0].astype(int) - frames[-1].astype(int)).max(axis=-1) > 40
        assert moved.sum() > 20, (cell.source, int(moved.sum()))
