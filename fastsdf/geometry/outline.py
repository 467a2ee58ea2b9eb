"""SVG path data and text to exact SDFs (:class:`fastsdf.shapes.Outline`).

Lines and quadratic Bezier segments are kept as they are: their distances are exact (the
quadratic's closest point solves a cubic in closed form). Cubic segments and elliptical arcs
are converted within a tolerance ``tol`` (in the units of the result), with a proven bound:

* a cubic ``P0..P3`` against the quadratic with the same ends and control
  ``(3 (P1 + P2) - P0 - P3) / 4``: their difference is ``D t (1 - t) (1 - 2 t) / 2`` with
  ``D = P3 - 3 P2 + 3 P1 - P0``, at most ``sqrt(3) / 36 |D|``; splitting the cubic into ``n``
  equal parameter pieces divides ``D`` by ``n**3``, so ``n`` is chosen to make the bound at
  most ``tol / 2``;
* an arc, as an affine image of a circular arc, is split into pieces of angle ``theta`` whose
  standard cubic (handles ``4/3 tan(theta / 4)``) lies within
  ``max(rx, ry) * 2.7e-4 * (theta / (pi / 2))**6`` of it (the circle's bound for a quarter
  turn, 2.7e-4, scaling as the sixth power of the angle); pieces are chosen to make this at
  most ``tol / 2``, and the cubics are then converted as above.

Every point of the converted outline is therefore within ``tol`` of the true curve and vice
versa, so the SDF differs from the true one by at most ``tol`` (the sign can differ only within
``tol`` of the boundary).

Text goes through matplotlib's ``TextPath`` (TrueType glyphs are lines and quadratics: exact),
one outline per glyph group (a glyph's outer loop with its holes), joined by a hard union.
"""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from fastsdf.expr.validate import shown
from fastsdf.shapes import SDF, Outline, union

__all__ = [
    "SvgPath",
    "SvgFile",
    "Text",
    "cubic_to_quadratics",
    "path_segments",
    "text_segments",
]

#: Maximum distance of the standard cubic from a quarter circle of radius 1 (2.7253e-4).
_QUARTER_ARC_ERROR = 2.73e-4


def _check_tol(tol: Any) -> float:
    if (
        isinstance(tol, bool)
        or not isinstance(tol, (int, float))
        or not tol > 0
        or not math.isfinite(tol)
    ):
        raise ValueError(f"tol must be a positive finite number, got tol={shown(tol)}")
    return float(tol)


def cubic_to_quadratics(
    p0: ArrayLike, p1: ArrayLike, p2: ArrayLike, p3: ArrayLike, tol: float
) -> np.ndarray:
    """Quadratic segment rows ``[1, x0, y0, cx, cy, x1, y1]`` within ``tol / 2`` of the cubic
    Bezier ``p0, p1, p2, p3`` (see the module docstring for the bound)."""
    P = np.array([p0, p1, p2, p3], dtype=np.float64)
    third = P[3] - 3 * P[2] + 3 * P[1] - P[0]
    err = math.sqrt(3.0) / 36.0 * float(np.hypot(*third))
    n = max(1, math.ceil((err / (0.5 * tol)) ** (1.0 / 3.0) - 1e-12)) if err > 0 else 1
    rows = []
    for k in range(n):
        t0, t1 = k / n, (k + 1) / n
        c = _cubic_piece(P, t0, t1)
        ctrl = (3.0 * (c[1] + c[2]) - c[0] - c[3]) / 4.0
        rows.append([1.0, c[0, 0], c[0, 1], ctrl[0], ctrl[1], c[3, 0], c[3, 1]])
    return np.array(rows)


def _cubic_point(P: np.ndarray, t: float) -> np.ndarray:
    s = 1.0 - t
    return s**3 * P[0] + 3 * s * s * t * P[1] + 3 * s * t * t * P[2] + t**3 * P[3]


def _cubic_piece(P: np.ndarray, t0: float, t1: float) -> np.ndarray:
    """Control points of the cubic restricted to ``[t0, t1]`` (ends evaluated directly)."""

    def deriv(t):
        s = 1.0 - t
        return 3 * (s * s * (P[1] - P[0]) + 2 * s * t * (P[2] - P[1]) + t * t * (P[3] - P[2]))

    a, b = _cubic_point(P, t0), _cubic_point(P, t1)
    h = t1 - t0
    return np.array([a, a + deriv(t0) * h / 3.0, b - deriv(t1) * h / 3.0, b])


