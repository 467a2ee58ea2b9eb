"""The fused particle step: integrate, query the world, sweep, respond (numba).

The step is written once, as phases, and every kernel is built from them:

- :mod:`.contact`: the collision response, the conservative-advancement march and the
  tunnelling sweep of one particle;
- :mod:`.phases`: the phases of one particle's step (checks, integration, free-flight
  budgets, the tunnelling check and sweep, the response) and their composition
  :func:`.phases.particle_step`, the step of one particle (the CPU's particle-by-particle
  kernels and the CUDA thread of :mod:`fastsdf.particles.cuda` call it);
- :mod:`.step`: the particle-by-particle loops on the CPU and the entry points;
- :mod:`.block`: the block step of grid worlds, the same phases in passes over 64 particles;
- :mod:`.config`, :mod:`.constants` and :mod:`.intrinsics`: the named structures the kernels
  take, the constants and the intrinsics they share (no scene in them).

They are real modules: importable and tested directly (``tests/test_step.py``) against the
small analytic world of :mod:`.scene`, the *scene block* they import. A simulation does not
call them from there: :mod:`fastsdf.particles.scene_blocks` writes a scene block of its own (the
world's query and the fused forces), :func:`kernel_source` puts it in front of the kernels'
bodies (each part's text below its ``KERNEL BODY`` marker), and the result is written to a
content-hashed file in the kernel cache (:mod:`fastsdf.backends.kernel.cache`) and imported.
Because the
kernels' whole source is in the generated file (and the import lines of the shared modules
carry their files' hashes), editing any part changes the hash, so a stale compiled kernel is
never loaded (numba's ``cache=True`` does not notice changes in other modules a cached function
calls into).

The scene block
---------------
A scene block must define:

``_CACHE``
    whether numba may cache the kernel on disk (False when a part cannot be imported by name);
``_query(data, x, y) -> (d, dd/dx, dd/dy)``
    the world's signed distance (negative inside) and gradient at one point, float64, given
    the simulation's query data ``data`` (an argument, so new data never recompiles);
``_fallback_missing(data, x, y, dx, dy) -> bool``
    whether a step from ``(x, y)`` by ``(dx, dy)`` (its sweep included) may query where the
    world cannot answer yet (a grid whose exact fallback is not compiled: it is compiled only
    when a particle first comes near the grid's edge, so a new scene starts at once);
``_force(x, y, vx, vy, m, t) -> (fx, fy)``, ``USE_FORCE`` and ``FORCE_AHEAD``
    the sum of the fused user forces (mass * length / s**2) at one particle and time ``t``;
    ``USE_FORCE = False`` when there are none (then ``m`` is not read for it).
    ``FORCE_AHEAD``: evaluate them for ``FORCE_BATCH`` particles at a time, ahead of their
    steps (same results). That pays for long-latency forces (a compiled field's square roots
    and divisions overlap across particles instead of lengthening each particle's dependent
    chain) and costs a second read of the state for cheap ones.
``MOVING``, ``_query_t(data, x, y, t) -> (d, dd/dx, dd/dy, dd/dt)``, ``_wall_speed(data)``
and ``_wall_speed_at(data, x, y, dx, dy)``
    for a world that moves (uses time): its distance at time ``t`` with the time derivative,
    a bound on ``|dd/dt|`` (length/s; how fast any surface can approach a particle), and a
    bound for a step by ``(dx, dy)`` ending at ``(x, y)`` (at most the first: far from every
    moving wall it is 0, so particles there skip queries as in a static world). A static world
    sets ``MOVING = False``, ``dd/dt = 0`` and wall speeds of 0.

Moving worlds
-------------
The step evaluates a moving world at the end of the step (``t + dt``). The response uses the
velocity relative to the wall: the surface's normal speed is ``w = -dd/dt / |grad d|`` (along
the outward normal), the relative normal velocity ``v_n - w`` reflects with ``cr`` and the
tangential velocity keeps ``(1 - cf)`` of itself (an SDF does not say how a surface slides
along itself, so the wall's tangential velocity is taken as zero). Distance budgets and the
tunnelling sweep use the wall speed bound ``W``: in one step the distance to a surface can
shrink by ``lip |D| + W dt``, so the sweep marches in space-time (:func:`march`) with that
rate, and a particle at rest is swept when the walls move more than ``TRACE_FRACTION r`` in a
step.

Sampler protocol (what a grid type provides so a grid world plugs in)
--------------------------------------------------------------------
A grid object ``g`` used as a world has:

``g.sampler``
    a module-level numba ``@njit`` function (importable as ``module.name``, compiled with
    ``cache=True``, preferably ``inline='always'``) with
    ``d, gx, gy, inside = sampler(data, x, y)``: float64 value and gradient at one point and a
    bool, False outside the grid's bounds (the values there are the grid's own clamped answer)
    or for a non-finite point (values NaN). It must not allocate or raise.
``g.sampler_data``
    a tuple of arrays and scalars (the grid's storage and geometry); arrays inside it are
    passed without reference counting (see :func:`borrow_all`), so ``g`` must keep them alive.
``g.exact``
    the exact SDF (a :class:`fastsdf.function.Function`), evaluated where ``inside`` is False
    when ``g.mode == 'exact'``; ``g.mode == 'nearest'`` keeps the sampler's clamped answer.
``g.bounds`` (optional)
    ``((x0, x1), (y0, y1))``, the rectangle where ``inside`` is True (without it the exact
    fallback is compiled when the simulation is built, not when first needed);
``g.spacing``
    node spacing ``(hx, hy)``: how far an 'exact'-mode grid may jump at its bounds.

The kernel of a grid world depends only on the sampler (its module, name and source), the mode
and the fused forces, not on the scene: the exact fallback is called through a C function
pointer carried in the query data (``data = (exact_address, x0, x1, y0, y1) +
sampler_data``; the parallel kernel cannot take nested tuples holding arrays). The address is 0
until a particle first comes near the grid's edge (``_fallback_missing``): a particle that
would then query outside stops (``FLAG_RESUME``), and the caller compiles the fallback and
resumes it, so a new scene's first steps need no compilation at all, so the kernel is
compiled once per installation and every later scene loads it from the cache.

One step, per particle (the physics is described in :mod:`fastsdf.particles`)
-------------------------------------------------------------------------------
The phases of :func:`.phases.particle_step`, in order:

1. acceleration ``a = g + (F_user + ext - drag v) / m`` (:func:`.phases.accelerate`);
2. integrate (semi-implicit or explicit Euler, :func:`.phases.euler`); the displacement is
   ``D``;
3. free-flight skipping: while the budget from an earlier query exceeds ``|D|``, no query
   (:func:`.phases.spend`);
4. query the end point, ``s = d - r``;
5. tunnelling sweep (:func:`.phases.swept`) when ``|D| > TRACE_FRACTION r`` and the end is
   not clear by ``lip |D|`` (:func:`.phases.needs_sweep`);
6. respond where ``s <= 0`` (:func:`_respond`), or, with ``rest > 0`` (``rest_speed``),
   hold a slow particle that :func:`_rests` where it was with zero velocity; else refill the
   skipping budget (:func:`.phases.refill`);
7. with resting contact, a particle whose step left its state bit-identical sleeps for the
   rest of the call (``SLEEP``: a static world and no user force, so every later step would
   repeat it).

One kernel family, its variants compiled specializations of one entry point (see
:func:`.step.step_ser`; each compiled when first used, then cached): the general
particle-by-particle step (``simd=None, plain=None``); the plain step (``plain=True``): calls
without query skipping, tunnelling check, moving world or resting contact (the peers' work:
``skip`` and ``trace`` off, ``rest`` 0), the same results from a shorter loop (the same phases
with those switches as constants), which runs a step particle after particle while few
particles of a block touch a surface and in two passes over batches of ``PLAIN_BATCH``
(integrate and query all, then respond) after a step where many did, so that mispredicted
contact branches do not discard the next particles' queries; and the block step (``simd=True``)
of a static grid world with stored gradients (``GRID_SIMD``, set in the scene block; float64
state, ``rest`` 0, no Python forces): the same results from :func:`.block._block_simd`, which
keeps ``LANES`` particles in the rows of one scratch array through all steps of a call and
runs each step as passes over them: a vector pass of forces, integration, free-flight budgets
and the grid cell (:func:`.block._simd_move`), a scalar pass loading the cells
(:func:`.block._simd_gather`, each cell's three channels blended in one vector), a scalar
fix-up of only the particles that need a tunnelling sweep or a query outside the grid
(:func:`.block._simd_fix`), and a vector pass of the response with selects instead of branches
(:func:`.block._simd_respond`). A step in which no particle of the block needs a query is the
first pass alone. Sleeping is not needed there (it changes no result). With ``plain=True``
the block step compiles the passes of calls without query skipping only. The tunnelling check
and resting contact are values of a call (``budget.trace``, ``physics.rest``), not
specializations: switching them recompiles nothing (resting contact takes the general
variant).

Checks (no separate pass over memory): before a call's first step every particle of a block
is checked on values the step loads anyway (``x``, ``v`` finite, ``r`` finite and >= 0, ``m``
finite and > 0 when read); ``cr``, ``cf`` are checked where a contact uses them; every step's
result is checked finite. With ``check_all`` (the caller's dirty flag: the state's ``m``,
``cr``, ``cf`` may have been written since the last call) the first pass also checks ``m``,
``cr`` and ``cf`` of every particle. A particle that fails is frozen at its last valid state for
the rest of the call and flagged in ``FLAGS`` (1: invalid input, 2: a step produced a
non-finite state, 3: invalid ``cr``/``cf`` at a contact); the kernels return how many were
frozen.

Entry points
------------
``step_ser(data, state, physics, budget, steps, block, simd, plain) -> frozen count`` and
``step_par`` (the same): the world's query data, the particles' arrays
(:class:`.config.State`), the physics of the call (:class:`.config.Physics`), the safety and
skipping settings (:class:`.config.Budget`), the number of steps, the particles per block and
the variant. ``step_ser`` releases the GIL: the caller (:mod:`fastsdf.particles.engine`) runs
a short call as slices of the particles on several threads (particles are independent, so the
results do not depend on the slicing), and a long one through ``step_par`` (numba's
``parallel=True``, compiled when first needed: its parfor passes double the compile time, and
it runs long calls a few percent faster). The third entry point is the GPU's, one thread per
particle (:mod:`fastsdf.particles.cuda`).
"""

