"""Frozen dataclasses that are JAX pytrees (numeric fields traced, ``static`` fields hashed).

The same habit as gymnax's ``EnvParams`` / flax's ``struct.dataclass``, on plain
``jax.tree_util.register_dataclass`` so the hot path does not import flax (0.6 s of start-up).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import jax
import numpy as np

__all__ = [
    "dataclass", "static", "replace", "FLOAT32_MAX", "FLOAT32_TINY", "real_number",
    "number_problem", "checked_number", "param_items", "check_defaults", "with_overrides",
    "field_names", "ranges", "in_range", "check_ranges"
]


def dataclass(cls):
    """``@dataclass``: a frozen dataclass registered as a pytree (see :func:`static`)."""
    return jax.tree_util.register_dataclass(dataclasses.dataclass(frozen=True)(cls))


def static(default=dataclasses.MISSING, **kw):
    """A field that is part of the tree structure (hashed, never traced): shapes, horizons."""
    return dataclasses.field(default=default, metadata={"static": True}, **kw)


def replace(obj, **changes):
    return dataclasses.replace(obj, **changes)


FLOAT32_MAX = float(np.finfo(np.float32).max)  # larger values become inf in the simulator
FLOAT32_TINY = float(np.finfo(np.float32).tiny)  # smallest normal float32 (1.2e-38)


def real_number(value) -> float | None:
    """``value`` as a float if it is one real number (Python, NumPy or a concrete 0-d JAX
    array; not a bool), else None."""
    if isinstance(value, (bool, np.bool_)) or isinstance(value, jax.core.Tracer):
        return None
    if isinstance(value, (int, float, np.integer, np.floating)):
        try:
            return float(value)
        except OverflowError:  # an int beyond float64: infinite for every check after
            return math.inf if value > 0 else -math.inf
    if isinstance(value, (np.ndarray, jax.Array)) and value.ndim == 0 and \
            (np.issubdtype(value.dtype, np.integer) or np.issubdtype(value.dtype, np.floating)):
        return float(value)
    return None


def number_problem(number: float) -> str | None:
    """Why ``number`` cannot be a parameter computed in float32 (it is not finite, beyond
    float32's range, or so small that float32 makes it 0 or loses its digits); None when it
    can."""
    if not math.isfinite(number):
        return "is not finite"
    if abs(number) > FLOAT32_MAX:
        return "is beyond float32's range (computed in float32)"
    if 0 < abs(number) < FLOAT32_TINY:
        return (f"is below float32's smallest normal number {FLOAT32_TINY:.3g} (computed in "
                "float32)")
    return None


def checked_number(name: str, value, where: str) -> float:
    """``value`` given for the parameter ``name`` as a float: one-line ValueError (``where:
    name=value ...``) unless it is one real number float32 can hold."""
    number = real_number(value)
    if number is None:
        raise ValueError(f"{where}: {name}={value!r:.40} is not a number")
    problem = number_problem(number)
    if problem:
        raise ValueError(f"{where}: {name}={value!r:.40} {problem}")
    return number


def param_items(params) -> dict:
    """The named parameters of a dataclass or a mapping of them ``{name: value}``; ``{}`` for
    None or any other pytree."""
    if dataclasses.is_dataclass(params) and not isinstance(params, type):
        return {f: getattr(params, f) for f in field_names(params)}
    return dict(params) if isinstance(params, Mapping) else {}


def check_defaults(params, owner: str) -> None:
    """One-line ValueError naming ``owner`` (``SUT 'x'``, ``requirement 'y'``) and the first
    parameter whose default is not a number (a boolean passes) or one float32 cannot hold:
    named parameters are scalars, traced, recorded in config.toml and set by ``NAME=VALUE``."""
    for name, v in param_items(params).items():
        if isinstance(v, (bool, np.bool_)):
            continue
        number = real_number(v)
        if number is None:
            raise ValueError(f"{owner}: parameter '{name}' has the default {v!r:.40}, not a "
                             "number (named parameters are scalars)")
        problem = number_problem(number)
        if problem:
            raise ValueError(f"{owner}: parameter '{name}' has the default {v!r:.40}, which "
                             f"{problem}")


def with_overrides(defaults, given: Mapping, where: str, owner: str):
    """``defaults`` (a dataclass or a mapping of numbers) with ``given {name: number}``
    applied, each checked (:func:`checked_number`) and within its field's interval
    (:func:`check_ranges`); one-line ValueError naming ``where``, ``owner`` and the name."""
    known = tuple(param_items(defaults))
    values = {}
    for name, value in dict(given).items():
        if name not in known:
            raise ValueError(f"{where}: {owner} has no parameter '{name}' "
                             f"(known: {', '.join(known) or 'none'})")
        values[name] = checked_number(name, value, where)
    if dataclasses.is_dataclass(defaults):
        check_ranges(defaults, values, f"{where}: {owner}")
        return dataclasses.replace(defaults, **values)
    return {**defaults, **values}


def field_names(obj_or_cls) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(obj_or_cls))


def ranges(obj_or_cls) -> dict[str, str]:
    """The valid intervals of a parameter class's fields, ``{name: "[lo, hi)"}`` (a class
    attribute ``RANGES``, merged along the class's bases; fields without one are unbounded)."""
    cls = obj_or_cls if isinstance(obj_or_cls, type) else type(obj_or_cls)
    out: dict[str, str] = {}
    for base in reversed(cls.__mro__):
        out.update(base.__dict__.get("RANGES", {}))
    return out


def in_range(value: float, interval: str) -> bool:
    """Whether ``value`` lies in ``interval`` (``"[0, 1)"``, ``"(0, inf)"``: brackets closed,
    parentheses open)."""
    lo, hi = (float(x) for x in interval[1:-1].split(","))
    return ((lo <= value) if interval[0] == "[" else (lo < value)) and \
        ((value <= hi) if interval[-1] == "]" else (value < hi))


def check_ranges(obj_or_cls, values: dict, where: str) -> None:
    """One-line ValueError for the first of ``values {name: number}`` outside its field's
    interval (see :func:`ranges`)."""
    bounds = ranges(obj_or_cls)
    for name, value in values.items():
        if name in bounds and not in_range(float(value), bounds[name]):
            raise ValueError(f"{where}: {name}={value!r} is outside {bounds[name]}")
