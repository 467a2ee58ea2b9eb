"""Measurements on grains: the angle of repose of a heap, the flow rate of a draining silo and
Beverloo's law fitted to flow rates."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from fastsdf.expr.validate import shown
from fastsdf.introspect import show_field_types

__all__ = ["BeverlooFit", "ReposeAngle", "beverloo_fit", "flow_rate", "repose_angle"]


@show_field_types
class ReposeAngle(NamedTuple):
    """The slope of a heap's flanks: ``left`` and ``right`` in degrees (NaN where a flank has
    fewer than 3 surface points in the band), and each flank's fitted line ``(slope,
    intercept)`` of the surface height ``y = slope x + intercept`` in ``lines``: ``(left,
    right)``."""

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
    Pass only the grains of the heap (not those in flight or on other surfaces):
    ``positions`` (n, 2) and ``radius`` (one, or (n,)), in any unit of length.
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
        raise ValueError(f"bin_width must be > 0 (or the grains' radius > 0), got {shown(width)}")
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


def flow_rate(
    times: np.ndarray,
    counts: np.ndarray,
    *,
    low: float = -math.inf,
    high: float = math.inf,
    after: float = -math.inf,
) -> float:
    """The rate at which a count grows (e.g. grains out of a silo, per unit time): the
    least-squares slope of ``counts`` against ``times`` over the samples with ``low <= count
    <= high`` and ``time >= after`` (the steady part of a discharge: after the start, before
    the fill runs low). Fewer than 3 such samples with distinct times are a ValueError."""
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    c = np.asarray(counts, dtype=np.float64).reshape(-1)
    if t.shape != c.shape:
        raise ValueError(f"times and counts must have one length, got {t.shape} and {c.shape}")
    window = (c >= low) & (c <= high) & (t >= after)
    if np.unique(t[window]).size < 3:
        raise ValueError(
            f"flow_rate needs 3 samples with counts in [low, high] = [{shown(low)}, "
            f"{shown(high)}] and "
            f"times >= after={shown(after)}, got {int(window.sum())}"
        )
    return float(np.polyfit(t[window], c[window], 1)[0])


@show_field_types
class BeverlooFit(NamedTuple):
    """Beverloo's law of the flow rate through a slot of width ``D`` in 2D, ``W = C sqrt(g)
    (D - k d)**exponent`` (grains per unit time, ``d`` the grains' diameter; ``exponent`` is
    1.5 in 2D, ``k`` about 1-3)."""

    C: float
    k: float
    exponent: float

    def rate(
        self, width: float | np.ndarray, diameter: float = 1.0, gravity: float = 1.0
    ) -> np.ndarray:
        """The law's flow rate through a slot of ``width``, for grains of ``diameter`` under
        ``gravity`` (the magnitude), in the units the law was fitted in."""
        gap = np.clip(np.asarray(width, dtype=np.float64) - self.k * diameter, 0.0, None)
        return np.asarray(self.C * math.sqrt(gravity) * gap**self.exponent)


def beverloo_fit(
    widths: np.ndarray,
    rates: np.ndarray,
    *,
    diameter: float = 1.0,
    gravity: float = 1.0,
    k: float | None = None,
    exponent: float | None = None,
) -> BeverlooFit:
    """Beverloo's law ``W = C sqrt(g) (D - k d)**exponent`` (2D) fitted to the flow ``rates``
    through slots of ``widths`` (least squares in ``log W``). ``k`` given: ``C`` and the
    exponent by a straight line through ``log W`` against ``log(D - k d)`` (2 widths at
    least). ``exponent`` given: ``k`` and ``C`` by a straight line through ``W**(1 /
    exponent)`` against ``D``. Both free: ``k`` is searched in ``[0, min(D) / d)`` (4 widths at
    least: three give an exact fit for many ``k``). ``diameter`` is the grains' ``d`` and
    ``gravity`` the magnitude ``g``, in the units of ``widths`` and ``rates`` (grains per unit
    time)."""
    d = np.asarray(widths, dtype=np.float64).reshape(-1)
    w = np.asarray(rates, dtype=np.float64).reshape(-1)
    if d.shape != w.shape or not (np.all(np.isfinite(d)) and np.all(np.isfinite(w))):
        raise ValueError("widths and rates must be finite and of one length")
    if not np.all(w > 0):
        raise ValueError(f"rates must be > 0, got rates={shown(w.tolist())}")
    need = 4 if k is None and exponent is None else 2
    if len(np.unique(d)) < need:
        raise ValueError(f"beverloo_fit needs {need} distinct widths here, got {shown(d.tolist())}")
    root_g = math.sqrt(gravity)

    def with_k(kk: float) -> tuple[BeverlooFit, float]:
        gap = d - kk * diameter
        if not np.all(gap > 0):
            raise ValueError(
                f"k={shown(kk)} leaves no gap in the slot of width {shown(float(d.min()))}"
            )
        x, y = np.log(gap), np.log(w)
        if exponent is None:
            b, a = np.polyfit(x, y, 1)
        else:
            b, a = exponent, float(np.mean(y - exponent * x))
        resid = float(np.sum((y - a - b * x) ** 2))
        return BeverlooFit(math.exp(a) / root_g, float(kk), float(b)), resid

    if k is not None:
        return with_k(float(k))[0]
    if exponent is not None:
        slope, intercept = np.polyfit(d, w ** (1.0 / exponent), 1)
        return with_k(float(-intercept / (slope * diameter)))[0]
    top = float(d.min()) / diameter
    ks = np.linspace(0.0, top, 401)[:-1]
    best = min(ks, key=lambda kk: with_k(float(kk))[1])
    lo, hi = max(best - top / 400, 0.0), min(best + top / 400, top * (1 - 1e-9))
    for _ in range(60):  # golden-section refinement around the best grid point
        m1, m2 = lo + 0.382 * (hi - lo), lo + 0.618 * (hi - lo)
        if with_k(m1)[1] < with_k(m2)[1]:
            hi = m2
        else:
            lo = m1
    return with_k(0.5 * (lo + hi))[0]
