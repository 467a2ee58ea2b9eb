"""A granular simulation: discs that collide with each other and with an SDF world.

The step is velocity Verlet (as LAMMPS's ``fix nve/sphere``): ``x += (v + F/m dt/2) dt``, new
forces ``F'`` at the new positions, ``v += (F + F')/m dt/2``. The dashpots see the velocity
predicted for the end of the step, ``v + F/m dt`` (second order; LAMMPS uses the half-step
velocity, which lags and biases strongly damped contacts). A substep is one force pass (each
grain gathers its forces and updates only its own velocity) and one elementwise pass
(:func:`~fastsdf.granular.kernels.kick_drift`), run as one parallel loop
(:func:`~fastsdf.granular.kernels.substep_pass`: the positions and predicted velocities are
double-buffered), with the world's query between two such loops. Without dashpots the step is
symplectic: the energy oscillates, it does not drift. The grains are split into chunks fixed
by their number, so a run gives the same bits on any number of threads; above
:data:`PARALLEL_MIN_GRAINS` the engine chooses its threads by measuring
(:mod:`fastsdf.granular.threads`).

Substeps: a soft contact lasts ``t_c = pi sqrt(m_eff / k_n)``, and the step must resolve it:
the frame step ``timestep`` (e.g. 1/30 s) is cut into equal substeps no longer than
``t_c / substeps_per_contact`` for the lightest possible contact (two of the smallest grains,
or the world's stiffer law against the smallest grain). About 40 substeps per contact is the
usual DEM resolution (t_c / 20 to t_c / 50; LAMMPS's reference bed runs at t_c / 44); at the
default 40 a head-on impact rebounds within 1% of the restitution for ``e >= 0.5`` (0.8% at
0.5, 0.13% at 0.9, measured), and the elastic gas of the tests keeps its energy within 1e-3
over 1e4 substeps. Strongly damped contacts need more: at ``e = 0.1`` the restitution is 6% off
at 40 substeps and within 1% from about 100 (the dashpot's velocity is a prediction, exact to
second order; the tests use 160). The contact of a tangential force is at the grain's radius
(as in LAMMPS), so angular momentum is kept up to a term of the order of overlap / radius.

Tangential force: by default history-free (LAMMPS ``gran/hooke``): viscous in the sliding
velocity of the contact point, capped by Coulomb. Without history there is no static friction:
a grain on a slope creeps (slowly, at the speed where the viscous force balances it), and heaps
relax toward flat over time. ``ContactLaw(history=True)`` keeps a tangential spring per contact
(Cundall-Strack, LAMMPS ``gran/hooke/history``; see
:func:`fastsdf.granular.kernels.pair_forces`): one number per list entry (in 2D the
tangent is a line, so the spring is its stretch along it), and one per grain against the world.
At every rebuild the grains are reordered and the list rebuilt: the old list, its springs and
the permutation are kept, and each new entry takes the spring of the same pair of grains from
the old list (:func:`fastsdf.granular.cells.carry_springs`, a search over the grain's few old
partners), so a contact never forgets its spring while it lasts. Rolling resistance
(``rolling_friction > 0``) adds a rolling spring per entry beside it.

Memory per grain (float64): the state and forces, 12 arrays, 96 bytes; the second buffer of
positions and predicted velocities, 40 bytes, in which a rebuild sorts (its scratch, sort keys
and permutation, and the cell arrays where they fit); the grain's index as given and float32
reference positions of the skin test, 16 bytes; the list's row starts, 8 bytes; the half list
(4-byte entries, a quarter of slack), about 15-20 bytes in a dense packing of equal discs (3
pairs per grain); cell arrays of their own only where the spare buffer cannot hold them (at
most ``2 n + 64`` cells, counts for at most 4 chunks: at most 52 bytes).
:meth:`GranularSimulation.memory_per_grain` reports the actual figure; about 175 bytes in a
dense bed. With history add, per list entry, 8 bytes of spring (16 with rolling
resistance), twice over (the current list and the one before the last rebuild, whose entries,
4 bytes each, and row starts, 8 bytes per grain, are kept too), and 8 (16) bytes per grain for
the springs against the world.

Ordering: grains are reordered by cell at every list rebuild (the cell list is a stable sort by
cell key), so neighbours in space are neighbours in memory; :attr:`GranularSimulation.ids`
maps the storage slots back to the grains' given numbering, which every public accessor uses.
"""

from __future__ import annotations

import math
import time as _time
from collections.abc import Callable
from typing import Any

import numba
import numpy as np
from numpy.typing import ArrayLike

from fastsdf.granular.cells import (
    INDEX_MASK,
    CellGrid,
    SortedGrains,
    build_verlet,
    carry_springs,
    cell_keys,
    counting_sort,
    list_pairs,
    make_grid,
    permute,
)
from fastsdf.granular.checks import warn_starting_state
from fastsdf.granular.kernels import (
    Bulk,
    Grains,
    Near,
    Substep,
    kick_drift,
    kinetic_energy,
    pair_energy,
    pair_forces,
    substep_pass,
    wall_energy,
    wall_forces,
)
from fastsdf.granular.params import (
    STANDARD_GRAVITY,
    ContactLaw,
    _real,
    check_contact_law,
    contact_time,
    derived_stiffness,
)
from fastsdf.granular.threads import ThreadTuner
from fastsdf.introspect import show_init_signature
from fastsdf.notice import RunProgress, compiling, compiling_first, warn_caller

__all__ = [
    "DEFAULT_RADIUS",
    "DEFAULT_SUBSTEPS_PER_CONTACT",
    "PARALLEL_MIN_GRAINS",
    "SUBSTEPS_WARNING",
    "SUBSTEPS_WARNING_WORK",
    "GranularSimulation",
    "SubstepWarning",
]

