"""The named structures a step kernel takes: the particles' arrays (:class:`State`), the physics
of a call (:class:`Physics`) and the safety and skipping settings (:class:`Budget`); and those
of one particle's contact helpers: its step (:class:`Motion`), its disc (:class:`Disc`) and the
part of the step a tunnelling sweep checks (:class:`Window`).

They are ``typing.NamedTuple`` classes, which numba compiles as structs: a kernel reads
``physics.dt`` as it read a positional argument, and a new value never recompiles. Generated
kernel modules import them from here, so the caller and every kernel share one class each.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from fastsdf.introspect import show_field_types

__all__ = ["State", "Physics", "Budget", "Motion", "Disc", "Window", "NO_EXT"]

#: ``State.EXT`` of a call without Python forces.
NO_EXT = np.zeros((0, 2))


@show_field_types
class State(NamedTuple):
    """The arrays of the particles a call steps (structure of arrays, one float dtype).

    ``X``, ``V``: (n, 2) positions and velocities (read and written); ``M``, ``R``, ``CR``,
    ``CF``: (n,) mass, radius, restitution, friction (read); ``EXT``: (n, 2) Python forces of
    this step, or (0, 2) without; ``FLAGS``: (n,) int freeze codes written by the kernel
    (``FLAG_*`` of :mod:`.constants`); ``check_all``: check ``m``, ``cr``, ``cf`` of every
    particle in the first pass (they may have been written since the last call).
    """

    X: np.ndarray
    V: np.ndarray
    M: np.ndarray
    R: np.ndarray
    CR: np.ndarray
    CF: np.ndarray
    EXT: np.ndarray
    FLAGS: np.ndarray
    check_all: bool


@show_field_types
class Physics(NamedTuple):
    """The physics of a call: timestep ``dt`` (s), time of the first step ``t0``, uniform
    acceleration ``(ax, ay)``, linear ``drag`` (mass/s), whether the mass is read (``use_m``:
    drag or Python forces) and Python forces are added (``use_ext``), explicit Euler
    (``explicit``; else semi-implicit), velocity response whenever in contact (``always``;
    else only while approaching), and resting contact below the speed ``rest`` (0: off)."""

    dt: float
    t0: float
    ax: float
    ay: float
    drag: float
    use_m: bool
    use_ext: bool
    explicit: bool
    always: bool
    rest: float


@show_field_types
class Budget(NamedTuple):
    """Safety and query skipping: the tunnelling sweep (``trace``), the world's Lipschitz bound
    ``lip``, the ``margin`` a grid may jump at its bounds, the relative rounding ``eps`` of
    stored coordinates, and free-flight query skipping (``skip``)."""

    trace: bool
    lip: float
    margin: float
    eps: float
    skip: bool


@show_field_types
class Motion(NamedTuple):
    """One particle's step: start ``(x, y)``, displacement ``(dx, dy)`` and velocity
    ``(vx, vy)``."""

    x: float
    y: float
    dx: float
    dy: float
    vx: float
    vy: float


@show_field_types
class Disc(NamedTuple):
    """One particle's radius ``r`` and its restitution ``cr`` and friction ``cf``."""

    r: float
    cr: float
    cf: float


@show_field_types
class Window(NamedTuple):
    """The part of a step a sweep checks: the step's parameters below ``t0`` and above ``t1``
    are known to be free; meanwhile time runs from ``ts`` over ``tdt`` and the walls move at
    most ``wd`` (0, 0, 0 in a static world)."""

    t0: float
    t1: float
    ts: float
    tdt: float
    wd: float
