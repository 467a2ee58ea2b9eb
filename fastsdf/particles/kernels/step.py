"""The particle-by-particle step: ``run_*`` (skipping, tunnelling sweep, moving worlds, resting
contact) and ``plain_*`` (none of those: the peers' work), parallel and serial entry points."""

import math

import numpy as np
from numba import njit, prange

from fastsdf.particles.kernels.config import Disc, Motion, Physics, State, Window
from fastsdf.particles.kernels.constants import (
    ASLEEP,
    CONTACT_TOL,
    FLAG_COEFF,
    FLAG_INPUT,
    FLAG_NONFINITE,
    FLAG_RESUME,
    FORCE_BATCH,
    TRACE_FRACTION,
)
from fastsdf.particles.kernels.contact import _respond, _rests, sweep
from fastsdf.particles.kernels.intrinsics import borrow_all
from fastsdf.particles.kernels.scene import (
    _CACHE,
    FORCE_AHEAD,
    MOVING,
    USE_FORCE,
    _fallback_missing,
    _force,
    _query,
    _query_t,
    _wall_speed_at,
)

__all__ = [
    "PLAIN_BATCH",
    "run_ser",
    "plain_ser",
    "run_par",
    "plain_par",
    "query_many",
    "force_many",
]

# >>> KERNEL BODY (from here on, copied into every generated kernel module) >>>

# ---------------------------------------------------------------------------------------------
# The particle-by-particle step.

#: Whether a particle whose step repeats its state may sleep for the rest of a call: the step
#: must not depend on time (no moving world, no user force, which may use ``t``).
SLEEP = not MOVING and not USE_FORCE


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
def _check_block(lo, hi, state, clear, inv_mass, use_m):
    """A block's first pass: ``1 / m`` into ``inv_mass`` (when ``use_m``) and the checks of
    the package docs; freezes a failing particle and returns how many failed."""
    X, V, M, R, CR, CF, EXT, FLAGS, check_all = state
    bad = 0
    for i in range(lo, hi):
        m = float(M[i]) if use_m or check_all else 1.0
        if use_m:
            inv_mass[i - lo] = 1.0 / m
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
def _accel(i, k, q, x, y, vx, vy, t, physics, arrays):
    """Acceleration ``g + (F_user + ext - drag v) / m`` of particle ``i`` (``k`` in its
    block) at time ``t`` with ``physics`` (:class:`.config.Physics`, whose ``use_m`` includes
    the fused user forces); ``arrays``: ``(M, EXT, inv_mass, fbuf)``, ``q``: the particle's
    row of ``fbuf`` when the user forces were evaluated ahead. Callers pass ``M``, ``EXT`` and
    ``inv_mass`` through :func:`borrow_all`: arrays read only in these branches would keep
    numba's reference counting (atomics) in the particle loop."""
    M, EXT, inv_mass, fbuf = arrays
    ax = physics.ax
    ay = physics.ay
    drag = physics.drag
    use_m = physics.use_m
    use_ext = physics.use_ext
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
def _block(data, lo, hi, steps, state, physics, budget):
    """All steps for particles lo..hi-1 (:class:`.config.State`, :class:`.config.Physics`,
    :class:`.config.Budget`); returns the number of particles frozen (flagged).

    The only compiled call that touches the arrays: helpers that take arrays are inlined and the
    others take scalars, so no reference counting happens per particle.

    Free-flight skipping (``skip``): after a query that finds a particle clear of every surface
    by ``s = d - r > 0``, it can move ``(s - margin) / lip`` before it could touch anything, so
    its next steps skip the SDF query until that budget is spent. This changes no result: a
    skipped query is one that would have found no contact. ``margin`` covers a grid's jump to
    the exact SDF at its bounds; ``eps`` is the relative rounding of stored coordinates.
    ``clear[k] < 0`` marks a frozen particle.
    """
    X, V, M, R, CR, CF, EXT, FLAGS, check_all = state
    dt, t0, ax, ay, drag, use_m, use_ext, explicit, always, rest = physics
    trace, lip, margin, eps, skip = budget
    data = borrow_all(data)
    M, EXT = borrow_all((M, EXT))  # see _accel
    clear = np.zeros(hi - lo)
    # A moving world: its surfaces move by at most wd per step near a particle (0 for a static
    # world, and far from every moving wall).
    wd = 0.0
    use_m = use_m or USE_FORCE
    own = Physics(dt, t0, ax, ay, drag, use_m, use_ext, explicit, always, rest)
    # 1 / m of the block, computed once per call rather than divided every step
    inv_mass = np.empty(hi - lo if use_m else 0)
    fbuf = np.empty((FORCE_BATCH if USE_FORCE and FORCE_AHEAD else 0, 2))
    bad = _check_block(lo, hi, state, clear, inv_mass, use_m)
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
            bx, by = _accel(
                i, k, k % FORCE_BATCH, x, y, vx, vy, t, own, (M, EXT, borrow_all(inv_mass), fbuf)
            )
            dx, dy, vx, vy = _integrate(vx, vy, bx, by, dt, explicit)
            if MOVING:
                wd = _wall_speed_at(data, x + dx, y + dy, dx, dy) * dt
            if c > 0.0:
                # (1 + CONTACT_TOL / lip): a skipped step must also be one whose sweep would
                # not have stopped at a near-contact (s <= CONTACT_TOL |step|).
                c -= (
                    math.sqrt(dx * dx + dy * dy) * (1.0 + CONTACT_TOL / lip)
                    + eps * (abs(x) + abs(y) + 1.0)
                    + wd / lip
                )
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
            # (a static world's dd/dt is the constant 0)
            d, gx, gy, gt = _query_t(data, x + dx, y + dy, t + dt)
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
                    crosses = ln > TRACE_FRACTION * r and not (s >= lip * ln and s > 0.0)
                else:
                    crosses = dd > (TRACE_FRACTION * r) * (TRACE_FRACTION * r) and not (
                        s * s >= lip * lip * dd and s > 0.0
                    )
                if crosses:
                    cr, cf, ok = _coeffs(CR, CF, u)
                    if not ok:
                        bad += _freeze(clear, FLAGS, k, u, FLAG_COEFF)
                        continue
                    # The part within s / L of the end is known to be free. (The start's
                    # budget is not used: results must not depend on how steps are grouped
                    # into calls.)
                    t1 = 1.0
                    if s > 0.0:
                        t1 = 1.0 - s / (lip * (ln if MOVING else math.sqrt(dd)))
                    x, y, dx, dy, vx, vy, bounced = sweep(
                        data,
                        Motion(x, y, dx, dy, vx, vy),
                        Disc(r, cr, cf),
                        lip,
                        always,
                        Window(0.0, t1, t, dt, wd),
                    )
                    if bounced:
                        d, gx, gy, gt = _query_t(data, x + dx, y + dy, t + dt)
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
                    x, y, vx, vy = _respond(
                        x, y, vx, vy, s, (gx, gy, gt), cr, cf, always and not bounced
                    )
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
def _plain_straight(data, lo, hi, step, t, state, physics, work):
    """One step of a block for :func:`_block_plain`, particle after particle (``work``: the
    block's flat state views and scratch, see :func:`_block_plain`)."""
    X, V, M, R, CR, CF, EXT, FLAGS, check_all = state
    dt, t0, ax, ay, drag, use_m, use_ext, explicit, always, rest = physics
    Xf, Vf, clear, inv_mass, fbuf, sb = work
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
        bx, by = _accel(
            i, k, k % FORCE_BATCH, x, y, vx, vy, t, physics, (M, EXT, borrow_all(inv_mass), fbuf)
        )
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
            x, y, vx, vy = _respond(x, y, vx, vy, s, (gx, gy, 0.0), cr, cf, always)
        if not _finite4(x, y, vx, vy):
            bad += _freeze(clear, FLAGS, k, u, FLAG_NONFINITE)
            continue
        _store(Xf, Vf, ix, iy, x, y, vx, vy)
    return bad, touching


