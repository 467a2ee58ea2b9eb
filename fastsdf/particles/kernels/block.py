"""The block step of grid worlds: ``LANES`` particles in scratch rows through all steps of a
call, each step in passes over them that LLVM turns into vector code, built from the phases of
:mod:`.phases` (the ``simd`` variant of the entry points of :mod:`.step`)."""

import math

import numpy as np
from numba import njit

from fastsdf.intrinsics import bits_f64, f64_bits, select
from fastsdf.particles.kernels.config import Disc, Motion, Window
from fastsdf.particles.kernels.constants import (
    FLAG_COEFF,
    FLAG_INPUT,
    FLAG_NONFINITE,
    FLAG_RESUME,
)
from fastsdf.particles.kernels.contact import _respond
from fastsdf.particles.kernels.intrinsics import _cell_vg, _gather4, borrow_all
from fastsdf.particles.kernels.phases import (
    _coeffs_ok,
    _finite4,
    accelerate,
    euler,
    input_ok,
    needs_sweep,
    outside_reach,
    refill,
    spend,
    swept,
    switched,
    with_user_forces,
)
from fastsdf.particles.kernels.scene import _CACHE, GRID_EXACT, USE_FORCE, _query

__all__ = ["LANES"]

# >>> KERNEL BODY (from here on, copied into every generated kernel module) >>>

