"""Evaluators of an expression: the compiled kernel (``kernel/``), the CUDA target (``cuda``),
pruning plans (``prune``) and the request every evaluator takes (``request``). The NumPy path
is the op table's reference (:func:`fastsdf.expr.graph.evaluate_numpy`), called by
:meth:`fastsdf.function.CompiledSDF.numpy`.

The layers above (the physics: :mod:`fastsdf.particles`, :mod:`fastsdf.granular`) reach the
evaluators through the names below only (an import-linter contract forbids them the
submodules):

- :func:`load_module`, :func:`hashed_import`: generated modules in the kernel cache (by content
  hash) and the import lines that carry a callee module's hash;
- :func:`exact_source`: the module of a scene's exact SDF as a C function for per-point callers
  (a grid's exact fallback, the particle step), with a pruning plan's header;
- :func:`plan_header`, :data:`HEADER_SIZE`: a pruning plan written into that header;
- :func:`call_vg_plan`: the numba intrinsic calling such a C function (value and gradient).
"""

from fastsdf.backends.kernel.cache import hashed_import, load_module
from fastsdf.backends.prune import HEADER_SIZE, call_vg_plan, exact_source, plan_header

__all__: list[str] = [
    "load_module",
    "hashed_import",
    "exact_source",
    "plan_header",
    "HEADER_SIZE",
    "call_vg_plan",
]
