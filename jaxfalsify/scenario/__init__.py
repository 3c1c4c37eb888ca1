"""What a scenario is and how it is measured: the logical scenario's space (space), weather,
metrics (RSS safe distance, time-to-collision) and the paper's reward. Imports ``base`` and
``io``.

Its modules load on first access (``jaxfalsify.scenario.metrics`` after ``import jaxfalsify``).
"""

import importlib as _importlib

__all__ = []

_MODULES = frozenset({'metrics', 'reward', 'space', 'weather'})


def __getattr__(name: str):
    if name in _MODULES:
        return _importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
