"""Video frames of 1e6 particles at 720p: the compiled frame writer against save_animation.

    python -m bench --only video

Both write the same density frames of the same particle states (taken from the demo's
simulation: the seed world on a 400x400 grid, gravity) to an MP4 at 1280x720, in one process, one
after the other. The simulation's steps are not timed: each frame swaps in a stored state.
'End to end' is the wall time from creating the writer (or the figure) to the closed file,
divided by the frames: the static picture, every splat and composite, ffmpeg's encoding.
"""

from __future__ import annotations

import os
import resource
import tempfile
import time
from types import SimpleNamespace

import numpy as np

from .common import stamp, table

COMMAND = "python -m bench --only video"
SIZE = (1280, 720)


def _cpu() -> float:
    """CPU seconds used so far by this process and its finished children (ffmpeg)."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _states(n: int, count: int, steps_between: int) -> tuple:
    from fastsdf.fields.grid import GridSDF
    from fastsdf.particles import Gravity, ParticleSimulation
    from fastsdf.shapes.scenes import seed_world

    f = seed_world()
    grid = GridSDF(f, bounds=((-2, 2), (-2, 2)), samples=[400j, 400j])
    sim = ParticleSimulation(grid, n=n, timestep=1 / 30, seed=0)
    sim.force_generators.append(Gravity())
    states = []
    for _ in range(count):
        sim.run(steps_between)
        states.append((np.array(sim.p["x"]), float(sim.t)))
    return f, states, np.array(sim.p["r"])


def _new_writer(f, states, r, frames: int, path: str, vmax: float, preset: str) -> dict:
    from fastsdf.viz.frames import VideoWriter

    t0, c0 = time.perf_counter(), _cpu()
    with VideoWriter(
        path,
        f,
        size=SIZE,
        fps=30,
        mode="density",
        vmax=vmax,
        preset=preset,
        title=f"{len(r):,} particles",
    ) as w:
        for i in range(frames):
            x, t = states[i % len(states)]
            w.add(x[:, 0], x[:, 1], r, t=t, step=i)
    total, cpu = time.perf_counter() - t0, _cpu() - c0
    # the particle layer alone (splat, composite, clock), without ffmpeg
    x, t = states[0]
    t1 = time.perf_counter()
    for _ in range(5):
        w.render(x[:, 0], x[:, 1], r, t=t, step=0)
    layer = (time.perf_counter() - t1) / 5
    return {"total": total, "cpu": cpu, "layer": layer, "size": os.path.getsize(path)}


def _save_animation(f, states, r, frames: int, path: str) -> dict:
    from fastsdf.viz.render import animate, save_animation, world_figure

    t0, c0 = time.perf_counter(), _cpu()
    fake = SimpleNamespace(p={"x": states[0][0], "r": r}, t=states[0][1], dt=1 / 30)
    at = {"i": 0}

    def advance(k: int) -> None:
        at["i"] += 1
        fake.p["x"], fake.t = states[at["i"] % len(states)]

    fig, ax, cax = world_figure(f, ((-2, 2), (-2, 2)), 400, (SIZE[0] / 100, SIZE[1] / 100), 100)
    anim = animate(
        fake,
        ax,
        frames,
        1,
        advance=advance,
        title=f"{len(r):,} particles, ",
        colorbar=cax,
        bounds=((-2, 2), (-2, 2)),
    )
    save_animation(anim, path, fps=30, progress=False)
    return {"total": time.perf_counter() - t0, "cpu": _cpu() - c0, "size": os.path.getsize(path)}


def run(quick: bool = False) -> str:
    n = 100_000 if quick else 1_000_000
    frames_new = 20 if quick else 120
    frames_old = 5 if quick else 20
    load0 = os.getloadavg()[0]
    f, states, r = _states(n, 8, 8)
    with tempfile.TemporaryDirectory() as tmp:
        # warm-up: kernels compiled or loaded, fonts and ffmpeg on disk in the page cache
        _new_writer(f, states, r, 2, os.path.join(tmp, "warm.mp4"), 1000.0, "veryfast")
        old = _save_animation(f, states, r, frames_old, os.path.join(tmp, "old.mp4"))
        new = _new_writer(
            f, states, r, frames_new, os.path.join(tmp, "new.mp4"), 1000.0, "veryfast"
        )
        mid = _new_writer(
            f, states, r, frames_new, os.path.join(tmp, "mid.mp4"), 1000.0, "superfast"
        )
        fast = _new_writer(
            f, states, r, frames_new, os.path.join(tmp, "fast.mp4"), 1000.0, "ultrafast"
        )
    load1 = os.getloadavg()[0]
    fps_old = frames_old / old["total"]
    rows = [
        [
            "`render.save_animation` (Matplotlib draw per frame)",
            frames_old,
            f"{old['total']:.1f}",
            f"{fps_old:.2f}",
            "1.0",
            f"{old['cpu'] / frames_old * 1e3:.0f}",
            "",
            f"{old['size'] / 1e3:.0f}",
        ],
    ]
    for name, res in (
        ("`viz.frames.VideoWriter`, preset veryfast (default)", new),
        ("`viz.frames.VideoWriter`, preset superfast", mid),
        ("`viz.frames.VideoWriter`, preset ultrafast", fast),
    ):
        fps = frames_new / res["total"]
        rows.append(
            [
                name,
                frames_new,
                f"{res['total']:.1f}",
                f"{fps:.1f}",
                f"{fps / fps_old:.0f}",
                f"{res['cpu'] / frames_new * 1e3:.0f}",
                f"{res['layer'] * 1e3:.1f}",
                f"{res['size'] / 1e3:.0f}",
            ]
        )
    head = [
        "writer",
        "frames",
        "wall (s)",
        "frames/s end to end",
        "x save_animation",
        "CPU per frame (ms)",
        "particle layer per frame (ms)",
        "file (kB)",
    ]
    return "\n".join(
        [
            "## Video",
            "",
            stamp(COMMAND) + f" Load average {load0:.1f} at start, {load1:.1f} at the end "
            f"(2 cores, shared).",
            "",
            f"{n:,} particles from the demo's simulation (seed world, 400x400 grid, gravity; 8 "
            "stored states, cycled), density frames at 1280x720 with a colour bar and the clock, "
            "H.264 (libx264, crf 20 for the new writer, matplotlib's bitrate 2400k for the old), "
            "30 fps; simulation steps not timed. Wall: from creating the writer or figure to the "
            "closed file. The particle layer: `VideoWriter.render` (splat, composite over a copy "
            "of the background, clock), without ffmpeg; ffmpeg encodes in its own process while "
            "the next frame is composed. CPU per frame: CPU seconds of this process and of "
            "ffmpeg (user + system) over the whole write, per frame: less sensitive than wall time "
            "to other processes on the machine; on 2 idle cores the wall time per frame can fall "
            "to about half of it when the encoder and the particle layer overlap.",
            "",
            table(head, rows),
            "",
        ]
    )
