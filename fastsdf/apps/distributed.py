"""Beyond one machine: point sets and particle simulations sharded over Dask.

Particles never interact with each other, only with the SDF, so a simulation splits into
independent shards. This module runs them on a ``dask.distributed`` cluster (install the extra:
``pip install fastsdf[distributed]``)::

    from dask.distributed import Client
    import fastsdf as sdf
    from fastsdf.apps.distributed import DistributedSimulation, local_cluster
    from fastsdf.particles import Gravity
    from fastsdf.shapes.scenes import box_world

    with local_cluster(workers=2) as cluster, Client(cluster) as client:
        world = sdf.GridSDF(box_world(20), samples=[400j, 400j])
        sim = DistributedSimulation(world, 10_000_000, client=client, seed=0,
                                    force_generators=[Gravity()])
        sim.run(100)                    # every shard steps on its worker, in parallel
        image = sim.density()           # (400, 400) counts: the sum of per-shard histograms
        sim.close()

What travels. An SDF pickles as its expression graph (a flat node list), never as compiled
code; a GridSDF as that graph plus its node array. A worker rebuilds the kernels on first use
from its own disk cache (``$FASTSDF_CACHE_DIR``): it compiles once per machine, and every later
process loads. The world and the simulation's configuration are sent to each worker once
(``client.scatter(..., broadcast=True)``); the particles are created on the workers from the
seed and never travel to the client unless you ask for them (:meth:`DistributedSimulation.gather`).

Shards are Dask *actors*: a stateful object living on one worker, whose method calls go from
the client to that worker (no task graph, no scheduler decision per call). The state (64 bytes
per particle) is mutated in place every step, which is what actors are for; a plain task
result is meant to be immutable, and the scheduler may copy it or silently recompute it from
its creation task after a worker dies, which here would mean a shard restarting from ``t = 0``
unnoticed. Every call returns the shard's step count and the client checks it, so a shard that
was lost (or re-created) raises :class:`ShardLostError` naming it; nothing is re-created in
secret. There are no checkpoints: after the error, build a new simulation.

Determinism: shard ``i`` of ``shards`` is exactly ::

    ParticleSimulation(world, n_i, seed=np.random.default_rng(
        np.random.SeedSequence(seed).spawn(shards)[i]), **parameters)

(followed by ``init(sim, i)`` if given) with ``n_i = n // shards + (i < n % shards)``, stepped
with the same force generators: the same seed and shard count give the same bits whichever
workers run the shards, and the same bits as running those simulations one after another in
one process.
"""

from __future__ import annotations

import contextlib
import hashlib
import numbers
import os
import pickle
import sys
import uuid
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from fastsdf.expr.validate import check_bounds, count, shown

__all__ = [
    "evaluate",
    "DistributedSimulation",
    "ShardLostError",
    "shard_sizes",
    "shard_seed",
    "local_cluster",
    "SimulationStats",
    "run_demo",
]

#: How long (seconds) to wait on a shard before checking that its worker is still alive.
POLL_SECONDS = 0.5


def _require_dask():
    try:
        import dask  # noqa: F401  (only whether it imports)
        import distributed  # noqa: F401
    except ImportError as exc:  # pragma: no cover - the extra is installed in CI
        raise ImportError(
            "fastsdf.apps.distributed needs dask.distributed: pip install 'fastsdf[distributed]'"
        ) from exc


def _digest(obj: object) -> str:
    return hashlib.sha256(pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)).hexdigest()[:32]


def _check_world(f: Any, name: str = "f") -> Any:
    from fastsdf.fields.grid import GridSDF
    from fastsdf.function import Function

    if not isinstance(f, (Function, GridSDF)):
        raise TypeError(
            f"{name} must be a fastsdf SDF (Function) or GridSDF, got {name}={shown(f)} "
            f"of type {type(f).__name__}"
        )
    return f


# ---------------------------------------------------------------------------------------------
# Point sets.


def _evaluate_block(xb: np.ndarray, yb: np.ndarray, f: Any, gradient: bool) -> np.ndarray:
    if gradient:
        d, g = f(xb, yb, compute_gradient=True)
        out = np.empty(d.shape + (3,))
        out[..., 0] = d
        out[..., 1:] = g
        return out
    return f(xb, yb)


