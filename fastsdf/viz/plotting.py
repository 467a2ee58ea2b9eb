"""Plotting signed distance functions with matplotlib, as the notebook does.

:func:`plot_sdf` draws an SDF on an axes: contour lines of the distance (all levels, or only the
zero level, the surface, always a distinct black line), optional labels on them, an optional
quiver of the gradient coloured by the distance, an optional filled inside/outside view and a
colour bar of the distance. By default it makes a figure to keep: coordinates on ticked and
labelled axes, a colour bar, tight margins; ``axes=False`` gives the notebook's bare look.
Particles and animations are drawn by :mod:`fastsdf.viz.render`, which builds on this module (this
module never imports it).

The SDF can be anything callable that returns the distance (negative inside, positive outside)
for arrays of coordinates:

- ``f(x, y, compute_gradient=...)``, returning ``d`` or, with ``compute_gradient=True``,
  ``(d, grad)`` with ``grad[..., 0] = dd/dx`` and ``grad[..., 1] = dd/dy``: a
  :class:`fastsdf.function.Function` (every shape of :mod:`fastsdf.shapes`) or a GridSDF;
- a plain ``f(x, y)`` returning ``d``;
- a plain ``f(p)`` taking an ``(n, 2)`` array of points and returning ``(n,)`` distances.

For the plain forms the gradient (for the quiver) is taken by central differences.

matplotlib is imported on first use, so ``import fastsdf`` stays light.
"""

from __future__ import annotations

import inspect
import numbers
from collections.abc import Callable
from typing import Any

import numpy as np

from fastsdf.expr.validate import check_bounds, shown

__all__ = [
    "plot_sdf",
    "sdf_grid",
    "check_bounds",
    "SOLID_COLOR",
    "BACKGROUND_COLOR",
    "SURFACE_COLOR",
    "ISOLINE_OPTIONS",
    "QUIVER_ARROWS",
]

#: Colour of the solid region (``d < 0``) in the filled view (``plot_sdf(..., filled=True)``).
SOLID_COLOR = "#4a5a6a"
#: Colour of the free region (``d >= 0``) in the filled view.
BACKGROUND_COLOR = "#f4f1ea"
#: Values accepted by ``plot_sdf(show_isolines=...)``.
ISOLINE_OPTIONS = ("all", "zero", False, None)
#: Quiver arrows along each axis (the notebook: every 5th of 100 samples).
QUIVER_ARROWS = 20


def _check_samples(samples: Any) -> tuple:
    """``samples`` (an int, or a pair for x and y) as ``(nx, ny)``, each an integer >= 2."""
    pair = samples if isinstance(samples, (tuple, list, np.ndarray)) else (samples, samples)
    if len(pair) != 2 or not all(
        isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_)) and int(v) >= 2
        for v in pair
    ):
        raise ValueError(
            f"samples must be an integer >= 2 or a pair of them (x, y), got "
            f"samples={shown(samples)}"
        )
    return int(pair[0]), int(pair[1])


