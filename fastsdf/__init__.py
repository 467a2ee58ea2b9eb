"""fastsdf: 2D signed distance functions compiled to parallel machine code.

``import fastsdf as sdf`` gives the notebook's modelling API (``sdf.Circle``, ``sdf.Halfspace``,
``sdf.Box``, ``|``, ``&``, ``-``, ``sdf.smoothness``, ``sdf.transform``) and more primitives,
modifiers and blends (``sdf.Ellipse``, ``sdf.Polygon``, ``f.round(r)``, ``f.repeat(...)``,
``a.union(b, k=0.1, kind='quadratic')``, ...); ``fastsdf.graph``
is the notebook's symbolic layer (``Symbol``, ``Function``, ``sym_*``). Distances are negative
inside, positive outside, in the units of the coordinates; all arithmetic is float64.
"""

from fastsdf.expr.graph import (
    Expr,
    Param,
    Symbol,
    sym_abs,
    sym_cos,
    sym_exp,
    sym_length,
    sym_log,
    sym_max,
    sym_min,
    sym_sin,
    sym_smax,
    sym_smin,
    sym_sqrt,
    t,
)
from fastsdf.fields.band import NarrowBandGridSDF
from fastsdf.fields.grid import GridSDF
from fastsdf.function import Function
from fastsdf.shapes import (
    SDF,
    Arc,
    Box,
    Capsule,
    Circle,
    Difference,
    Ellipse,
    EquilateralTriangle,
    Halfspace,
    Intersection,
    OrientedBox,
    Polygon,
    RegularPolygon,
    Ring,
    RoundedBox,
    Segment,
    Star,
    Triangle,
    Union,
    intersection,
    mirror,
    offset,
    repeat,
    rotate,
    scale,
    shell,
    smoothness,
    transform,
    translate,
    union,
)
from fastsdf.version import __version__
from fastsdf.viz.plotting import plot_sdf

__all__ = [
    "__version__",
    "Expr", "Function", "Symbol", "Param", "t",
    "sym_abs", "sym_cos", "sym_exp", "sym_length", "sym_log", "sym_max", "sym_min", "sym_sin",
    "sym_smax", "sym_smin", "sym_sqrt",
    "SDF", "Box", "Circle", "Difference", "Halfspace", "Intersection", "Union",
    "union", "intersection", "smoothness", "transform",
    "Segment", "Capsule", "RoundedBox", "OrientedBox", "EquilateralTriangle", "Triangle",
    "RegularPolygon", "Polygon", "Star", "Ellipse", "Arc", "Ring",
    "offset", "shell", "scale", "translate", "rotate", "mirror", "repeat",
    "GridSDF", "NarrowBandGridSDF", "plot_sdf",
]
