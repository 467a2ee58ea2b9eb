"""Drawing many particles: a compiled splat into a density image, and a per-frame particle layer.

Matplotlib draws one path per circle, which is fine for thousands of particles and hopeless for
millions. :func:`density_image` bins points into a pixel grid in a numba kernel (about 5-10 ms
for 1e6 points), and :func:`draw_particles` shows either circles (few particles) or that image
(many particles), returning a :class:`ParticleLayer` whose ``update(x, y)`` redraws it for each
frame of an animation. :func:`render_frame` draws a world and particles into one labelled figure,
:func:`animate` turns a running :class:`fastsdf.particles.ParticleSimulation` into a matplotlib
animation (without resetting it) and :func:`save_animation` writes one to MP4, GIF or HTML.

Drawing lives here, apart from the physics: a simulation holds no artists. This module imports
:mod:`fastsdf.viz.plotting` (the SDF's picture), never the other way round.

Image convention (shared by every function here): an image of ``shape=(H, W)`` covers
``bounds=[(x0, x1), (y0, y1)]`` in data units; pixel ``[i, j]`` holds the points with
``x0 + j*(x1-x0)/W <= x < x0 + (j+1)*(x1-x0)/W`` and likewise ``i`` along ``y``, so **row 0 is
the bottom** (show it with ``imshow(origin='lower', extent=(x0, x1, y0, y1))``). The last row and
column also take the points exactly on ``x1`` / ``y1``: the binning is that of
``numpy.histogram2d(x, y, bins=(W, H), range=bounds)``, transposed. Points outside the bounds or
with a NaN/infinite coordinate are dropped.
"""

from __future__ import annotations

import contextlib
import math
import numbers
import time
import weakref
from typing import Any

import numba
import numpy as np
from numba import njit, prange

from fastsdf.expr.validate import check_bounds, count, reals, shown

__all__ = [
    "density_image",
    "density_norm",
    "draw_particles",
    "ParticleLayer",
    "render_frame",
    "animate",
    "save_animation",
    "PARTICLE_COLOR",
    "PARTICLE_CMAP_COLORS",
    "DEFAULT_MAX_CIRCLES",
    "VIDEO_FORMATS",
    "sim_title",
    "notebook_draw",
    "notebook_animation",
]

#: Face colour of particles drawn as circles.
PARTICLE_COLOR = "#e6550d"
#: Colours (low to high density) of the colour map of the density image. Every one is far from
#: the SDF fill colours of :mod:`fastsdf.viz.plotting`, so particles stay visible over either.
PARTICLE_CMAP_COLORS = ("#fd8d3c", "#d94801", "#7f2704")
#: Up to this many particles :func:`draw_particles` draws circles; above, a density image.
DEFAULT_MAX_CIRCLES = 5000
#: Largest side (pixels) of a density image whose shape is derived from the axes.
MAX_IMAGE_SIDE = 4096

# Parallel binning uses one partial image per chunk of points. The serial loop bins 1e6 points
# in about 5-10 ms. On the shared, busy 2-core machine this was written on, the 2-thread kernel
# was slower at every size tried (1e6 and 1e7 points), so by default threads are used only from
# 2**20 points per thread on (not measured on a many-core machine).
_PAR_MIN_POINTS = 1 << 20


# ---------------------------------------------------------------------------------------------
# Kernels.


@njit(cache=True, nogil=True)
def _bin(v, lo, hi, scale, edges, n):
    """Bin of ``v`` among ``n`` equal bins with the given ``edges`` (histogram semantics), or -1.

    The index is computed arithmetically and then corrected against the exact edge values, so a
    point on an edge lands in the same bin as ``numpy.searchsorted(edges, v, 'right') - 1``.
    """
    if not (v >= lo and v <= hi):  # also rejects NaN
        return -1
    k = int((v - lo) * scale)
    if k > n - 1:
        k = n - 1
    elif k < 0:
        k = 0
    while k > 0 and v < edges[k]:
        k -= 1
    while k < n - 1 and v >= edges[k + 1]:
        k += 1
    return k


@njit(cache=True, nogil=True)
def _splat_range(xs, ys, ws, use_w, img, xe, ye, start, stop):
    h, w = img.shape
    x0, x1, y0, y1 = xe[0], xe[w], ye[0], ye[h]
    sx = w / (x1 - x0)
    sy = h / (y1 - y0)
    for p in range(start, stop):
        j = _bin(xs[p], x0, x1, sx, xe, w)
        if j < 0:
            continue
        i = _bin(ys[p], y0, y1, sy, ye, h)
        if i < 0:
            continue
        if use_w:
            img[i, j] += ws[p]
        else:
            img[i, j] += 1.0


