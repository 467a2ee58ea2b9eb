"""Compiled kernels of the granular step: contact forces (gathered per grain, race-free) and
the velocity-Verlet kicks and drift. Plain ``@njit`` functions on named structures, tested
directly (``tests/test_granular.py``).

The contact law is LAMMPS's ``gran/hooke`` (history-free): for a pair ``i, j`` with centres
``del = x_i - x_j`` at distance ``r < R_i + R_j``, ``n = del / r``, overlap ``delta = R_i + R_j -
r``, relative velocity ``v = v_i - v_j`` and its normal part ``v_n = v . n``, the force on ``i``
is ``(k_n delta - gamma_n v_n) n + f_t`` with ``gamma_n = 2 zeta sqrt(m_eff k_n)``; the
tangential force opposes the sliding velocity of the contact point ``v_t = v - v_n n + (R_i w_i
+ R_j w_j) (n_y, -n_x)`` with magnitude ``min(mu |F_n|, gamma_t |v_t|)``, and turns ``i`` by
``-R_i (n x f_t)``. A wall is the SDF world: ``delta = R - d``, ``n = grad d / |grad d|``, the
wall's velocity is its normal speed along ``n``, and ``m_eff = m_i``.

With history (LAMMPS ``gran/hooke/history``: :func:`pair_forces` and :func:`wall_forces`
given the contacts' memory instead of ``None``, a variant chosen at compile time) each contact
keeps a tangential spring (Cundall-Strack): its stretch ``xi`` along the tangent ``t = (-n_y,
n_x)`` grows by the sliding ``v_t dt`` of the contact point, the force is ``-(k_t xi + gamma_t
v_t) t``, and where that exceeds ``mu |F_n|`` it is set to the cap and ``xi`` truncated to
match (:func:`_contact_history`); optionally a rolling spring per contact resists relative
rotation (:func:`_rolling_spring`, model C of Ai, Chen, Rotter & Ooi 2011). Which model to
choose: ``docs/granular_models.md``.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np
from numba import njit, prange

from fastsdf.introspect import show_field_types

# The parallel passes run each chunk of grains through a serial function, or take the arrays
# they write out of a Grains tuple by attribute before their parallel loop: numba (0.68) drops
# stores made inside prange through ``g.x[i] = ...`` or through names bound by unpacking
# (``x, y = g.x, g.y`` included), not those of a function it calls.

# Floating-point liberties of the force pass: fused multiply-adds, reciprocals and signed
# zeros only (no reassociation: the two sides of a pair across chunks must compute the same
# bits; no "no-NaN" assumption: NaN must still propagate).
_FAST = {"contract", "arcp", "nsz"}

__all__ = [
    "Bulk",
    "Grain",
    "Grains",
    "Law",
    "Near",
    "Pair",
    "WallPair",
    "grain_mass",
    "half_kick",
    "image_shift",
    "kick_drift",
    "kick_grain",
    "kinetic_energy",
    "law_terms",
    "pair_energy",
    "pair_force",
    "pair_forces",
    "Substep",
    "substep_pass",
    "wall_energy",
    "wall_force",
    "wall_forces",
]


@show_field_types
class Grains(NamedTuple):
    """Structure of arrays of ``n`` discs (float64, shape (n,) each): position ``x, y``,
    velocity ``vx, vy``, angular velocity ``omega`` (rad/s, counter-clockwise), ``radius``, and
    the force ``fx, fy`` and torque ``torque`` of the last force evaluation, and the velocities
    predicted for the force evaluation ``px, py, pomega`` (see :func:`kick_drift`)."""

    x: np.ndarray
    y: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    omega: np.ndarray
    radius: np.ndarray
    fx: np.ndarray
    fy: np.ndarray
    torque: np.ndarray
    px: np.ndarray
    py: np.ndarray
    pomega: np.ndarray


@show_field_types
class Bulk(NamedTuple):
    """What every grain shares: ``density`` (mass per area; a disc of radius R weighs
    ``density pi R**2`` and has moment of inertia ``m R**2 / 2``), gravity ``(gravity_x,
    gravity_y)`` (length / s**2), and x periodicity: ``period > 0`` wraps x into
    ``[period_x0, period_x0 + period)`` (0: not periodic)."""

    density: float
    gravity_x: float
    gravity_y: float
    period_x0: float
    period: float


@njit(cache=True, inline="always", error_model="numpy")
def grain_mass(radius: float, density: float) -> float:
    """Mass of a disc."""
    return density * math.pi * radius * radius


@njit(cache=True, inline="always", error_model="numpy")
def _zeta(restitution):
    if restitution <= 0.0:
        return 1.0
    le = math.log(restitution)
    return -le / math.sqrt(math.pi * math.pi + le * le)


@show_field_types
class Law(NamedTuple):
    """A contact law as the per-contact arithmetic takes it (see :func:`law_terms`): the normal
    and tangential stiffness ``kn, kt``, the dashpot's damping ratio ``zeta`` and ``damp = 2
    zeta sqrt(kn)`` (a pair's dashpot is ``damp sqrt(m_eff)``), the friction ``mu``, the
    rolling friction ``mu_r``, the tangential damping ``tdamp`` (relative to the normal), the
    grains' ``density`` (a neighbour's mass) and the substep ``dt`` (the dashpot's first and
    last step of contact, see :func:`_contact`)."""

    kn: float
    kt: float
    zeta: float
    damp: float
    mu: float
    mu_r: float
    tdamp: float
    density: float
    dt: float


@show_field_types
class Pair(NamedTuple):
    """Grains ``i`` and ``j`` as their contact sees them: ``(dx, dy) = x_i - x_j`` (the
    periodic image applied), radii ``ri, rj``, relative (predicted) velocity ``(vx, vy) = v_i -
    v_j``, angular velocities ``wi, wj``; ``lower``: ``i < j`` (the side that fixes the sums'
    order and the normal of coincident centres, so that both sides compute the same bits)."""

    dx: float
    dy: float
    ri: float
    rj: float
    vx: float
    vy: float
    wi: float
    wj: float
    lower: bool


@show_field_types
class WallPair(NamedTuple):
    """A grain and the world as their contact sees them: the world's distance ``d`` at the
    grain's centre, its gradient ``(gx, gy)`` and the wall's normal speed ``vn`` (along ``grad
    d``; 0 for a static world); the grain's radius ``r``, (predicted) velocity ``(vx, vy)`` and
    angular velocity ``w``."""

    d: float
    gx: float
    gy: float
    vn: float
    r: float
    vx: float
    vy: float
    w: float


@show_field_types
class Grain(NamedTuple):
    """One grain's values as its elementwise pass takes them (:func:`kick_grain`): position
    ``x``, ``y``, velocity ``vx``, ``vy``, angular velocity ``omega``, radius, force ``fx``,
    ``fy`` and torque (the fields of :class:`Grains`)."""

    x: float
    y: float
    vx: float
    vy: float
    omega: float
    radius: float
    fx: float
    fy: float
    torque: float


@show_field_types
class Near(NamedTuple):
    """The grains a force pass asks the world about, ``idx`` (distinct storage slots), and the
    world there: distance ``d``, gradient ``(gx, gy)`` and the wall's normal speed ``vn``
    (arrays of ``len(idx)``)."""

    idx: np.ndarray
    d: np.ndarray
    gx: np.ndarray
    gy: np.ndarray
    vn: np.ndarray


@njit(cache=True, inline="always", error_model="numpy")
def image_shift(entry: int, period: float) -> float:
    """How far a neighbour-list entry sees its grain moved by its periodic image (see
    :mod:`fastsdf.granular.cells`): ``x_i - x_j - image_shift(entry, period)`` is the offset
    of the pair (0, ``period`` or ``-period``, exactly)."""
    image = entry >> 30  # 0: none, 1: x_j + period, 2: x_j - period
    return period * (np.float64(image & 1) - np.float64(image >> 1))


@njit(cache=True, inline="always", error_model="numpy")
def law_terms(law: Any, density: float, dt: float) -> Law:
    """The :class:`Law` of a :class:`~fastsdf.granular.ContactLaw` (its stiffness given) for
    grains of ``density`` stepped by ``dt``."""
    kn = law.stiffness
    zeta = _zeta(law.restitution)
    return Law(
        kn,
        law.tangential_stiffness * kn,
        zeta,
        2.0 * zeta * math.sqrt(kn),
        law.friction,
        law.rolling_friction,
        law.tangential_damping,
        density,
        dt,
    )


@njit(cache=True, inline="always", error_model="numpy")
def _recall(springs: np.ndarray, roll: bool) -> tuple:
    """A contact's memory from its ``springs`` (a row of the list's memory, a column of the
    world's): ``(s, m_roll)``, the tangential spring's stretch and, with ``roll``, the
    rolling torque (else 0)."""
    if roll:
        return springs[0], springs[1]
    return springs[0], 0.0


@njit(cache=True, inline="always", error_model="numpy")
def _keep(springs: np.ndarray, s: float, m_roll: float, roll: bool) -> None:
    """Store a contact's memory into its ``springs`` (see :func:`_recall`)."""
    springs[0] = s
    if roll:
        springs[1] = m_roll


