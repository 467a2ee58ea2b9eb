"""The particle family: what its simulations share.

Two members step particles in a world under the same names: :class:`ParticleSimulation`
(particles that meet only the world, stepped by this package's fused step,
:class:`fastsdf.particles.engine.ParticleEngine`) and :class:`GrainSimulation` (grains that also
collide with each other, stepped by the granular engine,
:class:`fastsdf.granular.GranularSimulation`). Each holds its engine as ``sim.engine``; both
derive from :class:`Simulation`, which holds the tools that work the same way for either
(and nothing that reads one engine's attributes): recorded runs, ``update``/``advance``,
``host``, ``save``/``load``, the kinetic energy and the notebook's drawing. The shared tools
outside this package (:mod:`fastsdf.io`, :mod:`fastsdf.viz`) take any member through the names
listed in :class:`Simulation`.
"""

from __future__ import annotations

import numbers
import os
import time
from abc import ABCMeta, abstractmethod
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from fastsdf.device import to_host
from fastsdf.introspect import show_init_signature
from fastsdf.notice import RunProgress
from fastsdf.particles.checkpoint import load_simulation, register_simulation, save_simulation

__all__ = ["Simulation", "DEFAULT_COUNT"]


class _DefaultCount(int):
    """The default particle count (100), told apart from an ``n`` given: with ``positions``
    the count comes from them."""


#: The default ``n`` of the family's constructors.
DEFAULT_COUNT = _DefaultCount(100)