@njit(cache=True)
def _splat_serial(xs, ys, ws, use_w, img, xe, ye):
    _splat_range(xs, ys, ws, use_w, img, xe, ye, 0, xs.shape[0])


@njit(cache=True, parallel=True)
def _splat_parallel(xs, ys, ws, use_w, img, xe, ye, chunks):
    # One private partial image per chunk (no write races), then a parallel sum over pixels.
    n = xs.shape[0]
    h, w = img.shape
    part = np.zeros((chunks, h, w))
    for c in prange(chunks):
        _splat_range(xs, ys, ws, use_w, part[c], xe, ye, c * n // chunks, (c + 1) * n // chunks)
    for i in prange(h):
        for c in range(chunks):
            for j in range(w):
                img[i, j] += part[c, i, j]


# ---------------------------------------------------------------------------------------------
# Validation helpers (errors name the parameter and the value).


def check_shape(shape: Any) -> tuple[int, int]:
    try:
        h, w = shape
    except (TypeError, ValueError):
        raise ValueError(
            f"shape must be a pair (H, W) of positive integers, got shape={shown(shape)}"
        ) from None
    if not all(
        isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_)) and int(v) >= 1
        for v in (h, w)
    ):
        raise ValueError(
            f"shape must be a pair (H, W) of positive integers, got shape={shown(shape)}"
        )
    return int(h), int(w)


# ---------------------------------------------------------------------------------------------
# Public API.


