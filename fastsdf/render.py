"""Drawing many particles: a compiled splat into a density image, and a per-frame particle layer.

Matplotlib draws one path per circle, which is fine for thousands of particles and hopeless for
millions. :func:`density_image` bins points into a pixel grid in a numba kernel (about 5-10 ms
for 1e6 points), and :func:`draw_particles` shows either circles (few particles) or that image
(many particles), returning a :class:`ParticleLayer` whose ``update(x, y)`` redraws it for each
frame of an animation.

Image convention (shared by every function here): an image of ``shape=(H, W)`` covers
``bounds=[(x0, x1), (y0, y1)]`` in data units; pixel ``[i, j]`` holds the points with
``x0 + j*(x1-x0)/W <= x < x0 + (j+1)*(x1-x0)/W`` and likewise ``i`` along ``y``, so **row 0 is
the bottom** (show it with ``imshow(origin='lower', extent=(x0, x1, y0, y1))``). The last row and
column also take the points exactly on ``x1`` / ``y1``: the binning is that of
``numpy.histogram2d(x, y, bins=(W, H), range=bounds)``, transposed. Points outside the bounds or
with a NaN/infinite coordinate are dropped.
"""

from __future__ import annotations

import math
import numbers

import numba
import numpy as np
from numba import njit, prange

from .plotting import check_bounds

__all__ = ["density_image", "draw_particles", "ParticleLayer",
           "PARTICLE_COLOR", "PARTICLE_CMAP_COLORS", "DEFAULT_MAX_CIRCLES"]

#: Face colour of particles drawn as circles.
PARTICLE_COLOR = "#e6550d"
#: Colours (low to high density) of the colour map of the density image. Every one is far from
#: the SDF fill colours of :mod:`fastsdf.plotting`, so particles stay visible over either.
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

def _check_count(value, name: str, minimum: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an integer >= {minimum}, got {name}={value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {name}={value!r}")
    return int(value)


def _check_shape(shape) -> tuple:
    try:
        h, w = shape
    except (TypeError, ValueError):
        raise ValueError(f"shape must be a pair (H, W) of positive integers, got shape={shape!r}") \
            from None
    if not all(isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_)) and v >= 1
               for v in (h, w)):
        raise ValueError(f"shape must be a pair (H, W) of positive integers, got shape={shape!r}")
    return int(h), int(w)


def _coords(v, name: str) -> np.ndarray:
    try:
        arr = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an array of real numbers, got {name} of type "
                         f"{type(v).__name__}") from None
    # 1-d arrays (strided views such as sim.p['x'][:, 0] included) go to the kernel as they are.
    return arr if arr.ndim == 1 else arr.reshape(-1)


# ---------------------------------------------------------------------------------------------
# Public API.

def density_image(x, y, bounds=((-2.0, 2.0), (-2.0, 2.0)), shape=(400, 400), weights=None,
                  parallel=None):
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
    h, w = _check_shape(shape)
    xs, ys = _coords(x, "x"), _coords(y, "y")
    if xs.shape != ys.shape:
        raise ValueError(f"x and y must have the same number of points, got {xs.size} and "
                         f"{ys.size}")
    use_w = weights is not None
    if use_w:
        ws = _coords(weights, "weights")
        if ws.shape != xs.shape:
            raise ValueError(f"weights must have one value per point ({xs.size}), got "
                             f"{ws.size} values")
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


def _axes_image_shape(ax, bounds) -> tuple:
    """One image pixel per screen pixel of ``ax`` over ``bounds`` (at the figure's dpi)."""
    try:
        ax.apply_aspect()
    except Exception:  # noqa: BLE001 - a layout that cannot be resolved yet: use the box as is
        pass
    box = ax.get_window_extent()
    (xl0, xl1), (yl0, yl1) = ax.get_xlim(), ax.get_ylim()
    (x0, x1), (y0, y1) = bounds
    w = box.width * (x1 - x0) / abs(xl1 - xl0) if xl1 != xl0 else box.width
    h = box.height * (y1 - y0) / abs(yl1 - yl0) if yl1 != yl0 else box.height
    return _clip_side(h), _clip_side(w)


def _clip_side(v: float) -> int:
    return int(min(MAX_IMAGE_SIDE, max(1, round(v)))) if math.isfinite(v) else 256


