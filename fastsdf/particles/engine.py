"""The engine of particles that meet only the world: :class:`ParticleEngine`, which a
:class:`fastsdf.particles.ParticleSimulation` holds as ``sim.engine`` (as a
:class:`fastsdf.particles.GrainSimulation` holds the granular engine).

It binds one world (what a step queries, :mod:`fastsdf.particles.world`: the generated kernel
module per set of fused forces and its query data, a grid's exact fallback, a pruned scene's
plan header, the parameters, the Lipschitz bound and margins) and runs calls of the fused step
(:mod:`fastsdf.particles.kernels`) on a :class:`fastsdf.particles.Particles` state: it picks
the kernel of a call, cuts the particles into slices for several threads or takes numba's
parallel entry point for a long call, and resumes particles that stopped at a grid's edge
before its exact fallback was bound. On a GPU (``device='cuda'``) it holds the device step,
:class:`fastsdf.particles.cuda.CudaStep`.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numba
import numpy as np

from fastsdf.backends import HEADER_SIZE, plan_header
from fastsdf.fields.band import NarrowBandGridSDF
from fastsdf.function import Function
from fastsdf.notice import compiling, warn_caller
from fastsdf.particles.kernels import NO_EXT, Budget, Physics, State
from fastsdf.particles.kernels.constants import FLAG_RESUME
from fastsdf.particles.scene_blocks import NO_TABLE
from fastsdf.particles.state import Particles
from fastsdf.particles.world import (
    _NO_PARAMS,
    SimulationParams,
    _exact_address,
    _grid_margin,
    _is_distance_bound,
    _is_grid,
    _kernel_module,
    wall_speed_table,
)

__all__ = ["ParticleEngine", "PARALLEL_MIN_PARTICLES", "DEFAULT_BLOCK", "LONG_CALL"]

#: Fewer particles than this run on one thread (thread start-up costs more than it saves).
PARALLEL_MIN_PARTICLES = 4096
#: A call of at least this many particle-steps (about 0.05 s) runs numba's parallel entry point.
LONG_CALL = 1 << 22
#: Particles per block of a call (block state fits in the L1/L2 cache).
DEFAULT_BLOCK = 512
# Threads that run slices of the particles through a kernel (which releases the GIL); made on
# first use, grown when numba's thread count is raised.
_POOL: list = [None]
# (kernel, state dtype, Python forces) combinations a kernel has been compiled for.
_READY: set = set()


def _pool(workers: int) -> ThreadPoolExecutor:
    pool = _POOL[0]
    if pool is None or pool._max_workers < workers:
        pool = _POOL[0] = ThreadPoolExecutor(workers, thread_name_prefix="fastsdf-step")
    return pool


class ParticleEngine:
    """The fused particle step of one world (see the module docs).

    Parameters
    ----------
    world : SDF (:class:`fastsdf.function.Function`), GridSDF or another grid of the sampler
        protocol (see :mod:`fastsdf.particles.kernels`).
    lipschitz : float or None
        A bound on ``|grad d|``; None: 1 for an SDF, ``sqrt(2)`` for a grid. Query skipping is
        on only where the bound is known (given, or the world is a distance bound).
    wall_speed : float or None
        A moving world's bound on ``|dd/dt|``; None: estimated per call, per region.
    device : {'cpu', 'cuda'}
        With ``'cuda'`` the engine also holds the GPU step (:attr:`gpu`).

    Attributes
    ----------
    world, params, lipschitz, margin, parametric, moving
        The world, the values of its runtime parameters, its Lipschitz bound, how far a grid
        may jump at its bounds, whether it has parameters and whether it moves.
    skip : bool
        Free-flight query skipping (on where the Lipschitz bound is known; tests and
        benchmarks turn it off to make every step query).
    simd : bool
        Whether a grid world may take the block kernel (tests compare it with the others).
    flags : int32 array or None
        The freeze code of every particle of the last call (see the kernels' checks).
    gpu : :class:`fastsdf.particles.cuda.CudaStep` or None
    """

    def __init__(
        self,
        world: Any,
        *,
        lipschitz: float | None = None,
        wall_speed: float | None = None,
        device: str = "cpu",
    ) -> None:
        module, data, keep = _kernel_module(world)  # raises TypeError for anything else
        self.world = world
        self._module, self._data, self._keep = module, data, keep
        # the kernel module and query data per set of fused user forces (by their ids)
        self._kernels: dict = {(): (module, data, keep, ())}
        # A grid in mode 'exact' binds its exact fallback when a particle first needs it; a
        # pruned SDF binds its C function at once. Both read the plan header.
        grid = _is_grid(world)
        pruned = isinstance(world, Function) and not grid and len(data) == 2
        self._hdr = np.zeros(HEADER_SIZE)
        self._hdr_plan = None  # the plan the header points into (kept alive here)
        self._exact_ptr: Any = None if (grid and world.mode == "exact") or pruned else 0
        if self._exact_ptr is None and (pruned or getattr(world, "bounds", None) is None):
            self.bind_fallback()
        self.parametric = isinstance(world, Function) and not grid and world.compiled.parametric
        self.moving = self.parametric and world.time_dependent
        self.params = SimulationParams(world) if self.parametric else SimulationParams(_NO_PARAMS)
        self.margin = _grid_margin(world)
        self._far = _far_answers(world, self.margin)
        self._far_warned = False
        self.lipschitz = (
            float(lipschitz) if lipschitz is not None else (math.sqrt(2.0) if grid else 1.0)
        )
        # Skipping queries is exact only if the bound holds; without a known bound (an SDF
        # whose exactness is 'none', or a bare expression) every step queries.
        self.skip = lipschitz is not None or _is_distance_bound(world)
        self.simd = True
        self.wall_speed = wall_speed
        self.flags: np.ndarray | None = None
        self._wall_table: Any = None
        self.gpu: Any = None
        if device == "cuda":
            self.use_device()

    def use_device(self) -> None:
        """Step on the GPU from now on: the world's query data on the device
        (:class:`fastsdf.particles.cuda.CudaStep`, which refuses a world it cannot step)."""
        from fastsdf.particles.cuda import CudaStep

        self.gpu = CudaStep(self.world)

    # -- the world's kernels and query data --------------------------------------------------
    @property
    def plan(self) -> Any:
        """The pruning plan the step's plan header points into now (None: no pruning)."""
        return self._hdr_plan

    @property
    def fallback_bound(self) -> bool:
        """Whether the exact fallback (a grid's, or a pruned scene's C function) is bound, or
        none is needed; a grid in mode 'exact' binds it when a particle first comes near its
        edge (:meth:`bind_fallback`)."""
        return self._exact_ptr is not None

    @property
    def data(self) -> tuple:
        """The query data of the world's kernel without user forces (its fallback bound)."""
        return self._data

    def kernel(self, user: tuple = ()) -> tuple:
        """The generated kernel module for these fused user forces (generated on first use)
        and its query data."""
        key = tuple(id(u) for u in user)
        entry = self._kernels.get(key)
        if entry is None or entry[3] != user:
            module, data, keep = _kernel_module(self.world, user)
            entry = self._kernels[key] = (module, data, keep, user)
        return entry[0], self._bind(entry[1])

    def _bind(self, data: tuple) -> tuple:
        """The query data with the exact fallback's address, once compiled (0 before), and
        that of the plan header (the last entry)."""
        ptr = self._exact_ptr
        return data if not ptr else (ptr[0],) + data[1:-1] + (int(self._hdr.ctypes.data),)

    def bind_fallback(self) -> None:
        """Compile (or load) the grid's exact fallback (a pruned SDF's C function) and bind it
        from now on."""
        if self._exact_ptr is None:
            f = self.world
            with compiling("the exact SDF behind the grid, for particles near its edge"):
                self._exact_ptr = _exact_address(f.exact if _is_grid(f) else f)
            self._data = self._bind(self._data)

    def update_plan(self, x: np.ndarray, steps: int) -> None:
        """Point the plan header at a pruning plan over the particles (positions ``x``, for a
        call of ``steps`` steps) that query the exact SDF per point (all of them for an SDF
        world, those outside the grid for a grid's exact fallback), or at none where pruning
        does not pay (see ``CompiledSDF.pruned_plan``).
        Particles that leave the plan's rectangle during the steps use every row."""
        if not self._exact_ptr:
            return
        f = self.world
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

    def scene_data(self, p: Any, t: float, dt: float, steps: int) -> tuple:
        """Query data of a parametric world for a call of ``steps`` steps of ``dt`` seconds from
        time ``t`` over the particles ``p``: (t,
        wall speed bound, table geometry and the per-region table, *parameters); see
        ``PARAMS_AT`` in :mod:`fastsdf.particles.scene_blocks`."""
        prm = self.params.as_tuple()
        wall = 0.0
        table = (0.0, 0.0, 1.0, NO_TABLE)
        if self.moving and steps:
            if self.wall_speed is None:
                r_max = float(np.max(p["r"]))
                wall, table = wall_speed_table(self.world, p["x"], r_max, t, dt, steps, prm)
            else:
                wall = self.wall_speed
        self._wall_table = table  # kept alive: the kernel borrows the array
        return (float(t), float(wall)) + table + prm

    def query(self, x: Any, y: Any, t: float = 0.0) -> tuple:
        """``(d, grad)`` of the world at points ``x``, ``y`` (at time ``t``), exactly as the step
        sees it (for a grid: the bilinear samples, with its out-of-bounds rule)."""
        xs = np.ascontiguousarray(x, dtype=np.float64).reshape(-1)
        ys = np.ascontiguousarray(y, dtype=np.float64).reshape(-1)
        out = np.empty((xs.shape[0], 3))
        self.bind_fallback()
        self.update_plan(np.stack([xs, ys], axis=1), 1)
        data = self.scene_data(None, t, 1.0, 0) if self.parametric else self._data
        self._module.query_many(data, xs, ys, out)
        return out[:, 0], out[:, 1:]

    # -- a call of the step ------------------------------------------------------------------
    def step(
        self,
        p: Particles,
        steps: int,
        physics: Physics,
        user: tuple = (),
        ext: np.ndarray | None = None,
        trace: bool = True,
        block: int | None = None,
    ) -> int:
        """Run ``steps`` steps of the particles ``p`` with ``physics``
        (:class:`fastsdf.particles.kernels.Physics`; its ``use_ext`` says whether ``ext``, the
        Python forces of a one-step call, is given), the fused user forces ``user``, the
        tunnelling check ``trace`` and ``block`` particles per block. Returns how many
        particles were frozen (their codes in :attr:`flags`)."""
        module, data = self.kernel(user)
        n = len(p)
        if self.flags is None or self.flags.shape[0] != n:
            self.flags = np.zeros(n, dtype=np.int32)
        if self.parametric:
            data = self.scene_data(p, physics.t0, physics.dt, steps)
        a = p._arrays
        check_all = p._dirty
        ext = NO_EXT if ext is None else ext
        state = State(a["x"], a["v"], a["m"], a["r"], a["cr"], a["cf"], ext, self.flags, check_all)
        margin = self._call_margin(a["r"])
        budget = Budget(
            trace=bool(trace),
            lip=self.lipschitz,
            margin=margin if math.isfinite(margin) else self.margin,
            eps=float(np.finfo(p.dtype).eps),
            skip=self.skip and math.isfinite(margin),
        )
        self.update_plan(a["x"], steps)
        block = block or DEFAULT_BLOCK
        bad = self._call(module, data, steps, state, physics, budget, block)
        if bad and self._exact_ptr is None:
            bad = self._resume(p, module, steps, state, physics, budget, block, bad)
        if check_all and not bad:
            p._dirty = False
        return bad

    def _call_margin(self, radius: np.ndarray) -> float:
        """The free-flight margin of a call whose particles have radii ``radius``: the world's
        (:attr:`margin`); in a band world whose far tiles' lower bounds these particles may
        touch, one that also covers how far those bounds lie below the distance (inf: no
        skipping), so that skipping still changes no result (see :func:`_far_answers`)."""
        if self._far is None or radius.shape[0] == 0:
            return self.margin
        floor, wide = self._far
        r_max = float(np.max(radius))
        if r_max + self.margin < floor:  # (a NaN radius takes the wide margin)
            return self.margin
        if not self._far_warned:
            self._far_warned = True
            lo, hi = self.world.band_range
            warn_caller(
                f"particles of radius up to {r_max:.4g} reach beyond the band of their "
                f"NarrowBandGridSDF world (band_range=({lo:g}, {hi:g})), where its far tiles "
                f"answer lower bounds of the distance (from {floor:.4g} on): they bounce off "
                f"those bounds a little away from the walls. Build the band as "
                f"band=(-w, r_max + w), w a few spacings (see NarrowBandGridSDF)."
            )
        return wide

    def _call(self, module, data, steps, state, physics, budget, block):
        """Run the call's kernel variant on ``numba.get_num_threads()`` threads from
        ``PARALLEL_MIN_PARTICLES`` particles on: a short call as one slice of whole blocks per
        thread through ``step_ser``, a long one (``LONG_CALL`` particle-steps) through the
        parallel entry point ``step_par``. Returns the frozen count."""
        variant = self._variant(module, state, physics, budget)
        args = (physics, budget, steps, block) + variant
        n = state.X.shape[0]
        threads = numba.get_num_threads() if n >= PARALLEL_MIN_PARTICLES else 1
        key = (module, variant, state.X.dtype, state.EXT.shape[0] > 0)
        if threads > 1 and n * steps >= LONG_CALL:
            # numba's parallel entry point: a few percent faster on long calls, and twice
            # the compile time, so compiled only when a long call first needs it
            if ("par",) + key in _READY:
                return module.step_par(data, state, *args)
            _READY.add(("par",) + key)
            with compiling("the particle step kernel for long calls"):
                return module.step_par(data, state, *args)
        if key not in _READY:
            # compile (or load) this variant here, with a notice, before threads (types new to
            # it, e.g. float32, compile here too, not in two threads at once)
            with compiling("the particle step kernel"):
                module.step_ser(data, _part(state, 0, 0), *args)
            _READY.add(key)
        if threads <= 1:
            return module.step_ser(data, state, *args)
        # one slice of whole blocks per thread, the first on this thread
        blocks = -(-n // block)
        per = -(-blocks // threads) * block

        def run(lo: int) -> int:
            return module.step_ser(data, _part(state, lo, lo + per), *args)

        rest = [_pool(threads).submit(run, lo) for lo in range(per, n, per)]
        return run(0) + sum(job.result() for job in rest)

    def _variant(self, module, state, physics, budget):
        """The kernel variant of a call, ``(simd, plain)`` (see
        :func:`fastsdf.particles.kernels.step.step_ser`): the block step of a static grid
        world (``simd``: float64 state, no resting contact, no Python forces), with or without
        query skipping; else the particle-by-particle step, plain (without skipping, tunnelling
        check, moving world and resting contact) or general. All give the same results."""
        simd = (
            self.simd
            and module.GRID_SIMD
            and not module.MOVING
            and physics.rest == 0.0
            and not physics.use_ext
            and state.X.dtype == np.float64
        )
        if simd:
            return True, None if budget.skip else True
        plain = not (budget.trace or budget.skip or physics.rest > 0.0 or module.MOVING)
        return None, True if plain else None

    def _resume(self, p, module, steps, state, physics, budget, block, bad):
        """Particles that stopped near the grid's edge before its exact fallback was bound
        (FLAG_RESUME + step): bind it, run each the rest of its steps from where it stopped
        (particles are independent, so the result is that of an uninterrupted call)."""
        flags = self.flags
        idx = np.flatnonzero(flags >= FLAG_RESUME)
        if not idx.size:
            return bad
        self.bind_fallback()
        arrays = p._arrays
        self.update_plan(arrays["x"], steps)
        data = next(self._bind(e[1]) for e in self._kernels.values() if e[0] is module)
        at = flags[idx] - FLAG_RESUME
        flags[idx] = 0
        bad -= idx.size
        ext = state.EXT
        for j in np.unique(at):
            sel = idx[at == j]
            sub = State(
                *(np.ascontiguousarray(arrays[k][sel]) for k in Particles.FIELDS),
                ext[sel] if ext.shape[0] else ext,
                np.zeros(sel.size, dtype=np.int32),
                False,
            )
            sub_physics = physics._replace(t0=physics.t0 + int(j) * physics.dt)
            bad += self._call(module, data, steps - int(j), sub, sub_physics, budget, block)
            arrays["x"][sel] = sub.X
            arrays["v"][sel] = sub.V
            flags[sel] = sub.FLAGS
        return bad


def _far_answers(world: Any, margin: float) -> tuple[float, float] | None:
    """For a band world (:class:`fastsdf.fields.band.NarrowBandGridSDF`): ``(floor, wide)``,
    the least distance its far tiles answer outside matter, and a free-flight margin that
    covers how far a far tile's answer may lie below the distance (inf: unknown); else None.

    Skipping a query changes no result when the skipped answer would have been clear of the
    particle: fine tiles interpolate the distance (within ``margin``), but a far tile answers a
    lower bound, up to a tile's diagonal (times the Lipschitz bound) below the distance. While
    every particle's radius lies below ``floor - margin``, no far answer touches a particle and
    the world's margin suffices; a larger particle takes ``wide``, the margin plus that gap."""
    if not isinstance(world, NarrowBandGridSDF):
        return None
    hx, hy = world.spacing
    slack = 0.5 * math.hypot(hx, hy)  # far bounds: less half a cell diagonal ...
    quantum = float(world.sampler_data[-1])  # ... quantized downwards by up to two quanta
    floor = world.band_range[1] - slack - 2.0 * quantum
    if world.lipschitz is None:
        return floor, math.inf
    tile_diagonal = world.tile * math.hypot(hx, hy)
    return floor, margin + world.lipschitz * tile_diagonal + slack + 2.0 * quantum


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