@njit(cache=True, inline="always", error_model="numpy", fastmath=_FAST)
def _contact(delta, nx, ny, vrx, vry, wr, gamma_n, law):
    """Force on the first body and the tangential force, for overlap ``delta`` along the unit
    normal ``n`` (pointing to the first body), relative velocity ``vr``, ``wr = R_i w_i +
    R_j w_j`` and dashpot ``gamma_n = 2 zeta sqrt(m_eff k_n)``, under ``law`` (a
    :class:`Law`). Returns ``(fx, fy, ftx, fty)``. The tangential force is ``-gamma_t v_t``
    unless that exceeds ``mu |F_n|`` (compared squared: the common, viscous case needs no
    square root).

    The dashpot switches on at full strength the moment two grains touch, so a step that
    contains the first touch (or the last) would apply it for the whole step: a first-order
    error that changes the restitution of a strongly damped contact by several percent,
    depending on where between two steps the touch falls. A force evaluated at one instant
    acts from half a step before to half a step after it (velocity Verlet), and the grains
    touched ``delta / |v_n|`` before it, so the dashpot is scaled by the fraction of that
    step spent in contact, ``1/2 + delta / (|v_n| dt)`` when below 1, which restores second
    order (``dt = 0``: no scaling)."""
    vn = vrx * nx + vry * ny
    reach = abs(vn) * law.dt
    if reach > 2.0 * delta:
        gamma_n *= 0.5 + delta / reach
    fn = law.kn * delta - gamma_n * vn
    vtx = vrx - vn * nx + wr * ny
    vty = vry - vn * ny - wr * nx
    gamma_t = law.tdamp * gamma_n
    cap = law.mu * fn
    vt2 = vtx * vtx + vty * vty
    if gamma_t * gamma_t * vt2 <= cap * cap:
        ftx = -gamma_t * vtx
        fty = -gamma_t * vty
    else:  # sliding: Coulomb's cap (vt2 > 0 here)
        ft = abs(cap) / math.sqrt(vt2)
        ftx = -ft * vtx
        fty = -ft * vty
    return fn * nx + ftx, fn * ny + fty, ftx, fty


