"""The simulation: :class:`ParticleSimulation` (physics only: state, clock, forces, the world and
the choice of compiled step; the notebook's ``reset(ax)``/``update(ax)`` and
:func:`create_animation` delegate their drawing to :mod:`fastsdf.viz.render`)."""

from __future__ import annotations

import inspect
import math
import numbers
import os
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numba
import numpy as np
from numpy.typing import ArrayLike

from fastsdf.backends import HEADER_SIZE, plan_header
from fastsdf.device import to_host
from fastsdf.function import Function
from fastsdf.introspect import show_init_signature
from fastsdf.notice import RunProgress, compiling
from fastsdf.particles import kernels as _kernels
from fastsdf.particles.checkpoint import load_simulation, register_simulation, save_simulation
from fastsdf.particles.forces import Gravity, fuse, python_forces
from fastsdf.particles.kernels import NO_EXT, Budget, Physics, State
from fastsdf.particles.state import Particles, _invalid_state_error, _real, _unit_interval
from fastsdf.particles.world import (
    _NO_PARAMS,
    _NO_TABLE,
    SimulationParams,
    _exact_address,
    _exactness,
    _grid_margin,
    _is_distance_bound,
    _is_grid,
    _kernel_module,
    wall_speed_table,
)

__all__ = ["ParticleSimulation", "create_animation", "PARALLEL_MIN_PARTICLES", "DEFAULT_BLOCK"]

# The step's constants live in fastsdf.particles.kernels.constants; documented here:
#: TRACE_FRACTION: the tunnelling check sweeps a particle whose step is longer than this fraction
#: of its radius (and whose end point is not provably clear); it is also the march's shortest
#: step. MIN_STEP: shortest march step, as a fraction of the step's length, when touching a
#: surface the particle leaves or slides along (matters for particles of radius 0).
#: CONTACT_TOL: a march stops at a contact when ``d - r`` is below this fraction of the step's
#: length. MAX_MARCH: at most this many SDF queries per swept segment; a particle that runs out
#: stops where it is (a point the march has shown to be free), losing the rest of that step's
#: displacement. MAX_BOUNCES: at most this many contacts per step; at the last one the particle
#: stops at the contact.
#: Fewer particles than this run on one thread (thread start-up costs more than it saves).
PARALLEL_MIN_PARTICLES = 4096
# Threads that run slices of the particles through a kernel (which releases the GIL); made on
# first use, grown when numba's thread count is raised.
_POOL: list = [None]
#: A call of at least this many particle-steps (about 0.05 s) runs numba's parallel entry point.
LONG_CALL = 1 << 22
# (kernel, state dtype, Python forces) combinations a kernel has been compiled for.
_READY: set = set()


def _pool(workers: int) -> ThreadPoolExecutor:
    pool = _POOL[0]
    if pool is None or pool._max_workers < workers:
        pool = _POOL[0] = ThreadPoolExecutor(workers, thread_name_prefix="fastsdf-step")
    return pool


#: Particles per block in :meth:`ParticleSimulation.run` (block state fits in the L1/L2 cache).
DEFAULT_BLOCK = 512
#: A run of at least this many particle-steps (a second or so of compiled work) goes in
#: pieces, so that it can show its progress once it is seen to take longer than
#: :data:`fastsdf.notice.PROGRESS_AFTER_S` (the same bits: particles do not interact).
PROGRESS_MIN_PARTICLE_STEPS = 50_000_000
#: The first piece of such a run, in particle-steps; later pieces last about
#: ``_PROGRESS_PIECE_S`` seconds each at the rate seen.
_PROGRESS_FIRST_PIECE = 10_000_000
_PROGRESS_PIECE_S = 0.5

_INTEGRATORS = ("symplectic", "euler")


class _DefaultCount(int):
    """The default ``n`` (100), told apart from an ``n`` given: with ``positions`` the count
    comes from them."""


_DEFAULT_N = _DefaultCount(100)
_COLLISIONS = ("approaching", "notebook")
_DEVICES = ("cpu", "cuda")


# ---------------------------------------------------------------------------------------------
# The simulation.


def _recorded(sim: Any, steps: Any, record: Any) -> bool:
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
    kind = "grains" if hasattr(sim, "engine") else "particles"
    with RunProgress(int(steps), f"{sim.n:,} {kind}, run({steps}, record=...)", "steps"):
        record.run(sim, int(steps))  # (the runs it makes report to this progress)
    return True


