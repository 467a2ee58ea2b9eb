"""What ``help()``, ``inspect.signature`` and the API pages show of a class."""

from __future__ import annotations

import inspect
import typing
from typing import TypeVar

__all__ = ["show_init_signature", "show_field_types"]

_Class = TypeVar("_Class", bound=type)


def show_init_signature(cls: type) -> None:
    """Make ``inspect.signature(cls)`` the parameters of ``cls.__init__``: a ``__new__`` that
    takes ``*args, **kwargs`` only to pick the class to build (a family member, a target)
    would otherwise be what they show."""
    init = inspect.signature(cls.__init__)  # type: ignore[misc]
    shown = init.replace(
        parameters=list(init.parameters.values())[1:],  # without self
        return_annotation=inspect.Signature.empty,
    )
    setattr(cls, "__signature__", shown)  # noqa: B010 (a dunder the type checker refuses)


def show_field_types(cls: _Class) -> _Class:
    """A ``typing.NamedTuple`` whose module has ``from __future__ import annotations`` keeps
    its fields' types as ``ForwardRef('float')``, which ``help()`` and ``inspect.signature``
    show; this puts the types themselves in their place (use as a class decorator)."""
    hints = typing.get_type_hints(cls)
    for holder in (cls, cls.__new__):
        annotations = getattr(holder, "__annotations__", None)
        if annotations is not None:
            annotations.update({k: v for k, v in hints.items() if k in annotations})
    return cls