from __future__ import annotations

import hashlib
import inspect
from types import ModuleType

from fastsdf import intrinsics as _intrinsics
from fastsdf.particles.kernels import (
    block,
    config,
    constants,
    contact,
    intrinsics,
    phases,
    step,
)
from fastsdf.particles.kernels.block import LANES
from fastsdf.particles.kernels.config import NO_EXT, Budget, Disc, Motion, Physics, State, Window
from fastsdf.particles.kernels.contact import _march, _respond, _rests, _sweep, march, sweep
from fastsdf.particles.kernels.intrinsics import borrow_all, call_vg
from fastsdf.particles.kernels.phases import particle_step
from fastsdf.particles.kernels.step import (
    PLAIN_BATCH,
    force_many,
    query_many,
    step_par,
    step_ser,
)

__all__ = [
    "kernel_source",
    "PARTS",
    "constants",
    "State",
    "Physics",
    "Budget",
    "Motion",
    "Disc",
    "Window",
    "NO_EXT",
    "LANES",
    "PLAIN_BATCH",
    "borrow_all",
    "call_vg",
    "step_ser",
    "step_par",
    "particle_step",
    "query_many",
    "force_many",
    "march",
    "sweep",
    "_respond",
    "_march",
    "_sweep",
    "_rests",
]

