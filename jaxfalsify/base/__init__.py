"""The foundation: validation helpers (config), pytrees, progress and start-up accounting, devices
and hosts (distributed), worker processes and user-module import (worker). Imports nothing else
of the package.

Its modules load on first access (``jaxfalsify.base.config`` after ``import jaxfalsify``).
"""

import importlib as _importlib

__all__ = []

_MODULES = frozenset({'config', 'distributed', 'progress', 'pytree', 'worker'})


def __getattr__(name: str):
    if name in _MODULES:
        return _importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
