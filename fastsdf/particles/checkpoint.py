"""Save a particle simulation to a file and load it back, to continue bit for bit.

``save_simulation(sim, path)`` writes one ``.npz`` file (a zip archive NumPy reads), pure data:

- ``x``, ``v``, ``m``, ``r``, ``cr``, ``cf`` (grains: ``x``, ``v``, ``m``, ``r``, ``omega``):
  the particle state as stored (float64 or float32), and ``t``, the clock: readable without
  fastsdf (``numpy.load(path)['x']``);
- ``meta``: a JSON description (format, fastsdf version, class, particle count, timestep,
  forces);
- ``state``: JSON describing everything else, whose arrays are the file's ``array_<k>``
  entries: the world as its expression graph (one node list, see
  :mod:`fastsdf.expr.serial`) and, for a ``GridSDF`` or ``NarrowBandGridSDF``, its samples and
  numbers; the parameters' values; the random generator given as ``seed`` (its bit
  generator's state); the forces by name with their numbers (``Gravity``, ``Drag``,
  ``FieldForce``: see :data:`fastsdf.particles.forces.SAVED_FORCES`); for grains, the granular
  engine's arrays (state in its storage order, neighbour lists, the contacts' springs with
  ``history=True``), contact laws and counters. Compiled kernels are not stored: they are
  rebuilt (or loaded from the kernel cache) on loading.

Loading runs no code from the file: it reads with ``numpy.load(..., allow_pickle=False)`` and
JSON, builds only fastsdf's own classes (a fixed list) from numbers, strings and arrays, and
checks every node of an expression graph before it is built (kernels are generated from it).

What is not data is refused by :func:`save_simulation` with a ``ValueError`` naming it: a
force that is a numba ``@njit`` function or a Python generator ``(p, t)``, a world of your own
class. ``save_simulation(sim, path, allow_pickle=True)`` stores such objects pickled (each on
its own, the rest stays data); :func:`load_simulation` then refuses the file unless given
``allow_pickle=True`` too, because unpickling runs code named in the file: opt in only for
files you trust. Files of the first format (version 1, a pickle as a whole) are read the same
way: only with ``allow_pickle=True``.

:func:`load_simulation` gives back a simulation whose next steps are exactly (bit for bit) those
the saved one would have taken. The file is written to a temporary file beside ``path`` and
renamed over it, so ``path`` always holds a complete file (the old one until the new one is
complete).

Pickling: a :class:`fastsdf.particles.ParticleSimulation` also pickles as it is
(``pickle.dumps(sim)``, ``copy.deepcopy(sim)``, sending it to another process); the unpickled
copy continues bit for bit too. Unpickling runs code named in the pickle: unpickle only what
you trust.
"""

from __future__ import annotations

import importlib
import io
import json
import math
import os
import pickle
import struct
import zipfile
from typing import Any

import numpy as np

from fastsdf.expr.graph import Expr
from fastsdf.expr.serial import GraphWriter, graph_from_data
from fastsdf.files import atomic_write
from fastsdf.particles.world import SimulationParams

__all__ = ["save_simulation", "load_simulation", "FORMAT", "FORMAT_VERSION"]

#: The ``format`` entry of a saved simulation's ``meta``.
FORMAT = "fastsdf.simulation"
#: Bumped when the layout changes; files of a newer version are refused. Version 1 was a
#: pickle as a whole (read only with ``allow_pickle=True``).
FORMAT_VERSION = 2
_PICKLED_FORMAT = 1
_FIELDS = ("x", "v", "m", "r", "cr", "cf")

# Named tuples a checkpoint holds (contact laws, the granular engine's grains and cell grid, a
# shape's exactness record), found by module and name in these modules only.
_TUPLE_MODULES = (
    "fastsdf.shapes.exactness",
    "fastsdf.granular.params",
    "fastsdf.granular.kernels",
    "fastsdf.granular.cells",
)
_BIT_GENERATORS = ("PCG64", "PCG64DXSM", "MT19937", "Philox", "SFC64")
_OPT_IN = (
    "save(path, allow_pickle=True) stores it pickled, and load(path, allow_pickle=True) reads "
    "it back (unpickling runs code named in the file: only for files you trust)"
)


