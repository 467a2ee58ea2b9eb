"""The step's loops on the CPU and its entry points: the particle-by-particle block
(:func:`_block`, each particle through :func:`.phases.particle_step`), its plain specialization
(:func:`_block_plain`), and ``step_ser`` / ``step_par``, which run the blocks of a call in the
kernel variant it asks for (the block step of grid worlds is :mod:`.block`)."""

import numpy as np
from numba import njit, prange

from fastsdf.particles.kernels.block import _block_simd
from fastsdf.particles.kernels.config import Budget, Physics, State
from fastsdf.particles.kernels.constants import (
    FLAG_COEFF,
    FLAG_INPUT,
    FLAG_NONFINITE,
    FLAG_RESUME,
    FORCE_BATCH,
)
from fastsdf.particles.kernels.contact import _respond
from fastsdf.particles.kernels.intrinsics import borrow_all
from fastsdf.particles.kernels.phases import (
    _coeffs,
    _finite4,
    accelerate,
    euler,
    input_ok,
    particle_step,
    switched,
    with_user_forces,
)
from fastsdf.particles.kernels.scene import (
    _CACHE,
    FORCE_AHEAD,
    USE_FORCE,
    _fallback_missing,
    _force,
    _query,
)

__all__ = ["PLAIN_BATCH", "step_ser", "step_par", "query_many", "force_many"]

# >>> KERNEL BODY (from here on, copied into every generated kernel module) >>>

# ---------------------------------------------------------------------------------------------
# The particle-by-particle step on the CPU.

#: Particles a batched plain step handles per pass (see :func:`_plain_staged`; at most
#: ``FORCE_BATCH``, the size of the buffer of forces evaluated ahead).
PLAIN_BATCH = 16


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _freeze(clear, FLAGS, k, i, flag):
    """Freeze particle ``i`` (``k`` in its block) with ``flag``; returns 1 (one more frozen)."""
    clear[k] = -1.0
    FLAGS[i] = flag
    return 1


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _check_block(lo, hi, state, clear, inv_mass, use_m):
    """A block's first pass: ``1 / m`` into ``inv_mass`` (when ``use_m``) and the checks of
    the package docs (:func:`.phases.input_ok`); freezes a failing particle and returns how
    many failed."""
    bad = 0
    for i in range(lo, hi):
        ok, m = input_ok(state, i, use_m)
        if use_m:
            inv_mass[i - lo] = 1.0 / m
        if not ok:
            bad += _freeze(clear, state.FLAGS, i - lo, i, FLAG_INPUT)
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
def _pushed(i, k, q, u, physics, work):
    """What particle ``i`` (``k`` in its block, row ``q`` of the forces evaluated ahead)
    brings to :func:`.phases.particle_step` besides its position and velocity: its radius,
    mass and ``1 / m`` (read where used), and ``(ux, uy, ex, ey)``."""
    R, M, EXT, inv_mass, fbuf = work
    m = float(M[u]) if USE_FORCE and not FORCE_AHEAD else 1.0
    inv_m = inv_mass[k] if physics.use_m else 1.0
    ux = uy = ex = ey = 0.0
    if USE_FORCE and FORCE_AHEAD:
        ux = fbuf[q, 0]
        uy = fbuf[q, 1]
    if physics.use_ext:
        ex = EXT[i, 0]
        ey = EXT[i, 1]
    return float(R[u]), m, inv_m, (ux, uy, ex, ey)


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _block(data, lo, hi, steps, state, physics, budget):
    """All steps for particles lo..hi-1 (:class:`.config.State`, :class:`.config.Physics`,
    :class:`.config.Budget`), each particle's step :func:`.phases.particle_step`; returns the
    number of particles frozen (flagged).

    The only compiled call that touches the arrays: helpers that take arrays are inlined and the
    others take scalars, so no reference counting happens per particle.

    Free-flight skipping (``skip``): after a query that finds a particle clear of every surface
    by ``s = d - r > 0``, it can move ``(s - margin) / lip`` before it could touch anything, so
    its next steps skip the SDF query until that budget is spent. This changes no result: a
    skipped query is one that would have found no contact. ``margin`` covers a grid's jump to
    the exact SDF at its bounds; ``eps`` is the relative rounding of stored coordinates.
    ``clear[k]`` holds particle ``k``'s budget; ``< 0`` marks a frozen particle.
    """
    X, V, M, R, CR, CF, EXT, FLAGS, check_all = state
    data = borrow_all(data)
    M, EXT = borrow_all((M, EXT))  # (arrays read only in some branches: see borrow_all)
    clear = np.zeros(hi - lo)
    use_m = physics.use_m or USE_FORCE
    own = switched(physics, use_m, physics.use_ext, physics.rest)
    # 1 / m of the block, computed once per call rather than divided every step
    inv_mass = np.empty(hi - lo if use_m else 0)
    fbuf = np.empty((FORCE_BATCH if USE_FORCE and FORCE_AHEAD else 0, 2))
    bad = _check_block(lo, hi, state, clear, inv_mass, use_m)
    Xf = X.reshape(X.size)
    Vf = V.reshape(V.size)
    work = (R, M, EXT, borrow_all(inv_mass), fbuf)
    for step in range(steps):
        t = physics.t0 + step * physics.dt
        for i in range(lo, hi):
            k = i - lo
            if USE_FORCE and FORCE_AHEAD and k % FORCE_BATCH == 0:
                _forces_ahead(Xf, Vf, M, clear, lo, i, min(hi, i + FORCE_BATCH), fbuf, t)
            c = clear[k]
            if c < 0.0:
                continue
            u, ix, iy, x, y, vx, vy = _load(Xf, Vf, i)
            r, m, inv_m, push = _pushed(i, k, k % FORCE_BATCH, u, own, work)
            here = (x, y, vx, vy, r, m, inv_m)
            x, y, vx, vy, c, code, _ = particle_step(
                data, here, (CR, CF, u), c, push, step, own, budget, steps
            )
            if code > 0:
                bad += _freeze(clear, FLAGS, k, u, code)
                continue
            clear[k] = c
            if code == 0:
                _store(Xf, Vf, ix, iy, x, y, vx, vy)
    return bad