@njit(cache=True, inline="always", error_model="numpy", fastmath=_FAST)
def _contact_history(delta, nx, ny, vrx, vry, wr, gamma_n, law, s):
    """:func:`_contact` with a tangential spring (Cundall-Strack, LAMMPS
    ``gran/hooke/history``). ``s`` is the spring's stretch along the tangent ``t = (-n_y,
    n_x)`` (a scalar: in 2D the tangent plane is a line, so carrying the spring along ``t``
    is LAMMPS's rotation of the shear vector into the current tangent plane, magnitude kept).
    The stretch grows by the sliding ``v_t dt`` of the contact point, ``v_t = v . t - wr``;
    the tangential force is ``f_t = -(k_t s + gamma_t v_t) t``; where ``|f_t| > mu |F_n|``
    the force is scaled to the cap and the spring shortened to match it, ``s = r (s + gamma_t
    v_t / k_t) - gamma_t v_t / k_t`` with ``r = mu |F_n| / |f_t|`` (Coulomb's truncation).
    Returns ``(fx, fy, ftx, fty, s, F_n)``. ``s`` is the same seen from either grain (both
    ``t`` and the relative velocity change sign), so the two sides of a pair listed twice
    carry the same spring."""
    vn = vrx * nx + vry * ny
    reach = abs(vn) * law.dt
    if reach > 2.0 * delta:
        gamma_n *= 0.5 + delta / reach
    fn = law.kn * delta - gamma_n * vn
    tx = -ny
    ty = nx
    vts = vrx * tx + vry * ty - wr
    s += vts * law.dt
    gamma_t = law.tdamp * gamma_n
    ft = -(law.kt * s + gamma_t * vts)
    cap = abs(law.mu * fn)
    if abs(ft) > cap:
        r = cap / abs(ft)
        lag = gamma_t * vts / law.kt
        s = r * (s + lag) - lag
        ft *= r
    ftx = ft * tx
    fty = ft * ty
    return fn * nx + ftx, fn * ny + fty, ftx, fty, s, fn


@njit(cache=True, inline="always", error_model="numpy")
def _rolling_spring(m_old, kr, cap, w_rel, dt):
    """Rolling resistance on the first body, an elastic-plastic spring (model C of Ai, Chen,
    Rotter & Ooi, Powder Technology 206 (2011) 269, without its dashpot: the ``epsd2`` form
    of Wensrich & Katterfeld, Powder Technology 217 (2012) 409): the torque ``M`` grows
    against the relative rotation, ``M -= k_r (w_i - w_j) dt``, and is capped at
    ``mu_r R_eff |F_n|``. Unlike a constant torque opposing the rotation (their model A),
    it holds a grain at rest: the torque does not vanish, and flip, as the rotation stops."""
    m = m_old - kr * w_rel * dt
    if m > cap:
        m = cap
    elif m < -cap:
        m = -cap
    return m


@njit(cache=True, inline="always", error_model="numpy", fastmath=_FAST)
def _touch(delta, nx, ny, vrx, vry, wr, gamma_n, law, s, history):
    """:func:`_contact` (``history`` False: the spring ``s`` and ``F_n`` returned as 0) or
    :func:`_contact_history`, as ``(fx, fy, ftx, fty, s, F_n)``."""
    if not history:
        cfx, cfy, ftx, fty = _contact(delta, nx, ny, vrx, vry, wr, gamma_n, law)
        return cfx, cfy, ftx, fty, 0.0, 0.0
    return _contact_history(delta, nx, ny, vrx, vry, wr, gamma_n, law, s)


