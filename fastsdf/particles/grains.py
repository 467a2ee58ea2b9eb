"""Grains: the member of the particle family whose particles also collide with each other.

``ParticleSimulation(world, positions=..., radius=..., contacts=ContactLaw())`` builds a
:class:`GrainSimulation`: a :class:`~fastsdf.particles.ParticleSimulation` (same names, same
tools: ``sim.p``, ``sim.t``, ``sim.dt``, ``sim.world``, ``sim.force_generators``,
``sim.run(steps, record=...)``, ``sim.save``/``load``, the notebook's ``reset(ax)``/``update(ax)``)
whose step is the granular engine :class:`fastsdf.granular.GranularSimulation` (soft-sphere
DEM, substepped within each step).

Why delegation and not one kernel family: the non-interacting step is one fused pass per
particle and step with no neighbours, the granular step a velocity-Verlet substep over a cell
and Verlet list, reordered by cell; they share the state's names, the world, the forces and
every tool, not a loop. Delegating keeps each engine's speed and verified physics as they are
(the non-interacting step bit for bit) and gives the family one front door.

The state: ``sim.p`` has the fields ``x``, ``v`` ((n, 2)), ``m``, ``r`` and ``omega`` ((n,)),
in the order the grains were given. The engine keeps its own arrays (reordered in space for
speed); ``sim.p`` is a window on them, filled when first read after a step and written back
(the engine restarting from it) at the next step only if a value was changed. ``m`` follows
from ``r`` and ``density`` (``density pi r**2``) and cannot be written. Between steps, the
window costs 56 bytes per grain; while stepping, nothing.

Forces: :class:`Gravity` sets the engine's gravity (and, for a derived stiffness, the contact
law and the substep); :class:`Drag`, :class:`FieldForce` and numba ``@njit`` forces ``(x, y,
vx, vy, m, t) -> (fx, fy)`` are fused into one compiled pass added to every force evaluation
(at the substep's positions and predicted velocities). A Python force generator ``(p, t)``
would run at every substep and is refused: write it with ``@njit``.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import numba
import numpy as np
from numpy.typing import ArrayLike

from fastsdf.backends import load_module
from fastsdf.granular.params import ContactLaw
from fastsdf.granular.simulation import (
    DEFAULT_RADIUS,
    DEFAULT_SUBSTEPS_PER_CONTACT,
    GranularSimulation,
)
from fastsdf.notice import compiling
from fastsdf.particles.family import DEFAULT_COUNT, Simulation
from fastsdf.particles.forces import Gravity, fuse
from fastsdf.particles.scene_blocks import force_lines
from fastsdf.particles.simulation import ParticleSimulation
from fastsdf.particles.state import FieldState
from fastsdf.version import __version__

__all__ = ["GrainSimulation", "GrainState"]


class GrainState(FieldState):
    """The grains' state in their given order: ``p['x']``, ``p['v']`` (n, 2), ``p['m']``,
    ``p['r']``, ``p['omega']`` (n,) (angular velocity, rad/s, counter-clockwise), with the
    family's mapping surface (:class:`~fastsdf.particles.state.FieldState`). Arrays read here
    may be written in place (``m`` excepted); the next step takes the changes. ``engine``: the
    granular engine whose arrays these are (kept in its spatial order)."""

    FIELDS = ("x", "v", "m", "r", "omega")
    _ITEM = "grain"

    def __init__(self, engine: GranularSimulation) -> None:
        self._engine = engine
        self._arrays: dict | None = None

    def _current(self) -> dict:
        e = self._engine
        return {
            "x": e.positions,
            "v": e.velocities,
            "m": e.masses,
            "r": e.radius,
            "omega": e.angular_velocities,
        }

    def _fields(self) -> dict:
        if self._arrays is None:
            self._arrays = self._current()
        return self._arrays

    def __len__(self) -> int:
        return int(self._engine.ids.shape[0])

    def sync(self) -> None:
        """Hand the changes written into the window to the engine (which restarts from them)
        and empty the window; called before every step."""
        if self._arrays is None:
            return
        mine, now = self._arrays, self._current()
        self._arrays = None
        changed = {
            k: mine[k] for k in self.FIELDS if not np.array_equal(mine[k], now[k], equal_nan=True)
        }
        if not changed:
            return
        e = self._engine
        if "m" in changed:
            expected = e.density * math.pi * np.asarray(changed.get("r", now["r"])) ** 2
            if not np.array_equal(changed["m"], expected):
                raise ValueError(
                    "p['m'] of grains follows from their radius and the density "
                    "(m = density pi r**2): write p['r'] or set density instead"
                )
        e.set_state(
            positions=changed.get("x"),
            velocities=changed.get("v"),
            angular_velocities=changed.get("omega"),
            radius=changed.get("r"),
        )

    def copy(self) -> dict:
        """An independent copy of the fields, as a dict of arrays."""
        return {k: v.copy() for k, v in self._fields().items()}

    def host(self) -> dict:
        """A copy of the fields (the state is on the host), as a dict of arrays."""
        return self.copy()


# ---------------------------------------------------------------------------------------------
# Forces beyond gravity: one compiled pass per set of fused forces.

_FORCE_PASS = """
@njit(cache=_CACHE, parallel=True, error_model="numpy")
def add_forces(g, density, t, drag):
    x = g.x
    y = g.y
    vx = g.px
    vy = g.py
    rad = g.radius
    fx = g.fx
    fy = g.fy
    for i in prange(x.shape[0]):
        r = rad[i]
        m = density * math.pi * r * r
        ax, ay = _force(x[i], y[i], vx[i], vy[i], m, t)
        fx[i] += ax - drag * vx[i]
        fy[i] += ay - drag * vy[i]
