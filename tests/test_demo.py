"""The main job: the CLI, the demo end to end at small size, and the notebook example."""

import os
import subprocess
import sys

import numpy as np
import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _cli(*args, cwd=None, env_extra=None):
    env = dict(os.environ, PYTHONPATH=REPO, MPLBACKEND="Agg", **(env_extra or {}))
    return subprocess.run([sys.executable, "-m", "fastsdf", *args], capture_output=True,
                          text=True, env=env, cwd=cwd, timeout=600)


@pytest.mark.parametrize("args,needle", [
    ([], "COMMAND"),
    (["demo", "--particles", "0"], "--particles"),
    (["demo", "--particles", "abc"], "--particles"),
    (["demo", "--steps", "-3"], "--steps"),
    (["demo", "--grid", "1"], "--grid"),
    (["demo", "--frames", "2.5"], "--frames"),
    (["demo", "--bogus"], "unrecognized"),
    (["nonsense"], "invalid choice"),
])
def test_cli_rejects_bad_arguments_with_exit_code_2(args, needle):
    res = _cli(*args)
    assert res.returncode == 2
    assert needle in res.stderr


def test_cli_help():
    res = _cli("demo", "--help")
    assert res.returncode == 0
    for flag in ("--particles", "--steps", "--grid", "--exact", "--seed", "--out"):
        assert flag in res.stdout


def _hex(color):
    from matplotlib.colors import to_rgb
    return np.array(to_rgb(color))


@pytest.mark.slow
@pytest.mark.parametrize("exact", [False, True])
def test_demo_runs_end_to_end_and_draws_the_world(tmp_path, exact):
    from matplotlib.image import imread

    from fastsdf.demo import run_demo
    from fastsdf.plotting import SOLID_COLOR, render_frame
    from fastsdf.render import PARTICLE_COLOR
    from fastsdf.scenes import box_world

    res = run_demo(particles=3000, steps=45, grid=120, exact=exact, seed=3, out=str(tmp_path),
                   frames=3)
    assert res.particle_steps_per_second > 0 and res.steps == 45
    assert os.path.exists(res.last_frame) and os.path.exists(res.animation)
    assert (res.grid_band_value_max is None) == exact
    assert res.inside_fraction < 0.01
    img = imread(res.last_frame)[..., :3]
    world = box_world(20, seed=3)
    probes = [(0.0, -1.95), (-1.9, -1.0), (1.9, -1.0)]  # deep in the funnel's floor and walls
    assert np.all(world(*np.array(probes).T) < -0.05)
    # Map data coordinates to PNG pixels with the same figure layout render_frame uses.
    fig = render_frame(world, np.zeros(0), np.zeros(0))
    to_px = fig.axes[0].transData
    height = img.shape[0]

    def pixel(x, y):
        px, py = to_px.transform((x, y))
        return img[int(round(height - py)), int(round(px))]

    for x, y in probes:
        np.testing.assert_allclose(pixel(x, y), _hex(SOLID_COLOR), atol=0.02)
    # Particles are drawn (as circles at this count) and sit above the floor.
    is_particle = np.all(np.abs(img - _hex(PARTICLE_COLOR)) < 0.08, axis=-1)
    assert is_particle.sum() > 50
    rows = np.nonzero(is_particle)[0]
    floor_row = height - to_px.transform((0.0, -1.8))[1]
    assert np.median(rows) < floor_row


@pytest.mark.slow
def test_notebook_example_runs_every_cell(tmp_path):
    env = dict(os.environ, PYTHONPATH=REPO, MPLBACKEND="Agg", FASTSDF_EXAMPLE_SMALL="1")
    res = subprocess.run([sys.executable, os.path.join(REPO, "examples", "seed_notebook.py"),
                          str(tmp_path)], capture_output=True, text=True, env=env, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "[-1.] [0.] [140.42135624]" in res.stdout  # cell 2's printed output
    assert "(length(x, y) - 1)" in res.stdout  # cell 3: the expression
    for name in ("cell_04.png", "cell_09.png", "cell_13.png", "cell_18.html", "cell_21.html",
                 "cell_22.html"):
        assert (tmp_path / name).stat().st_size > 1000, name
