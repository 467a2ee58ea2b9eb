"""The main job: the CLI, the demo end to end at small size, and the examples (the notebook:
test_notebook.py)."""

import math
import os
import subprocess
import sys

import numpy as np
import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _cli(*args, cwd=None, env_extra=None):
    env = dict(os.environ, PYTHONPATH=REPO, MPLBACKEND="Agg", **(env_extra or {}))
    return subprocess.run(
        [sys.executable, "-m", "fastsdf", *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=cwd,
        timeout=600,
    )


@pytest.mark.parametrize(
    "args,needle",
    [
        ([], "fastsdf: error: the following arguments are required: COMMAND"),
        (["demo", "--particles", "0"], "fastsdf demo: error: argument --particles"),
        (["demo", "--particles", "abc"], "fastsdf demo: error: argument --particles"),
        (["demo", "--steps", "-3"], "fastsdf demo: error: argument --steps"),
        (["demo", "--grid", "1"], "fastsdf demo: error: argument --grid"),
        (["demo", "--frames", "2.5"], "fastsdf demo: error: argument --frames"),
        (["demo", "--fps", "0"], "fastsdf demo: error: argument --fps"),
        (["demo", "--world", "moon"], "fastsdf demo: error: argument --world"),
        (["demo", "--mode", "linear"], "fastsdf demo: error: argument --mode"),
        (["demo", "--frames", "5", "--steps", "2"], "fastsdf demo: error: --frames 5 is more than"),
        (["demo", "--out", "/proc/nope", "--particles", "10"], "fastsdf demo: error: --out"),
        (["demo", "--bogus"], "unrecognized"),
        (["nonsense"], "fastsdf: error: argument COMMAND: invalid choice"),
    ],
)
def test_cli_errors_are_one_line_with_exit_code_2(args, needle):
    res = _cli(*args)
    assert res.returncode == 2
    assert needle in res.stderr
    assert res.stderr.count("\n") == 1 and res.stdout == "", res.stderr
    assert "Traceback" not in res.stderr


def test_cli_help_and_version():
    from fastsdf.version import __version__

    res = _cli("demo", "--help")
    assert res.returncode == 0
    for flag in (
        "--particles",
        "--steps",
        "--grid",
        "--exact",
        "--seed",
        "--out",
        "--world",
        "--mode",
        "--fps",
        "--frames",
    ):
        assert flag in res.stdout
    res = _cli("--version")
    assert res.returncode == 0 and res.stdout.strip() == f"fastsdf {__version__}"


def test_console_script_is_declared():
    import configparser

    cfg = configparser.ConfigParser()
    cfg.read(os.path.join(REPO, "setup.cfg"))
    scripts = cfg["options.entry_points"]["console_scripts"]
    assert "fastsdf = fastsdf.apps.cli:main" in scripts


def test_main_returns_through_systemexit_for_version(capsys):
    from fastsdf.apps.cli import main

    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0 and capsys.readouterr().out.startswith("fastsdf ")


def test_spawn_in_free_space_leaves_no_particle_in_matter():
    import fastsdf.particles as phys
    from fastsdf.apps.demo import spawn_in_free_space
    from fastsdf.shapes.scenes import box_world

    world = box_world(20, seed=0)
    sim = phys.ParticleSimulation(world, n=2000, seed=1)
    x0 = sim.p["x"].copy()
    before = world(x0[:, 0], x0[:, 1]) - sim.p["r"] < 0
    assert before.sum() > 100  # the notebook's blob overlaps this world's boxes
    moved = spawn_in_free_space(sim, world, np.random.default_rng(0))
    x = sim.p["x"]
    assert moved == before.sum()
    assert np.all(world(x[:, 0], x[:, 1]) - sim.p["r"] >= 0)
    np.testing.assert_array_equal(x[~before], x0[~before])  # free particles stay put


def test_frame_schedule_ends_at_the_last_step():
    from fastsdf.apps.demo import _frame_schedule

    for steps, frames in [(300, 120), (7, 7), (10, 3), (5, 1), (1, 1), (299, 60)]:
        sched = _frame_schedule(steps, frames)
        assert len(sched) == frames and sum(sched) == steps
        assert sched[0] == (steps if frames == 1 else 0) and min(sched[1:] or [1]) >= 1


def _hex(color):
    from matplotlib.colors import to_rgb

    return np.array(to_rgb(color))


@pytest.mark.slow
@pytest.mark.parametrize("exact", [False, True])
def test_demo_runs_end_to_end_and_draws_the_world(tmp_path, exact):
    from matplotlib.image import imread

    from fastsdf.apps.demo import run_demo, summary
    from fastsdf.shapes.scenes import box_world
    from fastsdf.viz.plotting import SOLID_COLOR
    from fastsdf.viz.render import PARTICLE_COLOR, render_frame

    res = run_demo(
        particles=3000,
        steps=45,
        grid=120,
        exact=exact,
        seed=3,
        out=str(tmp_path),
        frames=3,
        world="boxes",
    )
    assert res.particle_steps_per_second > 0 and res.steps == 45
    assert os.path.exists(res.last_frame) and res.animation.endswith(".mp4")
    assert os.path.getsize(res.animation) > 1000
    assert (res.grid_band_value_max is None) == exact
    assert (res.outside_grid_fraction is None) == exact
    assert res.inside_fraction < 0.01
    assert res.respawned > 0  # the notebook's blob overlaps this world's boxes
    text = summary(res)
    for needle in (
        "world: boxes",
        "45 steps",
        "1.50 s of simulated time",
        "M particle-steps/s",
        "for comparison",
        "--world seed",
    ):
        assert needle in text, needle
    assert ("were inside the grid (bilinear queries)" in text) != exact
    img = imread(res.last_frame)[..., :3]
    world = box_world(20, seed=0)
    probes = [(0.0, -1.95), (-1.9, -1.0), (1.9, -1.0)]  # deep in the funnel's floor and walls
    assert np.all(world(*np.array(probes).T) < -0.05)
    # Map data coordinates to PNG pixels with the same figure layout render_frame uses.
    fig = render_frame(world, np.zeros(0), np.zeros(0), figsize=(6.4, 5.6))  # the demo's
    fig.canvas.draw()
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
@pytest.mark.parametrize(
    "name,outputs",
    [
        ("custom_scene", ["custom_scene.png"]),
        ("raymarch", ["raymarch.png"]),
        ("custom_force", ["custom_force.png"]),
        ("save_video", ["particles.mp4"]),
        ("moving_walls", ["moving_walls.png", "moving_walls.mp4"]),
        ("sand", ["sand.png", "sand.mp4"]),
        ("heap", ["heap.png"]),
        ("silo", ["silo.png"]),
    ],
)
def test_examples_run_at_small_size(tmp_path, name, outputs):
    env = dict(os.environ, PYTHONPATH=REPO, MPLBACKEND="Agg", FASTSDF_EXAMPLE_SMALL="1")
    res = subprocess.run(
        [sys.executable, os.path.join(REPO, "examples", f"{name}.py"), str(tmp_path)],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert res.returncode == 0, res.stderr[-3000:]
    for out in outputs:
        assert (tmp_path / out).stat().st_size > 1000, out


def test_video_and_last_frame_colour_a_state_alike(tmp_path):
    """The particle demo's video frames and its last frame's picture share one colour scale
    (density_norm of density_top): the same particles get the same colours in both."""
    from matplotlib.image import imread

    from fastsdf.apps import demo
    from fastsdf.viz.frames import VideoWriter
    from fastsdf.viz.render import render_frame

    def floor(x, y):  # a plain callable world: nothing to compile
        return y + 1.8

    n = 20_000
    rng = np.random.default_rng(0)
    x, y = rng.normal(0.0, 0.05, n), rng.normal(-1.0, 0.05, n)  # a pile denser than the top
    top = demo.density_top(n)
    video = VideoWriter(
        str(tmp_path / "v.mp4"), floor, demo.BOUNDS, size=demo.VIDEO_SIZE, vmax=top, title="t"
    )
    frame = video.render(x, y).astype(float)
    png = str(tmp_path / "last.png")
    w, h = demo.VIDEO_SIZE
    fig = render_frame(
        floor,
        x,
        y,
        bounds=demo.BOUNDS,
        out_png=png,
        title="t",
        figsize=(w / 100, h / 100),
        dpi=100,
        vmax=top,
    )
    picture = imread(png)[..., :3] * 255.0
    norm = fig.particle_layer.artist.norm
    assert (norm.vmin, norm.vmax) == (video.norm.vmin, video.norm.vmax) == (1.0, top)
    assert picture.shape == frame.shape
    # the pile's saturated core and its flanks (means over boxes: the two splats may round a
    # point into neighbouring pixels)
    i, j = video.pixel(0.0, -1.0)
    for half in (3, 12, 25):
        box = (slice(i - half, i + half + 1), slice(j - half, j + half + 1))
        assert np.abs(frame[box].mean((0, 1)) - picture[box].mean((0, 1))).max() < 4.0, half


def test_summary_counts_in_words_and_explains_the_rate():
    from fastsdf.apps.demo import DemoResult, summary

    base = dict(
        world="seed",
        particles=1,
        steps=1,
        timestep=1 / 30,
        sdf="a 50x50 GridSDF",
        mode="exact",
        sim_seconds=0.0,
        first_step_seconds=0.5,
        particle_steps_per_second=float("nan"),
        outside_grid_fraction=0.25,
        exact_query_cost=12.0,
        grid_band_value_max=1e-3,
        grid_band_angle_rms_deg=0.5,
        respawned=1,
        inside_fraction=0.0,
        animation=None,
        last_frame="x.png",
        load=(99.0, 98.0),
    )
    text = summary(DemoResult(**base))
    assert "1 step of" in text and "1 steps" not in text and "1 particle in" in text
    assert "run more steps to measure a rate" in text
    assert "75.0% of particle positions were inside the grid" in text
    assert "25.0% were outside, answered by the exact SDF" in text
    assert "12x one grid query" in text
    assert "load (1-minute average) 99.0 before and 98.0 after" in text
    assert "competing for the cores" in text
    text = summary(
        DemoResult(
            **dict(
                base,
                steps=3,
                particles=2000,
                respawned=0,
                mode="nearest",
                particle_steps_per_second=4e6,
                sim_seconds=0.001,
            )
        )
    )
    assert "3 steps" in text and "2,000 particles" in text and "0 particles redrawn" in text
    assert "4.0 M particle-steps/s over 2 steps" in text
    assert "clamped to the grid's edge" in text
    boxes = summary(
        DemoResult(
            **dict(
                base, world="boxes", outside_grid_fraction=None, mode=None, exact_query_cost=None
            )
        )
    )
    assert "every query evaluates the exact compiled SDF" in boxes
    assert "fastsdf demo --world seed" in boxes


@pytest.mark.slow
def test_sand_scene_pours_grains_and_draws_them(tmp_path):
    from matplotlib.image import imread

    from fastsdf.apps.demo import (
        SAND_RADIUS,
        SAND_ROLLING_FRICTION,
        run_sand_demo,
        sand_summary,
    )
    from fastsdf.viz.render import PARTICLE_COLOR

    res = run_sand_demo(grains=96, steps=15, grid=100, out=str(tmp_path), frames=3)
    assert res.steps == 15 and res.grains == 96 and res.radius == SAND_RADIUS
    assert os.path.getsize(res.animation) > 1000 and res.animation.endswith("sand.mp4")
    # the stiffness derived for the 4-high world keeps the step count at the library's scale
    assert res.substeps_per_step <= 1500
    assert res.max_overlap < 0.05 and res.max_wall_overlap < 0.05
    assert res.history and res.rolling_friction == SAND_ROLLING_FRICTION  # the law that heaps
    text = sand_summary(res)
    for needle in (
        "96 grains",
        "substeps per 1/30 s step",
        "15 steps",
        "largest overlap",
        f"ContactLaw(history=True, rolling_friction={SAND_ROLLING_FRICTION:g})",
        "angle of repose: ",
    ):
        assert needle in text, needle
    # the angle printed is the one measured on both flanks (or says why there is none, or
    # why it is not reliable)
    for angle, side in ((res.repose_left, "left"), (res.repose_right, "right")):
        assert np.isnan(angle) or 0.0 <= angle <= 90.0
        if np.isfinite(res.repose_left) and np.isfinite(res.repose_right):
            assert f"{angle:.1f} ({side})" in text
    line = text.split("angle of repose: ")[1].splitlines()[0]
    assert ("mean" in line) == res.repose_reliable
    # grains are drawn: orange discs (PARTICLE_COLOR at alpha 0.8 over the light background)
    img = imread(res.last_frame)[..., :3]
    orange = _hex(PARTICLE_COLOR) * 0.8 + img[5, 5] * 0.2  # a corner: background
    assert np.all(np.abs(img - orange) < 0.1, axis=-1).sum() > 50


def test_sand_summary_prints_the_measured_angle_and_the_law():
    from dataclasses import replace

    from fastsdf.apps.demo import SandResult, sand_summary

    res = SandResult(
        world="seed",
        grains=10,
        radius=0.02,
        steps=2,
        timestep=1 / 30,
        sdf="a 50x50 GridSDF",
        stiffness=3000.0,
        substeps_per_step=900,
        first_step_seconds=0.5,
        sim_seconds=0.1,
        grain_substeps_per_second=1e5,
        max_overlap=0.0,
        max_wall_overlap=0.0,
        heap_fraction=1.0,
        heap_top=-1.0,
        animation=None,
        last_frame="x.png",
        repose_left=21.04,
        repose_right=25.0,
    )
    text = sand_summary(res)
    assert "angle of repose: 21.0 (left) and 25.0 (right) degrees, mean 23.0" in text
    one_flank = sand_summary(replace(res, repose_right=math.nan))
    assert "angle of repose: not measured" in one_flank
    assert "ContactLaw(history=True, rolling_friction=0.5) (a tangential spring" in text
    flat = sand_summary(replace(res, history=False, rolling_friction=0.0, repose_left=math.nan))
    assert "angle of repose: not measured" in flat and "ContactLaw() (no contact history" in flat
    assert "spread flat" in flat and "spread flat" not in one_flank
    # flanks more than REPOSE_AGREEMENT apart (the demo's first version printed "15.9 (left)
    # and 61.5 (right) degrees, mean 38.7" fitted on 48 grains): unreliable, and why
    apart = sand_summary(replace(res, repose_left=15.9, repose_right=61.5, cone_grains=48))
    assert "angle of repose: not reliable here" in apart and " mean " not in apart
    assert "15.9 (left) and 61.5 (right) degrees, more than 5 apart" in apart
    assert "48 grains, too few" in apart and "examples/heap.py" in apart
    assert (
        res.repose_reliable
        and not replace(res, repose_left=15.9, repose_right=61.5).repose_reliable
    )


def test_no_history_is_for_the_sand_scene_and_refused_with_rolling_friction():
    res = _cli("demo", "--no-history")
    assert res.returncode == 2 and "--scene sand only" in res.stderr
    from fastsdf.apps.demo import run_sand_demo

    with pytest.raises(ValueError, match="rolling_friction needs history=True"):
        run_sand_demo(history=False, rolling_friction=0.3)
    with pytest.raises(TypeError, match="history"):
        run_sand_demo(history="yes")


def test_sand_scene_refuses_dask_workers_in_one_line():
    res = _cli("demo", "--scene", "sand", "--workers", "2")
    assert res.returncode == 2 and "halo exchange" in res.stderr
    assert res.stderr.count("\n") == 1 and "Traceback" not in res.stderr
