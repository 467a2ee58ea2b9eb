"""The notebook's ``cgraph`` module (``import fastsdf.graph as cg``): the symbolic layer of
:mod:`fastsdf.expr.graph` and the compiled :class:`fastsdf.function.Function`, under one name."""

from fastsdf.expr.graph import *  # noqa: F403
from fastsdf.expr.graph import __all__ as _graph_all
from fastsdf.function import Function

__all__ = [*_graph_all, "Function"]
