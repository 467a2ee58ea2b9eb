"""On-disk cache of generated kernel modules, and the integrity of numba's cache files.

numba cannot cache functions created with ``exec`` (numba issue #3501), so each generated module
is written to a real ``.py`` file whose name is the SHA-256 of its content, and run from there;
numba's own ``cache=True`` then stores the machine code beside it (``__pycache__/*.nbi`` index
and ``*.nbc`` data files).

Every file in the cache can be damaged (a full disk, a killed process, a user's ``cp``), and none
may ever crash a user's process or silently load the wrong code:

* The generated ``.py`` is compared with the expected source on every load. A damaged one is
  replaced atomically (write a temporary file, ``os.replace``) and reported once; the module is
  always executed from the verified in-memory source (no ``.pyc`` is written or read).
* numba's index and data files for fastsdf's functions are written sealed: a magic line and the
  SHA-256 of the content precede numba's pickle. A file that is truncated, altered, unreadable or
  from another format fails the check; it is then removed, the function is compiled afresh and
  stored again (numba writes through a temporary file and ``os.replace``, so concurrent
  processes see either the old or the new complete file), and the repair is reported once with a
  ``RuntimeWarning`` naming the file. Any other failure while loading or saving a cache entry
  falls back to compiling, with a warning; it never propagates.

The directory is ``$FASTSDF_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/fastsdf``, else
``~/.cache/fastsdf``.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import pickle
import sys
import tempfile
import threading
import types
import warnings
from collections.abc import Iterable
from pathlib import Path
from typing import Any

__all__ = [
    "cache_dir",
    "source_key",
    "hashed_import",
    "load_module",
    "guard_module",
    "guard_dispatcher",
]

_MODULES: dict = {}
_LOCK = threading.Lock()
_REPORTED: set = set()

# Sealed numba cache files: this line, then the SHA-256 of the payload, then the payload.
_MAGIC = b"fastsdf sealed numba cache v1\n"
_DIGEST = 32


class _Corrupt(Exception):
    """A cache file failed its integrity check."""


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


_FILE_DIGESTS: dict = {}


def hashed_import(module: str, names: Iterable[str] = (), alias: str | None = None) -> str:
    """The line ``from module import names`` (or ``import module as alias``) followed by a hash
    of that module's source.

    numba's cache does not notice changes in a callee's module: a generated module that calls
    into ``module`` carries its hash, so a changed callee changes the generated source, hence
    its cache key."""
    digest = _FILE_DIGESTS.get(module)
    if digest is None:
        spec = importlib.util.find_spec(module)
        if spec is None or spec.origin is None:
            raise ImportError(f"no source file for module {module!r}")
        with open(spec.origin, "rb") as fh:
            digest = hashlib.sha256(fh.read()).hexdigest()[:16]
        _FILE_DIGESTS[module] = digest
    head = f"import {module} as {alias}" if alias else f"from {module} import {', '.join(names)}"
    return f"{head}  # sha256 {digest}"


def _report(path: object, what: str) -> None:
    """Warn once per process and file."""
    key = (str(path), what)
    with _LOCK:
        if key in _REPORTED:
            return
        _REPORTED.add(key)
    warnings.warn(f"fastsdf: kernel cache: {what} ({path})", RuntimeWarning, stacklevel=3)


def _write_atomic(path: Path, data: bytes, replace: bool) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same directory. With
    ``replace`` an existing file is replaced atomically; without, an existing file is kept
    (create-if-absent, so concurrent writers of the same content never clobber a reader)."""
    fd, name = tempfile.mkstemp(prefix=".tmp_", suffix=path.suffix, dir=path.parent)
    tmp: str | None = name
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        if replace:
            os.replace(name, path)
            tmp = None
            return
        try:
            os.link(name, path)  # atomic create-if-absent
        except FileExistsError:
            pass
        except OSError:  # file systems without hard links
            if not path.exists():
                os.replace(name, path)
                tmp = None
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)


def _read(path: Path) -> bytes | None:
    try:
        with open(path, "rb") as fh:
            return fh.read()
    except FileNotFoundError:
        return None


def load_module(source: str, prefix: str = "fastsdf_kernel") -> types.ModuleType:
    """Import the module with this source, writing it to the cache directory if needed.

    Returns the module; repeated calls in one process return the same module object. A cached
    file that does not hold exactly ``source`` is replaced (atomically) and reported once.
    """
    key = source_key(source)
    mod = _MODULES.get(key)
    if mod is not None:
        return mod
    name = f"{prefix}_{key}"
    directory = cache_dir()
    path = directory / f"{name}.py"
    data = source.encode("utf-8")
    try:
        directory.mkdir(parents=True, exist_ok=True)
        found = _read(path)
        if found is None:
            _write_atomic(path, data, replace=False)
            found = _read(path)
        if found != data:
            _write_atomic(path, data, replace=True)
            _report(path, "generated module did not hold its source; replaced")
            if _read(path) != data:
                raise OSError(f"cached file {path} does not hold the expected source")
    except OSError as exc:
        # No usable cache directory: compile from a private temporary file instead.
        warnings.warn(
            f"fastsdf: kernel cache unavailable ({exc}); compiling without the disk "
            f"cache. Set FASTSDF_CACHE_DIR to a writable directory.",
            RuntimeWarning,
            stacklevel=3,
        )
        directory = Path(tempfile.mkdtemp(prefix="fastsdf_"))
        path = directory / f"{name}.py"
        path.write_bytes(data)
    mod = types.ModuleType(name)
    mod.__file__ = str(path)
    sys.modules[name] = mod
    try:
        # Run the verified source, not whatever the file holds now; no .pyc is involved.
        exec(compile(source, str(path), "exec"), mod.__dict__)
    except BaseException:
        sys.modules.pop(name, None)
        raise
    guard_module(mod)
    _MODULES[key] = mod
    return mod


