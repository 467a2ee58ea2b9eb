"""One-line notices on stderr for waits a user would otherwise sit through in silence.

``with compiling("the kernel of a new scene"):`` runs its block; if the block is still running
after ``after`` seconds (default 1) and numba compiles for it, one line is printed on stderr,
e.g. ``fastsdf: compiling the kernel of a new scene (once; later runs load it from the
cache)...`` (nothing for a block that is merely slow, or loads kernels from the cache),
and when the block ends a line with its duration (every such wait is said: two new scenes,
two notices; :func:`compiling_first` wraps only the first call of numba kernels).
:func:`notice` prints a message at most once per process. ``FASTSDF_QUIET=1`` silences every
notice.

``with RunProgress(total, "what", "frames") as bar: ... bar.update(done)`` tracks a long
computation done in pieces: once it has measured a little of the work and the whole will take
longer than :data:`PROGRESS_AFTER_S`, it shows its progress and the time left on stderr (a
tqdm bar on a terminal; elsewhere, in a notebook or a log, a line now and then), estimated
from the work done, the time numba spends compiling left out. The simulations' ``run()`` use
it; this module is the bottom layer, so the physics imports it and no drawing code.
"""

from __future__ import annotations

import bisect
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
    "PROGRESS_MEASURE_S",
    "PROGRESS_WINDOW",
    "RunProgress",
    "compiling",
    "compile_seconds",
    "compiling_first",
    "is_terminal",
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


# The clock of the progress estimates (a test replaces it).
_clock = time.perf_counter


class _CompilerUse:
    """One thread's use of numba's compiler: how deep in its lock now and since when, the
    seconds spent holding or waiting for it (compiling, loading compiled kernels from the
    cache, or waiting for another thread's compile), and the compiles begun (a load from the
    cache takes the lock without compiling)."""

    __slots__ = ("depth", "since", "seconds", "compiles")

    def __init__(self) -> None:
        self.depth, self.since, self.seconds, self.compiles = 0, 0.0, 0.0, 0


_uses: dict[int, _CompilerUse] = {}
_compiles_begun = [0]  # in every thread
_listening = False


def _use(ident: int | None = None) -> _CompilerUse:
    ident = threading.get_ident() if ident is None else ident
    use = _uses.get(ident)
    if use is None:
        use = _uses[ident] = _CompilerUse()
    return use


def compile_seconds() -> float:
    """Seconds this thread has spent in numba's compiler (compiling, loading compiled kernels
    from the cache, or waiting for another thread's compile: numba holds one lock for all of
    it), counted from the first :class:`RunProgress` or :func:`compiling` block."""
    return _use().seconds


def _listen_to_numba() -> None:
    """Follow numba's compiler from now on: its lock (what :func:`compile_seconds` counts)
    and its compiles."""
    global _listening
    if _listening:
        return
    from numba.core import event

    class _Compiler(event.Listener):
        def on_start(self, event: event.Event) -> None:
            use = _use()
            if event.kind == "numba:compile":
                use.compiles += 1
                _compiles_begun[0] += 1
                return
            if not use.depth:
                use.since = _clock()
            use.depth += 1

        def on_end(self, event: event.Event) -> None:
            use = _use()
            if event.kind == "numba:compile" or use.depth <= 0:  # (begun before listening)
                return
            use.depth -= 1
            if not use.depth:
                use.seconds += _clock() - use.since

    listener = _Compiler()
    event.register("numba:compiler_lock", listener)
    event.register("numba:compile", listener)
    _listening = True


