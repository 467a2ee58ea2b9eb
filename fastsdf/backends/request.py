"""One evaluation request: a call's points, validated once, and what to compute for them.

Every evaluator (the compiled kernel, the NumPy reference, the CUDA kernels, a grid's sampler)
takes a :class:`Request`; the entry points (``Function.__call__``, ``GridSDF.__call__``, ...)
build it with :func:`make_request`, the one place where coordinates are checked, flattened and
their bounds found.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from numpy.typing import ArrayLike

from fastsdf.backends.prune import snap_bounds
from fastsdf.expr.points import as_points, device_points

__all__ = ["KINDS", "Request", "make_request", "check_kind"]

#: What a call computes: the value; the value and gradient; and also dd/dt (scenes with time).
KINDS = ("v", "vg", "vgt")


def check_kind(kind: str) -> str:
    """``kind`` if it is one of :data:`KINDS`, else a ``ValueError`` naming it."""
    if kind not in KINDS:
        raise ValueError(f"kind must be 'v', 'vg' or 'vgt', got kind={kind!r}")
    return kind


@dataclass(frozen=True)
class Request:
    """The points of one call and what to compute: ``xs``, ``ys`` flat float64 arrays (NumPy, or
    numba device arrays for ``device='cuda'``), ``shape`` the caller's shape of the result
    (``()`` for scalar coordinates), ``kind`` (:data:`KINDS`), the time ``t`` and the values of
    the scene's other parameters ``params`` (in the kernels' order), the pruning choice
    ``prune`` (None: decided per call) and tolerance ``tol``, and ``template``: the caller's
    array, whose kind a CUDA answer takes."""

    xs: Any
    ys: Any
    shape: tuple
    kind: str = "v"
    t: float = 0.0
    params: tuple = ()
    prune: bool | None = None
    tol: float | None = None
    device: str = "cpu"
    template: Any = None
    _bounds: list = field(default_factory=list, repr=False, compare=False)

    @property
    def n(self) -> int:
        """The number of points."""
        return int(self.xs.shape[0])

    @property
    def gradient(self) -> bool:
        """Whether the gradient is asked for."""
        return self.kind != "v"

    @property
    def bounds(self) -> tuple | None:
        """The rectangle of the finite points, snapped outward (see
        :func:`fastsdf.backends.prune.snap_bounds`): found once per request, on the host."""
        if not self._bounds:
            self._bounds.append(snap_bounds(self.xs, self.ys))
        return self._bounds[0]

    def answer(self, results: tuple) -> Any:
        """The evaluator's flat results in the caller's shape: the value alone, or ``(value,
        gradient)``, or ``(value, gradient, dd/dt)``; scalars for scalar coordinates. A CUDA
        answer comes back as the caller's kind of array."""
        shapes = (self.shape, self.shape + (2,), self.shape)
        out = [r.reshape(s) for r, s in zip(results, shapes)]
        if self.device == "cuda":
            from fastsdf.device import like

            out = [like(r, self.template) for r in out]
        elif not self.shape:
            out[0] = out[0][()]
            if len(out) == 3:
                out[2] = out[2][()]
        return out[0] if len(out) == 1 else tuple(out)


def make_request(
    x: ArrayLike,
    y: ArrayLike | None = None,
    kind: str = "v",
    t: float = 0.0,
    params: tuple = (),
    prune: bool | None = None,
    tol: float | None = None,
    device: str = "cpu",
) -> Request:
    """The :class:`Request` of a call on ``x, y`` (``y`` omitted: ``x`` holds points along its
    last axis; see :func:`fastsdf.expr.points.as_points`), its coordinates checked once here.
    ``device='cuda'``: device arrays are used where they are, anything else is copied there."""
    check_kind(kind)
    if device == "cuda":
        xs, ys, shape = device_points(x, y)
    else:
        xs, ys, shape = as_points(x, y)
    return Request(xs, ys, shape, kind, float(t), tuple(params), prune, tol, device, x)