#: The kernels' modules whose bodies a generated module holds, in order.
PARTS: tuple = (contact, phases, block, step)
#: The line after which a part's text is the kernel body (above it: its imports when used
#: directly, against the test world).
BODY_MARK = "# >>> KERNEL BODY (from here on, copied into every generated kernel module) >>>"


def _digest(module: ModuleType) -> str:
    return hashlib.sha256(inspect.getsource(module).encode()).hexdigest()[:16]


def _shared_imports() -> str:
    """Import lines of the scene-independent modules (the bottom layer's intrinsics, this
    package's constants, structures and intrinsics), each with its file's hash (so that an edit
    there changes every generated module's hash)."""
    names = sorted(
        n
        for n, obj in vars(intrinsics).items()
        if getattr(obj, "__module__", "") == intrinsics.__name__ and not inspect.isfunction(obj)
    )
    return (
        f"from {_intrinsics.__name__} import (  # noqa: F401  sha256 {_digest(_intrinsics)}\n"
        + "".join(f"    {n},\n" for n in _intrinsics.__all__)
        + ")\n"
        f"from {constants.__name__} import *  # noqa: F403  sha256 {_digest(constants)}\n"
        f"from {config.__name__} import (  # noqa: F401  sha256 {_digest(config)}\n"
        "    Budget, Disc, Motion, Physics, State, Window,\n"
        ")\n"
        f"from {intrinsics.__name__} import (  # noqa: F401  sha256 {_digest(intrinsics)}\n"
        + "".join(f"    {n},\n" for n in names)
        + ")\n"
    )


def _bodies() -> str:
    out = []
    for part in PARTS:
        src = inspect.getsource(part)
        out.append(src[src.index(BODY_MARK) + len(BODY_MARK) :].strip("\n"))
    return "\n\n\n".join(out) + "\n"


# Read once, when the package is imported: a kernel must match the modules this process runs
# with, even if the files change on disk later (an upgrade, an edit).
HEAD = (
    '"""A particle step kernel module generated by fastsdf.particles.scene_blocks from the modules '
    "of\nfastsdf.particles.kernels and one world's scene block; do not edit: the file name "
    'is the\nhash of this content."""\n\nimport math\n\nimport numpy as np\n'
    "from numba import njit, prange\n\n" + _shared_imports() + "\n"
)
TAIL = "\n\n" + _bodies()


def kernel_source(scene_block: str, head: str | None = None, tail: str | None = None) -> str:
    """The source of a kernel module: the shared imports (``head``, default :data:`HEAD`),
    ``scene_block`` (the definitions listed in this package's docs) and the kernels' bodies
    (``tail``, default :data:`TAIL`)."""
    return (HEAD if head is None else head) + scene_block + (TAIL if tail is None else tail)
