"""Particles colliding with signed distance functions: the notebook's ``phys`` module, compiled.

``import fastsdf.particles as phys`` gives the notebook's interface::

    sim = phys.ParticleSimulation(f, n=100, timestep=1/30, seed=0)
    sim.force_generators += [phys.Gravity()]          # fused into the compiled step
    anim = phys.create_animation(fig, ax, sim, frames=300, repeat=True, use_wall_time=False)
    sim.run(1000)                                     # 1000 steps in compiled code

Units and conventions. Lengths are in the SDF's coordinate units, time in seconds, mass in any
consistent unit; velocities are length/s, accelerations length/s**2, forces mass*length/s**2.
The SDF is negative inside solid matter and positive in free space; a particle is a disc of
radius ``r`` around ``x`` and is in contact where ``d(x) - r <= 0``. Particles do not interact
with each other and do not rotate.

One step (``timestep`` seconds), for every particle, in one fused compiled loop:

1. forces: fused :class:`Gravity` (``m * acceleration``), :class:`Drag` (``-c v``) and user
   forces written as numba functions ``@njit def f(x, y, vx, vy, m, t) -> (fx, fy)`` (in
   mass * length / s**2, at the particle's state before the step and the step's start time
   ``t``), compiled into the step; plus the sum of any Python force generators
   ``(p, t) -> (n, 2)`` (evaluated with NumPy before each compiled step: the slow path);
2. integration: semi-implicit (symplectic) Euler ``v += f/m dt; x += v dt`` (the default), or
   the notebook's explicit Euler ``x += v dt; v += f/m dt`` (``integrator='euler'``);
3. tunnelling check (``prevent_tunnelling=True``, the default): a particle moving farther than
   ``TRACE_FRACTION * r`` in the step, whose end point is not clear of every surface by the
   step's length, is swept along its displacement by conservative advancement (sphere tracing
   with the SDF's Lipschitz bound ``lipschitz``: 1 for SDFs, sqrt(2) for bilinear grids); at a
   contact the remaining displacement and the velocity are reflected with the response below,
   so it cannot pass through a thin wall. (A step shorter than half the radius cannot carry a
   disc that penetrates by less than half its radius across the middle of a wall, which is why
   short steps need no sweep);
4. collision response at the end point (House & Keyser): with ``s = d - r <= 0`` and
   ``n = grad d / |grad d|``: ``x -= (1 + cr) s n``; ``v = -cr v_n + (1 - cf) v_t``. By default
   the velocity responds only when ``v . n < 0`` (approaching; ``collision='approaching'``):
   a particle already separating is only pushed out, never turned back into the wall.
   ``collision='notebook'`` responds to the velocity whenever ``s <= 0``, as the notebook did.

``integrator='euler', collision='notebook', prevent_tunnelling=False`` reproduces the notebook's
``advance()`` (to rounding; :func:`reference_step` is that step in NumPy).

Why semi-implicit Euler is the default: it is symplectic, so its energy error stays bounded (of
the order of the work gravity does in one step) instead of accumulating, and a particle resting
on a floor stays within ``cr * g * dt**2`` of it. Explicit Euler moves a particle with the
previous step's velocity and gains energy at every bounce: at ``dt = 1/30`` a ball with
``cr = 0.8`` rebounds to 0.69-0.78 of its height instead of 0.64, and a "resting" particle with
``cr`` near 1 climbs without bound. Both cost the same.

Speed. The step skips the SDF query of a particle whose last query proved it clear of every
surface by more than it has moved since (a budget of ``(d - r) / lipschitz``, kept per
particle during one :meth:`ParticleSimulation.run` call); a skipped query is one that would have
found no contact, so the results are the same bits whatever the grouping of steps into calls.
:meth:`ParticleSimulation.run` runs all its steps on a block of :data:`DEFAULT_BLOCK` particles
while the block is in cache, so main memory is crossed about once per call, not once per step.

Memory: the state is structure-of-arrays (``x``, ``v``: (n, 2); ``m``, ``r``, ``cr``, ``cf``:
(n,)), 64 bytes per particle in float64 and 32 in float32 (``dtype=np.float32``; the arithmetic
is float64 either way). A step must read ``x``, ``v``, ``r`` and write ``x``, ``v``: 72 bytes
per particle in float64 (80 with drag, which reads ``m``), 36 in float32; ``cr`` and ``cf`` are
read only for particles in contact. The state is checked on the values a step loads anyway
(see :meth:`ParticleSimulation.run`); ``m``, ``cr``, ``cf`` are re-read in full only at the
first call after they were handed out through ``p`` (24 bytes per particle, once). The 8-byte
free-flight budget lives in a scratch array of one block.

The step kernel is the module :mod:`fastsdf._step` (readable, tested directly); each world gets a
copy with its query and fused forces in place, cached on disk by content hash. A grid world
with stored gradients and float64 state steps blocks of particles in vector passes (see
"Kernels" in :class:`ParticleSimulation`). A grid world's
kernel does not depend on the scene (its exact fallback is bound at run time), so it compiles
once per installation.
"""

from __future__ import annotations

import hashlib
import importlib
import inspect
import math
import numbers
import sys
import time
import warnings

import numba
import numpy as np
from typing import Any, Sequence
from numpy.typing import ArrayLike
from numba.core.dispatcher import Dispatcher

from fastsdf.expr.validate import real
from fastsdf.expr.validate import vec2 as _vec2
from fastsdf.version import __version__
from fastsdf.backends.kernel.cache import load_module
from fastsdf import _step
from fastsdf.fields import grid as _grid
from fastsdf.backends import prune as _prune
from fastsdf._step import CONTACT_TOL, MAX_BOUNCES, MAX_MARCH, MIN_STEP, TRACE_FRACTION
from fastsdf.function import Function

__all__ = ["SimulationParams", "ParticleSimulation", "Particles", "Gravity", "Drag", "FieldForce",
           "create_animation",
           "reference_step", "TRACE_FRACTION", "PARALLEL_MIN_PARTICLES", "DEFAULT_BLOCK"]

# The step's constants live in fastsdf._step (the kernel's source); documented here:
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
#: Particles per block in :meth:`ParticleSimulation.run` (block state fits in the L1/L2 cache).
DEFAULT_BLOCK = 512

_INTEGRATORS = ("symplectic", "euler")
_COLLISIONS = ("approaching", "notebook")


# ---------------------------------------------------------------------------------------------
# Parameter checking: errors name the parameter and the value.

def _real(value, name: str) -> float:
    """A real number, possibly non-finite: callers check the range with their own message."""
    return real(value, name, finite=False)


def _unit_interval(value, name: str) -> float:
    v = _real(value, name)
    if not 0.0 <= v <= 1.0:
        raise ValueError(f"{name} must be in [0, 1], got {name}={value!r}")
    return v


def _gen_name(gen) -> str:
    name = getattr(gen, "__qualname__", None) or getattr(gen, "__name__", None)
    return name if isinstance(name, str) else repr(gen)


# ---------------------------------------------------------------------------------------------
# Built-in force generators (fused into the compiled step; also plain Python callables).

