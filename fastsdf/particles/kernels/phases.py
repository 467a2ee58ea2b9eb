"""The phases of one particle's step, written once (see the package docs): the checks,
integration (forces and the Euler step), free-flight budgets, the query's reach, the tunnelling
check and sweep, the response, and their composition :func:`particle_step`.

Every kernel is built from them: the particle-by-particle step (``_block`` and the plain step
of :mod:`.step`, and the CUDA thread of :mod:`fastsdf.particles.cuda`) calls
:func:`particle_step`; the block step of grid worlds (:mod:`.block`) runs the same phases in
passes over its lanes. Those meant for the vector passes are written with selects (every
operand safe to compute), so that LLVM keeps them free of branches.
"""

import math

from numba import njit

from fastsdf.intrinsics import select
from fastsdf.particles.kernels.config import Disc, Motion, Physics, Window
from fastsdf.particles.kernels.constants import (
    ASLEEP,
    CONTACT_TOL,
    FLAG_COEFF,
    FLAG_NONFINITE,
    FLAG_RESUME,
    MAX_BOUNCES,
    TRACE_FRACTION,
)
from fastsdf.particles.kernels.contact import _respond, _rests, sweep
from fastsdf.particles.kernels.scene import (
    _CACHE,
    FORCE_AHEAD,
    MOVING,
    USE_FORCE,
    _fallback_missing,
    _force,
    _query_t,
    _wall_speed_at,
)

__all__ = ["particle_step", "with_user_forces", "accelerate", "euler", "needs_sweep", "swept"]

# >>> KERNEL BODY (from here on, copied into every generated kernel module) >>>

# ---------------------------------------------------------------------------------------------
# The phases of one particle's step.

