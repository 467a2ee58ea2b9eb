"""Plotting signed distance functions with matplotlib, as the notebook does.

:func:`plot_sdf` draws an SDF on an axes: contour lines of the distance (all levels, or only the
zero level, the surface), optional labels on them, an optional quiver of the gradient coloured by
the distance, and an optional filled inside/outside view. :func:`render_frame` puts an SDF and a
set of particles into one figure and saves it as a PNG (the last frame of a demo).

The SDF can be anything callable as ``f(x, y, compute_gradient=...)`` that returns the distance
(negative inside, positive outside) for arrays of coordinates and, with ``compute_gradient=True``,
``(d, grad)`` with ``grad[..., 0] = dd/dx`` and ``grad[..., 1] = dd/dy``: a
:class:`fastsdf.graph.Function` (every shape of :mod:`fastsdf.shapes`), a grid-sampled SDF, or a
plain Python function.

matplotlib (and numba, for the particles) is imported on first use, so ``import fastsdf`` stays
light.
"""

from __future__ import annotations

import numbers

import numpy as np

__all__ = ["plot_sdf", "render_frame", "sdf_grid", "check_bounds",
           "SOLID_COLOR", "BACKGROUND_COLOR", "ISOLINE_OPTIONS", "QUIVER_ARROWS"]

#: Colour of the solid region (``d < 0``) in the filled view (``plot_sdf(..., filled=True)``).
SOLID_COLOR = "#4a5a6a"
#: Colour of the free region (``d >= 0``) in the filled view.
BACKGROUND_COLOR = "#f4f1ea"
#: Values accepted by ``plot_sdf(show_isolines=...)``.
ISOLINE_OPTIONS = ("all", "zero", False, None)
#: Quiver arrows along each axis (the notebook: every 5th of 100 samples).
QUIVER_ARROWS = 20


def check_bounds(bounds, name: str = "bounds") -> tuple:
    """``bounds`` as ``((x0, x1), (y0, y1))`` floats.

    Raises ``ValueError`` naming ``name`` unless ``bounds`` is a finite ``[(x0, x1), (y0, y1)]``
    with ``x0 < x1`` and ``y0 < y1``.
    """
    try:
        arr = np.asarray(bounds, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be [(xmin, xmax), (ymin, ymax)], got {name}={bounds!r}") \
            from None
    if arr.shape != (2, 2):
        raise ValueError(f"{name} must be [(xmin, xmax), (ymin, ymax)], got {name}={bounds!r}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {name}={bounds!r}")
    if not (arr[0, 0] < arr[0, 1] and arr[1, 0] < arr[1, 1]):
        raise ValueError(f"{name} must have xmin < xmax and ymin < ymax, got {name}={bounds!r}")
    return ((float(arr[0, 0]), float(arr[0, 1])), (float(arr[1, 0]), float(arr[1, 1])))


def _check_samples(samples) -> tuple:
    """``samples`` (an int, or a pair for x and y) as ``(nx, ny)``, each an integer >= 2."""
    pair = samples if isinstance(samples, (tuple, list, np.ndarray)) else (samples, samples)
    if len(pair) != 2 or not all(
            isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_)) and v >= 2
            for v in pair):
        raise ValueError(f"samples must be an integer >= 2 or a pair of them (x, y), got "
                         f"samples={samples!r}")
    return int(pair[0]), int(pair[1])


def sdf_grid(f, bounds=((-2.0, 2.0), (-2.0, 2.0)), samples=200, compute_gradient=False):
    """Evaluate the SDF ``f`` on a regular grid over ``bounds``.

    ``samples`` points along each axis (an int, or ``(nx, ny)``), including the bounds
    themselves. Returns ``(xs, ys, d)`` or, with ``compute_gradient``, ``(xs, ys, d, grad)``:
    ``xs`` (nx,) and ``ys`` (ny,) are the sample coordinates, ``d`` is ``(ny, nx)`` with
    ``d[i, j] = f(xs[j], ys[i])`` (image layout, rows along y) and ``grad`` is ``(ny, nx, 2)``.
    """
    (x0, x1), (y0, y1) = check_bounds(bounds)
    nx, ny = _check_samples(samples)
    xs, ys = np.linspace(x0, x1, nx), np.linspace(y0, y1, ny)
    X, Y = np.meshgrid(xs, ys)
    if compute_gradient:
        d, grad = f(X, Y, compute_gradient=True)
        # Reshape: a callable may hand back flat arrays; the values are in point order.
        return xs, ys, np.reshape(np.asarray(d, dtype=np.float64), X.shape), \
            np.reshape(np.asarray(grad, dtype=np.float64), X.shape + (2,))
    d = f(X, Y, compute_gradient=False)
    return xs, ys, np.reshape(np.asarray(d, dtype=np.float64), X.shape)


def _setup_axes(ax, bounds):
    """The notebook's axes: limits = bounds, equal aspect, no ticks and no tick labels."""
    (x0, x1), (y0, y1) = bounds
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.tick_params(axis="both", which="both", bottom=False, top=False, left=False, right=False,
                   labelbottom=False, labeltop=False, labelleft=False, labelright=False)


