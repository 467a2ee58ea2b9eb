"""The simulation of particles that meet only the world: :class:`ParticleSimulation` (the
family's front door and its non-interacting member: state, clock, forces, settings; its fused
step is the engine it holds, :class:`fastsdf.particles.engine.ParticleEngine`; the notebook's
``reset(ax)``/``update(ax)`` and :func:`create_animation` delegate their drawing to
:mod:`fastsdf.viz.render`)."""

from __future__ import annotations

import inspect
import math
import numbers
import os
import time
import warnings
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from fastsdf.notice import RunProgress
from fastsdf.particles.engine import DEFAULT_BLOCK, PARALLEL_MIN_PARTICLES, ParticleEngine
from fastsdf.particles.family import DEFAULT_COUNT, Simulation
from fastsdf.particles.forces import FusedForces, Gravity, fuse, python_forces
from fastsdf.particles.kernels import Budget, Physics
from fastsdf.particles.kernels.constants import FLAG_COEFF, FLAG_NONFINITE
from fastsdf.particles.state import Particles, _invalid_state_error, _real, _unit_interval
from fastsdf.particles.world import SimulationParams, _exactness

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
#: (PARALLEL_MIN_PARTICLES: fewer particles run on one thread; DEFAULT_BLOCK: particles per
#: block of a call; see :mod:`fastsdf.particles.engine`.)

#: A run of at least this many particle-steps (a second or so of compiled work) goes in
#: pieces, so that it can show its progress once it is seen to take longer than
#: :data:`fastsdf.notice.PROGRESS_AFTER_S` (the same bits: particles do not interact).
PROGRESS_MIN_PARTICLE_STEPS = 50_000_000
#: The first piece of such a run, in particle-steps; later pieces last about
#: ``_PROGRESS_PIECE_S`` seconds each at the rate seen.
_PROGRESS_FIRST_PIECE = 10_000_000
_PROGRESS_PIECE_S = 0.5

_INTEGRATORS = ("symplectic", "euler")


_COLLISIONS = ("approaching", "notebook")
_DEVICES = ("cpu", "cuda")
#: Options only grains take (``contacts=ContactLaw(...)``).
_GRAIN_OPTIONS = (
    "wall_contacts",
    "substeps_per_contact",
    "substep",
    "skin",
    "periodic_x",
    "chunks",
)
#: Attributes of an earlier version's saved state that the engine now derives from the world.
_DERIVED = ("_parametric", "_moving", "_margin", "lipschitz", "_skip", "_module", "_data")


# ---------------------------------------------------------------------------------------------
# The simulation.


