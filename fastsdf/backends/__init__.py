"""Evaluators of an expression: the compiled kernel (``kernel/``), the tape interpreter (``vm``),
the NumPy path (``npeval``) and pruning plans (``prune``)."""

__all__: list[str] = []
