"""Progress bars (tqdm) for the demo, the examples and the benchmarks.

tqdm handles terminals, notebooks and redirection; a bar is drawn only when its stream is a
terminal, so ``make demo > log`` gets the results and no redraws.
"""

from __future__ import annotations

import sys
from typing import IO, Any

from tqdm.auto import tqdm

from fastsdf.notice import is_terminal

__all__ = ["Progress", "progress"]


def progress(total: int, label: str = "", stream: IO[str] | None = None, **kwargs: Any) -> tqdm:
    """A tqdm bar of ``total`` steps named ``label`` on ``stream`` (default stderr), off unless
    it is a terminal.

    Pass ``disable=False`` to force it on (e.g. in a notebook, where tqdm draws a widget).
    """
    stream = stream if stream is not None else sys.stderr
    kwargs.setdefault("disable", not is_terminal(stream))
    return tqdm(
        total=max(1, int(total)), desc=label, file=stream, dynamic_ncols=True, leave=True, **kwargs
    )


class Progress:
    """``with Progress(total, 'label') as bar: ... bar.step(note)``: a tqdm bar on ``stream``
    (see :func:`progress`); ``note`` is shown after the counts."""

    def __init__(self, total: int, label: str = "", stream: IO[str] | None = None):
        self._bar = progress(total, label, stream)

    def __enter__(self) -> Progress:
        return self

    def step(self, note: str = "", count: int = 1) -> None:
        """Advance by ``count`` and show ``note`` beside the bar."""
        if note:
            self._bar.set_postfix_str(note[:40], refresh=False)
        self._bar.update(count)

    def clear(self) -> None:
        """Erase the bar from its line (the next step draws it again), so that a line printed
        in between stands on its own."""
        self._bar.clear()

    def close(self) -> None:
        """Finish the bar (leaving it on screen)."""
        self._bar.close()

    def __exit__(self, *exc: object) -> None:
        self.close()
