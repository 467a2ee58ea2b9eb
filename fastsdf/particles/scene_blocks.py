"""The scene block of a generated step kernel module: what a world and the fused forces provide
to the kernels (``_query``, ``_fallback_missing``, ``_force``, ``MOVING``, ... as listed in
:mod:`fastsdf.particles.kernels`), written as source for the CPU's kernels (by kind of world:
a grid, a parametric or moving scene, a pruned scene, an exact scene) and for the GPU's thread
(:mod:`fastsdf.particles.cuda`), and the module generated from it (the kernels' bodies after the
block, cached by content hash).
"""

from __future__ import annotations

import hashlib
import importlib
import inspect
import sys
from typing import Any, NamedTuple

import numba
import numpy as np

from fastsdf.backends import call_vg_plan, hashed_import, load_module
from fastsdf.fields import grid as _grid
from fastsdf.function import Function
from fastsdf.introspect import show_field_types
from fastsdf.particles import kernels as _kernels
from fastsdf.version import __version__

__all__ = ["Scene", "world_scene", "device_scene", "force_lines", "generated_module"]

#: The decorator of the scene block's functions.
DECORATOR = '@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")'
#: Where a parametric world's parameters start in its query data: (t, W, x0, y0, 1/h, table,
#: *parameters). ``W`` bounds the walls' speed |dd/dt| everywhere; ``table[i, j]`` bounds it
#: over the cell of side h at (x0 + i h, y0 + j h) and its neighbours during the call (see
#: :func:`fastsdf.particles.world.wall_speed_table`). A step longer than a cell, or one ending
#: outside the table, uses W.
PARAMS_AT = 6
#: The table of a call without one (a static world, or a wall speed given).
NO_TABLE = np.zeros((0, 0))

# The call of a pruned C function with its plan header, imported where it is defined (with that
# module's hash: a change there changes every kernel that calls it).
_PLAN_IMPORT = hashed_import(call_vg_plan.__module__, [f"{call_vg_plan.__name__} as _call_vg_plan"])
# Generated modules whose scene block binds objects after import (no disk cache), by key.
_UNCACHED: dict = {}


@show_field_types
class Scene(NamedTuple):
    """A world's part of a scene block: ``lines`` (its imports and the definitions of
    ``_query``, ``_fallback_missing`` and the time functions), ``deps`` (what the kernel
    depends on, for the block's header), ``late`` (``(name, object)`` to bind after import:
    objects not importable by name), the query ``data``, a description ``desc``, the ``key``
    that names it among modules with late objects, and ``flags`` (``GRID_SIMD``,
    ``GRID_EXACT`` lines)."""

    lines: list
    deps: list
    late: list
    data: tuple
    desc: str
    key: tuple
    flags: list


def define(signature: str, *body: str) -> list:
    """A function of the scene block: the decorator, ``def signature:`` and its body."""
    return ["", "", DECORATOR, f"def {signature}:", *(f"    {line}" for line in body)]


def _is_grid(f: Any) -> bool:
    """Whether ``f`` is a grid of the sampler protocol (see :mod:`fastsdf.particles.kernels`)."""
    return all(hasattr(f, a) for a in ("sampler", "sampler_data", "exact", "mode"))


def _importable(fn: Any) -> tuple | None:
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


def _bind(fn: Any, alias: str) -> tuple:
    """The line binding the dispatcher ``fn`` as ``alias`` (its import, with its module in
    ``deps``) or, for a function that cannot be imported by name, a placeholder bound after
    import (``late``; such a module is never cached on disk). Returns ``(line, deps, late)``."""
    where = _importable(fn)
    # A function of __main__ (a script, a notebook) or without source may be redefined under
    # the same name: never cache a kernel that names it.
    if where is not None and (where[0] == "__main__" or _module_hash(where[0]) == "unknown"):
        where = None
    if where is None:
        return f"{alias} = None  # bound by fastsdf.particles", [], [(alias, fn)]
    deps = [f"{where[0]} (source {_module_hash(where[0])})"]
    return f"from {where[0]} import {where[1]} as {alias}", deps, []


