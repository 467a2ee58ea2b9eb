"""The modelling DSL: primitives, set operations and the modelling context.

Usage mirrors the notebook's ``cgraph.sdf``::

    import fastsdf as sdf
    f = sdf.Halfspace(normal=[0, 1], d=-1.8) | sdf.Halfspace(normal=[1, 1], d=-1.8)
    with sdf.smoothness(10), sdf.transform(angle=-0.3, offset=[0.5, 0]):
        f |= sdf.Circle(center=[0, 0], radius=0.5) & sdf.Box(minc=[-1, -0.2], maxc=[1, 0.2])
    d, grad = f(x, y, compute_gradient=True)

Every shape is an :class:`SDF`: a :class:`fastsdf.function.Function` of the symbols ``x`` and
``y``, callable on points, negative inside and positive outside, in the units of the
coordinates. ``a | b`` is the union, ``a & b`` the intersection, ``a - b`` the difference. Under
``smoothness(k)`` with ``k > 0``, union and intersection become the notebook's exponential
blends (``-log(exp(-k a) + exp(-k b)) / k`` and its mirror), evaluated in a form that cannot
overflow; the difference is always hard, as in the notebook. ``transform(angle, offset)`` places
newly created primitives rotated by ``angle`` (radians, counter-clockwise) and then moved by
``offset``. Both context managers nest: transforms compose (the outer one applied last).

Beyond the notebook: more primitives with exact distances (:class:`Segment`, :class:`Capsule`,
:class:`RoundedBox`, :class:`OrientedBox`, :class:`Triangle`, :class:`EquilateralTriangle`,
:class:`RegularPolygon`, :class:`Polygon`, :class:`Star`, :class:`Ellipse`, :class:`Arc`,
:class:`Ring`), modifiers (``f.round(r)``, ``f.shell(t)``, ``f.scale(s)``, ``f.translate(o)``,
``f.rotate(a)``, ``f.mirror(axis)``, ``f.repeat(spacing, count)``), polynomial blends
(``a.union(b, k=0.1, kind='quadratic')``, ``smoothness(0.1, kind='cubic')``) and
``f.exactness`` (``'exact'``, ``'bound'`` or ``'none'``), tracked through all of them.
"""

from fastsdf.shapes import context, operations, primitives
from fastsdf.shapes.context import *  # noqa: F403 (each part's __all__, re-exported)
from fastsdf.shapes.exactness import EXACTNESS
from fastsdf.shapes.operations import *  # noqa: F403
from fastsdf.shapes.primitives import *  # noqa: F403

__all__ = ["EXACTNESS"]
__all__ += primitives.__all__
__all__ += operations.__all__
__all__ += context.__all__