def path_segments(d: str, tol: float = 1e-4, flip_y: bool = True) -> np.ndarray:
    """Segment rows (see :class:`fastsdf.shapes.Outline`) of SVG path data ``d``.

    Parsed by ``svgelements`` (the optional ``geometry`` extra). Every subpath is closed (by a
    line back to its start where the data leaves it open, as SVG's fill does). ``flip_y``
    mirrors y (SVG's y axis points down), so the drawing appears upright in fastsdf's
    coordinates. Cubics and arcs are converted within ``tol`` (module docstring)."""
    try:
        from svgelements import Arc, Close, CubicBezier, Line, Move, Path, QuadraticBezier
    except ImportError:
        raise ImportError(
            "SVG paths need the svgelements package: pip install svgelements (or fastsdf[geometry])"
        ) from None
    tol = _check_tol(tol)
    if not isinstance(d, str):
        raise TypeError(f"d must be SVG path data (a string), got {type(d).__name__}")
    try:
        path = Path(d)
    except Exception as exc:  # svgelements raises various errors on bad data
        raise ValueError(f"could not parse the SVG path data d={d[:80]!r}: {exc}") from None
    sy = -1.0 if flip_y else 1.0
    rows: list = []
    start = None
    current = None

    def pt(p):
        return (float(p.x), sy * float(p.y))

    def close_subpath():
        if (
            start is not None
            and current is not None
            and np.hypot(current[0] - start[0], current[1] - start[1]) > 0
        ):
            rows.append([0.0, *current, 0.0, 0.0, *start])

    for seg in path:
        if isinstance(seg, Move):
            close_subpath()
            start = current = pt(seg.end)
            continue
        if current is None:
            raise ValueError("SVG path data must start with a move (M or m)")
        end = pt(seg.end)
        if isinstance(seg, (Line, Close)):
            if end != current:
                rows.append([0.0, *current, 0.0, 0.0, *end])
        elif isinstance(seg, QuadraticBezier):
            rows.append([1.0, *current, *pt(seg.control), *end])
        elif isinstance(seg, CubicBezier):
            rows.extend(
                cubic_to_quadratics(current, pt(seg.control1), pt(seg.control2), end, tol).tolist()
            )
        elif isinstance(seg, Arc):
            for c in _arc_cubics(seg, tol):
                p0, p1, p2, p3 = ((x, sy * y) for x, y in c)
                rows.extend(cubic_to_quadratics(p0, p1, p2, p3, tol).tolist())
            rows[-1][5:7] = end  # the arc's exact end (the pieces' rounding aside)
        else:
            raise ValueError(f"unsupported SVG path segment {type(seg).__name__}")
        current = end
        if isinstance(seg, Close):
            current = start
    close_subpath()
    if not rows:
        raise ValueError(f"the SVG path data d={d[:80]!r} draws nothing")
    return np.array(rows, dtype=np.float64)


def _arc_cubics(seg: Any, tol: float) -> list:
    """Cubics (four points each, SVG coordinates) within ``tol / 2`` of an elliptical arc:
    pieces of equal parametric angle ``theta`` with handles ``4/3 tan(theta / 4)`` along the
    tangent (module docstring for the bound)."""
    cx, cy = float(seg.center.x), float(seg.center.y)
    rx, ry = abs(float(seg.rx)), abs(float(seg.ry))
    phi = float(seg.get_rotation())
    sweep = float(seg.sweep)
    co, si = math.cos(phi), math.sin(phi)

    def at(th: float, dx: float = 0.0, dy: float = 0.0) -> tuple:
        ex, ey = rx * math.cos(th), ry * math.sin(th)
        tx, ty = -rx * math.sin(th), ry * math.cos(th)
        ex, ey = ex + dx * tx, ey + dx * ty
        return (cx + co * ex - si * ey, cy + si * ex + co * ey)

    sx, sy = float(seg.start.x) - cx, float(seg.start.y) - cy
    ux, uy = co * sx + si * sy, -si * sx + co * sy  # unrotated start
    th0 = math.atan2(uy / ry, ux / rx) if rx > 0 and ry > 0 else 0.0
    r = max(rx, ry)
    piece = 0.5 * math.pi * (0.5 * tol / max(r * _QUARTER_ARC_ERROR, 1e-300)) ** (1 / 6)
    n = max(1, math.ceil(abs(sweep) / piece))
    step = sweep / n
    k = 4.0 / 3.0 * math.tan(step / 4.0)
    out = []
    for i in range(n):
        a, b = th0 + i * step, th0 + (i + 1) * step
        out.append((at(a), at(a, k), at(b, -k), at(b)))
    return out