def force_lines(forces: Any, ahead: bool = True) -> tuple:
    """Scene-block lines binding the fused user forces and the ``_force`` function that sums
    them, ``USE_FORCE`` and ``FORCE_AHEAD``; returns ``(lines, deps, late)`` (see
    :func:`_bind`). ``ahead``: whether the kernel may evaluate long-latency forces ahead of
    their steps (the GPU's thread evaluates them inline)."""
    lines, deps, late = [], [], []
    for k, fn in enumerate(forces):
        line, dep, bound = _bind(fn, f"_uf{k}")
        lines.append(line)
        deps += dep
        late += bound
    body = ["fx = 0.0", "fy = 0.0"] if forces else []
    for k in range(len(forces)):
        body += [f"ax, ay = _uf{k}(x, y, vx, vy, m, t)", "fx += ax", "fy += ay"]
    result = "return fx, fy" if forces else "return 0.0, 0.0"
    lines += define("_force(x, y, vx, vy, m, t)", *body, result)
    batched = ahead and any(getattr(fn, "_fastsdf_batched", False) for fn in forces)
    lines += ["", "", f"USE_FORCE = {bool(forces)}", f"FORCE_AHEAD = {batched}"]
    return lines, deps, late


def _static_time() -> list:
    """A world that does not move: no time derivative, no wall speed."""
    return (
        ["", "", "MOVING = False"]
        + define(
            "_query_t(data, x, y, t)", "d, gx, gy = _query(data, x, y)", "return d, gx, gy, 0.0"
        )
        + define("_wall_speed(data)", "return 0.0")
        + define("_wall_speed_at(data, x, y, dx, dy)", "return 0.0")
    )


def _moving_time(scene: str, params: str, wall: str, wall_at: list) -> list:
    """A world that moves: ``_query_t`` through the scene's ``point_vgt`` with the parameters
    ``params`` (an expression of ``data``), and the wall speed bounds ``wall`` (an expression)
    and ``wall_at`` (a body)."""
    return (
        [f"from {scene} import point_vgt as _exact_t"]
        + define("_query_t(data, x, y, t)", f"return _exact_t(x, y, t, {params})")
        + define("_wall_speed(data)", f"return {wall}")
        + define("_wall_speed_at(data, x, y, dx, dy)", *wall_at)
        + ["", "", "MOVING = True"]
    )


# ---------------------------------------------------------------------------------------------
# The CPU's scene blocks, by kind of world.


def _grid_scene(f: Any) -> Scene:
    """A grid world: its sampler, and its exact fallback called through a C function address
    carried in the data (bound when first needed, see :mod:`fastsdf.particles.kernels`), so the
    block names only the sampler and its kernel is shared by every scene."""
    exact = f.exact
    mode = f.mode
    if mode == "exact" and not isinstance(exact, Function):
        raise TypeError(f"grid.exact must be a fastsdf Function, got {exact!r}")
    if mode not in ("exact", "nearest"):
        raise ValueError(f"grid mode must be 'exact' or 'nearest', got mode={mode!r}")
    line, deps, late = _bind(f.sampler, "_sampler")
    # data: (fallback address, bounds x4, *sampler_data, plan header address); the sampler's
    # data length is fixed by its kind (dense grid, band grid), as is the kernel.
    hdr = 5 + len(f.sampler_data)
    query = [f"d, gx, gy, inside = _sampler(data[5:{hdr}], x, y)"]
    missing = ["return False"]
    lines = [line]
    if mode == "exact":
        lines = [_PLAN_IMPORT] + lines
        query += [
            "if not inside:",
            "    if data[0] == 0:  # never reached: see _fallback_missing",
            "        return math.nan, math.nan, math.nan",
            f"    return _call_vg_plan(data[0], x, y, data[{hdr}])",
        ]
        missing = [
            "bounds = (data[1], data[2], data[3], data[4])",
            "return data[0] == 0 and outside_reach(x, y, dx, dy, bounds)",
        ]
    lines += define("_query(data, x, y)", *query, "return d, gx, gy")
    lines += define("_fallback_missing(data, x, y, dx, dy)", *missing)
    # Without bounds (optional in the protocol) the fallback is bound at once.
    (bx0, bx1), (by0, by1) = getattr(f, "bounds", None) or ((0.0, 0.0), (0.0, 0.0))
    bounds = (float(bx0), float(bx1), float(by0), float(by1))
    # the last entry: the address of the fallback's plan header (bound with the fallback)
    data = (0,) + bounds + tuple(f.sampler_data) + (0,)
    # The block step (the simd variant) is written for the dense grid's stored-gradient sampler.
    simd = f.sampler is _grid.sample_stored and len(f.sampler_data) == 9
    desc = f"a grid world (mode {mode!r}); the scene is bound at run time"
    flags = [f"GRID_SIMD = {simd}", f"GRID_EXACT = {mode == 'exact'}"]
    return Scene(lines, deps, late, data, desc, ("grid", id(f.sampler), mode), flags)


