"""Forces on particles: :class:`Gravity`, :class:`Drag`, :class:`FieldForce` (fused into the
compiled step), user ``@njit`` forces ``(x, y, vx, vy, m, t) -> (fx, fy)`` (fused) and Python
generators ``(p, t) -> (n, 2)`` (evaluated with NumPy before each step)."""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np
from numpy.typing import ArrayLike

from .. import __version__
from .._cache import load_module
from .._validate import vec2 as _vec2
from ..graph import Function
from .state import Particles, _real

__all__ = ["Gravity", "Drag", "FieldForce"]


def _gen_name(gen) -> str:
    name = getattr(gen, "__qualname__", None) or getattr(gen, "__name__", None)
    return name if isinstance(name, str) else repr(gen)



class Gravity:
    """Uniform gravity: force ``m * acceleration`` on every particle.

    ``acceleration`` is a pair in length/s**2; the default ``(0, -1)`` is the notebook's
    ``gravity(p, t) = p['m'][:, None] * [0, -1]``. In ``force_generators`` it is fused into the
    compiled step (no Python work per step); called as ``g(p, t)`` it returns the (n, 2) force
    array like any generator.
    """

    def __init__(self, acceleration: ArrayLike = (0.0, -1.0)):
        self.acceleration = _vec2(acceleration, "acceleration")

    def __call__(self, p, t):
        return np.asarray(p["m"], dtype=np.float64)[:, None] * self.acceleration

    def potential(self, p: Particles) -> np.ndarray:
        """Potential energy of each particle, ``-m (acceleration . x)`` (zero at the origin)."""
        x = np.asarray(p["x"], dtype=np.float64)
        return -np.asarray(p["m"], dtype=np.float64) * (x @ self.acceleration)

    def __repr__(self):
        return f"Gravity(acceleration={self.acceleration.tolist()})"


class Drag:
    """Linear drag: force ``-coefficient * v`` (coefficient in mass/s, >= 0).

    A particle of mass ``m`` loses velocity at the rate ``coefficient / m`` per second. Fused into
    the compiled step when in ``force_generators``; called as ``g(p, t)`` it returns the forces.
    """

    def __init__(self, coefficient: float = 0.1):
        c = _real(coefficient, "coefficient")
        if not (math.isfinite(c) and c >= 0.0):
            raise ValueError(f"coefficient must be finite and >= 0, got "
                             f"coefficient={coefficient!r}")
        self.coefficient = c

    def __call__(self, p, t):
        return -self.coefficient * np.asarray(p["v"], dtype=np.float64)

    def __repr__(self):
        return f"Drag(coefficient={self.coefficient!r})"


class FieldForce:
    """A force field written with the graph API, compiled and fused into the step.

    ``FieldForce(fx, fy)``: the force ``(fx(x, y), fy(x, y))`` (mass * length / s**2);
    ``FieldForce(potential=U)``: the conservative force ``-grad U(x, y)`` (U in energy units).
    With ``per_mass=True`` the field is an acceleration (the force is ``m`` times it), like
    :class:`Gravity`. Each of ``fx``, ``fy``, ``U`` is a :class:`fastsdf.graph.Function` (any
    fastsdf shape is one), or an expression of the symbols named ``x`` and ``y``. Each is
    compiled like an SDF (analytic gradient for the potential), so an attractor
    ``FieldForce(potential=-k / sym_sqrt(x**2 + y**2), per_mass=True)`` costs one inlined
    expression per particle and step. Called as ``f(p, t)`` it returns the (n, 2) forces
    (NumPy, like any generator).
    """

    def __init__(self, fx: Any = None, fy: Any = None, *, potential: Any = None,
                 per_mass: bool = False):
        if potential is None:
            if fx is None or fy is None:
                raise TypeError("FieldForce needs fx and fy, or potential=")
            self.parts = (_field_function(fx, "fx"), _field_function(fy, "fy"))
        else:
            if fx is not None or fy is not None:
                raise TypeError("FieldForce takes fx and fy, or potential=, not both")
            self.parts = (_field_function(potential, "potential"),)
        self.potential = potential is not None
        self.per_mass = bool(per_mass)
        self._dispatcher = None

    @property
    def dispatcher(self) -> Any:
        """The compiled ``@njit`` force ``(x, y, vx, vy, m, t) -> (fx, fy)`` (built on first
        use, from a content-hashed module in the kernel cache)."""
        if self._dispatcher is None:
            names = [f.compiled.module.__name__ for f in self.parts]
            scale = " * m" if self.per_mass else ""
            # A field with runtime parameters (or time) takes (x, y, t, params): the step's
            # time, and the parameters' values when the force was built (baked in).
            at = [", t, " + repr(f.param_tuple()) if f.compiled.parametric else ""
                  for f in self.parts]
            if self.potential:
                imports = f"from {names[0]} import point_vg as _u"
                body = f"    u, gx, gy = _u(x, y{at[0]})\n    return -gx{scale}, -gy{scale}"
            else:
                imports = (f"from {names[0]} import point_v as _fx\n"
                           f"from {names[1]} import point_v as _fy")
                body = f"    return _fx(x, y{at[0]}){scale}, _fy(x, y{at[1]}){scale}"
            source = (f'''"""Generated by fastsdf {__version__} (numba {numba.__version__}): a fused
force field. Dependencies: {", ".join(names)}."""
from numba import njit

{imports}


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def force(x, y, vx, vy, m, t):
{body}
''')
            self._dispatcher = load_module(source, prefix="fastsdf_force").force
            # A compiled field is usually long-latency arithmetic (square roots, divisions):
            # the step evaluates it for a batch of particles ahead (see fastsdf._step).
            self._dispatcher._fastsdf_batched = True
        return self._dispatcher

    def __call__(self, p, t):
        x = np.asarray(p["x"], dtype=np.float64)
        m = np.asarray(p["m"], dtype=np.float64) if self.per_mass else 1.0
        if self.potential:
            _, g = self.parts[0](x[:, 0], x[:, 1], compute_gradient=True)
            f = -g
        else:
            f = np.stack([self.parts[0](x[:, 0], x[:, 1]), self.parts[1](x[:, 0], x[:, 1])], 1)
        return f * (m[:, None] if self.per_mass else 1.0)

    def __repr__(self):
        what = f"potential={self.parts[0]!r}" if self.potential else \
            f"fx={self.parts[0]!r}, fy={self.parts[1]!r}"
        return f"FieldForce({what}, per_mass={self.per_mass})"


def _field_function(value, name: str) -> Function:
    """A Function of (x, y) from a Function or an expression of symbols named x and y."""
    if isinstance(value, Function):
        return value
    from ..graph import Symbol, as_expr
    try:
        expr = as_expr(value, name)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a fastsdf Function or an expression of x and y, got "
                        f"{name}={value!r}") from None
    return Function(expr, [Symbol("x"), Symbol("y")])

