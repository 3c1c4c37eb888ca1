"""The built-in systems under test, one file each, on a shared interface
(:mod:`jaxfalsify.suts.interface`); :mod:`jaxfalsify.suts.registry` registers them.

Its modules load on first access (``jaxfalsify.suts.autopilot`` after ``import jaxfalsify``).
"""

import importlib as _importlib

__all__ = []

_MODULES = frozenset({'autopilot', 'carla_tm', 'interface', 'registry', 'sensor_aeb'})


def __getattr__(name: str):
    if name in _MODULES:
        return _importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