#: The radius of grains given without one (length units: the library's scenes span 4).
DEFAULT_RADIUS = 0.02
#: Substeps per (undamped) contact time of the lightest contact, by default.
DEFAULT_SUBSTEPS_PER_CONTACT = 40
#: Fewer grains than this step on one thread: waking the other threads for every pass of
#: every substep costs more than it saves (and far more on a busy machine).
PARALLEL_MIN_GRAINS = 4096
#: From this many grains the force pass takes more than 8 chunks (see ``chunks``).
WIDE_CHUNKS_GRAINS = 65536
#: :meth:`GranularSimulation.run` warns (once per simulation) when a frame takes more substeps
#: than this (the library's default grains, radius 0.02 with a derived stiffness in its
#: 4-high scenes under g = 9.81, take about 940) and at least
#: :data:`SUBSTEPS_WARNING_WORK` grain-substeps, a frame of a second or so on a busy 2-core
#: machine (a frame of a few grains is quick however many substeps it takes).
SUBSTEPS_WARNING = 1000
SUBSTEPS_WARNING_WORK = 2_000_000
#: Grain-substeps between two progress updates of a run (a few hundredths of a second).
_PROGRESS_WORK = 200_000


class SubstepWarning(UserWarning):
    """A granular simulation cuts each frame into very many substeps (see
    :data:`SUBSTEPS_WARNING`): its contact is short against the frame."""


def _points(value: ArrayLike, name: str, n: int | None = None) -> np.ndarray:
    a = np.array(value, dtype=np.float64, copy=True)
    if a.ndim != 2 or a.shape[1] != 2 or (n is not None and a.shape[0] != n):
        want = "(n, 2)" if n is None else f"({n}, 2)"
        raise ValueError(f"{name} must have shape {want}, got {name} of shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(
            f"{name} must be finite, got a non-finite value at row "
            f"{int(np.flatnonzero(~np.isfinite(a).all(axis=1))[0])}"
        )
    return a


def _radii(radius: ArrayLike, n: int) -> np.ndarray:
    r = np.array(np.broadcast_to(np.asarray(radius, dtype=np.float64), (n,)))
    if not np.all(np.isfinite(r) & (r > 0)):
        bad = int(np.flatnonzero(~(np.isfinite(r) & (r > 0)))[0])
        raise ValueError(f"radius must be finite and > 0, got radius[{bad}]={float(r[bad])!r}")
    return r


def _positive(value: object, name: str) -> float:
    out = _real(value, name)
    if not out > 0:
        raise ValueError(f"{name} must be > 0, got {name}={value!r}")
    return out


def _gravity(gravity: ArrayLike) -> np.ndarray:
    gxy = np.asarray(gravity, dtype=np.float64)
    if gxy.shape != (2,) or not np.all(np.isfinite(gxy)):
        raise ValueError(f"gravity must be two finite numbers, got gravity={gravity!r}")
    return gxy


def _period(periodic_x: ArrayLike | None) -> tuple[float, float]:
    """``(x0, period)`` of ``periodic_x = (x0, x1)``; ``(0, 0)`` for None (not periodic)."""
    if periodic_x is None:
        return 0.0, 0.0
    px = np.asarray(periodic_x, dtype=np.float64)
    if px.shape != (2,) or not np.all(np.isfinite(px)) or not px[1] > px[0]:
        raise ValueError(f"periodic_x must be (x0, x1) with x0 < x1, got periodic_x={periodic_x!r}")
    return float(px[0]), float(px[1] - px[0])