def _calling_convention(f: Callable) -> str:
    """``'gradient'`` (``f(x, y, compute_gradient=...)``), ``'xy'`` (``f(x, y)``) or ``'points'``
    (``f(p)``, ``p`` of shape ``(n, 2)``)."""
    if not callable(f):
        raise TypeError(
            f"f must be a callable SDF (f(x, y) or f(p)), got f of type {type(f).__name__}"
        )
    try:
        params = list(inspect.signature(f).parameters.values())
    except (TypeError, ValueError):  # builtins and some extension callables have no signature
        return "xy"
    kinds = {p.kind for p in params}
    if any(p.name == "compute_gradient" for p in params) or inspect.Parameter.VAR_KEYWORD in kinds:
        return "gradient"
    positional = [
        p
        for p in params
        if p.kind in (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    ]
    if inspect.Parameter.VAR_POSITIONAL in kinds or len(positional) >= 2:
        return "xy"
    return "points"


def _values(f: Callable, kind: str, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    if kind == "gradient":
        d = f(X, Y, compute_gradient=False)
    elif kind == "xy":
        d = f(X, Y)
    else:
        d = f(np.column_stack([X.reshape(-1), Y.reshape(-1)]))
    # Reshape: a callable may hand back flat arrays; the values are in point order.
    return np.reshape(np.asarray(d, dtype=np.float64), X.shape)


def sdf_grid(
    f: Callable,
    bounds: Any = ((-2.0, 2.0), (-2.0, 2.0)),
    samples: Any = 200,
    compute_gradient: bool = False,
) -> tuple:
    """Evaluate the SDF ``f`` on a regular grid over ``bounds``.

    ``f``: any of the callables of the module docstring. ``samples`` points along each axis (an
    int, or ``(nx, ny)``), including the bounds themselves. Returns ``(xs, ys, d)`` or, with
    ``compute_gradient``, ``(xs, ys, d, grad)``: ``xs`` (nx,) and ``ys`` (ny,) are the sample
    coordinates, ``d`` is ``(ny, nx)`` with ``d[i, j] = f(xs[j], ys[i])`` (image layout, rows
    along y) and ``grad`` is ``(ny, nx, 2)`` (``f``'s own gradient when it computes one, else
    central differences with a step of 1e-6 of the bounds' size).
    """
    (x0, x1), (y0, y1) = check_bounds(bounds)
    nx, ny = _check_samples(samples)
    kind = _calling_convention(f)
    xs, ys = np.linspace(x0, x1, nx), np.linspace(y0, y1, ny)
    X, Y = np.meshgrid(xs, ys)
    if not compute_gradient:
        return xs, ys, _values(f, kind, X, Y)
    if kind == "gradient":
        d, grad = f(X, Y, compute_gradient=True)
        return (
            xs,
            ys,
            np.reshape(np.asarray(d, dtype=np.float64), X.shape),
            np.reshape(np.asarray(grad, dtype=np.float64), X.shape + (2,)),
        )
    h = 1e-6 * max(x1 - x0, y1 - y0)
    grad = np.stack(
        [
            (_values(f, kind, X + h, Y) - _values(f, kind, X - h, Y)) / (2 * h),
            (_values(f, kind, X, Y + h) - _values(f, kind, X, Y - h)) / (2 * h),
        ],
        -1,
    )
    return xs, ys, _values(f, kind, X, Y), grad


def _setup_axes(ax: Any, bounds: tuple, ticks: bool = False) -> None:
    """Limits = bounds and equal aspect; no ticks (the notebook's look) unless ``ticks``, which
    labels both axes in data units."""
    (x0, x1), (y0, y1) = bounds
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    if ticks:
        ax.tick_params(
            axis="both", which="both", bottom=True, left=True, labelbottom=True, labelleft=True
        )
        ax.set_xlabel("x")
        ax.set_ylabel("y")
    else:
        ax.tick_params(
            axis="both",
            which="both",
            bottom=False,
            top=False,
            left=False,
            right=False,
            labelbottom=False,
            labeltop=False,
            labelleft=False,
            labelright=False,
        )


#: Font size (points) of the isoline labels.
ISOLABEL_FONTSIZE = 8


def _check_levels(levels: Any, show_isolines: Any) -> Any:
    """``levels`` for ``ax.contour``: ``None``, a count >= 1, or a finite increasing 1-D array."""
    if levels is None:
        return None
    if show_isolines != "all":
        raise ValueError(
            f"levels applies to show_isolines='all', got levels={shown(levels)} with "
            f"show_isolines={shown(show_isolines)}"
        )
    if isinstance(levels, numbers.Integral) and not isinstance(levels, (bool, np.bool_)):
        if levels < 1:
            raise ValueError(
                f"levels must be a count >= 1 or distances, got levels={shown(levels)}"
            )
        return int(levels)
    try:
        values = np.asarray(levels, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(
            f"levels must be a count >= 1 or increasing distances, got levels={shown(levels)}"
        ) from None
    if values.ndim != 1 or values.size == 0 or not np.all(np.isfinite(values)):
        raise ValueError(
            f"levels must be a count >= 1 or increasing distances, got levels={shown(levels)}"
        )
    if np.any(np.diff(values) <= 0):
        raise ValueError(f"levels must be increasing, got levels={shown(levels)}")
    return values


def _figure_size(bounds: tuple, colorbar: bool, title: str | None) -> tuple:
    """Inches of a figure holding one equal-aspect axes over ``bounds`` (its longer side 5
    inches) with its tick labels, axis labels, colour bar and title, without spare margins."""
    (x0, x1), (y0, y1) = bounds
    aspect = (y1 - y0) / (x1 - x0)
    w, h = (5.0, 5.0 * aspect) if aspect <= 1.0 else (5.0 / aspect, 5.0)
    w, h = max(w, 2.0), max(h, 1.5)
    extra_w = 0.8 + (1.1 if colorbar else 0.2)  # y tick labels and label; the colour bar
    extra_h = 0.75 + (0.35 * (1 + title.count("\n")) if title else 0.1)
    return (round(w + extra_w, 2), round(h + extra_h, 2))


def _label_isolines(ax: Any, contours: Any, bounds: tuple) -> list:
    """Label each line of ``contours`` once, at the point nearest the middle of its length where
    the label fits inside ``bounds`` (matplotlib's own placement may put a label at the edge,
    where the axes cut it). Lines too short to carry a label stay unlabelled."""
    fig = ax.figure
    box = ax.get_position()
    fw, fh = fig.get_size_inches()
    (x0, x1), (y0, y1) = bounds
    # points per data unit (equal aspect: the tighter of the two directions)
    per_unit = 72.0 * min(box.width * fw / (x1 - x0), box.height * fh / (y1 - y0))
    half_h = 0.75 * ISOLABEL_FONTSIZE / per_unit
    positions = []
    for level, segments in zip(contours.levels, contours.allsegs, strict=True):
        text = f"{level:g}"
        half_w = (0.32 * ISOLABEL_FONTSIZE * len(text) + 2.0) / per_unit
        for seg in segments:
            if len(seg) < 3:
                continue
            steps = np.hypot(*np.diff(seg, axis=0).T)
            along = np.concatenate([[0.0], np.cumsum(steps)])
            if along[-1] < 6.0 * half_w:  # too short: the label would hide it
                continue
            # a rotated label fits when a disc of its half width does
            r = max(half_w, half_h)
            fits = (
                (seg[:, 0] - x0 > r)
                & (x1 - seg[:, 0] > r)
                & (seg[:, 1] - y0 > r)
                & (y1 - seg[:, 1] > r)
            )
            if not fits.any():
                continue
            candidates = np.flatnonzero(fits)
            best = candidates[np.argmin(np.abs(along[candidates] - along[-1] / 2.0))]
            positions.append((float(seg[best, 0]), float(seg[best, 1])))
    if not positions:
        return []
    return list(
        ax.clabel(contours, inline=True, fontsize=ISOLABEL_FONTSIZE, fmt="%g", manual=positions)
    )


#: The zero contour (the surface) is drawn in this colour and width (points), over the
#: coloured lines of the other distances.
SURFACE_COLOR = "black"
SURFACE_WIDTH = 2.0


def _check_show(show_isolines: Any, show_quiver: bool, colorbar: bool | None) -> bool:
    """Check ``show_isolines``; return whether to draw a colour bar (``colorbar=None``: when
    lines or arrows are coloured by the distance)."""
    ok = show_isolines is None or show_isolines is False
    ok = ok or (isinstance(show_isolines, str) and show_isolines in ISOLINE_OPTIONS)
    if not ok:
        raise ValueError(
            f"show_isolines must be 'all', 'zero', False or None, got "
            f"show_isolines={shown(show_isolines)}"
        )
    coloured = show_isolines == "all" or bool(show_quiver)
    if colorbar and not coloured:
        raise ValueError(
            f"colorbar=True needs something coloured by the distance "
            f"(show_isolines='all' or show_quiver=True), got "
            f"show_isolines={shown(show_isolines)}, show_quiver={shown(show_quiver)}"
        )
    return coloured if colorbar is None else bool(colorbar)


def _new_axes(bounds: tuple, axes: bool, colorbar: bool, title: str | None) -> Any:
    """A new pyplot figure's axes: sized to ``bounds`` (compressed layout) for ``axes``."""
    import matplotlib.pyplot as plt

    if axes:
        return plt.subplots(figsize=_figure_size(bounds, colorbar, title), layout="compressed")[1]
    return plt.subplots()[1]


def _draw_isolines(
    ax: Any, xs: np.ndarray, ys: np.ndarray, dm: Any, show: str, levels: Any, norm: Any
) -> dict:
    """The lines of ``show_isolines``: ``'all'``, coloured by the distance (``'contour'``),
    with the surface over them (``'surface'``, where ``d`` changes sign); ``'zero'``, the
    surface alone (``'contour'``)."""
    surface = dict(colors=SURFACE_COLOR, linewidths=SURFACE_WIDTH, zorder=2.5)
    if show == "zero":
        return {"contour": ax.contour(xs, ys, dm, levels=[0.0], **surface)}
    out = {"contour": ax.contour(xs, ys, dm, levels=levels, zorder=2, norm=norm)}
    if dm.count() and dm.min() < 0.0 < dm.max():
        out["surface"] = ax.contour(xs, ys, dm, levels=[0.0], **surface)
    return out


def _draw_colorbar(ax: Any, mappable: Any, axes: bool) -> Any:
    """A colour bar of the distance beside ``ax``."""
    # fraction/pad: a bar as tall as a square axes beside it (in the compressed layout of
    # axes=True, as tall as any axes: 0.046 would shorten it there).
    size = dict(fraction=0.05, aspect=25, pad=0.03) if axes else dict(fraction=0.046, pad=0.04)
    return ax.figure.colorbar(mappable, ax=ax, label="distance d (negative inside)", **size)


def plot_sdf(
    f_or_fig: Any,
    ax: Any = None,
    f: Callable | None = None,
    bounds: Any = ((-2, 2), (-2, 2)),
    samples: Any = 200,
    show_quiver: bool = True,
    show_isolines: str | bool | None = "all",
    show_isolabels: bool = False,
    filled: bool = False,
    colorbar: bool | None = None,
    ticks: bool | None = None,
    axes: bool = True,
    levels: Any = None,
    title: str | None = None,
) -> dict:
    """Plot the signed distance function ``f`` on a matplotlib axes.

    Call it as ``plot_sdf(f)`` (a new pyplot figure), ``plot_sdf(f, ax=ax)``, or with the
    notebook's positional signature ``plot_sdf(fig, ax, f, ...)`` (``fig`` is not used and may be
    ``None``). By default the picture is one to keep: axes in data units with ticks and labels
    ``x`` and ``y``, the distance's lines coloured by their value with a colour bar, the
    surface (the zero contour) a thick black line over them, and the gradient's arrows.

    Parameters
    ----------
    f_or_fig : callable SDF, or a figure (with ``ax`` and ``f``: the notebook's form)
        ``f``: any callable of the module docstring (``f(x, y, compute_gradient=...)``,
        ``f(x, y)`` or ``f(p)`` with ``p`` of shape ``(n, 2)``).
    ax : matplotlib axes or None (default: a new pyplot figure)
    f : callable SDF or None (default: ``f_or_fig``)
    bounds : [(xmin, xmax), (ymin, ymax)], default [(-2, 2), (-2, 2)]
        The region shown, in the units of the coordinates.
    samples : int >= 2 or (nx, ny), default 200
        Grid points along each axis where ``f`` is evaluated.
    show_quiver : bool, default True
        Arrows of the gradient (the direction of steepest ascent, out of solids) at about
        :data:`QUIVER_ARROWS` points per axis, coloured by the distance.
    show_isolines : 'all' (default), 'zero', False or None
        ``'all'``: lines at matplotlib's automatic distances (or ``levels``), coloured by the
        distance, and the surface (``d = 0``) in :data:`SURFACE_COLOR`; ``'zero'``: the
        surface only; ``False``/``None``: no lines.
    show_isolabels : bool, default False
        Write the distance on the lines, each label where it fits inside the axes (one per
        line long enough to carry one).
    filled : bool, default False
        Paint the solid region ``d < 0`` in :data:`SOLID_COLOR` and the rest in
        :data:`BACKGROUND_COLOR`, beneath the lines and arrows.
    colorbar : bool or None (default)
        A colour bar of the distance for the coloured lines and arrows; ``None``: one when
        something is coloured (``show_isolines='all'`` or ``show_quiver``). ``True`` with
        nothing coloured is a ``ValueError``.
    ticks : bool or None (default: as ``axes``)
        Ticks and axis labels in data units; ``False``: the notebook's bare look.
    axes : bool, default True
        A figure to keep: ticks and axis labels, and, when ``plot_sdf`` makes the figure, one
        sized to ``bounds`` with tight margins (matplotlib's compressed layout: the colour bar
        as tall as the axes). ``False``: the notebook's look (limits = ``bounds``, equal
        aspect, no ticks) in matplotlib's default figure.
    levels : None, int >= 1, or increasing distances
        The distances of the lines of ``show_isolines='all'``: matplotlib's automatic choice,
        a number of levels, or the values themselves. A level just below a local maximum of
        the distance (midway between two shapes, in a hole) draws a small closed loop around
        it; give the levels to keep them clear of such maxima.
    title : str or None
        The axes title.

    Returns a dict of ``'ax'`` (the axes drawn on) and the artists drawn: ``'fill'``,
    ``'contour'`` (the lines), ``'surface'`` (the zero contour over the lines of ``'all'``),
    ``'labels'``, ``'quiver'``, ``'colorbar'``. Bad arguments raise ``ValueError`` (``TypeError``
    for ``f``) naming the parameter.
    """
    if f is None:
        f = f_or_fig
    if f is None or not callable(f):
        raise TypeError(
            f"f must be a callable SDF, got f={shown(f)}: call plot_sdf(f), "
            f"plot_sdf(f, ax=ax) or plot_sdf(fig, ax, f)"
        )
    colorbar = _check_show(show_isolines, show_quiver, colorbar)
    bounds = check_bounds(bounds)
    samples = _check_samples(samples)
    levels = _check_levels(levels, show_isolines)
    if ax is None:
        ax = _new_axes(bounds, axes, colorbar, title)
    _setup_axes(ax, bounds, axes if ticks is None else ticks)
    if title is not None:
        ax.set_title(title)
    ret = {"ax": ax}
    if not (show_quiver or show_isolines or filled):
        return ret

    grid = sdf_grid(f, bounds, samples, compute_gradient=show_quiver)
    ret.update(
        _draw_layers(ax, grid, bounds, filled, show_isolines, show_isolabels, levels, colorbar)
    )
    if colorbar:
        mappable = ret["contour"] if show_isolines == "all" else ret["quiver"]
        ret["colorbar"] = _draw_colorbar(ax, mappable, axes)
    return ret


def _draw_layers(
    ax: Any,
    grid: tuple,
    bounds: tuple,
    filled: bool,
    show_isolines: Any,
    show_isolabels: bool,
    levels: Any,
    colorbar: bool,
) -> dict:
    """:func:`plot_sdf`'s layers from ``grid`` (:func:`sdf_grid`'s, with the gradient where
    arrows are drawn): the filled view, the lines (and their labels), the arrows, all
    coloured on one scale of the distance when there is a colour bar."""
    xs, ys, d = grid[:3]
    # NaN (e.g. where a grid-sampled SDF has no data) is left blank instead of breaking contour.
    dm = np.ma.masked_invalid(d)
    norm = None
    if colorbar and dm.count():
        from matplotlib.colors import Normalize

        norm = Normalize(float(dm.min()), float(dm.max()))  # one scale for lines and arrows
    ret: dict = {}
    if filled:
        ret["fill"] = ax.contourf(
            xs,
            ys,
            dm,
            levels=[-np.inf, 0.0, np.inf],
            colors=[SOLID_COLOR, BACKGROUND_COLOR],
            zorder=0.5,
        )
    if show_isolines:
        ret.update(_draw_isolines(ax, xs, ys, dm, str(show_isolines), levels, norm))
        if show_isolabels:
            ret["labels"] = _label_isolines(ax, ret["contour"], bounds)
    if len(grid) == 4:  # the arrows
        grad = grid[3]
        sx = max(1, round(len(xs) / QUIVER_ARROWS))
        sy = max(1, round(len(ys) / QUIVER_ARROWS))
        X, Y = np.meshgrid(xs[::sx], ys[::sy])
        ret["quiver"] = ax.quiver(
            X, Y, grad[::sy, ::sx, 0], grad[::sy, ::sx, 1], d[::sy, ::sx], zorder=3, norm=norm
        )
    return ret