def evaluate(f: Any, x: ArrayLike, y: ArrayLike, compute_gradient: bool = False) -> Any:
    """``f(x, y[, compute_gradient])`` on ``dask.array`` inputs, lazily, block by block.

    ``f``: a fastsdf SDF or GridSDF. ``x``, ``y``: dask arrays (or array-likes, wrapped with
    ``dask.array.asarray``) of the same shape; ``y`` is rechunked like ``x``. Returns a float64
    dask array ``d`` of that shape, or ``(d, grad)`` with ``grad`` of shape ``shape + (2,)``,
    ``grad[..., 0] = dd/dx`` (negative inside, as everywhere in fastsdf). Each block is computed
    by the single-process call on that block, so its values are the same bits. ``f`` enters the
    task graph once, as one piece of data: a worker unpickles it once (the graph, not compiled
    code) and compiles or loads its kernels once per process.
    """
    _require_dask()
    import dask
    import dask.array as da

    _check_world(f)
    xd = x if isinstance(x, da.Array) else da.asarray(x)
    yd = y if isinstance(y, da.Array) else da.asarray(y)
    for name, a in (("x", xd), ("y", yd)):
        if a.dtype.kind not in "iuf":
            raise TypeError(f"{name} must hold real numbers, got dtype {a.dtype}")
    if xd.shape != yd.shape:
        raise ValueError(f"x and y must have the same shape, got {xd.shape} and {yd.shape}")
    yd = yd.rechunk(xd.chunks)
    world = dask.delayed(f, name="fastsdf-world-" + _digest(f), pure=True)
    gradient = bool(compute_gradient)
    token = dask.base.tokenize(world.key, xd.name, yd.name, gradient)
    # with the gradient: one (..., 3) block of value, d/dx, d/dy, split below
    shape = dict(new_axis=xd.ndim, chunks=xd.chunks + ((3,),)) if gradient else {}
    out = da.map_blocks(
        _evaluate_block,
        xd,
        yd,
        world,
        gradient,
        dtype=np.float64,
        meta=np.empty((0,) * (xd.ndim + gradient)),
        name=("fastsdf-evaluate-vg-" if gradient else "fastsdf-evaluate-") + token,
        **shape,
    )
    if not gradient:
        return out
    return out[..., 0], out[..., 1:]


# ---------------------------------------------------------------------------------------------
# Sharded simulation.


class ShardLostError(RuntimeError):
    """A shard of a :class:`DistributedSimulation` is gone (its worker died or was restarted).

    ``shards``: the lost shard indices; ``workers``: the addresses they lived on; ``detail``:
    what Dask said. The other shards are intact, but the simulation can no longer advance
    consistently.
    """

    def __init__(self, shards: Sequence[int], workers: Sequence[str], detail: str = ""):
        self.shards = tuple(int(s) for s in shards)
        self.workers = tuple(workers)
        where = ", ".join(f"shard {s} on {w}" for s, w in zip(self.shards, self.workers))
        super().__init__(
            f"lost {len(self.shards)} shard(s): {where}; their particles are gone "
            f"(no checkpoints): build a new DistributedSimulation"
            + (f" ({detail})" if detail else "")
        )


def shard_sizes(n: int, shards: int) -> list:
    """Particles per shard: ``n // shards``, plus one for the first ``n % shards`` shards."""
    return [n // shards + (1 if i < n % shards else 0) for i in range(shards)]


def shard_seed(seed: Any, shards: int, i: int) -> np.random.Generator:
    """The random generator of shard ``i``: ``default_rng(SeedSequence(seed).spawn(shards)[i])``."""
    return np.random.default_rng(np.random.SeedSequence(seed).spawn(shards)[i])


_PARAMETERS = (
    "timestep",
    "integrator",
    "collision",
    "prevent_tunnelling",
    "dtype",
    "cr",
    "cf",
    "lipschitz",
    "block",
)


@dataclass(frozen=True)
class _Config:
    """What a worker needs to build and step its shards (pickles as a graph, a few bytes more)."""

    world: object
    n: int
    shards: int
    seed: object
    parameters: tuple
    init: Callable | None = None

    def build(self, i: int) -> tuple[Any, Any]:
        """Shard ``i`` and what ``init(sim, i)`` returned (None without ``init``)."""
        from fastsdf.particles import ParticleSimulation

        sizes = shard_sizes(self.n, self.shards)
        sim = ParticleSimulation(
            self.world,
            n=sizes[i],
            seed=shard_seed(self.seed, self.shards, i),
            **dict(self.parameters),
        )
        return sim, (self.init(sim, i) if self.init is not None else None)


def _workers(client: Any) -> dict:
    """The scheduler's live workers, ``{address: info}``, asked now. (Not
    ``client.scheduler_info()``: the client refreshes that cache in the background without the
    worker list, so reading it right after a refresh can show an empty cluster.)"""
    return dict(client.sync(client.scheduler.identity, n_workers=-1)["workers"])


def _set_threads(threads: int) -> None:
    import numba

    numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))


