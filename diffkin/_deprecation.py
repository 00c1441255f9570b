"""Deprecated names, kept for one release: each warns once (``DeprecationWarning``) and names its replacement.

The one place for the renames of issue #30 item 15; ``docs/api/deprecated.md`` lists them. Three forms:

- :func:`deprecated_alias` — an old function or method name calling the new one;
- :func:`renamed_arguments` — old keyword names accepted for the new ones;
- :func:`moved_names` — a module ``__getattr__`` for names whose one home is another module;
- :func:`reordered_target` — the target moved before ``q0``: old positional calls recognised by shape.
"""

from __future__ import annotations

import functools
import importlib
import warnings
from collections.abc import Callable

__all__ = ["deprecated_alias", "moved_names", "renamed_arguments", "reordered_target", "warn_deprecated"]

#: the old names that warned already in this process (once each; tests clear it)
_WARNED: set[str] = set()


def warn_deprecated(old: str, new: str, stacklevel: int = 3) -> None:
    """Warn once per process that ``old`` is deprecated in favour of ``new`` (removed in the next release)."""
    if old in _WARNED:
        return
    _WARNED.add(old)
    warnings.warn(f"{old} is deprecated and will be removed in the next release; use {new}",
                  DeprecationWarning, stacklevel=stacklevel)


def deprecated_alias(func: Callable, old: str, new: str) -> Callable:
    """``func`` under its old name ``old``: the same call, with a warning naming ``new``."""

    @functools.wraps(func)
    def alias(*args, **kwargs):
        warn_deprecated(old, new)
        return func(*args, **kwargs)

    alias.__doc__ = f"Deprecated alias of :func:`{new}` (removed in the next release)."
    alias.__deprecated__ = new
    return alias


def renamed_arguments(where: str, **renamed: str) -> Callable[[Callable], Callable]:
    """Accept the old keyword names of ``renamed`` (old -> new) for the decorated function's new ones.

    Giving both the old and the new name is a ``TypeError``, as any argument given twice.
    """

    def decorate(func: Callable) -> Callable:
        @functools.wraps(func)
        def wrapper(*args, **kwargs):
            for old in renamed.keys() & kwargs.keys():
                new = renamed[old]
                if new in kwargs:
                    raise TypeError(f"{where}() got both {new}= and its deprecated name {old}=")
                warn_deprecated(f"{where}({old}=...)", f"{where}({new}=...)")
                kwargs[new] = kwargs.pop(old)
            return func(*args, **kwargs)

        return wrapper

    return decorate


def reordered_target(where: str, q_name: str, old_order: Callable[..., bool]) -> Callable:
    """For ``f(chain, T_target, q0, ...)`` whose old order was ``f(chain, q0, T_target, ...)``: a
    positional call for which ``old_order(chain, a, b)`` says the old order (decided from the values' kinds
    and shapes) is swapped, with a warning; ``f(chain, q0, T_target=...)`` binds the positional to
    ``q_name``. Where the values cannot tell, the new order holds (documented with the function)."""

    def decorate(func: Callable) -> Callable:
        @functools.wraps(func)
        def wrapper(*args, **kwargs):
            if len(args) >= 3 and old_order(*args[:3]):
                warn_deprecated(f"{where}(chain, {q_name}, T_target, ...) (the old argument order)",
                                f"{where}(chain, T_target, {q_name}, ...)")
                args = (args[0], args[2], args[1], *args[3:])
            elif len(args) == 2 and "T_target" in kwargs and q_name not in kwargs:
                kwargs[q_name], args = args[1], args[:1]
            return func(*args, **kwargs)

        return wrapper

    return decorate


def moved_names(module: str, moved: dict[str, str]) -> Callable[[str], object]:
    """A module ``__getattr__``: ``module.NAME`` for ``NAME`` in ``moved`` (name -> its home module) warns
    and returns the home's object (the same object, so ``is`` and ``isinstance`` hold)."""

    def __getattr__(name: str):
        home = moved.get(name)
        if home is None:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        warn_deprecated(f"{module}.{name}", f"{home}.{name}")
        return getattr(importlib.import_module(home), name)

    return __getattr__