class Gravity:
    """Uniform gravity: force ``m * acceleration`` on every particle.

    ``acceleration`` is a pair in length/s**2; the default ``(0, -1)`` is the notebook's
    ``gravity(p, t) = p['m'][:, None] * [0, -1]``. In ``force_generators`` it is fused into the
    compiled step (no Python work per step); called as ``g(p, t)`` it returns the (n, 2) force
    array like any generator.
    """

    def __init__(self, acceleration: ArrayLike = (0.0, -1.0)):
        self.acceleration = _vec2(acceleration, "acceleration")

    def __call__(self, p, t):
        return np.asarray(p["m"], dtype=np.float64)[:, None] * self.acceleration

    def potential(self, p: Particles) -> np.ndarray:
        """Potential energy of each particle, ``-m (acceleration . x)`` (zero at the origin)."""
        x = np.asarray(p["x"], dtype=np.float64)
        return -np.asarray(p["m"], dtype=np.float64) * (x @ self.acceleration)

    def __repr__(self):
        return f"Gravity(acceleration={self.acceleration.tolist()})"


class Drag:
    """Linear drag: force ``-coefficient * v`` (coefficient in mass/s, >= 0).

    A particle of mass ``m`` loses velocity at the rate ``coefficient / m`` per second. Fused into
    the compiled step when in ``force_generators``; called as ``g(p, t)`` it returns the forces.
    """

    def __init__(self, coefficient: float = 0.1):
        c = _real(coefficient, "coefficient")
        if not (math.isfinite(c) and c >= 0.0):
            raise ValueError(f"coefficient must be finite and >= 0, got "
                             f"coefficient={coefficient!r}")
        self.coefficient = c

    def __call__(self, p, t):
        return -self.coefficient * np.asarray(p["v"], dtype=np.float64)

    def __repr__(self):
        return f"Drag(coefficient={self.coefficient!r})"


class FieldForce:
    """A force field written with the graph API, compiled and fused into the step.

    ``FieldForce(fx, fy)``: the force ``(fx(x, y), fy(x, y))`` (mass * length / s**2);
    ``FieldForce(potential=U)``: the conservative force ``-grad U(x, y)`` (U in energy units).
    With ``per_mass=True`` the field is an acceleration (the force is ``m`` times it), like
    :class:`Gravity`. Each of ``fx``, ``fy``, ``U`` is a :class:`fastsdf.function.Function` (any
    fastsdf shape is one), or an expression of the symbols named ``x`` and ``y``. Each is
    compiled like an SDF (analytic gradient for the potential), so an attractor
    ``FieldForce(potential=-k / sym_sqrt(x**2 + y**2), per_mass=True)`` costs one inlined
    expression per particle and step. Called as ``f(p, t)`` it returns the (n, 2) forces
    (NumPy, like any generator).
    """

    def __init__(self, fx: Any = None, fy: Any = None, *, potential: Any = None,
                 per_mass: bool = False):
        if potential is None:
            if fx is None or fy is None:
                raise TypeError("FieldForce needs fx and fy, or potential=")
            self.parts = (_field_function(fx, "fx"), _field_function(fy, "fy"))
        else:
            if fx is not None or fy is not None:
                raise TypeError("FieldForce takes fx and fy, or potential=, not both")
            self.parts = (_field_function(potential, "potential"),)
        self.potential = potential is not None
        self.per_mass = bool(per_mass)
        self._dispatcher = None

    @property
    def dispatcher(self) -> Any:
        """The compiled ``@njit`` force ``(x, y, vx, vy, m, t) -> (fx, fy)`` (built on first
        use, from a content-hashed module in the kernel cache)."""
        if self._dispatcher is None:
            names = [f.compiled.module.__name__ for f in self.parts]
            scale = " * m" if self.per_mass else ""
            # A field with runtime parameters (or time) takes (x, y, t, params): the step's
            # time, and the parameters' values when the force was built (baked in).
            at = [", t, " + repr(f.param_tuple()) if f.compiled.parametric else ""
                  for f in self.parts]
            if self.potential:
                imports = f"from {names[0]} import point_vg as _u"
                body = f"    u, gx, gy = _u(x, y{at[0]})\n    return -gx{scale}, -gy{scale}"
            else:
                imports = (f"from {names[0]} import point_v as _fx\n"
                           f"from {names[1]} import point_v as _fy")
                body = f"    return _fx(x, y{at[0]}){scale}, _fy(x, y{at[1]}){scale}"
            source = (f'''"""Generated by fastsdf {__version__} (numba {numba.__version__}): a fused
force field. Dependencies: {", ".join(names)}."""
from numba import njit

{imports}


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def force(x, y, vx, vy, m, t):
{body}
''')
            self._dispatcher = load_module(source, prefix="fastsdf_force").force
            # A compiled field is usually long-latency arithmetic (square roots, divisions):
            # the step evaluates it for a batch of particles ahead (see fastsdf._step).
            self._dispatcher._fastsdf_batched = True
        return self._dispatcher

    def __call__(self, p, t):
        x = np.asarray(p["x"], dtype=np.float64)
        m = np.asarray(p["m"], dtype=np.float64) if self.per_mass else 1.0
        if self.potential:
            _, g = self.parts[0](x[:, 0], x[:, 1], compute_gradient=True)
            f = -g
        else:
            f = np.stack([self.parts[0](x[:, 0], x[:, 1]), self.parts[1](x[:, 0], x[:, 1])], 1)
        return f * (m[:, None] if self.per_mass else 1.0)

    def __repr__(self):
        what = f"potential={self.parts[0]!r}" if self.potential else \
            f"fx={self.parts[0]!r}, fy={self.parts[1]!r}"
        return f"FieldForce({what}, per_mass={self.per_mass})"


def _field_function(value, name: str) -> Function:
    """A Function of (x, y) from a Function or an expression of symbols named x and y."""
    if isinstance(value, Function):
        return value
    from fastsdf.expr.graph import Symbol, as_expr
    try:
        expr = as_expr(value, name)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a fastsdf Function or an expression of x and y, got "
                        f"{name}={value!r}") from None
    return Function(expr, [Symbol("x"), Symbol("y")])


# ---------------------------------------------------------------------------------------------
# State.