def _chunk_count(chunks: int | None, n: int) -> int:
    """Chunks of the force pass, fixed by the number of grains (never by the threads: the
    chunks fix which pairs are listed twice and the order of each grain's sums, so the same
    chunks give the same bits on any number of threads). By default ``n // 256``, at most 8
    (the chunks two threads gave before they were fixed: the same bits as then), and from
    :data:`WIDE_CHUNKS_GRAINS` the largest power of two of at most ``n // 1024`` and
    ``sqrt(n) / 16`` chunks (16 at 1e5, for up to 16 threads), which keeps the pairs listed
    twice (about one row of grains per chunk boundary) to a few percent of a square bed. Powers
    of two split evenly among 1, 2, 4, 8 or 16 threads under numba's equal static schedule."""
    if chunks is None:
        chunks = max(1, min(8, n // 256))
        if n >= WIDE_CHUNKS_GRAINS:
            most = min(n // 1024, int(math.sqrt(n) / 16))
            while 2 * chunks <= most:
                chunks *= 2
    if isinstance(chunks, bool) or not isinstance(chunks, (int, np.integer)) or chunks < 1:
        raise ValueError(f"chunks must be an int >= 1, got chunks={chunks!r}")
    return int(min(chunks, n))


def world_height(world: Any, positions: np.ndarray, diameter: float, gravity: ArrayLike) -> float:
    """The world's height along gravity for a derived stiffness (see :class:`ContactLaw`): the
    extent of ``world.bounds`` (a grid's) along gravity, else the grains' extent at the start,
    at least ``10 diameter``."""
    g = np.asarray(gravity, dtype=np.float64)
    norm = float(np.hypot(g[0], g[1]))
    up = g / norm if norm > 0 else np.array([0.0, -1.0])
    bounds = getattr(world, "bounds", None)
    try:
        (x0, x1), (y0, y1) = bounds  # type: ignore[misc]
        corners = np.array([[x0, y0], [x0, y1], [x1, y0], [x1, y1]], dtype=np.float64)
    except (TypeError, ValueError):
        corners = positions
    along = corners @ up
    height = float(along.max() - along.min()) if corners.size else 0.0
    if not math.isfinite(height):
        height = 0.0
    return max(height, 10.0 * diameter)


class GranularSimulation:
    """Discs (soft-sphere DEM, ``gran/hooke``) under gravity, colliding with each other and
    with an SDF world: the engine under the particle family's grains, with the family's
    argument names and order (``GranularSimulation(world, positions=..., radius=...,
    contacts=ContactLaw(...))``; gravity is a parameter here, a force generator there).

    Parameters
    ----------
    world : fastsdf Function, GridSDF or None
        The walls: negative inside matter; a grain of radius R touches it where ``d < R``
        (overlap ``R - d`` along ``grad d``). A world built with time :data:`fastsdf.t` moves
        (evaluated at the simulation's time; the wall's normal speed ``-dd/dt / |grad d|``
        enters the dashpot). ``None``: no walls.
    positions : array (n, 2)
        Centres of the discs (length).
    velocities : array (n, 2) or None
        Initial velocities (length / s; default 0). Angular velocities start at 0.
    radius : float or array (n,)
        Radii (length, > 0; default 0.02); any mix of sizes (the neighbour cells are sized by
        the largest).
    contacts : ContactLaw or None
        The grain-grain law (default ``ContactLaw()``) (stiffness in force/length,
        restitution, friction, tangential damping); see :class:`fastsdf.granular.ContactLaw`.
    wall_contacts : ContactLaw or None
        The grain-world law (default: ``contacts``).
    density : float
        Mass per unit area (> 0): a disc weighs ``density pi R**2``, its moment of inertia is
        that of a solid disc, ``m R**2 / 2``.
    timestep : float
        Seconds per frame (:meth:`run` advances whole frames).
    gravity : (gx, gy)
        Acceleration of gravity (length / s**2); the default ``(0, -1)`` is that of
        :class:`fastsdf.particles.Gravity` (the notebook's, in the scene's length units).
    substeps_per_contact : float
        Resolution of the lightest contact when ``substep`` is None (>= 10).
    substep : float or None
        Integration step (s); ``None`` picks the largest step that divides ``timestep`` into
        equal parts no longer than ``t_c / substeps_per_contact`` (see the module docs).
    skin : float or None
        Verlet-list skin (length, > 0): the list is rebuilt when a grain has moved farther than
        ``skin / 2``. ``None``: a fifth of the mean diameter.
    periodic_x : (x0, x1) or None
        Make x periodic with period ``x1 - x0`` (grains leaving one side enter the other).
    chunks : int or None
        Contiguous chunks of grains the force pass runs over in parallel (tuning; the results
        depend on it by rounding only, and not on the number of threads or the threading
        layer). ``None``: fixed by the number of grains (``n // 256``, at most 8; from
        :data:`WIDE_CHUNKS_GRAINS`, more: 16 at 1e5).
    device : 'cpu' or 'cuda'
        Where the grains are stepped: ``'cuda'`` builds a
        :class:`fastsdf.granular.cuda.CudaGranularSimulation` (the same physics and names, its
        state on the GPU; needs numba-cuda, see :mod:`fastsdf.device`), which also takes
        ``max_neighbours``.
    """

    #: The engine of each device other than the CPU, registered by its subclass
    #: (``class ...(GranularSimulation, device='cuda')``: :mod:`fastsdf.granular.cuda`, which
    #: the package imports), so this module imports none of them.
    _devices: dict[str, type] = {}

    def __init_subclass__(cls, device: str | None = None, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if device is not None:
            GranularSimulation._devices[device] = cls

    def __new__(cls, *args: Any, device: str = "cpu", **kwargs: Any) -> GranularSimulation:
        if device not in ("cpu", "cuda"):
            raise ValueError(f"device must be 'cpu' or 'cuda', got device={device!r}")
        if device != "cpu" and cls is GranularSimulation:
            return object.__new__(GranularSimulation._devices[device])
        return object.__new__(cls)

    def __init__(
        self,
        world: Any,
        *,
        positions: ArrayLike,
        velocities: ArrayLike | None = None,
        radius: ArrayLike | float = DEFAULT_RADIUS,
        contacts: ContactLaw | None = None,
        wall_contacts: ContactLaw | None = None,
        density: float = 1.0,
        timestep: float = 1 / 30,
        gravity: ArrayLike = (0.0, -1.0),
        substeps_per_contact: float = DEFAULT_SUBSTEPS_PER_CONTACT,
        substep: float | None = None,
        skin: float | None = None,
        periodic_x: ArrayLike | None = None,
        chunks: int | None = None,
        device: str = "cpu",
    ) -> None:
        p = _points(positions, "positions")
        n = p.shape[0]
        if n < 1:
            raise ValueError("positions must hold at least one disc, got 0 rows")
        r = _radii(radius, n)
        v = np.zeros((n, 2)) if velocities is None else _points(velocities, "velocities", n)
        for name, law in (("contacts", contacts), ("wall_contacts", wall_contacts)):
            if law is not None and not isinstance(law, ContactLaw):
                raise TypeError(f"{name} must be a fastsdf.granular.ContactLaw, got {name}={law!r}")
        self.density = _positive(density, "density")
        gxy = _gravity(gravity)
        self.timestep = _positive(timestep, "timestep")
        spc = _real(substeps_per_contact, "substeps_per_contact")
        if not spc >= 10:
            raise ValueError(
                f"substeps_per_contact must be >= 10, "
                f"got substeps_per_contact={substeps_per_contact!r}"
            )
        if substep is not None:
            _positive(substep, "substep")
        if world is not None and not callable(world):
            raise TypeError(
                f"world must be a fastsdf Function or GridSDF (or None), got world={world!r}"
            )
        self.world = world
        self.moving = bool(getattr(world, "time_dependent", False))
        self.bulk = Bulk(self.density, float(gxy[0]), float(gxy[1]), *_period(periodic_x))
        # The laws as given (a stiffness of None is derived, see ContactLaw) and what sets the
        # substep: resolved now and again when gravity changes (set_gravity).
        self._laws_given = (ContactLaw() if contacts is None else contacts, wall_contacts)
        self._substeps_per_contact = spc
        self._substep_given = substep
        self._r_min = float(r.min())
        self._height = world_height(world, p, 2.0 * float(r.max()), gxy)
        self._resolve_laws()
        self.skin = _positive(0.4 * float(r.mean()) if skin is None else skin, "skin")
        self._cutoff = 2 * float(r.max()) + self.skin
        self.grains = Grains(
            p[:, 0].copy(), p[:, 1].copy(), v[:, 0].copy(), v[:, 1].copy(), np.zeros(n), r,
            *(np.zeros(n) for _ in range(6)),
        )  # fmt: skip
        self.ids = np.arange(n, dtype=np.int64)  # ids[slot]: the grain's index as given
        self._chunks = _chunk_count(chunks, n)
        self.grid: CellGrid | None = None
        # Contact memory (with history; see the module docs): springs per list entry (the
        # tangential stretch, and the rolling torque with rolling resistance), the list before
        # the last rebuild to carry them from, and the springs of each grain against the world.
        self._history = self.contact.history
        self._memory_cols = 2 if self.contact.rolling_friction > 0 else 1
        self._wall_idx = np.empty(0, np.int64)
        self._wall_d = np.empty(0)
        self.time = 0.0
        self.rebuilds = 0
        self.timings = {"rebuild": 0.0, "forces": 0.0, "walls": 0.0, "integrate": 0.0}
        self.wall_force = np.zeros(2)
        self._wall_sum = np.zeros(2)
        #: A compiled hook ``external(grains, density, t)`` adding forces to ``grains.fx,
        #: fy`` after the contact forces of every force pass (at the drifted positions and
        #: predicted velocities), or None.
        self.external: Any = None
        self._start_engine()
        warn_starting_state(self)

    def _start_engine(self) -> None:
        """The engine's workspace, the first neighbour list and forces (compiling the kernels
        on first use). The CUDA engine (:mod:`fastsdf.granular.cuda`) has its own."""
        n = self.ids.shape[0]
        self._x_ref = np.empty(n, np.float32)  # float32 suffices for the skin test (below)
        self._y_ref = np.empty(n, np.float32)
        self._double_buffer()
        self._push = np.empty((2, 0))
        self._no_world = Near(*(np.empty(0, t) for t in (np.int64, *[np.float64] * 4)))
        self._nbr_start = np.zeros(n + 1, np.int64)
        self._nbr: np.ndarray | None = None
        self._chunk_max = np.zeros(self._chunks)
        self._counts = np.empty((0, 0), np.int32)
        self._cell_start = np.empty(0, np.int64)
        self._spring = np.zeros((0, self._memory_cols))
        self._old_spring = np.zeros((0, self._memory_cols))
        self._old_start = np.zeros(n + 1 if self._history else 0, np.int64)
        self._old_nbr: np.ndarray | None = None
        wall_cols = 2 if self.wall_contact.rolling_friction > 0 else 1
        self._wall_spring = np.zeros((wall_cols, n if self.wall_contact.history else 0))
        with compiling("the granular kernels"):
            self._rebuild()
            np.copyto(self.grains.px, self.grains.vx)
            np.copyto(self.grains.py, self.grains.vy)
            self._forces(self._wall_sum, 0.0)
            # the first substep compiles the integration pass and the fused substep
            kick_drift(
                self.grains, 0.0, 0.0, self.density, self._x_ref, self._y_ref, self._chunk_max
            )
            self._pass(self._no_world, 0.0, 0.0, 0)
        self.wall_force = self._wall_sum.copy()

    #: The fields of :class:`Grains` that substep_pass double-buffers.
    _BUFFERED = ("x", "y", "px", "py", "pomega")

    def _double_buffer(self) -> None:
        """Hold the grains' positions and predicted velocities as the rows of a (5, n) block
        and give them a second block, :attr:`_spare` (see substep_pass): the grains and the
        spare swap after each pass. A rebuild runs between passes, when the spare is free,
        and sorts in its rows (:meth:`_workspace`)."""
        g = self.grains
        n = g.x.shape[0]
        now, spare = np.empty((5, n)), np.empty((5, n))
        for row, k in enumerate(self._BUFFERED):
            now[row] = getattr(g, k)
        self.grains = g._replace(**{k: now[row] for row, k in enumerate(self._BUFFERED)})
        self._spare = g._replace(**{k: spare[row] for row, k in enumerate(self._BUFFERED)})

    def _resolve_laws(self) -> None:
        """The contact laws (a stiffness of None derived from the grains, gravity and the
        world's height, see :class:`ContactLaw`), the lightest contact's duration and the
        substep."""
        gx, gy = self.bulk.gravity_x, self.bulk.gravity_y
        g = math.hypot(gx, gy) or STANDARD_GRAVITY
        contact, wall = self._laws_given

        def resolved(law: ContactLaw, name: str) -> ContactLaw:
            if law.stiffness is None:
                law = law._replace(stiffness=derived_stiffness(self.density, g, self._height))
            return check_contact_law(law, name)

        self.contact = resolved(contact, "contacts")
        self.wall_contact = self.contact if wall is None else resolved(wall, "wall_contacts")
        m_min = self.density * math.pi * self._r_min**2
        self.contact_time = min(
            contact_time(m_min / 2, self.contact),
            contact_time(m_min, self.wall_contact) if self.world is not None else math.inf,
        )
        if self._substep_given is None:
            target = self.contact_time / self._substeps_per_contact
        else:
            target = float(self._substep_given)
        self.substeps_per_frame = max(1, math.ceil(self.timestep / target - 1e-9))
        self.substep = self.timestep / self.substeps_per_frame

    def set_gravity(self, gravity: ArrayLike) -> None:
        """Change gravity (length / s**2) from now on: a derived stiffness and the substep
        follow it, and the forces are evaluated again at the current state."""
        gxy = _gravity(gravity)
        self.bulk = self.bulk._replace(gravity_x=float(gxy[0]), gravity_y=float(gxy[1]))
        self._resolve_laws()
        self._restart()

    def set_state(
        self,
        positions: ArrayLike | None = None,
        velocities: ArrayLike | None = None,
        angular_velocities: ArrayLike | None = None,
        radius: ArrayLike | None = None,
    ) -> None:
        """Replace the given fields, ``positions`` and ``velocities`` (n, 2),
        ``angular_velocities`` and ``radius`` (n,) (in the grains' given numbering; ``None``
        keeps a field) and continue from there:
        the neighbour list is rebuilt and the forces evaluated at the new state (a changed
        radius also changes the lightest contact, hence the substep)."""
        g = self.grains
        n = self.ids.shape[0]
        slots = self.ids
        if positions is not None:
            pos = _points(positions, "positions", n)
            g.x[:] = pos[slots, 0]
            g.y[:] = pos[slots, 1]
        if velocities is not None:
            vel = _points(velocities, "velocities", n)
            g.vx[:] = vel[slots, 0]
            g.vy[:] = vel[slots, 1]
        if angular_velocities is not None:
            w = np.asarray(angular_velocities, dtype=np.float64)
            if w.shape != (n,) or not np.all(np.isfinite(w)):
                raise ValueError(f"angular_velocities must be {n} finite numbers")
            g.omega[:] = w[slots]
        if radius is not None:
            r = _radii(radius, n)
            g.radius[:] = r[slots]
            self._r_min = float(r.min())
            self._cutoff = 2 * float(r.max()) + self.skin
            self._resolve_laws()
        self._restart()
        if positions is not None or radius is not None:
            warn_starting_state(self)

    def _restart(self) -> None:
        """Continue from the current positions and velocities as from a fresh start: rebuild
        the list, predict with the current velocities and evaluate the forces."""
        self._rebuild()
        np.copyto(self.grains.px, self.grains.vx)
        np.copyto(self.grains.py, self.grains.vy)
        np.copyto(self.grains.pomega, self.grains.omega)
        wall_sum = np.zeros(2)
        self._forces(wall_sum, 0.0)
        self.wall_force = wall_sum

    def __getstate__(self) -> dict:
        # The external force hook is rebound by its owner (it may live in a generated module).
        state = self.__dict__.copy()
        state["external"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._double_buffer()  # (a pickle keeps the rows, not their blocks)

    # -- neighbour search -----------------------------------------------------------------
    def _workspace(self, ncells: int) -> tuple:
        """``(keys, perm, counts, cell_start)`` of a rebuild over ``ncells`` cells, in the
        spare block's rows 1-4 (row 0 is the reorder's scratch) where they fit, else in
        arrays of their own (kept, grown by a quarter)."""
        n = self.ids.shape[0]
        chunks = min(self._chunks, 4)  # rows of per-chunk counts: bounded memory
        size = ncells + ncells // 4
        block = self._spare.x.base
        assert block is not None and block.shape == (5, n)
        free = block[1:].reshape(-1).view(np.int32)  # 8 n int32
        if 2 * n + 2 * (size + 1) + chunks * size <= free.shape[0]:
            start = free[2 * n : 2 * n + 2 * (size + 1)].view(np.int64)
            counts = free[2 * n + 2 * (size + 1) :][: chunks * size].reshape(chunks, size)
            return free[:n], free[n : 2 * n], counts, start
        if self._counts.shape[0] != chunks or self._counts.shape[1] < ncells:
            self._counts = np.empty((chunks, size), np.int32)
            self._cell_start = np.empty(size + 1, np.int64)
        return free[:n], free[n : 2 * n], self._counts, self._cell_start

    def _rebuild(self) -> None:
        t0 = _time.perf_counter()
        g = self.grains
        grid = make_grid(g.x, g.y, self._cutoff, self.bulk.period_x0, self.bulk.period)
        ncells = grid.ncx * grid.ncy
        keys, perm, counts, cell_start = self._workspace(ncells)
        cell_keys(g.x, g.y, grid, keys)
        counting_sort(keys, ncells, counts, perm, cell_start)
        carried = tuple(self._wall_spring) if self._wall_spring.shape[1] else ()
        permute((*g, self.ids, keys, *carried), perm, self._spare.x)
        if self._history:  # the current list becomes the old one, the old one's memory reused
            self._old_start, self._nbr_start = self._nbr_start, self._old_start
            self._old_nbr, self._nbr = self._nbr, self._old_nbr
            self._old_spring, self._spring = self._spring, self._old_spring
        cells = SortedGrains(g.x, g.y, g.radius, keys, cell_start, self.skin)
        self._nbr = build_verlet(cells, grid, self._chunks, self._nbr_start, self._nbr)
        self.grid = grid
        if self._history:
            if self._spring.shape[0] < self._nbr.shape[0]:
                self._spring = np.empty((self._nbr.shape[0], self._memory_cols))
            if self._old_nbr is None:
                self._spring[:] = 0.0
            else:
                # (first called at the first rebuild of a run, after the constructor's)
                with compiling_first("the granular kernels' contact memory", carry_springs):
                    carry_springs(
                        perm,
                        self._old_start,
                        self._old_nbr,
                        self._old_spring,
                        self._nbr_start,
                        self._nbr,
                        self._spring,
                    )
        np.copyto(self._x_ref, g.x)
        np.copyto(self._y_ref, g.y)
        # float32 references round by up to 2**-24 of the largest coordinate, per axis
        self._ref_margin = 2.5e-7 * max(float(np.abs(g.x).max()), float(np.abs(g.y).max()))
        if self.world is not None and not self.moving:
            d = np.asarray(self.world(g.x, g.y)).reshape(-1)
            self._wall_idx = np.flatnonzero(~(d - g.radius >= self.skin))  # NaN: keep
            if self._wall_spring.shape[1]:  # grains far from the world forget their springs
                listed = np.zeros(g.x.shape[0], np.bool_)
                listed[self._wall_idx] = True
                self._wall_spring[:, ~listed] = 0.0
        self.rebuilds += 1
        self.timings["rebuild"] += _time.perf_counter() - t0

    # -- forces ------------------------------------------------------------------------------
    def _query_world(self) -> Near:
        """The grains the force pass asks the world about and the world there."""
        g = self.grains
        if self.moving:
            idx = np.arange(g.x.shape[0])
            d, grad, dddt = self.world(
                g.x, g.y, compute_gradient=True, time_derivative=True, t=self.time
            )
            gn = np.hypot(grad[:, 0], grad[:, 1])
            with np.errstate(divide="ignore", invalid="ignore"):
                vn = np.where(gn > 0, -dddt / gn, 0.0)
        else:
            idx = self._wall_idx
            d, grad = self.world(g.x[idx], g.y[idx], compute_gradient=True)
            vn = np.zeros(idx.shape[0])
        d = np.ascontiguousarray(d, dtype=np.float64).reshape(-1)
        grad = np.asarray(grad, dtype=np.float64).reshape(-1, 2)
        return Near(idx, d, np.ascontiguousarray(grad[:, 0]), np.ascontiguousarray(grad[:, 1]), vn)

    def _forces(self, wall_sum: np.ndarray, dt: float) -> None:
        t0 = _time.perf_counter()
        pair_forces(
            self.grains,
            self._nbr_start,
            self._nbr,
            self._spring if self._history else None,
            self._chunks,
            self.contact,
            self.bulk,
            dt,
        )
        if self.external is not None:
            self.external(self.grains, self.density, self.time)
        t1 = _time.perf_counter()
        self.timings["forces"] += t1 - t0
        if self.world is not None:
            near = self._query_world()
            # (called with no grain near too: compiled with the engine's first forces)
            fx, fy = wall_forces(
                self.grains,
                near,
                self._wall_spring if self.wall_contact.history else None,
                self.wall_contact,
                self.bulk,
                dt,
            )
            wall_sum[0] += fx
            wall_sum[1] += fy
            self._wall_d = near.d
            self._wall_last = near.idx
            self.timings["walls"] += _time.perf_counter() - t1

    # -- time stepping ----------------------------------------------------------------------
    def run(self, frames: int = 1) -> None:
        """Advance ``frames`` frames of ``timestep`` seconds (``substeps_per_frame`` substeps
        each). :attr:`wall_force` becomes the mean force the world exerted on the grains over
        the last frame.

        A run expected to take longer than :data:`fastsdf.notice.PROGRESS_AFTER_S` shows its
        progress and the time left on stderr; a frame of more than :data:`SUBSTEPS_WARNING`
        substeps (and :data:`SUBSTEPS_WARNING_WORK` grain-substeps) is warned about (a
        :class:`SubstepWarning`, once per simulation) with its cause and remedies."""
        if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 0:
            raise ValueError(f"frames must be an int >= 0, got frames={frames!r}")
        frames = int(frames)
        if not frames:
            return
        self._warn_substeps()
        per_frame = self.substeps_per_frame
        n = self.grains.x.shape[0]
        every = max(1, _PROGRESS_WORK // n)
        what = f"{n:,} grains, run({frames}) at {per_frame:,} substeps per frame"
        with RunProgress(frames, what, "frames") as bar:
            for k in range(frames):
                self._tick = (lambda s, k=k: bar.update(k + s / per_frame), every)
                try:
                    self.advance(per_frame)
                finally:
                    self._tick = None
                bar.update(k + 1)

    #: While :meth:`run` steps: ``(tick(substeps_done), every)``, called every ``every``
    #: substeps of a frame (its progress).
    _tick: tuple[Callable[[int], None], int] | None = None

    def _warn_substeps(self) -> None:
        """Warn once, with the cause and the remedies, when a frame takes more than
        :data:`SUBSTEPS_WARNING` substeps and :data:`SUBSTEPS_WARNING_WORK` grain-substeps."""
        per_frame = self.substeps_per_frame
        work = per_frame * self.grains.x.shape[0]
        if per_frame <= SUBSTEPS_WARNING or work < SUBSTEPS_WARNING_WORK:
            return
        if getattr(self, "_warned_substeps", False):
            return
        self._warned_substeps = True
        head = (
            f"{per_frame:,} substeps per frame of {self.timestep:.4g} s ({work:,} "
            f"grain-substeps per frame): "
        )
        if self._substep_given is not None:
            warn_caller(
                head + f"the substep given, {self.substep:.3g} s, is that short (the lightest "
                f"contact lasts {self.contact_time:.3g} s). Fewer substeps: a longer substep, "
                f"or substep=None (the contact's time / substeps_per_contact).",
                SubstepWarning,
            )
            return
        m = self.density * math.pi * self._r_min**2
        pair = contact_time(m / 2, self.contact)
        against_world = self.contact_time < pair  # the world's law is the stiffer one
        law = self.wall_contact if against_world else self.contact
        given = self._laws_given[1] if against_world else self._laws_given[0]
        name = "wall_contact" if against_world else "contact"
        k = float(law.stiffness)  # type: ignore[arg-type]
        who = (
            f"a grain of radius {self._r_min:.3g} and mass {m:.3g} against the world"
            if against_world
            else f"two grains of radius {self._r_min:.3g} and mass {m:.3g}"
        )
        if given is None or given.stiffness is None:
            why = (
                f"stiffness {k:.4g}, derived for a column of grains as tall as the world, "
                f"H = {self._height:.3g} (a grid's bounds, else the grains' extent at the "
                f"start; see ContactLaw), to overlap 1% of a diameter at its bottom"
            )
            softer = f"a {name} law with a stiffness below the derived one"
        else:
            why = f"stiffness {k:.4g}, as given"
            softer = f"a softer {name} law"
        warn_caller(
            head + f"the lightest contact, {who} ({why}), lasts t_c = pi sqrt(m_eff / k) = "
            f"{self.contact_time:.3g} s and is resolved by {self._substeps_per_contact:g} "
            f"substeps. Fewer substeps: {softer} (ContactLaw(stiffness=...): the substeps "
            f"shrink as the square root of the stiffness, resting overlaps grow as its "
            f"inverse); bigger grains (t_c grows with the radius); or fewer "
            f"substeps_per_contact (>= 10; less accurate restitution). A shorter timestep "
            f"gives fewer substeps per frame, not fewer per second.",
            SubstepWarning,
        )

    def advance(self, substeps: int) -> None:
        """Advance ``substeps`` substeps of :attr:`substep` seconds (velocities end
        synchronized with positions). Fewer grains than :data:`PARALLEL_MIN_GRAINS` run on one
        thread. Above, with :attr:`tune_threads`, the run is timed in segments on numba's
        threads (``numba.get_num_threads()``) and on one, and the faster runs (see
        :mod:`fastsdf.granular.threads`): the results are the same bits on any number of
        threads."""
        threads = numba.get_num_threads()
        n = self.grains.x.shape[0]
        self._threads_now = None
        if threads > 1 and n < PARALLEL_MIN_GRAINS:
            numba.set_num_threads(1)
        elif threads > 1 and self.tune_threads:
            tuner = self._tuner
            if tuner is None or tuner.most != threads or tuner.grains != n:
                tuner = self._tuner = ThreadTuner(threads, n)
            self._threads_now = tuner
            tuner.start()
        try:
            self._advance(substeps)
        finally:
            if self._threads_now is not None:
                self._threads_now.stop()
                self._threads_now = None
            numba.set_num_threads(threads)

    #: Whether :meth:`advance` chooses its threads by measuring (see
    #: :mod:`fastsdf.granular.threads`); ``False``: numba's threads, as set.
    tune_threads: bool = True
    _tuner: ThreadTuner | None = None
    #: The tuner of the running :meth:`advance`, told of every substep (None: threads fixed).
    _threads_now: ThreadTuner | None = None

    def _advance(self, substeps: int) -> None:
        if self.external is not None:  # a compiled hook runs between the passes
            self._advance_staged(substeps)
            return
        if not substeps:
            return
        dt = self.substep
        # The reference positions are float32: allow for their rounding in the skin test.
        lim = max(0.5 * self.skin - self._ref_margin, 0.0) ** 2
        wall_sum = np.zeros(2)
        tick, every = self._tick or (None, 0)
        t0 = _time.perf_counter()
        kick_drift(self.grains, 0.0, dt, self.density, self._x_ref, self._y_ref, self._chunk_max)
        self.timings["integrate"] += _time.perf_counter() - t0
        for s in range(substeps):
            if tick is not None and s and s % every == 0:
                tick(s)
            self.time += dt
            if not self._chunk_max.max() <= lim:  # (drifted by the last pass)
                self._rebuild()
                lim = max(0.5 * self.skin - self._ref_margin, 0.0) ** 2
            t0 = _time.perf_counter()
            near = self._query_world() if self.world is not None else self._no_world
            t1 = _time.perf_counter()
            fx, fy = self._pass(near, dt, 0.0 if s == substeps - 1 else dt, self._chunks)
            wall_sum[0] += fx
            wall_sum[1] += fy
            self.timings["walls"] += t1 - t0
            self.timings["forces"] += _time.perf_counter() - t1
            if self._threads_now is not None:
                self._threads_now.substep_done()
        self.wall_force = wall_sum / substeps

    def _pass(self, near: Near, dt: float, dt_next: float, chunks: int) -> tuple:
        """One :func:`~fastsdf.granular.kernels.substep_pass` (the forces at the current
        positions, then the drift of ``dt_next``) over ``chunks`` chunks (0: none, which only
        compiles it), the grains and the spare buffer swapped after; returns the world's
        force."""
        if self._push.shape[1] != near.idx.shape[0]:
            self._push = np.empty((2, near.idx.shape[0]))
        step = Substep(
            dt, 0.5 * dt, dt_next, chunks, self._x_ref, self._y_ref, self._chunk_max, self._push
        )
        out = self._spare
        fx, fy = substep_pass(
            self.grains,
            out,
            self._nbr_start,
            self._nbr,
            self._spring if self._history else None,
            near,
            self._wall_spring if self.wall_contact.history else None,
            (self.contact, self.wall_contact),
            self.bulk,
            step,
        )
        if chunks:
            self._spare, self.grains = self.grains, out
        return fx, fy

    def _advance_staged(self, substeps: int) -> None:
        """:meth:`_advance` in three passes per substep, with :attr:`external` between the
        contact forces and the world's (the same arithmetic as the fused substep)."""
        g = self.grains
        dt = self.substep
        # The reference positions are float32: allow for their rounding in the skin test.
        lim = max(0.5 * self.skin - self._ref_margin, 0.0) ** 2
        wall_sum = np.zeros(2)
        tick, every = self._tick or (None, 0)
        for s in range(substeps):
            if tick is not None and s and s % every == 0:
                tick(s)
            t0 = _time.perf_counter()
            kick_drift(
                g,
                0.0 if s == 0 else 0.5 * dt,
                dt,
                self.density,
                self._x_ref,
                self._y_ref,
                self._chunk_max,
            )
            self.timings["integrate"] += _time.perf_counter() - t0
            self.time += dt
            big = self._chunk_max.max()
            if not big <= lim:
                self._rebuild()
                lim = max(0.5 * self.skin - self._ref_margin, 0.0) ** 2
            self._forces(wall_sum, dt)
            if self._threads_now is not None:
                self._threads_now.substep_done()
        if substeps:
            t0 = _time.perf_counter()
            kick_drift(g, 0.5 * dt, 0.0, self.density, self._x_ref, self._y_ref, self._chunk_max)
            self.timings["integrate"] += _time.perf_counter() - t0
            self.wall_force = wall_sum / substeps

    # -- observables ------------------------------------------------------------------------
    def _in_order(self, *columns: np.ndarray) -> np.ndarray:
        out = np.empty((self.ids.shape[0], len(columns)))
        for k, c in enumerate(columns):
            out[self.ids, k] = c
        return out

    @property
    def positions(self) -> np.ndarray:
        """Centres (n, 2), in the order the grains were given (a copy)."""
        return self._in_order(self.grains.x, self.grains.y)

    @property
    def velocities(self) -> np.ndarray:
        """Velocities (n, 2), in the order the grains were given (a copy)."""
        return self._in_order(self.grains.vx, self.grains.vy)

    @property
    def angular_velocities(self) -> np.ndarray:
        """Angular velocities (n,) in rad/s, counter-clockwise, in the given order."""
        return self._in_order(self.grains.omega)[:, 0]

    @property
    def radius(self) -> np.ndarray:
        """Radii (n,), in the given order."""
        return self._in_order(self.grains.radius)[:, 0]

    @property
    def masses(self) -> np.ndarray:
        """Masses (n,), in the given order."""
        return self.density * np.pi * self.radius**2

    def energy(self) -> dict[str, float]:
        """Energies at the current time, by part: ``kinetic`` (translational, ``m |v|**2 /
        2``), ``rotational`` (``m R**2 w**2 / 4``), ``potential`` (gravitational, ``-m g .
        x``, zero at the origin), the springs of the grain-grain and grain-world contacts:
        ``normal_springs`` (``k_n delta**2 / 2``), ``tangential_springs`` (``k_t s**2 / 2``,
        with history) and ``rolling_springs`` (``M**2 / (2 k_r)``, with rolling resistance),
        and their sum, ``total``. Without dashpots, and while no contact slips or parts, the
        total is conserved (see ``docs/granular_models.md``)."""
        g = self.grains
        kinetic, rotational, potential = kinetic_energy(g, self.bulk)
        memory = self._spring if self._history else None
        normal, tangential, rolling, _ = pair_energy(
            g, self._nbr_start, self._nbr, memory, self.contact, self.bulk
        )
        if self.world is not None:
            near = self._query_world()
            wall_memory = self._wall_spring if self.wall_contact.history else None
            wn, wt, wr, _ = wall_energy(g, near.idx, near.d, wall_memory, self.wall_contact)
            normal, tangential, rolling = normal + wn, tangential + wt, rolling + wr
        parts = {
            "kinetic": float(kinetic),
            "rotational": float(rotational),
            "potential": float(potential),
            "normal_springs": float(normal),
            "tangential_springs": float(tangential),
            "rolling_springs": float(rolling),
        }
        parts["total"] = sum(parts.values())
        return parts

    def contact_counts(self) -> tuple[int, int]:
        """``(pairs, walls)``: the grain-grain pairs in overlap now, and the grains
        overlapping the world."""
        _, _, _, pairs = pair_energy(
            self.grains, self._nbr_start, self._nbr, None, self.contact, self.bulk
        )
        walls = 0
        if self.world is not None:
            near = self._query_world()
            walls = wall_energy(self.grains, near.idx, near.d, None, self.wall_contact)[3]
        return int(pairs), int(walls)

    def neighbour_pairs(self) -> np.ndarray:
        """The pairs ``(i, j)``, ``i < j``, of the current Verlet list, in the grains' given
        numbering, as an (m, 2) int64 array sorted by rows."""
        assert self._nbr is not None
        pairs = self.ids[list_pairs(self._nbr_start, self._nbr)]
        pairs.sort(axis=1)
        return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]

    def tangential_springs(self) -> tuple:
        """The contacts' tangential springs (``history=True``): ``(pairs, stretch)``, the
        listed pairs ``(a, b)``, ``a < b``, in the grains' given numbering (an (m, 2) int64
        array sorted by rows) and each one's spring stretch ``s`` (length; 0 out of contact):
        the spring of either grain is ``s (-n_y, n_x)`` with ``n`` the unit normal pointing to
        that grain, so the same number from both sides; and the springs against the world,
        (n,) in the given order. Each pair once."""
        if not self._history:
            raise ValueError("tangential_springs needs contacts=ContactLaw(..., history=True)")
        assert self._nbr is not None
        n = self.ids.shape[0]
        start = self._nbr_start
        i = np.repeat(np.arange(n), np.diff(start))
        j = (self._nbr[: start[n]] & INDEX_MASK).astype(np.int64)
        s = self._spring[: start[n], 0].copy()
        a, b = self.ids[i], self.ids[j]
        pairs = np.stack([np.minimum(a, b), np.maximum(a, b)], 1)
        order = np.lexsort((pairs[:, 1], pairs[:, 0]))
        pairs, s = pairs[order], s[order]
        first = np.ones(len(pairs), np.bool_)
        first[1:] = np.any(pairs[1:] != pairs[:-1], axis=1)
        wall = np.zeros(n)
        if self._wall_spring.shape[1]:
            wall[self.ids] = self._wall_spring[0]
        return pairs[first], s[first], wall

    def contacts_per_grain(self) -> float:
        """Mean number of grain-grain contacts (overlaps) per grain, each counted at both
        grains."""
        return 2.0 * self.contact_counts()[0] / self.grains.x.shape[0]

    def memory_per_grain(self) -> float:
        """Bytes held per grain: state, neighbour list, sort and cell arrays, scratch."""
        arrays = [
            *self.grains,
            *self._spare,
            self.ids,
            self._x_ref,
            self._y_ref,
            self._nbr_start,
            self._counts,
            self._cell_start,
            self._spring,
            self._old_spring,
            self._old_start,
            self._wall_spring,
        ]
        if self._old_nbr is not None:
            arrays.append(self._old_nbr)
        if self._nbr is not None:
            arrays.append(self._nbr)
        owners = {id(a): a for a in (a if a.base is None else a.base for a in arrays)}
        return sum(a.nbytes for a in owners.values()) / self.grains.x.shape[0]

    def __repr__(self) -> str:
        return (
            f"GranularSimulation(n={self.grains.x.shape[0]}, substep={self.substep:.3g}, "
            f"substeps_per_frame={self.substeps_per_frame}, time={self.time:.6g})"
        )


show_init_signature(GranularSimulation)
