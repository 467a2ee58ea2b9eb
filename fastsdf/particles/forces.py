"""Forces on particles: :class:`Gravity`, :class:`Drag`, :class:`FieldForce` (fused into the
compiled step), user ``@njit`` forces ``(x, y, vx, vy, m, t) -> (fx, fy)`` (fused) and Python
generators ``(p, t) -> (n, 2)`` (evaluated with NumPy before each step)."""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import numba
import numpy as np
from numba.core.dispatcher import Dispatcher
from numpy.typing import ArrayLike

from fastsdf.backends import load_module
from fastsdf.expr.validate import vec2 as _vec2
from fastsdf.function import Function
from fastsdf.introspect import show_field_types
from fastsdf.particles.state import Particles, _real
from fastsdf.version import __version__

__all__ = ["Gravity", "Drag", "FieldForce", "FusedForces", "fuse", "SAVED_FORCES"]


def _gen_name(gen: Any) -> str:
    name = getattr(gen, "__qualname__", None) or getattr(gen, "__name__", None)
    return name if isinstance(name, str) else repr(gen)


class Gravity:
    """Uniform gravity: force ``m * acceleration`` on every particle (and grain).

    Parameters
    ----------
    acceleration : (ax, ay), default (0, -1)
        In length/s**2, lengths in the world's coordinate units. The default is the notebook's
        ``gravity(p, t) = p['m'][:, None] * [0, -1]``: one length unit per second squared,
        downward (the library's scenes span 4 units: a fall of 4 takes about 2.8 s). For
        a world measured in metres, pass the Earth's: ``Gravity((0, -9.81))``.

    In ``force_generators`` it is fused into the compiled step (no Python work per step); for
    grains it is the granular engine's gravity. Called as ``g(p, t)`` it returns the (n, 2)
    force array like any generator.
    """

    def __init__(self, acceleration: ArrayLike = (0.0, -1.0)):
        self.acceleration = _vec2(acceleration, "acceleration")

    def __call__(self, p: Any, t: float) -> np.ndarray:
        return np.asarray(p["m"], dtype=np.float64)[:, None] * self.acceleration

    def potential(self, p: Particles) -> np.ndarray:
        """Potential energy of each particle of ``p`` (its ``'x'`` and ``'m'``),
        ``-m (acceleration . x)`` (zero at the origin)."""
        x = np.asarray(p["x"], dtype=np.float64)
        return -np.asarray(p["m"], dtype=np.float64) * (x @ self.acceleration)

    def __repr__(self) -> str:
        return f"Gravity(acceleration={self.acceleration.tolist()})"


class Drag:
    """Linear drag: force ``-coefficient * v``.

    Parameters
    ----------
    coefficient : float, default 0.1
        In mass/s, >= 0: a particle of mass ``m`` loses velocity at the rate
        ``coefficient / m`` per second.

    Fused into the compiled step when in ``force_generators``; called as ``g(p, t)`` it returns
    the forces.
    """

    def __init__(self, coefficient: float = 0.1):
        c = _real(coefficient, "coefficient")
        if not (math.isfinite(c) and c >= 0.0):
            raise ValueError(
                f"coefficient must be finite and >= 0, got coefficient={coefficient!r}"
            )
        self.coefficient = c

    def __call__(self, p: Any, t: float) -> np.ndarray:
        return -self.coefficient * np.asarray(p["v"], dtype=np.float64)

    def __repr__(self) -> str:
        return f"Drag(coefficient={self.coefficient!r})"


