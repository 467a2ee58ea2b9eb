"""The world a simulation queries (an exact SDF, a pruned SDF, a grid or band grid, a moving
scene): what it is, its Lipschitz bound and margins, its parameters, and the scene block of the
generated step kernel module (see :mod:`fastsdf.particles.kernels`)."""

from __future__ import annotations

import hashlib
import importlib
import inspect
import math
import sys
from typing import Any

import numba
import numpy as np

from fastsdf.backends import call_vg_plan, exact_source, hashed_import, load_module
from fastsdf.expr.validate import real
from fastsdf.fields import grid as _grid
from fastsdf.function import Function
from fastsdf.particles import kernels as _kernels
from fastsdf.version import __version__

__all__ = ["SimulationParams", "WALL_TABLE_CELLS", "wall_speed_table"]


def _is_grid(f: Any) -> bool:
    return all(hasattr(f, a) for a in ("sampler", "sampler_data", "exact", "mode"))


def _importable(fn):
    """``(module, name)`` if the dispatcher ``fn`` can be imported by name, else None."""
    py = getattr(fn, "py_func", None)
    if py is None:
        return None
    mod_name, name = py.__module__, py.__name__
    try:
        mod = sys.modules.get(mod_name) or importlib.import_module(mod_name)
    except ImportError:
        return None
    if getattr(mod, name, None) is not fn:
        return None
    return mod_name, name


def _module_hash(mod_name: str) -> str:
    try:
        src = inspect.getsource(sys.modules[mod_name])
    except (OSError, TypeError, KeyError):
        return "unknown"
    return hashlib.sha256(src.encode()).hexdigest()[:16]


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


_KERNELS: dict = {}
_EXACT_OUT: dict = {}

_DECORATOR = '@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")'


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


def _prunes(f: Any) -> bool:
    """Whether the particle step on the SDF ``f`` evaluates per-tile row lists (a scene with
    at least ``PRUNE_MIN_OPERANDS`` operands in loops over tables, without parameters, and not
    only exponential blends with ``f.prune_tol`` unset), decided when the step is built."""
    from fastsdf import function as _function

    comp = f.compiled
    if comp.parametric:
        return False
    groups = comp.groups or ()
    if getattr(f, "prune_tol", None) is None and all(g["op"] in ("smin", "smax") for g in groups):
        return False  # exponential blends at half an ulp: next to nothing to drop
    return sum(len(g["members"]) for g in groups) >= _function.PRUNE_MIN_OPERANDS


# The call of a pruned C function with its plan header, imported where it is defined (with that
# module's hash: a change there changes every kernel that calls it).
_PLAN_IMPORT = hashed_import(call_vg_plan.__module__, [f"{call_vg_plan.__name__} as _call_vg_plan"])


def _force_parts(forces: Any, ahead: bool = True) -> tuple:
    """Scene-block lines binding the fused user forces and the ``_force`` function; names of
    forces that must be bound after import (not importable: no disk cache). ``ahead``: whether
    the kernel may evaluate long-latency forces ahead of their steps (``FORCE_AHEAD``; the
    GPU's thread evaluates them inline)."""
    lines, deps, late = [], [], []
    for k, fn in enumerate(forces):
        where = _importable(fn)
        # A function of __main__ (a script, a notebook) or without source may be redefined
        # under the same name: never cache a kernel that names it.
        if where is not None and (where[0] == "__main__" or _module_hash(where[0]) == "unknown"):
            where = None
        if where is None:
            lines.append(f"_uf{k} = None  # bound by fastsdf.particles")
            late.append((f"_uf{k}", fn))
        else:
            lines.append(f"from {where[0]} import {where[1]} as _uf{k}")
            deps.append(f"{where[0]} (source {_module_hash(where[0])})")
    body = [_DECORATOR, "def _force(x, y, vx, vy, m, t):"]
    if not forces:
        body.append("    return 0.0, 0.0")
    else:
        body += ["    fx = 0.0", "    fy = 0.0"]
        for k in range(len(forces)):
            body += [f"    ax, ay = _uf{k}(x, y, vx, vy, m, t)", "    fx += ax", "    fy += ay"]
        body.append("    return fx, fy")
    lines += ["", ""] + body
    lines.append(f"USE_FORCE = {bool(forces)}")
    batched = ahead and any(getattr(fn, "_fastsdf_batched", False) for fn in forces)
    lines.append(f"FORCE_AHEAD = {batched}")
    return lines, deps, late


# A world that does not move: no time derivative, no wall speed.
_STATIC_TIME_LINES = [
    "",
    "",
    "MOVING = False",
    "",
    "",
    _DECORATOR,
    "def _query_t(data, x, y, t):",
    "    d, gx, gy = _query(data, x, y)",
    "    return d, gx, gy, 0.0",
    "",
    "",
    _DECORATOR,
    "def _wall_speed(data):",
    "    return 0.0",
    "",
    "",
    _DECORATOR,
    "def _wall_speed_at(data, x, y, dx, dy):",
    "    return 0.0",
]