# -- the per-pair and per-grain arithmetic, shared by the CPU kernels below and the CUDA
# kernels of :mod:`fastsdf.granular.cuda` (numba-cuda compiles these plain ``@njit``
# functions for the device): one body, two targets.


@njit(cache=True, inline="always", error_model="numpy", fastmath=_FAST)
def pair_force(
    pair: Pair,
    mi: float,
    gamma_equal: float,
    law: Law,
    s: float,
    m_roll: float,
    history: bool,
    roll: bool,
) -> tuple:
    """The contact of grain ``i`` with grain ``j`` (a :class:`Pair`) under ``law`` (a
    :class:`Law`); ``mi`` is the mass of ``i``, ``gamma_equal = damp sqrt(mi / 2)`` the
    dashpot against an equal grain. ``history``: the tangential spring ``s`` (and, with
    ``roll``, the rolling torque ``m_roll``) is updated. Returns ``(touch, fx, fy, cross, s,
    m_roll)``: whether they overlap, the force on ``i``, ``cross = n x f_t`` (``i`` turns by
    ``m_roll - R_i cross``, ``j`` by ``-m_roll - R_j cross``) and the memory (0 out of
    contact)."""
    ri = pair.ri
    rj = pair.rj
    rsum = ri + rj
    d2 = pair.dx * pair.dx + pair.dy * pair.dy
    if d2 >= rsum * rsum:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    if d2 > 0.0:
        dist = math.sqrt(d2)
        inv = 1.0 / dist
        nx = pair.dx * inv
        ny = pair.dy * inv
    else:  # coincident centres: push apart along x, in opposite senses
        dist = 0.0
        nx = 1.0 if pair.lower else -1.0
        ny = 0.0
    if rj == ri:
        gamma_n = gamma_equal
    else:
        mj = grain_mass(rj, law.density)
        gamma_n = law.damp * math.sqrt(mi * mj / (mi + mj))
    # with history the same sum from both sides of a pair: the lower index first
    if pair.lower or not history:
        wr = ri * pair.wi + rj * pair.wj
    else:
        wr = rj * pair.wj + ri * pair.wi
    cfx, cfy, ftx, fty, s, fn = _touch(
        rsum - dist, nx, ny, pair.vx, pair.vy, wr, gamma_n, law, s, history
    )
    mr = 0.0
    if history and roll:
        r_eff = ri * rj / rsum
        mu_r = law.mu_r
        kr = 2.25 * law.kn * mu_r * mu_r * r_eff * r_eff
        mr = _rolling_spring(m_roll, kr, mu_r * r_eff * abs(fn), pair.wi - pair.wj, law.dt)
    return True, cfx, cfy, nx * fty - ny * ftx, s, mr


@njit(cache=True, inline="always", error_model="numpy")
def wall_force(
    wall: WallPair, law: Law, s: float, m_roll: float, history: bool, roll: bool
) -> tuple:
    """The world's contact on a grain (a :class:`WallPair`) under ``law``; memory as in
    :func:`pair_force` (``R_eff = R_i``). Returns ``(touch, fx, fy, torque, s, m_roll)``; no
    touch (memory 0) where the gradient is zero or not finite."""
    ri = wall.r
    delta = ri - wall.d
    gn = math.sqrt(wall.gx * wall.gx + wall.gy * wall.gy)
    if not (delta > 0.0 and gn > 0.0 and math.isfinite(gn)):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0
    nx = wall.gx / gn
    ny = wall.gy / gn
    mi = grain_mass(ri, law.density)
    cfx, cfy, ftx, fty, s, fn = _touch(
        delta,
        nx,
        ny,
        wall.vx - wall.vn * nx,
        wall.vy - wall.vn * ny,
        ri * wall.w,
        2.0 * law.zeta * math.sqrt(mi * law.kn),
        law,
        s,
        history,
    )
    if not history:
        return True, cfx, cfy, -(ri * (nx * fty - ny * ftx)), 0.0, 0.0
    mr = 0.0
    if roll:
        mu_r = law.mu_r
        kr = 2.25 * law.kn * mu_r * mu_r * ri * ri
        mr = _rolling_spring(m_roll, kr, mu_r * ri * abs(fn), wall.w, law.dt)
    return True, cfx, cfy, mr - ri * (nx * fty - ny * ftx), s, mr


@njit(cache=True, inline="always", error_model="numpy", fastmath=_FAST)
def half_kick(
    vx: float,
    vy: float,
    w: float,
    r: float,
    fx: float,
    fy: float,
    tq: float,
    dt_half: float,
    density: float,
) -> tuple:
    """A grain's velocities after half a step of its force ``(fx, fy)`` and torque ``tq``
    (the start of a force pass, see :func:`pair_forces`)."""
    m = grain_mass(r, density)
    a = dt_half / m
    return vx + fx * a, vy + fy * a, w + tq * a * 2.0 / (r * r)