#: Whether a particle whose step repeats its state may sleep for the rest of a call: the step
#: must not depend on time (no moving world, no user force, which may use ``t``).
SLEEP = not MOVING and not USE_FORCE
#: The code of :func:`particle_step` for a particle that sleeps from now on.
SLEPT = -1


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _finite4(x, y, vx, vy):
    """Whether all four are finite, in one test (``a - a`` is 0 for a finite ``a`` and NaN
    for an infinite or NaN one): fewer instructions and branches per step than four tests."""
    return (x - x) + (y - y) + (vx - vx) + (vy - vy) == 0.0


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _valid_input(x, y, vx, vy, r, m, use_m):
    """Whether a particle's loaded state may be stepped (cr, cf are checked at contacts)."""
    ok = (
        abs(x) < math.inf
        and abs(y) < math.inf
        and abs(vx) < math.inf
        and abs(vy) < math.inf
        and r >= 0.0
        and r < math.inf
    )
    if use_m:
        ok = ok and m > 0.0 and m < math.inf
    return ok


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _coeffs_ok(cr, cf):
    """Whether restitution ``cr`` and friction ``cf`` both lie in [0, 1]."""
    return (cr >= 0.0) & (cr <= 1.0) & (cf >= 0.0) & (cf <= 1.0)


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _coeffs(CR, CF, i):
    """``cr, cf`` of particle ``i`` and whether both lie in [0, 1]."""
    cr = float(CR[i])
    cf = float(CF[i])
    return cr, cf, _coeffs_ok(cr, cf)


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def input_ok(state, i, use_m):
    """Whether particle ``i`` of ``state`` (:class:`.config.State`) may be stepped, checked on
    what a step loads (``x``, ``v``, ``r``; ``m`` when ``use_m``) and, with
    ``state.check_all``, ``m``, ``cr`` and ``cf`` too; and its mass (1 where not read)."""
    X, V, M, R, CR, CF, EXT, FLAGS, check_all = state
    m = float(M[i]) if use_m or check_all else 1.0
    ok = _valid_input(
        float(X[i, 0]),
        float(X[i, 1]),
        float(V[i, 0]),
        float(V[i, 1]),
        float(R[i]),
        m,
        use_m or check_all,
    )
    if check_all:
        ok = ok and _coeffs(CR, CF, i)[2]
    return ok, m


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def switched(physics, use_m, use_ext, rest):
    """``physics`` with the switches ``use_m``, ``use_ext`` and ``rest`` replaced (a loop that
    knows them passes constants, which the compiler folds into the phases)."""
    return Physics(
        physics.dt,
        physics.t0,
        physics.ax,
        physics.ay,
        physics.drag,
        use_m,
        use_ext,
        physics.explicit,
        physics.always,
        rest,
    )


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def with_user_forces(push, x, y, vx, vy, m, t, inline):
    """``push = (ux, uy, ex, ey)`` (see :func:`accelerate`) with the fused user forces of a
    particle at ``(x, y)``, velocity ``(vx, vy)``, mass ``m`` and time ``t`` evaluated here
    (``USE_FORCE``), unless the loop evaluated them ahead (``FORCE_AHEAD``, and not
    ``inline``: the block step and the GPU's thread evaluate them here)."""
    if USE_FORCE and (inline or not FORCE_AHEAD):
        ux, uy = _force(x, y, vx, vy, m, t)
        return (ux, uy, push[2], push[3])
    return push


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def accelerate(vx, vy, inv_m, push, physics):
    """Acceleration ``g + (F_user + ext - drag v) / m`` (:class:`.config.Physics`: gravity,
    drag, whether the mass is read, ``use_m``, and Python forces added, ``use_ext``):
    ``push = (ux, uy, ex, ey)``, the fused user forces (used where ``USE_FORCE``) and the Python
    force of this particle; ``inv_m``: ``1 / m`` (used where ``use_m``)."""
    ux, uy, ex, ey = push
    fx = -physics.drag * vx
    fy = -physics.drag * vy
    fx = select(physics.use_ext, fx + ex, fx)
    fy = select(physics.use_ext, fy + ey, fy)
    if USE_FORCE:
        fx += ux
        fy += uy
    bx = select(physics.use_m, physics.ax + fx * inv_m, physics.ax)
    by = select(physics.use_m, physics.ay + fy * inv_m, physics.ay)
    return bx, by


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def euler(vx, vy, bx, by, physics):
    """One Euler step of the velocity by acceleration ``b``: the displacement and the new
    velocity (``physics.explicit``: the displacement from the old velocity; else
    semi-implicit, from the new one)."""
    dt = physics.dt
    nvx = vx + bx * dt
    nvy = vy + by * dt
    dx = select(physics.explicit, vx, nvx) * dt
    dy = select(physics.explicit, vy, nvy) * dt
    return dx, dy, nvx, nvy


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def spend(c, x, y, dx, dy, wd, budget):
    """A free-flight budget ``c`` after a step from ``(x, y)`` by ``(dx, dy)``: what is left
    after the step's length (by ``1 + CONTACT_TOL / lip``: a skipped step must also be one whose
    sweep would not have stopped at a near-contact, ``s <= CONTACT_TOL |step|``), the rounding
    of stored coordinates (``eps``, :class:`.config.Budget`) and, in a moving world, how far the
    walls came (``wd``). The step may skip its query if the result is > 0."""
    lip = budget.lip
    used = math.sqrt(dx * dx + dy * dy) * (1.0 + CONTACT_TOL / lip) + budget.eps * (
        abs(x) + abs(y) + 1.0
    )
    if MOVING:
        used += wd / lip
    return c - used


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def refill(s, margin, lip):
    """The free-flight budget after a query clear of every surface by ``s = d - r > margin``:
    ``(s - margin) / lip``, a little less (``margin`` covers a grid's jump at its bounds)."""
    return (s - margin) / lip * (1.0 - 1e-9)


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def outside_reach(x, y, dx, dy, bounds):
    """Whether a step from ``(x, y)`` by ``(dx, dy)`` may query outside the rectangle
    ``bounds = (x0, x1, y0, y1)``: every query of a step (its sweep and bounces included) lies
    within ``2 (MAX_BOUNCES + 1) |D|`` of its start."""
    x0, x1, y0, y1 = bounds
    reach = 2.0 * (MAX_BOUNCES + 1) * math.sqrt(dx * dx + dy * dy) + 1e-9
    return not ((x - reach >= x0) & (x + reach <= x1) & (y - reach >= y0) & (y + reach <= y1))


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def needs_sweep(dd, s, r, lip, wd):
    """The tunnelling check: whether a step of squared length ``dd`` ending at surface distance
    ``s`` needs a sweep. Only a step longer than ``TRACE_FRACTION r`` whose end is not clear of
    everything by the step's length (then no wall can lie across the step) does; in a moving
    world the length includes how far the walls move (``wd / lip``)."""
    if MOVING:
        ln = math.sqrt(dd) + wd / lip
        return (ln > TRACE_FRACTION * r) & (not ((s >= lip * ln) & (s > 0.0)))
    short = TRACE_FRACTION * r
    return (dd > short * short) & (not ((s * s >= lip * lip * dd) & (s > 0.0)))


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def swept(data, motion, disc, found, lip, always, window):
    """The tunnelling sweep of a step that needs one (:func:`needs_sweep`): ``motion``
    (:class:`.config.Motion`) swept with the disc ``disc`` (:class:`.config.Disc`) while time
    runs from ``window.ts`` over ``window.tdt`` and the walls move ``window.wd`` (see
    :func:`.contact.sweep`). ``found = (d, dd/dx, dd/dy, dd/dt)``: the world at the step's end,
    whose part within ``s / L`` of the end is known to be free. (The start's budget is not used:
    results must not depend on how steps are grouped into calls.)

    Returns the motion after the sweep, whether it bounced, and the world at its end point
    (queried again after a bounce). Compiled once per module for its callers."""
    x, y, dx, dy, vx, vy = motion
    s = found[0] - disc.r
    ln = math.sqrt(dx * dx + dy * dy)
    if MOVING:
        ln += window.wd / lip
    t1 = 1.0 - s / (lip * ln) if s > 0.0 else 1.0
    x, y, dx, dy, vx, vy, bounced = sweep(
        data, motion, disc, lip, always, Window(0.0, t1, window.ts, window.tdt, window.wd)
    )
    if bounced:
        found = _query_t(data, x + dx, y + dy, window.ts + window.tdt)
    return Motion(x, y, dx, dy, vx, vy), bounced, found