class ParticleLayer:
    """The particles drawn on an axes by :func:`draw_particles`; call :meth:`update` per frame.

    Attributes: ``ax``; ``mode``, ``'circles'`` or ``'density'``; ``artist``, the current
    matplotlib artist (an ``EllipseCollection`` or an ``AxesImage``); ``image``, the last density
    image (``None`` in circle mode); ``bounds``, ``shape``, ``max_circles``. The mode is chosen
    from the particle count at every update, so a layer switches representation if the count
    crosses ``max_circles``.
    """

    def __init__(self, ax, bounds, shape, max_circles, color, cmap, norm, alpha, zorder,
                 marker_points):
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
            raise ValueError(f"r must be a scalar or one radius per particle ({n}), got "
                             f"{r.shape[0]} radii")
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
        self.artist = EllipseCollection(size, size, np.zeros(n), units=units, offsets=offsets,
                                        offset_transform=self.ax.transData,
                                        facecolors=self.color, edgecolors="none",
                                        alpha=self.alpha, zorder=self.zorder + 1)
        self.ax.add_collection(self.artist, autolim=False)
        self.mode = "circles"

    # -- density image
    def _density(self, xs, ys):
        from matplotlib.colors import LogNorm
        if self.shape is None:
            self.shape = _axes_image_shape(self.ax, self.bounds)
        img = density_image(xs, ys, self.bounds, self.shape)
        shown = np.ma.masked_less_equal(img, 0.0)
        vmax = max(float(img.max()), 1.0)
        if self.mode == "density" and self.artist is not None:
            self.artist.set_data(shown)
            if self._fixed_norm is None:
                self.artist.norm.vmax = vmax
        else:
            self._drop()
            norm = self._fixed_norm if self._fixed_norm is not None else LogNorm(1.0, vmax)
            (x0, x1), (y0, y1) = self.bounds
            self.artist = self.ax.imshow(shown, origin="lower", extent=(x0, x1, y0, y1),
                                         cmap=self.cmap, norm=norm, interpolation="nearest",
                                         alpha=self.alpha, zorder=self.zorder,
                                         aspect=self.ax.get_aspect())
            self.mode = "density"
        self.image = img

    def _drop(self):
        if self.artist is not None:
            self.artist.remove()
        self.artist, self.image, self.mode = None, None, None

    def update(self, x, y, r=None):
        """Redraw for new particle positions ``x``, ``y`` (data units).

        ``r``: new radii as in :func:`draw_particles`; ``None`` keeps the previous ones. Returns
        ``(artist,)``, the artists to redraw with ``FuncAnimation(blit=True)``.
        """
        if r is None:
            r = self._r
        self._r = r
        xs, ys = _coords(x, "x"), _coords(y, "y")
        if xs.shape != ys.shape:
            raise ValueError(f"x and y must have the same number of points, got {xs.size} and "
                             f"{ys.size}")
        if xs.shape[0] <= self.max_circles:
            self._circles(xs, ys, r)
        else:
            self._density(xs, ys)
        return (self.artist,)

    def remove(self):
        """Take the particles off the axes."""
        self._drop()


def draw_particles(ax, x, y, r=None, bounds=None, max_circles=DEFAULT_MAX_CIRCLES, shape=None,
                   color=PARTICLE_COLOR, cmap=None, norm=None, alpha=0.8, zorder=4,
                   marker_points=4.0):
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
    more), above the SDF's fill and lines.

    The density image counts particle centres per pixel (see :func:`density_image`); radii do
    not enlarge it. Returns a :class:`ParticleLayer`; call ``layer.update(x, y)`` for each
    animation frame (it returns the artists to blit).
    """
    if bounds is None:
        bounds = (ax.get_xlim(), ax.get_ylim())
        bounds = tuple((min(b), max(b)) for b in bounds)
    bounds = check_bounds(bounds)
    max_circles = _check_count(max_circles, "max_circles", 0)
    if shape is not None:
        shape = _check_shape(shape)
    layer = ParticleLayer(ax, bounds, shape, max_circles, color,
                          cmap if cmap is not None else _particle_cmap(), norm, alpha, zorder,
                          marker_points)
    layer.update(x, y, r)
    return layer
