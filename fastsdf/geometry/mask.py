"""Masks and grey-level images to signed distance grids.

Pixel layout follows images (and ``matplotlib.pyplot.imshow``): ``mask[row, col]``, columns
along x, rows along y, row 0 at the top (``origin='upper'``, the default) or at the bottom
(``origin='lower'``). ``bounds = [(x0, x1), (y0, y1)]`` is the image's extent, the outer edges
of its pixels, so a pixel is ``(x1 - x0) / ncols`` wide and ``(y1 - y0) / nrows`` high. The
distances are sampled at the pixel centres: the :class:`fastsdf.fields.grid.GridSDF` returned has
its
nodes there, so its own bounds are the extent inset by half a pixel on every side.

Binary masks (:func:`from_mask`): the boundary runs halfway between neighbouring pixels of
different phase; a pixel's value is the exact Euclidean distance from its centre to the nearest
pixel centre of the other phase, less half a pixel, negative on True pixels (see
:func:`fastsdf.geometry.edt.signed_distance_transform`). For a shape rasterised by its pixel
centres that puts every node within about a pixel of its true distance (first order in the
pixel size; the table in bench/RESULTS.md).

Grey-level images (:func:`from_image`): a pixel is inside where its level exceeds
``threshold``. Where the image is anti-aliased (levels strictly between 0 and 1, read as the
fraction of the pixel covered), the edge is placed inside the pixel from its level, as in
Gustavson and Strand's anti-aliased distance transform (2011): the distance from a pixel centre
to an edge crossing a pixel ``q`` is its distance to ``q``'s centre plus the offset of the edge
in ``q``, which a straight edge of the given coverage and direction determines exactly. The
nearest edge pixel is found by an exact distance transform and the nearest edge point by
vector propagation from there; the result is exact for straight edges near the boundary and a
close approximation elsewhere, except near corners (measured in bench/RESULTS.md).
"""

from __future__ import annotations

import errno
import math
import os
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from fastsdf.expr.validate import check_bounds, shown, vec2
from fastsdf.fields.grid import GridSDF
from fastsdf.function import Function
from fastsdf.geometry.edt import distance_transform, edt_kernel, signed_distance_transform
from fastsdf.notice import compiling_first

__all__ = ["from_mask", "from_image", "pixel_grid", "edge_offset"]

_ORIGINS = ("upper", "lower")


def _check_origin(origin: str) -> str:
    if origin not in _ORIGINS:
        raise ValueError(f"origin must be 'upper' or 'lower', got origin={shown(origin)}")
    return origin


def _extent(bounds: ArrayLike, shape: tuple) -> tuple:
    """Validated extent and pixel size ``(px, py)`` of an image of ``shape`` (rows, cols)."""
    (x0, x1), (y0, y1) = check_bounds(bounds)
    rows, cols = shape
    if rows < 2 or cols < 2:
        raise ValueError(f"the image needs at least 2 pixels along each axis, got shape {shape}")
    return ((x0, x1), (y0, y1)), ((x1 - x0) / cols, (y1 - y0) / rows)


def pixel_grid(values: np.ndarray, bounds: ArrayLike, origin: str = "upper") -> tuple:
    """Node values ``(ncols, nrows)`` in the grid's layout (x along the first axis, y up) and
    the grid's bounds (the pixel centres), from a per-pixel array ``values[row, col]`` with
    row 0 at the top (``origin='upper'``) or the bottom (``'lower'``)."""
    _check_origin(origin)
    ((x0, x1), (y0, y1)), (px, py) = _extent(bounds, values.shape)
    nodes = values[::-1].T if origin == "upper" else values.T
    grid_bounds = ((x0 + 0.5 * px, x1 - 0.5 * px), (y0 + 0.5 * py, y1 - 0.5 * py))
    return np.ascontiguousarray(nodes), grid_bounds


def _square(px: float, py: float) -> bool:
    return abs(px - py) <= 1e-9 * max(px, py)


