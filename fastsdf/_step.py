"""The fused particle step: integrate, query the world, sweep, respond (numba).

This is a real module: its functions are importable and tested directly (``tests/test_step.py``)
against the small analytic world defined in the marked *scene block* below. A simulation does
not call them from here: :func:`fastsdf.particles._kernel_module` copies this file's source,
replaces the scene block with the simulation's own query and forces, writes the result to a
content-hashed file in the kernel cache (:mod:`fastsdf.backends.kernel.cache`) and imports that. Because the
whole of this source is in the generated file, editing this module changes the hash, so a
stale compiled kernel is never loaded (numba's ``cache=True`` does not notice changes in other
modules a cached function calls into).

The scene block
---------------
Everything between the ``SCENE BLOCK`` marker comments is replaced. It must define:

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
shrink by ``lip |D| + W dt``, so the sweep marches in space-time (:func:`_march_t`) with that
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
1. acceleration ``a = g + (F_user + ext - drag v) / m``;
2. integrate (semi-implicit or explicit Euler); the displacement is ``D``;
3. free-flight skipping: while the budget from an earlier query exceeds ``|D|``, no query;
4. query the end point, ``s = d - r``;
5. tunnelling sweep (:func:`_sweep`) when ``|D| > TRACE_FRACTION r`` and the end is not
   clear by ``lip |D|``;
6. respond where ``s <= 0`` (:func:`_respond`), or, with ``rest > 0`` (``rest_speed``),
   hold a slow particle that :func:`_rests` where it was with zero velocity; else refill the
   skipping budget;
7. a particle whose step left its state bit-identical sleeps for the rest of the call
   (``SLEEP``: a static world and no user force, so every later step would repeat it).

Calls without query skipping, tunnelling check, moving world or resting contact (the peers'
work: ``skip`` and ``trace`` off, ``rest`` 0) go to :func:`plain_par`/:func:`plain_ser`, a
separate entry point compiled only when first used: the same results from a shorter loop (no
budgets, no sweep), which runs a step particle after particle while few particles of a block
touch a surface and in two passes over batches of ``PLAIN_BATCH`` (integrate and query all,
then respond) after a step where many did, so that mispredicted contact branches do not
discard the next particles' queries.

A static grid world with stored gradients (``GRID_SIMD``, set in the scene block; float64
state, ``rest`` 0, no Python forces) goes to :func:`simd_par`/:func:`simd_ser` instead: the
same results from :func:`_block_simd`, which keeps ``LANES`` particles in the rows of one
scratch array through all steps of a call and runs each step as passes over them: a vector
pass of forces, integration, free-flight budgets and the grid cell (:func:`_simd_move`), a
scalar pass loading the cells (:func:`_simd_gather`, each cell's three channels blended in one
vector), a scalar fix-up of only the particles that need a tunnelling sweep or a query outside
the grid (:func:`_simd_fix`), and a vector pass of the response with selects instead of
branches (:func:`_simd_respond`). A step in which no particle of the block needs a query is
the first pass alone. Sleeping is not needed there (it changes no result).

Checks (no separate pass over memory): before a call's first step every particle of a block
is checked on values the step loads anyway (``x``, ``v`` finite, ``r`` finite and >= 0, ``m``
finite and > 0 when read); ``cr``, ``cf`` are checked where a contact uses them; every step's
result is checked finite. With ``check_all`` (the caller's dirty flag: the state's ``m``,
``cr``, ``cf`` may have been written since the last call) the first pass also checks ``m``,
``cr`` and ``cf`` of every particle. A particle that fails is frozen at its last valid state for the rest
of the call and flagged in ``FLAGS`` (1: invalid input, 2: a step produced a non-finite state,
3: invalid ``cr``/``cf`` at a contact); the kernels return how many were frozen.
"""

import math

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

# Tuning constants (documented in fastsdf.particles, which re-exports them).
TRACE_FRACTION = 0.5
MIN_STEP = 0.02
CONTACT_TOL = 1e-3
MAX_MARCH = 64
MAX_BOUNCES = 3
#: Particles whose user forces are evaluated together ahead of their steps.
FORCE_BATCH = 32

#: ``clear[k]`` of a particle asleep for the rest of a call (its state is a fixed point).
ASLEEP = -0.5

FLAG_INPUT = 1
FLAG_NONFINITE = 2
FLAG_COEFF = 3
#: FLAGS[i] = FLAG_RESUME + step: the particle stopped before ``step`` because it came near the
#: edge of a grid whose exact fallback is not bound yet; the caller binds it and resumes.
FLAG_RESUME = 16


# ---------------------------------------------------------------------------------------------
# Intrinsics.

def _borrowed_codegen(context, builder, ty, val):
    """``val`` of type ``ty`` with every array in it (recursively in tuples) made a view
    without a reference count."""
    if isinstance(ty, types.Array):
        src = context.make_array(ty)(context, builder, val)
        out = context.make_array(ty)(context, builder)
        for field in ("nitems", "itemsize", "data", "shape", "strides"):
            setattr(out, field, getattr(src, field))
        out.meminfo = cgutils.get_null_value(out.meminfo.type)
        out.parent = cgutils.get_null_value(out.parent.type)
        return out._getvalue()
    if isinstance(ty, types.BaseTuple):
        vals = [_borrowed_codegen(context, builder, t, builder.extract_value(val, k))
                for k, t in enumerate(ty.types)]
        return context.make_tuple(builder, ty, vals)
    return val


def _borrowable(ty) -> bool:
    if isinstance(ty, types.BaseTuple):
        return all(_borrowable(t) for t in ty.types)
    return isinstance(ty, (types.Array, types.Number, types.Boolean))


@intrinsic
def borrow_all(typingctx, data):
    """``data`` (an array, a number, or tuples of them, nested) with every array replaced by a
    view without a reference count (null meminfo).

    Passing an array to a function numba does not inline costs an atomic increment and
    decrement of its reference count around every call; with several threads querying one
    grid, those atomics on one shared cache line serialise the threads. The kernel makes such
    views once per block; the caller keeps the real arrays alive.
    """
    if not _borrowable(data):
        return None

    def codegen(context, builder, signature, args):
        return _borrowed_codegen(context, builder, signature.args[0], args[0])

    return data(data), codegen


