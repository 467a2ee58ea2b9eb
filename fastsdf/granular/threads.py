"""The number of threads of the granular passes, chosen by measuring during the run.

A substep of a few thousand grains lasts a few hundred microseconds: with numba's ``omp``
threading layer each parallel region ends at a barrier where the idle threads spin, so beside
other work (a second simulation, a browser, a sweep of runs) a thread that waits for a core
can stall the whole pass, and two threads become many times slower than one. The results do
not depend on the number of threads (the chunks of the passes are fixed by the grains), so the
engine may change it between substeps: :class:`ThreadTuner` times the run in segments at the
threads numba allows and at one thread, keeps the faster, and measures the other again from
time to time, at a small share of the run's time.
"""

from __future__ import annotations

import time

import numba

__all__ = ["SEGMENT_WORK", "ThreadTuner"]

#: Grain-substeps per measured segment (a few hundredths of a second on one core).
SEGMENT_WORK = 1_000_000
#: The other thread count is measured again once the run has spent this many times the cost
#: of one of its segments (at its last measured rate) since it was last measured: at most
#: about 1 / PROBE_EVERY of the run's time goes to measuring the slower choice.
PROBE_EVERY = 25.0


class ThreadTuner:
    """Chooses, segment after segment, between ``most`` threads and one for a simulation of
    ``grains`` grains.

    :meth:`next_threads` says how many threads the next segment runs on; :meth:`record` takes
    its work (grain-substeps) and duration. The cost of each choice (seconds per
    grain-substep) is the mean of its last two segments; the cheaper one runs, and the other
    is measured again (one segment) once the time run since its last measurement exceeds
    :data:`PROBE_EVERY` times what a segment of :data:`SEGMENT_WORK` costs it."""

    def __init__(self, most: int, grains: int) -> None:
        self.most = most
        self.grains = grains
        self.cost: dict[int, float] = {}
        self._since = 0.0  # seconds run since the other choice was last measured
        # the segment under way (it may span several calls of the engine's advance)
        self._segment = max(1, SEGMENT_WORK // grains)
        self._done = 0
        self._elapsed = 0.0
        self._threads = most
        self._t0 = 0.0

    def start(self) -> None:
        """The engine starts stepping: set the threads, start the clock."""
        if not self._done:
            self._threads = self.next_threads()
        numba.set_num_threads(self._threads)
        self._t0 = time.perf_counter()

    def substep_done(self) -> None:
        """One substep done: at the end of a segment, record it and choose the next one's
        threads."""
        self._done += 1
        if self._done < self._segment:
            return
        now = time.perf_counter()
        self.record(self._threads, self._done * self.grains, self._elapsed + now - self._t0)
        self._done = 0
        self._elapsed = 0.0
        self._threads = self.next_threads()
        numba.set_num_threads(self._threads)
        self._t0 = time.perf_counter()

    def stop(self) -> None:
        """The engine stops stepping (the segment goes on at the next :meth:`start`)."""
        self._elapsed += time.perf_counter() - self._t0

    def _best(self) -> int:
        return min(self.cost, key=self.cost.__getitem__)

    def next_threads(self) -> int:
        """The threads of the next segment."""
        for threads in (self.most, 1):
            if threads not in self.cost:
                return threads
        best = self._best()
        other = 1 if best == self.most else self.most
        if self._since >= PROBE_EVERY * SEGMENT_WORK * self.cost[other]:
            return other
        return best

    def record(self, threads: int, work: int, seconds: float) -> None:
        """A segment of ``work`` grain-substeps on ``threads`` threads took ``seconds``."""
        cost = seconds / max(work, 1)
        measured = len(self.cost) == 2
        if not measured or threads != self._best():  # a first figure, or a probe
            self.cost[threads] = cost
            self._since = 0.0
        else:
            self.cost[threads] = 0.5 * (self.cost[threads] + cost)
            self._since += seconds