_WALL_SPEED_AT = [
    "tab = data[5]",
    "u = (x - data[2]) * data[4]",
    "v = (y - data[3]) * data[4]",
    "if (u >= 0.0 and v >= 0.0 and u < tab.shape[0] and v < tab.shape[1]",
    "        and (dx * dx + dy * dy) * (data[4] * data[4]) <= 1.0):",
    "    return tab[int(u), int(v)]",
    "return data[1]",
]


def _parametric_scene(f: Function) -> Scene:
    """A scene with runtime parameters, and time (a moving world): parameters and time are
    data, set per call (one flat tuple of floats: the parallel kernel cannot take nested
    tuples)."""
    scene = f.compiled.module.__name__
    k = PARAMS_AT
    lines = [f"from {scene} import point_vg as _exact"]
    lines += define("_query(data, x, y)", f"return _exact(x, y, data[0], data[{k}:])")
    lines += define("_fallback_missing(data, x, y, dx, dy)", "return False")
    if f.time_dependent:
        lines += _moving_time(scene, f"data[{k}:]", "data[1]", _WALL_SPEED_AT)
    data = (0.0, 0.0, 0.0, 0.0, 1.0, NO_TABLE) + f.param_tuple()
    return Scene(lines, [scene], [], data, repr(f)[:300], ("sdf", id(f.compiled.module)), [])


def _pruned_scene(f: Function) -> Scene:
    """A scene with many operands in loops over tables: the step calls the scene's C function
    with the plan header (``data[1]``), which evaluates only the rows of the query point's
    tile."""
    scene = f.compiled.module.__name__
    lines = [_PLAN_IMPORT]
    lines += define("_query(data, x, y)", "return _call_vg_plan(data[0], x, y, data[1])")
    lines += define("_fallback_missing(data, x, y, dx, dy)", "return False")
    # data: (address of the C function, of the plan header): bound at once
    desc = repr(f)[:300] + " (pruned)"
    return Scene(lines, [scene], [], (0, 0), desc, ("sdf-pruned", id(f.compiled.module)), [])


def _exact_scene(f: Function) -> Scene:
    """A scene evaluated by its own per-point function, inlined into the step."""
    scene = f.compiled.module.__name__
    lines = [f"from {scene} import point_vg as _exact"]
    lines += define("_query(data, x, y)", "return _exact(x, y)")
    lines += define("_fallback_missing(data, x, y, dx, dy)", "return False")
    return Scene(lines, [scene], [], (0.0,), repr(f)[:300], ("sdf", id(f.compiled.module)), [])


def _prunes(f: Function) -> bool:
    """Whether the particle step on the SDF ``f`` evaluates per-tile row lists, decided when
    the step is built (see :meth:`fastsdf.function.CompiledSDF.prunable`)."""
    return bool(f.compiled.prunable(getattr(f, "prune_tol", None)))


def world_scene(f: Any) -> Scene:
    """The CPU kernels' scene of the world ``f`` (an SDF or a grid of the sampler protocol in
    :mod:`fastsdf.particles.kernels`); a TypeError for anything else."""
    if _is_grid(f):
        return _grid_scene(f)
    if isinstance(f, Function) and f.compiled.parametric:
        return _parametric_scene(f)
    if isinstance(f, Function) and _prunes(f):
        return _pruned_scene(f)
    if isinstance(f, Function):
        return _exact_scene(f)
    raise TypeError(
        f"f must be a fastsdf SDF (Function) or GridSDF, got f={f!r} of type {type(f).__name__}"
    )


# ---------------------------------------------------------------------------------------------
# The GPU thread's scene block.


