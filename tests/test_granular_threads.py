"""The granular engine's results do not depend on the number of threads: the chunks of its
passes are fixed by the number of grains, and its sums run in one order."""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest

import fastsdf as fs
from fastsdf.granular import ContactLaw, GranularSimulation
from fastsdf.granular.simulation import PARALLEL_MIN_GRAINS

two_threads = pytest.mark.skipif(
    numba.config.NUMBA_NUM_THREADS < 2, reason="numba has a single thread here"
)


def falling_bed(threads: int, n: int = 4800) -> tuple[GranularSimulation, dict]:
    """Discs of two sizes thrown on a loose lattice onto a floor with a bump (history and
    rolling friction, against each other and the world), stepped three frames on ``threads``
    threads; the simulation and what it reports."""
    before = numba.get_num_threads()
    numba.set_num_threads(threads)
    try:
        rng = np.random.default_rng(3)
        cols = int(math.sqrt(n) * 1.6)
        j, i = np.divmod(np.arange(n), cols)
        pos = np.stack([0.6 + i * 1.08 + rng.uniform(-0.03, 0.03, n), 0.55 + j * 1.08], 1)
        radius = np.where(rng.uniform(size=n) < 0.5, 0.5, rng.uniform(0.35, 0.5, n))
        width = cols * 1.08 + 0.2
        world = fs.Halfspace((0.0, 1.0), 0.0) | fs.Circle(center=[0.4 * width, -1.4], radius=1.5)
        law = ContactLaw(4e4, 0.5, 0.5, history=True, rolling_friction=0.2)
        sim = GranularSimulation(
            world,
            positions=pos,
            velocities=rng.normal(scale=3.0, size=(n, 2)),
            radius=radius,
            contacts=law,
            wall_contacts=law._replace(restitution=0.3),
            gravity=(0.0, -40.0),
            timestep=60 * 2.5e-4,
            substep=2.5e-4,
            skin=0.15,
            periodic_x=(0.0, width),
        )
        sim.run(3)
        out = {
            "positions": sim.positions,
            "velocities": sim.velocities,
            "angular_velocities": sim.angular_velocities,
            "wall_force": np.asarray(sim.wall_force),
            "energy": np.array(list(sim.energy().values())),
            "springs": sim.tangential_springs()[1],
        }
    finally:
        numba.set_num_threads(before)
    return sim, out


@two_threads
def test_a_bed_gives_the_same_bits_on_one_and_two_threads(monkeypatch):
    """Several thousand grains (above PARALLEL_MIN_GRAINS: the passes run on every thread),
    with history, through list rebuilds: every position, velocity, spring, the world's force
    and the energies are the same bits on 1 and 2 threads, and with the thread count chosen
    by measuring (short segments: it changes between 2 and 1 during the run)."""
    import fastsdf.granular.threads as threads

    one, a = falling_bed(1)
    assert one._tuner is None  # one thread: nothing to choose
    monkeypatch.setattr(threads, "SEGMENT_WORK", 20 * 4800)
    two, b = falling_bed(2)
    assert two._tuner is not None and set(two._tuner.cost) == {1, 2}
    assert one.ids.shape[0] >= PARALLEL_MIN_GRAINS
    assert one.rebuilds > 2  # the lists were rebuilt during the run
    assert one.contact_counts()[0] > 300 and one.contact_counts()[1] > 0
    for name in a:
        assert a[name].tobytes() == b[name].tobytes(), name


def test_the_default_chunks_follow_the_grains_not_the_threads():
    """The force pass's chunks, which fix the list and the order of each grain's sums, are
    chosen from the number of grains only: n // 256 up to 8 (what two threads gave before),
    more from WIDE_CHUNKS_GRAINS."""
    from fastsdf.granular.simulation import _chunk_count

    before = numba.get_num_threads()
    counts = {}
    for threads in sorted({1, numba.config.NUMBA_NUM_THREADS}):
        numba.set_num_threads(threads)
        try:
            counts[threads] = [_chunk_count(None, n) for n in (10, 700, 5000, 65535, 10**5, 10**6)]
        finally:
            numba.set_num_threads(before)
    assert len({tuple(c) for c in counts.values()}) == 1
    assert counts[1] == [1, 2, 8, 8, 16, 32]


def test_the_thread_tuner_keeps_the_faster_choice_and_measures_the_other_rarely():
    """Fed segment times, the tuner measures both choices, runs the faster, measures the other
    again only after PROBE_EVERY times that one's segment cost, and follows a change: when
    the threads start to wait for each other (a busy machine), it moves to one thread."""
    from fastsdf.granular.threads import PROBE_EVERY, SEGMENT_WORK, ThreadTuner

    tuner = ThreadTuner(most=2, grains=5000)
    seen = []

    def segment(cost_of: dict) -> None:
        threads = tuner.next_threads()
        seen.append(threads)
        tuner.record(threads, SEGMENT_WORK, cost_of[threads] * SEGMENT_WORK)

    quiet = {2: 1e-8, 1: 1.6e-8}  # two threads 1.6x faster
    for _ in range(200):
        segment(quiet)
    assert seen[:2] == [2, 1]
    probes = seen[2:].count(1)
    # a probe of one thread once per PROBE_EVERY of its segment costs of run time
    expected = 198 * quiet[2] / (PROBE_EVERY * quiet[1])
    assert 0 < probes <= expected + 1
    busy = {2: 2e-7, 1: 1.7e-8}  # two threads spin against other work: 12x slower
    seen.clear()
    for _ in range(200):
        segment(busy)
    assert seen[:3].count(1) >= 1 and seen[-100:].count(1) >= 95
