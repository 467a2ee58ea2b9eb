"""On-disk cache of generated kernel modules.

numba cannot cache functions created with ``exec`` (numba issue #3501), so each generated module
is written to a real ``.py`` file whose name is the SHA-256 of its content, and imported from
there; numba's own ``cache=True`` then stores the machine code beside it. A file is created once,
atomically, and never rewritten (its timestamp is part of numba's cache key), so concurrent
processes either create it or find it complete. The content is checked on every load, so a
kernel is never taken from a file that holds another scene.

The directory is ``$FASTSDF_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/fastsdf``, else
``~/.cache/fastsdf``.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
import tempfile
import warnings
from pathlib import Path

_MODULES: dict = {}


def cache_dir() -> Path:
    """The directory that holds generated kernel modules and numba's cache files for them."""
    env = os.environ.get("FASTSDF_CACHE_DIR")
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "fastsdf"


def source_key(source: str) -> str:
    """Content hash naming a generated module."""
    return hashlib.sha256(source.encode("utf-8")).hexdigest()[:40]


def _write_once(path: Path, source: str) -> None:
    """Create ``path`` with ``source`` unless it exists; never rewrite an existing file."""
    fd, tmp = tempfile.mkstemp(prefix=".tmp_", suffix=".py", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(source)
        try:
            os.link(tmp, path)  # atomic create-if-absent
        except FileExistsError:
            pass
        except OSError:  # file systems without hard links
            if not path.exists():
                os.replace(tmp, path)
                tmp = None
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)


def load_module(source: str, prefix: str = "fastsdf_kernel"):
    """Import the module with this source, writing it to the cache directory if needed.

    Returns the module; repeated calls in one process return the same module object.
    """
    key = source_key(source)
    mod = _MODULES.get(key)
    if mod is not None:
        return mod
    name = f"{prefix}_{key}"
    directory = cache_dir()
    path = directory / f"{name}.py"
    try:
        directory.mkdir(parents=True, exist_ok=True)
        if not path.exists():
            _write_once(path, source)
        if path.read_text(encoding="utf-8") != source:
            raise OSError(f"cached file {path} does not hold the expected source")
    except OSError as exc:
        # No usable cache directory: compile from a private temporary file instead.
        warnings.warn(f"fastsdf: kernel cache unavailable ({exc}); compiling without the disk "
                      f"cache. Set FASTSDF_CACHE_DIR to a writable directory.", RuntimeWarning,
                      stacklevel=3)
        directory = Path(tempfile.mkdtemp(prefix="fastsdf_"))
        path = directory / f"{name}.py"
        path.write_text(source, encoding="utf-8")
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    _MODULES[key] = mod
    return mod
