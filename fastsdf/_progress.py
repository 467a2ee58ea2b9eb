"""A minimal progress bar on stderr, shared by the demo and the benchmarks (no dependency)."""

from __future__ import annotations

import sys
import time


class Progress:
    """``with Progress(total, 'label') as bar: ... bar.step(note)`` draws ``[###---] k/total``."""

    def __init__(self, total: int, label: str = "", stream=None):
        self.total, self.label, self.done = max(1, int(total)), label, 0
        self.stream = stream or sys.stderr
        self.t0 = time.perf_counter()

    def __enter__(self):
        self._draw()
        return self

    def step(self, note: str = "", count: int = 1):
        self.done = min(self.total, self.done + count)
        self._draw(note)

    def _draw(self, note: str = ""):
        width = 30
        filled = int(width * self.done / self.total)
        bar = "#" * filled + "-" * (width - filled)
        elapsed = time.perf_counter() - self.t0
        self.stream.write(f"\r{self.label:<24} [{bar}] {self.done}/{self.total} "
                          f"{elapsed:6.1f}s {note[:40]:<40}")
        self.stream.flush()

    def __exit__(self, *exc):
        self.stream.write("\n")
        self.stream.flush()
