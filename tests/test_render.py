"""Drawing apart from physics: animate() never resets, save_animation() picks writers, the
notebook's reset(ax)/update(ax) draw through render, and the colour bar of a density image."""

import os

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

import fastsdf as sdf
import fastsdf.particles as phys
from fastsdf.viz import render
from fastsdf.viz.render import animate, draw_particles, save_animation

# Animations stepped by hand (not saved) are fine to drop.
pytestmark = pytest.mark.filterwarnings("ignore:Animation was deleted")


@pytest.fixture(scope="module")
def floor():
    return sdf.Halfspace(normal=[0, 1], d=-1.5)


def new_axes():
    fig = Figure(figsize=(3, 3), dpi=40)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.set_xlim(-2, 2)
    ax.set_ylim(-2, 2)
    return fig, ax


def test_animate_continues_the_simulation_and_never_resets(floor):
    sim = phys.ParticleSimulation(floor, n=50, seed=0)
    sim.force_generators.append(phys.Gravity())
    sim.run(30)
    after_run = sim.p["x"].copy()
    twin = phys.ParticleSimulation(floor, n=50, seed=0)
    twin.force_generators.append(phys.Gravity())
    twin.run(30 + 2 * 3)  # three frames after the first, two steps each
    fig, ax = new_axes()
    anim = animate(sim, ax, frames=4, steps_per_frame=2, title="drop, ")
    # Frame 0 shows the state as it is, with no step.
    anim._init_draw()
    anim._func(0)
    np.testing.assert_array_equal(sim.p["x"], after_run)
    assert ax.get_title() == "drop, t = 1.00 s (step 30)"
    for i in range(1, 4):
        anim._func(i)
    np.testing.assert_allclose(sim.p["x"], twin.p["x"])
    assert ax.get_title() == "drop, t = 1.20 s (step 36)"
    np.testing.assert_allclose(anim.particle_layer.artist.get_offsets(), sim.p["x"])


def test_animate_schedule_per_frame_and_custom_advance(floor):
    sim = phys.ParticleSimulation(floor, n=10, seed=0)
    calls = []

    def advance(k):
        calls.append(k)
        sim.run(k)

    fig, ax = new_axes()
    anim = animate(sim, ax, frames=3, steps_per_frame=[0, 5, 1], advance=advance, title=None)
    for i in range(3):
        anim._func(i)
    assert calls == [5, 1] and ax.get_title() == ""
    with pytest.raises(ValueError, match="steps_per_frame"):
        animate(sim, ax, frames=3, steps_per_frame=[1, 2])
    with pytest.raises(ValueError, match="frames"):
        animate(sim, ax, frames=0)


@pytest.mark.parametrize("ext", [".mp4", ".gif", ".html"])
def test_save_animation_writes_each_format(floor, tmp_path, ext):
    sim = phys.ParticleSimulation(floor, n=20, seed=0)
    fig, ax = new_axes()
    anim = animate(sim, ax, frames=3)
    path = save_animation(anim, str(tmp_path / f"clip{ext}"), fps=10, progress=False)
    assert path == os.path.abspath(str(tmp_path / f"clip{ext}"))
    with open(path, "rb") as fh:
        head = fh.read(64)
    magic = {".mp4": b"ftyp", ".gif": b"GIF8", ".html": b"<"}[ext]
    assert magic in head
    assert abs(sim.t - 2 * sim.dt) < 1e-12  # frames 1 and 2 advanced one step each


def test_save_animation_rejects_unknown_extension_and_missing_ffmpeg(floor, tmp_path, monkeypatch):
    sim = phys.ParticleSimulation(floor, n=5, seed=0)
    fig, ax = new_axes()
    anim = animate(sim, ax, frames=2)
    with pytest.raises(ValueError, match=r"path must end in one of .*\.mp4.*got path="):
        save_animation(anim, str(tmp_path / "clip.avi"))
    import fastsdf.viz.video as video

    monkeypatch.setattr(video, "ffmpeg_available", lambda: False)
    with pytest.raises(RuntimeError, match=r"fastsdf\[video\]"):
        save_animation(anim, str(tmp_path / "clip.mp4"))


def test_notebook_reset_and_update_draw_through_render(floor):
    sim = phys.ParticleSimulation(floor, n=30, seed=0)
    assert not hasattr(sim, "drawable") and not hasattr(sim, "_layer")
    fig, ax = new_axes()
    (first,) = sim.reset(ax)
    assert first in ax.collections
    (again,) = sim.update(ax)
    assert again is first
    np.testing.assert_allclose(again.get_offsets(), sim.p["x"])
    (fresh,) = sim.reset(ax)  # a reset redraws: the old artist leaves the axes
    assert first not in ax.collections and fresh in ax.collections
    assert sim.reset() == () and sim.update() == ()


def test_density_colorbar_counts_particles_per_pixel():
    fig, ax = new_axes()
    rng = np.random.default_rng(0)
    x, y = rng.normal(0, 0.2, 20_000), rng.normal(0, 0.2, 20_000)
    layer = draw_particles(ax, x, y, bounds=[(-2, 2), (-2, 2)], shape=(50, 50), colorbar=True)
    assert layer.mode == "density" and layer.colorbar is not None
    assert layer.colorbar.ax.get_ylabel() == "particles per pixel"
    assert layer.colorbar.norm.vmax == layer.image.max()
    fig.canvas.draw()
    labels = [t.get_text() for t in layer.colorbar.ax.get_yticklabels()]
    assert "1" in labels and not any("times" in t or "^" in t for t in labels), labels
    layer.update(x * 0.5, y * 0.5)  # a new range keeps plain labels
    fig.canvas.draw()
    labels = [t.get_text() for t in layer.colorbar.ax.get_yticklabels()]
    assert layer.colorbar.norm.vmax == layer.image.max()
    assert "10" in labels and not any("times" in t or "^" in t for t in labels), labels
    layer.update(x[:10], y[:10])  # circles: no colour bar
    assert layer.colorbar is None and len(fig.axes) == 1


def test_render_module_layering():
    """render draws on plotting; physics holds no artists; plotting never imports render."""
    import ast
    import inspect

    from fastsdf.viz import plotting

    for module, banned in ((plotting, "render"),):
        tree = ast.parse(inspect.getsource(module))
        mods = {
            getattr(n, "module", "") or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)
        }
        assert not any(banned in m for m in mods)
    assert "render_frame" in render.__all__ and "animate" in render.__all__