# ---------------------------------------------------------------------------------------------
# The block step of grid worlds: a block of particles held in scratch rows through all steps,
# each step in passes over the block that LLVM vectorizes (several particles per instruction).


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


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_load(S, state, b0, nb, use_m):
    """A block's state into the scratch rows (lanes past ``nb`` idle), with the checks of
    :func:`.phases.input_ok` (a particle that fails is flagged and idle). Returns how many
    failed."""
    X, V, M, R, CR, CF, EXT, FLAGS, check_all = state
    Xf = X.reshape(X.size)
    Vf = V.reshape(V.size)
    L = LANES
    W = _STRIDE
    bad = 0
    for k in range(L):
        if k < nb:
            i = np.uint64(b0 + k)
            ix = np.uint64(2) * i
            ok, m = input_ok(state, i, use_m)
            if not ok:
                FLAGS[i] = FLAG_INPUT
                bad += 1
            S[_X * W + k] = Xf[ix]
            S[_Y * W + k] = Xf[ix + np.uint64(1)]
            S[_VX * W + k] = Vf[ix]
            S[_VY * W + k] = Vf[ix + np.uint64(1)]
            S[_R * W + k] = R[i]
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
    W = _STRIDE
    for k in range(nb):
        ix = np.uint64(2) * np.uint64(b0 + k)
        Xf[ix] = S[_X * W + k]
        Xf[ix + np.uint64(1)] = S[_Y * W + k]
        Vf[ix] = S[_VX * W + k]
        Vf[ix + np.uint64(1)] = S[_VY * W + k]


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _simd_move(S, step, physics, budget, fbchk, b, g, skipping):
    """Pass 1 of a step (vector): forces and integration (:func:`.phases.accelerate`,
    :func:`.phases.euler`), the free-flight budget (:func:`.phases.spend`: a particle whose
    budget covers the step moves here and needs no query), the check for a grid fallback not
    bound yet (:func:`.phases.outside_reach` of the bounds ``b``), and the cell of the end point
    (index and bilinear fractions, the operations of ``fastsdf.fields.grid``'s sampler;
    ``g``: ``(x0, x1, y0, y1, 1/hx, 1/hy, nx - 2, ny - 2, ny)`` of the grid, floats). Returns
    how many particles need a query, how many were frozen, and how many of those that query
    end outside the grid. ``fbchk``, ``skipping``: constants in the compiled versions (without
    them, the budget's and the reach's square roots are left out)."""
    dt = physics.dt
    t = physics.t0 + step * dt
    own = switched(physics, physics.use_m, False, 0.0)  # (no Python forces here)
    L = LANES
    W = _STRIDE
    x0, x1, y0, y1, ihx, ihy, nxm2, nym2, nyf = g
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
        push = with_user_forces((0.0, 0.0, 0.0, 0.0), x, y, vx, vy, S[_M * W + q], t, True)
        bx, by = accelerate(vx, vy, S[_IM * W + q], push, own)
        dx, dy, nvx, nvy = euler(vx, vy, bx, by, own)
        c = S[_CLR * W + q] if skipping else 0.0
        c2 = spend(c, x, y, dx, dy, 0.0, budget)
        skip = (c > 0.0) & (c2 > 0.0)
        xe = x + dx
        ye = y + dy
        fin = _finite4(xe, ye, nvx, nvy)
        moved = live & skip
        keep = moved & fin
        S[_X1 * W + q] = select(keep, xe, x)
        S[_Y1 * W + q] = select(keep, ye, y)
        S[_VX1 * W + q] = select(keep, nvx, vx)
        S[_VY1 * W + q] = select(keep, nvy, vy)
        if skipping:
            S[_CLR1 * W + q] = select(skip, c2, 0.0)
        need = live & (not skip)
        miss = need & fbchk & outside_reach(x, y, dx, dy, b)
        need = need & (not miss)
        code = select(miss, resume, select(moved & (not fin), nonfinite, 0.0))
        # the sampler's _locate, branch-free
        inside = (xe >= x0) & (xe <= x1) & (ye >= y0) & (ye <= y1)
        ok = inside | ((abs(xe) < math.inf) & (abs(ye) < math.inf))
        xq = select(inside, xe, min(max(select(ok, xe, x0), x0), x1))
        yq = select(inside, ye, min(max(select(ok, ye, y0), y0), y1))
        u = (xq - x0) * ihx
        v = (yq - y0) * ihy
        fi = min(np.floor(u), nxm2)
        fj = min(np.floor(v), nym2)
        S[_TX * W + q] = u - fi
        S[_TY * W + q] = v - fj
        # the flat index as an integer (converted here, in vector registers: a scalar
        # conversion in the gather would lengthen each particle's dependent chain)
        S[_IDX * W + q] = bits_f64(np.int64(np.int32(3.0 * (fi * nyf + fj))))
        S[_INS * W + q] = select(inside, 1.0, 0.0)
        S[_OK * W + q] = select(ok, 1.0, 0.0)
        S[_DX * W + q] = dx
        S[_DY * W + q] = dy
        S[_NVX * W + q] = nvx
        S[_NVY * W + q] = nvy
        S[_NEED * W + q] = select(need, 1.0, 0.0)
        S[_CODE1 * W + q] = code
        nneed += need
        nfrz += code != 0.0
        nout += need & (not inside)
    return nneed, nfrz, nout


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_move_budget(S, step, physics, budget, fbchk, b, g):
    """:func:`_simd_move` with budgets (``skip``) or the fallback check (without budgets
    their row stays 0)."""
    return _simd_move(S, step, physics, budget, fbchk, b, g, True)


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_move_plain(S, step, physics, budget, fbchk, b, g):
    """:func:`_simd_move` without budgets or the fallback check (``skip``, ``fbchk`` False)."""
    return _simd_move(S, step, physics, budget, False, b, g, False)


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _fix_mark(S, q, trace, lip):
    """Whether lane ``q`` needs the scalar fix-up (:func:`_simd_fix`): a particle that queries
    and needs a tunnelling sweep (``trace``, :func:`.phases.needs_sweep`), or whose end point
    is outside an 'exact' grid. Marks it (and clears its bounce)."""
    W = _STRIDE
    need = S[_NEED * W + q] != 0.0
    r = S[_R * W + q]
    s = select(S[_OK * W + q] != 0.0, S[_D * W + q], math.nan) - r
    dx = S[_DX * W + q]
    dy = S[_DY * W + q]
    sweep = trace & needs_sweep(dx * dx + dy * dy, s, r, lip, 0.0)
    fix = need & (sweep | (GRID_EXACT & (S[_INS * W + q] == 0.0)))
    S[_FIX * W + q] = select(fix, 1.0, 0.0)
    S[_BNC * W + q] = 0.0
    return fix


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _simd_gather(S, grid, row, lip, trace, every, marks):
    """Pass 2 (scalar: loads from computed places): the bilinear value and gradient at the
    end point of each particle that needs a query, from its cell's two runs of 6 grid values
    (``row``: the flat distance between nodes (i, j) and (i + 1, j)); the operations of
    ``fastsdf.fields.grid.sample_stored`` (its NaN for a non-finite point is applied where the
    values are used, from the ``_OK`` row). Returns how many may touch a surface (a hint:
    ``d <= r`` before that NaN). ``every``: a constant in the two compiled versions, True
    when every particle queries (no test per particle; the others' cells are valid ones).
    ``marks`` (constant too): also mark the particles that need the scalar fix-up
    (:func:`_fix_mark`; here, for a tunnelling check: one pass less). Returns the count of
    those as well."""
    L = LANES
    W = _STRIDE
    ncon = 0
    nfix = 0
    for q in range(L):
        if every or S[_NEED * W + q] != 0.0:
            a = np.uint64(f64_bits(S[_IDX * W + q]))
            d, gx, gy = _cell_vg(grid, a, a + row, S[_TX * W + q], S[_TY * W + q])
            S[_D * W + q] = d
            S[_GX * W + q] = gx
            S[_GY * W + q] = gy
            ncon += d <= S[_R * W + q]
            if marks:
                nfix += _fix_mark(S, q, trace, lip)
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
    rows = (_IDX * W, _TX * W, _TY * W, _D * W, _GX * W, _GY * W, _R * W)
    ncon = 0
    for q in range(0, LANES, 4):
        ncon += _gather4(grid, S, q, row, rows)
    return ncon, 0


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_blend(S, trace, lip):
    """Pass 3 (vector): which particles need the scalar fix-up (:func:`_fix_mark`). Returns
    their count. (No row is rewritten here from its own value under a condition: LLVM makes
    that a masked store, microcoded and slow.)"""
    nfix = 0
    for q in range(LANES):
        nfix += _fix_mark(S, q, trace, lip)
    return nfix


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_query(data, x, y):
    """:func:`_query` outside the grid, compiled on its own for the fix-up (compile time)."""
    return _query(data, x, y)


