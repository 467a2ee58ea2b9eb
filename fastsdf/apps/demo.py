"""The main job: one of the notebook's worlds, a million particles, a video, a picture, the numbers.

``fastsdf demo`` (and ``make demo``) runs :func:`run_demo`: it builds a world (``'boxes'``, the
notebook's final world: the funnel and 20 random rotated boxes under smoothness 5, cell 13; or
``'seed'``, the funnel and a cut disc of cell 21, the scene of the headline figures in the
README and docs/performance.md),
samples it into a :class:`fastsdf.GridSDF` (or queries it exactly), spawns particles in free
space, lets them fall under ``Gravity()`` (the notebook's ``(0, -1)`` length/s**2) with the fused
particle step, and writes a video (MP4 with
the ``video`` extra or a system ffmpeg, GIF otherwise) and a PNG of the last frame. It reports
what it simulated and why the rate is what it is: the world, the grid and its out-of-bounds mode,
the share of particle positions outside the grid (whose queries fall back to the exact SDF in
``mode='exact'``) and the cost of one exact query against one grid query.

``fastsdf demo --scene sand`` runs :func:`run_sand_demo` instead: grains that collide with each
other (``ParticleSimulation(..., contacts=ContactLaw(history=True, rolling_friction=0.5))``)
pour from a hopper above the world's disc (:func:`sand_world`): a cone builds on the disc, as
in the fixed-base measurement of the angle of repose, and what runs off its flanks fills the
funnel; it writes ``sand.mp4`` and ``sand_last_frame.png`` and reports the contact law, the
substeps per step, the rate, the cone, its angle of repose and the largest overlap.
``--no-history`` pours them with the history-free ``ContactLaw()`` (no static friction: the
heap spreads flat).
"""

from __future__ import annotations

import math
import os
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import IO, Any

import numpy as np

from fastsdf.expr.validate import shown
from fastsdf.notice import compiling

__all__ = [
    "DemoResult",
    "SandResult",
    "run_demo",
    "run_sand_demo",
    "sand_summary",
    "hopper_fill",
    "sand_world",
    "SAND_GRAINS",
    "SAND_STEPS",
    "SAND_ROLLING_FRICTION",
    "REPOSE_AGREEMENT",
    "summary",
    "warm_readme_kernels",
    "README_GRAIN_LAW",
    "check_output_dir",
    "spawn_in_free_space",
    "WORLDS",
    "BOUNDS",
    "DEFAULT_FRAMES",
    "DEFAULT_FPS",
]

#: The region the grid samples and the pictures show (data units).
BOUNDS = ((-2.0, 2.0), (-2.0, 2.0))
#: Video frames and frames per second by default (a 6 s clip).
DEFAULT_FRAMES = 120
DEFAULT_FPS = 20
#: Pixels (width, height) of the demo's MP4.
VIDEO_SIZE = (640, 560)
#: The sand scene's grains, steps (1/30 s: the hopper empties in about 3 s, the cone then
#: settles) and mean grain radius by default (radii spread +-10% about it: equal discs
#: stack into a crystal, whose planes, not friction, would set the slope).
SAND_GRAINS = 900
SAND_STEPS = 180
SAND_RADIUS = 0.022
SAND_RADIUS_SPREAD = 0.1
#: The sand scene's angle of repose is reported where its cone's two flanks agree within this
#: (degrees); else it is said to be unreliable, with the reason.
REPOSE_AGREEMENT = 5.0
#: The sand scene's rolling resistance with contact history (discs hold a slope with it).
SAND_ROLLING_FRICTION = 0.5
#: The contact law of the README's grain block (``ContactLaw(**README_GRAIN_LAW)``), whose
#: kernels :func:`warm_readme_kernels` compiles (history and rolling resistance each select
#: their own compiled variant).
README_GRAIN_LAW: dict[str, Any] = {"history": True, "rolling_friction": 0.3}
#: The hopper's outlet: its lower end's height and its width (about ten grains: narrower
#: outlets jam, grains with rolling resistance arch like sand).
HOPPER_OUTLET_Y = 0.95
HOPPER_OUTLET_WIDTH = 0.45
_HOPPER_WALL = 0.03  # half the thickness of the hopper's walls
_HOPPER_SLOPE = 1.5  # rise over run of its walls (56 degrees: steeper than the grains hold)


def _boxes() -> Any:
    from fastsdf.shapes.scenes import box_world

    return box_world(20, seed=0)


def _seed() -> Any:
    from fastsdf.shapes.scenes import seed_world

    return seed_world()


#: The demo's worlds: name -> (builder, description).
WORLDS: dict[str, tuple[Callable[[], Any], str]] = {
    "boxes": (
        _boxes,
        "the notebook's final world (cell 13): the funnel and 20 random rotated "
        "boxes, smoothness 5",
    ),
    "seed": (
        _seed,
        "the seed world (cell 21): the funnel and a cut disc, smoothness 10; the "
        "scene of the headline figures (README, docs/performance.md)",
    ),
}


@dataclass
class DemoResult:
    """What :func:`run_demo` simulated, measured and wrote (paths are absolute).

    ``world``, ``particles``, ``steps``: as run; ``timestep``: seconds per step; ``sdf``: what
    the particles queried, in words, and ``mode`` the grid's answer outside its bounds
    (``None`` without a grid); ``sim_seconds``: the steps after the first, in seconds;
    ``grid_band_value_max`` and ``grid_band_angle_rms_deg``: the grid's largest value error
    and its gradient's RMS angle error in the collision band ``|d| < 0.1`` (``None`` without
    a grid); ``animation``, ``last_frame``: the video and the PNG written; ``notes``: remarks.
    ``particle_steps_per_second`` counts the steps after the first (which compiles or loads the
    kernel, ``first_step_seconds``); ``outside_grid_fraction`` is the share of particle positions
    outside the grid's bounds, sampled after every frame's steps (``None`` without a grid);
    ``exact_query_cost`` is the time of one exact SDF query (value and gradient) in units of one
    grid query, measured on points in the bounds (``None`` without a grid); ``respawned`` the
    particles drawn again because they started inside matter; ``inside_fraction`` the share of
    particles more than 1% of their radius inside the simulated SDF at the end; ``load`` the
    machine's 1-minute load average before and after the steps (``None`` where unknown).
    """

    world: str
    particles: int
    steps: int
    timestep: float
    sdf: str
    mode: str | None
    sim_seconds: float
    first_step_seconds: float
    particle_steps_per_second: float
    outside_grid_fraction: float | None
    exact_query_cost: float | None
    grid_band_value_max: float | None
    grid_band_angle_rms_deg: float | None
    respawned: int
    inside_fraction: float
    animation: str | None
    last_frame: str
    load: tuple[float, float] | None = None
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        """The fields as a plain dict."""
        return asdict(self)