@register_simulation
class ParticleSimulation:
    """Particles moving under forces and colliding with an SDF (the notebook's interface).

    Parameters
    ----------
    world : fastsdf SDF (:class:`fastsdf.function.Function`) or GridSDF
        The world; negative inside matter. A GridSDF is sampled bilinearly (its ``sampler``),
        falling back to its exact SDF outside its bounds in ``mode='exact'``. An exact SDF (or
        fallback) with many operands in loops over tables is pruned as ``f(x, y)`` is (see
        :mod:`fastsdf.backends.prune`): each query evaluates only the rows of its tile's lists, with
        the same bits for hard unions and intersections.
    n : int, default 100
        Number of particles (> 0); with ``positions``, their count.
    timestep : float, default 1/30
        Seconds per step (finite, > 0).
    positions, velocities, radius : array (n, 2), array (n, 2), float or array (n,)
        The start, in place of the notebook's random blob (see :meth:`reset`): each one given
        replaces that field of the blob; placed particles start at rest unless given
        ``velocities``; with ``radius`` the masses are ``density pi r**2`` (without it, the
        notebook's sizes: ``m ~ U(1, 10)``, ``r = 0.01 m``). :meth:`reset` returns to them.
        None given: the blob, exactly as before.
    contacts : :class:`fastsdf.granular.ContactLaw` or None
        ``None`` (default): particles meet only the world. A contact law: the particles are
        grains that also collide with each other (soft-sphere DEM): the simulation is then a
        :class:`fastsdf.particles.grains.GrainSimulation` (same names and tools; its step is
        the granular engine, see there); ``positions`` are required, ``radius`` defaults to
        0.02, and ``ContactLaw()`` derives its stiffness from the grains. The parameters from
        ``integrator`` on are the particles' own and do not apply to grains.
    wall_contacts : :class:`fastsdf.granular.ContactLaw` or None
        Grains only: the grain-world law (default: ``contacts``).
    substeps_per_contact, substep, skin, periodic_x, chunks : optional
        Grains only: the granular engine's (see :class:`fastsdf.granular.GranularSimulation`);
        ``substeps_per_contact=None`` is the engine's default, 40.
    density : float, default 1
        Mass per unit area, for the masses of particles given a ``radius`` and of grains.
    seed : int, numpy Generator or None
        Seed of the random initial state; the same seed gives the same state and trajectory.
        ``None`` draws fresh randomness at every :meth:`reset`.
    integrator : {'symplectic', 'euler'}
        Semi-implicit Euler (default) or the notebook's explicit Euler; see the module docs.
    collision : {'approaching', 'notebook'}
        Velocity response only while approaching (``v . n < 0``, House & Keyser; default) or
        whenever in contact (the notebook).
    prevent_tunnelling : bool, default True
        Sweep fast particles along their step (see the module docs). Off: the notebook's
        end-point test only, and a fast particle can pass through a wall thinner than its step.
    dtype : numpy float dtype, default float64
        Storage of the state (float64 or float32); arithmetic is float64 either way.
    rest_speed : float, default 0 (off)
        Resting contact: a particle that meets a surface (without a sweep) while moving slower
        than this (length/s), pushed into it by its acceleration, with a tangential
        acceleration at most ``cf`` times the normal one (static friction: a surface tilted
        less than ``atan(cf)`` under gravity), stays where it is with zero velocity instead of
        bouncing (the default contact keeps a micro-bounce of normal speed
        ``cr g dt / (1 + cr)`` and creeps down any tilt, so it never rests exactly). A resting
        particle's state is then a fixed point of the step: within one :meth:`run` call it
        sleeps (its steps are skipped, exactly) in a static world with no user force. It
        changes the physics (rest starts below ``rest_speed`` and a particle rests within
        about ``rest_speed dt + |g| dt**2`` of the surface), so it is off by default; try
        ``rest_speed`` of one to a few ``|g| dt``.
    cr, cf : float in [0, 1], default 0.6 and 0.3
        Restitution and friction given to every particle by :meth:`reset` (the original
        library's defaults); per-particle values can be written to ``p['cr']``, ``p['cf']``.
    lipschitz : float or None
        A bound on ``|grad d|`` for the tunnelling check and the free-flight query skipping:
        ``None`` takes 1 for an SDF and ``sqrt(2)`` for a GridSDF (the bound of a bilinear
        interpolant of a 1-Lipschitz function). That is right for SDFs whose ``exactness`` is
        ``'exact'`` or ``'bound'`` (every primitive, transform, hard and smooth blend of the
        library); for a world not known to be a distance bound (``exactness == 'none'``, or a
        bare :class:`fastsdf.function.Function`) a ``RuntimeWarning`` says so, queries are never
        skipped, and you should pass the bound.
    block : int or None
        Particles per block in :meth:`run` (tuning; ``None``: :data:`DEFAULT_BLOCK`).
    wall_speed : float or None
        For a moving world (built with :data:`fastsdf.t`): a bound on ``|dd/dt|`` (length/s,
        how fast any surface moves toward a particle), used by the tunnelling sweep and the
        free-flight budgets, everywhere. ``None`` estimates it at every :meth:`run` call, per
        region: 1.5 times the largest ``|dd/dt|`` sampled on a 64x64 grid over the particles
        (and at up to 4096 of them) at the call's step times, widened by the walls' travel,
        so particles far from every moving wall skip queries as in a static world; pass it
        when walls accelerate or move faster than those samples show.
    device : {'cpu', 'cuda'}, default 'cpu'
        ``'cuda'``: the particles live and step on a CUDA GPU (numba-cuda, the ``cuda``
        extra), one thread per particle through all steps of a :meth:`run` call (see
        :mod:`fastsdf.particles.cuda`): ``sim.p['x']`` is a device array (CuPy and PyTorch take
        it without a copy), ``sim.host('x')`` a NumPy copy; :meth:`run` does not wait for the
        GPU and :meth:`check` reports frozen particles. The step is the CPU's (the tunnelling
        sweep included; no query skipping, which changes no result), float64 state, with
        Gravity, Drag, FieldForce and ``@njit`` forces, in a dense GridSDF or an exact SDF
        (with parameters; moving too, without the sweep: pass ``prevent_tunnelling=False``);
        other worlds and options raise an error naming them.

    Moving worlds and parameters: a world built with runtime parameters
    (:func:`fastsdf.Param`) is stepped with the values in ``sim.params`` (change them between
    steps: no recompile), and one built with time :data:`fastsdf.t` is evaluated at the
    simulation's own time, so its walls move; the response uses the velocity relative to the
    wall (``v . n`` against the surface's normal speed ``-dd/dt / |grad d|``), so a piston
    pushes particles and a rising floor lifts them. The wall's tangential velocity is not
    known from an SDF (friction acts as if the wall did not slide along itself). A GridSDF
    samples a scene that does not move: give a moving scene as it is.

    Kernels (all give the same results, bit for bit; the choice is automatic, per call): a
    GridSDF world with stored gradients (the default ``gradient='stored'``, any grid dtype,
    either ``mode``) and float64 state, without ``rest_speed`` and Python force generators,
    runs the block kernel (``simd_ser``, :mod:`fastsdf.particles.kernels.block`): 64
    particles at a time held in scratch rows through all steps of a :meth:`run` call, each
    step in passes that the
    compiler turns into 4-wide vector code (forces, fused ``@njit`` forces and
    :class:`FieldForce` included; integration; the grid cell; the response), a short scalar
    pass loading the cells' grid values, and a scalar fix-up only for particles that need a
    tunnelling sweep or a query outside the grid. Everything else runs particle by particle:
    exact-SDF and moving worlds, ``gradient='fd'`` and band grids, float32 state, resting
    contact, Python forces (the ``plain`` kernel without skipping and tunnelling check, the
    general one otherwise).

    Attributes
    ----------
    p : :class:`Particles`
        The state: fields ``x, v, m, r, cr, cf``; write it freely between steps.
    t : float
        Simulated time in seconds since :meth:`reset`.
    force_generators : list
        :class:`Gravity` and :class:`Drag` instances (fused, fast) and Python callables
        ``(p, t) -> (n, 2)`` forces (evaluated with NumPy before each step: the slow path).
    """

    # Attributes set in __init__ (declared for the type checker: reset() reads them).
    n: int
    seed: Any
    integrator: str
    collision: str
    prevent_tunnelling: bool
    dtype: Any
    cr: float
    cf: float
    block: int | None
    force_generators: list
    t: float
    _ext: Any
    _flags: Any
    _wall: Any
    # The state: Particles, or fastsdf.particles.cuda.DeviceParticles with device='cuda' (the
    # class docstring's attributes describe it).
    p: Any
    #: The GPU step (:class:`fastsdf.particles.cuda.CudaStep`), None on the CPU (class
    #: defaults: members of the family that do not run this constructor are on the CPU).
    _gpu: Any = None
    device: str = "cpu"

    #: The member of the family that grains with contacts are (set by the subclass that
    #: declares ``class ...(ParticleSimulation, steps_contacts=True)``: the grains' module).
    _contact_member: type | None = None

    def __init_subclass__(cls, steps_contacts: bool = False, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        show_init_signature(cls)
        if steps_contacts:
            ParticleSimulation._contact_member = cls

    def __new__(cls, *args: Any, **kwargs: Any) -> ParticleSimulation:
        # Grains (contacts=ContactLaw(...)) are the member that steps with the granular engine.
        # (The signature shown for the class is __init__'s: see _show_init_signature.)
        member = ParticleSimulation._contact_member
        if cls is ParticleSimulation and kwargs.get("contacts") is not None and member:
            particles_only = sorted(set(kwargs) - set(inspect.signature(member).parameters))
            if particles_only:
                raise TypeError(
                    f"{particles_only[0]}= does not apply to grains (contacts=...): their "
                    f"restitution and friction are the contact law's (ContactLaw(restitution="
                    f"..., friction=...)), and they step by the granular engine's substeps"
                )
            return object.__new__(member)
        return object.__new__(cls)

    def __init__(
        self,
        world: Any,
        n: int = _DEFAULT_N,
        timestep: float = 1 / 30,
        *,
        positions: ArrayLike | None = None,
        velocities: ArrayLike | None = None,
        radius: ArrayLike | float | None = None,
        contacts: Any = None,
        wall_contacts: Any = None,
        substeps_per_contact: float | None = None,
        substep: float | None = None,
        skin: float | None = None,
        periodic_x: ArrayLike | None = None,
        chunks: int | None = None,
        density: float = 1.0,
        seed: Any = None,
        integrator: str = "symplectic",
        collision: str = "approaching",
        prevent_tunnelling: bool = True,
        dtype: Any = np.float64,
        cr: float = 0.6,
        cf: float = 0.3,
        lipschitz: float | None = None,
        block: int | None = None,
        wall_speed: float | None = None,
        rest_speed: float = 0.0,
        device: str = "cpu",
    ) -> None:
        grains_only = {
            "wall_contacts": wall_contacts,
            "substeps_per_contact": substeps_per_contact,
            "substep": substep,
            "skin": skin,
            "periodic_x": periodic_x,
            "chunks": chunks,
        }
        for name, value in grains_only.items():
            if value is not None:
                raise TypeError(
                    f"{name}= applies to grains only (contacts=ContactLaw(...)), got "
                    f"{name}={value!r} without contacts"
                )
        if device not in _DEVICES:
            raise ValueError(f"device must be one of {_DEVICES}, got device={device!r}")
        #: Where the particles are stepped: 'cpu' or 'cuda' (see :mod:`fastsdf.particles.cuda`).
        self.device = device
        rest = _real(rest_speed, "rest_speed")
        if not (math.isfinite(rest) and rest >= 0.0):
            raise ValueError(f"rest_speed must be finite and >= 0, got rest_speed={rest_speed!r}")
        #: Resting contact below this speed (length/s); 0: off (see the class docs).
        self.rest_speed = rest
        if wall_speed is not None:
            w = _real(wall_speed, "wall_speed")
            if not (math.isfinite(w) and w >= 0.0):
                raise ValueError(
                    f"wall_speed must be finite and >= 0, got wall_speed={wall_speed!r}"
                )
        self._wall_speed_arg = wall_speed
        self._given = _start_state(n, positions, velocities, radius, density)
        if self._given is not None and self._given[0] is not None:
            n = self._given[0].shape[0]
        if isinstance(n, float) and math.isfinite(n) and n == int(n):
            n = int(n)  # n=1e5, as the command line accepts it
        if isinstance(n, (bool, np.bool_)) or not isinstance(n, numbers.Integral):
            raise TypeError(f"n must be an integer, got n={n!r}")
        if n <= 0:
            raise ValueError(f"n must be > 0, got n={n!r}")
        dt = _real(timestep, "timestep")
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(f"timestep must be finite and > 0, got timestep={timestep!r}")
        if integrator not in _INTEGRATORS:
            raise ValueError(
                f"integrator must be one of {_INTEGRATORS}, got integrator={integrator!r}"
            )
        if collision not in _COLLISIONS:
            raise ValueError(f"collision must be one of {_COLLISIONS}, got collision={collision!r}")
        dtype = np.dtype(dtype)
        if dtype not in (np.dtype(np.float64), np.dtype(np.float32)):
            raise ValueError(f"dtype must be float64 or float32, got dtype={dtype}")
        if lipschitz is not None:
            lip = _real(lipschitz, "lipschitz")
            if not (math.isfinite(lip) and lip > 0.0):
                raise ValueError(f"lipschitz must be finite and > 0, got lipschitz={lipschitz!r}")
        if block is not None and (
            isinstance(block, (bool, np.bool_))
            or not isinstance(block, numbers.Integral)
            or block <= 0
        ):
            raise ValueError(f"block must be a positive integer or None, got block={block!r}")
        self.n = int(n)
        self.dt = dt
        self._lipschitz_arg = lipschitz
        self.seed = seed
        self.integrator = integrator
        self.collision = collision
        self.prevent_tunnelling = bool(prevent_tunnelling)
        self.dtype = dtype
        self.cr = _unit_interval(cr, "cr")
        self.cf = _unit_interval(cf, "cf")
        self.sdf = world
        self.block = None if block is None else int(block)
        self.force_generators = []
        self.t = 0.0
        self._ext = None
        self._flags = None
        self._wall = None
        self._gpu = None
        if device == "cuda":
            self._gpu = _cuda_step(self)
        self.reset()

    @property
    def sdf(self) -> Any:
        """The world (SDF or GridSDF). Assigning another one rebinds the compiled step."""
        return self._sdf

    @sdf.setter
    def sdf(self, f):
        module, data, keep = _kernel_module(f)  # raises TypeError for anything else
        self._sdf = f
        self._module, self._data, self._keep = module, data, keep
        self._kernels = {(): (module, data, keep, ())}
        # A grid in mode 'exact' binds its exact fallback when a particle first needs it; a
        # pruned SDF (see _prunes) binds its C function at once. Both read the plan header.
        pruned = isinstance(f, Function) and not _is_grid(f) and len(data) == 2
        self._hdr = np.zeros(HEADER_SIZE)
        self._hdr_plan = None  # the plan the header points into (kept alive here)
        self._exact_ptr = None if (_is_grid(f) and f.mode == "exact") or pruned else 0
        if self._exact_ptr is None and (pruned or getattr(f, "bounds", None) is None):
            self._bind_fallback()
        self._parametric = isinstance(f, Function) and not _is_grid(f) and f.compiled.parametric
        self._moving = self._parametric and f.time_dependent
        #: Values of the world's runtime parameters (see :class:`SimulationParams`).
        self.params = SimulationParams(f) if self._parametric else SimulationParams(_NO_PARAMS)
        self._margin = _grid_margin(f)
        #: The Lipschitz bound the tunnelling check and the free-flight budget use.
        self.lipschitz = (
            float(self._lipschitz_arg)
            if self._lipschitz_arg is not None
            else (math.sqrt(2.0) if _is_grid(f) else 1.0)
        )
        # Skipping queries is exact only if the bound holds; without a known bound (an SDF
        # whose exactness is 'none', or a bare expression) every step queries.
        known = self._lipschitz_arg is not None or _is_distance_bound(f)
        self._skip = known
        if not known and self.prevent_tunnelling:
            warnings.warn(
                f"the world's value is not known to be a distance bound (exactness "
                f"{_exactness(f)!r}): the tunnelling check assumes |grad d| <= "
                f"{self.lipschitz:g}; pass lipschitz= (a bound on |grad d|) if that is wrong",
                RuntimeWarning,
                stacklevel=3,
            )
        if getattr(self, "_gpu", None) is not None:
            self._gpu = _cuda_step(self)  # the new world's query data on the device

    @property
    def world(self) -> Any:
        """The world (the same as :attr:`sdf`)."""
        return self.sdf

    # -- notebook interface ----------------------------------------------------------------
    def reset(self, ax: Any = None) -> tuple:
        """Draw a fresh random state (the notebook's distribution) and set ``t = 0``.

        ``x ~ N([0, 1.5], 0.05 I)``, ``v ~ N(0, 0.1 I)``, ``m ~ U(1, 10)``, ``r = 0.01 m``,
        ``cr``, ``cf`` from the constructor; the fields given to the constructor
        (``positions``, ``velocities``, ``radius``) replace their draws. With an ``ax`` (the
        notebook's interface), also
        (re)draws the particles there with :func:`fastsdf.viz.render.draw_particles`: discs of the
        particles' radii in data units for up to 5000 particles, a density image above; returns
        the drawn artists (for matplotlib's blitting). To animate a simulation without resetting
        it, use :func:`fastsdf.viz.render.animate`.
        """
        rng = (
            self.seed
            if isinstance(self.seed, np.random.Generator)
            else np.random.default_rng(self.seed)
        )
        p = Particles(self.n, self.dtype)
        p["x"] = rng.normal([0.0, 1.5], math.sqrt(0.05), size=(self.n, 2))
        p["v"] = rng.normal([0.0, 0.0], math.sqrt(0.1), size=(self.n, 2))
        p["m"] = rng.uniform(1.0, 10.0, size=self.n)
        p["r"] = p["m"] * 0.01
        p["cr"] = self.cr
        p["cf"] = self.cf
        given = getattr(self, "_given", None)
        if given is not None:
            pos, vel, rad, density = given
            if pos is not None:
                p["x"] = pos
                p["v"] = 0.0  # particles placed start at rest unless given velocities
            if vel is not None:
                p["v"] = vel
            if rad is not None:
                p["r"] = rad
                p["m"] = density * math.pi * np.asarray(p["r"], dtype=np.float64) ** 2
        self.p = p
        if getattr(self, "_gpu", None) is not None:
            from fastsdf.particles.cuda import DeviceParticles

            self.p = DeviceParticles(p)  # copied to the device once
        self.t = 0.0
        self._wall = None
        return self._draw(ax, new=True)

    def update(self, ax: Any = None, use_wall_time: bool = False) -> tuple:
        """Advance one frame and refresh the drawing; returns the drawables.

        One step of ``timestep`` seconds; with ``use_wall_time``, as many fixed steps as fit in
        the wall-clock time since the previous update (at least one, at most 10), so the
        animation keeps real time while the physics keeps its fixed step.
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
        """Advance the simulation by one step of ``timestep`` seconds."""
        self.run(1)

    # -- the compiled loop -------------------------------------------------------------------
    def _fused_params(self):
        return fuse(self.force_generators)

    def _kernel(self, user):
        """The compiled step for these fused user forces (generated on first use)."""
        key = tuple(id(u) for u in user)
        entry = self._kernels.get(key)
        if entry is None or entry[3] != user:
            module, data, keep = _kernel_module(self._sdf, user)
            entry = self._kernels[key] = (module, data, keep, user)
        return entry[0], self._bind(entry[1])

    def _bind(self, data):
        """The query data with the exact fallback's address, once compiled (0 before), and
        that of the plan header (the last entry)."""
        ptr = self._exact_ptr
        return data if not ptr else (ptr[0],) + data[1:-1] + (int(self._hdr.ctypes.data),)

    def _bind_fallback(self):
        """Compile (or load) the grid's exact fallback (a pruned SDF's C function) and bind it
        from now on."""
        if self._exact_ptr is None:
            f = self._sdf
            with compiling("the exact SDF behind the grid, for particles near its edge"):
                self._exact_ptr = _exact_address(f.exact if _is_grid(f) else f)
            self._data = self._bind(self._data)

    def _update_plan(self, x: np.ndarray, steps: int) -> None:
        """Point the plan header at a pruning plan over the particles that query the exact SDF
        per point (all of them for an SDF world, those outside the grid for a grid's exact
        fallback), or at none where pruning does not pay (see ``CompiledSDF.pruned_plan``).
        Particles that leave the plan's rectangle during the steps use every row."""
        if not self._exact_ptr:
            return
        f = self._sdf
        exact = f.exact if _is_grid(f) else f
        if not exact.compiled.groups:
            return
        xs = np.asarray(x[:, 0], dtype=np.float64)
        ys = np.asarray(x[:, 1], dtype=np.float64)
        if _is_grid(f):
            (x0, x1), (y0, y1) = f.bounds
            out = ~((xs >= x0) & (xs <= x1) & (ys >= y0) & (ys <= y1))
            if not out.any():
                return  # nobody outside now: keep the header as it is
            xs, ys = xs[out], ys[out]
        plan = exact.compiled.pruned_plan(
            xs, ys, None, getattr(exact, "prune_tol", None), count=xs.shape[0] * max(1, int(steps))
        )
        if plan is not self._hdr_plan:
            plan_header(plan, self._hdr)
            self._hdr_plan = plan

    def _python_forces(self, gens: Any) -> np.ndarray:
        if self._ext is None or self._ext.shape != (self.n, 2):
            self._ext = np.empty((self.n, 2))
        return python_forces(gens, self.p, self.t, self._ext)

    def run(self, steps: int = 1, record: Any = None) -> None:
        """Advance ``steps`` steps (``steps * timestep`` seconds) in compiled code.

        ``record``: a recorder such as :class:`fastsdf.io.TrajectoryRecorder`, which then runs
        the steps in blocks and writes a frame every ``record.every`` steps (its ``run(sim,
        steps)``).

        With only fused forces (:class:`Gravity`, :class:`Drag`, numba ``@njit`` forces) this
        is one compiled call for all steps (a long run, from
        :data:`PROGRESS_MIN_PARTICLE_STEPS`, goes in pieces with the same results); with Python
        force generators, one generator evaluation and one compiled step per step. A run seen
        to take longer than :data:`fastsdf.notice.PROGRESS_AFTER_S` shows its progress and the
        time left on stderr.

        Errors. A particle whose state cannot be stepped (a non-finite position or velocity, a
        mass that is not > 0 where the mass is used, a negative or non-finite radius, ``cr`` or
        ``cf`` outside [0, 1] at a contact), or whose step would produce a non-finite state
        (e.g. a timestep so large that the motion overflows), is frozen at its last valid state
        and never carries a non-finite value. The other particles complete every step, ``t``
        advances by ``steps * timestep`` (clock and state agree), and then a ``ValueError``
        names the first such particle and what was wrong.
        """
        if _recorded(self, steps, record):
            return
        if steps == 0:
            return
        if self._gpu is not None:
            self._run_cuda(int(steps))
            return
        self._check_state_shape()
        ax, ay, drag, python, user = self._fused_params()
        module, data = self._kernel(user)
        what = f"{self.n:,} particles, run({steps})"
        if not python and self.n * steps < PROGRESS_MIN_PARTICLE_STEPS:
            with RunProgress(steps, what, "steps") as bar:  # (shown only inside a recorded run)
                bad = self._launch(module, data, int(steps), ax, ay, drag, None)
                self.t += steps * self.dt
                bar.update(steps)
        elif not python:  # in pieces, with progress
            bad = done = 0
            piece = max(1, _PROGRESS_FIRST_PIECE // self.n)
            with RunProgress(steps, what, "steps") as bar:
                while done < steps:
                    k = min(piece, steps - done)
                    t0 = time.perf_counter()
                    bad += self._launch(module, data, k, ax, ay, drag, None)
                    per_step = (time.perf_counter() - t0) / k
                    self.t += k * self.dt
                    done += k
                    bar.update(done)
                    piece = max(1, int(_PROGRESS_PIECE_S / max(per_step, 1e-9)))
                    module, data = self._kernel(user)  # (the fallback may have been bound)
        else:
            bad = 0
            with RunProgress(steps, what, "steps") as bar:
                for i in range(int(steps)):
                    ext = self._python_forces(python)
                    bad += self._launch(module, data, 1, ax, ay, drag, ext)
                    self.t += self.dt
                    bar.update(i + 1)
                    # (a step may have bound the grid's exact fallback: the next uses its
                    # address)
                    module, data = self._kernel(user)
        if bad:
            raise self._frozen_error(bad, int(steps))

    def _run_cuda(self, steps: int) -> None:
        """:meth:`run` on the GPU (:mod:`fastsdf.particles.cuda`): launched, not waited for."""
        from fastsdf.particles.cuda import DeviceParticles

        ax, ay, drag, python, user = self._fused_params()
        if python:
            raise TypeError(
                f"device='cuda' cannot run the Python force generator "
                f"{getattr(python[0], '__name__', python[0])!r} (it runs on the CPU only): "
                "write it as a numba @njit function (x, y, vx, vy, m, t) -> (fx, fy), or "
                "use device='cpu'"
            )
        if isinstance(self.p, Particles):
            self.p = DeviceParticles(self.p)  # a host state assigned to sim.p
        elif not isinstance(self.p, DeviceParticles) or len(self.p) != self.n:
            raise TypeError(
                f"sim.p must hold the {self.n} particles of this simulation (DeviceParticles "
                f"or Particles), got {self.p!r}"
            )
        self._gpu.run(
            self.p,
            steps,
            self.t,
            self.dt,
            (ax, ay, drag, user),
            self.integrator,
            self.collision,
            self.params.as_tuple(),
            self.lipschitz,
            self.prevent_tunnelling,
        )
        self.t += steps * self.dt

    def check(self) -> None:
        """With ``device='cuda'``: wait for the GPU and raise the :class:`ValueError` of
        :meth:`run` if particles were frozen since the last check (on the GPU, :meth:`run`
        does not wait for the steps to finish). Nothing to do on the CPU (:meth:`run` raises)."""
        if self._gpu is None:
            return
        count, flags = self._gpu.frozen()
        steps, self._gpu.steps_unchecked = self._gpu.steps_unchecked, 0
        if count:
            p, self.p = self.p, self.p.host()
            self._flags = flags
            try:
                err = self._frozen_error(count, steps)
            finally:
                self.p, self._flags = p, None
            raise err

    def host(self, name: str | None = None) -> Any:
        """A NumPy copy of the state's field ``name`` (``'x'``, ``'v'``, ``'m'``, ...), or of
        the whole state (a :class:`Particles`) without a name; with ``device='cuda'`` copied
        from the device (which waits for the GPU)."""
        if name is None:
            return self.p.host() if self._gpu is not None else self.p.copy()
        return np.array(to_host(self.p[name]))

    def save(self, path: str | os.PathLike, *, allow_pickle: bool = False) -> str:
        """Write the simulation to ``path`` (``.npz``) so that :meth:`load` continues it bit for
        bit: arrays and data only (the world's expression graph or grid, parameters, forces by
        name and numbers, the random generator's state), so loading runs no code from the file.
        A force or world that is not data (a numba ``@njit`` or Python force, a world class of
        your own) is a ``ValueError`` naming it, unless ``allow_pickle=True`` (then it is stored
        pickled and :meth:`load` needs ``allow_pickle=True`` too); see
        :func:`fastsdf.particles.checkpoint.save_simulation`. Returns the path. With
        ``device='cuda'`` the state's host copy is written (and :meth:`load` puts it back on
        the device)."""
        if self._gpu is None:
            return save_simulation(self, path, allow_pickle=allow_pickle)
        on_device, self.p = self.p, self.p.host()
        try:
            return save_simulation(self, path, allow_pickle=allow_pickle)
        finally:
            self.p = on_device

    @classmethod
    def load(cls, path: str | os.PathLike, *, allow_pickle: bool = False) -> ParticleSimulation:
        """The simulation saved by :meth:`save` at ``path``, continuing bit for bit. Runs no
        code from the file; a file holding pickled objects (saved with ``allow_pickle=True``, or
        by an older fastsdf) is refused with a ``ValueError`` unless ``allow_pickle=True``,
        which unpickles them (running code named in the file: only for files you trust)."""
        sim = load_simulation(path, allow_pickle=allow_pickle)
        if not isinstance(sim, cls):
            raise TypeError(f"{path!r} holds a {type(sim).__name__}, not a {cls.__name__}")
        return sim

    @property
    def dt(self) -> float:
        """The timestep in seconds (finite, > 0); assigning checks the value."""
        return self._dt

    @dt.setter
    def dt(self, value):
        dt = _real(value, "timestep")
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(f"timestep must be finite and > 0, got timestep={value!r}")
        self._dt = dt

    def _check_state_shape(self):
        p = self.p
        if not isinstance(p, Particles):
            raise TypeError(f"sim.p must be a Particles object, got {type(p).__name__}")
        if len(p) != self.n or p.dtype != self.dtype:
            raise ValueError(
                f"sim.p holds {len(p)} particles of {p.dtype}; this simulation "
                f"has n={self.n} of {self.dtype}"
            )

    def _launch(self, module, data, steps, ax, ay, drag, ext):
        p = self.p
        n = self.n
        use_ext = ext is not None
        if ext is None:
            ext = NO_EXT
        if self._flags is None or self._flags.shape[0] != n:
            self._flags = np.zeros(n, dtype=np.int32)
        if self._parametric:
            data = self._scene_data(steps)
        a = p._arrays
        check_all = p._dirty
        state = State(*(a[k] for k in Particles.FIELDS), ext, self._flags, check_all)
        physics = Physics(
            dt=self.dt,
            t0=self.t,
            ax=ax,
            ay=ay,
            drag=drag,
            use_m=use_ext or drag != 0.0,
            use_ext=use_ext,
            explicit=self.integrator == "euler",
            always=self.collision == "notebook",
            rest=float(self.rest_speed),
        )
        budget = Budget(
            trace=self.prevent_tunnelling,
            lip=self.lipschitz,
            margin=self._margin,
            eps=float(np.finfo(self.dtype).eps),
            skip=self._skip,
        )
        self._update_plan(a["x"], steps)
        bad = self._call(module, data, steps, state, physics, budget)
        if bad and self._exact_ptr is None:
            bad = self._resume(module, steps, state, physics, budget, bad)
        if check_all and not bad:
            p._dirty = False
        return bad

    def _call(self, module, data, steps, state, physics, budget):
        """Run the call's kernel on ``numba.get_num_threads()`` threads from
        ``PARALLEL_MIN_PARTICLES`` particles on: a short call as one slice of whole blocks per
        thread, a long one (``LONG_CALL`` particle-steps) through the kernel's parallel entry
        point. Returns the frozen count."""
        kernel = self._pick_kernel(module, state, physics, budget)
        block = self.block or DEFAULT_BLOCK
        n = state.X.shape[0]
        threads = numba.get_num_threads() if n >= PARALLEL_MIN_PARTICLES else 1
        if threads > 1 and n * steps >= LONG_CALL:
            # numba's parallel entry point: a few percent faster on long calls, and twice
            # the compile time, so compiled only when a long call first needs it
            kernel = getattr(module, kernel.py_func.__name__[: -len("_ser")] + "_par")
            if kernel.signatures:
                return kernel(data, state, physics, budget, steps, block)
            with compiling("the particle step kernel for long calls"):
                return kernel(data, state, physics, budget, steps, block)
        if not kernel.signatures:  # compile (or load) it here, with a notice, before threads
            with compiling("the particle step kernel"):
                kernel(data, _part(state, 0, 0), physics, budget, steps, block)
        elif threads > 1 and (kernel, state.X.dtype, state.EXT.shape[0] > 0) not in _READY:
            # (types new to it, e.g. float32, compile here, not in two threads at once)
            kernel(data, _part(state, 0, 0), physics, budget, steps, block)
        _READY.add((kernel, state.X.dtype, state.EXT.shape[0] > 0))
        if threads <= 1:
            return kernel(data, state, physics, budget, steps, block)
        # one slice of whole blocks per thread, the first on this thread
        blocks = -(-n // block)
        per = -(-blocks // threads) * block

        def run(lo: int) -> int:
            return kernel(data, _part(state, lo, lo + per), physics, budget, steps, block)

        rest = [_pool(threads).submit(run, lo) for lo in range(per, n, per)]
        return run(0) + sum(job.result() for job in rest)

    def _pick_kernel(self, module, state, physics, budget):
        """The kernel of ``module`` for a call: the block kernel of a static grid world
        (``simd_*``: float64 state, no resting contact, no Python forces), else the
        particle-by-particle kernel without skipping and tunnelling check (``plain_*``), else
        the general one (``run_*``). All give the same results."""
        simd = (
            getattr(self, "_simd", True)
            and module.GRID_SIMD
            and not module.MOVING
            and physics.rest == 0.0
            and not physics.use_ext
            and state.X.dtype == np.float64
        )
        plain = not (budget.trace or budget.skip or physics.rest > 0.0 or module.MOVING)
        if simd and budget.skip:
            return module.simd_ser
        if simd:
            return module.simd_plain_ser
        if plain:
            return module.plain_ser
        return module.run_ser

    def _resume(self, module, steps, state, physics, budget, bad):
        """Particles that stopped near the grid's edge before its exact fallback was bound
        (FLAG_RESUME + step): bind it, run each the rest of its steps from where it stopped
        (particles are independent, so the result is that of an uninterrupted call)."""
        flags = self._flags
        idx = np.flatnonzero(flags >= _kernels.FLAG_RESUME)
        if not idx.size:
            return bad
        self._bind_fallback()
        self._update_plan(self.p._arrays["x"], steps)
        data = next(self._bind(e[1]) for e in self._kernels.values() if e[0] is module)
        at = flags[idx] - _kernels.FLAG_RESUME
        flags[idx] = 0
        bad -= idx.size
        ext = state.EXT
        arrays = self.p._arrays
        for j in np.unique(at):
            sel = idx[at == j]
            sub = State(
                *(np.ascontiguousarray(arrays[k][sel]) for k in Particles.FIELDS),
                ext[sel] if ext.shape[0] else ext,
                np.zeros(sel.size, dtype=np.int32),
                False,
            )
            sub_physics = physics._replace(t0=physics.t0 + int(j) * physics.dt)
            bad += self._call(module, data, steps - int(j), sub, sub_physics, budget)
            arrays["x"][sel] = sub.X
            arrays["v"][sel] = sub.V
            flags[sel] = sub.FLAGS
        return bad

    def _frozen_error(self, count: int, steps: int) -> ValueError:
        """The error after a call that froze ``count`` particles (clears the flags)."""
        flags = self._flags
        idx = np.flatnonzero(flags)
        first, why = int(idx[0]), int(flags[idx[0]])
        flags[idx] = 0
        p = self.p
        if why == _kernels.FLAG_NONFINITE:
            x = np.asarray(p["x"][first], np.float64).tolist()
            v = np.asarray(p["v"][first], np.float64).tolist()
            what = (
                f"a step of particle {first} produced a non-finite state (timestep="
                f"{self.dt!r}; last finite state x={x}, v={v}); it was frozen there"
            )
        elif why == _kernels.FLAG_COEFF:
            what = (
                f"invalid particle state: p['cr'][{first}] = {float(p['cr'][first])!r} or "
                f"p['cf'][{first}] = {float(p['cf'][first])!r} is not in [0, 1] (found at "
                f"a contact); the particle was frozen there"
            )
        else:
            err = _invalid_state_error(p, count)
            what = str(err).split(" (", 1)[0] + "; the particle was left unchanged"
        return ValueError(
            f"{what}. {len(idx)} particle(s) frozen in all; the others completed "
            f"the {steps} step(s) and sim.t = {self.t!r} includes them"
        )

    def _scene_data(self, steps: int) -> tuple:
        """Query data of a parametric world: (t, wall speed bound, table geometry and the
        per-region table, *parameters); see ``_PARAMS_AT``."""
        prm = self.params.as_tuple()
        wall = 0.0
        table = (0.0, 0.0, 1.0, _NO_TABLE)
        if self._moving and steps:
            if self._wall_speed_arg is None:
                wall, table = self._wall_speed_table(steps, prm)
            else:
                wall = self._wall_speed_arg
        self._wall_table = table  # kept alive: the kernel borrows the array
        return (float(self.t), float(wall)) + table + prm

    def _wall_speed_table(self, steps: int, prm: tuple) -> tuple:
        """See :func:`fastsdf.particles.world.wall_speed_table`."""
        return wall_speed_table(
            self._sdf, self.p["x"], float(np.max(self.p["r"])), self.t, self.dt, steps, prm
        )

    # -- diagnostics -------------------------------------------------------------------------
    def kinetic_energy(self) -> float:
        """Total kinetic energy ``sum(m |v|**2 / 2)``."""
        v = np.asarray(self.p["v"], dtype=np.float64)
        return float(np.sum(0.5 * np.asarray(self.p["m"], dtype=np.float64) * (v * v).sum(1)))

    def potential_energy(self) -> float:
        """Total potential energy of the :class:`Gravity` generators (zero at the origin);
        other forces have no potential here."""
        return float(
            sum(
                np.sum(g.potential(self.p)) for g in self.force_generators if isinstance(g, Gravity)
            )
        )

    def energy(self) -> dict[str, float]:
        """Energies by part, the same names for every member of the family (grains:
        :meth:`fastsdf.granular.GranularSimulation.energy`): ``kinetic``, ``rotational``,
        ``potential`` (of the :class:`Gravity` generators, zero at the origin),
        ``normal_springs``, ``tangential_springs``, ``rolling_springs`` and their sum,
        ``total``. Particles do not turn and meet the world in instants, so here the rotation
        and the springs hold nothing: ``total`` is kinetic plus potential energy."""
        parts = {
            "kinetic": self.kinetic_energy(),
            "rotational": 0.0,
            "potential": self.potential_energy(),
            "normal_springs": 0.0,
            "tangential_springs": 0.0,
            "rolling_springs": 0.0,
        }
        parts["total"] = sum(parts.values())
        return parts

    def query(self, x: ArrayLike, y: ArrayLike) -> tuple:
        """``(d, grad)`` of the world at points, exactly as the compiled step sees it (for a
        GridSDF: the bilinear samples, with its out-of-bounds rule)."""
        xs = np.ascontiguousarray(x, dtype=np.float64).reshape(-1)
        ys = np.ascontiguousarray(y, dtype=np.float64).reshape(-1)
        out = np.empty((xs.shape[0], 3))
        self._bind_fallback()
        self._update_plan(np.stack([xs, ys], axis=1), 1)
        self._module.query_many(
            self._scene_data(0) if self._parametric else self._data, xs, ys, out
        )
        return out[:, 0], out[:, 1:]

    def _draw(self, ax, new):
        # The notebook's reset(ax)/update(ax) draw; the drawing and its state live in render.
        if ax is None:
            return ()
        from fastsdf.viz.render import notebook_draw

        return notebook_draw(self, ax, new)

    def __getstate__(self) -> dict:
        # The world travels as its graph (and a grid's nodes), the state as arrays; the bound
        # kernel module and scratch buffers stay behind and are rebuilt on unpickling (the
        # simulation holds no drawing: that lives in fastsdf.viz.render).
        # (Everything the ``sdf`` setter sets is rebuilt; per-particle arrays are kept.)
        state = self.__dict__.copy()
        for key in (
            "_module",
            "_data",
            "_keep",
            "_kernels",
            "_ext",
            "_wall",
            "_wall_table",
            "_exact_ptr",
            "_flags",
            "_hdr",
            "_hdr_plan",
            "_gpu",
        ):
            state.pop(key, None)
        if self._gpu is not None and not isinstance(self.p, Particles):
            state["p"] = self.p.host()  # the device state travels as its host copy
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._ext = self._wall = self._flags = self._gpu = None
        self.__dict__.setdefault("device", "cpu")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # warned when first built
            self.sdf = state["_sdf"]
        if self.device == "cuda":
            from fastsdf.particles.cuda import DeviceParticles

            self._gpu = _cuda_step(self)
            self.p = DeviceParticles(self.p)
        # Assigning the world resets its parameters to their defaults: set the saved values.
        saved = state.get("params")
        if saved:
            self.params.update(dict(saved))

    def __repr__(self) -> str:
        return (
            f"ParticleSimulation(n={self.n}, timestep={self.dt!r}, t={self.t:.4g}, "
            f"integrator={self.integrator!r}, collision={self.collision!r}, "
            f"prevent_tunnelling={self.prevent_tunnelling}, dtype={self.dtype.name})"
        )


show_init_signature(ParticleSimulation)


def _cuda_step(sim: Any) -> Any:
    """The GPU step of ``sim`` (``device='cuda'``), or a clear error for what it lacks."""
    from fastsdf.particles.cuda import CudaStep

    if sim.dtype != np.dtype(np.float64):
        raise ValueError(f"device='cuda' steps float64 state only, got dtype={sim.dtype}")
    if sim.rest_speed > 0.0:
        raise NotImplementedError(
            "device='cuda' does not support resting contact (rest_speed > 0); use device='cpu'"
        )
    if sim.prevent_tunnelling and sim._moving:
        raise NotImplementedError(
            "device='cuda' does not run the tunnelling sweep in a moving world; pass "
            "prevent_tunnelling=False"
        )
    return CudaStep(sim._sdf)


def _start_state(
    n: Any, positions: Any, velocities: Any, radius: Any, density: Any
) -> tuple | None:
    """The start fields given in place of the notebook's blob, checked: ``(x, v, r,
    density)`` (None where not given), or None when none is given."""
    if positions is None and velocities is None and radius is None:
        return None
    pos = vel = rad = None
    count = None if positions is None else np.asarray(positions).shape[0]
    if positions is not None:
        pos = np.array(positions, dtype=np.float64)
        if pos.ndim != 2 or pos.shape[1] != 2 or pos.shape[0] < 1:
            raise ValueError(f"positions must have shape (n, 2), n >= 1, got shape {pos.shape}")
        if n is not _DEFAULT_N and n != pos.shape[0]:
            raise ValueError(f"n={n!r} does not match positions, which hold {pos.shape[0]} rows")
    if count is None:
        count = int(n)
    if not np.all(np.isfinite(pos if pos is not None else 0.0)):
        raise ValueError("positions must be finite")
    if velocities is not None:
        vel = np.array(velocities, dtype=np.float64)
        if vel.shape != (count, 2) or not np.all(np.isfinite(vel)):
            raise ValueError(
                f"velocities must be finite, of shape ({count}, 2), got shape {vel.shape}"
            )
    if radius is not None:
        rad = np.array(np.broadcast_to(np.asarray(radius, dtype=np.float64), (count,)))
        if not np.all(np.isfinite(rad) & (rad >= 0)):
            bad = int(np.flatnonzero(~(np.isfinite(rad) & (rad >= 0)))[0])
            raise ValueError(f"radius must be finite and >= 0, got radius[{bad}]={rad[bad]!r}")
    dens = _real(density, "density")
    if not (math.isfinite(dens) and dens > 0):
        raise ValueError(f"density must be finite and > 0, got density={density!r}")
    return pos, vel, rad, dens


def _part(state: State, lo: int, hi: int) -> State:
    """The particles ``lo..hi-1`` of ``state`` (views; Python forces sliced too)."""
    X, V, M, R, CR, CF, EXT, FLAGS, check_all = state
    return State(
        X[lo:hi],
        V[lo:hi],
        M[lo:hi],
        R[lo:hi],
        CR[lo:hi],
        CF[lo:hi],
        EXT[lo:hi] if EXT.shape[0] else EXT,
        FLAGS[lo:hi],
        check_all,
    )


def create_animation(
    fig: Any,
    ax: Any,
    sim: Any,
    frames: int = 300,
    repeat: bool = True,
    use_wall_time: bool = False,
    interval: float | None = None,
) -> Any:
    """A matplotlib ``FuncAnimation`` of ``sim`` on ``ax`` (the notebook's helper).

    Each frame calls ``sim.update(ax, use_wall_time)``; the animation's init (and every repeat)
    calls ``sim.reset(ax)``, which redraws a fresh random state. ``interval`` is the delay
    between frames in milliseconds (default: the simulation's timestep). Returns the animation
    (keep a reference to it; ``anim.to_html5_video()`` renders it in a notebook: an MP4 when
    ffmpeg is installed, matplotlib's JavaScript player (``to_jshtml``) otherwise). The
    drawing is :func:`fastsdf.viz.render.notebook_animation`'s.
    """
    from fastsdf.viz.render import notebook_animation

    return notebook_animation(
        fig, ax, sim, frames=frames, repeat=repeat, use_wall_time=use_wall_time, interval=interval
    )
