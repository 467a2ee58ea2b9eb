"""Measurements on a pile of grains: the angle of repose of a heap."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

__all__ = ["ReposeAngle", "repose_angle"]


class ReposeAngle(NamedTuple):
    """The slope of a heap's flanks: ``left`` and ``right`` in degrees (NaN where a flank has
    fewer than 3 surface points in the band), and each flank's fitted line ``(slope,
    intercept)`` of the surface height ``y = slope x + intercept``."""

    left: float
    right: float
    lines: tuple[tuple[float, float], tuple[float, float]]

    @property
    def mean(self) -> float:
        """The mean of the flanks that were measured (NaN where neither was)."""
        finite = [a for a in (self.left, self.right) if math.isfinite(a)]
        return sum(finite) / len(finite) if finite else math.nan


def repose_angle(
    positions: np.ndarray,
    radius: float | np.ndarray,
    *,
    floor: float | None = None,
    bin_width: float | None = None,
) -> ReposeAngle:
    """The angle of repose of a heap of discs (gravity along -y), by a straight-line fit to
    each outer flank of its surface.

    The surface is the top (``y + R``) of the highest grain in each bin ``bin_width`` wide
    (default: the mean diameter). The heap's height runs from ``floor`` (default: the lowest
    point of the surface) to its highest point; the left flank is the surface left of the
    first bin that reaches 80% of that height, the right flank the surface right of the last
    such bin (so a heap with two summits is measured on its outer flanks). Each flank's points
    between 20% and 80% of the height get a least-squares line; its angle is ``atan |slope|``.
    Pass only the grains of the heap (not those in flight or on other surfaces).
    """
    x = np.asarray(positions, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 2:
        raise ValueError(f"positions must have shape (n, 2), got shape {x.shape}")
    r = np.broadcast_to(np.asarray(radius, dtype=np.float64), (len(x),))
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(r)) and np.all(r >= 0)):
        raise ValueError("positions must be finite and radius finite and >= 0")
    nan = (math.nan, math.nan)
    if len(x) == 0:
        return ReposeAngle(math.nan, math.nan, (nan, nan))
    width = 2.0 * float(r.mean()) if bin_width is None else float(bin_width)
    if not (math.isfinite(width) and width > 0):
        raise ValueError(f"bin_width must be > 0 (or the grains' radius > 0), got {width!r}")
    top = x[:, 1] + r
    bins, which = np.unique(np.floor(x[:, 0] / width).astype(np.int64), return_inverse=True)
    xs = np.bincount(which, weights=x[:, 0]) / np.bincount(which)  # ascending with the bins
    hs = np.full(len(bins), -np.inf)
    np.maximum.at(hs, which, top)
    base = float(hs.min()) if floor is None else float(floor)
    height = float(hs.max()) - base
    if not height > 0:
        return ReposeAngle(math.nan, math.nan, (nan, nan))
    band = (hs > base + 0.2 * height) & (hs < base + 0.8 * height)
    summit = np.flatnonzero(hs >= base + 0.8 * height)
    index = np.arange(len(hs))
    angles: list[float] = []
    lines: list[tuple[float, float]] = []
    for side in (index < summit[0], index > summit[-1]):
        sel = band & side
        if sel.sum() < 3:
            angles.append(math.nan)
            lines.append(nan)
            continue
        slope, intercept = np.polyfit(xs[sel], hs[sel], 1)
        angles.append(math.degrees(math.atan(abs(float(slope)))))
        lines.append((float(slope), float(intercept)))
    return ReposeAngle(angles[0], angles[1], (lines[0], lines[1]))