def density_image(
    x: Any,
    y: Any,
    bounds: Any = ((-2.0, 2.0), (-2.0, 2.0)),
    shape: tuple = (400, 400),
    weights: Any = None,
    parallel: bool | None = None,
) -> np.ndarray:
    """Count points per pixel: a ``(H, W)`` float64 image of the points ``(x, y)``.

    ``x``, ``y``: coordinates (data units), arrays of equal size and any shape (flattened).
    ``bounds``: ``[(x0, x1), (y0, y1)]``, the region the image covers. ``shape``: ``(H, W)``
    pixels (rows along y, columns along x). ``weights``: optional array of the same size; a
    pixel then holds the sum of its points' weights instead of their number.

    Pixel ``[i, j]`` covers ``x`` in ``[x0 + j dx, x0 + (j+1) dx)`` and ``y`` in
    ``[y0 + i dy, y0 + (i+1) dy)`` with ``dx = (x1 - x0) / W``, ``dy = (y1 - y0) / H``; row 0 is
    at the bottom (``imshow(..., origin='lower', extent=(x0, x1, y0, y1))``), and points exactly
    on ``x1`` or ``y1`` go into the last column / row. This is
    ``numpy.histogram2d(x, y, bins=(W, H), range=bounds, weights=weights)[0].T``, computed in a
    compiled kernel (in parallel with private partial images for large inputs). Points outside
    the bounds or with a NaN or infinite coordinate are dropped.

    ``parallel``: ``None`` (default) splits the points over numba's threads only when there are
    enough of them to pay for one private image per thread (at least ``2**20`` points per
    thread, and not much more image than points); ``True`` / ``False`` force the parallel /
    serial kernel. Both give the same image (the parallel one up to float rounding of weights).
    """
    (x0, x1), (y0, y1) = check_bounds(bounds)
    h, w = check_shape(shape)
    xs, ys = reals(x, "x"), reals(y, "y")
    if xs.shape != ys.shape:
        raise ValueError(
            f"x and y must have the same number of points, got {xs.size} and {ys.size}"
        )
    use_w = weights is not None
    if use_w:
        ws = reals(weights, "weights")
        if ws.shape != xs.shape:
            raise ValueError(
                f"weights must have one value per point ({xs.size}), got {ws.size} values"
            )
    else:
        ws = np.empty(0)
    xe = np.linspace(x0, x1, w + 1)
    ye = np.linspace(y0, y1, h + 1)
    img = np.zeros((h, w))
    n = xs.shape[0]
    if n == 0:
        return img
    # Partial images cost h*w each to zero and to sum: use as many as the points pay for.
    if parallel is None:
        chunks = min(numba.get_num_threads(), n // _PAR_MIN_POINTS, max(1, (4 * n) // (h * w)))
    elif parallel:
        chunks = max(2, min(numba.get_num_threads(), n))
    else:
        chunks = 1
    if chunks >= 2:
        _splat_parallel(xs, ys, ws, use_w, img, xe, ye, chunks)
    else:
        _splat_serial(xs, ys, ws, use_w, img, xe, ye)
    return img


def _particle_cmap():
    from matplotlib.colors import LinearSegmentedColormap

    cmap = LinearSegmentedColormap.from_list("fastsdf_particles", list(PARTICLE_CMAP_COLORS))
    return cmap.with_extremes(bad=(0.0, 0.0, 0.0, 0.0), under=(0.0, 0.0, 0.0, 0.0))


def _axes_image_shape(ax: Any, bounds: tuple) -> tuple[int, int]:
    """One image pixel per screen pixel of ``ax`` over ``bounds`` (at the figure's dpi)."""
    with contextlib.suppress(Exception):  # a layout not resolved yet: use the box as is
        ax.apply_aspect()
    box = ax.get_window_extent()
    (xl0, xl1), (yl0, yl1) = ax.get_xlim(), ax.get_ylim()
    (x0, x1), (y0, y1) = bounds
    w = box.width * (x1 - x0) / abs(xl1 - xl0) if xl1 != xl0 else box.width
    h = box.height * (y1 - y0) / abs(yl1 - yl0) if yl1 != yl0 else box.height
    return _clip_side(h), _clip_side(w)


def plain_log_ticks(colorbar: Any) -> None:
    """Tick labels ``1, 2, 5, 10, 100`` on a logarithmic colour bar instead of ``2x10^0``."""
    from matplotlib.ticker import FuncFormatter

    norm = colorbar.norm

    def major(v, _pos):
        return f"{v:g}"

    def minor(v, _pos):
        # Label 2 and 5 between decades only while the bar spans few decades (else crowded).
        span = math.log10(max(norm.vmax, 1.0) / max(norm.vmin, 1e-300))
        lead = int(round(v / 10 ** math.floor(math.log10(v)))) if v > 0 else 0
        return f"{v:g}" if span <= 2.0 and lead in (2, 5) else ""

    colorbar.ax.yaxis.set_major_formatter(FuncFormatter(major))
    colorbar.ax.yaxis.set_minor_formatter(FuncFormatter(minor))


def density_norm(vmax: float) -> Any:
    """The colour scale of a density picture: logarithmic from 1 to ``vmax`` particles per pixel
    (a ``matplotlib.colors.LogNorm``). The video's frames (:class:`fastsdf.viz.frames.VideoWriter`)
    and the still pictures (:func:`render_frame`, :func:`draw_particles`) both take it from here,
    so that a count has one colour in both for the same ``vmax``."""
    from matplotlib.colors import LogNorm

    return LogNorm(1.0, float(vmax))


def _clip_side(v: float) -> int:
    return int(min(MAX_IMAGE_SIDE, max(1, round(v)))) if math.isfinite(v) else 256


class ParticleLayer:
    """The particles drawn on an axes by :func:`draw_particles`; call :meth:`update` per frame.

    Attributes: ``ax``; ``mode``, ``'circles'`` or ``'density'``; ``artist``, the current
    matplotlib artist (an ``EllipseCollection`` or an ``AxesImage``); ``image``, the last density
    image (``None`` in circle mode); ``colorbar``, the density image's colour bar (particles per
    pixel) when one was asked for and the layer is in density mode, else ``None``; ``bounds``,
    ``shape``, ``max_circles``. The mode is chosen from the particle count at every update, so a
    layer switches representation if the count crosses ``max_circles``. The drawing options
    (``color``, ``cmap``, ``norm``, ``alpha``, ``zorder``, ``marker_points``, ``colorbar``)
    are :func:`draw_particles`'s.
    """

    def __init__(
        self,
        ax: Any,
        bounds: tuple,
        shape: tuple | None,
        max_circles: int,
        color: Any,
        cmap: Any,
        norm: Any,
        alpha: float,
        zorder: float,
        marker_points: float,
        colorbar: Any = False,
    ) -> None:
        # True: a colour bar beside ax; an Axes: the colour bar drawn into it.
        self.cax = colorbar if hasattr(colorbar, "figure") else None
        self.want_colorbar = self.cax is not None or bool(colorbar)
        self.colorbar = None
        self.ax = ax
        self.bounds = bounds
        self.shape = shape
        self.max_circles = max_circles
        self.color = color
        self.cmap = cmap
        self.alpha = alpha
        self.zorder = zorder
        self.marker_points = marker_points
        self._fixed_norm = norm
        self.mode = None
        self.artist = None
        self.image = None
        self._units = None
        self._r = None

    # -- circles
    def _radii(self, r, n):
        if r is None:
            return None
        r = np.asarray(r, dtype=np.float64)
        if r.ndim == 0:
            return np.full(n, float(r))
        r = r.reshape(-1)
        if r.shape[0] != n:
            raise ValueError(
                f"r must be a scalar or one radius per particle ({n}), got {r.shape[0]} radii"
            )
        return r

    def _circles(self, xs, ys, r):
        from matplotlib.collections import EllipseCollection

        n = xs.shape[0]
        offsets = np.column_stack([xs, ys])
        radii = self._radii(r, n)
        if radii is None:  # no radii: fixed-size dots, marker_points across
            size, units = np.full(n, float(self.marker_points)), "points"
        else:
            size, units = 2.0 * radii, "xy"
        if self.mode == "circles" and self.artist is not None and self._units == units:
            self.artist.set_offsets(offsets)
            self.artist.set_widths(size)
            self.artist.set_heights(size)
            return
        self._drop()
        self._units = units
        self.artist = EllipseCollection(
            size,
            size,
            np.zeros(n),
            units=units,
            offsets=offsets,
            offset_transform=self.ax.transData,
            facecolors=self.color,
            edgecolors="none",
            alpha=self.alpha,
            zorder=self.zorder + 1,
        )
        self.ax.add_collection(self.artist, autolim=False)
        self.mode = "circles"

    # -- density image
    def _density(self, xs, ys):
        if self.shape is None:
            self.shape = _axes_image_shape(self.ax, self.bounds)
        img = density_image(xs, ys, self.bounds, self.shape)
        shown = np.ma.masked_less_equal(img, 0.0)
        vmax = max(float(img.max()), 1.0)
        if self.mode == "density" and self.artist is not None:
            self.artist.set_data(shown)
            if self._fixed_norm is None:
                self.artist.norm.vmax = vmax
                if self.colorbar is not None:  # a new range resets the bar's tick labels
                    plain_log_ticks(self.colorbar)
        else:
            self._drop()
            norm = self._fixed_norm if self._fixed_norm is not None else density_norm(vmax)
            (x0, x1), (y0, y1) = self.bounds
            self.artist = self.ax.imshow(
                shown,
                origin="lower",
                extent=(x0, x1, y0, y1),
                cmap=self.cmap,
                norm=norm,
                interpolation="nearest",
                alpha=self.alpha,
                zorder=self.zorder,
                aspect=self.ax.get_aspect(),
            )
            self.mode = "density"
            if self.cax is not None:
                self.cax.set_visible(True)
                self.colorbar = self.ax.figure.colorbar(
                    self.artist, cax=self.cax, label="particles per pixel"
                )
            elif self.want_colorbar:
                # fraction/pad: a bar as tall as a square axes beside it.
                self.colorbar = self.ax.figure.colorbar(
                    self.artist, ax=self.ax, label="particles per pixel", fraction=0.046, pad=0.03
                )
            if self.colorbar is not None:
                plain_log_ticks(self.colorbar)
        self.image = img

    def _drop(self):
        if self.colorbar is not None:
            if self.cax is not None:  # keep the axes it was given, empty and hidden
                self.cax.cla()
                self.cax.set_visible(False)
            else:
                self.colorbar.remove()
            self.colorbar = None
        if self.artist is not None:
            self.artist.remove()
        self.artist, self.image, self.mode = None, None, None

    def update(self, x: Any, y: Any, r: Any = None) -> tuple:
        """Redraw for new particle positions ``x``, ``y`` (data units).

        ``r``: new radii as in :func:`draw_particles`; ``None`` keeps the previous ones. Returns
        ``(artist,)``, the artists to redraw with ``FuncAnimation(blit=True)``.
        """
        if r is None:
            r = self._r
        self._r = r
        xs, ys = reals(x, "x"), reals(y, "y")
        if xs.shape != ys.shape:
            raise ValueError(
                f"x and y must have the same number of points, got {xs.size} and {ys.size}"
            )
        if xs.shape[0] <= self.max_circles:
            self._circles(xs, ys, r)
        else:
            self._density(xs, ys)
        return (self.artist,)

    def remove(self) -> None:
        """Take the particles off the axes."""
        self._drop()


def draw_particles(
    ax: Any,
    x: Any,
    y: Any,
    r: Any = None,
    bounds: Any = None,
    max_circles: int = DEFAULT_MAX_CIRCLES,
    shape: tuple | None = None,
    color: Any = PARTICLE_COLOR,
    cmap: Any = None,
    norm: Any = None,
    alpha: float = 0.8,
    zorder: float = 4,
    marker_points: float = 4.0,
    colorbar: Any = False,
) -> ParticleLayer:
    """Draw particles on ``ax``: circles for up to ``max_circles`` particles, else a density image.

    ``x``, ``y``: particle centres (data units), arrays of equal size. ``r``: radii (data units,
    scalar or one per particle), used for circles; without it circles are dots
    ``marker_points`` points across. ``bounds``: ``[(x0, x1), (y0, y1)]`` covered by the
    density image, by default the axes' current limits (after :func:`fastsdf.plot_sdf`, the SDF's
    bounds); particles outside are not shown. ``shape``: ``(H, W)`` pixels of the density image,
    by default one per screen pixel of the axes. ``color``, ``alpha``: the circles' face colour
    and opacity. ``cmap``, ``norm``: colour map and normalisation of the density image (default:
    an orange-to-brown map, logarithmic from 1 to the busiest pixel's count, rescaled each
    frame; empty pixels are transparent). ``zorder``: the image's z-order (circles get one
    more), above the SDF's fill and lines. ``colorbar``: ``True`` adds a colour bar of particles
    per pixel beside the axes while the density image is shown; an axes draws it there instead
    (hidden while particles are drawn as circles).

    The density image counts particle centres per pixel (see :func:`density_image`); radii do
    not enlarge it. Returns a :class:`ParticleLayer`; call ``layer.update(x, y)`` for each
    animation frame (it returns the artists to blit).
    """
    if bounds is None:
        bounds = (ax.get_xlim(), ax.get_ylim())
        bounds = tuple((min(b), max(b)) for b in bounds)
    bounds = check_bounds(bounds)
    max_circles = count(max_circles, "max_circles", 0)
    if shape is not None:
        shape = check_shape(shape)
    layer = ParticleLayer(
        ax,
        bounds,
        shape,
        max_circles,
        color,
        cmap if cmap is not None else _particle_cmap(),
        norm,
        alpha,
        zorder,
        marker_points,
        colorbar,
    )
    layer.update(x, y, r)
    return layer


# ---------------------------------------------------------------------------------------------
# A world with particles in one figure; animations of a running simulation; saving them.


#: The width (inches) of a figure that :func:`render_frame` sizes to its bounds, and the
#: most its axes may be tall.
FRAME_WIDTH = 6.4
FRAME_MAX_HEIGHT = 6.4


def world_figure(
    f: Any,
    bounds: Any,
    samples: int,
    figsize: tuple | None,
    dpi: float,
    ticks: bool = True,
    bar: bool = True,
    title: bool = True,
) -> tuple:
    """``(fig, ax, cax)``: ``f``'s filled view on ``ax``, and a hidden axes ``cax`` for a colour
    bar beside it, laid out by hand so that nothing is cut and no margin is wasted (matplotlib's
    layout engines misplace a colour bar beside an equal-aspect axes). ``figsize=None``: a
    figure :data:`FRAME_WIDTH` wide (narrower for a tall world, whose axes stop at
    :data:`FRAME_MAX_HEIGHT`) as tall as the bounds' aspect needs, with room for the colour
    bar only with ``bar`` (without, the same axes in a narrower figure) and for a title only
    with ``title``."""
    from matplotlib.figure import Figure

    from fastsdf.viz.plotting import plot_sdf

    (x0, x1), (y0, y1) = check_bounds(bounds)
    left, bottom = (0.75, 0.47) if ticks else (0.15, 0.15)
    top = 0.32 if title else (0.15 if ticks else 0.1)
    # the colour bar: gap, width, room for its ticks and label (1.2 in all; else room for a
    # tick label)
    gap, width, right = (0.15, 0.2, 0.85) if bar else (0.0, 0.0, 0.3 if ticks else 0.15)
    aspect = (y1 - y0) / (x1 - x0)
    if figsize is None:  # the axes as wide with or without a colour bar: the figure narrower
        w = min(FRAME_WIDTH - left - 1.2, FRAME_MAX_HEIGHT / aspect)
        figsize = (round(left + w + gap + width + right, 2), round(bottom + w * aspect + top, 2))
    fig = Figure(figsize=figsize, dpi=dpi)
    W, H = fig.get_size_inches()
    w = min(W - left - gap - width - right, (H - bottom - top) / aspect)
    h = w * aspect
    ax = fig.add_axes((left / W, bottom / H, w / W, h / H))
    cax = fig.add_axes(((left + w + gap) / W, bottom / H, max(width, 0.01) / W, h / H))
    cax.set_visible(False)
    plot_sdf(
        fig,
        ax,
        f,
        bounds=bounds,
        samples=samples,
        show_quiver=False,
        show_isolines="zero",
        filled=True,
        ticks=ticks,
    )
    return fig, ax, cax


def render_frame(
    f: Any,
    x: Any,
    y: Any,
    r: Any = None,
    bounds: Any = ((-2, 2), (-2, 2)),
    out_png: str | None = None,
    title: str | None = None,
    samples: int = 400,
    max_circles: int | None = None,
    figsize: tuple | None = None,
    dpi: float = 100,
    colorbar: bool = True,
    ticks: bool = True,
    vmax: float | None = None,
) -> Any:
    """Draw the SDF ``f`` and particles at ``(x, y)`` in one figure, and save it as a PNG.

    The figure shows ``f``'s filled view (solid in :data:`fastsdf.viz.plotting.SOLID_COLOR`, free
    space in :data:`fastsdf.viz.plotting.BACKGROUND_COLOR`) with its zero contour, over ``bounds``
    (data units, sampled ``samples`` times per axis, axes labelled in data units unless
    ``ticks=False``), and the particles on top via :func:`draw_particles`: circles of radius
    ``r`` (data units; scalar or per particle) up to ``max_circles`` particles (default
    :data:`DEFAULT_MAX_CIRCLES`), a density image above that, with a colour bar of particles per
    pixel when ``colorbar``, scaled by :func:`density_norm` up to ``vmax`` particles per pixel
    (``None``: the busiest pixel's count; give a video's ``vmax`` to colour the picture as its
    frames). ``title`` is the axes title (say what is shown: the simulated time,
    the step). The figure is ``figsize`` inches at ``dpi`` (default: sized to ``bounds``,
    :data:`FRAME_WIDTH` wide with a colour bar, the same axes in a narrower figure without
    one), laid out
    without wasted margin (``fig.axes[1]`` holds the colour bar, hidden when there is none); if
    ``out_png`` is given it is saved there at that dpi, uncropped, so the axes' ``transData``
    maps data coordinates to the PNG's pixels (y counted from the bottom).

    Returns the ``matplotlib.figure.Figure`` (not registered with pyplot, so nothing needs
    closing; its axes is ``fig.axes[0]`` and the particle layer ``fig.particle_layer``).
    """
    max_circles = DEFAULT_MAX_CIRCLES if max_circles is None else max_circles
    # a colour bar: of the density image drawn above max_circles particles
    bar = bool(colorbar) and (figsize is not None or np.size(x) > max_circles)
    fig, ax, cax = world_figure(f, bounds, samples, figsize, dpi, ticks, bar, title is not None)
    layer = draw_particles(
        ax,
        x,
        y,
        r=r,
        bounds=bounds,
        colorbar=cax if colorbar else False,
        max_circles=max_circles,
        norm=None if vmax is None else density_norm(vmax),
    )
    fig.particle_layer = layer
    if title is not None:
        ax.set_title(title)
    if out_png is not None:
        fig.savefig(out_png, dpi=dpi)
    return fig


def _state(sim: Any) -> tuple:
    x = np.asarray(sim.p["x"], dtype=np.float64)
    return x[:, 0], x[:, 1], np.asarray(sim.p["r"], dtype=np.float64)


def sim_title(sim: Any, prefix: str = "") -> str:
    """``'<prefix>t = 1.23 s (step 37)'``: the simulated time of ``sim`` (``sim.t``, seconds
    since its last reset) and the steps of ``sim.dt`` it took."""
    t = float(getattr(sim, "t", float("nan")))
    dt = float(getattr(sim, "dt", float("nan")))
    if not math.isfinite(t):
        return prefix.rstrip(", ")
    steps = f" (step {round(t / dt)})" if math.isfinite(dt) and dt > 0 else ""
    return f"{prefix}t = {t:.2f} s{steps}"


def animate(
    sim: Any,
    ax: Any,
    frames: int = 100,
    steps_per_frame: Any = 1,
    *,
    use_wall_time: bool = False,
    interval: float | None = None,
    repeat: bool = False,
    title: str | None = "",
    colorbar: Any = False,
    advance: Any = None,
    blit: bool = False,
    **draw_kwargs: Any,
) -> Any:
    """A matplotlib animation of the running simulation ``sim`` on ``ax``, from its current state.

    Unlike the notebook's ``create_animation`` this never resets ``sim``: frame 0 shows the state
    as it is (after any ``sim.run(...)`` you did), and each later frame advances it by
    ``steps_per_frame`` steps (an int, or one count per frame) with ``sim.run`` (or with
    ``advance(k)`` if given, e.g. to time the steps), then redraws. With ``use_wall_time`` a frame
    advances by as many steps as fit in the wall-clock time since the previous frame (1 to 10),
    as the notebook's ``update(ax, use_wall_time=True)``. Drawing any existing world first
    (``fastsdf.plot_sdf(f, ax=ax, filled=True, show_quiver=False, show_isolines='zero')``) gives
    the usual picture; the particles are drawn by :func:`draw_particles` (``draw_kwargs`` go to
    it; ``colorbar``, ``True`` or an axes, adds a colour bar of particles per pixel to the
    density image).
    ``title``: when not ``None``, the axes title is ``title`` followed by each frame's simulated
    time and step count since the simulation's reset (:func:`sim_title`). ``interval``: delay
    between frames in ms (default the simulation's timestep times ``steps_per_frame``).
    ``repeat`` and ``blit`` are ``FuncAnimation``'s (a repeat continues the simulation).

    Each frame advances the simulation once more every time the animation is drawn or saved:
    saving it twice continues the simulation. Returns a ``FuncAnimation`` (keep a reference;
    :func:`save_animation` writes it to a file). The simulation object holds no artists.
    """
    from matplotlib.animation import FuncAnimation

    frames = count(frames, "frames", 1)
    if isinstance(steps_per_frame, numbers.Integral) and not isinstance(steps_per_frame, bool):
        schedule = [count(steps_per_frame, "steps_per_frame", 0)] * frames
    else:
        try:
            schedule = [count(k, "steps_per_frame", 0) for k in steps_per_frame]
        except TypeError:
            raise ValueError(
                f"steps_per_frame must be an integer >= 0 or one per frame, got "
                f"steps_per_frame={shown(steps_per_frame)}"
            ) from None
        if len(schedule) != frames:
            raise ValueError(
                f"steps_per_frame must have one count per frame ({frames}), got {len(schedule)}"
            )
    run = advance if advance is not None else sim.run
    dt = float(getattr(sim, "dt", 1 / 30))
    if interval is None:
        interval = 1000.0 * dt * max(1, schedule[-1])
    x, y, r = _state(sim)
    layer = draw_particles(ax, x, y, r=r, colorbar=colorbar, **draw_kwargs)
    state: dict[str, float | None] = {"wall": None}
    text = ax.set_title(sim_title(sim, title)) if title is not None else None

    def frame(i: int) -> tuple:
        if i > 0:
            k = schedule[i]
            if use_wall_time:
                now = time.perf_counter()
                if state["wall"] is not None:
                    k = int(min(10, max(1, round((now - state["wall"]) / dt))))
                state["wall"] = now
            if k:
                run(k)
        xs, ys, rs = _state(sim)
        artists = layer.update(xs, ys, rs)
        if text is not None and title is not None:
            text.set_text(sim_title(sim, title))
            artists = artists + (text,)
        return artists

    anim = FuncAnimation(
        ax.figure,
        frame,
        frames=frames,
        init_func=lambda: layer.update(*_state(sim)),
        interval=interval,
        blit=blit,
        repeat=repeat,
    )
    anim.particle_layer = layer  # type: ignore[attr-defined]  # the layer rides along
    return anim


#: Extensions :func:`save_animation` writes, and the matplotlib writer for each.
VIDEO_FORMATS = {
    ".mp4": "ffmpeg",
    ".m4v": "ffmpeg",
    ".mov": "ffmpeg",
    ".mkv": "ffmpeg",
    ".webm": "ffmpeg",
    ".gif": "pillow",
    ".html": "html",
}


def save_animation(
    anim: Any, path: str, fps: float | None = None, dpi: float | None = None, progress: bool = True
) -> str:
    """Write the matplotlib animation ``anim`` to ``path``; the writer follows the extension.

    ``.mp4`` (also ``.m4v``, ``.mov``, ``.mkv``, ``.webm``) uses ffmpeg: the system's, or the
    binary of the ``imageio-ffmpeg`` package (``pip install 'fastsdf[video]'``), so no system
    ffmpeg is needed; ``.gif`` uses Pillow (ships with matplotlib); ``.html`` matplotlib's
    JavaScript player. ``fps``: frames per second (default: from the animation's interval).
    ``dpi``: resolution (default the figure's). ``progress``: a progress bar on stderr while
    writing, shown only on a terminal. Returns the absolute path written.

    Raises ``ValueError`` for an extension it cannot write (naming the ones it can), and
    ``RuntimeError`` for a video extension when no ffmpeg can be found, saying what to install.
    """
    import os

    from matplotlib import animation

    from fastsdf.viz.progress import progress as _bar
    from fastsdf.viz.video import ffmpeg_available

    ext = os.path.splitext(str(path))[1].lower()
    if ext not in VIDEO_FORMATS:
        raise ValueError(
            f"path must end in one of {', '.join(VIDEO_FORMATS)}, got path={shown(path)}"
        )
    if fps is None:
        fps = 1000.0 / float(getattr(anim, "_interval", 50) or 50)
    kind = VIDEO_FORMATS[ext]
    if kind == "ffmpeg":
        if not ffmpeg_available():
            raise RuntimeError(
                f"writing {ext} needs ffmpeg: pip install 'fastsdf[video]' (it "
                f"installs imageio-ffmpeg, which ships one), or install ffmpeg, "
                f"or save a .gif"
            )
        # (matplotlib's stubs say int, its writers take any frame rate)
        writer: animation.AbstractMovieWriter = animation.FFMpegWriter(
            fps=fps,  # type: ignore[arg-type]
            bitrate=2400 if ext != ".webm" else -1,
        )
    elif kind == "pillow":
        writer = animation.PillowWriter(fps=fps)  # type: ignore[arg-type]
    else:
        writer = animation.HTMLWriter(fps=fps, embed_frames=True)  # type: ignore[arg-type]
    total = getattr(anim, "_save_count", None) or 0
    bar_options: dict[str, Any] = {} if progress else {"disable": True}
    with _bar(total, f"writing {os.path.basename(str(path))}", **bar_options) as bar:
        anim.save(str(path), writer=writer, dpi=dpi, progress_callback=lambda i, n: bar.update(1))
    return os.path.abspath(str(path))


# ---------------------------------------------------------------------------------------------
# The notebook's reset(ax) / update(ax): a simulation drawn on an axes, state kept here.

_VIEWS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def notebook_draw(sim: Any, ax: Any, new: bool) -> tuple:
    """Draw ``sim``'s particles on ``ax`` (``new``: replacing its previous drawing); returns the
    artists. ``ParticleSimulation.reset(ax)`` / ``update(ax)`` call this; the drawing is kept
    here, keyed by the simulation, not inside it."""
    x, y, r = _state(sim)
    layer = _VIEWS.get(sim)
    if new or layer is None or layer.ax is not ax:
        if layer is not None:
            layer.remove()
        layer = draw_particles(ax, x, y, r=r)
        _VIEWS[sim] = layer
        return (layer.artist,)
    return layer.update(x, y, r)


def notebook_animation(
    fig: Any,
    ax: Any,
    sim: Any,
    *,
    frames: int = 300,
    repeat: bool = True,
    use_wall_time: bool = False,
    interval: float | None = None,
) -> Any:
    """The drawing of :func:`fastsdf.particles.create_animation` (the notebook's helper), which
    states what ``fig``, ``ax``, ``sim``, ``frames``, ``repeat``, ``use_wall_time`` and
    ``interval`` do: a ``FuncAnimation`` whose frames call ``sim.update(ax, use_wall_time)``
    and whose init calls ``sim.reset(ax)``."""
    from matplotlib.animation import FuncAnimation

    if interval is None:
        interval = 1000.0 * getattr(sim, "dt", 1 / 30)

    def artists(returned):
        # Any simulation object with reset(ax) / update(ax, use_wall_time) works (the
        # notebook's own SimpleParticleSimulation returns nothing from reset): blitting needs
        # the artists, so fall back on sim.drawable.
        if returned is None:
            drawable = getattr(sim, "drawable", None)
            return (drawable,) if drawable is not None else ()
        return returned

    class _Animation(FuncAnimation):
        """``to_html5_video`` needs ffmpeg; without it, fall back to matplotlib's JavaScript
        player (``to_jshtml``) so the notebook's ``HTML(anim.to_html5_video())`` still works."""

        def to_html5_video(self, embed_limit=None):
            from matplotlib import animation, rcParams

            from fastsdf.viz.video import ffmpeg_available

            ffmpeg_available()  # points matplotlib at imageio-ffmpeg's binary when installed
            if animation.writers.is_available(rcParams["animation.writer"]):
                return super().to_html5_video(embed_limit=embed_limit)
            return self.to_jshtml(default_mode="loop" if repeat else "once")

    return _Animation(
        fig,
        lambda i: artists(sim.update(ax, use_wall_time=use_wall_time)),
        init_func=lambda: artists(sim.reset(ax)),
        frames=frames,
        interval=interval,
        blit=True,
        repeat=repeat,
    )
