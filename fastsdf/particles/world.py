"""The world a simulation queries (an exact SDF, a pruned SDF, a grid or band grid, a moving
scene): what it is, its Lipschitz bound and margins, its parameters, the walls' speeds of a
moving world, and its generated step kernel module (its scene block:
:mod:`fastsdf.particles.scene_blocks`; the kernels: :mod:`fastsdf.particles.kernels`)."""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from fastsdf.backends import exact_source, load_module
from fastsdf.expr.validate import real
from fastsdf.particles import kernels as _kernels
from fastsdf.particles.scene_blocks import _is_grid, block_source, generated_module, world_scene
from fastsdf.version import __version__

__all__ = ["SimulationParams", "WALL_TABLE_CELLS", "wall_speed_table"]


def _exactness(f: Any) -> str:
    """``'exact'``, ``'bound'`` or ``'none'`` (see :attr:`fastsdf.SDF.exactness`) of the world
    (of a grid's exact SDF); ``'unknown'`` for a bare :class:`fastsdf.function.Function`."""
    g = f.exact if _is_grid(f) and f.exact is not None else f
    return getattr(g, "exactness", "unknown")


def _is_distance_bound(f: Any) -> bool:
    """Whether the world is known to be 1-Lipschitz (so that a grid of it is sqrt(2))."""
    return _exactness(f) in ("exact", "bound")


def _grid_margin(f: Any) -> float:
    """How far a grid in mode 'exact' may jump where it hands over to the exact SDF at its
    bounds: one node spacing bounds the bilinear error of an exact SDF (0 for SDFs and for
    grids in mode 'nearest', which are continuous)."""
    if not _is_grid(f) or f.mode != "exact":
        return 0.0
    spacing = getattr(f, "spacing", None)
    if spacing is None:
        try:
            (x0, x1), (y0, y1) = f.bounds
            nx, ny = f.shape
            spacing = ((x1 - x0) / (nx - 1), (y1 - y0) / (ny - 1))
        except (AttributeError, TypeError, ValueError):
            return 0.1  # unknown grid: a generous margin (skips fewer queries, stays exact)
    return float(max(abs(float(h)) for h in spacing))


_EXACT_OUT: dict = {}


def _step_source() -> tuple:
    """What a generated kernel module holds before and after its scene block (see
    :func:`fastsdf.particles.kernels.kernel_source`)."""
    return _kernels.HEAD, _kernels.TAIL


def _exact_address(exact: Any) -> tuple:
    """A C function ``void(double x, double y, double *out, double *h)`` evaluating the exact
    SDF (``h``: a plan header of :mod:`fastsdf.backends.prune`; a scene with loops over tables
    evaluates
    only the rows of the point's tile): the grid kernel's fallback outside the grid and the
    pruned particle step, bound at run time through its address so that the kernel does not
    depend on the scene. Returns ``(address, keepalive)``."""
    scene = exact.compiled.module.__name__
    entry = _EXACT_OUT.get(scene)
    if entry is None:
        rows = bool(exact.compiled.groups) and not exact.compiled.parametric
        source = exact_source(scene, rows, f"{__version__} (numba {numba.__version__})")
        mod = load_module(source, prefix="fastsdf_exactptr")
        entry = _EXACT_OUT[scene] = (int(mod.exact_out.address), mod)
    return entry


class SimulationParams(dict):
    """``sim.params``: the values of the world's runtime parameters (not time: the simulation
    sets ``t`` to its own clock). Assign ``sim.params['angle'] = 0.3`` between steps; the next
    step uses it without recompiling. Unknown names and non-finite values are refused.
    ``f``: the world (an SDF with parameters), whose current values start the mapping."""

    def __init__(self, f: Any) -> None:
        super().__init__({k: v for k, v in f.params.items() if k != "t"})
        self._names = tuple(f.param_names)

    def __setitem__(self, name: str, value: float) -> None:
        if name not in self:
            raise KeyError(
                f"unknown parameter {name!r}; the world's parameters are "
                f"{sorted(self) or 'none'} (time is sim.t)"
            )
        super().__setitem__(name, real(value, f"params[{name!r}]"))

    def update(self, *args: Any, **kwargs: float) -> None:
        """Set several values (each checked as by ``sim.params[name] = value``)."""
        for k, v in dict(*args, **kwargs).items():
            self[k] = v

    def as_tuple(self) -> tuple:
        """The values in the order the compiled step takes them (sorted names)."""
        return tuple(dict.__getitem__(self, n) for n in self._names)

    def __reduce__(self) -> tuple:
        # pickle restores a dict subclass's items through __setitem__ before its attributes,
        # which the name check would refuse: rebuild from the values and names instead.
        return _rebuild_params, (dict(self), self._names)


def _rebuild_params(values: dict, names: tuple) -> SimulationParams:
    params = SimulationParams.__new__(SimulationParams)
    dict.update(params, values)
    params._names = names
    return params