def plot_sdf(fig, ax, f, bounds=[(-2, 2), (-2, 2)], samples=200, show_quiver=True,
             show_isolines='all', show_isolabels=False, filled=False):
    """Plot the signed distance function ``f`` on the matplotlib axes ``ax``.

    ``f``: any callable ``f(x, y, compute_gradient=...)`` (see the module docstring); it is
    evaluated on a ``samples`` x ``samples`` grid (an int >= 2, or a pair ``(nx, ny)``) spanning
    ``bounds = [(xmin, xmax), (ymin, ymax)]`` (data units). ``fig`` is accepted for the notebook's
    signature and not used.

    ``show_isolines``: ``'all'`` draws contour lines at matplotlib's automatic distance levels,
    ``'zero'`` only the zero level (the surface), ``False``/``None`` none. ``show_isolabels``
    writes the distance on the lines. ``show_quiver`` draws the gradient (direction of steepest
    distance ascent, pointing out of solids) at about ``QUIVER_ARROWS`` points per axis,
    coloured by the distance. ``filled`` paints the solid region ``d < 0`` in
    :data:`SOLID_COLOR` and the rest in :data:`BACKGROUND_COLOR`, beneath the lines and arrows.

    The axes get the notebook's look: limits = ``bounds``, equal aspect, no ticks. Returns a dict
    of the artists created, with the keys that apply: ``'fill'`` (the filled ``QuadContourSet``),
    ``'contour'`` (the line ``QuadContourSet``), ``'labels'`` (the label ``Text`` list),
    ``'quiver'`` (the ``Quiver``). Raises ``ValueError`` naming the parameter for an unknown
    ``show_isolines``, malformed or empty ``bounds``, or ``samples < 2``.
    """
    if isinstance(show_isolines, str) or show_isolines is None or show_isolines is False:
        ok = show_isolines in ISOLINE_OPTIONS
    else:
        ok = False
    if not ok:
        raise ValueError(f"show_isolines must be 'all', 'zero', False or None, got "
                         f"show_isolines={show_isolines!r}")
    bounds = check_bounds(bounds)
    samples = _check_samples(samples)

    _setup_axes(ax, bounds)
    ret = {}
    if not (show_quiver or show_isolines or filled):
        return ret

    if show_quiver:
        xs, ys, d, grad = sdf_grid(f, bounds, samples, compute_gradient=True)
    else:
        xs, ys, d = sdf_grid(f, bounds, samples)
    # NaN (e.g. where a grid-sampled SDF has no data) is left blank instead of breaking contour.
    dm = np.ma.masked_invalid(d)

    if filled:
        ret['fill'] = ax.contourf(xs, ys, dm, levels=[-np.inf, 0.0, np.inf],
                                  colors=[SOLID_COLOR, BACKGROUND_COLOR], zorder=0.5)
    if show_isolines:
        levels = [0.0] if show_isolines == 'zero' else None
        ret['contour'] = ax.contour(xs, ys, dm, levels=levels, zorder=2)
        if show_isolabels:
            ret['labels'] = ax.clabel(ret['contour'], inline=True, fontsize=8, fmt="%g")
    if show_quiver:
        sx = max(1, round(samples[0] / QUIVER_ARROWS))
        sy = max(1, round(samples[1] / QUIVER_ARROWS))
        X, Y = np.meshgrid(xs[::sx], ys[::sy])
        ret['quiver'] = ax.quiver(X, Y, grad[::sy, ::sx, 0], grad[::sy, ::sx, 1],
                                  d[::sy, ::sx], zorder=3)
    return ret


def render_frame(f, x, y, r=None, bounds=[(-2, 2), (-2, 2)], out_png=None, title=None,
                 samples=400, max_circles=None, figsize=(6.0, 6.0), dpi=100):
    """Draw the SDF ``f`` and particles at ``(x, y)`` in one figure and save it as a PNG.

    The figure shows ``f``'s filled view (solid in :data:`SOLID_COLOR`, free space in
    :data:`BACKGROUND_COLOR`) with its zero contour, over ``bounds`` (data units, sampled
    ``samples`` times per axis), and the particles on top via
    :func:`fastsdf.render.draw_particles`: circles of radius ``r`` (data units; scalar or per
    particle) up to ``max_circles`` particles (default
    :data:`fastsdf.render.DEFAULT_MAX_CIRCLES`), a density image above that. ``title`` is the
    axes title. The figure is ``figsize`` inches at ``dpi``; if ``out_png`` is given it is saved
    there at that dpi (no cropping, so the axes' ``transData`` maps data coordinates to the
    PNG's pixels, with y counted from the bottom).

    Returns the ``matplotlib.figure.Figure`` (not registered with pyplot, so nothing needs
    closing; its axes is ``fig.axes[0]`` and the particle layer ``fig.particle_layer``).
    """
    from matplotlib.figure import Figure

    from .render import DEFAULT_MAX_CIRCLES, draw_particles

    fig = Figure(figsize=figsize, dpi=dpi)
    ax = fig.add_subplot()
    plot_sdf(fig, ax, f, bounds=bounds, samples=samples, show_quiver=False,
             show_isolines='zero', filled=True)
    layer = draw_particles(ax, x, y, r=r, bounds=bounds,
                           max_circles=DEFAULT_MAX_CIRCLES if max_circles is None else max_circles)
    fig.particle_layer = layer
    if title is not None:
        ax.set_title(title)
    if out_png is not None:
        fig.savefig(out_png, dpi=dpi)
    return fig
