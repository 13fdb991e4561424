"""Lazy package attributes (PEP 562), for packages whose imports are heavy."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Iterable
from typing import Any

__all__ = ["lazy_attributes"]


def lazy_attributes(
    package: str, where: dict[str, str], public: Iterable[str]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """Module ``__getattr__`` and ``__dir__`` that import a name on first use.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    where : dict
        Attribute name -> sub-module (relative to ``package``) that defines it.
    public : iterable of str
        The package's ``__all__``, listed by ``dir()``.

    Returns
    -------
    (__getattr__, __dir__)
        To assign at the package's top level. The value is cached in the package, so
        ``__getattr__`` runs once per name.
    """
    names = sorted(public)

    def __getattr__(name: str) -> Any:
        if name in where:
            value = getattr(importlib.import_module(f"{package}.{where[name]}"), name)
            setattr(sys.modules[package], name, value)
            return value
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return names

    return __getattr__, __dir__
