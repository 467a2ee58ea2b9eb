"""What ``help()``, ``inspect.signature`` and the API pages show of a class."""

from __future__ import annotations

import inspect

__all__ = ["show_init_signature"]


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