# Query data of a parametric world: (t, W, x0, y0, 1/h, table, *parameters). ``W`` bounds the
# walls' speed |dd/dt| everywhere; ``table[i, j]`` bounds it over the cell of side h at
# (x0 + i h, y0 + j h) and its neighbours during the call (see _wall_speed_table). A step
# longer than a cell, or one ending outside the table, uses W.
_PARAMS_AT = 6
_WALL_SPEED_AT_LINES = [
    "def _wall_speed_at(data, x, y, dx, dy):",
    "    tab = data[5]",
    "    u = (x - data[2]) * data[4]",
    "    v = (y - data[3]) * data[4]",
    "    if (u >= 0.0 and v >= 0.0 and u < tab.shape[0] and v < tab.shape[1]",
    "            and (dx * dx + dy * dy) * (data[4] * data[4]) <= 1.0):",
    "        return tab[int(u), int(v)]",
    "    return data[1]",
]
_NO_TABLE = np.zeros((0, 0))
# The table's resolution: at most this many cells a side over the particles' bounding box.
WALL_TABLE_CELLS = 64


class SimulationParams(dict):
    """``sim.params``: the values of the world's runtime parameters (not time: the simulation
    sets ``t`` to its own clock). Assign ``sim.params['angle'] = 0.3`` between steps; the next
    step uses it without recompiling. Unknown names and non-finite values are refused."""

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


