"""One-line notices on stderr for waits a user would otherwise sit through in silence.

``with compiling("the kernel of a new scene"):`` runs its block; if the block is still running
after ``after`` seconds (default 1), one line is printed on stderr, e.g.
``fastsdf: compiling the kernel of a new scene (once; later runs load it from the cache)...``,
and when the block ends its duration is added on the same line. Each message is printed at
most once per process. ``FASTSDF_QUIET=1`` silences every notice.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["compiling", "notice"]

_said: set[str] = set()
_lock = threading.Lock()
# Nested waits print the outermost notice only.
_depth = threading.local()


def _quiet() -> bool:
    return os.environ.get("FASTSDF_QUIET", "").strip() not in ("", "0")


def notice(message: str) -> bool:
    """Print ``fastsdf: message`` on stderr once per process; returns whether it printed."""
    if _quiet():
        return False
    with _lock:
        if message in _said:
            return False
        _said.add(message)
    try:
        sys.stderr.write(f"fastsdf: {message}\n")
        sys.stderr.flush()
    except (AttributeError, ValueError, OSError):  # closed or missing stderr
        return False
    return True


@contextmanager
def compiling(what: str, after: float = 1.0) -> Iterator[None]:
    """Say ``compiling <what>`` on stderr if the block takes longer than ``after`` seconds.

    The line is printed from a timer thread while the block runs (numba releases the GIL often
    enough while it compiles), so the user sees it during the wait, not after it.
    """
    depth = getattr(_depth, "value", 0)
    if depth or _quiet():
        _depth.value = depth + 1
        try:
            yield
        finally:
            _depth.value = depth
        return
    message = f"compiling {what} (once; later runs load it from the cache)..."
    printed = threading.Event()

    def speak() -> None:
        if notice(message):
            printed.set()

    timer = threading.Timer(after, speak)
    timer.daemon = True
    start = time.perf_counter()
    _depth.value = 1
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
        _depth.value = 0
        if printed.is_set():
            try:
                sys.stderr.write(f"fastsdf: ...done in {time.perf_counter() - start:.1f} s\n")
                sys.stderr.flush()
            except (AttributeError, ValueError, OSError):
                pass