# ---------------------------------------------------------------------------------------------
# One step of one particle.


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def particle_step(data, here, coeffs, c, push, step, physics, budget, steps):
    """One step of one particle, the phases in order: forces and integration, free-flight
    skipping, the query of the end point, the tunnelling check and sweep, the response (or
    resting contact), the checks.

    ``here = (x, y, vx, vy, r, m, inv_m)``: the particle's state, mass (read by the user forces
    evaluated here) and ``1 / m``; ``coeffs = (CR, CF, i)``: where its ``cr`` and ``cf`` are
    read (only at a contact); ``c``: its free-flight budget; ``push = (ux, uy, ex, ey)``: its
    user forces when evaluated ahead (``FORCE_AHEAD``) and its Python force; ``step``: the
    step's index in a call of ``steps`` (:class:`.config.Physics`, :class:`.config.Budget`).

    Returns ``(x, y, vx, vy, c, code, touched)``: the new state and budget; ``code`` 0 (store
    them), a freeze code ``FLAG_*`` (keep the last valid state) or :data:`SLEPT` (the state did
    not change: it sleeps for the rest of the call); ``touched``: whether it met a surface."""
    x, y, vx, vy, r, m, inv_m = here
    dt = physics.dt
    t = physics.t0 + step * dt
    lip = budget.lip
    x0 = x
    y0 = y
    vx0 = vx
    vy0 = vy
    push = with_user_forces(push, x, y, vx, vy, m, t, False)
    bx, by = accelerate(vx, vy, inv_m, push, physics)
    dx, dy, vx, vy = euler(vx, vy, bx, by, physics)
    # A moving world: its surfaces move by at most wd in this step near the particle (0 for a
    # static world, and far from every moving wall).
    wd = 0.0
    if MOVING:
        wd = _wall_speed_at(data, x + dx, y + dy, dx, dy) * dt
    if c > 0.0:
        c = spend(c, x, y, dx, dy, wd, budget)
        if c > 0.0:  # free flight: no query
            x += dx
            y += dy
            return x, y, vx, vy, c, 0 if _finite4(x, y, vx, vy) else FLAG_NONFINITE, False
        c = 0.0
    if _fallback_missing(data, x, y, dx, dy):
        return x0, y0, vx0, vy0, c, FLAG_RESUME + step, False
    # (a static world's dd/dt is the constant 0)
    found = _query_t(data, x + dx, y + dy, t + dt)
    bounced = False
    if budget.trace and needs_sweep(dx * dx + dy * dy, found[0] - r, r, lip, wd):
        cr, cf, ok = _coeffs(coeffs[0], coeffs[1], coeffs[2])
        if not ok:
            return x0, y0, vx0, vy0, c, FLAG_COEFF, False
        motion, bounced, found = swept(
            data,
            Motion(x, y, dx, dy, vx, vy),
            Disc(r, cr, cf),
            found,
            lip,
            physics.always,
            Window(0.0, 1.0, t, dt, wd),
        )
        x, y, dx, dy, vx, vy = motion
    d, gx, gy, gt = found
    s = d - r
    x += dx
    y += dy
    touched = s <= 0.0
    if touched:
        cr, cf, ok = _coeffs(coeffs[0], coeffs[1], coeffs[2])
        if not ok:
            return x0, y0, vx0, vy0, c, FLAG_COEFF, True
        rest = physics.rest
        if rest > 0.0 and not bounced and _rests(vx0, vy0, bx, by, gx, gy, cf, rest):
            # resting contact: the surface holds the particle where it is
            x = x0
            y = y0
            vx = 0.0
            vy = 0.0
        else:
            x, y, vx, vy = _respond(
                x, y, vx, vy, s, (gx, gy, gt), cr, cf, physics.always and not bounced
            )
    elif budget.skip and s > budget.margin:
        c = refill(s, budget.margin, lip)
    if not _finite4(x, y, vx, vy):
        return x0, y0, vx0, vy0, c, FLAG_NONFINITE, touched
    if (
        SLEEP
        and physics.rest > 0.0
        and steps > 1
        and x == x0
        and y == y0
        and vx == vx0
        and vy == vy0
    ):
        # The step left the state bit-identical, and nothing else it depends on changes within
        # this call (static world, forces independent of time): every later step of the call
        # would repeat it, so the particle sleeps until the next call. (Only resting contact
        # makes such fixed points common.)
        return x, y, vx, vy, ASLEEP, SLEPT, touched
    return x, y, vx, vy, c, 0, touched