class Particles:
    """Particle state, structure-of-arrays, indexable like the notebook's structured array.

    Fields (``p['x']`` or ``p.x``; arrays you may read and write in place):

    ==== ======= ==========================================================
    x    (n, 2)  position (length units)
    v    (n, 2)  velocity (length/s)
    m    (n,)    mass (> 0)
    r    (n,)    radius of the particle's disc (length units, >= 0)
    cr   (n,)    coefficient of restitution in [0, 1] (1: elastic)
    cf   (n,)    coefficient of friction in [0, 1] (0: frictionless)
    ==== ======= ==========================================================

    ``p['x'] = value`` copies ``value`` into the existing array (broadcasting, e.g.
    ``p['cr'] = 0.9``), so the simulation keeps seeing it. All fields share one float dtype
    (float64 or float32). Values are checked when the simulation steps: ``x``, ``v``, ``r`` at
    every call (the step reads them anyway), ``m``, ``cr``, ``cf`` where a step uses them and,
    in full, at the first call after they were handed out (``p['m']``, ``p.cr``: the array
    may have been written in place), so unchanged state is not re-read every call.
    """

    FIELDS = ("x", "v", "m", "r", "cr", "cf")

    def __init__(self, n: int, dtype: Any = np.float64):
        self._n = int(n)
        self._dtype = np.dtype(dtype)
        self._arrays = {}
        #: Whether m, cr or cf may have changed since the step last checked them all.
        self._dirty = True
        for name in self.FIELDS:
            shape = (self._n, 2) if name in ("x", "v") else (self._n,)
            self._arrays[name] = np.zeros(shape, dtype=self._dtype)

    #: Fields the step does not read on every step: handing one out (it may be written in
    #: place) marks the state for a full check at the next step.
    _CHECKED_ON_ACCESS = ("m", "cr", "cf")

    def __getitem__(self, name):
        try:
            arr = self._arrays[name]
        except (KeyError, TypeError):
            raise KeyError(f"no particle field {name!r}; fields are {self.FIELDS}") from None
        if name in self._CHECKED_ON_ACCESS:
            self._dirty = True
        return arr

    def __setitem__(self, name, value):
        arr = self[name]
        try:
            value = np.asarray(value)
        except Exception:  # noqa: BLE001
            raise TypeError(f"p[{name!r}] must be an array of real numbers, "
                            f"got {value!r}") from None
        if value.dtype.kind not in "iuf":
            raise TypeError(f"p[{name!r}] must hold real numbers, got dtype {value.dtype}")
        try:
            np.copyto(arr, np.broadcast_to(value, arr.shape), casting="unsafe")
        except ValueError:
            raise ValueError(f"p[{name!r}] has shape {arr.shape}; cannot assign a value of "
                             f"shape {value.shape}") from None

    def __getattr__(self, name):
        arrays = self.__dict__.get("_arrays")
        if arrays is not None and name in arrays:
            if name in self._CHECKED_ON_ACCESS:
                self._dirty = True
            return arrays[name]
        raise AttributeError(name)

    def __len__(self):
        return self._n

    def __contains__(self, name):
        return name in self._arrays

    def keys(self) -> list:
        """The field names."""
        return self.FIELDS

    @property
    def dtype(self) -> np.dtype:
        """The float dtype of every field."""
        return self._dtype

    @property
    def nbytes(self) -> int:
        """Bytes held by the state (8 floats per particle)."""
        return sum(a.nbytes for a in self._arrays.values())

    def copy(self) -> "Particles":
        """An independent copy."""
        out = Particles(self._n, self._dtype)
        for name in self.FIELDS:
            out._arrays[name][...] = self._arrays[name]
        return out

    def as_structured(self) -> np.ndarray:
        """A copy as a NumPy structured array with the same fields (the notebook's layout)."""
        rec = np.zeros(self._n, dtype=[("x", self._dtype, 2), ("v", self._dtype, 2)]
                       + [(f, self._dtype) for f in ("m", "r", "cr", "cf")])
        for name in self.FIELDS:
            rec[name] = self._arrays[name]
        return rec

    def __repr__(self):
        return f"Particles(n={self._n}, dtype={self._dtype.name})"


# ---------------------------------------------------------------------------------------------
# Kernel generation.

def _is_grid(f) -> bool:
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


def _exactness(f) -> str:
    """``'exact'``, ``'bound'`` or ``'none'`` (see :attr:`fastsdf.SDF.exactness`) of the world
    (of a grid's exact SDF); ``'unknown'`` for a bare :class:`fastsdf.function.Function`."""
    g = f.exact if _is_grid(f) and f.exact is not None else f
    return getattr(g, "exactness", "unknown")


def _is_distance_bound(f) -> bool:
    """Whether the world is known to be 1-Lipschitz (so that a grid of it is sqrt(2))."""
    return _exactness(f) in ("exact", "bound")


def _grid_margin(f) -> float:
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

_SCENE_BEGIN = "# >>> SCENE BLOCK"
_SCENE_END = "# <<< SCENE BLOCK <<<"
_DECORATOR = '@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")'


# Read once, when the module is imported: the kernel must match the _step module this process
# runs with, even if the file changes on disk later (an upgrade, an edit).
_STEP_SOURCE = inspect.getsource(_step)


def _step_source() -> tuple:
    """The source of :mod:`fastsdf._step`, split around its scene block."""
    src = _STEP_SOURCE
    a = src.index(_SCENE_BEGIN)
    b = src.index(_SCENE_END) + len(_SCENE_END)
    return src[:a], src[b:]


def _exact_address(exact) -> tuple:
    """A C function ``void(double x, double y, double *out, double *h)`` evaluating the exact
    SDF (``h``: a plan header of :mod:`fastsdf.backends.prune`; a scene with loops over tables evaluates
    only the rows of the point's tile): the grid kernel's fallback outside the grid and the
    pruned particle step, bound at run time through its address so that the kernel does not
    depend on the scene. Returns ``(address, keepalive)``."""
    scene = exact.compiled.module.__name__
    entry = _EXACT_OUT.get(scene)
    if entry is None:
        rows = bool(exact.compiled.groups) and not exact.compiled.parametric
        source = _prune.exact_source(scene, rows, f"{__version__} (numba {numba.__version__})")
        mod = load_module(source, prefix="fastsdf_exactptr")
        entry = _EXACT_OUT[scene] = (int(mod.exact_out.address), mod)
    return entry


def _prunes(f) -> bool:
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


def _plan_import() -> str:
    with open(_prune.__file__, "rb") as fh:
        digest = hashlib.sha256(fh.read()).hexdigest()[:16]
    return f"from fastsdf.backends.prune import _call_vg_plan  # prune.py sha256 {digest}"


_PLAN_IMPORT = _plan_import()


def _force_parts(forces) -> tuple:
    """Scene-block lines binding the fused user forces and the ``_force`` function; names of
    forces that must be bound after import (not importable: no disk cache)."""
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
    batched = any(getattr(fn, "_fastsdf_batched", False) for fn in forces)
    lines.append(f"FORCE_AHEAD = {batched}")
    return lines, deps, late


# A world that does not move: no time derivative, no wall speed.
_STATIC_TIME_LINES = ["", "", "MOVING = False", "", "", _DECORATOR,
                      "def _query_t(data, x, y, t):", "    d, gx, gy = _query(data, x, y)",
                      "    return d, gx, gy, 0.0", "", "", _DECORATOR, "def _wall_speed(data):",
                      "    return 0.0", "", "", _DECORATOR,
                      "def _wall_speed_at(data, x, y, dx, dy):", "    return 0.0"]

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
    "    return data[1]"]
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
            raise KeyError(f"unknown parameter {name!r}; the world's parameters are "
                           f"{sorted(self) or 'none'} (time is sim.t)")
        super().__setitem__(name, real(value, f"params[{name!r}]"))

    def update(self, *args: Any, **kwargs: float) -> None:
        """Set several values (each checked as by ``sim.params[name] = value``)."""
        for k, v in dict(*args, **kwargs).items():
            self[k] = v

    def as_tuple(self) -> tuple:
        """The values in the order the compiled step takes them (sorted names)."""
        return tuple(dict.__getitem__(self, n) for n in self._names)