# ---------------------------------------------------------------------------------------------
# numba's cache files: sealed, checked, repaired.


#: The fastsdf modules that guard their own dispatchers when imported (so every process that
#: uses them reads and writes their cache files sealed).
_SELF_GUARDED: set = set()


def guard_module(module: types.ModuleType) -> None:
    """Seal and check the numba cache files of the cached dispatchers of ``module``: its own,
    and those it imports from fastsdf modules that guard themselves (a library module calls
    this on itself at import). Any other function it imports (a user's fused force, a field's
    sampler) is left alone: sealing its cache files would make numba fail to read them
    wherever it runs without the guard."""
    if not module.__name__.startswith("fastsdf_"):  # a library module guarding itself
        _SELF_GUARDED.add(module.__name__)
    for value in list(vars(module).values()):
        owner = getattr(getattr(value, "py_func", None), "__module__", None) or ""
        if owner == module.__name__ or owner in _SELF_GUARDED:
            guard_dispatcher(value)


def guard_dispatcher(dispatcher: object) -> None:
    """Make the disk cache of one numba dispatcher (``@njit(cache=True)``) safe: sealed files,
    and a damaged entry is removed, recompiled, stored again and reported once instead of
    raising. Anything that is not a cached dispatcher is left alone."""
    cache: Any = getattr(dispatcher, "_cache", None)  # numba's internals: untyped
    files = getattr(cache, "_cache_file", None)
    if files is None or getattr(cache, "_fastsdf_guarded", False):
        return
    try:
        index_path = files._index_path
        load, save = cache.load_overload, cache.save_overload
    except AttributeError:  # a numba whose cache internals differ: leave it as it is
        return
    files._load_index = types.MethodType(_load_index, files)
    files._save_index = types.MethodType(_save_index, files)
    files._load_data = types.MethodType(_load_data, files)
    files._save_data = types.MethodType(_save_data, files)

    def load_overload(sig: object, target_context: object) -> object:
        try:
            return load(sig, target_context)
        except Exception as exc:  # a cache must never break a computation
            _discard(files, index_path, exc)
            return None

    def save_overload(sig: object, data: object) -> None:
        try:
            save(sig, data)
        except Exception as exc:
            _discard(files, index_path, exc)
            try:
                save(sig, data)  # the damaged entry is gone: store a fresh one
            except Exception as again:
                _report(
                    index_path,
                    f"could not store a compiled kernel ({again!r}); it will "
                    f"be compiled again in the next process",
                )

    cache.load_overload = load_overload
    cache.save_overload = save_overload
    cache._fastsdf_guarded = True


def _discard(files: object, index_path: str, exc: BaseException) -> None:
    """Remove a function's damaged index and data files (they are rewritten on save)."""
    directory = os.path.dirname(index_path)
    base = os.path.basename(index_path)[: -len(".nbi")]
    removed = []
    try:
        names = os.listdir(directory)
    except OSError:
        names = []
    for n in names:
        if n == base + ".nbi" or (n.startswith(base + ".") and n.endswith(".nbc")):
            try:
                os.unlink(os.path.join(directory, n))
                removed.append(n)
            except FileNotFoundError:
                pass
            except OSError:
                pass
    reason = str(exc) if isinstance(exc, _Corrupt) else repr(exc)
    _report(
        index_path,
        f"damaged entry ({reason}); removed {len(removed)} file(s), "
        f"compiling afresh and storing a new copy",
    )


def _seal(payload: bytes) -> bytes:
    return _MAGIC + hashlib.sha256(payload).digest() + payload


def _unseal(raw: bytes, path: str) -> bytes:
    head = len(_MAGIC)
    if not raw.startswith(_MAGIC) or len(raw) < head + _DIGEST:
        raise _Corrupt(f"{os.path.basename(path)} is not a sealed fastsdf cache file")
    payload = raw[head + _DIGEST :]
    if hashlib.sha256(payload).digest() != raw[head : head + _DIGEST]:
        raise _Corrupt(f"{os.path.basename(path)} fails its checksum (truncated or altered)")
    return payload


def _load_index(self: Any) -> dict:
    # numba's format is pickle(version) + pickle((stamp, overloads)); sealed here as one pickle.
    raw = _read(Path(self._index_path))
    if raw is None:
        return {}
    if raw[:1] == b"\x80" and not raw.startswith(_MAGIC):
        return {}  # numba's own unsealed format (written without this guard): stale, replaced
    version, stamp, overloads = pickle.loads(_unseal(raw, self._index_path))
    if version != self._version or stamp != self._source_stamp:
        return {}  # another numba, or an older source: stale, overwritten on save
    return overloads


def _save_index(self: Any, overloads: dict) -> None:
    payload = self._dump((self._version, self._source_stamp, overloads))
    with self._open_for_write(self._index_path) as fh:
        fh.write(_seal(payload))


def _load_data(self: Any, name: str) -> object:
    path = self._data_path(name)
    with open(path, "rb") as fh:  # a missing file is an OSError, which numba treats as a miss
        raw = fh.read()
    return pickle.loads(_unseal(raw, path))


def _save_data(self: Any, name: str, data: object) -> None:
    with self._open_for_write(self._data_path(name)) as fh:
        fh.write(_seal(self._dump(data)))
