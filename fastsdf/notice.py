"""One-line notices on stderr for waits a user would otherwise sit through in silence.

``with compiling("the kernel of a new scene"):`` runs its block; if the block is still running
after ``after`` seconds (default 1), one line is printed on stderr, e.g.
``fastsdf: compiling the kernel of a new scene (once; later runs load it from the cache)...``,
and when the block ends a line with its duration (every such wait is said: two new scenes,
two notices; :func:`compiling_first` wraps only the first call of numba kernels).
:func:`notice` prints a message at most once per process. ``FASTSDF_QUIET=1`` silences every
notice.

``with RunProgress(total, "what", "frames") as bar: ... bar.update(done)`` tracks a long
computation done in pieces: once the rate of the pieces says the whole will take longer than
:data:`PROGRESS_AFTER_S`, it shows its progress and the time left on stderr (a tqdm bar on a
terminal; elsewhere, in a notebook or a log, a line now and then). The simulations' ``run()``
use it; this module is the bottom layer, so the physics imports it and no drawing code.
"""

from __future__ import annotations

import os
import sys
import threading
import time
import types
import warnings
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from typing import IO, Any

__all__ = [
    "PROGRESS_AFTER_S",
    "PROGRESS_LINE_EVERY_S",
    "RunProgress",
    "compiling",
    "compiling_first",
    "notice",
    "warn_caller",
]

#: A computation tracked by :class:`RunProgress` shows its progress once its estimated
#: duration exceeds this (seconds).
PROGRESS_AFTER_S = 5.0
#: Where stderr is not a terminal, a progress line at most this often (seconds).
PROGRESS_LINE_EVERY_S = 15.0

_said: set[str] = set()
_lock = threading.Lock()
# Nested waits print the outermost notice only.
_depth = threading.local()
# The RunProgress blocks open in this thread, innermost last.
_running = threading.local()


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
    message = f"fastsdf: compiling {what} (once; later runs load it from the cache)...\n"
    printed = threading.Event()

    def speak() -> None:
        try:
            sys.stderr.write(message)
            sys.stderr.flush()
        except (AttributeError, ValueError, OSError):  # closed or missing stderr
            return
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


def warn_caller(message: str, category: type[Warning] = UserWarning) -> None:
    """``warnings.warn(message, category)`` attributed to the first caller outside fastsdf
    (the user's line that ran into it, however deep inside the library it was found)."""
    package = os.path.dirname(os.path.abspath(__file__)) + os.sep
    frame: types.FrameType | None = sys._getframe(1)
    level = 2  # warn_caller's caller
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(package):
        level += 1
        frame = frame.f_back
    warnings.warn(message, category, stacklevel=level)


def compiling_first(what: str, *kernels: Any, after: float = 1.0) -> AbstractContextManager:
    """:func:`compiling` while any of ``kernels`` (numba dispatchers) has compiled nothing in
    this process yet (its first call compiles it, or loads it from numba's cache), else a
    no-op: a later call that merely takes long is not announced as compiling."""
    if all(getattr(k, "signatures", True) for k in kernels):
        return nullcontext()
    return compiling(what, after=after)


def _duration(seconds: float) -> str:
    """``42 s``, ``3 min 20 s``, ``1 h 05 min``."""
    s = max(0, int(round(seconds)))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def _amount(x: float) -> str:
    """``7``, ``3.4``, ``1,200``: tenths only where there are any."""
    return f"{x:,.1f}".removesuffix(".0")


def _is_terminal(stream: IO[str]) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # closed or not a real stream
        return False


