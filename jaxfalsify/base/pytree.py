"""Frozen dataclasses that are JAX pytrees (numeric fields traced, ``static`` fields hashed).

The same habit as gymnax's ``EnvParams`` / flax's ``struct.dataclass``, on plain
``jax.tree_util.register_dataclass`` so the hot path does not import flax (0.6 s of start-up).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np

__all__ = [
    "dataclass", "static", "replace", "FLOAT32_MAX", "real_number", "field_names", "ranges",
    "in_range", "check_ranges"
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
