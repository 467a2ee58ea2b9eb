"""Contact physics of one particle, written once: the collision response, conservative
advancement (the march) and the tunnelling sweep, for static and moving worlds."""

import math

from numba import njit

from fastsdf.intrinsics import select
from fastsdf.particles.kernels.config import Window
from fastsdf.particles.kernels.constants import (
    CONTACT_TOL,
    MAX_BOUNCES,
    MAX_MARCH,
    MIN_STEP,
    TRACE_FRACTION,
)
from fastsdf.particles.kernels.scene import _CACHE, MOVING, _query_t

__all__ = ["march", "sweep"]

# >>> KERNEL BODY (from here on, copied into every generated kernel module) >>>

# ---------------------------------------------------------------------------------------------
# Contact: response, march, sweep.


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _respond(x, y, vx, vy, s, grad, cr, cf, always):
    """Collision response of a disc whose surface distance is ``s = d - r <= 0`` (House and
    Keyser): ``x -= (1 + cr) s n`` and, when approaching (``v . n < 0``) or ``always``,
    ``v = -cr v_n + (1 - cf) v_t``, with ``n = grad / |grad|`` (``grad``: ``(dd/dx, dd/dy,
    dd/dt)`` of the world at the disc, ``dd/dt`` 0 for a static world). A zero or non-finite
    gradient (a ridge of a grid) gives no direction: the state is returned unchanged.

    Written with selects rather than branches (every operand is safe to compute), so that the
    block step runs it for several particles in the lanes of one vector instruction.

    A moving wall (``gt = dd/dt``) has normal speed ``w = -gt / |grad|``: the relative normal
    velocity ``v_n - w`` is what approaches and reflects (``v_n -> w - cr (v_n - w)``).
    """
    gx, gy, gt = grad
    gl2 = gx * gx + gy * gy
    ok = (gl2 > 0.0) & (gl2 < math.inf)
    inv = select(ok, 1.0 / math.sqrt(gl2), 0.0)
    nx = select(ok, gx * inv, 0.0)
    ny = select(ok, gy * inv, 0.0)
    k = (1.0 + cr) * s
    x -= k * nx
    y -= k * ny
    vn = vx * nx + vy * ny
    wn = -gt * inv  # the wall's normal speed (0 for a static world)
    vr = vn - wn
    resp = ok & ((vr < 0.0) | always)
    w = select(resp, 1.0 - cf, 1.0)  # tangential factor
    c = select(resp, cr, -1.0)  # relative normal velocity becomes -c vr (same for c = -1)
    vx = w * (vx - vn * nx) + (wn - c * vr) * nx
    vy = w * (vy - vn * ny) + (wn - c * vr) * ny
    return x, y, vx, vy


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def march(data, x0, y0, dx, dy, r, lip, window):
    """Conservative advancement of a disc of radius r from (x0, y0) along (dx, dy), in
    space-time (:class:`.config.Window`): time runs from ``ts`` over ``tdt`` meanwhile, and
    ``wd = W tdt`` bounds how far the surfaces move (a static world, ``MOVING`` False, is the
    case ``wd = 0``, ``dd/dt = 0``, specialised when the kernel compiles).

    The parts of the segment with parameter below ``t0`` and above ``t1`` are already known
    to be free. Along the path the distance changes at most at the rate ``lip |D| + wd`` per
    unit of the parameter, which sets the sphere-tracing step; a contact approaches when ``d``
    decreases along the path (``grad . D + dd/dt tdt < 0``). Returns (t, hit, s, nx, ny, wn):
    hit = 1 for an approaching contact at parameter t (surface distance s <= tolerance, unit
    normal n, the wall's normal speed ``wn`` there), 0 for a free path to t = 1, 2 when the
    iteration limit stopped it at t (a safe point, short of any contact).
    """
    t, t_free, ts, tdt, wd = window
    length = math.sqrt(dx * dx + dy * dy)
    if MOVING:
        length += wd / lip  # distance-equivalent length of the step
    inv_len = 1.0 / length
    tol = CONTACT_TOL * length
    # A step no longer than TRACE_FRACTION * r cannot carry the disc across a wall unseen (the
    # same reason short steps skip this check), so the march never needs smaller steps.
    short = TRACE_FRACTION * r * inv_len  # in units of t
    far = inv_len / lip  # t per unit of surface distance
    leave = max(short, MIN_STEP)
    if t >= t_free:
        return 1.0, 0, 0.0, 0.0, 0.0, 0.0
    for _ in range(MAX_MARCH):
        d, gx, gy, gt = _query_t(data, x0 + t * dx, y0 + t * dy, ts + t * tdt)
        s = d - r
        if s > tol:
            t += max(s * far, short)  # sphere tracing: free within s / L
            if t >= t_free:
                return 1.0, 0, 0.0, 0.0, 0.0, 0.0
            continue
        approach = gx * dx + gy * dy
        if MOVING:
            approach += gt * tdt
        if approach < 0.0:  # in contact and approaching
            gl = math.sqrt(gx * gx + gy * gy)
            # (a zero gradient never approaches a static world)
            if gl < math.inf and (gl > 0.0 or not MOVING):
                return t, 1, s, gx / gl, gy / gl, -gt / gl if MOVING else 0.0
            t += leave
        elif s == s:
            # touching but leaving (or sliding along) the surface: move on by a short step
            t += leave
        else:
            return 1.0, 0, 0.0, 0.0, 0.0, 0.0  # non-finite SDF: nothing to trace against
        if t >= t_free:
            return 1.0, 0, 0.0, 0.0, 0.0, 0.0
    return t, 2, 0.0, 0.0, 0.0, 0.0


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def sweep(data, motion, disc, lip, always, window):
    """Tunnelling check of one step: sweep the disc ``disc`` (:class:`.config.Disc`) from
    (x, y) along (dx, dy) with velocity (vx, vy) (``motion``, :class:`.config.Motion`) while
    time runs from ``ts`` over ``tdt`` (``window``, :class:`.config.Window`, see
    :func:`march`; ``wd``: how far the walls move meanwhile).

    ``t0``, ``t1``: the step's parameters below and above which it is already known to be
    free (from the start's and the end's distance budgets). At a contact the remaining
    displacement reflects off the wall where it will be, and the velocity relative to the
    wall reflects.

    Returns the new start point and remaining displacement, the velocity, and whether a
    contact was met (then the displacement and velocity have been reflected) or the end point
    moved for another reason.
    """
    x, y, dx, dy, vx, vy = motion
    r, cr, cf = disc
    t0, t1, ts, tdt, wd = window
    bounced = False
    for b in range(MAX_BOUNCES):
        t, hit, s, nx, ny, wn = march(data, x, y, dx, dy, r, lip, Window(t0, t1, ts, tdt, wd))
        t0 = 0.0
        t1 = 1.0
        if hit == 0:
            break
        x += t * dx
        y += t * dy
        if MOVING:
            ts += t * tdt
            tdt *= 1.0 - t
            wd *= 1.0 - t
        if hit == 2:  # iteration limit: stay at the last safe point
            return x, y, 0.0, 0.0, vx, vy, True
        rx = (1.0 - t) * dx
        ry = (1.0 - t) * dy
        # end point's depth below the tangent line at contact (moved with the wall until the
        # end of the step)
        pen = s + rx * nx + ry * ny
        if MOVING:
            pen -= wn * tdt
        if pen < 0.0:
            rx -= (1.0 + cr) * pen * nx
            ry -= (1.0 + cr) * pen * ny
        vn = vx * nx + vy * ny
        # the relative normal velocity vn - wn reflects (a static wall: wn = 0, written apart
        # so that the static step keeps its operations bit for bit)
        if MOVING:
            vr = vn - wn
            if vr < 0.0 or (always and not bounced):
                f = 1.0 - cf
                vx = f * (vx - vn * nx) + (wn - cr * vr) * nx
                vy = f * (vy - vn * ny) + (wn - cr * vr) * ny
        elif vn < 0.0 or (always and not bounced):
            f = 1.0 - cf
            vx = f * (vx - vn * nx) - cr * vn * nx
            vy = f * (vy - vn * ny) - cr * vn * ny
        bounced = True
        if b == MAX_BOUNCES - 1:  # out of bounces: stop at this contact
            return x, y, 0.0, 0.0, vx, vy, bounced
        dx = rx
        dy = ry
        short = TRACE_FRACTION * r
        # A short rest needs no sweep (see the step's test). The rest leaves the contact (or
        # slides along it): the march's first step from the contact point is a short one, so
        # take it without querying the contact again.
        if MOVING:
            rr = math.sqrt(dx * dx + dy * dy) + wd / lip
            if rr <= short:
                break
            if rx * nx + ry * ny - wn * tdt >= 0.0:
                t0 = max(short, MIN_STEP * rr) / rr
        else:
            rr = dx * dx + dy * dy
            if rr <= short * short:
                break
            length = math.sqrt(rr)
            if rx * nx + ry * ny >= 0.0:
                t0 = max(short, MIN_STEP * length) / length
    return x, y, dx, dy, vx, vy, bounced


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _march(data, x0, y0, dx, dy, r, lip, t, t_free):
    """:func:`march` in a world held still: returns (t, hit, s, nx, ny)."""
    return march(data, x0, y0, dx, dy, r, lip, Window(t, t_free, 0.0, 0.0, 0.0))[:5]


@njit(cache=_CACHE, nogil=True, error_model="numpy", inline="always")
def _sweep(data, motion, disc, lip, always, t0, t1):
    """:func:`sweep` in a world held still."""
    return sweep(data, motion, disc, lip, always, Window(t0, t1, 0.0, 0.0, 0.0))


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