class RunProgress:
    """The progress of a computation of ``total`` units (``unit``, e.g. ``'frames'``), done
    in pieces: call :meth:`update` with the units done so far after each piece.

    Nothing is shown while the estimated duration (the time so far plus the units left at the
    rate of the pieces after the first, which may include compiling) stays under ``after``
    seconds (default :data:`PROGRESS_AFTER_S`); from the first update that says it will not,
    stderr (or ``stream``) shows ``what``, the units done and the time left: a tqdm bar on a
    terminal, else a line every :data:`PROGRESS_LINE_EVERY_S` seconds and one at the end.
    ``FASTSDF_QUIET=1`` shows nothing. Use it as a context manager (or call :meth:`close`).

    Inside another one's ``with`` block (a recorded run, whose recorder runs the simulation
    in blocks) it shows nothing itself and reports to the outer one, in the same units:
    ``done`` here is the outer's ``done`` at its start plus this one's.
    """

    def __init__(
        self,
        total: float,
        what: str,
        unit: str = "steps",
        after: float | None = None,
        stream: IO[str] | None = None,
    ):
        self.total = float(total)
        self.what = what
        self.unit = unit
        self.after = PROGRESS_AFTER_S if after is None else float(after)
        self._stream = stream
        self._start = time.perf_counter()
        self._first: tuple[float, float] | None = None  # (time, done) at the first update
        self._done = 0.0
        self._shown = False
        self._bar: Any = None
        self._last_line = 0.0
        self._closed = False
        stack = getattr(_running, "stack", None)
        self._outer: RunProgress | None = stack[-1] if stack else None
        self._base = self._outer._done if self._outer is not None else 0.0

    @property
    def shown(self) -> bool:
        """Whether the progress has been shown."""
        return self._shown

    def _out(self) -> IO[str]:
        return self._stream if self._stream is not None else sys.stderr

    def remaining(self, now: float | None = None) -> float:
        """Estimated seconds left (inf before any unit is done)."""
        now = time.perf_counter() if now is None else now
        left = max(self.total - self._done, 0.0)
        if self._first is not None and self._done > self._first[1]:
            t1, d1 = self._first
            return (now - t1) / (self._done - d1) * left
        if self._done > 0:
            return (now - self._start) / self._done * left
        return float("inf") if left else 0.0

    def update(self, done: float) -> None:
        """``done`` units are done (in all, not since the last call)."""
        if self._closed:
            return
        if self._outer is not None:
            self._outer.update(self._base + float(done))
            return
        now = time.perf_counter()
        self._done = min(float(done), self.total)
        first = self._first is None
        if first:
            self._first = (now, self._done)
        elapsed = now - self._start
        left = self.remaining(now)
        if not self._shown:
            if first and elapsed <= self.after:
                return  # the first piece may have compiled: the next one gives the rate
            if _quiet() or not elapsed + left > self.after or self._done >= self.total:
                return  # (finished at its first update: nothing left to show)
            self._shown = True
            if _is_terminal(self._out()):
                from tqdm import tqdm

                self._bar = tqdm(
                    total=self.total,
                    desc=f"fastsdf: {self.what}",
                    unit=f" {self.unit}",
                    file=self._out(),
                    dynamic_ncols=True,
                    leave=True,
                    bar_format="{l_bar}{bar}| {n:.1f}/{total:.0f}{unit} [{elapsed}<{remaining}]",
                )
            else:
                self._line(elapsed, left)
                return
        if self._bar is not None:
            self._bar.update(self._done - self._bar.n)
        elif now - self._last_line >= PROGRESS_LINE_EVERY_S:
            self._line(elapsed, left)

    def _line(self, elapsed: float, left: float) -> None:
        self._last_line = time.perf_counter()
        self._write(
            f"fastsdf: {self.what}: {_amount(self._done)} of {_amount(self.total)} "
            f"{self.unit} in "
            f"{_duration(elapsed)}, about {_duration(left)} left\n"
        )

    def _write(self, text: str) -> None:
        try:
            out = self._out()
            out.write(text)
            out.flush()
        except (AttributeError, ValueError, OSError):  # closed or missing stderr
            pass

    def close(self) -> None:
        """End the display (a bar stays on screen; a line says how long it took)."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        elif self._shown and not self._closed:
            elapsed = time.perf_counter() - self._start
            self._write(
                f"fastsdf: {self.what}: {_amount(self._done)} of {_amount(self.total)} "
                f"{self.unit} in "
                f"{_duration(elapsed)}\n"
            )
        self._closed = True

    def __enter__(self) -> RunProgress:
        if not hasattr(_running, "stack"):
            _running.stack = []
        _running.stack.append(self)
        return self

    def __exit__(self, *exc: object) -> None:
        stack = _running.stack
        if stack and stack[-1] is self:
            stack.pop()
        self.close()