def device_scene(f: Any, unsupported: Any) -> Scene:
    """The GPU thread's scene of the world ``f``, in code numba-cuda compiles: a dense grid
    calls its sampler and, outside it in mode 'exact', the scene's point function (the CPU's
    block calls that through a C function address); an SDF its point function, without
    pruning (the same values). A moving world is evaluated with its time derivative, without
    wall speed bounds (the sweep and skipping of moving worlds do not run on the device).
    ``data`` holds the host arrays the query reads (copied to the device once); ``key`` names
    the compiled kernel. ``unsupported(what)``: the error for a world the GPU cannot step."""
    if _is_grid(f):
        sampler = f.sampler
        if sampler is not _grid.sample_stored and sampler is not _grid.sample_fd:
            name = getattr(sampler, "__name__", sampler)
            raise unsupported(
                f"the world {type(f).__name__} (sampler {name}): only a dense GridSDF or an "
                "exact SDF"
            )
        lines = [f"from {sampler.__module__} import {sampler.__name__} as _sampler"]
        query = ["d, gx, gy, inside = _sampler(data, x, y)"]
        scene = None
        if f.mode == "exact":
            if f.exact.compiled.parametric:
                raise unsupported("a grid whose exact SDF has runtime parameters")
            scene = f.exact.compiled.module.__name__
            lines.append(f"from {scene} import point_vg as _exact")
            query += ["if not inside:", "    return _exact(x, y)"]
        lines += define("_query(data, x, y)", *query, "return d, gx, gy")
        arrays = tuple(a for a in f.sampler_data if isinstance(a, np.ndarray))
        key: tuple = ("grid", sampler.__name__, f.mode, scene)
    elif isinstance(f, Function):
        comp = f.compiled
        scene = comp.module.__name__
        lines = [f"from {scene} import point_vg as _exact"]
        # a parametric world's launch argument is the tuple of its parameters' values
        call = "return _exact(x, y, 0.0, data)" if comp.parametric else "return _exact(x, y)"
        lines += define("_query(data, x, y)", call)
        arrays = ()
        key = ("sdf", scene)
        if comp.parametric and f.time_dependent:
            lines += _moving_time(scene, "data", "0.0", ["return 0.0"])
    else:
        raise TypeError(
            f"f must be a fastsdf SDF (Function) or GridSDF, got f={f!r} of type {type(f).__name__}"
        )
    lines += define("_fallback_missing(data, x, y, dx, dy)", "return False")
    flags = ["GRID_SIMD = False", "GRID_EXACT = False"]
    return Scene(lines, [], [], arrays, "", key, flags)


# ---------------------------------------------------------------------------------------------
# The generated module.


def block_source(scene: Scene, forces: tuple, ahead: bool = True, title: str = "") -> tuple:
    """The source of the kernel module of ``scene`` and the fused user ``forces`` (the shared
    imports, the scene block, the kernels' bodies) and the objects to bind after import."""
    f_lines, f_deps, f_late = force_lines(forces, ahead)
    late = scene.late + f_late
    lines = scene.lines
    if "MOVING = True" not in lines:
        lines = lines + _static_time()
    desc = scene.desc.replace("\n", " ")
    head = [
        title or f"# Scene block generated by fastsdf {__version__} (numba {numba.__version__}).",
        f"# World: {desc}",
        f"# Dependencies: {'; '.join(scene.deps + f_deps) or 'none'}",
        f"_CACHE = {not late}",
        *(scene.flags or ["GRID_SIMD = False", "GRID_EXACT = False"]),
        "",
    ]
    block = "\n".join(head + lines + [""] + f_lines) + "\n"
    return _kernels.kernel_source(block), late


def generated_module(source: str, late: list, key: tuple, prefix: str) -> tuple:
    """The module of ``source``, loaded from the kernel cache (file names start with
    ``prefix``); with objects to bind after import (``late``), a module of its own per set of
    objects and ``key`` (kept, with them alive, so their ids are not reused meanwhile).
    Returns ``(module, keepalive)``."""
    if not late:
        return load_module(source, prefix=prefix), None
    key = (prefix,) + key + tuple(id(obj) for _, obj in late)
    entry = _UNCACHED.get(key)
    if entry is None:
        mod = load_module(source + f"\n# uncached instance {len(_UNCACHED)}\n", prefix=prefix)
        for name, obj in late:
            setattr(mod, name, obj)
        entry = _UNCACHED[key] = (mod, [obj for _, obj in late])
    return entry