class FieldForce:
    """A force field written with the graph API, compiled and fused into the step.

    Parameters
    ----------
    fx, fy : Function or expression
        ``FieldForce(fx, fy)``: the force ``(fx(x, y), fy(x, y))`` (mass * length / s**2).
    potential : Function or expression
        ``FieldForce(potential=U)`` (in place of ``fx``, ``fy``): the conservative force
        ``-grad U(x, y)`` (U in energy units).
    per_mass : bool, default False
        The field is an acceleration (the force is ``m`` times it), like :class:`Gravity`.

    Each of ``fx``, ``fy``, ``U`` is a :class:`fastsdf.function.Function` (any
    fastsdf shape is one), or an expression of the symbols named ``x`` and ``y``. Each is
    compiled like an SDF (analytic gradient for the potential), so an attractor
    ``FieldForce(potential=-k / sym_sqrt(x**2 + y**2), per_mass=True)`` costs one inlined
    expression per particle and step. Called as ``f(p, t)`` it returns the (n, 2) forces
    (NumPy, like any generator).
    """

    def __init__(
        self, fx: Any = None, fy: Any = None, *, potential: Any = None, per_mass: bool = False
    ) -> None:
        if potential is None:
            if fx is None or fy is None:
                raise TypeError("FieldForce needs fx and fy, or potential=")
            self.parts: tuple[Function, ...] = (
                _field_function(fx, "fx"),
                _field_function(fy, "fy"),
            )
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
            at = [
                ", t, " + repr(f.param_tuple()) if f.compiled.parametric else "" for f in self.parts
            ]
            if self.potential:
                imports = f"from {names[0]} import point_vg as _u"
                body = f"    u, gx, gy = _u(x, y{at[0]})\n    return -gx{scale}, -gy{scale}"
            else:
                imports = (
                    f"from {names[0]} import point_v as _fx\nfrom {names[1]} import point_v as _fy"
                )
                body = f"    return _fx(x, y{at[0]}){scale}, _fy(x, y{at[1]}){scale}"
            source = f'''"""Generated by fastsdf {__version__} (numba {numba.__version__}): a fused
force field. Dependencies: {", ".join(names)}."""
from numba import njit

{imports}


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def force(x, y, vx, vy, m, t):
{body}
'''
            dispatcher = load_module(source, prefix="fastsdf_force").force
            # A compiled field is usually long-latency arithmetic (square roots, divisions):
            # the step evaluates it for a batch of particles ahead (see fastsdf.particles.kernels).
            dispatcher._fastsdf_batched = True
            self._dispatcher = dispatcher
        return self._dispatcher

    def __call__(self, p: Any, t: float) -> np.ndarray:
        x = np.asarray(p["x"], dtype=np.float64)
        if self.potential:
            _, g = self.parts[0](x[:, 0], x[:, 1], compute_gradient=True)
            f = -g
        else:
            f = np.stack([self.parts[0](x[:, 0], x[:, 1]), self.parts[1](x[:, 0], x[:, 1])], 1)
        if self.per_mass:
            f = f * np.asarray(p["m"], dtype=np.float64)[:, None]
        return f

    def __repr__(self) -> str:
        what = (
            f"potential={self.parts[0]!r}"
            if self.potential
            else f"fx={self.parts[0]!r}, fy={self.parts[1]!r}"
        )
        return f"FieldForce({what}, per_mass={self.per_mass})"


def _field_function(value: Any, name: str) -> Function:
    """A Function of (x, y) from a Function or an expression of symbols named x and y."""
    if isinstance(value, Function):
        return value
    from fastsdf.expr.graph import Symbol, as_expr

    try:
        expr = as_expr(value, name)
    except (TypeError, ValueError):
        raise TypeError(
            f"{name} must be a fastsdf Function or an expression of x and y, got {name}={value!r}"
        ) from None
    return Function(expr, [Symbol("x"), Symbol("y")])


def _field_force_args(force: FieldForce) -> dict:
    if force.potential:
        return {"potential": force.parts[0], "per_mass": force.per_mass}
    return {"fx": force.parts[0], "fy": force.parts[1], "per_mass": force.per_mass}


#: The forces a checkpoint (:mod:`fastsdf.particles.checkpoint`) stores as data: name ->
#: (class, the keyword arguments that rebuild an instance through its constructor: numbers,
#: and a FieldForce's functions as their expression graphs). Only these exact classes (not
#: subclasses); any other force (a numba @njit function, a Python generator) can only be pickled.
SAVED_FORCES: dict[str, tuple[type, Callable[[Any], dict]]] = {
    "Gravity": (Gravity, lambda g: {"acceleration": [float(a) for a in g.acceleration]}),
    "Drag": (Drag, lambda d: {"coefficient": float(d.coefficient)}),
    "FieldForce": (FieldForce, _field_force_args),
}


