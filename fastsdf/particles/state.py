"""Particle state: the mapping surface every state of the family shares (:class:`FieldState`:
host, device and the grains' window), the particles' structure of arrays (:class:`Particles`:
``x``, ``v``: (n, 2); ``m``, ``r``, ``cr``, ``cf``: (n,), one float dtype), and the checks of
parameters and state that name what is wrong."""

from __future__ import annotations

from typing import Any

import numpy as np

from fastsdf.expr.validate import real

__all__ = ["FieldState", "Particles"]


def _real(value: Any, name: str) -> float:
    """A real number, possibly non-finite: callers check the range with their own message."""
    return real(value, name, finite=False)


def _unit_interval(value: Any, name: str) -> float:
    v = _real(value, name)
    if not 0.0 <= v <= 1.0:
        raise ValueError(f"{name} must be in [0, 1], got {name}={value!r}")
    return v


class FieldState:
    """The mapping surface of a particle family's state, on the host or the device: fields by
    name (``p['x']``, ``p.x``), ``len(p)``, ``'x' in p``, :meth:`keys`, :attr:`dtype`,
    :attr:`nbytes`, :meth:`copy` and :meth:`host` (a NumPy copy).

    ``p['x'] = value`` copies ``value`` into the existing array (broadcasting, e.g.
    ``p['cr'] = 0.9``, casting to the state's dtype), so the simulation keeps seeing it. Members:
    :class:`Particles` (NumPy arrays), :class:`fastsdf.particles.cuda.DeviceParticles` (device
    arrays), :class:`fastsdf.particles.grains.GrainState` (a window on the granular engine's
    arrays). A member defines ``FIELDS``, ``__len__``, ``copy``, ``host`` and where its arrays
    are (:meth:`_fields`), and may take a device array as a value (:meth:`_assign_device`).
    """

    FIELDS: tuple[str, ...] = ()
    #: What the error for an unknown field calls a member's items.
    _ITEM = "particle"
    _arrays: Any

    def _fields(self) -> dict:
        """The arrays by name (filled on first use where a member makes them on demand)."""
        return self._arrays

    def _handed_out(self, name: str) -> None:
        """Called when the array of field ``name`` is handed out (it may be written in place)."""

    def __getitem__(self, name: str) -> Any:
        if not isinstance(name, str) or name not in self.FIELDS:
            raise KeyError(f"no {self._ITEM} field {name!r}; fields are {self.FIELDS}")
        arr = self._fields()[name]
        self._handed_out(name)
        return arr

    def __setitem__(self, name: str, value: Any) -> None:
        arr = self[name]
        if self._assign_device(name, arr, value):
            return
        try:
            host = np.asarray(value)
        except Exception:
            raise TypeError(
                f"p[{name!r}] must be an array of real numbers, got {value!r}"
            ) from None
        if host.dtype.kind not in "iuf":
            raise TypeError(f"p[{name!r}] must hold real numbers, got dtype {host.dtype}")
        try:
            full = np.broadcast_to(host, arr.shape)
        except ValueError:
            raise ValueError(
                f"p[{name!r}] has shape {arr.shape}; cannot assign a value of shape {host.shape}"
            ) from None
        self._write(arr, full)

    def _assign_device(self, name: str, arr: Any, value: Any) -> bool:
        """Assign a device array ``value`` on the device and say so (host members: never)."""
        return False

    def _write(self, arr: Any, full: np.ndarray) -> None:
        """Copy the host values ``full`` (broadcast to the field's shape) into ``arr``."""
        np.copyto(arr, full, casting="unsafe")

    def __getattr__(self, name: str) -> Any:
        # (only for names that are not attributes: the fields; never the member's own state,
        # which may be missing while an instance is being unpickled)
        if not name.startswith("_") and name in type(self).FIELDS:
            return self[name]
        raise AttributeError(name)

    def __len__(self) -> int:
        return int(self._n)

    def __contains__(self, name: object) -> bool:
        return name in self.FIELDS

    def keys(self) -> tuple[str, ...]:
        """The field names."""
        return self.FIELDS

    @property
    def dtype(self) -> np.dtype:
        """The float dtype of every field."""
        return np.dtype(np.float64)

    @property
    def nbytes(self) -> int:
        """Bytes held by the state's arrays now."""
        arrays = self.__dict__.get("_arrays") or {}
        return sum(int(a.nbytes) for a in arrays.values())

    def copy(self) -> Any:
        """An independent copy (where the state lives)."""
        raise NotImplementedError

    def host(self) -> Any:
        """A NumPy copy of the state."""
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}(n={len(self)}, dtype={self.dtype.name})"


