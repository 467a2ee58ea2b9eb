"""Contours out as vector files: SVG (no dependency) and DXF (the optional ``ezdxf`` package).

Both writers take ``path`` (the file to write) and ``shape``: a list of
:class:`fastsdf.geometry.contours.Contour`, or an SDF (any callable ``f(x, y)``), whose
contours at ``level`` (default 0: the boundary) are computed with
:func:`fastsdf.geometry.contours.contours` over ``bounds = [(x0, x1), (y0, y1)]`` (needed
then) on a ``resolution`` grid (nodes along x and y, default 512 x 512). They write
atomically: to a temporary file in the target's folder, then ``os.replace``, so a reader never
sees a half-written file, and return the contours written.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from fastsdf.files import atomic_write
from fastsdf.geometry.contours import Contour, contours

__all__ = ["svg_path_data", "to_dxf", "to_svg"]


def _as_contours(shape: Any, bounds: ArrayLike | None, resolution: Any, level: float) -> tuple:
    """``(list of Contour, bounds)`` from contours or an SDF."""
    if callable(shape):
        if bounds is None:
            raise ValueError(
                "bounds are needed to contour an SDF: pass bounds=[(x0, x1), (y0, y1)]"
            )
        return contours(shape, level=level, bounds=bounds, resolution=resolution), bounds
    try:
        items = list(shape)
    except TypeError:
        raise TypeError(
            f"expected an SDF or a list of Contour, got {type(shape).__name__}"
        ) from None
    out = []
    for c in items:
        if not isinstance(c, Contour):
            raise TypeError(
                f"expected Contour items (from fastsdf.geometry.contours), got {type(c).__name__}"
            )
        out.append(c)
    if bounds is None:
        pts = np.concatenate([c.points for c in out]) if out else np.zeros((1, 2))
        lo, hi = pts.min(0), pts.max(0)
        pad = 0.02 * max(float((hi - lo).max()), 1e-12)
        bounds = ((lo[0] - pad, hi[0] + pad), (lo[1] - pad, hi[1] + pad))
    return out, bounds


def svg_path_data(contour: Contour) -> str:
    """An SVG path ``d`` string of one contour in its own coordinates (``M x y L ... [Z]``),
    numbers written with 17 significant digits so they read back exactly."""
    p = contour.points
    pts = np.asarray(p, dtype=np.float64).tolist()
    words = [f"M {pts[0][0]!r} {pts[0][1]!r}"] + [f"L {x!r} {y!r}" for x, y in pts[1:]]
    if contour.closed:
        words.append("Z")
    return " ".join(words)


def to_svg(
    path: str | os.PathLike,
    shape: Any,
    bounds: ArrayLike | None = None,
    resolution: Any = (512, 512),
    level: float = 0.0,
    stroke: str = "black",
    stroke_width: float | None = None,
    fill: str = "none",
    width_px: int = 800,
) -> list[Contour]:
    """Write contours (or an SDF's zero contours) to an SVG file; returns the contours.

    Coordinates are kept as they are (y up) inside a group flipped by
    ``transform="matrix(1 0 0 -1 0 y0 + y1)"``, so a reader of the path data gets the
    function's coordinates back exactly; the ``viewBox`` is ``bounds`` (by default the
    contours' extent plus 2%). ``fill`` (an SVG colour, default ``'none'``) applies the
    even-odd rule (``fill-rule="evenodd"``), which shows holes as holes. ``stroke``: the
    lines' SVG colour; ``stroke_width`` in the coordinates' units, by default 1/500 of the
    view's width; ``width_px``: the picture's width in pixels (its height follows the
    bounds). ``path``, ``shape``, ``bounds``, ``resolution``, ``level``: see the module.
    """
    items, bounds = _as_contours(shape, bounds, resolution, level)
    (x0, x1), (y0, y1) = ((float(a), float(b)) for a, b in bounds)  # type: ignore
    w, h = x1 - x0, y1 - y0
    sw = w / 500.0 if stroke_width is None else float(stroke_width)
    height_px = max(1, int(round(width_px * h / w)))
    lines = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width_px}" '
        f'height="{height_px}" viewBox="{x0!r} {y0!r} {w!r} {h!r}">',
        f'<g transform="matrix(1 0 0 -1 0 {y0 + y1!r})" fill="{fill}" '
        f'fill-rule="evenodd" stroke="{stroke}" stroke-width="{sw!r}" '
        f'stroke-linejoin="round">',
    ]
    if fill != "none":  # one path, so that the even-odd rule sees holes inside solids
        lines.append(f'<path d="{" ".join(svg_path_data(c) for c in items)}"/>')
    else:
        lines += [f'<path d="{svg_path_data(c)}"/>' for c in items]
    lines += ["</g>", "</svg>", ""]
    text = "\n".join(lines)

    def write(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)

    atomic_write(path, write)
    return items


def to_dxf(
    path: str | os.PathLike,
    shape: Any,
    bounds: ArrayLike | None = None,
    resolution: Any = (512, 512),
    level: float = 0.0,
    layer: str = "CONTOURS",
) -> list[Contour]:
    """Write contours (or an SDF's zero contours) to a DXF file as lightweight polylines
    (closed ones flagged closed) on ``layer``; needs the optional ``ezdxf`` package
    (``pip install fastsdf[geometry]``). Returns the contours. ``path``, ``shape``,
    ``bounds``, ``resolution``, ``level``: see the module."""
    try:
        import ezdxf
    except ImportError:
        raise ImportError(
            "to_dxf needs the ezdxf package: pip install ezdxf (or fastsdf[geometry])"
        ) from None
    items, _ = _as_contours(shape, bounds, resolution, level)
    doc = ezdxf.new()
    msp = doc.modelspace()
    for c in items:
        msp.add_lwpolyline(
            c.points.tolist(), format="xy", close=c.closed, dxfattribs={"layer": layer}
        )
    atomic_write(path, doc.saveas)
    return items