def from_mask(
    mask: ArrayLike,
    bounds: ArrayLike,
    origin: str = "upper",
    exact: Function | None = None,
    mode: str = "nearest",
    dtype: Any = np.float64,
) -> GridSDF:
    """A signed distance grid from a binary mask: True (non-zero) pixels are inside.

    ``mask[row, col]`` with row 0 at the top (``origin='upper'``) or bottom (``'lower'``);
    ``bounds = [(x0, x1), (y0, y1)]`` the image's extent (outer pixel edges). Returns a
    :class:`fastsdf.fields.grid.GridSDF` with a node at every pixel centre (values only, gradients
    by
    finite differences), usable wherever a GridSDF is: calls, plots, particle simulations.
    Points outside the nodes' rectangle get the nearest edge's value (``mode='nearest'``)
    unless an ``exact`` SDF for the world beyond the image is given with ``mode='exact'``.
    The mask needs pixels of both phases. With square pixels neighbouring nodes differ by at
    most the pixel size, so the grid is marked ``exactness='exact'`` (safe for simulations'
    query skipping); with non-square pixels it is ``'none'``. ``dtype``: the grid's floats
    (float64, or float32 for half the memory).
    """
    a = np.asarray(mask)
    if a.ndim != 2:
        raise ValueError(f"mask must be a 2-d array (rows, cols), got shape {a.shape}")
    if a.dtype != np.bool_ and a.dtype.kind not in "iuf":
        raise TypeError(f"mask must be boolean or real, got dtype {a.dtype}")
    a = a.astype(bool) if a.dtype != np.bool_ else a
    _check_origin(origin)
    _, (px, py) = _extent(bounds, a.shape)
    if a.all() or not a.any():
        raise ValueError(
            "mask must hold pixels of both phases (inside and outside); got "
            f"{'all inside' if a.any() else 'all outside'}"
        )
    d = np.asarray(signed_distance_transform(a, sampling=(py, px)))
    nodes, gb = pixel_grid(d, bounds, origin)
    return GridSDF.from_samples(
        nodes,
        gb,
        exact=exact,
        mode=mode,
        dtype=dtype,
        exactness="exact" if _square(px, py) else "none",
    )