def _name(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


#: The simulation classes of the particle family, registered by their modules
#: (:func:`register_simulation`), which import this one.
_SIMULATIONS: list[type] = []


def register_simulation(cls: type) -> type:
    """Let checkpoints rebuild ``cls`` (a member of the particle family) from its state."""
    if cls not in _SIMULATIONS:
        _SIMULATIONS.append(cls)
    return cls


def _state_classes() -> dict[str, type]:
    """The classes a checkpoint rebuilds from their state (by ``__setstate__`` or their
    ``__dict__``): the simulations, the granular engine, the particle state, the worlds
    (fastsdf's Function and shapes, GridSDF, NarrowBandGridSDF)."""
    from fastsdf.fields.band import NarrowBandGridSDF
    from fastsdf.fields.grid import GridSDF
    from fastsdf.function import Function
    from fastsdf.granular.simulation import GranularSimulation
    from fastsdf.particles.state import Particles
    from fastsdf.shapes import SDF

    classes: list[type] = [
        *_SIMULATIONS,
        GranularSimulation,
        Particles,
        GridSDF,
        NarrowBandGridSDF,
        Function,
    ]
    stack: list[type] = [SDF]
    while stack:  # the shapes: SDF and its subclasses defined in fastsdf
        cls = stack.pop()
        if cls.__module__.startswith("fastsdf.") and cls not in classes:
            classes.append(cls)
            stack.extend(cls.__subclasses__())
    return {_name(c): c for c in classes}


def _forces() -> dict:
    from fastsdf.particles.forces import SAVED_FORCES

    return SAVED_FORCES


def _float_out(value: float) -> Any:
    return value if math.isfinite(value) else {"float": struct.pack("<d", value).hex()}


def _display(key: str) -> str:
    return {"_sdf": "sdf"}.get(key, key)


def _force_name(gen: Any) -> str:
    name = getattr(gen, "__qualname__", None) or getattr(gen, "__name__", None)
    return name if isinstance(name, str) else repr(gen)


class _Writer:
    """The state of a simulation as JSON-ready data and arrays (see the module docs): plain
    values as themselves, anything else as a tagged dict (``{"tuple": [...]}``, ``{"array":
    name}``, ``{"expr": node index}``, ``{"object": index}``, ...)."""

    def __init__(self, allow_pickle: bool, arrays: dict) -> None:
        self.allow_pickle = allow_pickle
        self.arrays = dict(arrays)  # name -> array, the state's fields under their names
        self._array_names = {id(a): name for name, a in arrays.items()}
        self.objects: list = []
        self._object_index: dict[int, int] = {}
        self._keep: list = []  # objects indexed by id() stay alive while written
        self.graph = GraphWriter()
        self.pickled: list[bytes] = []
        self.pickled_what: list[str] = []
        self.classes = _state_classes()
        self.forces = _forces()

    def _array(self, a: np.ndarray, where: str) -> dict:
        if a.dtype.hasobject:
            raise ValueError(f"{where} (an array of Python objects) cannot be saved as data")
        name = self._array_names.get(id(a))
        if name is None:
            name = self._array_names[id(a)] = f"array_{len(self.arrays)}"
            self.arrays[name] = a
            self._keep.append(a)
        return {"array": name}

    def _object(self, obj: Any, where: str, build: Any) -> dict:
        """``obj`` once in the object table (shared references stay shared)."""
        k = self._object_index.get(id(obj))
        if k is None:
            k = self._object_index[id(obj)] = len(self.objects)
            self.objects.append(None)  # its slot, filled below (a cycle refers to it)
            self._keep.append(obj)
            self.objects[k] = build()
        return {"object": k}

    def value(self, v: Any, where: str) -> Any:
        if v is None or isinstance(v, (bool, str)):
            return v
        if isinstance(v, np.generic):
            return {"scalar": self._array(np.asarray(v), where)["array"]}
        if isinstance(v, int):
            return v
        if isinstance(v, float):
            return _float_out(v)
        if isinstance(v, np.ndarray):
            return self._pickled(v, where) if v.dtype.hasobject else self._array(v, where)
        if isinstance(v, np.dtype):
            if v.hasobject:
                raise ValueError(f"{where} (dtype {v}) cannot be saved as data")
            return {"dtype": v.str}
        if isinstance(v, Expr):
            return {"expr": self.graph.add(v)}
        if type(v) is list:
            return [self.value(x, f"{where}[{i}]") for i, x in enumerate(v)]
        if type(v) in (dict, SimulationParams):  # (sim.params: its values; rebuilt on loading)
            return self._dict(v, where)
        if type(v) in (set, frozenset):
            items = sorted(v, key=repr)
            return {type(v).__name__: [self.value(x, f"{where} item") for x in items]}
        if type(v) is tuple:
            return {"tuple": [self.value(x, f"{where}[{i}]") for i, x in enumerate(v)]}
        cls = type(v)
        if isinstance(v, tuple) and hasattr(cls, "_fields") and cls.__module__ in _TUPLE_MODULES:
            return {
                "named": _name(cls),
                "fields": [self.value(x, f"{where}.{f}") for f, x in zip(cls._fields, v)],
            }
        force = next((n for n, (c, _) in self.forces.items() if cls is c), None)
        if force is not None:
            args = self.forces[force][1](v)
            return self._object(
                v, where, lambda: {"force": force, "args": self._dict(args, f"{where} ({force})")}
            )
        if isinstance(v, np.random.Generator):
            return self._object(
                v,
                where,
                lambda: {"generator": self.value(v.bit_generator, f"{where}.bit_generator")},
            )
        if cls.__name__ in _BIT_GENERATORS and cls is getattr(np.random, cls.__name__):
            return self._object(
                v,
                where,
                lambda: {"bit_generator": cls.__name__, "state": self.value(v.state, where)},
            )
        if cls is np.random.SeedSequence:
            fields = {
                "entropy": v.entropy,
                "spawn_key": list(v.spawn_key),
                "pool_size": v.pool_size,
                "n_children_spawned": v.n_children_spawned,
            }
            return self._object(v, where, lambda: {"seed_sequence": self._dict(fields, where)})
        if self.classes.get(_name(cls)) is cls:
            return self._object(v, where, lambda: self._instance(v, where))
        return self._pickled(v, where)

    def _dict(self, d: dict, where: str) -> dict:
        if all(type(k) is str for k in d):
            return {"dict": {k: self.value(x, f"{where}.{_display(k)}") for k, x in d.items()}}
        return {
            "items": [
                [self.value(k, f"{where} key"), self.value(x, f"{where}[{k!r}]")]
                for k, x in d.items()
            ]
        }

    def _instance(self, obj: Any, where: str) -> dict:
        state = obj.__getstate__()
        if not isinstance(state, dict):
            raise ValueError(f"{where} ({type(obj).__name__}) has no state to save as data")
        return {"class": _name(type(obj)), "state": self._dict(state, where)}

    def _pickled(self, obj: Any, where: str) -> dict:
        name = _force_name(obj)
        what = f"{where} ({name[:80]})"
        if not self.allow_pickle:
            raise ValueError(
                f"{what} cannot be saved as data: a checkpoint holds arrays, numbers and "
                f"fastsdf's own worlds (SDFs, Functions, GridSDF, NarrowBandGridSDF), forces "
                f"(Gravity, Drag, FieldForce) and contact laws, and this is a "
                f"{type(obj).__module__}.{type(obj).__qualname__}. Use those (a force field "
                f"of x and y as a FieldForce), or remove it before saving and add it again "
                f"after loading; or {_OPT_IN}"
            )
        try:
            blob = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as exc:
            raise ValueError(
                f"{what} cannot be saved, even pickled: {exc}. Define it at module level (a "
                f"function or a class instance), or as a numba @njit force, or remove it "
                f"before saving and add it again after loading"
            ) from None
        self.pickled.append(blob)
        self.pickled_what.append(what)
        return {"pickled": len(self.pickled) - 1}


def _is_simulation(sim: Any) -> bool:
    return all(hasattr(sim, a) for a in ("p", "t", "dt", "force_generators", "__getstate__"))


def save_simulation(sim: Any, path: str | os.PathLike, *, allow_pickle: bool = False) -> str:
    """Write ``sim`` (a :class:`fastsdf.particles.ParticleSimulation`) to ``path`` (``.npz``).

    The state, clock, parameters, world, random generator and forces (and, for grains, the
    granular engine with its contact springs) are saved as data (see the module docs);
    :func:`load_simulation` continues from them bit for bit, running no code from the file.
    Returns the absolute path.

    Raises ``ValueError`` naming what cannot be saved as data (a numba ``@njit`` force, a
    Python force generator, a world of a class of your own) and how to do without it; with
    ``allow_pickle=True`` such objects are stored pickled instead (then loading needs
    ``allow_pickle=True`` too), and only what cannot be pickled either (e.g. a lambda) is
    refused. ``TypeError`` if ``sim`` is not a simulation, ``OSError`` if ``path`` cannot be
    written. On any error an existing file at ``path`` is left as it was.
    """
    if not _is_simulation(sim):
        raise TypeError(f"sim must be a ParticleSimulation, got {type(sim).__name__}")
    p = sim.p
    fields = tuple(p.keys())
    # The state's fields under their own names (readable without fastsdf); a simulation whose
    # state object holds these very arrays refers to them, the others (grains, whose engine
    # keeps its own order) have them as a copy in the given order.
    arrays: dict[str, Any] = {name: p[name] for name in fields}
    for name, a in arrays.items():
        if not (isinstance(a, np.ndarray) and a.flags.c_contiguous):
            arrays[name] = np.ascontiguousarray(a)
    writer = _Writer(bool(allow_pickle), arrays)
    root = writer.value(sim, "sim")
    meta = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "fastsdf": _version(),
        "class": _name(type(sim)),
        "n": int(len(arrays["r"])),
        "dtype": str(arrays["x"].dtype),
        "t": float(sim.t),
        "timestep": float(sim.dt),
        "forces": [_force_name(g) for g in sim.force_generators],
        "fields": list(fields),
        "pickled": writer.pickled_what,
    }
    state = {"root": root, "objects": writer.objects, "graph": writer.graph.nodes}
    path = os.path.abspath(os.fspath(path))

    def text(obj: Any) -> np.ndarray:
        return np.frombuffer(json.dumps(obj).encode(), dtype=np.uint8)

    entries = dict(writer.arrays)
    entries.update(
        {f"pickled_{k}": np.frombuffer(b, np.uint8) for k, b in enumerate(writer.pickled)}
    )

    def write(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            np.savez(fh, **entries, t=np.float64(sim.t), meta=text(meta), state=text(state))
            fh.flush()
            os.fsync(fh.fileno())

    atomic_write(path, write)
    return path


def _version() -> str:
    from fastsdf.version import __version__

    return str(__version__)


class _Reader:
    """Rebuilds what :class:`_Writer` wrote; see its tags."""

    def __init__(self, data: Any, state: dict, allow_pickle: bool, path: str) -> None:
        self.data = data
        self.allow_pickle = allow_pickle
        self.path = path
        self.objects_data = state["objects"]
        if not isinstance(self.objects_data, list):
            raise ValueError("objects is not a list")
        self.objects: dict[int, Any] = {}
        self.arrays: dict[str, np.ndarray] = {}
        self.nodes = graph_from_data(state["graph"])
        self.classes = _state_classes()
        self.forces = _forces()

    def _array(self, name: Any) -> np.ndarray:
        if not isinstance(name, str) or name in ("meta", "state") or name.startswith("pickled_"):
            raise ValueError(f"{name!r} is not an array of the state")
        a = self.arrays.get(name)
        if a is None:
            try:  # (read with allow_pickle=False: an array of Python objects is refused)
                a = self.arrays[name] = np.array(self.data[name])
            except ValueError as exc:
                raise ValueError(f"array {name!r} cannot be read as data: {exc}") from None
        return a

    def value(self, v: Any) -> Any:
        if v is None or isinstance(v, (bool, str, int, float)):
            return v
        if isinstance(v, list):
            return [self.value(x) for x in v]
        if not (isinstance(v, dict) and len(v) in (1, 2)):
            raise ValueError(f"unexpected entry {v!r:.100}")
        tag = next(iter(v))
        body = v[tag]
        if tag == "dict":
            return {str(k): self.value(x) for k, x in body.items()}
        if tag == "items":
            return {self.value(k): self.value(x) for k, x in body}
        if tag == "tuple":
            return tuple(self.value(x) for x in body)
        if tag in ("set", "frozenset"):
            return (set if tag == "set" else frozenset)(self.value(x) for x in body)
        if tag == "float":
            return struct.unpack("<d", bytes.fromhex(body))[0]
        if tag == "array":
            return self._array(body)
        if tag == "scalar":
            a = self._array(body)
            if a.shape != ():
                raise ValueError(f"scalar {body!r} is not 0-dimensional")
            return a[()]
        if tag == "dtype":
            dt = np.dtype(str(body))
            if dt.hasobject:
                raise ValueError(f"dtype {body!r} holds Python objects")
            return dt
        if tag == "expr":
            if isinstance(body, bool) or not isinstance(body, int):
                raise ValueError(f"expression {body!r} is not a node index")
            return self.nodes[body]
        if tag == "named":
            return self._named(body, v["fields"])
        if tag == "object":
            return self._object(body)
        if tag == "pickled":
            return self._unpickle(body)
        raise ValueError(f"unknown entry {tag!r}")

    def _named(self, name: Any, fields: Any) -> tuple:
        module, _, qualname = str(name).rpartition(".")
        if module not in _TUPLE_MODULES:
            raise ValueError(f"{name!r} is not a type a checkpoint holds")
        cls = getattr(importlib.import_module(module), qualname, None)
        if not (isinstance(cls, type) and issubclass(cls, tuple) and hasattr(cls, "_fields")):
            raise ValueError(f"{name!r} is not a type a checkpoint holds")
        return cls(*(self.value(x) for x in fields))

    def _object(self, k: Any) -> Any:
        if isinstance(k, bool) or not isinstance(k, int) or not 0 <= k < len(self.objects_data):
            raise ValueError(f"object {k!r} is not in the file")
        if k in self.objects:
            return self.objects[k]
        entry = self.objects_data[k]
        if not isinstance(entry, dict):
            raise ValueError(f"object {k} is not described")
        if "force" in entry:
            cls, _ = self.forces[entry["force"]]
            obj = cls(**self.value(entry["args"]))
        elif "generator" in entry:
            obj = np.random.Generator(self.value(entry["generator"]))
        elif "bit_generator" in entry:
            name = entry["bit_generator"]
            if name not in _BIT_GENERATORS:
                raise ValueError(f"{name!r} is not a bit generator of numpy")
            obj = getattr(np.random, name)()
            obj.state = self.value(entry["state"])
        elif "seed_sequence" in entry:
            f = self.value(entry["seed_sequence"])
            obj = np.random.SeedSequence(
                f["entropy"],
                spawn_key=tuple(f["spawn_key"]),
                pool_size=f["pool_size"],
                n_children_spawned=f["n_children_spawned"],
            )
        elif "class" in entry:
            known: Any = self.classes.get(entry["class"])
            if known is None:
                raise ValueError(f"{entry['class']!r} is not a class a checkpoint holds")
            obj = known.__new__(known)
            self.objects[k] = obj  # (before its state: a reference back finds it)
            state = self.value(entry["state"])
            setstate = getattr(obj, "__setstate__", None)
            if setstate is not None:
                setstate(state)
            else:
                obj.__dict__.update(state)
        else:
            raise ValueError(f"object {k} is of no known kind")
        self.objects[k] = obj
        return obj

    def _unpickle(self, k: Any) -> Any:
        if not self.allow_pickle:
            raise ValueError(_pickle_refusal(self.path, "holds pickled objects"))
        return pickle.loads(bytes(self.data[f"pickled_{int(k)}"]))


def _pickle_refusal(path: str, what: str) -> str:
    return (
        f"{path!r} {what}; unpickling runs code named in the file, so it is not loaded: "
        f"pass allow_pickle=True (load_simulation(path, allow_pickle=True) or "
        f"ParticleSimulation.load(path, allow_pickle=True)) only if you trust the file"
    )


def load_simulation(path: str | os.PathLike, *, allow_pickle: bool = False) -> Any:
    """The simulation saved in ``path`` by :func:`save_simulation`, ready to continue.

    Reads arrays and JSON only (``numpy.load(..., allow_pickle=False)``) and builds fastsdf's
    own classes from them: no code named in the file runs. Its kernels are rebuilt (or loaded
    from the kernel cache). A file holding pickled objects (saved with ``allow_pickle=True``,
    or in the first, pickled format) is refused with a ``ValueError`` unless
    ``allow_pickle=True`` is given: then it is unpickled, which runs code named in the file
    (only for files you trust). Raises ``ValueError`` if the file is not a saved simulation,
    is damaged, or was written by a newer format.
    """
    path = os.fspath(path)
    try:
        with zipfile.ZipFile(path) as zf:
            names = set(zf.namelist())
    except zipfile.BadZipFile:
        raise ValueError(f"{path!r} is not a saved fastsdf simulation (not an .npz file)") from None
    if "meta.npy" not in names:
        raise ValueError(f"{path!r} is not a saved fastsdf simulation (no meta)")
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(bytes(data["meta"]).decode())
            if not isinstance(meta, dict) or meta.get("format") != FORMAT:
                got = meta.get("format") if isinstance(meta, dict) else None
                raise ValueError(f"{path!r} is not a saved fastsdf simulation (format {got!r})")
            version = meta.get("version", 0)
            if isinstance(version, bool) or not isinstance(version, int):
                raise ValueError(f"{path!r} has no valid format version ({version!r})")
            if version > FORMAT_VERSION:
                raise ValueError(
                    f"{path!r} was written in format version {version}; "
                    f"this fastsdf reads up to {FORMAT_VERSION}: upgrade fastsdf"
                )
            if version <= _PICKLED_FORMAT:
                if not allow_pickle:
                    raise ValueError(
                        _pickle_refusal(path, "is in the first checkpoint format, a pickle")
                    )
                return _load_pickled(data, meta)
            if meta.get("pickled") and not allow_pickle:
                what = ", ".join(str(w) for w in meta["pickled"])
                raise ValueError(_pickle_refusal(path, f"holds pickled objects ({what})"))
            if "state.npy" not in names:
                raise ValueError(f"{path!r} is not a saved fastsdf simulation (no state)")
            state = json.loads(bytes(data["state"]).decode())
            reader = _Reader(data, state, bool(allow_pickle), path)
            sim = reader.value(state["root"])
    except (
        KeyError,
        IndexError,
        TypeError,
        AttributeError,
        UnicodeDecodeError,
        struct.error,
        RecursionError,
    ) as exc:
        raise ValueError(f"{path!r} is not a valid saved fastsdf simulation: {exc}") from exc
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path!r} is not a valid saved fastsdf simulation: {exc}") from None
    if not _is_simulation(sim):
        raise ValueError(f"{path!r} holds a {type(sim).__name__}, not a simulation")
    return sim


def _load_pickled(data: Any, meta: dict) -> Any:
    """A file of the first format: the state's arrays and the rest pickled (opt-in only)."""
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