def SvgPath(
    d: str,
    fill_rule: str = "nonzero",
    tol: float = 1e-4,
    flip_y: bool = True,
    scale: float = 1.0,
    offset: ArrayLike = (0.0, 0.0),
) -> SDF:
    """The region an SVG path's data ``d`` fills, as an exact SDF (an
    :class:`fastsdf.shapes.Outline`): ``fill_rule`` as SVG's ``fill-rule`` (``'nonzero'``, its
    default, or ``'evenodd'``); coordinates multiplied by ``scale`` then moved by ``offset``
    (after the y flip, see :func:`path_segments`); ``tol`` (> 0, default 1e-4) bounds the
    error of cubics and arcs in the result's units. ``flip_y`` (default True) negates y, as
    SVG's y axis points down."""
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not scale > 0:
        raise ValueError(f"scale must be a positive number, got scale={shown(scale)}")
    off = np.asarray(offset, dtype=np.float64)
    if off.shape != (2,) or not np.isfinite(off).all():
        raise ValueError(f"offset must be a finite (x, y) pair, got offset={shown(offset)}")
    rows = path_segments(d, _check_tol(tol) / scale, flip_y)
    rows[:, 1:7] = rows[:, 1:7] * scale + np.tile(off, 3)
    return Outline(rows, fill_rule)


def SvgFile(
    path: str | os.PathLike,
    tol: float = 1e-4,
    flip_y: bool = True,
    scale: float = 1.0,
    offset: ArrayLike = (0.0, 0.0),
) -> SDF:
    """The region the ``<path>`` elements of an SVG file fill, as an exact SDF: the union of
    each path's :func:`SvgPath` (its own ``fill-rule``, its transforms applied), in the file's
    user units times ``scale``. Other elements (rectangles, circles, text) are not read: convert
    them to paths in the drawing program. Raises ``ValueError`` if the file holds no path.
    ``tol``, ``flip_y`` (default True: SVG's y points down, the result's up), ``scale`` and
    ``offset`` as for :func:`SvgPath`."""
    try:
        from svgelements import SVG
        from svgelements import Path as SvgElementPath
    except ImportError:
        raise ImportError(
            "SVG files need the svgelements package: pip install svgelements (or fastsdf[geometry])"
        ) from None
    name = os.fspath(path)
    if not os.path.isfile(name):
        raise ValueError(f"path must be an existing SVG file, got path={shown(name)}")
    shapes = []
    for element in SVG.parse(name).elements():
        if isinstance(element, SvgElementPath) and len(element) > 0:
            element.reify()  # apply its transform to the coordinates
            rule = str(element.values.get("fill-rule", "nonzero")).strip() or "nonzero"
            shapes.append(
                SvgPath(
                    element.d(), fill_rule=rule, tol=tol, flip_y=flip_y, scale=scale, offset=offset
                )
            )
    if not shapes:
        raise ValueError(f"the SVG file {shown(name)} holds no <path> element with data")
    return shapes[0] if len(shapes) == 1 else union(shapes)


def text_segments(
    text: str,
    size: float = 1.0,
    position: ArrayLike = (0.0, 0.0),
    family: str | None = None,
    tol: float = 1e-4,
) -> list[np.ndarray]:
    """Segment rows of ``text`` set by matplotlib's ``TextPath`` (baseline starting at
    ``position``, em size ``size``), one array per glyph group: each outermost loop with the
    loops inside it (holes), so that groups do not overlap. ``family``: a font family
    matplotlib knows (default: its default font, DejaVu Sans); ``tol`` (> 0, in the units of
    ``size``): the largest error of the glyphs' cubic curves converted to quadratics."""
    from matplotlib.font_manager import FontProperties
    from matplotlib.path import Path as MplPath
    from matplotlib.textpath import TextPath

    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"text must be a non-empty string, got text={shown(text)}")
    if isinstance(size, bool) or not isinstance(size, (int, float)) or not size > 0:
        raise ValueError(f"size must be a positive number, got size={shown(size)}")
    tol = _check_tol(tol)
    pos = np.asarray(position, dtype=np.float64)
    if pos.shape != (2,) or not np.isfinite(pos).all():
        raise ValueError(f"position must be a finite (x, y) pair, got position={shown(position)}")
    prop = FontProperties(family=family) if family else FontProperties()
    path = TextPath((float(pos[0]), float(pos[1])), text, size=float(size), prop=prop)
    loops: list = []
    rows: list = []
    start: Any = None
    current: Any = None
    for verts, code in path.iter_segments(simplify=False, curves=True):
        v = np.asarray(verts, dtype=np.float64).reshape(-1, 2)
        if code == MplPath.MOVETO:
            if rows:
                loops.append(_closed(rows, current, start))
            rows = []
            start = current = tuple(v[-1])
        elif code == MplPath.LINETO:
            end = tuple(v[-1])
            if end != current:
                rows.append([0.0, *current, 0.0, 0.0, *end])
            current = end
        elif code == MplPath.CURVE3:
            end = tuple(v[1])
            rows.append([1.0, *current, *v[0], *end])
            current = end
        elif code == MplPath.CURVE4:
            end = tuple(v[2])
            rows.extend(cubic_to_quadratics(current, v[0], v[1], end, tol).tolist())
            current = end
        elif code == MplPath.CLOSEPOLY:
            loops.append(_closed(rows, current, start))
            rows = []
            current = start
    if rows:
        loops.append(_closed(rows, current, start))
    loops = [np.array(lp) for lp in loops if lp]
    return _group_loops(loops)