def edge_offset(gx: np.ndarray, gy: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """Distance from a pixel's centre to a straight edge crossing it, in pixels, positive when
    the centre is outside: the edge has normal direction ``(gx, gy)`` (any length, any sign)
    and covers the fraction ``coverage`` of the (unit) pixel. Exact for straight edges
    (Gustavson and Strand 2011, eq. 3-5); ``0.5 - coverage`` for axis-aligned normals."""
    gx = np.abs(np.asarray(gx, dtype=np.float64))
    gy = np.abs(np.asarray(gy, dtype=np.float64))
    a = np.clip(np.asarray(coverage, dtype=np.float64), 0.0, 1.0)
    gx, gy, a = np.broadcast_arrays(gx, gy, a)
    length = np.hypot(gx, gy)
    with np.errstate(invalid="ignore", divide="ignore"):
        ux = np.where(length > 0, gx / length, 1.0)
        uy = np.where(length > 0, gy / length, 0.0)
    big, small = np.maximum(ux, uy), np.minimum(ux, uy)  # fold into the first octant
    a1 = 0.5 * small / big
    corner = np.sqrt(2.0 * big * small * np.minimum(a, 1.0 - a))
    out = np.where(
        a < a1,
        0.5 * (big + small) - corner,
        np.where(a < 1.0 - a1, (0.5 - a) * big, -0.5 * (big + small) + corner),
    )
    return np.where(small == 0.0, 0.5 - a, out)


def _sobel(a: np.ndarray) -> tuple:
    """Isotropic Sobel gradient (weights 1, sqrt 2, 1) along rows and columns, edges padded."""
    p = np.pad(a, 1, mode="edge")
    r2 = math.sqrt(2.0)
    gr = (p[2:, :-2] + r2 * p[2:, 1:-1] + p[2:, 2:]) - (
        p[:-2, :-2] + r2 * p[:-2, 1:-1] + p[:-2, 2:]
    )
    gc = (p[:-2, 2:] + r2 * p[1:-1, 2:] + p[2:, 2:]) - (
        p[:-2, :-2] + r2 * p[1:-1, :-2] + p[2:, :-2]
    )
    return gr, gc


def _levels(image: np.ndarray, levels: Any) -> np.ndarray:
    if levels is None:
        if image.dtype.kind in "iu":
            info = np.iinfo(image.dtype)
            lo, hi = (
                (0.0, float(info.max))
                if image.dtype.kind == "u"
                else (float(info.min), float(info.max))
            )
        else:
            lo, hi = 0.0, 1.0
    else:
        lo, hi = vec2(levels, "levels").tolist()
        if lo == hi:
            raise ValueError(f"levels must be two different numbers, got levels={shown(levels)}")
    return (image.astype(np.float64) - lo) / (hi - lo)


def _read_image(path: str | os.PathLike) -> np.ndarray:
    """The pixels of the image file ``path`` (PNG, JPEG and the other formats Pillow reads,
    which matplotlib installs): 8-bit images as their integers, as an array of them would
    be; deeper ones by matplotlib's ``imread``, as levels on [0, 1]."""
    name = os.fspath(path)
    if not os.path.isfile(name):
        raise FileNotFoundError(errno.ENOENT, "image: no such file", name)
    from matplotlib.image import imread
    from PIL import Image

    try:
        with Image.open(name) as im:
            if im.mode in ("1", "L", "LA", "RGB", "RGBA"):
                return np.asarray(im)
            if not im.mode.startswith(("I", "F")):  # palette, CMYK, ...: 8-bit colours
                return np.asarray(im.convert("RGBA"))
        return np.asarray(imread(name))
    except (OSError, ValueError, SyntaxError) as exc:  # (Pillow's errors for unreadable data)
        raise ValueError(f"image: {shown(name)} could not be read as an image ({exc})") from exc


def _grey_levels(image: ArrayLike | str | os.PathLike, levels: Any) -> np.ndarray:
    """``image`` (an array or an image file's path) as grey levels on [0, 1]: colour channels
    averaged, an alpha channel laid over white."""
    if isinstance(image, (str, os.PathLike)):
        image = _read_image(image)
    img = np.asarray(image)
    if img.ndim == 0 or img.dtype == object:
        raise TypeError(
            f"image must be a path to an image file or an array of grey levels (rows, cols) "
            f"or colours (rows, cols, 3 or 4), got image={shown(image)} "
            f"({type(image).__name__})"
        )
    if img.dtype == np.bool_:
        img = img.astype(np.float64)
    if img.dtype.kind not in "iuf":
        raise TypeError(f"image must hold real numbers, got dtype {img.dtype}")
    if not (img.ndim == 2 or (img.ndim == 3 and img.shape[-1] in (1, 2, 3, 4))):
        raise ValueError(
            f"image must be grey levels (rows, cols) or colours (rows, cols, 3 or 4), got "
            f"shape {img.shape}"
        )
    g = _levels(img, levels)
    if g.ndim == 3:
        channels = g.shape[-1]
        alpha = g[..., -1] if channels in (2, 4) else None
        g = g[..., : 3 if channels >= 3 else 1].mean(axis=-1)
        if alpha is not None:
            g = g * alpha + (1.0 - alpha)
    if not np.isfinite(g).all():
        raise ValueError("image must be finite at every pixel")
    return g


def from_image(
    image: ArrayLike | str | os.PathLike,
    bounds: ArrayLike,
    threshold: float = 0.5,
    origin: str = "upper",
    levels: ArrayLike | None = None,
    dark_inside: bool = False,
    subpixel: bool = True,
    exact: Function | None = None,
    mode: str = "nearest",
    dtype: Any = np.float64,
) -> GridSDF:
    """A signed distance grid from a grey-level image: pixels brighter than ``threshold`` are
    inside (darker ones with ``dark_inside=True``).

    Parameters
    ----------
    image : path, or array (rows, cols) or (rows, cols, 3 or 4)
        An image file (``str`` or ``os.PathLike``: PNG, JPEG and whatever else Pillow
        reads; a missing file is a ``FileNotFoundError``) or its pixels. Colours are
        averaged to a grey level and an alpha channel is laid over white.
    bounds : [(x0, x1), (y0, y1)]
        The image's extent in the world's units: the outer edges of its pixels.
    threshold : float in (0, 1), default 0.5
        The grey level of the edge.
    origin : 'upper' (default) or 'lower'
        Where row 0 is, as for ``matplotlib.pyplot.imshow``.
    levels : (black, white) or None
        The levels read as 0 and 1. ``None``: unsigned integers are divided by their type's
        maximum (255 for 8-bit images), floats are taken as they are.
    dark_inside : bool, default False
        Dark pixels are inside.
    subpixel : bool, default True
        Anti-aliased pixels (levels strictly between 0 and 1, square pixels only) place the
        edge inside the pixel from their level (read as coverage, shifted so that
        ``threshold`` is the edge: see the module docstring); ``False``, or a hard black and
        white image, gives :func:`from_mask` of the thresholded image.
    exact, mode, dtype
        As in :func:`from_mask`.

    Returns a :class:`fastsdf.fields.grid.GridSDF` with a node at every pixel centre, marked
    ``exactness='none'`` when sub-pixel placement is used (its node differences are not
    bounded by the spacing).
    """
    g = _grey_levels(image, levels)
    if (
        not isinstance(threshold, (int, float, np.floating, np.integer))
        or not 0.0 < float(threshold) < 1.0
    ):
        raise ValueError(
            f"threshold must be a level strictly between 0 and 1, got threshold={shown(threshold)}"
        )
    if dark_inside:
        g = 1.0 - g
    t = float(threshold)
    cov = np.clip(g - t + 0.5, 0.0, 1.0)  # coverage whose half level is the threshold
    inside = cov > 0.5
    _check_origin(origin)
    _, (px, py) = _extent(bounds, g.shape)
    partial = (cov > 0.0) & (cov < 1.0)
    if not subpixel or not partial.any():
        return from_mask(inside, bounds, origin=origin, exact=exact, mode=mode, dtype=dtype)
    if not _square(px, py):
        raise ValueError(
            f"sub-pixel edges need square pixels, got {shown(px)} x {shown(py)} (choose "
            f"bounds in the image's aspect ratio, or subpixel=False)"
        )
    if inside.all() or not inside.any():
        raise ValueError("image must hold pixels on both sides of the threshold")
    with compiling_first("the distance transform of images", edt_kernel, _nearest_edge_point):
        d = _subpixel_distance(cov, inside, partial) * px
    nodes, gb = pixel_grid(d, bounds, origin)
    return GridSDF.from_samples(nodes, gb, exact=exact, mode=mode, dtype=dtype, exactness="none")


@njit(cache=True, nogil=True, error_model="numpy")
def _nearest_edge_point(er, ec, qi, qj):
    """Distance from each pixel centre to the nearest edge point ``(er, ec)[q]`` (``inf`` off
    edge pixels), starting from the nearest edge pixel ``(qi, qj)`` and improved by vector
    propagation (Danielsson's raster passes, as in Gustavson and Strand's transform): each
    pixel tries its nearest edge pixel's eight neighbours and its own neighbours' choices."""
    n, m = er.shape
    best = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            a, b = qi[i, j], qj[i, j]
            d = math.hypot(i - er[a, b], j - ec[a, b])
            for da in range(-1, 2):
                for db in range(-1, 2):
                    r, c = a + da, b + db
                    if 0 <= r < n and 0 <= c < m and er[r, c] != np.inf:
                        e = math.hypot(i - er[r, c], j - ec[r, c])
                        if e < d:
                            d, qi[i, j], qj[i, j] = e, r, c
            best[i, j] = d
    for sweep in range(2):
        step = 1 if sweep == 0 else -1
        i0, i1 = (0, n) if step == 1 else (n - 1, -1)
        j0, j1 = (0, m) if step == 1 else (m - 1, -1)
        for i in range(i0, i1, step):
            for j in range(j0, j1, step):
                for di, dj in ((-step, -step), (-step, 0), (-step, step), (0, -step)):
                    r, c = i + di, j + dj
                    if 0 <= r < n and 0 <= c < m:
                        a, b = qi[r, c], qj[r, c]
                        e = math.hypot(i - er[a, b], j - ec[a, b])
                        if e < best[i, j]:
                            best[i, j], qi[i, j], qj[i, j] = e, a, b
    return best


def _subpixel_distance(cov: np.ndarray, inside: np.ndarray, partial: np.ndarray) -> np.ndarray:
    """Signed distance in pixels from every pixel centre to the anti-aliased edge.

    Each edge pixel ``q`` (partly covered, or a hard edge: fully covered or empty next to an
    empty or full pixel of the other phase) gets an edge point ``e = q - offset * u`` with ``u``
    the outward normal (minus the Sobel gradient of the coverage) and ``offset`` from
    :func:`edge_offset`. A pixel within two pixels of its nearest edge pixel takes its distance
    to the edge's tangent line there (exact for straight edges); farther pixels their distance
    to the nearest edge point (:func:`_nearest_edge_point`). The sign is the pixel's phase
    (the offset's own sign on edge pixels)."""
    hard = np.zeros_like(inside)
    solid = ~partial
    for axis in (0, 1):
        a0 = [slice(None), slice(None)]
        a1 = [slice(None), slice(None)]
        a0[axis], a1[axis] = slice(1, None), slice(None, -1)
        t0, t1 = tuple(a0), tuple(a1)
        step = (inside[t0] != inside[t1]) & solid[t0] & solid[t1]
        hard[t0] |= step
        hard[t1] |= step
    edge = partial | hard
    di, (qi, qj) = distance_transform(~edge, return_indices=True)
    n, m = cov.shape
    rows, cols = np.indices(cov.shape)
    gr, gc = _sobel(cov)
    length = np.hypot(gr, gc)
    ok = length > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        ur = np.where(ok, -gr / length, 0.0)  # outward unit normal per pixel
        uc = np.where(ok, -gc / length, 0.0)
    off = edge_offset(gr, gc, cov)
    er = np.where(edge, rows - off * ur, np.inf)  # edge points (index units) of edge pixels
    ec = np.where(edge, cols - off * uc, np.inf)
    vr, vc = rows - er[qi, qj], cols - ec[qi, qj]
    line = np.abs(vr * ur[qi, qj] + vc * uc[qi, qj])
    # Far pixels: the nearest edge point (q's centre need not carry it: a barely covered
    # pixel's edge lies up to 0.7 pixel behind its centre), by propagation.
    point = _nearest_edge_point(er, ec, qi.astype(np.int64), qj.astype(np.int64))
    ok = ok[qi, qj]
    off = off[qi, qj]
    dist = np.where((di <= 2.0) & ok, line, point)
    return np.where(di == 0, off, np.where(inside, -dist, dist))
