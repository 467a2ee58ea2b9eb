"""The scene block of the test world: what a world provides to the step kernels (see
:mod:`fastsdf.particles.kernels`), written by hand for a union of solid half-planes and discs.

The kernel modules import these names when used directly (``tests/test_step.py``); a generated
kernel module has a block of its own in their place (:mod:`fastsdf.particles.world`)."""

import math

from numba import njit

__all__ = ["MOVING", "USE_FORCE", "FORCE_AHEAD", "GRID_SIMD", "GRID_EXACT"]

# The test world: a union of solid half-planes and discs.
# data = (planes, discs): planes (k, 3) rows (nx, ny, c), unit normal n, solid where n.p <= c;
# discs (j, 3) rows (cx, cy, R). d = min over all of (n.p - c) and (|p - c| - R).
_CACHE = True
USE_FORCE = False
FORCE_AHEAD = False
# Not a grid world: the block kernel (the simd variant) does not apply.
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