# ---------------------------------------------------------------------------------------------
# The plain step: no query skipping, tunnelling check, moving world or resting contact.

#: The budget of the plain step: no sweep, no skipping (nothing else of it is read).
_PLAIN = Budget(trace=False, lip=1.0, margin=0.0, eps=0.0, skip=False)


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _plain_straight(data, lo, hi, step, state, physics, work):
    """One step of a block for :func:`_block_plain`, particle after particle, each
    :func:`.phases.particle_step` with the plain step's switches as constants (``work``: the
    block's flat state views and scratch, see :func:`_block_plain`). Returns the frozen count
    and how many particles touched a surface."""
    X, V, M, R, CR, CF, EXT, FLAGS, check_all = state
    Xf, Vf, clear, inv_mass, fbuf, sb = work
    t = physics.t0 + step * physics.dt
    bad = 0
    touching = 0
    for i in range(lo, hi):
        k = i - lo
        if USE_FORCE and FORCE_AHEAD and k % FORCE_BATCH == 0:
            _forces_ahead(Xf, Vf, M, clear, lo, i, min(hi, i + FORCE_BATCH), fbuf, t)
        if clear[k] < 0.0:
            continue
        u, ix, iy, x, y, vx, vy = _load(Xf, Vf, i)
        r, m, inv_m, push = _pushed(i, k, k % FORCE_BATCH, u, physics, (R, M, EXT, inv_mass, fbuf))
        here = (x, y, vx, vy, r, m, inv_m)
        x, y, vx, vy, c, code, touched = particle_step(
            data, here, (CR, CF, u), 0.0, push, step, physics, _PLAIN, 1
        )
        touching += touched
        if code > 0:
            bad += _freeze(clear, FLAGS, k, u, code)
            continue
        _store(Xf, Vf, ix, iy, x, y, vx, vy)
    return bad, touching


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _plain_staged(data, lo, hi, step, state, physics, work):
    """One step of a block for :func:`_block_plain`, ``PLAIN_BATCH`` particles at a time in
    two passes of the same phases: integrate and query all of them (independent iterations
    without data-dependent branches, so their dependent chains overlap), then respond (the
    contact branch mispredicts often while particles rest; there a mispredict no longer
    discards the next particles' queries). ``sb`` in ``work``: scratch of shape
    (7, PLAIN_BATCH)."""
    X, V, M, R, CR, CF, EXT, FLAGS, check_all = state
    Xf, Vf, clear, inv_mass, fbuf, sb = work
    t = physics.t0 + step * physics.dt
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
            r, m, inv_m, push = _pushed(i, k, q, u, physics, (R, M, EXT, inv_mass, fbuf))
            push = with_user_forces(push, x, y, vx, vy, m, t, False)
            bx, by = accelerate(vx, vy, inv_m, push, physics)
            dx, dy, vx, vy = euler(vx, vy, bx, by, physics)
            if _fallback_missing(data, x, y, dx, dy):
                bad += _freeze(clear, FLAGS, k, u, FLAG_RESUME + step)
                continue
            d, gx, gy = _query(data, x + dx, y + dy)
            sb[0, q] = x + dx
            sb[1, q] = y + dy
            sb[2, q] = vx
            sb[3, q] = vy
            sb[4, q] = d - r
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
                grad = (sb[5, q], sb[6, q], 0.0)
                x, y, vx, vy = _respond(x, y, vx, vy, s, grad, cr, cf, physics.always)
            if not _finite4(x, y, vx, vy):
                bad += _freeze(clear, FLAGS, k, u, FLAG_NONFINITE)
                continue
            ix = np.uint64(2) * u
            _store(Xf, Vf, ix, ix + np.uint64(1), x, y, vx, vy)
    return bad, touching


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _block_plain(data, lo, hi, steps, state, physics):
    """:func:`_block` without query skipping, tunnelling check, moving world or resting
    contact: every step is integrate, query, respond, as in the peers' kernels. Same results
    as :func:`_block` with those off, in fewer instructions per particle-step (the switches
    and the common flags as constants), so that out-of-order execution overlaps more
    particles' dependent chains. A step runs in batches (:func:`_plain_staged`) after a step
    where at least a quarter of the block touched a surface, else particle after particle
    (:func:`_plain_straight`); the two give the same results.
    """
    X, V, M, R, CR, CF, EXT, FLAGS, check_all = state
    data = borrow_all(data)
    M, EXT = borrow_all((M, EXT))  # (see _block)
    clear = np.zeros(hi - lo)
    use_m = physics.use_m or USE_FORCE
    inv_mass = np.empty(hi - lo if use_m else 0)
    fbuf = np.empty((FORCE_BATCH if USE_FORCE and FORCE_AHEAD else 0, 2))
    bad = _check_block(lo, hi, state, clear, inv_mass, use_m)
    # (the helpers are inlined: arrays borrowed here stay borrowed there)
    own = State(X, V, M, R, CR, CF, EXT, FLAGS, check_all)
    Xf = X.reshape(X.size)
    Vf = V.reshape(V.size)
    work = (Xf, Vf, clear, borrow_all(inv_mass), fbuf, np.empty((7, PLAIN_BATCH)))
    if not use_m and not physics.explicit and not physics.always:
        # the common flags as constants
        common = Physics(
            physics.dt,
            physics.t0,
            physics.ax,
            physics.ay,
            physics.drag,
            False,
            False,
            False,
            False,
            0.0,
        )
        return bad + _plain_steps(data, lo, hi, steps, own, common, work)
    plain = switched(physics, use_m, physics.use_ext, 0.0)
    return bad + _plain_steps(data, lo, hi, steps, own, plain, work)


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _plain_steps(data, lo, hi, steps, state, physics, work):
    """The steps of :func:`_block_plain`, straight or staged by the last step's contacts."""
    bad = 0
    touching = 0
    for step in range(steps):
        if 4 * touching >= hi - lo:
            b, touching = _plain_staged(data, lo, hi, step, state, physics, work)
        else:
            b, touching = _plain_straight(data, lo, hi, step, state, physics, work)
        bad += b
    return bad