class Particles(FieldState):
    """Particle state, structure-of-arrays, indexable like the notebook's structured array.

    Fields (``p['x']`` or ``p.x``; arrays you may read and write in place):

    ==== ======= ==========================================================
    x    (n, 2)  position (length units)
    v    (n, 2)  velocity (length/s)
    m    (n,)    mass (> 0)
    r    (n,)    radius of the particle's disc (length units, >= 0)
    cr   (n,)    coefficient of restitution in [0, 1] (1: elastic)
    cf   (n,)    coefficient of friction in [0, 1] (0: frictionless)
    ==== ======= ==========================================================

    ``p['x'] = value`` copies ``value`` into the existing array (broadcasting, e.g.
    ``p['cr'] = 0.9``), so the simulation keeps seeing it. All fields share one float dtype
    (float64 or float32). Values are checked when the simulation steps: ``x``, ``v``, ``r`` at
    every call (the step reads them anyway), ``m``, ``cr``, ``cf`` where a step uses them and,
    in full, at the first call after they were handed out (``p['m']``, ``p.cr``: the array
    may have been written in place), so unchanged state is not re-read every call.
    """

    FIELDS = ("x", "v", "m", "r", "cr", "cf")

    def __init__(self, n: int, dtype: Any = np.float64):
        self._n = int(n)
        self._dtype = np.dtype(dtype)
        self._arrays = {}
        #: Whether m, cr or cf may have changed since the step last checked them all.
        self._dirty = True
        for name in self.FIELDS:
            shape = (self._n, 2) if name in ("x", "v") else (self._n,)
            self._arrays[name] = np.zeros(shape, dtype=self._dtype)

    #: Fields the step does not read on every step: handing one out (it may be written in
    #: place) marks the state for a full check at the next step.
    _CHECKED_ON_ACCESS = ("m", "cr", "cf")

    def _handed_out(self, name: str) -> None:
        if name in self._CHECKED_ON_ACCESS:
            self._dirty = True

    @property
    def dtype(self) -> np.dtype:
        """The float dtype of every field."""
        return self._dtype

    def copy(self) -> Particles:
        """An independent copy."""
        out = Particles(self._n, self._dtype)
        for name in self.FIELDS:
            out._arrays[name][...] = self._arrays[name]
        return out

    def host(self) -> Particles:
        """A copy (the state is on the host already)."""
        return self.copy()

    def as_structured(self) -> np.ndarray:
        """A copy as a NumPy structured array with the same fields (the notebook's layout)."""
        rec = np.zeros(
            self._n,
            dtype=[("x", self._dtype, 2), ("v", self._dtype, 2)]
            + [(f, self._dtype) for f in ("m", "r", "cr", "cf")],
        )
        for name in self.FIELDS:
            rec[name] = self._arrays[name]
        return rec


def _invalid_state_error(p: Particles, count: int) -> ValueError:
    """A ValueError naming the first invalid particle (only computed on the error path)."""
    x = np.asarray(p["x"], dtype=np.float64)
    v = np.asarray(p["v"], dtype=np.float64)
    checks = [
        ("x", ~np.isfinite(x).all(axis=1), "must be finite"),
        ("v", ~np.isfinite(v).all(axis=1), "must be finite"),
        ("m", ~((p["m"] > 0) & np.isfinite(p["m"])), "must be finite and > 0"),
        ("r", ~((p["r"] >= 0) & np.isfinite(p["r"])), "must be finite and >= 0"),
        ("cr", ~((p["cr"] >= 0) & (p["cr"] <= 1)), "must be in [0, 1]"),
        ("cf", ~((p["cf"] >= 0) & (p["cf"] <= 1)), "must be in [0, 1]"),
    ]
    for name, mask, rule in checks:
        idx = np.flatnonzero(mask)
        if idx.size:
            i = int(idx[0])
            val = p[name][i]
            val = val.tolist() if np.ndim(val) else float(val)
            return ValueError(
                f"invalid particle state: p[{name!r}][{i}] = {val!r} {rule} "
                f"({count} invalid particle(s) in all; they were left unchanged, "
                f"the others were advanced)"
            )
    return ValueError(f"{count} particle(s) had an invalid state during the step")
