"""The foundation: validation helpers (config), pytrees, progress and start-up accounting, devices
and hosts (distributed), worker processes and user-module import (worker). Imports nothing else
of the package.

Its modules load on first access (``jaxfalsify.base.config`` after ``import jaxfalsify``).
"""

import importlib as _importlib
from pathlib import Path as _Path

__all__ = []


def __getattr__(name: str):
    if (_Path(__file__).parent / f"{name}.py").is_file():  # a module of this folder
        return _importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
