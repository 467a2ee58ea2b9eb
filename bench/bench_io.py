"""Recording trajectories: the cost of writing 1e6 positions every 10 steps, against the run.

    python -m bench --only io

Two identical simulations (the demo's: seed world on a 400x400 grid, gravity, 1e6 particles)
run the same steps in alternation, one with ``sim.run`` alone and one through
``TrajectoryRecorder.run`` writing a frame every 10 steps; the cost is the extra wall time of
the recorded one, per variant (stored dtype, file on disk or in memory).
"""

from __future__ import annotations

import os
import tempfile
import time

from .common import stamp, table

COMMAND = "python -m bench --only io"


def _sim(n: int):
    from fastsdf.fields.grid import GridSDF
    from fastsdf.particles import Gravity, ParticleSimulation
    from fastsdf.shapes.scenes import seed_world

    grid = GridSDF(seed_world(), bounds=((-2, 2), (-2, 2)), samples=[400j, 400j])
    sim = ParticleSimulation(grid, n=n, timestep=1 / 30, seed=0)
    sim.force_generators.append(Gravity())
    return sim


def run(quick: bool = False) -> str:
    from fastsdf.io import TrajectoryRecorder

    n = 100_000 if quick else 1_000_000
    steps, every, rounds = (40, 10, 2) if quick else (100, 10, 1)
    load0 = os.getloadavg()[0]
    variants = [("float64", "disk", None), ("float32", "disk", "float32")]
    if os.path.isdir("/dev/shm"):
        variants.append(("float64", "memory (/dev/shm)", None))
    rows = []
    for dtype_name, where, dtype in variants:
        plain, blocks, recorded = _sim(n), _sim(n), _sim(n)
        for s in (plain, blocks, recorded):
            s.run(1)  # compile or load the kernel outside the timing
        folder = "/dev/shm" if where.startswith("memory") else None
        with tempfile.TemporaryDirectory(dir=folder) as tmp:
            path = os.path.join(tmp, "traj.h5")
            t_plain = t_blocks = t_rec = 0.0
            with TrajectoryRecorder(path, every=every, dtype=dtype) as rec:
                rec.record(recorded)
                inside = {"record": 0.0, "run": 0.0}
                record, step = rec.record, recorded.run

                def timed_record(sim, record=record, inside=inside):
                    t0 = time.perf_counter()
                    record(sim)
                    inside["record"] += time.perf_counter() - t0

                def timed_run(k, step=step, inside=inside):
                    t0 = time.perf_counter()
                    step(k)
                    inside["run"] += time.perf_counter() - t0

                rec.record, recorded.run = timed_record, timed_run
                for _ in range(rounds):
                    t0 = time.perf_counter()
                    plain.run(steps)
                    t1 = time.perf_counter()
                    for _ in range(steps // every):
                        blocks.run(every)
                    t2 = time.perf_counter()
                    rec.run(recorded, steps)
                    t3 = time.perf_counter()
                    t_plain += t1 - t0
                    t_blocks += t2 - t1
                    t_rec += t3 - t2
            frames = rec.frames
            size = os.path.getsize(path)
        assert (plain.p["x"] == recorded.p["x"]).all()  # the recorder changes no bit
        rows.append(
            [
                dtype_name,
                where,
                frames,
                f"{t_plain:.2f}",
                f"{t_blocks:.2f}",
                f"{t_rec:.2f}",
                f"{100 * (t_rec - t_plain) / t_plain:+.0f}%",
                f"{100 * (t_rec - t_blocks) / t_blocks:+.0f}%",
                f"{100 * inside['record'] / inside['run']:.1f}%",
                f"{inside['record'] / (frames - 1) * 1e3:.0f}",
                f"{size / frames / 1e6:.1f}",
            ]
        )
    load1 = os.getloadavg()[0]
    head = [
        "stored as",
        "file in",
        "frames",
        "alone, one call (s)",
        f"alone, calls of {every} (s)",
        "recorded (s)",
        "cost vs one call",
        f"cost vs calls of {every}",
        "in record() / in sim.run",
        "record() per frame (ms)",
        "MB per frame",
    ]
    return "\n".join(
        [
            "## Trajectories",
            "",
            stamp(COMMAND) + f" Load average {load0:.1f} at start, {load1:.1f} at the end "
            f"(2 cores, shared).",
            "",
            f"{n:,} particles (the demo's simulation), {rounds} x {steps} steps, "
            "positions recorded "
            f"every {every} steps by `fastsdf.io.TrajectoryRecorder.run` (H5MD, HDF5 SWMR mode, "
            "one flush per frame, uncompressed), against identical simulations without recording, "
            f"alternated in one process: one `sim.run({steps})` call, and calls of {every} steps "
            "(what recording every 10 steps needs: the block kernel keeps particles in cache "
            "through the steps of one call, so shorter calls cost more). The recorded simulation "
            "ends in the same state, bit for bit (checked). 'in record() / in sim.run': the "
            "recorded simulation's time inside `record` (writing and flushing frames) over its "
            "time inside `sim.run`, both measured in the same loop: the direct measure of the "
            "recording's cost, less exposed to the machine's load than differences of runs.",
            "",
            table(head, rows),
            "",
        ]
    )