def check_output_dir(out: str) -> str:
    """Create the folder ``out`` if needed and check that a file can be written there.

    Returns its absolute path; raises ``OSError`` (with the system's reason) otherwise.
    """
    os.makedirs(out, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=out, prefix=".fastsdf-write-test-"):
        pass
    return os.path.abspath(out)


def spawn_in_free_space(sim: Any, f: Any, rng: np.random.Generator, tries: int = 100) -> int:
    """Redraw, from the simulation's own initial distribution, every particle that starts
    within its radius of matter (``f(x) - r < 0``) until none does.

    ``sim`` is a fresh :class:`fastsdf.particles.ParticleSimulation`; its ``reset`` draws the
    notebook's blob ``x ~ N([0, 1.5], 0.05 I)``. Rejected positions are replaced by fresh draws
    from ``rng`` (a ``numpy.random.Generator``): from the same blob (up to ``tries`` rounds),
    then uniform over :data:`BOUNDS`.
    Returns the number of particles that were redrawn; raises ``RuntimeError`` if the world
    leaves no room.
    """
    x = sim.p["x"]
    r = np.asarray(sim.p["r"], dtype=np.float64)
    bad = np.flatnonzero(f(x[:, 0], x[:, 1]) - r < 0)
    moved = bad.size
    centre, sd = np.array([0.0, 1.5]), np.sqrt(0.05)
    for attempt in range(2 * tries):
        if bad.size == 0:
            return int(moved)
        if attempt < tries:
            new = rng.normal(centre, sd, size=(bad.size, 2))
        else:
            (x0, x1), (y0, y1) = BOUNDS
            new = np.column_stack([rng.uniform(x0, x1, bad.size), rng.uniform(y0, y1, bad.size)])
        ok = f(new[:, 0], new[:, 1]) - r[bad] >= 0
        x[bad[ok]] = new[ok]
        bad = bad[~ok]
    raise RuntimeError(f"{bad.size} particles found no free space to start in")


def density_top(particles: int) -> float:
    """Top of the colour scale (particles per pixel) of the particle demo's video frames and of
    its last frame's picture, one value for both (:func:`fastsdf.viz.render.density_norm`): the
    pile on the funnel's floor gathers about 3 thousandths of the particles in one pixel of the
    640 x 560 picture by the last step (1e6 particles: about 3,000); at least 10."""
    return max(10.0, 3.0 * particles / 1000)


def _frame_schedule(steps: int, frames: int) -> list[int]:
    """Steps to take before each frame: frame 0 is the start, the last frame is step ``steps``."""
    if frames == 1:
        return [steps]
    marks = [round(k * steps / (frames - 1)) for k in range(frames)]
    return [marks[0]] + [b - a for a, b in zip(marks, marks[1:])]


def _video_writer_ext(err: IO[str]) -> str:
    from fastsdf.viz.video import ffmpeg_available

    if ffmpeg_available():
        return ".mp4"
    err.write(
        "note: no ffmpeg found (pip install 'fastsdf[video]' provides one): writing a GIF "
        "instead of an MP4\n"
    )
    return ".gif"


def _load_pair(before: float | None, after: float | None) -> tuple[float, float] | None:
    """``(load at the start, load at the end)``, or None where the platform has none."""
    return None if before is None or after is None else (before, after)


def _load() -> float | None:
    try:
        return float(os.getloadavg()[0])
    except (AttributeError, OSError):  # not available on this platform
        return None


def _timed_advance(
    sim: Any,
    k: int,
    timing: dict[str, Any],
    outside_share: Callable[[], float] = lambda: 0.0,
    what: str = "the particle step",
) -> None:
    """Advance ``sim`` by ``k`` steps, keeping the demo's timing record (``first``, ``rest``,
    ``steps``, ``outside``, ``load0``): the first call, which compiles (or loads) ``what``,
    is timed apart from the rest; ``outside_share()`` is the share of particles outside the
    grid now, standing for the steps before it."""
    if k <= 0:
        return
    if timing["first"] is None:
        t0 = time.perf_counter()
        with compiling(what):
            sim.run(1)
        timing["first"] = time.perf_counter() - t0
        timing["load0"] = _load()
        timing["outside"] += outside_share()
        timing["steps"] += 1
        k -= 1
    if k > 0:
        t0 = time.perf_counter()
        sim.run(k)
        timing["rest"] += time.perf_counter() - t0
        timing["outside"] += k * outside_share()
        timing["steps"] += k


def _new_timing() -> dict[str, Any]:
    return {"first": None, "rest": 0.0, "steps": 0, "outside": 0.0}


def _query_cost(grid: Any, n: int = 200_000, seed: int = 0) -> float:
    """Time of one exact query over one grid query (value and gradient, same points)."""
    rng = np.random.default_rng(seed)
    (x0, x1), (y0, y1) = BOUNDS
    x, y = rng.uniform(x0, x1, n), rng.uniform(y0, y1, n)

    def best(fn: Callable[[], Any]) -> float:
        fn()  # compile / warm
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return min(times)

    exact = best(lambda: grid.exact(x, y, compute_gradient=True))
    sampled = best(lambda: grid(x, y, compute_gradient=True))
    return exact / sampled if sampled > 0 else float("nan")