def _kernel_module(f, forces=()):
    """The generated kernel module for the world ``f`` (an SDF or a grid, see the sampler
    protocol in :mod:`fastsdf._step`) and the fused user forces, and its query data.

    Returns ``(module, data, keepalive)``. The kernel's source is :mod:`fastsdf._step` with
    its scene block replaced; a grid world's block names only the sampler, so its kernel is
    shared by every scene.
    """
    late = []
    keep = None
    # The vector block step (simd_par) is written for the dense grid's stored-gradient sampler.
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
        lines += ["", "", _DECORATOR, "def _query(data, x, y):",
                  f"    d, gx, gy, inside = _sampler(data[5:{hdr}], x, y)"]
        if mode == "exact":
            lines = [_PLAN_IMPORT] + lines
            lines += ["    if not inside:",
                      "        if data[0] == 0:  # never reached: see _fallback_missing",
                      "            return math.nan, math.nan, math.nan",
                      f"        return _call_vg_plan(data[0], x, y, data[{hdr}])"]
        lines.append("    return d, gx, gy")
        lines += ["", "", _DECORATOR, "def _fallback_missing(data, x, y, dx, dy):"]
        if mode == "exact":
            # Every query of a step (its sweep and bounces included) lies within
            # 2 (MAX_BOUNCES + 1) |D| of its start.
            lines += ["    if data[0] != 0:", "        return False",
                      "    reach = 2.0 * (MAX_BOUNCES + 1) * math.sqrt(dx * dx + dy * dy) + 1e-9",
                      "    return not (x - reach >= data[1] and x + reach <= data[2]",
                      "                and y - reach >= data[3] and y + reach <= data[4])"]
        else:
            lines.append("    return False")
        address = 0
        # Without bounds (optional in the protocol) the fallback is bound at once.
        (bx0, bx1), (by0, by1) = getattr(f, "bounds", None) or ((0.0, 0.0), (0.0, 0.0))
        # the last entry: the address of the fallback's plan header (bound with the fallback)
        data = (address, float(bx0), float(bx1), float(by0), float(by1)) + \
            tuple(f.sampler_data) + (0,)
        desc = f"a grid world (mode {mode!r}); the scene is bound at run time"
        key = ("grid", id(sampler), mode)
    elif isinstance(f, Function) and f.compiled.parametric:
        # Parameters and time are data, set per call: (t, wall speed bound, *parameters), one
        # flat tuple of floats (the parallel kernel cannot take nested tuples).
        scene = f.compiled.module.__name__
        k = _PARAMS_AT
        lines = [f"from {scene} import point_vg as _exact", "", "", _DECORATOR,
                 "def _query(data, x, y):", f"    return _exact(x, y, data[0], data[{k}:])", "",
                 "", _DECORATOR, "def _fallback_missing(data, x, y, dx, dy):", "    return False"]
        if f.time_dependent:
            lines += [f"from {scene} import point_vgt as _exact_t", "", "", _DECORATOR,
                      "def _query_t(data, x, y, t):", f"    return _exact_t(x, y, t, data[{k}:])",
                      "", "", _DECORATOR, "def _wall_speed(data):", "    return data[1]", "",
                      "", _DECORATOR] + _WALL_SPEED_AT_LINES + ["", "", "MOVING = True"]
        deps = [scene]
        data = (0.0, 0.0, 0.0, 0.0, 1.0, _NO_TABLE) + f.param_tuple()
        desc = repr(f)[:300]
        key = ("sdf", id(f.compiled.module))
    elif isinstance(f, Function) and _prunes(f):
        # Many operands in loops over tables: the step calls the scene's C function with the
        # plan header (data[1]), which evaluates only the rows of the query point's tile.
        scene = f.compiled.module.__name__
        lines = [_PLAN_IMPORT, "", "", _DECORATOR, "def _query(data, x, y):",
                 "    return _call_vg_plan(data[0], x, y, data[1])", "", "", _DECORATOR,
                 "def _fallback_missing(data, x, y, dx, dy):", "    return False"]
        deps = [scene]
        data = (0, 0)  # (address of the C function, of the plan header): bound at once
        desc = repr(f)[:300] + " (pruned)"
        key = ("sdf-pruned", id(f.compiled.module))
    elif isinstance(f, Function):
        scene = f.compiled.module.__name__
        lines = [f"from {scene} import point_vg as _exact", "", "", _DECORATOR,
                 "def _query(data, x, y):", "    return _exact(x, y)", "", "", _DECORATOR,
                 "def _fallback_missing(data, x, y, dx, dy):", "    return False"]
        deps = [scene]
        data = (0.0,)
        desc = repr(f)[:300]
        key = ("sdf", id(f.compiled.module))
    else:
        raise TypeError(f"f must be a fastsdf SDF (Function) or GridSDF, got f={f!r} of type "
                        f"{type(f).__name__}")
    if "MOVING = True" not in lines:
        lines += _STATIC_TIME_LINES
    force_lines, force_deps, force_late = _force_parts(forces)
    late += force_late
    deps += force_deps
    head, tail = _step_source()
    desc = desc.replace("\n", " ")
    block = [f"# Generated by fastsdf {__version__} (numba {numba.__version__}) from "
             f"fastsdf/_step.py; do not edit: the file name is the hash of this content.",
             f"# World: {desc}", f"# Dependencies: {'; '.join(deps) or 'none'}",
             f"_CACHE = {not late}", f"GRID_SIMD = {grid_simd}", f"GRID_EXACT = {grid_exact}",
             ""] + lines + [""] + force_lines
    source = head + "\n".join(block) + "\n" + tail
    if late:
        # One module per set of objects; the entry keeps them alive, so their ids are not
        # reused while the entry exists.
        key = key + tuple(id(obj) for _, obj in late)
        entry = _KERNELS.get(key)
        if entry is None:
            mod = load_module(source + f"\n# uncached instance {len(_KERNELS)}\n",
                              prefix="fastsdf_particles")
            for name, obj in late:
                setattr(mod, name, obj)
            entry = _KERNELS[key] = (mod, [obj for _, obj in late])
        return entry[0], data, (keep, entry[1])
    return load_module(source, prefix="fastsdf_particles"), data, keep


# ---------------------------------------------------------------------------------------------
# The simulation.