def _kernel_module(f, forces=()):
    """The generated kernel module for the world ``f`` (an SDF or a grid, see the sampler
    protocol in :mod:`fastsdf.particles.kernels`) and the fused user forces, and its query
    data.

    Returns ``(module, data, keepalive)``. The kernel's source is the kernels' bodies after
    this world's scene block; a grid world's block names only the sampler, so its kernel is
    shared by every scene.
    """
    late = []
    keep = None
    # The block step (the simd variant) is written for the dense grid's stored-gradient sampler.
    grid_simd = False
    grid_exact = False
    if _is_grid(f):
        exact = f.exact
        if f.mode == "exact" and not isinstance(exact, Function):
            raise TypeError(f"grid.exact must be a fastsdf Function, got {exact!r}")
        mode = f.mode
        if mode not in ("exact", "nearest"):
            raise ValueError(f"grid mode must be 'exact' or 'nearest', got mode={mode!r}")
        sampler = f.sampler
        grid_simd = sampler is _grid.sample_stored and len(f.sampler_data) == 9
        grid_exact = mode == "exact"
        where = _importable(sampler)
        if where is None:
            lines = ["_sampler = None  # bound by fastsdf.particles"]
            late.append(("_sampler", sampler))
            deps = []
        else:
            lines = [f"from {where[0]} import {where[1]} as _sampler"]
            deps = [f"{where[0]} (source {_module_hash(where[0])})"]
        # data: (fallback address, bounds x4, *sampler_data, plan header address); the
        # sampler's data length is fixed by its kind (dense grid, band grid), as is the kernel.
        hdr = 5 + len(f.sampler_data)
        lines += [
            "",
            "",
            _DECORATOR,
            "def _query(data, x, y):",
            f"    d, gx, gy, inside = _sampler(data[5:{hdr}], x, y)",
        ]
        if mode == "exact":
            lines = [_PLAN_IMPORT] + lines
            lines += [
                "    if not inside:",
                "        if data[0] == 0:  # never reached: see _fallback_missing",
                "            return math.nan, math.nan, math.nan",
                f"        return _call_vg_plan(data[0], x, y, data[{hdr}])",
            ]
        lines.append("    return d, gx, gy")
        lines += ["", "", _DECORATOR, "def _fallback_missing(data, x, y, dx, dy):"]
        if mode == "exact":
            # Every query of a step (its sweep and bounces included) lies within
            # 2 (MAX_BOUNCES + 1) |D| of its start.
            lines += [
                "    if data[0] != 0:",
                "        return False",
                "    reach = 2.0 * (MAX_BOUNCES + 1) * math.sqrt(dx * dx + dy * dy) + 1e-9",
                "    return not (x - reach >= data[1] and x + reach <= data[2]",
                "                and y - reach >= data[3] and y + reach <= data[4])",
            ]
        else:
            lines.append("    return False")
        address = 0
        # Without bounds (optional in the protocol) the fallback is bound at once.
        (bx0, bx1), (by0, by1) = getattr(f, "bounds", None) or ((0.0, 0.0), (0.0, 0.0))
        # the last entry: the address of the fallback's plan header (bound with the fallback)
        data = (
            (address, float(bx0), float(bx1), float(by0), float(by1)) + tuple(f.sampler_data) + (0,)
        )
        desc = f"a grid world (mode {mode!r}); the scene is bound at run time"
        key = ("grid", id(sampler), mode)
    elif isinstance(f, Function) and f.compiled.parametric:
        # Parameters and time are data, set per call: (t, wall speed bound, *parameters), one
        # flat tuple of floats (the parallel kernel cannot take nested tuples).
        scene = f.compiled.module.__name__
        k = _PARAMS_AT
        lines = [
            f"from {scene} import point_vg as _exact",
            "",
            "",
            _DECORATOR,
            "def _query(data, x, y):",
            f"    return _exact(x, y, data[0], data[{k}:])",
            "",
            "",
            _DECORATOR,
            "def _fallback_missing(data, x, y, dx, dy):",
            "    return False",
        ]
        if f.time_dependent:
            lines += (
                [
                    f"from {scene} import point_vgt as _exact_t",
                    "",
                    "",
                    _DECORATOR,
                    "def _query_t(data, x, y, t):",
                    f"    return _exact_t(x, y, t, data[{k}:])",
                    "",
                    "",
                    _DECORATOR,
                    "def _wall_speed(data):",
                    "    return data[1]",
                    "",
                    "",
                    _DECORATOR,
                ]
                + _WALL_SPEED_AT_LINES
                + ["", "", "MOVING = True"]
            )
        deps = [scene]
        data = (0.0, 0.0, 0.0, 0.0, 1.0, _NO_TABLE) + f.param_tuple()
        desc = repr(f)[:300]
        key = ("sdf", id(f.compiled.module))
    elif isinstance(f, Function) and _prunes(f):
        # Many operands in loops over tables: the step calls the scene's C function with the
        # plan header (data[1]), which evaluates only the rows of the query point's tile.
        scene = f.compiled.module.__name__
        lines = [
            _PLAN_IMPORT,
            "",
            "",
            _DECORATOR,
            "def _query(data, x, y):",
            "    return _call_vg_plan(data[0], x, y, data[1])",
            "",
            "",
            _DECORATOR,
            "def _fallback_missing(data, x, y, dx, dy):",
            "    return False",
        ]
        deps = [scene]
        data = (0, 0)  # (address of the C function, of the plan header): bound at once
        desc = repr(f)[:300] + " (pruned)"
        key = ("sdf-pruned", id(f.compiled.module))
    elif isinstance(f, Function):
        scene = f.compiled.module.__name__
        lines = [
            f"from {scene} import point_vg as _exact",
            "",
            "",
            _DECORATOR,
            "def _query(data, x, y):",
            "    return _exact(x, y)",
            "",
            "",
            _DECORATOR,
            "def _fallback_missing(data, x, y, dx, dy):",
            "    return False",
        ]
        deps = [scene]
        data = (0.0,)
        desc = repr(f)[:300]
        key = ("sdf", id(f.compiled.module))
    else:
        raise TypeError(
            f"f must be a fastsdf SDF (Function) or GridSDF, got f={f!r} of type {type(f).__name__}"
        )
    if "MOVING = True" not in lines:
        lines += _STATIC_TIME_LINES
    force_lines, force_deps, force_late = _force_parts(forces)
    late += force_late
    deps += force_deps
    desc = desc.replace("\n", " ")
    block = (
        [
            f"# Scene block generated by fastsdf {__version__} (numba {numba.__version__}).",
            f"# World: {desc}",
            f"# Dependencies: {'; '.join(deps) or 'none'}",
            f"_CACHE = {not late}",
            f"GRID_SIMD = {grid_simd}",
            f"GRID_EXACT = {grid_exact}",
            "",
        ]
        + lines
        + [""]
        + force_lines
    )
    source = _kernels.kernel_source("\n".join(block) + "\n")
    if late:
        # One module per set of objects; the entry keeps them alive, so their ids are not
        # reused while the entry exists.
        key = key + tuple(id(obj) for _, obj in late)
        entry = _KERNELS.get(key)
        if entry is None:
            mod = load_module(
                source + f"\n# uncached instance {len(_KERNELS)}\n", prefix="fastsdf_particles"
            )
            for name, obj in late:
                setattr(mod, name, obj)
            entry = _KERNELS[key] = (mod, [obj for _, obj in late])
        return entry[0], data, (keep, entry[1])
    return load_module(source, prefix="fastsdf_particles"), data, keep


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
    # the serial kernel: a few thousand points are not worth waking the threads
    kernel = f.compiled.kernel("vgt", parallel=False)
    out, grad, gt = np.empty(m), np.empty((m, 2)), np.empty(m)
    count = min(steps, 8)
    times = t + dt * np.unique(np.round(np.linspace(1, steps, count)))
    top = np.zeros(m)
    for at in times:
        kernel(X, Y, out, grad, gt, float(at), prm)
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