"""

_PASSES: dict = {}


def _force_pass(user: tuple) -> Any:
    """The compiled pass adding the fused forces ``user`` and drag to the grains' forces."""
    lines, deps, late = force_lines(user)
    head = [
        f"# Grain force pass generated by fastsdf {__version__} (numba {numba.__version__}).",
        f"# Dependencies: {'; '.join(deps) or 'none'}",
        "import math",
        "from numba import njit, prange",
        f"_CACHE = {not late}",
        "",
    ]
    source = "\n".join(head + lines) + "\n" + _FORCE_PASS
    if not late:
        return load_module(source, prefix="fastsdf_grainforce").add_forces
    key = tuple(id(obj) for _, obj in late)
    entry = _PASSES.get(key)
    if entry is None:
        mod = load_module(source + f"\n# uncached instance {len(_PASSES)}\n", "fastsdf_grainforce")
        for name, obj in late:
            setattr(mod, name, obj)
        entry = _PASSES[key] = (mod.add_forces, [obj for _, obj in late])
    return entry[0]


class _External:
    """The engine's hook: the compiled pass with the drag coefficient."""

    def __init__(self, fn: Any, drag: float) -> None:
        self.fn = fn
        self.drag = drag

    def __call__(self, grains: Any, density: float, t: float) -> None:
        self.fn(grains, density, t, self.drag)


# ---------------------------------------------------------------------------------------------
# The simulation.


def _points(value: ArrayLike, name: str) -> np.ndarray:
    a = np.array(value, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"{name} must have shape (n, 2), got {name} of shape {a.shape}")
    return a