def _kernel_module(f: Any, forces: tuple = ()) -> tuple:
    """The generated kernel module for the world ``f`` (an SDF or a grid, see the sampler
    protocol in :mod:`fastsdf.particles.kernels`) and the fused user forces, and its query
    data.

    Returns ``(module, data, keepalive)``. The kernel's source is the kernels' bodies after
    this world's scene block (:mod:`fastsdf.particles.scene_blocks`); a grid world's block
    names only the sampler, so its kernel is shared by every scene.
    """
    scene = world_scene(f)
    source, late = block_source(scene, tuple(forces))
    module, keep = generated_module(source, late, scene.key, "fastsdf_particles")
    return module, scene.data, keep


# The table's resolution: at most this many cells a side over the particles' bounding box.
WALL_TABLE_CELLS = 64


class _NoParams:
    params: dict = {}
    param_names: tuple = ()


_NO_PARAMS = _NoParams()


def _finite_rows(a: np.ndarray) -> np.ndarray:
    """The rows of the ``(k, 2)`` array ``a`` whose two coordinates are finite."""
    return a[np.isfinite(a[:, 0]) & np.isfinite(a[:, 1])]


def wall_speed_table(
    f: Any, x: np.ndarray, r_max: float, t: float, dt: float, steps: int, prm: tuple
) -> tuple:
    """The global bound W and the per-region table of wall speeds for one call.

    ``|dd/dt|`` is sampled on the nodes of a grid over the bounding box of a sample of the
    particles (at most ``WALL_TABLE_CELLS`` cells a side) at the call's first and last step
    times (and up to 6 times between), each cell gets 1.5 times the largest sample at its
    corners, and the
    table is widened by one cell plus the distance a wall moving at W travels during the
    call: a particle whose surroundings do not move (far from every moving wall) gets 0
    and skips its queries as in a static scene. W is the largest value of the table and of
    the samples at the particles (the estimate used where the table does not reach:
    steps longer than a cell, particles outside the box).

    ``f``: the moving world (a time-dependent Function), ``x``: the particles' positions,
    ``r_max``: their largest radius, ``t``, ``dt``, ``steps``: the call's start time, timestep
    and number of steps, ``prm``: the values of the world's parameters. Returns ``(W, (x0, y0,
    1/h, table))``.
    """
    x = np.asarray(x, dtype=np.float64)
    # The table's box from a sample of the particles (one outside it uses W) and the
    # samples for W: both cheap next to a step of every particle.
    # (column by column: numpy's reductions along the short axis of (k, 2) arrays are slow)
    box = _finite_rows(x[:: max(1, x.shape[0] // 16384)])
    sample = _finite_rows(x[:: max(1, x.shape[0] // 4096)])
    if not box.size:
        box = np.zeros((1, 2))
    lo = np.array([box[:, 0].min(), box[:, 1].min()])
    hi = np.array([box[:, 0].max(), box[:, 1].max()])
    size = float(max(hi - lo))
    if not size > 0:
        size = float(r_max) * 4 or 1.0
    n = WALL_TABLE_CELLS
    h = size / (n - 4)
    x0, y0 = lo - 2 * h  # two cells of room on each side
    gx = x0 + h * np.arange(n + 1)
    gy = y0 + h * np.arange(n + 1)
    X, Y = (a.ravel() for a in np.meshgrid(gx, gy, indexing="ij"))
    X = np.ascontiguousarray(np.concatenate([X, sample[:, 0]]))
    Y = np.ascontiguousarray(np.concatenate([Y, sample[:, 1]]))
    m, nodes = X.shape[0], (n + 1) * (n + 1)
    count = min(steps, 8)
    times = t + dt * np.unique(np.round(np.linspace(1, steps, count)))
    top = np.zeros(m)
    for at in times:
        gt = f.compiled.run(X, Y, "vgt", t=float(at), params=prm)[2]
        top = np.maximum(top, np.abs(np.where(np.isfinite(gt), gt, np.inf)))
    node = top[:nodes]
    at_particles = top[nodes:]
    top_speed = 1.5 * float(at_particles[np.isfinite(at_particles)].max(initial=0.0))
    node = node.reshape(n + 1, n + 1)
    cell = 1.5 * np.maximum(
        np.maximum(node[:-1, :-1], node[1:, :-1]), np.maximum(node[:-1, 1:], node[1:, 1:])
    )
    wall = max(top_speed, float(cell[np.isfinite(cell)].max(initial=0.0)))
    cell = np.where(np.isfinite(cell), cell, wall)  # unknown there (a non-finite dd/dt)
    # walls at the sample times move up to W (t_gap) between them and W dt in a step
    gap = max(float(np.max(np.diff(times))) if len(times) > 1 else 0.0, dt)
    reach = 1 + int(math.ceil(wall * gap / h))
    wide = cell
    for _ in range(min(reach, n)):
        pad = np.pad(wide, 1, mode="edge")
        wide = np.maximum.reduce(
            [
                pad[1:-1, 1:-1],
                pad[:-2, 1:-1],
                pad[2:, 1:-1],
                pad[1:-1, :-2],
                pad[1:-1, 2:],
                pad[:-2, :-2],
                pad[2:, 2:],
                pad[:-2, 2:],
                pad[2:, :-2],
            ]
        )
    return wall, (float(x0), float(y0), 1.0 / h, np.ascontiguousarray(wide))