@njit(cache=_CACHE, nogil=True, error_model="numpy")
def _simd_fix(data, S, lip, always, trace):
    """The scalar fix-up of the marked particles: the exact query outside the grid, and the
    tunnelling sweep (:func:`.phases.swept`, with the end point's query after a bounce), as
    in :func:`.phases.particle_step`. Returns how many were frozen (invalid ``cr``/``cf`` at
    a sweep)."""
    L = LANES
    W = _STRIDE
    nfrz = 0
    for q in range(L):
        if S[_FIX * W + q] == 0.0 or S[_NEED * W + q] == 0.0:  # (FIX is set for these only)
            continue
        x = S[_X * W + q]
        y = S[_Y * W + q]
        dx = S[_DX * W + q]
        dy = S[_DY * W + q]
        r = S[_R * W + q]
        if GRID_EXACT and S[_INS * W + q] == 0.0:
            d, gx, gy = _simd_query(data, x + dx, y + dy)
            S[_D * W + q] = d
            S[_GX * W + q] = gx
            S[_GY * W + q] = gy
            S[_OK * W + q] = 1.0  # these values stand as they are
        d = select(S[_OK * W + q] != 0.0, S[_D * W + q], math.nan)
        if not (trace and needs_sweep(dx * dx + dy * dy, d - r, r, lip, 0.0)):
            continue
        cr = S[_CR * W + q]
        cf = S[_CF * W + q]
        if not _coeffs_ok(cr, cf):
            S[_CODE1 * W + q] = float(FLAG_COEFF)
            nfrz += 1
            continue
        motion, bounced, found = swept(
            data,
            Motion(x, y, dx, dy, S[_NVX * W + q], S[_NVY * W + q]),
            Disc(r, cr, cf),
            (d, S[_GX * W + q], S[_GY * W + q], 0.0),
            lip,
            always,
            Window(0.0, 1.0, 0.0, 0.0, 0.0),
        )
        if bounced:
            S[_D * W + q] = found[0]
            S[_GX * W + q] = found[1]
            S[_GY * W + q] = found[2]
            S[_OK * W + q] = 1.0
            S[_BNC * W + q] = 1.0
        S[_XS * W + q] = motion.x
        S[_YS * W + q] = motion.y
        S[_DX * W + q] = motion.dx
        S[_DY * W + q] = motion.dy
        S[_NVX * W + q] = motion.vx
        S[_NVY * W + q] = motion.vy
    return nfrz


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _simd_respond(S, always, skip, lip, margin, contacts):
    """Pass 4 (vector): the end point, the collision response where ``s <= 0``
    (:func:`.contact._respond`), the checks, the free-flight budget (:func:`.phases.refill`),
    and the new state of every particle that queried and was not frozen. Returns how many were
    frozen. ``contacts``: a constant in the two compiled versions; False when no particle of
    the block touches a surface (then the response's square root and division are left out)."""
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
        x = select(bounced, S[_XS * W + q], x1) + S[_DX * W + q]
        y = select(bounced, S[_YS * W + q], y1) + S[_DY * W + q]
        vx = S[_NVX * W + q]
        vy = S[_NVY * W + q]
        ok = S[_OK * W + q] != 0.0  # False: a non-finite end point (the sampler's NaN)
        s = select(ok, S[_D * W + q], math.nan) - S[_R * W + q]
        cr = S[_CR * W + q]
        cf = S[_CF * W + q]
        contact = (s <= 0.0) & contacts
        # (where not ok, s is NaN: no contact, so the gradient's value does not matter)
        grad = (S[_GX * W + q], S[_GY * W + q], 0.0)
        rx, ry, rvx, rvy = _respond(x, y, vx, vy, s, grad, cr, cf, always & (not bounced))
        x = select(contact, rx, x)
        y = select(contact, ry, y)
        vx = select(contact, rvx, vx)
        vy = select(contact, rvy, vy)
        code0 = S[_CODE1 * W + q]
        code = select(
            code0 != 0.0,
            code0,
            select(
                contact & (not _coeffs_ok(cr, cf)),
                coeff,
                select(_finite4(x, y, vx, vy), 0.0, nonfinite),
            ),
        )
        commit = need & (code == 0.0)
        S[_X * W + q] = select(commit, x, x1)
        S[_Y * W + q] = select(commit, y, y1)
        S[_VX * W + q] = select(commit, vx, S[_VX1 * W + q])
        S[_VY * W + q] = select(commit, vy, S[_VY1 * W + q])
        if skip:
            budget = select((not contact) & (s > margin), refill(s, margin, lip), 0.0)
            S[_CLR * W + q] = select(need, budget, S[_CLR1 * W + q])
        S[_CODE * W + q] = select(need, code, code0)
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
    """Freeze the particles whose step set a code (see the package docs' checks)."""
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
def _block_simd(data, lo, hi, steps, state, physics, budget, plain):
    """:func:`.step._block` for a static grid world (``GRID_SIMD``) without resting contact or
    Python forces, the same results: ``LANES`` particles at a time through all steps, each
    step in passes over the block (:func:`_simd_move`, :func:`_simd_gather`,
    :func:`_simd_blend`, :func:`_simd_fix`, :func:`_simd_respond`); a step in which no
    particle of the block needs a query is the first pass alone.

    ``plain``: a compile-time switch by type, ``None`` for calls with free-flight query
    skipping (``budget.skip``), ``True`` for calls without (numba prunes ``plain is None``
    before compiling), so that each variant compiles only the passes it runs."""
    X, V, M, R, CR, CF, EXT, FLAGS, check_all = state
    trace, lip, margin, eps, skip = budget
    always = physics.always
    data = borrow_all(data)
    grid, x0, x1, y0, y1, ihx, ihy, nx, ny = data[5:14]
    b = (float(data[1]), float(data[2]), float(data[3]), float(data[4]))
    g = (
        float(x0),
        float(x1),
        float(y0),
        float(y1),
        float(ihx),
        float(ihy),
        float(nx - 2),
        float(ny - 2),
        float(ny),
    )
    row = np.uint64(3 * ny)
    fbchk = GRID_EXACT and data[0] == 0
    use_m = physics.use_m or USE_FORCE
    own = switched(physics, use_m, physics.use_ext, physics.rest)
    Xf = X.reshape(X.size)
    Vf = V.reshape(V.size)
    S = np.zeros(_ROWS * _STRIDE)
    bad = 0
    for b0 in range(lo, hi, LANES):
        nb = min(hi, b0 + LANES) - b0
        bad += _simd_load(S, state, b0, nb, use_m)
        for step in range(steps):
            if plain is None or fbchk:
                nneed, nfrz, nout = _simd_move_budget(S, step, own, budget, fbchk, b, g)
            else:
                nneed, nfrz, nout = _simd_move_plain(S, step, own, budget, fbchk, b, g)
            if nneed > 0:
                if plain is None or trace:
                    ncon, nfix = _simd_gather_some(S, grid, row, lip, trace)
                else:
                    ncon, nfix = _simd_gather_all(S, grid, row, lip)
                    # (a query outside an 'exact' grid needs the exact value)
                    if GRID_EXACT and nout > 0:
                        nfix = _simd_blend(S, trace, lip)
                if nfix > 0:
                    nfrz += _simd_fix(data, S, lip, always, trace)
                    ncon = 1
                if plain is None:
                    if ncon > 0:
                        nfrz += _simd_respond_all(S, always, skip, lip, margin)
                    else:
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