def _check_demo_args(
    world: str,
    mode: str | None,
    animate: bool,
    frames: int,
    steps: int,
    grid: int,
    fps: int,
    **counts: int,
) -> None:
    """``ValueError`` naming the first size that is not an integer at least its lower bound
    (1; 2 for ``grid``; ``counts`` are more, each at least 1), an unknown ``world`` or
    ``mode`` (a grid's, unless None), or more video frames than steps (each frame advances
    at least one step)."""
    sizes = {"frames": (frames, 1), "steps": (steps, 1), "grid": (grid, 2), "fps": (fps, 1)}
    sizes.update({name: (value, 1) for name, value in counts.items()})
    for name, (value, low) in sizes.items():
        if isinstance(value, bool) or int(value) != value or value < low:
            raise ValueError(f"{name} must be an integer >= {low}, got {name}={shown(value)}")
    if world not in WORLDS:
        raise ValueError(f"world must be one of {sorted(WORLDS)}, got world={shown(world)}")
    if mode is not None and mode not in ("exact", "nearest"):
        raise ValueError(f"mode must be 'exact' or 'nearest', got mode={shown(mode)}")
    if animate and frames > steps:
        raise ValueError(
            f"frames must be at most steps (every frame advances at least one step), "
            f"got frames={frames}, steps={steps}"
        )


@dataclass
class QueriedWorld:
    """The world a demo's particles meet: ``f``, the exact SDF; ``sdf``, what they query (a
    GridSDF of ``f``, or ``f`` itself); ``name``, that said in words; ``mode``, the grid's
    answer outside its bounds; the grid's error in the collision band (``band_max``,
    ``band_angle``) and the cost of an exact query in grid queries (``cost``); None without
    a grid."""

    f: Any
    sdf: Any
    name: str
    mode: str | None = None
    band_max: float | None = None
    band_angle: float | None = None
    cost: float | None = None


def queried_world(
    world: str,
    grid: int,
    mode: str,
    exact: bool,
    seed: int,
    step: Callable[[str], None] = lambda what: None,
) -> QueriedWorld:
    """The world ``world`` (a key of :data:`WORLDS`) sampled into a ``grid`` x ``grid``
    GridSDF over :data:`BOUNDS` answering ``mode`` outside it, with the grid's error and cost
    measured (``seed``: their points); ``exact=True``: the exact compiled SDF, no grid.
    ``step(what)`` is called before each part that takes time (a progress bar's)."""
    from fastsdf.fields.grid import GridSDF, measure_error

    f = WORLDS[world][0]()
    if exact:
        return QueriedWorld(f, f, "the exact compiled SDF (no grid)")
    t0 = time.perf_counter()
    with compiling(f"the {world} world's kernel and its {grid}x{grid} grid"):
        sdf = GridSDF(f, bounds=BOUNDS, samples=[grid * 1j, grid * 1j], mode=mode)
    built = time.perf_counter() - t0
    step("the grid's error")
    error = measure_error(sdf, seed=seed)
    name = f"a {grid}x{grid} GridSDF (built in {built:.2f} s)"
    return QueriedWorld(
        f,
        sdf,
        name,
        mode,
        error.band_value_max,
        error.band_angle_rms_deg,
        _query_cost(sdf, seed=seed),
    )


def particle_result(
    qw: QueriedWorld,
    world: str,
    particles: int,
    timing: dict[str, Any],
    timestep: float,
    x: np.ndarray,
    r: np.ndarray,
    respawned: int,
    animation: str | None,
    last_frame: str,
    load: tuple[float, float] | None,
) -> DemoResult:
    """The :class:`DemoResult` of a particle demo: ``timing`` as :func:`_timed_advance` kept
    it, ``x`` and ``r`` the particles (or a sample of them) at the end, whose penetration of
    the SDF they collided with is measured (the grid's own error is reported apart)."""
    d = np.asarray(qw.sdf(x[:, 0], x[:, 1])).reshape(-1) - r
    timed = timing["steps"] - 1
    rest = timing["rest"]
    return DemoResult(
        world=world,
        particles=particles,
        steps=timing["steps"],
        timestep=timestep,
        sdf=qw.name,
        mode=qw.mode,
        sim_seconds=rest,
        first_step_seconds=timing["first"] or 0.0,
        particle_steps_per_second=timed * particles / rest if rest > 0 else float("nan"),
        outside_grid_fraction=(
            None if qw.mode is None else timing["outside"] / max(1, timing["steps"])
        ),
        exact_query_cost=qw.cost,
        grid_band_value_max=qw.band_max,
        grid_band_angle_rms_deg=qw.band_angle,
        respawned=respawned,
        inside_fraction=float(np.mean(d < -0.01 * r)),
        load=load,
        animation=animation,
        last_frame=last_frame,
    )


def _write_video(
    sim: Any,
    f: Any,
    path: str,
    schedule: list[int],
    advance: Callable[[int], None],
    label: str,
    fps: int,
    err: IO[str],
    vmax: float | None = None,
) -> str:
    """Advance ``sim`` by ``schedule`` (``advance(k)``), a frame after each advance, to a
    video of it over the world ``f``: ``path`` with ``.mp4`` (ffmpeg: the particles splatted
    per frame over a picture drawn once, :mod:`fastsdf.viz.frames`) or ``.gif`` (matplotlib)
    appended; ``vmax``: the density's colour scale's top (particles per pixel, None: discs).
    Returns the path written."""
    from fastsdf.viz.frames import VideoWriter
    from fastsdf.viz.progress import Progress
    from fastsdf.viz.render import animate, density_norm, save_animation, world_figure

    path += _video_writer_ext(err)
    if path.endswith(".mp4"):
        with (
            Progress(len(schedule), "frames", stream=err) as bar,
            VideoWriter(path, f, BOUNDS, size=VIDEO_SIZE, fps=fps, vmax=vmax, title=label) as video,
        ):
            for i, k in enumerate(schedule):
                if i < 2:  # these may compile: their notices get a line of their own
                    bar.clear()
                advance(k)
                with compiling("the video's drawing kernels"):
                    video.add_simulation(sim)
                bar.step()
        return path
    fig, ax, cax = world_figure(f, BOUNDS, 400, (6.4, 5.6), 100)
    anim = animate(
        sim,
        ax,
        len(schedule),
        schedule,
        advance=advance,
        title=label + ", ",
        colorbar=cax if vmax is not None else False,
        bounds=BOUNDS,
        norm=None if vmax is None else density_norm(vmax),
    )
    save_animation(anim, path, fps=fps)
    return path