class GrainSimulation(Simulation):
    """Grains colliding with each other and with the world; built by
    ``ParticleSimulation(world, positions=..., radius=..., contacts=ContactLaw(...))``
    (see :mod:`fastsdf.particles.grains`).

    One step (``timestep`` seconds, ``sim.dt``) is ``sim.substeps_per_frame`` substeps of
    the granular engine (``sim.engine``, a :class:`fastsdf.granular.GranularSimulation`).
    Gravity comes from ``force_generators`` (:class:`Gravity`), as for particles.

    Parameters
    ----------
    world : fastsdf SDF, GridSDF or None
        The walls, negative inside matter (``None``: no walls).
    n : int, optional
        The number of grains, if given: it must match ``positions``.
    timestep : float, default 1/30
        Seconds per step.
    positions : array (n, 2)
        Start centres of the grains (required).
    velocities : array (n, 2) or None
        Start velocities (default 0).
    radius : float, array (n,) or None
        Radii (default 0.02).
    contacts : ContactLaw or None
        The grain-grain law (``None``: ``ContactLaw()``); a law without a stiffness derives it
        (see :class:`fastsdf.granular.ContactLaw`) from the grains, the density and the gravity
        of ``force_generators`` when a run starts.
    wall_contacts : ContactLaw or None
        The grain-world law (default: ``contacts``).
    substeps_per_contact : float or None
        Resolution of the lightest contact (``None``: 40, the engine's default).
    substep, skin, periodic_x, chunks : optional
        The engine's (see :class:`fastsdf.granular.GranularSimulation`).
    device : {'cpu', 'cuda'}, default 'cpu'
        ``'cuda'``: the engine on the GPU (:mod:`fastsdf.granular.cuda`).
    density : float, default 1
        Mass per unit area.
    seed : int, numpy Generator or None
        Kept as given (``sim.seed``), for the family's interface: grains start where they are
        given, nothing is drawn.
    """

    engine: GranularSimulation
    _dt: float
    _start: tuple
    p: GrainState
    _noun = "grains"
    #: Where the engine steps the grains ('cpu' or 'cuda').
    device: str = "cpu"

    def __init__(
        self,
        world: Any,
        n: int = DEFAULT_COUNT,
        timestep: float = 1 / 30,
        *,
        positions: ArrayLike | None = None,
        velocities: ArrayLike | None = None,
        radius: ArrayLike | float | None = None,
        contacts: ContactLaw | None = None,
        wall_contacts: ContactLaw | None = None,
        substeps_per_contact: float | None = None,
        substep: float | None = None,
        skin: float | None = None,
        periodic_x: ArrayLike | None = None,
        chunks: int | None = None,
        density: float = 1.0,
        device: str = "cpu",
        seed: Any = None,
    ) -> None:
        if positions is None:
            raise ValueError(
                "grains (contacts=...) need positions= (n, 2): the notebook's random "
                "blob would start them overlapping"
            )
        pos = _points(positions, "positions")
        if isinstance(n, (bool, np.bool_)) or not isinstance(n, numbers.Integral):
            raise TypeError(f"n must be an integer, got n={n!r}")
        if n is not DEFAULT_COUNT and int(n) != pos.shape[0]:
            raise ValueError(f"n={n!r} does not match positions, which hold {pos.shape[0]} rows")
        self.n = int(pos.shape[0])
        self.seed = seed
        self.device = device
        spc = DEFAULT_SUBSTEPS_PER_CONTACT if substeps_per_contact is None else substeps_per_contact
        self.engine = GranularSimulation(
            world,
            positions=pos,
            velocities=velocities,
            radius=DEFAULT_RADIUS if radius is None else radius,
            contacts=contacts,
            wall_contacts=wall_contacts,
            density=density,
            timestep=timestep,
            gravity=(0.0, 0.0),  # the force generators' (Gravity), set when a run starts
            substeps_per_contact=spc,
            substep=substep,
            skin=skin,
            periodic_x=periodic_x,
            chunks=chunks,
            device=device,
        )
        self._dt = self.engine.timestep
        self.force_generators: list = []
        self._fused: tuple | None = None
        self._wall = None
        # The start, for reset(): positions and radii, velocities only if any is not 0.
        g = self.engine
        self._start = (
            g.positions,
            g.radius,
            None if not np.any(g.velocities) else g.velocities,
        )
        self.p = GrainState(self.engine)

    # -- the family's names ------------------------------------------------------------
    @property
    def sdf(self) -> Any:
        """The world (SDF or GridSDF, or None); assigning another one continues the grains
        in it."""
        return self.engine.world

    @sdf.setter
    def sdf(self, f: Any) -> None:
        if f is not None and not callable(f):
            raise TypeError(f"the world must be a fastsdf SDF or GridSDF, got {f!r}")
        self.p.sync()
        self.engine.world = f
        self.engine.moving = bool(getattr(f, "time_dependent", False))
        self.engine.set_state()

    @property
    def t(self) -> float:
        """Simulated time in seconds."""
        return self.engine.time

    @t.setter
    def t(self, value: float) -> None:
        self.engine.time = float(value)

    @property
    def dt(self) -> float:
        """The step (frame) in seconds; assigning it keeps the substep's bound (the
        substeps per step follow)."""
        return self._dt

    @dt.setter
    def dt(self, value: float) -> None:
        dt = float(value)
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(f"timestep must be finite and > 0, got timestep={value!r}")
        self._dt = dt
        self.engine.timestep = dt
        self.engine.set_gravity((self.engine.bulk.gravity_x, self.engine.bulk.gravity_y))

    @property
    def contacts(self) -> ContactLaw:
        """The grain-grain law in use (its stiffness resolved)."""
        return self.engine.contact

    @property
    def density(self) -> float:
        """Mass per unit area."""
        return self.engine.density

    @property
    def substeps_per_frame(self) -> int:
        """Engine substeps per step of ``dt`` (follows the contact law and gravity)."""
        self._apply_forces()
        return self.engine.substeps_per_frame

    def memory_per_grain(self) -> float:
        """Bytes held per grain: the engine's, the start kept for :meth:`reset` and the
        state window when filled."""
        start = sum(a.nbytes for a in self._start if a is not None)
        return self.engine.memory_per_grain() + (start + self.p.nbytes) / self.n

    # -- stepping ----------------------------------------------------------------------
    def _apply_forces(self, restart: bool = True) -> None:
        """Hand the force generators to the engine (gravity, and one compiled pass for
        drag and fused forces) when they changed; the engine then evaluates its forces again
        at the current state (``restart``; not when rebinding a loaded simulation's hook)."""
        ax, ay, drag, python, user = fuse(self.force_generators)
        if python:
            raise TypeError(
                f"grains take Gravity, Drag, FieldForce and numba @njit forces (x, y, "
                f"vx, vy, m, t) -> (fx, fy); a Python force generator ({python[0]!r}) "
                f"would run at every substep: write it with numba's @njit"
            )
        key = (ax, ay, drag, tuple(id(u) for u in user))
        if self._fused is not None and self._fused[0] == key:
            return
        e = self.engine
        if user or drag:
            with compiling("the grains' force pass"):
                fn = _force_pass(user)
            e.external = _External(fn, drag)
        else:
            e.external = None
        if (ax, ay) != (e.bulk.gravity_x, e.bulk.gravity_y):
            e.set_gravity((ax, ay))
        elif restart:
            e.set_state()
        self._fused = (key, user)

    def _run(self, steps: int) -> None:
        """``steps`` steps of ``dt`` seconds, ``substeps_per_frame`` substeps each."""
        self.p.sync()
        self._apply_forces()
        self.engine.run(steps)

    def reset(self, ax: Any = None) -> tuple:
        """Back to the start (the positions, velocities and radii given), ``t = 0``; with
        an ``ax``, (re)draw the grains there (the notebook's interface)."""
        pos, r, v = self._start
        self.p = GrainState(self.engine)
        self.engine.set_state(
            positions=pos,
            velocities=np.zeros_like(pos) if v is None else v,
            angular_velocities=np.zeros(self.n),
            radius=r,
        )
        self.engine.time = 0.0
        self._wall = None
        return self._draw(ax, new=True)

    def energy(self) -> dict[str, float]:
        """Energies by part (the family's names): ``kinetic``, ``rotational``, ``potential``
        (gravitational), the contacts' ``normal_springs``, ``tangential_springs`` and
        ``rolling_springs``, and their sum, ``total``; see
        :meth:`fastsdf.granular.GranularSimulation.energy`."""
        self.p.sync()
        self._apply_forces()
        return self.engine.energy()

    def potential_energy(self) -> float:
        """Gravitational potential energy ``-m g . x`` (zero at the origin)."""
        x = np.asarray(self.p["x"])
        m = np.asarray(self.p["m"])
        ax, ay, _, _, _ = fuse([g for g in self.force_generators if isinstance(g, Gravity)])
        return float(-np.sum(m * (x[:, 0] * ax + x[:, 1] * ay)))

    def query(self, x: ArrayLike, y: ArrayLike) -> tuple:
        """``(d, grad)`` of the world at points ``x``, ``y`` (arrays of one shape)."""
        d, grad = self.engine.world(
            np.asarray(x, dtype=np.float64),
            np.asarray(y, dtype=np.float64),
            compute_gradient=True,
        )
        return d, grad

    # -- pickling and files --------------------------------------------------------------
    def __getstate__(self) -> dict:
        self.p.sync()
        state = self.__dict__.copy()
        state["p"] = None
        state["_fused"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        state = dict(state)
        state.pop("p", None)
        self.__dict__.update(state)
        self.p = GrainState(self.engine)
        self._apply_forces(restart=False)

    def __repr__(self) -> str:
        e = self.engine
        return (
            f"ParticleSimulation(n={self.n}, timestep={self.dt!r}, t={self.t:.4g}, "
            f"contacts={e.contact!r}, substeps_per_frame={e.substeps_per_frame})"
        )


# Grains are the family's member with contacts: ParticleSimulation(..., contacts=...) builds
# them, and they count as a ParticleSimulation without inheriting its step.
ParticleSimulation._admit_grains(GrainSimulation)
