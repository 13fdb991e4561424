"""Checks shared by every parameter dataclass: types coerced, ranges enforced.

Each parameter class calls :func:`check_fields` from its ``__post_init__``. Types come
from the class's own annotations, so a field's declared type is its contract:

* ``int``: an ``int``, a numpy integer or an integral float (``15.0``) becomes an
  ``int``; ``15.9``, ``True`` or ``"15"`` are refused;
* ``float``: any real number (numpy included) becomes a finite ``float``;
* ``bool``: ``bool`` or numpy bool only (the string ``"False"`` is true in Python);
* ``str``: a string;
* ``tuple[X, X]`` / ``tuple[X, ...]``: any sequence (not a string) of that length,
  items coerced, stored as a tuple;
* ``X | None``: ``None`` or an ``X``;
* another class name (a nested parameter class): an instance of it.

Ranges are stated per field (``positive``, ``non_negative``, ``within`` intervals,
``choices``) and apply to every item of a tuple. Errors name the class, the field and
the value (``ShadowPathParams.shadow_mm must be > 0, got -1``); they are
:class:`~BoneUSRecon.Logic.errors.BoneUSReconError` (a ``ValueError``), and for a wrong
type :class:`ParameterTypeError`, also a ``TypeError``. Written here rather than with
a validation library (pydantic, attrs validators): the classes stay plain frozen
dataclasses, and importing this costs nothing at CLI start-up.

Examples
--------
>>> from dataclasses import dataclass
>>> @dataclass(frozen=True)
... class P:
...     n: int = 3
...     size_mm: float = 1.0
...     def __post_init__(self) -> None:
...         check_fields(self, positive=("n", "size_mm"))
>>> P(n=4.0).n
4
>>> P(n=4.5)
Traceback (most recent call last):
...
BoneUSRecon.Logic.params_check.ParameterTypeError: P.n must be an integer, got 4.5
>>> P(size_mm=-1)
Traceback (most recent call last):
...
BoneUSRecon.Logic.errors.BoneUSReconError: P.size_mm must be > 0, got -1.0
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
import operator
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

from BoneUSRecon.Logic.errors import BoneUSReconError

__all__ = ["ParameterTypeError", "check_fields", "interval"]


class ParameterTypeError(BoneUSReconError, TypeError):
    """A parameter of the wrong type: a :class:`BoneUSReconError` and a ``TypeError``."""


Coerce = Callable[[str, Any], Any]


def _is_bool(v: Any) -> bool:
    """``bool`` or a numpy bool scalar (``np.bool_``), without importing numpy."""
    return isinstance(v, bool) or getattr(getattr(v, "dtype", None), "kind", "") == "b"


def _int(label: str, v: Any) -> int:
    if _is_bool(v):
        raise ParameterTypeError(f"{label} must be an integer, got {v!r}")
    try:
        return operator.index(v)  # int and numpy integers
    except TypeError:
        pass
    if isinstance(v, numbers.Real) and math.isfinite(v) and float(v).is_integer():
        return int(float(v))
    raise ParameterTypeError(f"{label} must be an integer, got {v!r}")


def _float(label: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        raise ParameterTypeError(f"{label} must be a number, got {v!r}")
    f = float(v)
    if not math.isfinite(f):
        raise BoneUSReconError(f"{label} must be finite, got {v!r}")
    return f


def _bool(label: str, v: Any) -> bool:
    if _is_bool(v) and getattr(v, "ndim", 0) == 0:
        return bool(v)
    raise ParameterTypeError(f"{label} must be True or False, got {v!r}")


def _str(label: str, v: Any) -> str:
    if isinstance(v, str):
        return v
    raise ParameterTypeError(f"{label} must be a string, got {v!r}")


_SCALARS: dict[str, Coerce] = {"int": _int, "float": _float, "bool": _bool, "str": _str}


def _split_top(text: str, sep: str) -> list[str]:
    """``text`` split at ``sep`` outside brackets."""
    parts, depth, start = [], 0, 0
    for i, c in enumerate(text):
        depth += c == "["
        depth -= c == "]"
        if depth == 0 and text.startswith(sep, i):
            parts.append(text[start:i].strip())
            start = i + len(sep)
    parts.append(text[start:].strip())
    return parts


def _coercer(annotation: str, module: str) -> Coerce | None:
    """The coercion for a (string) annotation; None when it is not checked (``Any``)."""
    alternatives = _split_top(annotation, "|")
    if len(alternatives) > 1:
        rest = [a for a in alternatives if a != "None"]
        inner = _coercer(" | ".join(rest), module)
        if inner is None:
            return None
        if len(rest) == len(alternatives):  # a union without None: not used by our classes
            return None
        return lambda label, v: None if v is None else inner(label, v)
    a = annotation.strip()
    if a in _SCALARS:
        return _SCALARS[a]
    if a.startswith("tuple[") and a.endswith("]"):
        items = _split_top(a[6:-1], ",")
        if len(items) == 2 and items[1] == "...":
            item = _coercer(items[0], module)
            n = None
        else:
            coercers = [_coercer(x, module) for x in items]
            if len(set(items)) != 1:
                return None  # mixed tuples: not used by our classes
            item, n = coercers[0], len(items)
        if item is None:
            return None

        def coerce_tuple(label: str, v: Any) -> tuple[Any, ...]:
            if isinstance(v, (str, bytes)) or not isinstance(v, Iterable):
                raise ParameterTypeError(f"{label} must be a sequence, got {v!r}")
            seq = tuple(v)
            if n is not None and len(seq) != n:
                raise BoneUSReconError(f"{label} must have {n} values, got {v!r}")
            return tuple(item(label, x) for x in seq)

        return coerce_tuple
    cls = getattr(sys.modules.get(module), a, None)
    if isinstance(cls, type):
        name = cls.__name__

        def check_instance(label: str, v: Any) -> Any:
            if not isinstance(v, cls):
                raise ParameterTypeError(f"{label} must be a {name}, got {v!r}")
            return v

        return check_instance
    return None


_SPECS: dict[type, list[tuple[str, Coerce]]] = {}


def _spec(cls: type) -> list[tuple[str, Coerce]]:
    """(field, coercion) pairs of a dataclass, worked out once per class."""
    spec = _SPECS.get(cls)
    if spec is None:
        spec = []
        for f in dataclasses.fields(cls):
            ann = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", "")
            c = _coercer(ann, cls.__module__)
            if c is not None:
                spec.append((f.name, c))
        _SPECS[cls] = spec
    return spec


@functools.cache
def interval(text: str) -> Callable[[float], bool]:
    """A membership test from interval notation: ``"[0, 1]"``, ``"(0, 100)"``, ``"[2, 1000]"``.

    >>> interval("(0, 1]")(1.0), interval("(0, 1]")(0.0)
    (True, False)
    """
    lo_s, hi_s = (s.strip() for s in text.strip()[1:-1].split(","))
    lo, hi = float(lo_s), float(hi_s)
    lo_open, hi_open = text.strip()[0] == "(", text.strip()[-1] == ")"
    return lambda v: (lo < v if lo_open else lo <= v) and (v < hi if hi_open else v <= hi)


def _items(v: Any) -> tuple[Any, ...]:
    if v is None:
        return ()
    return tuple(v) if isinstance(v, tuple) else (v,)


def check_fields(
    obj: Any,
    *,
    positive: Sequence[str] = (),
    non_negative: Sequence[str] = (),
    within: Mapping[str, str] | None = None,
    choices: Mapping[str, Sequence[str]] | None = None,
) -> None:
    """Coerce the fields of a (frozen) dataclass to their declared types, check ranges.

    Parameters
    ----------
    obj : dataclass instance
        Called from its ``__post_init__``; coerced values are set in place.
    positive, non_negative : sequence of str
        Fields that must be > 0 or >= 0 (each item of a tuple; ``None`` passes).
    within : dict, optional
        Field -> interval in notation ``"[lo, hi]"``, ``"(lo, hi)"``, ... .
    choices : dict, optional
        Field -> the allowed strings (each item of a tuple).

    Raises
    ------
    ParameterTypeError
        A value of the wrong type (also a ``TypeError``).
    BoneUSReconError
        A value out of range (a ``ValueError``), naming the class, field and value.
    """
    cls_name = type(obj).__name__
    for name, coerce in _spec(type(obj)):
        value = coerce(f"{cls_name}.{name}", getattr(obj, name))
        object.__setattr__(obj, name, value)
    for name in positive:
        for v in _items(getattr(obj, name)):
            if not v > 0:
                raise BoneUSReconError(f"{cls_name}.{name} must be > 0, got {getattr(obj, name)!r}")
    for name in non_negative:
        for v in _items(getattr(obj, name)):
            if not v >= 0:
                raise BoneUSReconError(
                    f"{cls_name}.{name} must be >= 0, got {getattr(obj, name)!r}"
                )
    for name, text in (within or {}).items():
        inside = interval(text)
        for v in _items(getattr(obj, name)):
            if not inside(v):
                raise BoneUSReconError(
                    f"{cls_name}.{name} must lie in {text}, got {getattr(obj, name)!r}"
                )
    for name, allowed in (choices or {}).items():
        for v in _items(getattr(obj, name)):
            if v not in allowed:
                raise BoneUSReconError(
                    f"{cls_name}.{name} must be one of {', '.join(map(str, allowed))}, got {v!r}"
                )