def run_demo(
    particles: int = 1_000_000,
    steps: int = 300,
    grid: int = 400,
    exact: bool = False,
    seed: int = 0,
    out: str = "demo-out",
    frames: int = DEFAULT_FRAMES,
    fps: int = DEFAULT_FPS,
    animate: bool = True,
    world: str = "seed",
    mode: str = "exact",
    stream: IO[str] | None = None,
) -> DemoResult:
    """Simulate ``particles`` particles for ``steps`` steps (1/30 s each) in a notebook world.

    ``world``: a key of :data:`WORLDS` (``'seed'``, the default, or ``'boxes'``). ``grid``: the
    GridSDF's samples per axis over :data:`BOUNDS`; ``mode``: the grid's answer outside its bounds
    (``'exact'``: the exact SDF, ``'nearest'``: clamped to the edge); ``exact=True`` queries the
    exact compiled SDF everywhere instead of a grid. Particles start in the notebook's blob,
    redrawn where they would start inside matter (:func:`spawn_in_free_space`). ``frames`` video
    frames (at most ``steps``; frame 0 is the start, the last is the final step) at ``fps`` are
    written to ``out`` (``animate=False`` skips the video); the last frame is always written as
    ``out/last_frame.png``. Progress bars go to ``stream`` (default stderr) when it is a terminal.
    Raises ``ValueError`` naming a bad parameter, ``OSError`` if ``out`` cannot be written.
    """
    import matplotlib

    matplotlib.use("Agg")

    from fastsdf.viz.render import render_frame, sim_title

    _check_demo_args(world, mode, animate, frames, steps, grid, fps, particles=particles)
    particles, steps, frames = int(particles), int(steps), int(frames)
    err = stream if stream is not None else sys.stderr
    out = check_output_dir(out)

    qw, sim, respawned = _demo_particles(world, grid, mode, exact, seed, particles, err)
    timing = _new_timing()

    def advance(k: int) -> None:
        _timed_advance(sim, k, timing, lambda: _outside_share(sim.p["x"]))

    label = f"{particles:,} particles"
    animation_path = None
    if animate:
        # all on one colour scale, the last frame's picture's too
        animation_path = _write_video(
            sim,
            qw.f,
            os.path.join(out, "particles"),
            _frame_schedule(steps, frames),
            advance,
            label,
            fps,
            err,
            vmax=density_top(particles),
        )
    advance(steps - timing["steps"])
    x = sim.p["x"]
    last = os.path.join(out, "last_frame.png")
    render_frame(
        qw.f,
        x[:, 0],
        x[:, 1],
        r=sim.p["r"],
        bounds=BOUNDS,
        out_png=last,
        title=sim_title(sim, label + ", "),
        figsize=(VIDEO_SIZE[0] / 100, VIDEO_SIZE[1] / 100),  # the video's pixels: same counts
        dpi=100,
        vmax=density_top(particles),
    )
    return particle_result(
        qw,
        world,
        particles,
        timing,
        sim.dt,
        x,
        np.asarray(sim.p["r"]),
        respawned,
        animation_path,
        last,
        _load_pair(timing.get("load0"), _load()),
    )


def _demo_particles(
    world: str, grid: int, mode: str, exact: bool, seed: int, particles: int, err: IO[str]
) -> tuple:
    """``(queried world, simulation, particles redrawn)``: the steps before the first frame,
    with a progress bar: the grid (which may compile: the bar is cleared so that the notice
    stands on its own line), its error and cost, ``particles`` particles in the notebook's
    blob under its gravity, none inside matter."""
    from fastsdf.particles import Gravity, ParticleSimulation
    from fastsdf.viz.progress import Progress

    with Progress(3, "setting up", stream=err) as setup:
        setup.clear()
        qw = queried_world(world, grid, mode, exact, seed, setup.step)
        setup.step("particles", count=2 if exact else 1)
        sim = ParticleSimulation(qw.sdf, n=particles, timestep=1 / 30, seed=seed)
        sim.force_generators.append(Gravity(acceleration=(0.0, -1.0)))
        respawned = spawn_in_free_space(sim, qw.f, np.random.default_rng([seed, 1]))
        setup.step()
    return qw, sim, respawned


def _outside_share(x: np.ndarray) -> float:
    """The share of the positions ``x`` outside :data:`BOUNDS`."""
    (x0, x1), (y0, y1) = BOUNDS
    inside = (x[:, 0] >= x0) & (x[:, 0] <= x1) & (x[:, 1] >= y0) & (x[:, 1] <= y1)
    return 1.0 - float(np.mean(inside))


