"""Evaluators of an expression: the compiled kernel (``kernel/``), the CUDA target (``cuda``),
pruning plans (``prune``) and the request every evaluator takes (``request``). The NumPy path
is the op table's reference (:func:`fastsdf.expr.graph.evaluate_numpy`), called by
:meth:`fastsdf.function.CompiledSDF.numpy`."""

__all__: list[str] = []