@njit(cache=True, inline="always", error_model="numpy")
def kick_grain(grain: Grain, dt_kick: float, dt: float, density: float) -> tuple:
    """One grain's elementwise pass (see :func:`kick_drift`): ``(x, y, vx, vy, w, px, py,
    pw)``, the drifted position, the completed velocities and the predicted ones."""
    r = grain.radius
    m = grain_mass(r, density)
    inv_m = 1.0 / m
    ax = grain.fx * inv_m
    ay = grain.fy * inv_m
    alpha = grain.torque * (2.0 * inv_m) / (r * r)
    vx = grain.vx + ax * dt_kick
    vy = grain.vy + ay * dt_kick
    w = grain.omega + alpha * dt_kick
    return (
        grain.x + (vx + 0.5 * ax * dt) * dt,
        grain.y + (vy + 0.5 * ay * dt) * dt,
        vx,
        vy,
        w,
        vx + ax * dt,
        vy + ay * dt,
        w + alpha * dt,
    )


@njit(cache=True, error_model="numpy", fastmath=_FAST)
def _start_chunk(g: Grains, lo: int, hi: int, law: Law, bulk: Bulk) -> None:
    """The start of a force pass for grains ``lo:hi`` (see :func:`pair_forces`): their
    velocities half-kicked by their previous force, their forces reset to gravity."""
    for i in range(lo, hi):
        ri = g.radius[i]
        mi = grain_mass(ri, law.density)
        g.vx[i], g.vy[i], g.omega[i] = half_kick(
            g.vx[i], g.vy[i], g.omega[i], ri, g.fx[i], g.fy[i], g.torque[i], 0.5 * law.dt,
            law.density,
        )  # fmt: skip
        g.fx[i] = mi * bulk.gravity_x
        g.fy[i] = mi * bulk.gravity_y
        g.torque[i] = 0.0


# (The predicted velocities of grain i are read in the loop over its neighbours, as they
# always were: which product of a sum becomes a fused multiply-add follows from what the
# compiler hoists out of the loop, so reading them once before it changes the rounding.)
@njit(cache=True, error_model="numpy", fastmath=_FAST)
def _chunk_pairs(
    g: Grains,
    lo: int,
    hi: int,
    nbr_start: np.ndarray,
    nbr: np.ndarray,
    memory: np.ndarray | None,
    law: Law,
    period: float,
) -> None:
    """The contacts of grains ``lo:hi`` with their listed neighbours (see
    :func:`pair_forces`), added to their forces, and to a neighbour's in the same chunk."""
    history = memory is not None
    roll = law.mu_r > 0.0
    x = g.x
    y = g.y
    for i in range(lo, hi):
        xi = x[i]
        yi = y[i]
        ri = g.radius[i]
        mi = grain_mass(ri, law.density)
        gamma_equal = law.damp * math.sqrt(0.5 * mi)  # the dashpot against an equal grain
        fx = 0.0
        fy = 0.0
        tq = 0.0
        for k in range(nbr_start[i], nbr_start[i + 1]):
            entry = nbr[k]
            j = entry & 0x3FFFFFFF
            pair = Pair(
                xi - x[j] - image_shift(entry, period), yi - y[j], ri, g.radius[j],
                g.px[i] - g.px[j], g.py[i] - g.py[j], g.pomega[i], g.pomega[j], i < j,
            )  # fmt: skip
            s, mr = _recall(memory[k], roll) if memory is not None else (0.0, 0.0)
            touch, cfx, cfy, cross, s, mr = pair_force(
                pair, mi, gamma_equal, law, s, mr, history, roll
            )
            if memory is not None:
                _keep(memory[k], s, mr, roll)
            if touch:
                fx += cfx
                fy += cfy
                tq += mr - ri * cross
                if j >= lo and j < hi:  # same chunk: Newton's third law here
                    g.fx[j] -= cfx
                    g.fy[j] -= cfy
                    g.torque[j] -= mr + g.radius[j] * cross
        g.fx[i] += fx
        g.fy[i] += fy
        g.torque[i] += tq


