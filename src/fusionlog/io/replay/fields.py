"""Field paths into decoded messages: ``pose.pose.position.x``, ``pose.covariance[0]``.

A decoded message is whatever the ecosystem's decoder returns: a ROS 2 message from
mcap-ros2-support (an object whose ``__slots__`` are its fields), a protobuf message (fields in
its ``DESCRIPTOR``), a ``rosbags`` message of a ROS 1 or ROS 2 bag (a dataclass whose
constants are ``ClassVar`` fields, not data; numeric arrays as numpy arrays), or JSON (dicts and
lists). Only declared fields are followed, never other
attributes or methods. Failures raise :class:`PathError` with a message that does not name the
file; the caller prefixes it.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from decimal import ROUND_HALF_EVEN, Context, Decimal
from fractions import Fraction
from typing import Any

import numpy as np

from fusionlog.core.timing import TIME_UNITS

__all__ = [
    "FieldPath",
    "PathError",
    "TIME_UNITS",
    "closest_paths",
    "describe",
    "is_array",
    "leaf_fields",
    "parse_path",
    "to_number",
    "to_time_ns",
]

INT64_MAX = 2**63 - 1
_CTX = Context(prec=80)  # exact for any time a JSON message can hold in 64-bit nanoseconds

# (sec, nanosec) of ROS 2, (sec, nsec) of Foxglove JSON, (secs, nsecs) of ROS 1 style JSON,
# (seconds, nanos) of google.protobuf.Timestamp
_TIME_PAIRS = (("sec", "nanosec"), ("sec", "nsec"), ("secs", "nsecs"), ("seconds", "nanos"))

_NAME = r"[^.\[\]]+"
_PATH = re.compile(rf"(?:{_NAME}|\[\d+\])(?:\.{_NAME}|\[\d+\])*")
_STEP = re.compile(rf"\[(\d+)\]|({_NAME})")
_MISSING = object()


class PathError(Exception):
    """A path that cannot be followed or a value of the wrong kind (one line, no file name)."""


@dataclass(frozen=True)
class FieldPath:
    text: str
    steps: tuple[str | int, ...]

    def resolve(self, msg: Any) -> Any:
        obj = msg
        for i, step in enumerate(self.steps):
            nxt = _child(obj, step)
            if nxt is _MISSING:
                raise PathError(self._missing(msg, obj, i))
            obj = nxt
        return obj

    def _missing(self, msg: Any, parent: Any, i: int) -> str:
        step = self.steps[i]
        where = _render(self.steps[:i])
        if isinstance(step, int):
            if is_array(parent):
                return (
                    f"index {step} out of range in {self.text}: {where or 'the message'} "
                    f"has {len(parent)} element{'' if len(parent) == 1 else 's'}"
                )
            return f"{where or 'the message'} is not an array, so {self.text} does not exist"
        hint = closest_paths(msg, self.text)
        tail = f" (closest: {', '.join(hint)})" if hint else ""
        return f"no field {self.text}{tail}"


def parse_path(text: str) -> FieldPath:
    """``a.b[2].c`` -> steps ("a", "b", 2, "c"). Raises PathError on bad syntax."""
    s = text.strip() if isinstance(text, str) else ""
    if not _PATH.fullmatch(s):
        raise PathError(f"bad field path {text!r} (expected names joined by dots, [i] for arrays)")
    steps = tuple(int(i) if i else name for i, name in _STEP.findall(s))
    return FieldPath(s, steps)


def _render(steps: Sequence[str | int]) -> str:
    out = ""
    for st in steps:
        out += f"[{st}]" if isinstance(st, int) else (f".{st}" if out else st)
    return out


_SCALARS = (str, int, float, bool, type(None), Decimal)  # Decimal: JSON's non-integers
_ARRAYS = (list, tuple, bytes, bytearray, memoryview)  # uint8[] of ROS 2 decodes as bytes


def _is_ros(t: type) -> bool:
    """mcap-ros2-support's message classes (made anew for every decoded message, so they are
    told apart by their class attributes before any ABC check, which would not be cached)."""
    return "_full_text" in t.__dict__ and "__slots__" in t.__dict__


def _dataclass_fields(t: type) -> list[str] | None:
    """The data fields of a rosbags message class (its constants are ClassVar: not data)."""
    fields = t.__dict__.get("__dataclass_fields__")
    if fields is None:
        return None
    return [
        name
        for name, f in fields.items()
        if not str(f.type).startswith("ClassVar") and not name.startswith("__")
    ]


def is_array(obj: Any) -> bool:
    t = type(obj)
    if t in _ARRAYS or t is np.ndarray:
        return True
    if t in _SCALARS or t is dict or _is_ros(t):
        return False
    return isinstance(obj, Sequence)


def _fields(obj: Any) -> list[str] | None:
    """The declared field names of a message, or None when ``obj`` is not one."""
    t = type(obj)
    if t is dict:
        return [k for k in obj if isinstance(k, str)]
    if t in _SCALARS or t in _ARRAYS:
        return None
    if _is_ros(t):
        return list(t.__dict__["__slots__"])
    if t is np.ndarray:
        return None
    if dataclasses.is_dataclass(t):
        return _dataclass_fields(t)
    desc = getattr(t, "DESCRIPTOR", None)
    if desc is not None and hasattr(desc, "fields"):
        return [f.name for f in desc.fields]
    if isinstance(obj, Mapping):
        return [k for k in obj if isinstance(k, str)]
    return None


def _child(obj: Any, step: str | int) -> Any:
    if isinstance(step, int):
        if is_array(obj) and step < len(obj):
            return obj[step]
        return _MISSING
    if type(obj) is dict:
        return obj.get(step, _MISSING)
    names = _fields(obj)
    if names is None or step not in names:
        return _MISSING
    if _is_ros(type(obj)) or dataclasses.is_dataclass(obj) or hasattr(type(obj), "DESCRIPTOR"):
        return getattr(obj, step, _MISSING)
    return obj[step]  # a Mapping other than dict


def _walk(obj: Any, prefix: str, depth: int) -> Iterator[str]:
    if depth > 12:
        return
    names = _fields(obj)
    if names is not None:
        for name in names:
            path = f"{prefix}.{name}" if prefix else name
            yield path
            yield from _walk(_child(obj, name), path, depth + 1)
    elif is_array(obj) and not isinstance(obj, bytes | bytearray | memoryview):
        for i in range(min(len(obj), 64)):
            path = f"{prefix}[{i}]"
            yield path
            yield from _walk(obj[i], path, depth + 1)


def closest_paths(msg: Any, path: str, n: int = 3) -> list[str]:
    """The field paths of ``msg`` closest to ``path`` (difflib), or its top-level fields."""
    paths = []
    for p in _walk(msg, "", 0):
        paths.append(p)
        if len(paths) >= 20000:
            break
    hint = difflib.get_close_matches(path, paths, n=n, cutoff=0.6)
    if not hint:
        hint = (_fields(msg) or [])[:8]
    return hint


def describe(value: Any) -> str:
    names = _fields(value)
    if names is not None:
        return f"a message (fields {', '.join(names[:8])}{', ...' if len(names) > 8 else ''})"
    if isinstance(value, str):
        return f"a string ({value[:40]!r})"
    if is_array(value):
        return f"an array of {len(value)} (give an element, e.g. [0])"
    if value is None:
        return "null"
    return f"a {type(value).__name__}"


def _is_number(value: Any) -> bool:
    if isinstance(value, bool):
        return False
    return isinstance(value, int | float | np.integer | np.floating | Decimal)


def to_number(value: Any, path: str) -> float:
    """A float (NaN and inf pass through; the caller skips them)."""
    if not _is_number(value):
        raise PathError(f"{path} is {describe(value)}, not a number")
    try:
        return float(value)
    except OverflowError as e:  # an int beyond float range
        raise PathError(f"{path} = {value} does not fit a double") from e


def to_time_ns(value: Any, path: str, unit: str) -> int | None:
    """Nanoseconds (exact for integers and ROS times), or None for a NaN/inf number.

    ``value`` is a time object (``sec``/``nanosec`` and the like) or a number in ``unit``.
    """
    for sec_name, ns_name in _TIME_PAIRS:
        sec, nsec = _child(value, sec_name), _child(value, ns_name)
        if sec is not _MISSING and nsec is not _MISSING:
            for name, part in ((sec_name, sec), (ns_name, nsec)):
                if not (_is_number(part) and float(part).is_integer()):
                    raise PathError(f"{path}.{name} is {describe(part)}, not an integer")
            sec, nsec = int(sec), int(nsec)
            if not 0 <= nsec < 1_000_000_000:
                raise PathError(f"{path}.{ns_name} = {nsec} is outside [0, 1e9)")
            return _check_range(sec * 1_000_000_000 + nsec, path)
    if _fields(value) is not None:
        raise PathError(
            f"{path} is {describe(value)}, not a time (needs sec and nanosec) or a number"
        )
    if not _is_number(value):
        raise PathError(f"{path} is {describe(value)}, not a time or a number")
    factor = TIME_UNITS[unit]
    if isinstance(value, int | np.integer):
        return _check_range(int(value) * factor, path)
    if isinstance(value, Decimal):  # JSON: from the digits, rounded half to even
        if not value.is_finite():
            return None
        try:
            ns = _CTX.multiply(value, factor).to_integral_value(rounding=ROUND_HALF_EVEN)
            return _check_range(int(ns), path)
        except ArithmeticError:  # decimal.Overflow: beyond any clock
            raise PathError(f"{path} = {value} does not fit 64-bit nanoseconds") from None
    v = float(value)
    if not math.isfinite(v):
        return None
    return _check_range(round(Fraction(v) * factor), path)


def _check_range(ns: int, path: str) -> int:
    if not -INT64_MAX - 1 <= ns <= INT64_MAX:
        raise PathError(f"{path} = {ns} ns does not fit 64-bit nanoseconds")
    return ns


def _type_name(value: Any) -> str:
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int | np.integer):
        return "int"
    if isinstance(value, float | np.floating | Decimal):
        return "float"
    if isinstance(value, str):
        return "string"
    return type(value).__name__


def _preview(value: Any) -> str:
    text = repr(value) if isinstance(value, str) else str(value)
    if isinstance(value, float | np.floating | Decimal):
        text = f"{float(value):.10g}"
    return text if len(text) <= 40 else text[:37] + "..."


def leaf_fields(msg: Any, limit: int = 200) -> list[tuple[str, str, str]]:
    """(field path, type, first value) of every number, string or array of numbers in ``msg``,
    for ``inspect``: what a replay file's ``values``/``time``/``covariance`` can name. An array
    of messages is shown through its first element (``[0]``); an array of numbers as one entry
    (``float[9]``, its first values), since ``[i]`` picks an element."""
    out: list[tuple[str, str, str]] = []

    def walk(obj: Any, prefix: str, depth: int) -> None:
        if len(out) >= limit or depth > 12:
            return
        names = _fields(obj)
        if names is not None:
            for name in names:
                walk(_child(obj, name), f"{prefix}.{name}" if prefix else name, depth + 1)
            return
        if is_array(obj):
            if isinstance(obj, bytes | bytearray | memoryview):
                out.append((prefix, f"bytes[{len(obj)}]", _preview(bytes(obj[:8]))))
            elif len(obj) and _fields(obj[0]) is not None:
                walk(obj[0], f"{prefix}[0]", depth + 1)
            elif not len(obj):
                out.append((prefix, "array[0]", "[]"))
            else:
                kind = _type_name(obj[0])
                head = ", ".join(_preview(x) for x in list(obj[:4]))
                out.append(
                    (prefix, f"{kind}[{len(obj)}]", f"[{head}{', ...' if len(obj) > 4 else ''}]")
                )
            return
        out.append((prefix, _type_name(obj), _preview(obj)))

    walk(msg, "", 0)
    return out
