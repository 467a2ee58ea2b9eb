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
from fastsdf.shapes import context as _context
from fastsdf.shapes import operations as _operations
from fastsdf.shapes import primitives as _primitives
from fastsdf.shapes.context import *  # noqa: F403 (the modelling API: fastsdf.shapes's names)
from fastsdf.shapes.operations import *  # noqa: F403
from fastsdf.shapes.primitives import *  # noqa: F403
from fastsdf.version import __version__
from fastsdf.viz.plotting import plot_sdf

__all__ = [
    "__version__",
    "Expr",
    "Function",
    "Symbol",
    "Param",
    "t",
    "sym_abs",
    "sym_cos",
    "sym_exp",
    "sym_length",
    "sym_log",
    "sym_max",
    "sym_min",
    "sym_sin",
    "sym_smax",
    "sym_smin",
    "sym_sqrt",
    "GridSDF",
    "NarrowBandGridSDF",
    "plot_sdf",
]
__all__ += _primitives.__all__
__all__ += _operations.__all__
__all__ += _context.__all__
