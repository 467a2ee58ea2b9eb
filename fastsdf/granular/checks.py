"""Checks of a granular simulation's starting state: grains that overlap each other deeply, or
start inside the world, are pushed apart at once by their stiff springs and thrown out at
speed; :func:`warn_starting_state` warns about them once, naming how many and the worst.

The pairs tested are the engine's neighbour list (every pair closer than the cutoff, found by
its cell list: no O(n**2) search), the world is asked once about every grain.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from fastsdf.granular.cells import INDEX_MASK
from fastsdf.introspect import show_field_types
from fastsdf.notice import warn_caller

__all__ = [
    "OVERLAP_TOLERANCE",
    "StartingStateWarning",
    "Overlaps",
    "grain_overlaps",
    "wall_overlaps",
    "warn_starting_state",
]

#: Overlaps up to this fraction of a radius (of the smaller grain of a pair) pass: a pile
#: packed by hand, or a state saved from a run, overlaps a little.
OVERLAP_TOLERANCE = 0.1


class StartingStateWarning(UserWarning):
    """Grains start overlapping each other, or the world, by more than
    :data:`OVERLAP_TOLERANCE` of a radius."""


@show_field_types
class Overlaps(NamedTuple):
    """Grains overlapping by more than the tolerance: how many ``grains`` take part, and the
    worst case (grain ``worst``, with grain ``other`` for a pair or -1 against the world),
    its overlap ``depth`` (length) and the ``radius`` it is measured against."""

    grains: int
    worst: int
    other: int
    depth: float
    radius: float


def grain_overlaps(
    x: np.ndarray,
    y: np.ndarray,
    radius: np.ndarray,
    pairs: np.ndarray,
    period: float = 0.0,
    tolerance: float = OVERLAP_TOLERANCE,
) -> Overlaps | None:
    """The pairs among ``pairs`` ((m, 2) indices into the grains' ``x``, ``y`` and ``radius``)
    overlapping by more than ``tolerance`` (< 1) times the smaller radius, or None;
    ``period > 0``: x is periodic with that period."""
    i, j = pairs[:, 0], pairs[:, 1]
    ri, rj = radius[i], radius[j]
    dx = x[i] - x[j]
    if period > 0:
        dx -= period * np.rint(dx / period)
    dy = y[i] - y[j]
    smaller = np.minimum(ri, rj)
    cut = ri + rj - tolerance * smaller  # (> 0) closer than this: too deep
    bad = np.flatnonzero(dx * dx + dy * dy < cut * cut)
    if bad.shape[0] == 0:
        return None
    depth = ri[bad] + rj[bad] - np.hypot(dx[bad], dy[bad])
    k = int(np.argmax(depth / smaller[bad]))
    grains = np.unique(pairs[bad]).shape[0]
    at = bad[k]
    return Overlaps(grains, int(i[at]), int(j[at]), float(depth[k]), float(smaller[at]))


def wall_overlaps(
    distance: np.ndarray, radius: np.ndarray, tolerance: float = OVERLAP_TOLERANCE
) -> Overlaps | None:
    """The grains whose centres lie at signed distances ``distance`` from the world (the
    SDF's values, negative inside) less than ``(1 - tolerance)`` times their radius: they
    overlap a wall by more than ``tolerance`` of their radius (or lie inside it); or None."""
    depth = radius - distance
    share = depth / radius
    bad = share > tolerance  # (NaN distances, outside a grid's bounds, pass)
    if not bad.any():
        return None
    k = int(np.argmax(np.where(bad, share, -np.inf)))
    return Overlaps(int(bad.sum()), k, -1, float(depth[k]), float(radius[k]))


def _count(n: int, one: str, many: str) -> str:
    return f"{n} {one}" if n == 1 else f"{n} {many}"


def _grains_said(found: Overlaps) -> str:
    share = 100.0 * found.depth / found.radius
    return (
        f"{_count(found.grains, 'grain overlaps', 'grains overlap')} another by more than "
        f"{100 * OVERLAP_TOLERANCE:g}% of the smaller radius (the worst: grains {found.worst} "
        f"and {found.other}, by {found.depth:.4g}, {share:.0f}% of radius {found.radius:.4g}): "
        f"spread them out, their centres at least the sum of their radii apart"
    )


def _walls_said(found: Overlaps) -> str:
    distance = found.radius - found.depth
    where = f"{-distance:.4g} inside the world" if distance < 0 else f"{distance:.4g} from it"
    return (
        f"{_count(found.grains, 'grain starts', 'grains start')} inside the world or "
        f"overlapping it by more than {100 * OVERLAP_TOLERANCE:g}% of the radius (the worst: "
        f"grain {found.worst}, its centre {where}, radius {found.radius:.4g}): give positions "
        f"outside the world, where its SDF is at least the grain's radius"
    )


def _listed(sim: Any) -> tuple[np.ndarray, ...]:
    """The grains' x, y and radii, the pairs of the engine's neighbour list (each once)
    and the grains' given numbers: in the CPU engine's storage order, read from its list as
    it is (sorting the pairs costs more than the check), else in the given order."""
    start = getattr(sim, "_nbr_start", None)
    nbr = getattr(sim, "_nbr", None)
    if isinstance(nbr, np.ndarray) and isinstance(start, np.ndarray):
        g = sim.grains
        n = start.shape[0] - 1
        i = np.repeat(np.arange(n), np.diff(start))
        j = (nbr[: start[n]] & INDEX_MASK).astype(np.int64)
        keep = i < j
        pairs = np.stack([i[keep], j[keep]], axis=1)
        return g.x, g.y, g.radius, pairs, sim.ids
    xy = sim.positions
    radius = sim.radius
    return xy[:, 0].copy(), xy[:, 1].copy(), radius, sim.neighbour_pairs(), np.arange(len(radius))


def warn_starting_state(sim: Any) -> None:
    """One :class:`StartingStateWarning` (attributed to the user's line) if ``sim``'s grains
    (a :class:`~fastsdf.granular.GranularSimulation`, either device) overlap each other or
    the world by more than :data:`OVERLAP_TOLERANCE` of a radius; grains are numbered as
    given."""
    x, y, radius, pairs, ids = _listed(sim)
    among = grain_overlaps(x, y, radius, pairs, float(sim.bulk.period))
    if among is not None:
        among = among._replace(worst=int(ids[among.worst]), other=int(ids[among.other]))
    walls = None
    if sim.world is not None:
        at = {"t": sim.time} if sim.moving else {}
        distance = sim.world(x, y, **at)
        walls = wall_overlaps(np.asarray(distance, dtype=np.float64).reshape(-1), radius)
        if walls is not None:
            walls = walls._replace(worst=int(ids[walls.worst]))
    said = [
        *([_grains_said(among)] if among is not None else []),
        *([_walls_said(walls)] if walls is not None else []),
    ]
    if said:
        warn_caller(
            "; ".join(said) + ". Their springs would throw them apart at speed at the start.",
            StartingStateWarning,
        )
