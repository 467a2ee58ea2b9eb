"""Expressions: the hash-consed graph, the op table, interval bounds, independent references of
the primitives, and the checks of every input."""

__all__: list[str] = []
