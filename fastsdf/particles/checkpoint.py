"""Save a particle simulation to a file and load it back, to continue bit for bit.

``save_simulation(sim, path)`` writes one ``.npz`` file (a zip archive NumPy reads):

- ``x``, ``v``, ``m``, ``r``, ``cr``, ``cf``: the particle state, as stored (float64 or
  float32), and ``t``, the clock: readable without fastsdf (``numpy.load(path)['x']``);
- ``meta``: a JSON description (format, fastsdf version, particle count, timestep, forces);
- ``simulation``: the rest of the simulation pickled: the world (its expression graph, a
  grid's samples), the parameters, the random generator given as ``seed``, the force
  generators. Compiled kernels are not stored: they are rebuilt (or loaded from the kernel
  cache) on loading.

:func:`load_simulation` gives back a simulation whose next steps are exactly (bit for bit) those
the saved one would have taken. The file is written to a temporary file beside ``path`` and
renamed over it, so ``path`` always holds a complete file (the old one until the new one is
complete).

A force generator must be picklable to be saved: :class:`fastsdf.particles.Gravity`,
:class:`~fastsdf.particles.Drag`, :class:`~fastsdf.particles.FieldForce`, numba ``@njit``
functions (numba pickles them by value) and module-level Python functions or class instances
are; a lambda or a function defined inside another function is not, and
:func:`save_simulation` raises a ``ValueError`` naming it.

Pickling: a :class:`fastsdf.particles.ParticleSimulation` also pickles as it is
(``pickle.dumps(sim)``, ``copy.deepcopy(sim)``, sending it to another process); the unpickled
copy continues bit for bit too, parameters of the world included. Loading a file, like
unpickling, runs code named in it: load only files you trust.
"""

from __future__ import annotations

import io
import json
import os
import pickle
import zipfile
from typing import Any

import numpy as np

from fastsdf.files import atomic_write

__all__ = ["save_simulation", "load_simulation", "FORMAT", "FORMAT_VERSION"]

#: The ``format`` entry of a saved simulation's ``meta``.
FORMAT = "fastsdf.simulation"
#: Bumped when the layout changes; files of a newer version are refused.
FORMAT_VERSION = 1
_FIELDS = ("x", "v", "m", "r", "cr", "cf")


def _force_name(gen: Any) -> str:
    name = getattr(gen, "__qualname__", None) or getattr(gen, "__name__", None)
    return name if isinstance(name, str) else repr(gen)


def _check_forces(sim: Any) -> list:
    """The force generators' names; a ``ValueError`` naming the first that cannot be pickled."""
    names = []
    for i, gen in enumerate(sim.force_generators):
        name = _force_name(gen)
        try:
            pickle.dumps(gen, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as exc:
            raise ValueError(
                f"force_generators[{i}] ({name}) cannot be saved: {exc}. Define it at module "
                f"level (a function or a class instance), or as a numba @njit force, or remove "
                f"it before saving and add it again after loading"
            ) from None
        names.append(name)
    return names


def _is_simulation(sim: Any) -> bool:
    return all(hasattr(sim, a) for a in ("p", "t", "dt", "force_generators", "__getstate__"))


def save_simulation(sim: Any, path: str | os.PathLike) -> str:
    """Write ``sim`` (a :class:`fastsdf.particles.ParticleSimulation`) to ``path`` (``.npz``).

    The state, clock, parameters, world, random generator and force generators are saved (see
    the module docs); :func:`load_simulation` continues from them bit for bit. Returns the
    absolute path. Raises ``ValueError`` naming a force generator that cannot be saved (e.g. a
    lambda), ``TypeError`` if ``sim`` is not a simulation, ``OSError`` if ``path`` cannot be
    written (an existing file there is then left as it was).
    """
    if not _is_simulation(sim):
        raise TypeError(f"sim must be a ParticleSimulation, got {type(sim).__name__}")
    forces = _check_forces(sim)
    state = sim.__getstate__()
    p = state.pop("p")
    # The world's parameter values travel as a plain dict, set again after loading (the
    # simulation rebuilds its parameter table from the world when its SDF is assigned).
    params = state.pop("params", None)
    state["_saved_params"] = dict(params) if params is not None else {}
    fields = tuple(p.keys()) if p is not None else ()
    if p is None:  # a member whose state travels in the pickled part only
        p = sim.p
        fields = tuple(p.keys())
    arrays: dict[str, Any] = {name: np.ascontiguousarray(p[name]) for name in fields}
    meta = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "fastsdf": _version(),
        "class": f"{type(sim).__module__}.{type(sim).__qualname__}",
        "n": int(len(arrays["r"])),
        "dtype": str(arrays["x"].dtype),
        "t": float(sim.t),
        "timestep": float(sim.dt),
        "forces": forces,
        "fields": list(fields),
    }
    blob = pickle.dumps((type(sim), state), protocol=pickle.HIGHEST_PROTOCOL)
    path = os.path.abspath(os.fspath(path))

    def write(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            np.savez(
                fh,
                **arrays,
                t=np.float64(sim.t),
                meta=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8),
                simulation=np.frombuffer(blob, dtype=np.uint8),
            )
            fh.flush()
            os.fsync(fh.fileno())

    atomic_write(path, write)
    return path


def _version() -> str:
    from fastsdf.version import __version__

    return str(__version__)


def load_simulation(path: str | os.PathLike) -> Any:
    """The simulation saved in ``path`` by :func:`save_simulation`, ready to continue.

    Its kernels are rebuilt (or loaded from the kernel cache). Raises ``ValueError`` if the file
    is not a saved simulation or was written by a newer format. Unpickles: load only files you
    trust.
    """
    path = os.fspath(path)
    try:
        with zipfile.ZipFile(path) as zf:
            names = set(zf.namelist())
            if "meta.npy" not in names or "simulation.npy" not in names:
                raise ValueError(f"{path!r} is not a saved fastsdf simulation (no meta)")
    except zipfile.BadZipFile:
        raise ValueError(f"{path!r} is not a saved fastsdf simulation (not an .npz file)") from None
    with np.load(path, allow_pickle=False) as data:
        meta = json.loads(bytes(data["meta"]).decode())
        if meta.get("format") != FORMAT:
            raise ValueError(
                f"{path!r} is not a saved fastsdf simulation (format {meta.get('format')!r})"
            )
        if int(meta.get("version", 0)) > FORMAT_VERSION:
            raise ValueError(
                f"{path!r} was written in format version {meta['version']}; "
                f"this fastsdf reads up to {FORMAT_VERSION}: upgrade fastsdf"
            )
        fields = tuple(meta.get("fields", _FIELDS))
        arrays = {name: np.array(data[name]) for name in fields}
        cls, state = pickle.load(io.BytesIO(bytes(data["simulation"])))
    from fastsdf.particles.state import Particles

    if fields == Particles.FIELDS:
        p = Particles(len(arrays["r"]), arrays["x"].dtype)
        for name, arr in arrays.items():
            p[name] = arr
        state["p"] = p
    else:  # grains: the engine in the pickled part holds the state
        state["p"] = arrays
    params = state.pop("_saved_params", {})
    sim = cls.__new__(cls)
    sim.__setstate__(state)
    if params:
        sim.params.update(params)
    return sim