class Simulation(metaclass=ABCMeta):
    """The base of the particle family's simulations (see the module docs).

    A member has the attributes ``p`` (its state: a
    :class:`fastsdf.particles.state.FieldState`), ``n``, ``t`` (seconds), ``dt`` (the step),
    ``sdf`` (the world; ``world`` reads it), ``force_generators``, ``seed`` and ``engine``, and
    defines :meth:`_run`, :meth:`reset`, :meth:`energy`, :meth:`potential_energy` and
    :meth:`query`. Every member is registered with the checkpoints
    (:mod:`fastsdf.particles.checkpoint`).
    """

    n: int
    t: float
    dt: float
    p: Any
    force_generators: list
    seed: Any
    engine: Any
    #: The wall-clock time of the last :meth:`update` with ``use_wall_time``.
    _wall: float | None = None
    #: What the progress of a recorded run calls the member's particles.
    _noun = "particles"

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        show_init_signature(cls)
        register_simulation(cls)

    # -- what each member defines ------------------------------------------------------------
    @abstractmethod
    def _run(self, steps: int) -> None:
        """Advance ``steps`` (>= 0) steps."""

    @abstractmethod
    def reset(self, ax: Any = None) -> tuple:
        """Back to the start; with an ``ax``, (re)draw the particles there."""

    @abstractmethod
    def energy(self) -> dict[str, float]:
        """Energies by part, the family's names (see :meth:`ParticleSimulation.energy`)."""

    @abstractmethod
    def potential_energy(self) -> float:
        """The potential energy of the :class:`Gravity` generators (zero at the origin)."""

    @abstractmethod
    def query(self, x: ArrayLike, y: ArrayLike) -> tuple:
        """``(d, grad)`` of the world at points ``x``, ``y`` (arrays of one shape), as the step
        sees it."""

    # -- the shared tools --------------------------------------------------------------------
    @property
    def world(self) -> Any:
        """The world (the same as ``sdf``)."""
        return self.sdf  # type: ignore[attr-defined]

    def run(self, steps: int = 1, record: Any = None) -> None:
        """Advance ``steps`` steps (``steps * dt`` seconds).

        ``record``: a recorder such as :class:`fastsdf.io.TrajectoryRecorder`, which then runs
        the steps in blocks and writes a frame every ``record.every`` steps (its ``run(sim,
        steps)``). See the member's step for what one step is and the errors it raises."""
        if _recorded(self, steps, record):
            return
        self._run(int(steps))

    def update(self, ax: Any = None, use_wall_time: bool = False) -> tuple:
        """Advance one frame and refresh the drawing on the axes ``ax`` (if given); returns the
        drawables.

        One step of ``dt`` seconds; with ``use_wall_time``, as many fixed steps as fit in the
        wall-clock time since the previous update (at least one, at most 10), so the animation
        keeps real time while the physics keeps its fixed step.
        """
        steps = 1
        if use_wall_time:
            now = time.perf_counter()
            if self._wall is not None:
                steps = int(min(10, max(1, round((now - self._wall) / self.dt))))
            self._wall = now
        self.run(steps)
        return self._draw(ax, new=False)

    def advance(self) -> None:
        """Advance the simulation by one step of ``dt`` seconds."""
        self.run(1)

    def check(self) -> None:
        """Wait for steps launched on a device and raise the errors they found (see the
        member's ``run``); a member that steps before ``run`` returns has nothing to do."""
        return None

    def host(self, name: str | None = None) -> Any:
        """A NumPy copy of the state's field ``name`` (``'x'``, ``'v'``, ``'m'``, ...), or of
        the whole state without a name (the state's ``host()``); a state on a device is copied
        from it (which waits for the device)."""
        if name is None:
            return self.p.host()
        return np.array(to_host(self.p[name]))

    def save(self, path: str | os.PathLike, *, allow_pickle: bool = False) -> str:
        """Write the simulation to ``path`` (``.npz``) so that :meth:`load` continues it bit for
        bit: arrays and data only (the world's expression graph or grid, parameters, forces by
        name and numbers, the random generator's state; grains: the engine's arrays and contact
        springs), so loading runs no code from the file. A force or world that is not data (a
        numba ``@njit`` or Python force, a world class of your own) is a ``ValueError`` naming
        it, unless ``allow_pickle=True`` (then it is stored pickled and :meth:`load` needs
        ``allow_pickle=True`` too); see :func:`fastsdf.particles.checkpoint.save_simulation`.
        Returns the path."""
        return save_simulation(self, path, allow_pickle=allow_pickle)

    @classmethod
    def load(cls, path: str | os.PathLike, *, allow_pickle: bool = False) -> Any:
        """The simulation saved by :meth:`save` at ``path``, continuing bit for bit. Runs no
        code from the file; a file holding pickled objects (saved with ``allow_pickle=True``, or
        by an older fastsdf) is refused with a ``ValueError`` unless ``allow_pickle=True``,
        which unpickles them (running code named in the file: only for files you trust)."""
        sim = load_simulation(path, allow_pickle=allow_pickle)
        if not isinstance(sim, cls):
            raise TypeError(f"{path!r} holds a {type(sim).__name__}, not a {cls.__name__}")
        return sim

    def kinetic_energy(self) -> float:
        """Total kinetic energy of translation ``sum(m |v|**2 / 2)``."""
        v = np.asarray(to_host(self.p["v"]), dtype=np.float64)
        m = np.asarray(to_host(self.p["m"]), dtype=np.float64)
        return float(np.sum(0.5 * m * (v * v).sum(1)))

    def _draw(self, ax: Any, new: bool) -> tuple:
        # The notebook's reset(ax)/update(ax) draw; the drawing and its state live in render.
        if ax is None:
            return ()
        from fastsdf.viz.render import notebook_draw

        return notebook_draw(self, ax, new)


def _recorded(sim: Simulation, steps: Any, record: Any) -> bool:
    """Check ``run``'s arguments; hand the run to ``record`` (which steps ``sim`` itself and
    records it) and say so, or return False for the caller to step."""
    if isinstance(steps, (bool, np.bool_)) or not isinstance(steps, numbers.Integral):
        raise TypeError(f"steps must be an integer, got steps={steps!r}")
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got steps={steps!r}")
    if record is None:
        return False
    if not callable(getattr(record, "run", None)):
        raise TypeError(
            f"record must be a recorder with a run(sim, steps) method, such as "
            f"fastsdf.io.TrajectoryRecorder, got record={record!r}"
        )
    what = f"{sim.n:,} {sim._noun}, run({steps}, record=...)"
    with RunProgress(int(steps), what, "steps"):
        record.run(sim, int(steps))  # (the runs it makes report to this progress)
    return True
