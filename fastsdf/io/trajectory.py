"""Trajectories in a standard file: particle fields every k steps, in HDF5 with the H5MD layout.

H5MD (https://www.nongnu.org/h5md/) is the layout LAMMPS (``dump h5md``) and GROMACS write and
pyh5md, MDAnalysis and others read. A file written by :class:`TrajectoryRecorder` holds::

    /h5md                       attrs version = [1, 1]
    /h5md/author                attrs name (and email)
    /h5md/creator               attrs name = "fastsdf", version
    /particles/<group>/box      attrs dimension = 2, boundary = ["none", "none"]
    /particles/<group>/<field>/value   [frames, N, 2] or [frames, N]  (chunked per frame)
    /particles/<group>/<field>/step    [frames] int64   (one dataset, hard-linked into every
    /particles/<group>/<field>/time    [frames] float64  field's group)

Fields: ``position`` (``sim.p['x']``), ``velocity`` (``p['v']``), ``mass`` (``p['m']``) and
``radius`` (``p['r']``, not one of H5MD's named elements but stored the same way).

Nothing lost: the file is written in HDF5's single-writer/multiple-reader (SWMR) mode and flushed
after every frame, so it is consistent on disk at every flush: if the writing process dies (a
crash, ``kill -9``), the file still opens and holds every frame flushed before. Such a file
keeps HDF5's "open for writing" mark: :func:`read_trajectory` opens it anyway (in SWMR read
mode), as does ``h5py.File(path, 'r', swmr=True)`` or ``pyh5md.File(path, 'r', swmr=True)``; a
file closed normally opens in every reader. A file cut off this way may hold the value of one
frame beyond its last ``step`` entry; readers take the frames that have a step.

h5py is an optional dependency: ``pip install 'fastsdf[io]'``.
"""

from __future__ import annotations

import getpass
import numbers
import os
from typing import Any

import numpy as np

from fastsdf.expr.validate import shown

__all__ = ["TrajectoryRecorder", "read_trajectory", "FIELDS"]

#: Recordable fields: H5MD element name -> the simulation's particle field.
FIELDS = {"position": "x", "velocity": "v", "mass": "m", "radius": "r"}
# Particles per chunk along N (a chunk of one frame: 4 MiB of float64 positions; smaller chunks
# cost more per byte in SWMR mode).
_CHUNK_PARTICLES = 1 << 18


def _h5py() -> Any:
    try:
        import h5py
    except ImportError:
        raise ImportError("trajectory files need h5py: pip install 'fastsdf[io]'") from None
    return h5py


def _particles(sim: Any) -> Any:
    """The particle fields of ``sim``: ``sim.p``, or for a simulation sharded over Dask workers
    (:class:`fastsdf.apps.distributed.DistributedSimulation`, which has no ``p``) ``sim.gather()``:
    the client collects the shards in order and writes one file."""
    p = getattr(sim, "p", None)
    return p if p is not None else sim.gather()


def _step_of(sim: Any) -> int:
    dt = float(sim.dt)
    return int(round(float(sim.t) / dt)) if dt > 0 else 0