def warm_readme_kernels(stream: IO[str] | None = None) -> float:
    """Compile (or load) the kernels the README's blocks use that the particle demo may not:
    the particle step's parallel entry point for long calls on the README's 400 x 400 grid
    of the seed world (whatever particle count the demo ran), the grains' (grains of the
    README's block, with its contact law and world, the exact seed world: some falling, some
    resting on the disc, so that their contacts with the world compile too) and the distance
    transforms of images (a small image through :func:`fastsdf.geometry.from_image`). So a
    block pasted after ``make demo`` loads them from the cache instead of compiling them.
    Says so on ``stream`` (default stderr); returns the seconds it took."""
    from fastsdf.fields.grid import GridSDF
    from fastsdf.geometry import from_image
    from fastsdf.granular.params import ContactLaw
    from fastsdf.particles import Gravity, ParticleSimulation
    from fastsdf.particles.engine import LONG_CALL, PARALLEL_MIN_PARTICLES

    err = stream if stream is not None else sys.stderr
    err.write(
        "fastsdf demo: compiling the kernels of the README's other blocks (particles, grains, "
        "images) for later ...\n"
    )
    err.flush()
    t0 = time.perf_counter()
    with compiling("the particle step for long runs"):
        grid = GridSDF(_seed(), bounds=BOUNDS, samples=[400j, 400j])  # the README's grid
        sim = ParticleSimulation(grid, n=PARALLEL_MIN_PARTICLES, seed=0)
        sim.force_generators.append(Gravity())
        sim.run(-(-LONG_CALL // PARALLEL_MIN_PARTICLES))
    r, world = 0.02, _seed()
    falling = np.column_stack([np.linspace(-0.1, 0.1, 3), np.full(3, 0.85)])
    # three more touching the disc's top: the lowest heights above it where the distance is r
    ys = np.linspace(0.0, 0.6, 601)
    resting = [
        (x, ys[np.argmax(world(np.full(ys.size, x), ys) > 0.95 * r)]) for x in (-0.2, 0, 0.2)
    ]
    with compiling("the grains' kernels"):
        sim = ParticleSimulation(
            world,
            positions=np.concatenate([falling, resting]),
            radius=r,
            contacts=ContactLaw(**README_GRAIN_LAW),
        )
        sim.force_generators.append(Gravity())
        sim.run(1)
    yy, xx = np.mgrid[0:24, 0:32]
    disc = np.clip(8.5 - np.hypot(xx - 15.5, yy - 11.5), 0.0, 1.0)  # an anti-aliased disc
    with compiling("the distance transforms of images"):
        from_image(disc, bounds=[(-2, 2), (-1.5, 1.5)])(0.0, 0.0)
    seconds = time.perf_counter() - t0
    err.write(f"fastsdf demo: ... ready in {seconds:.1f} s\n")
    err.flush()
    return seconds


def _plural(n: int, word: str) -> str:
    return f"{n:,} {word}" + ("" if n == 1 else "s")


def summary(res: DemoResult) -> str:
    """Human-readable lines for the demo's result ``res``: what was simulated, the rate, and
    why."""
    lines = [
        f"world: {res.world}, {WORLDS[res.world][1]}",
        f"queried through {res.sdf}"
        + (f", mode={res.mode!r} outside [-2, 2]^2" if res.mode else ""),
        f"spawned {_plural(res.particles, 'particle')} in free space ("
        f"{_plural(res.respawned, 'particle')} redrawn that would have started inside "
        f"matter)",
        f"simulated {_plural(res.steps, 'step')} of {res.timestep:.4g} s "
        f"({res.steps * res.timestep:.2f} s of simulated time)",
    ]
    if res.steps > 1:
        lines.append(
            f"rate: {res.particle_steps_per_second / 1e6:.1f} M particle-steps/s over "
            f"{_plural(res.steps - 1, 'step')} in {res.sim_seconds:.2f} s (the first "
            f"step, {res.first_step_seconds:.2f} s, compiles or loads the kernel and is "
            f"not counted)"
        )
    else:
        lines.append(
            f"the only step took {res.first_step_seconds:.2f} s, compiling or loading "
            f"the kernel included (run more steps to measure a rate)"
        )
    if res.outside_grid_fraction is not None:
        where = (
            "answered by the exact SDF"
            if res.mode == "exact"
            else "clamped to the grid's edge (cheap, approximate)"
        )
        lines.append(
            f"why this rate: {1 - res.outside_grid_fraction:.1%} of particle positions "
            f"were inside the grid (bilinear queries); {res.outside_grid_fraction:.1%} "
            f"were outside, {where}"
        )
        if res.exact_query_cost is not None:
            lines.append(
                f"  one exact query costs {res.exact_query_cost:.2g}x one grid query "
                f"in this world (value + gradient, measured here)"
            )
        lines.append(
            "  particles resting on surfaces query every step; falling ones skip "
            "queries while provably clear, so the rate also depends on how many rest"
        )
    else:
        lines.append("why this rate: every query evaluates the exact compiled SDF (no grid)")
    if res.load is not None:
        cores = os.cpu_count() or 1
        busy = (
            " (other processes were competing for the cores)" if max(res.load) > 0.5 * cores else ""
        )
        lines.append(
            f"machine load (1-minute average) {res.load[0]:.1f} before and "
            f"{res.load[1]:.1f} after the steps, on {cores} cores{busy}"
        )
    if res.world == "seed":
        lines.append(
            "for comparison: this is the scene of the README's headline particle "
            "figure (1e6 particles, 400x400 grid; python -m bench --only particles "
            "measures it beside its baselines, on a quiet machine); the notebook's final "
            "world is: fastsdf demo --world boxes"
        )
    else:
        lines.append(
            "for comparison: the README's headline particle figure is the seed world on "
            "a 400x400 grid, where particles stay inside the grid (python -m bench "
            "--only particles); run it here with: fastsdf demo --world seed"
        )
    if res.grid_band_value_max is not None:
        lines.append(
            f"grid error in the collision band |d| < 0.1: value max "
            f"{res.grid_band_value_max:.2e}, gradient angle RMS "
            f"{res.grid_band_angle_rms_deg:.3f} deg"
        )
    lines.append(
        f"particles more than 1% of their radius inside the simulated SDF at the end: "
        f"{res.inside_fraction:.3%}"
    )
    if res.animation:
        lines.append(f"video: {res.animation}")
    lines.append(f"last frame: {res.last_frame}")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# The sand scene: grains that collide with each other pour into the funnel and heap up.


@dataclass
class SandResult:
    """What :func:`run_sand_demo` simulated, measured and wrote (paths are absolute).

    ``world``, ``grains``, ``radius`` (the mean), ``steps``: as run; ``timestep``: seconds per
    step; ``sdf``: what the grains queried, in words; ``sim_seconds``: the steps after the
    first, in seconds; ``animation``, ``last_frame``: the video and the PNG written.
    ``substeps_per_step``: the granular engine's substeps per 1/30 s step (from the contact
    law's stiffness, ``stiffness``, derived from the grains by ``ContactLaw()``);
    ``first_step_seconds``: the first step (compiling or loading the kernels);
    ``grain_substeps_per_second``: the rate over the other steps; ``max_overlap``: the largest
    grain-grain overlap at the end over the diameter, ``max_wall_overlap`` the largest
    grain-world one (a grain in a corner of the world feels only the nearer wall, the SDF's
    nearest surface); ``heap_fraction``: the share of grains in the funnel (below the disc,
    ``y < -0.5``) at the end; ``heap_top``: the highest centre among those at rest there
    (slower than 0.05 length/s); ``cone_grains`` and ``cone_top``: the grains at rest on
    the disc, below the hopper, and the highest centre among them; ``repose_left`` and
    ``repose_right``: the angle of repose (degrees) of that cone's flanks, measured on them by
    :func:`fastsdf.granular.repose_angle` (NaN where a flank has no slope to fit);
    ``history`` and ``rolling_friction``: the contact law's; ``load``: as in
    :class:`DemoResult`.
    """

    world: str
    grains: int
    radius: float
    steps: int
    timestep: float
    sdf: str
    stiffness: float
    substeps_per_step: int
    first_step_seconds: float
    sim_seconds: float
    grain_substeps_per_second: float
    max_overlap: float
    max_wall_overlap: float
    heap_fraction: float
    heap_top: float
    animation: str | None
    last_frame: str
    load: tuple[float, float] | None = None
    history: bool = True
    rolling_friction: float = SAND_ROLLING_FRICTION
    repose_left: float = float("nan")
    repose_right: float = float("nan")
    cone_grains: int = 0
    cone_top: float = float("nan")

    def as_dict(self) -> dict:
        """The fields as a plain dict."""
        return asdict(self)

    @property
    def repose_reliable(self) -> bool:
        """Whether the cone's two flanks were measured and agree within
        :data:`REPOSE_AGREEMENT` degrees."""
        return bool(abs(self.repose_left - self.repose_right) <= REPOSE_AGREEMENT)


def sand_world(world: str = "seed") -> Any:
    """The world ``world`` (a key of :data:`WORLDS`) and a hopper above its disc: two walls
    rising from an outlet :data:`HOPPER_OUTLET_WIDTH` wide at height :data:`HOPPER_OUTLET_Y`."""
    from fastsdf.shapes import Capsule

    half = HOPPER_OUTLET_WIDTH / 2 + _HOPPER_WALL
    run = 2.0 / math.hypot(1.0, _HOPPER_SLOPE)
    rise = _HOPPER_SLOPE * run
    y = HOPPER_OUTLET_Y
    f = WORLDS[world][0]()
    return (
        f
        | Capsule((-half, y), (-half - run, y + rise), _HOPPER_WALL)
        | Capsule((half, y), (half + run, y + rise), _HOPPER_WALL)
    )


def hopper_fill(n: int, radius: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Start positions (n, 2) of grains of radii ``radius`` filling the hopper of
    :func:`sand_world` from its outlet up: rows of grains a little apart (their largest
    diameter and a tenth), alternate rows shifted by half a pitch, each grain clear of the
    walls, with a small random offset (so the fill does not settle as a crystal) drawn from
    ``rng`` (a ``numpy.random.Generator``)."""
    pitch = 2.2 * float(np.max(radius))
    rows: list[np.ndarray] = []
    count, y, row = 0, HOPPER_OUTLET_Y + pitch, 0
    while count < n:
        # the walls' inner faces run from the outlet's edges at _HOPPER_SLOPE; centres keep
        # 0.7 pitch (1.5 radii) from them
        half = HOPPER_OUTLET_WIDTH / 2 + (y - HOPPER_OUTLET_Y) / _HOPPER_SLOPE - 0.7 * pitch
        k = int(half / pitch) + 1
        xs = (np.arange(-k, k + 1) + (0.5 if row % 2 else 0.0)) * pitch  # a triangular lattice
        xs = xs[np.abs(xs) <= half]
        rows.append(np.column_stack([xs, np.full(xs.shape, y)]))
        count += xs.size
        y += 0.9 * pitch
        row += 1
    pos = np.concatenate(rows)[:n]
    return pos + rng.uniform(-0.02, 0.02, pos.shape) * pitch


def _max_overlaps(sim: Any, world: Any) -> tuple[float, float]:
    """The largest overlaps now over the diameter (of the smaller grain): grain-grain (over
    the listed pairs) and grain-world."""
    x = np.asarray(sim.p["x"])
    r = np.asarray(sim.p["r"])
    pairs = sim.engine.neighbour_pairs()
    worst = 0.0
    if pairs.size:
        i, j = pairs[:, 0], pairs[:, 1]
        gap = np.hypot(*(x[i] - x[j]).T)
        worst = float(np.max((r[i] + r[j] - gap) / (2 * np.minimum(r[i], r[j]))))
    wall = (r - np.asarray(world(x[:, 0], x[:, 1])).reshape(-1)) / (2 * r)
    return max(worst, 0.0), max(float(wall.max()), 0.0)


def run_sand_demo(
    grains: int = SAND_GRAINS,
    steps: int = SAND_STEPS,
    grid: int = 400,
    exact: bool = False,
    seed: int = 0,
    out: str = "demo-out",
    frames: int = SAND_STEPS,
    fps: int = DEFAULT_FPS,
    animate: bool = True,
    world: str = "seed",
    radius: float = SAND_RADIUS,
    stream: IO[str] | None = None,
    history: bool = True,
    rolling_friction: float = SAND_ROLLING_FRICTION,
) -> SandResult:
    """Pour ``grains`` grains of mean radius ``radius`` (radii +-:data:`SAND_RADIUS_SPREAD`
    about it) from a hopper onto the disc of a notebook world (``world``, a key of
    :data:`WORLDS`; :func:`sand_world`) and let them heap up: ``steps`` steps of 1/30 s under
    ``Gravity((0, -9.81))`` (length/s**2: the world in metres; ``Gravity()`` is
    the notebook's 1), grains colliding with each other and the world (``ParticleSimulation(...,
    contacts=ContactLaw(history=True, rolling_friction=rolling_friction))``: a tangential
    spring per contact, static friction, and rolling resistance, so the heap keeps a slope;
    ``history=False``: ``ContactLaw()``, history-free, the heap spreads flat; the stiffness
    derived from the grains and the world's height, see :class:`fastsdf.granular.ContactLaw`).
    The world is sampled into a ``grid`` x ``grid`` GridSDF over :data:`BOUNDS`
    (``exact=True``: queried exactly, with the stiffness the grid's height would give). The
    summary reports the angle of repose of the cone on the disc
    (:func:`fastsdf.granular.repose_angle` on the grains at rest there). Writes
    ``out/sand.mp4`` (``frames`` frames at ``fps``; a GIF without ffmpeg; ``animate=False``
    skips it) and ``out/sand_last_frame.png``. ``seed``: the radii's and the fill's random
    seed; ``stream``: where notices go (default stderr)."""
    import matplotlib

    matplotlib.use("Agg")

    from fastsdf.viz.render import render_frame, sim_title

    _check_sand_args(radius, history, rolling_friction)
    _check_demo_args(world, None, animate, frames, steps, grid, fps, grains=grains)
    grains, steps, frames = int(grains), int(steps), int(frames)
    err = stream if stream is not None else sys.stderr
    out = check_output_dir(out)
    f = sand_world(world)
    sim, sdf, sdf_name = _sand_simulation(
        f, grid, exact, seed, grains, radius, history, rolling_friction
    )
    timing = _new_timing()

    def advance(k: int) -> None:
        _timed_advance(sim, k, timing, what="the granular kernels")

    label = f"{grains:,} grains"
    animation_path = None
    if animate:
        schedule = _frame_schedule(steps, frames)
        animation_path = _write_video(
            sim, f, os.path.join(out, "sand"), schedule, advance, label, fps, err
        )
    advance(steps - timing["steps"])
    x = sim.p["x"]
    last = os.path.join(out, "sand_last_frame.png")
    render_frame(
        f,
        x[:, 0],
        x[:, 1],
        r=sim.p["r"],
        bounds=BOUNDS,
        out_png=last,
        title=sim_title(sim, label + ", "),
        colorbar=False,
    )
    return _sand_result(sim, sdf, sdf_name, world, radius, timing, animation_path, last)


def _sand_result(
    sim: Any,
    sdf: Any,
    sdf_name: str,
    world: str,
    radius: float,
    timing: dict[str, Any],
    animation: str | None,
    last_frame: str,
) -> SandResult:
    """The sand scene's :class:`SandResult`: its law and rate (``timing`` as
    :func:`_timed_advance` kept it), overlaps and heaps at the end, files written."""
    overlap, wall_overlap = _max_overlaps(sim, sdf)
    substeps, grains, rest = sim.substeps_per_frame, sim.n, timing["rest"]
    law = sim.contacts
    return SandResult(
        world=world,
        grains=grains,
        radius=float(radius),
        steps=timing["steps"],
        timestep=sim.dt,
        sdf=sdf_name,
        stiffness=float(law.stiffness),
        substeps_per_step=int(substeps),
        first_step_seconds=timing["first"] or 0.0,
        sim_seconds=rest,
        grain_substeps_per_second=(
            (timing["steps"] - 1) * substeps * grains / rest if rest > 0 else float("nan")
        ),
        max_overlap=overlap,
        max_wall_overlap=wall_overlap,
        animation=animation,
        last_frame=last_frame,
        load=_load_pair(timing.get("load0"), _load()),
        history=bool(law.history),
        rolling_friction=float(law.rolling_friction),
        **_sand_heaps(sim, radius),
    )


def _check_sand_args(radius: float, history: bool, rolling_friction: float) -> None:
    """``ValueError`` (``TypeError``) naming a grain radius outside (0, 0.2), a ``history``
    not a bool, or a rolling friction that is negative or given without history."""
    if not (np.isfinite(radius) and 0 < radius < 0.2):
        raise ValueError(f"radius must be in (0, 0.2), got radius={shown(radius)}")
    if not isinstance(history, bool):
        raise TypeError(f"history must be True or False, got history={shown(history)}")
    if not (np.isfinite(rolling_friction) and rolling_friction >= 0):
        raise ValueError(
            f"rolling_friction must be >= 0, got rolling_friction={shown(rolling_friction)}"
        )
    if rolling_friction and not history:
        raise ValueError(
            f"rolling_friction needs history=True, got rolling_friction="
            f"{shown(rolling_friction)} with history=False"
        )


def _sand_simulation(
    f: Any,
    grid: int,
    exact: bool,
    seed: int,
    grains: int,
    radius: float,
    history: bool,
    rolling_friction: float,
) -> tuple:
    """``(sim, sdf, sdf_name)``: the sand scene's grains in the hopper of ``f`` under
    ``Gravity((0, -9.81))``, meeting ``sdf`` (a ``grid`` x ``grid`` GridSDF of ``f``, or
    ``f`` itself with ``exact``), described by ``sdf_name``."""
    from fastsdf.fields.grid import GridSDF
    from fastsdf.granular.params import ContactLaw, derived_stiffness
    from fastsdf.particles import Gravity, ParticleSimulation

    g = 9.81
    law = ContactLaw(history=history, rolling_friction=float(rolling_friction))
    if exact:
        sdf, sdf_name = f, "the exact compiled SDF (no grid)"
        # The grains' extent would set the derived stiffness: take the pictured world's height.
        law = law._replace(stiffness=derived_stiffness(1.0, g, BOUNDS[1][1] - BOUNDS[1][0]))
    else:
        sdf = GridSDF(f, bounds=BOUNDS, samples=[grid * 1j, grid * 1j], mode="exact")
        sdf_name = f"a {grid}x{grid} GridSDF"
    rng = np.random.default_rng(seed)
    radii = radius * rng.uniform(1 - SAND_RADIUS_SPREAD, 1 + SAND_RADIUS_SPREAD, grains)
    sim: Any = ParticleSimulation(  # a GrainSimulation
        sdf, positions=hopper_fill(grains, radii, rng), radius=radii, contacts=law
    )
    sim.force_generators.append(Gravity((0.0, -g)))
    return sim, sdf, sdf_name


def _sand_heaps(sim: Any, radius: float) -> dict[str, Any]:
    """The :class:`SandResult` fields of the heaps: the funnel's (``heap_fraction``,
    ``heap_top``) and the cone on the disc (``cone_grains``, ``cone_top``, and its angle of
    repose ``repose_left`` and ``repose_right``)."""
    from fastsdf.granular.analysis import repose_angle

    x = np.asarray(sim.p["x"])
    heap = x[:, 1] < -0.5
    still = np.hypot(*np.asarray(sim.p["v"]).T) < 0.05
    resting = heap & still
    # the cone: grains at rest on the disc (|x| <= 0.5, its top near y = 0.3), below the outlet
    cone = still & (np.abs(x[:, 0]) < 0.6) & (x[:, 1] > 0.0) & (x[:, 1] < HOPPER_OUTLET_Y)
    # bins one mean radius wide: the cone is about sixteen diameters across, and bins of a
    # diameter would leave a flank too few surface points to fit
    repose = repose_angle(x[cone], np.asarray(sim.p["r"])[cone], bin_width=float(radius))
    return dict(
        heap_fraction=float(np.mean(heap)),
        heap_top=float(x[resting, 1].max()) if resting.any() else float("nan"),
        repose_left=repose.left,
        repose_right=repose.right,
        cone_grains=int(cone.sum()),
        cone_top=float(x[cone, 1].max()) if cone.any() else float("nan"),
    )


def _sand_law(res: SandResult) -> str:
    """The contact law as the user would write it, and what its options do."""
    if not res.history:
        return "ContactLaw() (no contact history: no static friction)"
    law = f"ContactLaw(history=True, rolling_friction={res.rolling_friction:g})"
    what = "a tangential spring per contact: static friction"
    if res.rolling_friction:
        what += "; rolling resistance: discs hold a slope"
    return f"{law} ({what})"


def _repose_line(res: SandResult) -> str:
    """The cone's angle of repose where its two flanks agree (within
    :data:`REPOSE_AGREEMENT` degrees), else why it is not measured or not reliable."""
    left, right = res.repose_left, res.repose_right
    where = (
        "the grains at rest on the disc, a line fitted to each flank of the cone's surface, "
        "bins one radius wide"
    )
    if res.repose_reliable:
        return (
            f"angle of repose: {left:.1f} (left) and {right:.1f} (right) degrees, mean "
            f"{(left + right) / 2:.1f} ({where})"
        )
    if np.isfinite(left) and np.isfinite(right):
        return (
            f"angle of repose: not reliable here: the cone's flanks give {left:.1f} (left) "
            f"and {right:.1f} (right) degrees, more than {REPOSE_AGREEMENT:g} apart; the cone "
            f"on the disc holds {_plural(res.cone_grains, 'grain')}, too few for a slope to "
            f"fit (a heap of hundreds of grains measures it: examples/heap.py pours 400 onto "
            f"a floor)"
        )
    if not res.history:
        return (
            "angle of repose: not measured (without contact history there is no static "
            "friction: the grains on the disc spread flat instead of forming a cone)"
        )
    return (
        "angle of repose: not measured (the grains at rest on the disc do not form a cone "
        "with two flanks: pour longer, or see examples/heap.py, which pours onto a floor)"
    )


def sand_summary(res: SandResult) -> str:
    """Human-readable lines for the sand scene's result ``res``."""
    lines = [
        f"world: {res.world}, {WORLDS[res.world][1]}; queried through {res.sdf}",
        f"poured {_plural(res.grains, 'grain')} of radius {res.radius:g} +-"
        f"{SAND_RADIUS_SPREAD:.0%} from a hopper above the disc under g = 9.81 length/s**2 "
        f"(the world in metres; Gravity()'s default is the notebook's 1)",
        f"contact law: {_sand_law(res)} derived its stiffness {res.stiffness:.4g} from the "
        f"grains (1% overlap under a column as tall as the world): "
        f"{res.substeps_per_step:,} substeps per 1/30 s step",
        f"simulated {_plural(res.steps, 'step')} of {res.timestep:.4g} s "
        f"({res.steps * res.timestep:.2f} s of simulated time)",
    ]
    if res.steps > 1:
        lines.append(
            f"rate: {res.grain_substeps_per_second / 1e6:.2f} M grain-substeps/s over "
            f"{_plural(res.steps - 1, 'step')} in {res.sim_seconds:.2f} s (the first step, "
            f"{res.first_step_seconds:.2f} s, compiles or loads the kernels and is not counted)"
        )
    else:
        lines.append(f"the only step took {res.first_step_seconds:.2f} s, compiling included")
    lines.append(
        f"cone: {_plural(res.cone_grains, 'grain')} at rest on the disc, the highest at "
        f"y = {res.cone_top:.2f}; {res.heap_fraction:.0%} of the grains in the funnel (below "
        f"the disc), the highest at rest at y = {res.heap_top:.2f}; largest overlap at the end "
        f"{res.max_overlap:.2%} of a diameter between grains, {res.max_wall_overlap:.2%} "
        f"against the world"
    )
    lines.append(_repose_line(res))
    if res.load is not None:
        lines.append(
            f"machine load (1-minute average) {res.load[0]:.1f} before and {res.load[1]:.1f} "
            f"after the steps, on {os.cpu_count() or 1} cores"
        )
    if res.animation:
        lines.append(f"video: {res.animation}")
    lines.append(f"last frame: {res.last_frame}")
    return "\n".join(lines)