class _Group:
    """The shards on one worker (a Dask actor: one per worker, so a call costs one round trip
    per worker whatever the shard count). Every method returns ``(steps, payload)``, ``steps``
    being ``{shard: steps done}``; payloads are small except :meth:`particles`."""

    def __init__(self, config: _Config, indices: list, threads: int):
        self.threads = threads
        _set_threads(threads)
        built = {i: config.build(i) for i in indices}
        self.sims = {i: b[0] for i, b in built.items()}
        self.init_results = {i: b[1] for i, b in built.items()}
        self.steps = {i: 0 for i in indices}

    def initialized(self) -> tuple[dict, dict]:
        return dict(self.steps), self.init_results

    def run(self, steps: int, generators: list) -> tuple[dict, dict]:
        _set_threads(self.threads)
        for i, sim in self.sims.items():
            sim.force_generators = list(generators)
            sim.run(steps)
            self.steps[i] += steps
        return dict(self.steps), {i: sim.t for i, sim in self.sims.items()}

    def summary(self, generators: list) -> tuple[dict, dict]:
        out = {}
        for i, sim in self.sims.items():
            sim.force_generators = list(generators)
            x = np.asarray(sim.p["x"], dtype=np.float64)
            with np.errstate(invalid="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN: NaN box
                bbox = np.array(
                    [np.nanmin(x[:, 0]), np.nanmin(x[:, 1]), np.nanmax(x[:, 0]), np.nanmax(x[:, 1])]
                )
            out[i] = (sim.n, sim.kinetic_energy(), sim.potential_energy(), bbox)
        return dict(self.steps), out

    def density(self, bounds: tuple, shape: tuple) -> tuple[dict, np.ndarray]:
        from fastsdf.viz.render import density_image

        _set_threads(self.threads)
        total = np.zeros(shape)
        for sim in self.sims.values():
            x = sim.p["x"]
            total += density_image(x[:, 0], x[:, 1], bounds, shape)
        return dict(self.steps), total

    def take(self, local: dict) -> tuple[dict, dict]:
        out = {}
        for i, rows in local.items():
            p = self.sims[i].p
            # (Particles has keys() but is not iterable)
            out[i] = {k: np.array(p[k][rows]) for k in p.keys()}  # noqa: SIM118
        return dict(self.steps), out

    def particles(self) -> tuple[dict, dict]:
        return dict(self.steps), {i: sim.p.copy() for i, sim in self.sims.items()}


@dataclass(frozen=True)
class SimulationStats:
    """Small reductions over all shards (see :meth:`DistributedSimulation.stats`).

    ``counts``: particles per shard; ``kinetic``, ``potential``: totals (energy units, summed
    over shards in shard order; potential of the :class:`fastsdf.particles.Gravity` generators,
    zero at the origin); ``bboxes``: ``(shards, 4)`` per-shard ``(xmin, ymin, xmax, ymax)`` of
    particle centres (length units; particles with a non-finite position are left out);
    ``bbox``: their union.
    """

    counts: tuple
    kinetic: float
    potential: float
    bboxes: np.ndarray
    bbox: tuple

    @property
    def n(self) -> int:
        """Total number of particles."""
        return int(sum(self.counts))

    @property
    def energy(self) -> float:
        """Kinetic plus potential energy."""
        return self.kinetic + self.potential


class DistributedSimulation:
    """A :class:`fastsdf.particles.ParticleSimulation` of ``n`` particles split into shards that
    live on Dask workers.

    Parameters
    ----------
    world : SDF or GridSDF
        As for ``ParticleSimulation``; it travels to each worker once, as a graph (and a grid's
        node array), and each worker compiles or loads its kernels from its own disk cache.
    n : int
        Total number of particles (>= ``shards``).
    client : dask.distributed.Client
        The cluster to run on (required: fastsdf never starts one behind your back; see
        :func:`local_cluster`).
    shards : int or None
        Number of shards; default one per worker. Shard ``i`` goes to worker ``i mod workers``
        (workers sorted by address); the shard count, not the worker count, fixes the result.
    seed : int, SeedSequence entropy or None
        Shard ``i`` draws its initial state from :func:`shard_seed` ``(seed, shards, i)``;
        ``None`` draws fresh entropy once (kept as :attr:`seed`).
    force_generators : list
        :class:`fastsdf.particles.Gravity`, :class:`fastsdf.particles.Drag` (fused) and
        picklable Python callables ``(p, t) -> (n_i, 2)``; a Python generator sees one shard's
        particles at a time. The list :attr:`force_generators` may be changed between runs.
    timestep, integrator, collision, prevent_tunnelling, dtype, cr, cf, lipschitz, block
        The ``ParticleSimulation`` parameters, same meaning and defaults.
    threads : int or None
        numba threads per shard call; default the worker's Dask thread count, so that worker
        processes sharing a machine do not oversubscribe its cores.
    init : callable or None
        ``init(sim, i)``, picklable, run once on each shard's worker right after the shard is
        built (e.g. to place its particles); the shard is ``sim``, a ``ParticleSimulation``.
        Its return values are kept in :attr:`init_results` (small values only). For
        reproducible results it must depend only on ``sim`` and ``i``.
    contacts : None
        Only None: grains that collide with each other (``ContactLaw``) are refused with a
        ValueError saying what works (non-interacting particles shard; grains would need a
        halo exchange between shards every substep).

    Each worker holds its shards' state (64 bytes per particle in float64); the client holds
    only small results. Use as a context manager or call :meth:`close` to free the workers.
    """

    client: Any
    n: int
    shards: int
    dtype: np.dtype
    steps: int
    t: float
    dt: float
    workers: list[str]
    init_results: list
    force_generators: list
    _lost: ShardLostError | None
    _groups: dict[str, list[int]]
    _futures: list
    _config_future: Any
    _actors: dict[str, Any] | None

    def __init__(
        self,
        world: Any,
        n: int,
        *,
        client: Any,
        shards: int | None = None,
        seed: Any = None,
        force_generators: Sequence = (),
        timestep: float = 1 / 30,
        integrator: str = "symplectic",
        collision: str = "approaching",
        prevent_tunnelling: bool = True,
        dtype: Any = np.float64,
        cr: float = 0.6,
        cf: float = 0.3,
        lipschitz: float | None = None,
        block: int | None = None,
        threads: int | None = None,
        init: Any = None,
        contacts: Any = None,
    ):
        if contacts is not None:
            raise ValueError(
                f"contacts={shown(contacts)}: grains that collide with each other cannot be "
                f"sharded as independent batches (each shard would need the grains near its "
                f"border from its neighbours every substep: a halo exchange, not implemented). "
                f"What shards: non-interacting particles (contacts=None); grains run in one "
                f"process: fastsdf.particles.ParticleSimulation(world, positions=..., "
                f"contacts=ContactLaw())"
            )
        _require_dask()
        from distributed import Client

        from fastsdf.particles import ParticleSimulation

        if not isinstance(client, Client):
            raise TypeError(f"client must be a dask.distributed.Client, got client={shown(client)}")
        _check_world(world, "world")
        info = _workers(client)
        if not info:
            raise ValueError("the client's cluster has no workers")
        addresses = sorted(info)
        n = count(n, "n")
        shards = count(len(addresses) if shards is None else shards, "shards")
        threads = None if threads is None else count(threads, "threads")
        if n < shards:
            raise ValueError(
                f"n must be >= shards (every shard holds a particle), got n={shown(n)}, "
                f"shards={shown(shards)}"
            )
        if seed is None:
            seed = np.random.SeedSequence().entropy
        parameters = dict(
            timestep=timestep,
            integrator=integrator,
            collision=collision,
            prevent_tunnelling=prevent_tunnelling,
            dtype=np.dtype(dtype),
            cr=cr,
            cf=cf,
            lipschitz=lipschitz,
            block=block,
        )
        # Validate every parameter here, on one particle, so that errors name the parameter
        # at construction instead of arriving as a remote traceback.
        probe = ParticleSimulation(world, n=1, seed=0, **parameters)
        for gen in force_generators:
            if not callable(gen):
                raise TypeError(
                    f"force_generators must hold Gravity, Drag or callables "
                    f"(p, t) -> (n, 2) forces, got {shown(gen)}"
                )
        self.client = client
        self.world = world
        self.n = int(n)
        self.shards = int(shards)
        self.seed = seed
        self.dt = probe.dt
        self.dtype = probe.dtype
        self.force_generators = list(force_generators)
        self.t = 0.0
        self.steps = 0
        self.sizes = shard_sizes(self.n, self.shards)
        self._lost = None
        if init is not None and not callable(init):
            raise TypeError(f"init must be a callable (sim, shard) or None, got init={shown(init)}")
        config = _Config(world, self.n, self.shards, seed, tuple(parameters.items()), init)
        self.workers = [addresses[i % len(addresses)] for i in range(self.shards)]
        self._start_shards(config, info, threads)
        #: What ``init(sim, i)`` returned on each shard, in shard order (None without init).
        self.init_results = [None] * self.shards
        if init is not None:
            for _, payload in self._call("initialized"):
                for i, value in payload.items():
                    self.init_results[i] = value

    def _start_shards(self, config: _Config, info: dict, threads: int | None) -> None:
        """Build the shards on their workers: ``config`` sent to each once, one actor per
        worker holding its shards, running ``threads`` numba threads (default its Dask
        thread count)."""
        client = self.client
        self._config_future = client.scatter(config, broadcast=True, hash=False)
        tag = uuid.uuid4().hex[:12]
        self._groups = {}
        for i, w in enumerate(self.workers):
            self._groups.setdefault(w, []).append(i)
        self._futures = [
            client.submit(
                _Group,
                self._config_future,
                indices,
                threads or info[w].get("nthreads", 1),
                actor=True,
                workers=[w],
                allow_other_workers=False,
                pure=False,
                key=f"fastsdf-shards-{tag}-{k}",
            )
            for k, (w, indices) in enumerate(self._groups.items())
        ]
        actors = self._gather(
            [(indices[0], f) for indices, f in zip(self._groups.values(), self._futures)],
            check_steps=False,
        )
        self._actors = dict(zip(self._groups, actors))

    # -- calls and loss detection -----------------------------------------------------------
    def _lost_error(self, shards: Sequence[int], detail: str = "") -> ShardLostError:
        # Shards share their worker's fate: name every shard that lived on a lost worker.
        gone = {self.workers[i] for i in shards}
        shards = sorted(i for i, w in enumerate(self.workers) if w in gone)
        self._lost = ShardLostError(shards, [self.workers[i] for i in shards], detail)
        return self._lost

    def _dead_shards(self) -> list:
        alive = set(_workers(self.client))
        return [i for i, w in enumerate(self.workers) if w not in alive]

    def _gather(self, pending: list, check_steps: bool = True) -> list:
        """Results of ``(shard, future)`` pairs (Dask futures or actor futures), in shard order.

        Waits in slices of :data:`POLL_SECONDS`; between slices it asks the scheduler which
        workers are alive, so a dead worker raises :class:`ShardLostError` instead of a hang.
        """
        from distributed import Future

        if pending and not isinstance(pending[0][1], Future):
            # Actor calls: one wait on the client's event loop for all of them (a blocking
            # wait per future costs a loop round trip each).
            results = self.client.sync(self._gather_async, list(pending))
        else:
            results = {}
            for i, fut in pending:
                while True:
                    try:
                        results[i] = fut.result(timeout=POLL_SECONDS)
                        break
                    except TimeoutError:
                        dead = self._dead_shards()
                        if dead:
                            raise self._lost_error(
                                dead, "worker no longer in the cluster"
                            ) from None
                    except Exception as exc:
                        self._raise_if_lost(i, exc)
                        raise
        out = [results[i] for i in sorted(results)]
        if check_steps:
            # A shard re-created behind our back would report fewer steps: never accept it.
            wrong = [i for steps, _ in out for i, k in steps.items() if k != self.steps]
            if wrong:
                raise self._lost_error(
                    wrong, f"a shard reported a step count other than the simulation's {self.steps}"
                )
        return out

    async def _gather_async(self, pending: list) -> dict:
        import asyncio

        async def one(fut):
            return await fut

        tasks = {asyncio.ensure_future(one(fut)): i for i, fut in pending}
        results = {}
        try:
            while tasks:
                done, _ = await asyncio.wait(
                    list(tasks), timeout=POLL_SECONDS, return_when=asyncio.FIRST_EXCEPTION
                )
                for task in done:
                    i = tasks.pop(task)
                    exc = task.exception()
                    if exc is not None:
                        self._raise_if_lost(i, exc)
                        raise exc
                    results[i] = task.result()
                if tasks and not done:
                    info = await self.client.scheduler.identity(n_workers=-1)
                    alive = set(info["workers"])
                    dead = [i for i, w in enumerate(self.workers) if w not in alive]
                    if dead:
                        raise self._lost_error(dead, "worker no longer in the cluster")
        finally:
            for task in tasks:
                task.cancel()
        return results

    def _raise_if_lost(self, i: int, exc: BaseException) -> None:
        """Raise :class:`ShardLostError` if ``exc`` says that shard ``i``'s worker is gone."""
        from distributed.comm.core import CommClosedError

        name = type(exc).__name__
        text = str(exc).lower()
        if (
            isinstance(exc, (OSError, CommClosedError))
            or name in ("CancelledError", "FutureCancelledError", "KilledWorker")
            or (isinstance(exc, RuntimeError) and ("lost" in text or "released" in text))
        ):
            raise self._lost_error([i], f"{name}: {exc}") from None

    def _call(self, method: str, *args: Any, workers: dict | None = None) -> list:
        """Call ``method(*args)`` on the actor of every worker (or of the given ones, a dict
        ``{worker: args}``) concurrently; ``[(steps, payload)]`` in worker order."""
        if self._lost is not None:
            raise self._lost
        if self._actors is None:
            raise RuntimeError("this DistributedSimulation is closed")
        if workers is None:
            workers = {w: args for w in self._actors}
        pending = [
            (self._groups[w][0], getattr(self._actors[w], method)(*a)) for w, a in workers.items()
        ]
        return self._gather(pending)

    # -- stepping -----------------------------------------------------------------------------
    def run(self, steps: int = 1) -> None:
        """Advance every shard ``steps`` steps of ``timestep`` seconds, in parallel.

        Returns when all shards are done. Raises :class:`ShardLostError` if a shard's worker
        died, and the shard's own ``ValueError`` for an invalid particle state.
        """
        if isinstance(steps, (bool, np.bool_)) or not isinstance(steps, numbers.Integral):
            raise TypeError(f"steps must be an integer, got steps={shown(steps)}")
        if steps < 0:
            raise ValueError(f"steps must be >= 0, got steps={shown(steps)}")
        if steps == 0:
            return
        if self._lost is not None:
            raise self._lost
        self.steps += int(steps)
        out = self._call("run", int(steps), list(self.force_generators))
        self.t = out[0][1][0]

    # -- reductions (small) ------------------------------------------------------------------
    def stats(self) -> SimulationStats:
        """Counts, energies and bounding boxes over all shards (a few numbers per shard)."""
        per = {}
        for _, payload in self._call("summary", list(self.force_generators)):
            per.update(payload)
        rows = [per[i] for i in range(self.shards)]
        bboxes = np.array([r[3] for r in rows], dtype=np.float64).reshape(-1, 4)
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            bbox = (
                float(np.nanmin(bboxes[:, 0])),
                float(np.nanmin(bboxes[:, 1])),
                float(np.nanmax(bboxes[:, 2])),
                float(np.nanmax(bboxes[:, 3])),
            )
        return SimulationStats(
            counts=tuple(int(r[0]) for r in rows),
            kinetic=float(sum(r[1] for r in rows)),
            potential=float(sum(r[2] for r in rows)),
            bboxes=bboxes,
            bbox=bbox,
        )

    def energy(self) -> dict[str, float]:
        """Energies by part, as :meth:`fastsdf.particles.ParticleSimulation.energy` names them
        (sums over shards, in shard order): ``kinetic``, ``potential`` (of the gravity
        generators), the parts particles do not hold (rotation, springs: 0) and ``total``."""
        st = self.stats()
        parts = {
            "kinetic": st.kinetic,
            "rotational": 0.0,
            "potential": st.potential,
            "normal_springs": 0.0,
            "tangential_springs": 0.0,
            "rolling_springs": 0.0,
        }
        parts["total"] = sum(parts.values())
        return parts

    def bounding_box(self) -> tuple:
        """``(xmin, ymin, xmax, ymax)`` of all particle centres (length units)."""
        return self.stats().bbox

    def density(
        self, bounds: ArrayLike = ((-2.0, 2.0), (-2.0, 2.0)), shape: tuple = (400, 400)
    ) -> np.ndarray:
        """Particle counts per pixel: the sum of the shards'
        :func:`fastsdf.viz.render.density_image` (float64, ``shape=(H, W)``, row 0 at the bottom,
        covering ``bounds``; exact integer counts, so the order of summation does not matter). Each
        worker sends one summed image: the client holds O(workers * H * W), not O(n)."""
        from fastsdf.viz.render import check_shape

        bounds = check_bounds(bounds)
        shape = check_shape(shape)
        total = np.zeros(shape)
        for _, image in self._call("density", bounds, shape):
            total += image
        return total

    def sample(self, k: int, seed: Any = None) -> dict:
        """``k`` particles drawn uniformly without replacement from all shards.

        Returns a dict of the fields ``x, v, m, r, cr, cf`` (float arrays of ``k`` rows) and
        ``index`` (their global indices, sorted; shard ``i`` holds the indices from
        ``sum(sizes[:i])``). Only the ``k`` rows travel. ``seed``: the draw's random seed
        (``None``: fresh entropy).
        """
        if (
            isinstance(k, (bool, np.bool_))
            or not isinstance(k, numbers.Integral)
            or not 0 <= k <= self.n
        ):
            raise ValueError(f"k must be an integer in [0, n={self.n}], got k={shown(k)}")
        from fastsdf.particles import Particles

        rng = np.random.default_rng(seed)
        index = np.sort(rng.choice(self.n, size=int(k), replace=False))
        starts = np.concatenate([[0], np.cumsum(self.sizes)])
        shard_of = np.searchsorted(starts, index, side="right") - 1
        asks = {}
        for i in np.unique(shard_of):
            i = int(i)
            asks.setdefault(self.workers[i], {})[i] = index[shard_of == i] - starts[i]
        parts = {}
        if asks:
            for _, payload in self._call("take", workers={w: (a,) for w, a in asks.items()}):
                parts.update(payload)
        out = {"index": index}
        for name in Particles.FIELDS:
            arrays = [parts[i][name] for i in sorted(parts)]
            out[name] = (
                np.concatenate(arrays)
                if arrays
                else np.zeros((0, 2) if name in ("x", "v") else (0,), self.dtype)
            )
        return out

    def gather(self) -> Any:
        """All particles on the client as one :class:`fastsdf.particles.Particles`, shards in
        order: O(n) memory, for tests and small runs only."""
        from fastsdf.particles import Particles

        parts = {}
        for _, payload in self._call("particles"):
            parts.update(payload)
        p = Particles(self.n, self.dtype)
        start = 0
        for i in range(self.shards):
            part = parts[i]
            for name in Particles.FIELDS:
                p[name][start : start + len(part)] = part[name]
            start += len(part)
        return p

    # -- lifetime -----------------------------------------------------------------------------
    def close(self) -> None:
        """Free the shards on the workers (idempotent)."""
        if self._actors is None:
            return
        futures = self._futures + [self._config_future]
        self._actors = None
        self._futures = []
        with contextlib.suppress(Exception):  # a closed client has nothing left to free
            self.client.cancel(futures)

    def __enter__(self) -> DistributedSimulation:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return (
            f"DistributedSimulation(n={self.n}, shards={self.shards}, "
            f"workers={len(set(self.workers))}, t={self.t:.4g}, steps={self.steps})"
        )


def local_cluster(workers: int = 2, threads_per_worker: int | None = None, **kwargs: Any) -> Any:
    """A ``dask.distributed.LocalCluster`` of ``workers`` processes on the loopback interface
    (127.0.0.1, no dashboard), ``threads_per_worker`` threads each (default: the machine's
    cores divided among the workers, at least 1). Close it (``with`` or ``.close()``)."""
    _require_dask()
    from distributed import LocalCluster

    if (
        isinstance(workers, (bool, np.bool_))
        or not isinstance(workers, numbers.Integral)
        or workers <= 0
    ):
        raise ValueError(f"workers must be a positive integer, got workers={shown(workers)}")
    if threads_per_worker is None:
        threads_per_worker = max(1, (os.cpu_count() or 1) // int(workers))
    options = dict(
        n_workers=int(workers),
        threads_per_worker=int(threads_per_worker),
        processes=True,
        host="127.0.0.1",
        dashboard_address="127.0.0.1:0",
    )
    options.update(kwargs)
    return LocalCluster(**options)


# ---------------------------------------------------------------------------------------------
# The demo on a LocalCluster (``python -m fastsdf demo --workers N``).


def _draw_density(ax: Any, image: np.ndarray, bounds: tuple, cax: Any = None) -> Any:
    """Show a density image (counts per pixel) as :func:`fastsdf.viz.render.draw_particles` does:
    the same colour map, logarithmic from 1 count, empty pixels transparent; with ``cax``, its
    colour bar of particles per pixel there."""
    from matplotlib.colors import LinearSegmentedColormap, LogNorm

    from fastsdf.viz.render import PARTICLE_CMAP_COLORS

    base = LinearSegmentedColormap.from_list("fastsdf_particles", list(PARTICLE_CMAP_COLORS))
    cmap = base.with_extremes(bad=(0.0, 0.0, 0.0, 0.0), under=(0.0, 0.0, 0.0, 0.0))
    (x0, x1), (y0, y1) = bounds
    shown = ax.imshow(
        np.ma.masked_less_equal(image, 0.0),
        origin="lower",
        extent=(x0, x1, y0, y1),
        cmap=cmap,
        norm=LogNorm(1.0, max(float(image.max()), 1.0 + 1e-9)),
        interpolation="nearest",
        alpha=0.8,
        zorder=4,
        aspect=ax.get_aspect(),
    )
    if cax is not None:
        from fastsdf.viz.render import plain_log_ticks

        cax.set_visible(True)
        plain_log_ticks(ax.figure.colorbar(shown, cax=cax, label="particles per pixel"))
    return shown


@dataclass(frozen=True)
class _Spawn:
    """The demo's ``init``: redraw the particles of shard ``i`` that start inside matter."""

    world: object
    seed: int

    def __call__(self, sim: Any, i: int) -> int:
        from fastsdf.apps.demo import spawn_in_free_space

        return spawn_in_free_space(sim, self.world, np.random.default_rng([self.seed, 1, i]))


def _density_video(
    sim: DistributedSimulation,
    f: Any,
    path: str,
    schedule: list[int],
    advance: Callable[[int], None],
    label: str,
    fps: int,
) -> None:
    """A video at ``path`` of ``sim`` over the world ``f``: its density image (only images
    travel from the workers) after each ``advance(k)`` of ``schedule``."""
    from matplotlib.animation import FuncAnimation

    from fastsdf.apps.demo import BOUNDS
    from fastsdf.viz.render import save_animation, world_figure

    shape = (480, 480)
    fig, ax, cax = world_figure(f, BOUNDS, 400, (6.4, 5.6), 100)
    artist = _draw_density(ax, sim.density(BOUNDS, shape), BOUNDS, cax)
    title = ax.set_title(label + "t = 0.00 s (step 0)")

    def update(i: int) -> tuple:
        advance(schedule[i])
        image = sim.density(BOUNDS, shape)
        artist.set_data(np.ma.masked_less_equal(image, 0.0))
        artist.norm.vmax = max(float(image.max()), 1.0 + 1e-9)
        title.set_text(f"{label}t = {sim.t:.2f} s (step {sim.steps})")
        return (artist,)

    anim = FuncAnimation(fig, update, frames=len(schedule), blit=False, repeat=False)
    save_animation(anim, path, fps=fps)


def _density_picture(sim: DistributedSimulation, f: Any, path: str, label: str) -> str:
    """A PNG at ``path`` of ``sim``'s density image over the world ``f``; returns ``path``."""
    from fastsdf.apps.demo import BOUNDS
    from fastsdf.viz.render import world_figure

    fig, ax, cax = world_figure(f, BOUNDS, 400, (6.4, 5.6), 100)
    _draw_density(ax, sim.density(BOUNDS, (600, 600)), BOUNDS, cax)
    ax.set_title(f"{label}t = {sim.t:.2f} s (step {sim.steps})")
    fig.savefig(path, dpi=100)
    return path


def run_demo(
    workers: int = 2,
    particles: int = 1_000_000,
    steps: int = 300,
    grid: int = 400,
    exact: bool = False,
    seed: int = 0,
    out: str = "demo-out",
    frames: int | None = None,
    fps: int | None = None,
    animate: bool = True,
    world: str = "boxes",
    mode: str = "exact",
    stream: Any = None,
    client: Any = None,
) -> Any:
    """:func:`fastsdf.apps.demo.run_demo` with the particles on a :func:`local_cluster` of
    ``workers`` processes (closed at the end), or on the cluster of ``client`` if given.

    Same parameters (``steps``, ``grid``, ``exact``, ``seed``, ``out``, ``frames``, ``fps``,
    ``animate``, ``world``, ``mode``, ``stream``) and result (a
    :class:`fastsdf.apps.demo.DemoResult`). The particles live on the
    workers, one shard per worker; each shard spawns its particles in free space there
    (:func:`fastsdf.apps.demo.spawn_in_free_space`); video frames and the last frame are drawn from
    :meth:`DistributedSimulation.density` images, so only images travel to this process, and
    the share of particles inside matter at the end is measured on a random sample of up to
    100,000 particles (:meth:`DistributedSimulation.sample`).
    """
    import matplotlib
    from distributed import Client

    from fastsdf.apps import demo as _demo
    from fastsdf.particles import Gravity

    matplotlib.use("Agg")
    frames = _demo.DEFAULT_FRAMES if frames is None else frames
    fps = _demo.DEFAULT_FPS if fps is None else fps
    _demo._check_demo_args(
        world, mode, animate, frames, steps, grid, fps, workers=workers, particles=particles
    )
    particles, steps, frames = int(particles), int(steps), int(frames)
    out = _demo.check_output_dir(out)
    qw = _demo.queried_world(world, grid, mode, exact, seed)
    f = qw.f
    with contextlib.ExitStack() as stack:
        if client is None:
            cluster = stack.enter_context(local_cluster(int(workers)))
            client = stack.enter_context(Client(cluster))
        workers = len(_workers(client))
        gravity = [Gravity(acceleration=(0.0, -1.0))]
        spawn = _Spawn(f, seed)
        sim = DistributedSimulation(
            qw.sdf, particles, client=client, seed=seed, force_generators=gravity, init=spawn
        )
        stack.enter_context(sim)
        qw.name += f", particles on {workers} Dask worker processes"
        timing = _demo._new_timing()

        def outside_share() -> float:
            # Particles inside the bounds, edges included: a 1x1 density image counts them.
            return 1.0 - float(sim.density(_demo.BOUNDS, (1, 1)).sum()) / particles

        def advance(k: int) -> None:
            _demo._timed_advance(sim, k, timing, outside_share)

        label = f"{particles:,} particles on {workers} workers, "
        animation_path = None
        if animate:
            ext = _demo._video_writer_ext(stream if stream is not None else sys.stderr)
            animation_path = os.path.join(out, "particles" + ext)
            schedule = _demo._frame_schedule(steps, frames)
            _density_video(sim, f, animation_path, schedule, advance, label, fps)
        advance(steps - timing["steps"])
        last = _density_picture(sim, f, os.path.join(out, "last_frame.png"), label)
        sample = sim.sample(min(particles, 100_000), seed=seed)
        respawned = int(sum(sim.init_results))
        dt = sim.dt
    load0 = timing.get("load0")
    return _demo.particle_result(
        qw,
        world,
        particles,
        timing,
        dt,
        sample["x"],
        sample["r"],
        respawned,
        animation_path,
        last,
        _demo._load_pair(load0, _demo._load()),
    )
