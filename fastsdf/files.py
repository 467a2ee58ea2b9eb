"""Files that are never seen half-written: each is written to a temporary file beside its
target and moved onto it in one step (``os.replace``), with the permissions a new file gets."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable

__all__ = ["atomic_write", "commit", "temporary_sibling"]


def _new_file_mode() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def temporary_sibling(path: str | os.PathLike) -> str:
    """Create an empty temporary file in ``path``'s folder (same file system, so the final move
    is atomic) and return its path; the suffix keeps ``path``'s extension for writers that read
    the format from it."""
    target = os.path.abspath(os.fspath(path))
    folder, name = os.path.split(target)
    stem, ext = os.path.splitext(name)
    fd, tmp = tempfile.mkstemp(prefix=f".{stem}.", suffix=f".partial{ext}", dir=folder)
    os.close(fd)
    return tmp


def commit(tmp: str, path: str | os.PathLike) -> None:
    """Move the finished temporary file ``tmp`` onto ``path`` in one step, with the permissions
    of a newly created file (``mkstemp`` makes it private to its owner)."""
    os.chmod(tmp, _new_file_mode())
    os.replace(tmp, os.fspath(path))


def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> None:
    """Call ``write(temporary path)``, then move the result onto ``path``; on any error the
    temporary file is removed and ``path`` is left as it was."""
    tmp = temporary_sibling(path)
    try:
        write(tmp)
        commit(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
