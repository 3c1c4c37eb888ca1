"""Frozen dataclasses that are JAX pytrees (numeric fields traced, ``static`` fields hashed).

The same habit as gymnax's ``EnvParams`` / flax's ``struct.dataclass``, on plain
``jax.tree_util.register_dataclass`` so the hot path does not import flax (0.6 s of start-up).
"""

from __future__ import annotations

import dataclasses

import jax


def dataclass(cls):
    """``@dataclass``: a frozen dataclass registered as a pytree (see :func:`static`)."""
    return jax.tree_util.register_dataclass(dataclasses.dataclass(frozen=True)(cls))


def static(default=dataclasses.MISSING, **kw):
    """A field that is part of the tree structure (hashed, never traced): shapes, horizons."""
    return dataclasses.field(default=default, metadata={"static": True}, **kw)


def replace(obj, **changes):
    return dataclasses.replace(obj, **changes)


def field_names(obj_or_cls) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(obj_or_cls))
