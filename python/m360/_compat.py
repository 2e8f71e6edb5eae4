"""Old spellings of public keywords, kept working with a DeprecationWarning."""

from __future__ import annotations

import functools
import inspect
import warnings
from collections.abc import Callable
from typing import Any, ParamSpec, TypeVar

from .errors import InputError

P = ParamSpec("P")
R = TypeVar("R")


def renamed(**old_to_new: str) -> Callable[[Callable[P, R]], Callable[P, R]]:
    """Accept each old keyword of the decorated function as its new one, with a warning.

    Passing both spellings is an :class:`m360.InputError`.
    """

    def decorate(function: Callable[P, R]) -> Callable[P, R]:
        names = list(inspect.signature(function).parameters)
        # How many positional arguments it takes to reach each new name.
        position = {new: names.index(new) for new in old_to_new.values()}

        @functools.wraps(function)
        def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
            for old, new in old_to_new.items():
                if old in kwargs:
                    warnings.warn(
                        f"{function.__qualname__}({old}=...) is deprecated; use {new}=...",
                        DeprecationWarning,
                        stacklevel=2,
                    )
                    if new in kwargs or len(args) > position[new]:
                        raise InputError(f"give {new} or {old} (deprecated), not both")
                    kwargs[new] = kwargs.pop(old)
            return function(*args, **kwargs)

        return wrapper

    return decorate


def moved(module: str, names: dict[str, tuple[Any, str]]) -> Callable[[str], Any]:
    """A module ``__getattr__`` serving names that moved (old name → (new module, new name))
    with a DeprecationWarning naming the new home."""

    def __getattr__(name: str) -> Any:
        if name in names:
            home, new = names[name]
            warnings.warn(
                f"{module}.{name} is deprecated; use {home.__name__}.{new}",
                DeprecationWarning,
                stacklevel=2,
            )
            return getattr(home, new)
        raise AttributeError(f"module {module!r} has no attribute {name!r}")

    return __getattr__