#: Particles a batched plain step handles per pass (see :func:`_plain_staged`; at most
#: ``FORCE_BATCH``, the size of the buffer of forces evaluated ahead).
PLAIN_BATCH = 16


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _plain_staged(data, lo, hi, step, t, state, physics, work):
    """One step of a block for :func:`_block_plain`, ``PLAIN_BATCH`` particles at a time in
    two passes: integrate and query all of them (independent iterations without
    data-dependent branches, so their dependent chains overlap), then respond (the contact
    branch mispredicts often while particles rest; there a mispredict no longer discards the
    next particles' queries). ``sb`` in ``work``: scratch of shape (7, PLAIN_BATCH)."""
    X, V, M, R, CR, CF, EXT, FLAGS, check_all = state
    dt, t0, ax, ay, drag, use_m, use_ext, explicit, always, rest = physics
    Xf, Vf, clear, inv_mass, fbuf, sb = work
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
            bx, by = _accel(i, k, q, x, y, vx, vy, t, physics, (M, EXT, borrow_all(inv_mass), fbuf))
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
                x, y, vx, vy = _respond(x, y, vx, vy, s, (sb[5, q], sb[6, q], 0.0), cr, cf, always)
            if not _finite4(x, y, vx, vy):
                bad += _freeze(clear, FLAGS, k, u, FLAG_NONFINITE)
                continue
            ix = np.uint64(2) * u
            _store(Xf, Vf, ix, ix + np.uint64(1), x, y, vx, vy)
    return bad, touching


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _plain_steps(data, lo, hi, steps, state, physics, work):
    """The steps of :func:`_block_plain`: a step in batches (:func:`_plain_staged`) after a
    step where at least a quarter of the block touched a surface, else particle after
    particle (:func:`_plain_straight`); the two give the same results."""
    dt = physics.dt
    t0 = physics.t0
    bad = 0
    touching = 0
    for step in range(steps):
        t = t0 + step * dt
        if 4 * touching >= hi - lo:
            b, touching = _plain_staged(data, lo, hi, step, t, state, physics, work)
        else:
            b, touching = _plain_straight(data, lo, hi, step, t, state, physics, work)
        bad += b
    return bad


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _block_plain(data, lo, hi, steps, state, physics):
    """:func:`_block` without query skipping, tunnelling check, moving world or resting
    contact: every step is integrate, query, respond, as in the peers' kernels. Same results
    as :func:`_block` with those off, in fewer instructions per particle-step (flat unsigned
    indexing, the common flags constant), so that out-of-order execution overlaps more
    particles' dependent chains.
    """
    X, V, M, R, CR, CF, EXT, FLAGS, check_all = state
    dt, t0, ax, ay, drag, use_m, use_ext, explicit, always, rest = physics
    data = borrow_all(data)
    M, EXT = borrow_all((M, EXT))  # see _accel
    clear = np.zeros(hi - lo)
    use_m = use_m or USE_FORCE
    inv_mass = np.empty(hi - lo if use_m else 0)
    fbuf = np.empty((FORCE_BATCH if USE_FORCE and FORCE_AHEAD else 0, 2))
    bad = _check_block(lo, hi, state, clear, inv_mass, use_m)
    Xf = X.reshape(X.size)
    Vf = V.reshape(V.size)
    sb = np.empty((7, PLAIN_BATCH))
    # (the helpers are inlined: arrays borrowed here stay borrowed there)
    own = State(X, V, M, R, CR, CF, EXT, FLAGS, check_all)
    work = (Xf, Vf, clear, borrow_all(inv_mass), fbuf, sb)
    if not use_m and not explicit and not always:
        # the common flags as constants
        bad += _plain_steps(
            data,
            lo,
            hi,
            steps,
            own,
            Physics(dt, t0, ax, ay, drag, False, False, False, False, rest),
            work,
        )
    else:
        bad += _plain_steps(
            data,
            lo,
            hi,
            steps,
            own,
            Physics(dt, t0, ax, ay, drag, use_m, use_ext, explicit, always, rest),
            work,
        )
    return bad


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def run_ser(data, state, physics, budget, steps, block):
    """The general kernel: ``steps`` steps of the particles of ``state``
    (:class:`.config.State`) with ``physics`` and ``budget`` (:class:`.config.Physics`,
    :class:`.config.Budget`) in the world ``data``, in blocks of ``block`` particles. Returns
    the frozen count. It releases the GIL: the caller runs slices of the particles on several
    threads (particles are independent, so the results do not depend on the slicing)."""
    n = state.X.shape[0]
    bad = 0
    for lo in range(0, n, block):
        bad += _block(data, lo, min(n, lo + block), steps, state, physics, budget)
    return bad


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def plain_ser(data, state, physics, budget, steps, block):
    """:func:`run_ser` for calls without query skipping, tunnelling check, moving world or
    resting contact (``budget.skip``, ``budget.trace`` False, ``physics.rest`` 0; the rest of
    ``budget`` is unused): the same results through :func:`_block_plain`. A separate entry
    point, compiled only when first used."""
    n = state.X.shape[0]
    bad = 0
    for lo in range(0, n, block):
        bad += _block_plain(data, lo, min(n, lo + block), steps, state, physics)
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


@njit(cache=_CACHE, parallel=True, error_model="numpy")
def run_par(data, state, physics, budget, steps, block):
    """:func:`run_ser` with the blocks over numba's threads (``parallel=True``), for long
    calls (see :meth:`fastsdf.particles.ParticleSimulation.run`); compiled only when first
    used. Returns the frozen count."""
    n = state.X.shape[0]
    nblocks = (n + block - 1) // block
    bad = 0
    for c in prange(nblocks):
        lo = c * block
        hi = min(n, lo + block)
        bad += _block(data, lo, hi, steps, state, physics, budget)
    return bad


@njit(cache=_CACHE, parallel=True, error_model="numpy")
def plain_par(data, state, physics, budget, steps, block):
    """:func:`plain_ser` with the blocks over numba's threads, for long calls."""
    n = state.X.shape[0]
    nblocks = (n + block - 1) // block
    bad = 0
    for c in prange(nblocks):
        lo = c * block
        hi = min(n, lo + block)
        bad += _block_plain(data, lo, hi, steps, state, physics)
    return bad