# ---------------------------------------------------------------------------------------------
# The entry points: one kernel family, its variants chosen by the types of two arguments.


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _block_of(data, lo, hi, steps, state, physics, budget, simd, plain):
    """The blocks lo..hi-1 in the variant ``(simd, plain)`` (see :func:`step_ser`; numba
    prunes the branches of the other variants before compiling, each ``None`` or True)."""
    if simd is None:
        if plain is None:
            return _block(data, lo, hi, steps, state, physics, budget)
        return _block_plain(data, lo, hi, steps, state, physics)
    return _block_simd(data, lo, hi, steps, state, physics, budget, plain)


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def step_ser(data, state, physics, budget, steps, block, simd, plain):
    """``steps`` steps of the particles of ``state`` (:class:`.config.State`) with ``physics``
    and ``budget`` (:class:`.config.Physics`, :class:`.config.Budget`) in the world ``data``,
    in blocks of ``block`` particles. Returns the frozen count. It releases the GIL: the caller
    runs slices of the particles on several threads (particles are independent, so the results
    do not depend on the slicing).

    The variant, each a compiled specialization (``None`` or True; all give the same results):
    ``simd=None, plain=None``: the general particle-by-particle step (:func:`_block`);
    ``simd=None, plain=True``: without skipping, tunnelling check, moving world and resting
    contact (:func:`_block_plain`); ``simd=True``: the block step of a static grid world
    (``GRID_SIMD``, float64 state, no resting contact, no Python forces; :mod:`.block`), with
    free-flight skipping (``plain=None``) or without (``plain=True``)."""
    n = state.X.shape[0]
    bad = 0
    for lo in range(0, n, block):
        bad += _block_of(data, lo, min(n, lo + block), steps, state, physics, budget, simd, plain)
    return bad


@njit(cache=_CACHE, parallel=True, error_model="numpy")
def step_par(data, state, physics, budget, steps, block, simd, plain):
    """:func:`step_ser` with the blocks over numba's threads (``parallel=True``), for long
    calls (see :mod:`fastsdf.particles.engine`); compiled only when first used."""
    n = state.X.shape[0]
    nblocks = (n + block - 1) // block
    bad = 0
    for c in prange(nblocks):
        lo = c * block
        hi = min(n, lo + block)
        bad += _block_of(data, lo, hi, steps, state, physics, budget, simd, plain)
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