def _closed(rows: list, current: Any, start: Any) -> list:
    if current is not None and start is not None and current != start:
        rows = rows + [[0.0, *current, 0.0, 0.0, *start]]
    return rows


def _inside_loop(point: np.ndarray, loop: np.ndarray) -> bool:
    """Even-odd test of ``point`` against a loop's control polygon flattened at its points."""
    # the flattened loop: ends and, for quadratics, the curve's midpoints, in order
    seq = []
    for r in loop:
        seq.append(r[1:3])
        if r[0] == 1:
            seq.append(0.25 * r[1:3] + 0.5 * r[3:5] + 0.25 * r[5:7])
    poly = np.array(seq)
    x, y = point
    a, b = poly, np.roll(poly, -1, axis=0)
    cross = (a[:, 1] > y) != (b[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xc = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return bool(np.sum(cross & (x < xc)) % 2)


def _group_loops(loops: list) -> list:
    """Group loops by containment: each loop goes with the outermost loop containing it."""
    n = len(loops)
    parent = list(range(n))
    boxes = []
    for lp in loops:
        pts = np.concatenate([lp[:, 1:3], lp[:, 5:7], lp[lp[:, 0] == 1, 3:5]])
        boxes.append((*pts.min(0), *pts.max(0)))
    for i in range(n):
        probe = 0.5 * (loops[i][0, 1:3] + loops[i][0, 5:7])
        for j in range(n):
            if i == j:
                continue
            bi, bj = boxes[i], boxes[j]
            contained = bj[0] <= bi[0] and bj[1] <= bi[1] and bi[2] <= bj[2] and bi[3] <= bj[3]
            if contained and _inside_loop(probe, loops[j]):
                area_j = (bj[2] - bj[0]) * (bj[3] - bj[1])
                pa = boxes[parent[i]]
                if parent[i] == i or area_j > (pa[2] - pa[0]) * (pa[3] - pa[1]):
                    parent[i] = j
    groups: dict = {}
    for i in range(n):
        root = i
        while parent[root] != root:
            root = parent[root]
        groups.setdefault(root, []).append(loops[i])
    return [np.concatenate(g) for g in groups.values()]


def Text(
    text: str,
    size: float = 1.0,
    position: ArrayLike = (0.0, 0.0),
    family: str | None = None,
    tol: float = 1e-4,
    split_glyphs: bool = False,
) -> SDF:
    """``text`` as an exact SDF: glyph outlines from matplotlib's ``TextPath`` (font
    ``family``, default matplotlib's), filled by the non-zero rule; it compiles and blends like
    any SDF. TrueType glyphs are exact; cubic (PostScript) glyphs are within ``tol``. Where
    glyphs overlap, the distance inside the overlap is a bound, not exact.

    Placement and size, in the world's length units (as a font sets type):

    - the baseline is the line ``y = position[1]``: letters without descenders stand on it
      (round ones such as 'o' and 's' overshoot it by about 1% of ``size``), descenders
      ('g', 'p', 'y') reach below it;
    - the pen starts at ``x = position[0]``: the first glyph's ink begins one left side bearing
      further right (a few hundredths of ``size``), and each glyph advances the pen by its
      width (with the font's kerning);
    - ``size`` is the em size (a font size in length units), not the height of the letters:
      in matplotlib's default font, DejaVu Sans, capitals are 0.729 ``size`` tall, 'p'
      descends 0.208 ``size`` below the baseline, and ``Text("fastsdf", size=1.0)`` spans
      x from 0.02 to 3.40 and y from -0.014 to 0.76 beyond ``position``.

    By default one :class:`fastsdf.shapes.Outline` holds every glyph (one loop over all
    segments per point, with bounding-box skips). ``split_glyphs=True`` builds a hard union of
    one outline per glyph group instead (each glyph solves at least one closest point per
    point, so it is slower for a word; tile pruning of long texts gives identical values)."""
    groups = text_segments(text, size, position, family, tol)
    if not groups:
        raise ValueError(f"text={shown(text)} has no visible glyphs")
    if not split_glyphs:
        return Outline(np.concatenate(groups), "nonzero")
    return union([Outline(g, "nonzero") for g in groups])