@njit(cache=True, parallel=True, error_model="numpy", fastmath=_FAST)
def pair_forces(
    g: Grains,
    nbr_start: np.ndarray,
    nbr: np.ndarray,
    memory: np.ndarray | None,
    chunks: int,
    law: Any,
    bulk: Bulk,
    dt: float,
) -> None:
    """The force pass of a substep, over ``chunks`` contiguous chunks of grains in parallel
    (the chunks the list was built for, see :func:`fastsdf.granular.cells.build_verlet`).
    Each chunk first half-kicks its grains' velocities with their previous force (``v +=
    F_old dt / 2m``) and resets their forces to gravity; then for each listed pair at the
    drifted positions and predicted velocities ``px, py, pomega`` it adds the contact force to
    its grain and, when the neighbour is in the same chunk, the opposite force to the
    neighbour. A chunk writes only its own grains and reads only positions and predicted
    velocities, which nothing writes here: no races. ``law`` is the
    :class:`~fastsdf.granular.ContactLaw`, ``dt`` the substep (for the dashpot's first and
    last step of contact, see :func:`_contact`).

    ``memory=None``: history-free (:func:`_contact`). Otherwise the contacts' memory
    (``law.history``): for list entry ``k``, ``memory[k, 0]`` is the tangential spring's
    stretch (see :func:`_contact_history`), and, when ``law.rolling_friction > 0``,
    ``memory[k, 1]`` the rolling spring's torque on the entry's grain
    (:func:`_rolling_spring`, ``k_r = 2.25 k_n mu_r**2 R_eff**2``). Both are set to 0 where
    the pair is not in contact (as LAMMPS forgets a history when the grains part). A pair
    listed at both grains (across chunks) updates both entries alike (the stretch is the same
    number from both sides, the torque its negative). The choice is made at compile time:
    numba prunes the ``memory is None`` branches for the type of ``memory``, so each variant
    compiles to its own loop."""
    terms = law_terms(law, bulk.density, dt)
    n = g.x.shape[0]
    for c in prange(chunks):
        lo = c * n // chunks
        hi = (c + 1) * n // chunks
        _start_chunk(g, lo, hi, terms, bulk)
        _chunk_pairs(g, lo, hi, nbr_start, nbr, memory, terms, bulk.period)


@njit(cache=True, error_model="numpy")
def _chunk_walls(
    g: Grains, near: Near, lo: int, hi: int, memory: np.ndarray | None, law: Law, push: np.ndarray
) -> None:
    """The world's contacts with the grains ``near.idx[lo:hi]`` (see :func:`wall_forces`),
    added to their forces; the force on each into ``push[:, k]`` (0 without contact)."""
    history = memory is not None
    roll = law.mu_r > 0.0
    for k in range(lo, hi):
        i = near.idx[k]
        wall = WallPair(near.d[k], near.gx[k], near.gy[k], near.vn[k], g.radius[i], g.px[i],
                        g.py[i], g.pomega[i])  # fmt: skip
        s, mr = _recall(memory[:, i], roll) if memory is not None else (0.0, 0.0)
        touch, cfx, cfy, tq, s, mr = wall_force(wall, law, s, mr, history, roll)
        if memory is not None:
            _keep(memory[:, i], s, mr, roll)
        push[0, k] = cfx
        push[1, k] = cfy
        if touch:
            g.fx[i] += cfx
            g.fy[i] += cfy
            g.torque[i] += tq


@njit(cache=True, inline="always", error_model="numpy")
def _total_push(push: np.ndarray) -> tuple:
    """The sum of ``push[0]`` and of ``push[1]``, in order (the same bits on any threads)."""
    sx = 0.0
    sy = 0.0
    for k in range(push.shape[1]):
        sx += push[0, k]
        sy += push[1, k]
    return sx, sy


