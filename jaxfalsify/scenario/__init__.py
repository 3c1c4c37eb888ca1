"""What a scenario is and how it is measured: the logical scenario's space (space), weather,
metrics (RSS safe distance, time-to-collision) and the paper's reward. Imports ``base`` and
``io``.

Its modules load on first access (``jaxfalsify.scenario.metrics`` after ``import jaxfalsify``).
"""

import importlib as _importlib
from pathlib import Path as _Path

__all__ = []


def __getattr__(name: str):
    if (_Path(__file__).parent / f"{name}.py").is_file():  # a module of this folder
        return _importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
