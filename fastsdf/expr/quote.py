"""Values as error messages quote them (the one formatting every check of the library uses;
below the expression graph, which quotes the non-numbers it refuses)."""

from __future__ import annotations

import reprlib

import numpy as np

__all__ = ["shown"]


class _Described(str):
    """Text that quotes itself as it is (a value described rather than written out)."""

    def __repr__(self) -> str:
        return str(self)


def _plain(value: object) -> object:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        if value.size <= 16:
            return value.tolist()
        return _Described(f"<an array of shape {value.shape} and dtype {value.dtype}>")
    if type(value) is tuple:
        return tuple(_plain(v) for v in value)
    if type(value) is list:
        return [_plain(v) for v in value]
    return value


_SHORT = reprlib.Repr()
_SHORT.maxlist = _SHORT.maxtuple = 8
_SHORT.maxstring = _SHORT.maxother = 200


def shown(value: object) -> str:
    """``repr(value)`` as an error message quotes it: NumPy's numbers as plain numbers
    (``-0.1``, not ``np.float64(-0.1)``) and its small arrays as lists, inside tuples and
    lists too; long ones cut short (``[0, 1, 2, 3, 4, 5, 6, 7, ...]``)."""
    return _SHORT.repr(_plain(value))