@intrinsic
def call_vg(typingctx, address, x, y):
    """``(d, dd/dx, dd/dy)`` from the C function ``void f(double x, double y, double *out)`` at
    ``address`` (a numba ``cfunc``): the exact fallback of grid worlds, bound at run time so
    that the kernel does not depend on the scene."""
    if not isinstance(address, types.Integer):
        return None
    sig = types.UniTuple(types.float64, 3)(address, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        a, xv, yv = args
        dbl = ir.DoubleType()
        fnty = ir.FunctionType(ir.VoidType(), [dbl, dbl, dbl.as_pointer()])
        fp = builder.inttoptr(a, fnty.as_pointer())
        out = cgutils.alloca_once(builder, dbl, size=3)
        builder.call(fp, [xv, yv, out])
        vals = [builder.load(builder.gep(out, [ir.Constant(ir.IntType(32), k)]))
                for k in range(3)]
        return context.make_tuple(builder, signature.return_type, vals)

    return sig, codegen


# >>> SCENE BLOCK (replaced in generated kernels; see the module docstring) >>>
# The test world: a union of solid half-planes and discs.
# data = (planes, discs): planes (k, 3) rows (nx, ny, c), unit normal n, solid where n.p <= c;
# discs (j, 3) rows (cx, cy, R). d = min over all of (n.p - c) and (|p - c| - R).
_CACHE = True
USE_FORCE = False
FORCE_AHEAD = False
# Not a grid world: the block kernel (simd_par/simd_ser) does not apply.
GRID_SIMD = False
GRID_EXACT = False


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _query(data, x, y):
    """(d, dd/dx, dd/dy) of the test world at one point."""
    planes, discs = data
    d = math.inf
    gx = 0.0
    gy = 0.0
    for k in range(planes.shape[0]):
        e = planes[k, 0] * x + planes[k, 1] * y - planes[k, 2]
        if e < d:
            d = e
            gx = planes[k, 0]
            gy = planes[k, 1]
    for k in range(discs.shape[0]):
        ux = x - discs[k, 0]
        uy = y - discs[k, 1]
        ln = math.sqrt(ux * ux + uy * uy)
        e = ln - discs[k, 2]
        if e < d:
            d = e
            gx = ux / ln if ln > 0.0 else 1.0
            gy = uy / ln if ln > 0.0 else 0.0
    return d, gx, gy


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _force(x, y, vx, vy, m, t):
    """Sum of the fused user forces (none in the test world)."""
    return 0.0, 0.0


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _fallback_missing(data, x, y, dx, dy):
    """Whether a step from (x, y) by (dx, dy) may query where the world is not available yet
    (never in the test world)."""
    return False


MOVING = False


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _query_t(data, x, y, t):
    """(d, dd/dx, dd/dy, dd/dt) at time t: the test world does not move."""
    d, gx, gy = _query(data, x, y)
    return d, gx, gy, 0.0


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _wall_speed(data):
    """A bound on |dd/dt| (the test world does not move)."""
    return 0.0


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _wall_speed_at(data, x, y, dx, dy):
    """A bound on |dd/dt| for a step by (dx, dy) ending at (x, y)."""
    return 0.0
# <<< SCENE BLOCK <<<


# ---------------------------------------------------------------------------------------------
# The step's parts.

#: Whether a particle whose step repeats its state may sleep for the rest of a call: the step
#: must not depend on time (no moving world, no user force, which may use ``t``).
SLEEP = not MOVING and not USE_FORCE

@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _respond(x, y, vx, vy, s, gx, gy, cr, cf, always, gt=0.0):
    """Collision response of a disc whose surface distance is ``s = d - r <= 0`` (House and
    Keyser): ``x -= (1 + cr) s n`` and, when approaching (``v . n < 0``) or ``always``,
    ``v = -cr v_n + (1 - cf) v_t``, with ``n = grad / |grad|``. A zero or non-finite gradient
    (a ridge of a grid) gives no direction: the state is returned unchanged.

    Written with selects rather than branches, so that a block of particles can share one
    instruction stream.

    A moving wall (``gt = dd/dt``) has normal speed ``w = -gt / |grad|``: the relative normal
    velocity ``v_n - w`` is what approaches and reflects (``v_n -> w - cr (v_n - w)``).
    """
    gl2 = gx * gx + gy * gy
    ok = gl2 > 0.0 and gl2 < math.inf
    inv = 1.0 / math.sqrt(gl2) if ok else 0.0
    nx = gx * inv if ok else 0.0
    ny = gy * inv if ok else 0.0
    k = (1.0 + cr) * s
    x -= k * nx
    y -= k * ny
    vn = vx * nx + vy * ny
    wn = -gt * inv                    # the wall's normal speed (0 for a static world)
    vr = vn - wn
    resp = ok and (vr < 0.0 or always)
    w = 1.0 - cf if resp else 1.0     # tangential factor
    c = cr if resp else -1.0          # relative normal velocity becomes -c vr (same for c = -1)
    vx = w * (vx - vn * nx) + (wn - c * vr) * nx
    vy = w * (vy - vn * ny) + (wn - c * vr) * ny
    return x, y, vx, vy


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _march(data, x0, y0, dx, dy, r, lip, t, t_free):
    """Conservative advancement of a disc of radius r from (x0, y0) along (dx, dy).

    The parts of the segment with parameter below ``t`` and above ``t_free`` are already known
    to be free. Returns (t, hit, s, nx, ny): hit = 1 for an approaching contact at parameter t
    (surface distance s <= tolerance, unit normal n), 0 for a free path to t = 1, 2 when the
    iteration limit stopped it at t (a safe point, short of any contact).
    """
    length = math.sqrt(dx * dx + dy * dy)
    inv_len = 1.0 / length
    tol = CONTACT_TOL * length
    # A step no longer than TRACE_FRACTION * r cannot carry the disc across a wall unseen (the
    # same reason short steps skip this check), so the march never needs smaller steps.
    short = TRACE_FRACTION * r * inv_len          # in units of t
    far = inv_len / lip                           # t per unit of surface distance
    leave = max(short, MIN_STEP)
    if t >= t_free:
        return 1.0, 0, 0.0, 0.0, 0.0
    for _ in range(MAX_MARCH):
        d, gx, gy = _query(data, x0 + t * dx, y0 + t * dy)
        s = d - r
        if s > tol:
            t += max(s * far, short)              # sphere tracing: free within s / L
        elif gx * dx + gy * dy < 0.0:             # in contact and approaching
            gl = math.sqrt(gx * gx + gy * gy)
            if gl < math.inf:
                return t, 1, s, gx / gl, gy / gl
            t += leave
        elif s == s:
            # touching but leaving (or sliding along) the surface: move on by a short step
            t += leave
        else:
            return 1.0, 0, 0.0, 0.0, 0.0          # non-finite SDF: nothing to trace against
        if t >= t_free:
            return 1.0, 0, 0.0, 0.0, 0.0
    return t, 2, 0.0, 0.0, 0.0


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _sweep(data, x, y, dx, dy, vx, vy, r, cr, cf, lip, always, t0, t1):
    """Tunnelling check of one step: sweep the disc from (x, y) along (dx, dy).

    ``t0``, ``t1``: the step's parameters below and above which it is already known to be
    free (from the start's and the end's distance budgets).

    Returns the new start point and remaining displacement, the velocity, and whether a
    contact was met (then the displacement and velocity have been reflected) or the end point
    moved for another reason.
    """
    bounced = False
    for b in range(MAX_BOUNCES):
        t, hit, s, nx, ny = _march(data, x, y, dx, dy, r, lip, t0, t1)
        t0 = 0.0
        t1 = 1.0
        if hit == 0:
            break
        x += t * dx
        y += t * dy
        if hit == 2:                  # iteration limit: stay at the last safe point
            return x, y, 0.0, 0.0, vx, vy, True
        rx = (1.0 - t) * dx
        ry = (1.0 - t) * dy
        pen = s + rx * nx + ry * ny   # end point's depth below the tangent line at contact
        if pen < 0.0:
            rx -= (1.0 + cr) * pen * nx
            ry -= (1.0 + cr) * pen * ny
        vn = vx * nx + vy * ny
        if vn < 0.0 or (always and not bounced):
            f = 1.0 - cf
            vx = f * (vx - vn * nx) - cr * vn * nx
            vy = f * (vy - vn * ny) - cr * vn * ny
        bounced = True
        if b == MAX_BOUNCES - 1:      # out of bounces: stop at this contact
            return x, y, 0.0, 0.0, vx, vy, bounced
        dx = rx
        dy = ry
        rr = dx * dx + dy * dy
        short = TRACE_FRACTION * r
        if rr <= short * short:       # a short rest needs no sweep (see the step's test)
            break
        # The rest leaves the contact (or slides along it): the march's first step from the
        # contact point is a short one, so take it without querying the contact again.
        length = math.sqrt(rr)
        if rx * nx + ry * ny >= 0.0:
            t0 = max(short, MIN_STEP * length) / length
    return x, y, dx, dy, vx, vy, bounced


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _march_t(data, x0, y0, dx, dy, r, lip, t, t_free, ts, tdt, wd):
    """:func:`_march` in space-time, for a moving world: the disc moves from (x0, y0) along
    (dx, dy) while time runs from ``ts`` over ``tdt``; ``wd = W tdt`` bounds how much the
    surfaces move meanwhile. Along the path the distance changes at most at the rate
    ``lip |D| + wd`` per unit of the parameter, which sets the sphere-tracing step; a contact
    approaches when ``d`` decreases along the path (``grad . D + dd/dt tdt < 0``). Returns
    (t, hit, s, nx, ny, wn), ``wn`` the wall's normal speed at the contact.
    """
    length = math.sqrt(dx * dx + dy * dy) + wd / lip   # distance-equivalent length of the step
    inv_len = 1.0 / length
    tol = CONTACT_TOL * length
    short = TRACE_FRACTION * r * inv_len
    far = inv_len / lip
    leave = max(short, MIN_STEP)
    if t >= t_free:
        return 1.0, 0, 0.0, 0.0, 0.0, 0.0
    for _ in range(MAX_MARCH):
        d, gx, gy, gt = _query_t(data, x0 + t * dx, y0 + t * dy, ts + t * tdt)
        s = d - r
        if s > tol:
            t += max(s * far, short)
        elif gx * dx + gy * dy + gt * tdt < 0.0:      # in contact and approaching
            gl = math.sqrt(gx * gx + gy * gy)
            if gl > 0.0 and gl < math.inf:
                return t, 1, s, gx / gl, gy / gl, -gt / gl
            t += leave
        elif s == s:
            t += leave
        else:
            return 1.0, 0, 0.0, 0.0, 0.0, 0.0
        if t >= t_free:
            return 1.0, 0, 0.0, 0.0, 0.0, 0.0
    return t, 2, 0.0, 0.0, 0.0, 0.0


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _sweep_t(data, x, y, dx, dy, vx, vy, r, cr, cf, lip, always, t0, t1, ts, tdt, wd):
    """:func:`_sweep` for a moving world (see :func:`_march_t`): at a contact the remaining
    displacement reflects off the wall where it will be, and the velocity relative to the
    wall reflects. Same returns as :func:`_sweep`."""
    bounced = False
    for b in range(MAX_BOUNCES):
        t, hit, s, nx, ny, wn = _march_t(data, x, y, dx, dy, r, lip, t0, t1, ts, tdt, wd)
        t0 = 0.0
        t1 = 1.0
        if hit == 0:
            break
        x += t * dx
        y += t * dy
        ts += t * tdt
        tdt *= 1.0 - t
        wd *= 1.0 - t
        if hit == 2:
            return x, y, 0.0, 0.0, vx, vy, True
        rx = (1.0 - t) * dx
        ry = (1.0 - t) * dy
        # end point's depth below the contact's tangent line, moved with the wall until the end
        pen = s + rx * nx + ry * ny - wn * tdt
        if pen < 0.0:
            rx -= (1.0 + cr) * pen * nx
            ry -= (1.0 + cr) * pen * ny
        vn = vx * nx + vy * ny
        vr = vn - wn
        if vr < 0.0 or (always and not bounced):
            f = 1.0 - cf
            vx = f * (vx - vn * nx) + (wn - cr * vr) * nx
            vy = f * (vy - vn * ny) + (wn - cr * vr) * ny
        bounced = True
        if b == MAX_BOUNCES - 1:
            return x, y, 0.0, 0.0, vx, vy, bounced
        dx = rx
        dy = ry
        rr = math.sqrt(dx * dx + dy * dy) + wd / lip
        short = TRACE_FRACTION * r
        if rr <= short:
            break
        if rx * nx + ry * ny - wn * tdt >= 0.0:
            t0 = max(short, MIN_STEP * rr) / rr
    return x, y, dx, dy, vx, vy, bounced


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _rests(vx, vy, ax, ay, gx, gy, cf, rest):
    """Whether a particle in contact rests (``rest_speed``): its velocity at the start of
    the step is below ``rest`` (length/s), its acceleration ``a`` pushes it into the surface
    (``a . n < 0``, ``n = grad / |grad|``) and static friction can hold it: the tangential
    part of ``a`` is at most ``cf`` times the normal part (surfaces tilted less than
    ``atan(cf)`` under gravity)."""
    gl2 = gx * gx + gy * gy
    if not (gl2 > 0.0 and gl2 < math.inf) or vx * vx + vy * vy > rest * rest:
        return False
    inv = 1.0 / math.sqrt(gl2)
    an = (ax * gx + ay * gy) * inv
    at2 = ax * ax + ay * ay - an * an
    return an < 0.0 and at2 <= cf * cf * an * an


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _finite4(x, y, vx, vy):
    """Whether all four are finite, in one test (``a - a`` is 0 for a finite ``a`` and NaN
    for an infinite or NaN one): fewer instructions and branches per step than four tests."""
    return (x - x) + (y - y) + (vx - vx) + (vy - vy) == 0.0


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _valid_input(x, y, vx, vy, r, m, use_m):
    """Whether a particle's loaded state may be stepped (cr, cf are checked at contacts)."""
    ok = (abs(x) < math.inf and abs(y) < math.inf and abs(vx) < math.inf
          and abs(vy) < math.inf and r >= 0.0 and r < math.inf)
    if use_m:
        ok = ok and m > 0.0 and m < math.inf
    return ok


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _freeze(clear, FLAGS, k, i, flag):
    """Freeze particle ``i`` (``k`` in its block) with ``flag``; returns 1 (one more frozen)."""
    clear[k] = -1.0
    FLAGS[i] = flag
    return 1


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _coeffs(CR, CF, i):
    """``cr, cf`` of particle ``i`` and whether both lie in [0, 1]."""
    cr = float(CR[i])
    cf = float(CF[i])
    return cr, cf, (cr >= 0.0) & (cr <= 1.0) & (cf >= 0.0) & (cf <= 1.0)


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _check_block(lo, hi, X, V, M, R, CR, CF, FLAGS, clear, inv_mass, use_m, check_all):
    """A block's first pass: ``1 / m`` into ``inv_mass`` (when ``use_m``) and the checks of
    the module docstring; freezes a failing particle and returns how many failed."""
    bad = 0
    for i in range(lo, hi):
        m = float(M[i]) if use_m or check_all else 1.0
        if use_m:
            inv_mass[i - lo] = 1.0 / m
        ok = _valid_input(float(X[i, 0]), float(X[i, 1]), float(V[i, 0]), float(V[i, 1]),
                          float(R[i]), m, use_m or check_all)
        if check_all:
            ok = ok and _coeffs(CR, CF, i)[2]
        if not ok:
            bad += _freeze(clear, FLAGS, i - lo, i, FLAG_INPUT)
    return bad


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _load(Xf, Vf, i):
    """Particle ``i``'s unsigned index and flat indices ``ix, iy`` into the flattened state
    (no negative-index wrap, no stride multiply), and its ``x, y, vx, vy``."""
    u = np.uint64(i)
    ix = np.uint64(2) * u
    iy = ix + np.uint64(1)
    return u, ix, iy, float(Xf[ix]), float(Xf[iy]), float(Vf[ix]), float(Vf[iy])


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _store(Xf, Vf, ix, iy, x, y, vx, vy):
    """Write a particle's state back (indices from :func:`_load`)."""
    Xf[ix] = x
    Xf[iy] = y
    Vf[ix] = vx
    Vf[iy] = vy


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _forces_ahead(Xf, Vf, M, clear, lo, j0, j1, fbuf, t):
    """The user forces of particles ``j0..j1-1`` into rows ``0..`` of ``fbuf`` (``FORCE_AHEAD``):
    a loop of independent iterations, so the CPU overlaps their arithmetic instead of adding
    its latency to each particle's dependent chain."""
    for j in range(j0, j1):
        if clear[j - lo] >= 0.0:
            u, ix, iy, x, y, vx, vy = _load(Xf, Vf, j)
            ux, uy = _force(x, y, vx, vy, float(M[u]), t)
            fbuf[j - j0, 0] = ux
            fbuf[j - j0, 1] = uy


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _accel(i, k, x, y, vx, vy, t, M, EXT, inv_mass, fbuf, q, ax, ay, drag, use_m, use_ext):
    """Acceleration ``g + (F_user + ext - drag v) / m`` of particle ``i`` (``k`` in its
    block); ``q``: its row of ``fbuf`` when the user forces were evaluated ahead. Callers pass
    ``M``, ``EXT`` and ``inv_mass`` through :func:`borrow_all`: arrays read only in these
    branches would keep numba's reference counting (atomics) in the particle loop."""
    bx = ax
    by = ay
    if use_m:
        inv_m = inv_mass[k]
        fx = -drag * vx
        fy = -drag * vy
        if use_ext:
            fx += EXT[i, 0]
            fy += EXT[i, 1]
        if USE_FORCE and FORCE_AHEAD:
            fx += fbuf[q, 0]
            fy += fbuf[q, 1]
        elif USE_FORCE:
            ux, uy = _force(x, y, vx, vy, float(M[np.uint64(i)]), t)
            fx += ux
            fy += uy
        bx += fx * inv_m
        by += fy * inv_m
    return bx, by


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _integrate(vx, vy, bx, by, dt, explicit):
    """One Euler step of the velocity by acceleration ``b``: the displacement and the new
    velocity (explicit: displacement from the old velocity; else semi-implicit)."""
    if explicit:
        dx = vx * dt
        dy = vy * dt
        vx += bx * dt
        vy += by * dt
    else:
        vx += bx * dt
        vy += by * dt
        dx = vx * dt
        dy = vy * dt
    return dx, dy, vx, vy


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _block(data, lo, hi, steps, X, V, M, R, CR, CF, EXT, FLAGS, dt, t0, ax, ay, drag, use_m,
           use_ext, explicit, always, trace, lip, margin, eps, skip, rest, check_all):
    """All steps for particles lo..hi-1; returns the number of particles frozen (flagged).

    The only compiled call that touches the arrays: helpers that take arrays are inlined and the
    others take scalars, so no reference counting happens per particle.

    Free-flight skipping (``skip``): after a query that finds a particle clear of every surface
    by ``s = d - r > 0``, it can move ``(s - margin) / lip`` before it could touch anything, so
    its next steps skip the SDF query until that budget is spent. This changes no result: a
    skipped query is one that would have found no contact. ``margin`` covers a grid's jump to
    the exact SDF at its bounds; ``eps`` is the relative rounding of stored coordinates.
    ``clear[k] < 0`` marks a frozen particle.
    """
    data = borrow_all(data)
    M, EXT = borrow_all((M, EXT))       # see _accel
    clear = np.zeros(hi - lo)
    # A moving world: its surfaces move by at most wd per step near a particle (0 for a static
    # world, and far from every moving wall).
    wd = 0.0
    use_m = use_m or USE_FORCE
    # 1 / m of the block, computed once per call rather than divided every step
    inv_mass = np.empty(hi - lo if use_m else 0)
    fbuf = np.empty((FORCE_BATCH if USE_FORCE and FORCE_AHEAD else 0, 2))
    bad = _check_block(lo, hi, X, V, M, R, CR, CF, FLAGS, clear, inv_mass, use_m, check_all)
    Xf = X.reshape(X.size)
    Vf = V.reshape(V.size)
    for step in range(steps):
        t = t0 + step * dt
        for i in range(lo, hi):
            k = i - lo
            if USE_FORCE and FORCE_AHEAD and k % FORCE_BATCH == 0:
                _forces_ahead(Xf, Vf, M, clear, lo, i, min(hi, i + FORCE_BATCH), fbuf, t)
            c = clear[k]
            if c < 0.0:
                continue
            u, ix, iy, x, y, vx, vy = _load(Xf, Vf, i)
            r = float(R[u])
            x0 = x
            y0 = y
            vx0 = vx
            vy0 = vy
            bx, by = _accel(i, k, x, y, vx, vy, t, M, EXT, borrow_all(inv_mass), fbuf,
                            k % FORCE_BATCH, ax, ay, drag, use_m, use_ext)
            dx, dy, vx, vy = _integrate(vx, vy, bx, by, dt, explicit)
            if MOVING:
                wd = _wall_speed_at(data, x + dx, y + dy, dx, dy) * dt
            if c > 0.0:
                # (1 + CONTACT_TOL / lip): a skipped step must also be one whose sweep would
                # not have stopped at a near-contact (s <= CONTACT_TOL |step|).
                c -= (math.sqrt(dx * dx + dy * dy) * (1.0 + CONTACT_TOL / lip)
                      + eps * (abs(x) + abs(y) + 1.0) + wd / lip)
                if c > 0.0:
                    x += dx
                    y += dy
                    if not _finite4(x, y, vx, vy):
                        bad += _freeze(clear, FLAGS, k, u, FLAG_NONFINITE)
                        continue
                    clear[k] = c
                    _store(Xf, Vf, ix, iy, x, y, vx, vy)
                    continue
                clear[k] = 0.0
            if _fallback_missing(data, x, y, dx, dy):
                bad += _freeze(clear, FLAGS, k, u, FLAG_RESUME + step)
                continue
            gt = 0.0
            if MOVING:
                d, gx, gy, gt = _query_t(data, x + dx, y + dy, t + dt)
            else:
                d, gx, gy = _query(data, x + dx, y + dy)
            s = d - r
            bounced = False
            if trace:
                dd = dx * dx + dy * dy
                ln = 0.0
                # Sweep only a step longer than TRACE_FRACTION * r whose end is not clear of
                # everything by the step's length (then no wall can lie across the step); for
                # a moving world the length includes how far the walls move (wd / lip).
                if MOVING:
                    ln = math.sqrt(dd) + wd / lip
                    sweep = ln > TRACE_FRACTION * r and not (s >= lip * ln and s > 0.0)
                else:
                    sweep = dd > (TRACE_FRACTION * r) * (TRACE_FRACTION * r) and not (
                        s * s >= lip * lip * dd and s > 0.0)
                if sweep:
                    cr, cf, ok = _coeffs(CR, CF, u)
                    if not ok:
                        bad += _freeze(clear, FLAGS, k, u, FLAG_COEFF)
                        continue
                    # The part within s / L of the end is known to be free. (The start's
                    # budget is not used: results must not depend on how steps are grouped
                    # into calls.)
                    if MOVING:
                        t1 = 1.0 - s / (lip * ln) if s > 0.0 else 1.0
                        x, y, dx, dy, vx, vy, bounced = _sweep_t(
                            data, x, y, dx, dy, vx, vy, r, cr, cf, lip, always, 0.0, t1, t, dt,
                            wd)
                        if bounced:
                            d, gx, gy, gt = _query_t(data, x + dx, y + dy, t + dt)
                            s = d - r
                    else:
                        t1 = 1.0 - s / (lip * math.sqrt(dd)) if s > 0.0 else 1.0
                        x, y, dx, dy, vx, vy, bounced = _sweep(data, x, y, dx, dy, vx, vy, r,
                                                               cr, cf, lip, always, 0.0, t1)
                        if bounced:
                            d, gx, gy = _query(data, x + dx, y + dy)
                            s = d - r
            x += dx
            y += dy
            if s <= 0.0:
                cr, cf, ok = _coeffs(CR, CF, u)
                if not ok:
                    bad += _freeze(clear, FLAGS, k, u, FLAG_COEFF)
                    continue
                if rest > 0.0 and not bounced and _rests(vx0, vy0, bx, by, gx, gy, cf, rest):
                    # resting contact: the surface holds the particle where it is
                    x = x0
                    y = y0
                    vx = 0.0
                    vy = 0.0
                else:
                    x, y, vx, vy = _respond(x, y, vx, vy, s, gx, gy, cr, cf,
                                            always and not bounced, gt)
            elif skip and s > margin:
                clear[k] = (s - margin) / lip * (1.0 - 1e-9)
            if not _finite4(x, y, vx, vy):
                bad += _freeze(clear, FLAGS, k, u, FLAG_NONFINITE)
                continue
            if SLEEP and x == x0 and y == y0 and vx == vx0 and vy == vy0 and steps > 1:
                # The step left the state bit-identical, and nothing else it depends on changes
                # within this call (static world, forces independent of time): every later
                # step of the call would repeat it, so the particle sleeps until the next call.
                clear[k] = ASLEEP
                continue
            _store(Xf, Vf, ix, iy, x, y, vx, vy)
    return bad


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _plain_straight(data, lo, hi, step, t, Xf, Vf, M, R, CR, CF, EXT, FLAGS, clear, inv_mass,
                    fbuf, dt, ax, ay, drag, use_m, use_ext, explicit, always):
    """One step of a block for :func:`_block_plain`, particle after particle."""
    bad = 0
    touching = 0
    for i in range(lo, hi):
        k = i - lo
        if USE_FORCE and FORCE_AHEAD and k % FORCE_BATCH == 0:
            _forces_ahead(Xf, Vf, M, clear, lo, i, min(hi, i + FORCE_BATCH), fbuf, t)
        if clear[k] < 0.0:
            continue
        u, ix, iy, x, y, vx, vy = _load(Xf, Vf, i)
        r = float(R[u])
        bx, by = _accel(i, k, x, y, vx, vy, t, M, EXT, borrow_all(inv_mass), fbuf,
                        k % FORCE_BATCH, ax, ay, drag, use_m, use_ext)
        dx, dy, vx, vy = _integrate(vx, vy, bx, by, dt, explicit)
        if _fallback_missing(data, x, y, dx, dy):
            bad += _freeze(clear, FLAGS, k, u, FLAG_RESUME + step)
            continue
        d, gx, gy = _query(data, x + dx, y + dy)
        s = d - r
        x += dx
        y += dy
        if s <= 0.0:
            touching += 1
            cr, cf, ok = _coeffs(CR, CF, u)
            if not ok:
                bad += _freeze(clear, FLAGS, k, u, FLAG_COEFF)
                continue
            x, y, vx, vy = _respond(x, y, vx, vy, s, gx, gy, cr, cf, always, 0.0)
        if not _finite4(x, y, vx, vy):
            bad += _freeze(clear, FLAGS, k, u, FLAG_NONFINITE)
            continue
        _store(Xf, Vf, ix, iy, x, y, vx, vy)
    return bad, touching


#: Particles a batched plain step handles per pass (see :func:`_plain_staged`; at most
#: ``FORCE_BATCH``, the size of the buffer of forces evaluated ahead).
PLAIN_BATCH = 16


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _plain_staged(data, lo, hi, step, t, Xf, Vf, M, R, CR, CF, EXT, FLAGS, clear, inv_mass,
                  fbuf, sb, dt, ax, ay, drag, use_m, use_ext, explicit, always):
    """One step of a block for :func:`_block_plain`, ``PLAIN_BATCH`` particles at a time in
    two passes: integrate and query all of them (independent iterations without
    data-dependent branches, so their dependent chains overlap), then respond (the contact
    branch mispredicts often while particles rest; there a mispredict no longer discards the
    next particles' queries). ``sb``: scratch of shape (7, PLAIN_BATCH)."""
    bad = 0
    touching = 0
    for b0 in range(lo, hi, PLAIN_BATCH):
        b1 = min(hi, b0 + PLAIN_BATCH)
        if USE_FORCE and FORCE_AHEAD:
            _forces_ahead(Xf, Vf, M, clear, lo, b0, b1, fbuf, t)
        for i in range(b0, b1):
            k = i - lo
            q = i - b0
            if clear[k] < 0.0:
                continue
            u, ix, iy, x, y, vx, vy = _load(Xf, Vf, i)
            bx, by = _accel(i, k, x, y, vx, vy, t, M, EXT, borrow_all(inv_mass), fbuf, q,
                            ax, ay, drag, use_m, use_ext)
            dx, dy, vx, vy = _integrate(vx, vy, bx, by, dt, explicit)
            if _fallback_missing(data, x, y, dx, dy):
                bad += _freeze(clear, FLAGS, k, u, FLAG_RESUME + step)
                continue
            d, gx, gy = _query(data, x + dx, y + dy)
            sb[0, q] = x + dx
            sb[1, q] = y + dy
            sb[2, q] = vx
            sb[3, q] = vy
            sb[4, q] = d - float(R[u])
            sb[5, q] = gx
            sb[6, q] = gy
        for i in range(b0, b1):
            k = i - lo
            q = i - b0
            if clear[k] < 0.0:
                continue
            u = np.uint64(i)
            s = sb[4, q]
            x = sb[0, q]
            y = sb[1, q]
            vx = sb[2, q]
            vy = sb[3, q]
            if s <= 0.0:
                touching += 1
                cr, cf, ok = _coeffs(CR, CF, u)
                if not ok:
                    bad += _freeze(clear, FLAGS, k, u, FLAG_COEFF)
                    continue
                x, y, vx, vy = _respond(x, y, vx, vy, s, sb[5, q], sb[6, q], cr, cf,
                                        always, 0.0)
            if not _finite4(x, y, vx, vy):
                bad += _freeze(clear, FLAGS, k, u, FLAG_NONFINITE)
                continue
            ix = np.uint64(2) * u
            _store(Xf, Vf, ix, ix + np.uint64(1), x, y, vx, vy)
    return bad, touching


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _plain_steps(data, lo, hi, steps, Xf, Vf, M, R, CR, CF, EXT, FLAGS, clear, inv_mass, fbuf,
                 sb, dt, t0, ax, ay, drag, use_m, use_ext, explicit, always):
    """The steps of :func:`_block_plain`: a step in batches (:func:`_plain_staged`) after a
    step where at least a quarter of the block touched a surface, else particle after
    particle (:func:`_plain_straight`); the two give the same results."""
    bad = 0
    touching = 0
    for step in range(steps):
        t = t0 + step * dt
        if 4 * touching >= hi - lo:
            b, touching = _plain_staged(data, lo, hi, step, t, Xf, Vf, M, R, CR, CF, EXT, FLAGS,
                                        clear, inv_mass, fbuf, sb, dt, ax, ay, drag, use_m,
                                        use_ext, explicit, always)
        else:
            b, touching = _plain_straight(data, lo, hi, step, t, Xf, Vf, M, R, CR, CF, EXT,
                                          FLAGS, clear, inv_mass, fbuf, dt, ax, ay, drag, use_m,
                                          use_ext, explicit, always)
        bad += b
    return bad


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _block_plain(data, lo, hi, steps, X, V, M, R, CR, CF, EXT, FLAGS, dt, t0, ax, ay, drag,
                 use_m, use_ext, explicit, always, check_all):
    """:func:`_block` without query skipping, tunnelling check, moving world or resting
    contact: every step is integrate, query, respond, as in the peers' kernels. Same results
    as :func:`_block` with those off, in fewer instructions per particle-step (flat unsigned
    indexing, the common flags constant), so that out-of-order execution overlaps more
    particles' dependent chains.
    """
    data = borrow_all(data)
    M, EXT = borrow_all((M, EXT))       # see _accel
    clear = np.zeros(hi - lo)
    use_m = use_m or USE_FORCE
    inv_mass = np.empty(hi - lo if use_m else 0)
    fbuf = np.empty((FORCE_BATCH if USE_FORCE and FORCE_AHEAD else 0, 2))
    bad = _check_block(lo, hi, X, V, M, R, CR, CF, FLAGS, clear, inv_mass, use_m, check_all)
    Xf = X.reshape(X.size)
    Vf = V.reshape(V.size)
    sb = np.empty((7, PLAIN_BATCH))
    if not use_m and not explicit and not always:
        bad += _plain_steps(data, lo, hi, steps, Xf, Vf, M, R, CR, CF, EXT, FLAGS, clear,
                            inv_mass, fbuf, sb, dt, t0, ax, ay, drag, False, False, False,
                            False)
    else:
        bad += _plain_steps(data, lo, hi, steps, Xf, Vf, M, R, CR, CF, EXT, FLAGS, clear,
                            inv_mass, fbuf, sb, dt, t0, ax, ay, drag, use_m, use_ext, explicit,
                            always)
    return bad


@njit(cache=_CACHE, parallel=True, error_model="numpy")
def run_par(data, steps, block, X, V, M, R, CR, CF, EXT, FLAGS, dt, t0, ax, ay, drag, use_m,
            use_ext, explicit, always, trace, lip, margin, eps, skip, rest, check_all):
    """Parallel kernel: blocks of particles over threads. Returns the frozen count."""
    n = X.shape[0]
    nblocks = (n + block - 1) // block
    bad = 0
    for c in prange(nblocks):
        lo = c * block
        hi = min(n, lo + block)
        bad += _block(data, lo, hi, steps, X, V, M, R, CR, CF, EXT, FLAGS, dt, t0, ax, ay,
                      drag, use_m, use_ext, explicit, always, trace, lip, margin, eps, skip,
                      rest, check_all)
    return bad


@njit(cache=_CACHE, error_model="numpy")
def run_ser(data, steps, block, X, V, M, R, CR, CF, EXT, FLAGS, dt, t0, ax, ay, drag, use_m,
            use_ext, explicit, always, trace, lip, margin, eps, skip, rest, check_all):
    """Serial kernel (small n). Returns the frozen count."""
    n = X.shape[0]
    bad = 0
    for lo in range(0, n, block):
        bad += _block(data, lo, min(n, lo + block), steps, X, V, M, R, CR, CF, EXT, FLAGS, dt,
                      t0, ax, ay, drag, use_m, use_ext, explicit, always, trace, lip, margin,
                      eps, skip, rest, check_all)
    return bad


@njit(cache=_CACHE, parallel=True, error_model="numpy")
def plain_par(data, steps, block, X, V, M, R, CR, CF, EXT, FLAGS, dt, t0, ax, ay, drag, use_m,
              use_ext, explicit, always, trace, lip, margin, eps, skip, rest, check_all):
    """:func:`run_par` for calls without query skipping, tunnelling check, moving world or
    resting contact (``skip``, ``trace`` False, ``rest`` 0; the others are unused): the same
    results through :func:`_block_plain`. A separate entry point, compiled only when first
    used."""
    n = X.shape[0]
    nblocks = (n + block - 1) // block
    bad = 0
    for c in prange(nblocks):
        lo = c * block
        hi = min(n, lo + block)
        bad += _block_plain(data, lo, hi, steps, X, V, M, R, CR, CF, EXT, FLAGS, dt, t0, ax,
                            ay, drag, use_m, use_ext, explicit, always, check_all)
    return bad


@njit(cache=_CACHE, error_model="numpy")
def plain_ser(data, steps, block, X, V, M, R, CR, CF, EXT, FLAGS, dt, t0, ax, ay, drag, use_m,
              use_ext, explicit, always, trace, lip, margin, eps, skip, rest, check_all):
    """Serial :func:`plain_par`."""
    n = X.shape[0]
    bad = 0
    for lo in range(0, n, block):
        bad += _block_plain(data, lo, min(n, lo + block), steps, X, V, M, R, CR, CF, EXT,
                            FLAGS, dt, t0, ax, ay, drag, use_m, use_ext, explicit, always,
                            check_all)
    return bad


# ---------------------------------------------------------------------------------------------
# The block step of grid worlds: a block of particles held in scratch rows through all steps,
# each step in passes over the block that LLVM vectorizes (several particles per instruction).

# A copy of fastsdf.backends.kernel.intrinsics.select: this module imports nothing from fastsdf, because the
# kernel cache hashes this file's source alone (a change in an imported intrinsic would not
# invalidate the compiled kernels).
@intrinsic
def _sel(typingctx, cond, a, b):
    """``a if cond else b`` for float64 values, compiled to a ``select`` (no branch), so that
    a loop using it can run several particles in the lanes of one vector instruction."""
    if not isinstance(cond, types.Boolean):
        return None
    sig = types.float64(cond, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        c, x, y = args
        x = context.cast(builder, x, signature.args[1], types.float64)
        y = context.cast(builder, y, signature.args[2], types.float64)
        return builder.select(c, x, y)

    return sig, codegen


@intrinsic
def _i64_as_f64(typingctx, i):
    """The float64 with the bit pattern of the int64 ``i`` (a bit cast), so that an integer
    can live in a row of the float scratch array."""
    if not isinstance(i, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        v = context.cast(builder, args[0], signature.args[0], types.int64)
        return builder.bitcast(v, ir.DoubleType())

    return types.float64(i), codegen


@intrinsic
def _f64_as_i64(typingctx, x):
    """The inverse of :func:`_i64_as_f64`."""
    if not isinstance(x, types.Float):
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return types.int64(x), codegen


@intrinsic
def _cell_vg(typingctx, grid, a, c, tx, ty):
    """``(d, dd/dx, dd/dy)``: the bilinear blends of a stored-gradient grid's cell, from its two
    runs ``grid[a:a + 6]`` (nodes (i, j), (i, j + 1)) and ``grid[c:c + 6]`` (nodes (i + 1, j),
    (i + 1, j + 1)), each ``[d, dd/dx, dd/dy]`` per node: the three channels in the lanes of
    one vector (two loads per run, the same operations per channel as the scalar blend, so the
    same bits). Reads only inside the runs."""
    if not (isinstance(grid, types.Array) and grid.dtype in (types.float64, types.float32)
            and isinstance(a, types.Integer) and isinstance(c, types.Integer)):
        return None
    sig = types.UniTuple(types.float64, 3)(grid, a, c, tx, ty)

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        el = context.get_data_type(signature.args[0].dtype)
        dbl = ir.DoubleType()
        vd = ir.VectorType(dbl, 4)
        i32 = ir.IntType(32)
        intp = context.get_value_type(types.intp)

        def load4(idx):
            ptr = builder.bitcast(builder.gep(ary.data, [idx]), ir.VectorType(el, 4).as_pointer())
            v = builder.load(ptr, align=signature.args[0].dtype.bitwidth // 8)
            return v if el == dbl else builder.fpext(v, vd)

        def runs(start):
            start = context.cast(builder, start, signature.args[1], types.intp)
            lo = load4(start)                                      # n0.d, n0.gx, n0.gy, n1.d
            hi = load4(builder.add(start, ir.Constant(intp, 2)))   # n0.gy, n1.d, n1.gx, n1.gy
            mask = ir.Constant(ir.VectorType(i32, 4), [1, 2, 3, 3])
            return lo, builder.shuffle_vector(hi, hi, mask)        # n1.d, n1.gx, n1.gy, -

        def splat(x, ty):
            x = context.cast(builder, x, ty, types.float64)
            v = builder.insert_element(ir.Constant(vd, ir.Undefined), x, ir.Constant(i32, 0))
            return builder.shuffle_vector(v, v, ir.Constant(ir.VectorType(i32, 4), [0] * 4))

        a0, a1 = runs(args[1])
        c0, c1 = runs(args[2])
        vtx = splat(args[3], signature.args[3])
        vty = splat(args[4], signature.args[4])
        lo = builder.fadd(a0, builder.fmul(vty, builder.fsub(a1, a0)))
        hi = builder.fadd(c0, builder.fmul(vty, builder.fsub(c1, c0)))
        r = builder.fadd(lo, builder.fmul(vtx, builder.fsub(hi, lo)))
        vals = [builder.extract_element(r, ir.Constant(i32, k)) for k in range(3)]
        return context.make_tuple(builder, signature.return_type, vals)

    return sig, codegen


@intrinsic
def _gather4(typingctx, grid, S, q, row, idx_at, tx_at, ty_at, d_at, gx_at, gy_at, r_at):
    """:func:`_cell_vg` for the four particles ``q .. q + 3`` of a block: their flat indices
    (int64 bits in ``S[idx_at + q:]``), fractions (``tx_at``, ``ty_at``) in, the values and
    gradients out as three vector stores into ``S[d_at + q:]``, ``gx_at``, ``gy_at`` (the
    four results transposed in registers; a scalar store per value would make the store
    port the bottleneck). Returns how many of the four have ``d <= S[r_at + q]``."""
    if not (isinstance(grid, types.Array) and grid.dtype in (types.float64, types.float32)
            and isinstance(S, types.Array) and S.dtype == types.float64):
        return None
    sig = types.int64(grid, S, q, row, idx_at, tx_at, ty_at, d_at, gx_at, gy_at, r_at)

    def codegen(context, builder, signature, args):
        gty = signature.args[0]
        g = context.make_array(gty)(context, builder, args[0])
        sa = context.make_array(signature.args[1])(context, builder, args[1])
        el = context.get_data_type(gty.dtype)
        dbl = ir.DoubleType()
        i32 = ir.IntType(32)
        i64 = ir.IntType(64)
        vd = ir.VectorType(dbl, 4)
        intp = context.get_value_type(types.intp)

        def idx(k):
            return context.cast(builder, args[k], signature.args[k], types.intp)

        qi = idx(2)
        rowi = idx(3)

        def sptr(k):
            ptr = builder.gep(sa.data, [builder.add(idx(k), qi)])
            return builder.bitcast(ptr, vd.as_pointer())

        def mask(vals):
            return ir.Constant(ir.VectorType(i32, len(vals)), vals)

        def load4(start):
            ptr = builder.bitcast(builder.gep(g.data, [start]), ir.VectorType(el, 4).as_pointer())
            v = builder.load(ptr, align=gty.dtype.bitwidth // 8)
            return v if el == dbl else builder.fpext(v, vd)

        def runs(start):
            lo = load4(start)
            hi = load4(builder.add(start, ir.Constant(intp, 2)))
            return lo, builder.shuffle_vector(hi, hi, mask([1, 2, 3, 3]))

        def splat(vec, k):
            return builder.shuffle_vector(vec, vec, mask([k] * 4))

        ivec = builder.bitcast(builder.load(sptr(4), align=8), ir.VectorType(i64, 4))
        txv = builder.load(sptr(5), align=8)
        tyv = builder.load(sptr(6), align=8)
        res = []
        for k in range(4):
            a = builder.extract_element(ivec, ir.Constant(i32, k))
            a0, a1 = runs(a)
            c0, c1 = runs(builder.add(a, rowi))
            tx = splat(txv, k)
            ty = splat(tyv, k)
            lo = builder.fadd(a0, builder.fmul(ty, builder.fsub(a1, a0)))
            hi = builder.fadd(c0, builder.fmul(ty, builder.fsub(c1, c0)))
            res.append(builder.fadd(lo, builder.fmul(tx, builder.fsub(hi, lo))))
        t0 = builder.shuffle_vector(res[0], res[1], mask([0, 4, 2, 6]))
        t1 = builder.shuffle_vector(res[2], res[3], mask([0, 4, 2, 6]))
        t2 = builder.shuffle_vector(res[0], res[1], mask([1, 5, 3, 7]))
        t3 = builder.shuffle_vector(res[2], res[3], mask([1, 5, 3, 7]))
        dv = builder.shuffle_vector(t0, t1, mask([0, 1, 4, 5]))
        builder.store(dv, sptr(7), align=8)
        builder.store(builder.shuffle_vector(t2, t3, mask([0, 1, 4, 5])), sptr(8), align=8)
        builder.store(builder.shuffle_vector(t0, t1, mask([2, 3, 6, 7])), sptr(9), align=8)
        le = builder.zext(builder.fcmp_ordered("<=", dv, builder.load(sptr(10), align=8)),
                          ir.VectorType(i64, 4))
        n = builder.extract_element(le, ir.Constant(i32, 0))
        for k in range(1, 4):
            n = builder.add(n, builder.extract_element(le, ir.Constant(i32, k)))
        return n

    return sig, codegen


#: Particles per block of the vector step (a multiple of every vector width). A block's scratch
#: rows (35 rows of 72 doubles, 20 KB) stay in a 32 KB L1 data cache through all steps of a
#: call: measured against 128 (38 KB), +3% settled and +16% falling with skipping off.
LANES = 64
# Rows of the block step's scratch array, one row of LANES values each (row k at k * _STRIDE):
# the constant distance between rows lets LLVM prove loads and stores of different rows
# independent without runtime checks. Flags are stored as 1.0 / 0.0.
_X, _Y, _VX, _VY, _R, _CR, _CF, _IM, _M, _LIVE, _CLR = range(11)
_XS, _YS, _DX, _DY, _NVX, _NVY = range(11, 17)
_TX, _TY, _IDX, _INS, _OK, _NEED, _CODE = range(17, 24)
_D, _GX, _GY, _FIX, _BNC = range(24, 29)
# The first pass's results (state, budget, freeze code), which the last pass turns into the
# step's: writing a row from a load of the same row under a condition makes LLVM emit masked
# stores (vmaskmovpd), which are microcoded and slow on this kind of CPU.
_X1, _Y1, _VX1, _VY1, _CLR1, _CODE1 = range(29, 35)
_ROWS = 35
#: Distance between rows: not a multiple of 4096 bytes for rows close together (loads of one
#: row and stores to another would falsely wait on each other: 4K aliasing).
_STRIDE = LANES + 8


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _lerp(tx, ty, a, b, c, e):
    """The bilinear blend of ``fastsdf.fields.grid`` (same operations, same order)."""
    lo = a + ty * (b - a)
    hi = c + ty * (e - c)
    return lo + tx * (hi - lo)


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _respond_sel(x, y, vx, vy, s, gx, gy, cr, cf, always):
    """:func:`_respond` of a static world with selects for every condition (the same
    operations in the same order, so the same bits), for the vector passes."""
    gt = 0.0
    gl2 = gx * gx + gy * gy
    ok = (gl2 > 0.0) & (gl2 < math.inf)
    inv = _sel(ok, 1.0 / math.sqrt(gl2), 0.0)
    nx = _sel(ok, gx * inv, 0.0)
    ny = _sel(ok, gy * inv, 0.0)
    k = (1.0 + cr) * s
    x -= k * nx
    y -= k * ny
    vn = vx * nx + vy * ny
    wn = -gt * inv
    vr = vn - wn
    resp = ok & ((vr < 0.0) | always)
    w = _sel(resp, 1.0 - cf, 1.0)
    c = _sel(resp, cr, -1.0)
    vx = w * (vx - vn * nx) + (wn - c * vr) * nx
    vy = w * (vy - vn * ny) + (wn - c * vr) * ny
    return x, y, vx, vy


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_load(S, Xf, Vf, M, R, CR, CF, FLAGS, b0, nb, use_m, check_all):
    """A block's state into the scratch rows (lanes past ``nb`` idle), with the checks of
    :func:`_check_block` (a particle that fails is flagged and idle). Returns how many
    failed."""
    L = LANES
    W = _STRIDE
    bad = 0
    for k in range(L):
        if k < nb:
            i = np.uint64(b0 + k)
            ix = np.uint64(2) * i
            x = float(Xf[ix])
            y = float(Xf[ix + np.uint64(1)])
            vx = float(Vf[ix])
            vy = float(Vf[ix + np.uint64(1)])
            r = float(R[i])
            m = float(M[i]) if use_m or check_all else 1.0
            ok = _valid_input(x, y, vx, vy, r, m, use_m or check_all)
            if check_all:
                ok = ok and _coeffs(CR, CF, i)[2]
            if not ok:
                FLAGS[i] = FLAG_INPUT
                bad += 1
            S[_X * W + k] = x
            S[_Y * W + k] = y
            S[_VX * W + k] = vx
            S[_VY * W + k] = vy
            S[_R * W + k] = r
            S[_CR * W + k] = CR[i]
            S[_CF * W + k] = CF[i]
            S[_IM * W + k] = 1.0 / m if use_m else 1.0
            S[_M * W + k] = M[i] if USE_FORCE else 1.0
            S[_LIVE * W + k] = 1.0 if ok else 0.0
        else:
            for row in (_X, _Y, _VX, _VY, _R, _CR, _CF, _IM, _M, _LIVE):
                S[row * W + k] = 0.0
        S[_CLR * W + k] = 0.0
    return bad


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_store(S, Xf, Vf, b0, nb):
    """The block's state back from the scratch rows."""
    L = LANES
    W = _STRIDE
    for k in range(nb):
        ix = np.uint64(2) * np.uint64(b0 + k)
        Xf[ix] = S[_X * W + k]
        Xf[ix + np.uint64(1)] = S[_Y * W + k]
        Vf[ix] = S[_VX * W + k]
        Vf[ix + np.uint64(1)] = S[_VY * W + k]


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _simd_move(S, step, t, dt, ax, ay, drag, use_m, explicit, lip, eps, fbchk, b, g, budget,
               skipping):
    """Pass 1 of a step (vector): forces, integration, the free-flight budget (a particle
    whose budget covers the step moves here and needs no query), the check for a grid
    fallback not bound yet, and the cell of the end point (index and bilinear fractions, the
    operations of ``fastsdf.fields.grid``'s sampler). ``b``: the bounds of :func:`_fallback_missing`;
    ``g``: ``(x0, x1, y0, y1, 1/hx, 1/hy, nx - 2, ny - 2, ny)`` of the grid, floats.
    Returns how many particles need a query, how many were frozen, and how many of those
    that query end outside the grid. ``budget``, ``skipping``: constants in the compiled
    versions; ``budget`` False when neither budgets nor the fallback check (``fbchk``) are
    used, ``skipping`` False without budgets (``skip``)."""
    L = LANES
    W = _STRIDE
    bx0, bx1, by0, by1 = b
    x0, x1, y0, y1, ihx, ihy, nxm2, nym2, nyf = g
    tol = 1.0 + CONTACT_TOL / lip
    resume = float(FLAG_RESUME + step)
    nonfinite = float(FLAG_NONFINITE)
    nneed = 0
    nfrz = 0
    nout = 0
    for q in range(L):
        live = S[_LIVE * W + q] != 0.0
        x = S[_X * W + q]
        y = S[_Y * W + q]
        vx = S[_VX * W + q]
        vy = S[_VY * W + q]
        fx = -drag * vx
        fy = -drag * vy
        if USE_FORCE:
            ux, uy = _force(x, y, vx, vy, S[_M * W + q], t)
            fx += ux
            fy += uy
        im = S[_IM * W + q]
        bx = _sel(use_m, ax + fx * im, ax)
        by = _sel(use_m, ay + fy * im, ay)
        nvx = vx + bx * dt
        nvy = vy + by * dt
        dx = _sel(explicit, vx, nvx) * dt
        dy = _sel(explicit, vy, nvy) * dt
        # the step's length (a square root: only for budgets and the fallback check)
        ln = math.sqrt(dx * dx + dy * dy) if budget else 0.0
        c = S[_CLR * W + q] if skipping else 0.0
        c2 = c - (ln * tol + eps * (abs(x) + abs(y) + 1.0))
        skip = (c > 0.0) & (c2 > 0.0)
        xe = x + dx
        ye = y + dy
        fin = _finite4(xe, ye, nvx, nvy)
        moved = live & skip
        keep = moved & fin
        S[_X1 * W + q] = _sel(keep, xe, x)
        S[_Y1 * W + q] = _sel(keep, ye, y)
        S[_VX1 * W + q] = _sel(keep, nvx, vx)
        S[_VY1 * W + q] = _sel(keep, nvy, vy)
        if skipping:
            S[_CLR1 * W + q] = _sel(skip, c2, 0.0)
        reach = 2.0 * (MAX_BOUNCES + 1) * ln + 1e-9
        away = (x - reach >= bx0) & (x + reach <= bx1) & (y - reach >= by0) & (y + reach <= by1)
        need = live & (not skip)
        miss = need & fbchk & (not away)
        need = need & (not miss)
        code = _sel(miss, resume, _sel(moved & (not fin), nonfinite, 0.0))
        # the sampler's _locate, branch-free
        inside = (xe >= x0) & (xe <= x1) & (ye >= y0) & (ye <= y1)
        ok = inside | ((abs(xe) < math.inf) & (abs(ye) < math.inf))
        xq = _sel(inside, xe, min(max(_sel(ok, xe, x0), x0), x1))
        yq = _sel(inside, ye, min(max(_sel(ok, ye, y0), y0), y1))
        u = (xq - x0) * ihx
        v = (yq - y0) * ihy
        fi = min(np.floor(u), nxm2)
        fj = min(np.floor(v), nym2)
        S[_TX * W + q] = u - fi
        S[_TY * W + q] = v - fj
        # the flat index as an integer (converted here, in vector registers: a scalar
        # conversion in the gather would lengthen each particle's dependent chain)
        S[_IDX * W + q] = _i64_as_f64(np.int64(np.int32(3.0 * (fi * nyf + fj))))
        S[_INS * W + q] = _sel(inside, 1.0, 0.0)
        S[_OK * W + q] = _sel(ok, 1.0, 0.0)
        S[_DX * W + q] = dx
        S[_DY * W + q] = dy
        S[_NVX * W + q] = nvx
        S[_NVY * W + q] = nvy
        S[_NEED * W + q] = _sel(need, 1.0, 0.0)
        S[_CODE1 * W + q] = code
        nneed += need
        nfrz += code != 0.0
        nout += need & (not inside)
    return nneed, nfrz, nout


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_move_budget(S, step, t, dt, ax, ay, drag, use_m, explicit, lip, eps, fbchk, b, g):
    """:func:`_simd_move` with budgets (``skip``) or the fallback check (without budgets
    their row stays 0)."""
    return _simd_move(S, step, t, dt, ax, ay, drag, use_m, explicit, lip, eps, fbchk, b, g, True,
                      True)


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_move_plain(S, step, t, dt, ax, ay, drag, use_m, explicit, lip, eps, fbchk, b, g):
    """:func:`_simd_move` without budgets or the fallback check (``skip``, ``fbchk`` False)."""
    return _simd_move(S, step, t, dt, ax, ay, drag, use_m, explicit, lip, eps, False, b, g,
                      False, False)


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _simd_gather(S, grid, row, lip, trace, every, marks):
    """Pass 2 (scalar: loads from computed places): the bilinear value and gradient at the
    end point of each particle that needs a query, from its cell's two runs of 6 grid values
    (``row``: the flat distance between nodes (i, j) and (i + 1, j)); the operations of
    ``fastsdf.fields.grid.sample_stored`` (its NaN for a non-finite point is applied where the
    values are used, from the ``_OK`` row). Returns how many may touch a surface (a hint:
    ``d <= r`` before that NaN). ``every``: a constant in the two compiled versions, True
    when every particle queries (no test per particle; the others' cells are valid ones).
    ``marks`` (constant too): also mark the particles that need the scalar fix-up, as
    :func:`_simd_blend` does (here, for a tunnelling check: one pass less). Returns the
    count of those as well."""
    L = LANES
    W = _STRIDE
    ncon = 0
    nfix = 0
    for q in range(L):
        if every or S[_NEED * W + q] != 0.0:
            a = np.uint64(_f64_as_i64(S[_IDX * W + q]))
            d, gx, gy = _cell_vg(grid, a, a + row, S[_TX * W + q], S[_TY * W + q])
            S[_D * W + q] = d
            S[_GX * W + q] = gx
            S[_GY * W + q] = gy
            r = S[_R * W + q]
            ncon += d <= r
            if marks:
                s = _sel(S[_OK * W + q] != 0.0, d, math.nan) - r
                dx = S[_DX * W + q]
                dy = S[_DY * W + q]
                dd = dx * dx + dy * dy
                sweep = trace & (dd > (TRACE_FRACTION * r) * (TRACE_FRACTION * r)) & (
                    not ((s * s >= lip * lip * dd) & (s > 0.0)))
                fix = (S[_NEED * W + q] != 0.0) & (sweep | (GRID_EXACT & (S[_INS * W + q] == 0.0)))
                S[_FIX * W + q] = _sel(fix, 1.0, 0.0)
                S[_BNC * W + q] = 0.0
                nfix += fix
    return ncon, nfix


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_gather_some(S, grid, row, lip, trace):
    """:func:`_simd_gather` of the particles that need a query, with the marks for the
    fix-up (a sweep where ``trace``, a query outside an 'exact' grid)."""
    return _simd_gather(S, grid, row, lip, trace, False, True)


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_gather_all(S, grid, row, lip):
    """:func:`_simd_gather` of every particle of the block, four at a time
    (:func:`_gather4`), without marks."""
    W = _STRIDE
    ncon = 0
    for q in range(0, LANES, 4):
        ncon += _gather4(grid, S, q, row, _IDX * W, _TX * W, _TY * W, _D * W, _GX * W, _GY * W,
                         _R * W)
    return ncon, 0


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_blend(S, trace, lip):
    """Pass 3 (vector): which particles need the scalar fix-up (a tunnelling sweep, or a
    query outside an 'exact' grid). Returns their count. (No row is rewritten here from its
    own value under a condition: LLVM makes that a masked store, microcoded and slow.)"""
    L = LANES
    W = _STRIDE
    nfix = 0
    for q in range(L):
        need = S[_NEED * W + q] != 0.0
        r = S[_R * W + q]
        s = _sel(S[_OK * W + q] != 0.0, S[_D * W + q], math.nan) - r
        dx = S[_DX * W + q]
        dy = S[_DY * W + q]
        dd = dx * dx + dy * dy
        sweep = trace & (dd > (TRACE_FRACTION * r) * (TRACE_FRACTION * r)) & (
            not ((s * s >= lip * lip * dd) & (s > 0.0)))
        fix = need & (sweep | (GRID_EXACT & (S[_INS * W + q] == 0.0)))
        S[_FIX * W + q] = _sel(fix, 1.0, 0.0)
        S[_BNC * W + q] = 0.0
        nfix += fix
    return nfix


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_query(data, x, y):
    """:func:`_query`, compiled once for the fix-up's two call sites (compile time)."""
    return _query(data, x, y)


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_fix(data, S, lip, always, trace):
    """The scalar fix-up of the marked particles: the exact query outside the grid, and the
    tunnelling sweep (:func:`_sweep`) with the end point's query after a bounce, as in
    :func:`_block`. Returns how many were frozen (invalid ``cr``/``cf`` at a sweep)."""
    L = LANES
    W = _STRIDE
    nfrz = 0
    for q in range(L):
        if S[_FIX * W + q] == 0.0 or S[_NEED * W + q] == 0.0:   # (FIX is set for these only)
            continue
        x = S[_X * W + q]
        y = S[_Y * W + q]
        dx = S[_DX * W + q]
        dy = S[_DY * W + q]
        r = S[_R * W + q]
        dd = dx * dx + dy * dy
        if GRID_EXACT and S[_INS * W + q] == 0.0:
            d, gx, gy = _simd_query(data, x + dx, y + dy)
            S[_D * W + q] = d
            S[_GX * W + q] = gx
            S[_GY * W + q] = gy
            S[_OK * W + q] = 1.0          # these values stand as they are
        s = _sel(S[_OK * W + q] != 0.0, S[_D * W + q], math.nan) - r
        if not (trace and dd > (TRACE_FRACTION * r) * (TRACE_FRACTION * r) and not (
                s * s >= lip * lip * dd and s > 0.0)):
            continue
        cr = S[_CR * W + q]
        cf = S[_CF * W + q]
        if not ((cr >= 0.0) & (cr <= 1.0) & (cf >= 0.0) & (cf <= 1.0)):
            S[_CODE1 * W + q] = float(FLAG_COEFF)
            nfrz += 1
            continue
        t1 = 1.0 - s / (lip * math.sqrt(dd)) if s > 0.0 else 1.0
        x, y, dx, dy, vx, vy, bounced = _sweep(data, x, y, dx, dy, S[_NVX * W + q],
                                               S[_NVY * W + q], r, cr, cf, lip, always, 0.0, t1)
        if bounced:
            d, gx, gy = _simd_query(data, x + dx, y + dy)
            S[_D * W + q] = d
            S[_GX * W + q] = gx
            S[_GY * W + q] = gy
            S[_OK * W + q] = 1.0
            S[_BNC * W + q] = 1.0
        S[_XS * W + q] = x
        S[_YS * W + q] = y
        S[_DX * W + q] = dx
        S[_DY * W + q] = dy
        S[_NVX * W + q] = vx
        S[_NVY * W + q] = vy
    return nfrz


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _simd_respond(S, always, skip, lip, margin, contacts):
    """Pass 4 (vector): the end point, the collision response where ``s <= 0``
    (:func:`_respond_sel`), the checks, the free-flight budget, and the new state of every
    particle that queried and was not frozen. Returns how many were frozen. ``contacts``: a
    constant in the two compiled versions; False when no particle of the block touches a
    surface (then the response's square root and division are left out)."""
    L = LANES
    W = _STRIDE
    coeff = float(FLAG_COEFF)
    nonfinite = float(FLAG_NONFINITE)
    nfrz = 0
    for q in range(L):
        need = S[_NEED * W + q] != 0.0
        # the step's start: moved by a sweep that bounced (XS, YS), else the state (X1 = X
        # for a particle that queries)
        bounced = S[_BNC * W + q] != 0.0
        x1 = S[_X1 * W + q]
        y1 = S[_Y1 * W + q]
        x = _sel(bounced, S[_XS * W + q], x1) + S[_DX * W + q]
        y = _sel(bounced, S[_YS * W + q], y1) + S[_DY * W + q]
        vx = S[_NVX * W + q]
        vy = S[_NVY * W + q]
        ok = S[_OK * W + q] != 0.0     # False: a non-finite end point (the sampler's NaN)
        s = _sel(ok, S[_D * W + q], math.nan) - S[_R * W + q]
        cr = S[_CR * W + q]
        cf = S[_CF * W + q]
        cok = (cr >= 0.0) & (cr <= 1.0) & (cf >= 0.0) & (cf <= 1.0)
        contact = (s <= 0.0) & contacts
        # (where not ok, s is NaN: no contact, so the gradient's value does not matter)
        rx, ry, rvx, rvy = _respond_sel(x, y, vx, vy, s, S[_GX * W + q], S[_GY * W + q], cr,
                                        cf, always & (not bounced))
        x = _sel(contact, rx, x)
        y = _sel(contact, ry, y)
        vx = _sel(contact, rvx, vx)
        vy = _sel(contact, rvy, vy)
        code0 = S[_CODE1 * W + q]
        code = _sel(code0 != 0.0, code0, _sel(contact & (not cok), coeff,
                                              _sel(_finite4(x, y, vx, vy), 0.0, nonfinite)))
        commit = need & (code == 0.0)
        S[_X * W + q] = _sel(commit, x, x1)
        S[_Y * W + q] = _sel(commit, y, y1)
        S[_VX * W + q] = _sel(commit, vx, S[_VX1 * W + q])
        S[_VY * W + q] = _sel(commit, vy, S[_VY1 * W + q])
        if skip:
            refill = (not contact) & (s > margin)
            S[_CLR * W + q] = _sel(need, _sel(refill, (s - margin) / lip * (1.0 - 1e-9), 0.0),
                                   S[_CLR1 * W + q])
        S[_CODE * W + q] = _sel(need, code, code0)
        nfrz += need & (code != 0.0)
    return nfrz


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_respond_all(S, always, skip, lip, margin):
    """:func:`_simd_respond` of a block where some particle may touch a surface, with budgets
    (``skip``)."""
    return _simd_respond(S, always, True, lip, margin, True)


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_respond_none(S, always, skip, lip, margin):
    """:func:`_simd_respond` of a block where no particle touches a surface, with budgets."""
    return _simd_respond(S, always, True, lip, margin, False)


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_respond_all_plain(S, always, skip, lip, margin):
    """:func:`_simd_respond_all` without budgets (``skip`` False: no division per particle)."""
    return _simd_respond(S, always, False, lip, margin, True)


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_respond_none_plain(S, always, skip, lip, margin):
    """:func:`_simd_respond_none` without budgets."""
    return _simd_respond(S, always, False, lip, margin, False)


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_commit(S):
    """The first pass's results as the step's (a step where no particle queried)."""
    L = LANES
    W = _STRIDE
    for q in range(L):
        S[_X * W + q] = S[_X1 * W + q]
        S[_Y * W + q] = S[_Y1 * W + q]
        S[_VX * W + q] = S[_VX1 * W + q]
        S[_VY * W + q] = S[_VY1 * W + q]
        S[_CLR * W + q] = S[_CLR1 * W + q]
        S[_CODE * W + q] = S[_CODE1 * W + q]


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_flags(S, FLAGS, b0, nb):
    """Freeze the particles whose step set a code (see the module docstring's checks)."""
    L = LANES
    W = _STRIDE
    bad = 0
    for q in range(nb):
        code = S[_CODE * W + q]
        if code != 0.0 and S[_LIVE * W + q] != 0.0:
            FLAGS[b0 + q] = int(code)
            S[_LIVE * W + q] = 0.0
            bad += 1
    return bad


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _block_simd(data, lo, hi, steps, X, V, M, R, CR, CF, FLAGS, dt, t0, ax, ay, drag, use_m,
                explicit, always, trace, lip, margin, eps, skip, check_all):
    """:func:`_block` for a static grid world (``GRID_SIMD``) without resting contact or
    Python forces, the same results: ``LANES`` particles at a time through all steps, each
    step in passes over the block (:func:`_simd_move`, :func:`_simd_gather`,
    :func:`_simd_blend`, :func:`_simd_fix`, :func:`_simd_respond`); a step in which no
    particle of the block needs a query is the first pass alone."""
    data = borrow_all(data)
    M = borrow_all(M)
    grid, x0, x1, y0, y1, ihx, ihy, nx, ny = data[5:14]
    b = (float(data[1]), float(data[2]), float(data[3]), float(data[4]))
    g = (float(x0), float(x1), float(y0), float(y1), float(ihx), float(ihy), float(nx - 2),
         float(ny - 2), float(ny))
    row = np.uint64(3 * ny)
    fbchk = GRID_EXACT and data[0] == 0
    use_m = use_m or USE_FORCE
    Xf = X.reshape(X.size)
    Vf = V.reshape(V.size)
    S = np.zeros(_ROWS * _STRIDE)
    bad = 0
    for b0 in range(lo, hi, LANES):
        nb = min(hi, b0 + LANES) - b0
        bad += _simd_load(S, Xf, Vf, M, R, CR, CF, FLAGS, b0, nb, use_m, check_all)
        for step in range(steps):
            t = t0 + step * dt
            if skip or fbchk:
                nneed, nfrz, nout = _simd_move_budget(S, step, t, dt, ax, ay, drag, use_m,
                                                      explicit, lip, eps, fbchk, b, g)
            else:
                nneed, nfrz, nout = _simd_move_plain(S, step, t, dt, ax, ay, drag, use_m,
                                                     explicit, lip, eps, fbchk, b, g)
            if nneed > 0:
                if skip or trace:
                    ncon, nfix = _simd_gather_some(S, grid, row, lip, trace)
                else:
                    ncon, nfix = _simd_gather_all(S, grid, row, lip)
                    # (a query outside an 'exact' grid needs the exact value)
                    if GRID_EXACT and nout > 0:
                        nfix = _simd_blend(S, trace, lip)
                if nfix > 0:
                    nfrz += _simd_fix(data, S, lip, always, trace)
                    ncon = 1
                if ncon > 0 and skip:
                    nfrz += _simd_respond_all(S, always, skip, lip, margin)
                elif skip:
                    nfrz += _simd_respond_none(S, always, skip, lip, margin)
                elif ncon > 0:
                    nfrz += _simd_respond_all_plain(S, always, skip, lip, margin)
                else:
                    nfrz += _simd_respond_none_plain(S, always, skip, lip, margin)
            else:
                _simd_commit(S)
            if nfrz > 0:
                bad += _simd_flags(S, FLAGS, b0, nb)
        _simd_store(S, Xf, Vf, b0, nb)
    return bad


@njit(cache=_CACHE, parallel=True, error_model="numpy")
def simd_par(data, steps, block, X, V, M, R, CR, CF, EXT, FLAGS, dt, t0, ax, ay, drag, use_m,
             use_ext, explicit, always, trace, lip, margin, eps, skip, rest, check_all):
    """:func:`run_par` for a static grid world (``GRID_SIMD``), float64 state, without
    resting contact (``rest`` 0) or Python forces (``use_ext`` False): the same results
    through :func:`_block_simd`. A separate entry point, compiled only when first used."""
    n = X.shape[0]
    nblocks = (n + block - 1) // block
    bad = 0
    for c in prange(nblocks):
        lo = c * block
        hi = min(n, lo + block)
        bad += _block_simd(data, lo, hi, steps, X, V, M, R, CR, CF, FLAGS, dt, t0, ax, ay,
                           drag, use_m, explicit, always, trace, lip, margin, eps, skip,
                           check_all)
    return bad


@njit(cache=_CACHE, error_model="numpy")
def simd_ser(data, steps, block, X, V, M, R, CR, CF, EXT, FLAGS, dt, t0, ax, ay, drag, use_m,
             use_ext, explicit, always, trace, lip, margin, eps, skip, rest, check_all):
    """Serial :func:`simd_par`."""
    n = X.shape[0]
    bad = 0
    for lo in range(0, n, block):
        bad += _block_simd(data, lo, min(n, lo + block), steps, X, V, M, R, CR, CF, FLAGS, dt,
                           t0, ax, ay, drag, use_m, explicit, always, trace, lip, margin, eps,
                           skip, check_all)
    return bad


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def query_many(data, xs, ys, out):
    """Value and gradient at many points through the kernel's own query (for tests)."""
    for i in range(xs.shape[0]):
        d, gx, gy = _query(data, xs[i], ys[i])
        out[i, 0] = d
        out[i, 1] = gx
        out[i, 2] = gy


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def force_many(xs, ys, vxs, vys, ms, t, out):
    """The fused user forces at many particles (for tests)."""
    for i in range(xs.shape[0]):
        fx, fy = _force(xs[i], ys[i], vxs[i], vys[i], ms[i], t)
        out[i, 0] = fx
        out[i, 1] = fy