class TrajectoryRecorder:
    """Write chosen particle fields of a simulation to ``path`` (HDF5, H5MD layout).

    ``every``: steps between frames in :meth:`run`. ``fields``: names from :data:`FIELDS`.
    ``group``: the H5MD particles group (``/particles/<group>``). ``dtype``: stored float type
    (default: the simulation's, bit for bit; ``'float32'`` halves the file). ``compression``:
    an h5py filter (``'gzip'``, ``'lzf'``) or ``None`` (the default: positions are floats with
    little redundancy, and compressing them costs far more than writing them). ``author``:
    the ``/h5md/author`` name (default: the login name).

    Use it as a context manager::

        with TrajectoryRecorder("run.h5", every=10, fields=("position", "velocity")) as rec:
            rec.run(sim, 1000)      # sim.run in blocks of 10 steps, a frame before and after each
        traj = read_trajectory("run.h5")          # {'position': [frames, N, 2], 'step', 'time'}

    or call :meth:`record` yourself whenever a frame should be written. The step of a frame is
    ``round(sim.t / sim.dt)``, its time ``sim.t``. A simulation sharded over Dask workers
    (:class:`fastsdf.apps.distributed.DistributedSimulation`) is recorded into one file by the
    client, which gathers the shards at each frame (``sim.gather()``: all particles travel to
    the client once per frame). Every frame is flushed to disk before
    :meth:`record` returns. An existing file at ``path`` is replaced when the first frame is
    written.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        every: int = 10,
        fields: tuple | list = ("position",),
        group: str = "all",
        *,
        dtype: Any = None,
        compression: str | None = None,
        author: str | None = None,
    ) -> None:
        if (
            isinstance(every, (bool, np.bool_))
            or not isinstance(every, numbers.Integral)
            or every < 1
        ):
            raise ValueError(f"every must be an integer >= 1, got every={shown(every)}")
        if isinstance(fields, str):
            fields = (fields,)
        fields = tuple(fields)
        bad = [f for f in fields if f not in FIELDS]
        if bad or not fields:
            raise ValueError(
                f"fields must be a non-empty selection of {tuple(FIELDS)}, got "
                f"fields={shown(fields)}"
            )
        if len(set(fields)) != len(fields):
            raise ValueError(f"fields must not repeat a name, got fields={shown(fields)}")
        if not isinstance(group, str) or not group or "/" in group:
            raise ValueError(
                f"group must be a non-empty name without '/', got group={shown(group)}"
            )
        if dtype is not None:
            dtype = np.dtype(dtype)
            if dtype.kind != "f":
                raise ValueError(f"dtype must be a float type, got dtype={dtype}")
        self.path: str = os.path.abspath(os.fspath(path))
        self.every: int = int(every)
        self.fields: tuple = fields
        self.group: str = group
        self.dtype: Any = dtype
        self.compression: str | None = compression
        self.author: str = author if author is not None else _login()
        self.frames: int = 0
        self._h5py: Any = _h5py()
        self._file: Any = None
        self._values: dict = {}
        self._step: Any = None
        self._time: Any = None
        self._last_step: int | None = None

    # -- file layout -------------------------------------------------------------------------
    def _create(self, sim: Any) -> None:
        from fastsdf.version import __version__

        h5py = self._h5py
        f = h5py.File(self.path, "w", libver="latest")
        try:
            h5md = f.create_group("h5md")
            h5md.attrs["version"] = np.array([1, 1])
            f.create_group("h5md/author").attrs["name"] = self.author
            creator = f.create_group("h5md/creator")
            creator.attrs["name"] = "fastsdf"
            creator.attrs["version"] = str(__version__)
            particles = f.create_group(f"particles/{self.group}")
            box = particles.create_group("box")
            box.attrs["dimension"] = 2
            box.attrs["boundary"] = np.array([b"none", b"none"])
            p = _particles(sim)
            for k, name in enumerate(self.fields):
                arr = np.asarray(p[FIELDS[name]])
                dtype = self.dtype if self.dtype is not None else arr.dtype
                n = arr.shape[0]
                tail = arr.shape[1:]
                chunk = (1, max(1, min(n, _CHUNK_PARTICLES))) + tail
                g = particles.create_group(name)
                self._values[name] = g.create_dataset(
                    "value",
                    shape=(0, n) + tail,
                    maxshape=(None, n) + tail,
                    dtype=dtype,
                    chunks=chunk,
                    compression=self.compression,
                )
                if k == 0:
                    self._step = g.create_dataset(
                        "step", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(4096,)
                    )
                    self._time = g.create_dataset(
                        "time", shape=(0,), maxshape=(None,), dtype=np.float64, chunks=(4096,)
                    )
                else:  # H5MD: step and time may be hard links to those of another element
                    g["step"] = self._step
                    g["time"] = self._time
            f.flush()
            f.swmr_mode = True  # from here on the file is consistent at every flush
        except BaseException:
            f.close()
            raise
        self._file = f

    # -- frames ------------------------------------------------------------------------------
    def record(self, sim: Any) -> None:
        """Write one frame of ``sim``'s chosen fields at its current step and time, and flush.

        The values go first and the step last, so a reader never finds a step without its
        values. Raises ``ValueError`` if the particle count changed since the first frame.
        """
        if self._file is None:
            if self.frames:
                raise RuntimeError(f"this recorder is closed; {self.path} was finished")
            self._create(sim)
        k = self.frames
        p = _particles(sim)
        for name, ds in self._values.items():
            arr = np.asarray(p[FIELDS[name]])
            if arr.shape != ds.shape[1:]:
                raise ValueError(
                    f"p[{shown(FIELDS[name])}] has shape {arr.shape}; this trajectory "
                    f"holds {ds.shape[1:]} per frame"
                )
            ds.resize(k + 1, axis=0)
            ds[k] = arr
        step = _step_of(sim)
        self._time.resize(k + 1, axis=0)
        self._time[k] = float(sim.t)
        self._step.resize(k + 1, axis=0)
        self._step[k] = step
        self._file.flush()
        self.frames = k + 1
        self._last_step = step

    def run(self, sim: Any, steps: int) -> None:
        """Advance ``sim`` by ``steps`` steps with ``sim.run`` in blocks of at most ``every``
        steps, recording the state before the first block (unless that step is already the
        last frame) and after every block that ends on a multiple of ``every`` or at the end."""
        if (
            isinstance(steps, (bool, np.bool_))
            or not isinstance(steps, numbers.Integral)
            or steps < 0
        ):
            raise ValueError(f"steps must be an integer >= 0, got steps={shown(steps)}")
        if self._last_step != _step_of(sim):
            self.record(sim)
        left = int(steps)
        while left > 0:
            step = _step_of(sim)
            k = min(left, self.every - step % self.every)
            sim.run(k)
            left -= k
            if _step_of(sim) % self.every == 0 or left == 0:
                self.record(sim)

    def close(self) -> str:
        """Close the file (it then opens in every HDF5 reader). Returns its path."""
        if self._file is not None:
            self._file.close()
            self._file = None
        return self.path

    def __enter__(self) -> TrajectoryRecorder:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _login() -> str:
    try:
        return getpass.getuser()
    except Exception:
        return "unknown"


def read_trajectory(
    path: str | os.PathLike, group: str = "all", fields: tuple | list | None = None
) -> dict:
    """The frames of the H5MD file at ``path`` as NumPy arrays: ``{'step': (F,), 'time':
    (F,), field: (F, N, ...) ...}`` for each time-dependent element of ``/particles/<group>``
    (or the ``fields`` named). Opens files left by a writer that died (SWMR read mode) and
    keeps only frames that have a step (see the module docs)."""
    h5py = _h5py()
    try:
        f = h5py.File(path, "r")
    except OSError:
        f = h5py.File(path, "r", swmr=True)  # a writer died with the file open for writing
    with f:
        if "h5md" not in f:
            raise ValueError(f"{shown(os.fspath(path))} is not an H5MD file (no /h5md group)")
        try:
            particles = f["particles"][group]
        except KeyError:
            raise ValueError(
                f"{shown(os.fspath(path))} has no particles group {shown(group)}"
            ) from None
        names = (
            [n for n in particles if n != "box" and "value" in particles[n]]
            if fields is None
            else list(fields)
        )
        out: dict = {}
        for name in names:
            g = particles[name]
            if "step" not in out:
                out["step"] = np.asarray(g["step"][()])
                out["time"] = np.asarray(g["time"][()])
            out[name] = np.asarray(g["value"][: len(out["step"])])
        frames = min((len(v) for v in out.values()), default=0)
        return {k: v[:frames] for k, v in out.items()}