class ParticleSimulation(Simulation):
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
    runs the block kernel (the ``simd`` variant, :mod:`fastsdf.particles.kernels.block`): 64
    particles at a time held in scratch rows through all steps of a :meth:`run` call, each
    step in passes that the
    compiler turns into 4-wide vector code (forces, fused ``@njit`` forces and
    :class:`FieldForce` included; integration; the grid cell; the response), a short scalar
    pass loading the cells' grid values, and a scalar fix-up only for particles that need a
    tunnelling sweep or a query outside the grid. Everything else runs particle by particle:
    exact-SDF and moving worlds, ``gradient='fd'`` and band grids, float32 state, resting
    contact, Python forces (the plain variant without skipping and tunnelling check, the
    general one otherwise); see :mod:`fastsdf.particles.kernels`.

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
    engine: ParticleEngine
    _ext: Any
    # The state: Particles, or fastsdf.particles.cuda.DeviceParticles with device='cuda' (the
    # class docstring's attributes describe it).
    p: Any
    device: str = "cpu"

    #: The member of the family that grains with contacts are (see :meth:`_admit_grains`).
    _contact_member: type | None = None

    @classmethod
    def _admit_grains(cls, member: type) -> type:
        """Make ``member`` the family's simulation of grains (``contacts=...``): this class's
        constructor builds it, and it counts as a ParticleSimulation (``isinstance``) while it
        shares only the family's tools (:class:`fastsdf.particles.family.Simulation`), not
        this class's step."""
        cls.register(member)
        cls._contact_member = member
        return member

    def __new__(cls, *args: Any, **kwargs: Any) -> Any:
        # Grains (contacts=ContactLaw(...)) are the member that steps with the granular engine.
        # (The signature shown for the class is __init__'s: see show_init_signature.)
        member = ParticleSimulation._contact_member
        if cls is ParticleSimulation and kwargs.get("contacts") is not None and member:
            particles_only = sorted(set(kwargs) - set(inspect.signature(member).parameters))
            if particles_only:
                raise TypeError(
                    f"{particles_only[0]}= does not apply to grains (contacts=...): their "
                    f"restitution and friction are the contact law's (ContactLaw(restitution="
                    f"..., friction=...)), and they step by the granular engine's substeps"
                )
            return member(*args, **kwargs)  # (not a subclass: its __init__ runs here only)
        return super().__new__(cls)

    def __init__(
        self,
        world: Any,
        n: int = DEFAULT_COUNT,
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
        given = (wall_contacts, substeps_per_contact, substep, skin, periodic_x, chunks)
        for name, value in zip(_GRAIN_OPTIONS, given, strict=True):
            if value is not None:
                raise TypeError(
                    f"{name}= applies to grains only (contacts=ContactLaw(...)), got "
                    f"{name}={value!r} without contacts"
                )
        #: Where the particles are stepped: 'cpu' or 'cuda' (see :mod:`fastsdf.particles.cuda`).
        self.device = _choice(device, _DEVICES, "device")
        #: Resting contact below this speed (length/s); 0: off (see the class docs).
        self.rest_speed = _non_negative(rest_speed, "rest_speed")
        if wall_speed is not None:
            _non_negative(wall_speed, "wall_speed")
        self._wall_speed_arg = wall_speed
        self._given = _start_state(n, positions, velocities, radius, density)
        self.n = _count(n if self._given is None or self._given[0] is None else len(self._given[0]))
        self.dt = timestep
        _choice(integrator, _INTEGRATORS, "integrator")
        _choice(collision, _COLLISIONS, "collision")
        dtype = np.dtype(dtype)
        if dtype not in (np.dtype(np.float64), np.dtype(np.float32)):
            raise ValueError(f"dtype must be float64 or float32, got dtype={dtype}")
        if lipschitz is not None:
            lip = _real(lipschitz, "lipschitz")
            if not (math.isfinite(lip) and lip > 0.0):
                raise ValueError(f"lipschitz must be finite and > 0, got lipschitz={lipschitz!r}")
        block = _block_size(block)
        self._lipschitz_arg = lipschitz
        self.seed = seed
        self.integrator = integrator
        self.collision = collision
        self.prevent_tunnelling = bool(prevent_tunnelling)
        self.dtype = dtype
        self.cr = _unit_interval(cr, "cr")
        self.cf = _unit_interval(cf, "cf")
        self.sdf = world
        self.block = block
        self.force_generators = []
        self.t = 0.0
        self._ext = None
        self.reset()

    @property
    def sdf(self) -> Any:
        """The world (SDF or GridSDF). Assigning another one rebinds the compiled step."""
        return self._sdf

    @sdf.setter
    def sdf(self, f):
        engine = ParticleEngine(f, lipschitz=self._lipschitz_arg, wall_speed=self._wall_speed_arg)
        if not engine.skip and self.prevent_tunnelling:
            warnings.warn(
                f"the world's value is not known to be a distance bound (exactness "
                f"{_exactness(f)!r}): the tunnelling check assumes |grad d| <= "
                f"{engine.lipschitz:g}; pass lipschitz= (a bound on |grad d|) if that is wrong",
                RuntimeWarning,
                stacklevel=3,
            )
        if self.device == "cuda":
            _check_cuda(self, engine.moving)
            engine.use_device()  # the new world's query data on the device
        self._sdf = f
        #: The fused step of this world (see :class:`fastsdf.particles.engine.ParticleEngine`).
        self.engine = engine

    @property
    def params(self) -> SimulationParams:
        """Values of the world's runtime parameters (see :class:`SimulationParams`)."""
        return self.engine.params

    @property
    def lipschitz(self) -> float:
        """The Lipschitz bound the tunnelling check and the free-flight budget use."""
        return self.engine.lipschitz

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
        if self.engine.gpu is not None:
            from fastsdf.particles.cuda import DeviceParticles

            self.p = DeviceParticles(p)  # copied to the device once
        self.t = 0.0
        self._wall = None
        return self._draw(ax, new=True)

    # -- stepping ----------------------------------------------------------------------------
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
        super().run(steps, record)

    def _run(self, steps: int) -> None:
        if steps == 0:
            return
        if self.engine.gpu is not None:
            self._run_cuda(steps, fuse(self.force_generators))
            return
        self._check_state_shape()
        forces = fuse(self.force_generators)
        what = f"{self.n:,} particles, run({steps})"
        bad = 0
        with RunProgress(steps, what, "steps") as bar:  # (shown only inside a recorded run)
            if forces.python:
                for i in range(steps):
                    ext = self._python_forces(forces.python)
                    bad += self._step(1, forces, ext)
                    bar.update(i + 1)
            elif self.n * steps < PROGRESS_MIN_PARTICLE_STEPS:
                bad = self._step(steps, forces)
                bar.update(steps)
            else:  # in pieces, with progress
                done = 0
                piece = max(1, _PROGRESS_FIRST_PIECE // self.n)
                while done < steps:
                    k = min(piece, steps - done)
                    t0 = time.perf_counter()
                    bad += self._step(k, forces)
                    per_step = (time.perf_counter() - t0) / k
                    done += k
                    bar.update(done)
                    piece = max(1, int(_PROGRESS_PIECE_S / max(per_step, 1e-9)))
        flags = self.engine.flags
        if bad and flags is not None:
            raise self._frozen_error(bad, steps, flags)

    def _physics(self, forces: FusedForces, use_ext: bool) -> Physics:
        """The physics of a call from now (:class:`fastsdf.particles.kernels.Physics`)."""
        return Physics(
            dt=self.dt,
            t0=self.t,
            ax=forces.ax,
            ay=forces.ay,
            drag=forces.drag,
            use_m=use_ext or forces.drag != 0.0,
            use_ext=use_ext,
            explicit=self.integrator == "euler",
            always=self.collision == "notebook",
            rest=float(self.rest_speed),
        )

    def _step(self, steps: int, forces: FusedForces, ext: np.ndarray | None = None) -> int:
        """One call of the engine's step (``ext``: the Python forces of a one-step call);
        advances the clock. Returns the frozen count."""
        physics = self._physics(forces, ext is not None)
        bad = self.engine.step(
            self.p, steps, physics, forces.user, ext, self.prevent_tunnelling, self.block
        )
        self.t += steps * self.dt
        return bad

    def _run_cuda(self, steps: int, forces: FusedForces) -> None:
        """:meth:`run` on the GPU (:mod:`fastsdf.particles.cuda`): launched, not waited for."""
        from fastsdf.particles.cuda import DeviceParticles

        if forces.python:
            python = forces.python[0]
            raise TypeError(
                f"device='cuda' cannot run the Python force generator "
                f"{getattr(python, '__name__', python)!r} (it runs on the CPU only): "
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
        budget = Budget(self.prevent_tunnelling, self.lipschitz, 0.0, 0.0, False)
        physics = self._physics(forces, False)
        self.engine.gpu.run(self.p, steps, physics, forces.user, budget, self.params.as_tuple())
        self.t += steps * self.dt

    def check(self) -> None:
        """With ``device='cuda'``: wait for the GPU and raise the :class:`ValueError` of
        :meth:`run` if particles were frozen since the last check (on the GPU, :meth:`run`
        does not wait for the steps to finish). Nothing to do on the CPU (:meth:`run` raises)."""
        gpu = self.engine.gpu
        if gpu is None:
            return
        count, flags = gpu.frozen()
        steps, gpu.steps_unchecked = gpu.steps_unchecked, 0
        if count:
            p, self.p = self.p, self.p.host()
            try:
                err = self._frozen_error(count, steps, flags)
            finally:
                self.p = p
            raise err

    def _python_forces(self, gens: Any) -> np.ndarray:
        if self._ext is None or self._ext.shape != (self.n, 2):
            self._ext = np.empty((self.n, 2))
        return python_forces(gens, self.p, self.t, self._ext)

    def _check_state_shape(self):
        p = self.p
        if not isinstance(p, Particles):
            raise TypeError(f"sim.p must be a Particles object, got {type(p).__name__}")
        if len(p) != self.n or p.dtype != self.dtype:
            raise ValueError(
                f"sim.p holds {len(p)} particles of {p.dtype}; this simulation "
                f"has n={self.n} of {self.dtype}"
            )

    def _frozen_error(self, count: int, steps: int, flags: np.ndarray) -> ValueError:
        """The error after a call that froze ``count`` particles (clears their ``flags``)."""
        idx = np.flatnonzero(flags)
        first, why = int(idx[0]), int(flags[idx[0]])
        flags[idx] = 0
        p = self.p
        if why == FLAG_NONFINITE:
            x = np.asarray(p["x"][first], np.float64).tolist()
            v = np.asarray(p["v"][first], np.float64).tolist()
            what = (
                f"a step of particle {first} produced a non-finite state (timestep="
                f"{self.dt!r}; last finite state x={x}, v={v}); it was frozen there"
            )
        elif why == FLAG_COEFF:
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

    # -- diagnostics -------------------------------------------------------------------------
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
        """``(d, grad)`` of the world at points ``x``, ``y`` (arrays of one shape), exactly as the
        compiled step sees it (for a GridSDF: the bilinear samples, with its out-of-bounds
        rule)."""
        return self.engine.query(x, y, self.t)

    # -- files and pickling ------------------------------------------------------------------
    def save(self, path: str | os.PathLike, *, allow_pickle: bool = False) -> str:
        """Write the simulation to ``path`` (``.npz``) so that :meth:`load` continues it bit for
        bit (see :meth:`fastsdf.particles.family.Simulation.save`; ``allow_pickle``: allow
        worlds and forces that only pickle can store). With ``device='cuda'`` the state's host
        copy is written (and :meth:`load` puts it back on the device)."""
        if self.engine.gpu is None:
            return super().save(path, allow_pickle=allow_pickle)
        on_device, self.p = self.p, self.p.host()
        try:
            return super().save(path, allow_pickle=allow_pickle)
        finally:
            self.p = on_device

    def __getstate__(self) -> dict:
        # The world travels as its graph (and a grid's nodes), the state as arrays, with the
        # parameters' values; the engine (kernel modules, query data, scratch) stays behind and
        # is rebuilt from the world on unpickling (the simulation holds no drawing: that lives
        # in fastsdf.viz.render).
        state = self.__dict__.copy()
        for key in ("engine", "_ext", "_wall"):
            state.pop(key, None)
        state["params"] = self.params
        if self.engine.gpu is not None and not isinstance(self.p, Particles):
            state["p"] = self.p.host()  # the device state travels as its host copy
        return state

    def __setstate__(self, state: dict) -> None:
        state = dict(state)
        saved = state.pop("params", None)
        for key in _DERIVED:  # (an earlier version's saved state)
            state.pop(key, None)
        self.__dict__.update(state)
        self._ext = self._wall = None
        for key, value in (
            ("device", "cpu"),
            ("rest_speed", 0.0),
            ("_wall_speed_arg", None),
            ("_lipschitz_arg", None),
            ("_given", None),
        ):
            self.__dict__.setdefault(key, value)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # warned when first built
            self.sdf = state["_sdf"]
        if self.device == "cuda":
            from fastsdf.particles.cuda import DeviceParticles

            self.p = DeviceParticles(self.p)
        # Assigning the world resets its parameters to their defaults: set the saved values.
        if saved:
            self.params.update(dict(saved))

    def __repr__(self) -> str:
        return (
            f"ParticleSimulation(n={self.n}, timestep={self.dt!r}, t={self.t:.4g}, "
            f"integrator={self.integrator!r}, collision={self.collision!r}, "
            f"prevent_tunnelling={self.prevent_tunnelling}, dtype={self.dtype.name})"
        )


def _check_cuda(sim: ParticleSimulation, moving: bool) -> None:
    """A clear error for what the GPU step (``device='cuda'``) lacks."""
    if sim.dtype != np.dtype(np.float64):
        raise ValueError(f"device='cuda' steps float64 state only, got dtype={sim.dtype}")
    if sim.rest_speed > 0.0:
        raise NotImplementedError(
            "device='cuda' does not support resting contact (rest_speed > 0); use device='cpu'"
        )
    if sim.prevent_tunnelling and moving:
        raise NotImplementedError(
            "device='cuda' does not run the tunnelling sweep in a moving world; pass "
            "prevent_tunnelling=False"
        )


def _choice(value: Any, allowed: tuple, name: str) -> Any:
    if value not in allowed:
        raise ValueError(f"{name} must be one of {allowed}, got {name}={value!r}")
    return value


def _non_negative(value: Any, name: str) -> float:
    v = _real(value, name)
    if not (math.isfinite(v) and v >= 0.0):
        raise ValueError(f"{name} must be finite and >= 0, got {name}={value!r}")
    return v


def _count(n: Any) -> int:
    """The particle count ``n`` (the rows of ``positions`` when given) as an int > 0."""
    if isinstance(n, float) and math.isfinite(n) and n == int(n):
        n = int(n)  # n=1e5, as the command line accepts it
    if isinstance(n, (bool, np.bool_)) or not isinstance(n, numbers.Integral):
        raise TypeError(f"n must be an integer, got n={n!r}")
    if n <= 0:
        raise ValueError(f"n must be > 0, got n={n!r}")
    return int(n)


def _block_size(block: Any) -> int | None:
    if block is not None and (
        isinstance(block, (bool, np.bool_)) or not isinstance(block, numbers.Integral) or block <= 0
    ):
        raise ValueError(f"block must be a positive integer or None, got block={block!r}")
    return None if block is None else int(block)


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
        if n is not DEFAULT_COUNT and n != pos.shape[0]:
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


def create_animation(
    fig: Any,
    ax: Any,
    sim: Any,
    frames: int = 300,
    repeat: bool = True,
    use_wall_time: bool = False,
    interval: float | None = None,
) -> Any:
    """A matplotlib ``FuncAnimation`` of ``sim`` on ``ax`` of the figure ``fig`` (the
    notebook's helper).

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