# ---------------------------------------------------------------------------------------------
# Sorting a simulation's force generators into what the step fuses and what runs in Python.

_WHAT = (
    "a force is Gravity(...), Drag(...), FieldForce(...), a numba @njit function "
    "(x, y, vx, vy, m, t) -> (fx, fy) or a Python callable (p, t) -> (n, 2) array"
)
_NJIT_ARGS = ("x", "y", "vx", "vy", "m", "t")


@show_field_types
class FusedForces(NamedTuple):
    """The forces of a step: the uniform acceleration ``(ax, ay)`` of the :class:`Gravity`
    generators, the :class:`Drag` coefficients' sum ``drag``, the Python generators
    ``python`` (evaluated with NumPy before each step) and the numba forces ``user`` fused
    into the compiled step (a :class:`FieldForce`'s compiled dispatcher among them)."""

    ax: float
    ay: float
    drag: float
    python: list
    user: tuple


def _takes(fn: Any, count: int) -> bool | None:
    """Whether ``fn`` can be called with ``count`` positional arguments (None: unknown)."""
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return None
    try:
        sig.bind(*range(count))
    except TypeError:
        return False
    return True


def fuse(force_generators: Sequence) -> FusedForces:
    """Sort ``force_generators`` (see :class:`FusedForces`); a TypeError names an entry that
    is not a force and says what a force must look like (a class given without its
    parentheses, a callable of the wrong arity)."""
    ax = ay = drag = 0.0
    python, user = [], []
    for k, gen in enumerate(force_generators):
        where = f"force_generators[{k}]"
        if isinstance(gen, type):
            name = gen.__name__
            hint = f"; add an instance: {name}()" if gen in (Gravity, Drag, FieldForce) else ""
            raise TypeError(f"{where} is the class {name}, not a force{hint} ({_WHAT})")
        if isinstance(gen, Gravity):
            ax += float(gen.acceleration[0])
            ay += float(gen.acceleration[1])
        elif isinstance(gen, Drag):
            drag += gen.coefficient
        elif isinstance(gen, Dispatcher):
            if _takes(gen.py_func, len(_NJIT_ARGS)) is False:
                raise TypeError(
                    f"{where}: the numba force {_gen_name(gen)} must take "
                    f"(x, y, vx, vy, m, t) and return (fx, fy); its signature is "
                    f"{inspect.signature(gen.py_func)}"
                )
            user.append(gen)
        elif isinstance(gen, FieldForce):
            user.append(gen.dispatcher)
        elif callable(gen):
            if _takes(gen, 2) is False:
                raise TypeError(
                    f"{where}: the force generator {_gen_name(gen)} must take "
                    f"(p, t) and return an (n, 2) array of forces; its signature "
                    f"is {inspect.signature(gen)}"
                )
            python.append(gen)
        else:
            raise TypeError(f"{where} is not a force: got {gen!r} ({_WHAT})")
    return FusedForces(ax, ay, drag, python, tuple(user))


def python_forces(gens: Sequence, p: Particles, t: float, out: np.ndarray) -> np.ndarray:
    """The sum of the Python generators' forces ``gen(p, t)`` into ``out`` ((n, 2)); checks
    what each returns (an (n, 2) array of finite real numbers)."""
    n = out.shape[0]
    out.fill(0.0)
    for gen in gens:
        name = _gen_name(gen)
        res = gen(p, t)
        try:
            arr = np.asarray(res)
        except Exception:
            raise TypeError(
                f"force generator {name} must return an (n, 2) array of forces, "
                f"got {type(res).__name__}"
            ) from None
        if arr.dtype.kind not in "iuf":
            raise TypeError(
                f"force generator {name} must return real forces, got an array of dtype {arr.dtype}"
            )
        if arr.shape != (n, 2):
            raise ValueError(
                f"force generator {name} must return forces of shape ({n}, 2), "
                f"got shape {arr.shape}"
            )
        if not np.all(np.isfinite(arr)):
            bad = int(np.flatnonzero(~np.isfinite(arr).all(axis=1))[0])
            raise ValueError(
                f"force generator {name} returned a non-finite force for "
                f"particle {bad}: {arr[bad].tolist()}"
            )
        out += arr
    return out