@njit(cache=True, parallel=True, error_model="numpy")
def wall_forces(
    g: Grains, near: Near, memory: np.ndarray | None, law: Any, bulk: Bulk, dt: float
) -> tuple:
    """Add the world's contact forces to the grains ``near.idx`` (see :class:`Near`) under
    ``law`` (a :class:`~fastsdf.granular.ContactLaw`), with the predicted velocities (run it
    after :func:`pair_forces`, which resets the forces). Returns the total force the world
    exerts on the grains, ``(Fx, Fy)``, summed in the order of ``near.idx`` (the same bits on
    any number of threads). Points with a non-finite or zero gradient feel nothing.

    ``memory=None``: history-free. Otherwise (``law.history``) one tangential spring per grain
    against the world, ``memory[0, i]`` for grain ``i`` (the world is one surface: a grain
    touches it at its nearest point, along ``grad d``), and its rolling spring
    ``memory[1, i]`` when ``law.rolling_friction > 0`` (``R_eff = R_i``; the world does not
    turn), reset to 0 for a grain listed here but out of contact. Chosen at compile time, as
    in :func:`pair_forces`."""
    terms = law_terms(law, bulk.density, dt)
    m = near.idx.shape[0]
    push = np.empty((2, m))
    chunks = (m + 255) // 256
    for c in prange(chunks):
        _chunk_walls(g, near, c * m // chunks, (c + 1) * m // chunks, memory, terms, push)
    return _total_push(push)


@njit(cache=True, error_model="numpy")
def _kick_chunk(
    g: Grains,
    out: Grains,
    lo: int,
    hi: int,
    dt_kick: float,
    dt: float,
    density: float,
    x_ref: np.ndarray,
    y_ref: np.ndarray,
) -> float:
    """The elementwise pass of grains ``lo:hi`` (see :func:`kick_drift`) from ``g`` into
    ``out`` (``g`` itself, or its other buffer of positions and predicted velocities);
    returns their largest squared displacement from ``(x_ref, y_ref)``."""
    big = 0.0
    for i in range(lo, hi):
        grain = Grain(g.x[i], g.y[i], g.vx[i], g.vy[i], g.omega[i], g.radius[i], g.fx[i],
                      g.fy[i], g.torque[i])  # fmt: skip
        x, y, vx, vy, w, px, py, pw = kick_grain(grain, dt_kick, dt, density)
        out.vx[i] = vx
        out.vy[i] = vy
        out.omega[i] = w
        out.px[i] = px
        out.py[i] = py
        out.pomega[i] = pw
        out.x[i] = x
        out.y[i] = y
        ex = x - x_ref[i]
        ey = y - y_ref[i]
        big = max(big, ex * ex + ey * ey)
    return big


@njit(cache=True, parallel=True, error_model="numpy")
def kick_drift(
    g: Grains,
    dt_kick: float,
    dt: float,
    density: float,
    x_ref: np.ndarray,
    y_ref: np.ndarray,
    chunk_max: np.ndarray,
) -> None:
    """The elementwise pass of a velocity-Verlet substep of length ``dt``, from force ``F``:
    complete the velocity, ``v += F/m dt_kick`` (``dt / 2`` after a force pass, 0 at the
    start of a frame when ``v`` is already synchronized), drift ``x += (v + F/m dt/2) dt``, and
    predict the velocity at the end of the substep, ``p = v + F/m dt``, for the dashpots of the
    next force pass (a second-order estimate: the half-step velocity LAMMPS uses there lags by
    half a step, which biases the restitution of strongly damped contacts by several percent).
    ``dt = 0`` only completes the kick. Writes into ``chunk_max[c]`` the largest squared
    displacement from ``(x_ref, y_ref)`` among the grains of chunk ``c`` (the
    ``len(chunk_max)`` chunks split the grains evenly; per-chunk slots, no shared writes)."""
    n = g.x.shape[0]
    chunks = chunk_max.shape[0]
    for c in prange(chunks):
        lo = c * n // chunks
        hi = (c + 1) * n // chunks
        chunk_max[c] = _kick_chunk(g, g, lo, hi, dt_kick, dt, density, x_ref, y_ref)


@show_field_types
class Substep(NamedTuple):
    """What a fused substep (:func:`substep_pass`) takes beside the grains, the list and the
    world: the substep ``dt``, the kick ``dt_kick`` that completes the velocities after the
    force pass (``dt / 2``) and the drift ``dt_next`` of the next substep (``dt``; 0 at the
    end of a frame: the velocities completed only), the number of ``chunks``, the float32
    reference positions ``x_ref, y_ref`` of the skin test, and what the pass writes:
    ``chunk_max`` (per chunk, the largest squared displacement from the references) and
    ``push`` (2, len(near.idx)), the world's force on each grain it was asked about."""

    dt: float
    dt_kick: float
    dt_next: float
    chunks: int
    x_ref: np.ndarray
    y_ref: np.ndarray
    chunk_max: np.ndarray
    push: np.ndarray


@njit(cache=True, parallel=True, error_model="numpy")
def substep_pass(
    g: Grains,
    out: Grains,
    nbr_start: np.ndarray,
    nbr: np.ndarray,
    memory: np.ndarray | None,
    near: Near,
    wall_memory: np.ndarray | None,
    laws: tuple,
    bulk: Bulk,
    step: Substep,
) -> tuple:
    """A substep's force pass and the next substep's elementwise pass in one parallel loop
    over the chunks of grains (see :class:`Substep`): each chunk runs :func:`pair_forces`'s
    work on its grains, then :func:`wall_forces`'s on those of them in ``near.idx`` (sorted),
    then :func:`kick_drift`'s from ``g`` into ``out``. ``out`` shares ``g``'s velocities,
    radii and forces, and holds its own positions and predicted velocities: a chunk drifts its
    grains while the others still read the positions of the force pass (double buffering),
    so one parallel region makes a substep, and every grain sees the same arithmetic in the
    same order as through the three passes. ``laws``: the grain-grain and grain-world
    :class:`~fastsdf.granular.ContactLaw`; ``memory`` and ``wall_memory`` as in
    :func:`pair_forces` and :func:`wall_forces`. Returns the world's total force, as
    :func:`wall_forces`."""
    terms = law_terms(laws[0], bulk.density, step.dt)
    wall_terms = law_terms(laws[1], bulk.density, step.dt)
    n = g.x.shape[0]
    chunks = step.chunks
    chunk_max = step.chunk_max
    push = step.push
    for c in prange(chunks):
        lo = c * n // chunks
        hi = (c + 1) * n // chunks
        _start_chunk(g, lo, hi, terms, bulk)
        _chunk_pairs(g, lo, hi, nbr_start, nbr, memory, terms, bulk.period)
        k_lo = np.searchsorted(near.idx, lo)
        k_hi = np.searchsorted(near.idx, hi)
        _chunk_walls(g, near, k_lo, k_hi, wall_memory, wall_terms, push)
        chunk_max[c] = _kick_chunk(
            g, out, lo, hi, step.dt_kick, step.dt_next, bulk.density, step.x_ref, step.y_ref
        )
    return _total_push(push)


@njit(cache=True, inline="always", error_model="numpy")
def _rolling_energy(torque, kn, mu_r, r_eff):
    """Energy ``M**2 / (2 k_r)`` of a rolling spring holding the torque ``M``, with ``k_r =
    2.25 k_n mu_r**2 R_eff**2`` (see :func:`_rolling_spring`: its torque grows by ``-k_r``
    times the relative rotation, and the cap only truncates it)."""
    return 0.5 * torque * torque / (2.25 * kn * mu_r * mu_r * r_eff * r_eff)


@njit(cache=True, inline="always", error_model="numpy")
def _springs_held(law, springs, r_eff):
    """``(tangential, rolling)``: the energy held by one contact's springs under ``law`` (a
    :class:`~fastsdf.granular.ContactLaw`), ``k_t s**2 / 2`` of the stretch ``springs[0]``
    and, with rolling friction, :func:`_rolling_energy` of the torque ``springs[1]``."""
    kn = law.stiffness
    s = springs[0]
    tangential = 0.5 * (law.tangential_stiffness * kn) * s * s
    mu_r = law.rolling_friction
    if mu_r > 0.0:
        return tangential, _rolling_energy(springs[1], kn, mu_r, r_eff)
    return tangential, 0.0


@njit(cache=True, error_model="numpy")
def pair_energy(
    g: Grains,
    nbr_start: np.ndarray,
    nbr: np.ndarray,
    memory: np.ndarray | None,
    law: Any,
    bulk: Bulk,
) -> tuple:
    """Elastic energy stored in the grain-grain contacts, each pair once: ``(normal,
    tangential, rolling, contacts)``, the normal springs ``k_n delta**2 / 2`` at the current
    positions, the tangential springs ``k_t s**2 / 2`` and the rolling springs ``M**2 / (2
    k_r)`` held in ``memory`` (the list's, as :func:`pair_forces` left it; ``None``: no
    history, no springs but the normal ones), and the number of pairs in overlap. A spring
    truncated by Coulomb's cap holds what is left after the truncation: the slip dissipated
    the rest."""
    en = 0.0
    et = 0.0
    er = 0.0
    count = 0
    kn = law.stiffness
    period = bulk.period
    for i in range(g.x.shape[0]):  # serial: sums in one order, the same bits on any threads
        for k in range(nbr_start[i], nbr_start[i + 1]):
            entry = nbr[k]
            j = entry & 0x3FFFFFFF
            if j <= i:  # a pair listed at both grains is counted at the lower index
                continue
            dx = g.x[i] - g.x[j] - image_shift(entry, period)
            dy = g.y[i] - g.y[j]
            rsum = g.radius[i] + g.radius[j]
            delta = rsum - math.sqrt(dx * dx + dy * dy)
            if delta > 0.0:
                en += 0.5 * kn * delta * delta
                count += 1
            if memory is not None:
                held, rolling = _springs_held(law, memory[k], g.radius[i] * g.radius[j] / rsum)
                et += held
                er += rolling
    return en, et, er, count


@njit(cache=True, error_model="numpy")
def wall_energy(
    g: Grains, idx: np.ndarray, d: np.ndarray, memory: np.ndarray | None, law: Any
) -> tuple:
    """Elastic energy stored in the grain-wall contacts of the grains ``idx`` at distances
    ``d``: ``(normal, tangential, rolling, contacts)`` as in :func:`pair_energy`, the springs
    read from the world's ``memory`` (one column per grain, as :func:`wall_forces` left it;
    ``None``: no history)."""
    en = 0.0
    et = 0.0
    er = 0.0
    count = 0
    kn = law.stiffness
    for k in range(idx.shape[0]):
        i = idx[k]
        delta = g.radius[i] - d[k]
        if delta > 0.0:
            en += 0.5 * kn * delta * delta
            count += 1
        if memory is not None:
            held, rolling = _springs_held(law, memory[:, i], g.radius[i])
            et += held
            er += rolling
    return en, et, er, count


@njit(cache=True, error_model="numpy")
def kinetic_energy(g: Grains, bulk: Bulk) -> tuple:
    """Translational and rotational kinetic energy and the gravitational potential energy
    ``-m g . x`` of all grains: ``(translational, rotational, potential)``."""
    et = 0.0
    er = 0.0
    ep = 0.0
    for i in range(g.x.shape[0]):  # serial: sums in one order, the same bits on any threads
        r = g.radius[i]
        m = grain_mass(r, bulk.density)
        et += 0.5 * m * (g.vx[i] * g.vx[i] + g.vy[i] * g.vy[i])
        er += 0.25 * m * r * r * g.omega[i] * g.omega[i]
        ep -= m * (bulk.gravity_x * g.x[i] + bulk.gravity_y * g.y[i])
    return et, er, ep