class ParticleSimulation:
    """Particles moving under forces and colliding with an SDF (the notebook's interface).

    Parameters
    ----------
    f : fastsdf SDF (:class:`fastsdf.function.Function`) or GridSDF
        The world; negative inside matter. A GridSDF is sampled bilinearly (its ``sampler``),
        falling back to its exact SDF outside its bounds in ``mode='exact'``. An exact SDF (or
        fallback) with many operands in loops over tables is pruned as ``f(x, y)`` is (see
        :mod:`fastsdf.backends.prune`): each query evaluates only the rows of its tile's lists, with
        the same bits for hard unions and intersections.
    n : int, default 100
        Number of particles (> 0).
    timestep : float, default 1/30
        Seconds per step (finite, > 0).
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
    runs the block kernel (``simd_par`` in :mod:`fastsdf._step`): 64 particles at a time held
    in scratch rows through all steps of a :meth:`run` call, each step in passes that the
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

    def __init__(self, f: Any, n: int = 100, timestep: float = 1 / 30, *, seed: Any = None,
                 integrator: str = "symplectic", collision: str = "approaching",
                 prevent_tunnelling: bool = True, dtype: Any = np.float64, cr: float = 0.6,
                 cf: float = 0.3, lipschitz: float | None = None, block: int | None = None,
                 wall_speed: float | None = None, rest_speed: float = 0.0):
        rest = _real(rest_speed, "rest_speed")
        if not (math.isfinite(rest) and rest >= 0.0):
            raise ValueError(f"rest_speed must be finite and >= 0, got rest_speed={rest_speed!r}")
        #: Resting contact below this speed (length/s); 0: off (see the class docs).
        self.rest_speed = rest
        if wall_speed is not None:
            w = _real(wall_speed, "wall_speed")
            if not (math.isfinite(w) and w >= 0.0):
                raise ValueError(f"wall_speed must be finite and >= 0, got "
                                 f"wall_speed={wall_speed!r}")
        self._wall_speed_arg = wall_speed
        if isinstance(n, (bool, np.bool_)) or not isinstance(n, numbers.Integral):
            raise TypeError(f"n must be an integer, got n={n!r}")
        if n <= 0:
            raise ValueError(f"n must be > 0, got n={n!r}")
        dt = _real(timestep, "timestep")
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(f"timestep must be finite and > 0, got timestep={timestep!r}")
        if integrator not in _INTEGRATORS:
            raise ValueError(f"integrator must be one of {_INTEGRATORS}, got "
                             f"integrator={integrator!r}")
        if collision not in _COLLISIONS:
            raise ValueError(f"collision must be one of {_COLLISIONS}, got collision={collision!r}")
        dtype = np.dtype(dtype)
        if dtype not in (np.dtype(np.float64), np.dtype(np.float32)):
            raise ValueError(f"dtype must be float64 or float32, got dtype={dtype}")
        if lipschitz is not None:
            lip = _real(lipschitz, "lipschitz")
            if not (math.isfinite(lip) and lip > 0.0):
                raise ValueError(f"lipschitz must be finite and > 0, got lipschitz={lipschitz!r}")
        if block is not None:
            if isinstance(block, (bool, np.bool_)) or not isinstance(block, numbers.Integral) \
                    or block <= 0:
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
        self.sdf = f
        self.block = None if block is None else int(block)
        self.force_generators = []
        self.t = 0.0
        self._ext = None
        self._flags = None
        self._wall = None
        self.reset()

    @property
    def sdf(self) -> Any:
        """The world (SDF or GridSDF). Assigning another one rebinds the compiled step."""
        return self._sdf

    @sdf.setter
    def sdf(self, f):
        module, data, keep = _kernel_module(f)   # raises TypeError for anything else
        self._sdf = f
        self._module, self._data, self._keep = module, data, keep
        self._kernels = {(): (module, data, keep, ())}
        # A grid in mode 'exact' binds its exact fallback when a particle first needs it; a
        # pruned SDF (see _prunes) binds its C function at once. Both read the plan header.
        pruned = isinstance(f, Function) and not _is_grid(f) and len(data) == 2
        self._hdr = np.zeros(_prune.HEADER_SIZE)
        self._hdr_plan = None  # the plan the header points into (kept alive here)
        self._exact_ptr = None if (_is_grid(f) and f.mode == "exact") or pruned else 0
        if self._exact_ptr is None and (pruned or getattr(f, "bounds", None) is None):
            self._bind_fallback()
        self._parametric = isinstance(f, Function) and not _is_grid(f) and \
            f.compiled.parametric
        self._moving = self._parametric and f.time_dependent
        #: Values of the world's runtime parameters (see :class:`SimulationParams`).
        self.params = SimulationParams(f) if self._parametric else SimulationParams(_NO_PARAMS)
        self._margin = _grid_margin(f)
        #: The Lipschitz bound the tunnelling check and the free-flight budget use.
        self.lipschitz = float(self._lipschitz_arg) if self._lipschitz_arg is not None \
            else (math.sqrt(2.0) if _is_grid(f) else 1.0)
        # Skipping queries is exact only if the bound holds; without a known bound (an SDF
        # whose exactness is 'none', or a bare expression) every step queries.
        known = self._lipschitz_arg is not None or _is_distance_bound(f)
        self._skip = known
        if not known and self.prevent_tunnelling:
            warnings.warn(
                f"the world's value is not known to be a distance bound (exactness "
                f"{_exactness(f)!r}): the tunnelling check assumes |grad d| <= "
                f"{self.lipschitz:g}; pass lipschitz= (a bound on |grad d|) if that is wrong",
                RuntimeWarning, stacklevel=3)

    # -- notebook interface ----------------------------------------------------------------
    def reset(self, ax: Any = None) -> tuple:
        """Draw a fresh random state (the notebook's distribution) and set ``t = 0``.

        ``x ~ N([0, 1.5], 0.05 I)``, ``v ~ N(0, 0.1 I)``, ``m ~ U(1, 10)``, ``r = 0.01 m``,
        ``cr``, ``cf`` from the constructor. With an ``ax`` (the notebook's interface), also
        (re)draws the particles there with :func:`fastsdf.viz.render.draw_particles`: discs of the
        particles' radii in data units for up to 5000 particles, a density image above; returns
        the drawn artists (for matplotlib's blitting). To animate a simulation without resetting
        it, use :func:`fastsdf.viz.render.animate`.
        """
        rng = self.seed if isinstance(self.seed, np.random.Generator) \
            else np.random.default_rng(self.seed)
        p = Particles(self.n, self.dtype)
        p["x"] = rng.normal([0.0, 1.5], math.sqrt(0.05), size=(self.n, 2))
        p["v"] = rng.normal([0.0, 0.0], math.sqrt(0.1), size=(self.n, 2))
        p["m"] = rng.uniform(1.0, 10.0, size=self.n)
        p["r"] = p["m"] * 0.01
        p["cr"] = self.cr
        p["cf"] = self.cf
        self.p = p
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
        ax = ay = drag = 0.0
        python, user = [], []
        for gen in self.force_generators:
            if isinstance(gen, Gravity):
                ax += float(gen.acceleration[0])
                ay += float(gen.acceleration[1])
            elif isinstance(gen, Drag):
                drag += gen.coefficient
            elif isinstance(gen, Dispatcher):
                user.append(gen)
            elif isinstance(gen, FieldForce):
                user.append(gen.dispatcher)
            elif callable(gen):
                python.append(gen)
            else:
                raise TypeError(f"force_generators must hold Gravity, Drag, numba @njit forces "
                                f"(x, y, vx, vy, m, t) -> (fx, fy) or callables "
                                f"(p, t) -> (n, 2) forces, got {gen!r}")
        return ax, ay, drag, python, tuple(user)

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
        plan = exact.compiled.pruned_plan(xs, ys, None, getattr(exact, "prune_tol", None),
                                          count=xs.shape[0] * max(1, int(steps)))
        if plan is not self._hdr_plan:
            _prune.plan_header(plan, self._hdr)
            self._hdr_plan = plan

    def _python_forces(self, gens) -> np.ndarray:
        n = self.n
        if self._ext is None or self._ext.shape != (n, 2):
            self._ext = np.empty((n, 2))
        ext = self._ext
        ext.fill(0.0)
        for gen in gens:
            name = _gen_name(gen)
            out = gen(self.p, self.t)
            try:
                arr = np.asarray(out)
            except Exception:  # noqa: BLE001
                raise TypeError(f"force generator {name} must return an (n, 2) array of forces, "
                                f"got {type(out).__name__}") from None
            if arr.dtype.kind not in "iuf":
                raise TypeError(f"force generator {name} must return real forces, got an array "
                                f"of dtype {arr.dtype}")
            if arr.shape != (n, 2):
                raise ValueError(f"force generator {name} must return forces of shape ({n}, 2), "
                                 f"got shape {arr.shape}")
            if not np.all(np.isfinite(arr)):
                bad = int(np.flatnonzero(~np.isfinite(arr).all(axis=1))[0])
                raise ValueError(f"force generator {name} returned a non-finite force for "
                                 f"particle {bad}: {arr[bad].tolist()}")
            ext += arr
        return ext

    def run(self, steps: int = 1) -> None:
        """Advance ``steps`` steps (``steps * timestep`` seconds) in compiled code.

        With only fused forces (:class:`Gravity`, :class:`Drag`, numba ``@njit`` forces) this
        is one compiled call for all steps; with Python force generators, one generator
        evaluation and one compiled step per step.

        Errors. A particle whose state cannot be stepped (a non-finite position or velocity, a
        mass that is not > 0 where the mass is used, a negative or non-finite radius, ``cr`` or
        ``cf`` outside [0, 1] at a contact), or whose step would produce a non-finite state
        (e.g. a timestep so large that the motion overflows), is frozen at its last valid state
        and never carries a non-finite value. The other particles complete every step, ``t``
        advances by ``steps * timestep`` (clock and state agree), and then a ``ValueError``
        names the first such particle and what was wrong.
        """
        if isinstance(steps, (bool, np.bool_)) or not isinstance(steps, numbers.Integral):
            raise TypeError(f"steps must be an integer, got steps={steps!r}")
        if steps < 0:
            raise ValueError(f"steps must be >= 0, got steps={steps!r}")
        if steps == 0:
            return
        self._check_state_shape()
        ax, ay, drag, python, user = self._fused_params()
        module, data = self._kernel(user)
        if not python:
            bad = self._launch(module, data, int(steps), ax, ay, drag, None)
            self.t += steps * self.dt
        else:
            bad = 0
            for _ in range(int(steps)):
                ext = self._python_forces(python)
                bad += self._launch(module, data, 1, ax, ay, drag, ext)
                self.t += self.dt
        if bad:
            raise self._frozen_error(bad, int(steps))

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
            raise ValueError(f"sim.p holds {len(p)} particles of {p.dtype}; this simulation "
                             f"has n={self.n} of {self.dtype}")

    def _launch(self, module, data, steps, ax, ay, drag, ext):
        p = self.p
        n = self.n
        use_ext = ext is not None
        if ext is None:
            ext = _NO_EXT
        use_m = use_ext or drag != 0.0
        if self._flags is None or self._flags.shape[0] != n:
            self._flags = np.zeros(n, dtype=np.int32)
        if self._parametric:
            data = self._scene_data(steps)
        a = p._arrays
        check_all = p._dirty
        args = (ext, self._flags, self.dt, self.t, ax, ay, drag, use_m, use_ext,
                self.integrator == "euler", self.collision == "notebook",
                self.prevent_tunnelling, self.lipschitz, self._margin,
                float(np.finfo(self.dtype).eps), self._skip, float(self.rest_speed))
        self._update_plan(a["x"], steps)
        bad = self._call(module, data, steps, [a[k] for k in Particles.FIELDS], args, check_all)
        if bad and self._exact_ptr is None:
            bad = self._resume(module, steps, args, bad)
        if check_all and not bad:
            p._dirty = False
        return bad

    def _call(self, module, data, steps, arrays, args, check_all):
        n = arrays[0].shape[0]
        parallel = n >= PARALLEL_MIN_PARTICLES and numba.get_num_threads() > 1
        kernel = self._pick_kernel(module, arrays, args, parallel)
        return kernel(data, steps, self.block or DEFAULT_BLOCK, *arrays, *args, check_all)

    def _pick_kernel(self, module, arrays, args, parallel):
        """The kernel of ``module`` for a call: the block kernel of a static grid world
        (``simd_*``: float64 state, no resting contact, no Python forces), else the
        particle-by-particle kernel without skipping and tunnelling check (``plain_*``), else
        the general one (``run_*``). All give the same results."""
        # args: (ext, flags, dt, t, ax, ay, drag, use_m, use_ext, explicit, always, trace,
        #        lip, margin, eps, skip, rest); bench/step_ab.py builds older step sources
        simd = getattr(self, "_simd", True) and getattr(module, "GRID_SIMD", False) and \
            hasattr(module, "simd_par") and not module.MOVING and args[16] == 0.0 and \
            not args[8] and arrays[0].dtype == np.float64
        plain = not (args[11] or args[15] or args[16] > 0.0 or module.MOVING) and \
            hasattr(module, "plain_par")
        if simd:
            return module.simd_par if parallel else module.simd_ser
        if plain:
            return module.plain_par if parallel else module.plain_ser
        return module.run_par if parallel else module.run_ser

    def _resume(self, module, steps, args, bad):
        """Particles that stopped near the grid's edge before its exact fallback was bound
        (FLAG_RESUME + step): bind it, run each the rest of its steps from where it stopped
        (particles are independent, so the result is that of an uninterrupted call)."""
        flags = self._flags
        idx = np.flatnonzero(flags >= _step.FLAG_RESUME)
        if not idx.size:
            return bad
        self._bind_fallback()
        self._update_plan(self.p._arrays["x"], steps)
        data = next(self._bind(e[1]) for e in self._kernels.values() if e[0] is module)
        at = flags[idx] - _step.FLAG_RESUME
        flags[idx] = 0
        bad -= idx.size
        ext, fl, dt, t0 = args[:4]
        arrays = self.p._arrays
        for j in np.unique(at):
            sel = idx[at == j]
            sub = [np.ascontiguousarray(arrays[k][sel]) for k in Particles.FIELDS]
            sub_flags = np.zeros(sel.size, dtype=np.int32)
            sub_ext = ext[sel] if ext.shape[0] else ext
            sub_args = (sub_ext, sub_flags, dt, t0 + int(j) * dt) + args[4:]
            bad += self._call(module, data, steps - int(j), sub, sub_args, False)
            arrays["x"][sel] = sub[0]
            arrays["v"][sel] = sub[1]
            flags[sel] = sub_flags
        return bad

    def _frozen_error(self, count: int, steps: int) -> ValueError:
        """The error after a call that froze ``count`` particles (clears the flags)."""
        flags = self._flags
        idx = np.flatnonzero(flags)
        first, why = int(idx[0]), int(flags[idx[0]])
        flags[idx] = 0
        p = self.p
        if why == _step.FLAG_NONFINITE:
            x = np.asarray(p["x"][first], np.float64).tolist()
            v = np.asarray(p["v"][first], np.float64).tolist()
            what = (f"a step of particle {first} produced a non-finite state (timestep="
                    f"{self.dt!r}; last finite state x={x}, v={v}); it was frozen there")
        elif why == _step.FLAG_COEFF:
            what = (f"invalid particle state: p['cr'][{first}] = {float(p['cr'][first])!r} or "
                    f"p['cf'][{first}] = {float(p['cf'][first])!r} is not in [0, 1] (found at "
                    f"a contact); the particle was frozen there")
        else:
            err = _invalid_state_error(p, count)
            what = str(err).split(" (", 1)[0] + "; the particle was left unchanged"
        return ValueError(f"{what}. {len(idx)} particle(s) frozen in all; the others completed "
                          f"the {steps} step(s) and sim.t = {self.t!r} includes them")

    def _scene_data(self, steps: int) -> tuple:
        """Query data of a parametric world: (t, wall speed bound, table geometry and the
        per-region table, *parameters); see ``_PARAMS_AT``."""
        prm = self.params.as_tuple()
        wall, table = 0.0, (0.0, 0.0, 1.0, _NO_TABLE)
        if self._moving and steps:
            wall = self._wall_speed_arg
            if wall is None:
                wall, table = self._wall_speed_table(steps, prm)
        self._wall_table = table  # kept alive: the kernel borrows the array
        return (float(self.t), float(wall)) + table + prm

    def _wall_speed_table(self, steps: int, prm: tuple) -> tuple:
        """The global bound W and the per-region table of wall speeds for one call.

        ``|dd/dt|`` is sampled on the nodes of a grid over the bounding box of a sample of the
        particles (at most
        ``WALL_TABLE_CELLS`` cells a side) at the call's first and last step times (and up to
        6 times between), each cell gets 1.5 times the largest sample at its corners, and the
        table is widened by one cell plus the distance a wall moving at W travels during the
        call: a particle whose surroundings do not move (far from every moving wall) gets 0
        and skips its queries as in a static scene. W is the largest value of the table and of
        the samples at the particles (the estimate used where the table does not reach:
        steps longer than a cell, particles outside the box).
        """
        x = np.asarray(self.p["x"], dtype=np.float64)
        # The table's box from a sample of the particles (one outside it uses W) and the
        # samples for W: both cheap next to a step of every particle.
        box = x[::max(1, x.shape[0] // 16384)]
        box = box[np.isfinite(box).all(axis=1)]
        sample = x[::max(1, x.shape[0] // 4096)]
        sample = sample[np.isfinite(sample).all(axis=1)]
        if not box.size:
            box = np.zeros((1, 2))
        lo, hi = box.min(axis=0), box.max(axis=0)
        size = float(max(hi - lo))
        if not size > 0:
            size = float(np.max(self.p["r"])) * 4 or 1.0
        n = WALL_TABLE_CELLS
        h = size / (n - 4)
        x0, y0 = lo - 2 * h          # two cells of room on each side
        gx = x0 + h * np.arange(n + 1)
        gy = y0 + h * np.arange(n + 1)
        X, Y = (a.ravel() for a in np.meshgrid(gx, gy, indexing="ij"))
        X = np.ascontiguousarray(np.concatenate([X, sample[:, 0]]))
        Y = np.ascontiguousarray(np.concatenate([Y, sample[:, 1]]))
        m, nodes = X.shape[0], (n + 1) * (n + 1)
        # the serial kernel: a few thousand points are not worth waking the threads
        kernel = self._sdf.compiled.kernel("vgt", parallel=False)
        out, grad, gt = np.empty(m), np.empty((m, 2)), np.empty(m)
        count = min(steps, 8)
        times = self.t + self.dt * np.unique(np.round(np.linspace(1, steps, count)))
        top = np.zeros(m)
        for t in times:
            kernel(X, Y, out, grad, gt, float(t), prm)
            top = np.maximum(top, np.abs(np.where(np.isfinite(gt), gt, np.inf)))
        node = top[:nodes]
        at_particles = top[nodes:]
        top = 1.5 * float(at_particles[np.isfinite(at_particles)].max(initial=0.0))
        node = node.reshape(n + 1, n + 1)
        cell = 1.5 * np.maximum(np.maximum(node[:-1, :-1], node[1:, :-1]),
                                np.maximum(node[:-1, 1:], node[1:, 1:]))
        wall = max(top, float(cell[np.isfinite(cell)].max(initial=0.0)))
        cell = np.where(np.isfinite(cell), cell, wall)  # unknown there (a non-finite dd/dt)
        # walls at the sample times move up to W (t_gap) between them and W dt in a step
        gap = max(float(np.max(np.diff(times))) if len(times) > 1 else 0.0, self.dt)
        reach = 1 + int(math.ceil(wall * gap / h))
        wide = cell
        for _ in range(min(reach, n)):
            pad = np.pad(wide, 1, mode="edge")
            wide = np.maximum.reduce([pad[1:-1, 1:-1], pad[:-2, 1:-1], pad[2:, 1:-1],
                                      pad[1:-1, :-2], pad[1:-1, 2:], pad[:-2, :-2], pad[2:, 2:],
                                      pad[:-2, 2:], pad[2:, :-2]])
        return wall, (float(x0), float(y0), 1.0 / h, np.ascontiguousarray(wide))

    # -- diagnostics -------------------------------------------------------------------------
    def kinetic_energy(self) -> float:
        """Total kinetic energy ``sum(m |v|**2 / 2)``."""
        v = np.asarray(self.p["v"], dtype=np.float64)
        return float(np.sum(0.5 * np.asarray(self.p["m"], dtype=np.float64) * (v * v).sum(1)))

    def potential_energy(self) -> float:
        """Total potential energy of the :class:`Gravity` generators (zero at the origin);
        other forces have no potential here."""
        return float(sum(np.sum(g.potential(self.p)) for g in self.force_generators
                         if isinstance(g, Gravity)))

    def energy(self) -> float:
        """Kinetic plus gravitational potential energy."""
        return self.kinetic_energy() + self.potential_energy()

    def query(self, x: ArrayLike, y: ArrayLike) -> tuple:
        """``(d, grad)`` of the world at points, exactly as the compiled step sees it (for a
        GridSDF: the bilinear samples, with its out-of-bounds rule)."""
        xs = np.ascontiguousarray(x, dtype=np.float64).reshape(-1)
        ys = np.ascontiguousarray(y, dtype=np.float64).reshape(-1)
        out = np.empty((xs.shape[0], 3))
        self._bind_fallback()
        self._update_plan(np.stack([xs, ys], axis=1), 1)
        self._module.query_many(self._scene_data(0) if self._parametric else self._data, xs, ys,
                                out)
        return out[:, 0], out[:, 1:]

    def _draw(self, ax, new):
        # The notebook's reset(ax)/update(ax) draw; the drawing and its state live in render.
        if ax is None:
            return ()
        from fastsdf.viz.render import notebook_draw
        return notebook_draw(self, ax, new)

    def __getstate__(self):
        # The world travels as its graph (and a grid's nodes), the state as arrays; the bound
        # kernel module and scratch buffers stay behind and are rebuilt on unpickling (the
        # simulation holds no drawing: that lives in fastsdf.viz.render).
        # (Everything the ``sdf`` setter sets is rebuilt; per-particle arrays are kept.)
        state = self.__dict__.copy()
        for key in ("_module", "_data", "_keep", "_kernels", "_ext", "_wall", "_wall_table",
                    "_exact_ptr", "_flags", "_hdr", "_hdr_plan"):
            state.pop(key, None)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._ext = self._wall = self._flags = None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # warned when first built
            self.sdf = state["_sdf"]

    def __repr__(self):
        return (f"ParticleSimulation(n={self.n}, timestep={self.dt!r}, t={self.t:.4g}, "
                f"integrator={self.integrator!r}, collision={self.collision!r}, "
                f"prevent_tunnelling={self.prevent_tunnelling}, dtype={self.dtype.name})")


_NO_EXT = np.zeros((0, 2))


class _NoParams:
    params: dict = {}
    param_names: tuple = ()


_NO_PARAMS = _NoParams()


def _invalid_state_error(p: Particles, count: int) -> ValueError:
    """A ValueError naming the first invalid particle (only computed on the error path)."""
    x = np.asarray(p["x"], dtype=np.float64)
    v = np.asarray(p["v"], dtype=np.float64)
    checks = [
        ("x", ~np.isfinite(x).all(axis=1), "must be finite"),
        ("v", ~np.isfinite(v).all(axis=1), "must be finite"),
        ("m", ~((p["m"] > 0) & np.isfinite(p["m"])), "must be finite and > 0"),
        ("r", ~((p["r"] >= 0) & np.isfinite(p["r"])), "must be finite and >= 0"),
        ("cr", ~((p["cr"] >= 0) & (p["cr"] <= 1)), "must be in [0, 1]"),
        ("cf", ~((p["cf"] >= 0) & (p["cf"] <= 1)), "must be in [0, 1]"),
    ]
    for name, mask, rule in checks:
        idx = np.flatnonzero(mask)
        if idx.size:
            i = int(idx[0])
            val = p[name][i]
            val = val.tolist() if np.ndim(val) else float(val)
            return ValueError(f"invalid particle state: p[{name!r}][{i}] = {val!r} {rule} "
                              f"({count} invalid particle(s) in all; they were left unchanged, "
                              f"the others were advanced)")
    return ValueError(f"{count} particle(s) had an invalid state during the step")


# ---------------------------------------------------------------------------------------------
# The notebook's step in NumPy (reference for tests, baseline for benchmarks).

def reference_step(p: Any, f: Any, dt: float, force_generators: Sequence = (),
                   t: float = 0.0) -> None:
    """One step of the notebook's ``ParticleSimulation.advance()``, in NumPy, in place.

    ``p`` is a :class:`Particles` (or a structured array with the same fields), ``f`` any SDF
    or GridSDF callable as ``f(x, y, compute_gradient=True)``. Forces are the sum of
    ``gen(p, t)`` over ``force_generators`` (Python callables; :class:`Gravity` and :class:`Drag`
    work too); then explicit Euler, one batch SDF query at the new positions, and the response
    wherever ``d - r <= 0`` (velocity responds regardless of ``v . n``, as in the notebook).
    This is what ``ParticleSimulation(..., integrator='euler', collision='notebook',
    prevent_tunnelling=False)`` computes in one fused compiled loop.
    """
    x, v = p["x"], p["v"]
    m = np.asarray(p["m"], dtype=np.float64)[:, None]
    force = np.zeros(x.shape)
    for gen in force_generators:
        force += gen(p, t)
    x += v * dt
    v += force / m * dt
    d, grad = f(x[:, 0], x[:, 1], compute_gradient=True)
    d = d - p["r"]
    c = np.flatnonzero(d <= 0)
    if c.size:
        g = grad[c]
        n = g / np.linalg.norm(g, axis=1)[:, None]
        vc = v[c]
        vn = (vc * n).sum(axis=1)[:, None] * n
        vt = vc - vn
        cr = np.asarray(p["cr"])[c][:, None]
        cf = np.asarray(p["cf"])[c][:, None]
        x[c] -= (1.0 + cr) * d[c][:, None] * n
        v[c] = -cr * vn + (1.0 - cf) * vt


# ---------------------------------------------------------------------------------------------
# Animation.

def create_animation(fig: Any, ax: Any, sim: Any, frames: int = 300, repeat: bool = True,
                     use_wall_time: bool = False, interval: float | None = None) -> Any:
    """A matplotlib ``FuncAnimation`` of ``sim`` on ``ax`` (the notebook's helper).

    Each frame calls ``sim.update(ax, use_wall_time)``; the animation's init (and every repeat)
    calls ``sim.reset(ax)``, which redraws a fresh random state. ``interval`` is the delay
    between frames in milliseconds (default: the simulation's timestep). Returns the animation
    (keep a reference to it; ``anim.to_html5_video()`` renders it in a notebook: an MP4 when
    ffmpeg is installed, matplotlib's JavaScript player (``to_jshtml``) otherwise).
    """
    from matplotlib.animation import FuncAnimation

    if interval is None:
        interval = 1000.0 * getattr(sim, "dt", 1 / 30)

    def artists(returned):
        # Any simulation object with reset(ax) / update(ax, use_wall_time) works (the
        # notebook's own SimpleParticleSimulation returns nothing from reset): blitting needs
        # the artists, so fall back on sim.drawable.
        if returned is None:
            drawable = getattr(sim, "drawable", None)
            return (drawable,) if drawable is not None else ()
        return returned

    class _Animation(FuncAnimation):
        """``to_html5_video`` needs ffmpeg; without it, fall back to matplotlib's JavaScript
        player (``to_jshtml``) so the notebook's ``HTML(anim.to_html5_video())`` still works."""

        def to_html5_video(self, embed_limit=None):
            from matplotlib import animation, rcParams

            from fastsdf.viz.video import ffmpeg_available
            ffmpeg_available()  # points matplotlib at imageio-ffmpeg's binary when installed
            if animation.writers.is_available(rcParams["animation.writer"]):
                return super().to_html5_video(embed_limit=embed_limit)
            return self.to_jshtml(default_mode="loop" if repeat else "once")

    return _Animation(fig, lambda i: artists(sim.update(ax, use_wall_time=use_wall_time)),
                      init_func=lambda: artists(sim.reset(ax)), frames=frames,
                      interval=interval, blit=True, repeat=repeat)