@contextmanager
def compiling(what: str, after: float = 1.0) -> Iterator[None]:
    """Say ``compiling <what>`` on stderr if the block takes longer than ``after`` seconds
    while numba compiles for it (in this thread, or in another while this one waits for
    numba's compiler), and when it ends how long it took; nothing while the block's time is
    not numba's compiling (a slow call, or kernels loaded from the cache).

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
    _listen_to_numba()
    use = _use()
    compiles, anywhere, seconds = use.compiles, _compiles_begun[0], use.seconds
    said = threading.Event()
    timer: list[threading.Timer] = []

    def compiled() -> bool:
        waited = use.depth > 0 or use.seconds > seconds  # for numba's compiler
        return use.compiles > compiles or (waited and _compiles_begun[0] > anywhere)

    def say(text: str) -> None:
        try:
            sys.stderr.write(f"fastsdf: {text}\n")
            sys.stderr.flush()
        except (AttributeError, ValueError, OSError):  # closed or missing stderr
            pass

    def speak() -> None:
        if not compiled():  # not (yet) numba compiling: look again soon
            timer[:] = [threading.Timer(0.25, speak)]
            timer[0].daemon = True
            timer[0].start()
            return
        said.set()
        say(f"compiling {what} (once; later runs load it from the cache)...")

    timer.append(threading.Timer(after, speak))
    timer[0].daemon = True
    start = time.perf_counter()
    _depth.value = 1
    timer[0].start()
    try:
        yield
    finally:
        timer[0].cancel()
        _depth.value = 0
        elapsed = time.perf_counter() - start
        if not said.is_set() and elapsed > after and compiled():
            speak()  # (quicker than the timer could tell)
        if said.is_set():
            say(f"...done in {elapsed:.1f} s")


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
    """:func:`compiling` (``what``, said after ``after`` seconds) while any of ``kernels``
    (numba dispatchers) has compiled nothing in this process yet (its first call compiles
    it, or loads it from numba's cache), else a no-op: a later call that merely takes long
    is not announced as compiling."""
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


def is_terminal(stream: IO[str]) -> bool:
    """Whether ``stream`` is a terminal (False for a closed or a stand-in stream)."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # closed or not a real stream
        return False


#: :class:`RunProgress` estimates the time left from the rate over this share of the work
#: done so far, the latest (the cost of a unit drifts as a run goes: grains settle).
PROGRESS_WINDOW = 0.5
#: ... and shows its first estimate once it has measured this many seconds of work (or its
#: ``after``, if less).
PROGRESS_MEASURE_S = 2.0
_MAX_SAMPLES = 512


class RunProgress:
    """The progress of a computation of ``total`` units (``unit``, e.g. ``'frames'``), done
    in pieces: call :meth:`update` with the units done so far after each piece.

    The time left is estimated from the work done, not from the time spent compiling: the
    seconds this thread spends in numba's compiler (compiling or loading kernels, which
    the first pieces of a run, or the first grain to reach a wall, may do) are left out of
    the rate, and the rate is that of the latest half of the work (:data:`PROGRESS_WINDOW`),
    as the cost of a unit drifts while a run goes (grains landing on a heap make frames
    slower, grains at rest faster: the estimate says when its latest quarter's rate differs
    from the quarter's before by over 30%). The first estimate is shown once
    :data:`PROGRESS_MEASURE_S` seconds of work are measured (or ``after``, if less), and only
    if the whole is estimated to take longer than ``after`` seconds (default
    :data:`PROGRESS_AFTER_S`). Then stderr (or ``stream``) shows ``what``, the units done,
    the time so far (and how much of it compiled) and the time left: a tqdm bar on a
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
        _listen_to_numba()
        self.total = float(total)
        self.what = what
        self.unit = unit
        self.after = PROGRESS_AFTER_S if after is None else float(after)
        self._stream = stream
        self._start = _clock()
        self._compiled_before = compile_seconds()
        # the work seconds and the units done after each piece that did some (the units
        # growing), thinned to at most _MAX_SAMPLES
        self._works: list[float] = [0.0]
        self._dones: list[float] = [0.0]
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

    def compiled(self) -> float:
        """Seconds of this computation spent in numba's compiler so far."""
        return compile_seconds() - self._compiled_before

    def _work(self, now: float) -> float:
        """Seconds of work so far: the time since the start less the compiling."""
        return max(now - self._start - self.compiled(), 0.0)

    def remaining(self, now: float | None = None) -> float:
        """Estimated seconds left at time ``now`` (default: the clock's now; inf before any
        unit is done): the units left at the rate of the latest :data:`PROGRESS_WINDOW` of
        the work, compiling left out."""
        now = _clock() if now is None else now
        left = max(self.total - self._done, 0.0)
        if not left:
            return 0.0
        if self._done <= 0:
            return float("inf")
        work = self._work(now)
        w0, d0 = self._sample_at(work * (1.0 - PROGRESS_WINDOW))
        if d0 >= self._done:  # (the whole window in the last piece)
            w0, d0 = self._works[-2], self._dones[-2]
        return (work - w0) / (self._done - d0) * left

    def _sample_at(self, work: float) -> tuple[float, float]:
        """The latest (work seconds, units done) measured at or before ``work``."""
        i = max(bisect.bisect_right(self._works, work) - 1, 0)
        return self._works[i], self._dones[i]

    def _trend(self) -> str:
        """`` (the frames are getting slower)`` where the latest quarter of the work did a unit
        in over 1.3 times the time of the quarter before (or faster), else ``''``."""
        work = self._works[-1]
        marks = [self._sample_at(work * share) for share in (0.5, 0.75)] + [(work, self._done)]
        (w0, d0), (w1, d1), (w2, d2) = marks
        if not d0 < d1 < d2:
            return ""
        ratio = ((w2 - w1) / (d2 - d1)) / ((w1 - w0) / (d1 - d0))
        if ratio > 1.3:
            return f" (the {self.unit} are getting slower)"
        if ratio < 1 / 1.3:
            return f" (the {self.unit} are getting faster)"
        return ""

    def update(self, done: float) -> None:
        """``done`` units are done (in all, not since the last call)."""
        if self._closed:
            return
        if self._outer is not None:
            self._outer.update(self._base + float(done))
            return
        now = _clock()
        done = min(float(done), self.total)
        if done > self._done:
            self._done = done
            self._works.append(self._work(now))
            self._dones.append(done)
            if len(self._works) > _MAX_SAMPLES:
                self._works = self._works[::2] + self._works[-1:]
                self._dones = self._dones[::2] + self._dones[-1:]
        elapsed = now - self._start
        left = self.remaining(now)
        if not self._shown:
            measured = self._work(now) >= min(self.after, PROGRESS_MEASURE_S)
            if _quiet() or not measured or self._done >= self.total:
                return  # (finished before measuring: nothing left to show)
            if not elapsed + left > self.after:
                return
            self._shown = True
            if is_terminal(self._out()):
                from tqdm import tqdm

                self._bar = tqdm(
                    total=self.total,
                    desc=f"fastsdf: {self.what}",
                    unit=f" {self.unit}",
                    file=self._out(),
                    dynamic_ncols=True,
                    leave=True,
                    bar_format="{l_bar}{bar}| {n:.1f}/{total:.0f}{unit} [{elapsed}{postfix}]",
                )
            else:
                self._line(elapsed, left)
                return
        if self._bar is not None:
            to_go = f"about {_duration(left)} left{self._trend()}" if left else ""
            self._bar.set_postfix_str(to_go, refresh=False)
            self._bar.update(self._done - self._bar.n)
        elif now - self._last_line >= PROGRESS_LINE_EVERY_S:
            self._line(elapsed, left)

    def _so_far(self, elapsed: float) -> str:
        """``12 of 600 frames in 5 s (3 s of it compiling)``."""
        compiled = self.compiled()
        text = f"{_amount(self._done)} of {_amount(self.total)} {self.unit} in {_duration(elapsed)}"
        if compiled >= 0.5:
            text += f" ({_duration(compiled)} of it compiling)"
        return text

    def _line(self, elapsed: float, left: float) -> None:
        self._last_line = _clock()
        self._write(
            f"fastsdf: {self.what}: {self._so_far(elapsed)}, about {_duration(left)} left"
            f"{self._trend()}\n"
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
            self._write(f"fastsdf: {self.what}: {self._so_far(_clock() - self._start)}\n")
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
